"""The README's and the guides' shell examples, as written (issues 20, 56), and the site they make.

Every command of every ``sh`` block is checked against what it names: a ``cadence`` command line is
parsed by the CLI's own parser (a renamed flag or command fails here), a ``CADENCE_<SECTION>_<KEY>``
variable is decoded by the config's own rules, a file in the repository or the shared data exists.
The examples that run in seconds on a laptop are then run as written, by bash, in the repository's root:
the router, the store, `cadence get` and zenoh-cli; `cadence decide`, whose output the README states; the
executor through a router with no operator. The others are run elsewhere: `cadence hrv` on the shared
files (test_hrv.py), the demo (test_demo.py), the lab's procedure (test_lab.py), the simulated study and
the fit (test_study.py), the install (test_systemd.py), the UR emulator (test_ur_emulator.py), record,
replay and report (test_recording.py, test_report.py); and the benchmarks in tests/bench.
"""

from __future__ import annotations

import importlib
import itertools
import json
import os
import re
import shlex
import signal
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

from cadence.cli import SERVICES, build_parser
from common.runtime.config import CONFIG_SECTIONS, CommonSettings, ConfigError, section
from tests.support.cell import CELL, free_port
from tests.support.paths import PAGES, REPO, SHARED_DATA

ROOT = REPO
PORT = "7447"  # the examples' router port; a free one is used in its place when they run


@dataclass(frozen=True)
class Block:
    page: str  # README.md, docs/….md
    line: int  # of the opening fence
    text: str


def sh_blocks() -> list[Block]:
    blocks: list[Block] = []
    for page in PAGES:
        current: list[str] | None = None
        start = 0
        for n, line in enumerate(page.read_text().splitlines(), 1):
            if current is None and line.strip() == "```sh":
                current, start = [], n
            elif current is not None and line.strip() == "```":
                blocks.append(Block(str(page.relative_to(ROOT)), start, "\n".join(current)))
                current = None
            elif current is not None:
                current.append(line)
    return blocks


def commands(text: str) -> list[list[str]]:
    """Each command of a block, as tokens, continuation lines joined and comments dropped."""
    out = []
    for line in text.replace("\\\n", " ").splitlines():
        tokens = shlex.split(line, comments=True)
        if tokens:
            out.append(tokens)
    return out


def section_type(name: str) -> type:
    if name == "cadence":
        return CommonSettings
    if name == "bus":
        from common.runtime.bus import BusConfig

        return BusConfig
    return importlib.import_module(SERVICES[name]).Settings


def check_setting(var: str, value: str) -> None:
    names = [s for s in CONFIG_SECTIONS if var.startswith(f"CADENCE_{s.upper()}_")]
    assert names, f"{var}: no config section of that name"
    name = max(names, key=len)  # CADENCE_DECISION_MAKER_… is decision_maker's, not a "decision" one
    key = var[len(f"CADENCE_{name.upper()}_") :].lower()
    kind = section_type(name)
    assert key in kind.__struct_fields__, f"{var}: [{name}] has no key {key!r}"
    try:
        section({}, name, kind, env={var: value})
    except ConfigError as exc:
        pytest.fail(f"{var}={value}: {exc}")


def check_cadence(argv: list[str]) -> None:
    try:
        build_parser().parse_args(argv)
    except SystemExit as exc:
        if exc.code != 0:
            pytest.fail(f"cadence {shlex.join(argv)}: the CLI refuses it (exit {exc.code})")


OTHER_PROGRAMS = {"printf", "systemctl", "journalctl"}


