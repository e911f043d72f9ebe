"""Stress-following infill: its pieces against closed forms and independent algorithms, and what it prints."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial import Delaunay, cKDTree

from neuralslicer.fea import FEASpec, run_fea
from neuralslicer.verify import verify_layers
from neuralslicer.fea.samples import stress_field
from neuralslicer.fea.shapes import BoxSolid
from neuralslicer.verify import printed_tangents
from neuralslicer.stress_field import StressField
from neuralslicer.toolpath import ToolpathConfig, toolpaths
from neuralslicer.toolpath import stress_infill as si
from neuralslicer.toolpath.synthetic import square_layer


class Analytic:
    """A stress field given by a function of the point (the StressLike protocol)."""

    def __init__(self, fn, reference: float = 1.0) -> None:
        """Tensors (n, 3, 3) = fn(points (n, 3))."""
        self.fn, self.reference_mpa = fn, reference

    def tensor_at(self, points: np.ndarray) -> np.ndarray:
        """The tensors at the points."""
        return self.fn(np.asarray(points, np.float64).reshape(-1, 3))


def uniaxial(direction) -> Analytic:
    """sigma = d d^T everywhere."""
    d = np.asarray(direction, np.float64) / np.linalg.norm(direction)
    return Analytic(lambda p: np.broadcast_to(np.outer(d, d), (len(p), 3, 3)).copy())


def in_plane(sxx, syy, sxy) -> Analytic:
    """A plane stress field (functions of x, y) in the xy plane."""
    def fn(p: np.ndarray) -> np.ndarray:
        t = np.zeros((len(p), 3, 3))
        t[:, 0, 0], t[:, 1, 1] = sxx(p[:, 0], p[:, 1]), syy(p[:, 0], p[:, 1])
        t[:, 0, 1] = t[:, 1, 0] = sxy(p[:, 0], p[:, 1])
        return t
    return Analytic(fn)


# the two half-index singular points of a 2-D line field at the origin: sigma = [[x, y], [y, -x]] (wedge)
# and [[x, -y], [-y, -x]] (trisector), both traceless: isotropic (zero) at the origin only
WEDGE = in_plane(lambda x, y: x / 10, lambda x, y: -x / 10, lambda x, y: y / 10)
TRISECTOR = in_plane(lambda x, y: x / 10, lambda x, y: -x / 10, lambda x, y: -y / 10)


def disc_with_hole(radius: float = 15.0, hole: float = 4.0, centre=(0.0, 0.0), z: float = 0.5,
                   rings: int = 40, sectors: int = 160) -> trimesh.Trimesh:
    """A planar annulus (polar grid) at height z, LPD +z: a patch with a round hole."""
    r = np.linspace(hole, radius, rings)
    t = np.linspace(0, 2 * np.pi, sectors, endpoint=False)
    rr, tt = np.meshgrid(r, t, indexing="ij")
    v = np.column_stack([centre[0] + (rr * np.cos(tt)).ravel(), centre[1] + (rr * np.sin(tt)).ravel(),
                         np.full(rr.size, z)])
    idx = np.arange(rings * sectors).reshape(rings, sectors)
    a, b = idx[:-1], np.roll(idx[:-1], -1, axis=1)
    c, d = np.roll(idx[1:], -1, axis=1), idx[1:]
    f = np.concatenate([np.stack([a.ravel(), b.ravel(), c.ravel()], 1), np.stack([a.ravel(), c.ravel(), d.ravel()], 1)])
    m = trimesh.Trimesh(v, f, process=False)
    m.vertex_attributes["lpd"] = np.tile([0.0, 0.0, 1.0], (len(v), 1))
    m.metadata["isovalue"] = z
    return m


def rect_layer(z: float, lx: float, ly: float, h: float = 0.5) -> trimesh.Trimesh:
    """A planar lx x ly rectangle from the origin at height z, grid spacing h, LPD +z."""
    nx, ny = int(round(lx / h)) + 1, int(round(ly / h)) + 1
    grid = np.stack(np.meshgrid(np.linspace(0, lx, nx), np.linspace(0, ly, ny), indexing="ij"), -1).reshape(-1, 2)
    idx = np.arange(nx * ny).reshape(nx, ny)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    m = trimesh.Trimesh(np.column_stack([grid, np.full(len(grid), z)]),
                        np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]), process=False)
    m.vertex_attributes["lpd"] = np.tile([0.0, 0.0, 1.0], (len(grid), 1))
    m.metadata["isovalue"] = z
    return m


def printed_moves(tp) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Extruding moves: midpoints (k, 3), unit directions (k, 3), lengths (k,)."""
    ext = np.flatnonzero(tp.extrude[1:]) + 1
    d = tp.xyz[ext] - tp.xyz[ext - 1]
    length = np.linalg.norm(d, axis=1)
    ok = length > 1e-9
    return 0.5 * (tp.xyz[ext] + tp.xyz[ext - 1])[ok], d[ok] / length[ok, None], length[ok]


