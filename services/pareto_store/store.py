"""SQLite (WAL) storage of computed Pareto sets, keyed by path id and content hash (DESIGN §10)."""

from __future__ import annotations

import sqlite3
import time
from pathlib import Path

import msgspec

from schemas.pareto import ParetoSet

_SCHEMA = """
CREATE TABLE IF NOT EXISTS pareto_sets (
    path_id      TEXT    NOT NULL,
    content_hash TEXT    NOT NULL,
    created_ns   INTEGER NOT NULL,
    payload      BLOB    NOT NULL,  -- the ParetoSet message, MessagePack
    PRIMARY KEY (path_id, content_hash)
)
"""


class SetStore:
    """One connection, used from one thread at a time (the service calls it through to_thread)."""

    def __init__(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        self._db = sqlite3.connect(path, check_same_thread=False, isolation_level=None)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=FULL")
        self._db.execute(_SCHEMA)
        self._decoder = msgspec.msgpack.Decoder(ParetoSet)

    def load(self, path_id: str, content_hash: str) -> ParetoSet | None:
        row = self._db.execute(
            "SELECT payload FROM pareto_sets WHERE path_id = ? AND content_hash = ?", (path_id, content_hash)
        ).fetchone()
        return None if row is None else self._decoder.decode(row[0])

    def save(self, msg: ParetoSet) -> None:
        with self._db:  # one transaction
            self._db.execute(
                "INSERT OR REPLACE INTO pareto_sets VALUES (?, ?, ?, ?)",
                (msg.path_id, msg.content_hash, time.time_ns(), msgspec.msgpack.encode(msg)),
            )

    def close(self) -> None:
        self._db.close()
