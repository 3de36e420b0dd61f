"""Where a drifting robot's tour frames go wrong (issue 33): per recorded tour frame, the error of the
pose the map uses (the frame's pose after the mapper's correction) against the simulator's true pose,
grouped by the odometry path driven since the last fix (a panorama or, with frame registration, a
frame placed by registration).

    python -m bench.tour_drift                        # generated:0, the noisy row's drift x 1
    python -m bench.tour_drift --frames on            # the same, tour frames registered
    python -m bench.tour_drift --drift-scale 0        # depth noise and holes alone (poses exact)
    python -m bench.tour_drift --drift-scale -1       # a noise-free robot (nothing may move)
    python -m bench.tour_drift --band median          # the scan's height band by each column's median range
    python -m bench.tour_drift --graph off            # the sequential localiser alone (no pose graph)
    python -m bench.tour_drift --graph-set weak_edges=true   # PoseGraphConfig fields
    python -m bench.tour_drift --scene generated:3:floors=2   # a two-floor house: the errors split by level
    python -m bench.tour_drift --noise-seed 1         # another draw of the robot's noise (the ladder's seeds)

Explores once and drives the tours (no reconstruction): about a minute of CPU on generated:0.
Besides the frames' error by path since a fix, it splits the errors by floor, by the pose graph's rooms
(panoramas joined by fully pinned scan edges: each room's block offset against what is left inside it)
and by tour.
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np

from bench.agent_maps import NOISE_SEED, _recording_truth, noise_config, tap_true_poses

BINS_M = (0.0, 0.25, 0.5, 1.0, 2.0, math.inf)


def run(spec: str, drift_scale: float, frames: bool, size_px: int = 128, rate_hz: float = 4.0,
        band_from_median: bool = False, graph: bool = True, graph_set: dict | None = None,
        noise_seed: int = NOISE_SEED) -> dict:
    from services.mapper.core import discover, discovery_config, execute_tours
    from services.robot_io.core.robot import ROBOTS
    from shared.schemas import CameraIntrinsics

    robot_cfg = {"scene": spec, "camera": CameraIntrinsics(width_px=size_px, height_px=size_px)}
    if drift_scale >= 0:  # negative: a noise-free robot (exact depth and poses)
        robot_cfg["noise"] = noise_config("noisy", drift_scale, noise_seed)
    robot = ROBOTS.create("sim", robot_cfg)
    truth = _recording_truth(robot)
    # panorama timestamp -> (the true pose it was taken at, its odometry pose)
    pano_truth = tap_true_poses(robot, "observe", lambda pano: pano.timestamp_s)
    cfg = discovery_config("default")
    cfg.localisation.frames.enabled = frames
    cfg.localisation.band_from_median = band_from_median
    cfg.localisation.graph.enabled = graph
    for k, v in (graph_set or {}).items():
        setattr(cfg.localisation.graph, k, v)
    # The graph's visited nodes as the exploration left them, before the pose graph re-placed them
    # (replace.py): the same nodes, before and after, on one trajectory.
    import services.mapper.core.discovery as discovery

    before_nodes: dict[str, np.ndarray] = {}
    real = discovery.replace_exploration

    def spy(result, localiser, before):
        before_nodes.update((n, result.graph.pos(n).copy()) for n in result.graph.g)
        return real(result, localiser, before)

    discovery.replace_exploration = spy
    c0 = time.process_time()
    try:
        d = discover(robot, cfg)
    finally:
        discovery.replace_exploration = real
    c1 = time.process_time()
    recs = execute_tours(robot, d.tours, d.scene, rate_hz=rate_hz)
    c2 = time.process_time()
    loc = d.scene.localiser
    fixes = sorted([s.timestamp_s for s in loc.steps if not s.outcome.startswith("odometry")]
                   + [s.timestamp_s for s in loc.frame_steps if not s.outcome.startswith("odometry")])
    rows = []  # (path since fix m, turn since fix deg, position error m, heading error deg)
    for rec in recs:
        frames_ = [f for f in rec.frames if f.index in truth]
        path_m, turn_rad, prev = 0.0, 0.0, None
        for f in frames_:
            odo = truth[f.index][1]
            if prev is not None:
                path_m += float(np.hypot(*np.subtract(odo.position_m[:2], prev.position_m[:2])))
                turn_rad += abs(math.remainder(odo.heading_rad - prev.heading_rad, 2 * math.pi))
            prev = odo
            k = np.searchsorted(fixes, f.timestamp_s, side="right")
            last = fixes[k - 1] if k else -math.inf
            if not rows or rows[-1][4] != last or rows[-1][5] != rec.region:
                base = (path_m, turn_rad)  # the first frame after a fix (or a tour's start) starts the count
            true = truth[f.index][0]
            rows.append((path_m - base[0], math.degrees(turn_rad - base[1]),
                         float(np.hypot(*np.subtract(true.position_m[:2], f.pose.position_m[:2]))),
                         abs(math.degrees(math.remainder(true.heading_rad - f.pose.heading_rad, 2 * math.pi))),
                         last, rec.region, float(true.position_m[2]), float(true.position_m[0]),
                         float(true.position_m[1])))
    a = np.array([r[:4] for r in rows]) if rows else np.zeros((0, 4))
    frame_region = np.array([r[5] for r in rows], np.int64)
    frame_xyz = np.array([(r[7], r[8], r[6]) for r in rows]).reshape(-1, 3)
    frame_z = frame_xyz[:, 2]
    # Each panorama's pose after its own step (what the model took it at) against the truth, with
    # the odometry path from the start: an error that grows with it is the model's own drift.
    panos, path_m, prev = [], 0.0, None
    pano_step = []  # each of those panoramas' step (and pose graph node) index
    pano_xy = []  # (true x, y, heading, placed x, y, heading, true z) for the per-level rigid fit
    outcomes_ = []  # each of those panoramas' localisation outcome
    for k, st in enumerate(loc.steps):
        if prev is not None:
            path_m += float(np.hypot(*np.subtract(st.odom.position_m[:2], prev.position_m[:2])))
        prev = st.odom
        true = pano_truth.get(st.timestamp_s, (None,))[0]
        if true is not None:
            placed = st.correction.pose(st.odom)
            panos.append((path_m, float(np.hypot(*np.subtract(true.position_m[:2], placed.position_m[:2]))),
                          abs(math.degrees(math.remainder(true.heading_rad - placed.heading_rad, 2 * math.pi))),
                          float(np.hypot(*np.subtract(true.position_m[:2], st.odom.position_m[:2]))),
                          not st.outcome.startswith("odometry")))
            outcomes_.append(st.outcome)
            pano_step.append(k)
            pano_xy.append((true.position_m[0], true.position_m[1], true.heading_rad,
                            placed.position_m[0], placed.position_m[1], placed.heading_rad, true.position_m[2]))
    # Each visited node against the true pose of the panorama that made it, before and after the
    # re-placement; each tour's planned start against where the robot truly began recording.
    from services.mapper.core import NodeStatus

    g = d.result.graph
    nodes = []  # (error before m, error after m, true z)
    for n in g.nodes_with(NodeStatus.VISITED):
        sc = d.result.scans[g.g.nodes[n]["order"] - 1]
        true = pano_truth.get(sc.timestamp_s, (None,))[0]
        if true is None:
            continue
        p0 = before_nodes.get(n, g.pos(n))
        nodes.append((float(np.hypot(*np.subtract(true.position_m[:2], p0[:2]))),
                      float(np.hypot(*np.subtract(true.position_m[:2], g.pos(n)[:2]))), float(true.position_m[2])))
    planned = {t.tour.region: t.tour.start_pose for t in d.tours}
    starts = [float(np.hypot(*np.subtract(truth[r.frames[0].index][0].position_m[:2],
                                          planned[r.region].position_m[:2])))
              for r in recs if r.frames and r.frames[0].index in truth and r.region in planned]
    between = _between_panoramas(recs, truth, pano_truth, loc)
    stands = _stand_headings(recs, truth)
    outcomes: dict[str, int] = {}
    for s in loc.frame_steps:
        key = s.outcome.split(":")[0]
        outcomes[key] = outcomes.get(key, 0) + 1
    # The pose graph's rooms: its panoramas joined by the last solve's fully pinned scan edges, and the
    # accepted edges pinned one way only (PoseGraph.weak) that join them.
    pg = loc.graph
    full = [(e.i, e.j) for e in (pg.edges.values() if pg else ()) if e is not None and e.accepted]
    one_way = [(e.i, e.j) for e in (pg.weak.values() if pg else ()) if e is not None and e.accepted]
    robot.close()
    return {"errors": a, "explore_cpu_s": c1 - c0, "tours_cpu_s": c2 - c1, "frame_outcomes": outcomes,
            "panoramas": loc.report()["outcomes"], "frames": len(a), "graph": loc.report().get("graph"),
            "pano_errors": np.array(panos) if panos else np.zeros((0, 5)), "frame_z": frame_z,
            "frame_region": frame_region, "frame_xyz": frame_xyz,
            "pano_poses": np.array(pano_xy) if pano_xy else np.zeros((0, 7)), "pano_outcomes": outcomes_,
            "node_errors": np.array(nodes) if nodes else np.zeros((0, 3)), "node_shift": loc.node_shift,
            "tour_start_vs_plan_m": np.array(starts), "between": between, "stands": stands,
            "rooms": rooms(len(pg.nodes), full)[pano_step] if pg else None, "pano_steps": pano_step,
            "one_way_pairs": one_way}


def _stand_headings(recs, truth: dict) -> dict:
    """The look-arounds' frames (runs of frames on one spot) as the reconstructor places them: each frame's
    heading error (deg) against the truth as recorded and after the reconstructor's stand registration
    (registration.register_stands, its default config), and how many stands it moved."""
    from services.reconstructor.core.frames import posed_from_frame
    from services.reconstructor.core.registration import StandRegistrationConfig, find_stands, register_stands

    cfg = StandRegistrationConfig()
    before, after, found, moved = [], [], 0, 0
    for rec in recs:
        frames = [f for f in rec.frames if f.index in truth]
        ims = [posed_from_frame(f) for f in frames]  # the camera height does not change a heading
        out, rep = register_stands(ims, cfg)
        found, moved = found + rep.stands, moved + rep.adjusted
        true = np.array([truth[f.index][0].heading_rad for f in frames])
        for a, b in find_stands(ims, cfg.same_place_m, cfg.min_frames):
            for dst, src in ((before, ims), (after, out)):
                h = np.array([im.heading_rad for im in src[a:b]])
                dst.append(np.abs(np.degrees(np.angle(np.exp(1j * (h - true[a:b]))))))
    cat = lambda v: np.concatenate(v) if v else np.zeros(0)  # noqa: E731
    return {"before_deg": cat(before), "after_deg": cat(after), "stands": found, "adjusted": moved}


def _between_panoramas(recs, truth: dict, pano_truth: dict, loc) -> np.ndarray:
    """Where a tour frame's pose error sits: (N, 4) per frame, position error (m) of its pose as
    recorded, of the pose the localiser's panorama corrections interpolated in time give it, of the
    one the panoramas' TRUE corrections (truth - odometry at each panorama) interpolated in time give
    it, and its heading error (deg) under the latter. The third is what exact panoramas would leave
    between them (the drift along the way); the second minus it is the panoramas' share."""
    from services.mapper.core.localise import Correction
    from shared.geometry import interpolate_offsets

    t_est, c_est = loc.schedule()
    pts = [(s.timestamp_s, pano_truth[s.timestamp_s]) for s in loc.steps if s.timestamp_s in pano_truth]
    if not pts:
        return np.zeros((0, 6))
    pts.sort(key=lambda p: p[0])
    t_true = np.array([p[0] for p in pts])
    c_true = np.array([[c.dx_m, c.dy_m, c.dyaw_rad] for c in (
        Correction.between(odo, np.asarray(tr.position_m[:2]), tr.heading_rad) for _, (tr, odo) in pts)])
    odo_true = [odo for _, (_, odo) in pts]
    out = []
    for rec in recs:
        fr = [f for f in rec.frames if f.index in truth]
        if not fr:
            continue
        ts = np.array([f.timestamp_s for f in fr])
        est, tru = interpolate_offsets(t_est, c_est, ts), interpolate_offsets(t_true, c_true, ts)
        # The same true corrections interpolated along the odometry path (position) and the turns
        # (heading) instead of time: the drift's own clocks.
        ev = sorted([(t, 0, o) for t, o in zip(t_true, odo_true)] + [(f.timestamp_s, 1, truth[f.index][1]) for f in fr],
                    key=lambda e: (e[0], e[1]))
        path, turn, prev = [], [], None
        for t, _, o in ev:
            if prev is None:
                path.append(0.0), turn.append(0.0)
            else:
                path.append(path[-1] + float(np.hypot(*np.subtract(o.position_m[:2], prev.position_m[:2]))))
                turn.append(turn[-1] + abs(math.remainder(o.heading_rad - prev.heading_rad, 2 * math.pi)))
            prev = o
        tt = np.array([e[0] for e in ev])
        kp, kt = np.array(path) + 1e-6 * tt, np.array(turn) + 1e-6 * tt
        isp = np.array([e[1] == 0 for e in ev])
        pathc = np.stack([np.interp(kp[~isp], kp[isp], c_true[:, 0]), np.interp(kp[~isp], kp[isp], c_true[:, 1]),
                          np.interp(kt[~isp], kt[isp], c_true[:, 2])], axis=1)
        for f, ce, ct, cp in zip(fr, est, tru, pathc):
            true, odo = truth[f.index]
            pe, pt_, pp = Correction(*ce).pose(odo), Correction(*ct).pose(odo), Correction(*cp).pose(odo)
            out.append((float(np.hypot(*np.subtract(true.position_m[:2], f.pose.position_m[:2]))),
                        float(np.hypot(*np.subtract(true.position_m[:2], pe.position_m[:2]))),
                        float(np.hypot(*np.subtract(true.position_m[:2], pt_.position_m[:2]))),
                        abs(math.degrees(math.remainder(true.heading_rad - pt_.heading_rad, 2 * math.pi))),
                        float(np.hypot(*np.subtract(true.position_m[:2], pp.position_m[:2]))),
                        abs(math.degrees(math.remainder(true.heading_rad - pp.heading_rad, 2 * math.pi)))))
    return np.array(out).reshape(-1, 6)


