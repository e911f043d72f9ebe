"""Convolution surfaces of skeleton segments with the Cauchy kernel, in closed form.

The field of a skeleton is ``F(x) = sum_seg ∫_seg k(|x - s|) ds`` with the Cauchy kernel
``k(d) = 1 / (1 + c² d²)²`` (McCormack & Sherstyuk 1998).  Along a segment ``a + t u``,
``t ∈ [0, L]``, with ``h = (x - a)·u`` and ``d⊥`` the distance to the segment's line,
``|x - s(t)|² = d⊥² + (h - t)²``; substituting ``w = c (t - h)`` and ``p² = 1 + c² d⊥²``::

    ∫ k ds = (1/c) [G2(w)]_{-c h}^{c (L - h)},   G2(w) = w / (2p²(p²+w²)) + atan(w/p) / (2p³)

and the gradient ``∇F = -4c² ∫ (x - s) / (p² + w²)³ ds`` splits into the part across the line
(``(x - a - h u) · (1/c) [G3]``) and the part along it (``u · (1/c²) [1 / (4 (p²+w²)²)]``), with
``G3(w) = w / (4p²(p²+w²)²) + 3w / (8p⁴(p²+w²)) + 3 atan(w/p) / (8p⁵)``.

The raw field is not a distance.  :func:`distance_from_field` maps it through the inverse of the
field of an infinite straight line, ``F_line(d) = π / (2c (1 + c²d²)^{3/2})``, so that
``H = D(F) - R`` equals the exact signed distance for a long straight tube of radius ``R`` and
behaves like a distance (unit gradient, growing linearly far away) elsewhere; the iso threshold of
the convolution surface is ``T = F_line(R)``.  Deep inside (``F > F_line(R/2)``) ``H`` continues
linearly in ``F`` (C¹), so it stays finite and monotone where several segments overlap.
"""
from __future__ import annotations

import numpy as np

from neuralslicer.types import FloatArray

#: (point, segment) pairs evaluated at once: small enough that the temporaries stay in cache
#: (measured 5x faster than 1M-pair chunks on a 2-core machine).
PAIR_CHUNK = 32_768


def line_field(d: FloatArray | float, c: float) -> FloatArray:
    """Field ``F_line(d) = π / (2c (1 + c²d²)^{3/2})`` of an infinite straight line at distance d."""
    return np.pi / (2.0 * c * (1.0 + (c * np.asarray(d, dtype=np.float64)) ** 2) ** 1.5)


def segment_field(points: FloatArray, segments: FloatArray, c: float,
                  gradient: bool = True) -> tuple[FloatArray, FloatArray | None]:
    """Convolution field F and its gradient of the skeleton ``segments (m, 2, 3)`` at ``points (n, 3)``.

    Exact closed form (no quadrature), summed over every segment in chunks of points, so the cost is
    O(n m) time and O(n + PAIR_CHUNK) memory.  Returns ``F (n,)`` and ``∇F (n, 3)`` (None if not asked).
    """
    x = np.asarray(points, dtype=np.float64)
    seg = np.asarray(segments, dtype=np.float64)
    origin = seg.reshape(-1, 3).mean(axis=0)  # centre everything: keeps |x|² - h² accurate
    x = x - origin
    a = seg[:, 0] - origin
    axis = seg[:, 1] - seg[:, 0]
    length = np.linalg.norm(axis, axis=1)
    u = axis / length[:, None]
    a_u = np.einsum("ij,ij->i", a, u)
    a_a = np.einsum("ij,ij->i", a, a)
    n, m = len(x), len(seg)
    F = np.empty(n)
    grad = np.empty((n, 3)) if gradient else None
    step = max(1, PAIR_CHUNK // max(m, 1))
    for start in range(0, n, step):
        xs = x[start:start + step]
        h = xs @ u.T - a_u  # (nc, m)
        rr = np.einsum("ij,ij->i", xs, xs)[:, None] - 2.0 * (xs @ a.T) + a_a
        p2 = 1.0 + c * c * np.maximum(rr - h * h, 0.0)
        p = np.sqrt(p2)
        w0 = -c * h
        w1 = c * (length - h)
        q0 = p2 + w0 * w0
        q1 = p2 + w1 * w1
        # atan(w1/p) - atan(w0/p) in one call (w1 - w0 = c L > 0)
        at = np.arctan2(p * (w1 - w0), p2 + w0 * w1)
        F[start:start + step] = ((w1 / q1 - w0 / q0) / (2.0 * p2) + at / (2.0 * p2 * p)).sum(axis=1) / c
        if gradient:
            i3 = ((w1 / q1 ** 2 - w0 / q0 ** 2) / (4.0 * p2)
                  + 3.0 * (w1 / q1 - w0 / q0) / (8.0 * p2 * p2)
                  + 3.0 * at / (8.0 * p2 * p2 * p))
            j3 = 0.25 * (1.0 / q0 ** 2 - 1.0 / q1 ** 2)  # = [-1/(4 q²)] from w0 to w1
            # Σ (x - a - h u) i3 = x Σ i3 - i3 @ a - (h i3) @ u
            across = xs * i3.sum(axis=1)[:, None] - i3 @ a - (h * i3) @ u
            along = j3 @ u
            grad[start:start + step] = -4.0 * c * (across - along / c)
    return F, grad


def distance_from_field(F: FloatArray, c: float, radius: float) -> tuple[FloatArray, FloatArray]:
    """Distance-like ``H = D(F) - radius`` and ``dH/dF`` (see the module docstring)."""
    F = np.maximum(np.asarray(F, dtype=np.float64), 1e-300)
    f_line0 = np.pi / (2.0 * c)
    f_knee = float(line_field(0.5 * radius, c))
    q_knee = (f_line0 / f_knee) ** (2.0 / 3.0)
    h_knee = np.sqrt(q_knee - 1.0) / c - radius
    slope_knee = -q_knee / (3.0 * c * f_knee * np.sqrt(q_knee - 1.0))
    outer = F <= f_knee
    Fo = np.where(outer, F, f_knee)
    q = (f_line0 / Fo) ** (2.0 / 3.0)
    root = np.sqrt(np.maximum(q - 1.0, 1e-300))
    H = np.where(outer, root / c - radius, h_knee + slope_knee * (F - f_knee))
    dH = np.where(outer, -q / (3.0 * c * Fo * root), slope_knee)
    return H, dH


def radius_from_threshold(threshold: float, c: float) -> float:
    """Tube radius R whose line field equals the iso threshold T (inverse of ``T = F_line(R)``)."""
    q = (np.pi / (2.0 * c * threshold)) ** (2.0 / 3.0)
    if q <= 1.0:
        raise ValueError(f"threshold {threshold} is at least the field on the axis, π/(2c) = "
                         f"{np.pi / (2 * c):.6g}: the surface would be empty")
    return float(np.sqrt(q - 1.0) / c)
