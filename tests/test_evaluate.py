"""The paper's tables (f2f_jax.tables) on a few built-in objects with the tiny config.

The objects are a cylinder, a U-shape and a capsule (built-in 2, 3 and 9): their collision hulls
take ~2 s together, and the flat WSG50 tips cannot lift them at mu 0.2 while their imprints can.
"""

import csv
import io

import numpy as np
import pytest

from f2f_jax import config
from f2f_jax import tables as E
from f2f_jax.data import builtin_objects
from f2f_jax.geometry import imprint_fingers, mesh_to_tsdf, wsg50_fingers
from f2f_jax.sim import evaluate as simulate

PICK = (2, 3, 9)


@pytest.fixture(scope="module")
def tiny():
    return config.tiny()


@pytest.fixture(scope="module")
def objects(tiny):
    meshes = builtin_objects(max(PICK) + 1, seed=0)
    return np.stack([mesh_to_tsdf(meshes[i], tiny.geometry) for i in PICK])


@pytest.fixture(scope="module")
def hulls(objects, tiny, tmp_path_factory):
    _, hulls, notes = E.prepare_objects(objects, tiny, cache_dir=tmp_path_factory.mktemp("hulls"),
                                        progress=False)
    assert notes == []
    return hulls


def broken_designer(objects):
    """Fingers with no solid voxel: infeasible."""
    empty = np.ones_like(np.asarray(objects, np.float32))
    return empty, empty.copy()


@pytest.fixture(scope="module")
def t1(objects, hulls, tiny):
    designers = {"WSG50": E.wsg50_designer(tiny), "Imprint": E.imprint_designer(tiny),
                 "Broken": broken_designer}
    return E.table1(designers, objects, tiny, object_hulls=hulls, progress=False)


def test_table1_imprint_beats_wsg50_and_the_averages_add_up(t1):
    assert t1.n_objects == len(PICK)
    assert t1.values["Imprint"]["grasp"] >= t1.values["WSG50"]["grasp"]
    assert t1.values["Imprint"]["grasp"] > 50.0  # imprints cage these shapes
    for name, row in t1.values.items():
        out = t1.outcomes[name]
        assert out.shape == (len(PICK), 11) and out.dtype == np.uint8
        # absolute rates over all objects: each column is the mean of its trial, in percent
        np.testing.assert_allclose([row[c] for c in ("grasp", "S1", "S2", "S3", "S4")],
                                   100 * out[:, :5].mean(0))
        np.testing.assert_allclose(row["S avg"], np.mean([row[f"S{k}"] for k in range(1, 5)]))
        rob = [row[c] for c in ("R-30", "R-20", "R-10", "R+10", "R+20", "R+30")]
        np.testing.assert_allclose(rob, 100 * out[:, 5:].mean(0))
        np.testing.assert_allclose(row["R avg"], np.mean(rob))
        # a trial after a failed grasp counts as a failure, so nothing exceeds the grasp rate
        assert all(row[c] <= row["grasp"] for c in E.TABLE1_COLUMNS)
    assert t1.feasible["WSG50"] == t1.feasible["Imprint"] == 1.0


def test_an_infeasible_designer_scores_zero_with_feasible_fraction_zero(t1):
    assert t1.feasible["Broken"] == 0.0
    assert all(v == 0.0 for v in t1.values["Broken"].values())
    assert not t1.outcomes["Broken"].any()


