"""The offline default policy: instruction sub-goals scored against anticipated semantics.

At each step the policy (1) advances its current sub-goal when the sub-goal's landmark or room has been
reached (seen close in the current panorama) or its turn and distance have been executed, (2) stops once
the final landmark is close (or, without labels, once every sub-goal is used up), and otherwise (3) scores
every waypoint by the current and next targets visible in its anticipated view (the map's semantic
channel; the observed view when anticipation is off), agreement with the expected turn and progress
(longer moves, no revisits). Without any labels it still navigates by turns and distances.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from libs.scenegraph import Router
from shared.registry import BackendConfig
from shared.schemas import CandidateKind, Decision

from .context import CandidateView, StepContext
from .history import turn_phrase
from .grounding import Grounding, GroundingError, ground
from .instruction import ParsedInstruction, SubGoal, Turn, label_matches, parse_instruction
from .policy import POLICIES, Policy

log = logging.getLogger(__name__)


class HeuristicConfig(BackendConfig):
    """Weights and thresholds of the heuristic policy."""

    semantic_weight: float = 3.0
    lookahead_weight: float = 1.0
    turn_weight: float = 1.5
    turn_sigma_deg: float = 35.0
    progress_weight: float = 0.4
    revisit_radius_m: float = 0.8
    revisit_penalty: float = 1.5
    hole_penalty: float = 0.5
    backtrack_score: float = -0.6
    reached_distance_m: float = 2.0  # an intermediate landmark counts as reached within this depth
    stop_distance_m: float = 1.6  # the final landmark must be this close to stop
    min_view_fraction: float = 0.02  # of a view's pixels, for a landmark to count as seen
    room_fraction: float = 0.3  # of the near pixels, for the agent to be in a room
    default_leg_m: float = 3.0  # a sub-goal whose target cannot be seen lasts this far
    max_distance_factor: float = 2.5  # give up on the labels' stop after this x the parsed distance
    # Which room the agent is in from the floor around it alone. Off by default: on bench.planner it
    # advanced "go through the X" sub-goals too early (SR 41.7 % vs 58.3 % with it off, same seeds).
    room_by_floor: bool = False
    floor_radius_m: float = 1.5  # the floor this near (depth) tells which room the agent stands in
    floor_share: float = 0.5  # of the near floor pixels, for the agent to be in a room
    room_weight: float = 2.0  # a candidate whose anticipated floor is the sought room
    explore_weight: float = 0.6  # per metre (capped at 2 m) away from every earlier position
    # How the anticipated view enters the score. "combine": the evidence for a target is the larger of
    # the observed and the anticipated fraction, plus a bonus when the target is close in the
    # anticipated view (reached by taking the candidate); the anticipated floor tells the candidate's
    # room. "replace" (the earlier rule): the anticipated view replaces the observed one. The anticipated
    # view from 1-3 m further along the same heading mostly shows a subset of the observed scene, so
    # replacing threw away what the agent sees and gained little.
    anticipation_use: Literal["combine", "replace"] = "combine"
    reach_weight: float = 1.5  # target within reached_distance_m in the candidate's anticipated view
    # The map's scene graph (issue 32): ground the instruction's final object on it, follow the geodesic
    # route there, stop where it is grounded. On by default: on the first 40 episodes of the generated
    # set (seed 0, rgbd maps) SR 65.0 vs 37.5 and SPL 52.1 vs 19.4 (bench.ablation --preset scene-graph).
    scene_graph: bool = True
    # Stop when the route to the grounded goal is this short (success is within 3 m of the true goal; the
    # grounded goal is within 1.4 m of it on the DEV set when right): on the DEV set (seed 2, 16 episodes)
    # 1.5 m vs 0.5 m: the same 14 successes, SPL 57.4 vs 56.3, 12.8 vs 13.1 steps.
    graph_stop_m: float = 1.5
    graph_object_stop_m: float = 1.0  # ... or its approach point this near (straight line, same floor)
    graph_revisit_penalty: float = 0.5  # per earlier visit of a candidate's target (m of progress)
    graph_prune_penalty: float = 1.0  # an anticipated view whose floor is a room off the route
    # SPL counts every metre: a move that goes 3 m for 1 m of progress wastes 2 m; each wasted metre costs
    # this much of a metre of progress.
    graph_detour_weight: float = 0.3
    # A dead end: a place where no move gains graph_min_progress_m along the route (the map's route goes
    # where the waypoint predictor offers no move: a doorway seen at a sharp angle, a gap under a table).
    # Going back there is what made the robot oscillate (A -> B -> A ...) until the revisit penalties grew;
    # a move ending within graph_dead_end_radius_m of one costs graph_dead_end_penalty (m of progress).
    graph_min_progress_m: float = 0.15
    graph_dead_end_radius_m: float = 1.0
    graph_dead_end_penalty: float = 2.0


@dataclass
class _MissionState:
    parsed: ParsedInstruction
    k: int = 0  # current sub-goal
    turn_done: bool = False
    leg_m: float = 0.0  # distance travelled in the current sub-goal
    total_m: float = 0.0
    last_xyz: np.ndarray | None = None
    grounding: Grounding | None = None
    router: Router | None = None
    ground_note: str = ""  # why the scene graph is not used (said in every reasoning)
    last_route_m: float | None = None
    dead_ends: list[np.ndarray] = field(default_factory=list)  # xy of places no move got on from


@POLICIES.register("heuristic", HeuristicConfig)
class HeuristicPolicy(Policy):
    name = "heuristic"

    def __init__(self, config: HeuristicConfig):
        super().__init__()
        self.config = config
        self._state: _MissionState | None = None
        self._ids_cache: dict[tuple, np.ndarray] = {}
        self._router: tuple[object, Router] | None = None

    def reset(self, mission_id: str) -> None:
        super().reset(mission_id)
        self._state = None

    # --- label helpers --------------------------------------------------------------------------

    def _ids(self, label_names: dict[int, str], target: str) -> np.ndarray:
        key = (id(label_names), len(label_names), target)
        ids = self._ids_cache.get(key)
        if ids is None:
            ids = np.array([i for i, n in label_names.items() if label_matches(n, target)], dtype=np.int64)
            self._ids_cache[key] = ids
        return ids

    def _fraction(
        self, labels: np.ndarray | None, depth: np.ndarray | None, ids: np.ndarray, max_depth_m=None
    ) -> float:
        if labels is None or ids.size == 0:
            return 0.0
        mask = np.isin(labels, ids)
        if max_depth_m is not None and depth is not None:
            mask &= (depth > 0) & (depth <= max_depth_m)
        return float(mask.mean())

    def _observed_sets(self, ctx: StepContext) -> list[tuple[np.ndarray, np.ndarray | None]]:
        """(labels, depth) of every current view: the panorama when present, else the candidates' views."""
        if ctx.panorama is not None and ctx.panorama.semantic is not None:
            return list(zip(ctx.panorama.semantic, ctx.panorama.depth_m))
        return [(v.observed_labels, v.observed_depth_m) for v in ctx.candidates if v.observed_labels is not None]

    def _has_labels(self, ctx: StepContext) -> bool:
        return bool(ctx.label_names) and (
            bool(self._observed_sets(ctx)) or any(v.anticipated_labels is not None for v in ctx.candidates)
        )

    def _landmark_close(self, ctx: StepContext, target: str, max_depth_m: float) -> float:
        """Largest fraction of a current view showing ``target`` within ``max_depth_m``."""
        ids = self._ids(ctx.label_names, target)
        best = 0.0
        for labels, depth in self._observed_sets(ctx):
            best = max(best, self._fraction(labels, depth, ids, max_depth_m))
        return best

    def _floor_ids(self, label_names: dict[int, str]) -> np.ndarray:
        key = (id(label_names), len(label_names), "<floor>")
        ids = self._ids_cache.get(key)
        if ids is None:
            ids = np.array([i for i, n in label_names.items() if "floor" in n.lower()], dtype=np.int64)
            self._ids_cache[key] = ids
        return ids

    def _floor_share(self, ctx: StepContext, sets, room: str, max_depth_m: float) -> tuple[float, int]:
        """(share of the near floor pixels that are ``room``'s floor, number of near floor pixels)."""
        floor_ids = self._floor_ids(ctx.label_names)
        room_ids = self._ids(ctx.label_names, room)
        if floor_ids.size == 0 or room_ids.size == 0:
            return 0.0, 0
        near = hit = 0
        for labels, depth in sets:
            if depth is None or labels is None:
                continue
            floor = (depth > 0) & (depth <= max_depth_m) & np.isin(labels, floor_ids)
            near += int(floor.sum())
            hit += int((floor & np.isin(labels, room_ids)).sum())
        return (hit / near if near else 0.0), near

    def _in_room(self, ctx: StepContext, room: str) -> bool:
        """In ``room``: enough of the near pixels carry its label (or, with ``room_by_floor``, most of the
        floor around the agent is its floor)."""
        sets = self._observed_sets(ctx)
        share, n = (self._floor_share(ctx, sets, room, self.config.floor_radius_m)
                    if self.config.room_by_floor else (0.0, 0))
        if self.config.room_by_floor and n > 0:
            return share >= self.config.floor_share
        ids = self._ids(ctx.label_names, room)
        near = total = 0
        for labels, depth in sets:
            if depth is None or labels is None:
                continue
            close = (depth > 0) & (depth <= 2.0) & (labels >= 0)
            total += int(close.sum())
            near += int((close & np.isin(labels, ids)).sum())
        return total > 0 and near / total >= self.config.room_fraction

    # --- sub-goal tracking --------------------------------------------------------------------------

    def _update(self, ctx: StepContext) -> _MissionState:
        st = self._state
        if st is None or st.parsed.text != ctx.instruction:
            st = self._state = _MissionState(parsed=parse_instruction(ctx.instruction))
        xyz = ctx.pose.xyz
        if st.last_xyz is not None:
            d = float(np.linalg.norm(xyz[:2] - st.last_xyz[:2]))
            st.leg_m += d
            st.total_m += d
        st.last_xyz = xyz
        has_labels = self._has_labels(ctx)
        while st.k < len(st.parsed.subgoals) and self._subgoal_done(ctx, st, st.parsed.subgoals[st.k], has_labels):
            log.debug("sub-goal %d done: %s", st.k, st.parsed.subgoals[st.k].text)
            st.k += 1
            st.turn_done = False
            st.leg_m = 0.0
        return st

    def _subgoal_done(self, ctx: StepContext, st: _MissionState, sg: SubGoal, has_labels: bool) -> bool:
        is_last = st.k == len(st.parsed.subgoals) - 1
        turn_ok = sg.turn is None or sg.turn == Turn.STRAIGHT or st.turn_done
        if sg.stop or (is_last and sg.landmarks):
            return False  # the final sub-goal ends with stop, decided separately
        if not turn_ok:
            return False
        if sg.distance_m is not None and st.leg_m + 0.25 < sg.distance_m:
            return False
        if has_labels and sg.leave:
            if not any(self._in_room(ctx, r) for r in sg.rooms):
                return True
            return st.leg_m >= self.config.default_leg_m * 2
        if has_labels and sg.targets:
            if any(self._landmark_close(ctx, t, self.config.reached_distance_m) >= self.config.min_view_fraction
                   for t in sg.landmarks):
                return True
            if any(self._in_room(ctx, r) for r in sg.rooms):
                return True
            return st.leg_m >= self.config.default_leg_m * 2  # never seen: do not wait forever
        if sg.targets and sg.distance_m is None:
            return st.leg_m >= self.config.default_leg_m
        return sg.distance_m is not None or sg.turn is not None and st.leg_m > 0.0

    def _should_stop(self, ctx: StepContext, st: _MissionState) -> tuple[bool, str]:
        parsed = st.parsed
        n = len(parsed.subgoals)
        if ctx.step == 0 and n > 0:
            return False, ""
        at_last = st.k >= n - 1
        if not at_last:
            return False, ""
        final = parsed.final_landmarks
        if self._has_labels(ctx) and final:
            close = max(self._landmark_close(ctx, t, self.config.stop_distance_m) for t in final)
            if close >= self.config.min_view_fraction:
                return True, f"the final landmark ({', '.join(final)}) is close ({100 * close:.0f}% of a view)"
            expected = sum(sg.distance_m or self.config.default_leg_m for sg in parsed.subgoals)
            if st.total_m > self.config.max_distance_factor * max(expected, self.config.default_leg_m):
                return True, "travelled far beyond the instruction's extent without reaching the landmark"
            return False, ""
        if self._has_labels(ctx) and parsed.final_rooms and not final:
            if any(self._in_room(ctx, r) for r in parsed.final_rooms):
                return True, f"inside the final room ({parsed.final_rooms[0]})"
        if st.k >= n:
            return True, "every sub-goal of the instruction is done"
        sg = parsed.subgoals[-1] if n else None
        leg = (sg.distance_m if sg and sg.distance_m else self.config.default_leg_m)
        turn_ok = sg is None or sg.turn is None or sg.turn == Turn.STRAIGHT or st.turn_done
        if turn_ok and st.leg_m + 0.25 >= leg:
            return True, "the last sub-goal's turn and distance are done"
        return False, ""

    # --- scoring ----------------------------------------------------------------------------------------

    def _score(self, ctx: StepContext, st: _MissionState, view: CandidateView) -> tuple[float, str]:
        cfg = self.config
        c = view.candidate
        sgs = st.parsed.subgoals
        cur = sgs[st.k] if st.k < len(sgs) else None
        nxt = sgs[st.k + 1] if st.k + 1 < len(sgs) else None
        notes: list[str] = []
        score = 0.0

        # Turn agreement: the current sub-goal's turn until executed, then a mild preference for straight.
        if cur is not None and cur.turn is not None and not st.turn_done:
            want, weight = cur.turn.angle_rad, cfg.turn_weight
        else:
            want, weight = 0.0, cfg.turn_weight * 0.3
        delta = math.degrees(abs(math.remainder(c.angle_rad - want, 2 * math.pi)))
        turn_s = weight * math.exp(-0.5 * (delta / cfg.turn_sigma_deg) ** 2)
        score += turn_s

        # Semantics: the observed view towards the candidate and, with anticipation, what the candidate
        # itself would see (see HeuristicConfig.anticipation_use).
        anticipated = ctx.ablation.anticipation and view.anticipated_labels is not None
        combine = anticipated and cfg.anticipation_use == "combine"
        if anticipated and not combine:
            sources = [(view.anticipated_labels, view.anticipated_depth_m)]
        else:
            sources = [(view.observed_labels, view.observed_depth_m)]
            if combine:
                sources.append((view.anticipated_labels, view.anticipated_depth_m))
        sources = [(lab, dep) for lab, dep in sources if lab is not None]
        if sources and ctx.label_names:
            for targets, w in ((cur.targets if cur else []), cfg.semantic_weight), (
                (nxt.targets if nxt else []), cfg.lookahead_weight
            ):
                for t in targets:
                    ids = self._ids(ctx.label_names, t)
                    f = max(self._fraction(lab, dep, ids) for lab, dep in sources)
                    if f > 0:
                        score += w * math.sqrt(f)
                        notes.append(f"{t} {100 * f:.0f}%")
            if combine and cur is not None:
                # Reached by taking this candidate: the current target is close in its anticipated view.
                close = max((self._fraction(view.anticipated_labels, view.anticipated_depth_m,
                                            self._ids(ctx.label_names, t), cfg.reached_distance_m)
                             for t in cur.targets), default=0.0)
                if close >= cfg.min_view_fraction:
                    score += cfg.reach_weight * math.sqrt(close)
                    notes.append(f"reaches {cur.targets[0]}")

        # Room entry: the floor under the view's near rows is the room being sought; the candidate's own
        # floor when it is anticipated.
        rooms = [r for sg in (cur, nxt) if sg is not None and not sg.leave for r in sg.rooms][:1]
        floor_view = sources[-1] if sources else (None, None)
        if floor_view[0] is not None and floor_view[1] is not None and ctx.label_names and rooms:
            share = max(self._floor_share(ctx, [floor_view], r, 2.5)[0] for r in rooms)
            if share > 0:
                score += cfg.room_weight * share
                notes.append(f"{rooms[0]} floor {100 * share:.0f}%")

        # Progress: prefer longer moves to new places; avoid returning where we have been, and
        # explore away from the trajectory so a dead end is not tried twice.
        score += cfg.progress_weight * min(c.distance_m or math.hypot(c.dx_m, c.dy_m), 3.0) / 3.0
        if len(ctx.trajectory_m) > 1:
            target = ctx.target_m(view)
            gaps = np.linalg.norm(ctx.trajectory_m[:, :2] - target[:2], axis=1)
            visits = int(np.count_nonzero(gaps[:-1] < cfg.revisit_radius_m))
            if visits:
                score -= cfg.revisit_penalty * visits
                notes.append("revisit" if visits == 1 else f"revisit x{visits}")
            score += cfg.explore_weight * min(float(gaps.min()), 2.0) / 2.0
        if anticipated and view.anticipated_hole_fraction is not None:
            score -= cfg.hole_penalty * view.anticipated_hole_fraction
        why = f"{turn_phrase(c.angle_rad)} {c.distance_m:.1f} m" + (f" ({', '.join(notes)})" if notes else "")
        return score, why

    # --- the scene graph's route (issue 32) -----------------------------------------------------

    def _graph_decide(self, ctx: StepContext, st: _MissionState) -> Decision | None:
        """Follow the route to the grounded goal; None when there is no grounding (the caller falls back)."""
        cfg = self.config
        graph = ctx.scene_graph
        if st.grounding is None and not st.ground_note:
            try:
                # One router per map (its raster graph and snapping tables), not one per mission.
                if self._router is None or self._router[0] is not graph:
                    self._router = (graph, Router(graph))
                st.router = self._router[1]
                st.grounding = ground(st.parsed, graph, st.router, ctx.pose.xyz, ctx.pose.heading_rad)
                log.info("mission %s grounded: %s", ctx.mission_id, st.grounding.explained)
            except GroundingError as exc:
                st.ground_note = f"scene graph not used: {exc}; local heuristic"
                log.info("mission %s: %s", ctx.mission_id, st.ground_note)
        g, router = st.grounding, st.router
        if g is None or router is None:
            return None
        here = ctx.pose.xyz
        d_here = router.distance(g.field, here)
        obj_m = math.dist(here[:2], g.goal_m[:2])
        same_floor = router.floor_of(here) == router.floor_of(g.goal_position_m)
        where = f"route to {g.goal_id}"
        stop = ctx.stop_candidate
        # The stand point is one side of the object; the true goal may be on another side, up to the object's
        # length away (a bed): the larger the object, the closer to the stand point before stopping.
        stop_m = min(cfg.graph_stop_m, max(0.5, cfg.graph_stop_m - max(g.goal_size_m[:2]) / 2))
        if stop is not None and (d_here <= stop_m or (same_floor and obj_m <= min(stop_m, cfg.graph_object_stop_m))):
            return self._decision(ctx, stop.index, f"{where}: stop - at the grounded goal ({g.explained}; "
                                  f"{d_here:.1f} m by the route, {obj_m:.1f} m from it)")
        replanned = st.last_route_m is not None and d_here > st.last_route_m + 0.3
        route_types = {graph.room(r).room_type for r in g.rooms if graph.room(r) is not None}
        floor_ids = self._floor_ids(ctx.label_names) if ctx.label_names else np.zeros(0, np.int64)
        scored = self._graph_scores(ctx, st, g, router, d_here, route_types, floor_ids)
        gains = [d_here - dt for _, v, _, dt in scored if v.kind == CandidateKind.WAYPOINT]
        if d_here > stop_m and max(gains, default=-1.0) < cfg.graph_min_progress_m:
            st.dead_ends.append(np.asarray(here[:2], float))
        st.last_route_m = d_here
        scored = [(sc, v, n) for sc, v, n, _ in scored]
        if not scored:
            return None
        if log.isEnabledFor(logging.DEBUG):  # every move's score, for reading an episode (built only then)
            log.debug("step %d at %s (%.1f m left): %s", ctx.step, np.round(here[:2], 2), d_here,
                      [(round(s, 2), s_v.kind.value, round(math.degrees(s_v.candidate.angle_rad)),
                        round(s_v.candidate.distance_m or 0.0, 1), n) for s, s_v, n in scored])
        best_score, best, notes = max(scored, key=lambda s: s[0])
        # Stuck near the goal: stop, but only the second time here (the first time the dead-end memory makes
        # the robot try another way in; the demo's bed stand point was reached so, 0.4 m instead of 1.3 m).
        stuck_again = len(st.dead_ends) > 1 and min(
            math.dist(here[:2], p) for p in st.dead_ends[:-1]) < cfg.graph_dead_end_radius_m
        # A room goal is an area: stuck within its radius of the stand point is in it (generated:8's demo
        # reached its bedroom 2.2 m from the stand point and went back and forth there until the budget ran out).
        near_m = 1.5 + g.goal_extent_m
        if stop is not None and max(gains, default=-1.0) < cfg.graph_min_progress_m and d_here < near_m and (
                stuck_again or d_here <= stop_m):
            return self._decision(ctx, stop.index, f"{where}: stop - no move gets closer and the goal is "
                                  f"{d_here:.1f} m away ({g.explained})")
        c = best.candidate
        move = "go back" if best.kind == CandidateKind.BACKTRACK else f"{turn_phrase(c.angle_rad)} {c.distance_m:.1f} m"
        again = "; off the route, re-planned from here" if replanned else ""
        return self._decision(ctx, best.index, f"{where} ({d_here:.1f} m left, {g.explained}): {move} "
                              f"({', '.join(notes)}){again}")

    def _graph_scores(self, ctx, st, g, router, d_here, route_types, floor_ids):
        """(score, candidate, notes, route distance of its target) of every move."""
        cfg = self.config
        scored = []
        for v in ctx.candidates:
            if v.kind == CandidateKind.STOP:
                continue
            target = ctx.target_m(v)
            dt = router.distance(g.field, target)
            if not math.isfinite(dt):
                continue
            gain = d_here - dt
            length = v.candidate.distance_m or math.hypot(v.candidate.dx_m, v.candidate.dy_m)
            score = gain - cfg.graph_detour_weight * max(0.0, length - gain)
            notes = [f"{gain:+.1f} m along the route"]
            if len(ctx.trajectory_m) > 1:
                gaps = np.linalg.norm(ctx.trajectory_m[:-1, :2] - target[:2], axis=1)
                visits = int(np.count_nonzero(gaps < cfg.revisit_radius_m))
                if visits:
                    score -= cfg.graph_revisit_penalty * visits
                    notes.append(f"revisit x{visits}")
            if st.dead_ends and min(math.dist(target[:2], p) for p in st.dead_ends) < cfg.graph_dead_end_radius_m:
                score -= cfg.graph_dead_end_penalty
                notes.append("a dead end")
            # The paper's use of anticipation: a candidate whose anticipated floor is a room the route does
            # not pass contradicts the next leg (the map is right there, the raster may be wrong).
            if (ctx.ablation.anticipation and v.anticipated_labels is not None and v.anticipated_depth_m is not None
                    and floor_ids.size and route_types):
                lab, dep = v.anticipated_labels, v.anticipated_depth_m
                near_floor = np.isin(lab, floor_ids) & (dep > 0) & (dep < 2.5)
                if near_floor.sum() > 0.05 * lab.size:
                    ids, counts = np.unique(lab[near_floor], return_counts=True)
                    name = ctx.label_names.get(int(ids[np.argmax(counts)]), "")
                    rtype = " ".join(w for w in name.lower().split() if w != "floor")
                    if rtype and not any(label_matches(t, rtype) or label_matches(rtype, t) for t in route_types):
                        score -= cfg.graph_prune_penalty
                        notes.append(f"pruned: anticipates a {rtype} off the route")
            scored.append((score, v, notes, dt))
        return scored

    def decide(self, ctx: StepContext) -> Decision:
        st = self._update(ctx)
        if self.config.scene_graph and ctx.scene_graph is not None:
            graph_decision = self._graph_decide(ctx, st)
            if graph_decision is not None:
                return graph_decision
        decision = self._local_decide(ctx, st)
        if st.ground_note:
            decision.reasoning = f"[{st.ground_note}] {decision.reasoning}"
        return decision

    def _local_decide(self, ctx: StepContext, st: _MissionState) -> Decision:
        sgs = st.parsed.subgoals
        where = f"sub-goal {min(st.k, len(sgs) - 1) + 1}/{len(sgs)}" if sgs else "no parsable sub-goal"
        stop = ctx.stop_candidate
        do_stop, why_stop = self._should_stop(ctx, st)
        if do_stop and stop is not None:
            return self._decision(ctx, stop.index, f"{where}: stop - {why_stop}")

        waypoints = ctx.by_kind(CandidateKind.WAYPOINT)
        scored = [(self._score(ctx, st, v), v) for v in waypoints]
        backtrack = ctx.by_kind(CandidateKind.BACKTRACK)
        if backtrack:
            scored.append(((self.config.backtrack_score, "go back: no better way on"), backtrack[0]))
        if not scored:
            idx = stop.index if stop is not None else ctx.candidates[0].index
            return self._decision(ctx, idx, f"{where}: no way to move - stop", fallback=stop is None)
        (best_score, why), best = max(scored, key=lambda s: s[0][0])
        # The turn of the current sub-goal is executed once we move in (roughly) its direction.
        cur = sgs[st.k] if st.k < len(sgs) else None
        if cur is not None and cur.turn is not None and best.kind == CandidateKind.WAYPOINT:
            tol = 60.0 if cur.turn != Turn.AROUND else 50.0
            if math.degrees(abs(math.remainder(best.candidate.angle_rad - cur.turn.angle_rad, 2 * math.pi))) < tol:
                st.turn_done = True
                if cur.distance_m is None and not cur.targets and not cur.stop and st.k < len(sgs) - 1:
                    # A bare "turn left" is done by this move, which already counts for the next clause
                    # ("turn left and walk 3 m": the turning move is part of the 3 m).
                    st.k += 1
                    st.turn_done = False
                    st.leg_m = 0.0
        text = cur.text if cur is not None else "final approach"
        return self._decision(ctx, best.index, f"{where} '{text}': {why} (score {best_score:.2f})")
