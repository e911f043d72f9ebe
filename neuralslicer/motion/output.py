"""The motion step's output: the toolpaths as moved, the machine program, the print's metrics and its collisions."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from neuralslicer.motion.collision import CollisionReport, part_collisions
from neuralslicer.motion.planning import MachineProgram
from neuralslicer.toolpath.types import Toolpaths


@dataclass(frozen=True)
class Motion:
    """A planned print (the motion step's output, as a later step reads it; ``tasks/codec.py: StoredMotion`` is the
    same read from the store a part at a time)."""

    toolpaths: Toolpaths
    program: MachineProgram
    metrics: dict
    collisions: CollisionReport

    def part_collisions(self) -> tuple[np.ndarray, np.ndarray]:
        """(hits (k,3), witnesses (k,3)): where the head hit material or the platform (``part_collisions``)."""
        c = self.collisions
        return part_collisions(self.toolpaths.xyz, c.indices, c.kind, c.locations)

    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """One group: toolpaths/* (as moved), program/*, collisions/* and the metrics."""
        tp_arrays, tp_attrs = self.toolpaths.to_arrays()
        prog_arrays, prog_attrs = self.program.to_arrays()
        c = self.collisions
        arrays = {**{f"toolpaths/{k}": v for k, v in tp_arrays.items()},
                  **{f"program/{k}": v for k, v in prog_arrays.items()},
                  "collisions/indices": c.indices, "collisions/kind": c.kind,
                  "collisions/locations": np.asarray(c.locations, dtype=np.float64).reshape(-1, 3)}
        return arrays, {"toolpaths": tp_attrs, "program": prog_attrs, "metrics": self.metrics}


def print_hits(motion: Any) -> tuple[int, int, int]:
    """(colliding waypoints, those whose head hits material or the platform, those below the platform) of a
    :class:`Motion` or anything read like one."""
    m = motion.metrics
    return int(m.get("n_collisions", 0)), len(motion.part_collisions()[0]), int(m.get("n_platform_collisions", 0))
