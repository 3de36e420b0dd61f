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
    """networkx graph keyed by voxel node ids, with the attributes the mapper needs.

    A node's status changes only through :meth:`set_status` (and :meth:`add_visited`), and edges
    only through :meth:`connect` and :meth:`remove_edge`: the graph keeps indexes in step with them
    (nodes by status and 1 m bucket, the walked subgraph), which exploration asks tens of thousands
    of times; rebuilding those answers from every node each time was a third of the mapper's own
    time at 1,000 m2.
    """

    #: Side of the buckets of the spatial index (m): "which nodes are near here" looks at 3 x 3 of
    #: them instead of every node, which keeps exploration linear in the building's size.
    BUCKET_M = 1.0

    def __init__(self, dxy_m: float = 0.2, dz_m: float = 0.5):
        if dxy_m <= 0 or dz_m <= 0:
            raise ValueError("voxel sizes must be positive")
        self.dxy_m = dxy_m
        self.dz_m = dz_m
        self.g = nx.Graph()
        # (status, bucket x, bucket y) -> {node: (x, y, z)}: ``near`` reads only the statuses asked.
        self._buckets: dict[tuple[NodeStatus, int, int], dict[str, tuple[float, float, float]]] = {}
        self._key: dict[str, tuple[NodeStatus, int, int]] = {}
        self._by_status: dict[NodeStatus, set[str]] = {s: set() for s in NodeStatus}
        self._seq: dict[str, int] = {}  # insertion order: ``nodes_with`` keeps the graph's order
        # The visited nodes and their edges as a graph of its own, edges added and removed with the
        # main graph's (so every node's neighbours come in the same order, and a shortest path on
        # it is the one on ``traversed()``, without building a filtered view each time).
        self._walked = nx.Graph()

    def _unindex(self, nid: str) -> None:
        key = self._key.pop(nid, None)
        if key is not None:
            self._buckets[key].pop(nid, None)
            self._by_status[key[0]].discard(nid)

    def _index(self, nid: str) -> None:
        a = self.g.nodes[nid]
        pos = a["pos"]
        key = (a["status"], math.floor(pos[0] / self.BUCKET_M), math.floor(pos[1] / self.BUCKET_M))
        self._buckets.setdefault(key, {})[nid] = (float(pos[0]), float(pos[1]), float(pos[2]))
        self._key[nid] = key
        self._by_status[a["status"]].add(nid)
        self._seq.setdefault(nid, len(self._seq))

    def near(self, position_m, radius_m: float, dz_m: float, *status: NodeStatus) -> list[str]:
        """Nodes of ``status`` (any, if none given) within ``radius_m`` horizontally and ``dz_m``
        vertically of a point, sorted by id."""
        if radius_m <= 0:
            return []
        px, py, pz = (float(v) for v in position_m)
        span = int(math.ceil(radius_m / self.BUCKET_M))
        bx, by = math.floor(px / self.BUCKET_M), math.floor(py / self.BUCKET_M)
        out = []
        for st in status or tuple(NodeStatus):
            for ix in range(bx - span, bx + span + 1):
                for iy in range(by - span, by + span + 1):
                    bucket = self._buckets.get((st, ix, iy))
                    if not bucket:
                        continue
                    for n, (x, y, z) in bucket.items():
                        if math.hypot(x - px, y - py) < radius_m and abs(z - pz) < dz_m:
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
                self._unindex(nid)
                attrs.update(status=NodeStatus.VISITED, pos=pos, order=order)
                self._index(nid)
                self._now_visited(nid)
        else:
            self.g.add_node(nid, pos=pos, status=NodeStatus.VISITED, order=order, parent=None)
            self._index(nid)
            self._now_visited(nid)
        return nid

    def _now_visited(self, nid: str) -> None:
        self._walked.add_node(nid)
        for m, d in self.g.adj[nid].items():  # none in exploration: edges join visited nodes only
            if self.g.nodes[m]["status"] == NodeStatus.VISITED:
                self._walked.add_edge(nid, m, **d)

    def set_status(self, nid: str, status: NodeStatus) -> None:
        """An observed node resolved (covered, unreachable, ...); a node becomes visited only by
        :meth:`add_visited`, and a visited one stays so."""
        a = self.g.nodes[nid]
        if a["status"] == status:
            return
        if NodeStatus.VISITED in (a["status"], status):
            raise ValueError(f"node {nid}: {a['status']} -> {status}: visited is set by add_visited only")
        self._unindex(nid)
        a["status"] = status
        self._index(nid)

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

    def connect(self, a: str, b: str, length_m: float | None = None, narrow: bool = False) -> None:
        """Join ``a`` and ``b`` by a walked edge. ``narrow``: laid on the way through a passage only
        the narrow body passes, so walking it again may take a sidestep (sidestep.py); kept once set."""
        if a == b:
            return
        if length_m is None:
            length_m = float(np.linalg.norm(self.pos(a) - self.pos(b)))
        if self.g.has_edge(a, b):
            length_m = min(length_m, self.g.edges[a, b]["length"])
            narrow = narrow or bool(self.g.edges[a, b].get("narrow", False))
        self.g.add_edge(a, b, length=float(length_m), narrow=narrow)
        if a in self._walked and b in self._walked:
            self._walked.add_edge(a, b, length=float(length_m), narrow=narrow)

    def narrow(self, a: str, b: str) -> bool:
        """Was the edge ``a``-``b`` laid through a narrow passage (see :meth:`connect`)?"""
        return bool(self.g.has_edge(a, b) and self.g.edges[a, b].get("narrow", False))

    def remove_edge(self, a: str, b: str) -> None:
        """Forget an edge (one that could not be walked again), if there is one."""
        if self.g.has_edge(a, b):
            self.g.remove_edge(a, b)
        if self._walked.has_edge(a, b):
            self._walked.remove_edge(a, b)

    def move(self, positions_m: dict[str, np.ndarray]) -> None:
        """Re-place nodes (the pose graph's correction of a drifting exploration, replace.py). The ids
        stay: they name the nodes in edges, tours, regions and parents, and a node is where its
        panorama was taken, not a voxel lookup; the spatial index follows the new positions."""
        for nid, p in positions_m.items():
            self._unindex(nid)
            self.g.nodes[nid]["pos"] = np.asarray(p, dtype=np.float64)
            self._index(nid)

    def pos(self, nid: str) -> np.ndarray:
        return self.g.nodes[nid]["pos"]

    def status(self, nid: str) -> NodeStatus:
        return self.g.nodes[nid]["status"]

    def nodes_with(self, *status: NodeStatus) -> list[str]:
        """The nodes of these statuses, in the order they joined the graph."""
        if len(status) == 1:
            found = self._by_status[status[0]]
        else:
            found = set().union(*(self._by_status[s] for s in status))
        return sorted(found, key=self._seq.__getitem__)

    def positions(self, nodes: list[str]) -> np.ndarray:
        if not nodes:
            return np.zeros((0, 3))
        return np.stack([self.g.nodes[n]["pos"] for n in nodes])

    def traversed(self) -> nx.Graph:
        """Subgraph of visited nodes and the edges between them (what the robot walked)."""
        return self.g.subgraph(self.nodes_with(NodeStatus.VISITED))

    def walked(self) -> nx.Graph:
        """The same nodes and edges as :meth:`traversed`, as a graph kept up to date (no view to
        build): exploration plans on it after every move. Read it, never change it."""
        return self._walked

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
