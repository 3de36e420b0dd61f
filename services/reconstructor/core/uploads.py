"""Uploads in parts: a cloud file assembled on disk, part by part, then imported from the file.

An upload (``MapImportRequest`` with an ``upload_id``) never sits whole in memory: each part is
appended to ``<root>/<upload_id>.part`` and the store parses the finished file. The state of an upload
is on disk only (the file's size is what was received; a sidecar names its map and file name), so
reconstructor replicas sharing a store folder can each take a part. Any failure drops the upload,
and an upload nobody added to for ``idle_s`` is dropped as abandoned (a sender that died mid-way).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import threading
import time
from pathlib import Path

from .errors import InputError

log = logging.getLogger(__name__)


class UploadError(InputError):
    """A part that does not fit its upload (wrong offset, another map, too many open uploads)."""


class Uploads:
    def __init__(self, root: str | Path, *, max_open: int = 8, idle_s: float = 300.0):
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        self.max_open, self.idle_s = max_open, idle_s
        self._lock = threading.Lock()
        self.expire()

    def _paths(self, upload_id: str, filename: str) -> tuple[Path, Path]:
        suffix = Path(filename).suffix.lower()
        return self.root / f"{upload_id}.part{suffix}", self.root / f"{upload_id}.json"

    def open_ids(self) -> list[str]:
        return sorted(p.stem for p in self.root.glob("*.json"))

    def append(self, upload_id: str, map_id: str, filename: str, offset: int, data: bytes) -> int:
        """Append ``data`` at ``offset``; returns the bytes received so far. On any error the upload
        is dropped (the sender starts again), so nothing half-written is ever kept."""
        part, side = self._paths(upload_id, filename)
        with self._lock:
            try:
                if offset == 0:
                    self.expire()
                    if not side.exists() and len(self.open_ids()) >= self.max_open:
                        raise UploadError(f"{self.max_open} uploads are open already: try again later")
                    side.write_text(json.dumps({"map_id": map_id, "filename": filename}))
                    mode = "wb"
                else:
                    try:
                        meta = json.loads(side.read_text())
                    except (OSError, ValueError):
                        raise UploadError(f"no upload {upload_id!r} in progress (expired or dropped?)") from None
                    if meta != {"map_id": map_id, "filename": filename}:
                        raise UploadError(f"upload {upload_id!r} is of {meta}, not {map_id!r}/{filename!r}")
                    mode = "r+b"
                with open(part, mode) as fh:
                    size = fh.seek(0, os.SEEK_END)
                    if size != offset:
                        raise UploadError(f"upload {upload_id!r}: part at offset {offset}, {size} bytes received")
                    fh.write(data)
                    return size + len(data)
            except BaseException:
                self._drop(upload_id, filename)
                raise

    def path(self, upload_id: str, filename: str) -> Path:
        return self._paths(upload_id, filename)[0]

    def drop(self, upload_id: str, filename: str) -> None:
        with self._lock:
            self._drop(upload_id, filename)

    def _drop(self, upload_id: str, filename: str) -> None:
        for p in self._paths(upload_id, filename):
            with contextlib.suppress(FileNotFoundError):
                p.unlink()

    def expire(self) -> None:
        """Drop the files of uploads nobody added to for ``idle_s``."""
        cutoff = time.time() - self.idle_s
        for p in self.root.iterdir():
            with contextlib.suppress(FileNotFoundError):
                if p.stat().st_mtime < cutoff:
                    log.warning("dropping abandoned upload file %s", p.name)
                    p.unlink()
