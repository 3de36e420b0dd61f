"""Anticipated views of a coloured point cloud (paper Section 4.3), in two modes.

This module is the algorithm's description and the renderer's public face; the code lives in
:mod:`config` (settings, result), :mod:`ops_numpy` and :mod:`ops_torch` (the array backends) and
:mod:`renderer` (``SplatRenderer`` and ``RENDERERS``).

``visibility`` (the default) gives each point a footprint from its local spacing and its depth,
removes the background that shows through the gaps between foreground footprints (visibility
splatting) and fills what is left by a depth-aware pull-push (:mod:`visibility` names the
published techniques). Its front pass is the one described below (a pixel's front layer reduced
to one surfel, plus the sum of its points' spacing); the image-space passes follow it. It agrees
with the torch backend within the tolerance stated in tests/unit/renderer/test_renderer_visibility.py
(<= 0.2 % of the pixels differ; the compiled and array numpy paths are bit-identical). Its
image-space passes run compiled too (:mod:`visibility_kernels`), bit-identical to the array code.

Where the map records the side each point was seen from (``PointCloud.view_dirs``, the mean
direction towards the cameras that saw it), normals are oriented towards that side (as a range
scan's normals are towards its scanner) and a point seen from its other side is drawn in a neutral
"unknown" grey, at its depth and with its label: the face of a wall the robot never mapped shows as
a wall of unknown colour, not in the paint of the room behind it (``SplatConfig.unseen_side``).

What a view draws is bounded by its pixels, not by the map: blocks outside the frustum are
culled, and each remaining block is drawn from precomputed voxel-averaged levels of detail
(:mod:`lod`: Potree-style layered LOD, per-block selection as in sequential point trees) at the
coarsest level whose cell projects to at most ``lod_cell_px`` pixels. A far room thus costs about
its pixels, whatever its density, and per-view cost stays flat as a building grows.

``paper`` is the paper's fixed 3x3 Gaussian splat, kept for the ablation:

Every point is projected with the pinhole model; its colour and depth are spread over the 3x3
pixels around it with Gaussian weights of the distance between the point's sub-pixel position and
each pixel centre; at a pixel only the points within a depth tolerance ``epsilon`` of the minimum
depth recorded there contribute, and they are averaged with those distance weights. The label
image takes the label of the nearest splat that reaches a pixel (no blending).

Two algorithms produce this image:

* ``exact``: every point is splatted into its nine pixels and tested against the per-pixel minimum
  depth (9 contributions per point). The reference.
* ``layered`` (default): the front layer of each pixel (points within ``epsilon`` of the pixel's own
  nearest point) is first reduced to one surfel (count, sum of colour and depth, mean sub-pixel
  offset); the nine-pixel splat and the occlusion test then run on these surfels in image space.
  Per point this costs one scatter-min and one scatter-add instead of nine of each, which is what
  makes a view cost a small multiple of one pass over the visible points. It differs from
  ``exact`` only where a pixel's front layer straddles a neighbour's tolerance band (silhouettes);
  the tests bound that difference.

The minimum depth at a pixel after splatting is the 3x3 minimum filter of the per-pixel minimum
before splatting (a splat carries its point's depth unchanged), so neither algorithm needs a
nine-fold z-buffer.

Both algorithms are written once against a tiny array backend, implemented with numpy and with
torch (CUDA when available, else CPU); the two give the same images within float tolerance. The
numpy backend runs ``layered`` through compiled loops (:mod:`kernels`, numba) when numba is
installed, bit-identical to its array code and ~5x faster, and renders the views of one call on
``workers`` threads.
"""

from libs.pointrender.config import LOD_CELL_PX, RenderedViews, SplatConfig, TorchSplatConfig
from libs.pointrender.ops_numpy import point_normals_of, point_sides_of, point_spacing_of, share_point_geometry
from libs.pointrender.renderer import RENDERERS, SplatRenderer

__all__ = [
    "LOD_CELL_PX", "RENDERERS", "RenderedViews", "SplatConfig", "SplatRenderer", "TorchSplatConfig", "point_normals_of", "point_sides_of", "point_spacing_of",
    "share_point_geometry",
]
