"""What a co-training run holds while it works, in one place: ``RunState``.

``CoTrainRun.run`` makes it once the run's data is ready and its newest checkpoint is restored, and
hands it to every stage (``CoTrainRun``'s pretraining, ``cycle.run_cycle``); nothing else about a
run changes while it runs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from f2f_jax.train.checkpoint import Checkpoints
from f2f_jax.train.run_data import RunData, read_rows

STAGES = ("ae", "fn", "gn", "cycle")  # a checkpoint's stage, in the order a run makes them
NOTHING_DONE = (-1, 0, 0)


@dataclass
class RunState:
    """A run's working state.

    data: its objects, split, grasp store and pretraining rows (``run_data.RunData``); heldout:
    the held-out baseline rows (imprint, flat pads, WSG-FMF) of the evaluation objects; ckpt: its
    checkpoints; nets: the three nets' ``TrainState`` ("ae", "fn", "gn") and "key" (as
    ``state.fresh_run_state`` makes them), replaced after every epoch; position: (stage index in
    ``STAGES``, epoch, cycle) of the newest checkpoint, ``NOTHING_DONE`` before any; generated:
    (c, every design simulated in cycles 1..c), kept between cycles (``cycle.generated_rows``);
    pairs: the generator's pretraining pairs, made on first use (``CoTrainRun.imprint_pairs``);
    teacher: the teacher objects of a run taught by the simulator or the imprints
    (``teacher.teacher_set``), made on first use.
    """

    data: RunData
    heldout: dict[str, np.ndarray]
    ckpt: Checkpoints
    nets: dict
    position: tuple[int, int, int] = NOTHING_DONE
    generated: tuple[int, dict[str, np.ndarray]] | None = None
    pairs: dict[str, np.ndarray] | None = None
    teacher: object | None = None  # teacher.TeacherSet

    def done(self, stage: str, epoch: int = 0, cycle: int = 0) -> bool:
        """Whether the newest checkpoint is at or after (stage, epoch, cycle)."""
        return (STAGES.index(stage), epoch, cycle) <= self.position

    def models_tree(self) -> dict:
        """The generator's and the fitness net's variables: a checkpoint's ``models`` item."""
        return {"generator": self.nets["gn"].variables, "fitness": self.nets["fn"].variables}

    def rows(self, select: Callable[[int, str], bool], shared: bool = False) -> dict[str, np.ndarray]:
        """Store rows (``read_rows``); ``shared``: their object volumes shared from the run's
        objects (``SharedVolumes``) rather than read, one copy per object however many rows."""
        if not shared:
            return read_rows(self.data.store, select)
        return read_rows(self.data.store, select, objects=(self.data.object_table, self.data.names))
