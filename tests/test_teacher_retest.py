"""research/teacher_retest.py: whether the teacher's targets keep their lead on moved copies."""

import numpy as np
import pytest

import research.teacher_retest as study


def _outcomes(passed):
    """[...] trials passed -> [..., 11] outcomes, the first ``passed`` trials 1."""
    passed = np.asarray(passed)
    return (np.arange(11) < passed[..., None]).astype(np.uint8)


def test_a_lead_that_vanishes_on_moved_copies_is_counted_lost():
    exact = _outcomes([[11, 9], [10, 9], [9, 8]])  # [n, 2]: target, imprint; every target leads
    moved = _outcomes(np.array([[[11, 9], [8, 9], [8, 8]],   # copy 1
                                [[10, 9], [8, 10], [8, 8]]]))  # copy 2: object 1's lead was luck
    stored = exact.copy()
    stored[2, 0, -1] ^= 1  # one stored outcome the re-simulation does not reproduce
    t = study.retest_table(exact, moved, stored, ["generator", "imprint, 1 voxel looser", "generator"])
    assert t["exact_reproduced"] == 2
    assert t["exact"]["target"] == pytest.approx(10.0) and t["exact"]["imprint"] == pytest.approx(26 / 3)
    assert t["lead_kept"] == 1 and t["lead_lost"] == 1  # object 2 ties on its copies
    gain = t["moved_gain"]  # per object +1.5, -1.5, 0
    assert gain["diff"] == pytest.approx(0.0) and gain["better"] == 1 and gain["worse"] == 1
    assert t["by_origin"]["imprint, 1 voxel looser"] == {"objects": 1, "exact_gain": 1.0, "moved_gain": -1.5}
    assert t["by_origin"]["generator"]["moved_gain"] == pytest.approx(0.75)


def test_without_copies_the_exact_pairs_give_the_gain():
    """The PyBullet judge's exact-only retest: the paired gain is over the exact outcomes, and no
    moved figure is made up."""
    exact = _outcomes([[11, 9], [8, 9], [9, 9]])  # per object +2, -1, 0
    t = study.retest_table(exact, np.zeros((0, *exact.shape), np.uint8), exact, ["generator"] * 3)
    gain = t["exact_gain"]
    assert gain["diff"] == pytest.approx(1 / 3) and gain["better"] == 1 and gain["worse"] == 1
    assert t["moved"] is None and t["moved_gain"] is None and t["lead_kept"] is None
    assert t["by_origin"]["generator"] == {"objects": 3, "exact_gain": pytest.approx(1 / 3),
                                           "moved_gain": None}


@pytest.mark.parametrize("flags", [["--copies", "0"], ["--tolerance", "0"], ["--cycle", "0"],
                                   ["--judge", "pybullet", "--copies", "-1"],
                                   ["--judge", "pybullet", "--workers", "0"]])
def test_bad_options_are_refused_before_any_work(flags, tmp_path):
    with pytest.raises(SystemExit) as exc:
        study.main(["--run-dir", str(tmp_path), *flags])
    assert exc.value.code == 2


def test_a_folder_that_is_no_run_is_refused(tmp_path):
    with pytest.raises(SystemExit) as exc:
        study.main(["--run-dir", str(tmp_path)])
    assert exc.value.code == 2


def test_the_pybullet_judge_takes_no_copies_and_still_checks_the_folder(tmp_path, capsys):
    """``--copies 0`` is allowed with the PyBullet judge (its exact outcomes are new), so what
    refuses the empty folder is that it is no run."""
    pytest.importorskip("pybullet")
    with pytest.raises(SystemExit) as exc:
        study.main(["--run-dir", str(tmp_path), "--judge", "pybullet", "--copies", "0"])
    assert exc.value.code == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]  # argparse's last line: the reason
    assert "is not a run directory" in error and "--copies" not in error


def test_the_join_counts_the_peers_gain_over_the_targets_whose_lead_held():
    """Object 0 leads on the moved copies and gains under the peer; object 1 loses its lead on the
    copies, so the moved-copies subset leaves its peer loss out; object 2 leads by 2 and ties."""
    moved = np.array([[[10, 9], [8, 9], [11, 9]],
                      [[10, 9], [9, 9], [11, 9]]])  # [C=2, n=3, 2]: leads +1, -0.5, +2
    peer = np.array([[11, 8], [5, 9], [9, 9]])  # gains +3, -4, 0
    t = study.join_table(moved, peer)
    assert t["all"]["objects"] == 3 and t["all"]["diff"] == pytest.approx(-1 / 3)
    kept = t["lead kept on the copies"]
    assert kept["objects"] == 2 and kept["diff"] == pytest.approx(1.5)
    assert kept["better"] == 1 and kept["worse"] == 0
    assert t["lead >= 2 trials on the copies"] == {"objects": 1, "diff": 0.0, "ci_low": 0.0, "ci_high": 0.0,
                                                   "better": 0, "worse": 0}
    assert t["the peer's imprint misses a trial"]["objects"] == 3  # 8, 9 and 9 of 11


def test_a_join_of_files_without_per_object_trials_is_refused(tmp_path):
    old = tmp_path / "old.json"
    old.write_text('{"improved": 3}')
    with pytest.raises(SystemExit, match="per-object"):
        study.main(["--join", str(old), str(old)])
