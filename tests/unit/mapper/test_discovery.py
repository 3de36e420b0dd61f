import numpy as np
import pytest
from scipy.spatial import cKDTree

from shared.geometry import PinholeCamera
from shared.schemas import ExplorationOutcome, NavGraph, Tour

from services.mapper.core import (
    DiscoveryConfig,
    ExplorationConfig,
    NodeStatus,
    discover,
    execute_tours,
)
from services.mapper.tools.boxworld import BoxWorldRobot


@pytest.fixture(scope="module")
def run(rooms_discovery):
    return rooms_discovery


def test_exploration_covers_the_house(run):
    world, _, d = run
    assert d.result.finished
    g = d.result.graph
    nodes = g.positions(g.nodes_with(NodeStatus.VISITED, NodeStatus.COVERED))
    cells = world.reachable_cells(0.2, 0.25)
    dist, _ = cKDTree(nodes).query(cells)
    assert (dist < 2.0).mean() >= 0.6


def test_the_summary_is_what_the_exploration_event_carries(run):
    # The job turns the summary into the wire ExplorationOutcome (extra fields forbidden): a field added
    # on one side only failed every real exploration while the core's tests passed.
    outcome = ExplorationOutcome(**run[2].result.summary())
    assert outcome.finished and outcome.mapped_free_m2 > 0 and outcome.coverage_estimate > 0


def test_graph_edges_only_between_visited_nodes(run):
    _, _, d = run
    g = d.result.graph.g
    for u, v in g.edges:
        assert g.nodes[u]["status"] == NodeStatus.VISITED and g.nodes[v]["status"] == NodeStatus.VISITED
    msg = d.nav_graph()
    assert isinstance(msg, NavGraph)
    assert sum(n.visited for n in msg.nodes) == d.result.steps or sum(n.visited for n in msg.nodes) <= d.result.steps


def test_tours_cover_their_regions_and_keep_clearance(run):
    world, _, d = run
    assert d.tours
    for pt in d.tours:
        assert isinstance(pt.tour, Tour)
        assert pt.tour.coverage >= min(0.9, pt.achievable_coverage) - 1e-9
        for p in pt.tour.path_m:
            assert not world.blocked(p[0], p[1], 0.0, 0.2)
        assert pt.order_length_m <= pt.nn_length_m + 1.0  # lambda term may trade a little length


def test_deterministic(run):
    world, _, d = run
    robot = BoxWorldRobot(world, PinholeCamera(48, 48, 90.0))
    d2 = discover(robot)
    assert d2.result.visit_order == d.result.visit_order
    assert [len(t.tour.hubs_m) for t in d2.tours] == [len(t.tour.hubs_m) for t in d.tours]


def test_step_budget_is_respected(world):
    robot = BoxWorldRobot(world, PinholeCamera(32, 32, 90.0))
    d = discover(robot, DiscoveryConfig(exploration=ExplorationConfig(max_steps=3)))
    assert d.result.steps == 3 and not d.result.finished
    assert d.result.stop_reason == "steps" and d.result.step_budget == 3


def test_safety_budget_scales_with_the_discovered_area_and_still_builds_the_map(world, run):
    robot = BoxWorldRobot(world, PinholeCamera(32, 32, 90.0))
    cfg = ExplorationConfig(min_steps=2, steps_per_m2=0.1)
    d = discover(robot, DiscoveryConfig(exploration=cfg))
    r = d.result
    assert r.stop_reason == "steps" and not r.finished
    # The budget is not a fixed count: it grew with every square metre the graph reached.
    assert r.discovered_m2 > 10 and r.steps == r.step_budget == int(2 + 0.1 * r.discovered_m2)
    assert 0.0 < r.coverage_estimate < 1.0
    summary = r.summary()
    assert summary["stop_reason"] == "steps" and summary["coverage_estimate"] == round(r.coverage_estimate, 3)
    # The partial exploration still yields a scene map and tours.
    assert d.scene.regions and d.tours
    # The same world explored without the small budget, under the default one: it ends by itself. The
    # module's shared exploration (48 px, the default config) is that run; a second full exploration
    # here cost 2.2-2.5 s of CPU for the same claim.
    _, _, full = run
    assert full.result.finished and full.result.stop_reason == "exhausted"
    assert full.result.steps < full.result.step_budget


