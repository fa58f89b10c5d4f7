"""The package's layers import only downwards (docs/architecture.md).

Every ``import`` in the library, at the top of a module or inside a function, is read with ``ast``
and checked against ``LAYERS``: a part may import its own layer and the ones below it, never one
above.  The library never imports the scripts (``experiments/``, ``benchmarks/``, ``research/``,
``tools/``) or the tests, and the bottom layers stay free of the heavy frameworks that the layers
above them bring in.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "f2f_jax"

# Bottom first.  A name is a module or sub-package directly under f2f_jax/.
LAYERS = [
    {"config", "errors", "fileio", "run_plan"},
    {"geometry"},
    {"data", "render"},
    {"sim"},
    {"dataset", "nets"},
    {"train"},
    {"designer", "design_pool"},
    {"tables", "bench"},
    {"cli", "__init__"},
]
LEVEL = {name: i for i, names in enumerate(LAYERS) for name in names}
# Frameworks a part must not import, even lazily: the geometry and the object sources run where
# neither the simulator nor JAX is wanted (meshing workers, Ray tasks), the simulator without JAX.
FORBIDDEN = {
    "geometry": {"jax", "flax", "optax", "orbax", "mujoco", "matplotlib"},
    "data": {"jax", "flax", "optax", "orbax", "mujoco", "matplotlib"},
    "sim": {"jax", "flax", "optax", "orbax"},
    "dataset": {"jax", "flax", "optax", "orbax", "matplotlib"},
}
# Modules that run MJX (JAX on purpose): the accelerator backend and its pieces.
JAX_IN_SIM = {"sim/mjx_batch.py", "sim/mjx_collision.py"}
SCRIPTS = {"experiments", "benchmarks", "research", "tools", "tests"}


def _part(path: Path) -> str:
    rel = path.relative_to(PACKAGE)
    return rel.parts[0].removesuffix(".py")


def _imports(path: Path, text: str | None = None) -> list[tuple[int, str]]:
    """(line, absolute dotted module) of every import in the file, relative ones resolved."""
    tree = ast.parse(path.read_text() if text is None else text, str(path))
    package = ["f2f_jax", *path.relative_to(PACKAGE).parent.parts]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            out.append((node.lineno, module))
            if module == "f2f_jax":  # from f2f_jax import sim, designer
                out += [(node.lineno, f"f2f_jax.{alias.name}") for alias in node.names]
    return out


FILES = sorted(PACKAGE.rglob("*.py"))


def test_every_part_has_a_layer():
    parts = {_part(p) for p in FILES}
    assert parts - set(LEVEL) == set(), "give each new part of f2f_jax a layer in LAYERS"


@pytest.mark.parametrize("path", FILES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_imports_run_down_the_layers(path):
    part = _part(path)
    rel = str(path.relative_to(PACKAGE))
    bad = []
    for line, module in _imports(path):
        top, *rest = module.split(".")
        if top in SCRIPTS:
            bad.append(f"{rel}:{line} imports the script or test module {module}")
        if top in FORBIDDEN.get(part, ()) and rel not in JAX_IN_SIM:
            bad.append(f"{rel}:{line} imports {module}: {part}/ stays free of {sorted(FORBIDDEN[part])}")
        if top == "f2f_jax" and rest:
            target = rest[0]
            if target in LEVEL and LEVEL[target] > LEVEL[part]:
                bad.append(f"{rel}:{line} ({part}, layer {LEVEL[part]}) imports {module} "
                           f"(layer {LEVEL[target]}): an arrow back up")
    assert not bad, "\n".join(bad)


def test_the_check_sees_an_arrow_back():
    """The reader finds function-local, relative and ``from f2f_jax import`` imports (the forms that
    hid arrows back before)."""
    probe = PACKAGE / "geometry" / "_probe.py"  # never written: the text is parsed as if it were
    src = ("def f():\n    from f2f_jax.train import steps\n    from ..sim import scene\n"
           "    import jax\n    from f2f_jax import designer\n")
    found = [m for _, m in _imports(probe, src)]
    assert found == ["f2f_jax.train", "f2f_jax.sim", "jax", "f2f_jax", "f2f_jax.designer"]
