"""Can a fitness net learn to rank one object's designs, given many of them?

Co-training climbs the fitness net, so it only helps where the net ranks one object's candidate
designs as the simulator does; the runs' own nets do not (within-object Spearman ~0,
benchmarks/RESULTS.md). This script measures whether within-object data, made cheaply, changes that:

    # 1. training data: for each generator (every run's pretrained and final nets) and each run's
    #    objects, K candidates per object (own design + latent perturbations), first grasp only
    python research/fitness_ranking.py make --runs R0 R1 R2 --test-run R0 --candidates 16 \\
        --noise 0.4 --out D
    #    (--fresh 148 --fresh-seed 8: built-in objects beside the runs' own, coacd'd once and cached)
    # 2. the test: R0's held-out objects and 48 fresh ones, 16 candidates each, all 11 trials
    python research/fitness_ranking.py test --test-run R0 --fresh 48 --seed 7 --out D
    # 3. a net trained on D (grasp BCE + a within-object pairwise loss), scored on the test
    python research/fitness_ranking.py fit --data D --model gaps --steps 3000 --rows 16000

The first grasp decides most of what differs between one object's designs (a failed grasp fails
all 11 trials; 76% of the within-object variance of trials passed on the test below), and it costs
a third of an evaluation to simulate, so the training data simulates the grasp only. ``make``
skips chunks already on disk (a killed run goes on); the test's objects are never trained on (their
volumes are compared). ``fit`` prints, at intervals, on the test: ``spearman`` (within-object rank
correlation of the net's grasp probability with trials passed: ``tables.stats.ranking_stats``),
``within_auc`` (per object with held and failed candidates, the chance a held one scores above a
failed one; 0.5 is chance, 1.0 a perfect grasp oracle, whose Spearman is only ~0.44 here because
13 of the 45 objects whose candidates differ hold every grasp), and the trials passed by the net's
pick against the generator's own design, the average and the best candidate.

Models: ``gaps``, eight 40 x 40 maps of each jaw's gap to the object per (y, z) column at closure
(soft, from the volumes) into a 2D CNN; ``volumes``, the project's 3D fitness net. Both end in the
config's fully connected head and one grasp logit.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np


# --------------------------------------------------------------------------------------------
# Pure pieces (tested in tests/test_fitness_ranking.py)
# --------------------------------------------------------------------------------------------

def within_object_auc(scores: np.ndarray, grasp: np.ndarray, feasible: np.ndarray | None = None):
    """Mean over objects with held and failed (feasible) candidates of P(score of a held one >
    score of a failed one), ties half.  scores, grasp: [N, K].  Returns (auc or nan, objects)."""
    s, g = np.asarray(scores, np.float64), np.asarray(grasp)
    f = np.ones(g.shape, bool) if feasible is None else np.asarray(feasible, bool)
    if s.shape != g.shape or s.shape != f.shape or s.ndim != 2:
        raise ValueError(f"scores {s.shape}, grasp {g.shape}, feasible {f.shape}: expected [N, K] each")
    aucs = []
    for si, gi, fi in zip(s, g, f):
        pos, neg = si[(gi == 1) & fi], si[(gi == 0) & fi]
        if len(pos) and len(neg):
            d = pos[:, None] - neg[None]
            aucs.append(float((d > 0).mean() + 0.5 * (d == 0).mean()))
    return (float(np.mean(aucs)) if aucs else float("nan")), len(aucs)


def pair_loss(logits, labels):
    """Within-object pairwise logistic loss: logits, labels [G, P] (G objects, P candidates each);
    mean over ordered pairs (i, j) of one object with label_i > label_j of softplus(l_j - l_i)."""
    import jax
    import jax.numpy as jnp

    diff = logits[:, :, None] - logits[:, None, :]
    want = (labels[:, :, None] > labels[:, None, :]).astype(jnp.float32)
    return (want * jax.nn.softplus(-diff)).sum() / jnp.maximum(want.sum(), 1.0)


def contact_maps(volume, sharpness: float = 30.0):
    """[B, 120, 40, 40] fitness layout -> [B, 40, 40, 8]: per (y, z) column, each jaw's gap to the
    object at closure (finger height over its mount and the object's first surface seen from that
    jaw, both as soft counts of occupied voxels, so differentiable), both gaps less their minimum
    over the map, the object's thickness and presence, both finger heights; voxel units / 20."""
    import jax
    import jax.numpy as jnp

    left, obj, right = volume[:, :40], volume[:, 40:80], volume[:, 80:]
    empty = lambda t: 1.0 - jax.nn.sigmoid(-sharpness * t)  # noqa: E731
    e_left, e_obj, e_right = empty(left), empty(obj), empty(right)
    h_left = 40 - jnp.cumprod(e_left[:, ::-1], axis=1).sum(1)
    h_right = 40 - jnp.cumprod(e_right, axis=1).sum(1)
    s_left = jnp.cumprod(e_obj, axis=1).sum(1)
    s_right = jnp.cumprod(e_obj[:, ::-1], axis=1).sum(1)
    present = 1 - jnp.prod(e_obj, axis=1)
    d_left, d_right = s_left + 20 - h_left, s_right + 20 - h_right
    m_left = d_left - d_left.min(axis=(1, 2), keepdims=True)
    m_right = d_right - d_right.min(axis=(1, 2), keepdims=True)
    thick = jnp.clip(40 - s_left - s_right, 0, 40)
    return jnp.stack([d_left / 20, d_right / 20, m_left / 20, m_right / 20, thick / 20, present,
                      h_left / 20, h_right / 20], -1)


