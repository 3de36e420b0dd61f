"""Reconstructor core: physically grounded scene reconstruction and the map store (paper 4.2).

Pure Python (numpy / open3d / scipy / scikit-image); never imports zenoh. The bus adapter
(``services/reconstructor/service.py``) decodes requests, calls :class:`Reconstructor` and
:class:`MapStore`, and encodes their results.
"""

from .align import AlignmentConfig, AlignmentReport, MetricAligner, to_world
from .depth import DEFAULT_METRIC_DEPTH, METRIC_DEPTH, DepthAnythingConfig, MetricDepth, SensorDepth
from .errors import (
    AlignmentError,
    BackendUnavailableError,
    EmptyRecordingError,
    InputError,
    InvalidFrameError,
    InvalidMapIdError,
    MapFormatError,
    MapNotFoundError,
    MapStoreError,
    MissingDepthError,
    ReconstructorError,
)
from .frames import PosedImage, RegionInput, posed_from_frame, posed_from_matrix, region_from_frames, region_from_recording
from .pipeline import MapBuild, ReconstructionConfig, Reconstructor, RegionReport, chamfer
from .regional import (
    DEFAULT_RECONSTRUCTOR,
    RECONSTRUCTORS,
    MonoSimConfig,
    RegionalCloud,
    RegionalReconstructor,
    RgbdConfig,
)
from .slam3r import Slam3rConfig
from .store import MapStore, StoredMap
from . import kernels  # noqa: F401  (services warm the fusion kernels up through it)
from .voxel import VoxelAccumulator, voxel_downsample

__all__ = [
    "DEFAULT_METRIC_DEPTH", "DEFAULT_RECONSTRUCTOR", "METRIC_DEPTH", "RECONSTRUCTORS", "AlignmentConfig",
    "AlignmentError", "AlignmentReport", "BackendUnavailableError", "DepthAnythingConfig",
    "EmptyRecordingError", "InputError", "InvalidFrameError", "InvalidMapIdError", "MapBuild", "MapFormatError",
    "MapNotFoundError", "MapStore", "MapStoreError", "MetricAligner", "MetricDepth", "MissingDepthError",
    "MonoSimConfig", "PosedImage", "ReconstructionConfig", "Reconstructor", "ReconstructorError",
    "RegionInput", "RegionReport", "RegionalCloud", "RegionalReconstructor", "RgbdConfig", "SensorDepth",
    "Slam3rConfig", "StoredMap", "VoxelAccumulator", "chamfer", "posed_from_frame", "posed_from_matrix",
    "region_from_frames", "region_from_recording", "to_world", "voxel_downsample",
]
