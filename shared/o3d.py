"""open3d, without the cost of the plotly/dash drawing front-end that ``import open3d`` loads.

Every process that touches open3d (robot-io's ray caster and nav grid, the ROS 2 stand-in, cloud files)
imports it from here: ``from shared.o3d import o3d``. Why: open3d's ``__init__`` imports
``open3d.visualization``, whose ``draw_plotly`` imports plotly and dash, and dash imports IPython, werkzeug
and flask - ~700 modules and 0.33 s of CPU of the 0.7 s that ``import open3d`` costs (measured: 0.70-0.80
-> 0.37-0.39 s, three runs each), paid at every start of a robot-io process, and the system tests start
dozens. Nothing here draws with plotly.

How: before open3d is first imported, ``open3d.visualization.draw_plotly`` is registered as a stand-in
module whose three functions (the names open3d's ``visualization/__init__`` imports from it) load the
real module from its file on their first call, so ``o3d.visualization.draw_plotly(...)`` still works,
only later. Any other name asked of the stand-in loads the real module at once and returns its value
(a later open3d that imports more from that file gets its real objects, at the old cost). Where open3d
is already imported (by code that did not come here first), nothing changes: this module only returns it.
"""

from __future__ import annotations

import importlib.util
import sys
import threading
import types

_PLOTLY = "open3d.visualization.draw_plotly"
# What open3d 0.20's visualization/__init__ imports from draw_plotly: all functions.
_DEFERRED = ("get_plotly_fig", "draw_plotly", "draw_plotly_server")


def _defer_plotly() -> None:
    if "open3d" in sys.modules or _PLOTLY in sys.modules:
        return
    spec = importlib.util.find_spec("open3d")  # a top-level spec: found, not executed
    if spec is None or not spec.submodule_search_locations:
        return  # no open3d: the import below raises as it always did
    path = f"{spec.submodule_search_locations[0]}/visualization/draw_plotly.py"
    real: list[types.ModuleType] = []
    lock = threading.Lock()

    def load() -> types.ModuleType:
        with lock:
            if not real:
                file_spec = importlib.util.spec_from_file_location(_PLOTLY, path)
                module = importlib.util.module_from_spec(file_spec)
                file_spec.loader.exec_module(module)
                real.append(module)
            return real[0]

    def deferred(name: str):
        def call(*args, **kwargs):
            return getattr(load(), name)(*args, **kwargs)

        call.__name__ = call.__qualname__ = name
        call.__doc__ = f"open3d's ``{name}``, its module (plotly, dash) loaded on the first call."
        return call

    stand_in = types.ModuleType(_PLOTLY, "open3d's draw_plotly, loaded on first use (shared.o3d)")
    stand_in.__dict__.update({name: deferred(name) for name in _DEFERRED})

    def any_other(name: str):  # PEP 562: a name not deferred; the import system's dunder probes stay cheap
        if name.startswith("__"):
            raise AttributeError(name)
        return getattr(load(), name)

    stand_in.__getattr__ = any_other
    sys.modules[_PLOTLY] = stand_in


_defer_plotly()
import open3d as o3d  # noqa: E402  (after the stand-in is in place)

__all__ = ["o3d"]
