"""SQLite (WAL) storage of computed Pareto sets, keyed by path id and content hash (DESIGN §10).

A damaged database is moved aside and a new one started, so the store plans again rather than crash-loop
(DESIGN §9); a stored set that no longer decodes is deleted and planned again."""

from __future__ import annotations

import logging
import sqlite3
from pathlib import Path

import msgspec

from common.runtime.clock import wall_ns
from common.runtime.storage import quarantine
from common.trajectory.planner import content_hash
from common.trajectory.task import Task
from schemas.pareto import ParetoSet

log = logging.getLogger("cadence.pareto_store")

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

    def __init__(self, path: Path, read_only: bool = False) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        if read_only:
            # immutable: no lock and no -shm file to make (a full disk cannot take one); what is still
            # in the WAL alone is not seen, and planned again
            self._db = sqlite3.connect(f"file:{path}?mode=ro&immutable=1", uri=True, check_same_thread=False,
                                       isolation_level=None)  # fmt: skip
        else:
            self._db = sqlite3.connect(path, check_same_thread=False, isolation_level=None)
        try:
            if not read_only:
                self._db.execute("PRAGMA journal_mode=WAL")
                self._db.execute("PRAGMA synchronous=FULL")
                self._db.execute(_SCHEMA)
            (verdict,) = self._db.execute("PRAGMA quick_check").fetchone()
            if verdict != "ok":
                raise sqlite3.DatabaseError(f"integrity check: {verdict}")
        except sqlite3.DatabaseError:
            self._db.close()
            raise
        self._decoder = msgspec.msgpack.Decoder(ParetoSet)

    @classmethod
    def open(cls, path: Path) -> tuple[SetStore, str | None]:
        """The store at ``path``; a damaged one is moved aside (with its WAL) and a new one made. The
        second value says what was wrong, for the log and the status. A full or read-only disk is not
        damage (SQLite's OperationalError): the database is left as it is and opened to read, so the sets
        it holds are served, and what is planned meanwhile is served from memory."""
        try:
            return cls(path), None
        except sqlite3.OperationalError as exc:
            if not path.exists():
                raise
            why = f"{path}: {exc}; not damaged, left as it is: serving the sets it holds, storing none"
            return cls(path, read_only=True), why
        except sqlite3.DatabaseError as exc:
            moved = quarantine(path)
            for side in ("-wal", "-shm"):
                extra = path.with_name(path.name + side)
                if extra.exists():
                    extra.rename(moved.with_name(moved.name + side))
            problem = f"{path}: {exc}; moved aside to {moved.name}, the sets will be planned again"
            return cls(path), problem

    def current(self, task: Task) -> tuple[dict[str, str], dict[str, ParetoSet]]:
        """Each path's content hash (its waypoints, limits and planner settings), and the stored sets that
        have it: a set planned for anything else is never served."""
        digests = {pid: content_hash(p, task.limits, task.planner) for pid, p in task.paths.items()}
        stored = {pid: self.load(pid, digest) for pid, digest in digests.items()}
        return digests, {pid: s for pid, s in stored.items() if s is not None}

    def load(self, path_id: str, content_hash: str) -> ParetoSet | None:
        row = self._db.execute(
            "SELECT payload FROM pareto_sets WHERE path_id = ? AND content_hash = ?", (path_id, content_hash)
        ).fetchone()
        if row is None:
            return None
        try:
            s = self._decoder.decode(row[0])
        except (msgspec.ValidationError, msgspec.DecodeError) as exc:
            log.error(
                "the stored set for '%s' does not decode (%s): deleted, it will be planned again",
                path_id,
                exc,
            )
            self.delete(path_id, content_hash)
            return None
        return s if (s.path_id, s.content_hash) == (path_id, content_hash) else None

    def by_hash(self, content_hash: str) -> ParetoSet | None:
        """A set planned from the inputs ``content_hash`` names, whatever its path is called here: what
        this store answers another cell of the plant that asks for it (``PLANT_SETS``)."""
        rows = self._db.execute(
            "SELECT payload FROM pareto_sets WHERE content_hash = ? ORDER BY created_ns DESC", (content_hash,)
        ).fetchall()
        for (payload,) in rows:
            try:
                s = self._decoder.decode(payload)
            except (msgspec.ValidationError, msgspec.DecodeError):
                continue
            if s.content_hash == content_hash:
                return s
        return None

    def previous(self, path_id: str, content_hash: str) -> ParetoSet | None:
        """The newest set of this path planned for something else (a waypoint since edited): its
        solutions seed the new search (planner.warm_seeds). None when there is none that decodes."""
        rows = self._db.execute(
            "SELECT payload FROM pareto_sets WHERE path_id = ? AND content_hash != ? "
            "ORDER BY created_ns DESC",
            (path_id, content_hash),
        ).fetchall()
        for (payload,) in rows:
            try:
                return self._decoder.decode(payload)
            except (msgspec.ValidationError, msgspec.DecodeError):
                continue
        return None

    def delete(self, path_id: str, content_hash: str) -> None:
        with self._db:
            self._db.execute(
                "DELETE FROM pareto_sets WHERE path_id = ? AND content_hash = ?", (path_id, content_hash)
            )

    def save(self, msg: ParetoSet) -> None:
        with self._db:  # one transaction
            self._db.execute(
                "INSERT OR REPLACE INTO pareto_sets VALUES (?, ?, ?, ?)",
                (msg.path_id, msg.content_hash, wall_ns(), msgspec.msgpack.encode(msg)),
            )

    def close(self) -> None:
        self._db.close()
