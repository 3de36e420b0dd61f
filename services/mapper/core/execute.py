"""Tour execution: drive the robot along each planned tour and record each region's video.

The robot walks to the tour's start over traversed graph edges (known to be passable), turns to
the start heading, and then, inside ``robot.recording(sink)``, follows the refined path with a
look-around at every hub. The frames of a region are returned with the pose at which recording
started (the region's local origin for the reconstructor).
"""

from __future__ import annotations

import contextlib
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import networkx as nx
import numpy as np

from shared.geometry import interpolate_offsets, wrap_angle
from shared.schemas import Frame, MoveResult, MoveStatus, Panorama, Pose

from services.mapper.core.errors import TourExecutionError
from services.mapper.core.localise import Correction, LocalisedRobot
from services.mapper.core.navgraph import NodeStatus
from services.mapper.core.occupancy import line_of_sight
from services.mapper.core.regions import SceneMap
from services.mapper.core.sidestep import SidestepConfig, move_sidestepping
from services.mapper.core.tours import PlannedTour

log = logging.getLogger(__name__)


@runtime_checkable
class TourRobot(Protocol):
    """What tour execution needs from a robot (robot-io's port, its bus client, the box world)."""

    @property
    def pose(self) -> Pose: ...

    def observe(self) -> Panorama: ...

    def move_to(self, dx_m: float, dy_m: float) -> MoveResult: ...

    def turn(self, angle_rad: float) -> Any: ...

    def look_around(self) -> list[Frame]: ...

    def recording(self, sink: Callable[[Frame], None], rate_hz: float = ...) -> contextlib.AbstractContextManager: ...


@dataclass
class RegionRecording:
    region: int
    start_pose: Pose
    frames: list[Frame] = field(default_factory=list)
    hubs_visited: int = 0
    blocked_moves: int = 0
    travelled_m: float = 0.0
    # The map <- odom correction in effect from each robot time on while recording (start first):
    # the frames above already carry it; a robot that publishes its frames itself (robot-io over the
    # bus) sends odometry poses, and these say how to correct them.
    corrections: list[tuple[float, Correction]] = field(default_factory=list)
    # True once the pose graph re-placed the recording (replace_recordings): a frame's correction is
    # interpolated in time between the entries around it.
    interpolated: bool = False


def execute_tours(
    robot: TourRobot,
    tours: list[PlannedTour],
    scene: SceneMap | None = None,
    rate_hz: float = 5.0,
    on_recording: Callable[[RegionRecording], None] | None = None,
    on_skip: Callable[[PlannedTour, TourExecutionError], None] | None = None,
    checkpoint: Callable[[], None] | None = None,
    sidestep: SidestepConfig | None = None,
) -> list[RegionRecording]:
    """Drive every tour in order; returns one recording per tour that could be driven.

    A tour whose start cannot be reached (a doorway the planner thought wider, say) is tried once
    more after all the others, from wherever they left the robot; only then is it skipped and
    reported through ``on_skip``: one region short is a smaller map, not a failed exploration.
    (generated:2012, noisy: the exploration ended beyond a narrow passage that the transits could
    not walk back through, and the first three tours were skipped; the robot got out on the way to
    the fourth.)
    Only when no tour at all can be driven is that an error. ``checkpoint`` is called before every
    move; it raises to abandon the tours (a cancelled job), a recording under way being stopped.
    ``sidestep`` (the exploration's; its defaults when None) retries a transit along an edge laid
    through a narrow passage a few centimetres aside where a jamb stops it early, as the exploration
    walked it (sidestep.py).
    """
    out = []
    if scene is not None and scene.localiser is not None and not isinstance(robot, LocalisedRobot):
        robot = LocalisedRobot(robot, scene.localiser)
    later: list[PlannedTour] = []
    for last_try, todo in ((False, tours), (True, later)):
        for pt in todo:
            try:
                rec = execute_tour(robot, pt, scene, rate_hz, checkpoint=checkpoint, sidestep=sidestep)
            except TourExecutionError as exc:
                if not last_try:
                    log.info("region %d out of reach (%s): trying it again after the other tours", pt.tour.region, exc)
                    later.append(pt)
                    continue
                log.warning("skipping region %d: %s", pt.tour.region, exc)
                if on_skip is not None:
                    on_skip(pt, exc)
                continue
            out.append(rec)
            if on_recording is not None:
                on_recording(rec)
    if tours and not out:
        raise TourExecutionError(f"none of the {len(tours)} tours could be driven")
    localiser = getattr(robot, "localiser", None)
    if localiser is not None and out:
        replace_recordings(out, localiser)
    return out


