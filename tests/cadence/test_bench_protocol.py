"""The benchmarks' timing protocol (cadence/bench/protocol.py, issue 77): equal tries, one of each side in
turn, CPU of the process tree (a child's too, once it ended) beside wall time."""

from __future__ import annotations

import subprocess
import sys

import pytest

from cadence.bench.protocol import interleaved, protocol


def test_the_sides_take_equal_tries_in_turn_and_a_childs_cpu_counts() -> None:
    order: list[str] = []

    def spin() -> int:  # a child that burns about 0.2 s of CPU: counted once it has ended
        order.append("child")
        return subprocess.run(
            [sys.executable, "-c", "i = 0\nwhile i < 4_000_000: i += 1"], check=True
        ).returncode

    def nothing() -> int:
        order.append("nothing")
        return 0

    sides, last = interleaved({"child": spin, "nothing": nothing}, tries=3)
    assert order == ["child", "nothing"] * 3
    assert last == {"child": 0, "nothing": 0}
    assert len(sides["child"].cpu_s) == len(sides["nothing"].cpu_s) == 3
    assert sides["child"].cpu > 10 * max(sides["nothing"].cpu, 1e-3)  # the child's CPU, not the parent's wait
    assert all(w > 0.0 for w in sides["child"].wall_s)
    assert set(sides["child"].to_json()) >= {"cpu_s", "wall_s", "cpu_spread"}
    with pytest.raises(ValueError, match="tries"):
        interleaved({"a": nothing}, tries=0)
    said = protocol(3, 1)
    assert said["tries"] == 3 and said["interleaved"] is True and said["workers"] == 1 and said["load"] >= 0.0
