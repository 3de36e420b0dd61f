"""Where anticipated views come from (issue 20 item 6): the map (the method) or, as an evaluation control,
ray-cast from the simulator's true scene at the same poses. Real simulator, real renderer core."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.mapper.core import PREDICTORS
from services.planner.core import POLICIES
from services.planner.core.mission import AnticipationError, MissionLoop, TrueSceneViews
from services.planner.core.policy import Policy
from services.renderer.core import MapRenderer, SpatialMapper
from libs.pointrender import RENDERERS, IndexedCloud
from shared.schemas import CameraIntrinsics, MissionOptions, RenderRequest, SceneViewsRequest, ViewPose

pytestmark = pytest.mark.timeout(120)

CAM = {"width_px": 64, "height_px": 64, "hfov_deg": 90.0}


@pytest.fixture(scope="module")
def world(house_robot, house_map_cloud):
    # The session's simulator of generated:0 at this file's camera (tests/unit/conftest.py), not one
    # of its own: every test here resets it to the start pose before it moves or looks.
    c = house_map_cloud  # the same scene's cloud, sampled once for the session
    port = MapRenderer(IndexedCloud(c), RENDERERS.create("numpy"), SpatialMapper())
    return house_robot, port, c.label_names


class Keeps(Policy):
    """Keeps every step's anticipated views and poses; takes the first waypoint, then stops."""

    name = "keeps"

    def __init__(self):
        super().__init__()
        self.seen: list[tuple] = []

    def decide(self, ctx):
        movable = [v for v in ctx.candidates if v.anticipated_rgb is not None]
        self.seen.append((ctx.pose, movable))
        if ctx.step == 0 and movable:
            return self._decision(ctx, movable[0].index, "first")
        return self._decision(ctx, ctx.stop_candidate.index, "stop")


def _loop(world, policy, robot=None):
    sim, port, names = world
    sim.reset()
    return MissionLoop(robot=robot or sim, predictor=PREDICTORS.create("geometric"), renderer=port, policy=policy,
                       emit=lambda *a, **k: None, label_names=names)


def test_scene_views_at_the_robot_pose_are_its_own_observation(world):
    sim, _, _ = world
    sim.reset()
    pano = sim.observe(CameraIntrinsics(**CAM))
    out = sim.scene_views([ViewPose(position_m=pano.pose.position_m, heading_rad=pano.headings_rad[3])],
                          CameraIntrinsics(**CAM))
    assert np.array_equal(out.rgb[0], pano.rgb[3])
    assert np.allclose(out.depth_m[0], pano.depth_m[3], atol=1e-4)
    assert np.array_equal(out.labels[0], pano.semantic[3])
    assert not out.hole_mask[0][out.depth_m[0] > 0].any()


def test_true_scene_missions_see_the_simulator_views_at_the_candidates(world):
    sim, _, _ = world
    policy = Keeps()
    out = _loop(world, policy).run("m-true", "walk to the kitchen", "local",
                                   MissionOptions(max_steps=3, anticipation_views="true-scene"))
    assert out.steps >= 1
    pose, views = policy.seen[0]
    assert views
    v = views[0]
    c = v.candidate
    sim.reset()  # back at the start pose, where step 0 was rendered
    want = sim.scene_views([ViewPose(position_m=(pose.position_m[0] + c.dx_m, pose.position_m[1] + c.dy_m,
                                                 pose.position_m[2]), heading_rad=math.atan2(c.dy_m, c.dx_m))],
                           CameraIntrinsics(hfov_deg=90.0))
    assert np.array_equal(v.anticipated_rgb, want.rgb[0])
    assert np.array_equal(v.anticipated_labels, want.labels[0])


def test_the_heuristic_runs_on_map_and_true_scene_views(world):
    for source in ("map", "true-scene"):
        out = _loop(world, POLICIES.create("heuristic")).run(
            f"m-{source}", "walk forward 2 meters and stop", "local",
            MissionOptions(max_steps=2, anticipation_views=source))
        assert out.steps >= 1


def test_unknown_or_unavailable_sources_are_refused(world):
    loop = _loop(world, Keeps())
    with pytest.raises(AnticipationError, match="known: map, true-scene"):
        loop.anticipation_source("dream")

    class NoScene:  # a robot port without the simulator's scene (a real robot)
        def __getattr__(self, name):
            if name == "scene_views":
                raise AttributeError(name)
            return getattr(world[0], name)

    with pytest.raises(AnticipationError, match="true-scene a simulator"):
        _loop(world, Keeps(), robot=NoScene()).anticipation_source("true-scene")
    assert isinstance(loop.anticipation_source("true-scene"), TrueSceneViews)


def test_requests_carry_the_splat_mode_and_refuse_unknown_ones():
    v = [ViewPose(position_m=(0.0, 0.0, 0.0))]
    assert RenderRequest(map_id="m", views=v, splat_mode="paper").splat_mode == "paper"
    assert RenderRequest(map_id="m", views=v).splat_mode is None  # the renderer's own mode
    with pytest.raises(ValueError):
        RenderRequest(map_id="m", views=v, splat_mode="3x3")
    with pytest.raises(ValueError):
        MissionOptions(anticipation_views="dream")
    with pytest.raises(ValueError):
        SceneViewsRequest(views=[])
