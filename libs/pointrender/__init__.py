"""Point-cloud rendering: anticipated views of a coloured, labelled cloud (paper Section 4.3).

A library, not a service: the renderer service draws a stored map with it, and the reconstructor
renders a regional cloud with the same splatting for its metric alignment (paper 4.2), so the two
stay one algorithm. Pure numpy/numba/torch; no bus here.

* :mod:`.splat` - the algorithm (modes ``visibility`` and ``paper``) and the renderer's public names, from
  :mod:`.config` (settings), :mod:`.ops_numpy` / :mod:`.ops_torch` (array backends) and :mod:`.renderer`
  (``SplatRenderer``, ``RENDERERS``: ``numpy``, ``torch``);
* :mod:`.cloud` - :class:`IndexedCloud`, a cloud cut into spatial blocks for culling;
* :mod:`.lod` - voxel levels of detail per block;
* :mod:`.visibility` (+ :mod:`.visibility_kernels`) - the image-space visibility and hole-filling passes;
* :mod:`.kernels` - the compiled front pass and the paper's 3x3 compose.
"""

from libs.pointrender import visibility
from libs.pointrender.cloud import Frustum, IndexedCloud
from libs.pointrender.errors import BackendUnavailableError, RendererError
from libs.pointrender.splat import (
    RENDERERS,
    RenderedViews,
    SplatConfig,
    SplatRenderer,
    TorchSplatConfig,
)

__all__ = [
    "RENDERERS", "BackendUnavailableError", "Frustum", "IndexedCloud", "RenderedViews", "RendererError",
    "SplatConfig", "SplatRenderer", "TorchSplatConfig", "visibility",
]
