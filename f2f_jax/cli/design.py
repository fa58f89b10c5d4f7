"""The ``f2f-design`` command.

``f2f-design MESH --out DIR``: design a finger pair for one mesh and write

    DIR/left.stl, DIR/right.stl   fingers with their mount plates, watertight, millimetres; the
                                  STL header names the object and how it was scaled
    DIR/design.png                the object held by the fingers, three views, outcome boxes
    DIR/scores.json               predicted (and simulated) outcome per trial name, feasibility,
                                  the checkpoint, the input file and the object's placement
                                  (scale mode, factor, size in mm), pool candidates left out;
                                  with --tolerance MM the trials passed by each moved copy

The defaults are ``f2f_jax.design``'s (the verified pool: ``designer.DEFAULT_CANDIDATES``
candidates and the object's imprints, simulated); with no --run-dir and no $F2F_RUN_DIR the
weights shipped with the package design.  Everything is written into a hidden sibling directory first and renamed to DIR at the end, so a
failure leaves nothing behind.  Errors (missing or unreadable mesh, no checkpoint, a volume that
cannot be designed for) print one line to stderr and exit with status 2.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import sys
import uuid
import warnings
from pathlib import Path

from f2f_jax.cli import reproducible, sim_options  # no JAX until reproducible_xla runs
# numpy only, --help stays quick; design()'s defaults and geometry's scale modes live there
from f2f_jax.config import BACKENDS, DEFAULT_CANDIDATES, DEFAULT_VERIFY, SCALES, UNITS

EXIT_ERROR = 2


def _design_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="f2f-design",
        description="Design a pair of parallel-jaw gripper fingers for an object mesh; writes "
                    "left.stl, right.stl, design.png and scores.json.")
    p.add_argument("mesh", type=Path, help="object mesh (.obj, .stl, .ply, .glb, .gltf, .off)")
    p.add_argument("--scale", choices=SCALES, default=None,
                   help="how the mesh is placed in the 6 cm design cube: 'stretch' each axis to "
                        "fill it (the paper's convention: the fingers fit a stretched object), "
                        "'fit' one factor for all axes (shape kept; the factor is reported), "
                        "'real' the mesh's own size (needs --units; at most 57 mm per axis). "
                        "Default: as the nets' training objects were placed (stretch)")
    p.add_argument("--units", choices=list(UNITS), default=None,
                   help="the mesh's units, for --scale real (implies it when --scale is not given)")
    p.add_argument("--out", type=Path, required=True, help="output directory (must not exist or be "
                   "empty, unless --force)")
    p.add_argument("--run-dir", type=Path, default=None, help="co-training run whose newest "
                   "checkpoint designs (default: $F2F_RUN_DIR, else the weights shipped with "
                   "the package)")
    p.add_argument("--candidates", type=int, default=DEFAULT_CANDIDATES,
                   help=f"designs sampled (latent noise) and ranked; default {DEFAULT_CANDIDATES}")
    p.add_argument("--verify", action=argparse.BooleanOptionalAction, default=DEFAULT_VERIFY,
                   help="simulate the feasible candidates and rank by simulated outcome (default on)")
    p.add_argument("--imprint", action=argparse.BooleanOptionalAction, default=None,
                   help="also rank the object's imprint pair and two variants of it, so a verified "
                        "pick never passes fewer trials than imprints (default: with --verify)")
    p.add_argument("--tolerance", type=float, default=0.0, metavar="MM",
                   help="with --verify, also simulate --copies copies of every candidate with both "
                        "fingers moved by a smooth random field of this standard deviation in mm (a "
                        "printer's error: 0.3 moves the fingers' surface ~0.15 mm on average; the "
                        "same fields for every candidate) and rank by the mean over them; costs "
                        "1 + copies times the simulation "
                        "(default 0: off)")
    p.add_argument("--copies", type=int, default=3, help="moved copies per candidate with "
                   "--tolerance (default 3)")
    p.add_argument("--seed", type=int, default=0, help="seed of the candidates' latent noise (and "
                   "of the moved copies' fields)")
    p.add_argument("--backend", choices=list(BACKENDS), default="mujoco",
                   help="simulator for --verify (default mujoco, on CPU threads)")
    sim_options.add_cli_arguments(p, what="--verify simulates")  # no simulator imported
    p.add_argument("--force", action="store_true", help="replace a non-empty --out directory")
    reproducible.add_cli_argument(p)
    return p


def _load_trained_nets(run_dir):
    from f2f_jax.designer import _load_trained_nets  # run_dir, $F2F_RUN_DIR or shipped weights

    return _load_trained_nets(run_dir)


def _fail(message: str) -> int:
    print(f"f2f-design: error: {message}", file=sys.stderr)
    return EXIT_ERROR


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``f2f-design``; returns the exit status (0 ok, 2 error)."""
    parser = _design_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, or a usage error already printed by argparse
        return int(exc.code or 0)
    if args.candidates < 1:
        return _fail(f"--candidates must be >= 1, got {args.candidates}")
    if not args.tolerance >= 0 or args.tolerance == float("inf"):
        return _fail(f"--tolerance must be a finite standard deviation >= 0 (mm), got {args.tolerance}")
    if args.tolerance > 0 and not args.verify:
        return _fail("--tolerance simulates moved copies of the candidates: it needs --verify")
    if args.copies < 1:
        return _fail(f"--copies must be >= 1, got {args.copies}")
    if args.xla_threads < 0:
        return _fail(f"--xla-threads must be >= 0, got {args.xla_threads}")
    if args.verify and (problem := sim_options.backend_problem(args, args.backend)):
        return _fail(problem)
    if args.units is not None and args.scale is None:
        args.scale = "real"
    if args.scale == "real" and args.units is None:
        return _fail("--scale real needs the mesh's units: --units m, cm, mm or in")
    if args.units is not None and args.scale != "real":
        return _fail(f"--units reads the mesh at its real size; --scale {args.scale} sizes it to "
                     "the design cube (drop --units, or use --scale real)")
    out: Path = args.out
    if out.exists() and not out.is_dir():
        return _fail(f"--out {out} exists and is not a directory")
    if out.is_dir() and any(out.iterdir()) and not args.force:
        return _fail(f"--out {out} exists and is not empty; choose another directory or pass --force")

    from f2f_jax.errors import F2FError

    try:
        return _run_design(args)
    except FileNotFoundError as exc:
        return _fail(str(exc))
    except F2FError as exc:  # MeshError, VolumeError, CheckpointError, ...
        return _fail(str(exc))
    except OSError as exc:  # writing the outputs
        return _fail(f"{type(exc).__name__}: {exc}")


