"""research/design_tolerance.py: the table of picks re-simulated on fresh moved copies."""

import numpy as np
import pytest

import research.design_tolerance as bench
from tests.test_sim_retest import _outcomes  # [N, J] trials passed -> [N, J, 11] outcomes


def test_pick_table_pairs_each_pick_with_the_base_and_imprint_on_fresh_copies():
    picks = {"exact": np.array([0, 1, 2]), "moved": np.array([0, 3, 2]), "imprint": np.array([4, 4, 4])}
    reported = {"exact": np.array([11, 11, 10]), "moved": np.array([10.5, 10.0, 9.5]),
                "imprint": np.array([8, 8, 8])}
    fresh = {"exact": _outcomes(np.array([[9, 9], [2, 4], [10, 10]])),   # object 1's was luck
             "moved": _outcomes(np.array([[9, 9], [9, 9], [10, 10]])),
             "imprint": _outcomes(np.array([[8, 8], [8, 8], [8, 8]]))}
    table = bench.pick_table(picks, reported, fresh, base="exact", imprint="imprint")
    assert table["exact"]["reported"] == pytest.approx(32 / 3)
    assert table["exact"]["fresh"] == pytest.approx(44 / 6)
    assert table["moved"]["fresh"] == pytest.approx(28 / 3)
    gain = table["moved"]["gain_over_base"]  # +0, +6, +0 trials per object
    assert gain[0] == pytest.approx(2.0) and 0 <= gain[1] <= gain[0] <= gain[2] <= 6
    assert table["moved"]["gain_over_imprint"][0] == pytest.approx(28 / 3 - 8)
    assert table["exact"]["gain_over_base"] == [0.0, 0.0, 0.0]
    assert table["moved"]["same_pick_as_base"] == 2 and table["imprint"]["same_pick_as_base"] == 0


@pytest.mark.parametrize("flags", [["--tolerance", "0"], ["--copies", "0"], ["--fresh-copies", "0"]])
def test_bad_options_are_refused_before_any_work(flags, tmp_path):
    with pytest.raises(SystemExit) as exc:
        bench.main(["--run-dir", str(tmp_path / "missing"), *flags])
    assert exc.value.code == 2
