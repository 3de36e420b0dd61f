"""Algorithm 1 end to end: explore, find stairs and regions, plan one tour per region."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

from pydantic import BaseModel, ConfigDict, Field

from shared.schemas import NavGraph, Tour

from services.mapper.core.explorer import ExplorationConfig, ExplorationResult, ExplorationStep, Explorer, ExplorerRobot
from services.mapper.core.localise import LocalisedRobot, Localiser, LocaliserConfig
from services.mapper.core.predictor import DEFAULT_PREDICTOR, PREDICTORS, WaypointPredictor
from services.mapper.core.regions import RegionConfig, SceneMap, analyse
from services.mapper.core.replace import replace_exploration
from services.mapper.core.tours import PlannedTour, TourConfig, TourPlanner


log = logging.getLogger(__name__)

#: Exploration's default predictor knobs (see DiscoveryConfig.predictor_config). No escape sweep
#: (GeometricPredictorConfig.escape_clearance_m): a mission boxed in at its start has nowhere to go
#: back to, but an exploration's dead end is left along the graph to the next frontier, and passages
#: narrower than the body are the frontier planner's narrow body's (issue 21). With the escape on, it
#: fired at 4 of the 231 panoramas of generated:3:floors=2 (stair landings, a hall corner); their
#: frontiers reordered the walk and both two-floor houses of the seed-0 set got other maps
#: (generated:11:floors=2 948,056 -> 933,671 points), while the one-floor ones stayed byte-identical.
WIDE_EXPLORATION = {"max_candidates": 10, "nms_angle_deg": 15.0, "escape_clearance_m": None}


#: Discovery knobs for cluttered real scans (Replica office0: a few m2 of passages between desks,
#: some narrower than the default predictor body). The predictor's body is the simulator agent's
#: (0.1 m radius instead of the 0.2 m default margin) and nodes sit closer together, so that short
#: partial moves along a twisting passage still add nodes. Measured with 64 px views (share of the
#: reachable area within 1.5 m of a visited node / panoramas): defaults 71 % / 2, this 100 % / 13.
#: Tours run where the robot itself walked: the scans miss clutter that the agent's body meets
#: (map-planned paths: 69 % of their samples on the simulator's walkable grid; walked: 100 %).
#: In a generated house, whose box furniture the scans see whole, walked tours are 4-8 times
#: longer than map-planned ones (generated:0: 289 m against 65 m), so the default stays "map".
CLUTTERED_SCAN: dict = {
    "predictor_config": {**WIDE_EXPLORATION, "body_radius_m": 0.1},
    "exploration": {"visit_radius_m": 0.4, "min_progress_m": 0.1, "frontier_merge_m": 0.25},
    "tours": {"paths_on": "walked"},
}


#: Named discovery profiles (an exploration's ``options.profile``): the scene kind a user knows and
#: the mapper cannot tell from its scans. ``options.discovery`` overrides fields on top of one.
DISCOVERY_PROFILES: dict[str, dict] = {"default": {}, "cluttered-scan": CLUTTERED_SCAN}


def discovery_config(profile: str = "default", overrides: dict | None = None) -> DiscoveryConfig:
    """The :class:`DiscoveryConfig` of a named profile with ``overrides`` merged in (nested dicts field
    by field). Raises ``KeyError`` for an unknown profile and pydantic's ``ValidationError`` for bad
    overrides."""
    if profile not in DISCOVERY_PROFILES:
        raise KeyError(f"unknown discovery profile {profile!r}; known: {', '.join(DISCOVERY_PROFILES)}")

    def merge(base: dict, top: dict) -> dict:
        out = dict(base)
        for k, v in top.items():
            out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
        return out

    return DiscoveryConfig.model_validate(merge(DISCOVERY_PROFILES[profile], overrides or {}))


class DiscoveryConfig(BaseModel):
    """Everything Algorithm 1 takes; the defaults are the paper's."""

    model_config = ConfigDict(extra="forbid")

    predictor: str = DEFAULT_PREDICTOR
    # Knobs of the exploration's predictor. The planner navigates with the CWP contract (5
    # candidates, 30 deg NMS: the backend's defaults, ``predictor_config=None``); exploration
    # defaults to a wider setting, because one narrow doorway or stairwell door missed by the
    # 5-candidate NMS cuts off everything behind it. Measured with the real simulator
    # (bench/mapper.py; share of the reachable area within 1.5 m of a visited node):
    #                         64 px: CWP          wide (10, 15 deg) | 96 px: CWP         wide
    #   generated:0                 99.4 % / 119  100 % / 140       |  97.0 % / 110  100 % / 135
    #   generated:1:floors=2        98.9 % / 136  99.9 % / 181      |  48.2 % / 64   99.7 % / 151
    #   generated:2                 99.3 % / 107  97.4 % / 133      |
    #   generated:3:floors=2        98.3 % / 132  99.4 % / 160      |
    # (coverage / panoramas). The contract is ~20 % cheaper but once failed to find the stairs.
    predictor_config: dict | None = Field(default_factory=lambda: dict(WIDE_EXPLORATION))
    exploration: ExplorationConfig = Field(default_factory=ExplorationConfig)
    regions: RegionConfig = Field(default_factory=RegionConfig)
    tours: TourConfig = Field(default_factory=TourConfig)
    # The mapper's own map <- odom correction (localise.py): exact poses pass through it unchanged.
    localisation: LocaliserConfig = Field(default_factory=LocaliserConfig)


