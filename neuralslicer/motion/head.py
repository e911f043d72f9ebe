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


#: a part's membership rule (h_lo, strict, h_hi, slope, radius): h above h_lo (strictly when ``strict``), h at most
#: h_hi, and the distance from the axis at most slope h + radius (``in_rule``; the scan's kernel reads it too)
Rule = tuple[float, float, float, float, float]


def cone_rule(nozzle: Nozzle, min_height: float) -> Rule:
    """The cone above ``min_height`` (its top, h = cone_length, included)."""
    return (float(min_height), 0.0, nozzle.cone_length, float(np.tan(np.radians(nozzle.cone_half_angle_deg))), 0.0)


def holder_rule(nozzle: Nozzle) -> Rule:
    """The holder: above the cone (strictly), up to its top, within its radius."""
    L = nozzle.cone_length
    return (L, 1.0, L + nozzle.holder_length, 0.0, nozzle.holder_radius)


def in_rule(h: FloatArray, radial: FloatArray, rule: Rule) -> BoolArray:
    """Membership (k,) in a part given by its rule, at heights ``h`` along the axis and distances ``radial`` from it."""
    h_lo, strict, h_hi, slope, radius = rule
    low = h > h_lo if strict else h >= h_lo
    return low & (h <= h_hi) & (radial <= h * slope + radius)


def in_cone(h: FloatArray, radial: FloatArray, nozzle: Nozzle, min_height: float) -> BoolArray:
    """In the cone above ``min_height`` (``cone_rule``)."""
    return in_rule(h, radial, cone_rule(nozzle, min_height))


def in_holder(h: FloatArray, radial: FloatArray, nozzle: Nozzle) -> BoolArray:
    """In the holder (``holder_rule``)."""
    return in_rule(h, radial, holder_rule(nozzle))


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
