"""The layers of the product code, read from its source (issues 27 and 44): the import graph of the
modules of ``autoalign/``, ``losses/``, ``rasterizers/``, ``recon/`` and ``cli/`` (installed as
``autoalign.*``), counting imports inside functions, has no cycle; the packages import only
downwards in :data:`PACKAGE_ORDER`; nothing outside ``cli/`` imports ``autoalign.cli`` or
``autoalign.experiments``; and no function is longer than 80 lines, no class longer than 250,
except the few listed below with their reason.
"""

from __future__ import annotations

import ast
from graphlib import CycleError, TopologicalSorter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"autoalign": "autoalign", "losses": "autoalign.losses", "rasterizers": "autoalign.rasterizers",
            "recon": "autoalign.recon", "cli": "autoalign.cli"}
"""Source folder -> installed package name (see pyproject.toml)."""
PACKAGE_ORDER = ("geometry", "rasterizers", "losses", "engine", "scene", "quality", "jobs", "label", "cli")
"""The packages from the bottom up (README, How it works): each imports only those before it.
``label`` and ``cli`` share the top: the label page's session and the commands that serve it. The
shared utilities (``io``, ``runtime``, ``errors``) and the entry points (``batch``, ``torch``, ``jax``,
``recon``) stand outside the order."""
TOP = ("label", "cli")
ORDER_EXCEPTIONS: dict[tuple[str, str], str] = {
    # (importer, imported): why it may stay (one line each; take an entry off once it is gone)
    ("autoalign.scene.refine", "autoalign.quality.verdict"):
        "the scene stage judges each instance alone to choose those whose masks decide the scale",
}
MAX_FUNCTION_LINES = 80
MAX_CLASS_LINES = 250
LONG_ALLOWED: dict[str, str] = {
    # "path:name": "why it may stay longer" (one line each; take an entry off once it fits)
}


def product_modules() -> dict[str, Path]:
    """Installed module name -> source file, for every product module."""
    modules = {}
    for folder, package in PACKAGES.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            parts = [p for p in path.relative_to(ROOT / folder).with_suffix("").parts if p != "__init__"]
            modules[".".join([package, *parts])] = path
    return modules


def _imported(node: ast.AST, module: str, is_package: bool) -> list[str]:
    """The module names an import statement names (relative imports resolved), with ``from X import
    Y`` also giving ``X.Y`` (a submodule or not: filtered by the caller)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    if not isinstance(node, ast.ImportFrom):
        return []
    base = node.module or ""
    if node.level:
        anchor = module.split(".")[: len(module.split(".")) - node.level + (1 if is_package else 0)]
        base = ".".join(anchor + ([base] if base else []))
    return [base] + [f"{base}.{a.name}" for a in node.names]


def import_graph() -> dict[str, set[str]]:
    """Module -> the product modules (and ``autoalign.experiments.*``) it imports anywhere in its
    source: also inside functions and ``TYPE_CHECKING`` blocks."""
    modules = product_modules()
    graph: dict[str, set[str]] = {name: set() for name in modules}
    for name, path in modules.items():
        tree = ast.parse(path.read_text(), str(path))
        for node in ast.walk(tree):
            for target in _imported(node, name, path.name == "__init__.py"):
                if target != name and (target in modules or target.startswith("autoalign.experiments")):
                    graph[name].add(target)
    return graph


def test_the_import_graph_has_no_cycle():
    graph = import_graph()
    assert len(graph) > 50 and "autoalign.cli.main" in graph and "autoalign.batch" in graph
    try:
        TopologicalSorter(graph).prepare()  # raises on a cycle, naming one
    except CycleError as exc:
        raise AssertionError(f"import cycle: {' -> '.join(exc.args[1])}") from None


def _layer(module: str) -> int | None:
    """The place of ``module``'s package in :data:`PACKAGE_ORDER` (the top's two share one); None outside it."""
    parts = module.split(".")
    if len(parts) < 2 or parts[1] not in PACKAGE_ORDER:
        return None
    return min(PACKAGE_ORDER.index(parts[1]), PACKAGE_ORDER.index(TOP[0]))


def test_packages_import_only_downwards():
    graph = import_graph()
    upward = {(a, b) for a, targets in graph.items() for b in targets
              if _layer(a) is not None and _layer(b) is not None and _layer(b) > _layer(a)}
    assert sorted(upward - set(ORDER_EXCEPTIONS)) == [], sorted(upward - set(ORDER_EXCEPTIONS))
    assert sorted(set(ORDER_EXCEPTIONS) - upward) == [], "no longer imported upwards: take them off ORDER_EXCEPTIONS"
    assert _layer("autoalign.engine.refine") < _layer("autoalign.quality.verdict") < _layer("autoalign.cli.main")


def test_core_never_imports_the_command_line_or_the_experiments():
    graph = import_graph()
    wrong = sorted((a, b) for a, targets in graph.items() for b in targets
                   if not a.startswith("autoalign.cli") and b.startswith(("autoalign.cli", "autoalign.experiments")))
    assert wrong == [], wrong


def test_functions_and_classes_are_short():
    long = {}
    for folder in ("autoalign", "cli", "losses", "rasterizers", "recon"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                limit = (MAX_CLASS_LINES if isinstance(node, ast.ClassDef) else MAX_FUNCTION_LINES
                         if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) else None)
                if limit is not None and node.end_lineno - node.lineno + 1 > limit:
                    long[f"{path.relative_to(ROOT)}:{node.name}"] = node.end_lineno - node.lineno + 1
    assert sorted(set(long) - set(LONG_ALLOWED)) == [], long
    assert sorted(set(LONG_ALLOWED) - set(long)) == [], "no longer too long: take them off LONG_ALLOWED"
