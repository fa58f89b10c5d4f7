"""Geometry throughput: mesh -> TSDF -> imprint fingers -> convex pieces, with fit figures.

    python benchmarks/geometry_throughput.py [--objects 25] [--coacd-objects 4] [--sweep]
                                             [--json out.json]

Prints one table: time per shape for each stage (mean / median / p95, CPU time, one thread),
finger-hull fit (IoU, intrusion into the finger's empty space, shortfall), coacd time per object
and the cache-hit speed-up.  ``--sweep`` adds the pieces-vs-fit-vs-time trade-off of
``finger_hulls`` (K in 8..32, balanced and cover modes).  Objects come from
``f2f_jax.data.builtin_objects`` when it exists, else from seeded trimesh primitives.
"""

from __future__ import annotations

import os

# One core, as the figures claim: BLAS threads would otherwise share the small products.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import trimesh  # noqa: E402

from f2f_jax.config import GeometryConfig  # noqa: E402
from f2f_jax.geometry import coacd_pieces as OH  # noqa: E402
from f2f_jax.geometry import (  # noqa: E402
    finger_from_shape,
    finger_pose,
    imprint_fingers,
    mesh_to_tsdf,
    tsdf_to_mesh,
)
from f2f_jax.geometry import finger_tiling as FH  # noqa: E402
from f2f_jax.geometry import hulls as H  # noqa: E402


def primitive_objects(n: int, seed: int) -> list[trimesh.Trimesh]:
    """Seeded stand-ins for the built-in object set: turned boxes, cylinders, capsules,
    ellipsoids, tori, cones and tubes."""
    rng = np.random.default_rng(seed)
    makers = [
        lambda: trimesh.creation.box(rng.uniform(0.3, 1.0, 3)),
        lambda: trimesh.creation.cylinder(rng.uniform(0.2, 0.5), rng.uniform(0.5, 1.5)),
        lambda: trimesh.creation.capsule(rng.uniform(0.5, 1.5), rng.uniform(0.2, 0.5)),
        lambda: trimesh.creation.icosphere(3).apply_scale(rng.uniform(0.5, 1.0, 3)),
        lambda: trimesh.creation.torus(1.0, rng.uniform(0.2, 0.5)),
        lambda: trimesh.creation.cone(rng.uniform(0.3, 0.6), rng.uniform(0.5, 1.5)),
        lambda: trimesh.creation.annulus(rng.uniform(0.2, 0.4), 0.5, rng.uniform(0.3, 1.0)),
    ]
    out = []
    for i in range(n):
        mesh = makers[i % len(makers)]()
        mesh.apply_transform(trimesh.transformations.random_rotation_matrix(rng.random(3)))
        mesh.metadata["name"] = f"primitive_{i}"
        out.append(mesh)
    return out


def load_objects(n: int, seed: int) -> tuple[list[trimesh.Trimesh], str]:
    try:
        from f2f_jax.data import builtin_objects

        return list(builtin_objects(n, seed=seed)), "f2f_jax.data.builtin_objects"
    except (ImportError, AttributeError):
        return primitive_objects(n, seed), "trimesh primitives (builtin_objects not available)"


def timed(fn, *args, **kwargs):
    """Result and CPU seconds of this process: one thread, so one core's time, and not inflated
    by other work on a shared machine as the wall clock is."""
    start = time.process_time()
    out = fn(*args, **kwargs)
    return out, time.process_time() - start


def stats_ms(seconds: list[float]) -> dict:
    a = np.asarray(seconds) * 1e3
    return dict(mean_ms=float(a.mean()), median_ms=float(np.median(a)),
                p95_ms=float(np.percentile(a, 95)), n=int(a.size))


def sphere_depth(h: H.Hulls, g: GeometryConfig) -> float:
    """Deepest point of the left imprint finger's pieces inside its sphere, at closure (m)."""
    from scipy.optimize import nnls

    pose = finger_pose("left", -g.cube_size, g)
    centre = np.array([0.0, 0.0, pose[2, 3]])
    radius = g.cube_size / 2 - g.voxel_size
    deepest = 0.0
    for piece in h.pieces():
        world = piece.astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
        weights, _ = nnls(np.vstack([world.T, 1e3 * np.ones(len(world))]), np.r_[centre, 1e3])
        deepest = max(deepest, radius - float(np.linalg.norm(weights @ world - centre)))
    return deepest


