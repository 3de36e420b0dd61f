"""A straight move that a jamb stops in its first decimetres, tried again a few centimetres aside.

The explorer and the tours plan every move on the scans' 10 cm free-space map and send the robot
straight along it. Through a passage barely wider than the robot, a line a few centimetres off the
passage's middle grazes a jamb: a robot whose depth is noisy, or whose odometry drifted, sees the
passage's sides a cell off. generated:2013:floors=2 (noisy, seed 0) so lost its stairs and the
whole upper floor: the way there is a lane 0.3 m wide beside a cabinet, the noisy map put its
middle 7 cm west of the true one, the move down it stopped after 0.13 m on the cabinet's corner,
and the exploration gave the lane up as unreachable. The noise-free robot had walked down it.

So a move blocked before ``early_m`` is taken again, shifted sideways: back to where it started,
a sidestep of each offset in turn (left, then right), the same displacement from there, and the
sidestep undone at the end, so the robot stands where the move was meant to end (a graph node's
position stays true, as does the straight edge to it within the offset). A move that none of the
offsets gets through ends back where it started, reported blocked after the first try's metres,
as if it had not been tried again. Moves blocked further on are left to the caller: there the
robot got somewhere, and the caller takes a panorama where it stopped.

Only where the map itself says the way is narrow: a retry that fails is motion too, and a drifting
robot's odometry drifts over every shift and every try. Tried on every early-blocked move (stop 58),
the noisy explorations of generated:0 changed (140 panoramas and 303 moves against 154 and 398, no
retry getting through anywhere) and the map came out worse. So the explorer sidesteps only on its way
to a frontier that only the narrow body reaches (explorer.py), and the tours and later walks only
along the edges laid on such a way (the edges' ``narrow`` mark): a plain wall is never tried aside.
"""

from __future__ import annotations

import logging
import math
from typing import Annotated, Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from shared.schemas import MoveResult, MoveStatus

log = logging.getLogger(__name__)


class SidestepConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    # Sideways shifts tried, each to the left and then to the right of the move; () turns it off.
    # Half a map cell and one: the free-space map places a passage's sides to within a cell. A
    # shift of half a metre is no longer the same passage.
    offsets_m: tuple[Annotated[float, Field(gt=0.0, le=0.5)], ...] = Field((0.05, 0.1), max_length=8)
    # Only a move blocked before this many metres is tried again (the explorer's min_progress_m: a
    # blocked move that got no further adds no node, so the caller has nothing to lose).
    early_m: float = Field(0.3, ge=0.0, le=2.0)
    # A move shorter than this is not tried again (the caller's own small corrections).
    min_move_m: float = Field(0.3, ge=0.0, le=2.0)


def move_sidestepping(robot: Any, dx_m: float, dy_m: float, cfg: SidestepConfig) -> MoveResult:
    """``robot.move_to(dx_m, dy_m)``, tried again shifted sideways where it is blocked early (see
    the module docstring). Got through: ``travelled_m`` is the move's length (the sidesteps are the
    robot's own detour); else the first try's metres. ``steps`` counts every try's. Only for moves
    the map holds as narrow (the module docstring says why)."""
    start = robot.pose.xyz[:2].copy()
    res = robot.move_to(dx_m, dy_m)
    length = math.hypot(dx_m, dy_m)
    if (res.status == MoveStatus.REACHED or not cfg.offsets_m or res.travelled_m >= cfg.early_m
            or length < cfg.min_move_m):
        return res
    steps = res.steps
    if not _go(robot, start):
        return res  # could not get back to the start: the caller handles the robot where it is
    ux, uy = dx_m / length, dy_m / length
    for off in cfg.offsets_m:
        for side in (1.0, -1.0):
            sx, sy = -uy * off * side, ux * off * side  # to the left of the move, then to the right
            shift = robot.move_to(sx, sy)
            steps += shift.steps
            if shift.status == MoveStatus.REACHED:
                along = robot.move_to(dx_m, dy_m)
                steps += along.steps
                if along.status == MoveStatus.REACHED:
                    back = robot.move_to(-sx, -sy)
                    steps += back.steps
                    log.info("a move blocked after %.2f m got through %.2f m to the %s", res.travelled_m, off,
                             "left" if side > 0 else "right")
                    return MoveResult(status=MoveStatus.REACHED, pose=robot.pose, travelled_m=length, steps=steps)
            if not _go(robot, start):
                return MoveResult(status=MoveStatus.BLOCKED, pose=robot.pose, travelled_m=res.travelled_m,
                                  steps=steps)
    return MoveResult(status=MoveStatus.BLOCKED, pose=robot.pose, travelled_m=res.travelled_m, steps=steps)


def _go(robot: Any, xy: np.ndarray, tolerance_m: float = 0.02) -> bool:
    """Back to ``xy`` by a straight move (the way the robot came): True once within the tolerance."""
    d = xy - robot.pose.xyz[:2]
    if math.hypot(*d) > 1e-3:
        robot.move_to(float(d[0]), float(d[1]))
    return bool(math.hypot(*(xy - robot.pose.xyz[:2])) <= tolerance_m)
