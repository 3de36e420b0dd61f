"""Candidates, navigation graphs and tours."""

from __future__ import annotations

from enum import StrEnum

from pydantic import Field

from shared.arrays import Array

from .base import BUILD_MAX_FRAMES, Distance_m, Message, Metres, Radians, Seconds, SegmentId, Xyz_m
from .geometry import Pose


# --- candidates, graphs, tours -------------------------------------------------------------------


class CandidateKind(StrEnum):
    WAYPOINT = "waypoint"
    BACKTRACK = "backtrack"
    STOP = "stop"


class Candidate(Message):
    """A possible action: a waypoint (dx, dy) in world axes, a backtrack, or stop."""

    index: int = Field(ge=0, le=10_000)
    kind: CandidateKind = CandidateKind.WAYPOINT
    dx_m: Metres = 0.0
    dy_m: Metres = 0.0
    angle_rad: Radians = 0.0  # relative to the agent heading, positive = left
    distance_m: Distance_m = 0.0
    score: float = Field(0.0, ge=-1e9, le=1e9)


class CandidateSet(Message):
    pose: Pose
    candidates: list[Candidate]


class NavNode(Message):
    # Bounded like every number a request carries: the graph now travels in BuildMapRequest (issue 32).
    node_id: str
    position_m: Xyz_m
    visited: bool
    region: int | None = Field(None, ge=-1, le=100_000)
    floor: int = Field(0, ge=-100, le=100)


class NavEdge(Message):
    a: str
    b: str
    length_m: Distance_m


class NavGraph(Message):
    nodes: list[NavNode]
    edges: list[NavEdge]
    stairs: list[str] = Field(default_factory=list)


class Tour(Message):
    region: int
    start_pose: Pose
    hubs_m: Array("float64", 2)  # (K, 3) hub positions in visiting order
    path_m: Array("float64", 2)  # (P, 3) dense refined path
    coverage: float


class OdomCorrection(Message):
    """The mapper's map <- odom correction from robot time ``since_s`` on (until the next one):
    ``map = odom + (dx, dy)``, ``heading_map = heading_odom + dyaw`` (issue 33)."""

    since_s: Seconds
    dx_m: Metres
    dy_m: Metres
    dyaw_rad: Radians


class TourRecording(Message):
    """A finished recorded tour; its frames were published on ``IO_FRAMES`` under ``recording``."""

    exploration_id: SegmentId
    recording: SegmentId
    region: int = Field(ge=-1, le=100_000)
    start_pose: Pose  # as the frames report it: the robot's odometry
    frame_count: int = Field(ge=0, le=BUILD_MAX_FRAMES)
    # The frames carry the robot's odometry poses; the mapper localised the robot meanwhile, and
    # these corrections (in time order, each from its robot time on) put a frame, and ``start_pose``,
    # in the map frame that the exploration's graph and the other regions share. Empty: none known.
    odom_corrections: list[OdomCorrection] = Field(default_factory=list, max_length=10_000)
    # True: a frame takes the correction interpolated in time between the entries around it (each
    # entry a panorama placed by the mapper's pose graph), not the latest one.
    odom_corrections_interpolated: bool = False
