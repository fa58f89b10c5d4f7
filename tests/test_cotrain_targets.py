"""Where co-training's anchor pulls the generator (CoTrainRun._best_fingers): each object's imprint,
until a design simulated in a cycle passes strictly more trials on that object."""

import numpy as np
import pytest

from f2f_jax import config
from f2f_jax.errors import F2FError
from f2f_jax.train.cotrain import CoTrainRun


def _fingers(level: float) -> np.ndarray:
    return np.full((2, 2, 2), level, np.float16)


def _run() -> CoTrainRun:
    run = object.__new__(CoTrainRun)  # only what the targets read: names and pretraining rows
    run.names = ["mug", "cup", "box"]
    passed = {"mug": 6, "cup": 11, "box": 3}
    run.pre = {"kind": np.array(["imprint", "wsg50", "imprint", "imprint"]),
               "name": np.array(["mug", "mug", "cup", "box"]),
               "outcome": np.array([[1] * passed["mug"] + [0] * (11 - passed["mug"]), [0] * 11,
                                    [1] * 11, [1] * 3 + [0] * 8], np.uint8),
               "left": np.stack([_fingers(v) for v in (1, 9, 2, 3)]),
               "right": np.stack([-_fingers(v) for v in (1, 9, 2, 3)])}
    return run


def test_best_fingers_move_from_the_imprint_only_to_a_design_that_passed_more():
    run = _run()
    gen = {"name": np.array(["mug", "mug", "mug", "cup", "box"]),
           "outcome": np.array([[1] * 6 + [0] * 5, [1] * 8 + [0] * 3, [1] * 8 + [0] * 3, [1] * 10 + [0],
                                [0] * 11], np.uint8),
           "left": np.stack([_fingers(v) for v in (10, 11, 12, 13, 14)]),
           "right": np.stack([-_fingers(v) for v in (10, 11, 12, 13, 14)])}
    lefts, rights = run._best_fingers(np.array([0, 1, 2, 0]), gen)
    # mug: the first design with 8 trials (not the tie after it, not the one that only equals the
    # imprint's 6); cup: its imprint passed all 11; box: no design beat its imprint's 3
    assert lefts[:, 0, 0, 0].tolist() == [11, 2, 3, 11]
    np.testing.assert_array_equal(rights, -lefts)
    # before any cycle: the imprints
    empty = {k: v[:0] for k, v in gen.items()}
    assert run._best_fingers(np.array([0, 2]), empty)[0][:, 0, 0, 0].tolist() == [1, 3]


def test_anchor_settings_are_checked():
    cfg = config.tiny()
    bad = cfg.replace(train=cfg.train.__class__(**{**cfg.train.__dict__, "anchor_target": "elite"}))
    with pytest.raises(F2FError, match="anchor_target must be one of"):
        CoTrainRun("/nonexistent-run", bad)
    bad = cfg.replace(train=cfg.train.__class__(**{**cfg.train.__dict__, "cycle_candidates": 0}))
    with pytest.raises(F2FError, match="cycle_candidates must be >= 1"):
        CoTrainRun("/nonexistent-run", bad)
    bad = cfg.replace(train=cfg.train.__class__(**{**cfg.train.__dict__, "fn_refit_steps": 0}))
    with pytest.raises(F2FError, match="fn_refit_steps must be >= 1"):
        CoTrainRun("/nonexistent-run", bad)
    bad = cfg.replace(train=cfg.train.__class__(**{**cfg.train.__dict__, "imprint_objects": -1}))
    with pytest.raises(F2FError, match="imprint_objects must be >= 0"):
        CoTrainRun("/nonexistent-run", bad)
    bad = cfg.replace(train=cfg.train.__class__(**{**cfg.train.__dict__, "gn_anneal_epochs": -2}))
    with pytest.raises(F2FError, match="gn_anneal_epochs must be >= 0"):
        CoTrainRun("/nonexistent-run", bad)
    bad = cfg.replace(train=cfg.train.__class__(**{**cfg.train.__dict__, "objectives": "grasp"}))
    with pytest.raises(F2FError, match="objectives must be one of .*'imprint'"):
        CoTrainRun("/nonexistent-run", bad)
