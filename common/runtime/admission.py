"""What a receiver does with a message that decodes but does not fit its state (DESIGN §9; docs/operations.md,
"Bad input"). The rules are decided here once, and every service applies them the same way:

1. Impossible on its face (an RR no heart makes, a window that ends before it starts, k above n, an empty
   Pareto set, a data time after 2100): the schema refuses it at decode (``schemas/``, msgspec ``Meta``
   and ``__post_init__``). The bus counts it under ``decode_errors``.
2. Possible, but not for this receiver: a data time far from the data time the receiver's stream has
   reached (ahead or behind), a duplicate of what it already answered, a sample rate other than the
   stream's. ``TimeLine`` decides; the service drops the message with ``Bus.reject`` (counted under
   ``rejected/<key>/<reason>``, logged at most once per key every 10 s) and never acts on it or persists
   it.
3. A handler that fails anyway is counted under ``handler_errors/<key>/<error>`` and the next message is
   handled (``Bus.handle``).

Data ahead of the receiver's clock is different (DESIGN §4): nothing honest comes from the future, so a
message that ends later than the receiver's clock plus the cell's skew bound (``skew_s``) is refused,
counted as ``ahead``, and never moves a time line, however many agree with it: a run of planted windows
or accelerometer an hour ahead once locked the honest stream out for its length.

Why mostly the stream's own data time and not the receiver's clock: a replay carries the recorded data
times (DESIGN §4), so a receiver cannot tell a recording from last week from a broken clock by its clock.
It can tell a single message that leaps away from its stream. A source that really moved in time (a
restarted replay, a clock set right, a strap back after an hour) sends a run of messages that are in line
with each other: after ``confirm`` of them the line moves there and the stream starts afresh. The
receiver's data clock (wall time live, the shared clock of a simulation) decides only where the stream
has no line yet or a line far from the clock: a message near the clock is believed at once, one far from
it waits for ``confirm`` more. So one hostile or broken message costs at most itself, even as a stream's
first, and an honest stream can never be locked out.
"""

from __future__ import annotations

from collections.abc import Hashable
from dataclasses import dataclass
from typing import Literal

SKEW_S = 0.05  # the cell's clock skew bound by default (CommonSettings.clock_skew_s)

Action = Literal["accept", "restart", "drop"]


@dataclass(frozen=True, slots=True)
class Verdict:
    action: Action
    code: str = ""  # why, short: the counter's name
    detail: str = ""  # why, for the log

    @property
    def acted_on(self) -> bool:
        return self.action != "drop"


_ACCEPT = Verdict("accept")


@dataclass(slots=True)
class _Line:
    position_ns: int  # the data time the stream has reached: the end of what was accepted
    kind: Hashable  # what must not change within a stream (a sample rate)
    run: int = 1  # messages in line with this one, itself included