def inside(layer: trimesh.Trimesh, points: np.ndarray, margin: float) -> np.ndarray:
    """Points (k, 3) at least ``margin`` from the layer's boundary (k,) bool: off the shells and line ends."""
    from neuralslicer.toolpath.geometry import ElementSet, boundary_vertices

    edges = boundary_vertices(np.asarray(layer.faces))[1]
    return ElementSet(np.asarray(layer.vertices), edges).distance(points) > margin


def largest_gap(tp, layer: trimesh.Trimesh, n: int = 30_000) -> float:
    """The radius of the largest disc of the layer no printed bead covers (beads as wide as their waypoints)."""
    ext = np.flatnonzero(tp.extrude[1:]) + 1
    a, b = tp.xyz[ext - 1], tp.xyz[ext]
    t = np.linspace(0, 1, 9)[:, None, None]
    dense = (a[None] * (1 - t) + b[None] * t).reshape(-1, 3)
    width = np.tile(0.5 * (tp.width[ext - 1] + tp.width[ext]), 9)
    pts = trimesh.sample.sample_surface_even(layer, n, seed=0)[0]
    dist, i = cKDTree(dense).query(pts, k=8)
    return float((dist - 0.5 * width[i]).min(axis=1).max())


def test_in_plane_stress_is_projected_tau_max_for_a_uniaxial_stress() -> None:
    """sigma = s tau tau^T on a plane with normal n: direction P tau / |P tau|, magnitude s |P tau|^2, decisiveness 1;
    an isotropic in-plane state and pure shear 0 (no principal stress is the larger)."""
    rng = np.random.default_rng(0)
    tau = rng.normal(size=(50, 3))
    tau /= np.linalg.norm(tau, axis=1, keepdims=True)
    n = rng.normal(size=(50, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    s = rng.uniform(-3, 3, 50)
    direction, magnitude, anisotropy = si.in_plane_stress(s[:, None, None] * np.einsum("ni,nj->nij", tau, tau), n)
    p = tau - np.sum(tau * n, axis=1, keepdims=True) * n
    assert np.allclose(np.abs(np.sum(direction * p, axis=1)), np.linalg.norm(p, axis=1), atol=1e-9)
    assert np.allclose(magnitude, np.abs(s) * np.sum(p * p, axis=1))
    assert np.allclose(anisotropy, 1.0)                      # decisiveness
    assert np.allclose(np.sum(direction * n, axis=1), 0.0, atol=1e-12)
    iso = np.diag([2.0, 2.0, 5.0])[None]
    shear = np.array([[[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]])
    z = np.array([[0.0, 0.0, 1.0]])
    assert si.in_plane_stress(iso, z)[2][0] == pytest.approx(0.0)
    assert si.in_plane_stress(shear, z)[2][0] == pytest.approx(0.0)
    # sigma = diag(3, 1): the in-plane principal stress of largest magnitude is 3 along x, decisiveness (3 - 1) / (3 + 1)
    d, mag, coh = si.in_plane_stress(np.diag([3.0, 1.0, 7.0])[None], z)
    assert abs(d[0, 0]) == pytest.approx(1.0) and mag[0] == pytest.approx(3.0) and coh[0] == pytest.approx(0.5)
    # the region measure is l1 - l2: 2 here, 0 for the isotropic state, 2 for the unit pure shear
    assert si.stress_region(np.diag([3.0, 1.0, 7.0])[None], z, 1.0, 1.0)[0] == pytest.approx(1.0)
    assert si.stress_region(iso, z, 1.0, 1.0)[0] == pytest.approx(-1.0)
    assert si.stress_region(shear, z, 1.0, 1.0)[0] == pytest.approx(1.0)
    # ... and diag(1, -3): 3 along y (compression counts as much as tension)
    d, mag, _ = si.in_plane_stress(np.diag([1.0, -3.0, 0.0])[None], z)
    assert abs(d[0, 1]) == pytest.approx(1.0) and mag[0] == pytest.approx(3.0)


def test_delaunay_flips_reach_the_delaunay_triangulation_of_a_planar_point_set() -> None:
    """Starting from a bad triangulation of random points in a square (a fan from one corner, re-triangulated by
    sorting), the flips end at scipy's Delaunay triangulation (points in general position: it is unique)."""
    rng = np.random.default_rng(3)
    pts = rng.uniform(0, 10, (60, 2))
    ref = Delaunay(pts)
    # a valid but poor triangulation of the same hull: Delaunay of the points stretched 20x along x, mapped back
    bad = Delaunay(pts * [1.0, 20.0]).simplices
    v = np.column_stack([pts, np.zeros(len(pts))])
    bad = np.where((np.cross(v[bad[:, 1]] - v[bad[:, 0]], v[bad[:, 2]] - v[bad[:, 0]])[:, 2] < 0)[:, None],
                   bad[:, ::-1], bad)
    flipped, offset = si.delaunay_flips(v, bad)
    canon = lambda f: {tuple(sorted(t)) for t in f.tolist()}  # noqa: E731
    assert canon(bad) != canon(ref.simplices)
    assert canon(flipped) == canon(ref.simplices)
    assert offset == pytest.approx(0.0, abs=1e-12)   # a planar patch does not leave its plane
    n, _ = si.face_frames(v, flipped)
    assert np.all(n[:, 2] > 0)                       # orientation kept


def test_least_squares_fit_recovers_a_gradient_field_and_orientation_makes_signs_agree() -> None:
    """On a curved patch, the line field of grad(x + 2y) with random signs: orienting gives one sign (up to a global
    flip) and the fit recovers x + 2y up to a constant."""
    cap = trimesh.creation.icosphere(subdivisions=4, radius=20.0)
    keep = np.all(cap.vertices[cap.faces][:, :, 2] > 12.0, axis=1)
    used, inv = np.unique(cap.faces[keep], return_inverse=True)
    v, f = cap.vertices[used], inv.reshape(-1, 3)
    normals, areas = si.face_frames(v, f)
    g = np.array([1.0, 2.0, 0.0])
    target = g - np.sum(g * normals, axis=1, keepdims=True) * normals          # the surface gradient of x + 2y
    signs = np.random.default_rng(0).choice([-1.0, 1.0], len(f))
    pairs, _ = si.face_adjacency(f)
    oriented = si.orient_line_field(target * signs[:, None], np.ones(len(f)), pairs)
    agree = np.sign(np.sum(oriented * target, axis=1))
    assert abs(agree.sum()) == len(f)
    phi = si.fit_potential(si.gradient_operator(v, f, normals, areas), oriented * agree[0], areas)
    exact = v @ g
    assert np.ptp(phi - exact) < 0.02 * np.ptp(exact)


def test_a_uniform_stress_gives_straight_parallel_lines_at_the_line_width() -> None:
    """Uniaxial stress along x on a planar square: every infill move runs along x, the lines are one line width
    apart, and their widths are the line width (no convergence to adapt to)."""
    cfg = ToolpathConfig(infill="stress", n_shells=0, join_factor=0.0)
    tp = toolpaths([square_layer(0.5, 20.0, 41)], 0.0, cfg, stress=uniaxial([1, 0, 0]))
    mid, d, length = printed_moves(tp)
    assert np.degrees(np.arccos(np.clip(np.abs(d[:, 0]), 0, 1))).max() < 0.01
    ys = np.unique(np.round(mid[:, 1], 4))
    assert np.allclose(np.diff(ys), 0.5, atol=1e-4)
    assert np.allclose(tp.width[tp.path >= 0], 0.5, rtol=1e-3)
    assert tp.attrs["stress_infill_fraction"] == pytest.approx(1.0)


def test_converging_radial_stress_keeps_the_spacing_within_a_factor_sqrt2_and_the_patch_covered() -> None:
    """Radial stress on an annulus: the lines are radii, so they converge toward the hole; lines end and start so
    that neighbouring lines stay between w / sqrt 2 and w sqrt 2 apart, each as wide as that spacing, and no
    uncovered spot is wider than a line width."""
    def radial(p: np.ndarray) -> np.ndarray:
        r = p[:, :2] / np.linalg.norm(p[:, :2], axis=1, keepdims=True)
        t = np.zeros((len(p), 3, 3))
        t[:, :2, :2] = r[:, :, None] * r[:, None, :]
        return t
    layer = disc_with_hole()
    cfg = ToolpathConfig(infill="stress")
    tp = toolpaths([layer], 0.0, cfg, stress=Analytic(radial))
    mid, d, length = printed_moves(tp)
    r = np.linalg.norm(mid[:, :2], axis=1)
    inner = inside(layer, mid, 2.0)                            # away from the shells and the line ends
    radial_dir = mid[inner, :2] / r[inner, None]
    ang = np.degrees(np.arccos(np.clip(np.abs(np.sum(d[inner, :2] * radial_dir, axis=1)), 0, 1)))
    assert np.average(ang < 5.0, weights=length[inner]) > 0.99
    on = tp.path >= 0
    assert tp.width[on].min() >= 0.5 / np.sqrt(2) - 1e-9 and tp.width[on].max() <= 0.5 * np.sqrt(2) + 1e-9
    # spacing: angular gaps between neighbouring radial lines at several radii, times the radius
    for radius in (6.5, 9.0, 12.0):
        band = inner & (np.abs(r - radius) < 0.25)
        theta = np.sort(np.arctan2(mid[band, 1], mid[band, 0]))
        gaps = np.diff(np.r_[theta, theta[0] + 2 * np.pi]) * radius
        gaps = np.sort(gaps[gaps > 0.05])                     # (the same line sampled twice in the band)
        # where the annulus is cut open (the field turns once around the hole) two lines may meet a line apart
        assert gaps[:-1].max() < 0.5 * np.sqrt(2) * 1.1 and gaps[-1] < 2 * 0.5 * np.sqrt(2)
        assert np.median(gaps) > 0.5 / np.sqrt(2)
    assert largest_gap(tp, layer) <= 0.25


@pytest.mark.parametrize("field", [WEDGE, TRISECTOR], ids=["wedge", "trisector"])
@pytest.mark.parametrize("hole", [None, (5.0, 3.0)], ids=["no hole", "hole"])
def test_isotropic_points_and_holes_do_not_break_the_patch(field: Analytic, hole) -> None:
    """The two kinds of half-index singular point (the stress is isotropic there), with and without a hole next to
    it: the lines follow the field away from the point and no uncovered spot is wider than a line width."""
    layer = disc_with_hole(hole=2.5) if hole is None else disc_with_hole(hole=hole[1], centre=(hole[0], 0.0))
    if hole is None:    # a disc: close the small hole at the centre by moving it off the singular point
        layer = disc_with_hole(radius=15.0, hole=2.0, centre=(-9.0, 9.0))
    tp = toolpaths([layer], 0.0, ToolpathConfig(infill="stress"), stress=field)
    mid, d, length = printed_moves(tp)
    t, _, _ = si.in_plane_stress(field.tensor_at(mid), np.tile([0.0, 0.0, 1.0], (len(mid), 1)))
    far = (np.linalg.norm(mid[:, :2], axis=1) > 3.0) & inside(layer, mid, 2.0)
    aligned = np.abs(np.sum(d * t, axis=1)) > np.cos(np.radians(10))
    assert np.average(aligned[far], weights=length[far]) > 0.97
    assert largest_gap(tp, layer) <= 0.25


def test_zero_stress_falls_back_to_the_regular_pattern() -> None:
    """A load case without stress anywhere: every patch gets the zig-zag, bit for bit, and the fraction says so."""
    layers = [square_layer(0.5, 20.0, 21), square_layer(1.0, 20.0, 21)]
    zero = Analytic(lambda p: np.zeros((len(p), 3, 3)), reference=0.0)
    tp = toolpaths(layers, 0.0, ToolpathConfig(infill="stress"), stress=zero)
    zig = toolpaths(layers, 0.0, ToolpathConfig(infill="zigzag"))
    assert tp.attrs["stress_infill_fraction"] == 0.0
    assert np.array_equal(tp.xyz, zig.xyz) and np.array_equal(tp.width, zig.width)


def test_stress_infill_without_a_stress_field_is_an_input_error() -> None:
    """infill: stress with no load case names the setting and what is missing."""
    from neuralslicer.errors import InputError

    with pytest.raises(InputError, match="fea"):
        toolpaths([square_layer(0.5)], 0.0, ToolpathConfig(infill="stress"))


def test_auto_infill_is_zigzag_without_stress_bit_for_bit() -> None:
    """The default (auto) without a stress field is the zig-zag, to the last bit; with one it follows the stress."""
    layers = [square_layer(0.5 * (i + 1), 20.0, 21) for i in range(3)]
    auto, zig = toolpaths(layers, 0.0), toolpaths(layers, 0.0, ToolpathConfig(infill="zigzag"))
    for k in ("xyz", "axis", "thickness", "width", "extrude", "path", "layer"):
        assert np.array_equal(getattr(auto, k), getattr(zig, k))
    assert toolpaths(layers, 0.0, stress=uniaxial([1, 0, 0])).attrs["config"]["infill"] == "stress"


def cantilever_in_bending():
    """A 60 x 10 x 10 beam clamped at x = 0 and bent by an end couple (x forces on its top and bottom at x = 60)."""
    solid = BoxSolid((0, 0, 0), (60, 10, 10))
    spec = FEASpec.model_validate(dict(
        supports=[dict(box=[[-1, -1, -1], [0.5, 11, 11]])],
        loads=[dict(box=[[59.5, -1, 8.9], [61, 11, 11]], force_n=[20.0, 0, 0]),
               dict(box=[[59.5, -1, -1], [61, 11, 1.1]], force_n=[-20.0, 0, 0])],
        voxels=60 * 10 * 10))
    return solid, spec


def test_cantilever_in_pure_bending_gets_infill_along_x_on_every_layer() -> None:
    """The FEA of a beam bent by an end couple has its stress along x: on every layer (but at the neutral axis,
    where it vanishes), the stress infill runs within 5 degrees of x."""
    solid, spec = cantilever_in_bending()
    result = run_fea(solid, spec)
    stress = stress_field(result, spec.top_fraction)
    heights = [0.6, 1.4, 2.2, 3.0, 3.8, 6.2, 7.0, 7.8, 8.6, 9.4]
    layers = [rect_layer(z, 60.0, 10.0) for z in heights]
    cfg = ToolpathConfig(infill="stress", n_shells=1, join_factor=0.0, stress_threshold=0.02)
    tp = toolpaths(layers, 0.0, cfg, stress=stress)
    mid, d, length = printed_moves(tp)
    inner = (mid[:, 0] > 3.0) & (mid[:, 0] < 57.0) & (mid[:, 1] > 1.5) & (mid[:, 1] < 8.5)
    ang = np.degrees(np.arccos(np.clip(np.abs(d[:, 0]), 0, 1)))
    layer_of_move = tp.layer[np.flatnonzero(tp.extrude[1:]) + 1][np.linalg.norm(np.diff(tp.xyz, axis=0), axis=1)[
        np.flatnonzero(tp.extrude[1:])] > 1e-9]
    for li in range(len(layers)):
        on = inner & (layer_of_move == li)
        assert on.any(), f"layer {li} has no infill"
        assert np.average(ang[on] < 5.0, weights=length[on]) > 0.99, f"layer {li}"


def test_an_x_loaded_bar_printed_along_the_stress_is_twice_as_stiff_as_across() -> None:
    """A bar pulled along x, planar layers: with stress infill (lines along x) it strains at most half as much as
    with infill along y, through the anisotropic FEA of each print's own toolpaths (Y1 / Y2 = 2.9): its elongation
    and the strain of most of it. (The largest strain is at the ends in both, where the shells and the line joins
    run across the load.)"""
    solid = BoxSolid((0, 0, 0), (40, 10, 10))
    spec = FEASpec.model_validate(dict(
        supports=[dict(plane=dict(axis="x", value=0.0), fix=[True, False, False]),
                  dict(plane=dict(axis="y", value=0.0), fix=[False, True, False]),
                  dict(plane=dict(axis="z", value=0.0), fix=[False, False, True])],
        loads=[dict(plane=dict(axis="x", value=40.0), pressure_mpa=-2.0)], voxels=40 * 10 * 10))
    result = run_fea(solid, spec)
    layers = [rect_layer(z, 40.0, 10.0) for z in np.arange(0.5, 10.0, 1.0)]
    # no shells: they run along x in both prints and would carry the load in both
    along = toolpaths(layers, 0.0, ToolpathConfig(infill="stress", n_shells=0), stress=stress_field(result))
    # zig-zag lines are isolines of the coordinate along infill_angle_deg: 0 gives lines along y
    across = toolpaths(layers, 0.0, ToolpathConfig(infill="zigzag", n_shells=0, infill_angle_deg=0.0,
                                                   infill_angle_step_deg=0.0))
    up = lambda p: np.tile([0.0, 0.0, 1.0], (len(p), 1))  # noqa: E731
    s_along = verify_layers(solid, spec, up, tangent_at=printed_tangents(along), reference=result)
    s_across = verify_layers(solid, spec, up, tangent_at=printed_tangents(across), reference=result)
    assert s_across["max_displacement_mm"] >= 2.0 * s_along["max_displacement_mm"]
    assert np.median(s_across["strain"]) >= 2.0 * np.median(s_along["strain"])


def test_stress_field_interpolation_is_exact_for_a_linear_field() -> None:
    """Trilinear interpolation between voxel centres reproduces a linear tensor field; outside, the nearest voxel."""
    ijk = np.stack(np.meshgrid(np.arange(5), np.arange(4), np.arange(3), indexing="ij"), -1).reshape(-1, 3)
    origin, h = np.array([1.0, 2.0, 3.0]), 0.5
    centres = origin + (ijk + 0.5) * h
    A = np.random.default_rng(0).normal(size=(3, 3, 3))
    lin = lambda p: np.einsum("ijk,nk->nij", A, p)  # noqa: E731
    field = StressField(origin, h, ijk, lin(centres), 1.0)
    p = origin + np.random.default_rng(1).uniform(0.5 * h, [4.5 * h, 3.5 * h, 2.5 * h], size=(200, 3))
    assert np.allclose(field.tensor_at(p), lin(p), atol=1e-12)
    far = np.array([[100.0, 0.0, 0.0]])
    nearest = np.argmin(np.linalg.norm(centres - far, axis=1))
    assert np.allclose(field.tensor_at(far)[0], lin(centres[[nearest]])[0])
