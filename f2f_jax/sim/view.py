"""Look at one grasp: a PNG strip of the trial phases, so a person can see why a grasp failed
(``render_trials``; the command is ``python -m f2f_jax.cli.view``).

Panels: after settling, after closing, after lifting, after holding (the grasp), then the end of
each push S1..S4 and of each turned grasp R-30..R+30, titled with the trial's outcome.  Drawn
with matplotlib from the simulated poses of the collision pieces (no OpenGL needed).
"""

from __future__ import annotations

import dataclasses

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402
from scipy.spatial import ConvexHull  # noqa: E402

from f2f_jax.config import TRIAL_NAMES, Config  # noqa: E402
from f2f_jax.fileio import atomic_path  # noqa: E402
from f2f_jax.sim.protocol import GraspRunner, run_trials  # noqa: E402


@dataclasses.dataclass
class Frame:
    label: str
    geom_xpos: np.ndarray  # [G, 3]
    geom_xmat: np.ndarray  # [G, 9]


class RecordingRunner(GraspRunner):
    """A GraspRunner that keeps the geom poses at the end of every phase it runs."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.frames: list[Frame] = []
        self.trial = "grasp"
        self._phase = 0

    def snapshot(self, label: str) -> None:
        mujoco.mj_kinematics(self.model, self.data)
        self.frames.append(Frame(label, self.data.geom_xpos.copy(), self.data.geom_xmat.copy()))

    def advance(self, n, *, stop_below=None, chunk=25, until_rest=False):
        try:
            return super().advance(n, stop_below=stop_below, chunk=chunk, until_rest=until_rest)
        finally:
            self._phase += 1
            self.snapshot(f"{self.trial}:{self._phase}")

    def grasp(self, yaw):
        self._phase = 0
        self.trial = "grasp" if not self.frames else f"turn {np.rad2deg(yaw):+.0f}°"
        return super().grasp(yaw)

    def push(self, state, z_start, direction):
        self._phase = 0
        self.trial = f"push {np.round(direction, 2).tolist()}"
        return super().push(state, z_start, direction)


def _geom_faces(model: mujoco.MjModel, geom: int) -> np.ndarray | None:
    """[F, 3, 3] triangles of a mesh geom in its own frame."""
    if model.geom_type[geom] != mujoco.mjtGeom.mjGEOM_MESH:
        return None
    mesh = model.geom_dataid[geom]
    adr, num = model.mesh_vertadr[mesh], model.mesh_vertnum[mesh]
    verts = np.asarray(model.mesh_vert[adr: adr + num], np.float64)
    try:
        hull = ConvexHull(verts)
    except Exception:  # noqa: BLE001 - a degenerate placeholder piece is simply not drawn
        return None
    return verts[hull.simplices]


OBJECT_COLOUR = (0.85, 0.45, 0.2, 1.0)
FINGER_COLOUR = (0.25, 0.45, 0.8, 0.25)  # see-through, so the object inside a cage stays visible


@dataclasses.dataclass
class Strip:
    """One simulator's run of a triple, ready to draw: the panels (frame, title), each piece's
    triangles in its own frame (metres) and colour, keyed by the frames' piece index."""

    label: str
    panels: list[tuple[Frame, str]]
    faces: dict[int, np.ndarray]
    colours: dict[int, tuple]
    outcome: np.ndarray


def _draw(ax, frame: Frame, faces: dict, colours: dict, title: str, top_cm: float):
    for g, tri in faces.items():
        rot = frame.geom_xmat[g].reshape(3, 3)
        world = tri @ rot.T + frame.geom_xpos[g]
        ax.add_collection3d(Poly3DCollection(world * 100, facecolor=colours[g],
                                             edgecolor=(0, 0, 0, 0.15), linewidths=0.1))
    half = max(8.0, (top_cm + 1) / 2)
    ax.plot([-half, half], [0, 0], [0, 0], color="0.4", lw=1)  # the floor, seen edge-on
    ax.set(xlim=(-half, half), ylim=(-half, half), zlim=(-1, 2 * half - 1))
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=15, azim=-80)  # nearly along -y: the jaws close left-right
    ax.set_title(title, fontsize=8)
    ax.set_xticks([]), ax.set_yticks([]), ax.set_zticks([])


