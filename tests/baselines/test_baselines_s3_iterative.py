"""S3-Slicer's iterative deformation (DeformTet.cpp): its own energy per iteration, the realised overhang against the
one-shot variant on held-out surface points, its rotation steps against closed forms, the parameter table."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from neuralslicer.baselines.s3_config import S3_PRESETS, S3Config, S3DeformConfig
from neuralslicer.baselines.s3_deform import (S3Mesh, hybrid_rotations, inverse_deformation_field, s3_deform,
                                              s3_field, strength_rotations,
                                              support_less_rotations, svd_rotations, transfer_field)
from neuralslicer.data import DATA_DIR
from neuralslicer.metrics import overhang_area_fraction
from neuralslicer.samples import SurfaceSamples
from neuralslicer.tetmesh import TET_FACES, TetLocator, barycentric_gradients, boundary_faces, box_tet_grid, orient_tets

RING = DATA_DIR / "ring.tet"


def _solid(keep, n: tuple[int, int, int], hi: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """The tets of a box grid whose centroids satisfy keep (k,3) -> (k,) bool, unused vertices dropped."""
    V, T = box_tet_grid(n, np.zeros(3), np.asarray(hi, dtype=float))
    T = T[keep(V[T].mean(axis=1))]
    used, T = np.unique(T, return_inverse=True)
    return V[used], T.reshape(-1, 4)


def sphere(n_surface: int = 400, radius: float = 30.0) -> tuple[np.ndarray, np.ndarray]:
    """A ball of radius 30 mm (S3's models are this size: its 1 mm bottom band is fixed), Delaunay tets of Fibonacci points on two spheres and the centre
    (a smooth boundary: a voxel ball's flat faces point straight down, where S3's rotation axis is undefined)."""
    from scipy.spatial import Delaunay

    i = np.arange(n_surface) + 0.5
    phi, th = np.arccos(1 - 2 * i / n_surface), np.pi * (1 + 5**0.5) * i
    u = np.stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)], axis=1)
    V = np.concatenate([radius * u, 0.5 * radius * u[::4], [[0.0, 0.0, 0.0]]]) + radius
    T = Delaunay(V).simplices
    vol = np.abs(np.einsum("ij,ij->i", V[T[:, 1]] - V[T[:, 0]],
                           np.cross(V[T[:, 2]] - V[T[:, 0]], V[T[:, 3]] - V[T[:, 0]])))
    return V, orient_tets(V, T[vol > 1e-9])


def l_part() -> tuple[np.ndarray, np.ndarray]:
    """The L part of the tests: an 8 mm column and a 12 mm arm at z 12..16 that overhangs the platform."""
    return _solid(lambda c: (c[:, 0] < 8) | (c[:, 2] > 12), (10, 4, 8), (20, 10, 16))


def torus() -> tuple[np.ndarray, np.ndarray]:
    """A ring standing on its rim (axis along y), like S3's ring: R 8, r 2.5 mm."""
    def keep(c):
        d = np.hypot(c[:, 0] - 11, c[:, 2] - 11) - 8
        return np.hypot(d, c[:, 1] - 3) < 2.6
    return _solid(keep, (22, 6, 22), (22, 6, 22))


def boundary_samples(V: np.ndarray, T: np.ndarray, n: int = 0, seed: int = 0) -> SurfaceSamples:
    """B from the boundary faces: their centroids (n = 0) or n area-uniform held-out points, outward normals."""
    F = boundary_faces(orient_tets(V, T))
    mesh = trimesh.Trimesh(V, F, process=False)
    if n:
        pts, face = trimesh.sample.sample_surface(mesh, n, seed=seed)
        areas = np.full(n, mesh.area / n)
    else:
        pts, face, areas = mesh.triangles_center, np.arange(len(F)), mesh.area_faces
    normals = np.asarray(mesh.face_normals[face])
    floor = (np.abs(pts[:, 2] - V[:, 2].min()) < 1e-6) & (normals[:, 2] < -0.9)
    knn = cKDTree(pts).query(pts, k=11)[1][:, 1:]
    return SurfaceSamples(np.asarray(pts), normals, np.asarray(areas, dtype=float), knn, floor)


def realised_overhang(V: np.ndarray, T: np.ndarray, G: np.ndarray, held: SurfaceSamples) -> float:
    """Overhang area fraction of held-out surface points judged by the LPD of the tet they lie in (as the project's
    held-out metric), computed here from G and the mesh."""
    grad = np.einsum("ei,eij->ej", G[T], barycentric_gradients(V, T))
    lpd = grad / np.linalg.norm(grad, axis=1, keepdims=True)
    idx, _ = TetLocator(V, T).locate(held.points)
    if np.any(idx < 0):  # points a hair outside: the nearest tet
        miss = idx < 0
        idx[miss] = cKDTree(V[T].mean(axis=1)).query(held.points[miss])[1]
    return overhang_area_fraction(held.normals, held.areas, held.on_platform, lpd[idx])


@pytest.mark.parametrize("model", [sphere, l_part])
def test_each_outer_iteration_lowers_s3s_fabrication_energy(model):
    V, T = model()
    cfg = S3DeformConfig(outer_loops=2).filled()  # the ring's row: two outer iterations (7 inner, 30 deg)
    res = s3_deform(V, T, cfg)
    energy = res.history["fabrication_sl"]  # at the start of each outer iteration, and after the last
    assert len(energy) == 3 and energy[0] > 0
    assert energy[1] < 0.6 * energy[0], energy
    assert energy[2] < energy[1], energy
    assert len(res.history["inner_sl"]) == 2 * cfg.inner_loops and len(res.history["asap"]) == 2
    assert res.satisfaction["deformed_space_overhang_area_fraction"] < 0.5 * res.satisfaction[
        "planar_overhang_area_fraction"]


@pytest.mark.parametrize("model", [
    pytest.param(sphere, marks=pytest.mark.xfail(strict=True, raises=AssertionError, reason=(
        "measured: S3 never rotates the tets with a vertex within 1 mm of the floor (_detectBottomTet) and keeps their "
        "rotation in the smoothing; on this coarse ball their faces reach 2.9 mm up, and the underside up to one surface "
        "edge above them stays overhanging (8.8 % held out against the one-shot's 0.07 %, planar 14.8 %; 8.2 of the "
        "8.8 % lie within 5 mm of the floor, none above 8 mm: test_residual_overhang_on_the_ball_is_next_to_the_floor); "
        "the one-shot variant has no bottom band"))),
    l_part])
def test_realised_overhang_at_most_the_one_shot_variants(model):
    from neuralslicer.baselines.s3 import optimise_s3

    V, T = model()
    T = orient_tets(V, T)
    B, held = boundary_samples(V, T), boundary_samples(V, T, n=3000, seed=7)
    iterative = s3_field(V, T, B, (V, T), None, ["sf"], S3DeformConfig(preset="none"))
    oneshot = optimise_s3(V, T, B, None, ["sf"], S3Config(device="cpu", steps=400), float(V[:, 2].min()))
    planar = realised_overhang(V, T, V[:, 2], held)
    it, one = realised_overhang(V, T, iterative.G, held), realised_overhang(V, T, oneshot.G, held)
    assert planar > 0.05
    assert it <= one + 1e-3, (it, one, planar)
    assert it < 0.6 * planar
    # the field on the mesh it deformed is the deformed height (transfer to itself is the identity)
    assert np.allclose(iterative.G, iterative.deformation.G)


def test_residual_overhang_on_the_ball_is_next_to_the_floor():
    """Why the ball is an xfail above: all S3 leaves is within one surface edge of the boundary faces of its bottom
    band (tets with a vertex within 1 mm of the floor, kept unrotated: S3's design), none where it rotates."""
    V, T = sphere()
    T = orient_tets(V, T)
    held = boundary_samples(V, T, n=3000, seed=7)
    res = s3_deform(V, T, S3DeformConfig())
    mesh = S3Mesh.build(V, T, 1.0)
    tri = V[mesh.tets[mesh.face_tet][np.arange(len(mesh.face_tet))[:, None], TET_FACES[mesh.face_local]]]
    edge = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).mean()
    reach = tri[mesh.bottom[mesh.face_tet]][..., 2].max() + edge  # the band's faces and their neighbours
    grad = np.einsum("ei,eij->ej", res.G[T], barycentric_gradients(V, T))
    lpd = grad / np.linalg.norm(grad, axis=1, keepdims=True)
    idx, _ = TetLocator(V, T).locate(held.points)
    idx = np.where(idx < 0, cKDTree(V[T].mean(axis=1)).query(held.points)[1], idx)
    over = (-np.einsum("ij,ij->i", held.normals, lpd[idx]) > math.sin(math.radians(45))) & ~held.on_platform
    low = held.points[:, 2] <= reach
    area = held.areas[~held.on_platform].sum()
    assert reach < 10.0  # a third of the ball's radius
    assert held.areas[over & low].sum() / area > 0.05  # the 8.8 % of the xfail above
    assert held.areas[over & ~low].sum() / area < 0.002  # the overhangs S3 detects and rotates are gone


