"""S3-Slicer's iterative deformation (Zhang et al. 2022) as its authors run it: ``ShapeLab/DeformTet.cpp``.

Every outer iteration (``runASAP_SupportLess_test3``, ``runASAP_StrengthReinforcement_test``,
``runASAP_Hybrid_SL_SR``):

1. re-detect the critical elements on the current deformed mesh: tets with a boundary face whose outward
   normal is more than ``support_free_angle`` below the horizontal (SL; tets touching the bottom band are
   never critical), and the tets of the stress samples T (SR);
2. inner iterations: (first one only) every tet's rotation from the deformed mesh by SVD (``R = U Vᵀ`` of
   the deformation gradient); each critical tet's rotation pre-multiplied by the rotation that brings its
   (rotated) rest overhang normal to the support-free limit against +z (SL), its rotated ``tau_max`` into
   the horizontal plane (SR), or both constraints at once (hybrid); then the quaternions smoothed over the
   face-adjacent tets (a Laplacian with weight ``w_smooth``) while the critical and bottom tets keep theirs
   (weight ``keep``);
3. one as-similar-as-possible solve per axis with the positions and a per-element scale as unknowns:
   ``sum_e w_e^2 |N x_e - s_e (R_e P_e)_axis|^2 + w_nb^2 sum_faces (s_i - s_j)^2 + w_reg^2 sum_e (s_e - 1)^2``,
   ``w_e`` the critical weight of SL / SR tets and 1 elsewhere.

The field is the height of the deformed mesh at its vertices (``_cal_virtual_Vfield``): the curved layers are its
level sets in the model space. With ``layer_field: inverse_deformation`` it is what S3's GUI slices instead
(``MainWindow::inverseDeformation``): the height's unit gradient, smoothed and integrated back.  Numpy/scipy only:
sparse systems, each factorised once per outer iteration.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from neuralslicer.baselines.s3_config import S3DeformConfig
from neuralslicer.fea.samples import StressSamples
from neuralslicer.metrics import overhang_area_fraction
from neuralslicer.neural.initial_guess import heat_geodesic
from neuralslicer.samples import SurfaceSamples
from neuralslicer.tetmesh import TET_FACES, TetLocator, barycentric_gradients, orient_tets

ProgressFn = Callable[[int, dict], None]
UP = np.array([0.0, 0.0, 1.0])


def _unit(v: np.ndarray) -> np.ndarray:
    """Rows of v (k,3) scaled to unit length (zero rows stay zero)."""
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)


def rotations_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotations (k,3,3) taking the directions a (k,3) onto b (k,3) about a x b (Eigen's setFromTwoVectors)."""
    a, b = _unit(a), _unit(b)
    axis = np.cross(a, b)
    s = np.linalg.norm(axis, axis=1)
    c = np.einsum("ij,ij->i", a, b)
    # antiparallel: any axis orthogonal to a
    ortho = np.cross(a, np.where(np.abs(a[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]]))
    axis = np.where((s < 1e-12)[:, None], _unit(ortho) * np.pi * (c < 0)[:, None], _unit(axis) * np.arctan2(s, c)[:, None])
    return Rotation.from_rotvec(axis).as_matrix()


def _axis_angle(axis: np.ndarray, angle: float | np.ndarray) -> np.ndarray:
    """Rotations (k,3,3) about unit axes (k,3) by angle (rad)."""
    return Rotation.from_rotvec(_unit(axis) * np.reshape(angle, (-1, 1))).as_matrix()


def svd_rotations(frames_inv: np.ndarray, current: np.ndarray) -> np.ndarray:
    """Each tet's rotation (m,3,3) from rest to current: the polar factor U Vᵀ of F = (pinv(Pᵀ) tP)ᵀ (det fixed to +1)."""
    F = np.transpose(frames_inv @ current, (0, 2, 1))
    U, _, Vt = np.linalg.svd(F)
    d = np.sign(np.linalg.det(U @ Vt))
    U[:, :, 2] *= d[:, None]
    return U @ Vt