def check_command(tokens: list[str], variables: dict[str, str]) -> None:
    """One command of a block; ``variables`` gathers the block's own (``CELL=…``, ``export …``)."""
    stages = [list(g) for pipe, g in itertools.groupby(tokens, lambda t: t == "|") if not pipe]
    for words in stages:
        if words[:1] == ["export"]:
            words = words[1:]
        env = {}
        while words and re.fullmatch(r"[A-Z_][A-Z0-9_]*=.*", words[0]):
            var, _, value = words.pop(0).partition("=")
            env[var] = value
        for var, value in env.items():
            if var.startswith("CADENCE_"):
                check_setting(var, value)
            if not words:
                variables[var] = value
        if words[:1] == ["sudo"]:
            words = words[1:]
        if words[:2] == ["nice", "-n"]:  # a priority, then the command itself
            words = words[3:]
        if words[-1:] == ["&"]:
            words = words[:-1]
        expanded: list[str] = []
        for w in words:
            expanded += shlex.split(variables[w[1:]]) if w.startswith("$") and w[1:] in variables else [w]
        for w in expanded:
            if (w.startswith("../shared/") and SHARED_DATA.exists()) or w.startswith("deploy/"):
                p = ROOT / w  # a WFDB record is named without its extensions
                assert p.exists() or p.with_name(p.name + ".hea").exists(), f"{w}: no such file"
        if not expanded:
            continue
        if expanded[:3] == ["uv", "run", "cadence"]:
            check_cadence(expanded[3:])
        elif expanded[0].endswith("/bin/cadence"):
            check_cadence(expanded[1:])
        elif expanded[:3] == ["uv", "run", "zenoh"]:
            assert "--decoder" in expanded
            assert expanded[expanded.index("--decoder") + 1] == "cadence"
        elif expanded[:3] in (
            ["uv", "run", "pytest"],
            ["uv", "run", "ruff"],
            ["uv", "sync", "--compile-bytecode"],
            ["uv", "run", "mkdocs"],
        ):
            pass  # what CI runs
        else:
            assert expanded[0] in OTHER_PROGRAMS, f"{expanded[0]}: a program this test does not know"


def test_every_command_of_every_example_is_one_the_cli_and_the_settings_accept(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.chdir(ROOT)
    blocks = sh_blocks()
    assert len(blocks) >= 15, "the README's and the guides' examples were not found"
    assert {b.page for b in blocks} >= {"README.md", "docs/study.md", "docs/operations.md"}
    checked = 0
    for block in blocks:
        variables: dict[str, str] = {}
        for tokens in commands(block.text):
            try:
                check_command(tokens, variables)
            except (AssertionError, pytest.fail.Exception) as exc:
                pytest.fail(f"{block.page}:{block.line}: {shlex.join(tokens)}\n{exc}")
            checked += 1
    print(f"{checked} commands in {len(blocks)} blocks")


def test_the_checks_catch_a_renamed_flag_and_an_unknown_setting() -> None:
    with pytest.raises(pytest.fail.Exception, match="refuses"):
        check_command(["uv", "run", "cadence", "decide", "--rr-rest-s", "0.85"], {})
    with pytest.raises(AssertionError, match="no key 'fixed'"):
        check_command(["CADENCE_DECISION_MAKER_FIXED=a", "uv", "run", "cadence", "run", "decision_maker"], {})
    with pytest.raises(pytest.fail.Exception, match="CADENCE_DECISION_MAKER_MODE=sometimes"):
        check_command(
            ["CADENCE_DECISION_MAKER_MODE=sometimes", "uv", "run", "cadence", "run", "decision_maker"], {}
        )


def test_the_readme_is_short_and_the_guides_build_into_a_site_with_no_broken_link(tmp_path: Path) -> None:
    """A newcomer reads the README to the end (issue 56: it had grown to 1,526 lines of design log); the
    rest is in the guides, which `mkdocs build --strict` builds as CI does: a link to a page or an
    anchor that is not there, or a page left out of the nav, fails it."""
    from tests.support.paths import README

    assert len(README.read_text().splitlines()) <= 300
    r = subprocess.run(["mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")], cwd=ROOT,
                       capture_output=True, text=True, timeout=120)  # fmt: skip
    assert r.returncode == 0, r.stdout + r.stderr
    for page in ("index", "study", "operations", "robot", "decision", "design", "development"):
        assert (tmp_path / "site" / ("" if page == "index" else page) / "index.html").is_file(), page


