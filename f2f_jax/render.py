"""Pictures a person can look at: a grasp (object and two fingers in the gripper) and grids of shapes.

Drawn with matplotlib's 3D polygons on an off-screen Agg canvas (no OpenGL, no display, no global
backend switch), from surfaces made by ``geometry.tsdf_to_mesh`` and placed with
``geometry.finger_pose``.  A full-resolution surface (~15-25k triangles) draws in well under a
second; ``step=2`` averages the volume over 2x2x2 blocks first (~4k triangles, blocky edges) for
large grids.

    render_grasp("grasp.png", obj, left, right, scores=outcome, title="imprint")
    render_volumes("shapes.png", tsdfs, titles=names)
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle
from mpl_toolkits.mplot3d.art3d import Poly3DCollection

from f2f_jax.config import TRIAL_NAMES, GeometryConfig
from f2f_jax.fileio import atomic_path
from f2f_jax.geometry import finger_pose, tsdf_to_mesh

OBJECT_COLOUR = (0.55, 0.58, 0.62)  # grey
LEFT_COLOUR = (0.90, 0.62, 0.10)  # orange
RIGHT_COLOUR = (0.20, 0.55, 0.85)  # blue
SUCCESS_COLOUR = (0.20, 0.70, 0.30)
FAILURE_COLOUR = (0.85, 0.20, 0.20)
FLOOR_COLOUR = (0.85, 0.85, 0.80, 0.5)
_LIGHT = np.array([-0.4, -0.6, 0.7]) / np.linalg.norm([-0.4, -0.6, 0.7])  # from front-left, above
# (title, elevation, azimuth, orthographic): front looks along +y (x right, z up), top down -z
VIEWS = (("front", 0.0, -90.0, True), ("top", 90.0, -90.0, True), ("iso", 25.0, -55.0, False))


def _geometry(cfg) -> GeometryConfig:
    """A Config, a GeometryConfig or None (defaults) -> GeometryConfig."""
    if cfg is None:
        return GeometryConfig()
    return cfg if isinstance(cfg, GeometryConfig) else cfg.geometry


def volume_mesh(tsdf, cfg: GeometryConfig | None = None, *, step: int = 1, name: str = "tsdf"):
    """Surface of a volume for drawing: vertices [V, 3] and faces [F, 3] in the volume's frame (m).

    step: average the volume over step^3 blocks first (fewer triangles); falls back to full
    resolution when a thin shape would vanish at the coarse size.
    """
    cfg = cfg or GeometryConfig()
    arr = np.asarray(tsdf, np.float32)
    r = cfg.resolution
    if step > 1 and r % step == 0:
        coarse = arr.reshape(r // step, step, r // step, step, r // step, step).mean((1, 3, 5))
        # voxel centres of the coarse grid are the block centres, so the frame is unchanged
        if (coarse < 0).any() and (coarse >= 0).any():
            mesh = tsdf_to_mesh(coarse, dataclasses.replace(cfg, resolution=r // step), name=name)
            return np.asarray(mesh.vertices), np.asarray(mesh.faces)
    mesh = tsdf_to_mesh(arr, cfg, name=name)
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def _transform(vertices: np.ndarray, pose: np.ndarray) -> np.ndarray:
    return vertices @ pose[:3, :3].T + pose[:3, 3]


def grasp_scene(object_tsdf=None, left_tsdf=None, right_tsdf=None, *, opening: float = 0.0,
                cfg=None, step: int = 1) -> list[tuple[np.ndarray, np.ndarray, tuple]]:
    """The parts of a grasp in world coordinates: [(vertices [V,3] m, faces [F,3], rgb), ...].

    The object rests on the floor (its volume frame lowered by ``rest_offset``); each finger's
    mount plane is ``cube_size + opening`` from the gripper's centre plane x = 0, so at
    ``opening=0`` an imprint finger's tip plane (w = 6 cm) reaches the object's mid-plane.
    """
    g = _geometry(cfg)
    parts = []
    if object_tsdf is not None:
        v, f = volume_mesh(object_tsdf, g, step=step, name="object")
        parts.append((v + [0.0, 0.0, g.rest_offset], f, OBJECT_COLOUR))
    mount = g.cube_size + opening
    for side, tsdf, colour, x in (("left", left_tsdf, LEFT_COLOUR, -mount),
                                   ("right", right_tsdf, RIGHT_COLOUR, mount)):
        if tsdf is not None:
            v, f = volume_mesh(tsdf, g, step=step, name=f"{side} finger")
            parts.append((_transform(v, finger_pose(side, x, g)), f, colour))
    return parts


def _shade(vertices: np.ndarray, faces: np.ndarray, colour, alpha: float = 1.0) -> np.ndarray:
    """Per-face RGBA [F, 4] with Lambert shading from a fixed light."""
    tri = vertices[faces]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    # two-sided light: both sides of a face are seen from some view
    lambert = np.abs(normals @ _LIGHT)
    rgb = np.clip(np.asarray(colour)[None, :3] * (0.35 + 0.65 * lambert[:, None]), 0.0, 1.0)
    return np.concatenate([rgb, np.full((len(rgb), 1), alpha)], axis=1)


def _draw_parts(ax, parts, bounds: np.ndarray, *, elev: float, azim: float, ortho: bool,
                floor: bool = True, finger_alpha: float = 1.0, zoom: float = 1.0) -> None:
    for vertices, faces, colour in parts:
        alpha = 1.0 if colour == OBJECT_COLOUR else finger_alpha
        poly = Poly3DCollection(vertices[faces], facecolors=_shade(vertices, faces, colour, alpha),
                                edgecolors="none", linewidths=0)
        ax.add_collection3d(poly)
    lo, hi = bounds
    if floor:
        fx = [lo[0], hi[0], hi[0], lo[0]]
        fy = [lo[1], lo[1], hi[1], hi[1]]
        ax.add_collection3d(Poly3DCollection([list(zip(fx, fy, [0.0] * 4))], facecolors=[FLOOR_COLOUR],
                                             edgecolors=[(0.5, 0.5, 0.5, 0.6)], linewidths=0.5))
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(lo[2], hi[2])
    ax.set_box_aspect(hi - lo, zoom=zoom)
    ax.view_init(elev=elev, azim=azim)
    ax.set_proj_type("ortho" if ortho else "persp")
    ax.set_axis_off()


def _scene_bounds(parts, pad: float = 0.004) -> np.ndarray:
    allv = np.concatenate([v for v, _, _ in parts])
    lo, hi = allv.min(0) - pad, allv.max(0) + pad
    lo[2] = min(lo[2], 0.0)  # always show the floor
    return np.stack([lo, hi])


def _draw_scores(ax, scores) -> None:
    """A row of boxes grasp, S1..S4, R-30..R+30: green where the trial succeeded (>= 0.5)."""
    scores = np.asarray(scores, dtype=float).ravel()
    if scores.shape != (len(TRIAL_NAMES),):
        raise ValueError(f"scores: expected {len(TRIAL_NAMES)} values ({', '.join(TRIAL_NAMES)}), "
                         f"got shape {scores.shape}")
    binary = np.all((scores == 0) | (scores == 1))
    for k, (name, s) in enumerate(zip(TRIAL_NAMES, scores)):
        colour = SUCCESS_COLOUR if s >= 0.5 else FAILURE_COLOUR
        ax.add_patch(Rectangle((k + 0.06, 0.08), 0.88, 0.84, facecolor=colour, edgecolor="black", lw=0.8))
        label = name if binary else f"{name}\n{s:.2f}"
        ax.text(k + 0.5, 0.5, label, ha="center", va="center", color="white", fontsize=9, weight="bold")
    ax.set_xlim(0, len(TRIAL_NAMES))
    ax.set_ylim(0, 1)
    ax.set_axis_off()


def _save(fig: Figure, path) -> Path:
    """Write the figure as PNG atomically: a temporary file in the same folder, then a rename."""
    path = Path(path)
    FigureCanvasAgg(fig)
    with atomic_path(path) as tmp:
        with open(tmp, "xb") as f:
            fig.savefig(f, format="png")
    return path


def render_grasp(path, object_tsdf=None, left_tsdf=None, right_tsdf=None, *, title: str | None = None,
                 scores=None, opening: float = 0.0, cfg=None, step: int = 1, dpi: int = 90) -> Path:
    """Draw an object and two fingers as the gripper holds them, in three views; save a PNG.

    object_tsdf, left_tsdf, right_tsdf: [40, 40, 40] volumes (any may be None, not all).
    scores: optional [11] outcomes or probabilities, drawn as a row of green/red boxes
    (grasp, S1..S4, R-30..R+30).  opening: extra distance (m) each finger's mount stands back
    from full closure (mount planes at x = -/+ (cube_size + opening)).  cfg: Config or
    GeometryConfig.  Returns the path written.
    """
    if object_tsdf is None and left_tsdf is None and right_tsdf is None:
        raise ValueError("render_grasp: give at least one of object_tsdf, left_tsdf, right_tsdf")
    parts = grasp_scene(object_tsdf, left_tsdf, right_tsdf, opening=opening, cfg=cfg, step=step)
    bounds = _scene_bounds(parts)
    has_scores = scores is not None
    fig = Figure(figsize=(12, 4.0 if has_scores else 3.4), dpi=dpi)
    bottom = 0.13 if has_scores else 0.0
    top = 0.9 if title else 1.0
    # see-through fingers when there is an object: closed imprint fingers would hide it
    finger_alpha = 0.5 if object_tsdf is not None else 1.0
    for k, (name, elev, azim, ortho) in enumerate(VIEWS):
        ax = fig.add_axes([k / 3, bottom, 1 / 3, top - bottom], projection="3d")
        _draw_parts(ax, parts, bounds, elev=elev, azim=azim, ortho=ortho, finger_alpha=finger_alpha,
                    zoom=1.1)
        ax.text2D(0.5, 0.95, name, transform=ax.transAxes, ha="center", fontsize=10)
    if title:
        fig.suptitle(title, fontsize=12)
    if has_scores:
        _draw_scores(fig.add_axes([0.05, 0.01, 0.9, 0.11]), scores)
    return _save(fig, path)


def render_volumes(path, tsdfs, titles=None, *, ncols: int | None = None, cfg=None, step: int = 1,
                   panel_size: float = 2.2, dpi: int = 80, elev: float = 25.0, azim: float = -55.0) -> Path:
    """Draw a grid of shapes, one iso view each, in their volume frames; save a PNG.

    tsdfs: [N, 40, 40, 40] or a list of volumes; titles: N strings (or None).
    """
    g = _geometry(cfg)
    tsdfs = list(tsdfs)
    if not tsdfs:
        raise ValueError("render_volumes: no volumes to draw")
    if titles is not None and len(titles) != len(tsdfs):
        raise ValueError(f"render_volumes: {len(titles)} titles for {len(tsdfs)} volumes")
    n = len(tsdfs)
    ncols = ncols or int(np.ceil(np.sqrt(n * 4 / 3)))
    nrows = int(np.ceil(n / ncols))
    fig = Figure(figsize=(panel_size * ncols, panel_size * nrows), dpi=dpi)
    h = g.cube_size / 2
    bounds = np.array([[-h, -h, 0.0], [h, h, g.cube_size]])
    for i, tsdf in enumerate(tsdfs):
        row, col = divmod(i, ncols)
        ax = fig.add_axes([col / ncols, 1 - (row + 1) / nrows, 1 / ncols, 0.92 / nrows], projection="3d")
        v, f = volume_mesh(tsdf, g, step=step, name=titles[i] if titles else f"volume {i}")
        _draw_parts(ax, [(v, f, OBJECT_COLOUR)], bounds, elev=elev, azim=azim, ortho=False, floor=False,
                    zoom=1.15)
        if titles:
            ax.set_title(str(titles[i]), fontsize=8, y=0.95)
    return _save(fig, path)
