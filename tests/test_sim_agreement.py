"""The agreement statistics and perturbed fingers (f2f_jax.bench.agreement), the argument checks of
benchmarks/sim_agreement.py (MJX's agreement runs included: ``--triples dataset --judged-runs``) and of
the other simulator benchmarks (sim_throughput, its batched and peer rows, mjx_contacts, gpu_check)."""

import importlib
import json

import numpy as np
import pytest

from f2f_jax.bench import agreement

agreement_script = importlib.import_module("benchmarks.sim_agreement")

KINDS = ["imprint", "imprint", "wsg50", "cut"]


def _outcomes() -> np.ndarray:
    """Four hand-made [11] outcome vectors: all held, none held, grasp only, grasp + S1 + R-30."""
    out = np.zeros((4, 11), np.uint8)
    out[0] = 1
    out[2, 0] = 1
    out[3, [0, 1, 5]] = 1
    return out


def test_identical_outcomes_agree_fully():
    a = _outcomes()
    s = agreement.agreement_stats(a, a.copy(), KINDS)
    assert s["agreement_per_trial"] == 1.0 and s["agreement_vectors"] == 1.0
    assert set(s["agreement_per_trial_kind"].values()) == {1.0}
    assert s["agreement_per_kind"] == {"imprint": 1.0, "wsg50": 1.0, "cut": 1.0}
    assert s["rate_gap_max"] == {"grasp": 0.0, "trials": 0.0}


def test_one_flipped_trial():
    a = _outcomes()
    b = a.copy()
    b[3, 1] = 0  # the cut pair's S1 fails under the judge
    s = agreement.agreement_stats(a, b, KINDS)
    assert s["agreement_per_trial"] == pytest.approx(1 - 1 / 44)
    assert s["agreement_vectors"] == 0.75
    assert s["agreement_per_trial_kind"]["S1"] == 0.75
    assert s["agreement_per_trial_kind"]["grasp"] == 1.0
    assert s["agreement_per_kind"]["cut"] == pytest.approx(10 / 11)
    assert s["agreement_per_kind"]["imprint"] == 1.0
    # the cut kind passes 3 trials under one, 2 under the other: a gap of 1/11 trials
    assert s["rate_gap_max"] == {"grasp": 0.0, "trials": pytest.approx(100 / 11)}


def test_rates_per_kind():
    a = _outcomes()
    s = agreement.agreement_stats(a, np.zeros_like(a), KINDS, labels=("fast", "reference"))
    assert list(s["rates"]) == ["imprint", "wsg50", "cut", "all"]
    assert s["rates"]["imprint"]["fast"] == dict(grasp=0.5, trials=5.5, S=0.5, R=0.5)
    assert s["rates"]["cut"]["fast"] == dict(grasp=1.0, trials=3.0, S=0.25, R=pytest.approx(1 / 6))
    assert s["rates"]["all"]["fast"]["grasp"] == 0.75
    assert s["rates"]["all"]["fast"]["trials"] == (11 + 0 + 1 + 3) / 4
    assert s["rates"]["all"]["reference"] == dict(grasp=0.0, trials=0.0, S=0.0, R=0.0)
    assert s["rate_gap_max"]["grasp"] == 100.0  # wsg50 and cut: held by one preset only
    assert s["rate_gap_max"]["trials"] == pytest.approx(100 * 5.5 / 11)  # imprint


def test_grasp_confusion_counts():
    a = np.zeros((5, 11), np.uint8)
    b = np.zeros((5, 11), np.uint8)
    a[[0, 1, 2], 0] = 1  # judged holds 0, 1, 2
    b[[1, 2, 3], 0] = 1  # judge holds 1, 2, 3
    s = agreement.agreement_stats(a, b, ["imprint"] * 5)
    assert s["grasp_confusion"] == [[1, 1], [1, 2]]  # [judged][judge]: triple 4 neither, 3 judge only, 0 judged only


def test_inconsistent_inputs_raise():
    a = _outcomes()
    with pytest.raises(ValueError, match="labels"):
        agreement.agreement_stats(a, a, KINDS, labels=("fast", "fast"))
    with pytest.raises(ValueError, match="outcome arrays"):
        agreement.agreement_stats(a, a[:3], KINDS)
    with pytest.raises(ValueError, match="outcome arrays"):
        agreement.agreement_stats(a, a, KINDS[:3])