@pytest.mark.slow
@pytest.mark.xfail(strict=True, raises=AssertionError, reason=(
    "measured (112 s unloaded, 321 s at load 5): on the ring's own 40,064-tet mesh the faithful S3 leaves 0.96 % held-out overhang, the one-shot "
    "variant (400 steps) 0.20 %: the issue's expectation does not hold. All of S3's residual is on the underside of the "
    "inner top arch, where the heat-method growth direction from the (off-centre) bottom band meets itself (its cut "
    "locus, x = -7 mm): the two sides are turned in opposite senses and the smoothing leaves the faces between "
    "unrotated (deformed normal z -0.97 there, -0.42 to -0.56 on its left); 1-4 outer iterations all leave 0.96 %. "
    "Neither difference found outside the loop closes it: S3's heat diffusion time (t = 100 h^2, heatMethod.cpp:257) "
    "gives 0.98 %, its inverse-deformation post-processing of the field (s3.layer_field) 1.29 %. "
    "See docs/baselines.md"))
def test_ring_iterative_at_most_one_shot():
    from neuralslicer.baselines.s3 import optimise_s3
    from neuralslicer.frames import apply_up
    from neuralslicer.model.io import read_volume

    V, T = read_volume(str(RING))
    V = apply_up(V, "y")
    T = orient_tets(V, T)
    B, held = boundary_samples(V, T), boundary_samples(V, T, n=20000, seed=7)
    iterative = s3_field(V, T, B, (V, T), None, ["sf"], S3DeformConfig(), model_name="ring")
    assert iterative.config.outer_loops == 2 and iterative.config.w_neighbor_scale == 5.0  # MainWindow.cpp:733
    oneshot = optimise_s3(V, T, B, None, ["sf"], S3Config(device="cpu", steps=400), float(V[:, 2].min()))
    it, one = realised_overhang(V, T, iterative.G, held), realised_overhang(V, T, oneshot.G, held)
    assert it <= one, (it, one)