def replace_recordings(recs: list[RegionRecording], localiser: Any) -> None:
    """Every recorded frame re-placed by the final pose graph (posegraph.py): solved once more over
    all the panoramas (the tours' own among them), each frame takes the map <- odom correction
    interpolated in time between the panoramas around it, and each recording's corrections become
    that schedule (for a robot that publishes its frames itself: the reconstructor interpolates the
    same way). Without a graph, with frames registered one by one (their corrections are not in the
    schedule), or for a robot the localiser never corrected (an exact one: bit for bit), the
    recordings stay as they are."""
    if localiser.graph is None or localiser.config.frames.enabled or not localiser.drift_seen:
        return
    rep = localiser.optimise(final=True)
    log.info("pose graph before the build: %s", None if rep is None else rep.summary())
    times, offsets = localiser.schedule()
    for rec in recs:
        if not rec.corrections:
            continue
        t0 = rec.corrections[0][0]
        first = max(0, int(np.searchsorted(times, t0, side="right")) - 1)
        last = len(times)
        if rec.frames:  # up to the first panorama after the last frame
            last = min(len(times), int(np.searchsorted(times, rec.frames[-1].timestamp_s, side="left")) + 1)
        t, o = times[first:last], offsets[first:last]
        applied_t = np.array([c[0] for c in rec.corrections])
        if rec.frames:
            ts = np.array([f.timestamp_s for f in rec.frames])
            new = interpolate_offsets(t, o, ts)
            old_k = np.maximum(np.searchsorted(applied_t, ts, side="right") - 1, 0)
            rec.frames = [Correction(*new[k]).frame(rec.corrections[old_k[k]][1].odom_frame(f))
                          for k, f in enumerate(rec.frames)]
        start_odom = rec.corrections[0][1].odom(rec.start_pose)
        rec.corrections = [(float(tk), Correction(*map(float, ok))) for tk, ok in zip(t, o)]
        rec.start_pose = rec.corrections[0][1].pose(start_odom)
        rec.interpolated = True


def execute_tour(robot: TourRobot, pt: PlannedTour, scene: SceneMap | None = None, rate_hz: float = 5.0,
                 checkpoint: Callable[[], None] | None = None,
                 sidestep: SidestepConfig | None = None) -> RegionRecording:
    check = checkpoint or _no_checkpoint
    side = SidestepConfig() if sidestep is None else sidestep
    tour = pt.tour
    start = np.asarray(tour.start_pose.position_m)
    path = np.asarray(tour.path_m)
    check()
    if scene is not None:
        _transit(robot, scene, start, check, sidestep=side)
    relocalise = getattr(robot, "relocalise", None)
    if relocalise is not None:
        # Re-localised where the transit ended, the tour's start reached by the map, not by odometry:
        # a drifted robot missed one-hub regions by more than the 0.75 m it may start short.
        relocalise()
    first = _reach_tour_start(robot, tour.region, path if len(path) else start[None], scene, check, sidestep=side)
    turn = float(wrap_angle(tour.start_pose.heading_rad - robot.pose.heading_rad))
    if abs(turn) > 1e-3:
        robot.turn(turn)
    frames: list[Frame] = []
    seen: set[int] = set()

    def sink(frame: Frame) -> None:
        seen.add(frame.index)
        frames.append(frame)

    rec = RegionRecording(region=tour.region, start_pose=robot.pose)
    localiser = getattr(robot, "localiser", None)

    def note_correction() -> None:
        if localiser is not None and (not rec.corrections or rec.corrections[-1][1] != localiser.correction):
            # From the robot time of the panorama that set it (the frames' clock, on any robot).
            since = localiser.steps[-1].timestamp_s if localiser.steps else 0.0
            rec.corrections.append((float(since), localiser.correction))

    hubs = set(pt.hub_path_index)
    # Hubs before the first reachable sample are looked around from there, their nearest
    # reachable place on the path.
    if any(k < first for k in hubs):
        hubs.add(first)
    note_correction()
    moved_since_hub = False
    with robot.recording(sink, rate_hz):
        for k in range(first, len(path)):
            check()  # inside the recording: abandoning it here stops the recording on the way out
            if k > first:
                cur = robot.pose.xyz
                d = path[k, :2] - cur[:2]
                if np.hypot(*d) > 1e-3:
                    moved_since_hub = True
                    res = robot.move_to(float(d[0]), float(d[1]))
                    rec.travelled_m += res.travelled_m
                    if res.status != MoveStatus.REACHED:
                        rec.blocked_moves += 1
            if k in hubs:
                if relocalise is not None:
                    relocalise()
                    note_correction()
                for f in robot.look_around():
                    # Some robots also emit look-around frames through the sink: keep one copy.
                    if f.index not in seen:
                        sink(f)
                if relocalise is not None:
                    # The look-around turned the robot some 480 deg: a panorama after it measures the
                    # heading drift that the frames until the next hub would otherwise carry.
                    relocalise(after_look_around=True)
                    note_correction()
                rec.hubs_visited += 1
                moved_since_hub = False
        if moved_since_hub and relocalise is not None:
            # The path went on past the last hub: a panorama where it ends gives that stretch's frames a
            # fix after them too (LocaliserConfig.relocalise_at_tour_end), instead of the last hub's alone.
            relocalise(tour_end=True)
            note_correction()
    # The sink and the look-around return interleave: the reconstructor wants the video in time order.
    rec.frames = sorted(frames, key=lambda f: (f.timestamp_s, f.index))
    log.info(
        "region %d: %d frames, %d hubs, %.1f m, %d blocked",
        tour.region, len(frames), rec.hubs_visited, rec.travelled_m, rec.blocked_moves,
    )
    return rec


