"""Which operator errors count (ε = errors per cycle): every one but the experimenter's marks they
withdrew. An ``undo`` (`cadence mark undo`, key ``u`` in a session's live view) withdraws the
experimenter's last mark before it and counts for nothing itself; the session, the analysis, the report
and the demo all count by this one rule."""

from __future__ import annotations

from collections.abc import Iterable

from schemas.operator import OperatorError


def counted(errors: Iterable[OperatorError]) -> list[OperatorError]:
    """The errors that count, in data-time order."""
    kept: list[OperatorError] = []
    for e in sorted(errors, key=lambda e: (e.t_ns, e.seq)):
        if e.kind != "undo":
            kept.append(e)
        elif marks := [i for i, m in enumerate(kept) if m.source == "experimenter"]:
            kept.pop(marks[-1])
    return kept