def test_markdown_and_csv_hold_every_row_column_and_the_papers_figures(t1, tmp_path):
    md = t1.to_markdown()
    for name in E.PAPER_TABLE1:
        assert f"| {name} | ours |" in md
    assert "| Broken | ours |" in md and "not in paper" in md  # our extra row, after the paper's
    assert md.index("| WSG50 |") < md.index("| Imprint |") < md.index("| Fit2Form |") < md.index("| Broken |")
    assert md.count("not run") == len(E.PAPER_TABLE1) - 2  # every paper row but WSG50 and Imprint
    for header in ("Grasp", "S1", "S4", "S avg", "-30°", "+30°", "R avg", "feasible"):
        assert f" {header} |" in md
    for figure in ("25.8", "87.6", "78.8", "59.8", "21.3"):
        assert figure in md
    assert f"{t1.values['Imprint']['grasp']:.1f}" in md

    rows = list(csv.DictReader(io.StringIO(t1.to_csv())))
    assert {(r["designer"], r["source"]) for r in rows} >= {(n, s) for n in E.PAPER_TABLE1
                                                            for s in ("ours", "paper")}
    assert set(E.TABLE1_COLUMNS) <= set(rows[0])
    by = {(r["designer"], r["source"]): r for r in rows}
    assert float(by[("Fit2Form", "paper")]["R avg"]) == 78.8
    assert float(by[("WSG50", "paper")]["grasp"]) == 25.8
    assert by[("ImpGN", "ours")]["status"] == "not run"
    assert float(by[("Imprint", "ours")]["S avg"]) == pytest.approx(t1.values["Imprint"]["S avg"], abs=0.01)
    assert float(by[("Broken", "ours")]["feasible"]) == 0.0

    paths = t1.write(tmp_path)
    assert paths["md"].read_text(encoding="utf-8") == md
    assert paths["png"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(tmp_path.glob(".*tmp*"))  # atomic writes leave no temporary files


def test_object_offsets_far_out_of_the_jaws_make_imprint_grasps_fail(objects, hulls, tiny, t1):
    capsule, h = objects[2], hulls[2]
    left, right = imprint_fingers(capsule, tiny)
    assert t1.outcomes["Imprint"][2, 0] == 1  # held at the grasp location
    # per-candidate offsets: in place, and 8 cm along y (beyond the 6 cm fingers)
    out = simulate([capsule] * 2, [left] * 2, [right] * 2, cfg=tiny, object_hulls=[h, h],
                   object_xy=[[0.0, 0.0], [0.0, 0.08]])
    np.testing.assert_array_equal(out[0], t1.outcomes["Imprint"][2])
    assert not out[1].any()
    # one [2] offset for every candidate: 8 cm the other way
    out = simulate([capsule], [left], [right], cfg=tiny, object_hulls=h, object_xy=(0.0, -0.08))
    assert not out.any()
    with pytest.raises(NotImplementedError):
        simulate([capsule], [left], [right], cfg=tiny, backend="mjx", object_xy=(0.0, 0.01))
    with pytest.raises(ValueError, match="object_xy"):
        simulate([capsule], [left], [right], cfg=tiny, object_hulls=h, object_xy=[[0.0, 0.0, 0.0]])


def test_mass_and_friction_conditions_reach_the_simulator(objects, hulls, tiny):
    """Flat tips slip at mu 0.2, hold a 50 g capsule at mu 1.5 (3 N of friction), drop 500 g."""
    left, right = wsg50_fingers(tiny)
    grasp = {}
    for cond in (E.Condition("nominal"), E.Condition("grippy", friction=1.5),
                 E.Condition("grippy heavy", friction=1.5, object_mass=0.5)):
        cfg = cond.config(tiny)
        assert cfg.sim.finger_friction == (cond.friction or tiny.sim.finger_friction)
        assert cfg.sim.object_mass == (cond.object_mass or tiny.sim.object_mass)
        grasp[cond.name] = simulate([objects[2]], [left], [right], cfg=cfg, object_hulls=hulls[2])[0, 0]
    assert grasp == {"nominal": 0, "grippy": 1, "grippy heavy": 0}


def test_wsg_fmf_fingers_hold_the_capsule_the_flat_pads_drop(objects, hulls, tiny, t1):
    """The paper's WSG50 baseline (Schunk's WSG-FMF fingers): their stepped, grooved face lifts
    the capsule at mu 0.2 and keeps it through the six turned grasps, where flat pads slip."""
    pytest.importorskip("pybullet_data")
    left, right = E.wsg_fmf_designer(tiny)(objects[2:3])
    out = simulate(objects[2:3], left, right, cfg=tiny, object_hulls=hulls[2])[0]
    assert out[0] == 1 and out[5:].all()
    assert not t1.outcomes["WSG50"][2].any()  # the flat pads of the same table


def test_table2_has_the_papers_conditions(objects, hulls, tiny, t1):
    assert E.TABLE2_COLUMNS == ("Original", "m 100g", "m 150g", "mu 0.1", "mu 0.05",
                                "x ±0.5, y ±1 cm", "x ±0.5, y ±2 cm")
    conds = {c.name: c for c in E.TABLE2_CONDITIONS}
    assert conds["m 150g"].config(tiny).sim.object_mass == 0.150
    assert conds["mu 0.05"].config(tiny).sim.finger_friction == 0.05
    assert set(E.PAPER_TABLE2) == {"WSG50", "Imprint", "Fit2Form"}
    assert E.PAPER_TABLE2["Fit2Form"]["x ±0.5, y ±2 cm"] == 83.6

    xy = E.position_offsets(200, conds["x ±0.5, y ±2 cm"], seed=0)
    assert np.all((np.abs(xy[:, 0]) >= 0.001) & (np.abs(xy[:, 0]) <= 0.005))
    assert np.all((np.abs(xy[:, 1]) >= 0.001) & (np.abs(xy[:, 1]) <= 0.020))
    assert (xy < 0).any(axis=0).all() and (xy > 0).any(axis=0).all()
    np.testing.assert_array_equal(xy, E.position_offsets(200, conds["x ±0.5, y ±2 cm"], seed=0))
    assert E.position_offsets(5, conds["mu 0.1"]) is None

    # the capsule with its imprint under every condition (7 evaluations)
    t2 = E.table2({"Imprint": E.imprint_designer(tiny)}, objects[2:], tiny, object_hulls=hulls[2:],
                  progress=False)
    assert t2.columns == E.TABLE2_COLUMNS
    assert t2.outcomes["Imprint"].shape == (len(E.TABLE2_CONDITIONS), 1, 1)  # the grasp only
    # same object, same fingers, same physics: the original column repeats Table 1's grasp
    assert t2.values["Imprint"]["Original"] == 100.0 * t1.outcomes["Imprint"][2, 0]
    md = t2.to_markdown()
    assert "| Imprint | ours |" in md and "| Fit2Form | ours | not run" in md and "88.9" in md


def test_a_killed_table_resumes_with_the_rows_it_had_finished(objects, hulls, tiny, t1, tmp_path,
                                                              monkeypatch):
    """A StepStore keeps each row's outcomes as it ends: after a kill in the second row the same
    table simulates only that row and comes out as if never stopped; a row whose recipe changed
    is simulated again; designs are kept until ``finish``, outcomes after it."""
    from f2f_jax import sim
    from f2f_jax.tables import steps

    designers = {"WSG50": E.wsg50_designer(tiny), "Imprint": E.imprint_designer(tiny)}
    recipes = {"WSG50": "flat pads", "Imprint": "imprint"}

    def store(**changed):
        return steps.StepStore(tmp_path, steps.common_digest(objects, tiny, seed=0), {**recipes, **changed})

    real, calls = sim.evaluate_with_info, []  # table1's call

    def killed_in_the_second_row(*args, **kw):
        calls.append(len(args[0]))
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*args, **kw)

    monkeypatch.setattr(sim, "evaluate_with_info", killed_in_the_second_row)
    kept = {k: steps.StoredDesigner(store(), k, d) for k, d in designers.items()}
    with pytest.raises(KeyboardInterrupt):
        E.table1(kept, objects, tiny, object_hulls=hulls, progress=False, store=store())
    assert len(list((tmp_path / steps.DIRECTORY).glob("design-*.npz"))) == 2  # both rows designed
    calls.clear()
    monkeypatch.setattr(sim, "evaluate_with_info", lambda *a, **kw: (calls.append(len(a[0])), real(*a, **kw))[1])
    again = E.table1(kept, objects, tiny, object_hulls=hulls, progress=False, store=store())
    assert calls == [len(objects)]  # only the row the kill interrupted
    for k in designers:
        np.testing.assert_array_equal(again.outcomes[k], t1.outcomes[k])
        assert again.feasible[k] == t1.feasible[k]
    calls.clear()
    E.table1(designers, objects, tiny, object_hulls=hulls, progress=False, store=store(Imprint="other"))
    assert calls == [len(objects)]  # a changed recipe is another step
    store().finish()
    left = sorted(p.name.split("-")[0] for p in (tmp_path / steps.DIRECTORY).iterdir())
    assert left == ["outcome"] * 3
    # a step file cut short by a kill mid-write is not taken up, it is done again
    store()._path("table1", "WSG50").write_bytes(b"PK\x03")
    calls.clear()
    E.table1(designers, objects, tiny, object_hulls=hulls, progress=False, store=store())
    assert len(calls) == 1
    # a batched backend gets every missing row in one call (here plain MuJoCo stands in for it)
    calls.clear()
    monkeypatch.setattr(sim, "evaluate_with_info", lambda *a, **kw: (calls.append(len(a[0])),
                                                                     real(*a, **{**kw, "backend": "mujoco"}))[1])
    batched = E.table1(designers, objects, tiny, object_hulls=hulls, progress=False, backend="mjx",
                       store=store(WSG50="again", Imprint="again"))
    assert calls == [2 * len(objects)]
    np.testing.assert_array_equal(batched.outcomes["Imprint"], t1.outcomes["Imprint"])


