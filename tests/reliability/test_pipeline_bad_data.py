"""Bad data in the pipeline, each with a clear outcome: non-finite poses (HTTP 422 and bus
``bad_request``, the handler never runs), an empty or tiny cloud (import refused, nothing stored)."""

from __future__ import annotations

import math

import httpx
import numpy as np
import pytest

from services.reconstructor.core.errors import MapStoreError
from services.reconstructor.core.store import MapStore
from shared import keys
from shared.bus import FakeBus, FakeNetwork
from shared.bus.base import QueryTarget
from shared.bus.typed import TypedBus
from shared.cloud import CloudFormatError
from shared.codec import decode
from shared.schemas import ErrorCode, ErrorReply, MoveRequest, Pose, PoseReply, ResetRequest
from tests.reliability.fuzzing import _envelope
from tests.reliability.http_server import live_gateway

NON_FINITE = [math.nan, math.inf, -math.inf]


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity", "1e999"])
def test_non_finite_start_pose_over_http_is_422(tmp_path, literal):
    body = ('{"instruction": "go", "map_id": "house", "options": {"start_pose": '
            f'{{"position_m": [1.0, {literal}, 0.0], "heading_rad": 0.0}}}}}}')
    with live_gateway(tmp_path) as (url, _world), httpx.Client(base_url=url, timeout=10) as http:
        r = http.post("/missions", content=body, headers={"Content-Type": "application/json"})
        assert r.status_code == 422, r.text
        assert http.get("/missions").json()["total"] == 0


@pytest.mark.parametrize("value", NON_FINITE)
@pytest.mark.parametrize("make", [
    lambda v: ("MoveRequest", {"dx_m": v, "dy_m": 0.0}, keys.IO_MOVE),
    lambda v: ("ResetRequest", {"pose": {"position_m": [0.0, v, 0.0], "heading_rad": 0.0}}, keys.IO_RESET),
    lambda v: ("ResetRequest", {"pose": {"position_m": [0.0, 0.0, 0.0], "heading_rad": v}}, keys.IO_RESET),
])
def test_non_finite_pose_on_the_bus_is_bad_request_and_never_reaches_the_robot(value, make):
    schema, data, key_t = make(value)
    model = {"MoveRequest": MoveRequest, "ResetRequest": ResetRequest}[schema]
    net = FakeNetwork()
    served, asker = FakeBus(net), FakeBus(net)
    calls = []
    key = key_t.format(robot="robot0")
    TypedBus(served, "robot_io").serve(key, model, lambda req: calls.append(req) or PoseReply(pose=Pose(position_m=(0, 0, 0))))
    replies = asker.query(key, _envelope({"s": schema, "v": 1, "d": data, "a": []}), timeout_s=2.0,
                          target=QueryTarget.BEST)
    assert replies and not replies[0].ok
    err = decode(replies[0].error, ErrorReply)
    assert err.code == ErrorCode.BAD_REQUEST and "finite" in err.message
    assert not calls
    served.close()
    asker.close()


def _ply(n: int) -> bytes:
    pts = np.random.default_rng(0).uniform(-1, 1, (n, 3)).astype("<f4")
    head = f"ply\nformat binary_little_endian 1.0\nelement vertex {n}\nproperty float x\nproperty float y\n" \
           "property float z\nend_header\n"
    return head.encode() + pts.tobytes()


@pytest.mark.parametrize("data", [_ply(0), b"ply\nformat ascii 1.0\nend_header\n", b"ply\ngarbage",
                                  b"ply\nformat binary_little_endian 1.0\nelement vertex 1000\nproperty float x\n"
                                  b"property float y\nproperty float z\nend_header\n" + b"\0" * 12])
def test_empty_tiny_or_broken_cloud_import_is_refused_and_stores_nothing(tmp_path, data):
    store = MapStore(tmp_path / "maps", fsync=False)
    with pytest.raises((MapStoreError, CloudFormatError)) as info:
        store.import_cloud("bad", data, filename="bad.ply")
    assert str(info.value)
    assert store.list() == []
    assert not [p for p in (tmp_path / "maps").rglob("*") if p.is_file() and p.name != ".lock"]


# --- a scene with no walkable area ------------------------------------------------------------------------------


def _quads_scene(name: str, quads: list, consistent_winding: bool = False):
    """A scene of flat quads (4 corners each, wound as given)."""
    from libs.world import Scene

    v = np.asarray(quads, np.float64).reshape(-1, 3)
    t = np.array([[b, b + 1, b + 2] for b in range(0, len(v), 4)] + [[b, b + 2, b + 3] for b in range(0, len(v), 4)],
                 np.int32)
    return Scene(name=name, vertices=v, triangles=t, vertex_colors=np.full(v.shape, 0.5, np.float32),
                 triangle_labels=np.zeros(len(t), np.int32), consistent_winding=consistent_winding)


