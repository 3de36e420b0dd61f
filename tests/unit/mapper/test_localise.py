"""The mapper's online localisation (localise.py): a known drift recovered, exact poses left bit for
bit as they are, a featureless corridor kept on odometry, and tours recorded with the correction."""

from __future__ import annotations

import math

import numpy as np
import pytest

from shared.geometry import PinholeCamera, wrap_angle
from shared.schemas import Frame, MoveResult, Panorama, Pose

from services.mapper.core import DiscoveryConfig, ExplorationConfig, discover, execute_tours
from services.mapper.core.localise import Correction, LocalisedRobot, Localiser, LocaliserConfig, panorama_scan
from services.mapper.tools.boxworld import Box, BoxWorld, BoxWorldRobot, rooms_world


class DriftingRobot:
    """A box-world robot whose odometry is off by ``offset`` (x, y, heading) once it is set, the way
    the simulator's drift is: an offset in world axes on the reported pose and the panorama's headings;
    moves are displacements, the same in odometry and the world."""

    def __init__(self, robot: BoxWorldRobot):
        self.robot = robot
        self.offset = (0.0, 0.0, 0.0)
        self.truth: dict[int, Pose] = {}  # frame index -> the pose it was truly taken at

    def _odom(self, p: Pose) -> Pose:
        dx, dy, dh = self.offset
        x, y, z = p.position_m
        return Pose(position_m=(x + dx, y + dy, z), heading_rad=float(wrap_angle(p.heading_rad + dh)))

    @property
    def true_pose(self) -> Pose:
        return self.robot.pose

    @property
    def pose(self) -> Pose:
        return self._odom(self.robot.pose)

    def observe(self) -> Panorama:
        pano = self.robot.observe()
        return pano.model_copy(update={"pose": self._odom(pano.pose), "headings_rad": np.asarray(
            wrap_angle(pano.headings_rad + self.offset[2]), np.float64)})

    def move_to(self, dx_m: float, dy_m: float) -> MoveResult:
        res = self.robot.move_to(dx_m, dy_m)
        return res.model_copy(update={"pose": self._odom(res.pose)})

    def turn(self, angle_rad: float) -> Pose:
        return self._odom(self.robot.turn(angle_rad))

    def _frame(self, f: Frame) -> Frame:
        self.truth[f.index] = f.pose
        return f.model_copy(update={"pose": self._odom(f.pose),
                                    "imu_heading_rad": float(wrap_angle(f.imu_heading_rad + self.offset[2]))})

    def look_around(self) -> list[Frame]:
        return [self._frame(f) for f in self.robot.look_around()]

    def recording(self, sink, rate_hz: float = 5.0):
        return self.robot.recording(lambda f: sink(self._frame(f)), rate_hz)


def _error(a: Pose, b: Pose) -> tuple[float, float]:
    return (math.hypot(a.position_m[0] - b.position_m[0], a.position_m[1] - b.position_m[1]),
            math.degrees(abs(math.remainder(a.heading_rad - b.heading_rad, 2 * math.pi))))


@pytest.fixture(scope="module")
def rooms():
    return rooms_world()


def test_scan_points_lie_on_the_walls(rooms):
    """The horizontal scan of a panorama in the big room (walls at x=0, y=0, y=4 and x=6 but for
    its door) lands on those walls, from the heading the panorama reports."""
    robot = BoxWorldRobot(rooms, PinholeCamera(48, 48, 90.0))
    robot.reset(Pose(position_m=(2.0, 2.0, 0.0), heading_rad=0.4))
    pano = robot.observe()
    scan = panorama_scan(pano, LocaliserConfig())
    assert len(scan) > 200
    c, s = math.cos(0.4), math.sin(0.4)
    xy = scan[:, :2] @ np.array([[c, -s], [s, c]]).T + (2.0, 2.0)
    to_wall = np.min(np.abs(np.stack([xy[:, 0], xy[:, 1], xy[:, 1] - 3.95, xy[:, 0] - 5.95], axis=1)), axis=1)
    assert np.percentile(to_wall, 95) < 0.01


