"""reconstructor service: the bus adapter around its core (decode request -> call core -> encode reply)."""

from __future__ import annotations

from shared.runner import Node, Service, ServiceSettings


class ReconstructorServiceSettings(ServiceSettings):
    pass


class ReconstructorService(Service):
    name = "reconstructor"
    Settings = ReconstructorServiceSettings

    def start(self, node: Node) -> None:
        # info and metrics queryables and the liveliness token come from the runner.
        pass
