"""Design fingers for an object: the public face of a trained run.

    pair = f2f_jax.design(obj_tsdf)                       # the verified pool, shipped weights
    pair = f2f_jax.design("part.stl", scale="real", units="mm")   # a mesh at its real size
    pair = f2f_jax.design(obj_tsdf, verify=False, candidates=1)   # the generator alone: fast
    pair.export_stl("out/"); pair.render("out/design.png"); print(pair)

The defaults (``DEFAULT_CANDIDATES`` = 16 and ``DEFAULT_VERIFY``, shared with ``f2f-design``) are
the verified pool: 16 generated candidates and the object's imprints, simulated, best simulated
first.  ``verify=False`` ranks by the fitness net alone and simulates nothing.

How a design is chosen, per object:

1. The generator maps the object to two finger latents; candidate 0 decodes them as they are, the
   other ``candidates - 1`` add Gaussian noise (standard deviation ``noise``, default
   ``nets.inference.LATENT_NOISE`` = 0.2, i.e. 0.1 of the latents' [-1, 1] range, clipped back
   into it) to each finger latent before the frozen decoder.  A height-map generator
   (``net.generator = "heights"``) writes the two fingers' height maps instead, and its candidates
   add a smooth random field to each (``nets.inference.code_noise``).  All objects and all
   candidates go through the generator in one jitted call.
2. Each finger keeps its largest face-connected component and is checked for feasibility
   (``geometry.postprocess``), as in co-training.
3. The fitness net predicts the 11 outcome probabilities of every candidate (one jitted call).
4. With ``verify=True`` the feasible candidates of all objects are simulated in one
   ``sim.evaluate`` call.  The pool then also holds the object's imprint pair and two variants
   of it (``IMPRINT_VARIANTS``: the imprints of the object grown and shrunk by one voxel, a
   looser and a tighter fit), so the verified pick never passes fewer of its simulated trials
   than the imprint fingers would; ``imprint=False`` leaves them out, ``imprint=True`` adds them
   without ``verify`` too.  ``FingerPair.origin`` says where the pick came from.  A variant that
   cannot be made (a box filling the cube, grown by a voxel, leaves nothing to imprint) is left
   out of the pool and named in ``FingerPair.left_out``; the object is still designed for.
   With ``tolerance`` (millimetres) each feasible candidate is also simulated as ``copies`` moved
   copies: both fingers' height maps moved by a smooth random field of that standard deviation
   (``nets.inference.perturbed_heights``), a printer's error, the same fields for all of one
   object's candidates (they are compared under the same errors).  One trial of a design turns on
   tenths of a millimetre of finger (``research/sim_retest.py --perturb heights``: a field of
   0.15 mm flips 5% of trials), so a pick by its exact outcome alone is partly luck; a pick by
   its mean over the copies is one whose outcome survives printing, and
   ``FingerPair.simulated_mean`` says what to expect of the printed fingers.
5. Ranking: made and feasible first, then the simulated outcome (number of the 11 trials passed, when
   verified; with ``tolerance``, its mean over the exact design and its moved copies), then the
   mean predicted probability, then the candidate index (the generator's own output wins full
   ties).  When no candidate is feasible the best-predicted one is returned with
   ``feasible=False`` and an ``InfeasibleDesignWarning``.

Inside the jitted calls the candidates run in chunks of ``nets.inference.CHUNK`` (``lax.map``), so
memory stays bounded for large batches (256 objects x 64 candidates) while the call stays one.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import warnings
from pathlib import Path

import jax
import numpy as np
import trimesh

from f2f_jax.config import (
    BACKENDS,
    DEFAULT_CANDIDATES,
    DEFAULT_VERIFY,
    TRIAL_NAMES,
    GeometryConfig,
)
from f2f_jax.errors import F2FError, VolumeError
from f2f_jax.geometry import (
    Placement,
    check_placement,
    check_tsdf,
    export_finger_stl,
    object_volume,
    postprocess,
)
from f2f_jax.nets import RESOLUTION
from f2f_jax.design_pool import (  # noqa: F401  (the pool's steps, also reachable from here)
    GENERATOR,
    GENERATOR_HEIGHT_NOISE,
    GENERATOR_NOISE,
    IMPRINT_VARIANTS,
    imprint_candidates,
    left_out_reason,
    printed_copies,
    rank_candidates,
    simulate_candidates,
    simulate_moved,
    tolerance_voxels,
)
from f2f_jax.nets.inference import LATENT_NOISE, TrainedNets, as_key, predict, propose

log = logging.getLogger(__name__)

class InfeasibleDesignWarning(UserWarning):
    """No candidate of an object was printable; the best-predicted infeasible one was returned."""


@dataclasses.dataclass(frozen=True, eq=False, repr=False)
class FingerPair:
    """One designed finger pair and its scores.

    left, right: [40, 40, 40] float32 finger TSDFs (finger frame of config.py, mount at w = 0).
    predicted: [11] float32 fitness-net probabilities in ``TRIAL_NAMES`` order.
    simulated: [11] uint8 simulated outcomes, or None when not verified.
    feasible: both fingers printable and mountable (``geometry.is_feasible``).
    object: [40, 40, 40] float32, the input object volume.
    candidate: which of the ``n_candidates`` it was (0: the generator's own output);
    n_feasible: how many candidates were feasible; source: the nets' checkpoint.
    origin: where the candidate came from: "generator" (its own output), "generator + latent
        noise" ("generator + height noise" for a height-map generator), or one of the
        ``IMPRINT_VARIANTS`` ("imprint", ...).
    moved: [C, 11] uint8 simulated outcomes of C copies of the pair with both fingers moved by a
        smooth field of standard deviation ``tolerance`` (mm; ``design(..., tolerance=...)``), or
        None (tolerance 0).
    left_out: the origins of pool candidates that could not be made for this object (an imprint
        variant of a box that fills the cube: ``imprint_candidates``), left out of the ranking.
    placement: how the object's mesh was placed in the design cube (``geometry.Placement``: the
        scale mode and factor the fingers fit), or None when a TSDF was given.
    """

    left: np.ndarray
    right: np.ndarray
    predicted: np.ndarray
    simulated: np.ndarray | None
    feasible: bool
    object: np.ndarray
    candidate: int = 0
    n_candidates: int = 1
    n_feasible: int = 0
    source: str = ""
    geometry: GeometryConfig = dataclasses.field(default_factory=GeometryConfig)
    origin: str = GENERATOR
    moved: np.ndarray | None = None
    tolerance: float = 0.0
    left_out: tuple[str, ...] = ()
    placement: Placement | None = None

    @property
    def predicted_mean(self) -> float:
        """Mean predicted success probability over the 11 outcomes."""
        return float(np.mean(self.predicted))

    @property
    def simulated_mean(self) -> float | None:
        """Trials passed, averaged over the exact pair and its moved copies (what the verified
        ranking used); the exact pair's count without copies; None when not verified."""
        if self.simulated is None:
            return None
        runs = [self.simulated[None]] + ([] if self.moved is None else [self.moved])
        return float(np.concatenate(runs).sum(axis=-1).mean())

    def export_stl(self, directory, *, name: str | None = None) -> tuple[Path, Path]:
        """Write ``left.stl`` and ``right.stl`` (finger plus mount plate, watertight, millimetres)
        into ``directory`` (created if missing).  Returns (left_path, right_path).  Each STL's
        header names the side, the object (``name``) and how it was placed (``placement``).

        Raises VolumeError for an infeasible pair: it cannot be printed and mounted.
        """
        if not self.feasible:
            raise VolumeError("this finger pair is not feasible (no candidate was); refusing to "
                              "export it: try more candidates or a trained checkpoint")
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        where = "TSDF in the design cube" if self.placement is None else self.placement.short()
        obj = f" {name}" if name else ""
        left, right = (export_finger_stl(
            finger, directory / f"{side}.stl", self.geometry,
            header=f"f2f_jax {side} finger (mm) for{obj}: {where}")
            for side, finger in (("left", self.left), ("right", self.right)))
        return left, right

    def render(self, path, *, title: str | None = None, dpi: int = 90) -> Path:
        """PNG of the object held by the two fingers (three views) with the outcome boxes: the
        simulated outcomes when verified, else the predicted probabilities."""
        from f2f_jax.render import render_grasp  # matplotlib: only when a picture is asked for

        if title is None:
            title = self._headline()
        scores = self.simulated if self.simulated is not None else self.predicted
        return render_grasp(path, self.object, self.left, self.right, title=title, scores=scores,
                            cfg=self.geometry, dpi=dpi)

    def scores(self) -> dict:
        """JSON-ready scores: predicted (and simulated) per outcome name, feasibility, provenance."""
        return dict(
            feasible=bool(self.feasible),
            predicted={n: round(float(p), 6) for n, p in zip(TRIAL_NAMES, self.predicted)},
            predicted_mean=round(self.predicted_mean, 6),
            simulated=(None if self.simulated is None else
                       {n: int(s) for n, s in zip(TRIAL_NAMES, self.simulated)}),
            simulated_passed=None if self.simulated is None else int(np.sum(self.simulated)),
            tolerance_mm=float(self.tolerance),
            moved_passed=None if self.moved is None else [int(n) for n in self.moved.sum(axis=-1)],
            simulated_mean=(None if self.simulated_mean is None else round(self.simulated_mean, 4)),
            candidate=int(self.candidate), n_candidates=int(self.n_candidates),
            n_feasible=int(self.n_feasible), origin=self.origin, source=self.source,
            left_out=[dict(origin=name, reason=left_out_reason(name)) for name in self.left_out],
            object_scale=None if self.placement is None else self.placement.to_json(),
        )

    def _headline(self) -> str:
        state = "feasible" if self.feasible else "NOT feasible"
        text = (f"{state}, candidate {self.candidate} of {self.n_candidates} ({self.origin}; "
                f"{self.n_feasible} feasible), predicted mean {self.predicted_mean:.2f}")
        if self.simulated is not None:
            text += f", simulated {int(np.sum(self.simulated))}/{len(self.simulated)}"
        if self.moved is not None:
            text += (f" ({self.simulated_mean:.1f} on average with {len(self.moved)} copies moved "
                     f"by {self.tolerance:g} mm)")
        return text

    def __str__(self) -> str:
        lines = [f"FingerPair: {self._headline()}"]
        if self.source:
            lines.append(f"  nets: {self.source}")
        moved = self.moved is not None
        header = f"  {'outcome':<8}{'predicted':>10}{'simulated':>10}"
        lines.append(header + (f"{'moved':>8}" if moved else ""))
        for i, name in enumerate(TRIAL_NAMES):
            sim = "-" if self.simulated is None else str(int(self.simulated[i]))
            row = f"  {name:<8}{self.predicted[i]:>10.3f}{sim:>10}"
            if moved:
                row += f"{int(self.moved[:, i].sum())}/{len(self.moved)}".rjust(8)
            lines.append(row)
        sim = "-" if self.simulated is None else f"{int(np.sum(self.simulated))}/{len(self.simulated)}"
        row = f"  {'mean':<8}{self.predicted_mean:>10.3f}{sim:>10}"
        if moved:
            row += f"{self.moved.sum(axis=-1).mean():.1f}".rjust(8)
        lines.append(row)
        return "\n".join(lines)

    __repr__ = __str__


