"""How much of the imprint fingers' grasp survives the shape auto-encoder?

The generator never outputs fingers directly: it outputs two latents, and the shape auto-encoder's
decoder turns them into volumes. It is pretrained to put out the encoder's latents of the imprint
fingers, so **an imprint encoded and decoded again is the best that pretraining can teach it**,
and co-training starts from there. This script simulates, on a run's held-out objects and fresh
ones, what the simulator thinks of each step of that chain:

    python research/finger_fidelity.py --run-dir runs/cotrain --fresh 48 --seed 7 --json out.json

Rows (all post-processed as designs are, all 11 trials): ``imprint`` (``geometry.imprint_fingers``),
``imprint through the auto-encoder`` (the run's encoder means, clipped to the decoder's [-1, 1],
decoded), the generator's own design after pretraining (``RUN/pretrained``) and after co-training
(``RUN``); with ``--learned-heights STEPS`` a generator that decodes height maps instead, trained
on the run's training objects' imprints (``--extra-objects N`` more builtin ones: imprints cost no
simulation); and with ``--pca K ...`` the imprints' height maps through a K-component PCA fitted
on the run's training objects' imprints (mirrored four ways): what a code of K numbers keeps of the
one thing about a finger the simulator uses. Beside the trials: each finger's volume IoU with its
imprint, and the mean absolute difference of the height maps the simulator meshes
(``geometry.finger_tiling.finger_height_map``, in voxels, over the columns either finger
occupies), the measure that decides where the jaws touch.
"""

from __future__ import annotations

import argparse
import json
import textwrap
import time
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm


def height_gap_voxels(a: np.ndarray, b: np.ndarray, cfg=None) -> float:
    """Mean |height map a - height map b| in voxels over the columns either finger occupies."""
    from f2f_jax.config import GeometryConfig
    from f2f_jax.geometry.finger_tiling import finger_height_map

    g = cfg or GeometryConfig()
    ha, hb = finger_height_map(a, g), finger_height_map(b, g)
    cols = (ha > 0) | (hb > 0)
    voxel = g.voxel_size
    return float(np.abs(ha - hb)[cols].mean() / voxel) if cols.any() else 0.0


def finger_from_heights(heights: np.ndarray, cfg=None) -> np.ndarray:
    """[R, R] heights over the mount (metres; < half a voxel: an empty column) -> [R, R, R] finger
    volume, solid from the mount to each column's height (a projective TSDF along w, as imprints)."""
    from f2f_jax.config import GeometryConfig

    g = cfg or GeometryConfig()
    h = np.where(heights >= g.voxel_size / 2, heights, -np.inf)
    w = (np.arange(g.resolution) + 0.5) * g.voxel_size
    return np.clip((w[None, None, :] - h[:, :, None]) / g.truncation, -1.0, 1.0).astype(np.float32)


def pca_roundtrip(train: np.ndarray, maps: np.ndarray, k: int) -> np.ndarray:
    """Project maps [N, ...] on the first k principal components of train [M, ...] and back."""
    x = train.reshape(len(train), -1)
    mean = x.mean(0)
    _, _, vt = np.linalg.svd(x - mean, full_matrices=False)
    basis = vt[:k]
    y = maps.reshape(len(maps), -1) - mean
    return ((y @ basis.T) @ basis + mean).reshape(maps.shape)


def through_autoencoder(nets, fingers: np.ndarray) -> np.ndarray:
    """[N, 40, 40, 40] finger volumes -> the same encoded (means) and decoded by the run's nets."""
    import jax
    import jax.numpy as jnp

    from f2f_jax.nets.generator import FingerGenerator

    gen = FingerGenerator(nets.config.net)

    @jax.jit
    def roundtrip(x):
        z = gen.apply(nets.generator, x, method=lambda m, v: m.encoder(v, train=False)[0])
        z = jnp.clip(z, -1.0, 1.0)  # the decoder saw latents in [-1, 1] only (the generator's tanh)
        return gen.apply(nets.generator, z, method=lambda m, v: m.decoder(v, train=False))

    return np.concatenate([np.asarray(roundtrip(jnp.asarray(fingers[i:i + 32], jnp.float32)))
                           for i in range(0, len(fingers), 32)])


