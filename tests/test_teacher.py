"""The simulator as the generator's teacher: which pair becomes an object's target, which settings
are refused, and that the teacher config can fork a default run's pretraining."""

from __future__ import annotations

import numpy as np
import pytest

from f2f_jax import config
from f2f_jax.errors import ConfigError
from f2f_jax.train.cotrain import check_config
from f2f_jax.train.run_dir import COTRAIN_FIELDS, differing_fields
from f2f_jax.train.checkpoint import config_to_dict
from f2f_jax.train.teacher import IMPRINT, TeacherSet, best_rows, teacher_targets


def _rows(entries):
    """Rows of (object name, kind, cycle, trials passed), with left/right volumes that say which
    row they are (every voxel holds the row index)."""
    n = len(entries)
    outcome = np.zeros((n, 11), np.uint8)
    for i, (_, _, _, passed) in enumerate(entries):
        outcome[i, :passed] = 1
    vol = np.arange(n, dtype=np.float16)[:, None, None, None] * np.ones((1, 2, 2, 2), np.float16)
    return {"name": np.array([e[0] for e in entries]), "kind": np.array([e[1] for e in entries]),
            "cycle": np.array([e[2] for e in entries]), "outcome": outcome, "left": vol, "right": -vol}


def test_best_rows_prefer_more_trials_then_the_imprint_then_the_earlier_cycle():
    rows = _rows([
        ("a", IMPRINT, 1, 7), ("a", "generator", 1, 9), ("a", "generator + height noise", 2, 9),
        ("b", "generator", 1, 8), ("b", IMPRINT, 1, 8), ("b", "imprint, 1 voxel looser", 1, 8),
        ("c", "generator", 2, 3), ("c", "generator", 1, 3),
    ])
    best, passed, imprint = best_rows(rows, ["a", "b", "c", "d"])
    assert best.tolist() == [1, 4, 7, -1]  # a: most trials, earlier cycle; b: the imprint's tie
    assert passed.tolist() == [9, 8, 3, -1]
    assert imprint.tolist() == [7, 8, -1, -1]


def test_targets_keep_the_imprint_unless_a_design_passes_strictly_more():
    rows = _rows([("a", IMPRINT, 1, 7), ("a", "generator", 2, 9),
                  ("b", IMPRINT, 1, 8), ("b", "generator", 1, 8),
                  ("c", "generator", 1, 11)])  # c has no imprint row: nothing to compare with
    r = 2
    ts = TeacherSet(objects=np.zeros((3, r, r, r), np.float16), names=["a", "b", "c"],
                    imprint_left=np.full((3, r, r, r), 100, np.float16),
                    imprint_right=np.full((3, r, r, r), -100, np.float16),
                    fn_holdout=np.zeros(3, bool))
    left, right, stats = teacher_targets(None, ts, rows)
    assert left[0].flat[0] == 1 and right[0].flat[0] == -1  # row 1: a's generator design
    assert left[1].flat[0] == 100 and left[2].flat[0] == 100  # imprints kept
    assert stats["improved_objects"] == 1 and stats["improved_by_origin"] == {"generator": 1}
    assert stats["target_trials"] == pytest.approx((9 + 8 + 0) / 3)
    control, _, none = teacher_targets(None, ts, None)  # the control: every target an imprint
    assert (control == 100).all() and none == {}


@pytest.mark.parametrize("field, value, words", [
    ("teacher", "oracle", "train.teacher must be one of"),
    ("teacher_candidates", 0, "teacher_candidates must be >= 1"),
    ("teacher_chunk", 0, "teacher_chunk must be >= 1"),
    ("teacher_fn_holdout", 1.0, "teacher_fn_holdout must be in [0, 1)"),
    ("teacher_lr", 0.0, "teacher_lr must be > 0"),
])
def test_bad_teacher_settings_are_refused(field, value, words):
    cfg = config.teacher()
    bad = cfg.replace(train=__import__("dataclasses").replace(cfg.train, **{field: value}))
    with pytest.raises(ConfigError, match=words.replace("[", r"\[").replace(")", r"\)")):
        check_config(bad)


def test_teacher_config_forks_a_default_runs_pretraining():
    """The teacher config differs from the default only in co-training fields, so both it and its
    control start from one default run's pretraining (``--from-pretrained``)."""
    differ = differing_fields(config_to_dict(config.default()), config_to_dict(config.teacher()))
    assert differ and all(f.split(".")[0] == "train" and f.split(".")[1] in COTRAIN_FIELDS for f in differ)
    t = config.teacher().train
    assert t.teacher == "simulator" and t.teacher_objects + 51 >= 280
    # its extra teacher objects are the builtin objects whose pieces ship with the package
    assert t.teacher_seed == 0 and t.n_objects + t.teacher_objects <= 300


def test_the_plan_counts_the_teacher_designs():
    from f2f_jax import run_plan

    teach = config.teacher()
    plan = run_plan.planned_simulations(teach)
    assert plan["cycles"] == (51 + 236) * (3 * 4 + 3)  # 4 a cycle, the 3 imprint variants once
    control = teach.replace(train=__import__("dataclasses").replace(teach.train, teacher="imprint"))
    assert run_plan.planned_simulations(control)["cycles"] == 0


def test_start_from_weights_refuses_what_is_not_a_run(tmp_path, capsys):
    """research/start_from_weights.py: a folder without a run's parts, or a used output, is a
    clear error before anything is written."""
    import importlib

    script = importlib.import_module("research.start_from_weights")
    (tmp_path / "data").mkdir()
    with pytest.raises(SystemExit):
        script.main(["--data", str(tmp_path / "data"), "--out", str(tmp_path / "out")])
    assert "holds no objects" in capsys.readouterr().err and not (tmp_path / "out").exists()
    (tmp_path / "used").mkdir()
    (tmp_path / "used" / "x").write_text("x")
    with pytest.raises(SystemExit):
        script.main(["--data", str(tmp_path / "data"), "--out", str(tmp_path / "used")])
    assert "is not empty" in capsys.readouterr().err