def test_network_designers_post_process_like_training(objects, tiny):
    """Randomly initialised nets: shapes, largest-component post-processing, and RandEmb+FN's
    determinism per object (its optimisation is exercised with 0 steps: a random fitness net is
    flat, so more steps would test nothing but time)."""
    import jax

    from f2f_jax.geometry.fingers import feasibility_report
    from f2f_jax.train.state import init_trained_nets

    models = init_trained_nets(tiny, seed=0)
    lefts, rights = E.nets_designer(models, batch=2)(objects[:2])
    assert lefts.shape == rights.shape == (2, 40, 40, 40) and lefts.dtype == np.float32
    for f in (*lefts, *rights):
        assert feasibility_report(f, tiny)["components"] <= 1

    design = E.random_embedding_designer(models, jax.random.key(3), samples=2, steps=0)
    left, right = design(objects[1:3])
    assert left.shape == (2, 40, 40, 40)
    assert all(feasibility_report(f, tiny)["components"] <= 1 for f in (*left, *right))
    again, _ = E.random_embedding_designer(models, jax.random.key(3), samples=2, steps=0)(objects[1:3])
    np.testing.assert_array_equal(again, left)  # seeded by the key (and the object's index)
    with pytest.raises(ValueError, match="objective"):
        E.random_embedding_designer(models, jax.random.key(0), objective="stability")