def test_a_known_drift_is_recovered(rooms):
    """The start anchors the model; the robot walks 1.3 m while its odometry drifts 6 cm and 2 deg
    (four times the noisy row's drift): the next panorama is placed within 1.5 cm and 0.3 deg of the
    truth, and every pose the mapper sees afterwards (moves, frames) is corrected the same way."""
    robot = DriftingRobot(BoxWorldRobot(rooms, PinholeCamera(64, 64, 90.0)))
    robot.robot.reset(Pose(position_m=(2.0, 2.0, 0.0), heading_rad=0.0))
    loc = Localiser()
    lr = LocalisedRobot(robot, loc)
    first = robot.observe()
    assert lr.localiser.localise(first) is first  # the anchor is taken as it is
    lr.move_to(1.2, 0.5)
    robot.offset = (0.05, -0.035, math.radians(2.0))
    pano = lr.observe()
    assert loc.steps[-1].outcome == "corrected", loc.steps[-1]
    pos, head = _error(pano.pose, robot.true_pose)
    assert pos < 0.015 and head < 0.3, (pos, head, loc.steps[-1])
    c = loc.correction
    assert abs(c.dx_m + 0.05) < 0.015 and abs(c.dy_m - 0.035) < 0.015 and abs(math.degrees(c.dyaw_rad) + 2.0) < 0.3
    # The views' headings turn with the pose: view 0 looks where the pose heads.
    assert abs(math.remainder(pano.headings_rad[0] - pano.pose.heading_rad, 2 * math.pi)) < 1e-9
    res = lr.move_to(-0.5, 0.3)
    assert _error(res.pose, robot.true_pose)[0] < 0.02
    assert _error(lr.pose, robot.true_pose)[0] < 0.02
    frame = Frame(index=0, timestamp_s=1.0, pose=robot.pose, imu_heading_rad=robot.pose.heading_rad,
                  camera=pano.camera, rgb=np.zeros((4, 4, 3), np.uint8))
    fixed = loc.correction.frame(frame)
    assert _error(fixed.pose, robot.true_pose)[0] < 0.02
    assert abs(math.remainder(fixed.imu_heading_rad - robot.true_pose.heading_rad, 2 * math.pi)) < math.radians(0.3)


def test_exact_poses_pass_through_unchanged(rooms):
    """Without drift the registration agrees with odometry within its gate: every panorama comes back
    as the very same object and the correction stays exactly zero."""
    robot = BoxWorldRobot(rooms, PinholeCamera(48, 48, 90.0))
    lr = LocalisedRobot(robot, Localiser())
    for dx, dy in ((0.0, 0.0), (1.0, 0.5), (1.5, -0.5), (0.0, 1.0)):
        lr.move_to(dx, dy)
        pano = robot.observe()
        assert lr.localiser.localise(pano) is pano
    assert lr.localiser.correction == Correction()
    assert {s.outcome for s in lr.localiser.steps[1:]} <= {"agrees", "odometry: degenerate", "odometry: poor fit"}
    assert any(s.outcome == "agrees" for s in lr.localiser.steps)


def test_exploration_and_tours_are_bit_identical_without_noise(rooms):
    """Discovery and tours with the correction on record the same graph and frames, pose for pose,
    as with it off, on an exact robot (the gate is on measured disagreement, not on a noise flag)."""
    def run(enabled: bool):
        robot = BoxWorldRobot(rooms, PinholeCamera(48, 48, 90.0))
        cfg = DiscoveryConfig(exploration=ExplorationConfig(max_steps=10))
        cfg.localisation.enabled = enabled
        d = discover(robot, cfg)
        recs = execute_tours(robot, d.tours, d.scene, rate_hz=2.0)
        graph = sorted((n, tuple(d.result.graph.pos(n))) for n in d.result.graph.g)
        frames = [(r.region, r.start_pose, [(f.pose, f.imu_heading_rad, f.rgb.tobytes()) for f in r.frames]) for r in recs]
        return graph, frames, d.scene.localiser

    graph_off, frames_off, loc_off = run(False)
    graph_on, frames_on, loc_on = run(True)
    assert loc_off is None and loc_on is not None and len(loc_on.steps) > 10  # tours re-localised too
    assert loc_on.correction == Correction()
    # Nothing was ever corrected, so the pose graph registered no pair of panoramas: its pair ICPs
    # wait for drift (they doubled a noise-free exploration's CPU for nothing).
    assert not loc_on.drift_seen and loc_on.graph is not None and not loc_on.graph.edges
    assert graph_on == graph_off
    assert frames_on == frames_off


def corridor_world() -> BoxWorld:
    """A corridor 1.6 m wide and 40 m long: nothing within the scan's range says where along it."""
    t, h = 0.1, 2.6
    return BoxWorld(boxes=[Box((-20, -t, 0), (20, 0, h)), Box((-20, 1.6, 0), (20, 1.6 + t, h)),
                           Box((-20 - t, 0, 0), (-20, 1.6, h)), Box((20, 0, 0), (20 + t, 1.6, h))],
                    floors=[Box((-20, 0, -0.1), (20, 1.6, 0.0))], start=(0.0, 0.8, 0.0))


