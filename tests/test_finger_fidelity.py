"""research/finger_fidelity.py: the height-map difference it reports beside the simulated trials."""

import importlib

import numpy as np
import pytest

fidelity = importlib.import_module("research.finger_fidelity")


def test_height_gap_counts_voxels_of_height_where_either_finger_stands(sphere_tsdf):
    from f2f_jax.geometry import imprint_fingers, wsg50_fingers

    left, _ = imprint_fingers(sphere_tsdf)
    pad, _ = wsg50_fingers()
    assert fidelity.height_gap_voxels(left, left) == 0.0
    # the pad two voxels taller everywhere (the empty top voxels wrap round to the mount)
    assert fidelity.height_gap_voxels(np.roll(pad, 2, axis=2), pad) == pytest.approx(2.0, abs=1e-6)
    # the imprint against the pad: the imprint's relief differs, several voxels of it
    assert fidelity.height_gap_voxels(pad, left) > 1.0


def test_a_finger_rebuilt_from_its_height_map_keeps_it(sphere_tsdf):
    from f2f_jax.geometry import imprint_fingers
    from f2f_jax.geometry.finger_tiling import finger_height_map

    left, right = imprint_fingers(sphere_tsdf)
    for finger in (left, right):
        heights = finger_height_map(finger)
        rebuilt = fidelity.finger_from_heights(heights)
        # every column within half a voxel (the imprint's TSDF is not linear along w, so the
        # interpolated surface moves a little), the solid voxels the same but for a few
        gap = np.abs(finger_height_map(rebuilt) - heights) / 0.0015
        assert gap.max() < 0.5 and fidelity.height_gap_voxels(rebuilt, finger) < 0.2
        assert ((rebuilt < 0) != (finger < 0)).mean() < 0.01


def test_pca_roundtrip_is_exact_at_full_rank_and_lossy_below(rng):
    train = rng.normal(size=(20, 6, 5))
    np.testing.assert_allclose(fidelity.pca_roundtrip(train, train[:3], 20), train[:3], atol=1e-9)
    coarse = fidelity.pca_roundtrip(train, train[:3], 2)
    fine = fidelity.pca_roundtrip(train, train[:3], 10)
    assert np.abs(fine - train[:3]).mean() < np.abs(coarse - train[:3]).mean()


def test_height_map_generator_learns_the_imprint_of_unseen_objects(sphere_tsdf):
    """Column-local: trained on the sphere at 12 places, it must put out the imprint heights of
    the sphere at places it never saw within ~1 voxel (untrained, it is ~20 voxels off)."""
    train = np.stack([np.roll(sphere_tsdf, (dy, dz), axis=(1, 2))
                      for dy in (-6, -2, 2, 6) for dz in (-4, 0, 4)])
    test = np.stack([np.roll(sphere_tsdf, s, axis=(1, 2)) for s in ((-4, 2), (4, -2))])
    targets = fidelity.imprint_height_targets(train)
    assert targets.shape == (12, 40, 40, 2) and targets.max() > 10
    truth = fidelity.imprint_height_targets(test)
    untrained, _ = fidelity.train_height_generator(train, targets, steps=0)
    trained, loss = fidelity.train_height_generator(train, targets, steps=150, batch=12)
    assert np.abs(untrained(test) - truth).mean() > 5.0
    assert loss < 1.5 and np.abs(trained(test) - truth).mean() < 1.5


def test_height_map_picture_is_written_and_survives_an_empty_finger(tmp_path, sphere_tsdf):
    from f2f_jax.geometry import imprint_fingers, wsg50_fingers

    left, _ = imprint_fingers(sphere_tsdf)
    pad, _ = wsg50_fingers()
    empty = np.ones_like(pad)  # an infeasible design: nothing solid
    rows = {"imprint": (np.stack([left, left]), [11, 9]), "a design": (np.stack([pad, empty]), [3, 0])}
    path = tmp_path / "heights.png"
    fidelity.height_map_picture(rows, np.stack([sphere_tsdf, sphere_tsdf]), path)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 5000
