"""Look at one grasp: a PNG strip of the trial phases (``sim.view.render_trials``), so a person can
see why a grasp failed.

    python -m f2f_jax.cli.view --object sphere --fingers imprint --out grasp.png
    python -m f2f_jax.cli.view --object mug.obj --fingers wsg50 --friction 1.0 --out grasp.png

Panels: after settling, after closing, after lifting, after holding (the grasp), then the end of
each push S1..S4 and of each turned grasp R-30..R+30, titled with the trial's outcome.  Drawn
with matplotlib from the simulated poses of the collision pieces (no OpenGL needed).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys

from f2f_jax import config as config_mod  # numpy only: --help stays quick


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--object", default="sphere", help="'sphere', 'box' or a mesh file")
    p.add_argument("--fingers", default="imprint", choices=["imprint", "wsg50"])
    p.add_argument("--friction", type=float, default=None, help="finger-object friction")
    p.add_argument("--config", default="default", choices=sorted(config_mod.CONFIGS))
    p.add_argument("--sim-preset", default="fast", choices=sorted(config_mod.SIM_PRESETS),
                   help="collision geometry and early exits (default: fast)")
    p.add_argument("--out", default="grasp.png")
    args = p.parse_args(argv)

    import trimesh

    from f2f_jax.data.sources import load_mesh
    from f2f_jax.geometry import imprint_fingers, mesh_to_tsdf, wsg50_fingers
    from f2f_jax.geometry.finger_tiling import finger_hulls
    from f2f_jax.geometry.pieces import object_pieces
    from f2f_jax.sim.scene import build_model
    from f2f_jax.sim.view import render_trials

    cfg = config_mod.with_sim_preset(config_mod.get(args.config), args.sim_preset)
    if args.object == "sphere":
        mesh = trimesh.creation.icosphere(subdivisions=3)
    elif args.object == "box":
        mesh = trimesh.creation.box((0.04, 0.03, 0.05))
    else:
        mesh = load_mesh(args.object)
    obj = mesh_to_tsdf(mesh)
    left, right = imprint_fingers(obj) if args.fingers == "imprint" else wsg50_fingers()
    if args.friction is not None:
        cfg = cfg.replace(sim=dataclasses.replace(cfg.sim, finger_friction=args.friction))
    model = build_model(object_pieces(obj, cfg), finger_hulls(left, cfg), finger_hulls(right, cfg),
                        cfg)
    outcome = render_trials(model, cfg, args.out)
    print(f"{args.out}: outcome {dict(zip(config_mod.TRIAL_NAMES, outcome.tolist()))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
