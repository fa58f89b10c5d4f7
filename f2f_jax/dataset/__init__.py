"""The grasp dataset: the append-only store of simulated (object, left, right) outcomes and the
pretraining pairs that fill it.  It sits above ``sim`` (it runs the simulator) and below ``train``
(which reads it); object sources live below ``sim`` in ``f2f_jax.data``."""

from f2f_jax.dataset.pretraining import (
    KINDS,
    PERTURBED,
    build_grasp_dataset,
    perturbed_finger,
    perturbed_pairs,
    pretraining_pairs,
)
from f2f_jax.dataset.store import GraspStore

__all__ = ["KINDS", "PERTURBED", "GraspStore", "build_grasp_dataset", "perturbed_finger", "perturbed_pairs",
           "pretraining_pairs"]
