"""f2f_jax: Fit2Form gripper-finger design in JAX/Flax with a MuJoCo/MJX grasp simulator.

Submodules load on first use, so ``import f2f_jax`` stays fast and geometry-only users never
import JAX or MuJoCo.
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

_SUBMODULES = ("config", "errors", "geometry", "sim", "data", "nets", "train", "render", "designer")


def __getattr__(name: str):
    if name in _SUBMODULES:
        return importlib.import_module(f"{__name__}.{name}")
    if name in ("design", "FingerPair"):
        from f2f_jax import designer  # the module has its own name: `f2f_jax.design` stays the function

        return getattr(designer, name)
    raise AttributeError(f"module 'f2f_jax' has no attribute {name!r}")


def __dir__():
    return sorted((*globals(), *_SUBMODULES, "design", "FingerPair"))
