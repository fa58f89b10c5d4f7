"""Frozen configuration: every physical constant of the system lives here, in SI units.

Frames (shared by geometry, simulation and learning):

* A shape volume is ``[40, 40, 40]`` float32 TSDF over a 6 cm cube (1.5 mm voxels), values in
  ``[-1, 1]``, negative inside, truncated at 5 voxels.
* Every volume has one local frame, in metres: axes 0 and 1 centred on the cube (voxel centres at
  ``(i + 0.5) * voxel - 3 cm``), axis 2 starting at the cube's base (``(i + 0.5) * voxel``).
  ``tsdf_to_mesh`` returns vertices in this frame.
* An **object** volume is indexed ``[ix, iy, iz]`` along world ``x, y, z``; its frame is the world
  frame of an object resting on the floor at the grasp location (``x, y in [-3, 3] cm``,
  ``z in [0, 6] cm``), lowered by one voxel (``GeometryConfig.rest_offset``) so that the object,
  normalised with one empty voxel under it, rests on the floor.  The gripper closes along world x.
* A **finger** volume is indexed ``[iu, iv, iw]``: ``w`` is the mount normal (``iw = 0`` touches the
  mount plate, ``iw`` grows towards the object), ``v`` points up (world +z), ``u = v x w``.  The left
  finger sits at -x and closes towards +x (``w -> +x``, ``u -> +y``), the right finger sits at +x
  (``w -> -x``, ``u -> -y``): the right finger is the left one turned 180 degrees about world z, so
  both are proper rigid placements and a printed finger fits either jaw.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class GeometryConfig:
    resolution: int = 40  # voxels per side (paper: 40^3)
    cube_size: float = 0.06  # m, side of the volume (paper: 6 cm)
    truncation_voxels: float = 5.0  # TSDF truncation, in voxels
    feasible_base_fraction: float = 0.10  # solid share of a mount-side plane (paper: 10%)
    feasible_base_planes: int = 4  # planes from the mount searched for that share (original code: 4)
    cut_search_fraction: float = 1.0 / 3.0  # fingers cut from objects: search the first third (paper)
    # Convex pieces per shape and vertices per piece; the batched simulator's fixed layout.
    object_hulls: int = 8
    finger_hulls: int = 16
    hull_vertices: int = 32
    mount_plate_thickness: float = 0.004  # m, printed plate under each finger (export only)
    # How an object becomes convex pieces (geometry.pieces): "coacd" (13-30 s per non-convex
    # object, cached on disk) or "tiles" (hulls over its depth map along the closing axis, ~0.15 s,
    # no cache; 94-95% of trials agree with coacd's: docs/simulator.md).
    object_method: str = "coacd"
    # How a mesh becomes an object volume (``geometry.place_mesh``): "stretch", each axis scaled
    # to fill the cube (the paper's convention), or "fit", one factor for all three axes.  The nets
    # learn objects placed this way, and ``design`` places a user's mesh alike unless told
    # otherwise ("real" keeps its size).
    object_scale: str = "stretch"

    @property
    def rest_offset(self) -> float:
        """World z of a volume frame's origin in the gripper scene (metres).

        A normalised object has one empty voxel under it, so it rests on the floor with its volume
        frame lowered by one voxel; the fingers' frames are lowered alike so that imprints line up.
        """
        return -self.voxel_size

    @property
    def voxel_size(self) -> float:
        return self.cube_size / self.resolution

    @property
    def truncation(self) -> float:
        """Truncation distance in metres."""
        return self.truncation_voxels * self.voxel_size


@dataclass(frozen=True)
class SimConfig:
    # --- physics ---
    # 4 ms with the implicitfast integrator (the ``fast`` preset), which takes the lift and jaw
    # servos' stiffness and damping into the step; ``reference`` is 2 ms explicit Euler.  Their
    # agreement is in docs/simulator.md.
    timestep: float = 0.004  # s
    integrator: str = "implicitfast"  # "euler" (reference) or "implicitfast"
    iterations: int = 50  # Newton iterations: grasps are contact-rich and need a converged solve
    ls_iterations: int = 20
    cone: str = "elliptic"  # elliptic cones give friction limits close to the Coulomb model
    impratio: float = 10.0  # stiffer friction than normal constraints: stops slow creep of held objects
    condim: int = 4  # torsional friction too: a pinched object does not spin freely around the grip axis
    gravity: float = 9.81  # m/s^2
    # --- object ---
    object_mass: float = 0.050  # kg (paper: 50 g)
    finger_friction: float = 0.2  # effective finger-object coefficient (paper: object 0.2)
    object_friction: float = 0.5  # object-floor
    # --- gripper ---
    grip_force: float = 1.0  # N, force limit of each jaw actuator (paper: 1.0 N)
    jaw_kp: float = 200.0  # N/m, position gain; saturates at grip_force beyond 5 mm of error
    jaw_damping: float = 10.0  # N s/m
    lift_kp: float = 2000.0
    lift_damping: float = 80.0
    open_margin: float = 0.004  # m, clearance between a finger and the object at t = 0
    # --- phases (s) ---
    settle_time: float = 0.2
    close_time: float = 0.4
    lift_height: float = 0.12  # m
    lift_time: float = 0.75
    hold_time: float = 1.0
    push_force: float = 1.5  # N (paper: 1.5 N)
    push_time: float = 1.0 / 12.0  # s (original: 20 steps of 1/240 s)
    push_hold_time: float = 1.7
    success_min_height: float = 0.05  # m, object centre above its start for "lifted"
    robustness_angles_deg: tuple[float, ...] = (-30.0, -20.0, -10.0, 10.0, 20.0, 30.0)
    stability_directions: tuple[tuple[float, float, float], ...] = (
        (0.0, 0.0, -1.0),
        (0.0, 0.70710678, -0.70710678),
        (0.61237244, -0.35355339, -0.70710678),
        (-0.61237244, -0.35355339, -0.70710678),
    )
    max_speed: float = 50.0  # m/s; any body faster than this is an exploded state
    # Phases that wait for things to come to rest (settle, close, hold, post-push hold) end once
    # nothing moves faster than rest_speed for rest_time (protocol.GraspRunner.advance); 0 runs
    # every phase to its full length (the ``reference`` preset).
    rest_speed: float = 0.002  # m/s
    rest_time: float = 0.1  # s
    # The six turned grasps start from the first grasp's settled object turned about the vertical
    # instead of settling again (the floor is the same under that turn; the jaws are open and
    # touch nothing).  False settles every grasp (``reference``).
    shared_settle: bool = True

    @property
    def n_trials(self) -> int:
        return 1 + len(self.stability_directions) + len(self.robustness_angles_deg)

    def steps(self, seconds: float) -> int:
        return max(1, int(round(seconds / self.timestep)))


TRIAL_NAMES: tuple[str, ...] = (
    "grasp", "S1", "S2", "S3", "S4", "R-30", "R-20", "R-10", "R+10", "R+20", "R+30",
)
# The simulator backends ``sim.evaluate`` runs: plain MuJoCo (threads), MJX, MuJoCo Warp.
BACKENDS: tuple[str, ...] = ("mujoco", "mjx", "warp")
# Where ``sim.evaluate`` runs the candidates, each with the backends it runs: "threads" of this
# process, or "ray" tasks on a cluster (``sim.ray_executor``), which distribute the mujoco backend
# alone (the batched ones step every candidate on this machine's accelerators).  Here, with their
# rule, because the command lines check their flags before importing the simulator.
EXECUTORS: dict[str, tuple[str, ...]] = {"threads": BACKENDS, "ray": ("mujoco",)}


def executor_problem(executor: str, backend: str) -> str | None:
    """Why ``executor`` cannot run ``backend``, or None: ``sim.evaluate`` raises it as a
    ValueError, the command lines print it."""
    if executor not in EXECUTORS:
        return f"unknown executor {executor!r}; choose one of {tuple(EXECUTORS)}"
    if backend not in EXECUTORS[executor]:
        return (f"executor={executor!r} distributes the {' or '.join(EXECUTORS[executor])} "
                f"backend only; the {backend!r} backend batches every candidate on this machine's "
                "accelerators")
    return None


# How a mesh is placed in the shape cube (``geometry.place_mesh``), and the units (metres per
# unit) a real-size mesh may be in.  Here, with design()'s defaults, because f2f-design reads them
# for its flags without importing the geometry or JAX.
SCALES: tuple[str, ...] = ("stretch", "fit", "real")
UNITS: dict[str, float] = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254}
# design()'s and f2f-design's defaults: the verified pool (benchmarks/design_judges.py and
# design_latency.py measure what each mode passes and costs).
DEFAULT_CANDIDATES = 16
DEFAULT_VERIFY = True


@dataclass(frozen=True)
class NetConfig:
    latent_dim: int = 686  # paper
    # Shape encoder: 3^3 VALID convolutions, stride 2 at the fifth (paper): 40 -> 32 -> 15 -> 7.
    encoder_channels: tuple[int, ...] = (8, 16, 32, 64, 64, 32, 16, 8, 4)
    encoder_strides: tuple[int, ...] = (1, 1, 1, 1, 2, 1, 1, 1, 1)
    # Initial log-variance of the encoder's posterior (bias of the logvar head): std ~0.05, small
    # next to the [-1, 1] latent range, so a fresh VAE starts nearly deterministic.
    encoder_logvar_init: float = -6.0
    # Shape decoder: FCs, reshape to a cube of decoder_seed_size^3 x (decoder_fc[-1] / seed^3)
    # channels (4096 = 64 x 4^3), then 3^3 VALID transposed convolutions (paper):
    # 4 -> 6 -> 8 -> 24 (stride 3) -> 26 -> ... -> 40.
    decoder_fc: tuple[int, ...] = (1024, 2048, 4096)
    decoder_seed_size: int = 4
    decoder_channels: tuple[int, ...] = (64, 64, 32, 16, 8, 4, 2, 1, 1, 1, 1)
    decoder_strides: tuple[int, ...] = (1, 1, 3, 1, 1, 1, 1, 1, 1, 1, 1)
    # Kernel edge of each transposed convolution; empty: 3 for every layer (paper).
    decoder_kernels: tuple[int, ...] = ()
    generator_fc: tuple[int, ...] = (2096, 4096)
    # What the generator writes (``nets.generator_module``): "latent", the paper's two finger
    # latents read by the frozen shape decoder (``FingerGenerator``), or "heights", each finger's
    # height map over its mount written column by column from the object's planes
    # (``HeightGenerator``: no decoder between the generator and the fingers the simulator meshes).
    generator: str = "latent"
    # HeightGenerator: widths of its 3 x 3 convolutions over the (y, z) grid.  The finger TSDFs it
    # writes are truncated as the geometry's (GeometryConfig.truncation_voxels).
    height_channels: tuple[int, ...] = (64, 64, 64)
    # Fitness ResNet: one stride-2 conv per stage (the first 5^3, pad 2), then fitness_blocks
    # residual blocks at that width; a last stride-2 conv at the last width: 120x40x40 -> 1x1x1.
    fitness_channels: tuple[int, ...] = (32, 64, 128, 256, 512, 1024)
    fitness_blocks: tuple[int, ...] = (2, 2, 1, 1, 1, 1)
    fitness_fc: tuple[int, ...] = (512, 256, 128)
    # BatchNorm running averages: PyTorch's momentum 0.1 (the original) is Flax's 0.9.
    bn_momentum: float = 0.9
    leaky_slope: float = 0.01  # PyTorch's LeakyReLU default, as in the original


@dataclass(frozen=True)
class TrainConfig:
    seed: int = 0
    lr: float = 1e-4  # paper, all stages
    weight_decay: float = 1e-5  # paper
    ae_epochs: int = 100
    ae_batch_size: int = 128
    fn_epochs: int = 100
    fn_batch_size: int = 64
    gn_epochs: int = 100
    # Shuffled passes over the imprint pairs per generator-pretraining epoch (each capped at
    # max_steps_per_epoch steps): more steps without a checkpoint after each pass.
    gn_passes: int = 1
    cycles: int = 20
    objects_per_cycle: int = 512  # paper
    cotrain_batch_size: int = 32  # 16 new + 16 pretrain (paper)
    fn_target_loss: float = 0.2
    gn_target_loss: float = -0.95
    min_epochs: int = 5
    max_epochs: int = 50
    max_steps_per_epoch: int = 500
    kl_weight: float = 0.0  # VAE KL weight; 0 is the original's plain reconstruction MSE
    # Learning rate of the generator in the co-training cycles (None: lr); it must move slower than
    # the fitness net can follow (docs/learning.md).
    generator_lr: float | None = None
    # Generator objective: "GS", "GS+R", "GS+S" or "full" (the paper's Table 1 rows).
    objectives: str = "full"
    # Co-training trains the nets only once this many designs have been simulated (the original
    # code's cotrain_warmup_datapoints: 2048, four cycles of 512); the fitness net refits on all
    # designs simulated so far, half of each batch, the other half pretraining rows (as the original).
    warmup_designs: int = 2048
    # Designs per object and cycle: the generator's own and cycle_candidates - 1 perturbations of
    # it (``nets.inference``), all simulated and stored: designs of one object that differ a little.
    cycle_candidates: int = 1
    # --- the run's data (experiments/cotrain.py) ---
    n_objects: int = 1000  # built-in objects made when no --objects directory is given
    test_fraction: float = 0.2  # held-out share of the objects (a seeded split, kept in the run's objects/)
    cut_pairs: int = 2  # pretraining pairs cut from other shapes, per object
    # Perturbed imprint pairs per object in the pretraining dataset (the imprint plus smooth random
    # fields of rising size, ``dataset.perturbed_pairs``): one object's designs that differ a
    # little, so the fitness net sees what separates its good fingers from its bad.
    perturbed_pairs: int = 0
    # More objects for the generator's pretraining alone: the imprint pairs of this many built-in
    # objects beyond the run's own (indices n_objects.. of the seed's stream: never one of the
    # run's objects, nor one of ``evaluate.py --fresh``'s, which come from another seed) join the
    # run's training imprints.  Nothing is simulated: ~0.3 s of TSDF per object on 2 cores, kept
    # in the run's imprint_objects/.
    imprint_objects: int = 0
    eval_objects: int = 64  # held-out objects scored after cycle 0 and after the last cycle
    # --- what teaches the generator in the cycles (``train.teacher``, docs/learning.md) ---
    # "fitness": the paper's co-training against the fitness net.  "simulator": expert iteration
    # (``train/teacher.py``): each cycle simulates ``teacher_candidates`` designs of every teacher
    # object (the generator's own and its height-noise candidates; in the first cycle also the
    # imprint and its two variants), and the generator is regressed onto each object's
    # best-simulated pair so far (ties go to the imprint).  "imprint": its control, the same
    # cycles' steps on the same objects' imprints, nothing simulated.
    teacher: str = "fitness"
    # The teacher objects: the run's training objects and built-in objects n_objects ..
    # n_objects + teacher_objects - 1 of seed teacher_seed's stream (seed 0's pieces ship with
    # the package up to object 639; others run coacd once), never one of the run's held-out objects.
    teacher_objects: int = 0
    teacher_seed: int = 0
    teacher_candidates: int = 4  # designs per teacher object and cycle, the generator's own first
    teacher_epochs: int = 4  # generator (and fitness-net) epochs per cycle on the teacher's targets
    # Learning rate of the generator's steps onto the targets (None: lr, as pretraining; the
    # co-training cycles' generator_lr is a tenth of it).
    teacher_lr: float | None = None
    teacher_chunk: int = 64  # objects simulated per store chunk: a kill loses at most one chunk
    # Teacher objects whose rows the fitness net does not train on: its within-object ranking is
    # measured on their candidates, each cycle (the teacher's generator trains on every object).
    teacher_fn_holdout: float = 0.1
    # Targets confirmed on moved copies (``train/teacher.py``, ``confirm_targets``): 0 takes each
    # object's best exact pair.  C > 0 simulates an object's new best pair and its imprint on C
    # copies, both fingers' height maps moved by one smooth field of ``teacher_tolerance`` mm per
    # copy and side (the same for the two, as ``design(tolerance=)`` compares candidates), and
    # keeps the pair only when its mean over the copies leads the imprint's by at least
    # ``teacher_min_lead`` trials (and by more than none); a pair refused is not tried again.
    teacher_copies: int = 0
    teacher_tolerance: float = 0.3
    teacher_min_lead: float = 2.0


@dataclass(frozen=True)
class Config:
    geometry: GeometryConfig = field(default_factory=GeometryConfig)
    sim: SimConfig = field(default_factory=SimConfig)
    net: NetConfig = field(default_factory=NetConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    def replace(self, **sections) -> "Config":
        return dataclasses.replace(self, **sections)


def paper() -> Config:
    """The paper's network sizes and training schedule: a GPU run."""
    return Config()


