"""Ids come from the key a request came on (issue 31 item 2).

A real reconstructor on one zenoh peer, asked from another: every handler on a map's key takes the map
from the key, and a payload map id that disagrees with it is refused with a typed error reply (the
service keeps serving). The subscribers (frames, map announcements) read their ids with the same
parsing, and ignore a sample whose key is not a concrete key of theirs.
"""

from __future__ import annotations

import numpy as np
import pytest

from services.reconstructor.service import ReconstructorService, ReconstructorSettings
from shared import keys
from shared.bus.typed import RemoteError, TypedBus
from shared.cloud import PointCloud, encode
from shared.runner import RunningService
from shared.schemas import (
    BuildCancelRequest,
    BuildMapRequest,
    ErrorCode,
    JobAccepted,
    MapChunk,
    MapChunkRequest,
    MapImportProgress,
    MapImportRequest,
    MapInfo,
    MapRequest,
    Pose,
    TourRecording,
)
from tests.waiting import wait_until


def _ply(points: int = 50) -> bytes:
    rng = np.random.default_rng(0)
    return encode(PointCloud(rng.uniform(-2, 2, (points, 3)).astype(np.float32),
                             rng.integers(0, 256, (points, 3), dtype=np.uint8)))


@pytest.fixture
def store(peers, tmp_path):
    a, b = peers
    svc = ReconstructorService(ReconstructorSettings(instance="rec-ids", store_dir=str(tmp_path / "maps")))
    running = RunningService(svc, a)
    typed = TypedBus(b, "ids-test")
    key = keys.MAP_IMPORT.format(map="alpha")
    wait_until(lambda: b.alive(keys.ALIVE.pattern(service="reconstructor"), timeout_s=0.5),
               what="reconstructor up")
    # A real map "alpha" to ask about (and, forged, to try to reach from another map's key).
    info = typed.request(key, MapImportRequest(map_id="alpha", filename="a.ply", data=_ply()), MapInfo,
                         timeout_s=30)
    assert info.map_id == "alpha"
    yield svc, typed, tmp_path / "maps"
    running.close()


def _refused(typed: TypedBus, key: str, req, reply) -> RemoteError:
    with pytest.raises(RemoteError) as e:
        typed.request(key, req, reply, timeout_s=10)
    return e.value


def test_a_payload_id_that_disagrees_with_the_key_is_refused_on_every_map_handler(store):
    svc, typed, root = store
    beta = dict(map="beta")
    cases = [
        (keys.MAP_INFO.format(**beta), MapRequest(map_id="alpha"), MapInfo),
        (keys.MAP_CHUNK.format(**beta), MapChunkRequest(map_id="alpha"), MapChunk),
        (keys.MAP_IMPORT.format(**beta), MapImportRequest(map_id="alpha", filename="x.ply", data=_ply()), MapInfo),
        (keys.MAP_IMPORT.format(**beta), MapImportRequest(map_id="alpha", filename="x.ply", data=b"ply\n",
                                                          upload_id="u1", last=False), MapImportProgress),
        (keys.MAP_BUILD.format(**beta), BuildMapRequest(build_id="b1", exploration_id="e1", map_id="alpha",
                                                        recordings=[TourRecording(recording="r1", frame_count=1, region=0,
                                                                                  exploration_id="e1",
                                                                                  start_pose=Pose(position_m=(0.0, 0.0, 0.0)))]),
         JobAccepted),
    ]
    for key, req, reply in cases:
        err = _refused(typed, key, req, reply)
        assert err.code == ErrorCode.BAD_REQUEST, (key, err)
        assert "disagrees with the key" in err.message and "'beta'" in err.message, err.message
    # Nothing was made for either map by the forged requests, and the service still serves.
    assert sorted(p.name for p in root.iterdir() if not p.name.startswith(".")) == ["alpha"]
    assert not any((root / ".uploads").iterdir())
    assert typed.request(keys.MAP_INFO.format(map="alpha"), MapRequest(map_id="alpha"), MapInfo,
                         timeout_s=10).map_id == "alpha"