def design(obj, *, params: TrainedNets | None = None, key=None,
           candidates: int = DEFAULT_CANDIDATES, verify: bool = DEFAULT_VERIFY,
           backend: str = "mujoco", run_dir=None, noise: float = LATENT_NOISE,
           progress: bool | None = None, executor: str = "threads", imprint: bool | None = None,
           tolerance: float = 0.0, copies: int = 3, scale: str | None = None,
           units: str | None = None):
    """Design a finger pair for each object.

    obj: one object -> FingerPair, or a batch -> list of FingerPairs.  An object is a [40, 40, 40]
        float32 TSDF (negative inside; a batch [B, 40, 40, 40]), a ``trimesh.Trimesh``, or a mesh
        file's path (a batch: a list of meshes or paths).  Meshes are placed in the design cube
        by ``geometry.place_mesh`` with ``scale`` and ``units`` and ``FingerPair.placement`` says
        how; a TSDF is already in the cube.
    params: trained TrainedNets; None loads ``run_dir``'s newest checkpoint, or, with no run_dir
        and no ``$F2F_RUN_DIR``, the weights that ship with the package
        (``train.weights.load_weights``).
    key: jax PRNG key (or an int seed) for the latent noise of candidates 1..K-1; default key(0).
    candidates: K >= 1 designs sampled per object (see the module docstring for the ranking).
    verify: simulate the feasible candidates (one ``sim.evaluate`` call with ``backend``) and rank
        by simulated outcome first (the default); False: the fitness net's ranking alone, no
        simulation (fast).  executor: that call's (``sim.evaluate``: "threads" or "ray").
    imprint: also put the object's imprint pair and its variants (``IMPRINT_VARIANTS``) in the
        pool, after the K generated candidates; None (default): when ``verify``.
    noise: standard deviation of the latent noise (latent units; the latents span [-1, 1]); for a
        height-map generator (``net.generator = "heights"``) the noise of a smooth field added to
        each height map, ``noise x nets.inference.HEIGHT_NOISE_VOXELS`` voxels.
    progress: the simulation's progress bar with ``verify`` (None: ``sim.evaluate``'s default).
    tolerance: with ``verify``, also simulate ``copies`` copies of every feasible candidate with
        both fingers' height maps moved by a smooth random field of this standard deviation in
        millimetres at its 5 x 5 grid points over the mount (a column moves by about half of it
        on average: 0.3 moves them ~0.15 mm; 0, the default: no copies), and rank by the mean over
        the exact pair and its copies; costs 1 + copies times the simulation.  The copies' fields
        are drawn from ``key``, one per copy, object and side, shared by the object's candidates.
        ``research/design_tolerance.py`` measures what it buys.
    scale, units: how a mesh is placed in the cube (``geometry.place_mesh``): "stretch", "fit" or
        "real" (with units "m", "cm", "mm" or "in"); None: as the nets' training objects were
        placed (``config.geometry.object_scale``).  Only for meshes.

    Raises VolumeError for a wrong shape, NaN/inf values or an empty or all-inside volume (naming
    the batch index), MeshError for a mesh that cannot become a volume (naming it), ValueError for
    bad options, CheckpointError (an F2FError) when no nets can be loaded.  Warns
    InfeasibleDesignWarning for every object whose candidates are all infeasible.
    """
    meshes, single = _as_meshes(obj)
    if meshes is None:
        if scale is not None or units is not None:
            raise ValueError("scale and units place a mesh in the design cube; a TSDF is in it "
                             "already (give the mesh, or leave them out)")
        objects, single = _as_objects(obj)
    else:
        check_placement(scale, units)  # before the nets load
    _check_options(candidates, backend, noise, tolerance, verify, copies)
    candidates = int(candidates)
    nets = _load_trained_nets(run_dir) if params is None else params
    if not isinstance(nets, TrainedNets):
        raise TypeError(f"params must be f2f_jax.nets.inference.TrainedNets (or None to load a "
                        f"checkpoint), got {type(nets).__name__}")
    key = as_key(key)
    g = nets.config.geometry
    placements = None
    if meshes is not None:
        objects, placements = _mesh_objects(meshes, g, scale, units)
    if imprint is None:
        imprint = verify

    lefts, rights = propose(nets, objects, key, candidates, noise)
    noisy = GENERATOR_HEIGHT_NOISE if nets.config.net.generator == "heights" else GENERATOR_NOISE
    origins = [GENERATOR] + [noisy] * (candidates - 1)
    made = np.ones((len(objects), candidates), bool)
    if imprint:
        imp_lefts, imp_rights, imp_made = imprint_candidates(objects, g)
        lefts = np.concatenate([lefts, imp_lefts], axis=1)
        rights = np.concatenate([rights, imp_rights], axis=1)
        made = np.concatenate([made, imp_made], axis=1)
        origins += [name for name, _ in IMPRINT_VARIANTS]
    left_out = [[origins[k] for k in np.nonzero(~made[b])[0]] for b in range(len(objects))]
    for b, names in enumerate(left_out):
        for name in names:
            log.info("design: %s left out of the pool of %s: %s", name,
                     "the object" if single else f"object {b}", left_out_reason(name))
    feasible = postprocess(lefts, rights, g) & made
    predicted = predict(nets, objects, lefts, rights)
    if not np.all(np.isfinite(predicted)):
        raise F2FError(f"the fitness net of {nets.source or 'these nets'} predicted NaN/inf; "
                       "the checkpoint is broken")
    simulated = (simulate_candidates(nets, objects, lefts, rights, feasible, backend, progress,
                           executor=executor) if verify else None)
    moved = None
    if verify and tolerance > 0:
        rng = np.random.default_rng(np.asarray(jax.random.key_data(jax.random.fold_in(key, 1))).ravel())
        moved = simulate_moved(nets, objects, lefts, rights, feasible, backend,
                               tolerance_voxels(tolerance, g), int(copies), rng, progress,
                               executor=executor, shared=True)
    best = rank_candidates(feasible, predicted, simulated, moved, made=made)[:, 0]

    hopeless = np.nonzero(~feasible.any(axis=1))[0]
    if len(hopeless):
        which = "the object" if single else f"objects {hopeless.tolist()}"
        warnings.warn(f"design: none of the {len(origins)} candidates for {which} is feasible; "
                      "returning the best-predicted one with feasible=False (try more candidates "
                      "or a better-trained checkpoint)", InfeasibleDesignWarning, stacklevel=2)

    pairs = []
    for b, k in enumerate(best):
        pairs.append(FingerPair(
            left=lefts[b, k].copy(), right=rights[b, k].copy(),
            predicted=predicted[b, k].astype(np.float32),
            simulated=None if simulated is None else simulated[b, k].copy(),
            feasible=bool(feasible[b, k]), object=objects[b].copy(), candidate=int(k),
            n_candidates=len(origins), n_feasible=int(feasible[b].sum()), source=nets.source,
            geometry=g, origin=origins[k], moved=None if moved is None else moved[:, b, k].copy(),
            tolerance=float(tolerance) if moved is not None else 0.0,
            left_out=tuple(left_out[b]), placement=None if placements is None else placements[b]))
    return pairs[0] if single else pairs