def height_targets(lefts: np.ndarray, rights: np.ndarray, cfg=None) -> np.ndarray:
    """Finger pairs [N, 40, 40, 40] x2 -> [N, 40, 40, 2] their height maps in voxels, both indexed
    [world y, world z] (the right finger's u runs along -y, so its map is flipped)."""
    from f2f_jax.config import GeometryConfig
    from f2f_jax.geometry.finger_tiling import finger_height_map

    g = cfg or GeometryConfig()
    out = np.zeros((len(lefts), g.resolution, g.resolution, 2), np.float32)
    for i, (left, right) in enumerate(zip(lefts, rights)):
        out[i, ..., 0] = finger_height_map(left, g) / g.voxel_size
        out[i, ..., 1] = finger_height_map(right, g)[::-1] / g.voxel_size
    return out


def imprint_height_targets(objects: np.ndarray, cfg=None) -> np.ndarray:
    """[N, 40, 40, 40] objects -> [N, 40, 40, 2] their imprint fingers' ``height_targets``."""
    from f2f_jax.geometry import imprint_fingers

    pairs = [imprint_fingers(o, cfg) for o in objects]
    return height_targets([p[0] for p in pairs], [p[1] for p in pairs], cfg)


def train_height_generator(objects: np.ndarray, targets: np.ndarray, steps: int, seed: int = 0,
                           batch: int = 32):
    """A column-local generator, object -> both fingers' height maps: the object's x planes as the
    channels of a 2D CNN over (y, z) (three 3 x 3 layers of 64, then 1 x 1 to two maps), trained
    with Adam (L1 in voxels) on objects [N, 40, 40, 40] and targets [N, 40, 40, 2].
    Returns (predict: objects -> heights [N, 40, 40, 2] in voxels, final training L1)."""
    import flax.linen as nn
    import jax
    import jax.numpy as jnp
    import optax

    class Heights(nn.Module):
        @nn.compact
        def __call__(self, x):
            for width in (64, 64, 64):
                x = nn.leaky_relu(nn.Conv(width, (3, 3), padding=1)(x), 0.2)
            return nn.Conv(2, (1, 1))(x) * 10.0 + 10.0  # heights are 0-40 voxels, most near 10-20

    def planes(o):  # [B, x, y, z] -> [B, y, z, x]
        return jnp.transpose(jnp.asarray(o, jnp.float32), (0, 2, 3, 1))

    model = Heights()
    params = model.init(jax.random.PRNGKey(seed), planes(objects[:1]))
    opt = optax.adamw(1e-3, weight_decay=1e-5)
    state = opt.init(params)

    @jax.jit
    def step(params, state, x, y):
        loss, grads = jax.value_and_grad(lambda q: jnp.mean(jnp.abs(model.apply(q, planes(x)) - y)))(params)
        updates, state = opt.update(grads, state, params)
        return optax.apply_updates(params, updates), state, loss

    rng = np.random.default_rng(seed)
    loss = np.nan
    for _ in range(steps):
        b = rng.choice(len(objects), min(batch, len(objects)), replace=False)
        params, state, loss = step(params, state, objects[b].astype(np.float32), targets[b])
    apply = jax.jit(lambda x: model.apply(params, planes(x)))

    def predict(objs):
        return np.concatenate([np.asarray(apply(objs[i:i + batch].astype(np.float32)))
                               for i in range(0, len(objs), batch)])
    return predict, float(loss)


