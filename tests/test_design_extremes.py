"""design() and f2f-design on shapes at the extremes: every mode returns a pair per object.

Boxes that fill the design cube (any box, stretched per axis), a 2 x 1 x 0.5 box kept in shape,
thin plates at the aspect limit, long rods on each axis, a sphere, and one object of each builtin
family (seed 0, objects 0-22: every family once, stretched to the cube as runs place them).  A
derived pool candidate that cannot be made for such a shape (the looser imprint of a box filling
the cube, the tighter one of a plate two voxels thin) is left out and named; the object is still
designed for.  Random tiny nets: their own candidates are rarely feasible, so the pool's imprints
hold the designs, which is the path these shapes used to break.
"""

import json
import logging

import numpy as np
import pytest
import trimesh

from f2f_jax import config
from f2f_jax import designer as design_module
from f2f_jax.cli.design import main as design_main
from f2f_jax.data import FAMILIES, builtin_object
from f2f_jax.geometry import object_volume
from f2f_jax.train.state import init_trained_nets

LOOSER, TIGHTER = "imprint, 1 voxel looser", "imprint, 1 voxel tighter"


def _primitives() -> dict[str, tuple[trimesh.Trimesh, str]]:
    box = trimesh.creation.box
    return {
        "cube, stretched": (box((1.0, 1.0, 1.0)), "stretch"),
        "2x1x0.5 box, stretched": (box((2.0, 1.0, 0.5)), "stretch"),
        "2x1x0.5 box, fit": (box((2.0, 1.0, 0.5)), "fit"),
        "plate in xy, fit": (box((1.0, 1.0, 0.05)), "fit"),
        "plate in yz, fit": (box((0.05, 1.0, 1.0)), "fit"),
        "rod along x, fit": (box((10.0, 1.0, 1.0)), "fit"),
        "rod along y, fit": (box((1.0, 10.0, 1.0)), "fit"),
        "rod along z, fit": (box((1.0, 1.0, 10.0)), "fit"),
        "sphere": (trimesh.creation.icosphere(subdivisions=3, radius=1.0), "stretch"),
    }


@pytest.fixture(scope="module")
def nets():
    return init_trained_nets(config.get("tiny"))


@pytest.fixture(scope="module")
def primitives(nets):
    g = nets.config.geometry
    return {name: object_volume(mesh, g, scale=scale)[0]
            for name, (mesh, scale) in _primitives().items()}


@pytest.fixture(scope="module")
def families(nets):
    objects = {}
    for i in range(len(FAMILIES)):
        mesh = builtin_object(i, 0)
        objects[mesh.metadata["family"]] = object_volume(mesh, nets.config.geometry)[0]
    assert sorted(objects) == sorted(FAMILIES)
    return objects


def test_boxes_filling_the_cube_leave_the_looser_imprint_out(nets, primitives, caplog):
    g = nets.config.geometry
    names = list(primitives)
    _, _, made = design_module.imprint_candidates(np.stack(list(primitives.values())), g)
    made = dict(zip(names, made))
    for name in ("cube, stretched", "2x1x0.5 box, stretched"):
        assert made[name].tolist() == [True, False, True], name  # grown, nothing is left outside
    for name in ("plate in xy, fit", "plate in yz, fit"):
        assert made[name].tolist() == [True, True, False], name  # shrunk, a 2-voxel wall vanishes
    for name in ("2x1x0.5 box, fit", "rod along x, fit", "rod along z, fit", "sphere"):
        assert made[name].all(), name
    with caplog.at_level(logging.INFO, logger="f2f_jax.designer"):
        pair = design_module.design(primitives["cube, stretched"], params=nets, candidates=1,
                                    verify=False, imprint=True)
    assert pair.left_out == (LOOSER,) and pair.origin != LOOSER
    logged = [r.getMessage() for r in caplog.records if LOOSER in r.getMessage()]
    assert len(logged) == 1 and "fills the whole design cube" in logged[0]
    (entry,) = pair.scores()["left_out"]
    assert entry["origin"] == LOOSER and "design cube" in entry["reason"]


