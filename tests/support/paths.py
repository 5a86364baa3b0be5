"""Where the tests find things: the checkout, the example task and its sets (planned once a run), the
shared recordings; and paths the project has never seen, from ``random_path`` with a printed seed."""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest

from common.trajectory.bspline import Boundary
from common.trajectory.task import PathPlan

REPO = Path(__file__).resolve().parents[2]


EXAMPLE_TASK = REPO / "deploy" / "tasks" / "box_filling.toml"


SHARED_DATA = REPO.parent / "shared" / "data"


# the benchmarks (marker ``bench``, not in a plain ``uv run pytest``) in the shorter form .ci/run runs
BENCH_QUICK = os.environ.get("CADENCE_BENCH") == "quick"


def random_path(seed: int, n_waypoints: int = 6, boundary: bool = False) -> PathPlan:
    """A UR16e-like path: waypoints within ±π, consecutive steps of up to ~70° per joint."""
    rng = np.random.default_rng(seed)
    wp = [rng.uniform(-1.5, 1.5, 6)]
    for _ in range(n_waypoints - 1):
        wp.append(np.clip(wp[-1] + rng.uniform(-1.2, 1.2, 6), -np.pi, np.pi))
    wp = np.array(wp)
    if boundary:
        small = lambda s: rng.uniform(-s, s, 6)  # noqa: E731
        b = Boundary(small(0.2), small(0.5), small(2.0), small(0.2), small(0.5), small(2.0))
    else:
        b = Boundary.at_rest(6)
    print(f"random_path(seed={seed}, W={n_waypoints}, boundary={boundary})")
    return PathPlan(f"random{seed}", wp, b)


def plan_sets(task_file: Path, db: Path) -> Path:
    """Every path of ``task_file`` planned, in this process, into a store's SQLite file ``db``: the
    shipped set where one was planned from the same inputs (as the store serves it)."""
    from common.trajectory.shipped import shipped_or_planned
    from common.trajectory.task import load_task
    from services.pareto_store.store import SetStore

    task = load_task(task_file)
    store, _ = SetStore.open(db)
    for path in task.paths.values():
        store.save(shipped_or_planned(path, task))
    store.close()
    return db


_PLANNED: dict[str, Path] = {}  # a task program's text → its sets, planned once per test run


def planned_once(task_file: Path, tmp_path_factory: pytest.TempPathFactory | None = None) -> Path:
    """A store's SQLite file with ``task_file``'s sets, planned the first time a test asks for them.
    A store that plans in each test puts its low-priority worker behind any CPU load on the machine:
    under CI's load a store took over 60 s to serve a one-path task."""
    text = task_file.read_text()
    if text not in _PLANNED:
        folder = (
            tmp_path_factory.mktemp("sets") if tmp_path_factory else Path(tempfile.mkdtemp(prefix="sets-"))
        )
        if tmp_path_factory is None:
            atexit.register(shutil.rmtree, folder, True)
        _PLANNED[text] = plan_sets(task_file, folder / "pareto.sqlite")
    return _PLANNED[text]


README = REPO / "README.md"
DOCS = REPO / "docs"  # the guides (mkdocs.yml)
# what a reader is shown: every shell block of these is checked (tests/cadence/test_readme.py)
PAGES = (README, *sorted(DOCS.glob("*.md")))