def _ranker(mode: str, net_cfg):
    """``volumes``: the project's FitnessNet with one (grasp) output; ``gaps``: ``contact_maps``
    into a 2D CNN and the same fully connected head."""
    import flax.linen as nn
    import jax.numpy as jnp

    from f2f_jax.nets.fitness import FitnessNet
    from f2f_jax.nets.shape import batch_norm

    if mode == "volumes":
        class Volumes(nn.Module):
            @nn.compact
            def __call__(self, v, *, train):
                return FitnessNet(net_cfg, n_outputs=1, name="net")(v, train=train)[:, 0]
        return Volumes()

    class Gaps(nn.Module):
        @nn.compact
        def __call__(self, v, *, train):
            c = net_cfg
            x = contact_maps(v)
            for i, (w, s) in enumerate(((16, 1), (32, 2), (32, 2), (64, 2))):
                x = nn.Conv(w, (3, 3), strides=(s, s), padding=1, use_bias=False, name=f"g{i}")(x)
                x = nn.leaky_relu(batch_norm(c, train, jnp.float32, name=f"g{i}_bn")(x), c.leaky_slope)
            x = x.reshape(x.shape[0], -1)
            for i, width in enumerate(c.fitness_fc):
                x = nn.Dense(width, use_bias=False, name=f"fc{i}")(x)
                x = nn.leaky_relu(batch_norm(c, train, jnp.float32, name=f"fc{i}_bn")(x), c.leaky_slope)
            return nn.Dense(1, name="grasp")(x)[:, 0]

    return Gaps()


# --------------------------------------------------------------------------------------------
# make / test: candidates simulated
# --------------------------------------------------------------------------------------------

def _digest(volume: np.ndarray) -> str:
    return hashlib.sha1(np.asarray(volume, np.float16).tobytes()).hexdigest()


