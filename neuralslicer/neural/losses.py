"""Loss terms of SPEC step 8, each normalised by the total weight of its sample set.

All functions take torch tensors and are differentiable w.r.t. the LPDs / network outputs:

- ``L_SF = sum_B |A_p| sigma(k_SF (-n.d - sin a)) / sum_B |A_p|``
- ``L_SR = sum_T |V_e| sigma(k_SR (|d.tau| - sin b)) / sum_T |V_e|``
- ``L_PO = sum_B |A_p| max(0, min_{j in N_p} (p_j - p).d) / (sum_B |A_p| * h)`` with h the mean
  distance from a sample to its k nearest samples (makes L_PO unit-free)
- ``L_HS = sum_pairs w_ij |s_i - s_j|^2 / sum_pairs w_ij``, ``w_ij = (|V_i| + |V_j|) / 2``
- ``L_HQ = sum_pairs w_ij (1 - q_i.q_j)^2 / sum_pairs w_ij`` (q unit)
- ``L_CA`` (see :func:`collision_loss`), mean over adjacent tet pairs.
- ``L_TB = sum_e |V_e| relu((cos b - d_z) / (1 - cos b))^2 / sum_e |V_e|`` (see :func:`tilt_bound_loss`): the
  LPD within ``b`` of +z, as a three-axis printer's vertical nozzle needs.
"""
from __future__ import annotations

import math

import torch