def default() -> Config:
    """The CPU-sized default of ``experiments/cotrain.py``: the paper's physics and protocol, narrow
    strided nets and a short schedule that finish 20 cycles on a 2-core CPU in under 45 minutes."""
    base = Config()
    return base.replace(
        net=NetConfig(
            latent_dim=128,
            # 40 -> 19 -> 9 -> 4 -> 2, all strided: 36 ms per batch of 16 (forward + gradients) on
            # 2 cores
            encoder_channels=(4, 8, 16, 32), encoder_strides=(2, 2, 2, 1),
            # 4 -> 13 -> 40: two stride-3 transposed convolutions of kernel 4 (overlapping by one
            # voxel), nothing at full resolution but the output layer (docs/learning.md)
            decoder_fc=(512, 1024), decoder_seed_size=4, decoder_channels=(16, 1),
            decoder_strides=(3, 3), decoder_kernels=(4, 4),
            generator_fc=(512, 512),
            fitness_channels=(4, 8, 16, 32), fitness_blocks=(0, 1, 1, 1), fitness_fc=(128, 64),
            # the height-map generator ("latent" is the paper's; docs/learning.md compares them)
            generator="heights",
        ),
        # Co-training epochs 1..2 per net and cycle (paper: 5..50): the fitness net's refit is under
        # its target BCE after one epoch from cycle 4 on, and the generator never reaches its target
        # here, so it runs the cap.  The whole run: ~28 min on 2 cores with seed 0's shipped pieces
        # (docs/scaling.md).  The latent generator's schedule is one pass
        # (``--set net.generator=latent --set train.gn_passes=1``).
        train=dataclasses.replace(
            base.train, lr=1e-3, generator_lr=1e-4, ae_epochs=40, ae_batch_size=32, fn_epochs=10, fn_batch_size=32,
            gn_epochs=20, gn_passes=12, objects_per_cycle=32, cotrain_batch_size=32, min_epochs=1, max_epochs=2,
            max_steps_per_epoch=8, n_objects=64, eval_objects=16, cut_pairs=1, warmup_designs=64,
            # the imprints of 600 built-in objects past the run's 64 join the generator's
            # pretraining (1,920 steps instead of 480; docs/learning.md)
            imprint_objects=600,
        ),
    )