def height_map_picture(rows: dict, objects: np.ndarray, path, n: int = 4, cfg=None) -> None:
    """A PNG grid: for the first n objects (rows), each kind of left finger's height map (columns),
    in voxels over the mount, with the trials the pair passed in the title.  rows: label ->
    (left fingers [N, 40, 40, 40], trials passed [N])."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from f2f_jax.config import GeometryConfig
    from f2f_jax.errors import VolumeError
    from f2f_jax.geometry.finger_tiling import finger_height_map

    g = cfg or GeometryConfig()
    labels = list(rows)
    n = min(n, len(objects))
    fig = Figure(figsize=(2.2 * len(labels), 2.3 * n))
    FigureCanvasAgg(fig)
    for i in range(n):
        for j, label in enumerate(labels):
            (fingers, trials) = rows[label]
            ax = fig.add_subplot(n, len(labels), i * len(labels) + j + 1)
            try:
                heights = finger_height_map(fingers[i], g) / g.voxel_size
            except VolumeError:  # an empty (infeasible) finger
                heights = np.zeros((g.resolution, g.resolution))
            im = ax.imshow(heights.T, origin="lower", vmin=0, vmax=g.resolution, cmap="viridis")
            ax.set_xticks([])
            ax.set_yticks([])
            title = f"{textwrap.fill(label, 24)}\n{trials[i]}/11" if i == 0 else f"{trials[i]}/11"
            ax.set_title(title, fontsize=7)
    fig.colorbar(im, ax=fig.axes, shrink=0.6, label="left finger height over the mount (voxels)")
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run-dir", required=True, help="a co-training run (with pretrained/)")
    ap.add_argument("--fresh", type=int, default=48, help="fresh builtin objects beside the held-out ones")
    ap.add_argument("--seed", type=int, default=7, help="seed of the fresh objects")
    ap.add_argument("--pca", type=int, nargs="*", default=[],
                    help="also imprints' height maps through a PCA of this many components (e.g. 16 128)")
    ap.add_argument("--learned-heights", type=int, default=0, metavar="STEPS",
                    help="also a column-local CNN trained for STEPS steps on the run's training objects' "
                         "imprint height maps (a generator that decodes height maps, after pretraining)")
    ap.add_argument("--extra-objects", type=int, default=0,
                    help="builtin objects (seed 11) added to the learned generator's training")
    ap.add_argument("--png", help="a picture of the first objects' left-finger height maps, row by row")
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    if args.extra_objects and not args.learned_heights:
        ap.error("--extra-objects trains the height-map generator: give --learned-heights STEPS too")

    from f2f_jax.data import builtin_objects, held_out_objects
    from f2f_jax.geometry import imprint_fingers, mesh_to_tsdf, postprocess, solid_iou
    from f2f_jax.sim import evaluate
    from f2f_jax.train.checkpoint import load_trained_nets

    run = Path(args.run_dir)
    nets = load_trained_nets(run)
    g = nets.config.geometry
    objs, names = held_out_objects(run, g)
    if args.fresh:
        meshes = builtin_objects(args.fresh, seed=args.seed)
        objs = np.concatenate([objs, np.stack([mesh_to_tsdf(m, g) for m in meshes])]).astype(np.float32)
    n = len(objs)
    print(f"{run}: {n} objects ({n - args.fresh} held-out, {args.fresh} fresh)", flush=True)

    imprints = [imprint_fingers(o, g) for o in objs]
    rows = {"imprint": (np.stack([p[0] for p in imprints]), np.stack([p[1] for p in imprints]))}
    if "encoder" in nets.generator["params"]:  # a height-map generator's run has no codec in it
        rows["imprint through the auto-encoder"] = (through_autoencoder(nets, rows["imprint"][0]),
                                                    through_autoencoder(nets, rows["imprint"][1]))
    if args.pca or args.learned_heights:
        from f2f_jax.data import object_split, run_objects
        from f2f_jax.geometry.finger_tiling import finger_height_map

        all_objs, all_names = run_objects(run, g)
        train = set(object_split(run / "objects")["train"])
        train_objs = np.stack([o for o, name in zip(all_objs, all_names) if name in train]).astype(np.float32)
    if args.pca:
        maps = np.stack([finger_height_map(f, g) for o in train_objs for f in imprint_fingers(o, g)])
        maps = np.concatenate([maps, maps[:, ::-1], maps[:, :, ::-1], maps[:, ::-1, ::-1]])  # mirrors in u, v
        test_maps = [np.stack([finger_height_map(f, g) for f in side]) for side in rows["imprint"]]
        for k in args.pca:
            rows[f"imprint heights, PCA {k} (of {len(maps)} maps)"] = tuple(
                np.stack([finger_from_heights(h, g) for h in pca_roundtrip(maps, m, k)]) for m in test_maps)
    if args.learned_heights:
        if args.extra_objects:
            meshes = tqdm(builtin_objects(args.extra_objects, seed=11), desc="extra objects -> TSDF",
                          unit="obj")
            extra = np.stack([mesh_to_tsdf(m, g) for m in meshes])
            tested = {o.astype(np.float16).tobytes() for o in objs}  # never train on a test object
            keep = [o.astype(np.float16).tobytes() not in tested for o in extra]
            train_objs = np.concatenate([train_objs, extra[keep]])
        t = time.time()
        predict, loss = train_height_generator(train_objs, imprint_height_targets(train_objs, g),
                                               args.learned_heights)
        heights = predict(objs) * g.voxel_size
        test_l1 = np.abs(heights / g.voxel_size - height_targets(*rows["imprint"], g)).mean()
        print(f"height-map generator: {len(train_objs)} objects, {args.learned_heights} steps, "
              f"{time.time() - t:.0f} s; L1 train {loss:.2f}, test {test_l1:.2f} voxels", flush=True)
        rows[f"height-map generator ({len(train_objs)} objects, {args.learned_heights} steps)"] = (
            np.stack([finger_from_heights(h, g) for h in heights[..., 0]]),
            np.stack([finger_from_heights(h[::-1], g) for h in heights[..., 1]]))
    for label, path in (("generator, pretrained", run / "pretrained"), ("generator, co-trained", run)):
        lefts, rights = load_trained_nets(path).generate(objs)
        rows[label] = (np.array(lefts), np.array(rights))

    results, processed = {}, {}
    il, ir = rows["imprint"]
    for label, (lefts, rights) in rows.items():
        lefts, rights = lefts.copy(), rights.copy()
        feasible = postprocess(lefts[:, None], rights[:, None], g)[:, 0]
        processed[label] = lefts
        t = time.time()
        out = np.zeros((n, nets.config.sim.n_trials), np.uint8)
        if feasible.any():
            out[feasible] = evaluate(objs[feasible], lefts[feasible], rights[feasible], cfg=nets.config,
                                     progress=False)
        iou = np.concatenate([solid_iou(lefts, il), solid_iou(rights, ir)])
        gap = [height_gap_voxels(a, b, g) for f, ref in ((lefts, il), (rights, ir))
               for a, b, ok in zip(f, ref, feasible) if ok]
        results[label] = dict(
            feasible=float(feasible.mean()), grasp=float(out[:, 0].mean()), s_avg=float(out[:, 1:5].mean()),
            r_avg=float(out[:, 5:].mean()), trials=float(out.sum(1).mean()),
            iou_with_imprint=float(np.mean(iou)), height_gap_voxels=float(np.mean(gap)) if gap else None,
            seconds=time.time() - t, per_object=out.sum(1).tolist())
        r = results[label]
        gap_text = "-" if r["height_gap_voxels"] is None else f"{r['height_gap_voxels']:.2f}"
        print(f"{label:40s} feasible {r['feasible']:.3f}  grasp {r['grasp']:.3f}  S {r['s_avg']:.3f}  "
              f"R {r['r_avg']:.3f}  trials {r['trials']:.2f}/11  IoU with imprint "
              f"{r['iou_with_imprint']:.3f}  height gap {gap_text} voxels "
              f" [{r['seconds']:.0f} s]", flush=True)
    if args.png:
        height_map_picture({label: (processed[label], results[label]["per_object"]) for label in rows}, objs,
                           args.png, cfg=g)
        print(f"picture: {args.png}", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(dict(run=str(run), n=n, fresh=args.fresh, seed=args.seed,
                                                   rows=results), indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
