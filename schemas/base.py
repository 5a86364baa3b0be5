"""What every message on the bus shares (DESIGN §3; msgspec docs/schema-evolution.rst).

Every message is a frozen Struct tagged ``"<family>.<name>.v<N>"`` in the field ``type``, encoded as
MessagePack, and carries the data time it refers to (``t_ns``, ns since the Unix epoch) and its sender's
sequence number (``seq``). New fields get defaults; a breaking change gets a new tag version. Unknown
fields are skipped (``forbid_unknown_fields`` stays off on the wire) so old decoders read new senders.

Validation at the edge, once (README "Bad input"): every field carries the bounds of what it can be in a
real cell (msgspec ``Meta``), and what relates two fields is checked in ``__post_init__``, which msgspec
runs at decode and turns into a ``ValidationError``. A message that decodes is therefore possible on its
face; whether it fits the receiver's state (its data time, what it already answered) is the receiver's
rule, in ``common/runtime/admission.py``.
"""

from __future__ import annotations

from typing import Annotated

import msgspec

# Data time after 2100-01-01 is a corrupt clock, not data (and keeps every time well inside int64).
MAX_TIME_NS = 4_102_444_800_000_000_000
INT64_MAX = 2**63 - 1
# What a human heart can do, beat to beat and averaged over a window: 20 to 300 beats per minute.
RR_MIN_S, RR_MAX_S = 0.2, 3.0
HUGE = 1e300  # bounds a float that must be finite: NaN and ±inf fail any comparison with it

TimeNs = Annotated[int, msgspec.Meta(ge=0, le=MAX_TIME_NS)]
NonNegInt = Annotated[int, msgspec.Meta(ge=0, le=INT64_MAX)]
Finite = Annotated[float, msgspec.Meta(ge=-HUGE, le=HUGE)]
PositiveFloat = Annotated[float, msgspec.Meta(gt=0, le=HUGE)]
Seconds = Annotated[float, msgspec.Meta(ge=0, le=HUGE)]
Fraction = Annotated[float, msgspec.Meta(ge=0.0, le=1.0)]
RrSeconds = Annotated[float, msgspec.Meta(ge=RR_MIN_S, le=RR_MAX_S)]
Name = Annotated[str, msgspec.Meta(max_length=200)]
Text = Annotated[str, msgspec.Meta(max_length=4000)]


class Message(msgspec.Struct, frozen=True, kw_only=True, tag_field="type"):
    t_ns: TimeNs
    seq: NonNegInt
