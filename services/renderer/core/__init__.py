"""Renderer core: anticipated views and the spatial map of a stored map (no bus here).

The point splatting itself is the shared library :mod:`libs.pointrender` (the reconstructor's
metric alignment renders with it too); this core binds it to one map (:class:`MapRenderer`), splits
a map into floors and draws the top-down spatial map.
"""

from services.renderer.core.errors import (
    BackendUnavailableError,
    MapMismatchError,
    RendererError,
)
from services.renderer.core.port import MapRenderer
from services.renderer.core.spatial_map import (
    OccupancyGrid,
    SpatialMapConfig,
    SpatialMapImage,
    SpatialMapper,
)
from libs.pointrender import (
    RENDERERS,
    IndexedCloud,
    RenderedViews,
    SplatConfig,
    SplatRenderer,
    TorchSplatConfig,
    visibility,
)

__all__ = [
    "RENDERERS", "BackendUnavailableError", "IndexedCloud", "MapMismatchError", "MapRenderer",
    "OccupancyGrid", "RenderedViews", "RendererError", "SpatialMapConfig",
    "SpatialMapImage", "SpatialMapper", "SplatConfig", "SplatRenderer", "TorchSplatConfig", "visibility",
]
