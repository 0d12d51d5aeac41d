"""No module imports from a layer above its own (README, "Layout")."""

from __future__ import annotations

import ast
from pathlib import Path

import flamenerf

# Lowest first; a module may import its own layer and the layers below it.
LAYERS = [
    {"__init__", "errors", "io", "outdir", "lock", "images", "geometry", "meshes", "runtime",
     "cpu_kernels", "gpu_kernels", "gpu_build", "config", "keyvalues"},
    {"data"},
    {"tracking"},
    {"synthetic", "model"},
    {"training"},
    {"evaluation", "rendering"},
    {"workflows", "viewer"},
    {"commands"},
    {"cli", "__main__"},  # `python -m flamenerf` runs the cli
]


def _layer(name: str) -> int:
    """Layer of a module path relative to the package, e.g. "data.scene" -> 1."""
    top = name.split(".")[0]
    for i, names in enumerate(LAYERS):
        if top in names:
            return i
    raise AssertionError(f"flamenerf.{top}: not in any layer of tests/test_layers.py")


def _imports(path: Path):
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            mods = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        elif isinstance(node, ast.Import):
            mods = [a.name for a in node.names]
        else:
            continue
        for m in mods:
            if m.startswith("flamenerf.") and m.count(".") >= 1:
                yield node.lineno, m.split(".", 1)[1]


def test_no_module_imports_from_a_higher_layer():
    root = Path(flamenerf.__file__).parent
    bad = []
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root).with_suffix("")
        own = _layer(".".join(rel.parts))
        for line, mod in _imports(path):
            try:
                theirs = _layer(mod)
            except AssertionError:
                # `from flamenerf import __version__` names an attribute, not a module
                if mod.split(".")[0].startswith("__"):
                    continue
                raise
            if theirs > own:
                bad.append(f"{rel}.py:{line} imports flamenerf.{mod}")
    assert not bad, "\n".join(bad)
