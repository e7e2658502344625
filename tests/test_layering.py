"""Layering: ``csa_core`` is the science and never imports the service or the client.

The service adds ``csa serve`` through an entry point (see ``server/cli.py``);
nothing in ``csa_core`` names ``server`` or ``client`` in an import, and importing every
module of the package leaves neither (nor the web stack) in ``sys.modules``.
Inside ``csa_core``, the data layer (``csa_core.data``) is the bottom: it imports none of the
packages built on it (``csa_core.nerf``, ``csa_core.seg``, ``csa_core.adapt``, ...), only
itself and the shared top-level modules (``csa_core.errors``, ``csa_core.atomic_io``, ...).

Inside ``server``, no two modules import each other, directly or around a circle, at module
level (an import inside a function would only hide such a circle: none is allowed to). The
HTTP layer (``server/routers``, the dashboard ``server/ui``) reaches the database through the
service layer (``server/services``): it builds no query and finds no row itself, and the
dashboard calls no route of the REST API as a function."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from collections import deque
from collections.abc import Iterable
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CORE = REPO / "csa_core"
SERVER = REPO / "server"
UPPER = ("server", "client")  # packages that sit on top of csa_core
WEB_STACK = (
    "fastapi",
    "uvicorn",
    "starlette",
    "sqlalchemy",
    "alembic",
    "pydantic_settings",
    "httpx",
)


def imported_names(tree: ast.AST) -> list[tuple[int, str]]:
    """(line, module) of every import statement, and of importlib.import_module("...") calls."""
    found: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.append((node.lineno, node.module))
        elif isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant):
            func = node.func
            name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
            if name in ("import_module", "__import__") and isinstance(node.args[0].value, str):
                found.append((node.lineno, node.args[0].value))
    return found


def test_the_scan_sees_every_kind_of_import():
    source = (
        "import server\nfrom server.app import x\nimport importlib\n"
        "importlib.import_module('client.cli')\nfrom . import y\n"
    )
    assert imported_names(ast.parse(source)) == [
        (1, "server"),
        (2, "server.app"),
        (3, "importlib"),
        (4, "client.cli"),
    ]


def test_no_module_of_csa_core_imports_the_service_or_the_client():
    files = sorted(CORE.rglob("*.py"))
    assert len(files) > 50  # the whole package was scanned, not an empty folder
    offending = [
        f"{path.relative_to(REPO)}:{line}: imports {module}"
        for path in files
        for line, module in imported_names(ast.parse(path.read_text(), filename=str(path)))
        if module.split(".")[0] in UPPER + WEB_STACK
    ]
    assert offending == []


def test_importing_every_csa_core_module_loads_neither_the_service_nor_the_web_stack():
    code = f"""
import importlib, json, pkgutil, sys
import csa_core
names = sorted(m.name for m in pkgutil.walk_packages(csa_core.__path__, "csa_core."))
for name in names:
    importlib.import_module(name)
