"""The command-line tools' XLA settings: the thread pool's size, not the machine, decides the numbers."""

import json
import os
import subprocess
import sys

import pytest

from f2f_jax.cli import cotrain, reproducible

# One convolution's kernel gradient: XLA's CPU pool splits its sums by thread count.
_SCRIPT = r"""
import hashlib, json, os, sys
from f2f_jax.cli.reproducible import reproducible_xla
mode = sys.argv[1]
allowed = sorted(os.sched_getaffinity(0))
if mode == "narrow":  # a 1-CPU machine, with the same XLA flags as the others (AVX2 code)
    os.sched_setaffinity(0, allowed[:1])
    reproducible_xla(0)
else:
    reproducible_xla(int(mode))
import jax, jax.numpy as jnp, numpy as np
x = jnp.asarray(np.random.default_rng(0).normal(size=(8, 24, 24, 24, 4)).astype(np.float32))
k = jnp.asarray(np.random.default_rng(1).normal(size=(3, 3, 3, 4, 4)).astype(np.float32))
conv = lambda k: jax.lax.conv_general_dilated(x, k, (1, 1, 1), "VALID",
                                              dimension_numbers=("NDHWC", "DHWIO", "NDHWC"))
g = np.asarray(jax.jit(jax.grad(lambda k: jnp.sum(jnp.tanh(conv(k)) ** 2)))(k))
print(json.dumps(dict(hash=hashlib.sha1(g.tobytes()).hexdigest(),
                      cpus_after=len(os.sched_getaffinity(0)), flags=os.environ.get("XLA_FLAGS", ""))))
"""


def _run(mode: str) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    out = subprocess.run([sys.executable, "-c", _SCRIPT, mode], capture_output=True, text=True,
                         env=env, timeout=300, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity") or len(os.sched_getaffinity(0)) < 2,
                    reason="needs CPU affinity and at least 2 CPUs")
def test_pool_size_not_cpus_decides_the_numbers():
    one_cpu = _run("narrow")  # what a 1-core machine computes
    every_cpu = _run("0")  # the pool left at every CPU
    if every_cpu["hash"] == one_cpu["hash"]:
        pytest.skip("this convolution sums alike with 1 and all threads here: nothing to tell apart")
    pinned = _run("1")  # a 1-thread pool on this multi-core machine
    assert pinned["hash"] == one_cpu["hash"]
    # and the rest of the process (the simulator's threads) got every CPU back
    assert pinned["cpus_after"] == len(os.sched_getaffinity(0))
    # the default pool (2 threads) on this machine is the 2-core reference's
    if len(os.sched_getaffinity(0)) == reproducible.REFERENCE_THREADS:
        assert _run(str(reproducible.REFERENCE_THREADS))["hash"] == every_cpu["hash"]


def test_flags_added_but_a_users_value_wins(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_max_isa=AVX")
    reproducible._add_flag(reproducible._MAX_ISA)
    reproducible._add_flag(reproducible._GPU_DETERMINISTIC)
    flags = os.environ["XLA_FLAGS"].split()
    assert "--xla_cpu_max_isa=AVX" in flags and reproducible._MAX_ISA not in flags
    assert reproducible._GPU_DETERMINISTIC in flags


def test_bad_thread_counts_are_refused(capsys):
    with pytest.raises(ValueError, match=">= 0"):
        reproducible.reproducible_xla(-1)
    assert cotrain.main(["--xla-threads", "-2", "--run-dir", "unused"]) == 2
    assert "--xla-threads must be >= 0" in capsys.readouterr().err
