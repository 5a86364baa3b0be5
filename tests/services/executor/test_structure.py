"""The executor's rooms, held to what docs/design.md says of them (issue 57): read from the source's own
imports and calls, so a change that breaks a wall fails here rather than in a reviewer's drawing."""

from __future__ import annotations

import ast
from functools import cache

from tests.support.paths import REPO

EXECUTOR = REPO / "services" / "executor"
PACKAGE = "services.executor"


def imports() -> dict[str, set[str]]:
    """Each module of the executor: the executor's modules it imports (by module name, no package)."""
    out: dict[str, set[str]] = {}
    for f in sorted(EXECUTOR.glob("*.py")):
        names: set[str] = set()
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith(PACKAGE + "."):
                names.add(node.module.removeprefix(PACKAGE + "."))
            elif isinstance(node, ast.Import):
                names |= {
                    a.name.removeprefix(PACKAGE + ".") for a in node.names if a.name.startswith(PACKAGE)
                }
        out[f.stem] = names
    return out


def floors(graph: dict[str, set[str]]) -> dict[str, int]:
    """1 for a module that imports none of the others, else one above the highest it imports."""

    @cache
    def floor(m: str) -> int:
        return 1 + max((floor(d) for d in graph[m]), default=0)

    return {m: floor(m) for m in graph if m != "__init__"}


def test_the_executor_stands_on_five_floors_of_imports_at_most() -> None:
    f = floors(imports())
    assert max(f.values()) <= 5, sorted(f.items(), key=lambda x: -x[1])
    assert f["__main__"] == max(f.values())  # the node builds the parts; no part reaches up to it


def test_only_the_node_and_the_task_program_hold_the_supervisor_the_parts_hold_its_face() -> None:
    """The other parts see the supervisor as kit.py's ``Safety``: the state, ``fire`` and the events."""
    holders = {m for m, deps in imports().items() if "supervisor" in deps}
    assert holders == {"__main__", "cycles"}


def test_every_task_the_executor_starts_is_in_the_nodes_task_group() -> None:
    """No ``create_task`` or ``ensure_future`` in the executor but the lockstep servo's motion, which its
    caller awaits (servo.py): the rest goes through ``Kit.start_soon`` / ``Node.start_soon``."""
    found = []
    for f in sorted(EXECUTOR.glob("*.py")):
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.Attribute) and node.attr in ("create_task", "ensure_future"):
                found.append(f"{f.name}:{node.lineno}")
    assert [x for x in found if not x.startswith("servo.py:")] == []
    assert len(found) == 1  # the lockstep servo's one


def test_no_class_of_the_executor_runs_over_250_lines_and_each_says_what_it_owns() -> None:
    long, silent = [], []
    for f in sorted(EXECUTOR.glob("*.py")):
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.ClassDef):
                assert node.end_lineno is not None
                if node.end_lineno - node.lineno + 1 > 250:
                    long.append(f"{f.name}:{node.name}")
                if ast.get_docstring(node) is None and not node.name.startswith("_"):
                    silent.append(f"{f.name}:{node.name}")
    assert long == []
    assert silent == []
