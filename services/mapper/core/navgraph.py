"""The exploration's navigation graph: grid node ids, visited/observed nodes, traversed edges.

Positions map to node ids through a non-uniform voxel grid (paper 4.1): ``dxy_m`` (0.2 m) across,
``dz_m`` (0.5 m) up, so two poses in one voxel are one node. A node is *visited* (the robot stood
there and looked around) or only *observed* (a candidate waypoint seen from a visited node). Edges
join only nodes the robot physically travelled between.
"""

from __future__ import annotations

import math
from enum import StrEnum

import networkx as nx
import numpy as np

from shared.schemas import NavEdge, NavGraph, NavNode


class NodeStatus(StrEnum):
    VISITED = "visited"
    FRONTIER = "frontier"  # observed, still to visit
    COVERED = "covered"  # observed, not worth a visit (a visited node is close by)
    UNREACHABLE = "unreachable"  # observed, the robot tried and could not get there


class GridGraph:
    """networkx graph keyed by voxel node ids, with the attributes the mapper needs."""

    #: Side of the buckets of the spatial index (m): "which nodes are near here" looks at 3 x 3 of
    #: them instead of every node, which keeps exploration linear in the building's size.
    BUCKET_M = 1.0

    def __init__(self, dxy_m: float = 0.2, dz_m: float = 0.5):
        if dxy_m <= 0 or dz_m <= 0:
            raise ValueError("voxel sizes must be positive")
        self.dxy_m = dxy_m
        self.dz_m = dz_m
        self.g = nx.Graph()
        self._buckets: dict[tuple[int, int], set[str]] = {}

    def _bucket(self, pos) -> tuple[int, int]:
        return (math.floor(pos[0] / self.BUCKET_M), math.floor(pos[1] / self.BUCKET_M))

    def _index(self, nid: str, old=None) -> None:
        if old is not None:
            self._buckets.get(self._bucket(old), set()).discard(nid)
        self._buckets.setdefault(self._bucket(self.g.nodes[nid]["pos"]), set()).add(nid)

    def near(self, position_m, radius_m: float, dz_m: float, *status: NodeStatus) -> list[str]:
        """Nodes of ``status`` within ``radius_m`` horizontally and ``dz_m`` vertically of a point."""
        if radius_m <= 0:
            return []
        p = np.asarray(position_m, dtype=np.float64)
        span = int(math.ceil(radius_m / self.BUCKET_M))
        bx, by = self._bucket(p)
        out = []
        for ix in range(bx - span, bx + span + 1):
            for iy in range(by - span, by + span + 1):
                for n in self._buckets.get((ix, iy), ()):
                    a = self.g.nodes[n]
                    if status and a["status"] not in status:
                        continue
                    q = a["pos"]
                    if math.hypot(q[0] - p[0], q[1] - p[1]) < radius_m and abs(q[2] - p[2]) < dz_m:
                        out.append(n)
        return sorted(out)

    @property
    def graph(self) -> nx.Graph:
        """The underlying networkx graph (alias of ``g``)."""
        return self.g

    def node_id(self, position_m) -> str:
        """The voxel id of a position: ``"ix_iy_iz"``."""
        x, y, z = (float(v) for v in position_m)
        ix = math.floor(x / self.dxy_m)
        iy = math.floor(y / self.dxy_m)
        iz = math.floor((z + 0.25 * self.dz_m) / self.dz_m)  # a floor at z=0 sits mid-voxel
        return f"{ix}_{iy}_{iz}"

    def add_visited(self, position_m, order: int) -> str:
        nid = self.node_id(position_m)
        pos = np.asarray(position_m, dtype=np.float64)
        if nid in self.g:
            attrs = self.g.nodes[nid]
            if attrs["status"] != NodeStatus.VISITED:
                old = attrs["pos"]
                attrs.update(status=NodeStatus.VISITED, pos=pos, order=order)
                self._index(nid, old)
        else:
            self.g.add_node(nid, pos=pos, status=NodeStatus.VISITED, order=order, parent=None)
            self._index(nid)
        return nid

    def add_observed(self, position_m, parent: str, score: float) -> str | None:
        """Add a candidate node seen from ``parent``; None when its voxel is already known."""
        nid = self.node_id(position_m)
        if nid in self.g:
            return None
        self.g.add_node(
            nid,
            pos=np.asarray(position_m, dtype=np.float64),
            status=NodeStatus.FRONTIER,
            parent=parent,
            score=float(score),
            order=-1,
        )
        self._index(nid)
        return nid

    def connect(self, a: str, b: str, length_m: float | None = None) -> None:
        if a == b:
            return
        if length_m is None:
            length_m = float(np.linalg.norm(self.pos(a) - self.pos(b)))
        if self.g.has_edge(a, b):
            length_m = min(length_m, self.g.edges[a, b]["length"])
        self.g.add_edge(a, b, length=float(length_m))

    def pos(self, nid: str) -> np.ndarray:
        return self.g.nodes[nid]["pos"]

    def status(self, nid: str) -> NodeStatus:
        return self.g.nodes[nid]["status"]

    def nodes_with(self, *status: NodeStatus) -> list[str]:
        return [n for n, s in self.g.nodes(data="status") if s in status]

    def positions(self, nodes: list[str]) -> np.ndarray:
        if not nodes:
            return np.zeros((0, 3))
        return np.stack([self.g.nodes[n]["pos"] for n in nodes])

    def traversed(self) -> nx.Graph:
        """Subgraph of visited nodes and the edges between them (what the robot walked)."""
        return self.g.subgraph(self.nodes_with(NodeStatus.VISITED))

    def to_schema(self, stairs: set[str] | None = None) -> NavGraph:
        """The bus message: every node (visited or observed) and every traversed edge."""
        stairs = stairs or set()
        nodes = [
            NavNode(
                node_id=n,
                position_m=tuple(float(v) for v in a["pos"]),
                visited=a["status"] == NodeStatus.VISITED,
                region=a.get("region"),
                floor=int(a.get("floor", 0) or 0),
            )
            for n, a in self.g.nodes(data=True)
        ]
        edges = [NavEdge(a=u, b=v, length_m=float(d["length"])) for u, v, d in self.g.edges(data=True)]
        return NavGraph(nodes=nodes, edges=edges, stairs=sorted(stairs))
