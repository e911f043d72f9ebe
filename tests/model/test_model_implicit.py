"""Implicit components against analytic shapes: values, signs, gradients, round trips."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.integrate import quad

from neuralslicer.model.components import (
    MeshComponent, ShellComponent, StrutsComponent, TubesComponent,
)
from neuralslicer.model.convolution import (
    distance_from_field, line_field, radius_from_threshold, segment_field,
)
from neuralslicer.model.solid import Solid

RNG = np.random.default_rng(7)


def sphere_points(n: int, r0: float, r1: float) -> np.ndarray:
    """Points at radii in [r0, r1] around the origin."""
    d = RNG.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * RNG.uniform(r0, r1, size=(n, 1))


def fd_gradient(f, x: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """Central finite differences of a batched scalar function."""
    cols = [(f(x + eps * e) - f(x - eps * e)) / (2 * eps) for e in np.eye(3)]
    return np.stack(cols, axis=1)


@pytest.fixture(scope="module")
def sphere() -> MeshComponent:
    """Icosphere of radius 10 (20,480 faces)."""
    m = trimesh.creation.icosphere(subdivisions=5, radius=10.0)
    return MeshComponent(m.vertices, m.faces)


@pytest.fixture(scope="module")
def torus() -> tuple[MeshComponent, float, float]:
    """Torus R = 10, r = 3 finely tessellated."""
    m = trimesh.creation.torus(10.0, 3.0, major_sections=160, minor_sections=64)
    return MeshComponent(m.vertices, m.faces), 10.0, 3.0


def test_sphere_mesh_signed_distance(sphere: MeshComponent) -> None:
    x = sphere_points(4000, 8.0, 12.0)
    exact = np.linalg.norm(x, axis=1) - 10.0
    H, G = sphere.value_and_grad(x)
    tol = 0.01 * sphere.feature_size
    assert abs(sphere.feature_size - 2 * 10 / 3) < 0.05
    assert np.abs(H - exact).max() < tol
    assert np.all(np.sign(H[np.abs(exact) > tol]) == np.sign(exact[np.abs(exact) > tol]))
    # far away and at the centre
    assert sphere.value(np.array([[0.0, 0.0, 0.0]]))[0] == pytest.approx(-10.0, abs=tol)
    assert sphere.value(np.array([[30.0, 0.0, 0.0]]))[0] == pytest.approx(20.0, abs=tol)
    # gradient: unit, radial within ~1 degree, and equal to finite differences off the surface
    radial = x / np.linalg.norm(x, axis=1, keepdims=True)
    assert np.allclose(np.linalg.norm(G, axis=1), 1.0)
    assert np.degrees(np.arccos(np.clip((G * radial).sum(1), -1, 1))).max() < 2.0
    off = x[np.abs(exact) > 0.5][:200]
    assert np.allclose(sphere.value_and_grad(off)[1], fd_gradient(sphere.value, off), atol=1e-4)


def test_inverted_and_holey_mesh_keeps_sign() -> None:
    m = trimesh.creation.icosphere(subdivisions=4, radius=5.0)
    inverted = MeshComponent(m.vertices, m.faces[:, ::-1])  # inward normals are fixed on load
    assert inverted.value(np.zeros((1, 3)))[0] < 0
    holey = MeshComponent(m.vertices, m.faces[5:])  # a small hole: winding number still ~1 inside
    x = sphere_points(500, 0.0, 4.0)
    assert np.all(holey.value(x) < 0)
    assert np.all(holey.value(sphere_points(500, 6.0, 9.0)) > 0)


def test_torus_mesh_signed_distance(torus) -> None:
    comp, R, r = torus
    theta = RNG.uniform(0, 2 * np.pi, 3000)
    phi = RNG.uniform(0, 2 * np.pi, 3000)
    rho = RNG.uniform(r - 1.0, r + 1.0, 3000)
    x = np.stack([(R + rho * np.cos(phi)) * np.cos(theta), (R + rho * np.cos(phi)) * np.sin(theta),
                  rho * np.sin(phi)], axis=1)
    exact = np.hypot(np.hypot(x[:, 0], x[:, 1]) - R, x[:, 2]) - r
    tol = 0.01 * comp.feature_size
    assert comp.feature_size == pytest.approx(r, rel=0.01)
    H = comp.value(x)
    assert np.abs(H - exact).max() < tol
    assert comp.value(np.zeros((1, 3)))[0] > 0  # the hole is outside
    assert comp.value(np.array([[R, 0.0, 0.0]]))[0] == pytest.approx(-r, abs=tol)


def capsule_exact(x: np.ndarray, a: np.ndarray, b: np.ndarray, r: float) -> np.ndarray:
    """Closed-form distance to a capsule."""
    ab = b - a
    t = np.clip(((x - a) @ ab) / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(x - (a + t[:, None] * ab), axis=1) - r


def test_struts_capsules_exact() -> None:
    a, b = np.array([1.0, -2.0, 0.5]), np.array([6.0, 3.0, 4.0])
    c2 = np.array([-5.0, 0.0, 0.0])
    comp = StrutsComponent(np.array([[a, b], [b, c2]]), radius=1.5)
    x = RNG.uniform(-8, 9, size=(3000, 3))
    exact = np.minimum(capsule_exact(x, a, b, 1.5), capsule_exact(x, b, c2, 1.5))
    H, G = comp.value_and_grad(x)
    assert np.abs(H - exact).max() < 1e-9
    away = np.abs(H + 1.5) > 0.05
    assert np.allclose(G[away], fd_gradient(comp.value, x[away]), atol=1e-5)
    assert comp.min_z == pytest.approx(0.0 - 1.5)
    assert comp.feature_size == 3.0


def open_cylinder(radius: float, height: float, sections: int = 256, rings: int = 20) -> trimesh.Trimesh:
    """Open cylinder surface (no caps) around the z axis, z in [0, height]."""
    th = np.linspace(0, 2 * np.pi, sections, endpoint=False)
    z = np.linspace(0, height, rings + 1)
    v = np.stack([np.tile(radius * np.cos(th), rings + 1), np.tile(radius * np.sin(th), rings + 1),
                  np.repeat(z, sections)], axis=1)
    i = np.arange(sections)
    j = (i + 1) % sections
    faces = []
    for k in range(rings):
        a, b, c, d = k * sections + i, k * sections + j, (k + 1) * sections + j, (k + 1) * sections + i
        faces += [np.stack([a, b, c], 1), np.stack([a, c, d], 1)]
    return trimesh.Trimesh(v, np.concatenate(faces), process=False)


def test_cylinder_shell() -> None:
    cyl = open_cylinder(10.0, 20.0)
    comp = ShellComponent(cyl.vertices, cyl.faces, thickness=2.0)
    th = RNG.uniform(0, 2 * np.pi, 3000)
    rho = RNG.uniform(8.0, 12.0, 3000)
    x = np.stack([rho * np.cos(th), rho * np.sin(th), RNG.uniform(2.0, 18.0, 3000)], axis=1)
    exact = np.abs(rho - 10.0) - 1.0
    H, G = comp.value_and_grad(x)
    assert np.abs(H - exact).max() < 0.01 * comp.feature_size
    outward = np.sign(rho - 10.0)[:, None] * np.stack([np.cos(th), np.sin(th), 0 * th], 1)
    assert np.degrees(np.arccos(np.clip((G * outward).sum(1), -1, 1))).max() < 1.0
    assert comp.value(np.array([[0.0, 0.0, 10.0]]))[0] == pytest.approx(9.0, abs=0.02)
    # beyond the rim: distance to the rim circle
    assert comp.value(np.array([[10.0, 0.0, 23.0]]))[0] == pytest.approx(2.0, abs=1e-6)


def test_convolution_segment_matches_quadrature() -> None:
    a, b = np.array([0.5, -1.0, 2.0]), np.array([4.0, 2.0, -1.0])
    c = 0.8
    x = RNG.uniform(-4, 6, size=(12, 3))
    F, G = segment_field(x, np.array([[a, b]]), c)
    L = np.linalg.norm(b - a)
    for xi, fi in zip(x, F):
        ref = quad(lambda t: (1 + c * c * np.sum((xi - a - t * (b - a)) ** 2)) ** -2, 0, 1,
                   epsabs=1e-14, epsrel=1e-12)[0] * L
        assert fi == pytest.approx(ref, rel=1e-9)
    fd = fd_gradient(lambda p: segment_field(p, np.array([[a, b]]), c, gradient=False)[0], x)
    assert np.allclose(G, fd, rtol=1e-6, atol=1e-9)


def test_convolution_two_segments_add_and_chunking(monkeypatch) -> None:
    from neuralslicer.model import convolution

    seg = RNG.uniform(-3, 3, size=(7, 2, 3))
    x = RNG.uniform(-5, 5, size=(50, 3))
    F_all, G_all = segment_field(x, seg, 1.1)
    F_sum = sum(segment_field(x, seg[i:i + 1], 1.1)[0] for i in range(7))
    assert np.allclose(F_all, F_sum, rtol=1e-12)
    monkeypatch.setattr(convolution, "PAIR_CHUNK", 20)  # force many chunks
    F_chunked, G_chunked = segment_field(x, seg, 1.1)
    assert np.allclose(F_chunked, F_all, rtol=1e-13) and np.allclose(G_chunked, G_all, rtol=1e-12)


def test_line_field_and_distance_transform() -> None:
    c, R = 0.5, 2.0
    d = np.linspace(0.0, 20.0, 201)
    F = line_field(d, c)
    # closed form of ∫_{-inf}^{inf} (1 + c²(d² + t²))^-2 dt, checked by quadrature at one d
    ref = quad(lambda t: (1 + c * c * (3.0 ** 2 + t * t)) ** -2, -np.inf, np.inf)[0]
    assert float(line_field(3.0, c)) == pytest.approx(ref, rel=1e-10)
    H, dH = distance_from_field(F, c, R)
    outer = d >= R / 2
    assert np.allclose(H[outer], d[outer] - R, atol=1e-10)
    assert np.all(np.diff(H) > 0)  # monotone in d, also in the linear inner part
    assert radius_from_threshold(float(line_field(R, c)), c) == pytest.approx(R)
    fd = (distance_from_field(F * (1 + 1e-7), c, R)[0] - distance_from_field(F * (1 - 1e-7), c, R)[0]) / (2e-7 * F)
    assert np.allclose(dH, fd, rtol=1e-5)


def test_tube_long_segment_is_distance_like() -> None:
    R = 2.0
    comp = TubesComponent(np.array([[[0.0, 0.0, -200.0], [0.0, 0.0, 200.0]]]), radius=R)
    th = RNG.uniform(0, 2 * np.pi, 500)
    rho = RNG.uniform(R - 0.5, R + 0.5, 500)
    x = np.stack([rho * np.cos(th), rho * np.sin(th), RNG.uniform(-5, 5, 500)], 1)
    H, G = comp.value_and_grad(x)
    assert np.abs(H - (rho - R)).max() < 0.01 * comp.feature_size
    radial = np.stack([np.cos(th), np.sin(th), 0 * th], 1)
    assert np.degrees(np.arccos(np.clip((G * radial).sum(1), -1, 1))).max() < 0.5
    assert np.allclose(G, fd_gradient(comp.value, x), atol=1e-5)
    hollow = TubesComponent(comp.segments, radius=R, wall=0.5)
    Hh = hollow.value(x)
    assert np.allclose(Hh, np.maximum(rho - R, -(rho - R) - 0.5), atol=0.01 * hollow.feature_size)
    assert hollow.value(np.zeros((1, 3)))[0] > 0  # the bore is outside


def test_tube_skeleton_gradient_and_sign() -> None:
    pts = np.array([[0, 0, 0], [10, 0, 0], [10, 10, 0], [0, 10, 5]], float)
    comp = TubesComponent(np.stack([pts[:-1], pts[1:]], axis=1), radius=1.5)
    on_axis = np.array([[5.0, 0, 0], [10, 5, 0], [10, 0, 0]])
    assert np.all(comp.value(on_axis) < -1.0)
    assert np.all(comp.value(np.array([[5.0, 5.0, 0.0], [30, 30, 30]])) > 0)
    x = RNG.uniform(-3, 13, size=(300, 3))
    assert np.allclose(comp.value_and_grad(x)[1], fd_gradient(comp.value, x), rtol=1e-5, atol=1e-6)


def test_union_and_smooth_union_gradients(sphere: MeshComponent) -> None:
    struts = StrutsComponent(np.array([[[0.0, 0, 0], [25.0, 0, 0]]]), radius=2.0)
    hard = Solid([sphere, struts])
    x = sphere_points(400, 0.0, 20.0)
    assert np.allclose(hard.H(x), np.minimum(sphere.value(x), struts.value(x)))
    soft = Solid([sphere, struts], smooth_union=2.0)
    Hs = soft.H(x)
    assert np.all(Hs <= hard.H(x) + 1e-12) and np.all(Hs >= hard.H(x) - 2.0 / 4 - 1e-12)
    away = np.abs(sphere.value(x)) > 0.3
    assert np.allclose(soft.grad_H(x[away]), fd_gradient(soft.H, x[away]), atol=1e-4)


def test_solid_round_trip_identical(sphere: MeshComponent) -> None:
    comps = [sphere,
             ShellComponent(*(lambda c: (c.vertices + [0, 0, 15], c.faces))(open_cylinder(5.0, 10.0, 32, 4)), 1.0),
             StrutsComponent(np.array([[[0.0, 0, 0], [25.0, 0, 0]]]), radius=2.0),
             TubesComponent(np.array([[[0.0, 0, -20], [0.0, 10, -25]]]), radius=1.0, c=0.7, wall=0.3)]
    solid = Solid(comps, platform_z=-30.0, smooth_union=0.5, meta={"up": "y"})
    arrays, attrs = solid.to_arrays()
    import json

    attrs = json.loads(json.dumps(attrs))
    again = Solid.from_arrays({k: np.array(v) for k, v in arrays.items()}, attrs)
    x = RNG.uniform(-30, 30, size=(2000, 3))
    assert np.array_equal(solid.H(x), again.H(x))
    assert np.array_equal(solid.grad_H(x), again.grad_H(x))
    assert again.platform_z == -30.0 and again.meta == {"up": "y"}
    assert again.feature_size == solid.feature_size == 0.3


def test_surface_marching_cubes_of_struts() -> None:
    solid = Solid([StrutsComponent(np.array([[[0.0, 0, 0], [10.0, 0, 0]]]), radius=2.0)])
    surf = solid.surface()
    assert surf.is_watertight
    assert np.abs(solid.H(surf.vertices)).max() < 1e-6
    exact = np.pi * 4 * 10 + 4 / 3 * np.pi * 8
    assert solid.volume() == pytest.approx(exact, rel=0.08)  # inscribed polygons at voxel r/2
    assert solid.surface(voxel=0.1).volume == pytest.approx(exact, rel=0.002)
    assert np.allclose(solid.bounds, [[-2, -2, -2], [12, 2, 2]])
    assert solid.platform_z == -2.0


def test_tubes_bounds_from_surface() -> None:
    comp = TubesComponent(np.array([[[0.0, 0, 0], [20.0, 0, 0]]]), radius=2.0)
    solid = Solid([comp])
    lo, hi = solid.bounds
    # middle of a long tube: radius ≈ R; caps: shorter than a capsule (the field fades at the ends)
    assert lo[1] == pytest.approx(-2.0, abs=0.05) and hi[2] == pytest.approx(2.0, abs=0.05)
    assert -2.0 < lo[0] < 0.5 and 19.5 < hi[0] < 22.0
    assert solid.platform_z == pytest.approx(lo[2])


@pytest.mark.parametrize("spread", [0.0, 0.3])
def test_values_above_counts_and_maxes_like_every_point_evaluated(sphere, spread, monkeypatch):
    """``values_above`` (cube centres certify most points) gives the count above tol and the largest value of H at
    every point: waypoint-like points inside the mesh sphere, some just outside (``spread``), none outside."""
    from neuralslicer.model import grid

    monkeypatch.setattr(grid, "ABOVE_DIRECT", 1_000)
    monkeypatch.setattr(grid, "ABOVE_CUBES", 2_000)
    monkeypatch.setattr(grid, "ABOVE_BLOCK", 777)         # the points' bounds made in blocks
    pts = sphere_points(40_000, 0.0, 9.8 + spread)
    calls = []

    def H(x):
        calls.append(len(x))
        return sphere.value(x)

    h = sphere.value(pts)
    count, best = grid.values_above(H, pts, 1e-3)
    assert count == int((h > 1e-3).sum()) and best == pytest.approx(float(h.max()), abs=0)
    assert (count > 0) == (spread > 0)
    assert sum(calls) < 0.7 * len(pts)           # the deep points are certified by their cube's centre
    direct = grid.values_above(H, pts[:500], 1e-3)
    assert direct == (int((h[:500] > 1e-3).sum()), float(h[:500].max()))


def test_values_above_evaluates_the_points_whose_bound_tops_the_largest_value(monkeypatch):
    """Points all deep inside a ball (no point is near its surface): the largest value found among the first
    evaluated points is below the bounds of others, which are evaluated too, so the maximum is exact."""
    from neuralslicer.model import grid

    monkeypatch.setattr(grid, "ABOVE_DIRECT", 10)
    monkeypatch.setattr(grid, "ABOVE_CUBES", 64)
    pts = sphere_points(5_000, 0.0, 3.0)
    H = lambda x: np.linalg.norm(x, axis=1) - 10.0        # noqa: E731 - the ball of radius 10
    count, best = grid.values_above(H, pts, 1e-3)
    assert count == 0 and best == pytest.approx(float(H(pts).max()), abs=0)
