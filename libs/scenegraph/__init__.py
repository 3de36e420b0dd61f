"""The spatial scene graph of a map (issue 32): built from the map's labelled points and the exploration's
navigation graph (:mod:`.builder`), and routes over its walkable space (:mod:`.route`). Imports only
``shared``, so the reconstructor (which stores it), the planner (which reads it) and bench all use it."""

from .builder import SceneGraphConfig, build_scene_graph, colour_name, room_type_of  # noqa: F401
from .route import Router  # noqa: F401