def tiny() -> Config:
    """Short phases and narrow nets: for tests and quick looks, same physics."""
    base = Config()
    return base.replace(
        sim=dataclasses.replace(
            base.sim, settle_time=0.1, close_time=0.3, lift_time=0.4, lift_height=0.08,
            hold_time=0.3, push_hold_time=0.5,
        ),
        net=NetConfig(
            latent_dim=32, encoder_channels=(4, 8, 8, 16), encoder_strides=(2, 2, 2, 1),
            decoder_fc=(64, 128), decoder_seed_size=4, decoder_channels=(8, 1),
            decoder_strides=(3, 3), decoder_kernels=(4, 4), generator_fc=(64, 64),
            fitness_channels=(4, 8, 8, 16), fitness_blocks=(0, 1, 0, 0), fitness_fc=(32, 16),
        ),
        train=dataclasses.replace(
            base.train, lr=1e-3, ae_epochs=2, fn_epochs=3, gn_epochs=2, cycles=3, objects_per_cycle=16,
            ae_batch_size=8, fn_batch_size=8, cotrain_batch_size=8, min_epochs=1, max_epochs=3,
            max_steps_per_epoch=4, n_objects=16, eval_objects=4, cut_pairs=1, warmup_designs=32,
            imprint_objects=4,
        ),
    )


