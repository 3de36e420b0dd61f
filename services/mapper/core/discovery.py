"""Algorithm 1 end to end: explore, find stairs and regions, plan one tour per region."""

from __future__ import annotations

import time
from dataclasses import dataclass

from pydantic import BaseModel, ConfigDict, Field

from shared.schemas import NavGraph, Tour

from services.mapper.core.explorer import ExplorationConfig, ExplorationResult, Explorer, ExplorerRobot
from services.mapper.core.predictor import DEFAULT_PREDICTOR, PREDICTORS, WaypointPredictor
from services.mapper.core.regions import RegionConfig, SceneMap, analyse
from services.mapper.core.tours import PlannedTour, TourConfig, TourPlanner


class DiscoveryConfig(BaseModel):
    """Everything Algorithm 1 takes; the defaults are the paper's."""

    model_config = ConfigDict(extra="forbid")

    predictor: str = DEFAULT_PREDICTOR
    # Exploration wants more, narrower candidates than the planner's CWP contract (5, 30 deg NMS):
    # with 5 the DFS misses doorways seen at an angle and covers ~30-45 % of a generated house,
    # with 10 at 15 deg it covers ~99 % (bench/mapper.py). Same backend, only its knobs differ.
    predictor_config: dict = Field(
        default_factory=lambda: {"max_candidates": 10, "nms_angle_deg": 15.0}
    )
    exploration: ExplorationConfig = Field(default_factory=ExplorationConfig)
    regions: RegionConfig = Field(default_factory=RegionConfig)
    tours: TourConfig = Field(default_factory=TourConfig)


@dataclass
class Discovery:
    result: ExplorationResult
    scene: SceneMap
    tours: list[PlannedTour]
    timings_s: dict[str, float]

    def nav_graph(self) -> NavGraph:
        return self.result.graph.to_schema(self.scene.stairs)

    def tour_messages(self) -> list[Tour]:
        return [t.tour for t in self.tours]


def discover(robot: ExplorerRobot, config: DiscoveryConfig | None = None,
             predictor: WaypointPredictor | None = None) -> Discovery:
    cfg = config or DiscoveryConfig()
    pred = predictor or PREDICTORS.create(cfg.predictor, cfg.predictor_config or None)
    t0 = time.perf_counter()
    result = Explorer(pred, cfg.exploration).explore(robot)
    t1 = time.perf_counter()
    scene = analyse(result, cfg.regions)
    t2 = time.perf_counter()
    tours = TourPlanner(cfg.tours).plan(scene)
    t3 = time.perf_counter()
    return Discovery(result, scene, tours, {
        "explore": t1 - t0, "analyse": t2 - t1, "plan": t3 - t2,
        "set_cover_2opt": sum(t.plan_s for t in tours)})
