"""Backends registered by name with a typed config (the lerobot pattern).

A port (robot, waypoint predictor, reconstruction, metric depth, policy) owns one ``Registry``.
Implementations register themselves with their config class; services create them from the name
in their settings. Fakes register exactly like real backends.

    ROBOTS = Registry[Robot]("robot")

    class SimConfig(BackendConfig):
        scene: str = "generated:0"

    @ROBOTS.register("sim", SimConfig)
    class SimRobot(Robot): ...

    robot = ROBOTS.create("sim", {"scene": "generated:3"})
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, Generic, TypeVar

from pydantic import BaseModel, ConfigDict

T = TypeVar("T")


class BackendConfig(BaseModel):
    """Base of every backend config: unknown fields are an error, not silently ignored."""

    model_config = ConfigDict(extra="forbid")


class UnknownBackendError(KeyError):
    def __init__(self, kind: str, name: str, known: list[str]):
        super().__init__(f"unknown {kind} backend {name!r}; known: {', '.join(known) or 'none'}")
        self.kind, self.name, self.known = kind, name, known

    def __str__(self) -> str:  # KeyError quotes its message; we want it plain
        return self.args[0]


class Registry(Generic[T]):
    def __init__(self, kind: str):
        self.kind = kind
        self._entries: dict[str, tuple[Callable[..., T], type[BackendConfig]]] = {}

    def register(self, name: str, config_cls: type[BackendConfig] = BackendConfig):
        def deco(factory):
            if name in self._entries:
                raise ValueError(f"{self.kind} backend {name!r} registered twice")
            self._entries[name] = (factory, config_cls)
            return factory

        return deco

    def names(self) -> list[str]:
        return sorted(self._entries)

    def config_class(self, name: str) -> type[BackendConfig]:
        return self._lookup(name)[1]

    def create(self, name: str, config: BackendConfig | Mapping[str, Any] | None = None) -> T:
        factory, config_cls = self._lookup(name)
        if config is None:
            cfg = config_cls()
        elif isinstance(config, BackendConfig):
            if not isinstance(config, config_cls):
                raise TypeError(f"{self.kind} backend {name!r} takes {config_cls.__name__}")
            cfg = config
        else:
            cfg = config_cls.model_validate(dict(config))
        return factory(cfg)

    def _lookup(self, name: str):
        try:
            return self._entries[name]
        except KeyError:
            raise UnknownBackendError(self.kind, name, self.names()) from None