def _normalised_sum(values: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """sum w v / sum w (0 when there are no samples)."""
    if values.numel() == 0:
        return weights.new_zeros(())
    return (weights * values).sum() / weights.sum().clamp_min(1e-300)


def support_free_loss(
    lpd: torch.Tensor, normals: torch.Tensor, areas: torch.Tensor, alpha: float, k: float
) -> torch.Tensor:
    """L_SF for LPDs d_p (n,3), outward normals (n,3), weights |A_p| (n,); alpha in radians."""
    overhang = -(normals * lpd).sum(dim=1) - math.sin(alpha)
    return _normalised_sum(torch.sigmoid(k * overhang), areas)


def strength_loss(
    lpd: torch.Tensor, tau: torch.Tensor, volumes: torch.Tensor, beta: float, k: float
) -> torch.Tensor:
    """L_SR for LPDs (n,3), unit max-stress directions (n,3), voxel volumes (n,); beta in radians."""
    x = (lpd * tau).sum(dim=1).abs() - math.sin(beta)
    return _normalised_sum(torch.sigmoid(k * x), volumes)


def neighbour_offsets(points: torch.Tensor, neighbours: torch.Tensor, all_points: torch.Tensor) -> torch.Tensor:
    """p_j - p (n,k,3) for samples p (n,3) and their neighbour ids (n,k) into all_points."""
    return all_points[neighbours] - points[:, None, :]


def point_overhang_loss(
    lpd: torch.Tensor,
    points: torch.Tensor,
    neighbours: torch.Tensor,
    all_points: torch.Tensor,
    areas: torch.Tensor,
    length: float,
    offsets: torch.Tensor | None = None,
) -> torch.Tensor:
    """L_PO for samples p (n,3) with LPDs (n,3), neighbour ids (n,k) into all_points, weights (n,); ``offsets``:
    their :func:`neighbour_offsets` when known (the samples do not move)."""
    diff = neighbour_offsets(points, neighbours, all_points) if offsets is None else offsets  # (n,k,3)
    proj = torch.einsum("nkj,nj->nk", diff, lpd)
    return _normalised_sum(torch.relu(proj.min(dim=1).values), areas) / length


def harmonic_scale_loss(
    scales: torch.Tensor, pairs: torch.Tensor, pair_weights: torch.Tensor
) -> torch.Tensor:
    """L_HS for per-element scale ratios (m,3), adjacent pairs (k,2), weights (|V_i|+|V_j|)/2."""
    diff = scales.index_select(0, pairs[:, 0]) - scales.index_select(0, pairs[:, 1])
    return _normalised_sum((diff * diff).sum(dim=1), pair_weights)


def harmonic_quaternion_loss(
    quaternions: torch.Tensor, pairs: torch.Tensor, pair_weights: torch.Tensor
) -> torch.Tensor:
    """L_HQ for per-element unit quaternions (m,4), adjacent pairs (k,2), pair weights (k,)."""
    dot = (quaternions.index_select(0, pairs[:, 0]) * quaternions.index_select(0, pairs[:, 1])).sum(dim=1)
    return _normalised_sum((1.0 - dot) ** 2, pair_weights)


def crease_concavity(
    gradients: torch.Tensor, pairs: torch.Tensor, face_normals: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """(n_L x n_R).h and n_L.n_R per adjacent pair, > 0 where the isosurface has a valley.

    ``n = grad G / |grad G|`` per tet; ``h`` is the unit isoline direction of G on the shared face,
    ``h = f x t / |f x t|`` with ``f`` the face normal from L into R and ``t`` the in-face gradient.
    With this orientation ``(n_L x n_R).h = sin(theta) sign``: positive in a concave crease (a
    valley seen from the side where G grows, where the nozzle is), negative in a convex one.
    """
    gl, gr = gradients.index_select(0, pairs[:, 0]), gradients.index_select(0, pairs[:, 1])
    nl, nr = gl / gl.norm(dim=1, keepdim=True).clamp_min(1e-12), gr / gr.norm(dim=1, keepdim=True).clamp_min(1e-12)
    g_mean = 0.5 * (gl + gr)  # tangential part is shared by both sides for a continuous G
    t = g_mean - (g_mean * face_normals).sum(dim=1, keepdim=True) * face_normals
    h = torch.linalg.cross(face_normals, t, dim=1)
    h = h / h.norm(dim=1, keepdim=True).clamp_min(1e-12)
    x = (torch.linalg.cross(nl, nr, dim=1) * h).sum(dim=1)
    return x, (nl * nr).sum(dim=1)


def collision_excess(
    gradients: torch.Tensor, pairs: torch.Tensor, face_normals: torch.Tensor, phi: float
) -> torch.Tensor:
    """Signed excess angle ``theta - (pi - phi)`` (rad) per adjacent pair; > 0 is a collision.

    ``theta = atan2((n_L x n_R).h, n_L.n_R)`` is the signed kink between the isosurface normals
    (positive in a valley). A cone of apex angle ``phi`` touches the bottom of a valley without
    gouging iff the valley's opening angle ``pi - theta`` is at least ``phi``.
    """
    if pairs.numel() == 0:
        return gradients.new_zeros((0,))
    x, c = crease_concavity(gradients, pairs, face_normals)
    return torch.atan2(x, c) - (math.pi - phi)


def collision_loss(
    gradients: torch.Tensor, pairs: torch.Tensor, face_normals: torch.Tensor, phi: float
) -> torch.Tensor:
    """L_CA: mean over adjacent pairs of max(0, theta - (pi - phi)) in concave creases
    (see :func:`collision_excess`)."""
    if pairs.numel() == 0:
        return gradients.new_zeros(())
    return torch.relu(collision_excess(gradients, pairs, face_normals, phi)).mean()


def tilt_excess(directions: torch.Tensor, bound: float) -> torch.Tensor:
    """``cos(bound) - d_z`` per direction (n,) for any non-zero vectors (n,3) (normalised here, d = v / |v|);
    > 0 where the direction is more than ``bound`` (rad) from +z."""
    d_z = directions[:, 2] / directions.norm(dim=1).clamp_min(1e-12)
    return math.cos(bound) - d_z


def tilt_bound_loss(directions: torch.Tensor, weights: torch.Tensor, bound: float) -> torch.Tensor:
    """L_TB: ``sum w relu((cos b - d_z) / (1 - cos b))^2 / sum w`` for directions (n,3) (LPDs or gradients of G,
    normalised here), weights (n,) (cage tet volumes) and the bound ``b`` (rad, 0 < b <= pi).

    Zero while every direction is within ``b`` of +z; the excess is measured in units of ``1 - cos b`` (the
    cosine's range inside the bound), so 1 is a direction as far outside the bound as +z is inside it, whatever
    the bound.
    """
    if directions.numel() == 0:
        return weights.new_zeros(())
    scale = max(1.0 - math.cos(bound), 1e-12)
    return _normalised_sum(torch.relu(tilt_excess(directions, bound) / scale) ** 2, weights)
