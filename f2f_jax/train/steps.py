"""Jitted training steps, one factory per stage.

Every step is ``step(state, batch..., key) -> (state, metrics)``: a pure function compiled once per
batch shape, with the incoming state donated (its buffers are reused for the new one) and no host
synchronisation inside; callers fetch the metrics when they log.  Batches are sharded over the
local devices along their first axis (``shard``), parameters replicated, so one call uses one CPU,
one GPU or eight GPUs unchanged.
"""

from __future__ import annotations

import functools
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from f2f_jax.config import Config
from f2f_jax.geometry import solid_iou
from f2f_jax.nets import FitnessNet, ShapeAutoEncoder, fitness_input, generator_module
from f2f_jax.nets.inference import generate
from f2f_jax.train.losses import fitness_loss, generator_loss, reconstruction_mse, vae_loss
from f2f_jax.train.state import TrainState, generator_optimizer, optimizer

Step = Callable[..., tuple[TrainState, dict[str, jax.Array]]]


# -- data parallelism ---------------------------------------------------------------------------
@functools.lru_cache(maxsize=None)
def _mesh() -> Mesh:
    return Mesh(np.array(jax.local_devices()), ("data",))


def shard(*arrays):
    """Put host arrays on the local devices, split along axis 0 when it divides evenly.

    With one device (a CPU, one GPU) this is a plain transfer.  Returns one array or a tuple.
    """
    mesh = _mesh()
    n_dev = mesh.devices.size
    out = []
    for a in arrays:
        a = np.asarray(a)
        if n_dev > 1 and a.ndim and a.shape[0] % n_dev == 0:
            spec = PartitionSpec("data")
        else:
            spec = PartitionSpec()
        out.append(jax.device_put(a, NamedSharding(mesh, spec)))
    return out[0] if len(out) == 1 else tuple(out)


def replicate(tree):
    """Place a pytree (a train state, variables) on every local device, replicated: the layout
    the steps return, so the first and later calls share one compiled program."""
    return jax.device_put(tree, NamedSharding(_mesh(), PartitionSpec()))


def _apply_grads(opt: optax.GradientTransformation, state: TrainState, grads, batch_stats) -> TrainState:
    updates, opt_state = opt.update(grads, state.opt_state, state.params)
    return state.replace(params=optax.apply_updates(state.params, updates), batch_stats=batch_stats,
                         opt_state=opt_state, step=state.step + 1)


def _merge_stats(old: Any, new: Any) -> Any:
    """Replace the subtrees of ``old`` that ``new`` updated (frozen submodules keep theirs)."""
    if not isinstance(new, dict):
        return new
    out = dict(old)
    for k, v in new.items():
        out[k] = _merge_stats(old.get(k, {}), v) if isinstance(v, dict) else v
    return out


# -- stage 1: shape auto-encoder -----------------------------------------------------------------
@functools.lru_cache(maxsize=None)
def ae_step(cfg: Config) -> Step:
    """``step(state, volumes [B,40,40,40], key) -> (state, {"loss", "mse"})`` for the shape VAE."""
    model = ShapeAutoEncoder(cfg.net)
    opt = optimizer(cfg.train)
    kl_weight = cfg.train.kl_weight

    def loss_fn(params, batch_stats, x, key):
        (recon, mu, logvar), upd = model.apply({"params": params, "batch_stats": batch_stats}, x,
                                               train=True, key=key, mutable=["batch_stats"])
        loss = vae_loss(recon, x, mu, logvar, kl_weight)
        return loss, (upd["batch_stats"], reconstruction_mse(recon, x))

    @functools.partial(jax.jit, donate_argnums=0)
    def step(state: TrainState, x, key):
        (loss, (stats, mse)), grads = jax.value_and_grad(loss_fn, has_aux=True)(
            state.params, state.batch_stats, x, key)
        return _apply_grads(opt, state, grads, stats), {"loss": loss, "mse": mse}

    return step


@functools.lru_cache(maxsize=None)
def ae_reconstruct(cfg: Config) -> Callable:
    """``f(variables, volumes) -> recon`` in evaluation mode (posterior mean, running stats)."""
    model = ShapeAutoEncoder(cfg.net)

    @jax.jit
    def f(variables, x):
        return model.apply(variables, x, train=False)[0]

    return f


# -- stage 2: fitness net ------------------------------------------------------------------------
@functools.lru_cache(maxsize=None)
def fn_step(cfg: Config) -> Step:
    """``step(state, objects, lefts, rights, outcomes [B,11]) -> (state, {"loss"})`` (BCE)."""
    model = FitnessNet(cfg.net)
    opt = optimizer(cfg.train)

    def loss_fn(params, batch_stats, obj, left, right, y):
        logits, upd = model.apply({"params": params, "batch_stats": batch_stats},
                                  fitness_input(obj, left, right), train=True, mutable=["batch_stats"])
        return fitness_loss(logits, y), upd["batch_stats"]

    @functools.partial(jax.jit, donate_argnums=0)
    def step(state: TrainState, obj, left, right, y):
        (loss, stats), grads = jax.value_and_grad(loss_fn, has_aux=True)(
            state.params, state.batch_stats, obj, left, right, y)
        return _apply_grads(opt, state, grads, stats), {"loss": loss}

    return step