def test_a_featureless_corridor_keeps_odometry_along_it():
    """In a corridor the walls pin the robot across it but not along it: a drift along the corridor
    must not be 'corrected' by whatever the matcher slides to, so odometry is kept along it, while
    the sideways drift is still corrected by the walls."""
    robot = DriftingRobot(BoxWorldRobot(corridor_world(), PinholeCamera(48, 48, 90.0)))
    loc = Localiser()
    lr = LocalisedRobot(robot, loc)
    lr.observe()
    lr.move_to(1.0, 0.0)
    robot.offset = (0.3, 0.04, 0.0)
    lr.observe()
    step = loc.steps[-1]
    assert step.outcome == "corrected" and step.constraint < loc.config.min_constraint, step
    assert abs(loc.correction.dx_m) < 0.01  # along: odometry, 0.3 m off, kept as it is
    assert abs(loc.correction.dy_m + 0.04) < 0.01  # across: corrected
    assert loc.report()["odometry_along_one_direction"] == 1


@pytest.mark.parametrize("graph", [False, True])
def test_tours_record_the_correction_in_effect(rooms, graph):
    """A drifting robot's tours: the frames carry corrected poses, and each recording lists the
    corrections in effect (what a robot that publishes its own frames needs to correct them); with
    the pose graph (the default) too."""
    robot = DriftingRobot(BoxWorldRobot(rooms, PinholeCamera(48, 48, 90.0)))
    cfg = DiscoveryConfig(exploration=ExplorationConfig(max_steps=8))
    # This drift jumps at once; a real one grows with the path, which the defaults (re-registering
    # after 1 m, odometry's prior widening with the path) allow for.
    cfg.localisation.relocalise_after_m = 0.0
    cfg.localisation.prior_m = cfg.localisation.prior_max_m = 0.05
    # ... and the pose graph's odometry edges, as wide as the jump (its own defaults widen with the path).
    cfg.localisation.graph.enabled = graph
    cfg.localisation.graph.odom_m, cfg.localisation.graph.odom_rad = 0.1, math.radians(3.0)
    d = discover(robot, cfg)
    robot.offset = (0.06, 0.04, math.radians(1.5))  # drift after the exploration: only the tours see it
    recs = execute_tours(robot, d.tours, d.scene, rate_hz=2.0)
    assert recs
    loc = d.scene.localiser
    assert any(s.outcome == "corrected" for s in loc.steps)
    errors = []
    for rec in recs:
        assert rec.corrections and rec.corrections[-1][1] != Correction()
        # A start in a doorway pins the robot one way only (odometry kept along the other): never
        # worse than odometry's 7 cm.
        assert _error(rec.start_pose, robot.truth[rec.frames[0].index])[0] < 0.065
        errors += [_error(f.pose, robot.truth[f.index]) for f in rec.frames]
    pos, head = np.array(errors).T
    # Odometry is 7 cm and 1.5 deg off; the recorded frames are not. With the graph the worst frame
    # is 0.6 deg off, not 0.3: on this 48 px box world one panorama after a look-around took a
    # sequential heading correction 0.6 deg too far, and the graph leaves placements that fit every
    # scan edge within its uncertainty (chi2 7.7 < 16.3): the gate that keeps noise-free maps exact
    # (posegraph.PoseGraph.solve). A weakness of the gate, measured here, not hidden.
    assert np.median(pos) < 0.015 and head.max() < (0.7 if graph else 0.3), (np.median(pos), head.max())



class _DriftingJobRobot:
    """The exploration job's box-world robot (robot-io as the job sees it) whose odometry drifts
    with the path it drives: every pose it reports (panoramas, moves, frames) is off by
    (12, -8) mm times the square root of the metres driven."""

    def __new__(cls):
        from tests.unit.mapper.test_exploration_cancel import Robot

        class Drifting(Robot):
            driven_m = 0.0
            true_starts: list = []

            @property
            def pose(self) -> Pose:
                x, y, z = (float(v) for v in self._pos)
                k = math.sqrt(self.driven_m)
                return Pose(position_m=(x + 0.012 * k, y - 0.008 * k, z), heading_rad=self._heading)

            def move_to(self, dx_m: float, dy_m: float):
                before = self._pos.copy()
                res = super().move_to(dx_m, dy_m)
                self.driven_m += float(np.hypot(*(self._pos[:2] - before[:2])))
                return res.model_copy(update={"pose": self.pose})

            def recording(self, sink=None, rate_hz: float = 5.0):
                self.true_starts.append(tuple(float(v) for v in self._pos))
                return super().recording(sink, rate_hz)

        return Drifting()