def _top_cm(strip: Strip) -> float:
    """Highest drawn point of a strip's panels (cm)."""
    top = 0.0
    for frame, _ in strip.panels:
        for g, tri in strip.faces.items():
            z = tri.reshape(-1, 3) @ frame.geom_xmat[g].reshape(3, 3)[2] + frame.geom_xpos[g][2]
            top = max(top, float(z.max()))
    return 100 * top


def trial_strip(model: mujoco.MjModel, cfg: Config, label: str = "MuJoCo") -> Strip:
    """Run the 11 trials of one model, keeping the panels to draw: after settling, after
    closing, the grasp's end, then the end of each push and turned grasp."""
    runner = RecordingRunner(model, cfg)
    result = run_trials(model, cfg, runner=runner)
    ids = runner.ids
    shown = {int(g): OBJECT_COLOUR for g in ids.object_geoms}
    shown.update({int(g): FINGER_COLOUR for g in ids.all_finger_geoms})
    faces = {g: f for g in shown if (f := _geom_faces(model, g)) is not None}
    # The last frame of each trial, plus the grasp's phases.
    by_trial: dict[str, list[Frame]] = {}
    for f in runner.frames:
        by_trial.setdefault(f.label.split(":")[0], []).append(f)
    grasp_frames = by_trial.pop("grasp", [])
    panels = [(f, name) for name, f in zip(("settled", "closed"), grasp_frames[:2])]
    if grasp_frames:
        panels.append((grasp_frames[-1], f"grasp: {'held' if result.outcome[0] else 'dropped'}"))
    for k, (trial, frames) in enumerate(by_trial.items()):
        index = 1 + k
        ok = result.outcome[index] if index < len(result.outcome) else 0
        panels.append((frames[-1], f"{TRIAL_NAMES[index]}: {'held' if ok else 'failed'}"))
    label = f"{label}: {_scores(result.outcome)} ({result.steps} steps)"
    return Strip(label, panels, faces, {g: shown[g] for g in faces}, result.outcome)


def _scores(outcome) -> str:
    scores = "".join(str(int(v)) for v in outcome)
    return f"{scores[0]} {scores[1:5]} {scores[5:]}"


def draw_strips(strips: list[Strip], path, title: str = "", cols: int = 5) -> None:
    """Draw strips one under another (each on its own rows, ``cols`` panels a row) to ``path``
    (PNG, written atomically), on one scale: the highest point of any panel fits."""
    top = max([_top_cm(s) for s in strips] + [14.0])
    layout = []  # (strip, panel index) per grid cell, None where a strip's last row ends early
    for strip in strips:
        n = len(strip.panels)
        cells = list(range(n)) + [None] * (-n % cols)
        layout += [(strip, i) if i is not None else None for i in cells]
    rows = max(1, len(layout) // cols)
    fig = plt.figure(figsize=(3 * cols, 3 * rows))
    for cell, item in enumerate(layout):
        if item is None:
            continue
        strip, i = item
        frame, name = strip.panels[i]
        name = f"{strip.label}\n{name}" if i == 0 and len(strips) > 1 else name
        _draw(fig.add_subplot(rows, cols, cell + 1, projection="3d"), frame, strip.faces,
              strip.colours, name, top)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=80, format="png")
    plt.close(fig)


def render_trials(model: mujoco.MjModel, cfg: Config, path) -> np.ndarray:
    """Run the 11 trials of one model, draw the phases to ``path`` (PNG); returns the outcome."""
    strip = trial_strip(model, cfg)
    draw_strips([strip], path, title=f"outcome {strip.label.split(': ', 1)[1]}",
                cols=min(len(strip.panels), 5))
    return strip.outcome