@functools.lru_cache(maxsize=None)
def fn_eval(cfg: Config) -> Callable:
    """``f(variables, objects, lefts, rights, outcomes) -> (bce, probabilities [B,11])`` (eval mode)."""
    model = FitnessNet(cfg.net)

    @jax.jit
    def f(variables, obj, left, right, y):
        logits = model.apply(variables, fitness_input(obj, left, right), train=False)
        return fitness_loss(logits, y), jax.nn.sigmoid(logits)

    return f


# -- stage 3: generator, pretrained on imprint fingers --------------------------------------------
def _latents(model, variables, obj):
    """The generator's finger codes in training mode, and its updated BatchNorm statistics (none
    for a generator without BatchNorm)."""
    (zl, zr), upd = model.apply(variables, obj, train=True, method=type(model).latents,
                                mutable=["batch_stats"])
    return zl, zr, upd.get("batch_stats", {})


@functools.lru_cache(maxsize=None)
def gn_imprint_step(cfg: Config) -> Step:
    """``step(state, objects, imprint_lefts, imprint_rights) -> (state, {"loss"})``: the generator's
    distance to the imprint fingers (``imprint_distance``: the latent MSE to the frozen encoder's
    latents of the imprints, or the height maps' L1 for ``net.generator = "heights"``)."""
    model = generator_module(cfg.net)

    def loss_fn(params, batch_stats, obj, left, right):
        variables = {"params": params, "batch_stats": batch_stats}
        zl, zr, stats = _latents(model, variables, obj)
        dist = model.apply(variables, zl, zr, left, right, method=type(model).imprint_distance)
        return dist, stats

    opt = generator_optimizer(cfg)

    @functools.partial(jax.jit, donate_argnums=0)
    def step(state: TrainState, obj, left, right):
        (loss, stats), grads = jax.value_and_grad(loss_fn, has_aux=True)(
            state.params, state.batch_stats, obj, left, right)
        return _apply_grads(opt, state, grads, _merge_stats(state.batch_stats, stats)), {"loss": loss}

    return step


# -- stage 4: generator against the fitness net ---------------------------------------------------
@functools.lru_cache(maxsize=None)
def gn_fitness_step(cfg: Config, objectives: str | None = None) -> Step:
    """The generator against a frozen fitness net.

    ``step(state, fitness_variables, objects) -> (state, {"loss", "fitness" [11]})`` with
    loss = -mean sigmoid F over the selected outputs (``objectives``, default cfg.train's).
    """
    model = generator_module(cfg.net)
    fitness = FitnessNet(cfg.net)
    objectives = objectives or cfg.train.objectives

    def loss_fn(params, batch_stats, fit_vars, obj):
        variables = {"params": params, "batch_stats": batch_stats}
        zl, zr, stats = _latents(model, variables, obj)
        left, right = model.apply(variables, zl, zr, method=type(model).decode)
        logits = fitness.apply(fit_vars, fitness_input(obj, left, right), train=False)
        aux = {"fitness": jnp.mean(jax.nn.sigmoid(logits), 0)}
        return generator_loss(logits, objectives), (stats, aux)

    opt = generator_optimizer(cfg)

    @functools.partial(jax.jit, donate_argnums=0)
    def step(state: TrainState, fit_vars, obj):
        (loss, (stats, aux)), grads = jax.value_and_grad(loss_fn, has_aux=True)(
            state.params, state.batch_stats, fit_vars, obj)
        new = _apply_grads(opt, state, grads, _merge_stats(state.batch_stats, stats))
        return new, {"loss": loss, **aux}

    return step


def generate_batched(net_cfg, variables: dict, objects: np.ndarray,
                     batch: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """Generator output (evaluation mode) for any number of objects, ``batch`` at a time; when
    there are several chunks the last is padded so every call has one compiled shape.

    objects: [N, 40, 40, 40] float32. Returns lefts, rights: [N, 40, 40, 40] float32 numpy.
    """
    lefts, rights = [], []
    for s in range(0, len(objects), batch):
        chunk = objects[s:s + batch]
        pad = batch - len(chunk) if len(objects) > batch else 0
        x = np.concatenate([chunk, np.repeat(chunk[-1:], pad, 0)]) if pad else chunk
        left, right = generate(net_cfg, variables, shard(np.asarray(x, np.float32)))
        lefts.append(np.asarray(left, np.float32)[: len(chunk)])
        rights.append(np.asarray(right, np.float32)[: len(chunk)])
    return np.concatenate(lefts), np.concatenate(rights)


def reconstruction_iou(cfg: Config, ae_variables: dict, volumes: np.ndarray) -> float:
    """Mean IoU of the solid voxels (TSDF < 0) of volumes [N, R, R, R] and the shape VAE's
    reconstructions of them, ``cfg.train.ae_batch_size`` volumes per call."""
    f, bs = ae_reconstruct(cfg), cfg.train.ae_batch_size
    recon = np.concatenate([np.asarray(f(ae_variables, shard(volumes[s:s + bs])))
                            for s in range(0, len(volumes), bs)])
    return float(np.mean(solid_iou(volumes, recon)))
