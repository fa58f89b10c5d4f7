"""The command lines' simulation flags: ``--executor {threads,ray}`` and ``--ray-address ADDR``.

No JAX and no simulator at import (``config`` alone): ``f2f-design --help`` stays quick.  The
executor names and which backends each runs are ``config.EXECUTORS`` / ``executor_problem``;
``executor_from_cli`` imports ``sim.ray_executor`` only for ``--executor ray``.
"""

from __future__ import annotations

import argparse

from f2f_jax.config import EXECUTORS, executor_problem


def add_cli_arguments(parser: argparse.ArgumentParser, *,
                      what: str = "simulation runs") -> None:
    """``--executor {threads,ray}`` and ``--ray-address ADDR`` on an argparse parser.
    what: the help's subject ("where <what>: ...")."""
    parser.add_argument("--executor", default="threads", choices=list(EXECUTORS),
                        help=f"where {what}: threads of this machine (default) or Ray tasks on a "
                             "cluster (needs the ray extra: pip install -e \".[ray]\")")
    parser.add_argument("--ray-address", default=None, metavar="ADDR",
                        help="--executor ray: the cluster's head, 'auto' or host:port (default: a "
                             "cluster started on this machine by `ray start`, else a local one)")


def backend_problem(args, backend: str | None) -> str | None:
    """``config.executor_problem`` for the parsed --executor and a --backend (None: not given,
    nothing to refuse), in the flags' words; None when they go together."""
    if backend is None:
        return None
    problem = executor_problem(args.executor, backend)
    if problem is None:
        return None
    return f"{problem}; drop --backend {backend}"


def executor_from_cli(args) -> str:
    """The parsed --executor; for "ray", joins (or starts) the cluster now, so a missing extra
    or a wrong address is said before any work (F2FError / MissingExtraError), and prints what it
    joined.  --ray-address without --executor ray exits (SystemExit)."""
    if args.executor == "ray":
        from f2f_jax.sim import ray_executor  # the simulator (not Ray yet) only now

        ray = ray_executor.connect(args.ray_address)
        nodes = sum(1 for node in ray.nodes() if node.get("Alive"))
        print(f"ray: {ray_executor.cluster_cpus(ray)} CPUs on {nodes} node(s), cluster "
              f"{ray.get_runtime_context().gcs_address}", flush=True)
    elif args.ray_address is not None:
        raise SystemExit("--ray-address needs --executor ray")
    return args.executor
