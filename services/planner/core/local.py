"""Run missions in-process (no bus): the simulator, the predictor and the renderer core as ports.

Used by benchmarks and tests of the navigation stack; the planner service runs the same
:class:`MissionLoop` with bus clients instead.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shared.schemas import MissionOptions

from .mission import MissionLoop, MissionOutcome
from .policy import POLICIES


@dataclass
class LocalStack:
    robot: object  # services.robot_io.core.Robot
    predictor: object  # services.mapper.core.WaypointPredictor
    renderer: object  # services.renderer.core.MapRenderer
    label_names: dict[int, str]
    scene_graph: object | None = None  # shared.schemas.SceneGraph of the map (libs.scenegraph builds it)

    def run(self, instruction: str, opts: MissionOptions, mission_id: str = "local") -> MissionOutcome:
        policy = POLICIES.create(opts.policy, opts.policy_config or None)
        try:
            loop = MissionLoop(robot=self.robot, predictor=self.predictor, renderer=self.renderer, policy=policy,
                               emit=lambda *a, **k: None, label_names=self.label_names,
                               scene_graph=self.scene_graph)
            return loop.run(mission_id, instruction, "local", opts)
        finally:
            policy.close()


def episode_options(ep, policy: str, **kw) -> MissionOptions:
    """Mission options for a generated or R2R-CE episode (start, goal and reference path)."""
    return MissionOptions(policy=policy, start_pose=ep.start_pose, goal_m=tuple(map(float, ep.goal_m)),
                          reference_path_m=[tuple(map(float, p)) for p in np.asarray(ep.reference_path_m)], **kw)
