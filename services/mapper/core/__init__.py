"""Mapper core: waypoint prediction, active exploration, regions, tour planning and execution.

Pure Python (numpy/scipy/networkx/open3d); the bus adapter in ``services/mapper/service.py`` only
decodes requests, calls these functions and encodes the results.

The names below are imported from their submodule on first use (:func:`shared.lazy.lazy_exports`): the
mapper process needs only the predictor to serve, and exploration (scipy, networkx: ~0.6 s of CPU) loads
with its first job.
"""

from shared.lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "discovery": ("DISCOVERY_PROFILES", "Discovery", "DiscoveryConfig", "discover", "discovery_config"),
    "errors": ("ExplorationError", "MapperError", "PlanningError", "PredictorError", "TourExecutionError"),
    "execute": ("RegionRecording", "TourRobot", "execute_tour", "execute_tours"),
    "explorer": ("ExplorationConfig", "ExplorationResult", "Explorer", "ExplorerRobot"),
    "navgraph": ("GridGraph", "NodeStatus"),
    "predictor": ("DEFAULT_PREDICTOR", "PREDICTORS", "GeometricPredictor", "GeometricPredictorConfig", "Prediction",
                  "WaypointPredictor", "create_predictor"),
    "regions": ("RegionConfig", "SceneMap", "analyse"),
    "tours": ("PlannedTour", "TourConfig", "TourPlanner"),
})
