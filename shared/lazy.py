"""Re-exports of a package's ``__init__`` that import their submodule on first use (PEP 562).

A service's core package re-exports its submodules' names for its tests and tools, but a service process
needs only some of them at start: the mapper serves waypoint predictions from the moment it is alive,
and only an exploration needs the explorer, regions and tours, which bring scipy and networkx (0.6 s of
CPU at every start of a process that may never explore). With ``lazy_exports`` the package reads as
before (``from pkg import Name``, ``pkg.Name``, ``from pkg import *``, ``dir(pkg)``), and a submodule is
imported the first time one of its names is asked for.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping


def lazy_exports(package: str, exports: Mapping[str, tuple[str, ...]]
                 ) -> tuple[Callable[[str], object], Callable[[], list[str]], list[str]]:
    """``(__getattr__, __dir__, __all__)`` for the ``__init__`` of ``package``; ``exports`` maps each
    submodule (its name in the package) to the names the package re-exports from it."""
    where = {name: module for module, names in exports.items() for name in names}

    def __getattr__(name: str) -> object:
        module = where.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{module}"), name)
        setattr(sys.modules[package], name, value)  # the next access is a plain attribute
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(where))

    return __getattr__, __dir__, sorted(where)
