"""Figures of the ros2 backend against the ROS 2 stand-in (both key styles), printed as tables.

    python -m bench.ros2 [--what panorama,control,images,compressed,sr] [--episodes 4]

* panorama: time of one 12-view ``observe`` (turn, settle, capture x 12), simulated and wall, at the
  stand-in's time scale;
* control: the backend's control-loop rate while turning (ticks per wall second and per robot second);
* images: colour images the backend receives and decodes per second, from the stand-in (rendering
  bound) and from a publisher of pre-encoded 640x480 rgb8 + 16UC1 frames (the transport + CDR bound);
* compressed: raw rgb8 / jpeg / png colour and raw 16UC1 / compressedDepth depth at 640x480, bytes per
  frame and frames per second end to end (encode as image_transport does, zenoh, decode as the backend);
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


def _views_640x480(scene: str, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` rendered 640x480 colour + depth views of ``scene`` (real content: jpeg and png sizes
    depend on it; noise would not compress and a flat image would compress absurdly well)."""
    from services.robot_io.core import ROBOTS

    with ROBOTS.create("sim", {"scene": scene, "camera": {"width_px": 640, "height_px": 480, "hfov_deg": 87.0}}) as r:
        pano = r.observe()
    return pano.rgb[:n], np.nan_to_num(pano.depth_m[:n], nan=0.0, posinf=0.0)


# (row name, topic type, encoder of one view (rgb, depth_m) -> message, decoder of a message -> array)
_CODECS = {
    "rgb8 (raw)": ("image", lambda rgb, d: msgs.image(0.0, "cam", rgb, "rgb8"), msgs.image_array),
    "jpeg q90": ("compressed_image", lambda rgb, d: msgs.compressed_image(0.0, "cam", rgb, fmt="jpeg"),
                 msgs.compressed_rgb),
    "png": ("compressed_image", lambda rgb, d: msgs.compressed_image(0.0, "cam", rgb, fmt="png"), msgs.compressed_rgb),
    "16UC1 (raw)": ("image", lambda rgb, d: msgs.image(0.0, "cam", (d * 1000).astype(np.uint16), "16UC1"),
                    msgs.image_array),
    "compressedDepth png": ("compressed_image",
                            lambda rgb, d: msgs.compressed_depth(0.0, "cam", (d * 1000).astype(np.uint16)),
                            msgs.compressed_depth_m),
}


def bench_compressed(keys: str, scene: str, frames: int) -> list[dict]:
    """Raw against compressed at 640x480, end to end: the publisher encodes each frame as a camera
    driver with image_transport would, zenoh carries it, the subscriber decodes it as the backend
    does. fps = frames decoded per wall second (count-bounded: ``frames`` per codec)."""
    rgbs, depths = _views_640x480(scene, 6)
    rows = []
    for name, (type_key, encode, decode) in _CODECS.items():
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        ta, tb = _transport(listen=[endpoint]), _transport(connect=[endpoint])
        na, nb = Ros2Node(ta, key_style(keys), "cam"), Ros2Node(tb, key_style(keys), "ant")
        got, nbytes, dec_s = [0], [0], [0.0]
        all_in = threading.Event()

        def on(msg, _info, decode=decode):
            t = time.perf_counter()
            decode(msg)
            dec_s[0] += time.perf_counter() - t
            got[0] += 1
            if got[0] >= frames:
                all_in.set()

        nb.subscribe("/camera/image", msgs.MESSAGES[type_key], on, max_queue=frames)
        time.sleep(1.0)  # discovery between the two sessions
        pub = na.publisher("/camera/image", msgs.MESSAGES[type_key])
        enc_s = 0.0
        t0 = time.perf_counter()
        for i in range(frames):
            t = time.perf_counter()
            payload = msgs.encode(msgs.MESSAGES[type_key], encode(rgbs[i % len(rgbs)], depths[i % len(depths)]))
            enc_s += time.perf_counter() - t
            nbytes[0] += len(payload)
            pub.publish_raw(payload)
        all_in.wait(30.0)
        dt = time.perf_counter() - t0
        na.close(), nb.close(), ta.close(), tb.close()
        rows.append({"keys": keys, "640x480": name, "bytes_per_frame": int(nbytes[0] / frames),
                     "fps_end_to_end": got[0] / dt, "encode_ms": 1e3 * enc_s / frames,
                     "decode_ms": 1e3 * dec_s[0] / max(1, got[0]), "received": f"{got[0]}/{frames}",
                     "MB_per_s_at_30fps": nbytes[0] / frames * 30 / 1e6})
    return rows


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
    ap.add_argument("--frames", type=int, default=60, help="compressed: frames per codec")
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
    if "compressed" in what:
        print("## raw vs compressed at 640x480 (encode, zenoh, decode; rendered views)\n")
        print(table([r for k in keys for r in bench_compressed(k, a.scene, a.frames)]) + "\n", flush=True)
    if "sr" in what:
        print("## SR: embedded simulator vs ros2 backend through the stand-in (curated cloud)\n")
        print(table(bench_sr(a.scene, a.episodes, keys[0], a.time_scale, a.policy, a.max_steps,
                             tuple(a.backends.split(",")))) + "\n", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
