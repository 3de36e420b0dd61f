"""The spatial map names the scene graph's room instances (issue 32): the same names as the prompt's text,
drawn at the rooms' centroids, through the mission loop and the real renderer core."""

from __future__ import annotations

import numpy as np
import pytest

from libs.pointrender import RENDERERS, IndexedCloud
from libs.scenegraph import build_scene_graph
from libs.scenegraph.text import floor_room_labels
from services.mapper.core import PREDICTORS
from services.planner.core.mission import MissionLoop
from services.planner.core.policy import Policy
from services.renderer.core import MapRenderer, SpatialMapper
from services.robot_io.core import ROBOTS
from shared.schemas import MapRoomLabel, MissionOptions, Pose
from tests.unit.scenegraph.test_graph_policy import _two_rooms

pytestmark = pytest.mark.timeout(90)

_TEXT = np.array((20, 110, 40))  # the room names' colour in services/renderer/core/spatial_map.py


def _text_px(img: np.ndarray, centre_px, half=(60, 14)) -> int:
    x, y = (int(v) for v in centre_px)
    box = img[max(0, y - half[1]): y + half[1], max(0, x - half[0]): x + half[0]].astype(int)
    return int((np.abs(box - _TEXT).sum(axis=2) < 30).sum())


def test_graph_names_replace_the_clouds_and_sit_at_the_given_places():
    cloud = _two_rooms()
    index, mapper = IndexedCloud(cloud), SpatialMapper()
    pose = Pose(position_m=(1.0, 2.0, 0.0))
    labels = floor_room_labels(build_scene_graph(cloud), pose.xyz)
    assert sorted(n for n, _, _ in labels) == ["bedroom", "kitchen"]
    img = mapper.draw(index, pose, room_labels=labels)
    to_px = lambda x, y: np.rint(img.world_to_px[:, :2] @ [x, y] + img.world_to_px[:, 2])  # noqa: E731
    for _, x, y in labels:
        assert _text_px(img.image, to_px(x, y)) > 20
    # An empty list names nothing (the cloud's own labels are not drawn instead).
    bare = mapper.draw(index, pose, room_labels=[])
    assert all(_text_px(bare.image, to_px(x, y)) == 0 for _, x, y in labels)
    # An instance's name goes where it is told, not at the cloud's per-type centre.
    moved = mapper.draw(index, pose, room_labels=[("bedroom 2", 6.0, 0.6)])
    assert _text_px(moved.image, to_px(6.0, 0.6)) > 20 and _text_px(moved.image, to_px(2.0, 2.0)) == 0


class Recording:
    """The real renderer port; records the room labels each spatial map was asked to draw."""

    def __init__(self, port):
        self.port, self.asked = port, []

    def views(self, *a, **kw):
        return self.port.views(*a, **kw)

    def spatial_map(self, *a, **kw):
        self.asked.append(kw.get("room_labels"))
        return self.port.spatial_map(*a, **kw)


class First(Policy):
    """Takes the first candidate (the loop's mechanics are under test, not a policy)."""

    name = "first"

    def decide(self, ctx):
        return self._decision(ctx, ctx.candidates[0].index, "first")


def test_the_mission_loop_hands_the_graphs_room_names_to_the_renderer(house_map_cloud):
    robot = ROBOTS.create("sim", {"scene": "generated:0", "camera": {"width_px": 64, "height_px": 64, "hfov_deg": 90.0}})
    try:
        cloud = house_map_cloud  # generated:0's, sampled once for the session
        graph = build_scene_graph(cloud)
        renderer = Recording(MapRenderer(IndexedCloud(cloud), RENDERERS.create("numpy"), SpatialMapper()))
        for g, want in ((graph, True), (None, False)):
            renderer.asked.clear()
            robot.reset()
            loop = MissionLoop(robot=robot, predictor=PREDICTORS.create("geometric"), renderer=renderer,
                               policy=First(), emit=lambda *a, **k: None, label_names=cloud.label_names,
                               scene_graph=g)
            loop.run("m-rooms", "walk on", "local", MissionOptions(max_steps=1, anticipation=False))
            assert renderer.asked, "the spatial map was never asked for"
            if not want:
                assert renderer.asked == [None]  # no graph: the renderer names the cloud's labels
                continue
            got = renderer.asked[0]
            assert got and all(isinstance(r, MapRoomLabel) for r in got)
            floor0 = [r for r in graph.rooms if r.floor == 0]
            assert len(got) == len(floor0)
            # Same-type rooms are told apart by number, as in the prompt's text form.
            types = [r.room_type for r in floor0 if r.room_type]
            if len(types) > len(set(types)):
                assert any(r.name[-1].isdigit() for r in got)
    finally:
        robot.close()
