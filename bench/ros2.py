"""Figures of the ros2 backend against the ROS 2 stand-in (both key styles), printed as tables.

    python -m bench.ros2 [--what panorama,control,images,sr] [--episodes 4]

* panorama: time of one 12-view ``observe`` (turn, settle, capture x 12), simulated and wall, at the
  stand-in's time scale;
* control: the backend's control-loop rate while turning (ticks per wall second and per robot second);
* images: colour images the backend receives and decodes per second, from the stand-in (rendering
  bound) and from a publisher of pre-encoded 640x480 rgb8 + 16UC1 frames (the transport + CDR bound);
* sr: SR / SPL / NE of a few generated episodes through the whole system (curated cloud of the scene),
  with robot-io's embedded simulator and with the ros2 backend against the stand-in.
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from deploy.launcher import Launcher, StandIn, free_port
from libs.ros2 import messages as msgs
from services.robot_io.core.ros2.backend import Ros2Config, Ros2Robot
from libs.ros2.keys import key_style
from libs.ros2.node import Ros2Node
from libs.ros2.profiles import profile
from services.robot_io.core.ros2.standin import StandInConfig, StandInRobot
from services.robot_io.ros2_zenoh import ZenohRos2Transport, ZenohTransportConfig
from shared.bus.config import ZenohSettings

OVERRIDES = {"clock": "/clock", "teleport_service": "/teleport", "map": "/map"}


def _transport(**kw):
    return ZenohRos2Transport(ZenohTransportConfig(zenoh=ZenohSettings(**kw)))


class _Pair:
    """A stand-in (its own thread and session) and a backend connected to it over loopback."""

    def __init__(self, keys: str, scene: str, time_scale: float, camera_px: int):
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.t = _transport(listen=[self.endpoint])
        cfg = StandInConfig(scene=scene, time_scale=time_scale, camera={"width_px": camera_px, "height_px": camera_px})
        self.standin = StandInRobot(cfg, profile("generic", OVERRIDES), self.t, key_style(keys))
        self.thread = threading.Thread(target=self.standin.run, daemon=True)
        self.thread.start()
        self.robot = Ros2Robot(Ros2Config(keys=keys, profile_overrides=OVERRIDES, max_data_age_s=0.5 * time_scale,
                                          clock_timeout_s=5.0, transport_config={"zenoh": {"connect": [self.endpoint]}}))

    def close(self):
        self.robot.close()
        self.standin.stop()
        self.thread.join(5)
        self.standin.close()
        self.t.close()


def bench_panorama(keys: str, scene: str, time_scale: float, n: int, camera_px: int) -> dict:
    p = _Pair(keys, scene, time_scale, camera_px)
    try:
        sim, wall, rates = [], [], []
        for _ in range(n):
            t0c, t0w = p.robot.clock.now(), time.monotonic()
            k0 = len(p.robot.control_ticks)
            p.robot.observe()
            sim.append(p.robot.clock.now() - t0c)
            wall.append(time.monotonic() - t0w)
            ticks = p.robot.control_ticks[k0:]
            rates.append((len(ticks) - 1) / (ticks[-1] - ticks[0]) if len(ticks) > 1 else float("nan"))
        return {"keys": keys, "time_scale": time_scale, "camera_px": camera_px, "panoramas": n,
                "sim_s": float(np.median(sim)), "wall_s": float(np.median(wall)),
                "achieved_scale": float(np.median(np.array(sim) / np.array(wall))),
                "control_hz_wall": float(np.median(rates)),
                "control_hz_robot": float(np.median(rates)) / max(p.robot.clock.rate, 1e-9),
                "configured_control_hz": p.robot.config.control_rate_hz}
    finally:
        p.close()


def bench_images(keys: str, seconds: float, width: int = 640, height: int = 480) -> dict:
    """A publisher of pre-encoded frames as fast as it can; a subscriber that decodes every one."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    ta, tb = _transport(listen=[endpoint]), _transport(connect=[endpoint])
    na, nb = Ros2Node(ta, key_style(keys), "cam"), Ros2Node(tb, key_style(keys), "ant")
    got = [0, 0]
    done = threading.Event()

    def on(msg, _info):
        a = msgs.image_array(msg)
        got[0] += 1
        got[1] += a.nbytes

    nb.subscribe("/camera/color/image_raw", msgs.MESSAGES["image"], on, max_queue=4)
    time.sleep(1.0)  # discovery between the two sessions
    pub = na.publisher("/camera/color/image_raw", msgs.MESSAGES["image"])
    rgb = (np.random.default_rng(0).random((height, width, 3)) * 255).astype(np.uint8)
    payload = msgs.encode(msgs.MESSAGES["image"], msgs.image(0.0, "cam", rgb, "rgb8"))
    sent = 0
    t0 = time.monotonic()
    while time.monotonic() - t0 < seconds:
        pub.publish_raw(payload)
        sent += 1
        time.sleep(0.001)  # a camera does not busy-loop either; bounds the queue
    dt = time.monotonic() - t0
    time.sleep(0.5)
    done.set()
    na.close(), nb.close(), ta.close(), tb.close()
    return {"keys": keys, "size": f"{width}x{height} rgb8", "sent_per_s": sent / dt, "decoded_per_s": got[0] / dt,
            "MB_per_s": got[1] / dt / 1e6}


