"""Layering: ``csa_core`` is the science and never imports the service or the client.

The service adds ``csa serve`` through an entry point (see ``server/cli.py``);
nothing in ``csa_core`` names ``server`` or ``client`` in an import, and importing every
module of the package leaves neither (nor the web stack) in ``sys.modules``.
Inside ``csa_core``, the data layer (``csa_core.data``) is the bottom: it imports none of the
packages built on it (``csa_core.nerf``, ``csa_core.seg``, ``csa_core.adapt``, ...), only
itself and the shared top-level modules (``csa_core.errors``, ``csa_core.atomic_io``, ...)."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CORE = REPO / "csa_core"
UPPER = ("server", "client")  # packages that sit on top of csa_core
WEB_STACK = ("fastapi", "uvicorn", "starlette", "sqlalchemy", "alembic", "pydantic_settings", "httpx")


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
    source = "import server\nfrom server.app import x\nimport importlib\nimportlib.import_module('client.cli')\nfrom . import y\n"
    assert imported_names(ast.parse(source)) == [(1, "server"), (2, "server.app"), (3, "importlib"), (4, "client.cli")]


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
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=REPO)
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert {"csa_core.cli.main", "csa_core.adapt.continual", "csa_core.nerf.fit"} <= set(result["modules"])
    assert result["loaded"] == []


def test_the_data_layer_imports_no_package_built_on_it():
    above = sorted(p.name for p in CORE.iterdir() if (p / "__init__.py").is_file() and p.name != "data")
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
