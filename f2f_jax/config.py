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

import ast
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
    # object, cached on disk) or "tiles" (hulls over its depth map along the closing axis,
    # ~0.15 s, no cache; 94-95% of trials agree with coacd's, under the 96% a preset needs:
    # benchmarks/RESULTS.md).
    object_method: str = "coacd"
    # How a mesh becomes an object volume (``geometry.place_mesh``): "stretch", each axis scaled
    # to fill the cube (the paper's convention: a 2 x 1 x 1 box becomes a cube), or "fit", one
    # factor for all three axes (the shape kept).  The nets learn objects placed this way, so
    # ``design`` places a user's mesh the same way unless told otherwise ("real" keeps its size).
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
    # --- physics (reasons beside each value) ---
    # 4 ms with the implicitfast integrator (the ``fast`` preset): half the steps of 2 ms, with
    # outcomes that differ from 2 ms explicit Euler (the ``reference`` preset) about as much as
    # MuJoCo differs from itself when the object is 1% heavier: 98.2% and 98.4% of trials agree
    # on two sets of 256 builtin triples (test-retest 98.3%, 99.0%), 98.0% on 192 random_urdfs
    # triples (98.9%).  5 ms falls to 97.1% and drops 3 imprint grasps of 64.  implicitfast
    # takes the lift and jaw servos' stiffness and damping into the step (benchmarks/RESULTS.md).
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
    # The two jaws' fingers meet each other, as real fingers and the original's gripper
    # (self-collision on) do, so no design can close by passing through its partner.  On 320
    # builtin triples it changes no outcome and no time (RESULTS.md "The decision").  Fingers
    # never meet the floor: their cube's bottom voxel lies 1.5 mm below it (GeometryConfig.
    # rest_offset), and a floor pressing on them would drag the closing jaws.
    finger_collisions: bool = True
    # --- phases (s) ---
    settle_time: float = 0.2
    close_time: float = 0.4
    lift_height: float = 0.12  # m
    lift_time: float = 0.75
    hold_time: float = 1.0
    push_force: float = 1.5  # N (paper: 1.5 N)
    push_time: float = 1.0 / 12.0  # s (original: 20 steps of 1/240 s)
    # where the push acts: "com", the object's centre of mass (a push that only shoves), or
    # "origin", the world origin below the object's centre on the floor (the original's call,
    # which also twists the object); measured by benchmarks/protocol_fidelity.py --ablations
    push_point: str = "com"
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
    # touch nothing): 9% fewer steps, agreement with ``reference`` unchanged (98.12% against
    # 98.15% of 2,816 trials, benchmarks/RESULTS.md).  False settles every grasp (``reference``).
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
    # HeightGenerator: widths of its 3 x 3 convolutions over the (y, z) grid, and the truncation
    # (voxels) of the finger TSDFs it writes: the geometry's, so the fitness net sees imprint-like
    # volumes (GeometryConfig.truncation_voxels).
    height_channels: tuple[int, ...] = (64, 64, 64)
    height_truncation_voxels: float = 5.0
    # Fitness ResNet: one stride-2 conv per stage (the first 5^3, pad 2), then fitness_blocks
    # residual blocks at that width; a last stride-2 conv at the last width: 120x40x40 -> 1x1x1.
    fitness_channels: tuple[int, ...] = (32, 64, 128, 256, 512, 1024)
    fitness_blocks: tuple[int, ...] = (2, 2, 1, 1, 1, 1)
    fitness_fc: tuple[int, ...] = (512, 256, 128)
    fitness_stem_kernel: int = 5  # first stride-2 convolution (paper: 5^3; odd, padded to "same")
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
    # Generator-pretraining epochs after the gn_epochs, at generator_lr (an annealing phase: the
    # imprint loss plateaus noisily at lr, and co-training's own steps run at generator_lr).
    # Measured with 5 epochs on the default at 3 seeds: imprint L1 0.57-0.69 -> 0.38, ImpGN +0.18
    # trials of 11 on 61 objects, but Fit2Form after co-training -0.05: so 0 by default.
    gn_anneal_epochs: int = 0
    cycles: int = 20
    objects_per_cycle: int = 512  # paper
    cotrain_batch_size: int = 32  # 16 new + 16 pretrain (paper)
    fn_target_loss: float = 0.2
    gn_target_loss: float = -0.95
    min_epochs: int = 5
    max_epochs: int = 50
    max_steps_per_epoch: int = 500
    kl_weight: float = 0.0  # VAE KL weight; 0 is the original's plain reconstruction MSE
    # learning rate of the generator in the co-training cycles (None: lr).  It must move slower
    # than the fitness net can follow: at 1e-3 (the CPU default's lr) the generator learnt designs
    # the fitness net overrated and held-out grasp success fell from 0.77 to 0.59 in 9 cycles.
    generator_lr: float | None = None
    # generator objective: "GS", "GS+R", "GS+S" or "full" (Table 1), or "imprint": co-training's
    # control, as many generator steps on the imprints instead of against the fitness net
    objectives: str = "full"
    # Co-training trains the nets only once this many designs have been simulated (the original
    # code's cotrain_warmup_datapoints: 2048, four cycles of 512); the fitness net refits on all
    # designs simulated so far, half of each batch, the other half pretraining rows (as the original).
    warmup_designs: int = 2048
    # Weight of the squared latent distance to the imprint fingers in the generator's co-training
    # loss (0: the paper's -mean F alone); see steps.gn_fitness_step.
    imprint_anchor: float = 0.0
    # What the anchor pulls towards: "imprint" (the object's imprint fingers) or "best" (per
    # training object, the fingers that have passed the most simulated trials so far: its imprint,
    # replaced only by a cycle design that passed strictly more; the simulator, not the fitness
    # net, then says where the generator should go).
    anchor_target: str = "imprint"
    # Designs per object and cycle: the generator's own and cycle_candidates - 1 latent
    # perturbations of it (nets.inference.LATENT_NOISE), all simulated and stored (designs of one
    # object that differ a little, for the fitness net and for anchor_target="best").
    cycle_candidates: int = 1
    # Steps per epoch of the fitness net's refit in a cycle (None: max_steps_per_epoch, the
    # pretraining's cap).  A cycle that simulates K times the designs needs about K times the
    # steps for its fitness net to see each of them as often (benchmarks/RESULTS.md).
    fn_refit_steps: int | None = None
    # --- the run's data (experiments/cotrain.py) ---
    n_objects: int = 1000  # built-in objects made when no --objects directory is given
    test_fraction: float = 0.2  # held-out share of the objects (a seeded split, kept in the run's objects/)
    cut_pairs: int = 2  # pretraining pairs cut from other shapes, per object
    # Perturbed imprint pairs per object in the pretraining dataset (the imprint plus smooth random
    # fields of rising size, ``dataset.perturbed_pairs``): one object's designs that differ a
    # little, so the fitness net sees what separates its good fingers from its bad
    perturbed_pairs: int = 0
    # Their fields' largest peak, a share of the TSDF range (the k-th of K pairs gets k / K of it):
    # at 0.3, 5 of 16 builtin objects' imprint + 6 perturbed pairs differ in any trial; at 0.6, 8
    # (benchmarks/RESULTS.md)
    perturbed_peak: float = 0.3
    # More objects for the generator's pretraining alone: the imprint pairs of this many built-in
    # objects beyond the run's own (indices n_objects.. of the seed's stream: never one of the
    # run's objects, nor one of ``evaluate.py --fresh``'s, which come from another seed) join the
    # run's training imprints.  Nothing is simulated: ~0.3 s of TSDF per object on 2 cores, kept
    # in the run's imprint_objects/.
    imprint_objects: int = 0
    eval_objects: int = 64  # held-out objects scored after cycle 0 and after the last cycle


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
            # 2 cores against 625 ms for (8, 16, 16, 32, 32) at strides (2, 1, 2, 1, 1)
            encoder_channels=(4, 8, 16, 32), encoder_strides=(2, 2, 2, 1),
            # 4 -> 13 -> 40: two stride-3 transposed convolutions of kernel 4 (overlapping by one
            # voxel), nothing at full resolution but the output layer.  Against the first default's
            # 4 -> 12 -> 36 -> 38 -> 40 (kernel 3; two stride-1 layers at full resolution): a VAE
            # training step 2.6x cheaper (1.32 s against 3.44 s, batch 32, 2 cores), the whole run
            # 16 min instead of 36-43, and held-out IoU 0.676 / 0.582 / 0.487 against 0.634 /
            # 0.558 / 0.360 at seeds 0 / 1 / 2 (benchmarks/RESULTS.md)
            decoder_fc=(512, 1024), decoder_seed_size=4, decoder_channels=(16, 1),
            decoder_strides=(3, 3), decoder_kernels=(4, 4),
            generator_fc=(512, 512),
            fitness_channels=(4, 8, 16, 32), fitness_blocks=(0, 1, 1, 1), fitness_fc=(128, 64),
            # the height-map generator (benchmarks/RESULTS.md): on 61 objects its own
            # designs pass 1.5-1.6 trials of 11 more than the latent generator's at seed 0, after
            # pretraining and after co-training, 93% grasp against 77% ("latent": the paper's)
            generator="heights",
        ),
        # Co-training epochs 1..2 per net and cycle (paper: 5..50): the fitness net's refit is
        # under its target BCE after one epoch from cycle 4 on, and the generator never reaches
        # its target here, so it runs the cap (2 passes over the 51 training objects).  A cycle
        # costs ~27 s with the decoder above (~45 s with the first one, ~75 s with 2..6 epochs);
        # the whole run 16 min on 2 cores with seed 0's shipped pieces and the latent generator,
        # 19 min 43 s with the height generator (cycles 31-35 s), 29 min 57 s with
        # the 600 extra imprint objects below (+2.5 min of TSDFs, +9 min of
        # pretraining), longer at seeds whose 64 objects go through coacd first
        # (benchmarks/RESULTS.md).  The height generator's
        # pretraining: 12 passes of 2 steps an epoch, 480 steps (~2 min), where one pass (40
        # steps) leaves it far from the imprints; the latent generator's schedule was one pass
        # (``--set net.generator=latent --set train.gn_passes=1``: the default before the height generator).
        train=dataclasses.replace(
            base.train, lr=1e-3, generator_lr=1e-4, ae_epochs=40, ae_batch_size=32, fn_epochs=10, fn_batch_size=32,
            gn_epochs=20, gn_passes=12, objects_per_cycle=32, cotrain_batch_size=32, min_epochs=1, max_epochs=2,
            max_steps_per_epoch=8, n_objects=64, eval_objects=16, cut_pairs=1, warmup_designs=64,
            # the imprints of 600 built-in objects past the run's 64 join the generator's
            # pretraining (1,920 steps instead of 480: 12 passes are capped at 8 steps each):
            # on 61 objects its co-trained designs pass +0.44, +0.15 and +0.67 trials of 11 more
            # than without them at seeds 0, 1, 2, and co-training then adds +0.23..+0.43 trials
            # (benchmarks/RESULTS.md)
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
    warp`` on a GPU.  Its figures are in ``planned_simulations``; what it costs, measured and
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


CONFIGS = {"tiny": tiny, "default": default, "paper": paper, "workstation": workstation}


def held_out_count(n: int, test_fraction: float) -> int:
    """How many of ``n`` objects a split holds out (``TrainConfig.test_fraction``): the share,
    rounded, with at least one object on each side when there are two or more."""
    return min(max(int(round(test_fraction * n)), 1), n - 1) if n >= 2 else 0


def planned_simulations(cfg: Config, n_objects: int | None = None) -> dict[str, int]:
    """How many 11-trial evaluations a run of ``cfg`` simulates, by stage, on ``n_objects`` objects
    (default: the config's built-in ``n_objects``): the pretraining dataset (at most: cut and
    perturbed pairs that cannot be made feasibly are skipped), the held-out baselines (imprint
    and flat pads; WSG-FMF with the pybullet extra adds one per held-out object), the co-training
    cycles' designs and the two held-out evaluations of the generator; "total" sums them."""
    t = cfg.train
    n = t.n_objects if n_objects is None else n_objects
    n_test = held_out_count(n, t.test_fraction)
    out = {"dataset": (n - n_test) * (2 + t.cut_pairs + t.perturbed_pairs), "baselines": 2 * n_test,
           "cycles": t.cycles * t.objects_per_cycle * t.cycle_candidates,
           "heldout": 2 * min(t.eval_objects, n_test)}
    out["total"] = sum(out.values())
    return out


def planned_row_bytes(cfg: Config, n_objects: int | None = None) -> int:
    """Bytes of the grasp rows a run of ``cfg`` holds in memory by its last cycle: the pretraining
    dataset and every cycle's designs, two float16 finger volumes each, and one float16 volume per
    object (rows share their object's: ``train.run_data.SharedVolumes``)."""
    plan = planned_simulations(cfg, n_objects)
    n = cfg.train.n_objects if n_objects is None else n_objects
    return (2 * (plan["dataset"] + plan["cycles"]) + n) * 2 * cfg.geometry.resolution ** 3

# Simulation presets: the collision geometry and the protocol's early exits, by name.  "fast" is
# what every config above uses; "reference" is the first build's simulator (every phase run to
# its full length), the judge that benchmarks/sim_agreement.py compares the fast preset with:
# on 256 mixed builtin triples 98.1% of trials agree (a 1% heavier object: 98.3%) with 3.9x fewer
# steps (benchmarks/RESULTS.md).  Only the fields named here differ between presets.
SIM_PRESETS: dict[str, dict[str, dict]] = {
    "fast": dict(geometry=dict(object_method="coacd"),
                 sim=dict(timestep=0.004, integrator="implicitfast", rest_speed=0.002,
                          rest_time=0.1, shared_settle=True)),
    "reference": dict(geometry=dict(object_method="coacd"),
                      sim=dict(timestep=0.002, integrator="euler", rest_speed=0.0, rest_time=0.1,
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

SECTIONS = ("geometry", "sim", "net", "train")


def override(cfg: Config, assignments) -> Config:
    """``cfg`` with ``SECTION.FIELD=VALUE`` assignments applied in order (the command lines'
    ``--set``), e.g. ``["train.generator_lr=3e-4", "sim.timestep=0.002", "net.fitness_fc=(256, 128)"]``.

    Every field of the four sections can be set; the value is read as the field's type (int,
    float, bool, str, a tuple, or None where the field allows it) and anything else is refused
    with a ValueError that names the field and what it takes.
    """
    for text in assignments:
        key, sep, raw = str(text).partition("=")
        section, dot, name = key.strip().partition(".")
        if not sep or not dot or not name:
            raise ValueError(f"--set {text!r}: expected SECTION.FIELD=VALUE, e.g. train.generator_lr=3e-4")
        if section not in SECTIONS:
            raise ValueError(f"--set {key}: no config section {section!r}; choose one of "
                             f"{', '.join(SECTIONS)}")
        part = getattr(cfg, section)
        fields = {f.name: f for f in dataclasses.fields(part)}
        if name not in fields:
            raise ValueError(f"--set {key}: {section} has no field {name!r}; its fields: {', '.join(fields)}")
        value = _read_value(raw.strip(), str(fields[name].type), key.strip())
        cfg = cfg.replace(**{section: dataclasses.replace(part, **{name: value})})
    return cfg


def _read_value(raw: str, annotation: str, key: str):
    """``raw`` as a value of the field type ``annotation`` (the dataclass's annotation string)."""
    base = annotation.replace("| None", "").strip()
    kind = f"{'an' if base[0] in 'aeiou' else 'a'} {base}"
    if raw.lower() == "none":
        if "None" in annotation:
            return None
        raise ValueError(f"--set {key}=None: {key} takes {kind}, not None")
    if base == "str":
        return raw
    if base == "bool":
        if raw.lower() in ("true", "false"):
            return raw.lower() == "true"
        raise ValueError(f"--set {key}={raw}: {key} takes true or false")
    try:
        value = ast.literal_eval(raw)
    except (ValueError, SyntaxError):
        raise ValueError(f"--set {key}={raw}: {key} takes {kind}") from None
    if base == "int" and isinstance(value, int) and not isinstance(value, bool):
        return value
    if base == "float" and isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if base.startswith("tuple") and isinstance(value, (tuple, list)):
        return tuple(tuple(v) if isinstance(v, list) else v for v in value)
    raise ValueError(f"--set {key}={raw}: {key} takes {kind}")
