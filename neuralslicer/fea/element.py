"""The 8-node trilinear hexahedron on a cube voxel, and the constitutive matrices.

Voigt order is ``[xx, yy, zz, yz, xz, xy]`` with engineering shear strains (gamma = 2 eps).
Local node ``a`` of a voxel sits at corner ``CORNERS[a]`` (VTK_HEXAHEDRON order: the bottom face
counter-clockwise, then the top face), in units of the voxel side ``h``.
"""
from __future__ import annotations

import numpy as np

#: Corner offsets (8, 3) int64 of the local nodes, in VTK_HEXAHEDRON order.
CORNERS = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0],
                    [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], dtype=np.int64)

_VOIGT = [(0, 0), (1, 1), (2, 2), (1, 2), (0, 2), (0, 1)]


def shape_gradients(xi: np.ndarray) -> np.ndarray:
    """Gradients of the 8 shape functions w.r.t. reference coords in [-1,1]^3.

    xi : (3,) float64 -> (8, 3) float64.
    """
    s = 2.0 * CORNERS - 1.0                                   # (8,3) corner signs
    f = 1.0 + s * np.asarray(xi, dtype=np.float64)[None, :]   # (8,3)
    g = np.empty((8, 3))
    g[:, 0] = s[:, 0] * f[:, 1] * f[:, 2] / 8.0
    g[:, 1] = f[:, 0] * s[:, 1] * f[:, 2] / 8.0
    g[:, 2] = f[:, 0] * f[:, 1] * s[:, 2] / 8.0
    return g


def strain_matrix(xi: np.ndarray, h: float = 1.0) -> np.ndarray:
    """Strain-displacement matrix B (6, 24) at reference point ``xi`` of a cube of side ``h``."""
    dN = shape_gradients(xi) * (2.0 / h)                      # d/dx = (2/h) d/dxi
    B = np.zeros((6, 24))
    for a in range(8):
        dx, dy, dz = dN[a]
        c = 3 * a
        B[0, c], B[1, c + 1], B[2, c + 2] = dx, dy, dz
        B[3, c + 1], B[3, c + 2] = dz, dy
        B[4, c], B[4, c + 2] = dz, dx
        B[5, c], B[5, c + 1] = dy, dx
    return B


def gauss_points() -> np.ndarray:
    """The 2x2x2 Gauss points (8, 3) on [-1,1]^3 (all weights 1)."""
    g = 1.0 / np.sqrt(3.0)
    return (2.0 * CORNERS - 1.0) * g


def stiffness_basis() -> np.ndarray:
    """Q (6, 6, 24, 24) with ``Ke = h * sum_pq D[p,q] Q[p,q]`` for a cube of side h (2x2x2 Gauss)."""
    Q = np.zeros((6, 6, 24, 24))
    for xi in gauss_points():
        B = strain_matrix(xi, 1.0)
        Q += np.einsum("pr,qs->pqrs", B, B)
    return Q / 8.0        # |J| = (h/2)^3 with B ~ 1/h  ->  h^3/8 / h^2 = h/8


def element_stiffness(D: np.ndarray, h: float) -> np.ndarray:
    """Element stiffness (24, 24) of a cube voxel of side ``h`` with constitutive matrix D (6, 6)."""
    return h * np.einsum("pq,pqrs->rs", D, stiffness_basis())


def isotropic_D(E: float, nu: float) -> np.ndarray:
    """Isotropic constitutive matrix (6, 6) for Young's modulus E and Poisson ratio nu."""
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    mu = E / (2.0 * (1.0 + nu))
    D = np.zeros((6, 6))
    D[:3, :3] = lam
    D[np.arange(3), np.arange(3)] = lam + 2.0 * mu
    D[np.arange(3, 6), np.arange(3, 6)] = mu
    return D


def transversely_isotropic_D(E1: float, E2: float, nu12: float, nu23: float,
                             G12: float) -> np.ndarray:
    """Constitutive matrix (6, 6) in the material frame, axis 1 stiff, 2-3 plane isotropic."""
    G23 = E2 / (2.0 * (1.0 + nu23))
    S = np.zeros((6, 6))
    S[0, 0] = 1.0 / E1
    S[1, 1] = S[2, 2] = 1.0 / E2
    S[0, 1] = S[1, 0] = S[0, 2] = S[2, 0] = -nu12 / E1
    S[1, 2] = S[2, 1] = -nu23 / E2
    S[3, 3] = 1.0 / G23
    S[4, 4] = S[5, 5] = 1.0 / G12
    return np.linalg.inv(S)


def stress_rotation(R: np.ndarray) -> np.ndarray:
    """Voigt stress transformation T (n, 6, 6) for frames R (n, 3, 3) (columns = material axes).

    ``sigma_global = T sigma_material``; with engineering shear, ``eps_material = T^T eps_global``
    and so ``D_global = T D_material T^T``.
    """
    R = np.asarray(R, dtype=np.float64)
    T = np.empty(R.shape[:-2] + (6, 6))
    for m, (a, b) in enumerate(_VOIGT):
        for k, (i, j) in enumerate(_VOIGT):
            t = R[..., a, i] * R[..., b, j]
            if i != j:
                t = t + R[..., a, j] * R[..., b, i]
            T[..., m, k] = t
    return T


def rotate_D(D_material: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Per-voxel global constitutive matrices (n, 6, 6) from D (6, 6) and frames R (n, 3, 3)."""
    T = stress_rotation(R)
    return np.einsum("nmk,kl,npl->nmp", T, D_material, T, optimize=True)


def voigt_to_tensor(v: np.ndarray, engineering_shear: bool = False) -> np.ndarray:
    """Symmetric tensors (n, 3, 3) from Voigt vectors (n, 6); halve shears if engineering strain."""
    v = np.asarray(v)
    s = 0.5 if engineering_shear else 1.0
    t = np.empty(v.shape[:-1] + (3, 3))
    t[..., 0, 0], t[..., 1, 1], t[..., 2, 2] = v[..., 0], v[..., 1], v[..., 2]
    t[..., 1, 2] = t[..., 2, 1] = s * v[..., 3]
    t[..., 0, 2] = t[..., 2, 0] = s * v[..., 4]
    t[..., 0, 1] = t[..., 1, 0] = s * v[..., 5]
    return t