def _quad(x0, y0, x1, y1, z, down=False):
    q = [[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]]
    return q[::-1] if down else q


_SMALL_CAM = {"width_px": 32, "height_px": 32, "hfov_deg": 90.0}
NO_WALKABLE = {
    # A ceiling (faces down) over nothing: nowhere to stand.
    "ceiling_only": lambda: _quads_scene("ceiling", [_quad(0, 0, 4, 4, 2.5, down=True)], consistent_winding=True),
    # A floor narrower than the agent's 0.2 m footprint.
    "floor_smaller_than_agent": lambda: _quads_scene("speck", [_quad(0, 0, 0.15, 0.15, 0.0)]),
    # A floor under a ceiling too low for the agent (no headroom).
    "no_headroom": lambda: _quads_scene("crawlspace", [_quad(0, 0, 4, 4, 0.0), _quad(0, 0, 4, 4, 1.0, down=True)],
                                        consistent_winding=True),
}


@pytest.mark.parametrize("make", NO_WALKABLE.values(), ids=NO_WALKABLE)
def test_scene_without_walkable_area_is_refused_with_a_typed_error(make):
    from libs.world import NavigationError, SceneError
    from services.robot_io.core import SimConfig, SimRobot

    with pytest.raises(SceneError) as info:
        SimRobot(SimConfig(camera=_SMALL_CAM), scene=make())
    assert isinstance(info.value, NavigationError) and isinstance(info.value, ValueError)
    assert "no walkable floor" in str(info.value) and "radius 0.10 m" in str(info.value)


def test_a_walkable_floor_of_the_same_kind_loads():
    from services.robot_io.core import SimConfig, SimRobot

    robot = SimRobot(SimConfig(camera=_SMALL_CAM), scene=_quads_scene("room", [_quad(0, 0, 4, 4, 0.0)]))
    assert robot.nav.reachable_area_m2 > 10 and abs(robot.pose.position_m[2]) < 0.05
    robot.close()


def test_load_scene_without_walkable_area_over_the_bus_is_bad_request_and_the_service_keeps_serving(tmp_path):
    from shared.o3d import o3d

    from services.robot_io.service import RobotIoService, RobotIoSettings
    from shared.bus.typed import RemoteError
    from shared.clients import RobotClient
    from shared.runner import RunningService

    bad = {}
    for name, quads in {"walls": [[[0, 0, 0], [4, 0, 0], [4, 0, 2.5], [0, 0, 2.5]]],
                        "speck": [_quad(0, 0, 0.15, 0.15, 0.0)]}.items():
        s = _quads_scene(name, quads)
        path = tmp_path / f"{name}.ply"
        o3d.io.write_triangle_mesh(str(path), o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(s.vertices), o3d.utility.Vector3iVector(s.triangles)))
        bad[name] = path
    good = tmp_path / "room.ply"
    room = _quads_scene("room", [_quad(0, 0, 4, 4, 0.0)])
    o3d.io.write_triangle_mesh(str(good), o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(room.vertices), o3d.utility.Vector3iVector(room.triangles)))
    net = FakeNetwork()
    settings = RobotIoSettings(instance="io-bad", robot_config={"scene": str(good), "camera": _SMALL_CAM},
                               scene_dirs=[str(tmp_path)])
    with RunningService(RobotIoService(settings), FakeBus(net)):
        robot = RobotClient(TypedBus(FakeBus(net)), "robot0", timeout_s=10.0)
        before = robot.scene()
        for name, path in bad.items():
            with pytest.raises(RemoteError) as info:
                robot.load_scene(str(path))
            assert info.value.code == ErrorCode.BAD_REQUEST, info.value
            assert "no walkable floor" in str(info.value) and name in str(info.value)
        # Still serving, on the scene it had.
        after = robot.scene()
        assert after.scene == before.scene and after.reachable_area_m2 == pytest.approx(before.reachable_area_m2)
        pano = robot.observe()
        assert pano.rgb.shape[1:3] == (32, 32)


# --- an empty or tiny cloud ---------------------------------------------------------------------------------------


def _tiny_cloud(n: int, z_m: float = 3.0):
    """``n`` points well above the floor band (a speck of ceiling): nothing to see, nothing on the floor."""
    from shared.cloud import PointCloud

    xyz = np.random.default_rng(n).uniform(-0.5, 0.5, (n, 3)).astype(np.float32)
    xyz[:, 2] += z_m
    return PointCloud(xyz, np.full((n, 3), 200, np.uint8), np.zeros(n, np.int32), {0: "ceiling"})


