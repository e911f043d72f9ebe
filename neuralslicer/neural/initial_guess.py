"""Initial guesses for G (SPEC step 9): height, heat-method geodesic distance, user field."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.interpolate import LinearNDInterpolator
from scipy.spatial import cKDTree

from neuralslicer.errors import InputError
from neuralslicer.tetmesh import barycentric_gradients, tet_volumes


def stiffness_and_mass(vertices: np.ndarray, tets: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
    """P1 stiffness (cotangent Laplacian) L (n,n) sparse PSD and lumped mass (n,) of a tet mesh."""
    grads = barycentric_gradients(vertices, tets)
    vol = np.abs(tet_volumes(vertices, tets))
    local = np.einsum("e,eik,ejk->eij", vol, grads, grads)
    rows = np.repeat(tets, 4, axis=1).ravel()
    cols = np.tile(tets, (1, 4)).ravel()
    n = len(vertices)
    L = sp.coo_matrix((local.ravel(), (rows, cols)), shape=(n, n)).tocsr()
    mass = np.bincount(tets.ravel(), weights=np.repeat(vol / 4.0, 4), minlength=n)
    return L, mass


def heat_geodesic(
    vertices: np.ndarray, tets: np.ndarray, sources: np.ndarray, time_factor: float = 1.0
) -> np.ndarray:
    """Heat-method geodesic distance (n,) from the source vertices (bool (n,) or ids) on a tet mesh.

    One backward-Euler heat step ``(M + t L) u = delta`` with ``t = time_factor * h^2`` (h: mean
    edge length), the normalised field ``X = -grad u / |grad u|`` per tet, and the Poisson solve
    ``L phi = div X`` with ``phi = 0`` on the sources (Crane et al. 2017).
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    tets = np.asarray(tets, dtype=np.int64)
    n = len(vertices)
    src = np.zeros(n, dtype=bool)
    src[np.asarray(sources)] = True
    L, mass = stiffness_and_mass(vertices, tets)
    edges = vertices[tets[:, [0, 0, 0, 1, 1, 2]]] - vertices[tets[:, [1, 2, 3, 2, 3, 3]]]
    h = float(np.linalg.norm(edges, axis=2).mean())
    t = time_factor * h * h
    delta = np.where(src, mass, 0.0)
    u = spla.spsolve((sp.diags(mass) + t * L).tocsc(), delta)
    grads = barycentric_gradients(vertices, tets)
    gu = np.einsum("ei,eij->ej", u[tets], grads)
    X = -gu / np.maximum(np.linalg.norm(gu, axis=1, keepdims=True), 1e-300)
    vol = np.abs(tet_volumes(vertices, tets))
    div = np.einsum("e,eij,ej->ei", vol, grads, X)
    b = np.bincount(tets.ravel(), weights=div.ravel(), minlength=n)
    free = ~src
    phi = np.zeros(n)
    phi[free] = spla.spsolve(L[free][:, free].tocsc(), b[free])
    return phi


def platform_vertices(vertices: np.ndarray, platform_z: float | None, tolerance: float) -> np.ndarray:
    """Mask (n,) of cage vertices at/below the platform (or the lowest layer of vertices)."""
    z = vertices[:, 2]
    mask = z <= (z.min() if platform_z is None else platform_z) + tolerance
    if not mask.any():
        mask = z <= z.min() + tolerance
    return mask


def user_field_on_cage(
    vertices: np.ndarray, values: np.ndarray, points: np.ndarray | None = None
) -> np.ndarray:
    """A user scalar field at the cage vertices (n,): given there, or interpolated from points (p,3)."""
    values = np.asarray(values, dtype=np.float64).ravel()
    if points is None:
        if len(values) != len(vertices):
            from neuralslicer.errors import InputError

            raise InputError("init.user_field", f"{len(values)} values for {len(vertices)} cage vertices")
        return values
    points = np.asarray(points, dtype=np.float64)
    out = LinearNDInterpolator(points, values)(vertices)
    bad = ~np.isfinite(out)
    if bad.any():
        _, j = cKDTree(points).query(vertices[bad])
        out[bad] = values[j]
    return out


def height_matched(field: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """Affine copy of field (n,) whose range is the vertices' z range (same minimum)."""
    z = vertices[:, 2]
    span = float(np.ptp(field))
    if span <= 0:
        return z.copy()
    return z.min() + (field - field.min()) * (np.ptp(z) / span)


def load_user_field(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """A user field file (.npz: points (p,3) in the build frame, values (p,)), checked: (points, values)."""
    try:
        with np.load(path) as data:
            points = np.asarray(data["points"], dtype=np.float64)
            values = np.asarray(data["values"], dtype=np.float64).ravel()
    except (OSError, KeyError, ValueError) as exc:
        raise InputError(path, f"a user field is an .npz with 'points' (p,3) and 'values' (p,): {exc}") from None
    if points.ndim != 2 or points.shape[1] != 3 or len(points) != len(values) or not np.isfinite(values).all():
        raise InputError(path, f"points {points.shape} and values {values.shape} do not match (p,3) and (p,)")
    return points, values
