"""robot-io and mapper services on the fake bus, driven through the typed clients."""

import time

import numpy as np
import pytest

from services.mapper.service import MapperService, MapperSettings
from services.robot_io.service import RobotIoService, RobotIoSettings, downscale_frame
from shared import keys
from shared.bus import FakeBus, FakeNetwork
from shared.bus.typed import RemoteError, TypedBus
from shared.clients import MapperClient, RobotClient
from shared.runner import RunningService
from shared.schemas import CameraIntrinsics, ErrorCode, Frame, MoveStatus, Pose, RecordReply, RecordRequest

CAM = {"width_px": 64, "height_px": 64, "hfov_deg": 90.0}


@pytest.fixture(scope="module")
def services_net():
    """robot-io and the mapper in this process on one fake network (not named ``system``: that name marks
    a test that launches OS processes, tests/conftest.py)."""
    net = FakeNetwork()
    robot_settings = RobotIoSettings(instance="io-1", robot_config={"scene": "generated:0", "camera": CAM})
    with RunningService(RobotIoService(robot_settings), FakeBus(net)), \
            RunningService(MapperService(MapperSettings(instance="m-1")), FakeBus(net)):
        yield net


def test_observe_move_and_pose_over_the_bus(services_net):
    bus = TypedBus(FakeBus(services_net))
    robot = RobotClient(bus, "robot0")
    start = robot.reset()
    pano = robot.observe()
    assert pano.rgb.shape == (12, 64, 64, 3) and pano.semantic is not None
    cands = MapperClient(bus, "robot0").predict(pano)
    assert 1 <= len(cands) <= 5
    c = cands[0]
    res = robot.move_to(c.dx_m, c.dy_m)
    assert res.status in (MoveStatus.REACHED, MoveStatus.BLOCKED)
    assert np.hypot(*(res.pose.xyz - start.xyz)[:2]) == pytest.approx(res.travelled_m, abs=0.3)
    scene = robot.scene()
    assert scene.rooms and scene.label_names and scene.reachable_area_m2 > 20


def test_recording_publishes_frames_and_counts_them(services_net):
    bus = TypedBus(FakeBus(services_net))
    robot = RobotClient(bus, "robot0", recording_px=32, recording_prefix="tour")
    robot.reset()
    got: list[Frame] = []
    bus.subscribe(keys.IO_FRAMES.pattern(robot="robot0"), Frame, lambda k, f: got.append(f))
    with robot.recording(rate_hz=5.0) as name:
        assert name == "tour-r0"  # the client names a job's recordings, so they can be told apart
        robot.turn(1.0)
        robot.look_around()
    n = robot.last_recording.frame_count
    assert n > 5
    end = time.monotonic() + 5
    while len(got) < n and time.monotonic() < end:
        time.sleep(0.01)
    assert len(got) == n and got[0].rgb.shape == (32, 32, 3) and got[0].camera.width_px == 32


def test_bad_requests_get_typed_errors_and_service_keeps_serving(services_net):
    bus = TypedBus(FakeBus(services_net))
    robot = RobotClient(bus, "robot0")
    # The client refuses a bad recording name itself (SegmentId); a payload forged past it is refused by
    # the service with a typed error.
    with pytest.raises(ValueError):
        with robot.recording(recording="bad/name"):
            pass
    forged = RecordRequest.model_construct(**{**RecordRequest(recording="ok", start=True).model_dump(),
                                              "recording": "bad/name"})
    with pytest.raises(RemoteError) as e:
        bus.request(keys.IO_RECORD.format(robot="robot0"), forged, RecordReply)
    assert e.value.code == ErrorCode.BAD_REQUEST
    with pytest.raises(RemoteError) as e:
        bus.request(keys.IO_RECORD.format(robot="robot0"), RecordRequest(recording="nope", start=False), RecordReply)
    assert e.value.code == ErrorCode.BAD_REQUEST
    for bad in [b"", b"\x00" * 50, b"ANT1" + b"\xff" * 100]:
        (reply,) = bus.raw.query(keys.IO_MOVE.format(robot="robot0"), bad)
        assert not reply.ok
    assert robot.observe().rgb.shape[0] == 12


def test_downscale_keeps_field_of_view_geometry():
    rng = np.random.default_rng(0)
    cam = CameraIntrinsics(width_px=128, height_px=128)
    f = Frame(index=0, timestamp_s=0, pose=Pose(position_m=(0, 0, 0)), imu_heading_rad=0.0, camera=cam,
              rgb=rng.integers(0, 255, (128, 128, 3), dtype=np.uint8), depth_m=np.full((128, 128), 2.0, np.float32))
    small = downscale_frame(f, 32)
    assert small.rgb.shape == (32, 32, 3) and small.depth_m.shape == (32, 32)
    assert small.camera.hfov_deg == cam.hfov_deg
    assert small.camera.pinhole().fx == pytest.approx(cam.pinhole().fx / 4)


def test_load_scene_switches_the_simulator_and_refuses_bad_specs(services_net):
    bus = TypedBus(FakeBus(services_net))
    robot = RobotClient(bus, "robot0")
    before = robot.scene()
    other = robot.load_scene("generated:3")
    assert other.scene != before.scene
    with pytest.raises(RemoteError):
        robot.load_scene("/no/such/mesh.ply")
    assert robot.scene().scene == other.scene  # a failed load leaves the current scene in place
    robot.load_scene("generated:0")


def test_exploration_options_are_refused_before_the_job_is_accepted(services_net):
    """A bad discovery profile or knob is an answer to the submit, not a failed job: nothing starts."""
    from shared.schemas import ExplorationRequest

    mapper = MapperClient(TypedBus(FakeBus(services_net)), "robot0")
    for i, options in enumerate([{"profile": "no-such-profile"}, {"discovery": {"exploration": {"nope": 1}}},
                                 {"profile": 3}, {"discovery": []}]):
        ack = mapper.explore(ExplorationRequest(exploration_id=f"x-bad{i}", map_id="m", options=options))
        assert not ack.accepted and "bad exploration options" in ack.reason, options