# --------------------------------------------------------------------------------------------
# helpers


_SHIPPED_NETS: TrainedNets | None = None


def _load_trained_nets(run_dir) -> TrainedNets:
    """The nets design() runs when no params are given: ``run_dir``'s newest checkpoint, else
    ``$F2F_RUN_DIR``'s, else the weights that ship with the package (read once per process, and
    said once in the log).  Lazy imports: design with params= never touches orbax."""
    global _SHIPPED_NETS
    if run_dir is not None or os.environ.get("F2F_RUN_DIR"):
        from f2f_jax.train.checkpoint import load_trained_nets  # orbax: not for design(params=...)

        return load_trained_nets(run_dir)
    if _SHIPPED_NETS is None:
        from f2f_jax.train.weights import load_weights, weights_info

        _SHIPPED_NETS = load_weights()
        info = weights_info()
        log.warning("design: no run given (run_dir, $F2F_RUN_DIR): using the weights shipped with "
                    "f2f_jax (%s, commit %s, seed %s)", info.get("provenance", {}).get("command"),
                    info.get("commit"), info["config"]["train"].get("seed"))
    return _SHIPPED_NETS


def _check_options(candidates, backend, noise, tolerance, verify, copies) -> None:
    """design()'s options, refused with a ValueError that names the bad one."""
    if isinstance(candidates, bool) or not isinstance(candidates, (int, np.integer)) or candidates < 1:
        raise ValueError(f"candidates must be an integer >= 1, got {candidates!r}")
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; choose one of {BACKENDS}")
    if not np.isfinite(noise) or noise < 0:
        raise ValueError(f"noise must be a finite standard deviation >= 0, got {noise!r}")
    if not np.isfinite(tolerance) or tolerance < 0:
        raise ValueError(f"tolerance must be a finite standard deviation >= 0 (mm), got {tolerance!r}")
    if tolerance > 0 and not verify:
        raise ValueError("tolerance simulates moved copies of the candidates: it needs verify=True")
    if isinstance(copies, bool) or not isinstance(copies, (int, np.integer)) or copies < 1:
        raise ValueError(f"copies must be an integer >= 1, got {copies!r}")


