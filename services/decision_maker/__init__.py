"""The decision maker's public interface: the decision as the service makes it (``Decider``: admission,
holds and persistence around Alg. 1 or the personal mode), for the benchmark on real people, and where
it keeps its state, for the demo's summary."""

from services.decision_maker.state import STATE_FILE, Decider, MovementRule

__all__ = ["STATE_FILE", "Decider", "MovementRule"]
