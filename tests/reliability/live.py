"""A live system in one test process: a real zenoh router on a free loopback port and every service
that serves a queryable (robot-io, mapper, reconstructor, renderer, planner) as a real service, each
on its own zenoh session, plus a gateway app on its own session for HTTP (TestClient).

Lighter than the process-level ``system`` fixture (no interpreter per service), so the fuzz and
forgery classes can try every queryable and every event kind in seconds, while every message still
crosses a real zenoh router.
"""

from __future__ import annotations

import contextlib
import json
from dataclasses import dataclass, field
from pathlib import Path

from deploy.launcher import free_port
from shared import keys
from shared.bus.config import ZenohSettings, zenoh_config
from shared.bus.typed import TypedBus
from shared.bus.zenoh_bus import ZenohBus
from shared.runner import RunningService
from shared.schemas import MapImportRequest, MapInfo
from tests.waiting import wait_until

ROBOT = "robot0"
LIVE_MAP = "live-house"
CAMERA = {"width_px": 48, "height_px": 48, "hfov_deg": 90.0}


@dataclass
class Live:
    endpoint: str
    bus: ZenohBus
    typed: TypedBus
    services: dict[str, RunningService]
    run_dir: Path
    buses: dict[str, ZenohBus] = field(default_factory=dict)
    makers: dict[str, object] = field(default_factory=dict)

    def service(self, name: str):
        return self.services[name].service

    def kill(self, name: str) -> None:
        """As close to SIGKILL as one process allows: the service's zenoh session goes first (its
        token drops, nothing more it says reaches anyone), then its threads are stopped."""
        self.buses.pop(name).close()
        with contextlib.suppress(Exception):
            self.services.pop(name).close()

    def start(self, name: str) -> None:
        """(Re)start a service under the same instance name: a new incarnation."""
        b = ZenohBus(ZenohSettings(connect=[self.endpoint]))
        self.buses[name] = b
        self.services[name] = RunningService(self.makers[name](), b)
        instance = self.services[name].node.instance
        wait_until(lambda: self.bus.alive(keys.ALIVE.format(service=name, instance=instance), timeout_s=0.5), 20,
                   f"{name} seen alive again")


@contextlib.contextmanager
def live_system(run_dir: Path, *, map_ply: bytes):
    import zenoh

    from services.mapper.service import MapperService, MapperSettings
    from services.planner.service import PlannerService, PlannerSettings
    from services.reconstructor.service import ReconstructorService, ReconstructorSettings
    from services.renderer.service import RendererService, RendererSettings
    from services.robot_io.service import RobotIoService, RobotIoSettings

    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    router = zenoh.open(zenoh_config(ZenohSettings(mode="router", listen=[endpoint])))
    live = None
    try:
        def bus() -> ZenohBus:
            return ZenohBus(ZenohSettings(connect=[endpoint]))

        specs = {
            "robot_io": lambda: RobotIoService(RobotIoSettings(
                instance="io-live", robot_config={"scene": "generated:0", "camera": CAMERA})),
            "reconstructor": lambda: ReconstructorService(ReconstructorSettings(
                instance="rec-live", store_dir=str(run_dir / "maps"))),
            "renderer": lambda: RendererService(RendererSettings(instance="ren-live")),
            "mapper": lambda: MapperService(MapperSettings(instance="map-live")),
            "planner": lambda: PlannerService(PlannerSettings(instance="plan-live", call_timeout_s=20.0)),
        }
        buses, running = {}, {}
        for name, make in specs.items():
            buses[name] = bus()
            running[name] = RunningService(make(), buses[name])
        client = bus()
        live = Live(endpoint, client, TypedBus(client, "live-test"), running, run_dir, buses, dict(specs))
        wait_until(lambda: len(client.alive(keys.ALIVE.pattern(), timeout_s=0.5)) >= len(specs), 30,
                   "every live service seen through the router")
        live.typed.request(keys.MAP_IMPORT.format(map=LIVE_MAP),
                           MapImportRequest(map_id=LIVE_MAP, filename="scene.ply", data=map_ply), MapInfo,
                           timeout_s=60)
        yield live
    finally:
        if live is not None:
            for r in reversed(list(live.services.values())):
                r.close()
            for b in live.buses.values():
                b.close()
            live.bus.close()
        router.close()


def gateway_settings(live: Live, tmp: Path, **overrides):
    from services.gateway.settings import GatewaySettings

    return GatewaySettings(instance=overrides.pop("instance", "gw-live"), db_path=tmp / "gw.sqlite3",
                           zenoh=ZenohSettings(connect=[live.endpoint]), request_timeout_s=10.0,
                           sse_keepalive_s=0.2, **overrides)


def dumps(obj) -> str:
    return json.dumps(obj, default=str)
