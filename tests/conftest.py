"""Shared fixtures: a few canonical shapes, made once per test run."""

from f2f_jax.cli.reproducible import reproducible_xla

# Before anything starts JAX: the tests compute as the command-line tools do (AVX2 code, a 2-thread
# XLA pool), so a run killed in a `cotrain.py` subprocess and resumed in a test process ends where
# one never stopped ends, on an AVX-512 machine as on an AVX2 one.
reproducible_xla()

import numpy as np  # noqa: E402
import pytest
import trimesh

from f2f_jax import config
from f2f_jax.geometry import mesh_to_tsdf


def cup_mesh(radius=0.03, height=0.06, wall=0.006, base=0.008) -> trimesh.Trimesh:
    """An open-topped cup as two touching watertight bodies: a base disc and a tube wall."""
    disc = trimesh.creation.cylinder(radius=radius, height=base)
    disc.apply_translation([0, 0, base / 2])
    tube = trimesh.creation.annulus(r_min=radius - wall, r_max=radius, height=height - base)
    tube.apply_translation([0, 0, base + (height - base) / 2])
    mesh = trimesh.util.concatenate([disc, tube])
    mesh.metadata["name"] = "cup"
    return mesh


@pytest.fixture(scope="session")
def cfg():
    return config.default()


@pytest.fixture(scope="session")
def tiny_cfg():
    return config.tiny()


@pytest.fixture(scope="session")
def sphere_mesh():
    return trimesh.creation.icosphere(subdivisions=4, radius=0.03)


@pytest.fixture(scope="session")
def sphere_tsdf(sphere_mesh):
    return mesh_to_tsdf(sphere_mesh)


@pytest.fixture(scope="session")
def rng():
    return np.random.default_rng(0)