def _is_mesh_like(x) -> bool:
    return isinstance(x, (trimesh.Trimesh, str, os.PathLike))


def _as_meshes(obj) -> tuple[list | None, bool]:
    """(meshes or paths, single) when ``obj`` is a mesh, a path or a list of them; (None, _) for
    anything else (read as TSDF arrays by ``_as_objects``)."""
    if _is_mesh_like(obj):
        return [obj], True
    if isinstance(obj, (list, tuple)) and obj and all(_is_mesh_like(x) for x in obj):
        return list(obj), False
    return None, False


def _mesh_objects(meshes, g: GeometryConfig, scale, units) -> tuple[np.ndarray, list[Placement]]:
    """Meshes or mesh files -> object volumes [B, R, R, R] and their placements."""
    from f2f_jax.data.sources import load_mesh  # trimesh file readers: only for paths

    volumes, placements = [], []
    for item in meshes:
        mesh = item if isinstance(item, trimesh.Trimesh) else load_mesh(item)
        tsdf, placement = object_volume(mesh, g, scale=scale, units=units)
        volumes.append(tsdf)
        placements.append(placement)
    return np.stack(volumes), placements


def _as_objects(obj_tsdf) -> tuple[np.ndarray, bool]:
    """Validate the input: -> ([B, R, R, R] float32, single)."""
    r = RESOLUTION
    try:
        arr = np.asarray(obj_tsdf)
    except Exception as exc:  # ragged lists and the like
        raise VolumeError(f"obj_tsdf: cannot read as an array ({type(exc).__name__}: {exc})") from None
    g = GeometryConfig()
    if arr.ndim == 3:
        return check_tsdf(arr, "obj_tsdf", g)[None].copy(), True
    if arr.ndim == 4:
        if arr.shape[0] == 0:
            raise VolumeError("obj_tsdf: empty batch (shape [0, ...])")
        return np.stack([check_tsdf(a, f"obj_tsdf[{i}]", g) for i, a in enumerate(arr)]), False
    raise VolumeError(f"obj_tsdf: expected one volume [{r}, {r}, {r}] or a batch [B, {r}, {r}, {r}], "
                      f"got shape {arr.shape}")