def finger_figures(fingers, g, **kwargs) -> dict:
    """Time and fit of finger_hulls over a list of finger volumes."""
    FH.finger_hulls(fingers[0], g, **kwargs)  # warm caches and imports
    times, fits = [], []
    for f in fingers:
        h, dt = timed(FH.finger_hulls, f, g, **kwargs)
        times.append(dt)
        fits.append(H.hull_fit(f, h, g))
    iou = np.array([f["iou"] for f in fits])
    intr = np.array([f["max_intrusion_m"] for f in fits]) * 1e3
    short = np.array([f["max_shortfall_m"] for f in fits]) * 1e3
    return dict(time=stats_ms(times), iou_mean=float(iou.mean()), iou_min=float(iou.min()),
                intrusion_mm_mean=float(intr.mean()), intrusion_mm_max=float(intr.max()),
                shortfall_mm_mean=float(short.mean()), shortfall_mm_max=float(short.max()))


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--objects", type=int, default=25, help="objects (2 imprint fingers each)")
    ap.add_argument("--coacd-objects", type=int, default=4, help="objects run through coacd")
    ap.add_argument("--coacd-start", type=int, default=3,
                    help="first of them (the primitives cycle box, cylinder, capsule, ellipsoid, "
                         "torus, cone, tube; convex ones skip coacd)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sweep", action="store_true", help="finger pieces vs fit vs time")
    ap.add_argument("--json", type=str, default=None, help="write the figures here")
    args = ap.parse_args(argv)
    g = GeometryConfig()
    objects, source = load_objects(args.objects, args.seed)
    rows: list[tuple[str, str, str]] = []
    out: dict = dict(objects=len(objects), source=source, seed=args.seed,
                     machine=dict(python=platform.python_version(), cpu=platform.processor(),
                                  cores=os.cpu_count(), threads="OPENBLAS/OMP = 1"))

    # mesh -> TSDF, imprint
    tsdfs, t_tsdf = [], []
    for mesh in objects:
        tsdf, dt = timed(mesh_to_tsdf, mesh, g)
        tsdfs.append(tsdf)
        t_tsdf.append(dt)
    fingers, t_imprint = [], []
    for tsdf in tsdfs:
        pair, dt = timed(imprint_fingers, tsdf, g)
        fingers.extend(pair)
        t_imprint.append(dt)
    out["mesh_to_tsdf"] = stats_ms(t_tsdf)
    out["imprint_pair"] = stats_ms(t_imprint)
    rows.append(("mesh -> TSDF", _ms(out["mesh_to_tsdf"]), f"{len(objects)} objects"))
    rows.append(("imprint fingers (pair)", _ms(out["imprint_pair"]), ""))

    # finger hulls, default layout
    fig = finger_figures(fingers, g)
    out["finger_hulls"] = fig
    rows.append((f"finger_hulls K={g.finger_hulls} V={g.hull_vertices}", _ms(fig["time"]),
                 f"{len(fingers)} imprint fingers, all distinct (nothing remembered)"))
    rows.append(("  fit: IoU mean / min", f"{fig['iou_mean']:.3f} / {fig['iou_min']:.3f}", ""))
    rows.append(("  fit: intrusion mean / max", f"{fig['intrusion_mm_mean']:.2f} / "
                 f"{fig['intrusion_mm_max']:.2f} mm", "into the finger's empty space"))
    rows.append(("  fit: shortfall mean / max", f"{fig['shortfall_mm_mean']:.2f} / "
                 f"{fig['shortfall_mm_max']:.2f} mm", "solid left outside"))
    sphere = imprint_fingers(mesh_to_tsdf(trimesh.creation.icosphere(), g), g)[0]
    for cover in (False, True):
        depth = sphere_depth(FH.finger_hulls(sphere, g, cover=cover), g)
        out[f"sphere_imprint_depth_mm_{'cover' if cover else 'balanced'}"] = depth * 1e3
        rows.append((f"  sphere imprint: depth into sphere{' (cover)' if cover else ''}",
                     f"{depth * 1e3:.2f} mm", "left finger at closure"))

    if args.sweep:
        out["sweep"] = []
        subset = fingers[: min(len(fingers), 16)]
        for cover in (False, True):
            for k in (8, 16, 24, 32):
                f = finger_figures(subset, g, max_pieces=k, cover=cover)
                f.update(max_pieces=k, cover=cover)
                out["sweep"].append(f)
                rows.append((f"sweep K={k:2d} {'cover' if cover else 'balanced':8s}",
                             _ms(f["time"]), f"IoU {f['iou_mean']:.3f}, intrusion mean/max "
                             f"{f['intrusion_mm_mean']:.2f}/{f['intrusion_mm_max']:.2f} mm, "
                             f"shortfall max {f['shortfall_mm_max']:.2f} mm"))

    # fingers cut from other objects: these have undercuts, which the height map fills
    cut = [f for f in (finger_from_shape(t, g) for t in tsdfs) if f is not None]
    if cut:
        fig = finger_figures(cut, g)
        out["finger_hulls_cut"] = fig
        rows.append(("finger_hulls, fingers cut from shapes", _ms(fig["time"]),
                     f"{len(cut)} fingers; IoU {fig['iou_mean']:.3f}, intrusion mean/max "
                     f"{fig['intrusion_mm_mean']:.2f}/{fig['intrusion_mm_max']:.2f} mm "
                     "(undercuts filled)"))

    # objects: coacd once, then the cache
    coacd_rows = []
    with tempfile.TemporaryDirectory() as cache:
        for i in range(args.coacd_start, min(len(tsdfs), args.coacd_start + args.coacd_objects)):
            tsdf = tsdfs[i]
            name = objects[i].metadata.get("name", str(i))
            wall0 = time.perf_counter()
            # no cache (nor the pieces shipped for builtin objects) for the timed first call
            h, dt = timed(OH.object_hulls, tsdf, g, cache_dir=False)
            wall = time.perf_counter() - wall0
            OH.store_object_hulls(tsdf, h, g, cache_dir=cache)
            _, hit = timed(OH.object_hulls, tsdf, g, cache_dir=cache)
            fit = H.hull_fit(tsdf, h, g)
            row = dict(object=name, cpu_seconds=dt, wall_seconds=wall, cache_hit_ms=hit * 1e3,
                       speedup=dt / max(hit, 1e-6), pieces=h.n_pieces, **fit)
            rows.append((f"object_hulls {name}", f"{dt:.2f} s ({wall:.2f} s wall)",
                         f"{h.n_pieces} pieces, IoU {fit['iou']:.3f}, intrusion "
                         f"{fit['max_intrusion_m'] * 1e3:.2f} mm, shortfall "
                         f"{fit['max_shortfall_m'] * 1e3:.2f} mm; cache hit {hit * 1e3:.1f} ms "
                         f"({row['speedup']:.0f}x)"))
            if args.sweep:  # the same coacd pieces in layouts of 4, 8, 16 pieces
                pieces = OH.decompose_mesh(tsdf_to_mesh(tsdf, g), name=name)
                row["sweep"] = []
                for k in (4, 8, 16):
                    hk = OH.pieces_to_hulls(list(pieces), k, g.hull_vertices, g, name)
                    fk = H.hull_fit(tsdf, hk, g)
                    row["sweep"].append(dict(max_pieces=k, coacd_pieces=len(pieces), **fk))
                    rows.append((f"  K={k:2d} (coacd gave {len(pieces)})", "",
                                 f"IoU {fk['iou']:.3f}, intrusion "
                                 f"{fk['max_intrusion_m'] * 1e3:.2f} mm, shortfall "
                                 f"{fk['max_shortfall_m'] * 1e3:.2f} mm"))
            coacd_rows.append(row)
    out["object_hulls"] = coacd_rows

    width = max(len(r[0]) for r in rows) + 2
    print(f"objects: {len(objects)} from {source}; CPU time of one thread")
    print(f"{'stage':{width}s}{'time (mean / median / p95)':34s}notes")
    for name, value, note in rows:
        print(f"{name:{width}s}{value:34s}{note}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=2)
    return out


def _ms(s: dict) -> str:
    return f"{s['mean_ms']:.1f} / {s['median_ms']:.1f} / {s['p95_ms']:.1f} ms"


if __name__ == "__main__":
    main()