class TimeLine:
    """Which data times are in line with a stream (rule 2 above).

    A message covering [start, end) is in line when it starts no earlier than ``tolerance_s`` before the
    line's position and no later than ``ahead_s`` after it, ends after it, and is of the line's kind.
    One that ends within ``duplicate_s`` before the position is a duplicate: dropped, and no sign that
    the source moved. Anything else is out of line: dropped, unless it is the ``confirm``-th message in
    a row in line with the one before it, which moves the line there (``restart``).
    """

    def __init__(
        self,
        ahead_s: float,
        tolerance_s: float = 0.0,
        duplicate_s: float = 0.0,
        confirm: int = 2,
        skew_s: float = SKEW_S,
    ) -> None:
        if not (ahead_s > 0 and tolerance_s >= 0 and duplicate_s >= 0 and confirm >= 2 and skew_s >= 0):
            raise ValueError("ahead_s > 0, tolerance_s ≥ 0, duplicate_s ≥ 0, confirm ≥ 2 and skew_s ≥ 0")
        self.ahead_ns = round(ahead_s * 1e9)
        self.skew_ns = round(skew_s * 1e9)
        self.tolerance_ns = round(tolerance_s * 1e9)
        self.duplicate_ns = round(duplicate_s * 1e9)
        self.confirm = confirm
        self._line: _Line | None = None
        self._candidate: _Line | None = None

    @property
    def position_ns(self) -> int | None:
        return self._line.position_ns if self._line is not None else None

    def anchor(self, position_ns: int, kind: Hashable = None) -> None:
        """Resume at a position known from before (a persisted state)."""
        self._line, self._candidate = _Line(position_ns, kind), None

    def _in_line(self, line: _Line, start_ns: int, end_ns: int, kind: Hashable) -> bool:
        p = line.position_ns
        return kind == line.kind and p - self.tolerance_ns <= start_ns <= p + self.ahead_ns and end_ns > p

    def future(self, end_ns: int, clock_ns: int) -> Verdict | None:
        """The verdict on a message that ends after the receiver's clock (plus the skew bound), judged
        alone, before anything is asked or moved for it; None for one that does not."""
        if end_ns <= clock_ns + self.skew_ns:
            return None
        return Verdict(
            "drop",
            "ahead",
            f"data time {(end_ns - clock_ns) / 1e9:.3f} s ahead of the receiver's clock (the skew "
            f"bound is {self.skew_ns / 1e9:g} s): from the future, refused",
        )

    def admit(
        self, start_ns: int, end_ns: int, kind: Hashable = None, clock_ns: int | None = None
    ) -> Verdict:
        """The verdict on a message covering [start, end). ``clock_ns`` is the receiver's data clock:
        a message near it (within ``ahead_s``) is believed where the stream has no line yet or its line
        is itself far from the clock (a stale persisted position, a replay that ended); elsewhere the
        stream's own line rules, so replays of old recordings work on their recorded times. A message that
        ends after the clock (plus the skew bound) is refused before anything else."""
        if clock_ns is not None and (future := self.future(end_ns, clock_ns)) is not None:
            return future
        line = self._line
        near = clock_ns is not None and abs(start_ns - clock_ns) <= self.ahead_ns
        if line is None and (clock_ns is None or near):
            self._line = _Line(end_ns, kind)
            return _ACCEPT
        if line is not None and self._in_line(line, start_ns, end_ns, kind):
            line.position_ns = max(line.position_ns, end_ns)
            self._candidate = None
            return _ACCEPT
        if (
            line is not None
            and kind == line.kind
            and line.position_ns - self.duplicate_ns < end_ns <= line.position_ns
        ):
            return Verdict("drop", "duplicate", "already answered (ends at or before the stream's data time)")
        if (
            near
            and clock_ns is not None
            and line is not None
            and abs(line.position_ns - clock_ns) > self.ahead_ns
        ):
            self._line, self._candidate = _Line(end_ns, kind), None
            return Verdict(
                "restart", "restarted", "at the receiver's data clock, the stream's was far from it"
            )
        cand = self._candidate
        if cand is not None and self._in_line(cand, start_ns, end_ns, kind):
            cand.position_ns, cand.run = max(cand.position_ns, end_ns), cand.run + 1
            if cand.run >= self.confirm:
                self._line, self._candidate = cand, None
                return Verdict(
                    "restart",
                    "restarted",
                    f"{cand.run} messages in a row agree on a new data time: starting afresh",
                )
        else:
            self._candidate = _Line(end_ns, kind)
        if line is None:
            assert clock_ns is not None
            off_s = (start_ns - clock_ns) / 1e9
            return Verdict(
                "drop",
                "far_from_clock",
                f"data time {abs(off_s):.3f} s {'ahead of' if off_s > 0 else 'behind'} the receiver's clock, "
                "and no stream to place it in yet",
            )
        if kind != line.kind:
            return Verdict("drop", "changed", f"{kind} where the stream has {line.kind}")
        p = line.position_ns
        off_s = ((start_ns - p) if start_ns > p else (end_ns - p)) / 1e9
        return Verdict(
            "drop",
            "ahead" if off_s > 0 else "behind",
            f"data time {abs(off_s):.3f} s {'ahead of' if off_s > 0 else 'behind'} the stream's",
        )
