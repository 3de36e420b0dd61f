"""``make bench``: every benchmark script in turn (each prints its own table)."""

from __future__ import annotations

import importlib
import sys
import time

# Each entry is a module with a main(); the order runs the cheap ones first.
BENCHES = ["bench.bus", "bench.robot_io", "bench.scene_files", "bench.renderer", "bench.mapper", "bench.reconstructor",
           "bench.planner", "bench.vlm_layouts", "bench.gateway", "bench.replicas", "bench.reliability", "bench.export"]


def main(argv: list[str]) -> int:
    wanted = [f"bench.{a}" for a in argv] or BENCHES
    failed = []
    for name in wanted:
        try:
            mod = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name == name:
                continue  # not written yet
            raise
        print(f"\n# {name}  ({time.strftime('%H:%M:%S')})", flush=True)
        try:
            # Each bench parses its own flags: give it none of ours.
            saved, sys.argv = sys.argv, [name]
            try:
                mod.main()
            finally:
                sys.argv = saved
        except Exception as exc:  # one broken bench must not hide the others' figures
            failed.append(name)
            print(f"{name} FAILED: {type(exc).__name__}: {exc}", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
