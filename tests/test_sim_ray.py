"""sim.evaluate(executor="ray") on a local 2-CPU Ray cluster: the threaded run's outcomes bit
for bit, through a killed worker, a candidate that kills every worker it meets, and a killed
make_dataset driver; and a clear error without the extra."""

import os
import signal
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import trimesh

from f2f_jax import sim
from f2f_jax.dataset.store import GraspStore
from f2f_jax.errors import MissingExtraError
from f2f_jax.geometry import imprint_fingers, mesh_to_tsdf, wsg50_fingers
from f2f_jax.geometry.pieces import object_pieces
from f2f_jax.sim import ray_executor

ROOT = Path(__file__).resolve().parents[1]


def _meshes():
    box = trimesh.creation.box((0.04, 0.03, 0.05))
    box.apply_translation([0, 0, 0.025])
    cyl = trimesh.creation.cylinder(0.018, 0.05)
    cyl.apply_translation([0, 0, 0.025])
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.022)
    ball.apply_translation([0, 0, 0.022])
    cone = trimesh.creation.cone(0.025, 0.05)
    return {"box": box, "cylinder": cyl, "ball": ball, "cone": cone}


@pytest.fixture(scope="module")
def triples(tiny_cfg):
    """Convex objects (one hull each: no coacd) with their imprint and WSG50 pairs, plus an
    infeasible (empty) left finger: 9 candidates, the caged imprint grasps (cylinder, ball) held."""
    g = tiny_cfg.geometry
    objs, lefts, rights = [], [], []
    for mesh in _meshes().values():
        obj = mesh_to_tsdf(mesh, g)
        for left, right in (imprint_fingers(obj, g), wsg50_fingers(g)):
            objs.append(obj), lefts.append(left), rights.append(right)
    empty = np.ones_like(lefts[0])
    objs.append(objs[0]), lefts.append(empty), rights.append(rights[0])
    return np.stack(objs), np.stack(lefts), np.stack(rights)


@pytest.fixture(scope="module")
def threaded(triples, tiny_cfg, tmp_path_factory):
    cache = tmp_path_factory.mktemp("hulls")
    out, info = sim.evaluate_with_info(*triples, cfg=tiny_cfg, threads=2, cache_dir=cache)
    # the imprints cage the cylinder and the ball; the box and the cone are held or not by how
    # they slide (at mu 0.2 two flat faces give 0.4 N of friction for 0.49 N of weight)
    assert out[2, 0] == 1 and out[4, 0] == 1, "imprint fingers should hold the cylinder and ball"
    return out, info


@pytest.fixture(scope="module")
def ray_cluster():
    ray = pytest.importorskip("ray")
    with warnings.catch_warnings():  # JAX's fork warning: Ray's subprocesses exec at once
        warnings.filterwarnings("ignore", message="os.fork", category=RuntimeWarning)
        # a fresh local cluster, even where `ray start` left one running on this machine
        ray.init(address="local", num_cpus=2, logging_level="WARNING", include_dashboard=False)
    yield ray
    ray.shutdown()