def support_less_rotations(normal: np.ndarray, guide: np.ndarray, alpha: float) -> np.ndarray:
    """``_cal_rotationMatrix_supportLess``: the rotation that puts the face normal (k,3) alpha below the horizontal.

    The normal turned by +-(alpha + 90 deg) about normal x guide: the candidate closer to the guide (the rotated
    heat-method direction) is rotated onto +z, so that afterwards the normal makes alpha + 90 deg with +z.
    """
    axis = np.cross(normal, _unit(guide))
    c1 = np.einsum("kij,kj->ki", _axis_angle(axis, alpha + np.pi / 2), normal)
    c2 = np.einsum("kij,kj->ki", _axis_angle(axis, -(alpha + np.pi / 2)), normal)
    g = _unit(guide)
    pick = np.einsum("ij,ij->i", c1, g) > np.einsum("ij,ij->i", c2, g)
    return rotations_between(np.where(pick[:, None], c1, c2), np.broadcast_to(UP, normal.shape))


def strength_rotations(tau: np.ndarray) -> np.ndarray:
    """``_cal_rotationMatrix_strengthReinforcement``: the rotation of tau (k,3) onto its horizontal projection."""
    proj = tau * np.array([1.0, 1.0, 0.0])
    return rotations_between(tau, proj)


def hybrid_rotations(normal: np.ndarray, tau: np.ndarray, alpha: float) -> np.ndarray:
    """``_cal_rotationMatrix_SL_SR``: a direction d with d.n = sin(alpha) and d.tau = 0 (the one nearer +z) onto +z.

    Without such a unit vector, tau turned by +-90 deg about tau x z (the nearer to +z) goes onto +z instead.
    """
    n, t = _unit(normal), _unit(tau)
    line = np.cross(n, t)
    ln = np.linalg.norm(line, axis=1)
    # the point of the line {d.n = sin a, d.t = 0} nearest the origin: d0 = sin(a) (t x line) / |line|^2 ... via 2x2
    nt = np.einsum("ij,ij->i", n, t)
    den = np.maximum(1.0 - nt * nt, 1e-300)
    a_n = math.sin(alpha) / den
    d0 = a_n[:, None] * (n - nt[:, None] * t)
    u = _unit(line)
    r2 = 1.0 - np.einsum("ij,ij->i", d0, d0)
    ok = (ln > 1e-9) & (r2 >= 0)
    h = np.sqrt(np.maximum(r2, 0.0))[:, None]
    c1, c2 = d0 + h * u, d0 - h * u
    axis = np.cross(t, np.broadcast_to(UP, t.shape))
    f1 = np.einsum("kij,kj->ki", _axis_angle(axis, np.pi / 2), t)
    f2 = np.einsum("kij,kj->ki", _axis_angle(axis, -np.pi / 2), t)
    c1, c2 = np.where(ok[:, None], c1, f1), np.where(ok[:, None], c2, f2)
    pick = c1[:, 2] >= c2[:, 2]
    return rotations_between(np.where(pick[:, None], c1, c2), np.broadcast_to(UP, n.shape))


