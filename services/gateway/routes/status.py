from __future__ import annotations

from collections import defaultdict

from fastapi import APIRouter
from pydantic import BaseModel, Field

from services.gateway.deps import BusDep, SettingsDep
from shared.clients import ServicesClient
from shared.schemas import ServiceInfo

router = APIRouter(tags=["status"])


class InstanceStatus(BaseModel):
    instance: str
    version: str | None = None
    backends: dict[str, str] = Field(default_factory=dict)
    uptime_s: float | None = None
    healthy: bool | None = Field(None, description="False: alive but its state is broken; None: info did not answer")
    problem: str = ""


class ServiceStatus(BaseModel):
    service: str
    instances: int
    details: list[InstanceStatus]


class SystemStatus(BaseModel):
    services: list[ServiceStatus]
    all_alive: bool
    all_healthy: bool = Field(description="every expected service alive, and no instance reports a broken state")
    expected: list[str]


EXPECTED = ["gateway", "mapper", "planner", "reconstructor", "renderer", "robot_io"]


@router.get("/status", response_model=SystemStatus)
def status(bus: BusDep, settings: SettingsDep) -> SystemStatus:
    """Every service instance seen alive (its liveliness token, or its info queryable answering), with
    versions from its info."""
    import time

    services_client = ServicesClient(bus, timeout_s=settings.status_timeout_s)
    infos: dict[tuple[str, str], ServiceInfo] = {(r.service, r.instance): r for r in services_client.infos()}
    # Alive: its liveliness token or its info answered, as the job reaper judges a worker. A loaded
    # system's liveliness query can end without a busy instance's reply (seen: `make up` printed
    # "running" and /status then said all_alive false while every service answered its info).
    alive = sorted(set(services_client.alive()) | set(infos))
    by_service: dict[str, list[InstanceStatus]] = defaultdict(list)
    now = time.time()
    for service, instance in alive:
        info = infos.get((service, instance))
        by_service[service].append(InstanceStatus(
            instance=instance,
            version=info.version if info else None,
            backends=info.backends if info else {},
            uptime_s=round(now - info.started_s, 3) if info else None,
            healthy=info.healthy if info else None, problem=info.problem if info else "",
        ))
    services = [ServiceStatus(service=s, instances=len(v), details=v) for s, v in sorted(by_service.items())]
    all_alive = set(EXPECTED) <= by_service.keys()
    healthy = all_alive and all(d.healthy is not False for v in by_service.values() for d in v)
    return SystemStatus(services=services, all_alive=all_alive, all_healthy=healthy, expected=EXPECTED)
