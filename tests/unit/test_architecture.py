"""The house's walls, read from the code's own imports (STYLE 1 and 12).

- a service never imports another service: what crosses a boundary lives in ``shared/``;
- ``shared/`` never imports a service (it is the library every service stands on);
- core logic never imports zenoh: only a service's bus adapter and ``shared/bus`` / the runner do.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every import in a file, relative imports resolved against its package."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    package = path.relative_to(ROOT).with_suffix("").parts[:-1]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.extend((node.lineno, a.name) for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                name = ".".join((*base, node.module) if node.module else base)
            else:
                name = node.module or ""
            out.append((node.lineno, name))
    return out


def _py(folder: str) -> list[Path]:
    return sorted(p for p in (ROOT / folder).rglob("*.py") if "__pycache__" not in p.parts)


SERVICES = sorted(p.name for p in (ROOT / "services").iterdir() if (p / "__init__.py").exists())


def test_the_walk_sees_every_service():
    assert {"gateway", "mapper", "planner", "reconstructor", "renderer", "robot_io"} <= set(SERVICES)


@pytest.mark.parametrize("service", SERVICES)
def test_a_service_never_imports_another_service(service):
    crossing = [
        f"{path.relative_to(ROOT)}:{line} imports {name}"
        for path in _py(f"services/{service}")
        for line, name in _imports(path)
        if name.startswith("services.") and name.split(".")[1] != service
    ]
    assert not crossing, "types that cross services belong in shared/:\n" + "\n".join(crossing)


def test_shared_never_imports_a_service():
    found = [f"{p.relative_to(ROOT)}:{line} imports {name}" for p in _py("shared")
             for line, name in _imports(p) if name == "services" or name.startswith("services.")]
    assert not found, "\n".join(found)


def test_core_logic_never_imports_zenoh():
    cores = [p for s in SERVICES for p in _py(f"services/{s}/core")] + _py("shared/pointrender")
    assert cores
    found = [f"{p.relative_to(ROOT)}:{line} imports {name}" for p in cores
             for line, name in _imports(p) if name == "zenoh" or name.startswith("zenoh.")]
    assert not found, "\n".join(found)


def test_the_check_reads_relative_and_absolute_imports():
    """The reader resolves relative and absolute imports (a wall check that sees nothing is no check)."""
    probe = ROOT / "services" / "renderer" / "core" / "port.py"
    names = {n for _, n in _imports(probe)}
    assert "shared.pointrender.splat" in names and "services.renderer.core.errors" in names
