"""research/fitness_ranking.py: within-object AUC, the pairwise loss, the gap maps, and `fit` end to end."""

import importlib

import jax.numpy as jnp
import numpy as np
import pytest

ranking = importlib.import_module("research.fitness_ranking")


def test_within_object_auc_counts_only_objects_with_both_outcomes():
    scores = np.array([[0.9, 0.8, 0.1, 0.2], [0.1, 0.9, 0.5, 0.5], [0.3, 0.3, 0.3, 0.3]])
    grasp = np.array([[1, 1, 0, 0], [1, 0, 1, 0], [1, 1, 1, 1]])
    auc, n = ranking.within_object_auc(scores, grasp)
    # object 0 perfect (1.0); object 1: held 0.1, 0.5 against failed 0.9, 0.5 -> 0.5 tie of 4
    # pairs, 0 wins -> 0.125; object 2 has no failed candidate and is left out
    assert n == 2 and auc == pytest.approx((1.0 + 0.125) / 2)
    # an infeasible candidate is not a failed grasp to rank against
    feasible = np.array([[1, 1, 0, 0], [1, 0, 1, 0], [1, 1, 1, 1]], bool)
    auc, n = ranking.within_object_auc(scores, grasp, feasible)
    assert n == 0 and np.isnan(auc)
    with pytest.raises(ValueError, match=r"\[N, K\]"):
        ranking.within_object_auc(scores[0], grasp[0])


def test_pair_loss_falls_when_held_candidates_score_higher():
    labels = jnp.array([[1.0, 0.0, 1.0, 0.0]])
    right = ranking.pair_loss(jnp.array([[3.0, -3.0, 2.0, -2.0]]), labels)
    wrong = ranking.pair_loss(jnp.array([[-3.0, 3.0, -2.0, 2.0]]), labels)
    tied = ranking.pair_loss(jnp.zeros((1, 4)), labels)
    assert float(tied) == pytest.approx(np.log(2))
    assert float(right) < float(tied) < float(wrong)
    # objects whose candidates all hold (or all fail) add nothing: same loss, same value
    assert float(ranking.pair_loss(jnp.zeros((1, 4)), jnp.ones((1, 4)))) == 0.0


def test_gap_maps_see_the_imprint_close_on_the_object(sphere_tsdf):
    from f2f_jax.geometry import imprint_fingers, wsg50_fingers
    from f2f_jax.nets.fitness import fitness_input

    maps = {}
    for name, (left, right) in {"imprint": imprint_fingers(sphere_tsdf), "flat": wsg50_fingers()}.items():
        v = fitness_input(jnp.asarray(sphere_tsdf)[None], jnp.asarray(left)[None], jnp.asarray(right)[None])
        maps[name] = np.asarray(ranking.contact_maps(v))[0]
    on_object = maps["imprint"][..., 5] > 0.5
    assert on_object.sum() > 50
    # relative gaps (each jaw's gap less its smallest) on the object's columns: the imprint meets
    # the sphere over its face, the flat pad at the sphere's equator only
    for jaw in (2, 3):
        imprint = np.median(maps["imprint"][..., jaw][on_object])
        assert imprint < 0.1
        assert np.median(maps["flat"][..., jaw][on_object]) > 2 * imprint + 0.05


def test_fit_learns_a_within_object_ranking_that_the_gaps_decide(tmp_path, sphere_tsdf):
    """End to end on data whose labels only the fingers' alignment decides: per object (the sphere
    moved in y and z), four imprints of the same sphere, two made where the object lies (held) and
    two made 3 voxels away (failed): all four equally big, so only fit tells them apart. The ranker
    must rank held above failed on objects it never saw (the test's and the validation's)."""
    import json

    from f2f_jax.geometry import imprint_fingers

    def objects_and_candidates(shifts):
        objs, lefts, rights = [], [], []
        for dy, dz in shifts:
            objs.append(np.roll(sphere_tsdf, (dy, dz), axis=(1, 2)))
            cands = [imprint_fingers(np.roll(sphere_tsdf, (dy + a, dz + b), axis=(1, 2)))
                     for a, b in ((0, 0), (3, 0), (0, -3), (1, 0))]
            lefts.append(np.stack([c[0] for c in cands]))
            rights.append(np.stack([c[1] for c in cands]))
        held = np.tile(np.array([1, 0, 0, 1], np.uint8), (len(shifts), 1))
        return np.stack(objs), np.stack(lefts), np.stack(rights), held

    shifts = [(dy, dz) for dy in (-6, -3, 0, 3, 6) for dz in (-4, 0, 4)]
    objs, lefts, rights, held = objects_and_candidates(shifts)
    np.savez(tmp_path / "r0_synthetic_o0.npz", objects=objs.astype(np.float16),
             lefts=lefts.astype(np.float16), rights=rights.astype(np.float16),
             feasible=np.ones(held.shape, bool), grasp=held)
    t_objs, t_lefts, t_rights, t_held = objects_and_candidates([(-5, -2), (5, 2), (-1, 5), (2, -5)])
    simulated = np.repeat(t_held[..., None], 11, -1)
    simulated[:, 0, 1:] = 0  # the own design passes fewer trials than the other held candidate
    np.savez(tmp_path / "test.npz", objects=t_objs, lefts=t_lefts, rights=t_rights,
             feasible=np.ones(t_held.shape, bool), simulated=simulated)

    out = tmp_path / "fit.json"
    assert ranking.main(["fit", "--data", str(tmp_path), "--steps", "80", "--objects", "4",
                         "--per-object", "4", "--reports", "1", "--val-fraction", "0.3",
                         "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    last = result["report"][-1]
    assert result["rows"] < 4 * len(shifts)  # some objects were kept out to validate on
    assert last["within_objects"] == 4 and last["within_auc"] > 0.9
    assert last["val_auc"] > 0.9
