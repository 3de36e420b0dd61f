"""Mapper core: waypoint prediction, active exploration, regions, tour planning and execution.

Pure Python (numpy/scipy/networkx/open3d); the bus adapter in ``services/mapper/service.py`` only
decodes requests, calls these functions and encodes the results.
"""

from services.mapper.core.discovery import (
    DISCOVERY_PROFILES,
    Discovery,
    DiscoveryConfig,
    discover,
    discovery_config,
)
from services.mapper.core.errors import (
    ExplorationError,
    MapperError,
    PlanningError,
    PredictorError,
    TourExecutionError,
)
from services.mapper.core.execute import RegionRecording, TourRobot, execute_tour, execute_tours
from services.mapper.core.explorer import ExplorationConfig, ExplorationResult, Explorer, ExplorerRobot
from services.mapper.core.navgraph import GridGraph, NodeStatus
from services.mapper.core.predictor import (
    DEFAULT_PREDICTOR,
    PREDICTORS,
    GeometricPredictor,
    GeometricPredictorConfig,
    Prediction,
    WaypointPredictor,
    create_predictor,
)
from services.mapper.core.regions import RegionConfig, SceneMap, analyse
from services.mapper.core.tours import PlannedTour, TourConfig, TourPlanner

__all__ = [
    "DEFAULT_PREDICTOR", "DISCOVERY_PROFILES", "PREDICTORS", "Discovery", "DiscoveryConfig", "ExplorationConfig",
    "ExplorationError", "ExplorationResult", "Explorer", "ExplorerRobot", "GeometricPredictor",
    "GeometricPredictorConfig", "GridGraph", "MapperError", "NodeStatus", "PlannedTour",
    "PlanningError", "Prediction", "PredictorError", "RegionConfig", "RegionRecording", "SceneMap",
    "TourConfig", "TourExecutionError", "TourPlanner", "TourRobot", "WaypointPredictor",
    "analyse", "create_predictor", "discover", "discovery_config", "execute_tour", "execute_tours",
]