@pytest.mark.parametrize("argv", [
    ["--n", "0"],
    ["--n-objects", "0"],
    ["--presets", "fast", "bogus"],
    ["--presets", "fast"],
    ["--objects", "/nonexistent/meshes"],
    ["--backends", "warp", "bullet"],
    ["--hull-vertices", "3"],
    ["--object-method", "vhacd"],
    ["--judged-runs", "0"],
    ["--triples", "dataset", "--objects", "/tmp"],
    ["--triples", "dataset", "--kinds", "perturbed"],
])
def test_bad_arguments_exit_2(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        agreement_script.main(argv)
    assert exc.value.code == 2
    assert capsys.readouterr().err  # argparse explains why


def test_empty_objects_directory_is_refused(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        agreement_script.main(["--objects", str(tmp_path)])
    assert exc.value.code == 2
    assert "no mesh files" in capsys.readouterr().err


def test_object_method_changes_only_the_judged_side(tmp_path):
    """``--object-method tiles``: the judged side meshes its objects by tiles (timed per object),
    the judge keeps its preset's coacd pieces; the JSON says so."""
    out = tmp_path / "agree.json"
    assert agreement_script.main(["--n", "2", "--n-objects", "1", "--config", "tiny", "--presets", "fast",
                                  "reference", "--object-method", "tiles", "--threads", "1",
                                  "--json", str(out)]) == 0
    got = json.loads(out.read_text())
    assert got["presets"] == ["fast/tiles", "reference"] and got["object_method"] == "tiles"
    assert got["object_meshing_s"]["max"] > 0  # tiles are made here and timed; coacd would be null
    assert got["n"] == 2 and len(got["rates"]["all"]) == 2  # both sides simulated


def test_the_dataset_triples_run_twice_on_the_judged_side_agree_with_themselves(tmp_path, capsys):
    """``--triples dataset --judged-runs 2``: the pretraining dataset's pairs of builtin objects
    (what MJX's agreement was measured on), the judged side run twice and both runs reported."""
    out = tmp_path / "agree.json"
    assert agreement_script.main(["--n", "2", "--config", "tiny", "--presets", "fast", "fast",
                                  "--triples", "dataset", "--kinds", "imprint", "wsg50",
                                  "--judged-runs", "2", "--threads", "1", "--json", str(out)]) == 0
    got = json.loads(out.read_text())
    assert got["triples"] == "dataset" and got["kinds"] == {"imprint": 1, "wsg50": 1}
    assert len(got["judged_runs"]) == 2 and got["agreement_per_trial"] == 1.0
    assert got["per_trial_both_held"] == [1.0] * 11  # the imprint pair holds in both
    printed = capsys.readouterr().out
    assert "judged run 2" in printed and "differs from run 1" not in printed
    assert "(triples both sides held)" in printed


def test_perturbed_finger_is_feasible_and_new(cfg):
    from f2f_jax.data import builtin_object
    from f2f_jax.dataset import perturbed_finger
    from f2f_jax.geometry import imprint_fingers, is_feasible, mesh_to_tsdf

    left, _ = imprint_fingers(mesh_to_tsdf(builtin_object(0), cfg.geometry), cfg.geometry)
    finger = perturbed_finger(left, np.random.default_rng(0), cfg.geometry)
    assert finger is not None and finger.shape == left.shape and finger.dtype == np.float32
    assert is_feasible(finger, cfg.geometry)
    assert finger.min() >= -1.0 and finger.max() <= 1.0
    flipped = np.count_nonzero((finger < 0) != (left < 0))
    assert 0 < flipped < 0.1 * left.size  # a different finger, still close to the imprint


def test_gpu_check_refuses_a_machine_without_a_gpu_unless_asked(monkeypatch, capsys):
    """benchmarks/gpu_check.py sizes its steps for a GPU: on a CPU it runs only with --cpu."""
    gpu_check = importlib.import_module("benchmarks.gpu_check")
    monkeypatch.setattr(gpu_check, "device_info", lambda: {"jax": ["cpu:cpu"], "warp": ["cpu"]})
    with pytest.raises(SystemExit) as exc:
        gpu_check.main(["--out", "unused.json"])
    assert exc.value.code == 2 and "--cpu" in capsys.readouterr().err
    names = [name for name, _, _ in gpu_check.plan(gpu_check.argparse.Namespace(
        tiny=True, sizes=[2], warp_presets=["fast"], agreement_preset="fast", throughput_s=1, mjx_s=1,
        agreement_s=1, training_s=1))]
    assert names == ["throughput", "agreement", "mjx", "training"]


@pytest.mark.parametrize("argv", [["--backends", "mujoco,bullet"], ["--backends", ","],
                                  ["--batch-sizes", "0"]])
def test_sim_throughput_refuses_unknown_backends_before_any_work(argv, capsys):
    throughput = importlib.import_module("benchmarks.sim_throughput")
    with pytest.raises(SystemExit) as exc:
        throughput.main(argv)
    assert exc.value.code == 2 and "--backends" in capsys.readouterr().err


def test_sim_throughput_times_mjx_grasp_program_alone_apart_from_its_compile():
    """``--grasp-only``: per batch size the grasp program's first call (compile) and a second,
    timed one; the figures follow from the simulator's step counts (a stand-in simulator here:
    MJX itself compiles for minutes on a CPU)."""
    from types import SimpleNamespace

    throughput = importlib.import_module("benchmarks.sim_throughput")

    class Stand_in:
        n_settle, n_close, lift_ctrl, n_hold, compile_seconds = 2, 3, np.zeros(4), 1, 0.0
        seen = set()

        def batch(self, models):
            return SimpleNamespace(fields=len(models), convex=None, planes=None)

        def _call(self, name, size, fields, convex, planes, yaw):
            assert name == "grasp" and fields == size == len(yaw)
            if size not in self.seen:
                self.seen.add(size)
                self.compile_seconds += 5.0
            return (np.arange(size) % 2 == 0,)

    stand_in = Stand_in()
    out = {}
    throughput.grasp_rows(SimpleNamespace(simulator_for=lambda model, cfg: stand_in), ["m0", "m1", "m2"],
                          None, [2, 4], out, "mjx")
    rows = out["mjx_grasp_rows"]
    assert [r["batch"] for r in rows] == [2, 4] and [r["compile_s"] for r in rows] == [5.0, 5.0]
    assert all(r["held"] == 0.5 and r["env_steps_per_s"] == pytest.approx(r["grasps_per_s"] * 10)
               for r in rows)


def test_sim_throughput_times_the_pybullet_peer_alone_on_four_convex_shapes(capsys):
    pytest.importorskip("pybullet")
    throughput = importlib.import_module("benchmarks.sim_throughput")
    assert throughput.main(["--peer-shapes", "convex"]) == 0
    printed = capsys.readouterr().out
    for shape in ("sphere", "box", "cylinder", "cone"):
        assert f"\n{shape}" in printed
    assert "4 evaluations" in printed and "steps/evaluation" in printed
    with pytest.raises(SystemExit):
        throughput.main(["--peer-shapes", "convex", "--peer-repeat", "0"])


def test_mjx_contacts_refuses_pieces_below_a_tetrahedron(capsys):
    contacts = importlib.import_module("benchmarks.mjx_contacts")
    with pytest.raises(SystemExit) as exc:
        contacts.main(["--vertices", "32", "3"])
    assert exc.value.code == 2 and "--vertices" in capsys.readouterr().err


def test_sim_throughput_times_no_finger_meshing_in_any_row(monkeypatch, tmp_path):
    """The simulator meshes each distinct finger once per process: sim_throughput meshes them
    before its first timed row, or that row (fast) pays for what the next (reference) reuses."""
    from f2f_jax import sim
    from f2f_jax.geometry import finger_tiling

    throughput = importlib.import_module("benchmarks.sim_throughput")
    monkeypatch.setattr(finger_tiling, "_memo", type(finger_tiling._memo)())  # none remembered
    meshed = {"n": 0, "inside_rows": 0}
    real_hulls, real_evaluate = finger_tiling.finger_hulls, sim.evaluate_with_info
    rows = {"open": False}

    def counting_hulls(*args, **kwargs):
        meshed["n"] += 1
        meshed["inside_rows"] += rows["open"]
        return real_hulls(*args, **kwargs)

    def timed_row(*args, **kwargs):
        rows["open"] = True
        try:
            return real_evaluate(*args, **kwargs)
        finally:
            rows["open"] = False

    monkeypatch.setattr(finger_tiling, "finger_hulls", counting_hulls)
    monkeypatch.setattr(throughput.sim, "evaluate_with_info", timed_row)
    assert throughput.main(["--config", "tiny", "--n", "1", "--per-core-n", "0", "--no-pybullet",
                            "--meshing-n", "0", "--threads", "1", "--json", str(tmp_path / "t.json")]) == 0
    assert meshed["n"] == 2 and meshed["inside_rows"] == 0  # the pair meshed once, before timing
    result = json.loads((tmp_path / "t.json").read_text())
    assert "object_meshing_s" not in result and result["n"] == 1


def test_gpu_check_summary_lists_every_figure_a_step_produced():
    """The summary gathers what the steps wrote (a step cut short keeps its finished rows) and
    leaves out steps that wrote nothing."""
    gpu_check = importlib.import_module("benchmarks.gpu_check")
    row = dict(batch=2048, compile_s=0.0, run_s=89.0, evals_per_s=23.02, env_steps_per_s=271456.2,
               agreement_with_mujoco=0.9953)
    result = {"throughput": {"cores": 16, "n": 24, "mujoco_evals_per_s": 3.39, "reference_evals_per_s": 4.19,
                             "warp_rows": [row], "warp_fast_rows": [dict(row, evals_per_s=46.1)]},
              "agreement": {"presets": ["fast@warp", "reference"], "n": 256, "agreement_per_trial": 0.9925,
                            "agreement_vectors": 0.953, "rate_gap_max": {"grasp": 1.6, "trials": 0.7}},
              "steps": {"mjx": {"rc": "timeout"}}}
    lines = gpu_check.summary(result)
    text = "\n".join(lines)
    assert "| warp | 2048 | 0.0 | 89.0 | 23.02 | 271,456 | 99.53% |" in lines
    assert "| warp_fast | 2048 |" in text and "46.10" in text
    assert "fast@warp against reference, 256 triples: 99.25% of trials" in text
    assert "reference 4.19" in text and "MJX" not in text and "training" not in text
    assert gpu_check.summary({"steps": {}}) == []
