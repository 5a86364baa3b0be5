"""A study's plan (`cadence study plan`): who the subjects are, in what order each meets the conditions,
and where their session files go; `cadence session --study` reads it.

- Subjects are pseudonymous IDs (S01, S02, …): a typo is refused at the session, not found at the
  analysis as an unpaired subject. Who is who, and any demographics, stay in a separate file
  (``demographics.csv`` beside the plan, one row per ID to fill in by hand) that no session file names.
- The order of conditions is counterbalanced by a Williams design (Williams 1949): every condition
  comes equally often in each place, and follows every other equally often, so learning and carry-over
  cancel over the subjects. For three conditions it takes two Latin squares: 6 sequences; subjects take
  them in a seeded shuffled order, block by block, so any 6 consecutive subjects are balanced.
- A subject's next session is the first condition of their sequence without a complete session file in
  the plan's sessions folder; a cut-short one is run again.
"""

from __future__ import annotations

import csv
import io
import json
import random
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import msgspec

from common.runtime.errors import InputError
from common.runtime.storage import write_readable
from schemas.session import Condition, SessionEnd, SessionInfo

DEMOGRAPHICS = ("id", "age", "sex", "handedness", "notes")


def williams(k: int) -> list[list[int]]:
    """The sequences of a Williams design for k conditions: k of them for even k, 2k for odd k."""
    first, lo, hi = [0], 1, k - 1
    while len(first) < k:
        first.append(lo)
        lo += 1
        if len(first) < k:
            first.append(hi)
            hi -= 1
    square = [[(c + i) % k for c in first] for i in range(k)]
    return square if k % 2 == 0 else square + [row[::-1] for row in square]


class Subject(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    id: str
    order: list[Condition]


class StudyPlan(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    name: str
    subjects: Annotated[list[Subject], msgspec.Meta(min_length=1)]
    minutes: Annotated[float, msgspec.Meta(gt=0, le=240)] = 10.0  # per session, data time
    training_minutes: Annotated[float, msgspec.Meta(ge=0, le=60)] = 5.0  # before a subject's first session
    break_minutes: Annotated[float, msgspec.Meta(ge=0, le=240)] = 5.0  # at least, between two sessions
    sessions: str = "sessions"  # the folder of session files, beside the plan

    def __post_init__(self) -> None:
        """What the schema cannot say: each subject once, each condition once per subject, the sessions'
        folder inside the plan's (a plan pointing elsewhere would read and write files outside it)."""
        ids = [s.id for s in self.subjects]
        if twice := sorted({i for i in ids if ids.count(i) > 1}):
            raise ValueError(f"subjects listed more than once: {', '.join(twice)}")
        for s in self.subjects:
            if len(set(s.order)) != len(s.order):
                raise ValueError(f"subject {s.id}: a condition twice in its order {s.order}")
        folder = Path(self.sessions)
        if folder.is_absolute() or ".." in folder.parts or not self.sessions.strip():
            raise ValueError(f'sessions = {self.sessions!r}: a folder inside the plan\'s, e.g. "sessions"')

    def subject(self, sid: str) -> Subject:
        for s in self.subjects:
            if s.id == sid:
                return s
        ids = [s.id for s in self.subjects]
        raise InputError(f"subject {sid!r} is not in study {self.name!r} ({ids[0]} … {ids[-1]})")


def make_plan(name: str, n: int, conditions: list[Condition], seed: int = 1) -> StudyPlan:
    """The yoked control (y) holds the subject's own mean k of (c), so it comes last, after the
    counterbalanced others."""
    yoked: list[Condition] = ["y"] if "y" in conditions else []
    conditions = [c for c in conditions if c != "y"]
    seqs = williams(len(conditions))
    rng = random.Random(seed)
    order: list[list[int]] = []
    while len(order) < n:
        block = seqs[:]
        rng.shuffle(block)
        order += block
    width = max(2, len(str(n)))
    subjects = [Subject(f"S{i + 1:0{width}d}", [conditions[c] for c in order[i]] + yoked) for i in range(n)]
    return StudyPlan(name=name, subjects=subjects)


def write_plan(plan: StudyPlan, path: Path) -> list[Path]:
    """The plan as TOML, and beside it the demographics sheet, never overwritten (it holds people's data).
    Both or neither: the sheet first, and taken back if the plan then cannot be written (a plan written
    without its sheet was refused on a rerun, for the plan existed, and the sheet was never written)."""
    lines = [f"name = {json.dumps(plan.name)}", f"minutes = {plan.minutes:g}",
             f"training_minutes = {plan.training_minutes:g}", f"break_minutes = {plan.break_minutes:g}",
             f"sessions = {json.dumps(plan.sessions)}", ""]  # fmt: skip
    for s in plan.subjects:
        lines += ["[[subjects]]", f"id = {json.dumps(s.id)}", f"order = {json.dumps(s.order)}", ""]
    sheet = path.with_name("demographics.csv")
    written: list[Path] = []
    if not sheet.exists():
        rows = io.StringIO(newline="")
        w = csv.writer(rows)
        w.writerow(DEMOGRAPHICS)
        for s in plan.subjects:
            w.writerow([s.id, *[""] * (len(DEMOGRAPHICS) - 1)])
        _write_or_say(sheet, rows.getvalue().encode())
        written.append(sheet)
    try:
        _write_or_say(path, "\n".join(lines).encode())
    except InputError:
        for f in written:  # just written, nobody's data yet
            f.unlink(missing_ok=True)
        raise
    return [path, *written]


def _write_or_say(path: Path, data: bytes) -> None:
    """Whole or not at all (a full disk once left a sheet at 0 bytes); the error names this file."""
    try:
        write_readable(path, data)
    except OSError as exc:
        raise InputError(f"{path}: cannot be written ({exc.strerror or exc})") from None


def load_plan(path: Path) -> StudyPlan:
    try:
        return msgspec.convert(tomllib.loads(path.read_text(encoding="utf-8")), StudyPlan)
    except OSError as exc:
        raise InputError(f"{path}: {exc.strerror}") from None
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not a study plan: not UTF-8 text (byte {exc.start})") from None
    except (tomllib.TOMLDecodeError, msgspec.ValidationError) as exc:
        raise InputError(f"{path}: not a study plan: {exc}") from None


@dataclass(frozen=True, slots=True)
class Done:
    path: Path
    info: SessionInfo
    end: SessionEnd


def sessions_of(plan: StudyPlan, folder: Path, sid: str) -> list[Done]:
    """The subject's closed session files in the plan's folder, by start."""
    from cadence.lab.session_file import read_records

    done = []
    for path in sorted(folder.glob("*.mcap")):
        try:
            info, end = read_records(path)
        except InputError:
            continue  # not a closed session file: the analysis says why
        if info.subject == sid and info.study == plan.name:
            done.append(Done(path, info, end))
    return sorted(done, key=lambda d: d.info.start_ns)


@dataclass(frozen=True, slots=True)
class Next:
    condition: Condition
    period: int  # 1 = the subject's first
    previous: Done | None  # the subject's last session, for the break since
    training: bool  # the subject's first session: training first


def next_session(plan: StudyPlan, folder: Path, sid: str) -> Next | None:
    """The subject's next condition in their order; None when every one has a complete session."""
    subject = plan.subject(sid)
    done = sessions_of(plan, folder, sid)
    complete = {d.info.condition for d in done if d.end.complete}
    for i, c in enumerate(subject.order):
        if c not in complete:
            return Next(c, i + 1, done[-1] if done else None, not done)
    return None