def bench_standin_images(keys: str, scene: str, time_scale: float, camera_px: int, seconds: float) -> dict:
    p = _Pair(keys, scene, time_scale, camera_px)
    try:
        c0, t0, s0 = p.robot._color.count, time.monotonic(), p.robot.clock.now()
        time.sleep(seconds)
        dc, dt, ds = p.robot._color.count - c0, time.monotonic() - t0, p.robot.clock.now() - s0
        return {"keys": keys, "camera_px": camera_px, "time_scale": time_scale, "images_per_wall_s": dc / dt,
                "images_per_robot_s": dc / ds, "configured_hz": p.standin.config.camera_rate_hz,
                "achieved_scale": ds / dt}
    finally:
        p.close()


def bench_sr(scene: str, episodes: int, keys: str, time_scale: float, policy: str, max_steps: int,
             backends: tuple[str, ...] = ("sim", "ros2")) -> list[dict]:
    from evaluation.gateway_client import GatewayClient
    from evaluation.runner import EvalRunner, MapSource, RunConfig
    from libs.world import generate_episodes
    from services.robot_io.core import ROBOTS

    with ROBOTS.create("sim", {"scene": scene}) as sim:
        eps = generate_episodes(sim.scene, sim.nav, episodes, seed=7).episodes
        labels = {int(k): v for k, v in sim.scene.label_names.items()}
    rows = []
    for backend in backends:
        run_dir = Path(tempfile.mkdtemp(prefix=f"ros2-sr-{backend}-"))
        env = {"ANT_ROBOT_CONFIG": json.dumps({"scene": scene}), "ANT_STORE_DIR": str(run_dir / "maps"),
               "ANT_DB_PATH": str(run_dir / "gateway.sqlite3")}
        standin = StandIn(scene=scene, keys=keys, time_scale=time_scale, label_names=labels) if backend == "ros2" else None
        t0 = time.monotonic()
        with Launcher(run_dir, extra_env=env, standin=standin) as launcher:
            with GatewayClient.connect(launcher.gateway_url) as gw:
                cfg = RunConfig(policy=policy, max_steps=max_steps, map_source=MapSource.CURATED, limit=episodes)
                report = EvalRunner(gw, None, cfg, run_dir / "eval", label=backend, progress=False).run(eps, None)
        row = {k: report.row.get(k) for k in ("count", "NE", "OSR", "SR", "SPL", "nDTW", "TL", "steps", "step_s")}
        rows.append({"backend": backend if backend == "sim" else f"ros2 ({keys}, stand-in x{time_scale:g})",
                     **row, "wall_s": time.monotonic() - t0})
    return rows


def table(rows: list[dict]) -> str:
    if not rows:
        return ""
    cols = list(rows[0])
    fmt = lambda v: f"{v:.3g}" if isinstance(v, float) else str(v)
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(fmt(r.get(c)) for c in cols) + " |" for r in rows]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--what", default="panorama,images")
    ap.add_argument("--scene", default="generated:3:area=50")
    ap.add_argument("--time-scale", type=float, default=2.0)
    ap.add_argument("--camera-px", type=int, default=256)
    ap.add_argument("--panoramas", type=int, default=2)
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--episodes", type=int, default=3)
    ap.add_argument("--policy", default="heuristic")
    ap.add_argument("--max-steps", type=int, default=15)
    ap.add_argument("--keys", default="bridge,rmw_zenoh")
    ap.add_argument("--backends", default="sim,ros2", help="sr: which robot backends")
    a = ap.parse_args(argv)
    what = a.what.split(",")
    keys = a.keys.split(",")
    if "panorama" in what or "control" in what:
        print("## panorama (12 views) and control rate\n")
        print(table([bench_panorama(k, a.scene, a.time_scale, a.panoramas, a.camera_px) for k in keys]) + "\n", flush=True)
    if "images" in what:
        print("## image throughput: transport + CDR decode (pre-encoded frames)\n")
        print(table([bench_images(k, a.seconds) for k in keys]) + "\n", flush=True)
        print("## image throughput: from the stand-in (rendered frames)\n")
        print(table([bench_standin_images(k, a.scene, a.time_scale, a.camera_px, a.seconds) for k in keys]) + "\n",
              flush=True)
    if "sr" in what:
        print("## SR: embedded simulator vs ros2 backend through the stand-in (curated cloud)\n")
        print(table(bench_sr(a.scene, a.episodes, keys[0], a.time_scale, a.policy, a.max_steps,
                             tuple(a.backends.split(",")))) + "\n", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