def make(args) -> int:
    from f2f_jax.config import default
    from f2f_jax.data import builtin_objects, held_out_objects, run_objects
    from f2f_jax.geometry import postprocess
    from f2f_jax.nets.inference import propose
    from f2f_jax.sim import evaluate
    from f2f_jax.tables.table import grasp_only
    from f2f_jax.train.checkpoint import load_trained_nets

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    geometry = default().geometry
    test_objs, _ = held_out_objects(args.test_run, geometry)
    seen = {_digest(o) for o in test_objs}  # objects never trained on: the test's, then each once
    if (out / "test.npz").exists():  # the test's fresh objects too, when `test` has already run
        with np.load(out / "test.npz") as z:
            seen |= {_digest(o) for o in z["objects"]}

    def unseen(tsdfs, limit=None):
        """Indices of the volumes not seen before (at most ``limit``), now marked seen."""
        digests = [_digest(o) for o in tsdfs]
        keep = [j for j, d in enumerate(digests) if d not in seen][:limit]
        seen.update(digests[j] for j in keep)
        return keep

    objects = {}
    for i, run in enumerate(map(Path, args.runs)):
        tsdfs, names = run_objects(run, geometry)
        keep = unseen(tsdfs, args.objects_per_run)
        if keep:  # runs of one seed share their objects: each object once
            objects[i] = (tsdfs[keep], [names[j] for j in keep])
        print(f"run {run}: {len(keep)} of {len(tsdfs)} objects (the rest are the test's or an "
              f"earlier run's)", flush=True)
    if args.fresh:  # more objects than the runs hold: built-in ones of another seed (coacd, cached)
        from f2f_jax.geometry import mesh_to_tsdf
        meshes = builtin_objects(args.fresh, seed=args.fresh_seed)
        tsdfs = np.stack([mesh_to_tsdf(m, geometry) for m in meshes])
        keep = unseen(tsdfs)
        objects["fresh"] = (tsdfs[keep], [f"fresh{args.fresh_seed}/{meshes[j].metadata.get('name')}"
                                          for j in keep])
        print(f"fresh (seed {args.fresh_seed}): {len(keep)} of {len(tsdfs)} objects (the rest are the "
              f"test's or a run's)", flush=True)
    total, start = 0, time.time()
    for noise in args.noise:
        for i, run in enumerate(map(Path, args.runs)):
            for ck in args.checkpoints:
                nets = load_trained_nets(run / "pretrained" if ck == "pretrained" else run)
                cfg = grasp_only(nets.config)
                for j, (objs, names) in objects.items():
                    path = out / f"r{i}_{ck}_n{noise}_k{args.candidates}_o{j}.npz"
                    if path.exists():
                        continue
                    key = int.from_bytes(hashlib.sha1(path.name.encode()).digest()[:4], "little")
                    lefts, rights = propose(nets, objs.astype(np.float32), key, args.candidates, noise)
                    feasible = postprocess(lefts, rights, cfg.geometry)
                    ib, ik = np.nonzero(feasible)
                    t = time.time()
                    grasp = np.zeros(feasible.shape, np.uint8)
                    if len(ib):
                        grasp[ib, ik] = evaluate(objs[ib], lefts[ib, ik], rights[ib, ik], cfg=cfg,
                                                 progress=False)[:, 0]
                    dt = time.time() - t
                    total += len(ib)
                    tmp = path.with_suffix(".tmp.npz")
                    np.savez(tmp, objects=objs.astype(np.float16), lefts=lefts.astype(np.float16),
                             rights=rights.astype(np.float16), feasible=feasible, grasp=grasp,
                             names=np.array(names))
                    tmp.rename(path)
                    # objects whose feasible candidates both held and failed (infeasible ones are not rows)
                    mixed = int(((feasible & (grasp == 1)).any(1) & (feasible & (grasp == 0)).any(1)).sum())
                    held = f"{grasp[feasible].mean():.3f}" if len(ib) else "- (no feasible candidate)"
                    print(f"{path.name}: {len(ib)} grasps in {dt:.0f} s ({len(ib) / max(dt, 1e-9):.1f}/s), "
                          f"held {held}, objects with both {mixed}/{len(objs)}; "
                          f"{total} in all [{time.time() - start:.0f} s]", flush=True)
    return 0


