"""The PyBullet peer timed on imprint triples: evaluations per second of the original Fit2Form
protocol (``f2f_jax.bench.pybullet_peer``, whose docstring says what it keeps and where it
differs).  Needs the ``pybullet`` extra."""

from __future__ import annotations

import argparse
import importlib.metadata
import platform

import trimesh

from f2f_jax.bench.pybullet_runs import convex_object_hulls, evaluate_original
from f2f_jax.config import TRIAL_NAMES, default
from f2f_jax.geometry import finger_hulls, imprint_fingers, mesh_to_tsdf, object_hulls


def _demo_shapes() -> dict[str, trimesh.Trimesh]:
    """Convex shapes that rest still on the floor (each is stretched to fill the cube)."""
    return {
        "sphere": trimesh.creation.icosphere(subdivisions=3, radius=0.03),
        "box": trimesh.creation.box(extents=(0.06, 0.06, 0.06)),
        "cylinder": trimesh.creation.cylinder(radius=0.03, height=0.06, sections=32),
        "cone": trimesh.creation.cone(radius=0.03, height=0.06, sections=32),
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=1,
                        help="evaluate each imprint triple this many times")
    parser.add_argument("--objects", choices=("convex", "coacd"), default="convex",
                        help="object pieces: one hull (convex demo shapes) or coacd_pieces.object_hulls")
    args = parser.parse_args(argv)
    cfg = default()
    objects, lefts, rights, names = [], [], [], []
    for name, mesh in _demo_shapes().items():
        tsdf = mesh_to_tsdf(mesh, cfg.geometry, name=name)
        left, right = imprint_fingers(tsdf, cfg.geometry)
        if args.objects == "coacd":
            obj = object_hulls(tsdf, cfg.geometry)
        else:
            obj = convex_object_hulls(tsdf, cfg)
        left_hulls = finger_hulls(left, cfg.geometry)
        right_hulls = finger_hulls(right, cfg.geometry)
        objects += [obj] * args.repeat
        lefts += [left_hulls] * args.repeat
        rights += [right_hulls] * args.repeat
        names += [name] * args.repeat
    outcomes, stats = evaluate_original(objects, lefts, rights, cfg=cfg)
    print(f"pybullet {importlib.metadata.version('pybullet')} | DIRECT client, one process "
          f"(one core) | {platform.processor() or platform.machine()} | dt 1/240 | world x10")
    print("triple      pieces(o/l/r)  steps   " + " ".join(f"{t:>4}" for t in TRIAL_NAMES))
    for i, name in enumerate(names):
        pieces = f"{objects[i].n_pieces}/{lefts[i].n_pieces}/{rights[i].n_pieces}"
        print(f"{name:<10}  {pieces:<13}  {stats['steps_per_evaluation'][i]:>6}  "
              + " ".join(f"{v:>4}" for v in outcomes[i]))
    print(f"{stats['evaluations']} evaluations, {stats['steps']} steps in "
          f"{stats['seconds']:.1f} s: "
          f"{stats['evaluations_per_second']:.3f} evaluations/s, "
          f"{stats['steps_per_second']:.0f} steps/s, "
          f"{stats['steps'] / stats['evaluations']:.0f} steps/evaluation, "
          f"{stats['build_seconds']:.2f} s building bodies, {stats['unstable']} unstable")
    for label, mask in (("grasp held, all 11 trials run", outcomes[:, 0] == 1),
                        ("grasp failed, one attempt", outcomes[:, 0] == 0)):
        if mask.any():
            steps = stats["steps_per_evaluation"][mask].sum()
            secs = stats["seconds_per_evaluation"][mask].sum()
            print(f"{label}: {mask.sum()} evaluations, {steps / mask.sum():.0f} steps each, "
                  f"{mask.sum() / secs:.3f} evaluations/s, {steps / secs:.0f} steps/s")


if __name__ == "__main__":
    main()
