"""Marching triangles, chaining and resampling against analytic isolines."""
from __future__ import annotations

import numpy as np
import pytest

from neuralslicer.toolpath.isolines import chain_segments, isoline_points, resample_polylines
from neuralslicer.toolpath.synthetic import disc_layer, square_layer


def test_straight_isolines_of_a_coordinate_lie_on_the_level():
    m = square_layer(0.0, size=10.0, n=13)
    levels = np.array([-3.3, 0.1, 2.7])
    iso = isoline_points(m.faces, m.vertices[:, 0], levels)
    pts = iso.interpolate(m.vertices)
    assert np.allclose(pts[:, 0], levels[iso.level], atol=1e-12)
    poly = chain_segments(iso.segments, len(pts))
    assert len(poly) == 3 and not poly.closed.any()
    for i in range(3):
        ids = poly.ids[poly.offsets[i]:poly.offsets[i + 1]]
        y = pts[ids, 1]
        # each line crosses the whole square, monotonically
        assert np.isclose(abs(y[-1] - y[0]), 10.0)
        assert np.all(np.diff(y) > 0) or np.all(np.diff(y) < 0)


def test_radial_isolines_are_closed_loops_oriented_consistently():
    m = disc_layer(0.0, radius=5.0, n_rings=20, n_sectors=64)
    r = np.linalg.norm(m.vertices[:, :2], axis=1)
    iso = isoline_points(m.faces, r, np.array([1.1, 3.3]))
    pts = iso.interpolate(m.vertices)
    poly = chain_segments(iso.segments, len(pts))
    assert len(poly) == 2 and poly.closed.all()
    for i in range(2):
        ids = poly.ids[poly.offsets[i]:poly.offsets[i + 1]]
        assert ids[0] == ids[-1]
        p = pts[ids]
        # larger values on the left (w.r.t. +z normal): the loop runs clockwise around the centre
        area = 0.5 * np.sum(p[:-1, 0] * p[1:, 1] - p[1:, 0] * p[:-1, 1])
        assert area < 0


def test_resampling_keeps_ends_and_bounds_the_spacing():
    t = np.linspace(0, 1, 7)
    a = np.column_stack([t * 10, np.zeros(7), np.zeros(7)])
    b = np.array([[0, 0, 0], [4, 0, 0], [4, 4, 0.0]])            # a sharp corner at (4, 0)
    pts, off, attr = resample_polylines(np.vstack([a, b]), np.array([0, 7, 10]), 0.3,
                                        attributes=np.arange(10.0)[:, None])
    assert len(off) == 3
    first, second = pts[off[0]:off[1]], pts[off[1]:off[2]]
    assert np.allclose(first[[0, -1]], a[[0, -1]]) and np.allclose(second[[0, -1]], b[[0, -1]])
    for p in (first, second):
        assert np.linalg.norm(np.diff(p, axis=0), axis=1).max() <= 0.3 + 1e-12
    assert np.any(np.all(np.isclose(second, [4, 0, 0]), axis=1)), "corner vertex kept"
    assert np.isclose(attr[off[1] - 1, 0], 6.0) and np.isclose(attr[0, 0], 0.0)


@pytest.mark.parametrize("n_points", [0, 5])
def test_chaining_nothing(n_points):
    poly = chain_segments(np.zeros((0, 2), np.int64), n_points)
    assert len(poly) == 0
