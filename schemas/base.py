"""What every message on the bus shares (DESIGN §3; msgspec docs/schema-evolution.rst).

Every message is a frozen Struct tagged ``"<family>.<name>.v<N>"`` in the field ``type``, encoded as
MessagePack, and carries the data time it refers to (``t_ns``, ns since the Unix epoch) and its sender's
sequence number (``seq``). New fields get defaults; a breaking change gets a new tag version. Unknown
fields are skipped (``forbid_unknown_fields`` stays off on the wire) so old decoders read new senders.
"""

from __future__ import annotations

from typing import Annotated

import msgspec

NonNegInt = Annotated[int, msgspec.Meta(ge=0)]
PositiveFloat = Annotated[float, msgspec.Meta(gt=0)]
Seconds = Annotated[float, msgspec.Meta(ge=0)]


class Message(msgspec.Struct, frozen=True, kw_only=True, tag_field="type"):
    t_ns: NonNegInt
    seq: NonNegInt