def test_rotation_steps_reach_their_targets():
    rng = np.random.default_rng(0)
    alpha = math.radians(30)
    n = rng.normal(size=(50, 3)) * [1, 1, 0.3] - [0, 0, 1]
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    guide = np.tile([0.0, 0.0, 1.0], (50, 1)) + 0.2 * rng.normal(size=(50, 3))
    R = support_less_rotations(n, guide, alpha)
    assert np.allclose(np.linalg.det(R), 1) and np.allclose(np.einsum("kij,kj->ki", R, n)[:, 2], -math.sin(alpha))
    tau = rng.normal(size=(50, 3))
    tau /= np.linalg.norm(tau, axis=1, keepdims=True)
    assert np.allclose(np.einsum("kij,kj->ki", strength_rotations(tau), tau)[:, 2], 0, atol=1e-12)
    # hybrid: tau horizontal and the face normal at sin(alpha) from up, where both can hold
    Rh = hybrid_rotations(n, tau, alpha)
    nt = np.abs(np.einsum("ij,ij->i", n, tau)) < math.cos(alpha) - 1e-6
    assert np.allclose(np.einsum("kij,kj->ki", Rh, tau)[nt, 2], 0, atol=1e-9)
    assert np.allclose(np.einsum("kij,kj->ki", Rh, n)[nt, 2], math.sin(alpha))