loaded = sorted(m for m in sys.modules if m.split(".")[0] in {UPPER + WEB_STACK!r})
print(json.dumps({{"modules": names, "loaded": loaded}}))
"""
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=REPO
    )
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    expected = {"csa_core.cli.main", "csa_core.adapt.continual", "csa_core.nerf.fit"}
    assert expected <= set(result["modules"])
    assert result["loaded"] == []


def test_the_data_layer_imports_no_package_built_on_it():
    above = sorted(
        p.name for p in CORE.iterdir() if (p / "__init__.py").is_file() and p.name != "data"
    )
    assert {"nerf", "seg", "adapt"} <= set(above)
    files = sorted((CORE / "data").rglob("*.py"))
    assert any(p.name == "label_noise.py" for p in files)  # the whole data package was scanned
    offending = [
        f"{path.relative_to(REPO)}:{line}: imports {module}"
        for path in files
        for line, module in imported_names(ast.parse(path.read_text(), filename=str(path)))
        if module.split(".")[:2] in [["csa_core", name] for name in above]
    ]
    assert offending == []


# -- inside the service ----------------------------------------------------------------------


def module_names(package: Path) -> dict[str, Path]:
    """Dotted name -> file of every module of ``package`` (a package by its ``__init__.py``)."""
    names = {}
    for path in sorted(package.rglob("*.py")):
        parts = list(path.relative_to(package.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        names[".".join(parts)] = path
    return names


def _type_checking_only(node: ast.If) -> bool:
    """``if TYPE_CHECKING:`` (or ``typing.TYPE_CHECKING``): imports that never run."""
    return getattr(node.test, "id", getattr(node.test, "attr", None)) == "TYPE_CHECKING"


def server_imports(
    tree: ast.Module, module: str, known: Iterable[str], in_functions: bool = False
) -> list[str]:
    """The modules among ``known`` that importing ``module`` imports: by its statements at
    module level (in ``if``, ``try``, ``with`` blocks and class bodies too, not under ``if
    TYPE_CHECKING``) and, with ``in_functions``, inside its functions as well. ``from a import
    b`` imports the module ``a.b`` when there is one, else ``a``; relative imports are
    resolved against ``module``."""
    known = set(known)
    package = module if f"{module}.__init__" in known else module.rpartition(".")[0]
    skipped = () if in_functions else (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)
    found: list[str] = []

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.Import):
            found.extend(alias.name for alias in node.names if alias.name in known)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                base = f"{anchor}.{base}" if base else anchor
            for alias in node.names:
                name = f"{base}.{alias.name}"
                found.extend([name] if name in known else [base] if base in known else [])
        elif isinstance(node, ast.If) and _type_checking_only(node):
            for child in node.orelse:
                visit(child)
        elif not isinstance(node, skipped):
            for child in ast.iter_child_nodes(node):
                visit(child)

    visit(tree)
    return [name for name in dict.fromkeys(found) if name != module]


def import_graph(package: Path, in_functions: bool = False) -> dict[str, list[str]]:
    modules = module_names(package)
    known = set(modules) | {f"{m}.__init__" for m, p in modules.items() if p.name == "__init__.py"}
    return {
        name: server_imports(ast.parse(path.read_text()), name, known, in_functions)
        for name, path in modules.items()
    }


def _circle(graph: dict[str, list[str]], members: set[str], start: str) -> list[str]:
    """A shortest circle from ``start`` back to it through ``members``."""
    parents: dict[str, str] = {}
    queue = deque([start])
    while queue:
        node = queue.popleft()
        for nxt in graph[node]:
            if nxt == start:
                path = [node]
                while path[-1] != start:
                    path.append(parents[path[-1]])
                return [*reversed(path), start]
            if nxt in members and nxt not in parents:
                parents[nxt] = node
                queue.append(nxt)
    raise AssertionError(f"{start} is in no circle")


def import_cycles(graph: dict[str, list[str]]) -> list[list[str]]:
    """One circle of each group of modules that import each other (the strongly connected
    components of ``graph`` with more than one module), as ``[a, b, ..., a]``."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    groups: list[set[str]] = []

    def connect(node: str) -> None:  # Tarjan's algorithm
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for nxt in graph.get(node, []):
            if nxt not in index:
                connect(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            group = set()
            while node not in group:
                member = stack.pop()
                on_stack.discard(member)
                group.add(member)
            if len(group) > 1:
                groups.append(group)

    for node in sorted(graph):
        if node not in index:
            connect(node)
    return sorted(_circle(graph, group, min(group)) for group in groups)


def test_the_scan_of_imports_skips_functions_and_type_checking_and_names_submodules():
    source = (
        "import a.b\n"
        "from a import c, helper\n"
        "from . import d\n"
        "from typing import TYPE_CHECKING\n"
        "if TYPE_CHECKING:\n"
        "    import a.e\n"
        "try:\n"
        "    import a.f\n"
        "except ImportError:\n"
        "    pass\n"
        "def later():\n"
        "    import a.g\n"
        "class K:\n"
        "    import a.h\n"
    )
    known = ["a", "a.__init__", "a.b", "a.c", "a.d", "a.e", "a.f", "a.g", "a.h", "a.x"]
    found = server_imports(ast.parse(source), "a.x", known)
    assert found == ["a.b", "a.c", "a", "a.d", "a.f", "a.h"]
    everywhere = server_imports(ast.parse(source), "a.x", known, in_functions=True)
    assert everywhere == ["a.b", "a.c", "a", "a.d", "a.f", "a.g", "a.h"]


def test_the_cycle_finder_reports_each_circle_once():
    graph = {"a": ["b"], "b": ["c", "d"], "c": ["a"], "d": [], "e": ["e2"], "e2": ["e"]}
    assert import_cycles(graph) == [["a", "b", "c", "a"], ["e", "e2", "e"]]
    assert import_cycles({"a": ["b"], "b": ["c", "a"], "c": ["b"]}) == [["a", "b", "a"]]
    assert import_cycles({"a": ["b"], "b": []}) == []


def test_no_modules_of_the_service_import_each_other_in_a_circle():
    graph = import_graph(SERVER)
    assert len(graph) > 80 and "server.services.scenes" in graph  # the whole package
    assert "server.errors" in graph["server.upload_limits"]  # the scan sees server's imports
    assert import_cycles(graph) == []


def test_no_import_inside_a_function_hides_a_circle():
    """An import inside a function runs later, so a circle through it does not fail at import
    time: it stays hidden until the modules change. ``server/errors.py`` and
    ``server/upload_limits.py`` were such a circle; what both need is in ``server/asgi.py``."""
    graph = import_graph(SERVER, in_functions=True)
    assert "server.scene_folders" in graph["server.lookups"]  # imports in functions are seen
    assert import_cycles(graph) == []


# What the HTTP layer gets through the service layer (server/services) instead of itself.
QUERY_MODULES = ("server.lookups", "server.registry", "server.frame_store", "server.memory_bank")


def test_routers_and_the_dashboard_build_no_query_of_their_own():
    files = sorted((SERVER / "routers").glob("*.py")) + sorted((SERVER / "ui").glob("*.py"))
    assert any(p.name == "page_data.py" for p in files)
    offending = []
    for path in files:
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            if not isinstance(node, ast.Import | ast.ImportFrom):
                continue
            names = [a.name for a in node.names]
            if isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if base == "sqlalchemy.orm" and names == ["Session"]:
                    continue  # the session's type only (a parameter passed on to the services)
                names = [base, *(f"{base}.{n}" for n in names)]
            for name in names:
                if name.split(".")[0] == "sqlalchemy" or name in QUERY_MODULES:
                    offending.append(f"{path.relative_to(REPO)}:{node.lineno}: imports {name}")
    assert offending == []


def test_the_dashboard_calls_no_route_of_the_rest_api():
    """The pages use the service layer as the routes do; ``server/app.py`` mounts the REST
    routers under ``/ui/api/v1`` for the pages' scripts."""
    files = sorted((SERVER / "ui").glob("*.py"))
    offending = [
        f"{path.relative_to(REPO)}:{line}: imports {module}"
        for path in files
        for line, module in imported_names(ast.parse(path.read_text(), filename=str(path)))
        if module == "server.routers" or module.startswith("server.routers.")
    ]
    assert offending == []
