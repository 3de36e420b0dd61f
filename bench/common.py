"""Small helpers shared by the benchmark scripts (they print; they are not tests)."""

from __future__ import annotations

import time

import numpy as np


def percentiles_ms(samples_s, qs=(50, 95, 99)) -> dict[str, float]:
    a = np.asarray(samples_s) * 1e3
    return {f"p{q}": float(np.percentile(a, q)) for q in qs}


def table_markdown(title: str, rows: list[tuple], header: tuple) -> str:
    """The markdown of ``table`` (a bench that also writes its table to a file under runs/ uses this)."""
    lines = [f"## {title}", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(f"{v:.3g}" if isinstance(v, float) else str(v) for v in r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def table(title: str, rows: list[tuple], header: tuple) -> None:
    print("\n" + table_markdown(title, rows, header), end="")


class Timer:
    def __enter__(self):
        self.t0 = time.perf_counter()
        return self

    def __exit__(self, *exc):
        self.s = time.perf_counter() - self.t0


def wait_gateway(url: str, deadline_s: float, alive=lambda: True, interval_s: float = 0.2) -> bool:
    """Wait until the gateway at ``url`` answers ``GET /maps`` (it reaches the map store); False when
    ``deadline_s`` passes or ``alive()`` says the process died first."""
    import httpx

    end = time.monotonic() + deadline_s
    while time.monotonic() < end and alive():
        try:
            if httpx.get(f"{url}/maps", timeout=2).status_code == 200:
                return True
        except httpx.HTTPError:
            pass
        time.sleep(interval_s)
    return False
