"""Writers of the formats robotics tools read: Nav2 maps, PCD clouds, trajectory CSV.

Pure functions of numpy arrays (no bus, no service): the gateway streams them as downloads, the
evaluation and the tools write them to files. The PLY layout lives in :mod:`shared.cloud`; Rerun
recordings in :mod:`shared.recording`.
"""

from shared.export.nav2 import (
    FREE, OCCUPIED, UNKNOWN, Nav2Map, OccupancyConfig, floor_z_of, nav2_files, occupancy_from_cloud,
)
from shared.export.pcd import encode_pcd
from shared.export.trajectory import trajectory_csv

__all__ = [
    "FREE", "OCCUPIED", "UNKNOWN", "Nav2Map", "OccupancyConfig", "encode_pcd", "floor_z_of", "nav2_files",
    "occupancy_from_cloud", "trajectory_csv",
]
