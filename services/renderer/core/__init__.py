"""Renderer core: anticipated views and the spatial map from a coloured point cloud (no bus here)."""

from services.renderer.core.cloud import IndexedCloud
from services.renderer.core.errors import (
    BackendUnavailableError,
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
    "RENDERERS", "BackendUnavailableError", "IndexedCloud", "MapRenderer",
    "OccupancyGrid", "RenderedViews", "RendererError", "SpatialMapConfig",
    "SpatialMapImage", "SpatialMapper", "SplatConfig", "SplatRenderer", "TorchSplatConfig",
]