def levels(z_m: np.ndarray, share: float = 0.1) -> np.ndarray:
    """The floor heights among the panoramas' true heights: heights (to 5 cm) that hold at least
    ``share`` of the panoramas. The stairs' panoramas (every step of a climb) are each at their own."""
    if not len(z_m):
        return np.zeros(0)
    h, n = np.unique(np.round(z_m / 0.05).astype(int), return_counts=True)
    return np.sort(0.05 * h[n >= share * len(z_m)].astype(float))


def rigid_fit(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """The planar rigid transform (Kabsch) taking ``src`` (N, 2) onto ``dst``: (x, y), yaw, and the
    residual of each point after it. Small residuals under a large error: the level is internally
    consistent and sits rigidly off (a floor hanging on the stairs' odometry)."""
    cs, cd = src.mean(0), dst.mean(0)
    h = (src - cs).T @ (dst - cd)
    yaw = math.atan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1])
    r = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    t = cd - cs @ r.T
    return t, yaw, np.hypot(*(src @ r.T + t - dst).T)


def rooms(n: int, pairs: list[tuple[int, int]]) -> np.ndarray:
    """Each of ``n`` panoramas' room: the connected components of ``pairs`` (the pose graph's fully
    pinned scan edges), numbered from 0 in the order of their first panorama."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    a = np.array(pairs, np.int64).reshape(-1, 2)
    _, lab = connected_components(coo_matrix((np.ones(len(a)), (a[:, 0], a[:, 1])), shape=(n, n)), directed=False)
    first = {}
    for k, c in enumerate(lab):
        first.setdefault(int(c), len(first))
    return np.array([first[int(c)] for c in lab], np.int64)


def room_blocks(room: np.ndarray, placed_xy: np.ndarray, true_xy: np.ndarray) -> list[tuple]:
    """Per room (rooms(...)): (room, panoramas, its mean offset (x, y) from the truth, each panorama's
    error median, and after the room's mean offset is taken off). A room rigid within millimetres but
    centimetres off as a block is placed against the others by odometry alone (issue 33)."""
    out = []
    for k in np.unique(room):
        m = room == k
        d = placed_xy[m] - true_xy[m]
        off = d.mean(axis=0)
        out.append((int(k), int(m.sum()), off, float(np.median(np.hypot(*d.T))),
                    float(np.median(np.hypot(*(d - off).T)))))
    return out


def report_rooms(r: dict, most: int = 12) -> None:
    """The panoramas' error split into their rooms' block offsets and what is left inside each room."""
    room, pp = r.get("rooms"), r["pano_poses"]
    if room is None or not len(pp):
        return
    blocks = room_blocks(room, pp[:, 3:5], pp[:, :2])
    step_room = dict(zip(r["pano_steps"], room))
    out = {k: 0 for k, *_ in blocks}
    for i, j in r["one_way_pairs"]:
        a, b = step_room.get(i), step_room.get(j)
        if a is not None and b is not None and a != b:
            out[a] += 1
            out[b] += 1
    d = pp[:, 3:5] - pp[:, :2]
    inside = np.concatenate([(d[room == k] - off) for k, _, off, _, _ in blocks])
    print(f"   pose graph rooms (panoramas joined by fully pinned scan edges): {len(blocks)}; panoramas' error "
          f"median {100 * np.median(np.hypot(*d.T)):.1f} cm, {100 * np.median(np.hypot(*inside.T)):.1f} cm "
          f"with each room's block offset taken off")
    print("   | room | panoramas | level z (m) | block offset x, y (cm) | pos median (cm) | after the block (cm) "
          "| one-way pairs to other rooms |")
    print("   |---|---|---|---|---|---|---|")
    for k, n, off, med, rest in sorted(blocks, key=lambda b: -b[1])[:most]:
        z = float(np.median(pp[room == k, 6]))
        print(f"   | {k} | {n} | {z:.1f} | {100 * off[0]:+.1f}, {100 * off[1]:+.1f} | {100 * med:.1f} | "
              f"{100 * rest:.1f} | {out[k]} |")


def report_levels(r: dict) -> None:
    """The errors split by floor (the true height): which floor's frames and panoramas are off, and
    whether a floor's panoramas are off rigidly (one offset for the floor) or each its own way."""
    pp = r["pano_poses"]
    lv = levels(pp[:, 6]) if len(pp) else np.zeros(0)
    if len(lv) < 2:
        return
    print("   by level (true height): tour frames' and panoramas' error; panoramas after the level's best rigid fit")
    print("   | level z | frames | frame pos median / p90 (cm) | frame heading median / p90 (deg) | panoramas "
          "| pano pos median / p90 (cm) | pano heading median (deg) | rigid fit (cm, deg) | after fit median / p90 (cm) |")
    print("   |---|---|---|---|---|---|---|---|---|")
    a, fz = r["errors"], r["frame_z"]
    for z in lv:
        fm = np.abs(fz - z) < 0.3 if len(fz) else np.zeros(0, bool)
        pm = np.abs(pp[:, 6] - z) < 0.3
        e, p = a[fm], pp[pm]
        fr = (f"{100 * np.median(e[:, 2]):.1f} / {100 * np.percentile(e[:, 2], 90):.1f} | "
              f"{np.median(e[:, 3]):.2f} / {np.percentile(e[:, 3], 90):.2f}") if len(e) else "- | -"
        dpos = np.hypot(*(p[:, :2] - p[:, 3:5]).T)
        dh = np.abs(np.degrees([math.remainder(t - q, 2 * math.pi) for t, q in zip(p[:, 2], p[:, 5])]))
        if len(p) >= 2:
            t, yaw, res = rigid_fit(p[:, 3:5], p[:, :2])
            fit = f"{100 * math.hypot(*t):.1f}, {math.degrees(yaw):.2f} | {100 * np.median(res):.1f} / {100 * np.percentile(res, 90):.1f}"
        else:
            fit = "- | -"
        print(f"   | {z:.2f} m | {int(fm.sum())} | {fr} | {len(p)} | {100 * np.median(dpos):.1f} / "
              f"{100 * np.percentile(dpos, 90):.1f} | {np.median(dh):.2f} | {fit} |")
    stairs = ~np.any(np.abs(fz[:, None] - lv[None]) < 0.3, axis=1) if len(fz) else np.zeros(0, bool)
    if stairs.any():
        e = a[stairs]
        print(f"   frames on the stairs (no level): {int(stairs.sum())}, pos median {100 * np.median(e[:, 2]):.1f} cm")


def report_tours(r: dict) -> None:
    """The error per tour (its region): a drifting robot's frames inherit their tour's panoramas' offset,
    every frame alike (median near p90), so the tours, not the frames, are what the map is placed by."""
    a, reg = r["errors"], r["frame_region"]
    if not len(a):
        return
    print("   per tour: | region | frames | where (true x, y, z mean, m) | pos median / p90 (cm) "
          "| heading median / p90 (deg) |")
    print("   |---|---|---|---|---|")
    med = []
    for k in np.unique(reg):
        e = a[reg == k]
        med.append(np.median(e[:, 2]))
        w = r["frame_xyz"][reg == k].mean(axis=0)
        print(f"   | {k} | {len(e)} | {w[0]:.1f}, {w[1]:.1f}, {w[2]:.1f} | "
              f"{100 * np.median(e[:, 2]):.1f} / {100 * np.percentile(e[:, 2], 90):.1f} | "
              f"{np.median(e[:, 3]):.2f} / {np.percentile(e[:, 3], 90):.2f} |")
    print(f"   tours' median position error: median {100 * np.median(med):.1f} cm, worst {100 * max(med):.1f} cm")


def report(r: dict) -> None:
    a = r["errors"]
    print(f"   {r['frames']} tour frames; CPU explore {r['explore_cpu_s']:.1f} s, tours {r['tours_cpu_s']:.1f} s; "
          f"panoramas {r['panoramas']}; frames registered {r['frame_outcomes']}")
    if r.get("graph"):
        print(f"   pose graph (last solve): {r['graph']}")
    print("   | path since fix | frames | pos median / p90 / max (cm) | heading median / p90 (deg) "
          "| turn median (deg) |")
    print("   |---|---|---|---|---|")
    rows = [(f"{lo:g}-{hi:g} m", (a[:, 0] >= lo) & (a[:, 0] < hi)) for lo, hi in zip(BINS_M[:-1], BINS_M[1:])]
    for name, m in rows + [("all", np.ones(len(a), bool))]:
        if not m.any():
            continue
        e = a[m]
        pos = 100 * e[:, 2]
        print(f"   | {name} | {int(m.sum())} | {np.median(pos):.1f} / {np.percentile(pos, 90):.1f} / {pos.max():.1f} | "
              f"{np.median(e[:, 3]):.2f} / {np.percentile(e[:, 3], 90):.2f} | {np.median(e[:, 1]):.0f} |")
    b = r.get("between")
    if b is not None and len(b):
        q = lambda v: f"{100 * np.median(v):.1f} / {100 * np.percentile(v, 90):.1f}"  # noqa: E731
        print(f"   tour frames' position error median / p90 (cm): as recorded {q(b[:, 0])}; under the panoramas' "
              f"corrections interpolated in time {q(b[:, 1])}; under the panoramas' true corrections interpolated "
              f"in time {q(b[:, 2])} (heading {np.median(b[:, 3]):.2f} / {np.percentile(b[:, 3], 90):.2f} deg): "
              f"the last is the drift between exact panoramas; true corrections along the path and turns "
              f"{q(b[:, 4])} (heading {np.median(b[:, 5]):.2f} / {np.percentile(b[:, 5], 90):.2f} deg)")
    st = r.get("stands")
    if st is not None and len(st["before_deg"]):
        q = lambda v: f"{np.median(v):.2f} / {np.percentile(v, 90):.2f} / {v.max():.2f}"  # noqa: E731
        print(f"   look-arounds: {st['stands']} stands ({len(st['before_deg'])} frames on one spot), heading error "
              f"median / p90 / max (deg): as recorded {q(st['before_deg'])}; after the reconstructor's stand "
              f"registration {q(st['after_deg'])} ({st['adjusted']} stands moved)")
    ne, ns = r["node_errors"], r["node_shift"]
    if len(ne):
        print(f"   graph: {len(ne)} visited nodes against the truth of their panoramas, median / p90 (cm): before "
              f"the re-placement {100 * np.median(ne[:, 0]):.1f} / {100 * np.percentile(ne[:, 0], 90):.1f}, after "
              f"{100 * np.median(ne[:, 1]):.1f} / {100 * np.percentile(ne[:, 1], 90):.1f}; {ns.nodes_moved} nodes moved "
              f"(median {100 * ns.median_m:.1f} cm, max {100 * ns.max_m:.1f} cm)")
    ts = r["tour_start_vs_plan_m"]
    if len(ts):
        print(f"   tours: {len(ts)} true starts against the planned start, median / max (cm): "
              f"{100 * np.median(ts):.1f} / {100 * ts.max():.1f}")
    p = r["pano_errors"]
    if len(p):
        print("   panoramas (the model's poses) by odometry path from the start:")
        print("   | path from start | panoramas | placed | pos median / p90 (cm) | heading median (deg) "
              "| odometry pos median (cm) |")
        print("   |---|---|---|---|---|---|")
        edges = np.quantile(p[:, 0], [0, 0.25, 0.5, 0.75, 1.0])
        for lo, hi in zip(edges[:-1], edges[1:]):
            e = p[(p[:, 0] >= lo) & (p[:, 0] <= hi)]
            if not len(e):
                continue
            print(f"   | {lo:.0f}-{hi:.0f} m | {len(e)} | {int(e[:, 4].sum())} | {100 * np.median(e[:, 1]):.1f} / "
                  f"{100 * np.percentile(e[:, 1], 90):.1f} | {np.median(e[:, 2]):.2f} | "
                  f"{100 * np.median(e[:, 3]):.1f} |")


def _value(text: str):
    """A --graph-set value: JSON where it parses (numbers, true), else the word itself."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="generated:0")
    ap.add_argument("--drift-scale", type=float, default=1.0)
    ap.add_argument("--noise-seed", type=int, default=NOISE_SEED,
                    help="the robot's noise draws (bench.anticipation --noise-seeds: the ladder's seeds)")
    ap.add_argument("--frames", choices=("on", "off"), default="off", help="register tour frames (issue 33)")
    ap.add_argument("--graph", choices=("on", "off"), default="on", help="the panoramas' pose graph (posegraph.py)")
    ap.add_argument("--band", choices=("median", "pixel"), default="pixel",
                    help="scan height band chosen by each column's median range, or by each pixel's own depth")
    ap.add_argument("--graph-set", nargs="+", default=[], metavar="FIELD=JSON",
                    help="PoseGraphConfig fields, e.g. weak_edges=true min_fitness=0.25")
    args = ap.parse_args()
    print(f"## {args.scene}, drift x{args.drift_scale:g} (noise seed {args.noise_seed}), frame registration "
          f"{args.frames}, band by {args.band}, pose graph {args.graph} {' '.join(args.graph_set)}")
    r = run(args.scene, args.drift_scale, args.frames == "on", band_from_median=args.band == "median",
            graph=args.graph == "on", graph_set={k: _value(v) for k, v in (a.split("=", 1) for a in args.graph_set)},
            noise_seed=args.noise_seed)
    report(r)
    report_levels(r)
    report_rooms(r)
    report_tours(r)


if __name__ == "__main__":
    main()