@dataclass
class S3Mesh:
    """The tet mesh S3 deforms, with what its loop needs: rest frames, boundary faces, adjacency, bottom band.

    vertices : (n,3); tets : (m,4) positively oriented; frames : (m,4,3) rest vertex offsets from the centroid;
    frames_inv : (m,3,4) pinv(frames); face_tet, face_local : (f,) boundary faces as (owner tet, face slot);
    pairs : (k,2) face-adjacent tets; bottom : (m,) bool, tets with a vertex within ``bottom_height`` of the floor.
    """

    vertices: np.ndarray
    tets: np.ndarray
    frames: np.ndarray
    frames_inv: np.ndarray
    face_tet: np.ndarray
    face_local: np.ndarray
    pairs: np.ndarray
    bottom: np.ndarray

    @classmethod
    def build(cls, vertices: np.ndarray, tets: np.ndarray, bottom_height: float) -> "S3Mesh":
        """Orient the tets and precompute the rest frames, boundary faces, adjacency and bottom tets."""
        V = np.asarray(vertices, dtype=np.float64)
        T = orient_tets(V, np.asarray(tets, dtype=np.int64))
        P = V[T] - V[T].mean(axis=1, keepdims=True)
        faces = np.sort(T[:, TET_FACES], axis=2).reshape(-1, 3)
        _, inverse, counts = np.unique(faces, axis=0, return_inverse=True, return_counts=True)
        inverse = inverse.ravel()
        boundary = np.flatnonzero(counts[inverse] == 1)
        order = np.argsort(inverse, kind="stable")
        inv_sorted = inverse[order]
        same = np.flatnonzero(inv_sorted[1:] == inv_sorted[:-1])
        pairs = np.stack([order[same] // 4, order[same + 1] // 4], axis=1)
        z = V[:, 2]
        bottom = np.any(z[T] < z.min() + bottom_height, axis=1)
        return cls(V, T, P, np.linalg.pinv(P), boundary // 4, boundary % 4, pairs, bottom)

    def face_normals(self, vertices: np.ndarray) -> np.ndarray:
        """Outward unit normals (f,3) and areas (f,) of the boundary faces at the given vertex positions."""
        tri = vertices[self.tets[self.face_tet][np.arange(len(self.face_tet))[:, None], TET_FACES[self.face_local]]]
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        return _unit(cross), 0.5 * np.linalg.norm(cross, axis=1)


@dataclass
class S3DeformResult:
    """S3's deformation of one tet mesh.

    G : (n,) the layer field at the mesh vertices: the deformed height, or S3's post-processed field of it
    (``layer_field: inverse_deformation``, :func:`inverse_deformation_field`); deformed : (n,3); rotations : (m,3,3)
    the smoothed target rotations of the last inner iteration; scales : (m,3) per-axis element scales; history :
    'fabrication_sl', 'fabrication_sr' (S3's energies of the deformed mesh at the start of each outer iteration and
    after the last), 'asap' (the ASAP residual of each solve), 'inner_sl', 'inner_sr' (the inner-loop energies),
    'critical' (the number of critical tets per outer iteration); satisfaction : overhang area fractions of the
    boundary faces.
    """

    G: np.ndarray
    deformed: np.ndarray
    rotations: np.ndarray
    scales: np.ndarray
    history: dict[str, list[float]]
    satisfaction: dict[str, float]
    wall_time_s: float
    attrs: dict = field(default_factory=dict)


def _energies(mesh: S3Mesh, X: np.ndarray, tau: np.ndarray, sr_tets: np.ndarray, cfg: S3DeformConfig) -> tuple[float, float]:
    """S3's fabrication energies of the deformed mesh X: SL sum over overhang tets of the excess angle (rad) of their
    mean overhang normal past 90 deg + alpha (``_calFabricationEnergy_SupportLess``); SR sum of (angle(R tau, z) -
    90 deg)^2 with R the SVD rotation (``_calFabricationEnergy_StrengthReinforcement``)."""
    sl = 0.0
    if cfg.w_critical_sl > 0:
        normals, _ = mesh.face_normals(X)
        alpha = math.radians(cfg.support_free_angle_deg)
        over = (normals[:, 2] < -math.sin(alpha)) & ~mesh.bottom[mesh.face_tet]
        tets, inv = np.unique(mesh.face_tet[over], return_inverse=True)
        if len(tets):
            mean = np.zeros((len(tets), 3))
            np.add.at(mean, inv, normals[over])
            angle = np.arccos(np.clip(_unit(mean)[:, 2], -1, 1))
            sl = float(np.maximum(angle - (alpha + np.pi / 2), 0.0).sum())
    sr = 0.0
    if len(sr_tets):
        R = svd_rotations(mesh.frames_inv[sr_tets], X[mesh.tets[sr_tets]] - X[mesh.tets[sr_tets]].mean(1, keepdims=True))
        t = np.einsum("kij,kj->ki", R, tau[sr_tets])
        sr = float(((np.arccos(np.clip(t[:, 2], -1, 1)) - np.pi / 2) ** 2).sum())
    return sl, sr


def _overhang_tets(mesh: S3Mesh, X: np.ndarray, alpha: float) -> tuple[np.ndarray, np.ndarray]:
    """``_detectOverhangFace``: (overhang tet mask (m,), its first overhang face's rest outward normal (m,3))."""
    normals, _ = mesh.face_normals(X)
    rest, _ = mesh.face_normals(mesh.vertices)
    over = (normals[:, 2] < -math.sin(alpha)) & ~mesh.bottom[mesh.face_tet]
    mask = np.zeros(len(mesh.tets), dtype=bool)
    mask[mesh.face_tet[over]] = True
    n0 = np.zeros((len(mesh.tets), 3))
    idx = np.flatnonzero(over)[::-1]  # the first overhang face of each tet wins (written last)
    n0[mesh.face_tet[idx]] = rest[idx]
    return mask, n0


def _quaternion_smoother(mesh: S3Mesh, keep: np.ndarray, cfg: S3DeformConfig) -> Callable[[np.ndarray], np.ndarray]:
    """``_globalQuaternionSmooth1_*``: least squares w_s (q_e - mean of its face neighbours) = 0, keep (q_e - q̂_e) = 0
    on the kept tets; factorised once, returns q (m,4) for q̂ (m,4)."""
    m = len(mesh.tets)
    if not keep.any():  # nothing to keep: the rotations stay as estimated (no critical tets)
        return lambda q_hat: q_hat
    i, j = mesh.pairs[:, 0], mesh.pairs[:, 1]
    deg = np.bincount(np.concatenate([i, j]), minlength=m).astype(np.float64)
    inv = 1.0 / np.maximum(deg, 1.0)
    rows = np.concatenate([np.arange(m), i, j])
    cols = np.concatenate([np.arange(m), j, i])
    vals = np.concatenate([np.ones(m), -inv[i], -inv[j]]) * cfg.w_smooth
    L = sp.csr_matrix((vals, (rows, cols)), shape=(m, m))
    w2 = np.where(keep, cfg.keep_weight ** 2, 0.0)
    solve = spla.factorized((L.T @ L + sp.diags(w2)).tocsc())
    return lambda q_hat: np.stack([solve(w2 * q_hat[:, c]) for c in range(4)], axis=1)


def _asap_solve(mesh: S3Mesh, X: np.ndarray, R: np.ndarray, weight: np.ndarray, cfg: S3DeformConfig
                ) -> tuple[np.ndarray, np.ndarray, float]:
    """The ASAP step of DeformTet.cpp: per axis, positions (n) and element scales (m) by least squares; vertex 0 is
    pinned at its current position (the system only fixes the shape: translation is its null space).

    Returns (positions (n,3), scales (m,3), the summed residual energy)."""
    n, m = len(mesh.vertices), len(mesh.tets)
    T = mesh.tets
    target = np.einsum("eij,ekj->eki", R, mesh.frames)  # (m,4,3): R_e P_e, vertex rows
    c = np.full((4, 4), -0.25) + np.eye(4)
    r4 = (np.arange(m)[:, None] * 4 + np.arange(4)[None, :])  # (m,4) row of (tet, local vertex j)
    rows_n = np.repeat(r4[:, :, None], 4, axis=2).ravel()  # row (e, j), col vertex i
    cols_n = np.repeat(T[:, None, :], 4, axis=1).ravel()
    vals_n = (weight[:, None, None] * c[None, :, :]).ravel()  # c[j, i]
    k = len(mesh.pairs)
    rows_p = np.repeat(4 * m + np.arange(k), 2)
    cols_p = n + mesh.pairs.ravel()
    vals_p = np.tile([cfg.w_neighbor_scale, -cfg.w_neighbor_scale], k)
    rows_r = 4 * m + k + np.arange(m)
    nrows = 5 * m + k + 1
    X_new, S, energy = np.empty((n, 3)), np.empty((m, 3)), 0.0
    for axis in range(3):
        rows = np.concatenate([rows_n, r4.ravel(), rows_p, rows_r, [nrows - 1]])
        cols = np.concatenate([cols_n, np.repeat(n + np.arange(m), 4), cols_p, n + np.arange(m), [0]])
        vals = np.concatenate([vals_n, (-weight[:, None] * target[:, :, axis]).ravel(), vals_p,
                               np.full(m, cfg.w_regular_scale), [1.0]])
        A = sp.csr_matrix((vals, (rows, cols)), shape=(nrows, n + m))
        b = np.zeros(nrows)
        b[rows_r] = cfg.w_regular_scale
        b[-1] = X[0, axis]
        x = spla.factorized((A.T @ A).tocsc())(A.T @ b)
        X_new[:, axis], S[:, axis] = x[:n], x[n:]
        energy += float(np.sum((A @ x - b) ** 2))
    return X_new, S, energy


def _critical_weight(over: np.ndarray, sr: np.ndarray, cfg: S3DeformConfig) -> np.ndarray:
    """``_get_critcalTet_Weight``: the SL weight on overhang tets, the SR weight on stress tets (it wins), else 1."""
    w = np.ones(len(over))
    w[over] = cfg.w_critical_sl
    w[sr] = cfg.w_critical_sr
    return w


def _to_quaternions(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (m,4), w first, w >= 0, of the rotations R (m,3,3)."""
    q = Rotation.from_matrix(R).as_quat()[:, [3, 0, 1, 2]]
    return q * np.where(q[:, :1] < 0, -1.0, 1.0)


def _from_quaternions(q: np.ndarray) -> np.ndarray:
    """Rotations (m,3,3) of quaternions (m,4), w first, normalised first."""
    q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-300)
    return Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()


def s3_deform(
    vertices: np.ndarray,
    tets: np.ndarray,
    config: S3DeformConfig | None = None,
    sr_tets: np.ndarray | None = None,
    tau: np.ndarray | None = None,
    progress: ProgressFn | None = None,
) -> S3DeformResult:
    """S3-Slicer's deformation of a tet mesh (build frame, z up), as ``DeformTet.cpp`` runs it.

    Parameters
    ----------
    vertices : (n,3) float64, tets : (m,4) int64 -- the mesh S3 deforms (the model's own, or the cage).
    config : S3DeformConfig; its SL weight 0 turns the support-free objective off.
    sr_tets : (m,) bool, the strength-critical tets; tau : (m,3) their unit max-stress directions (rest frame).
    progress(iteration, info) : after every outer iteration with the energies.
    """
    t0 = time.perf_counter()
    cfg = (config or S3DeformConfig()).filled()  # fields left None: S3's defaults
    mesh = S3Mesh.build(vertices, tets, cfg.bottom_height_mm)
    m = len(mesh.tets)
    sr = np.zeros(m, dtype=bool) if sr_tets is None else np.asarray(sr_tets, dtype=bool)
    tau = np.zeros((m, 3)) if tau is None else _unit(np.asarray(tau, dtype=np.float64))
    sl_on = cfg.w_critical_sl > 0
    alpha = math.radians(cfg.support_free_angle_deg)
    # the heat method's direction away from the bottom (preProcess_4SupportLess(3)): the rotation axis guide
    guide = np.zeros((m, 3))
    if sl_on:
        bottom_vertices = np.unique(mesh.tets[mesh.bottom]) if mesh.bottom.any() else np.argsort(mesh.vertices[:, 2])[:1]
        phi = heat_geodesic(mesh.vertices, mesh.tets, bottom_vertices)
        guide = np.einsum("ei,eij->ej", phi[mesh.tets], barycentric_gradients(mesh.vertices, mesh.tets))
    X = mesh.vertices.copy()
    R = np.broadcast_to(np.eye(3), (m, 3, 3)).copy()
    S = np.ones((m, 3))
    hist: dict[str, list[float]] = {k: [] for k in ("fabrication_sl", "fabrication_sr", "asap", "inner_sl", "inner_sr",
                                                     "critical")}
    for loop in range(cfg.outer_loops):
        e_sl, e_sr = _energies(mesh, X, tau, sr, cfg)
        hist["fabrication_sl"].append(e_sl)
        hist["fabrication_sr"].append(e_sr)
        over, n0 = _overhang_tets(mesh, X, alpha) if sl_on else (np.zeros(m, dtype=bool), np.zeros((m, 3)))
        hist["critical"].append(float((over | sr).sum()))
        smooth = _quaternion_smoother(mesh, over | sr | (mesh.bottom & sl_on), cfg)
        for inner in range(cfg.inner_loops):
            if inner == 0:
                R = svd_rotations(mesh.frames_inv, X[mesh.tets] - X[mesh.tets].mean(axis=1, keepdims=True))
            only_sl, only_sr, both = over & ~sr, sr & ~over, over & sr
            if only_sl.any():
                f = np.einsum("kij,kj->ki", R[only_sl], n0[only_sl])
                g = np.einsum("kij,kj->ki", R[only_sl], guide[only_sl])
                R[only_sl] = support_less_rotations(f, g, alpha) @ R[only_sl]
            if only_sr.any():
                R[only_sr] = strength_rotations(np.einsum("kij,kj->ki", R[only_sr], tau[only_sr])) @ R[only_sr]
            if both.any():
                f = np.einsum("kij,kj->ki", R[both], n0[both])
                t = np.einsum("kij,kj->ki", R[both], tau[both])
                R[both] = hybrid_rotations(f, t, alpha) @ R[both]
            R = _from_quaternions(smooth(_to_quaternions(R)))
            hist["inner_sl"].append(_inner_sl(R, n0, over, alpha))
            hist["inner_sr"].append(_inner_sr(R, tau, sr))
        X, S, e_asap = _asap_solve(mesh, X, R, _critical_weight(over, sr, cfg), cfg)
        hist["asap"].append(e_asap)
        if progress is not None:
            progress(loop + 1, {"fabrication_sl": e_sl, "fabrication_sr": e_sr, "asap": e_asap,
                                "critical": hist["critical"][-1], "elapsed_s": time.perf_counter() - t0, "phase": "s3"})
    e_sl, e_sr = _energies(mesh, X, tau, sr, cfg)
    hist["fabrication_sl"].append(e_sl)
    hist["fabrication_sr"].append(e_sr)
    G = X[:, 2] - X[:, 2].min()
    if cfg.layer_field == "inverse_deformation":
        G = inverse_deformation_field(mesh.vertices, mesh.tets, G, mesh.pairs)
    return S3DeformResult(G=G, deformed=X, rotations=R, scales=S, history=hist,
                          satisfaction=_satisfaction(mesh, X, G), wall_time_s=time.perf_counter() - t0,
                          attrs={"n_vertices": len(X), "n_tets": m, "bottom_tets": int(mesh.bottom.sum()),
                                 "sr_tets": int(sr.sum())})


def inverse_deformation_field(vertices: np.ndarray, tets: np.ndarray, height: np.ndarray, pairs: np.ndarray,
                              smooth_loops: int = 10) -> np.ndarray:
    """S3's layer field from the deformed height (``MainWindow::inverseDeformation``, MainWindow.cpp:1540-1576):
    the height's unit gradient per tet on the rest mesh (``_scalarField_2_vectorField(true)``, :2531), smoothed
    ``smooth_loops`` times in place, in tet order, each tet's vector replaced by the normalised sum of itself and
    its face neighbours (``_vectorField_smooth(10, true)``, :2603), and integrated back by unweighted least squares,
    one row per tet and axis (``_vectorField_2_scalarField(false)``, :2632). S3 then normalises the field to [0, 1];
    here it keeps its millimetres (unit gradient), 0 at its lowest vertex.

    vertices (n,3), tets (m,4) oriented, height (n,), pairs (k,2) face-adjacent tets; returns (n,).
    """
    V, T = np.asarray(vertices, dtype=np.float64), np.asarray(tets, dtype=np.int64)
    n, m = len(V), len(T)
    grads = barycentric_gradients(V, T)  # (m,4,3): S3's VolumeMatrix
    v = _unit(np.einsum("ei,eij->ej", np.asarray(height, dtype=np.float64)[T], grads))
    if smooth_loops > 0:
        order = np.argsort(np.concatenate([pairs[:, 0], pairs[:, 1]]), kind="stable")
        other = np.concatenate([pairs[:, 1], pairs[:, 0]])[order].tolist()
        start = np.concatenate([[0], np.cumsum(np.bincount(pairs.ravel(), minlength=m))]).tolist()
        x, y, z = v[:, 0].tolist(), v[:, 1].tolist(), v[:, 2].tolist()
        for _ in range(smooth_loops):  # Gauss-Seidel order, as S3 walks its tet list
            for e in range(m):
                sx, sy, sz = x[e], y[e], z[e]
                for j in other[start[e]:start[e + 1]]:
                    sx += x[j]
                    sy += y[j]
                    sz += z[j]
                r = math.sqrt(sx * sx + sy * sy + sz * sz)
                r = r if r > 0.0 else 1.0  # Eigen's normalize() leaves a zero sum as it is
                x[e], y[e], z[e] = sx / r, sy / r, sz / r
        v = np.stack([x, y, z], axis=1)
    rows = (3 * np.arange(m)[:, None, None] + np.arange(3)[None, None, :]).repeat(4, axis=1)  # (m,4,3)
    cols = np.broadcast_to(T[:, :, None], (m, 4, 3))
    A = sp.csr_matrix((grads.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * m, n))
    AtA = (A.T @ A).tolil()
    AtA[0, 0] += 1.0  # the constant is free (S3's Pardiso LU picks one); pin vertex 0 softly
    phi = spla.factorized(AtA.tocsc())(A.T @ v.ravel())
    return phi - phi.min()


def _inner_sl(R: np.ndarray, n0: np.ndarray, over: np.ndarray, alpha: float) -> float:
    """``_get_energy_innerLoop_supportLess``: mean excess angle (deg) of the rotated rest overhang normals."""
    if not over.any():
        return 0.0
    f = np.einsum("kij,kj->ki", R[over], n0[over])
    angle = np.arccos(np.clip(f[:, 2], -1, 1))
    return float(np.degrees(np.maximum(angle - (alpha + np.pi / 2), 0.0).mean()))


def _inner_sr(R: np.ndarray, tau: np.ndarray, sr: np.ndarray) -> float:
    """``_get_energy_innerLoop_strengthReinforcement``: mean |angle(R tau, z) - 90 deg| (deg)."""
    if not sr.any():
        return 0.0
    t = np.einsum("kij,kj->ki", R[sr], tau[sr])
    return float(np.degrees(np.abs(np.arccos(np.clip(t[:, 2], -1, 1)) - np.pi / 2).mean()))


def _satisfaction(mesh: S3Mesh, X: np.ndarray, G: np.ndarray, alpha_deg: float = 45.0) -> dict[str, float]:
    """Overhang area fractions of the boundary faces (bottom band excluded) at 45 deg: in the deformed space (S3's
    final check, the deformed normals against +z) and realised (the rest normals against the LPD grad G)."""
    s = math.sin(math.radians(alpha_deg))
    rest, area = mesh.face_normals(mesh.vertices)
    deformed, _ = mesh.face_normals(X)
    grad = np.einsum("ei,eij->ej", G[mesh.tets], barycentric_gradients(mesh.vertices, mesh.tets))
    lpd = _unit(grad)[mesh.face_tet]
    keep = ~mesh.bottom[mesh.face_tet]
    total = max(float(area[keep].sum()), 1e-300)
    return {"deformed_space_overhang_area_fraction": float(area[keep & (deformed[:, 2] < -s)].sum()) / total,
            "overhang_area_fraction": float(area[keep & (-np.einsum("ij,ij->i", rest, lpd) > s)].sum()) / total,
            "planar_overhang_area_fraction": float(area[keep & (rest[:, 2] < -s)].sum()) / total}


def transfer_field(vertices: np.ndarray, tets: np.ndarray, G: np.ndarray, points: np.ndarray) -> np.ndarray:
    """G (n,) on a tet mesh at points (k,3): barycentric inside, the affine extension of the nearest tet outside."""
    V, T = np.asarray(vertices, dtype=np.float64), np.asarray(tets, dtype=np.int64)
    idx, bary = TetLocator(V, T).locate(points)
    out = np.einsum("ki,ki->k", G[T[np.maximum(idx, 0)]], bary)
    miss = idx < 0
    if miss.any():
        centroids = V[T].mean(axis=1)
        _, near = cKDTree(centroids).query(points[miss])
        grad = np.einsum("ei,eij->ej", G[T[near]], barycentric_gradients(V, T[near]))
        out[miss] = G[T[near]].mean(axis=1) + np.einsum("kj,kj->k", grad, points[miss] - centroids[near])
    return out


def stress_tets(vertices: np.ndarray, tets: np.ndarray, stress_samples: StressSamples) -> tuple[np.ndarray, np.ndarray]:
    """S3's strength-critical tets from the stress samples T: (mask (m,), tau (m,3)), tau the volume-weighted mean of
    the sign-aligned tau_max of the samples each tet contains (S3 marks its top-stress elements from its own FEA)."""
    idx, _ = TetLocator(vertices, tets).locate(stress_samples.points)
    ok = idx >= 0
    tau = np.asarray(stress_samples.tau_max, dtype=np.float64)[ok]
    ref = np.zeros((len(tets), 3))
    first = np.unique(idx[ok], return_index=True)
    ref[first[0]] = tau[first[1]]
    tau = tau * np.where(np.einsum("ij,ij->i", tau, ref[idx[ok]]) < 0, -1.0, 1.0)[:, None]
    acc = np.zeros((len(tets), 3))
    np.add.at(acc, idx[ok], tau * np.asarray(stress_samples.volumes, dtype=np.float64)[ok, None])
    mask = np.linalg.norm(acc, axis=1) > 0
    return mask, _unit(acc)


@dataclass
class S3FieldResult:
    """The S3 baseline's field with the neural field's output contract: G (n,) at the cage vertices, lpd (m,3) per
    cage tet; the deformation itself (on the model's tet mesh or the cage) in ``deformation``."""

    G: np.ndarray
    lpd: np.ndarray
    deformation: S3DeformResult
    config: S3DeformConfig
    on: str
    satisfaction: dict[str, float]
    objectives: list[str]
    preset: str
    wall_time_s: float

    def summary(self) -> dict:
        """JSON-ready figures: iterations, energies, satisfaction, sizes, parameters."""
        h = self.deformation.history
        final = {"fabrication_sl": h["fabrication_sl"][-1], "fabrication_sr": h["fabrication_sr"][-1]}
        if h["asap"]:
            final["asap"] = h["asap"][-1]
        return {"method": "s3", "kind": "s3", "steps": self.config.outer_loops, "converged": True,
                "stop": f"{self.config.outer_loops} outer x {self.config.inner_loops} inner iterations (S3's fixed counts)",
                "wall_time_s": self.wall_time_s, "final": final, "satisfaction": dict(self.satisfaction),
                "on": self.on, "preset": self.preset, "objectives": self.objectives,
                "energy_by_iteration": ", ".join(f"{e:.4g}" for e in h["fabrication_sl" if "sf" in self.objectives
                                                                       else "fabrication_sr"]),
                "deformed_mesh": {k: int(v) for k, v in self.deformation.attrs.items()},
                "config": self.config.model_dump(mode="json")}

    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict]:
        """(arrays, json attrs) of the field group: G, lpd, the deformed mesh's height and history/<energy>."""
        d = self.deformation
        arrays = {"G": self.G, "lpd": self.lpd, "deformed_vertices": d.deformed, "element_scales": d.scales}
        arrays.update({f"history/{k}": np.asarray(v, dtype=np.float64) for k, v in d.history.items()
                       if k != "critical" and np.any(np.asarray(v) != 0)})
        return arrays, {**self.summary(), "schema_version": 2}


def s3_field(
    cage_vertices: np.ndarray,
    cage_tets: np.ndarray,
    samples: SurfaceSamples,
    model_tets: tuple[np.ndarray, np.ndarray] | None = None,
    stress_samples: StressSamples | None = None,
    objectives: list[str] | tuple[str, ...] = ("sf",),
    config: S3DeformConfig | None = None,
    model_name: str = "",
    alpha_deg: float = 45.0,
    progress: ProgressFn | None = None,
) -> S3FieldResult:
    """S3-Slicer's field G on the cage: its deformation of the model's own tet mesh (``model_tets``: vertices (n,3),
    tets (m,4), build frame) when ``config.on == 'model'`` and there is one, else of the cage; G is the deformed
    height (or S3's post-processed field of it, ``config.layer_field``), carried to the cage vertices (barycentric, the nearest tet's affine extension outside the model)."""
    t0 = time.perf_counter()
    objectives = [o for o in objectives if o in ("sf", "sr")]
    base = config or S3DeformConfig()
    cfg = base.resolve(model_name, objectives)
    on = "model" if (base.on == "model" and model_tets is not None) else "cage"
    V, T = (model_tets if on == "model" else (cage_vertices, cage_tets))
    V, T = np.asarray(V, dtype=np.float64), orient_tets(np.asarray(V, dtype=np.float64), np.asarray(T, dtype=np.int64))
    sr, tau = stress_tets(V, T, stress_samples) if (stress_samples is not None and "sr" in objectives) else (None, None)
    deformation = s3_deform(V, T, cfg, sr, tau, progress)
    G = deformation.G if on == "cage" else transfer_field(V, T, deformation.G, cage_vertices)
    grad = np.einsum("ei,eij->ej", G[cage_tets], barycentric_gradients(cage_vertices, cage_tets))
    lpd = _unit(grad)
    idx, _ = TetLocator(cage_vertices, cage_tets).locate(samples.points)
    lpd_b = np.where((idx >= 0)[:, None], lpd[np.maximum(idx, 0)], np.nan)
    sat = {f"{on}_mesh_{k}": v for k, v in deformation.satisfaction.items()}
    sat["overhang_area_fraction"] = overhang_area_fraction(samples.normals, samples.areas, samples.on_platform, lpd_b,
                                                           alpha_deg)
    return S3FieldResult(G=G, lpd=lpd, deformation=deformation, config=cfg, on=on, satisfaction=sat,
                         objectives=objectives, preset=base.preset_row(model_name, objectives),
                         wall_time_s=time.perf_counter() - t0)


__all__ = ["S3Mesh", "S3DeformResult", "S3FieldResult", "s3_deform", "s3_field", "stress_tets", "transfer_field",
           "inverse_deformation_field", "rotations_between", "svd_rotations", "support_less_rotations", "strength_rotations", "hybrid_rotations"]