def _run_design(args) -> int:
    # Heavy imports (JAX, MuJoCo, trimesh) only after the cheap checks of main: a typo in a
    # path fails in a blink, and ``f2f-design --help`` answers at once.
    from f2f_jax.data.sources import load_mesh

    mesh = load_mesh(args.mesh)
    reproducible.reproducible_xla(args.xla_threads)  # before JAX starts: the same designs everywhere
    nets = _load_trained_nets(args.run_dir)

    import jax

    from f2f_jax import designer as design_module
    from f2f_jax.config import TRIAL_NAMES
    from f2f_jax.geometry import object_volume

    obj, placement = object_volume(mesh, nets.config.geometry, scale=args.scale,
                                   units=args.units, name=str(args.mesh))
    executor = sim_options.executor_from_cli(args) if args.verify else "threads"
    with warnings.catch_warnings():
        # the one-line error below says it; the warning would repeat it
        warnings.simplefilter("ignore", design_module.InfeasibleDesignWarning)
        pair = design_module.design(obj, params=nets, key=jax.random.key(args.seed),
                                    candidates=args.candidates, verify=args.verify,
                                    backend=args.backend, imprint=args.imprint,
                                    executor=executor, tolerance=args.tolerance, copies=args.copies)
    pair = dataclasses.replace(pair, placement=placement)
    print(f"f2f-design: {placement.describe()}", file=sys.stderr)
    if not pair.feasible:
        return _fail(f"no feasible finger pair among {pair.n_candidates} candidates for {args.mesh} "
                     f"(best predicted mean {pair.predicted_mean:.2f}); try more --candidates or "
                     "a better-trained --run-dir")

    out: Path = args.out
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.tmp-{uuid.uuid4().hex[:8]}"
    tmp.mkdir()
    try:
        pair.export_stl(tmp, name=Path(args.mesh).name)
        pair.render(tmp / "design.png", title=f"{Path(args.mesh).name}: {pair._headline()}")
        scores = pair.scores()
        scores.pop("source")  # recorded as "checkpoint"
        scores = dict(input=str(Path(args.mesh).resolve()), checkpoint=nets.source,
                      trial_names=list(TRIAL_NAMES), verified=bool(args.verify),
                      backend=args.backend if args.verify else None, seed=args.seed,
                      units="stl in millimetres, mount plate at z <= 0", **scores)
        (tmp / "scores.json").write_text(json.dumps(scores, indent=2) + "\n")
        _replace_dir(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    print(pair)
    print(f"wrote {out}/left.stl, right.stl, design.png, scores.json")
    return 0


def _replace_dir(tmp: Path, out: Path) -> None:
    """Rename the finished ``tmp`` onto ``out``; an existing ``out`` (checked empty, or --force)
    is moved aside first and removed only after the new one is in place."""
    if not out.exists():
        os.rename(tmp, out)
        return
    old = out.parent / f".{out.name}.old-{uuid.uuid4().hex[:8]}"
    os.rename(out, old)
    try:
        os.rename(tmp, out)
    except BaseException:
        os.rename(old, out)
        raise
    shutil.rmtree(old, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
