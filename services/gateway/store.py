"""SQLite persistence (WAL) of jobs (missions, explorations), their events and their images.

* ``jobs``: one row per job with its request and the record folded from its events
  (:func:`services.gateway.records.apply_event`), updated in the same transaction as each event;
* ``events``: every event, keyed (job, seq); a redelivered event is ignored, so ingest is idempotent;
* ``images``: each JPEG stored once, served by URL.

Writes go through one connection under a lock (SQLite has one writer anyway); reads use one
connection per thread, which WAL lets run beside the writer without blocking.

Every write also updates a small in-memory entry per job (revision, state, last seq), so the hot
reads of a dashboard under load - "has this job changed since I encoded it?" and "how far has it
got?" - cost a dict lookup instead of a query. This assumes that this process is the only writer
of the file (one gateway per database), which is how the gateway is deployed.
"""

from __future__ import annotations

import json
import logging
import re
import sqlite3
import threading
import time
from dataclasses import dataclass
from functools import cached_property
from itertools import count
from pathlib import Path
from typing import Any

from services.gateway.records import KIND_STATES, TERMINAL, JobKind, apply_event, empty_summary
from shared.schemas import JobEvent, JobState

log = logging.getLogger(__name__)

_TERMINAL_VALUES = frozenset(s.value for s in TERMINAL)
_IMAGE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
    id TEXT PRIMARY KEY,
    kind TEXT NOT NULL,
    state TEXT NOT NULL,
    step INTEGER NOT NULL DEFAULT 0,
    last_seq INTEGER NOT NULL DEFAULT -1,
    request TEXT NOT NULL,
    summary TEXT NOT NULL,
    created_s REAL NOT NULL,
    updated_s REAL NOT NULL
);
CREATE INDEX IF NOT EXISTS jobs_kind_state ON jobs (kind, state, created_s);
CREATE INDEX IF NOT EXISTS jobs_kind_created ON jobs (kind, created_s);
CREATE TABLE IF NOT EXISTS events (
    job_id TEXT NOT NULL,
    seq INTEGER NOT NULL,
    kind TEXT NOT NULL,
    state TEXT NOT NULL,
    step INTEGER NOT NULL,
    timestamp_s REAL NOT NULL,
    data TEXT NOT NULL,
    images TEXT NOT NULL,
    PRIMARY KEY (job_id, seq)
) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS images (
    job_id TEXT NOT NULL,
    seq INTEGER NOT NULL,
    name TEXT NOT NULL,
    jpeg BLOB NOT NULL,
    PRIMARY KEY (job_id, seq, name)
);
"""


class StoreError(Exception):
    """Base of the store's errors."""


class JobExists(StoreError):
    pass


class EventRejected(StoreError):
    """An event that cannot be true of its job (unknown job, the job already ended, a seq that does
    not increase, a kind that contradicts its state): stored nowhere, counted by the ingest."""

    def __init__(self, job_id: str, seq: int, reason: str):
        super().__init__(f"event {job_id}/{seq} rejected: {reason}")
        self.job_id, self.seq, self.reason = job_id, seq, reason


def image_url(kind: JobKind, job_id: str, seq: int, name: str) -> str:
    return f"/{kind.value}s/{job_id}/events/{seq}/images/{name}.jpg"


@dataclass(frozen=True)
class JobRow:
    id: str
    kind: JobKind
    state: JobState
    step: int
    last_seq: int
    request: dict[str, Any]
    summary: dict[str, Any]
    created_s: float
    updated_s: float

    @property
    def terminal(self) -> bool:
        return self.state in TERMINAL


@dataclass(frozen=True)
class StoredEvent:
    """One stored event; ``data_json`` is the stored text, parsed into ``data`` only when asked."""

    job_id: str
    seq: int
    kind: str
    state: JobState
    step: int
    timestamp_s: float
    data_json: str
    image_names: list[str]

    @cached_property
    def data(self) -> dict[str, Any]:
        return json.loads(self.data_json)


@dataclass(frozen=True)
class JobMeta:
    """What the store knows of a job without reading it: ``revision`` changes on every write."""

    revision: int
    state: JobState
    last_seq: int