def test_the_agreeing_request_is_served_from_the_key(store):
    _svc, typed, _root = store
    assert typed.request(keys.MAP_CHUNK.format(map="alpha"), MapChunkRequest(map_id="alpha"), MapChunk,
                         timeout_s=10).xyz_m.shape[0] > 0
    err = _refused(typed, keys.MAP_INFO.format(map="beta"), MapRequest(map_id="beta"), MapInfo)
    assert err.code == ErrorCode.NOT_FOUND  # agreed, looked up under the key's map: none
    # A build cancel names only the build: the map is the key's, so map beta's key cannot stop alpha's.
    reply = typed.request(keys.MAP_BUILD_CANCEL.format(map="beta"), BuildCancelRequest(build_id="b9"),
                          JobAccepted, timeout_s=10)
    assert not reply.accepted and "beta" in reply.reason


def test_subscribers_take_ids_from_the_key_and_ignore_a_key_not_theirs(store):
    svc, _typed, _root = store
    assert keys.ids_of(keys.IO_FRAMES, "ant/r1/io/frames/tour-3") == {"robot": "r1", "recording": "tour-3"}
    assert keys.ids_of(keys.MAP_UPDATED, "ant/maps/alpha/updated") == {"map": "alpha"}
    assert keys.ids_of(keys.RENDER_VIEWS, "ant/render/views/@renderer-0") == {}
    for bad in ("ant/r1/io/frames/*", "ant/r1/io/frames/a/b", "ant/r1/io/pose"):
        with pytest.raises(keys.KeyExprError):
            keys.ids_of(keys.IO_FRAMES, bad)
    svc._on_frame("ant/r1/io/frames/**", None)  # not concrete: dropped before the payload is looked at
    assert not svc.frames._recs


def test_agree_checks_each_named_part():
    req = MapRequest(map_id="a")
    assert keys.agree(keys.MAP_INFO, "ant/maps/a/info", req, map="map_id") == {"map": "a"}
    with pytest.raises(keys.KeyMismatch):
        keys.agree(keys.MAP_INFO, "ant/maps/b/info", req, map="map_id")
    with pytest.raises(keys.KeyExprError):  # a part the template does not have
        keys.agree(keys.MAP_INFO, "ant/maps/a/info", req, robot="map_id")
    with pytest.raises(keys.KeyExprError):  # a wildcard asked is no concrete key
        keys.ids_of(keys.MAP_INFO, "ant/maps/*/info")


def test_segment_ids_are_refused_on_decode():
    from pydantic import ValidationError

    for bad in ("", "a/b", "*", "**", "$x", "a" * 65, "-a"):
        with pytest.raises(ValidationError):
            MapRequest(map_id=bad)


def test_the_gateway_records_a_job_under_its_key_only(tmp_path):
    """The recording writer queues a finished job named by the key it came on; an event whose job id
    disagrees with its key is ignored (it would write another job's recording)."""
    from services.gateway.routes.downloads import RecordingWriter
    from services.gateway.settings import GatewaySettings
    from shared.bus import FakeBus, FakeNetwork
    from shared.schemas import JobEvent, JobEventKind, JobState

    bus = FakeBus(FakeNetwork())
    writer = RecordingWriter(TypedBus(bus, "rec-test"), None, GatewaySettings(db_path=tmp_path / "gw.sqlite3"))
    try:
        def ended(job):
            return JobEvent(job_id=job, seq=3, kind=JobEventKind.FINISHED, state=JobState.SUCCEEDED)

        key = keys.MISSION_EVENTS.format(robot="robot0", mission="m1")
        writer._on_event(key, ended("m2"), keys.MISSION_EVENTS, "mission")
        assert writer._queue.empty()
        writer._on_event(key, ended("m1"), keys.MISSION_EVENTS, "mission")
        assert writer._queue.get_nowait() == ("m1", 3)
    finally:
        writer._stopping.set()
        for s in writer._subs:
            s.close()
        writer._queue.put(None)
        writer._worker.join(10.0)
        bus.close()
