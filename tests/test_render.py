"""Grasp and shape-grid renderings: PNGs that show something, fingers placed as in the gripper."""

import matplotlib.image as mpimg
import numpy as np
import pytest

from f2f_jax.geometry import finger_extent, imprint_fingers, wsg50_fingers
from f2f_jax.render import grasp_scene, render_grasp, render_volumes


def _colour_counts(path):
    img = mpimg.imread(path)[..., :3]
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return img, {
        "orange": int(((r - b > 0.3) & (r > g) & (g > b)).sum()),  # left finger
        "blue": int(((b - r > 0.25) & (b > g)).sum()),  # right finger
        "green": int(((g - r > 0.3) & (g - b > 0.2)).sum()),  # successful trials
        "red": int(((r - g > 0.45) & (r - b > 0.45)).sum()),  # failed trials
        "grey": int(((abs(r - g) < 0.04) & (abs(g - b) < 0.08) & (r > 0.15) & (r < 0.75)).sum()),  # object
    }


def test_render_grasp_draws_object_fingers_and_scores(tmp_path, sphere_tsdf):
    left, right = imprint_fingers(sphere_tsdf)
    out = tmp_path / "sub" / "grasp.png"
    scores = [1, 1, 0, 1, 1, 0, 1, 1, 1, 0, 1]
    assert render_grasp(out, sphere_tsdf, left, right, title="sphere", scores=scores, opening=0.01) == out
    img, counts = _colour_counts(out)
    assert img.shape[0] > 200 and img.shape[1] > 600
    assert img.std() > 0.1  # not blank
    for colour in ("orange", "blue", "green", "red", "grey"):
        assert counts[colour] > 300, counts
    # 8 green and 3 red boxes of equal size
    assert 1.5 < counts["green"] / counts["red"] < 4.5, counts
    assert not [p for p in out.parent.iterdir() if p.name != "grasp.png"]  # no temporary left


def test_render_grasp_without_object_or_scores(tmp_path):
    left, right = wsg50_fingers()
    out = render_grasp(tmp_path / "fingers.png", None, left, right)
    _, counts = _colour_counts(out)
    assert counts["orange"] > 300 and counts["blue"] > 300
    assert counts["green"] == 0 and counts["red"] == 0


def test_render_grasp_rejects_bad_input(tmp_path, sphere_tsdf):
    with pytest.raises(ValueError, match="at least one"):
        render_grasp(tmp_path / "x.png")
    with pytest.raises(ValueError, match="11 values"):
        render_grasp(tmp_path / "x.png", sphere_tsdf, scores=[1, 0, 1])
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("opening", [0.0, 0.012])
def test_grasp_scene_places_fingers_at_the_jaws(sphere_tsdf, cfg, opening):
    g = cfg.geometry
    left, right = imprint_fingers(sphere_tsdf)
    (ov, _, _), (lv, _, _), (rv, _, _) = grasp_scene(sphere_tsdf, left, right, opening=opening, cfg=g)
    vox = g.voxel_size
    # The object rests on the floor, centred on the gripper's axis.
    assert abs(ov[:, 2].min()) < vox
    assert abs(ov[:, 0].min() + ov[:, 0].max()) < vox
    # Mount planes at -/+ (cube + opening); each tip reaches finger_extent from its mount.
    assert lv[:, 0].min() == pytest.approx(-(g.cube_size + opening), abs=vox)
    assert lv[:, 0].max() == pytest.approx(-(g.cube_size + opening) + finger_extent(left, g), abs=vox)
    assert rv[:, 0].max() == pytest.approx(g.cube_size + opening, abs=vox)
    assert rv[:, 0].min() == pytest.approx(g.cube_size + opening - finger_extent(right, g), abs=vox)
    if opening == 0.0:
        # imprint fingers closed on a sphere: their cavities hug its surface, tips at mid-plane
        assert lv[:, 0].max() == pytest.approx(0.0, abs=vox)
        assert rv[:, 0].min() == pytest.approx(0.0, abs=vox)
    # Fingers and object share the vertical frame.
    assert lv[:, 2].min() == pytest.approx(rv[:, 2].min(), abs=1e-9)
    assert abs(lv[:, 2].max() - ov[:, 2].max()) < 2 * vox


def test_render_volumes_grid(tmp_path, sphere_tsdf):
    left, right = imprint_fingers(sphere_tsdf)
    out = render_volumes(tmp_path / "grid.png", [sphere_tsdf, left, right], ["sphere", "left", "right"])
    img, counts = _colour_counts(out)
    assert img.std() > 0.05 and counts["grey"] > 1000
    with pytest.raises(ValueError, match="2 titles for 3 volumes"):
        render_volumes(tmp_path / "bad.png", [sphere_tsdf, left, right], ["a", "b"])
    assert not (tmp_path / "bad.png").exists()


def test_render_volumes_coarse_step_keeps_thin_shapes(tmp_path, cfg):
    # a 1-voxel plate vanishes when averaged over 2x2x2 blocks: the drawing falls back to full res
    plate = np.ones((40, 40, 40), np.float32)
    plate[5:35, 5:35, 20] = -0.2
    out = render_volumes(tmp_path / "plate.png", [plate], step=2)
    assert mpimg.imread(out)[..., :3].std() > 0.02
