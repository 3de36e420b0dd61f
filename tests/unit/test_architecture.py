"""The house's walls, read from the code's own imports (STYLE 1 and 12).

- a service never imports another service: what crosses a boundary lives in ``shared/``;
- ``shared/`` never imports a service (it is the library every service stands on);
- core logic never imports zenoh: only a service's bus adapter and ``shared/bus`` / the runner do;
- ``libs/`` (pure libraries) import nothing of ours but ``shared/`` (and each other's own package);
- a service never imports ``bench``, ``evaluation``, ``deploy`` or ``tools`` (they stand on services, not
  the other way round);
- no import cycle anywhere in the tree (module to module, through any package);
- open3d is imported through ``shared.o3d`` only, so no process pays for its plotly/dash front-end because
  some module happened to import open3d first.
"""

from __future__ import annotations

import ast
import functools
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@functools.lru_cache(maxsize=None)
def _import_nodes(path: Path) -> tuple[tuple[ast.Import | ast.ImportFrom, bool], ...]:
    """Every import statement of a file, at any depth, and whether it runs: not under ``if TYPE_CHECKING:``
    (annotations only: it loads nothing). Parsed once per session: the checks below walk the same files
    again and again (each service, each library, the whole tree for cycles and for open3d), and parsing
    them was most of this module's time."""
    found: list[tuple[ast.Import | ast.ImportFrom, bool]] = []

    def visit(node: ast.AST, runs: bool) -> None:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            found.append((node, runs))
        elif isinstance(node, ast.If) and getattr(node.test, "id", None) == "TYPE_CHECKING":
            for child in node.body:
                visit(child, False)
            for child in node.orelse:
                visit(child, runs)
        else:
            for child in ast.iter_child_nodes(node):
                visit(child, runs)

    visit(ast.parse(path.read_text(encoding="utf-8"), filename=str(path)), True)
    return tuple(found)


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every import in a file, relative imports resolved against its package."""
    package = path.relative_to(ROOT).with_suffix("").parts[:-1]
    out = []
    for node, _ in _import_nodes(path):
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
    cores = [p for s in SERVICES for p in _py(f"services/{s}/core")] + _py("libs/pointrender")
    assert cores
    found = [f"{p.relative_to(ROOT)}:{line} imports {name}" for p in cores
             for line, name in _imports(p) if name == "zenoh" or name.startswith("zenoh.")]
    assert not found, "\n".join(found)


def test_the_check_reads_relative_and_absolute_imports():
    """The reader resolves relative and absolute imports (a wall check that sees nothing is no check)."""
    probe = ROOT / "services" / "renderer" / "core" / "port.py"
    names = {n for _, n in _imports(probe)}
    assert "libs.pointrender.splat" in names and "services.renderer.core.errors" in names


def _runtime_imports(path: Path) -> list[tuple[int, str]]:
    """(line, module) of the absolute ``import X`` / ``from X import`` statements that run (not under
    ``if TYPE_CHECKING:``)."""
    out: list[tuple[int, str]] = []
    for node, runs in _import_nodes(path):
        if runs and isinstance(node, ast.Import):
            out.extend((node.lineno, a.name) for a in node.names)
        elif runs and isinstance(node, ast.ImportFrom) and not node.level:
            out.append((node.lineno, node.module or ""))
    return out


def test_open3d_is_imported_through_shared_o3d_only():
    """``import open3d`` loads plotly and dash (~700 modules, 0.3-0.5 s of CPU a process); shared.o3d loads
    them on first use. One direct import anywhere that runs first brings the whole cost back."""
    files = [p for top in OURS for p in _py(top) if p != ROOT / "shared" / "o3d.py"]
    found = [f"{p.relative_to(ROOT)}:{line} imports {name}" for p in files
             for line, name in _runtime_imports(p) if name == "open3d" or name.startswith("open3d.")]
    assert not found, "\n".join(found)


def test_the_open3d_check_sees_runtime_imports_and_skips_type_checking(tmp_path):
    probe = tmp_path / "probe.py"
    probe.write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import open3d\n"
                     "def f():\n    import open3d.geometry\n")
    assert [name for _, name in _runtime_imports(probe) if name.startswith("open3d")] == ["open3d.geometry"]


OURS = ("shared", "libs", "services", "bench", "evaluation", "deploy", "tools", "tests")
LIBS = sorted(p.name for p in (ROOT / "libs").iterdir() if (p / "__init__.py").exists())


def test_the_walk_sees_every_library():
    assert {"pointrender", "world", "ros2"} <= set(LIBS)


@pytest.mark.parametrize("lib", LIBS)
def test_a_library_imports_only_shared_and_itself(lib):
    found = [f"{p.relative_to(ROOT)}:{line} imports {name}" for p in _py(f"libs/{lib}")
             for line, name in _imports(p)
             if name.split(".")[0] in OURS and not (name == "shared" or name.startswith("shared.")
                                                     or name == f"libs.{lib}" or name.startswith(f"libs.{lib}."))]
    assert not found, "a library stands on shared/ alone:\n" + "\n".join(found)


def test_shared_never_imports_a_library_or_a_tool():
    found = [f"{p.relative_to(ROOT)}:{line} imports {name}" for p in _py("shared")
             for line, name in _imports(p) if name.split(".")[0] in ("libs", "bench", "evaluation", "deploy", "tools")]
    assert not found, "\n".join(found)


@pytest.mark.parametrize("service", SERVICES)
def test_a_service_never_imports_bench_evaluation_deploy_or_tools(service):
    found = [f"{p.relative_to(ROOT)}:{line} imports {name}" for p in _py(f"services/{service}")
             for line, name in _imports(p) if name.split(".")[0] in ("bench", "evaluation", "deploy", "tools")]
    assert not found, "services stand below the tools that drive them:\n" + "\n".join(found)


def _module_of(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _import_graph(tops: tuple[str, ...] = OURS) -> dict[str, set[str]]:
    """Module -> the modules of ours it imports, at any depth of the file (a deferred import inside a
    function still ties the two). ``from pkg import name`` points at ``pkg.name`` where that is a
    module, else at ``pkg`` (its ``__init__``)."""
    files = [p for top in tops if (ROOT / top).is_dir() for p in _py(top)]
    modules = {_module_of(p): p for p in files}
    graph: dict[str, set[str]] = {}
    for mod, path in modules.items():
        package = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
        out: set[str] = set()
        for node, _ in _import_nodes(path):
            if isinstance(node, ast.Import):
                out.update(a.name for a in node.names if a.name in modules)
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    parts = package.split(".")
                    base = parts[: len(parts) - node.level + 1]
                    name = ".".join((*base, node.module) if node.module else base)
                else:
                    name = node.module or ""
                for a in node.names:
                    if f"{name}.{a.name}" in modules:
                        out.add(f"{name}.{a.name}")
                    elif name in modules:
                        out.add(name)
        out.discard(mod)
        graph[mod] = out
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found: list[list[str]] = []
    counter = 0
    for root in sorted(graph):
        if root in index:
            continue
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on.add(root)
        work = [(root, iter(sorted(graph[root])))]
        while work:
            node, children = work[-1]
            advanced = False
            for child in children:
                if child not in graph:
                    continue
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                    advanced = True
                    break
                if child in on:
                    low[node] = min(low[node], index[child])
            if advanced:
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                comp = []
                while True:
                    top = stack.pop()
                    on.discard(top)
                    comp.append(top)
                    if top == node:
                        break
                if len(comp) > 1:
                    found.append(sorted(comp))
    return found


def test_no_import_cycle_anywhere():
    cycles = _cycles(_import_graph())
    assert not cycles, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_the_cycle_check_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []
    probe = _import_graph(("bench",))
    assert "bench.anticipation" in probe and probe["bench.anticipation"], "the graph must see bench's imports"
