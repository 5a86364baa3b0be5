"""The selection in force (DESIGN §8): the one holder of the decision maker's k in the executor, of the k the
arm runs at, and of a switch within a path. A selection is a sequence: one is new only when its seq is
greater than the one in force, by no more than a bounded step, and its stamp not older than the one in
force by more than a period (``admit``). At start the current one is asked for (selections are state,
DESIGN §11), and where the decision maker cannot be reached, ``start_selection`` says what stands in for it.
"""

from __future__ import annotations

import asyncio
import logging

import numpy as np

from common.decision import k_for_path
from common.runtime.bus import Bus
from common.runtime.node import Rejected
from common.safety.states import Event
from schemas.decision import Selection
from schemas.topology import SELECTION
from services.executor.kit import Kit, Safety
from services.executor.playback import PathRun
from services.executor.reaction import Reactions
from services.executor.records import Records
from services.executor.sets import SetCache
from services.executor.settings import Settings

log = logging.getLogger("cadence.executor")
SEQ_STEP = 16  # a selection's seq may pass the one in force by this, and one more per second of its stamp


def admit(sel: Selection, cur: Selection | None, period_s: float) -> bool:
    """Whether ``sel`` is a new decision over ``cur`` (False: the current one said again, nothing to do);
    ``Rejected`` when it must not stand. New only when its seq is greater *and* its stamp is not older than
    the one in force by more than ``period_s`` (a decision may be stamped a little before one a rogue
    stamped ahead: the end of its window), and its seq passes the one in force by at most ``SEQ_STEP`` and
    one more per second between their stamps: an honest decision maker numbers one selection per window.
    Either alone let a rogue with the decision maker's account lock it out: seq 2⁶³−1 at a current stamp
    made every honest one after it stale, a stamp 40 ms ahead refused the next honest decision, and one
    stamped an hour ago, at 10 Hz, held its k most of the time uncounted."""
    if cur is None:
        return True
    if (sel.seq, sel.t_ns, sel.k, sel.n) == (cur.seq, cur.t_ns, cur.k, cur.n):
        return False  # said again while it holds
    was = f"the one applied (k = {cur.k}, seq {cur.seq})"
    if sel.seq <= cur.seq:
        raise Rejected("stale", f"a selection (k = {sel.k}, seq {sel.seq}) numbered no later than {was}")
    behind_s = (cur.t_ns - sel.t_ns) / 1e9
    if behind_s > period_s:
        raise Rejected("stale", f"a selection (k = {sel.k}, seq {sel.seq}) stamped {behind_s:.3f} s before "
                       f"{was}: over {period_s:g} s")  # fmt: skip
    step = SEQ_STEP + max(0, sel.t_ns - cur.t_ns) // 1_000_000_000
    if sel.seq - cur.seq > step:
        raise Rejected("jump", f"a selection (k = {sel.k}, seq {sel.seq}) numbered {sel.seq - cur.seq} past "
                       f"{was}: at most {step} for the time between their stamps")  # fmt: skip
    return True


