"""benchmarks/finger_fidelity.py: the height-map difference it reports beside the simulated trials."""

import importlib

import numpy as np
import pytest

fidelity = importlib.import_module("benchmarks.finger_fidelity")


def test_height_gap_counts_voxels_of_height_where_either_finger_stands(sphere_tsdf):
    from f2f_jax.geometry import imprint_fingers, wsg50_fingers

    left, _ = imprint_fingers(sphere_tsdf)
    pad, _ = wsg50_fingers()
    assert fidelity.height_gap_voxels(left, left) == 0.0
    # the pad two voxels taller everywhere (the empty top voxels wrap round to the mount)
    assert fidelity.height_gap_voxels(np.roll(pad, 2, axis=2), pad) == pytest.approx(2.0, abs=1e-6)
    # the imprint against the pad: the imprint's relief differs, several voxels of it
    assert fidelity.height_gap_voxels(pad, left) > 1.0
