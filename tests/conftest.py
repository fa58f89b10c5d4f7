"""Shared fixtures: a few canonical shapes, made once per session."""

import numpy as np
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
