"""The print head written out from its definition, for tests that check the collision code against it."""
from __future__ import annotations

import numpy as np

from neuralslicer.motion.profile import Nozzle

#: the head of the collision tests: a 30° cone 8 mm long under a 15 mm holder 30 mm long
NOZZLE = Nozzle(cone_half_angle_deg=30.0, cone_length=8.0, holder_radius=15.0, holder_length=30.0)


def inside_head(points: np.ndarray, tip: np.ndarray, axis: np.ndarray, nz: Nozzle, min_height: float = 0.0
                ) -> np.ndarray:
    """Exact membership of points (k, 3) in the cone (from ``min_height`` above the tip) + holder at one pose."""
    d = points - tip
    h = d @ axis
    radial = np.linalg.norm(d - h[:, None] * axis, axis=1)
    cone = (h >= min_height) & (h <= nz.cone_length) & (radial <= h * np.tan(np.radians(nz.cone_half_angle_deg)))
    holder = (h > nz.cone_length) & (h <= nz.cone_length + nz.holder_length) & (radial <= nz.holder_radius)
    return cone | holder
