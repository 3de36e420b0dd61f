"""The map store: versioned maps on disk, written atomically, served in chunks.

Layout under ``root``::

    <map_id>/v000001/cloud.ply          points, colours, labels, label names and view directions
                                        (:mod:`shared.cloud`'s PLY)
    <map_id>/v000001/meta.json          MapInfo + details (source, regions, scale factors, timings)
    <map_id>/v000001/scene_graph.json   the version's scene graph (libs.scenegraph, from the cloud's labels
                                        and the exploration's navigation graph; issue 32)
    <map_id>/.lock                      serialises version allocation between processes

A version is written into a hidden temporary directory beside the versions, every file is fsynced,
then the directory is renamed into place (atomic on POSIX) and the parent fsynced. A crash at any
point leaves either the complete version or an orphaned temporary directory that listing ignores
and the next writer cleans up; never a half-written map. ``meta.json`` records the SHA-256 of the
PLY, checked on load.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import logging
import os
import shutil
import tempfile
import threading
import time
import uuid
from collections import OrderedDict
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from shared.cloud import CloudFormatError, PointCloud, copy_ours, header, read_cloud, read_cloud_bytes, records
from shared.keys import KeyExprError, validate_segment
from libs.scenegraph import build_scene_graph
from libs.scenegraph.labeller import LABELLERS, Labeller, LabellerError, geometric_graph
from shared.schemas import DriftCorrection, MapChunk, MapInfo, MapLabelling, NavGraph, SceneGraph

from . import foreign
from .errors import InvalidMapIdError, MapFormatError, MapNotFoundError, MapStoreError

log = logging.getLogger(__name__)

_TMP_PREFIX = ".tmp-"


class _NotOurs(Exception):
    """The file is not a PLY of our layout: parsed whole instead."""


_CLOUD = "cloud.ply"
_META = "meta.json"
_GRAPH = "scene_graph.json"
# The MLLM labeller's answers, per map (beside its versions; a dot name is no version): keyed by the
# frames and the model, so a rebuild from the same tours asks nothing, across restarts too.
_LABEL_CACHE = ".labels-cache.json"
_STALE_TMP_S = 3600.0


@dataclass
class StoredMap:
    """A loaded map version: its metadata, the extra details and the cloud."""

    info: MapInfo
    cloud: PointCloud
    details: dict[str, Any]


class MapStore:
    """Versioned maps under ``root``; safe for several threads and processes sharing the folder."""

    def __init__(self, root: str | Path, cache_maps: int = 2, fsync: bool = True,
                 max_whole_bytes: int = 256 << 20, labeller: Labeller | None = None):
        self.root = Path(root)
        # Who names the rooms of each version's scene graph (libs.scenegraph.labeller; default: the
        # map's own semantic labels, which only a simulator or a detector upstream provides).
        self.labeller = labeller or LABELLERS.create("sim")
        # A file that cannot be read a chunk at a time (compressed PCD, PLY list properties before the
        # vertices) is parsed whole (open3d: ~50 bytes per point held); larger ones are refused.
        self.max_whole_bytes = int(max_whole_bytes)
        self.root.mkdir(parents=True, exist_ok=True)
        self.fsync = fsync
        self._cache: OrderedDict[tuple[str, int], StoredMap] = OrderedDict()
        self._cache_size = max(0, int(cache_maps))
        self._lock = threading.Lock()

    # --- writing -------------------------------------------------------------------------------

    def save(
        self,
        map_id: str,
        cloud: PointCloud,
        source: str = "",
        regions: int = 0,
        scale_factors: list[float] | None = None,
        timings_s: dict[str, float] | None = None,
        details: dict[str, Any] | None = None,
        navigation: NavGraph | None = None,
        frames: Mapping[int, Sequence[np.ndarray]] | None = None,
        drift_correction: DriftCorrection | None = None,
    ) -> MapInfo:
        """Store ``cloud`` as the next version of ``map_id``; returns its :class:`MapInfo`.

        The version's scene graph is built here by the store's labeller, from the cloud, the
        exploration's ``navigation`` graph (when the map came from one) and ``frames`` (region -> a few
        of its tour frames, RGB, for the ``mllm`` labeller), and written beside the cloud; what the
        labelling cost is the info's ``labelling``."""
        if len(cloud) == 0:
            raise MapFormatError(f"map {map_id!r}: refusing to store an empty cloud")

        def write(ply: Path) -> dict[str, Any]:
            cloud.save(ply)
            lo, hi = cloud.bounds()
            return dict(point_count=len(cloud), bounds_min_m=tuple(float(v) for v in lo),
                        bounds_max_m=tuple(float(v) for v in hi), has_labels=cloud.labels is not None,
                        label_names={int(k): v for k, v in cloud.label_names.items()})

        return self._store(map_id, write, source=source, regions=regions, scale_factors=scale_factors,
                           timings_s=timings_s, details=details, drift_correction=drift_correction,
                           graph_of=lambda: self._label(map_id, cloud, navigation, frames))

    def _label(self, map_id: str, cloud: PointCloud, navigation: NavGraph | None,
               frames: Mapping[int, Sequence[np.ndarray]] | None) -> tuple[SceneGraph, MapLabelling]:
        """The version's scene graph through the labeller; a labeller that fails (a refused or garbled
        answer, an unreachable server) leaves the geometric graph, and the labelling says why."""
        lab = self.labeller
        cache = self._map_dir(map_id, create=True) / _LABEL_CACHE
        try:
            out = lab.label(cloud, navigation, frames, map_id=map_id, cache_path=cache)
            graph, usage, error = out.graph, out.usage, ""
        except LabellerError as exc:
            log.warning("map %s: the %s labeller failed, the graph stays unnamed: %s", map_id, lab.name, exc)
            graph, usage, error = geometric_graph(cloud, navigation, map_id=map_id), exc.usage, str(exc)[:1000]
        labelling = MapLabelling(
            labeller=lab.name, model=str(getattr(lab.config, "model", "")), regions=len(frames or {}),
            rooms_named=sum(bool(r.room_type) for r in graph.rooms), error=error,
            **usage.model_dump(include={"calls", "prompt_tokens", "completion_tokens", "cost_usd", "reasks",
                                        "cache_hits"}))
        return graph, labelling

    def _store(self, map_id: str, write, *, source: str = "", regions: int = 0,
               scale_factors: list[float] | None = None, timings_s: dict[str, float] | None = None,
               details: dict[str, Any] | None = None, graph_of=None,
               drift_correction: DriftCorrection | None = None) -> MapInfo:
        """The next version of ``map_id`` from ``write(ply_path) -> MapInfo fields`` (count, bounds,
        labels), written in a temporary folder renamed into place: a failure leaves nothing.

        ``graph_of() -> (SceneGraph, MapLabelling)`` builds the version's scene graph, written beside the
        cloud, and says who named its rooms (the info's ``labelling``). A cloud
        streamed in slices (an upload of any size) has none at import, since building it needs the
        whole cloud in memory: :meth:`scene_graph` builds it from the stored cloud when first asked."""
        try:
            self._map_dir(map_id)
            new_map = False
        except MapNotFoundError:
            new_map = True
        map_dir = self._map_dir(map_id, create=True)
        self._clean_stale(map_dir)
        tmp = Path(tempfile.mkdtemp(prefix=_TMP_PREFIX, dir=map_dir))
        try:
            ply = tmp / _CLOUD
            fields = write(ply)
            digest = _sha256(ply)
            graph, labelling = graph_of() if graph_of is not None else (None, None)
            with self._version_lock(map_dir):
                version = self._next_version(map_dir)
                info = MapInfo(
                    map_id=map_id, version=version, **fields,
                    source=source, regions=regions, scale_factors=list(scale_factors or []),
                    timings_s=dict(timings_s or {}), created_s=time.time(), labelling=labelling,
                    drift_correction=drift_correction,
                )
                files = {_CLOUD: digest}
                if graph is not None:
                    graph.version = version
                    (tmp / _GRAPH).write_text(graph.model_dump_json())
                    files[_GRAPH] = _sha256(tmp / _GRAPH)
                meta = {"info": info.model_dump(mode="json"), "details": _jsonable(details or {}),
                        "files": files}
                (tmp / _META).write_text(json.dumps(meta, indent=1))
                if self.fsync:
                    for f in tmp.iterdir():
                        _fsync_file(f)
                    _fsync_dir(tmp)
                os.rename(tmp, map_dir / _version_name(version))
                if self.fsync:
                    _fsync_dir(map_dir)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            if new_map:  # a refused first version leaves no empty map behind (rmdir fails if one raced in)
                with contextlib.suppress(OSError):
                    map_dir.rmdir()
            raise
        log.info("stored map %s v%d: %d points", map_id, version, info.point_count)
        return info

    def import_cloud(
        self, map_id: str, data: bytes | str | Path, filename: str | None = None, source: str | None = None,
        max_points: int = 50_000_000,
    ) -> MapInfo:
        """Store a user's PLY/PCD cloud (bytes with a ``filename``, or a path: parsed from the file, never
        read into memory whole) as a new map version."""
        try:
            if isinstance(data, (bytes, bytearray, memoryview)):
                if not filename:
                    raise MapFormatError("importing bytes needs a filename (.ply or .pcd)")
                cloud = read_cloud_bytes(data, filename)
            else:
                p = Path(data)
                if p.suffix.lower() not in (".ply", ".pcd"):
                    raise MapFormatError(f"{p.name!r}: only .ply and .pcd clouds can be imported")
                if p.suffix.lower() == ".ply":
                    stored = self._import_ours(map_id, p, filename or p.name, source, max_points)
                    if stored is not None:
                        return stored
                stored = self._import_foreign(map_id, p, filename or p.name, source, max_points)
                if stored is not None:
                    return stored
                if p.stat().st_size > self.max_whole_bytes:
                    raise MapFormatError(
                        f"{filename or p.name}: a compressed PCD, or a PLY with list properties before its vertices, "
                        f"is parsed whole; this one is {p.stat().st_size} bytes, the limit is {self.max_whole_bytes}")
                try:
                    cloud = read_cloud(p)
                except CloudFormatError as exc:
                    # An upload's file on disk is named for the upload: report the sender's name.
                    raise CloudFormatError(str(exc).replace(p.name, filename, 1) if filename else str(exc)) from None
                filename = filename or p.name
        except CloudFormatError as exc:
            raise MapFormatError(str(exc)) from None
        if len(cloud) > max_points:
            raise MapFormatError(f"{filename}: {len(cloud)} points exceed the limit of {max_points}")
        return self.save(map_id, cloud, source=source or f"import:{filename}", details={"imported": filename})

    def _import_ours(self, map_id: str, path: Path, filename: str, source: str | None,
                     max_points: int) -> MapInfo | None:
        """A PLY of our layout copied into the store a slice at a time (the upload of a 500 MB file
        costs ~16 MB, not the cloud); None for any other file."""
        def write(ply: Path) -> dict[str, Any]:
            try:
                copied = copy_ours(path, ply)
            except CloudFormatError as exc:
                raise MapFormatError(f"{filename}: {str(exc).replace(path.name, filename, 1)}") from None
            if copied is None:
                raise _NotOurs
            if copied.count > max_points:
                raise MapFormatError(f"{filename}: {copied.count} points exceed the limit of {max_points}")
            return dict(point_count=copied.count, bounds_min_m=copied.bounds_min, bounds_max_m=copied.bounds_max,
                        has_labels=copied.with_labels, label_names=copied.label_names)

        try:
            return self._store(map_id, write, source=source or f"import:{filename}", details={"imported": filename})
        except _NotOurs:
            return None

    def _import_foreign(self, map_id: str, path: Path, filename: str, source: str | None,
                        max_points: int) -> MapInfo | None:
        """A PLY of another layout, or a PCD, converted into ours a chunk at a time (:mod:`.foreign`):
        the records go to a body file beside the cloud with the count and bounds taken on the way, then
        the header (which states the count) and the body make the cloud. None for a file that must be
        parsed whole (a compressed PCD, list properties before the vertices)."""
        try:
            layout = foreign.layout_of(path)
        except foreign.NotStreamable:
            return None
        except CloudFormatError as exc:
            raise MapFormatError(f"{filename}: {exc}") from None
        if layout.count > max_points:
            raise MapFormatError(f"{filename}: {layout.count} points exceed the limit of {max_points}")

        def write(ply: Path) -> dict[str, Any]:
            body = ply.with_name("body.part")
            count, lo_b, hi_b, dropped = 0, np.full(3, np.inf), np.full(3, -np.inf), 0
            try:
                with open(body, "wb") as out:
                    for xyz, rgb in foreign.chunks(path, layout):
                        finite = np.isfinite(xyz).all(axis=1)
                        if not finite.all():
                            dropped += int((~finite).sum())
                            xyz, rgb = xyz[finite], rgb[finite]
                        if len(xyz):
                            count += len(xyz)
                            lo_b, hi_b = np.minimum(lo_b, xyz.min(axis=0)), np.maximum(hi_b, xyz.max(axis=0))
                            out.write(records(xyz, rgb))
                if not count:
                    raise CloudFormatError("every point is non-finite" if layout.count else "no points could be read")
                if dropped:
                    log.warning("%s: dropping %d non-finite points", filename, dropped)
                with open(ply, "wb") as out, open(body, "rb") as src:
                    out.write(header(count, False))
                    shutil.copyfileobj(src, out, 16 << 20)
            except CloudFormatError as exc:
                raise MapFormatError(f"{filename}: {exc}") from None
            finally:
                body.unlink(missing_ok=True)
            return dict(point_count=count, bounds_min_m=tuple(float(v) for v in lo_b),
                        bounds_max_m=tuple(float(v) for v in hi_b), has_labels=False, label_names={})

        return self._store(map_id, write, source=source or f"import:{filename}", details={"imported": filename})

    # --- reading -------------------------------------------------------------------------------

    def list(self, all_versions: bool = False) -> list[MapInfo]:
        """Every map's latest version (or every version), sorted by id then version."""
        out = []
        for d in sorted(self.root.iterdir()) if self.root.is_dir() else []:
            if not d.is_dir() or d.name.startswith("."):
                continue
            versions = self._versions(d)
            for v in versions if all_versions else versions[-1:]:
                with contextlib.suppress(MapStoreError):
                    out.append(self.info(d.name, v))
        return out

    def versions(self, map_id: str) -> list[int]:
        return self._versions(self._map_dir(map_id))

    def info(self, map_id: str, version: int | None = None) -> MapInfo:
        return MapInfo.model_validate(self._meta(map_id, version)["info"])

    def details(self, map_id: str, version: int | None = None) -> dict[str, Any]:
        return self._meta(map_id, version).get("details", {})

    def load(self, map_id: str, version: int | None = None, verify: bool = True) -> StoredMap:
        """The map's cloud and metadata (latest version when ``version`` is None); cached."""
        v = self._resolve(map_id, version)
        key = (map_id, v)
        with self._lock:
            if key in self._cache:
                self._cache.move_to_end(key)
                return self._cache[key]
        vdir = self._map_dir(map_id) / _version_name(v)
        meta = self._meta(map_id, v)
        ply = vdir / _CLOUD
        if verify:
            want = meta.get("files", {}).get(_CLOUD)
            if want is not None and _sha256(ply) != want:
                raise MapFormatError(f"map {map_id} v{v}: cloud file does not match its checksum")
        try:
            cloud = PointCloud.load(ply)
        except CloudFormatError as exc:
            raise MapFormatError(f"map {map_id} v{v}: {exc}") from exc
        info = MapInfo.model_validate(meta["info"])
        cloud.label_names = {int(k): v for k, v in info.label_names.items()} or cloud.label_names
        if len(cloud) != info.point_count:
            raise MapFormatError(f"map {map_id} v{v}: {len(cloud)} points, metadata says {info.point_count}")
        stored = StoredMap(info, cloud, meta.get("details", {}))
        with self._lock:
            if self._cache_size:
                self._cache[key] = stored
                while len(self._cache) > self._cache_size:
                    self._cache.popitem(last=False)
        return stored

    def scene_graph(self, map_id: str, version: int | None = None) -> SceneGraph:
        """The version's scene graph; a version stored before graphs were (no file) gets one built from its
        cloud now, without its exploration's navigation graph (which was not kept then)."""
        v = self._resolve(map_id, version)
        path = self._map_dir(map_id) / _version_name(v) / _GRAPH
        if not path.is_file():
            return build_scene_graph(self.load(map_id, v).cloud, None, map_id=map_id, version=v)
        want = self._meta(map_id, v).get("files", {}).get(_GRAPH)
        if want is not None and _sha256(path) != want:
            raise MapFormatError(f"map {map_id} v{v}: scene graph file does not match its checksum")
        try:
            return SceneGraph.model_validate_json(path.read_text())
        except ValueError as exc:
            raise MapFormatError(f"map {map_id} v{v}: unreadable scene graph ({exc})") from exc

    def chunk(self, map_id: str, version: int | None = None, index: int = 0, max_points: int = 1_000_000) -> MapChunk:
        """Chunk ``index`` of ``ceil(N / max_points)``: what the bus serves per ``MapChunkRequest``."""
        if max_points < 1:
            raise MapStoreError(f"max_points must be positive, got {max_points}")
        m = self.load(map_id, version)
        n = len(m.cloud)
        count = max(1, -(-n // max_points))
        if not 0 <= index < count:
            raise MapNotFoundError(f"map {map_id} v{m.info.version}: chunk {index} of {count} does not exist")
        sl = slice(index * max_points, min(n, (index + 1) * max_points))
        c = m.cloud
        return MapChunk(
            map_id=map_id, version=m.info.version, index=index, count=count,
            xyz_m=c.xyz[sl], rgb=c.rgb[sl], labels=None if c.labels is None else c.labels[sl],
            view_dirs=None if c.view_dirs is None else c.view_dirs[sl],
        )

    def chunks(self, map_id: str, version: int | None = None, max_points: int = 1_000_000) -> Iterator[MapChunk]:
        first = self.chunk(map_id, version, 0, max_points)
        yield first
        for i in range(1, first.count):
            yield self.chunk(map_id, first.version, i, max_points)

    def delete(self, map_id: str, version: int | None = None) -> None:
        """Remove one version (or the whole map); the rename first makes it vanish atomically."""
        map_dir = self._map_dir(map_id)
        target = map_dir if version is None else map_dir / _version_name(self._resolve(map_id, version))
        if not target.is_dir():
            raise MapNotFoundError(f"map {map_id!r} version {version} not found")
        trash = target.with_name(f"{_TMP_PREFIX}del-{uuid.uuid4().hex}")
        os.rename(target, trash)
        shutil.rmtree(trash, ignore_errors=True)
        with self._lock:
            for key in [k for k in self._cache if k[0] == map_id and (version is None or k[1] == version)]:
                del self._cache[key]

    # --- internals -----------------------------------------------------------------------------

    def _map_dir(self, map_id: str, create: bool = False) -> Path:
        try:
            validate_segment(map_id, "map id")
        except KeyExprError as exc:
            raise InvalidMapIdError(str(exc)) from None
        d = self.root / map_id
        if create:
            d.mkdir(parents=True, exist_ok=True)
        elif not d.is_dir():
            raise MapNotFoundError(f"no map {map_id!r}")
        return d

    @staticmethod
    def _versions(map_dir: Path) -> list[int]:
        out = []
        for d in map_dir.iterdir():
            if d.is_dir() and d.name.startswith("v") and d.name[1:].isdigit() and (d / _META).is_file():
                out.append(int(d.name[1:]))
        return sorted(out)

    def _next_version(self, map_dir: Path) -> int:
        # Deleted versions are never reused: a counter file (under the version lock) remembers the
        # highest number ever handed out, so a client caching "v2" never sees a different v2.
        counter = map_dir / ".last_version"
        used = [int(d.name[1:]) for d in map_dir.iterdir() if d.name.startswith("v") and d.name[1:].isdigit()]
        with contextlib.suppress(OSError, ValueError):
            used.append(int(counter.read_text().strip()))
        version = max(used, default=0) + 1
        tmp = map_dir / f"{_TMP_PREFIX}counter-{uuid.uuid4().hex}"
        tmp.write_text(str(version))
        if self.fsync:
            _fsync_file(tmp)
        os.replace(tmp, counter)
        return version

    def _resolve(self, map_id: str, version: int | None) -> int:
        versions = self._versions(self._map_dir(map_id))
        if not versions:
            raise MapNotFoundError(f"map {map_id!r} has no stored version")
        if version is None:
            return versions[-1]
        if version not in versions:
            raise MapNotFoundError(f"map {map_id!r} has no version {version} (have {versions})")
        return version

    def _meta(self, map_id: str, version: int | None) -> dict:
        v = self._resolve(map_id, version)
        p = self._map_dir(map_id) / _version_name(v) / _META
        try:
            return json.loads(p.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise MapFormatError(f"map {map_id} v{v}: unreadable metadata ({exc})") from exc

    @contextlib.contextmanager
    def _version_lock(self, map_dir: Path):
        with open(map_dir / ".lock", "a+") as fh:
            fcntl.flock(fh, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(fh, fcntl.LOCK_UN)

    @staticmethod
    def _clean_stale(map_dir: Path) -> None:
        now = time.time()
        for d in map_dir.glob(_TMP_PREFIX + "*"):
            # Only old ones: a young temporary directory may belong to a writer still at work.
            with contextlib.suppress(OSError):
                if now - d.stat().st_mtime > _STALE_TMP_S:
                    shutil.rmtree(d, ignore_errors=True) if d.is_dir() else d.unlink()


def _version_name(v: int) -> str:
    return f"v{v:06d}"


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _fsync_file(path: Path) -> None:
    with open(path, "rb") as fh:
        os.fsync(fh.fileno())


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _jsonable(obj: Any) -> Any:
    """Round-trip through JSON with numpy scalars and arrays turned into Python values."""
    def default(o):
        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
        raise TypeError(f"{type(o).__name__} is not JSON serialisable")

    return json.loads(json.dumps(obj, default=default, allow_nan=True))