def test_cli_refuses_bad_arguments_before_any_work(tmp_path, capsys):
    from f2f_jax.cli import evaluate as cli

    assert cli.main(["--tables", "3"]) == 2
    assert cli.main(["--extra", "no-equals-sign"]) == 2
    assert cli.main(["--extra", f"GS={tmp_path / 'missing'}"]) == 2
    assert cli.main(["--run-dir", str(tmp_path / "missing")]) == 2
    assert cli.main(["--run-dir", str(tmp_path)]) == 2  # a directory without an object set
    assert cli.main(["--fresh", "4"]) == 2  # new objects are added to a run's held-out ones
    assert cli.main(["--checkpoint", str(tmp_path)]) == 2  # whose held-out objects?
    assert cli.main(["--run-dir", str(tmp_path), "--checkpoint", str(tmp_path)]) == 2  # no checkpoints/
    (tmp_path / "objects").mkdir()
    (tmp_path / "objects" / "source.json").write_text('{"source": "builtin", "n": 8, "seed": 3}')
    assert cli.main(["--run-dir", str(tmp_path), "--fresh", "4", "--seed", "3"]) == 2
    err = capsys.readouterr().err
    assert "--tables '3'" in err and "NAME=RUN_DIR" in err and "no object set" in err
    assert "would not be new" in err and "--checkpoint DIR needs --run-dir" in err
    assert "no checkpoints/ directory" in err


