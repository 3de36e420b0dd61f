"""Renderer core: anticipated views and the spatial map from a coloured point cloud (no bus here)."""

from services.renderer.core import visibility
from services.renderer.core.cloud import IndexedCloud, PointCloud, sample_mesh
from services.renderer.core.errors import (
    BackendUnavailableError,
    CloudFormatError,
    EmptyCloudError,
    RendererError,
)
from services.renderer.core.port import MapRenderer
from services.renderer.core.spatial_map import (
    OccupancyGrid,
    SpatialMapConfig,
    SpatialMapImage,
    SpatialMapper,
)
from services.renderer.core.splat import (
    RENDERERS,
    RenderedViews,
    SplatConfig,
    SplatRenderer,
    TorchSplatConfig,
)

__all__ = [
    "RENDERERS", "BackendUnavailableError", "CloudFormatError", "EmptyCloudError", "IndexedCloud", "MapRenderer",
    "OccupancyGrid", "PointCloud", "RenderedViews", "RendererError", "SpatialMapConfig",
    "SpatialMapImage", "SpatialMapper", "sample_mesh", "SplatConfig", "SplatRenderer", "TorchSplatConfig", "visibility",
]