class SelectionInForce:
    """Owns the newest selection decided (``selection``, and ``changed`` set at each), the k the arm runs
    at or ran last (``k``), and the switch to a new k within a running path."""

    def __init__(
        self,
        kit: Kit,
        settings: Settings,
        bus: Bus,
        safety: Safety,
        records: Records,
        sets: SetCache,
        reactions: Reactions,
    ) -> None:
        self.kit, self.settings, self.bus, self.safety, self.records = kit, settings, bus, safety, records
        self.sets, self.reactions = sets, reactions
        self.selection: Selection | None = None
        self.changed = asyncio.Event()
        self.k: int | None = None
        self.switching: asyncio.Task[None] | None = None  # in the node's task group (Kit.start_soon)

    def select(self, sel: Selection) -> None:
        """A selection is a sequence (DESIGN §8, ``admit``): what it refuses is counted (``stale``,
        ``jump``) and logged at most once per 10 s. The decision maker's republishing of the current one is
        no new decision."""
        if not admit(sel, self.selection, self.settings.selection_period_s):
            return
        self.selection = sel
        self.changed.set()
        self.records.received(sel)
        self.safety.fire(Event.SELECTION)
        run = self.reactions.run
        if run is not None and self.settings.switch_within_path and self.switching is None:
            self.switching = self.kit.start_soon(self.switch_within(run), "a switch within a path")

    def running_at(self, k: int) -> None:
        """The arm runs (or ran last) at ``k``: what robot/state says."""
        self.k = k

    async def switch_within(self, run: PathRun) -> None:
        """A new selection during a path: the rest of it at the new k, when that can join within the
        limits and at the scale the person's distance allows on it (``PathRun``,
        services/executor/playback.py); otherwise, as ever, from the next path start."""
        try:
            s = self.sets.sets.get(run.path.id)
            n = len(s.solutions) if s is not None else 0

            def wanted() -> int:
                return k_for_path(self.selection.k, n) if self.selection is not None else 0

            while s is not None and self.selection is not None and self.reactions.run is run:
                k, sel, k_was = wanted(), self.selection, run.k
                if k == run.k:
                    return
                lead = self.settings.switch_lead_s
                took, why = await run.switch(k, np.array(s.solutions[k - 1].h), wanted, lead,
                                             self.reactions.allowed)  # fmt: skip
                if not took:
                    if why != "no longer wanted":
                        self.safety.event("info", f"{why}: k = {k} from the next path", run.path.id)
                    return
                text = (f"k {k_was} → {k} within '{run.path.id}' at s = {run.switched_at:.3f} s; it now ends "
                        f"at {run.playback.curve.t_f:.3f} s, at most {run.figures.speed_m_s:.2f} m/s, "
                        f"stopping within {run.figures.stop_time_s:.2f} s")  # fmt: skip
                self.safety.event("switch", text, run.path.id)
                self.k = k
                await self.records.applied(sel, hold=False)  # the arm is moving
        except Exception as e:  # the path runs on at its k: the switch's failure is said, not the node's
            log.exception("a switch within '%s' failed", run.path.id)
            why = f"the switch within the path failed ({e!r}): the new k from the next path"
            self.safety.event("info", why, run.path.id)
        finally:
            self.switching = None

    async def ask(self) -> bool:
        """Selections are state: ask for the current one at start (DESIGN §11). True when one came."""
        for r in await self.bus.get(SELECTION, timeout=self.settings.query_timeout_s):
            if r.message is not None:
                try:
                    self.select(r.message)
                except Rejected as exc:  # a newer one came on the key meanwhile: that one stands
                    self.bus.reject(self.bus.key(SELECTION.suffix), exc.code, exc.detail)
                return True
        return False

    async def start(self) -> None:
        """No motion without a current selection: the decision maker's, or, when it cannot be reached, what
        ``start_selection`` allows. What was chosen, and why, is an event."""
        # answered, or published meanwhile (the fallbacks below must not override the decision maker's)
        if await self.ask() or self.selection is not None:
            assert self.selection is not None
            self.safety.event("info", f"selection from the decision maker: k = {self.selection.k}")
            return
        settings = self.settings
        policy = settings.start_selection or ("wait" if settings.backend == "ur_rtde" else "last")
        last = self.records.store.record.newest
        max_age = settings.last_selection_max_age_s
        unreachable = "the decision maker does not answer"
        if policy == "last" and last is not None and last.age_s() <= max_age:
            self.select(last.selection())
            self.safety.event(
                "info",
                f"{unreachable}: going on at the newest selection it decided, k = {last.k} (n = {last.n}), "
                f'{last.age_s():.0f} s ago (start_selection = "last")',
            )
        elif policy == "initial":
            k = settings.initial_k
            # stamped 0: the executor's own, older than any the decision maker makes
            self.select(Selection(t_ns=0, seq=0, k=k, n=k, delta=0, reason="initial"))
            self.safety.event(
                "info",
                f'{unreachable}: starting at initial_k = {k}, as configured (start_selection = "initial")',
            )
        else:
            why = (
                'start_selection = "wait"'
                if policy == "wait"
                else "no selection on file"
                if last is None
                else f"the last one on file is {last.age_s():.0f} s old, over {max_age:.0f} s"
            )
            self.safety.event("info", f"{unreachable}: waiting for a selection ({why})")
