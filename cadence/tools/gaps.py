"""What a watcher of the bus did not see, from the senders' own numbers (DESIGN §3: each sender numbers
its messages per key). The demo's summary was made by an observer in the demo's own process: stopped for
10 s it counted 8 cycles where a monitor saw 12, and said nothing (issue 39). A key's ``seq`` says how
many it missed: a jump forward is that many lost, the same number again is a republication, and a lower
one is the sender started afresh (a restarted service counts from 0), whose first numbers, if they are not
there, were lost too.

Only a key with one sender can be judged so: two senders' numbers interleave.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field


@dataclass
class Gaps:
    last: dict[str, int] = field(default_factory=dict)  # by key, the last number seen
    missed: Counter[str] = field(default_factory=Counter)  # by key, messages the numbers say were sent
    restarts: Counter[str] = field(default_factory=Counter)  # by key, the sender started afresh

    def note(self, key: str, seq: int) -> int:
        """One message seen; how many before it were not."""
        last = self.last.get(key)
        self.last[key] = seq if last is None or seq != last else last
        if last is None or seq == last:  # the first seen (what came before the watcher is not its to count)
            return 0
        if seq > last:
            lost = seq - last - 1
        else:  # numbered from 0 again: a new sender (a restart), and what it sent before this
            self.restarts[key] += 1
            lost = seq
        self.missed[key] += lost
        return lost

    def said(self) -> str:
        """One line for a person, empty when nothing was missed."""
        if not self.missed or not any(self.missed.values()):
            return ""
        parts = ", ".join(f"{key.rsplit('/', 2)[-2]}/{key.rsplit('/', 1)[-1]} {n}"
                          for key, n in sorted(self.missed.items()) if n)  # fmt: skip
        return f"the observer missed messages the cell sent ({parts}): the counts are the senders' numbers"