def test_the_exploration_keeps_the_depth_noise_its_robot_declared(world, run):
    """The tours plan on it (TourConfig.vis_radius_for): the largest any panorama declared."""

    class Noisy(BoxWorldRobot):
        def observe(self):
            pano = super().observe()
            return pano.model_copy(update={"depth_noise_rel": 0.02 if self.observations == 2 else 0.01})

    d = discover(Noisy(world, PinholeCamera(32, 32, 90.0)), DiscoveryConfig(exploration=ExplorationConfig(max_steps=3)))
    assert d.result.depth_noise_rel == 0.02
    assert run[2].result.depth_noise_rel == 0.0
    # The exploration's event carries it, and the touring progress says why the hubs stand closer.
    from services.mapper.core.exploration_job import tour_range_phrase
    from services.mapper.core.tours import TourConfig

    outcome = ExplorationOutcome(**d.result.summary())
    assert outcome.depth_noise_rel == 0.02
    assert tour_range_phrase(outcome, TourConfig()) == (
        " (hubs count what lies within 1.8 m: the robot declares depth noise 0.02)")
    assert tour_range_phrase(ExplorationOutcome(**run[2].result.summary()), TourConfig()) == ""


def test_unreachable_candidates_are_not_retried(world):
    class Stubborn(BoxWorldRobot):
        """Refuses every move east of x = 3 m."""

        def move_to(self, dx_m, dy_m):
            if self.pose.position_m[0] + dx_m > 3.0:
                self.moves += 1
                from shared.schemas import MoveResult, MoveStatus
                return MoveResult(status=MoveStatus.BLOCKED, pose=self.pose, travelled_m=0.0, steps=0)
            return super().move_to(dx_m, dy_m)

    robot = Stubborn(world, PinholeCamera(32, 32, 90.0))
    d = discover(robot)
    assert d.result.finished
    assert d.result.unreachable >= 1
    assert d.result.moves < 200


def test_execute_tours_records_frames_per_region(run):
    world, robot, d = run
    recs = execute_tours(robot, d.tours, d.scene)
    assert [r.region for r in recs] == [t.tour.region for t in d.tours]
    for rec, pt in zip(recs, d.tours, strict=True):
        assert rec.hubs_visited == len(pt.tour.hubs_m)
        assert len(rec.frames) >= 6 * rec.hubs_visited  # look-around frames at least
        assert rec.blocked_moves == 0
        assert np.allclose(rec.start_pose.position_m[:2], pt.tour.start_pose.position_m[:2], atol=0.06)
        idx = [f.index for f in rec.frames]
        assert len(idx) == len(set(idx))


def test_a_profile_is_data_and_overrides_merge_into_it_field_by_field():
    from services.mapper.core import DISCOVERY_PROFILES, discovery_config
    from services.mapper.core.discovery import CLUTTERED_SCAN

    assert discovery_config() == DiscoveryConfig()
    scan = discovery_config("cluttered-scan")
    assert DISCOVERY_PROFILES["cluttered-scan"] is CLUTTERED_SCAN
    assert scan.tours.paths_on == "walked" and scan.predictor_config["body_radius_m"] == 0.1
    # One nested knob overridden; the profile's other knobs at that level stay.
    mixed = discovery_config("cluttered-scan", {"exploration": {"visit_radius_m": 0.5}})
    assert mixed.exploration.visit_radius_m == 0.5 and mixed.exploration.min_progress_m == 0.1
    with pytest.raises(KeyError, match="cluttered-scan"):
        discovery_config("office")