def _json(obj: Any) -> str:
    # Planner data may hold numpy scalars or tuples; anything JSON cannot encode becomes its str.
    return json.dumps(obj, separators=(",", ":"), default=lambda o: o.item() if hasattr(o, "item") else str(o))


class GatewayStore:
    """The gateway's database. Thread-safe; ``with GatewayStore(path) as store: ...``."""

    def __init__(self, path: Path | str):
        self.path = Path(path)
        if str(path) != ":memory:":
            self.path.parent.mkdir(parents=True, exist_ok=True)
        self._write_lock = threading.Lock()
        self._local = threading.local()
        self._readers: list[sqlite3.Connection] = []
        self._readers_lock = threading.Lock()
        self._closed = False
        self._meta: dict[str, JobMeta] = {}
        self._meta_lock = threading.Lock()
        self._revisions = count(1)
        self._writer = self._connect()
        with self._write_lock, self._writer:
            self._writer.executescript(_SCHEMA)

    def _connect(self) -> sqlite3.Connection:
        conn = sqlite3.connect(self.path, check_same_thread=False, timeout=30.0, isolation_level=None)
        conn.execute("PRAGMA journal_mode=WAL")
        # NORMAL in WAL mode loses at most the last transactions on power loss, never corrupts.
        conn.execute("PRAGMA synchronous=NORMAL")
        conn.execute("PRAGMA busy_timeout=30000")
        return conn

    def _reader(self) -> sqlite3.Connection:
        if self._closed:
            raise StoreError("the store is closed")
        conn = getattr(self._local, "conn", None)
        if conn is None:
            conn = self._connect()
            conn.execute("PRAGMA query_only=1")
            self._local.conn = conn
            with self._readers_lock:
                self._readers.append(conn)
        return conn

    # --- in-memory job metadata ---------------------------------------------------------------------
    def _set_meta(self, job_id: str, state: JobState | str, last_seq: int) -> None:
        # Called after COMMIT: a reader that sees the new revision also sees the new row.
        with self._meta_lock:
            self._meta[job_id] = JobMeta(next(self._revisions), JobState(state), last_seq)

    def _adopt(self, row: JobRow) -> int:
        """Register a job read from the file; returns its revision, or -1 when a write raced the read
        (then the caller must not cache what it read under any revision)."""
        with self._meta_lock:
            meta = self._meta.get(row.id)
            if meta is None:
                meta = self._meta[row.id] = JobMeta(next(self._revisions), row.state, row.last_seq)
                return meta.revision
        return -1

    def revision(self, job_id: str) -> int | None:
        """The job's current revision (None: not read or written by this process yet)."""
        meta = self._meta.get(job_id)
        return None if meta is None else meta.revision

    def get_job_revision(self, job_id: str, kind: JobKind | None = None) -> tuple[JobRow | None, int]:
        """A job and the revision it is at (-1: do not cache it). The revision is read first, so a
        concurrent write can only make the pair look older than it is, never newer."""
        rev = self.revision(job_id)
        row = self.get_job(job_id, kind)
        if row is None:
            return None, -1
        return row, self._adopt(row) if rev is None else rev

    # --- jobs --------------------------------------------------------------------------------------
    def create_job(self, kind: JobKind, job_id: str, request: dict[str, Any]) -> JobRow:
        now = time.time()
        with self._write_lock:
            try:
                self._writer.execute(
                    "INSERT INTO jobs (id, kind, state, step, last_seq, request, summary, created_s, updated_s)"
                    " VALUES (?, ?, ?, 0, -1, ?, ?, ?, ?)",
                    (job_id, kind.value, JobState.QUEUED.value, _json(request), _json(empty_summary()),
                     now, now))
            except sqlite3.IntegrityError:
                raise JobExists(f"{kind.value} {job_id!r} already exists") from None
            self._set_meta(job_id, JobState.QUEUED, -1)
        row = self.get_job(job_id)
        assert row is not None
        return row

    def delete_job(self, job_id: str) -> None:
        """Forget a job that never started (its submission was refused)."""
        with self._write_lock:
            self._writer.execute("BEGIN IMMEDIATE")
            try:
                for table, col in (("images", "job_id"), ("events", "job_id"), ("jobs", "id")):
                    self._writer.execute(f"DELETE FROM {table} WHERE {col} = ?", (job_id,))
                self._writer.execute("COMMIT")
            except BaseException:
                self._writer.execute("ROLLBACK")
                raise
            with self._meta_lock:
                self._meta.pop(job_id, None)

    def set_owner(self, job_id: str, owner: dict[str, Any] | None) -> None:
        """Record the worker instance (and its incarnation) that accepted the job (see the reaper)."""
        with self._write_lock:
            row = self._writer.execute("SELECT summary, state, last_seq FROM jobs WHERE id = ?", (job_id,)).fetchone()
            if row is None:
                return
            summary = json.loads(row[0])
            summary["owner"] = owner
            self._writer.execute("UPDATE jobs SET summary = ?, updated_s = ? WHERE id = ?",
                                 (_json(summary), time.time(), job_id))
            self._set_meta(job_id, row[1], row[2])

    def mark(self, job_id: str, state: JobState, error: str | None = None) -> None:
        """Set a job's state from the gateway itself (e.g. the planner lost it)."""
        with self._write_lock:
            row = self._writer.execute("SELECT summary, last_seq FROM jobs WHERE id = ?", (job_id,)).fetchone()
            if row is None:
                return
            summary = json.loads(row[0])
            if error:
                summary["error"] = error
            self._writer.execute("UPDATE jobs SET state = ?, summary = ?, updated_s = ? WHERE id = ?",
                                 (state.value, _json(summary), time.time(), job_id))
            self._set_meta(job_id, state, row[1])

    @staticmethod
    def _row(r: tuple) -> JobRow:
        return JobRow(id=r[0], kind=JobKind(r[1]), state=JobState(r[2]), step=r[3], last_seq=r[4],
                      request=json.loads(r[5]), summary=json.loads(r[6]), created_s=r[7], updated_s=r[8])

    _COLS = "id, kind, state, step, last_seq, request, summary, created_s, updated_s"

    def get_job(self, job_id: str, kind: JobKind | None = None) -> JobRow | None:
        r = self._reader().execute(f"SELECT {self._COLS} FROM jobs WHERE id = ?", (job_id,)).fetchone()
        if r is None or (kind is not None and r[1] != kind.value):
            return None
        return self._row(r)

    def job_progress(self, job_id: str) -> tuple[JobState, int] | None:
        """(state, last_seq) of a job: what an SSE stream checks on every wake-up (a dict lookup
        once the job is known to this process)."""
        meta = self._meta.get(job_id)
        if meta is not None:
            return meta.state, meta.last_seq
        row = self.get_job(job_id)
        if row is None:
            return None
        self._adopt(row)
        return row.state, row.last_seq

    def list_jobs(self, kind: JobKind, *, states: list[JobState] | None = None, limit: int = 50,
                  offset: int = 0) -> tuple[list[JobRow], int]:
        """Newest first; returns (page, total matching)."""
        where, args = "kind = ?", [kind.value]
        if states:
            where += f" AND state IN ({','.join('?' * len(states))})"
            args += [s.value for s in states]
        db = self._reader()
        total = db.execute(f"SELECT COUNT(*) FROM jobs WHERE {where}", args).fetchone()[0]
        rows = db.execute(f"SELECT {self._COLS} FROM jobs WHERE {where} ORDER BY created_s DESC, id"
                          " LIMIT ? OFFSET ?", [*args, limit, offset]).fetchall()
        return [self._row(r) for r in rows], total

    # --- events ------------------------------------------------------------------------------------
    def append_event(self, kind: JobKind, event: JobEvent) -> StoredEvent | None:
        """Store one event, its images and the refolded record; returns the event as stored (what a
        stream sends), or None when it was already stored (a redelivery: ingest is idempotent).

        Raises :class:`EventRejected` for an event that cannot be true: its job is unknown here or of
        another kind (events never create jobs: the gateway creates a job's row before its service
        hears of it), the job has already ended (terminal states are final), its seq does not
        increase, or its kind contradicts its state (a ``step`` that is ``succeeded``).
        """
        if event.state not in KIND_STATES[event.kind]:
            raise EventRejected(event.job_id, event.seq,
                                f"a {event.kind.value} event cannot be {event.state.value}")
        names = [n for n in event.images if _IMAGE_NAME.match(n)]
        if len(names) != len(event.images):
            log.warning("event %s/%d: dropped images with invalid names %s", event.job_id, event.seq,
                        sorted(set(event.images) - set(names)))
        urls = {n: image_url(kind, event.job_id, event.seq, n) for n in names}
        data_json = _json(event.data_json())
        with self._write_lock:
            db = self._writer
            db.execute("BEGIN IMMEDIATE")
            try:
                r = db.execute("SELECT state, last_seq, summary, kind, step FROM jobs WHERE id = ?",
                               (event.job_id,)).fetchone()
                reason = None
                if r is None or r[3] != kind.value:
                    reason = f"no {kind.value} {event.job_id!r} here"
                elif event.seq <= r[1] or r[0] in _TERMINAL_VALUES:
                    seen = db.execute("SELECT 1 FROM events WHERE job_id = ? AND seq = ?",
                                      (event.job_id, event.seq)).fetchone()
                    if seen is not None:  # a redelivery of what we hold
                        db.execute("ROLLBACK")
                        return None
                    reason = (f"the {kind.value} has already ended ({r[0]})" if r[0] in _TERMINAL_VALUES
                              else f"seq {event.seq} does not increase (last {r[1]})")
                elif event.step < r[4] and event.state not in TERMINAL:
                    reason = f"step {event.step} goes back (at {r[4]})"
                if reason is not None:  # rolled back below
                    raise EventRejected(event.job_id, event.seq, reason)
                cur = db.execute(
                    "INSERT OR IGNORE INTO events (job_id, seq, kind, state, step, timestamp_s, data, images)"
                    " VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                    (event.job_id, event.seq, event.kind.value, event.state.value, event.step,
                     event.timestamp_s, data_json, _json(names)))
                if cur.rowcount == 0:
                    db.execute("ROLLBACK")
                    return None
                db.executemany("INSERT OR REPLACE INTO images (job_id, seq, name, jpeg) VALUES (?, ?, ?, ?)",
                               [(event.job_id, event.seq, n, bytes(event.images[n])) for n in names])
                summary = apply_event(json.loads(r[2]), event, urls)
                state = event.state.value
                # The step never goes back: a final event that says 0 keeps the steps walked.
                step = max(event.step, r[4])
                db.execute("UPDATE jobs SET state = ?, step = ?, last_seq = ?, summary = ?, updated_s = ? WHERE id = ?",
                           (state, step, event.seq, _json(summary), time.time(), event.job_id))
                db.execute("COMMIT")
            except BaseException:
                db.execute("ROLLBACK")
                raise
            self._set_meta(event.job_id, state, event.seq)
        return StoredEvent(job_id=event.job_id, seq=event.seq, kind=event.kind.value, state=event.state,
                           step=event.step, timestamp_s=event.timestamp_s, data_json=data_json, image_names=names)

    def events(self, job_id: str, after_seq: int = -1, limit: int = 1000) -> list[StoredEvent]:
        rows = self._reader().execute(
            "SELECT job_id, seq, kind, state, step, timestamp_s, data, images FROM events"
            " WHERE job_id = ? AND seq > ? ORDER BY seq LIMIT ?", (job_id, after_seq, limit)).fetchall()
        return [StoredEvent(job_id=r[0], seq=r[1], kind=r[2], state=JobState(r[3]), step=r[4],
                            timestamp_s=r[5], data_json=r[6], image_names=json.loads(r[7])) for r in rows]

    def image(self, job_id: str, seq: int, name: str) -> bytes | None:
        r = self._reader().execute("SELECT jpeg FROM images WHERE job_id = ? AND seq = ? AND name = ?",
                                   (job_id, seq, name)).fetchone()
        return None if r is None else bytes(r[0])

    def counts(self) -> dict[str, int]:
        db = self._reader()
        return {t: db.execute(f"SELECT COUNT(*) FROM {t}").fetchone()[0] for t in ("jobs", "events", "images")}

    # --- lifecycle ---------------------------------------------------------------------------------
    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        with self._readers_lock:
            for conn in self._readers:
                conn.close()
            self._readers.clear()
        with self._write_lock:
            self._writer.close()

    def __enter__(self) -> GatewayStore:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
