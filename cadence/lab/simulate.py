"""A simulated study from end to end (`cadence study simulate|fit`): plan the task, optionally fit the
twin to Table I on part of the cohort, simulate every subject in every condition into session files, and
analyse them as `cadence study analyse` does. The simulation itself is cadence/lab/study.py."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from cadence.lab.study import Model, calibrate_twin, motions, simulate_session, subjects
from schemas.session import Condition

if TYPE_CHECKING:
    from cadence.lab.analysis import Study
    from cadence.lab.fit import Fit


@dataclass(frozen=True, slots=True)
class Cohort:
    """A simulated study's cohort and its runs (`cadence study simulate|fit`)."""

    task: Path
    subjects: int = 12
    minutes: float = 10.0  # per condition and subject
    calibrate: float = 5.0  # minutes at rest per subject
    seed: int = 1
    out: Path = Path("study-out")


def simulate_study(
    cohort_of: Cohort, model: Model | None = None, fit_subjects: int = 0
) -> tuple[Study, Fit | None]:
    """Plan, then (with ``fit_subjects``) fit the twin on a cohort of that size, then write a session file
    per subject and condition under ``out``/sessions and analyse them as `study analyse` does; progress
    and the tables on the terminal."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from cadence.lab.analysis import analyse, write_study
    from cadence.lab.fit import cohort_for, fit
    from cadence.lab.session_file import load_session
    from cadence.lab.tables import err, out, print_study
    from common.trajectory.shipped import sets_digest, shipped_or_planned
    from common.trajectory.task import load_task

    conditions: tuple[Condition, ...] = ("a", "b", "c")
    args = cohort_of
    task_path = args.task
    task = load_task(task_path)
    cohort = subjects(args.subjects, args.seed)
    folder = args.out / "sessions"
    folder.mkdir(parents=True, exist_ok=True)
    files, fitted = [], None
    with Progress(
        TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), console=err
    ) as progress:
        plan = progress.add_task("planning the Pareto sets", total=len(task.paths))
        sols = {}
        for pid, path in task.paths.items():
            sols[pid] = [np.array(s.h) for s in shipped_or_planned(path, task).solutions]
            progress.advance(plan)
        digest = sets_digest(sols)
        progress.update(plan, description=f"Pareto sets {digest[:12]}")
        moves = motions(task, sols)
        n_per_path = {pid: len(v) for pid, v in sols.items()}
        if fit_subjects:
            bar = progress.add_task("fitting the twin to Table I (a), (b)", total=None)
            few = cohort[:fit_subjects]
            fit_cohort = cohort_for(task, moves, n_per_path, few, args.minutes, args.calibrate)
            fitted = fit(fit_cohort, lambda what: progress.update(bar, description=f"fitting: {what}"))
            progress.update(bar, description="fitted the twin to Table I (a), (b)", total=1, completed=1)
            model = fitted.model
        runs = progress.add_task("simulating subjects × conditions", total=len(cohort) * len(conditions))
        for sub in cohort:
            cal = calibrate_twin(sub, args.calibrate, model)
            for c in conditions:
                f = folder / f"{sub.name}_{c}.mcap"
                simulate_session(task, task_path, moves, n_per_path, sub, cal, c, args.minutes, f, model,
                                 digest)  # fmt: skip
                files.append(f)
                progress.advance(runs)
    study = analyse([load_session(f) for f in files])
    print_study(study)
    written = write_study(study, args.out)
    out.print(f"written: {len(files)} session files in {folder}; {', '.join(written)} in {args.out}")
    return study, fitted
