"""The pure pieces of benchmarks/fitness_ranking.py: within-object AUC, the pairwise loss, the gap maps."""

import importlib

import jax.numpy as jnp
import numpy as np
import pytest

ranking = importlib.import_module("benchmarks.fitness_ranking")


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
