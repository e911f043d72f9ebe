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


def _annulus(r_in: float, r_out: float, n_rings: int, n_sectors: int):
    """Planar annulus (polar grid): vertices (n, 3), faces (m, 3), both rims regular n_sectors-gons."""
    r = np.linspace(r_in, r_out, n_rings + 1)
    t = np.linspace(0, 2 * np.pi, n_sectors, endpoint=False)
    rr, tt = np.meshgrid(r, t, indexing="ij")
    v = np.column_stack([(rr * np.cos(tt)).ravel(), (rr * np.sin(tt)).ravel(), np.zeros(rr.size)])
    idx = lambda i, j: i * n_sectors + (j % n_sectors)  # noqa: E731
    j = np.arange(n_sectors)
    f = [np.stack(q, 1) for i in range(n_rings)
         for q in ((idx(i, j), idx(i + 1, j), idx(i + 1, j + 1)), (idx(i, j), idx(i + 1, j + 1), idx(i, j + 1)))]
    return v, np.concatenate(f)


def _polygon_distance(points: np.ndarray, r: float, n: int) -> np.ndarray:
    """Distance (brute force) from points (k, 3) in z = 0 to the regular n-gon of circumradius r."""
    t = np.linspace(0, 2 * np.pi, n + 1)
    a = np.column_stack([r * np.cos(t[:-1]), r * np.sin(t[:-1])])
    b = np.column_stack([r * np.cos(t[1:]), r * np.sin(t[1:])])
    p = points[:, None, :2]
    u = np.clip(np.einsum("kmj,mj->km", p - a, b - a) / np.einsum("mj,mj->m", b - a, b - a), 0, 1)
    return np.linalg.norm(p - (a + u[..., None] * (b - a)), axis=2).min(axis=1)


def test_boundary_distance_isolines_on_a_refined_annulus_match_the_exact_offsets():
    """Shell isolines of the straight-line boundary distance, on a coarse annulus refined near its rims only,
    lie at the level from the nearer rim (an independent brute-force distance to both polygons)."""
    from neuralslicer.toolpath.geometry import Patch, boundary_distance, refine_patch

    v, f = _annulus(4.0, 10.0, 2, 48)                                       # edges 1-3 mm
    patch = refine_patch(Patch(v, f, np.tile([0.0, 0.0, 1.0], (len(v), 1))), 0.25, band=1.5)
    d = boundary_distance(patch, upper=1.5)
    exact = np.minimum(_polygon_distance(patch.vertices, 4.0, 48), _polygon_distance(patch.vertices, 10.0, 48))
    assert np.allclose(d, np.minimum(exact, 1.5), atol=1e-9)               # exact at every vertex, clipped
    levels = np.array([0.25, 0.75, 1.25])
    iso = isoline_points(patch.faces, d, levels)
    pts = iso.interpolate(patch.vertices)
    poly = chain_segments(iso.segments, len(pts))
    assert len(poly) == 6 and poly.closed.all()                            # one loop per rim and level
    at = np.minimum(_polygon_distance(pts, 4.0, 48), _polygon_distance(pts, 10.0, 48))
    # linear interpolation is exact along the straight rims; near the polygon corners d bends
    assert np.abs(at - levels[iso.level]).max() < 0.02
    assert np.median(np.abs(at - levels[iso.level])) < 1e-9


def test_segment_distances_and_ray_hits_match_brute_force():
    from neuralslicer.toolpath.geometry import ElementSet, TriangleSet

    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(40, 3)), rng.normal(size=(40, 3))
    v = np.concatenate([a, b])
    segs = np.column_stack([np.arange(40), 40 + np.arange(40)])
    p = rng.normal(size=(500, 3)) * 2
    ab = b - a
    u = np.clip(np.einsum("kmj,mj->km", p[:, None] - a, ab) / np.einsum("mj,mj->m", ab, ab), 0, 1)
    brute = np.linalg.norm(p[:, None] - (a + u[..., None] * ab), axis=2).min(axis=1)
    assert np.allclose(ElementSet(v, segs).distance(p), brute, atol=1e-12)
    # rays down onto a planar disc at z = 1: hit at z - 1 when inside it, none beyond reach or outside
    m = disc_layer(1.0, radius=5.0, n_rings=6, n_sectors=40)
    tris = TriangleSet(np.asarray(m.vertices), np.asarray(m.faces))
    o = np.column_stack([rng.uniform(-6, 6, (300, 2)), rng.uniform(1.1, 4.0, 300)])
    down = np.tile([0.0, 0.0, -1.0], (300, 1))
    t = tris.ray_distance(o, down, reach=2.0)
    inside = np.linalg.norm(o[:, :2], axis=1) < 5.0 * np.cos(np.pi / 40) - 1e-6
    expect = np.where(inside & (o[:, 2] - 1.0 <= 2.0), o[:, 2] - 1.0, np.inf)
    outside_rim = np.linalg.norm(o[:, :2], axis=1) > 5.0
    sure = inside | outside_rim                                             # skip the rim's polygon sliver
    assert np.allclose(t[sure], expect[sure], atol=1e-6)
