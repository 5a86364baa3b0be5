"""The live session at the experimenter's terminal (`cadence session`): the subject's next session by the
study plan, the yoked k, the single keys that mark errors, the NASA-TLX at the end and the live view. The
session itself (checks, calibration, condition, recording) is cadence/lab/session.py."""

from __future__ import annotations

import argparse
import asyncio
import sys
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import TYPE_CHECKING

import msgspec
from rich.console import Console
from rich.table import Table

from common.runtime.errors import InputError

if TYPE_CHECKING:
    from cadence.lab.design import StudyPlan
    from cadence.lab.session import SessionOptions, Watch
    from schemas.session import Tlx

err = Console(stderr=True)


def planned(args: argparse.Namespace) -> StudyPlan | None:
    """With --study: the subject's next session by the plan, filled into ``args`` (condition, minutes,
    training, place, the last session's end); the plan. Without: the defaults, and no plan."""
    from cadence.lab.design import load_plan, next_session
    from schemas.session import CONDITION_NAMES

    args.period = args.previous_end_ns = None
    if not args.study:
        if args.condition is None:
            raise InputError("--condition: required without --study")
        args.minutes = args.minutes or 10.0
        return None
    plan = load_plan(Path(args.study))
    nxt = next_session(plan, sessions_folder(plan, args), args.subject)
    if nxt is None:
        raise InputError(f"subject {args.subject} has a complete session in every condition of {args.study}")
    if args.condition not in (None, nxt.condition):
        raise InputError(
            f"subject {args.subject}'s next session in {args.study} is ({nxt.condition}), period "
            f"{nxt.period}, not ({args.condition}): the order is the study's design"
        )
    args.condition, args.period = nxt.condition, nxt.period
    args.minutes = args.minutes or plan.minutes
    if args.training is None:
        args.training = plan.training_minutes if nxt.training else 0.0
    if nxt.previous is not None:
        args.previous_end_ns = nxt.previous.end.end_ns
    periods = len(plan.subject(args.subject).order)
    err.print(f"study {plan.name}: subject {args.subject}, period {nxt.period} of {periods}: condition "
              f"({nxt.condition}) {CONDITION_NAMES[nxt.condition]}"
              + (f", {args.training:g} min of training first" if args.training else ""))  # fmt: skip
    return plan


def sessions_folder(plan: StudyPlan, args: argparse.Namespace) -> Path:
    return Path(args.study).parent / plan.sessions


def fresh_path(folder: Path, subject: str, condition: str) -> Path:
    """SUBJECT_CONDITION.mcap in ``folder``: a run after a cut-short one gets _2, _3, …"""
    path, n = folder / f"{subject}_{condition}.mcap", 1
    while path.exists():
        n += 1
        path = folder / f"{subject}_{condition}_{n}.mcap"
    return path


def yoked_k(args: argparse.Namespace, plan: StudyPlan | None) -> int | None:
    """Condition y: the subject's mean k of (c), rounded, from their (c) session."""
    from cadence.lab.design import sessions_of
    from cadence.lab.session_file import load_session

    if args.condition != "y":
        return None
    if args.yoked_to:
        source = Path(args.yoked_to)
    else:
        done = (
            [d for d in sessions_of(plan, sessions_folder(plan, args), args.subject)
             if d.info.condition == "c" and d.end.complete] if plan else []
        )  # fmt: skip
        if not done:
            raise InputError(f"condition y: no complete (c) session of subject {args.subject} to yoke to")
        source = done[-1].path
    s = load_session(source)
    if s.info.subject != args.subject or s.info.condition != "c":
        raise InputError(f"{source}: not subject {args.subject}'s (c) session")
    k = round(s.mean_k)
    err.print(f"condition y: k = {k}, the mean k of {source.name} ({s.mean_k:.2f})")
    return k


def tty_keys(q: asyncio.Queue[str]) -> Callable[[], None] | None:
    """Single keys from the terminal into ``q`` (cbreak mode: no Enter needed); the returned function
    gives the terminal back. None when standard input is not a terminal."""
    import termios
    import threading
    import tty

    if not sys.stdin.isatty():
        return None
    loop = asyncio.get_running_loop()
    fd = sys.stdin.fileno()
    saved = termios.tcgetattr(fd)
    tty.setcbreak(fd)

    def read() -> None:
        while ch := sys.stdin.read(1):
            loop.call_soon_threadsafe(q.put_nowait, ch)

    threading.Thread(target=read, daemon=True).start()
    return lambda: termios.tcsetattr(fd, termios.TCSADRAIN, saved)


def parse_tlx(text: str) -> Tlx:
    from schemas.session import Tlx

    try:
        values = [int(v) for v in text.split(",")]
        return msgspec.convert(dict(zip(Tlx.__struct_fields__, values, strict=True)), Tlx)
    except (ValueError, msgspec.ValidationError) as exc:
        raise InputError(f"--tlx {text}: six integers 0-100, mental to frustration ({exc})") from None


def ask_tlx(given: Tlx | None) -> Callable[[], Awaitable[Tlx | None]]:
    """The questionnaire at the end: the scores given, or each item asked on the terminal."""

    async def ask() -> Tlx | None:
        if given is not None:
            return given
        from schemas.session import Tlx

        answers = []
        for item in Tlx.__struct_fields__:
            while True:
                text = await asyncio.to_thread(
                    input, f"NASA-TLX {item} (0-100, empty: skip the questionnaire): "
                )
                if not text.strip():
                    return None
                if text.strip().isdecimal() and 0 <= int(text) <= 100:
                    answers.append(text.strip())
                    break
        return parse_tlx(",".join(answers))

    return ask


def session_view(phase: str, w: Watch, opts: SessionOptions) -> Table:
    """The experimenter's view: the checks until the cell is ready, then RR, k, cycles, errors, time left."""
    from cadence.lab.session import STALE_S

    t = Table(
        title=f"cadence session — subject {opts.subject}, condition ({opts.condition}): {phase}",
        caption="keys: e wrong object, l late, o other error, u undo the last mark · 1…9 the task's n-th "
        "signal · Ctrl-C ends",
    )
    if w.start_ns is None:
        t.add_column("check")
        t.add_column("state")
        for what, why in w.readiness().items():
            t.add_row(what, "[green]ok[/green]" if why is None else why)
        return t
    for col in ("time left", "mean RR (last window)", "k", "cycles", "φ so far", "errors", "robot"):
        t.add_column(col, justify="right")
    done_s = max(0.0, (w.data_ns - w.start_ns) / 1e9)
    win = w.window
    quiet = time.monotonic() - w.data_wall
    t.add_row(
        f"{max(0.0, opts.minutes * 60 - done_s):.0f} s" + (f" [red](no data for {quiet:.0f} s)[/red]"
                                                           if quiet > STALE_S else ""),
        f"{win.mean_rr_s:.3f} s ({win.quality})" if win and win.mean_rr_s else "—",
        str(w.selection.k) if w.selection else "—",
        str(w.cycles),
        f"{w.cycles / (done_s / 60):.2f}/min" if done_s > 0 else "—",
        str(w.errors),
        w.robot.state if w.robot else "—",
    )  # fmt: skip
    return t