def test_the_studies_beside_evaluate_refuse_bad_arguments_before_any_work(tmp_path, capsys):
    """research/generator_candidates.py and research/printed_table.py take evaluate.py's flags
    and their own; a bad one ends the call before any object is made."""
    import importlib

    candidates = importlib.import_module("research.generator_candidates")
    printed = importlib.import_module("research.printed_table")
    for main, flags in ((candidates.main, ["--fitness-ranking", "2"]),  # no --run-dir
                        (candidates.main, ["--run-dir", str(tmp_path)]),  # nothing asked
                        (candidates.main, ["--run-dir", str(tmp_path), "--fitness-ranking", "1"]),
                        (candidates.main, ["--run-dir", str(tmp_path), "--neighbourhood", "0"]),
                        (printed.main, ["--tolerance", "0"]), (printed.main, ["--tolerance", "inf"]),
                        (printed.main, ["--tolerance", "-0.3"]), (printed.main, ["--copies", "0"]),
                        (printed.main, ["--extra", "no-equals-sign"])):
        with pytest.raises(SystemExit) as exc:
            main(flags)
        assert exc.value.code == 2, flags
    err = capsys.readouterr().err
    assert "--run-dir is needed" in err and "K >= 2 candidates to rank" in err
    assert "--tolerance MM needs a finite MM > 0" in err and "--copies J needs J >= 1" in err
    assert "NAME=RUN_DIR" in err


def test_printed_table_scores_every_row_on_the_same_moved_fingers(tmp_path, monkeypatch):
    """research/printed_table.py: Table 1 again with both fingers of every row moved by a
    printer's error, two copies per object; imprints moved by ~0.15 mm still hold what flat pads
    drop, and the same command again simulates nothing (the moved outcomes are kept steps)."""
    import importlib
    import json

    from f2f_jax import sim

    study = importlib.import_module("research.printed_table")
    monkeypatch.setenv("F2F_CACHE_DIR", str(tmp_path / "cache"))
    out = tmp_path / "eval"
    argv = ["--config", "tiny", "--objects", "2", "--tolerance", "0.3", "--copies", "2",
            "--out", str(out), "--quiet"]
    assert study.main(argv) == 0
    results = json.loads((out / "printed.json").read_text())
    printed = results["table1_printed"]
    assert printed["tolerance_mm"] == 0.3 and printed["copies"] == 2
    assert set(printed["values"]) >= {"Flat pads", "Imprint"} and results["objects"] == 2
    assert printed["values"]["Imprint"]["grasp"] > printed["values"]["Flat pads"]["grasp"]
    text = (out / "table1_printed.md").read_text()
    assert "as printed" in text and "2 objects x 2 moved copies" in text
    calls = []
    for name in ("evaluate", "evaluate_with_info"):  # the printed copies' call and table1's
        real = getattr(sim, name)
        monkeypatch.setattr(sim, name, lambda *a, real=real, **kw: (calls.append(len(a[0])),
                                                                    real(*a, **kw))[1])
    assert study.main(argv) == 0 and calls == []
    again = json.loads((out / "printed.json").read_text())["table1_printed"]
    assert again["values"] == printed["values"]