@dataclass
class Discovery:
    """The outcome of Algorithm 1: the exploration, the scene map (floors, stairs, regions) and
    one planned tour per region, with the wall time of each phase."""

    result: ExplorationResult
    scene: SceneMap
    tours: list[PlannedTour]
    timings_s: dict[str, float]

    def nav_graph(self) -> NavGraph:
        return self.result.graph.to_schema(self.scene.stairs)

    def tour_messages(self) -> list[Tour]:
        return [t.tour for t in self.tours]


def discover(robot: ExplorerRobot, config: DiscoveryConfig | None = None,
             predictor: WaypointPredictor | None = None, checkpoint: Callable[[], None] | None = None,
             on_step: Callable[[ExplorationStep], None] | None = None) -> Discovery:
    """Explore with ``robot``, then find stairs, floors and regions and plan one tour per region.

    ``predictor`` overrides the one named in ``config`` (e.g. a shared, already loaded backend).
    ``checkpoint`` is called before every exploration step and between the phases; it raises to
    abandon the discovery (a cancelled exploration job stops within one step); ``on_step`` hears
    where the exploration stands after every panorama.
    """
    cfg = config or DiscoveryConfig()
    pred = predictor or PREDICTORS.create(cfg.predictor, cfg.predictor_config or None)
    t0 = time.perf_counter()
    if cfg.localisation.enabled and not isinstance(robot, LocalisedRobot):
        robot = LocalisedRobot(robot, Localiser(cfg.localisation), bridge=True)
    result = Explorer(pred, cfg.exploration).explore(robot, checkpoint, on_step)
    if isinstance(robot, LocalisedRobot):
        # The panoramas' poses made globally consistent (loop closures) before the tours start from
        # them; the graph, scans and trajectory move with them only where the localiser's config says
        # (off by default: see LocaliserConfig.replace_exploration).
        replace = robot.localiser.config.replace_exploration  # the localiser's own config (it may come wrapped)
        before = [s.correction for s in robot.localiser.steps] if replace else []
        robot.localiser.optimise()
        if replace:
            replace_exploration(result, robot.localiser, before)
    t1 = time.perf_counter()
    if checkpoint is not None:
        checkpoint()
    scene = analyse(result, cfg.regions)
    if isinstance(robot, LocalisedRobot):
        scene.localiser = robot.localiser
        # Whether the localiser placed anything is otherwise invisible until the map's drift record
        # (a robot whose panoramas give it no scan, say, is quietly dead-reckoned).
        ns = robot.localiser.node_shift
        log.info("localisation over the exploration: %s; %d bridge panoramas (%.1f m driven for them); "
                 "%d graph nodes moved with the panoramas (median %.3f m, max %.3f m)",
                 robot.localiser.report(), robot.bridges, robot.bridge_m, ns.nodes_moved, ns.median_m, ns.max_m)
    t2 = time.perf_counter()
    if checkpoint is not None:
        checkpoint()
    tours = TourPlanner(cfg.tours).plan(scene)
    t3 = time.perf_counter()
    return Discovery(result, scene, tours, {
        "explore": t1 - t0, "analyse": t2 - t1, "plan": t3 - t2,
        "set_cover_2opt": sum(t.plan_s for t in tours)})