def _no_checkpoint() -> None:
    pass


def _reach_tour_start(robot: TourRobot, region: int, path: np.ndarray, scene: SceneMap | None,
                      check: Callable[[], None], samples: tuple[int, ...] = (0, 1, 2, 3, 4, 6, 8, 12),
                      short_m: float = 0.75, sidestep: SidestepConfig | None = None) -> int:
    """Move straight to the tour's start, or, where the simulator (or the world) has no room for
    the robot there, to the first of the later path ``samples`` it can reach, each approached over
    the exploration's walked edges from the node nearest it: the index of the sample reached. A
    tour's hubs are chosen on the scans' free-space map, which misses desk edges and clutter; a
    1,000 m2 building lost 2 of its 40 regions to a start inside a piece of furniture, the whole
    region unrecorded for one unreachable pose. When no sample can be reached (a region of one
    hub has a path of one sample), the tour starts where the robot stopped if that is within
    ``short_m`` of a sample: a look-around a few decimetres off the hub sees the same room.
    ``sidestep`` goes to every transit (:func:`_transit`)."""
    tried = [k for k in samples if k < len(path)]
    travelled = 0.0
    for n, k in enumerate(tried):
        if n and scene is not None:
            _transit(robot, scene, path[k], check, sidestep=sidestep)
        d = path[k, :2] - robot.pose.xyz[:2]
        if np.hypot(*d) <= 0.05:
            return k
        check()
        res = robot.move_to(float(d[0]), float(d[1]))
        travelled += res.travelled_m
        if res.status == MoveStatus.REACHED:
            if k:
                log.info("region %d: tour start out of reach; starting at path sample %d", region, k)
            return k
    gap = np.hypot(*(path[tried, :2] - robot.pose.xyz[:2]).T)
    if len(gap) and gap.min() <= short_m:
        k = tried[int(np.argmin(gap))]
        log.info("region %d: tour start out of reach; starting %.2f m short of path sample %d", region, gap.min(), k)
        return k
    if scene is not None and _from_a_node_that_sees_it(robot, region, path[0], scene, check, sidestep):
        log.info("region %d: tour start reached from the nearest node that sees it", region)
        return 0
    raise TourExecutionError(
        f"region {region}: could not reach the tour start nor {len(tried) - 1} later path samples ({travelled:.2f} m)"
    )