def test_ranking_stats_tell_a_fitness_net_that_ranks_from_one_that_ranks_backwards():
    rng = np.random.default_rng(0)
    sim = (rng.random((6, 5, 11)) < rng.random((6, 5, 1))).astype(np.uint8)  # candidates differ
    value = sim.sum(-1)
    good = np.repeat((value / 11.0)[..., None], 11, -1) * 0.8 + 0.1   # ranks like the simulator
    bad = 1.0 - good                                                    # ranks backwards
    g, b = E.ranking_stats(good, sim), E.ranking_stats(bad, sim)
    assert g["spearman"] == pytest.approx(1.0) and b["spearman"] == pytest.approx(-1.0)
    assert g["trials_picked"] == g["trials_best"] == value.max(1).mean()
    assert b["trials_picked"] == b["trials_worst"] == value.min(1).mean()
    assert g["trials_first"] == value[:, 0].mean() and g["trials_mean"] == value.mean()
    assert g["grasp_auc"] > 0.5 > b["grasp_auc"]
    # objects whose candidates all pass the same trials cannot be ranked: left out, not scored 0
    same = np.repeat(sim[:, :1], 5, 1)
    assert np.isnan(E.ranking_stats(good, same)["spearman"])
    with pytest.raises(ValueError, match="11"):
        E.ranking_stats(good[..., :3], sim)


def test_paired_spearman_sees_one_fitness_net_rank_better_than_another():
    """Two fitness nets on the same candidates: the one that ranks like the simulator beats one
    that ranks at random, with an interval above zero; a net against itself gains exactly 0."""
    rng = np.random.default_rng(2)
    sim = (rng.random((30, 6, 11)) < rng.random((30, 6, 1))).astype(np.uint8)
    good = np.repeat((sim.sum(-1) / 11.0)[..., None], 11, -1)
    noise = rng.random((30, 6, 11))
    rho = E.within_object_spearman(good, sim)
    ranked = ~np.isnan(rho)
    assert ranked.sum() == E.ranking_stats(good, sim)["objects_ranked"] and np.allclose(rho[ranked], 1.0)
    g = E.paired_spearman(good, noise, sim)
    assert g["objects"] == ranked.sum() and g["ci_low"] > 0.5 and g["worse"] == 0
    assert g["ci_low"] <= g["diff"] <= g["ci_high"]
    assert E.paired_spearman(noise, good, sim)["ci_high"] < 0
    same = E.paired_spearman(noise, noise, sim)
    assert same["diff"] == same["ci_low"] == same["ci_high"] == 0 and same["better"] == same["worse"] == 0
    flat = np.repeat(sim[:, :1], 6, 1)  # nothing to rank on any object
    assert E.paired_spearman(good, noise, flat)["objects"] == 0


def test_nearest_own_ranks_by_distance_from_the_generators_own_design():
    """The no-fitness-net baseline: candidates further from candidate 0 (either finger) score
    lower, so it ranks perfectly where straying costs trials and backwards where it pays."""
    rng = np.random.default_rng(3)
    n, k, r = 4, 5, 6
    own = rng.uniform(-1, 1, (n, 1, r, r, r)).astype(np.float32)
    step = np.arange(k, dtype=np.float32)[None, :, None, None, None] * 0.1  # candidate j strays j steps
    lefts = own + step * rng.choice([-1, 1], (n, k, r, r, r))
    rights = np.repeat(own, k, 1)
    rights[:, 2] += 0.05  # the right finger counts too: candidate 2 strays a little further
    score = E.nearest_own_scores(lefts, rights)
    assert score.shape == (n, k) and np.all(score[:, 0] == 0)
    assert np.all(np.diff(score, axis=1) < 0)  # each candidate strays further than the one before
    sim = np.zeros((n, k, 11), np.uint8)
    for j in range(k):
        sim[:, j, : 11 - 2 * j] = 1  # straying costs two trials a step
    prior = np.repeat(score[..., None], 11, -1)
    stats = E.ranking_stats(prior, sim)
    assert stats["spearman"] == pytest.approx(1.0) and stats["trials_picked"] == 11
    assert E.ranking_stats(prior, sim[:, ::-1])["spearman"] == pytest.approx(-1.0)
    with pytest.raises(ValueError, match="R, R, R"):
        E.nearest_own_scores(lefts[0], rights[0])


