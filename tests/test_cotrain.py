"""Co-training end to end (tiny config, 16 built-in objects): a run killed after cycle 2 and rerun
ends with the parameters of a run never stopped; the fitness net learns; checkpoints that are
corrupt are skipped; bad command lines fail cleanly without touching a run."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from f2f_jax import config
from f2f_jax.errors import CheckpointError
from f2f_jax.train.checkpoint import Checkpoints, config_from_dict, config_to_dict, load_trained_nets
from f2f_jax.train.cotrain import CoTrainRun
from f2f_jax.train.epochs import NaNLossError, check_finite

ROOT = Path(__file__).resolve().parents[1]
CYCLES = 3

pytestmark = pytest.mark.slow


def _cli(*args: str) -> list[str]:
    return [sys.executable, str(ROOT / "experiments" / "cotrain.py"), "--config", "tiny", "--quiet", *args]


def _log(run_dir: Path) -> list[dict]:
    path = run_dir / "log.jsonl"
    if not path.exists():
        return []
    out = []
    for line in path.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            pass
    return out


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    """One tiny run of 3 cycles, never stopped, in this process."""
    run_dir = tmp_path_factory.mktemp("cotrain") / "whole"
    run = CoTrainRun(run_dir, config.tiny(), config_name="tiny", progress=False)
    summary = run.run(CYCLES)
    return run_dir, summary


def test_killed_and_resumed_run_matches_uninterrupted(uninterrupted, tmp_path):
    whole_dir, _ = uninterrupted
    run_dir = tmp_path / "killed"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen(_cli("--cycles", str(CYCLES), "--run-dir", str(run_dir)), env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    try:
        deadline = time.monotonic() + 600
        while not any(r.get("stage") == "cycle" and r.get("cycle") == 2 for r in _log(run_dir)):
            if proc.poll() is not None:
                pytest.fail(f"run ended before cycle 2: {proc.stderr.read().decode()[-2000:]}")
            if time.monotonic() > deadline:
                pytest.fail("cycle 2 not reached in 10 minutes")
            time.sleep(0.2)
        os.killpg(proc.pid, signal.SIGKILL)  # no chance to clean up: like a power cut
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        proc.stderr.close()
    assert not (run_dir / "summary.json").exists()

    # rerun the same command (in this process: the compiled steps are shared with the whole run)
    summary = CoTrainRun(run_dir, config.tiny(), config_name="tiny", progress=False).run(CYCLES)
    a, b = load_trained_nets(whole_dir), load_trained_nets(run_dir)
    for part in ("generator", "fitness"):
        leaves_a, leaves_b = jax.tree.leaves(getattr(a, part)), jax.tree.leaves(getattr(b, part))
        assert len(leaves_a) == len(leaves_b)
        for x, y in zip(leaves_a, leaves_b):
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=0, atol=1e-6)
    # the rerun resumed (pretraining was not repeated) ...
    log = _log(run_dir)
    assert sum(r.get("stage") == "ae" and r.get("epoch") == 1 for r in log) == 1
    # ... and the simulated designs of every cycle were stored once, not twice
    cycles = [r["cycle"] for r in _log(run_dir) if r.get("stage") == "cycle"]
    assert sorted(set(cycles)) == [1, 2, 3]
    from f2f_jax.dataset.store import GraspStore

    rows = GraspStore(run_dir / "store").read(("cycle",))["cycle"]
    assert [int((rows == c).sum()) for c in (1, 2, 3)] == [config.tiny().train.objects_per_cycle] * 3
    assert summary["success"].keys() == _summary(whole_dir)["success"].keys()


def _summary(run_dir: Path) -> dict:
    return json.loads((run_dir / "summary.json").read_text())


def test_fitness_net_learns_and_run_reports(uninterrupted):
    run_dir, summary = uninterrupted
    log = _log(run_dir)
    bce = [r["heldout_bce"] for r in log if r.get("stage") == "fn" and "heldout_bce" in r
           and r.get("cycle", 0) == 0]
    assert len(bce) == config.tiny().train.fn_epochs + 1
    assert bce[-1] < bce[0], bce  # held-out BCE after pretraining below the untrained net's
    # the imprint baseline grasps the held-out objects, the flat WSG50 tips do not
    assert summary["success"]["imprint"][0] > summary["success"]["wsg50"][0]
    # the paper's WSG50 fingers (WSG-FMF, from the pybullet extra of the dev install) beside them
    fmf = summary["success"]["wsg50-fmf"]
    n_held = summary["held_out_objects"]
    assert len(fmf) == 11  # rates over the held-out objects: multiples of 1 / n
    np.testing.assert_allclose(np.asarray(fmf) * n_held, np.round(np.asarray(fmf) * n_held),
                               atol=6e-5 * n_held)  # summary rates are rounded to 4 places
    assert {"generator, cycle 0", f"generator, cycle {CYCLES}"} <= summary["success"].keys()
    logged = [r["heldout_iou"] for r in log if r.get("stage") == "ae" and "heldout_iou" in r]
    assert summary["ae_heldout_iou"] == pytest.approx(logged[-1], abs=1e-4)  # the figure the run logged
    # the generator after pretraining (the paper's ImpGN) is kept apart from the rolling checkpoints
    imp_gn, final = load_trained_nets(run_dir / "pretrained"), load_trained_nets(run_dir)
    assert "cycle 0)" in imp_gn.source and f"cycle {CYCLES})" in final.source
    assert any(not np.array_equal(a, b) for a, b in zip(jax.tree.leaves(imp_gn.generator["params"]),
                                                      jax.tree.leaves(final.generator["params"])))
    assert (run_dir / "curves.png").stat().st_size > 10_000
    # the nets train once warmup_designs designs were simulated (2 tiny cycles), on all of them
    cyc = {r["cycle"]: r for r in log if r.get("stage") == "cycle"}
    assert cyc[1]["fn_epochs"] == cyc[1]["gn_epochs"] == 0 and cyc[1]["designs_so_far"] == 16
    assert cyc[2]["fn_epochs"] > 0 and cyc[2]["gn_epochs"] > 0 and cyc[3]["designs_so_far"] == 48
    # the generator's pretraining saw the imprints of the extra objects too: 13 training objects
    # and 4 more are 3 batches of 8 a pass (2 without them), and no extra object was simulated
    t = config.tiny().train
    data = next(r for r in log if r.get("stage") == "data")
    assert data["imprint_objects"] == t.imprint_objects == 4 and data["train"] == 13
    assert {r["steps"] for r in log if r.get("stage") == "gn" and r.get("cycle") == 0} == {3 * t.gn_passes}
    from f2f_jax.dataset.store import GraspStore

    stored = {str(n) for n in GraspStore(run_dir / "store").read(("name",))["name"]}
    extra = {str(n) for n in np.load(next((run_dir / "imprint_objects").glob("part-*.npz")))["names"]}
    assert len(extra) == 4 and not extra & stored
    for r in log:
        if "loss" in r:
            assert np.isfinite(r["loss"])


def test_corrupt_checkpoint_is_skipped(uninterrupted, tmp_path):
    run_dir, _ = uninterrupted
    copy = tmp_path / "copy"
    shutil.copytree(run_dir / "checkpoints", copy / "checkpoints")
    ckpt = Checkpoints(copy / "checkpoints")
    newest = ckpt.steps()[-1]
    # flip bytes in every array file of the newest checkpoint's models item
    files = [p for p in (copy / "checkpoints" / str(newest) / "models").rglob("*") if p.is_file()
             and p.stat().st_size > 64 and p.suffix not in (".json",) and "metadata" not in p.name]
    assert files
    for p in files:
        data = bytearray(p.read_bytes())
        for i in range(len(data) // 2, len(data) // 2 + 32):
            data[i] ^= 0xFF
        p.write_bytes(bytes(data))
    with pytest.warns(UserWarning, match="corrupt"):
        models = load_trained_nets(copy)
    # the one before: the checkpoint after cycle CYCLES - 1
    assert f"checkpoints/{newest - 1} " in models.source and f"cycle {CYCLES - 1})" in models.source


def test_missing_checkpoint_names_the_command(tmp_path):
    with pytest.raises(CheckpointError, match="experiments/cotrain.py"):
        load_trained_nets(tmp_path / "nothing")


def test_bad_command_lines_fail_cleanly(uninterrupted, tmp_path, capsys):
    from f2f_jax.cli import cotrain as cli
    assert cli.main(["--cycles", "0", "--run-dir", str(tmp_path / "a")]) == 2
    assert "--cycles" in capsys.readouterr().err
    assert cli.main(["--objects", str(tmp_path / "missing"), "--run-dir", str(tmp_path / "b")]) == 2
    assert "no such directory" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert cli.main(["--objects", str(tmp_path / "empty"), "--run-dir", str(tmp_path / "c")]) == 2
    assert "no mesh files" in capsys.readouterr().err
    assert not any((tmp_path / d).exists() for d in "abc")
    # a run directory made with another config is refused and left as it was
    run_dir, _ = uninterrupted
    before = {p: p.stat().st_mtime_ns for p in run_dir.rglob("*")}
    assert cli.main(["--config", "default", "--cycles", "1", "--run-dir", str(run_dir), "--quiet"]) == 2
    assert "another --run-dir" in capsys.readouterr().err
    tiny = ["--config", "tiny", "--quiet", "--run-dir", str(run_dir)]
    assert cli.main(["--cycles", "1", *tiny]) == 2  # it holds 3
    assert "already holds 3 cycles" in capsys.readouterr().err
    assert cli.main(["--cycles", "3", "--backend", "mjx", *tiny]) == 2
    assert "--backend mujoco" in capsys.readouterr().err
    assert cli.main(["--seed", "-1", "--run-dir", str(tmp_path / "d")]) == 2
    assert not (tmp_path / "d").exists()
    assert {p: p.stat().st_mtime_ns for p in run_dir.rglob("*")} == before


def test_nan_loss_names_the_step():
    with pytest.raises(NaNLossError, match="step 12"):
        check_finite(np.array([0.5, 0.4, np.nan]), "fn", 10)


@pytest.mark.parametrize("name", sorted(config.CONFIGS))
def test_config_round_trips_through_checkpoint_json(name):
    cfg = config.get(name)
    assert config_from_dict(json.loads(json.dumps(config_to_dict(cfg)))) == cfg


def test_ablation_starts_from_another_runs_pretraining(uninterrupted, tmp_path, capsys):
    """--from-pretrained: the cycles of a GS run of one epoch per net and cycle start from the whole
    run's pretrained models and data, without the whole run's designs; other settings are refused."""
    from f2f_jax.cli import cotrain as cli
    src, _ = uninterrupted
    run_dir = tmp_path / "gs"
    args = ["--config", "tiny", "--quiet", "--cycles", "2", "--objectives", "GS",
            "--set", "train.max_epochs=1", "--from-pretrained", str(src), "--run-dir", str(run_dir)]
    assert cli.main(args) == 0, capsys.readouterr().err
    from f2f_jax.dataset.store import GraspStore

    src_rows = GraspStore(src / "store").read(("cycle",))["cycle"]
    rows = GraspStore(run_dir / "store").read(("cycle",))["cycle"]
    assert (rows < 0).sum() == (src_rows < 0).sum() and (rows == 1).sum() == (rows == 2).sum() == 16
    log = _log(run_dir)
    assert sum(r.get("stage") == "ae" and r.get("epoch") == 1 for r in log) == 1  # copied, not rerun
    # cycle 2's 32 designs make 8 half-batches, capped at 4 steps a refit epoch; one epoch per net
    assert [r["steps"] for r in log if r.get("stage") == "fn" and r.get("cycle") == 2] == [4]
    assert config.tiny().train.max_steps_per_epoch == 4
    gs = [r for r in log if r.get("stage") == "gn" and r.get("cycle") == 2]
    assert [r["epoch"] for r in gs] == [1] and len(gs[0]["fitness"]) == 11
    a, b = load_trained_nets(src / "pretrained"), load_trained_nets(run_dir / "pretrained")
    for x, y in zip(jax.tree.leaves(a.generator), jax.tree.leaves(b.generator)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert load_trained_nets(run_dir).objectives == "GS"
    assert _summary(run_dir)["success"]["generator, cycle 0"] == _summary(src)["success"]["generator, cycle 0"]
    # the same command resumes it; a run of other pretraining settings, or a used directory, is refused
    assert cli.main(args) == 0
    assert cli.main([*args[:-1], str(tmp_path / "other"), "--seed", "3"]) == 2
    assert "pretrained with other settings (train.seed)" in capsys.readouterr().err
    assert not (tmp_path / "other").exists()
    (tmp_path / "used").mkdir()
    (tmp_path / "used" / "x").write_text("x")
    assert cli.main([*args[:-1], str(tmp_path / "used")]) == 2
    assert "not empty" in capsys.readouterr().err
    # a run directory started from one run does not go on from another
    elsewhere = [*args[:-3], str(tmp_path / "used"), "--run-dir", str(run_dir)]
    assert cli.main(elsewhere) == 2
    assert "was not started from" in capsys.readouterr().err


def test_evaluate_compares_a_run_with_its_cycle0_generator_paired(uninterrupted, tmp_path, capsys):
    """experiments/evaluate.py, then research/generator_candidates.py --neighbourhood beside it:
    both generators' candidates simulated on the run's held-out objects plus new built-in ones,
    and the paired gain is the difference of the two."""
    import importlib

    from f2f_jax.cli import evaluate as cli

    study = importlib.import_module("research.generator_candidates")
    run_dir, _ = uninterrupted
    out = tmp_path / "eval"
    common = ["--run-dir", str(run_dir), "--extra", f"cycle 0={run_dir / 'pretrained'}", "--objects", "1",
              "--fresh", "1", "--seed", "5", "--quiet", "--out", str(out)]
    args = [*common, "--tables", "1", "--no-randemb", "--design-search", "1"]
    study_args = [*common, "--neighbourhood", "2", "--fitness-ranking", "2"]
    assert cli.main(args) == 0, capsys.readouterr().err
    assert study.main(study_args) == 0, capsys.readouterr().err
    res = json.loads((out / "results.json").read_text())
    cand = json.loads((out / "candidates.json").read_text())
    assert res["objects"] == 2 and res["names"][1].startswith("fresh/") and cand["names"] == res["names"]
    assert cand["fitness_ranking"]["candidates"] == 2 and cand["fitness_ranking"]["objects"] == 2
    judged = cand["fitness_ranking"]["judges"]["cycle 0"]  # the extra's fitness net, same candidates
    assert judged["trials_mean"] == cand["fitness_ranking"]["trials_mean"]
    assert judged["spearman_gain"]["objects"] <= 2
    assert cand["fitness_ranking"]["nearest_own"]["trials_picked"] == cand["fitness_ranking"]["trials_first"]
    # the design pool (the generator's candidate and the imprints, verified) passes, object by
    # object, at least the trials the Imprint row's fingers pass: they are in its pool
    outcomes = res["table1"]["outcomes"]
    pool = [sum(map(int, o)) for o in outcomes["Design pool (1 + imprints, verify)"]]
    assert all(a >= b for a, b in zip(pool, [sum(map(int, o)) for o in outcomes["Imprint"]]))
    assert "Fit2Form + search (1, verify)" in outcomes
    nb = cand["neighbourhood"]
    (first, after), (name, before) = nb["stats"].items()
    assert name == "cycle 0" and after["candidates"] == 2 and after["objects"] == 2
    assert np.asarray(nb["outcomes"][first]).shape == (2, 2, 11)
    gain = nb["gains"]["cycle 0"]["trials_mean"]
    assert gain["diff"] == pytest.approx(after["trials_mean"] - before["trials_mean"])
    assert gain["ci_low"] <= gain["diff"] <= gain["ci_high"]
    printed = capsys.readouterr().out
    assert "paired over objects" in printed and "Design pool: where the verified picks" in printed
    assert "cycle 0's fitness net on the same candidates" in printed
    # the seed table reads what evaluate.py wrote: one run given twice has no spread
    from f2f_jax.cli import seed_table
    assert seed_table.main([str(out), str(out / "results.json"), "--labels", "a,b",
                            "--paired", f"{first} minus cycle 0", "--out", str(tmp_path / "seeds")]) == 0
    assert "minus cycle 0, paired over objects" in (tmp_path / "seeds" / "paired_seeds.md").read_text()
    md = (tmp_path / "seeds" / "table1_seeds.md").read_text()
    imprint = next(line for line in md.splitlines() if line.startswith("| Imprint | ours"))
    assert imprint.count("± 0.0") == 13 and "| Fit2Form + search (1, verify) | " in md
    # the same commands again take up every row's finished outcomes: no row is designed or
    # simulated for the table or the candidates again, and they come out the same
    kept = sorted(p.name.split("-")[0] for p in (out / ".steps").iterdir())
    assert kept and set(kept) == {"outcome"}  # the designs were dropped once results.json was written
    assert cli.main(args) == 0 and study.main(study_args) == 0
    captured = capsys.readouterr()
    assert "took up" in captured.err and "designing:" not in captured.err
    assert "neighbourhood of" not in captured.err and "fitness ranking:" not in captured.err
    again = json.loads((out / "results.json").read_text())
    assert again["table1"] == res["table1"]
    again = json.loads((out / "candidates.json").read_text())
    for part in ("neighbourhood", "fitness_ranking"):
        assert again[part] == cand[part], part
    assert "Design pool: where the verified picks" in captured.out
    # --checkpoint RUN/pretrained: the pretrained nets (ImpGN) on the same held-out objects
    assert cli.main(["--run-dir", str(run_dir), "--checkpoint", str(run_dir / "pretrained"), "--objects", "1",
                     "--tables", "1", "--no-randemb", "--quiet", "--out", str(tmp_path / "pre")]) == 0
    pre = json.loads((tmp_path / "pre" / "results.json").read_text())["table1"]["outcomes"]
    assert "ImpGN" in pre and "Fit2Form" not in pre


def test_simulator_teaches_the_generator_and_a_killed_cycle_loses_nothing(uninterrupted, tmp_path):
    """train.teacher=simulator from the whole run's pretraining: cycle 1 killed while its second
    chunk of teacher designs simulates, then rerun, keeps the first chunk and stores every chunk
    once; the generator's loss to its targets (each object's best-simulated pair) falls; the imprint control simulates nothing and takes the same steps."""
    import dataclasses

    from f2f_jax.dataset.store import GraspStore
    from f2f_jax.train.run_data import read_rows
    from f2f_jax.train.teacher import IMPRINT, best_rows, teacher_set, teacher_targets

    src, _ = uninterrupted
    tiny = config.tiny()
    cfg = tiny.replace(train=dataclasses.replace(
        tiny.train, teacher="simulator", teacher_objects=1, teacher_candidates=2, teacher_chunk=8,
        teacher_epochs=2))

    def fork(name, c=cfg):
        return CoTrainRun.from_pretrained(tmp_path / name, src, c, config_name="tiny", progress=False)

    run = fork("teach")
    real, calls = run.simulate, []

    def simulate_once(*args):
        if calls:
            raise KeyboardInterrupt  # a kill while the second chunk simulates
        calls.append(1)
        return real(*args)

    run.simulate = simulate_once
    with pytest.raises(KeyboardInterrupt):
        run.run(2)
    store = GraspStore(tmp_path / "teach" / "store")
    assert "teacher-1-0" in store.done_keys() and "teacher-1-1" not in store.done_keys()
    first = store.read(("outcome", "kind", "name"), start=len(store) - store.chunks()[-1].rows)

    fork("teach").run(2)
    store = GraspStore(tmp_path / "teach" / "store")
    keys = [k for c in store.chunks() for k in c.keys if k.startswith("teacher")]
    assert keys == ["teacher-1-0", "teacher-1-1", "teacher-2-0", "teacher-2-1"]  # 14 objects, 8 a chunk
    rows = store.read(("cycle", "kind", "name", "outcome"))
    c1, c2 = rows["cycle"] == 1, rows["cycle"] == 2
    for k in first:  # the chunk simulated before the kill is kept as it was
        np.testing.assert_array_equal(first[k], rows[k][c1][:len(first[k])])
    names = sorted(set(rows["name"][c1]))
    assert len(names) == 13 + 1  # the tiny run's 13 training objects and one more built-in object
    assert not set(names) & set(json.loads((src / "objects" / "split.json").read_text())["test"])
    assert (rows["kind"][c1] == IMPRINT).sum() == 14 and not (rows["kind"][c2] == IMPRINT).any()
    assert (rows["kind"][c2] == "generator").sum() == 14 and c2.sum() == 14 * 2

    # the targets are each object's best-simulated pair; the generator came closer to them
    again = fork("teach")
    st = again.start()
    ts = teacher_set(again, st)
    shared = read_rows(st.data.store, lambda cyc, k: 1 <= cyc <= 2, objects=(ts.objects, ts.names))
    left, right, stats = teacher_targets(st, ts, shared)
    best, passed, imprint = best_rows(shared, ts.names)
    assert (passed >= imprint).all() and stats["target_trials"] >= stats["imprint_trials"]
    summaries = [r for r in _log(tmp_path / "teach") if r.get("stage") == "cycle"]
    assert [s["cycle"] for s in summaries] == [1, 2] and summaries[-1]["improved_objects"] == stats["improved_objects"]
    # the generator's regression onto them (its pretraining loss, in training mode) falls
    gn = [r["loss"] for r in _log(tmp_path / "teach") if r.get("stage") == "gn" and r.get("cycle", 0) >= 1]
    assert len(gn) == 4 and gn[-1] < gn[0]

    # the control: the same steps on the imprints, nothing simulated in its cycles
    fork("control", cfg.replace(train=dataclasses.replace(cfg.train, teacher="imprint"))).run(2)
    assert not (GraspStore(tmp_path / "control" / "store").read(("cycle",))["cycle"] >= 1).any()
    steps = [[r["steps"] for r in _log(tmp_path / d) if r.get("stage") == "gn" and r.get("cycle", 0) >= 1]
             for d in ("teach", "control")]
    assert steps[0] == steps[1] and len(steps[0]) == 4
