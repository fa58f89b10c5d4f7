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
    ("teacher_copies", -1, "teacher_copies must be >= 0"),
    ("teacher_tolerance", 0.0, "teacher_tolerance must be > 0"),
    ("teacher_min_lead", -1.0, "teacher_min_lead must be >= 0"),
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


def _finger(height: float, r: int = 8) -> np.ndarray:
    from f2f_jax.nets.generator import heights_to_tsdf

    return np.asarray(heights_to_tsdf(np.full((1, r, r), height, np.float32), 5.0)[0], np.float16)


def test_confirmed_targets_need_a_lead_on_moved_copies_and_are_simulated_once(tmp_path):
    """``train.teacher_copies``: a target must lead its imprint on moved copies; a pair that
    loses its lead there is refused and never tried again, the next-best pair gets its turn a
    cycle later, the imprint's copies are simulated once, and a killed confirmation resumes."""
    import dataclasses
    import json
    from types import SimpleNamespace

    from f2f_jax.train.teacher import CONFIRM_FILE, confirm_targets

    def trials(vol):  # a stand-in simulator: trials passed grow with the left finger's height
        return min(11, 2 * int(round(float((np.asarray(vol) < 0).sum(-1).mean()))))

    calls = []

    def simulate(objs, lefts, rights, what):
        calls.append(len(lefts))
        out = np.zeros((len(lefts), 11), np.uint8)
        for i, left in enumerate(lefts):
            out[i, :trials(left)] = 1
        return out

    imp = _finger(2)  # 4 trials, exactly and on its copies
    entries = [("a", IMPRINT, 1, 4, imp, imp), ("a", "generator", 1, 9, _finger(5), imp),  # copies: 10
               ("b", IMPRINT, 1, 4, imp, imp),
               ("b", "generator", 1, 11, imp, _finger(3)),  # 11 exactly, 4 on its copies: luck
               ("b", "generator + height noise", 1, 7, _finger(4), imp),  # 7 exactly, 8 on copies
               ("c", IMPRINT, 1, 4, imp, imp), ("c", "generator", 1, 4, _finger(6), imp)]  # no lead
    outcome = np.zeros((len(entries), 11), np.uint8)
    for i, e in enumerate(entries):
        outcome[i, :e[3]] = 1
    rows = {"name": np.array([e[0] for e in entries]), "kind": np.array([e[1] for e in entries]),
            "cycle": np.array([e[2] for e in entries]), "outcome": outcome,
            "left": np.stack([e[4] for e in entries]), "right": np.stack([e[5] for e in entries])}
    ts = TeacherSet(objects=np.zeros((3, 8, 8, 8), np.float16), names=["a", "b", "c"],
                    imprint_left=np.stack([imp] * 3), imprint_right=np.stack([imp] * 3),
                    fn_holdout=np.zeros(3, bool))
    cfg = config.teacher()
    cfg = cfg.replace(train=dataclasses.replace(cfg.train, teacher_copies=3, teacher_chunk=1))
    run = SimpleNamespace(cfg=cfg, dir=tmp_path, seed=0, progress=False, simulate=simulate)

    def killed(*args):  # a kill while the second object's copies simulate
        if calls:
            raise KeyboardInterrupt
        return simulate(*args)

    run.simulate = killed
    with pytest.raises(KeyboardInterrupt):
        confirm_targets(run, ts, 1, rows)
    assert calls == [6] and len(json.loads((tmp_path / CONFIRM_FILE).read_text())["designs"]) == 1
    run.simulate = simulate
    chosen, stats = confirm_targets(run, ts, 1, rows)
    assert calls == [6, 6]  # only b's target and imprint: a's were kept from before the kill
    assert chosen.tolist() == [1, -1, -1]  # a kept; b's lucky pair refused; c never led
    assert stats["exact_improved_objects"] == 2 and stats["refused_this_cycle"] == 1
    assert stats["target_lead_on_copies"] == pytest.approx(6.0)
    left, _, tstats = teacher_targets(None, ts, rows, chosen)
    assert (left[0] == rows["left"][1]).all() and (left[1] == imp).all()
    assert tstats["improved_objects"] == 1 and tstats["target_trials"] == pytest.approx((9 + 4 + 4) / 3)

    chosen, stats = confirm_targets(run, ts, 2, rows)  # the next cycle: b's next-best pair's turn
    assert calls == [6, 6, 3]  # b's new pair alone: its imprint's copies are known
    assert chosen.tolist() == [1, 4, -1] and stats["kept_this_cycle"] == 1
    again, _ = confirm_targets(run, ts, 2, rows)  # a rerun of the cycle simulates nothing
    assert calls == [6, 6, 3] and again.tolist() == [1, 4, -1]
    strict = cfg.replace(train=dataclasses.replace(cfg.train, teacher_min_lead=5.0))
    run2 = SimpleNamespace(cfg=strict, dir=tmp_path / "strict", seed=0, progress=False, simulate=simulate)
    assert confirm_targets(run2, ts, 1, rows)[0].tolist() == [1, -1, -1]  # a leads by 6 >= 5
    assert confirm_targets(run2, ts, 2, rows)[0].tolist() == [1, -1, -1]  # b's 4 < 5
