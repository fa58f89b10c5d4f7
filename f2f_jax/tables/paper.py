"""The paper's numbers (fit2form-corl2020.tex, Table 1 and the appendix's Table 2), in percent, and
Table 2's conditions: what our tables are printed beside."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from f2f_jax.config import Config

TABLE1_COLUMNS: tuple[str, ...] = (
    "grasp", "S1", "S2", "S3", "S4", "S avg", "R-30", "R-20", "R-10", "R+10", "R+20", "R+30", "R avg",
)
STABILITY = ("S1", "S2", "S3", "S4")
ROBUSTNESS = ("R-30", "R-20", "R-10", "R+10", "R+20", "R+30")

PAPER_OBJECTS = 5127  # the paper's evaluation objects (8 unseen ShapeNet categories + Dex-Net)

PAPER_TABLE1: dict[str, dict[str, float]] = {name: dict(zip(TABLE1_COLUMNS, values)) for name, values in (
    ("WSG50", (25.8, 3.3, 2.1, 2.1, 1.9, 2.4, 12.2, 14.3, 17.6, 17.5, 14.6, 12.9, 14.8)),
    ("Imprint", (78.0, 64.9, 59.0, 57.3, 57.8, 59.8, 66.6, 68.9, 70.7, 70.0, 68.7, 67.0, 68.7)),
    ("RandEmb+FN", (21.3, 12.4, 6.5, 6.8, 6.6, 8.1, 12.7, 13.9, 16.4, 16.2, 13.4, 11.9, 14.1)),
    ("ImpGN", (28.9, 13.3, 10.4, 10.5, 10.3, 11.1, 17.1, 20.0, 23.2, 23.0, 19.5, 16.3, 19.8)),
    ("Fit2Form/ImpGN", (81.8, 65.6, 54.8, 59.0, 56.6, 59.0, 72.0, 73.9, 76.2, 75.1, 74.2, 73.4, 74.1)),
    ("Fit2Form GS", (85.2, 64.3, 57.0, 58.6, 53.3, 58.3, 71.0, 75.2, 78.5, 78.0, 74.0, 69.7, 74.4)),
    ("Fit2Form GS + R", (81.8, 62.8, 51.9, 53.3, 50.9, 54.7, 70.6, 72.9, 75.5, 74.6, 71.9, 69.5, 72.5)),
    ("Fit2Form GS + S", (87.5, 70.8, 66.0, 62.6, 64.1, 65.9, 75.7, 78.1, 81.4, 81.2, 78.3, 75.3, 78.3)),
    ("Fit2Form", (87.6, 69.0, 61.6, 60.5, 61.7, 63.2, 76.1, 78.3, 81.1, 81.1, 79.2, 76.8, 78.8)),
)}


@dataclass(frozen=True)
class Condition:
    """One column of Table 2: a change of the physics or of where the object lies.

    object_mass: kg (None: the config's 50 g); friction: finger-object coefficient (None: the
    config's 0.2); x_range, y_range: (lo, hi) m of the object's shift along x (the closing
    direction) and y, each drawn per object as sign * uniform(lo, hi) with a random sign
    (the paper's "x in +-[0.1, 0.5], y in +-[0.1, 1] cm"); None: no shift.
    """

    name: str
    object_mass: float | None = None
    friction: float | None = None
    x_range: tuple[float, float] | None = None
    y_range: tuple[float, float] | None = None

    def config(self, cfg: Config) -> Config:
        """``cfg`` with this condition's mass and friction (``SimConfig.object_mass`` and
        ``SimConfig.finger_friction``, which ``sim.evaluate`` passes to ``scene.build_model``).

        The paper changes the object's lateral friction; in PyBullet that multiplies into every
        contact of the object, here only the finger-object coefficient changes (the floor keeps
        ``object_friction``): what a grasp holds on to is the same, sliding on the floor is not.
        """
        changes = {}
        if self.object_mass is not None:
            changes["object_mass"] = float(self.object_mass)
        if self.friction is not None:
            changes["finger_friction"] = float(self.friction)
        return cfg.replace(sim=dataclasses.replace(cfg.sim, **changes)) if changes else cfg

    @property
    def moves_object(self) -> bool:
        return self.x_range is not None or self.y_range is not None


TABLE2_CONDITIONS: tuple[Condition, ...] = (
    Condition("Original"),
    Condition("m 100g", object_mass=0.100),
    Condition("m 150g", object_mass=0.150),
    Condition("mu 0.1", friction=0.1),
    Condition("mu 0.05", friction=0.05),
    Condition("x ±0.5, y ±1 cm", x_range=(0.001, 0.005), y_range=(0.001, 0.010)),
    Condition("x ±0.5, y ±2 cm", x_range=(0.001, 0.005), y_range=(0.001, 0.020)),
)
TABLE2_COLUMNS: tuple[str, ...] = tuple(c.name for c in TABLE2_CONDITIONS)

PAPER_TABLE2: dict[str, dict[str, float]] = {name: dict(zip(TABLE2_COLUMNS, values)) for name, values in (
    ("WSG50", (25.8, 2.2, 1.5, 6.7, 2.0, 24.8, 21.8)),
    ("Imprint", (78.0, 57.9, 49.4, 68.4, 63.9, 75.6, 72.8)),
    ("Fit2Form", (88.9, 63.9, 51.6, 76.3, 73.0, 86.3, 83.6)),
)}

# What a checkpoint's ``TrainedNets.objectives`` is called in Table 1.
OBJECTIVE_ROWS = {"full": "Fit2Form", "GS": "Fit2Form GS", "GS+R": "Fit2Form GS + R",
                  "GS+S": "Fit2Form GS + S", "imprint": "ImpGN"}