class _CaptureBuild:
    """A map builder that keeps the request and refuses it (the test reads what the mapper sent)."""

    def __init__(self):
        self.requests: list = []

    def build(self, req, *, on_event=None, cancel=None):
        self.requests.append(req)
        raise RuntimeError("captured")


@pytest.mark.parametrize("drift", [True, False])
def test_the_exploration_job_hands_the_corrections_to_the_reconstructor(drift):
    """Robot-io publishes the tours' frames with odometry poses, past the mapper: the job sends each
    recording's start pose as odometry has it, beside the corrections that put it (and the frames)
    where the robot truly was. An exact robot's recordings carry none and are as before."""
    from shared.bus import FakeNetwork
    from tests.unit.mapper.test_exploration_cancel import Job, Robot

    robot = _DriftingJobRobot() if drift else Robot()
    maps = _CaptureBuild()
    job = Job(FakeNetwork(), robot, maps, max_steps=10)
    try:
        job.end()
    finally:
        job.close()
    (req,) = maps.requests
    assert req.recordings
    # The pose graph's record goes with the build: an exact robot's moved no panorama.
    assert req.pose_graph is not None and req.pose_graph.panoramas >= 10
    assert req.pose_graph.applied == drift and (req.pose_graph.panoramas_corrected > 0) == drift
    for rec in req.recordings:
        if not drift:
            assert rec.odom_corrections == []
            continue
        true = robot.true_starts[int(rec.recording.rsplit("-r", 1)[1])]
        odo_err = math.hypot(rec.start_pose.position_m[0] - true[0], rec.start_pose.position_m[1] - true[1])
        c = rec.odom_corrections[0]
        fixed = (rec.start_pose.position_m[0] + c.dx_m, rec.start_pose.position_m[1] + c.dy_m)
        assert odo_err > 0.03  # the drift is real by then
        # The correction of the last fix: what drifted since (under the 1 m re-registration) and the fix's
        # own error remain. Since the odometry prior was widened (ad7169e: 0.03 -> 0.042 m median at a
        # tour start on generated:0) a fix on this 32 px box world lands 3-4 cm from the truth, not < 3.
        fixed_err = math.hypot(fixed[0] - true[0], fixed[1] - true[1])
        assert fixed_err < min(0.05, odo_err / 3), (odo_err, fixed_err, c)


@pytest.mark.parametrize("bridge", [False, True])
def test_a_panorama_past_a_door_is_bridged_to_the_room_behind(rooms, bridge):
    """Exploring through the door into the north room (2.6 m, one straight move) while odometry drifts
    5 cm: the panorama there sees nothing of the model within its range and is placed by odometry
    alone, 5 cm off (the two-floor house's rooms kept such crossings' drift). With the bridge the
    robot steps back half the move, takes a panorama in the doorway, placed by the room behind it
    (against the model without the unplaced panorama's dead-reckoned room: with it, the doorway's
    panorama was pulled half way to it and the far one stayed 5 cm off), and returns; the far
    panorama is placed again from there, within 1 cm."""
    robot = DriftingRobot(BoxWorldRobot(rooms, PinholeCamera(64, 64, 90.0)))
    robot.robot.reset(Pose(position_m=(2.0, 1.5, 0.0), heading_rad=0.0))
    loc = Localiser()
    lr = LocalisedRobot(robot, loc, bridge=bridge)
    lr.observe()
    lr.move_to(0.0, 1.0)
    robot.offset = (0.02, -0.01, math.radians(0.3))
    lr.observe()
    assert loc.drift_seen  # bridges wait for drift, as the pose graph does
    lr.move_to(0.0, 2.6)
    robot.offset = (0.06, 0.02, math.radians(0.3))
    lr.observe()
    far = loc.steps[2]
    true = Pose(position_m=(2.0, 5.1, 0.0), heading_rad=far.odom.heading_rad - math.radians(0.3))
    assert _error(robot.true_pose, true)[0] < 1e-9  # back where the panorama was taken
    pos, _ = _error(far.correction.pose(far.odom), true)
    if not bridge:
        assert len(loc.steps) == 3 and far.outcome.startswith("odometry") and pos > 0.045
        return
    assert lr.bridges == 1 and len(loc.steps) == 4 and loc.steps[3].outcome == "corrected", loc.steps
    assert lr.bridge_m == pytest.approx(2.6, abs=0.05)  # half the move back and forward again
    assert pos < 0.01, (pos, far)
    assert len(loc.graph.nodes) == 4 and np.allclose(loc.graph.nodes[2].pose[:2], far.correction.pose(far.odom).position_m[:2])