def test_svd_rotation_recovers_a_rigid_motion_and_the_asap_keeps_an_unconstrained_mesh():
    V, T = l_part()
    mesh = S3Mesh.build(V, T, 1.0)
    Q = trimesh.transformations.rotation_matrix(0.4, [1, 2, 3])[:3, :3]
    X = V @ Q.T + 5.0
    R = svd_rotations(mesh.frames_inv, X[mesh.tets] - X[mesh.tets].mean(axis=1, keepdims=True))
    assert np.allclose(R, Q, atol=1e-9)
    # no critical tets (SL off): the loop leaves the mesh as it is, G = z
    res = s3_deform(V, T, S3DeformConfig(w_critical_sl=0.0))
    assert np.allclose(res.G, V[:, 2] - V[:, 2].min(), atol=1e-6)
    assert np.allclose(res.scales, 1.0, atol=1e-6)


def test_transfer_is_exact_for_an_affine_field():
    V, T = sphere()
    G = V @ [0.3, -0.2, 1.0] + 2.0
    pts = np.random.default_rng(1).uniform(-2, 12, size=(200, 3))  # inside and outside the ball
    assert np.allclose(transfer_field(V, T, G, pts), pts @ [0.3, -0.2, 1.0] + 2.0)


def test_inverse_deformation_field_keeps_an_affine_height_and_integrates_unit_gradients():
    """S3's post-processing (MainWindow.cpp:1540-1576): an affine height has one gradient direction, which the
    smoothing keeps, so the field is the distance along it; a bent height comes back with unit gradient."""
    V, T = sphere()
    mesh = S3Mesh.build(V, T, 1.0)
    u = np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0])
    F = inverse_deformation_field(mesh.vertices, mesh.tets, 2.5 * (V @ u) + 7.0, mesh.pairs)
    assert np.allclose(F, V @ u - (V @ u).min(), atol=1e-8)
    F = inverse_deformation_field(mesh.vertices, mesh.tets, V[:, 2] + 0.02 * (V[:, 0] - 30) ** 2, mesh.pairs)
    g = np.linalg.norm(np.einsum("ei,eij->ej", F[mesh.tets], barycentric_gradients(mesh.vertices, mesh.tets)), axis=1)
    assert F.min() == 0.0 and 0.9 < np.median(g) < 1.1
    # through s3_deform: with nothing to rotate the field is the height either way
    res = s3_deform(V, T, S3DeformConfig(w_critical_sl=0.0, layer_field="inverse_deformation"))
    assert np.allclose(res.G, V[:, 2] - V[:, 2].min(), atol=1e-6)


def test_parameters_follow_s3s_table():
    ring = S3DeformConfig().resolve("ring", ["sf"])
    assert (ring.outer_loops, ring.inner_loops, ring.w_critical_sl, ring.w_neighbor_scale, ring.w_regular_scale,
            ring.w_smooth, ring.support_free_angle_deg) == (2, 7, 15.0, 5.0, 1.0, 40.0, 30.0)
    hybrid = S3DeformConfig().resolve("topopt_new4", ["sf", "sr"])
    assert (hybrid.w_critical_sr, hybrid.w_smooth) == (8.0, 50.0)
    sr_only = S3DeformConfig().resolve("bracket", ["sr"])
    assert (sr_only.w_critical_sl, sr_only.w_critical_sr, sr_only.w_smooth) == (0.0, 8.0, 50.0)
    assert S3DeformConfig(outer_loops=3).resolve("ring", ["sf"]).outer_loops == 3  # what is set explicitly wins
    assert S3DeformConfig().resolve("lpart", ["sf"]).w_smooth == S3_PRESETS["tube"][7]
    # the row still applies to a config read back from its dump (as the pipeline's configs are): every field
    # is then "set" for pydantic, so explicit means "not None"
    from neuralslicer.config import SliceConfig

    round_trip = SliceConfig.model_validate(SliceConfig().model_dump(mode="json")).s3.resolve("ring", ["sf"])
    assert (round_trip.outer_loops, round_trip.w_neighbor_scale) == (2, 5.0)
    assert S3DeformConfig(preset="none").resolve("ring", ["sf"]).outer_loops == 1  # S3's defaults, no row
    with pytest.raises(ValueError, match="unknown row"):
        S3DeformConfig(preset="nope").resolve("x", ["sf"])
