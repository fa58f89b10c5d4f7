"""The same numbers on one machine whatever its core count: XLA settings the command-line tools
apply before JAX starts.

XLA on the CPU splits a convolution's or matrix product's sums over its thread pool, and JAX sizes
that pool by the CPUs the process may run on.  Another split adds the same terms in another order,
so a run on 8 cores and a run on 2 differ in the last bits after the first training step; training
and the simulator's thresholds then pass the difference on into other designs and other tables.
(Measured: three VAE steps of the default config give other parameters with 1 thread than with
2; ``tests/test_reproducible.py`` checks it on one convolution.)  The same goes for the CPU's
vector width: code generated for AVX instead of this machine's AVX2 gives other losses.

``reproducible_xla`` therefore, before JAX starts:

* sizes XLA's CPU thread pool to ``threads`` (default 2, the machine of the README's figures) by
  narrowing the process to that many CPUs while the CPU client is made, then widening it again:
  the pool keeps its size, and everything started afterwards (the simulator's threads, Ray)
  may use every CPU;
* on x86-64, caps XLA's generated code at AVX2 (``--xla_cpu_max_isa=AVX2``), so an AVX-512
  machine computes as an AVX2 one (on an AVX2 machine the flag changes nothing: same bits);
* asks for deterministic GPU kernels (no atomics in reductions), so a resumed run ends where an
  uninterrupted one ends.

So a run's figures do not depend on how many cores its machine has.  They still depend on the
machine: the default pretraining at seed 2 on two 2-core AMD EPYC machines (one of
them a Zen 3 without AVX-512) gave auto-encoder held-out IoUs of 0.486 and 0.491, most
likely because the CPU kernels block their sums by the cache sizes they find; no flag here fixes
that, so another machine's run is to be compared with the README's spread over seeds.  Costs:
training uses 2 of a bigger machine's cores (``--xla-threads 0`` lifts that, and the figures then
differ in the way described above).
Where the process cannot be narrowed (macOS) or JAX has already started in this process (a
notebook, a test calling ``main``), the pool stays as it is.
"""

from __future__ import annotations

import os
import platform
import sys
import warnings

REFERENCE_THREADS = 2  # XLA CPU threads of the README's and RESULTS.md's runs
_GPU_DETERMINISTIC = "--xla_gpu_deterministic_ops=true"
_MAX_ISA = "--xla_cpu_max_isa=AVX2"


def _add_flag(flag: str) -> None:
    name = flag.split("=")[0]
    current = os.environ.get("XLA_FLAGS", "")
    if name not in current:  # a value the user set wins
        os.environ["XLA_FLAGS"] = f"{current} {flag}".strip()


def _jax_started() -> bool:
    if "jax" not in sys.modules:
        return False
    try:
        from jax._src import xla_bridge

        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):  # a JAX without this (private) query: assume started
        return True


def reproducible_xla(threads: int | None = REFERENCE_THREADS) -> int | None:
    """Apply the module's settings; call before anything in the process uses JAX.

    threads: XLA CPU threads (>= 1), or 0 / None to leave the pool at every CPU.  Returns the
    pool size set, or None when it was left alone (not asked, JAX already started, or no CPU
    affinity on this platform).  Warns when the machine has fewer CPUs than ``threads``.
    """
    if threads is not None and threads < 0:
        raise ValueError(f"XLA threads must be >= 0, got {threads}")
    if _jax_started():
        return None  # flags and pool are fixed once the backends exist
    _add_flag(_GPU_DETERMINISTIC)
    if platform.machine().lower() in ("x86_64", "amd64"):
        _add_flag(_MAX_ISA)
    if not threads or not hasattr(os, "sched_setaffinity"):
        return None
    allowed = os.sched_getaffinity(0)
    if len(allowed) < threads:
        warnings.warn(f"XLA was asked for {threads} CPU threads but this process may use "
                      f"{len(allowed)} CPUs: training numbers will differ from a {threads}-thread "
                      "run's (RESULTS.md's figures were made with 2)", RuntimeWarning, stacklevel=2)
        threads = len(allowed)
    import jax

    os.sched_setaffinity(0, sorted(allowed)[:threads])
    try:
        jax.devices("cpu")  # the CPU client is made now, its thread pool sized by the CPUs above
    finally:
        os.sched_setaffinity(0, allowed)
    return threads


def add_cli_argument(parser) -> None:
    parser.add_argument("--xla-threads", type=int, default=REFERENCE_THREADS, metavar="N",
                        help=f"XLA CPU threads for the nets (default {REFERENCE_THREADS}: the same "
                             "numbers on any core count of one machine; "
                             "0: every CPU, faster training on big machines, other numbers)")
