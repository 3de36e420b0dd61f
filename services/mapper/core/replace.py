"""The exploration re-placed by the pose graph (issue 33, item 2: "correct the exploration graph's
nodes and the hubs the same way, so tours, the map and the scene graph agree").

The explorer records every node, scan and trajectory pose where the localiser put it at the time:
the sequential placement of the panorama just taken, or the dead-reckoned pose of a move under the
correction then in effect. When the exploration ends the pose graph (posegraph.py) re-places the
panoramas, and the regions, the occupancy grids, the hubs, the tours and the scene graph are all
derived from those records afterwards. So the records follow the panoramas, by one rule:

- a panorama's scan, and the visited node it made, take its new placement;
- an observed node (a candidate, a map frontier and its way) is placed relative to its parent's
  panorama, so it turns and shifts with it (its offset was measured in that panorama's views);
- a trajectory pose between two panoramas takes the correction interpolated between theirs along
  the odometry path driven (as the tours' frames are interpolated in time: execute.replace_recordings),
  and the last panorama's after it.

Node ids stay (see GridGraph.move). A robot the localiser never corrected (no drift seen), or whose
panoramas all keep their placements, keeps every record bit for bit.
"""

from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np

from shared.geometry import interpolate_offsets, wrap_angle

from services.mapper.core.explorer import ExplorationResult
from services.mapper.core.localise import Correction, Localiser, NodeShift
from services.mapper.core.navgraph import NodeStatus

log = logging.getLogger(__name__)


def replace_exploration(result: ExplorationResult, localiser: Localiser, before: list[Correction]) -> NodeShift:
    """Move ``result``'s graph nodes, scans and trajectory with its panoramas' placements in
    ``localiser`` (after :meth:`Localiser.optimise`). ``before``: each localiser step's correction
    before that solve (the correction in effect after the panorama and any bridge of it, which the
    moves after it were handed under). Returns (and keeps on the localiser) what moved."""
    shift = NodeShift()
    localiser.node_shift = shift
    steps = localiser.steps
    if not localiser.drift_seen or not result.scans or len(before) != len(steps):
        return shift
    at_time: dict[float, int] = {}
    for k, s in enumerate(steps):
        at_time.setdefault(s.timestamp_s, k)
    ks = [at_time.get(sc.timestamp_s) for sc in result.scans]
    if any(k is None for k in ks) or any(sc.trajectory_index < 0 for sc in result.scans):
        log.warning("exploration not re-placed: %d of %d panoramas unknown to the localiser",
                    sum(k is None for k in ks), len(ks))
        return shift
    old = np.array([(sc.position_m[0], sc.position_m[1], sc.heading_rad) for sc in result.scans])
    new = np.array([(p.position_m[0], p.position_m[1], p.heading_rad)
                    for p in (steps[k].correction.pose(steps[k].odom) for k in ks)])
    dxy = new[:, :2] - old[:, :2]
    dyaw = wrap_angle(new[:, 2] - old[:, 2])
    if not (dxy.any() or dyaw.any()):
        return shift

    def moved(i: int, p: np.ndarray) -> np.ndarray:
        """``p`` (x, y, z) moved rigidly with scan ``i``: turned about it, then shifted."""
        c, s = math.cos(dyaw[i]), math.sin(dyaw[i])
        d = np.asarray(p, np.float64)[:2] - old[i, :2]
        return np.array([old[i, 0] + dxy[i, 0] + c * d[0] - s * d[1],
                         old[i, 1] + dxy[i, 1] + s * d[0] + c * d[1], float(p[2])])

    # The nodes: a visited node is where its first panorama was taken (its ``order``-th); an observed
    # one goes with the panorama of the visited node it was seen from.
    gg = result.graph
    scan_of = {n: int(a["order"]) - 1 for n, a in gg.g.nodes(data=True) if a["status"] == NodeStatus.VISITED}
    positions, way = {}, {}
    for n, a in gg.g.nodes(data=True):
        i = scan_of.get(n)
        if i is None:
            i = scan_of.get(a.get("parent"))
        if i is None:  # no visited parent (none in an exploration): the nearest panorama
            i = int(np.argmin(np.hypot(*(old[:, :2] - a["pos"][:2]).T)))
        positions[n] = moved(i, a["pos"])
        if a.get("way"):
            way[n] = [moved(i, w) for w in a["way"]]
    shifts = np.array([math.hypot(*(positions[n][:2] - gg.pos(n)[:2])) for n in positions])
    gg.move(positions)
    for n, w in way.items():
        gg.g.nodes[n]["way"] = w
    result.scans = [dataclasses.replace(sc, position_m=np.array([new[i, 0], new[i, 1], sc.position_m[2]]),
                                        heading_rad=float(new[i, 2]))
                    for i, sc in enumerate(result.scans)]
    result.trajectory_m = _replace_trajectory(result.trajectory_m, result.scans, [steps[k] for k in ks],
                                              [before[k] for k in ks])
    shift.nodes_moved = int(np.count_nonzero(shifts))
    shift.median_m = float(np.median(shifts)) if len(shifts) else 0.0
    shift.max_m = float(shifts.max()) if len(shifts) else 0.0
    log.info("exploration re-placed by the pose graph: %d of %d nodes moved (median %.3f m, max %.3f m)",
             shift.nodes_moved, len(shifts), shift.median_m, shift.max_m)
    return shift


def _replace_trajectory(traj: np.ndarray, scans: list, steps: list, before: list[Correction]) -> np.ndarray:
    """The trajectory with each panorama's entry at its (new) scan position and the moves between two
    panoramas under the correction interpolated between theirs along the odometry path."""
    out = np.array(traj, np.float64, copy=True)
    if not len(out):
        return out
    cut = [sc.trajectory_index for sc in scans] + [len(out)]
    for i, sc in enumerate(scans):
        a, b = cut[i], cut[i + 1]
        out[a, :2] = sc.position_m[:2]
        if b <= a + 1:
            continue
        b_old = before[i]
        # Odometry positions of the panorama, the moves after it and the next panorama.
        odo = [np.asarray(steps[i].odom.position_m[:2], np.float64)]
        odo += [out[j, :2] - (b_old.dx_m, b_old.dy_m) for j in range(a + 1, b)]
        c_a = steps[i].correction
        ends = [(c_a.dx_m, c_a.dy_m, c_a.dyaw_rad)]
        if i + 1 < len(scans):
            odo.append(np.asarray(steps[i + 1].odom.position_m[:2], np.float64))
            c_b = steps[i + 1].correction
            ends.append((c_b.dx_m, c_b.dy_m, c_b.dyaw_rad))
        path = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(np.array(odo), axis=0).T))])
        if len(ends) == 2 and path[-1] > 0.0:
            c = interpolate_offsets([0.0, path[-1]], np.array(ends), path[1:b - a])
        else:
            c = np.repeat(np.array(ends[:1]), b - a - 1, axis=0)
        out[a + 1:b, :2] = np.array(odo[1:b - a]) + c[:, :2]
    return out