@pytest.mark.parametrize("imprint", [False, True])
def test_every_shape_gets_a_pair_without_simulation(nets, primitives, families, imprint):
    objects = {**primitives, **families}
    pairs = design_module.design(np.stack(list(objects.values())), params=nets, candidates=2,
                                 verify=False, imprint=imprint)
    assert len(pairs) == len(objects) == 32
    for name, pair in zip(objects, pairs):
        assert pair.left.shape == pair.right.shape == (40, 40, 40), name
        assert np.isfinite(pair.predicted).all(), name
        if imprint:  # the plain imprint is made for every object: the pick is feasible
            assert pair.feasible and pair.n_candidates == 5, name


@pytest.mark.slow
@pytest.mark.parametrize("tolerance", [0.0, 0.3])
def test_every_shape_gets_a_verified_pair(nets, primitives, families, tolerance, tmp_path,
                                          monkeypatch):
    """The default mode (the verified pool), and with moved copies under ``tolerance``: every
    object of the batch gets a feasible, simulated pair, the left-out variants named."""
    monkeypatch.setenv("F2F_CACHE_DIR", str(tmp_path / "cache"))  # shipped pieces for the families
    objects = {**primitives, **families}
    pairs = design_module.design(np.stack(list(objects.values())), params=nets, candidates=2,
                                 tolerance=tolerance, copies=1, progress=False)
    assert len(pairs) == len(objects)
    for name, pair in zip(objects, pairs):
        assert pair.feasible and pair.simulated is not None, name
        assert pair.origin not in pair.left_out, name
        assert (pair.moved is not None) == (tolerance > 0), name
    by_name = dict(zip(objects, pairs))
    assert by_name["cube, stretched"].left_out == (LOOSER,)
    assert by_name["plate in xy, fit"].left_out == (TIGHTER,)
    assert by_name["sphere"].left_out == ()


@pytest.mark.slow
@pytest.mark.parametrize("size, scale", [((0.05, 0.05, 0.05), []),
                                         ((0.04, 0.02, 0.01), []),
                                         ((0.04, 0.02, 0.01), ["--scale", "fit"]),
                                         ((40.0, 20.0, 10.0), ["--units", "mm"])])
def test_cli_designs_boxes_with_its_defaults(nets, size, scale, tmp_path, monkeypatch, capsys):
    """A cube and a 2 x 1 x 0.5 box, default options (16 candidates, verified pool): four files,
    exit 0; the placement is in scores.json and in the STL headers."""
    monkeypatch.setenv("F2F_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr("f2f_jax.cli.design._load_trained_nets", lambda run_dir: nets)
    path = tmp_path / "box.stl"
    trimesh.creation.box(size).export(path)
    out = tmp_path / "out"
    assert design_main([str(path), "--out", str(out), *scale]) == 0, capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["design.png", "left.stl", "right.stl",
                                                     "scores.json"]
    scores = json.loads((out / "scores.json").read_text())
    placement = scores["object_scale"]
    mode = "real" if "--units" in scale else "fit" if "fit" in scale else "stretch"
    assert scores["feasible"] and scores["verified"] and placement["mode"] == mode
    assert scores["n_candidates"] == design_module.DEFAULT_CANDIDATES + 3
    if mode == "stretch":
        assert [e["origin"] for e in scores["left_out"]] == [LOOSER]
    else:  # shape kept: 40 x 20 x 10 mm at its real size, or its largest side 57 mm when fit
        got = np.array(placement["object_size_mm"])
        want = [40.0, 20.0, 10.0] if mode == "real" else [57.0, 28.5, 14.25]
        np.testing.assert_allclose(got, want, rtol=1e-6)
    header = (out / "left.stl").read_bytes()[:80].decode("ascii")
    assert header.startswith("f2f_jax left finger (mm) for box.stl") and mode[:4] in header
    loaded = trimesh.load(out / "right.stl")
    assert len(loaded.faces) > 0
    if scores["origin"].startswith("imprint"):  # random nets' own fingers may be porous noise
        assert loaded.is_watertight