def test(args) -> int:
    from f2f_jax.data import builtin_objects, held_out_objects
    from f2f_jax.geometry import mesh_to_tsdf
    from f2f_jax.tables.stats import candidate_outcomes
    from f2f_jax.train.checkpoint import load_trained_nets

    nets = load_trained_nets(Path(args.test_run))
    objs, names = held_out_objects(args.test_run, nets.config.geometry)
    meshes = builtin_objects(args.fresh, seed=args.seed) if args.fresh else []
    if meshes:
        fresh = np.stack([mesh_to_tsdf(m, nets.config.geometry) for m in meshes])
        objs = np.concatenate([objs, fresh])
        names = list(names) + [f"fresh/{m.metadata.get('name')}" for m in meshes]
    t = time.time()
    lefts, rights, feasible, simulated = candidate_outcomes(nets, objs, nets.config,
                                                            candidates=args.candidates, key=args.key,
                                                            progress=True)
    path = Path(args.out) / "test.npz"
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, objects=objs.astype(np.float16), lefts=lefts.astype(np.float16),
             rights=rights.astype(np.float16), feasible=feasible, simulated=simulated, names=np.array(names))
    print(f"{path}: {feasible.sum()} candidates simulated in {time.time() - t:.0f} s", flush=True)
    return 0


# --------------------------------------------------------------------------------------------
# fit
# --------------------------------------------------------------------------------------------

def _load_groups(directory: Path, max_rows: int):
    """Training rows grouped by object: volumes, grasp labels and [(object index, rows)]."""
    objects, lefts, rights, labels, groups, n = [], [], [], [], [], 0
    for path in sorted(directory.glob("r*_o*.npz")):
        with np.load(path) as npz:  # each array read once (an NpzFile reads it again on every access)
            z = {k: npz[k] for k in ("objects", "lefts", "rights", "feasible", "grasp")}
        feasible = z["feasible"]
        for i in range(len(feasible)):
            ks = np.nonzero(feasible[i])[0]
            if len(ks) < 2 or n + len(ks) > max_rows:
                continue
            objects.append(z["objects"][i])
            lefts.append(z["lefts"][i, ks])
            rights.append(z["rights"][i, ks])
            labels.append(z["grasp"][i, ks])
            groups.append((len(objects) - 1, np.arange(n, n + len(ks))))
            n += len(ks)
    if not groups:
        raise SystemExit(f"{directory}: no training rows (run `make` first)")
    return (np.stack(objects), np.concatenate(lefts), np.concatenate(rights),
            np.concatenate(labels).astype(np.float32), groups)


