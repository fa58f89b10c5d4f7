"""Tables over several runs (f2f_jax.tables.seeds, experiments/seed_table.py): mean ± sd per
cell, rows matched by name, each row against a reference run by run."""

import json

import numpy as np
import pytest

from f2f_jax.cli import seed_table as cli
from f2f_jax.tables import PAPER_TABLE2, ROBUSTNESS, STABILITY, TABLE1_COLUMNS, TABLE2_COLUMNS
from f2f_jax.tables.seeds import SR_MEAN, combine_results, fresh_source, load_results


def _row(level: float, step: float = 0.0) -> dict:
    return {c: level + step * i for i, c in enumerate(TABLE1_COLUMNS)}


def _results(rows: dict, objects: int = 13, table2: dict | None = None) -> dict:
    out = {"objects": objects, "table1": {"values": rows, "feasible": {k: 1.0 for k in rows}}}
    if table2 is not None:
        out["table2"] = {"values": table2}
    return out


def _write(directory, results: dict):
    directory.mkdir(parents=True)
    (directory / "results.json").write_text(json.dumps(results))
    return directory


def test_mean_sd_and_rows_missing_from_some_runs():
    runs = [_results({"Imprint": _row(90), "Fit2Form": _row(70)}),
            _results({"Imprint": _row(80), "Fit2Form GS": _row(60)}),
            _results({"Imprint": _row(85), "Fit2Form": _row(76)}, objects=61)]
    t = combine_results(runs, ["s0", "s1", "s2"])["table1"]
    assert t.objects == [13, 13, 61]
    s = t.stats("Imprint", "grasp")
    assert s["mean"] == pytest.approx(85.0) and s["sd"] == pytest.approx(5.0)  # sample sd of 90, 80, 85
    assert (s["min"], s["max"], s["runs"]) == (80.0, 90.0, 3)
    assert t.stats("Fit2Form", "R avg")["runs"] == 2 and t.stats("Fit2Form GS", "S1")["sd"] == 0.0
    assert t.rows()[:3] == ["Imprint", "Fit2Form GS", "Fit2Form"]  # the paper's order first
    md = t.to_markdown()
    assert "| Imprint | ours | 85.0 ± 5.0 |" in md and "| Fit2Form GS | ours | 60.0 ± 0.0 |" in md
    assert "s2 (61 objects)" in md


def test_versus_pairs_runs_and_counts_the_ones_at_least_as_good():
    sr = STABILITY + ROBUSTNESS
    imprint = [_row(90), _row(80)]
    ours = [dict(_row(70), **{c: 92.0 for c in sr}), dict(_row(85), **{c: 70.0 for c in sr})]
    t = combine_results([_results({"Imprint": a, "Fit2Form": b}) for a, b in zip(imprint, ours)])["table1"]
    g = t.versus("Fit2Form", "Imprint", "grasp")
    assert g["mean"] == pytest.approx(-7.5) and g["at_least"] == 1 and g["runs"] == 2
    d = t.versus("Fit2Form", "Imprint", SR_MEAN)  # 92 - 90 in run 1, 70 - 80 in run 2
    assert d["mean"] == pytest.approx(-4.0) and d["sd"] == pytest.approx(np.std([2.0, -10.0], ddof=1))
    assert d["at_least"] == 1
    md = t.to_markdown(versus="Imprint")
    assert "| Fit2Form | -7.5 ± " in md and "(1/2)" in md
    with pytest.raises(KeyError, match="no row 'WSG50'"):
        t.to_markdown(versus="WSG50")


def test_table2_and_runs_without_it():
    t2 = {"Imprint": {c: 50.0 + i for i, c in enumerate(TABLE2_COLUMNS)}}
    tables = combine_results([_results({"Imprint": _row(90)}, table2=t2), _results({"Imprint": _row(80)})],
                             ["a", "b"])
    assert tables["table1"].labels == ["a", "b"] and tables["table2"].labels == ["a"]
    md = tables["table2"].to_markdown()
    paper = PAPER_TABLE2["Imprint"][TABLE2_COLUMNS[0]]
    assert f"| | paper | {paper:.1f} |" in md and "| Imprint | ours | 50.0 ± 0.0 | 51.0 ± 0.0 |" in md


