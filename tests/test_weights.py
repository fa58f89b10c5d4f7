"""Weights files (f2f_jax.train.weights) and the model the package ships.

If the nets' layout changes, ``test_shipped_weights_load`` fails with the command that rebuilds
the shipped file (``weights.REBUILD``).
"""

import json
import logging

import jax
import numpy as np
import pytest

from f2f_jax import config
from f2f_jax import designer as design_module
from f2f_jax.data.objects import builtin_object
from f2f_jax.errors import CheckpointError
from f2f_jax.geometry import is_feasible, mesh_to_tsdf
from f2f_jax.train import weights
from f2f_jax.train.state import init_trained_nets


def _leaves(tree):
    return weights.flatten(jax.device_get(tree))


@pytest.fixture(scope="module")
def tiny_nets():
    return init_trained_nets(config.get("tiny"))


def test_round_trip_keeps_every_array_and_says_where_it_came_from(tiny_nets, tmp_path):
    npz, meta_path = weights.save_weights(tiny_nets, tmp_path / "w", provenance={"seed": 3})
    back = weights.load_weights(tmp_path / "w")
    for part in ("generator", "fitness"):
        a, b = _leaves(getattr(tiny_nets, part)), _leaves(getattr(back, part))
        assert a.keys() == b.keys()
        for name in a:
            np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    assert back.config == tiny_nets.config
    meta = json.loads(meta_path.read_text())
    assert meta["provenance"] == {"seed": 3} and meta["bytes"] == npz.stat().st_size
    assert meta["parameters"] == sum(v.size for p in ("generator", "fitness")
                                     for v in _leaves(getattr(tiny_nets, p)).values())


def test_a_damaged_or_foreign_file_is_refused_with_the_rebuild_command(tiny_nets, tmp_path):
    npz, meta_path = weights.save_weights(tiny_nets, tmp_path / "w")
    data = bytearray(npz.read_bytes())
    data[len(data) // 2] ^= 0xFF
    npz.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match="digest.*--export"):
        weights.load_weights(tmp_path / "w")

    # a file written for nets of another size: the layout check catches it
    weights.save_weights(tiny_nets, tmp_path / "v")
    meta = json.loads((tmp_path / "v.json").read_text())
    meta["config"]["net"]["latent_dim"] = 2 * meta["config"]["net"]["latent_dim"]
    (tmp_path / "v.json").write_text(json.dumps(meta))
    with pytest.raises(CheckpointError, match="other nets.*--export"):
        weights.load_weights(tmp_path / "v")
    with pytest.raises(CheckpointError, match="no weights"):
        weights.load_weights(tmp_path / "missing")


def test_shipped_weights_load():
    """The package's own model matches the nets this version builds (else: rebuild it)."""
    nets = weights.load_weights()
    info = weights.weights_info()
    assert info["bytes"] <= 25 * 2**20
    prov = info["provenance"]
    assert info["commit"] and prov["command"].startswith("python experiments/cotrain.py")
    assert prov["summary"]["held_out_objects"] > 0
    assert any(name.startswith("generator") for name in prov["summary"]["success"])
    assert prov["objects_split"]["test"], "the held-out objects are named"
    assert nets.config.train.seed == info["config"]["train"]["seed"]


def test_design_without_a_run_uses_the_shipped_weights_and_says_so(monkeypatch, caplog):
    monkeypatch.delenv("F2F_RUN_DIR", raising=False)
    monkeypatch.setattr(design_module, "_SHIPPED_NETS", None)
    obj = mesh_to_tsdf(builtin_object(5, seed=0))
    with caplog.at_level(logging.WARNING, logger=design_module.log.name):
        pairs = design_module.design(np.stack([obj, obj]), verify=False)
        design_module.design(obj, verify=False)
    said = [r for r in caplog.records if "shipped" in r.getMessage()]
    assert len(said) == 1, "said once per process"
    for pair in pairs:
        assert is_feasible(pair.left) and is_feasible(pair.right)
        assert pair.origin.startswith(design_module.GENERATOR)  # no imprints without verify