def _transit(robot: TourRobot, scene: SceneMap, goal_m: np.ndarray, check: Callable[[], None] = _no_checkpoint,
             replan_attempts: int = 5, sidestep: SidestepConfig | None = None) -> None:
    """Walk over traversed edges from the node nearest the robot to the node nearest the goal.

    An edge walked one way during exploration may not be walkable back the same straight way (the
    simulator slid along a bed's corner into a nook between the bed and a wardrobe, and the
    straight line back clips that corner): a blocked edge is left out, the robot steps back to the
    node it came from, and the route is planned again, as exploration does. A drifting robot first
    re-localises where the move stopped and tries the edge once more (:func:`_relocalised`). When
    dropping an edge cuts the robot's part of the graph off from the goal's, it rejoins it by a
    direct move from where it stands (:func:`_rejoin`), else where the two parts meet
    (:func:`_cross_where_parts_meet`). With ``sidestep``, an edge the exploration laid through a
    narrow passage (``GridGraph.narrow``) that a jamb stops early is first tried a few centimetres
    aside, as the exploration may have walked it (sidestep.py); every other edge is walked as before.
    ``check`` is called before every move (a cancelled exploration stops here).
    """
    g = scene.result.graph
    visited = g.nodes_with(NodeStatus.VISITED)
    if not visited:
        return
    pos = g.positions(visited)

    def nearest(p):
        d = np.linalg.norm(pos[:, :2] - p[:2], axis=1) + 3.0 * np.abs(pos[:, 2] - p[2])
        return visited[int(np.argmin(d))]

    a = nearest(robot.pose.xyz)
    b = nearest(goal_m)
    edges = nx.Graph(g.traversed())  # a copy: blocked edges are dropped for this transit only
    dropped: set[frozenset[str]] = set()  # blocked edges, never planned again in this transit
    for _ in range(replan_attempts):
        try:
            route = nx.shortest_path(edges, a, b, weight="length")
        except (nx.NetworkXNoPath, nx.NodeNotFound):
            here = a
            a = _rejoin(robot, g, edges, a, b)
            if a is None and _cross_where_parts_meet(g, edges, here, b, dropped):
                a = here
            if a is None:
                log.warning("no traversed route to the tour start; trying straight")
                return
            continue
        prev = None
        for n in route:
            cur = robot.pose.xyz
            d = g.pos(n)[:2] - cur[:2]
            if math.hypot(*d) >= 0.05:
                check()
                if sidestep is not None and prev is not None and g.narrow(prev, n):
                    res = move_sidestepping(robot, float(d[0]), float(d[1]), sidestep)
                else:
                    res = robot.move_to(float(d[0]), float(d[1]))
                if res.status != MoveStatus.REACHED and _relocalised(robot):
                    d = g.pos(n)[:2] - robot.pose.xyz[:2]
                    check()
                    res = robot.move_to(float(d[0]), float(d[1]))
                if res.status != MoveStatus.REACHED:
                    log.warning("transit blocked towards node %s; planning around that edge", n)
                    if prev is None:
                        return
                    edges.remove_edge(prev, n)
                    dropped.add(frozenset((prev, n)))
                    back = g.pos(prev)[:2] - robot.pose.xyz[:2]
                    if math.hypot(*back) > 1e-3:
                        robot.move_to(float(back[0]), float(back[1]))
                    a = prev
                    break
            prev = n
        else:
            return


def _relocalised(robot: TourRobot, min_shift_m: float = 0.03) -> bool:
    """A transit move of a drifting robot was blocked: re-registered where it stopped (robot.relocalise,
    which waits for the metres it needs since the last placed panorama); True when that moved the pose
    by ``min_shift_m`` or more, so that the same edge is worth one more try from where the map now puts
    the robot. An exact robot (its localiser has seen no drift) takes no panorama and no second try:
    its moves, and so its tours, stay bit for bit. generated:3:floors=2 (noise seed 1, 1x): three
    blocked transit moves re-localised by 11-19 cm (the map's error 10-12 cm -> 1-2 cm at two of
    them); the one whose edge could be walked from the map's pose went through on the second try,
    and the tours' blocked transit moves went 15 -> 10, the edges slid down the stairs among them."""
    localiser = getattr(robot, "localiser", None)
    relocalise = getattr(robot, "relocalise", None)
    if localiser is None or relocalise is None or not localiser.drift_seen:
        return False
    before = robot.pose.xyz
    relocalise()
    shift_m = float(np.hypot(*(robot.pose.xyz[:2] - before[:2])))
    if shift_m >= min_shift_m:
        log.info("transit move blocked: re-localised %.2f m away, trying the edge again", shift_m)
    return shift_m >= min_shift_m