def test_paired_gain_sees_a_real_gain_and_no_gain_where_there_is_none():
    rng = np.random.default_rng(1)
    before = (rng.random((40, 4, 11)) < 0.5).astype(np.uint8)
    after = before.copy()
    after[:30, :, 5:] = 1  # 30 of 40 objects pass the robustness trials with every candidate
    g = E.paired_gain(after, before)
    t = g["trials_mean"]
    assert t["diff"] > 0 and t["ci_low"] > 0 and t["worse"] == 0 and 0 < t["better"] <= 30
    assert t["after"] - t["before"] == pytest.approx(t["diff"])
    assert g["grasp_mean"]["diff"] == 0 and g["grasp_own"]["better"] == 0  # grasps untouched
    same = E.paired_gain(before, before)["trials_own"]
    assert same["diff"] == same["ci_low"] == same["ci_high"] == 0
    # a generator that got worse: the interval lies below zero
    assert E.paired_gain(before, after)["trials_mean"]["ci_high"] < 0
    s = E.neighbourhood_stats(after)
    assert s["trials_mean"] == t["after"] and s["candidates"] == 4
    with pytest.raises(ValueError, match="same N objects"):
        E.paired_gain(after[:5], before)


def test_fitness_ranking_simulates_every_candidate_of_a_run(objects, hulls, tiny):
    from f2f_jax.train.state import init_trained_nets

    models = init_trained_nets(tiny, seed=0)
    r = E.fitness_ranking(models, objects[:2], tiny, candidates=2, object_hulls=hulls[:2],
                          progress=False)
    assert (r["objects"], r["candidates"]) == (2, 2)
    assert r["trials_worst"] <= min(r["trials_first"], r["trials_picked"], r["trials_mean"])
    assert max(r["trials_first"], r["trials_picked"], r["trials_mean"]) <= r["trials_best"] <= 11
    with pytest.raises(ValueError, match="candidates"):
        E.fitness_ranking(models, objects[:1], tiny, candidates=1)
    # other nets' fitness nets judge the same candidates: the designs come out the same without
    # simulating, and the run's own net judged again is the run's figure to the digit
    lefts, rights, feasible = E.candidate_designs(models, objects[:2], tiny, candidates=2)
    again = E.candidate_designs(models, objects[:2], tiny, candidates=2)
    for a, b in zip((lefts, rights, feasible), again):
        np.testing.assert_array_equal(a, b)
    simulated = np.zeros((2, 2, 11), np.uint8)
    simulated[:, 1] = 1  # the second candidate of each object passes every trial
    other = init_trained_nets(tiny, seed=1)
    rep = E.ranking_report(models, objects[:2], lefts, rights, feasible, simulated,
                           judges={"itself": models, "other": other})
    assert set(rep["judges"]) == {"itself", "other"}
    mine = {k: v for k, v in rep.items() if k not in ("judges", "nearest_own")}
    assert {k: v for k, v in rep["judges"]["itself"].items() if k != "spearman_gain"} == {
        k: v for k, v in mine.items() if k not in ("objects", "candidates", "feasible")}
    g = rep["judges"]["itself"]["spearman_gain"]
    assert g["objects"] == mine["objects_ranked"] > 0 and g["diff"] == 0
    assert rep["judges"]["other"]["spearman_gain"]["objects"] <= 2
    near = rep["nearest_own"]  # the baseline scores the same candidates: it always picks candidate 0
    assert near["trials_picked"] == near["trials_first"] == 0 and near["spearman_gain"]["objects"] <= 2
