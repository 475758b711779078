"""The package's layers, checked from the imports of every module (docs/architecture.md).

The allowed order is written once, here, bottom to top. A module may import from its own
layer and the layers below it, never from a layer above; inside a layer, the packages must
not import each other in a cycle. The stages import only stages of earlier method sections.
Warp kernels are launched only by the kernel drivers (``holowarp.ops``, ``holowarp.sim``).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

REPO = Path(__file__).resolve().parents[1]

#: Bottom to top. Entries are module prefixes; a module belongs to the longest prefix.
LAYERS = [
    ("kernels", ["holowarp.kernels"]),
    ("base", ["holowarp.errors", "holowarp.fileio", "holowarp.device", "holowarp.camera", "holowarp.frame",
              "holowarp.config", "holowarp.progress", "holowarp.scenes", "holowarp.repeatable"]),
    ("core", ["holowarp.tetmesh", "holowarp.primitives", "holowarp.refine"]),
    ("drivers", ["holowarp.ops", "holowarp.sim"]),
    ("io", ["holowarp.surface_io", "holowarp.mesh_io", "holowarp.usd"]),
    ("domain", ["holowarp.data", "holowarp.render_gt", "holowarp.carve", "holowarp.metrics", "holowarp.manifold",
                "holowarp.gaussians", "holowarp.tetgs", "holowarp.energies", "holowarp.losses", "holowarp.optim",
                "holowarp.viz", "holowarp.previews", "holowarp.shapes"]),
    ("stages", ["holowarp.stages"]),
    ("applications", ["holowarp.runstate", "holowarp.report", "holowarp.preflight", "holowarp.pipeline",
                      "holowarp.synthesis", "holowarp.scene_synth", "holowarp.simulation", "holowarp.baselines",
                      "holowarp.suite"]),
    ("commands", ["holowarp.cli", "holowarp.reconstruct", "holowarp.simulate", "holowarp.synth", "holowarp.evaluate",
                  "holowarp.convert", "holowarp.gs2d", "holowarp.improve", "holowarp.bench", "holowarp.poses",
                  "holowarp.baselines.visual_hull", "holowarp.batch"]),
    ("api", ["holowarp"]),  # the package root: lazy re-exports of the public entry points
]

#: The stages in method order (method.md §3-§7b, then §11); each may import only earlier ones.
STAGE_ORDER = ["gaussian_init", "tet_init", "topology", "geometry", "cleanup", "polish", "improve", "export", "objects"]

#: The only packages whose code may launch Warp kernels.
KERNEL_DRIVERS = ("holowarp.ops", "holowarp.sim")

#: Longest function allowed in holowarp/ (lines, docstring included).
MAX_FUNCTION_LINES = 80


def _modules():
    """{module name: path} for every module of the installed package tree."""
    out = {}
    for root, prefix in ((REPO / "holowarp", "holowarp"), (REPO / "kernels", "holowarp.kernels"), (REPO / "scenes", "holowarp.scenes")):
        for f in sorted(root.rglob("*.py")):
            parts = list(f.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join([prefix, *parts])] = f
    return out


MODULES: dict = {}


def _imports(path: Path, module: str) -> set[str]:
    """Every holowarp module ``path`` imports, at any depth of the file (lazy imports count)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    pkg = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.startswith("holowarp")}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(pkg.split(".")[: len(pkg.split(".")) - node.level + 1] + ([base] if base else []))
            if base.startswith("holowarp"):
                # ``from pkg import name``: the submodule ``pkg.name`` if there is one, else ``pkg``.
                found |= {f"{base}.{a.name}" if f"{base}.{a.name}" in MODULES else base for a in node.names}
    return found


MODULES.update(_modules())


def _layer(name: str) -> tuple[int, str]:
    """(layer index, package prefix) of a module; the longest matching prefix wins."""
    best = None
    for i, (_, prefixes) in enumerate(LAYERS):
        for p in prefixes:
            if (name == p or name.startswith(p + ".")) and (best is None or len(p) > len(best[1])):
                best = (i, p)
    return best


def _resolve(name: str) -> str | None:
    """The module an imported name refers to (``from pkg import name`` may name an attribute)."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


def _edges():
    for mod, path in MODULES.items():
        for imp in _imports(path, mod):
            target = _resolve(imp)
            if target is not None and target != mod:
                yield mod, target


def test_every_module_has_a_layer():
    assert [m for m in MODULES if _layer(m) is None] == []


def test_no_module_imports_from_a_layer_above_it():
    upward = []
    for mod, target in _edges():
        (li, _), (lj, _) = _layer(mod), _layer(target)
        if lj > li:
            upward.append(f"{mod} ({LAYERS[li][0]}) imports {target} ({LAYERS[lj][0]})")
    assert upward == []


def test_packages_do_not_import_each_other_in_a_cycle():
    pkgs = sorted({_layer(m)[1] for m in MODULES})
    index = {p: i for i, p in enumerate(pkgs)}
    rows, cols = [], []
    for mod, target in _edges():
        a, b = index[_layer(mod)[1]], index[_layer(target)[1]]
        if a != b and _layer(target)[1] != "holowarp":
            rows.append(a)
            cols.append(b)
    g = coo_matrix(([1] * len(rows), (rows, cols)), shape=(len(pkgs), len(pkgs)))
    n, labels = connected_components(g, directed=True, connection="strong")
    cycles = [[p for p in pkgs if labels[index[p]] == c] for c in range(n)]
    assert [c for c in cycles if len(c) > 1] == []


def test_stages_import_only_earlier_stages():
    assert sorted(STAGE_ORDER) == sorted(m.split(".")[-1] for m in MODULES if m.startswith("holowarp.stages."))
    later = []
    for mod, target in _edges():
        if mod.startswith("holowarp.stages.") and target.startswith("holowarp.stages."):
            a, b = STAGE_ORDER.index(mod.split(".")[2]), STAGE_ORDER.index(target.split(".")[2])
            if b >= a:
                later.append(f"{mod} imports {target}")
    assert later == []


def test_kernels_are_launched_only_by_the_kernel_drivers():
    launches = []
    for mod, path in MODULES.items():
        if mod.startswith(KERNEL_DRIVERS) or mod.startswith("holowarp.kernels"):
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "launch":
                launches.append(f"{path.relative_to(REPO)}:{node.lineno}")
    assert launches == []


def test_kernels_import_neither_torch_nor_the_rest_of_holowarp():
    bad = []
    for mod, path in MODULES.items():
        if not mod.startswith("holowarp.kernels"):
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else (
                [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            bad += [f"{mod}: {n}" for n in names if n.split(".")[0] == "torch" or
                    (n.startswith("holowarp") and not n.startswith("holowarp.kernels"))]
    assert bad == []


@pytest.mark.parametrize("mod", [m for m in MODULES if m.startswith("holowarp") and not m.startswith("holowarp.kernels")])
def test_no_function_is_longer_than_the_limit(mod):
    path = MODULES[mod]
    long = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            n = node.end_lineno - node.lineno + 1
            if n > MAX_FUNCTION_LINES:
                long.append(f"{node.name} ({n} lines, line {node.lineno})")
    assert long == []