def test_missing_extra_names_the_install_command(triples, tiny_cfg, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    with pytest.raises(MissingExtraError, match=r'pip install -e "\.\[ray\]"'):
        sim.evaluate(*[t[:1] for t in triples], cfg=tiny_cfg, executor="ray")
    with pytest.raises(ValueError, match="unknown executor"):
        sim.evaluate(*[t[:1] for t in triples], cfg=tiny_cfg, executor="dask")
    with pytest.raises(ValueError, match="mujoco"):
        sim.evaluate(*[t[:1] for t in triples], cfg=tiny_cfg, executor="ray", backend="mjx")
    with pytest.raises(ValueError, match="task_size"):  # said before Ray is needed
        ray_executor.run(triples[0][:1], triples[1][:1], triples[2][:1], [0], tiny_cfg,
                         task_size=0)


@pytest.mark.slow
def test_ray_gives_the_threaded_outcomes(ray_cluster, triples, threaded, tiny_cfg, tmp_path):
    want, want_info = threaded
    # uneven tasks (4 + 4 + 1 candidates), object pieces made by Ray tasks into a fresh cache
    out, info = sim.evaluate_with_info(*triples, cfg=tiny_cfg, executor="ray", task_size=4,
                                       cache_dir=tmp_path)
    np.testing.assert_array_equal(out, want)
    np.testing.assert_array_equal(info.steps, want_info.steps)
    assert info.infeasible[-1] and not info.failed.any()
    assert len(list(tmp_path.glob("*.npz"))) == 4  # the driver cached each object's pieces once
    # shifted objects, given pieces: still the threaded run's outcomes
    xy = np.linspace(-0.004, 0.004, len(want) * 2).reshape(-1, 2)
    kw = dict(cfg=tiny_cfg, object_xy=xy, cache_dir=tmp_path)
    shifted = sim.evaluate(*triples, executor="ray", **kw)
    np.testing.assert_array_equal(shifted, sim.evaluate(*triples, threads=2, **kw))


def _busy_workers() -> list[int]:
    """PIDs of processes running a trials task now (Ray titles a busy worker after its task)."""
    pids = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                if b"ray::trials_task" in Path(f"/proc/{entry}/cmdline").read_bytes():
                    pids.append(int(entry))
            except OSError:
                pass
    return pids


@pytest.mark.slow
def test_killed_worker_is_retried_and_outcomes_complete(ray_cluster, triples, threaded, tiny_cfg,
                                                       tmp_path):
    result = {}

    def run():
        result["out"] = sim.evaluate_with_info(*triples, cfg=tiny_cfg, executor="ray", task_size=1,
                                               cache_dir=tmp_path)

    thread = threading.Thread(target=run)
    thread.start()
    killed = None
    deadline = time.monotonic() + 120
    while killed is None and thread.is_alive() and time.monotonic() < deadline:
        busy = _busy_workers()
        if busy:
            os.kill(busy[0], signal.SIGKILL)
            killed = busy[0]
        time.sleep(0.02)
    thread.join(timeout=300)
    assert killed is not None, "no busy worker was seen to kill"
    out, info = result["out"]
    np.testing.assert_array_equal(out, threaded[0])
    assert not info.failed.any()


class _KillsItsWorker:
    """Pieces whose unpickling ends the process that loads them: a candidate that crashes every
    worker it is sent to (as a segfault on a bad object would)."""

    def __reduce__(self):
        return os._exit, (3,)


@pytest.mark.slow
def test_candidate_that_crashes_workers_fails_alone(ray_cluster, triples, threaded, tiny_cfg,
                                                    monkeypatch):
    monkeypatch.setattr(ray_executor, "TASK_RETRIES", 1)
    objs, lefts, rights = (t[:4] for t in triples)
    hulls = [object_pieces(o, tiny_cfg, cache_dir=False) for o in objs]
    hulls[1] = _KillsItsWorker()
    out, info = sim.evaluate_with_info(objs, lefts, rights, cfg=tiny_cfg, executor="ray", task_size=4,
                                       object_hulls=hulls)
    assert info.failed.tolist() == [False, True, False, False]
    assert "ray task failed" in info.errors[1]
    np.testing.assert_array_equal(out[[0, 2, 3]], threaded[0][[0, 2, 3]])
    assert not out[1].any()


@pytest.mark.slow
def test_killed_make_dataset_driver_loses_and_duplicates_nothing(ray_cluster, tmp_path):
    meshes = tmp_path / "meshes"
    meshes.mkdir()
    for name, mesh in _meshes().items():
        mesh.export(meshes / f"{name}.obj")
    address = ray_cluster.get_runtime_context().gcs_address
    cmd = [sys.executable, str(ROOT / "experiments" / "make_dataset.py"), "--objects", str(meshes),
           "--n", "4", "--config", "tiny", "--cut-pairs", "0", "--batch", "1",
           "--executor", "ray", "--ray-address", address, "--out", str(tmp_path / "run")]
    env = dict(os.environ, F2F_CACHE_DIR=str(tmp_path / "cache"))
    store_dir = tmp_path / "run" / "store"
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and proc.poll() is None:
        if store_dir.exists() and len(GraspStore(store_dir).done_keys()) >= 1:
            break
        time.sleep(0.05)
    assert proc.poll() is None, f"make_dataset ended before it was killed: {proc.stderr.read()[-2000:]}"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    proc.stderr.close()
    first = GraspStore(store_dir).done_keys()
    assert 1 <= len(first) < 4
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    data = GraspStore(store_dir).read(("kind", "outcome"))
    names = GraspStore(store_dir).read(("name",))["name"]
    want = {f"meshes/{n}" for n in _meshes()}  # a mesh directory's objects: dir/stem
    assert GraspStore(store_dir).done_keys() == want
    assert sorted(zip(names.tolist(), data["kind"].tolist())) == sorted(
        (n, k) for n in want for k in ("imprint", "wsg50"))


@pytest.mark.slow
def test_paper_table_on_ray_is_the_threaded_one(ray_cluster, triples, threaded, tiny_cfg):
    from f2f_jax import tables as E

    objs = triples[0][0:8:2]
    hulls = [object_pieces(o, tiny_cfg, cache_dir=False) for o in objs]
    designers = {"Imprint": E.imprint_designer(tiny_cfg), "WSG50": E.wsg50_designer(tiny_cfg)}
    t1 = E.table1(designers, objs, tiny_cfg, object_hulls=hulls, progress=False, executor="ray")
    np.testing.assert_array_equal(t1.outcomes["Imprint"], threaded[0][0:8:2])
    np.testing.assert_array_equal(t1.outcomes["WSG50"], threaded[0][1:8:2])


def test_command_lines_refuse_ray_misuse_before_any_work(tmp_path, capsys, monkeypatch):
    from f2f_jax.cli import cotrain, evaluate, make_dataset
    run = ["--run-dir", str(tmp_path / "run")]
    assert cotrain.main([*run, "--executor", "ray", "--backend", "mjx"]) == 2
    assert evaluate.main(["--executor", "ray", "--backend", "mjx"]) == 2
    with pytest.raises(SystemExit):
        make_dataset.main(["--out", str(tmp_path / "ds"), "--executor", "ray", "--backend", "mjx"])
    monkeypatch.setitem(sys.modules, "ray", None)
    assert cotrain.main([*run, "--executor", "ray"]) == 2
    assert evaluate.main(["--executor", "ray"]) == 2
    with pytest.raises(SystemExit):
        make_dataset.main(["--out", str(tmp_path / "ds"), "--executor", "ray"])
    err = capsys.readouterr().err
    assert err.count('pip install -e ".[ray]"') == 3 and "mujoco backend" in err
    assert not (tmp_path / "run").exists() and not (tmp_path / "ds").exists()
