"""The print head's geometry in its own frame: membership, enclosing balls, lowest point, platform clearance.

The head is a cone (apex at the tool tip, axis along the tool axis, half angle and length from the profile)
topped by a holder cylinder. Material closer to the tip than ``min_height`` along the axis is the bead being
laid and never counts. A point is described by its height ``h`` along the axis above the tip and its distance
``radial`` from the axis: both parts are solids of revolution, convex in the (h, radial) half-plane.
"""
from __future__ import annotations

import numpy as np

from neuralslicer.motion.profile import Nozzle
from neuralslicer.types import BoolArray, FloatArray


def axial(d: FloatArray, axis: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Height along the axis and distance from it (k,) of offsets ``d = point - tip`` (k, 3), axes (k, 3) unit."""
    h = np.einsum("ij,ij->i", d, axis)
    return h, np.sqrt(np.maximum(np.einsum("ij,ij->i", d, d) - h * h, 0.0))


def cone_bottom(nozzle: Nozzle, min_height: float) -> float:
    """Height of the cone's lowest counted cross-section: ``min_height`` clipped to [0, cone_length]."""
    return min(max(min_height, 0.0), nozzle.cone_length)


def in_cone(h: FloatArray, radial: FloatArray, nozzle: Nozzle, min_height: float) -> BoolArray:
    """In the cone above ``min_height`` (its top, h = cone_length, included)."""
    ta = np.tan(np.radians(nozzle.cone_half_angle_deg))
    return (h >= min_height) & (h <= nozzle.cone_length) & (radial <= h * ta)


def in_holder(h: FloatArray, radial: FloatArray, nozzle: Nozzle) -> BoolArray:
    """In the holder: above the cone (strictly), up to its top, within its radius."""
    L = nozzle.cone_length
    return (h > L) & (h <= L + nozzle.holder_length) & (radial <= nozzle.holder_radius)


def _inside_head(d: FloatArray, axis: FloatArray, nozzle: Nozzle, min_height: float) -> BoolArray:
    """Exact membership of offsets ``d = point - tip`` (k,3) in the head along ``axis`` (k,3)."""
    h, radial = axial(d, axis)
    return in_cone(h, radial, nozzle, min_height) | in_holder(h, radial, nozzle)


def cone_ball(nozzle: Nozzle, min_height: float) -> tuple[float, float]:
    """(height of the centre on the axis, radius) of the smallest ball on the axis enclosing the cone above
    ``min_height`` (its two rims)."""
    ta = np.tan(np.radians(nozzle.cone_half_angle_deg))
    a, b = cone_bottom(nozzle, min_height), nozzle.cone_length
    ra, rb = a * ta, b * ta
    c = float(np.clip((b * b + rb * rb - a * a - ra * ra) / (2 * (b - a) + 1e-300), a, b))
    return c, float(max(np.hypot(c - a, ra), np.hypot(b - c, rb)))


def holder_ball(nozzle: Nozzle) -> tuple[float, float]:
    """(height of the centre on the axis, radius) of the ball enclosing the holder."""
    half = 0.5 * nozzle.holder_length
    return nozzle.cone_length + half, float(np.hypot(half, nozzle.holder_radius))


def platform_clearance(xyz: FloatArray, axis: FloatArray, nozzle: Nozzle, platform_z: float) -> FloatArray:
    """Height of the lowest point of the head above the platform, per waypoint (n,) (exact)."""
    az = np.clip(axis[:, 2], -1.0, 1.0)
    horiz = np.sqrt(np.maximum(0.0, 1.0 - az ** 2))
    L, ta = nozzle.cone_length, np.tan(np.radians(nozzle.cone_half_angle_deg))
    low = np.minimum(0.0, L * az - L * ta * horiz)
    if nozzle.holder_length > 0:
        for h in (L, L + nozzle.holder_length):
            low = np.minimum(low, h * az - nozzle.holder_radius * horiz)
    return xyz[:, 2] + low - platform_z


def head_lowest_z(xyz: FloatArray, axis: FloatArray, nozzle: Nozzle, min_height: float) -> FloatArray:
    """Lowest z (n,) of the part of the head above ``min_height`` along the tool axis (what ``_inside_head``
    counts), for tips ``xyz`` (n, 3) and unit axes (n, 3); exact up to rounding. The cone frustum and the
    holder are linear in the height along the axis, so the lowest point lies on one of their end rims."""
    az = np.clip(axis[:, 2], -1.0, 1.0)
    horiz = np.sqrt(np.maximum(0.0, 1.0 - az ** 2))
    L, ta = nozzle.cone_length, np.tan(np.radians(nozzle.cone_half_angle_deg))
    h0 = cone_bottom(nozzle, min_height)
    low = np.minimum(h0 * (az - ta * horiz), L * (az - ta * horiz))
    if nozzle.holder_length > 0:
        for h in (L, L + nozzle.holder_length):
            low = np.minimum(low, h * az - nozzle.holder_radius * horiz)
    return xyz[:, 2] + low
