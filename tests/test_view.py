import matplotlib.image as mpimg

from f2f_jax.cli import view


def test_viewer_draws_the_phases_of_a_failed_grasp(tmp_path):
    out = tmp_path / "grasp.png"
    assert view.main(["--object", "box", "--fingers", "wsg50", "--config", "tiny", "--out", str(out)]) == 0
    img = mpimg.imread(out)[..., :3]
    assert img.shape[0] > 100 and img.shape[1] > 300
    # Not blank: the orange object and the blue fingers are both drawn.
    orange = (img[..., 0] > 0.7) & (img[..., 1] > 0.3) & (img[..., 1] < 0.6) & (img[..., 2] < 0.35)
    blue = (img[..., 2] > 0.6) & (img[..., 0] < 0.45)
    assert orange.sum() > 200 and blue.sum() > 200
    assert not list(tmp_path.glob("*.tmp*"))