def workstation() -> Config:
    """The default's nets, physics and protocol on >= 100x its simulated results and 10x its objects:
    a many-core CPU machine (plain MuJoCo in threads, or Ray tasks on a cluster) or ``--backend
    warp`` on a GPU.  Its figures are in ``run_plan.planned_simulations``; what it costs, measured and
    projected, is in benchmarks/RESULTS.md."""
    base = default()
    return base.replace(
        train=dataclasses.replace(
            base.train,
            # 640 objects (512 training, 128 held-out): 10x the default's; the 576 past the
            # shipped pieces' 64 go through coacd once (13-30 s each on one core, cached)
            n_objects=640, eval_objects=64,
            # per training object: imprint, WSG50, 2 cut pairs and 6 perturbed imprint pairs, and
            # in every cycle 16 designs of each of 256 objects (the generator's own and 15 height-
            # noise candidates): one object's designs that differ a little, for the fitness net
            cut_pairs=2, perturbed_pairs=6, objects_per_cycle=256, cycle_candidates=16,
            warmup_designs=4096,
            # 8x the default's steps per epoch, so each cycle's refit sees its new designs
            max_steps_per_epoch=64,
        ),
    )


def teacher() -> Config:
    """The default's nets and pretraining, with the simulator as the generator's teacher instead
    of the fitness net (``train.teacher``): 3 cycles over 51 + 236 teacher objects (builtin 64-299
    of seed 0, whose pieces ship with the package), 4 designs of each a cycle and the imprint
    variants in the first: ~4,300 simulations (docs/learning.md).  Its control is ``--set
    train.teacher=imprint``; both can start from a default run's pretraining (``--from-pretrained``)."""
    base = default()
    return base.replace(train=dataclasses.replace(
        base.train, teacher="simulator", cycles=3, teacher_objects=236, teacher_candidates=4,
        teacher_epochs=1))