def _from_a_node_that_sees_it(robot: TourRobot, region: int, goal_m: np.ndarray, scene: SceneMap,
                              check: Callable[[], None], sidestep: SidestepConfig | None = None) -> bool:
    """The tour's start approached from the visited node of its floor nearest it that sees it on the
    floor's map (unknown cells hide), when the straight move from where the transit ended failed:
    the transit ends at the nearest node, and a wall may stand between it and the start
    (generated:3:floors=2 at 1x lost a one-hub region so: its hub 1.7 m from a node in the next room
    and 2 m from its own). Only where the tour would be skipped, so every tour driven before is
    driven as before. True when the start is reached."""
    fi = scene.region_floor.get(region)
    if fi is None or not scene.floors[fi].nodes:
        return False
    floor, g = scene.floors[fi], scene.result.graph
    occ = floor.occupancy
    pos = g.positions(floor.nodes)
    shape = np.array(occ.free.shape)
    a = np.clip(occ.to_index(pos[:, :2]), 0, shape - 1)
    b = np.repeat(np.clip(occ.to_index(goal_m[None, :2]), 0, shape - 1), len(a), axis=0)
    seen = np.flatnonzero(line_of_sight(~occ.free, a, b))
    if not len(seen):
        return False
    k = seen[int(np.argmin(np.hypot(*(pos[seen, :2] - goal_m[:2]).T)))]
    _transit(robot, scene, pos[k], check, sidestep=sidestep)
    d = goal_m[:2] - robot.pose.xyz[:2]
    if np.hypot(*d) <= 0.05:
        return True
    check()
    return robot.move_to(float(d[0]), float(d[1])).status == MoveStatus.REACHED


def _rejoin(robot: TourRobot, g, edges: nx.Graph, here: str, goal: str, radius_m: float = 3.0,
            tries: int = 3) -> str | None:
    """The robot stands at ``here``, cut off from ``goal`` (its only edge back was blocked): a
    direct move to one of the nearest visited nodes on the goal's side, on the same floor and
    within ``radius_m``; the node reached, or None."""
    if goal not in edges:
        return None
    side = list(nx.node_connected_component(edges, goal))
    p = g.positions(side)
    at = g.pos(here)
    dist = np.where(np.abs(p[:, 2] - at[2]) < 0.4, np.linalg.norm(p[:, :2] - at[:2], axis=1), np.inf)
    for k in np.argsort(dist)[:tries]:
        if dist[k] > radius_m:
            break
        d = p[k, :2] - robot.pose.xyz[:2]
        res = robot.move_to(float(d[0]), float(d[1]))
        if res.status == MoveStatus.REACHED:
            edges.add_edge(here, side[k], length=res.travelled_m)
            return side[k]
        back = at[:2] - robot.pose.xyz[:2]
        if math.hypot(*back) > 1e-3:
            robot.move_to(float(back[0]), float(back[1]))
    return None


def _cross_where_parts_meet(g, edges: nx.Graph, here: str, goal: str, dropped: set[frozenset[str]],
                            radius_m: float = 3.0, same_level_m: float = 0.4) -> bool:
    """No direct move from ``here`` rejoins the goal's part of the walked graph: an edge, for the route
    to walk like any other, between the two nodes of the two parts, on one level, that stand nearest
    each other (an edge this transit found blocked, in ``dropped``, is not planned again: the next
    pair is). True when one was added; False when no pair is left within ``radius_m``.

    The robot steps back from a blocked edge onto the node it came from, which may stand on a flight
    of stairs, a floor above every node of the goal's part, where :func:`_rejoin` finds nothing on its
    level. generated:3:floors=2 (noise seed 1, 1x) so skipped a one-hub region: its nodes were joined
    to the rest only by edges slid down the flight in exploration, which stop at the flight's foot,
    0.5 m short, when walked back, and would from the very pose the map gave the robot (it stood 1-9
    cm from it: not drift), while its nearest node stood 0.2 m from one of the rest at that foot.
    The explorer's ``_bridge`` rejoins its parts the same way."""
    if goal not in edges:
        return False
    theirs = sorted(nx.node_connected_component(edges, goal))  # sorted: a set's order changes with the hash seed
    mine = sorted(nx.node_connected_component(edges, here)) if here in edges else [here]
    pa, pb = g.positions(mine), g.positions(theirs)
    level = np.abs(pa[:, None, 2] - pb[None, :, 2]) < same_level_m
    gap = np.where(level, np.linalg.norm(pa[:, None, :2] - pb[None, :, :2], axis=2), np.inf)
    for k in np.argsort(gap, axis=None, kind="stable"):
        i, j = np.unravel_index(k, gap.shape)
        if gap[i, j] > radius_m:
            return False
        if frozenset((mine[i], theirs[j])) not in dropped:
            edges.add_edge(mine[i], theirs[j], length=float(gap[i, j]))
            log.info("transit cut off from %s: crossing %s -> %s (%.2f m)", goal, mine[i], theirs[j], gap[i, j])
            return True
    return False
