"""Upload memory (issue 31 item 4): a large PLY streamed through the gateway into the reconstructor.

The launcher's router, reconstructor and gateway run as real processes, authenticated and behind the
generated ACL as in production. A cloud file of ``--mb`` megabytes (default 500) is written to
``--dir`` (default /tmp) a slice at a time and POSTed from the file as the request body; ``--format``:
ours (a PLY in the store's layout, copied slice by slice), ply-foreign (double xyz, extra properties:
converted a chunk at a time) or pcd (binary, converted likewise). Before the
measured upload each process's peak RSS (VmHWM) is reset to its current RSS (``/proc/<pid>/clear_refs``
5), so the peak afterwards is what the upload cost it. A first small upload runs before (``--no-warm``
skips it): whatever a first upload costs once (code paths run the first time, the bus's part
buffers, allocator arenas) is not the file's size.

The last line printed is the verdict: each process's peak RSS growth against ``--limit-mb`` (150).

    nice -n 5 python -m bench.upload [--mb 500] [--format ours|ply-foreign|pcd] [--dir /tmp/x]
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

from bench.common import table, wait_gateway
from shared.cloud import header, records

MB = 1 << 20
SERVICES = ("gateway", "reconstructor")


def write_ply(path: Path, size_bytes: int, seed: int = 0) -> int:
    """A PLY in our layout (15 bytes a point) of about ``size_bytes``, written a slice at a time."""
    rng = np.random.default_rng(seed)
    count = size_bytes // 15
    with open(path, "wb") as fh:
        fh.write(header(count, False, comment="bench.upload"))
        left = count
        while left:
            n = min(left, 1_000_000)
            fh.write(records(rng.uniform(-20.0, 20.0, (n, 3)).astype(np.float32),
                             rng.integers(0, 256, (n, 3), dtype=np.uint8)))
            left -= n
    return count


def write_foreign_ply(path: Path, size_bytes: int, seed: int = 0) -> int:
    """A PLY of another layout than ours (32 bytes a point): double xyz, an extra float, colour after
    it with an alpha channel - what a scanner's export looks like; the store converts it a chunk at a
    time."""
    dt = np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("intensity", "<f4"), ("red", "u1"), ("green", "u1"),
                   ("blue", "u1"), ("alpha", "u1")])
    props = "".join(f"property {t} {n}\n" for t, n in (("double", "x"), ("double", "y"), ("double", "z"),
                                                        ("float", "intensity"), ("uchar", "red"), ("uchar", "green"),
                                                        ("uchar", "blue"), ("uchar", "alpha")))
    count = size_bytes // dt.itemsize
    head = f"ply\nformat binary_little_endian 1.0\ncomment bench.upload\nelement vertex {count}\n{props}end_header\n"
    return _write_records(path, head.encode(), dt, count, seed)


def write_pcd(path: Path, size_bytes: int, seed: int = 0) -> int:
    """A binary PCD (16 bytes a point: x y z and the packed rgb float)."""
    dt = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")])
    count = size_bytes // dt.itemsize
    head = ("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
            f"WIDTH {count}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {count}\nDATA binary\n")
    return _write_records(path, head.encode(), dt, count, seed)


def _write_records(path: Path, head: bytes, dt: np.dtype, count: int, seed: int) -> int:
    rng = np.random.default_rng(seed)
    with open(path, "wb") as fh:
        fh.write(head)
        left = count
        while left:
            n = min(left, 1_000_000)
            rec = np.zeros(n, dt)
            for axis in "xyz":
                rec[axis] = rng.uniform(-20.0, 20.0, n)
            if "rgb" in dt.names:
                rec["rgb"] = rng.integers(0, 1 << 24, n, dtype=np.uint32)
            else:
                for ch in ("red", "green", "blue", "alpha"):
                    rec[ch] = rng.integers(0, 256, n, dtype=np.uint8)
            fh.write(rec.tobytes())
            left -= n
    return count


# --format -> (file suffix, writer): the import path each exercises (ours: copied slice by slice;
# the others: converted a chunk at a time by services/reconstructor/core/foreign.py).
FORMATS = {"ours": (".ply", write_ply), "ply-foreign": (".ply", write_foreign_ply), "pcd": (".pcd", write_pcd)}


def _status_kb(pid: int, field: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise KeyError(field)


def _upload(url: str, path: Path, map_id: str) -> dict:
    with httpx.Client(base_url=url, timeout=1800) as http, open(path, "rb") as body:
        r = http.post("/maps", params={"map_id": map_id, "filename": path.name}, content=body,
                      headers={"Content-Type": "application/octet-stream",
                               "Content-Length": str(path.stat().st_size)})
    if r.status_code != 201:
        raise RuntimeError(f"upload of {path.name} answered {r.status_code}: {r.text[:500]}")
    return r.json()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mb", type=int, default=500, help="size of the uploaded PLY in MiB")
    ap.add_argument("--dir", default=None, help="where the PLY and the run's files go (default: a /tmp folder)")
    ap.add_argument("--limit-mb", type=float, default=150.0, help="peak RSS growth allowed per process")
    ap.add_argument("--no-warm", action="store_true", help="measure the first upload (no warm-up upload)")
    ap.add_argument("--format", choices=sorted(FORMATS), default="ours",
                    help="ours: a PLY in the store's layout; ply-foreign: double xyz, extra properties; pcd: binary PCD")
    args = ap.parse_args()
    if not Path("/proc/self/clear_refs").exists():
        print("bench.upload needs Linux /proc (clear_refs, VmHWM): skipped")
        return 0
    from deploy.launcher import Launcher

    work = Path(tempfile.mkdtemp(prefix="bench-upload-", dir=args.dir))
    try:
        suffix, writer = FORMATS[args.format]
        ply = work / f"big{suffix}"
        t0 = time.perf_counter()
        points = writer(ply, args.mb * MB)
        size = ply.stat().st_size
        print(f"wrote {ply} ({size / MB:.0f} MiB, {points} points) in {time.perf_counter() - t0:.1f} s", flush=True)
        (work / "run").mkdir()
        env = {"ANT_LOG_LEVEL": "WARNING", "ANT_REQUEST_TIMEOUT_S": "120"}
        with Launcher(work / "run", services=list(SERVICES), extra_env=env, restart=False) as launcher:
            url = launcher.gateway_url
            if not wait_gateway(url, 120.0, interval_s=0.5):
                raise TimeoutError("the gateway did not reach the reconstructor within 120 s")
            pids = {name: launcher.proc(f"{name}-0").popen.pid for name in SERVICES}
            if not args.no_warm:
                warm = work / f"warm{suffix}"
                writer(warm, 8 * MB, seed=1)
                _upload(url, warm, "warm")
            before = {}
            for name, pid in pids.items():
                Path(f"/proc/{pid}/clear_refs").write_text("5")  # VmHWM := current RSS
                before[name] = _status_kb(pid, "VmRSS")
            t0 = time.perf_counter()
            info = _upload(url, ply, "big")
            took_s = time.perf_counter() - t0
            growth = {n: (_status_kb(p, "VmHWM") - before[n]) / 1024 for n, p in pids.items()}
            left = {n: (_status_kb(p, "VmRSS") - before[n]) / 1024 for n, p in pids.items()}
        if info["point_count"] != points:
            raise RuntimeError(f"stored {info['point_count']} points, uploaded {points}")
        table(f"upload of a {size / MB:.0f} MiB {args.format} file ({points} points) in {took_s:.1f} s "
              f"({size / MB / took_s:.1f} MiB/s)",
              [(n, before[n] / 1024, growth[n], left[n], growth[n] / (size / MB)) for n in SERVICES],
              ("process", "RSS before (MiB)", "peak growth (MiB)", "RSS left (MiB)", "growth / file size"))
        ok = all(g < args.limit_mb for g in growth.values())
        print(f"upload {size / MB:.0f} MiB {args.format}: peak RSS growth gateway {growth['gateway']:.0f} MiB, "
              f"reconstructor {growth['reconstructor']:.0f} MiB (limit {args.limit_mb:.0f} MiB each): "
              f"{'PASS' if ok else 'FAIL'}", flush=True)
        shutil.rmtree(work, ignore_errors=True)
        return 0 if ok else 1
    except BaseException:
        for p in [*work.glob("*.ply"), *work.glob("*.pcd")]:  # the big files go; the run's logs stay for a look
            p.unlink()
        print(f"bench.upload failed: logs under {work / 'run' / 'logs'}", file=sys.stderr)
        raise


if __name__ == "__main__":
    sys.exit(main())
