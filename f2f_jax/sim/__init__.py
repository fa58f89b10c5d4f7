"""Grasp simulation: the WSG50-like scene, the 11 trials and the backends that run them.

``evaluate(objects, lefts, rights, backend="mujoco")`` is the entry point: [N, 40, 40, 40] TSDF
triples in, [N, 11] uint8 outcomes out (``TRIAL_NAMES`` order); ``evaluate_with_info`` also returns
the call's ``EvaluationInfo`` (steps, unstable trials, infeasible and failed candidates).
"""

from f2f_jax.config import TRIAL_NAMES
from f2f_jax.sim.mujoco_cpu import (
    BACKENDS,
    EvaluationInfo,
    evaluate,
    evaluate_with_info,
)
from f2f_jax.sim.opening import JawOpener
from f2f_jax.sim.protocol import GraspRunner, TrialResult, run_trials
from f2f_jax.sim.scene import (
    GRIPPER_XML,
    SceneIds,
    SceneLayout,
    build_model,
    describe_layout,
    finger_object_contacts,
    scene_ids,
)

__all__ = [
    "BACKENDS", "GRIPPER_XML", "EvaluationInfo", "GraspRunner", "JawOpener", "SceneIds", "SceneLayout",
    "TRIAL_NAMES", "TrialResult", "build_model", "describe_layout", "evaluate",
    "evaluate_with_info", "finger_object_contacts", "run_trials", "scene_ids",
]