def test_bad_inputs_are_refused_clearly(tmp_path):
    with pytest.raises(ValueError, match="no runs"):
        combine_results([])
    with pytest.raises(ValueError, match="2 labels for 1 runs"):
        combine_results([_results({"Imprint": _row(1)})], ["a", "b"])
    broken = _row(1)
    del broken["S3"]
    with pytest.raises(ValueError, match=r"row 'Imprint' lacks columns \['S3'\]"):
        combine_results([_results({"Imprint": broken})])
    with pytest.raises(FileNotFoundError, match="run experiments/evaluate.py"):
        load_results(tmp_path)
    (tmp_path / "results.json").write_text("{not json")
    with pytest.raises(ValueError, match="not a results.json"):
        load_results(tmp_path)
    (tmp_path / "results.json").write_text(json.dumps({"objects": 3}))
    with pytest.raises(ValueError, match="neither table1 nor table2"):
        load_results(tmp_path / "results.json")


def test_cli_writes_the_tables_and_labels_runs_by_their_directories(tmp_path, capsys):
    a = _write(tmp_path / "s0" / "eval", _results({"Imprint": _row(90), "Fit2Form": _row(70)}))
    b = _write(tmp_path / "s1" / "eval", _results({"Imprint": _row(80), "Fit2Form": _row(74)}))
    out = tmp_path / "seeds"
    assert cli.main([str(a), str(b), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "Runs: s0 (13 objects), s1 (13 objects)" in printed and "Each row minus Imprint" in printed
    assert {p.name for p in out.iterdir()} == {"table1_seeds.md", "table1_seeds.csv", "table1_seeds.png"}
    lines = (out / "table1_seeds.csv").read_text().splitlines()
    assert lines[0].startswith("table,designer,statistic,grasp,S1")
    assert "table1,Fit2Form,mean,72.00," in "\n".join(lines)
    assert any(line.startswith("table1,Fit2Form,s1,74.00,") for line in lines)
    # wrong label count, unknown reference row, a missing run: clear errors, nothing written
    with pytest.raises(SystemExit):
        cli.main([str(a), str(b), "--labels", "x"])
    assert "--labels gives 1 labels for 2 results" in capsys.readouterr().err
    assert cli.main([str(a), "--versus", "WSG50"]) == 1
    assert "no row 'WSG50'" in capsys.readouterr().err
    assert cli.main([str(a), str(tmp_path / "missing")]) == 1
    assert "no results.json" in capsys.readouterr().err
    assert cli.main([str(a), "--versus", ""]) == 0 and "Each row minus" not in capsys.readouterr().out


def test_held_out_and_fresh_objects_are_recounted_from_the_outcomes(tmp_path, capsys):
    from f2f_jax.tables import table1_values

    rng = np.random.default_rng(0)
    names = ["builtin/0001_mug", "builtin/0002_cup", "fresh/builtin/0000_tube", "fresh/builtin/0001_box",
             "fresh/builtin/0002_nut"]
    runs = []
    for _ in range(2):
        out = {row: rng.integers(0, 2, (5, 11)).astype(np.uint8) for row in ("Imprint", "Fit2Form")}
        runs.append({"objects": 5, "names": names,
                     "table1": {"values": {k: table1_values(v) for k, v in out.items()},
                                "outcomes": {k: ["".join(map(str, o)) for o in v] for k, v in out.items()}},
                     "_raw": out})
    held = combine_results(runs, ["a", "b"], objects="held-out")["table1"]
    fresh = combine_results(runs, ["a", "b"], objects="fresh")["table1"]
    assert held.objects == [2, 2] and fresh.objects == [3, 3] and fresh.subset == "fresh"
    for i, r in enumerate(runs):
        assert held.values["Fit2Form"][i] == pytest.approx(table1_values(r["_raw"]["Fit2Form"][:2]))
        assert fresh.values["Imprint"][i] == pytest.approx(table1_values(r["_raw"]["Imprint"][2:]))
    # the object-weighted mean of the two subsets is the whole table
    whole = combine_results(runs, ["a", "b"])["table1"]
    both = (2 * held.per_run("Imprint", "R avg") + 3 * fresh.per_run("Imprint", "R avg")) / 5
    np.testing.assert_allclose(both, whole.per_run("Imprint", "R avg"))
    assert "fresh objects only" in fresh.to_markdown()
    # a run without fresh objects drops out of the fresh table; runs without outcomes are refused
    only_held = dict(runs[0], names=names[:2], objects=2,
                     table1=dict(runs[0]["table1"], outcomes={k: v[:2] for k, v in
                                                              runs[0]["table1"]["outcomes"].items()}))
    assert combine_results([only_held, runs[1]], ["a", "b"], objects="fresh")["table1"].labels == ["b"]
    assert combine_results([only_held], objects="fresh") == {}
    with pytest.raises(ValueError, match="keeps no per-object table1 outcomes"):
        combine_results([_results({"Imprint": _row(1)})], objects="fresh")
    with pytest.raises(ValueError, match="objects must be one of"):
        combine_results(runs, objects="train")
    a = _write(tmp_path / "a", {k: v for k, v in only_held.items() if k != "_raw"})
    assert cli.main([str(a), "--objects", "fresh"]) == 1
    assert "none of the runs evaluated fresh objects" in capsys.readouterr().err
    assert cli.main([str(a), "--objects", "held-out", "--out", str(tmp_path / "o")]) == 0
    assert (tmp_path / "o" / "table1_seeds_held-out.md").exists()


def test_rows_evaluated_later_merge_into_their_run_by_label():
    names = ["builtin/0001_mug", "fresh/builtin/0000_tube"]
    imprint, f2f, gs = (np.array(o, np.uint8) for o in ([[1] * 11, [1] * 6 + [0] * 5],
                                                          [[1] * 11, [1] * 11], [[0] * 11, [1] * 11]))

    def run(**rows):
        from f2f_jax.tables import table1_values
        return {"objects": 2, "names": names,
                "table1": {"values": {k: table1_values(v) for k, v in rows.items()},
                           "outcomes": {k: ["".join(map(str, o)) for o in v] for k, v in rows.items()}}}

    first, later = run(Imprint=imprint, Fit2Form=f2f), run(Imprint=imprint, **{"Fit2Form GS": gs})
    t = combine_results([first, run(Imprint=imprint, Fit2Form=gs), later], ["s0", "s1", "s0"])["table1"]
    assert t.labels == ["s0", "s1"] and t.objects == [2, 2]
    assert t.stats("Fit2Form GS", "grasp") == pytest.approx({"mean": 50.0, "sd": 0.0, "min": 50.0,
                                                             "max": 50.0, "runs": 1})
    assert t.per_run("Fit2Form", "grasp").tolist() == [100.0, 50.0]
    assert first["table1"]["values"].keys() == {"Imprint", "Fit2Form"}  # the inputs are left alone
    fresh = combine_results([first, later], ["s0", "s0"], objects="fresh")["table1"]
    assert fresh.per_run("Fit2Form GS", "S1").tolist() == [100.0]
    # a shared row with other outcomes, or other objects, cannot belong to the same run
    with pytest.raises(ValueError, match="row 'Imprint' differs"):
        combine_results([first, run(Imprint=gs)], ["s0", "s0"])
    with pytest.raises(ValueError, match="evaluated different objects"):
        combine_results([first, dict(later, names=names[::-1])], ["s0", "s0"])


def _neighbourhood_run(after: np.ndarray, before: np.ndarray, names: list[str], fresh_seed: int = 7,
                       after_name: str = "Fit2Form", before_name: str = "control") -> dict:
    n_fresh = sum(n.startswith("fresh/") for n in names)
    out = _results({"Imprint": _row(90)}, objects=len(names))
    out.update(names=names, source=f"held-out objects of runs/x + {fresh_source(n_fresh, fresh_seed)}",
               neighbourhood={"outcomes": {after_name: after.tolist(), before_name: before.tolist()}})
    return out


def _outcomes(trials: np.ndarray, k: int = 2) -> np.ndarray:
    """[N, k, 11] outcomes whose every candidate passes the first ``trials[i]`` trials."""
    return (np.arange(11)[None, None, :] < np.asarray(trials)[:, None, None]).repeat(k, 1).astype(float)


def test_paired_over_runs_pools_seeds_and_resamples_shared_fresh_objects_as_one():
    from f2f_jax.tables.seeds import paired_markdown, paired_over_runs

    names = ["builtin/0000_mug", "builtin/0001_box", "fresh/builtin/0000_tray", "fresh/builtin/0001_cup"]
    runs = [_neighbourhood_run(_outcomes([9, 8, 10, 7]), _outcomes([8, 7, 9, 6]), names),
            _neighbourhood_run(_outcomes([6, 8, 10, 7]), _outcomes([5, 7, 9, 6]), names),
            _neighbourhood_run(_outcomes([6, 8, 10, 7]), _outcomes([5, 7, 9, 6]), names, fresh_seed=8)]
    g = paired_over_runs(runs, ["s0", "s1", "s2"], "Fit2Form", "control")
    p = g["pooled"]["trials_own"]
    assert (p["diff"], p["ci_low"], p["ci_high"]) == (1.0, 1.0, 1.0) and p["better"] == 12
    # held-out names repeat across seeds but are other shapes; the fresh ones of seed 7 are shared
    assert p["objects"] == 12 and p["clusters"] == 3 * 2 + 2 + 2  # 3 x held-out, seed 7, seed 8
    assert g["objects"] == {"s0": 4, "s1": 4, "s2": 4} and g["skipped"] == []
    assert g["runs"]["s1"]["trials_mean"]["diff"] == 1.0
    fresh = paired_over_runs(runs, ["s0", "s1", "s2"], "Fit2Form", "control", objects="fresh")
    assert fresh["pooled"]["trials_own"]["objects"] == 6 and fresh["pooled"]["trials_own"]["clusters"] == 4
    md = paired_markdown("Fit2Form", "control", g)
    assert "| pooled | 12 (10 distinct) | +1.00 [+1.00, +1.00] (12 / 0) |" in md

    # a run without one of the generators is named, and none at all is an error
    other = _neighbourhood_run(_outcomes([9, 8, 10, 7]), _outcomes([8, 7, 9, 6]), names, before_name="ImpGN")
    assert paired_over_runs(runs[:1] + [other], ["s0", "s9"], "Fit2Form", "control")["skipped"] == ["s9"]
    with pytest.raises(ValueError, match="no run holds neighbourhood outcomes of both"):
        paired_over_runs([other], ["s9"], "Fit2Form", "control")


def test_pooled_interval_does_not_shrink_when_seeds_repeat_the_same_objects():
    """Three runs on the same 40 fresh objects, with the same differences: the pooled interval
    is as wide as one run's (resampling the 120 pairs one by one would narrow it by ~sqrt(3))."""
    from f2f_jax.tables.seeds import paired_over_runs
    from f2f_jax.tables.stats import paired_gain

    rng = np.random.default_rng(3)
    names = [f"fresh/builtin/{i:04d}_box" for i in range(40)]
    before = rng.integers(3, 9, 40)
    after = before + rng.integers(-2, 3, 40)
    run = _neighbourhood_run(_outcomes(after), _outcomes(before), names)
    one = paired_gain(_outcomes(after), _outcomes(before))["trials_own"]
    pooled = paired_over_runs([run] * 3, ["a", "b", "c"], "Fit2Form", "control")["pooled"]["trials_own"]
    width = lambda g: g["ci_high"] - g["ci_low"]  # noqa: E731
    assert pooled["clusters"] == 40 and pooled["diff"] == pytest.approx(one["diff"])
    assert width(pooled) == pytest.approx(width(one), rel=0.15)


def test_seed_table_paired_flag(tmp_path, capsys):
    names = ["builtin/0000_mug", "fresh/builtin/0000_tray"]
    dirs = [_write(tmp_path / f"s{i}", _neighbourhood_run(_outcomes([9, 8]), _outcomes([8, 8]), names))
            for i in range(2)]
    out = tmp_path / "seeds"
    assert cli.main([str(d) for d in dirs] + ["--paired", "Fit2Form minus control", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "Fit2Form minus control, paired over objects" in printed and "| pooled | 4 (3 distinct) |" in printed
    assert (out / "paired_seeds.md").read_text().startswith("Fit2Form minus control")
    assert cli.main([str(d) for d in dirs] + ["--paired", "Fit2Form minus ImpGN"]) == 1
    assert "no run holds neighbourhood outcomes" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.main([str(dirs[0]), "--paired", "Fit2Form - control"])