@pytest.mark.parametrize("backend", ["numpy", "torch"])
@pytest.mark.parametrize("n", [1, 5])
def test_tiny_cloud_renders_holes_and_an_unknown_map(backend, n):
    from services.renderer.core import MapRenderer, SpatialMapper
    from services.renderer.core.spatial_map import _COLOURS, UNKNOWN
    from libs.pointrender import RENDERERS, IndexedCloud
    from shared.schemas import CameraIntrinsics, Candidate, CandidateKind, ViewPose

    index = IndexedCloud(_tiny_cloud(n))
    port = MapRenderer(index, RENDERERS.create(backend), SpatialMapper())
    views = [ViewPose(position_m=(3.0, 0.0, 0.0), heading_rad=np.pi), ViewPose(position_m=(40.0, 40.0, 0.0))]
    out = port.views("tiny", views, CameraIntrinsics(width_px=48, height_px=48))
    assert out.rgb.shape == (2, 48, 48, 3) and out.hole_mask.shape == (2, 48, 48)
    assert out.hole_mask[1].all()  # far away: nothing at all
    assert out.hole_mask.mean() > 0.95  # a few points cover a few pixels at most
    assert (out.depth_m[out.hole_mask] == 0).all() and (out.labels[out.hole_mask] == -1).all()
    assert (out.depth_m[~out.hole_mask] > 0).all()
    pose = Pose(position_m=(0.0, 0.0, 0.0))
    grid = SpatialMapper().grid(index, 0.0)
    assert (grid.cells == UNKNOWN).all()
    smap = port.spatial_map("tiny", pose, np.zeros((1, 3)), [Candidate(index=0, kind=CandidateKind.STOP)],
                            size_px=96)
    assert smap.image.shape == (96, 96, 3) and smap.metres_per_px > 0
    colours, counts = np.unique(smap.image.reshape(-1, 3), axis=0, return_counts=True)
    assert tuple(colours[np.argmax(counts)]) == _COLOURS[UNKNOWN]


def test_empty_cloud_is_a_typed_error_that_is_also_a_value_error():
    from shared.cloud import EmptyCloudError, PointCloud
    from libs.pointrender import IndexedCloud
    from shared.schemas import MapChunk

    with pytest.raises(EmptyCloudError):
        IndexedCloud(PointCloud(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)))
    chunk = MapChunk(map_id="hollow", version=3, index=0, count=1, xyz_m=np.zeros((0, 3), np.float32),
                     rgb=np.zeros((0, 3), np.uint8))
    with pytest.raises(EmptyCloudError, match="'hollow' version 3 has no points") as info:
        PointCloud.from_chunks([chunk])
    assert isinstance(info.value, ValueError)


def _serve_map(bus: TypedBus, map_id: str, n: int) -> None:
    """MAP_INFO / MAP_CHUNK for one map of ``n`` points, as the reconstructor's map store answers them."""
    from shared.schemas import MapChunk, MapChunkRequest, MapInfo, MapRequest

    cloud = _tiny_cloud(n)
    lo, hi = (cloud.xyz.min(0), cloud.xyz.max(0)) if n else (np.zeros(3), np.zeros(3))
    info = MapInfo(map_id=map_id, version=1, point_count=n, bounds_min_m=tuple(map(float, lo)),
                   bounds_max_m=tuple(map(float, hi)), has_labels=True, label_names=cloud.label_names)
    chunk = MapChunk(map_id=map_id, version=1, index=0, count=1, xyz_m=cloud.xyz, rgb=cloud.rgb, labels=cloud.labels)
    bus.serve(keys.MAP_INFO.format(map=map_id), MapRequest, lambda _r: info)
    bus.serve(keys.MAP_CHUNK.format(map=map_id), MapChunkRequest, lambda _r: chunk)


