"""bench/bus: the project's Bus layer against raw zenoh, same payloads, same run.

* throughput of 1,000,000-point float32 xyz + uint8 rgb clouds (publish -> subscriber has arrays);
* round trip of a 12-view 256x256 RGB-D panorama query (request -> decoded arrays), p50/p99.

Targets (issue 2): project/raw throughput >= 0.8; panorama round trip p50 < 10 ms on loopback.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import zenoh

from bench.common import percentiles_ms, table
from deploy.launcher import free_port
from shared.bus.config import ZenohSettings
from shared.bus.typed import TypedBus
from shared.bus.zenoh_bus import ZenohBus
from shared.schemas import CameraIntrinsics, MapChunk, ObserveRequest, Panorama, Pose

N_POINTS = 1_000_000


def make_cloud(rng):
    return MapChunk(map_id="bench", version=1, index=0, count=1,
                    xyz_m=rng.random((N_POINTS, 3), dtype=np.float32),
                    rgb=rng.integers(0, 255, (N_POINTS, 3), dtype=np.uint8))


def make_panorama(rng):
    return Panorama(pose=Pose(position_m=(0, 0, 0)), camera=CameraIntrinsics(),
                    headings_rad=np.arange(12, dtype=np.float64),
                    rgb=rng.integers(0, 255, (12, 256, 256, 3), dtype=np.uint8),
                    depth_m=rng.random((12, 256, 256), dtype=np.float32),
                    semantic=rng.integers(0, 40, (12, 256, 256)).astype(np.int32))


def wait_for(pred, timeout_s=10.0):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if pred():
            return
        time.sleep(0.01)
    raise TimeoutError("bench setup did not become ready")


def throughput_project(a: ZenohBus, b: ZenohBus, cloud: MapChunk, n: int) -> float:
    ta, tb = TypedBus(a), TypedBus(b)
    got = []
    sub = tb.subscribe("bench/p/cloud", MapChunk, lambda k, m: got.append(m.xyz_m.shape[0]))
    wait_for(lambda: ta.publish("bench/p/cloud", cloud) or got)
    got.clear()
    t0 = time.perf_counter()
    for _ in range(n):
        ta.publish("bench/p/cloud", cloud)
    wait_for(lambda: len(got) >= n, 60)
    dt = time.perf_counter() - t0
    sub.close()
    return n / dt


def throughput_raw(sa: zenoh.Session, sb: zenoh.Session, cloud: MapChunk, n: int) -> float:
    got = []
    done = threading.Event()

    def on(sample):
        data = sample.payload.to_bytes()
        xyz = np.frombuffer(data, np.float32, N_POINTS * 3).reshape(-1, 3)
        got.append(xyz.shape[0])
        if len(got) >= n:
            done.set()

    sub = sb.declare_subscriber("bench/r/cloud", on)
    pub = sa.declare_publisher("bench/r/cloud", congestion_control=zenoh.CongestionControl.BLOCK)
    wait_for(lambda: pub.put(cloud.xyz_m.tobytes() + cloud.rgb.tobytes()) or got)
    got.clear()
    t0 = time.perf_counter()
    for _ in range(n):
        pub.put(cloud.xyz_m.tobytes() + cloud.rgb.tobytes())
    wait_for(lambda: len(got) >= n, 60)
    dt = time.perf_counter() - t0
    sub.undeclare()
    pub.undeclare()
    return n / dt


def rtt_project(a: ZenohBus, b: ZenohBus, pano: Panorama, n: int) -> list[float]:
    ta, tb = TypedBus(a), TypedBus(b)
    ent = ta.serve("bench/p/observe", ObserveRequest, lambda req: pano)
    wait_for(lambda: b.query("bench/p/observe", b"x", timeout_s=0.5))
    out = []
    for _ in range(n):
        t0 = time.perf_counter()
        rep = tb.request("bench/p/observe", ObserveRequest(), Panorama)
        assert rep.depth_m.shape == (12, 256, 256)
        out.append(time.perf_counter() - t0)
    ent.close()
    return out


def rtt_raw(sa: zenoh.Session, sb: zenoh.Session, pano: Panorama, n: int) -> list[float]:
    blob = pano.rgb.tobytes() + pano.depth_m.tobytes() + pano.semantic.tobytes()
    q = sa.declare_queryable("bench/r/observe", lambda query: query.reply("bench/r/observe", blob))
    wait_for(lambda: list(sb.get("bench/r/observe", timeout=0.5)))
    out = []
    rgb_n = pano.rgb.nbytes
    for _ in range(n):
        t0 = time.perf_counter()
        (reply,) = list(sb.get("bench/r/observe", payload=b"x", timeout=5))
        data = reply.ok.payload.to_bytes()
        depth = np.frombuffer(data, np.float32, 12 * 256 * 256, offset=rgb_n).reshape(12, 256, 256)
        assert depth.shape == (12, 256, 256)
        out.append(time.perf_counter() - t0)
    q.undeclare()
    return out


def main() -> dict:
    rng = np.random.default_rng(0)
    cloud, pano = make_cloud(rng), make_panorama(rng)
    port = free_port()
    a = ZenohBus(ZenohSettings(listen=[f"tcp/127.0.0.1:{port}"]))
    b = ZenohBus(ZenohSettings(connect=[f"tcp/127.0.0.1:{port}"]))
    wait_for(lambda: (a.liveliness_token("bench/alive/a") and b.alive("bench/alive/a", timeout_s=0.5)))
    n_clouds, n_rtt = 30, 300
    # Interleave raw and project runs so that a noisy neighbour hurts both alike.
    raw_tp, proj_tp = [], []
    for _ in range(2):
        raw_tp.append(throughput_raw(a.session, b.session, cloud, n_clouds))
        proj_tp.append(throughput_project(a, b, cloud, n_clouds))
    raw_rtt = rtt_raw(a.session, b.session, pano, n_rtt)
    proj_rtt = rtt_project(a, b, pano, n_rtt)
    b.close()
    a.close()
    mb = (cloud.xyz_m.nbytes + cloud.rgb.nbytes) / 1e6
    tp_raw, tp_proj = max(raw_tp), max(proj_tp)
    pr, pp = percentiles_ms(raw_rtt), percentiles_ms(proj_rtt)
    table("bus: 1M-point xyz+rgb cloud throughput (publish -> arrays at subscriber)",
          [("raw zenoh", tp_raw, tp_raw * mb), ("project Bus", tp_proj, tp_proj * mb),
           ("ratio project/raw", tp_proj / tp_raw, "target >= 0.8")],
          ("path", "clouds/s", "MB/s"))
    table("bus: 12-view 256x256 RGB-D(+semantic) panorama query round trip",
          [("raw zenoh", pr["p50"], pr["p99"]), ("project Bus", pp["p50"], pp["p99"]),
           ("ratio p50 project/raw", pp["p50"] / pr["p50"], "target p50 < 10 ms")],
          ("path", "p50 ms", "p99 ms"))
    return {"throughput_ratio": tp_proj / tp_raw, "rtt_p50_ms": pp["p50"], "rtt_p99_ms": pp["p99"]}


if __name__ == "__main__":
    main()
