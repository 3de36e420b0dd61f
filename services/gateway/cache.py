"""Encoded job records, cached per revision and served with an ETag.

A dashboard polls ``GET /missions/{id}`` several times a second per viewer, while the record only
changes when an event arrives (about once a second per running job). Building the record, validating
it and encoding its trajectory and decisions on every poll is what made the gateway slow under load;
here it happens once per revision of the job (:meth:`GatewayStore.revision`, bumped on every write),
and a poll is a dict lookup plus sending bytes - or a bodiless ``304 Not Modified`` when the client
sends the ETag it already has in ``If-None-Match``.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

from fastapi import Response
from pydantic import BaseModel

from services.gateway.records import JobKind
from services.gateway.store import GatewayStore, JobRow

# Polled records must be revalidated on every poll: clients may keep them, but never trust them blind.
CACHE_CONTROL = "no-cache"


@dataclass(frozen=True)
class EncodedRecord:
    kind: JobKind
    revision: int
    body: bytes
    etag: str


class RecordCache:
    """LRU of encoded records by job id; thread-safe. ``max_jobs`` bounds its memory."""

    def __init__(self, store: GatewayStore, max_jobs: int = 512):
        self.store, self.max_jobs = store, max_jobs
        self._entries: OrderedDict[str, EncodedRecord] = OrderedDict()
        self._lock = threading.Lock()
        self.hits = self.misses = 0

    def get(self, job_id: str, kind: JobKind, build: Callable[[JobRow], BaseModel]) -> EncodedRecord | None:
        """The job's current record, encoded; None when there is no such job of that kind."""
        rev = self.store.revision(job_id)
        with self._lock:
            entry = self._entries.get(job_id)
            if entry is not None and rev is not None and entry.revision == rev and entry.kind == kind:
                self._entries.move_to_end(job_id)
                self.hits += 1
                return entry
        self.misses += 1
        row, rev = self.store.get_job_revision(job_id, kind)
        if row is None:
            return None
        body = build(row).model_dump_json().encode()
        # A content hash, not the revision: revisions restart with the process, content does not.
        entry = EncodedRecord(kind, rev, body, f'"{hashlib.blake2b(body, digest_size=12).hexdigest()}"')
        if rev >= 0:
            with self._lock:
                self._entries[job_id] = entry
                self._entries.move_to_end(job_id)
                while len(self._entries) > self.max_jobs:
                    self._entries.popitem(last=False)
        return entry


def etag_matches(if_none_match: str | None, etag: str) -> bool:
    """RFC 9110 weak comparison of ``If-None-Match`` (a list, or ``*``) against ``etag``."""
    if not if_none_match:
        return False
    candidates = [t.strip() for t in if_none_match.split(",")]
    return any(t == "*" or t.removeprefix("W/") == etag for t in candidates)


def record_response(entry: EncodedRecord, if_none_match: str | None) -> Response:
    headers = {"ETag": entry.etag, "Cache-Control": CACHE_CONTROL}
    if etag_matches(if_none_match, entry.etag):
        return Response(status_code=304, headers=headers)
    return Response(entry.body, media_type="application/json", headers=headers)