def fit(args) -> int:
    from f2f_jax.cli.reproducible import reproducible_xla

    reproducible_xla()
    import jax
    import jax.numpy as jnp
    import optax

    from f2f_jax.config import default
    from f2f_jax.nets.fitness import fitness_input
    from f2f_jax.tables.stats import ranking_stats

    objects, lefts, rights, labels, groups = _load_groups(Path(args.data), args.rows)
    row_object = np.concatenate([np.full(len(rows), o) for o, rows in groups])
    # validation: whole objects (every generator's candidates of them) kept out of training
    held = {i for i, o in enumerate(objects) if int(_digest(o)[:8], 16) % 1000 < 1000 * args.val_fraction}
    val = [gr for gr in groups if gr[0] in held and np.ptp(labels[gr[1]]) > 0]
    groups = [gr for gr in groups if gr[0] not in held]
    mixed = [gr for gr in groups if np.ptp(labels[gr[1]]) > 0]
    n_train = sum(len(rows) for _, rows in groups)
    print(f"{n_train} training rows, {len(groups)} objects x generators, {len(mixed)} with held and "
          f"failed grasps; held {labels.mean():.3f}; validation: {len(val)} mixed groups", flush=True)
    if not mixed and args.pair > 0:
        raise SystemExit("no object has both held and failed candidates: nothing to rank")
    test_set = np.load(Path(args.test or Path(args.data) / "test.npz"))

    model = _ranker(args.model, default().net)
    zeros = jnp.zeros((2, 40, 40, 40))
    variables = model.init(jax.random.PRNGKey(args.seed), fitness_input(zeros, zeros, zeros), train=False)
    params, stats = variables["params"], variables["batch_stats"]
    opt = optax.adamw(args.lr, weight_decay=1e-5)
    opt_state = opt.init(params)
    g, p = args.objects, args.per_object

    @jax.jit
    def step(params, stats, opt_state, obj, left, right, y, flips):
        v = fitness_input(obj, left, right)
        if args.flip:  # the world's mirror symmetries: x (the jaws swap), y; z is up
            v = jnp.where(flips[:, 0, None, None, None], jnp.flip(v, 1), v)
            v = jnp.where(flips[:, 1, None, None, None], jnp.flip(v, 2), v)

        def loss_fn(q):
            logit, upd = model.apply({"params": q, "batch_stats": stats}, v,
                                     train=True, mutable=["batch_stats"])
            bce = optax.sigmoid_binary_cross_entropy(logit, y).mean()
            pair = pair_loss(logit.reshape(g, p), y.reshape(g, p))
            return bce + args.pair * pair, (upd["batch_stats"], bce, pair)
        (_, (stats, bce, pair)), grads = jax.value_and_grad(loss_fn, has_aux=True)(params)
        updates, opt_state = opt.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), stats, opt_state, bce, pair

    @jax.jit
    def score(params, stats, obj, left, right):
        return model.apply({"params": params, "batch_stats": stats}, fitness_input(obj, left, right),
                           train=False)

    n_obj, k = test_set["feasible"].shape
    t_left = test_set["lefts"].reshape(n_obj * k, 40, 40, 40)
    t_right = test_set["rights"].reshape(n_obj * k, 40, 40, 40)
    simulated = test_set["simulated"].astype(np.float64)
    val_rows = np.concatenate([rows for _, rows in val]) if val else np.zeros(0, int)

    def scores(obj_table, obj_of_row, left_table, right_table, rows, chunk=64):
        """The ranker's logits of ``rows`` (their object ``obj_table[obj_of_row]``), ``chunk`` at a
        time, the last chunk padded with its final row so that one compiled shape serves all."""
        out = []
        for i in range(0, len(rows), chunk):
            r, o = rows[i:i + chunk], obj_of_row[i:i + chunk]
            pad = np.concatenate([np.arange(len(r)), np.full(chunk - len(r), len(r) - 1)])
            got = score(params, stats, *(jnp.asarray(a[pad], jnp.float32) for a in (
                obj_table[o], left_table[r], right_table[r])))
            out.append(np.asarray(got)[:len(r)])
        return np.concatenate(out) if out else np.zeros(0, np.float32)

    def evaluate():
        s = scores(test_set["objects"], np.repeat(np.arange(n_obj), k), t_left, t_right,
                   np.arange(n_obj * k)).reshape(n_obj, k)
        prob = np.where(test_set["feasible"], 1 / (1 + np.exp(-s)), 0.0)
        out = ranking_stats(np.repeat(prob[..., None], simulated.shape[-1], -1), simulated)
        out["within_auc"], out["within_objects"] = within_object_auc(prob, simulated[..., 0],
                                                                     test_set["feasible"])
        v = np.split(scores(objects, row_object[val_rows], lefts, rights, val_rows),
                     np.cumsum([len(rows) for _, rows in val])[:-1])
        aucs = [within_object_auc(sv[None], labels[rows][None])[0] for sv, (_, rows) in zip(v, val)]
        out["val_auc"] = float(np.mean(aucs)) if aucs else float("nan")
        return out

    rng = np.random.default_rng(args.seed)
    history, report, start = [], [], time.time()
    for i in range(args.steps):
        half = g // 2 if mixed else 0  # half the objects of a batch have held and failed candidates
        chosen = ([mixed[j] for j in rng.integers(0, len(mixed), half)]
                  + [groups[j] for j in rng.integers(0, len(groups), g - half)])
        idx = np.concatenate([rng.choice(rows, p, replace=len(rows) < p) for _, rows in chosen])
        params, stats, opt_state, bce, pair = step(
            params, stats, opt_state, *(jnp.asarray(a, jnp.float32) for a in
                                        (objects[row_object[idx]], lefts[idx], rights[idx], labels[idx])),
            jnp.asarray(rng.random((len(idx), 2)) < 0.5))
        history.append((float(bce), float(pair)))
        if (i + 1) % max(1, args.steps // args.reports) == 0:
            st = evaluate()
            st.update(step=i + 1, bce=float(np.mean(history[-100:], 0)[0]),
                      pair=float(np.mean(history[-100:], 0)[1]), seconds=time.time() - start)
            report.append(st)
            print(f"step {i + 1}: train bce {st['bce']:.3f} pair {st['pair']:.3f} | test spearman "
                  f"{st['spearman']:.3f}, within-object grasp AUC {st['within_auc']:.3f} "
                  f"({st['within_objects']} objects); trials of 11: pick {st['trials_picked']:.2f}, "
                  f"own {st['trials_first']:.2f}, mean {st['trials_mean']:.2f}, best "
                  f"{st['trials_best']:.2f}; grasp AUC {st['grasp_auc']:.3f}; validation within-object "
                  f"AUC {st['val_auc']:.3f} [{st['seconds']:.0f} s]",
                  flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(dict(rows=n_train, objects=len(groups),
                                                   mixed=len(mixed), args=vars(args), report=report),
                                              indent=1, default=str))
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="command", required=True)
    m = sub.add_parser("make", help="grasp-only candidates of the runs' generators on their objects")
    m.add_argument("--runs", nargs="+", required=True, help="co-training run directories")
    m.add_argument("--test-run", required=True, help="the run whose held-out objects are the test's")
    m.add_argument("--checkpoints", nargs="+", default=["pretrained", "final"],
                   choices=["pretrained", "final"])
    m.add_argument("--candidates", type=int, default=16)
    m.add_argument("--noise", type=float, nargs="+", default=[0.4], help="latent noise (design's is 0.2)")
    m.add_argument("--objects-per-run", type=int, default=10**9)
    m.add_argument("--fresh", type=int, default=0,
                   help="also this many built-in objects of --fresh-seed (coacd on first use, cached)")
    m.add_argument("--fresh-seed", type=int, default=8,
                   help="seed of the --fresh objects (the test's fresh objects are seed 7's: keep apart)")
    m.add_argument("--out", required=True)
    t = sub.add_parser("test", help="the ranking test: full protocol, K candidates per object")
    t.add_argument("--test-run", required=True)
    t.add_argument("--fresh", type=int, default=48)
    t.add_argument("--seed", type=int, default=7)
    t.add_argument("--candidates", type=int, default=16)
    t.add_argument("--key", type=int, default=11)
    t.add_argument("--out", required=True)
    f = sub.add_parser("fit", help="train a ranker on the made data, score it on the test")
    f.add_argument("--data", required=True)
    f.add_argument("--test", help="test.npz (default: DATA/test.npz)")
    f.add_argument("--model", choices=["gaps", "volumes"], default="gaps")
    f.add_argument("--rows", type=int, default=10**9, help="at most this many training rows")
    f.add_argument("--steps", type=int, default=3000)
    f.add_argument("--objects", type=int, default=8, help="objects per batch")
    f.add_argument("--per-object", type=int, default=8, help="candidates per object in a batch")
    f.add_argument("--pair", type=float, default=1.0, help="weight of the within-object pairwise loss")
    f.add_argument("--lr", type=float, default=1e-3)
    f.add_argument("--seed", type=int, default=0)
    f.add_argument("--reports", type=int, default=6)
    f.add_argument("--val-fraction", type=float, default=0.15,
                   help="share of the training objects kept out to validate on")
    f.add_argument("--no-flip", dest="flip", action="store_false",
                   help="no mirror augmentation (x: the jaws swap; y)")
    f.add_argument("--json")
    args = ap.parse_args(argv)
    if args.command in ("make", "test"):
        for run in (args.runs if args.command == "make" else []) + [args.test_run]:
            if not (Path(run) / "run.json").exists():
                ap.error(f"{run}: not a co-training run directory (no run.json)")
    if getattr(args, "candidates", 2) < 2:
        ap.error("--candidates must be >= 2: one design per object ranks nothing")
    return {"make": make, "test": test, "fit": fit}[args.command](args)


if __name__ == "__main__":
    sys.exit(main())