def test_renderer_service_on_empty_and_tiny_maps():
    from services.renderer.service import RendererService, RendererSettings
    from shared.bus.typed import RemoteError
    from shared.clients import RendererClient
    from shared.runner import RunningService
    from shared.schemas import CameraIntrinsics, ViewPose

    net = FakeNetwork()
    store = TypedBus(FakeBus(net), "reconstructor")
    for n in (0, 1, 5):
        _serve_map(store, f"m{n}", n)
    with RunningService(RendererService(RendererSettings(instance="r-bad")), FakeBus(net)):
        client = RendererClient(TypedBus(FakeBus(net)), timeout_s=20.0)
        views = [ViewPose(position_m=(3.0, 0.0, 0.0), heading_rad=np.pi)]
        cam = CameraIntrinsics(width_px=32, height_px=32)
        pose = Pose(position_m=(0.0, 0.0, 0.0))
        for call in (lambda: client.views("m0", views, cam), lambda: client.spatial_map("m0", pose, size_px=64)):
            with pytest.raises(RemoteError) as info:
                call()
            assert info.value.code == ErrorCode.BAD_REQUEST and "'m0' version 1 has no points" in str(info.value)
        for n in (1, 5):
            out = client.views(f"m{n}", views, cam)
            assert out.hole_mask.mean() > 0.95 and (out.depth_m[out.hole_mask] == 0).all()
            smap = client.spatial_map(f"m{n}", pose, size_px=64)
            assert smap.image.shape == (64, 64, 3)
    store.raw.close()


# --- NaN / inf in array payloads ----------------------------------------------------------------------------------


def _good_messages() -> dict:
    from shared.schemas import CameraIntrinsics, Frame, MapChunk, Panorama

    cam = CameraIntrinsics(width_px=8, height_px=8, hfov_deg=90.0)
    pose = Pose(position_m=(1.0, 2.0, 0.0), heading_rad=0.5)
    depth = np.full((8, 8), 2.0, np.float32)
    depth[0, 0] = 0.0  # 0 = no measurement is fine
    return {
        "frame": Frame(index=0, timestamp_s=1.0, pose=pose, imu_heading_rad=0.5, camera=cam,
                       rgb=np.zeros((8, 8, 3), np.uint8), depth_m=depth),
        "panorama": Panorama(pose=pose, camera=cam, headings_rad=np.linspace(0, -np.pi, 3),
                             rgb=np.zeros((3, 8, 8, 3), np.uint8), depth_m=np.stack([depth] * 3)),
        "chunk": MapChunk(map_id="m", version=1, index=0, count=1, xyz_m=np.zeros((4, 3), np.float32),
                          rgb=np.zeros((4, 3), np.uint8)),
    }


def _poisoned(msg, field: str, value: float, at=(0,)):
    arr = np.array(getattr(msg, field), copy=True)
    arr[at] = value
    return msg.model_copy(update={field: arr})  # model_copy does not validate: a bad sender's payload


BAD_ARRAYS = [("frame", "depth_m", (1, 1)), ("panorama", "depth_m", (2, 3, 4)), ("panorama", "headings_rad", (1,)),
              ("chunk", "xyz_m", (3, 2))]


@pytest.mark.parametrize("value", NON_FINITE)
@pytest.mark.parametrize("which,field,at", BAD_ARRAYS)
def test_non_finite_array_payloads_are_refused_by_decode(which, field, at, value):
    from shared.codec import CodecError, encode

    good = _good_messages()[which]
    assert decode(encode(good), type(good)) is not None  # the clean message decodes
    with pytest.raises(CodecError) as info:
        decode(encode(_poisoned(good, field, value, at)), type(good))
    assert info.value.reason == "invalid" and field in str(info.value) and "finite" in str(info.value)


@pytest.mark.parametrize("which", ["frame", "panorama"])
def test_negative_depth_is_refused_too(which):
    from shared.codec import CodecError, encode

    good = _good_messages()[which]
    bad = _poisoned(good, "depth_m", -1.0, (0,) * good.depth_m.ndim)
    with pytest.raises(CodecError, match=">= 0"):
        decode(encode(bad), type(good))


@pytest.mark.parametrize("field", ["timestamp_s", "pitch_rad", "imu_heading_rad"])
def test_non_finite_frame_scalars_are_refused(field):
    from shared.codec import CodecError, encode

    good = _good_messages()["frame"]
    with pytest.raises(CodecError, match="finite"):
        decode(encode(good.model_copy(update={field: math.nan})), type(good))


def test_a_poisoned_map_chunk_over_the_bus_never_reaches_the_handler():
    from shared.codec import encode
    from shared.schemas import MapChunk

    net = FakeNetwork()
    served, asker = FakeBus(net), FakeBus(net)
    calls = []
    TypedBus(served, "x").serve("test/chunk", MapChunk, lambda c: calls.append(c) or c)
    bad = _poisoned(_good_messages()["chunk"], "xyz_m", math.nan, (1, 0))
    replies = asker.query("test/chunk", encode(bad), timeout_s=2.0, target=QueryTarget.BEST)
    assert replies and not replies[0].ok
    err = decode(replies[0].error, ErrorReply)
    assert err.code == ErrorCode.BAD_REQUEST and "xyz_m" in err.message and not calls
    served.close()
    asker.close()