CONFIGS = {"tiny": tiny, "default": default, "paper": paper, "workstation": workstation,
           "teacher": teacher}


def held_out_count(n: int, test_fraction: float) -> int:
    """How many of ``n`` objects a split holds out (``TrainConfig.test_fraction``): the share,
    rounded, with at least one object on each side when there are two or more."""
    return min(max(int(round(test_fraction * n)), 1), n - 1) if n >= 2 else 0


# Simulation presets: the step and the protocol's early exits, by name.  "fast" is what every
# config above uses; "reference" runs every phase to its full length at 2 ms, the judge that
# benchmarks/sim_agreement.py compares the fast preset with (docs/simulator.md).  Only the fields
# named here differ between presets.
SIM_PRESETS: dict[str, dict[str, dict]] = {
    "fast": dict(sim=dict(timestep=0.004, integrator="implicitfast", rest_speed=0.002,
                          rest_time=0.1, shared_settle=True)),
    "reference": dict(sim=dict(timestep=0.002, integrator="euler", rest_speed=0.0, rest_time=0.1,
                               shared_settle=False)),
}


def with_sim_preset(cfg: Config, name: str) -> Config:
    """``cfg`` with the simulation preset ``name`` ("fast" or "reference") applied."""
    try:
        preset = SIM_PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown simulation preset {name!r}; choose one of "
                         f"{sorted(SIM_PRESETS)}") from None
    return cfg.replace(**{section: dataclasses.replace(getattr(cfg, section), **fields)
                          for section, fields in preset.items()})


def sim_preset_name(cfg: Config) -> str:
    """The name of the simulation preset ``cfg`` is set to, or "custom" when it matches none."""
    for name, preset in SIM_PRESETS.items():
        if all(getattr(getattr(cfg, section), key) == value
               for section, fields in preset.items() for key, value in fields.items()):
            return name
    return "custom"


def get(name: str) -> Config:
    try:
        return CONFIGS[name]()
    except KeyError:
        raise ValueError(f"unknown config {name!r}; choose one of {sorted(CONFIGS)}") from None


def voxel_centres(cfg: GeometryConfig | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Voxel centre coordinates (metres) along the three axes of a volume's local frame."""
    cfg = cfg or GeometryConfig()
    c = (np.arange(cfg.resolution) + 0.5) * cfg.voxel_size
    return c - cfg.cube_size / 2, c - cfg.cube_size / 2, c


def geometry_config(cfg=None) -> GeometryConfig:
    """The GeometryConfig of ``cfg``: a Config's, a GeometryConfig itself, or the default for None."""
    if cfg is None:
        return GeometryConfig()
    return cfg.geometry if isinstance(cfg, Config) else cfg