def test_a_broken_link_in_a_guide_fails_the_build(tmp_path: Path) -> None:
    """The check above can fail: a copy of the guides with one link to a heading that is not there."""
    import shutil

    shutil.copytree(ROOT / "docs", tmp_path / "docs")
    shutil.copy(ROOT / "mkdocs.yml", tmp_path / "mkdocs.yml")
    page = tmp_path / "docs" / "index.md"
    page.write_text(page.read_text() + "\nSee [the missing part](study.md#no-such-heading).\n")
    r = subprocess.run(["mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")], cwd=tmp_path,
                       capture_output=True, text=True, timeout=120)  # fmt: skip
    assert r.returncode != 0
    assert "no-such-heading" in r.stdout + r.stderr


# --- run as written ---------------------------------------------------------------------------------


def block_with(needle: str) -> Block:
    found = [b for b in sh_blocks() if needle in b.text]
    assert len(found) == 1, f"the README and the guides have {len(found)} examples with {needle!r}"
    return found[0]


@pytest.fixture
def shell_env(tmp_path: Path) -> dict[str, str]:
    """What the examples run in: this machine's environment, with the services' data in a temporary
    folder."""
    return {**os.environ, "CADENCE_CADENCE_DATA_DIR": str(tmp_path / "data"), "NO_COLOR": "1"}


def run_until(
    script: str, env: dict[str, str], done: Callable[[str], bool], timeout_s: float, out: Path
) -> str:
    """Runs ``script`` with bash in the repository's root until its output satisfies ``done``, then
    stops it and everything it started in the background (its own process group)."""
    with out.open("w") as f:
        proc = subprocess.Popen(
            ["bash", "-c", script],
            cwd=ROOT,
            env=env,
            stdout=f,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        deadline = time.monotonic() + timeout_s
        try:
            while time.monotonic() < deadline and proc.poll() is None and not done(out.read_text()):
                time.sleep(0.2)
        finally:
            with_signal = signal.SIGTERM
            for _ in range(2):
                try:
                    os.killpg(proc.pid, with_signal)
                except ProcessLookupError:
                    break
                try:
                    proc.wait(timeout=10)
                    break
                except subprocess.TimeoutExpired:
                    with_signal = signal.SIGKILL
    return out.read_text()


def test_the_router_store_get_and_zenoh_example_runs_as_written(
    shell_env: dict[str, str], tmp_path: Path
) -> None:
    block = block_with(f"cadence get cadence/{CELL}/pareto")
    script = block.text.replace(PORT, str(free_port()))
    keyed = re.compile(rf"^cadence/{CELL}/\S+ \{{", re.MULTILINE)

    def done(text: str) -> bool:
        return '"pareto.solution.v1"' in text and keyed.search(text) is not None

    text = run_until(script, shell_env, done, 90.0, tmp_path / "out.txt")
    assert done(text), text[-3000:]
    solution = json.loads(next(line for line in text.splitlines() if '"pareto.solution.v1"' in line))
    assert solution["path_id"] == "b1_to_b2"
    assert solution["solution"]["k"] == 15  # what the example asks


def test_the_decide_example_prints_what_the_readme_says(shell_env: dict[str, str]) -> None:
    block = block_with("cadence decide")
    line = next(line for line in block.text.splitlines() if "cadence decide" in line)
    command, _, said = line.partition("#")
    r = subprocess.run(
        ["bash", "-c", command], cwd=ROOT, env=shell_env, capture_output=True, text=True, timeout=60
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == said.split()


def test_the_executor_example_goes_through_the_router_and_past_the_wait_for_steps(
    shell_env: dict[str, str], tmp_path: Path
) -> None:
    block = block_with("cadence run executor --speed 5")
    script = block.text.replace(PORT, str(free_port()))
    first_path = re.compile(r"moving: 'b1_to_b2'")

    def done(text: str) -> bool:  # a second cycle started: the first one's wait_for steps passed
        return len(first_path.findall(text)) >= 2

    text = run_until(script, shell_env, done, 120.0, tmp_path / "out.txt")
    assert done(text), text[-3000:]
