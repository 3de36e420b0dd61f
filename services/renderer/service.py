"""renderer service: the bus adapter around its core (decode request -> call core -> encode reply)."""

from __future__ import annotations

from shared.runner import Node, Service, ServiceSettings


class RendererServiceSettings(ServiceSettings):
    pass


class RendererService(Service):
    name = "renderer"
    Settings = RendererServiceSettings

    def start(self, node: Node) -> None:
        # info and metrics queryables and the liveliness token come from the runner.
        pass
