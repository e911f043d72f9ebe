"""Stress-following infill on a layer patch (``toolpath.infill: stress``; Fang et al. 2020, "Reinforced FDM").

On every layer the stress tensor is restricted to the layer's tangent plane; its principal direction of
largest magnitude ``t`` is where a filament carries the most load (for a uniaxial stress
``sigma = s tau tau^T`` it is exactly tau_max projected onto the layer). Infill lines run along ``t``:
they are isolines of a scalar ``phi`` on the patch whose gradient is fitted, by sparse least squares over
the patch's triangles, to ``n x t`` (n: the layer normal), the sign of that line field made consistent
along a maximum-agreement spanning tree of the triangles.

Even spacing: where ``|grad phi|`` grows the isolines converge, where it shrinks they diverge. The lines are
isolines at levels of a dyadic hierarchy (the step ``w |grad phi|_ref`` halved or doubled up to
``stress_levels`` times), and a line of order ``o`` (its level a multiple of ``2^o`` base steps, not of
``2^(o+1)``) is kept only where ``log2(|grad phi| / ref) <= o + 1/2``: where lines converge every second
one ends, where they diverge one starts between two, so the local spacing stays within
``[w / sqrt 2, w sqrt 2]``; each waypoint's width is set to its local spacing, so the layer is covered
evenly. Where the in-plane stress is below ``stress_threshold`` times the reference magnitude the region is
left to the regular pattern.

Singular (isotropic) points of the direction field have no direction: their triangles weigh little in the
fit (the weight falls with the anisotropy of the in-plane stress), the spanning tree puts the sign seam of
the line field through them, and ``phi`` stays smooth there: the isolines turn around the point (a ridge or
a centre of ``phi``), where ``|grad phi|`` falls and the hierarchy inserts lines, so the patch stays covered.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import breadth_first_order, connected_components, dijkstra, minimum_spanning_tree
from scipy.sparse.linalg import spsolve

from neuralslicer.types import FloatArray, IndexArray

#: weight of a triangle with no significant stress in the direction fit, relative to a fully stressed one
_FLOOR_WEIGHT = 0.05
#: neighbouring triangles whose oriented lines make a larger angle than this (cos 60°) are cut apart
_SEAM_COS = 0.5
#: how much more the fit holds the direction of the scalar's gradient than its length (see ``fit_potential``)
_DIRECTION_STIFFNESS = 100.0


def _unit(v: FloatArray) -> FloatArray:
    """Rows of v scaled to unit length (zero rows stay zero)."""
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


def tangent_basis(normals: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Two unit vectors (n, 3), (n, 3) spanning the plane normal to each unit normal (n, 3)."""
    pick = np.argmin(np.abs(normals), axis=1)
    e = np.zeros_like(normals)
    e[np.arange(len(normals)), pick] = 1.0
    b1 = _unit(np.cross(normals, e))
    return b1, np.cross(normals, b1)


def _in_plane(tensors: FloatArray, normals: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray,
                                                                FloatArray]:
    """A tangent basis b1, b2 (n, 3) of the planes with unit normals (n, 3) and the restricted tensors' components
    in it: a = b1 sigma b1, b = b1 sigma b2, c = b2 sigma b2 (n,)."""
    b1, b2 = tangent_basis(normals)
    a = np.einsum("ni,nij,nj->n", b1, tensors, b1)
    c = np.einsum("ni,nij,nj->n", b2, tensors, b2)
    b = np.einsum("ni,nij,nj->n", b1, tensors, b2)
    return b1, b2, a, b, c


def in_plane_stress(tensors: FloatArray, normals: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The dominant in-plane principal stress of tensors (n, 3, 3) on planes with unit normals (n, 3).

    Returns the unit direction (n, 3) in the plane of the principal stress of largest magnitude of the
    restricted tensor ``P sigma P``, that magnitude (n,) in MPa, and how decisively it is the larger one (n,) in
    [0, 1], ``(|l_a| - |l_b|) / (|l_a| + |l_b|)``: 1 for a uniaxial stress, 0 for an in-plane isotropic one and for
    pure shear, where the two principal directions carry as much (the choice flips from one to the other where
    the mean stress changes sign: near the neutral axis of a bent beam).
    """
    b1, b2, a, b, c = _in_plane(tensors, normals)
    m = 0.5 * (a + c)
    r = np.hypot(0.5 * (a - c), b)
    theta = 0.5 * np.arctan2(2.0 * b, a - c) + np.where(m < 0, 0.5 * np.pi, 0.0)
    direction = np.cos(theta)[:, None] * b1 + np.sin(theta)[:, None] * b2
    total = np.abs(m + r) + np.abs(m - r)                  # |l_a| + |l_b|
    decisive = np.where(total > 0, np.abs(np.abs(m + r) - np.abs(m - r)) / np.where(total > 0, total, 1.0), 0.0)
    return direction, np.abs(m) + r, decisive


def stress_region(tensors: FloatArray, normals: FloatArray, threshold: float, reference: float) -> FloatArray:
    """Per point (n,): how much the in-layer stress prefers a direction, ``l1 - l2`` of its two in-plane principal
    stresses (twice the largest in-plane shear stress), over ``threshold`` x ``reference``, minus 1: >= 0 where the
    infill follows the stress. A uniaxial stress counts in full; an in-layer isotropic one (a Poisson-induced
    biaxial state, or no stress) not at all, however large."""
    _, _, a, b, c = _in_plane(tensors, normals)
    return 2.0 * np.hypot(0.5 * (a - c), b) / (threshold * reference) - 1.0


def face_frames(vertices: FloatArray, faces: IndexArray) -> tuple[FloatArray, FloatArray]:
    """Unit face normals (m, 3) (by the faces' orientation) and face areas (m,)."""
    tri = vertices[faces]
    cr = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area2 = np.linalg.norm(cr, axis=1)
    return cr / np.where(area2 > 0, area2, 1.0)[:, None], 0.5 * area2


def gradient_operator(vertices: FloatArray, faces: IndexArray, normals: FloatArray, areas: FloatArray) -> sparse.csr_matrix:
    """The per-face gradient of a piecewise linear function, as a sparse (3m, n) matrix (rows x, y, z of face f
    at 3f, 3f+1, 3f+2): grad B_i = n x (x_k - x_j) / (2 A) for the edge opposite vertex i."""
    m = len(faces)
    inv = 1.0 / np.where(areas > 0, 2.0 * areas, 1.0)
    rows, cols, vals = [], [], []
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        g = np.cross(normals, vertices[faces[:, k]] - vertices[faces[:, j]]) * inv[:, None]
        for d in range(3):
            rows.append(3 * np.arange(m) + d)
            cols.append(faces[:, i])
            vals.append(g[:, d])
    return sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                             shape=(3 * m, len(vertices)))


def face_adjacency(faces: IndexArray) -> tuple[IndexArray, IndexArray]:
    """Pairs (k, 2) of faces sharing an edge, and that edge's vertices (k, 2) (an edge of more than two faces
    pairs its first two)."""
    m = len(faces)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    f = np.tile(np.arange(m), 3)
    e.sort(axis=1)
    key = e[:, 0] * (int(faces.max()) + 1 if m else 1) + e[:, 1]
    order = np.argsort(key, kind="stable")
    key, f, e = key[order], f[order], e[order]
    same = np.flatnonzero(key[1:] == key[:-1])
    return np.stack([f[same], f[same + 1]], axis=1), e[same]


def delaunay_flips(vertices: FloatArray, faces: IndexArray, max_dihedral_deg: float = 30.0, rounds: int = 50
                   ) -> tuple[IndexArray, float]:
    """The faces (m, 3) with edges flipped toward a Delaunay triangulation of the same vertices, and how far the new
    triangles leave the old ones (the largest distance between the two diagonals of a flipped pair, mm).

    An interior edge whose two opposite angles sum to more than 180° is flipped to the other diagonal of its two
    triangles (kept oriented) when they are nearly coplanar (normals within ``max_dihedral_deg``) and the new
    triangles are not degenerate; each round flips the worst edge of every face at most once. Slivers of a
    marching-tetrahedra layer (a long edge with its third vertex close to it) are where a piecewise linear scalar's
    gradient across the triangle is set by tiny differences: after the flips their isolines follow the field.
    """
    f = np.asarray(faces, np.int64).copy()
    v = np.asarray(vertices, np.float64)
    n = len(v)
    cos_max = np.cos(np.radians(max_dihedral_deg))
    offset = 0.0
    pairs, edges = face_adjacency(f)
    pending = np.ones(len(pairs), bool)                      # pairs whose faces changed, or that lost a tie
    for _ in range(rounds):
        e = np.flatnonzero(pending)
        if not len(e):
            break
        a, b = pairs[e, 0], pairs[e, 1]
        # orient each edge as it runs in face a: (p, q) with face a = (p, q, c) and face b = (q, p, d)
        la = np.argmax(f[a] == edges[e, :1], axis=1)
        forward = f[a, (la + 1) % 3] == edges[e, 1]
        p = np.where(forward, edges[e, 0], edges[e, 1])
        q = np.where(forward, edges[e, 1], edges[e, 0])
        c = f[a].sum(axis=1) - p - q
        d = f[b].sum(axis=1) - p - q
        angle = _angle(v[p] - v[c], v[q] - v[c]) + _angle(v[p] - v[d], v[q] - v[d])
        n1, n2 = np.cross(v[d] - v[p], v[c] - v[p]), np.cross(v[c] - v[q], v[d] - v[q])
        l1, l2 = np.linalg.norm(n1, axis=1), np.linalg.norm(n2, axis=1)
        na, _ = face_frames(v, f[a])
        nb, _ = face_frames(v, f[b])
        ok = ((angle > np.pi + 1e-9) & (np.einsum("ij,ij->i", na, nb) > cos_max)
              & (l1 > 1e-12 * np.maximum(l2, 1e-300)) & (l2 > 1e-12 * np.maximum(l1, 1e-300))
              & (np.einsum("ij,ij->i", n1, na) > 0) & (np.einsum("ij,ij->i", n2, na) > 0) & (c != d))
        if not ok.any():
            break
        # each face flips at most its worst edge (ties broken by the edge's index, so no face is taken twice)
        score = np.where(ok, angle + 1e-9 * e / len(pairs), -np.inf)
        best = np.full(len(f), -np.inf)
        np.maximum.at(best, a, score)
        np.maximum.at(best, b, score)
        t = np.flatnonzero(ok & (score >= best[a]) & (score >= best[b]))
        cr = np.cross(v[d[t]] - v[c[t]], v[q[t]] - v[p[t]])
        gap = np.abs(np.einsum("ij,ij->i", cr, v[p[t]] - v[c[t]])) / np.maximum(np.linalg.norm(cr, axis=1), 1e-300)
        offset = max(offset, float(gap.max(initial=0.0)))
        a, b, p, q, c, d = a[t], b[t], p[t], q[t], c[t], d[t]
        f[a] = np.stack([p, d, c], axis=1)
        f[b] = np.stack([d, q, c], axis=1)
        # the adjacency follows: the flipped edge joins c-d; edge q-c moved from face a to b, edge p-d from b to a
        key = np.sort(edges, axis=1) @ np.array([n, 1])
        order = np.argsort(key)
        for (x, y), old, new in (((q, c), a, b), ((p, d), b, a)):
            k = np.minimum(x, y) * n + np.maximum(x, y)
            where = np.minimum(np.searchsorted(key[order], k), len(order) - 1)
            found = key[order][where] == k
            idx = order[where[found]]
            side = (pairs[idx] == old[found, None]).argmax(axis=1)
            pairs[idx, side] = new[found]
        edges[e[t]] = np.stack([np.minimum(c, d), np.maximum(c, d)], axis=1)
        pending[:] = False
        pending[e[ok]] = True                                        # lost a tie or flipped: look again
        touched = np.zeros(len(f), bool)
        touched[np.r_[a, b]] = True
        pending |= touched[pairs[:, 0]] | touched[pairs[:, 1]]
    return f, offset


def _angle(x: FloatArray, y: FloatArray) -> FloatArray:
    """Angles (n,) between the rows of x and y (n, 3), radians."""
    return np.arctan2(np.linalg.norm(np.cross(x, y), axis=1), np.einsum("ij,ij->i", x, y))


def cut_mesh(faces: IndexArray, pairs: IndexArray, edges: IndexArray, cut: np.ndarray, n_vertices: int
             ) -> tuple[IndexArray, IndexArray]:
    """The mesh cut open along the shared edges of the face pairs marked ``cut`` (k,) bool: a vertex is split
    into one copy per fan of its faces that no cut separates. Returns the new faces (m, 3) and, per new vertex,
    the original vertex (n',)."""
    m = len(faces)
    keep = ~cut
    f, g, ev = pairs[keep, 0], pairs[keep, 1], edges[keep]
    links = []
    for end in (0, 1):
        v = ev[:, end]
        lf = np.argmax(faces[f] == v[:, None], axis=1)
        lg = np.argmax(faces[g] == v[:, None], axis=1)
        links.append(np.stack([3 * f + lf, 3 * g + lg], axis=1))
    link = np.concatenate(links) if links else np.zeros((0, 2), np.int64)
    graph = sparse.coo_matrix((np.ones(len(link)), (link[:, 0], link[:, 1])), shape=(3 * m, 3 * m))
    _, label = connected_components(graph, directed=False)
    _, first, new_id = np.unique(label, return_index=True, return_inverse=True)
    origin = faces.ravel()[first]
    return new_id.reshape(m, 3).astype(np.int64), origin.astype(np.int64)


def boundary_loops(faces: IndexArray) -> list[IndexArray]:
    """The vertex sets of the boundary loops of a triangle mesh (edges used by one face), longest first."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    n = int(faces.max()) + 1 if len(faces) else 1
    ukey, counts = np.unique(e[:, 0] * n + e[:, 1], return_counts=True)
    b = ukey[counts == 1]
    if not len(b):
        return []
    be = np.stack([b // n, b % n], axis=1)
    graph = sparse.coo_matrix((np.ones(len(be)), (be[:, 0], be[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    verts = np.unique(be)
    loops = [verts[label[verts] == lab] for lab in np.unique(label[verts])]
    return sorted(loops, key=len, reverse=True)


def branch_cuts(vertices: FloatArray, faces: IndexArray, pairs: IndexArray, edges: IndexArray, field: FloatArray,
                min_circulation: float, groups: IndexArray | None = None) -> np.ndarray:
    """Face pairs (k,) bool to cut open so that the oriented line field (m, 3) can be integrated on every piece.

    The cut holds the seams (pairs whose lines disagree in sign or turn by more than 60°), a shortest edge path from every seam end inside a
    patch (a singular point) to its outer (longest) boundary loop, and one from every hole that a seam or such a
    path touches, or around which the field circulates by more than ``min_circulation`` (mm). Each piece is then
    simply connected and its field has one sign: the isolines fit it and may end on the cut. ``groups`` (n,): the
    patch of each vertex when the mesh holds several (each has its own outer loop).
    """
    n = len(vertices)
    # a seam: neighbours whose lines disagree in sign, or turn by more than 60° (a line where the choice of the
    # larger principal stress jumps, as across the neutral axis of a bent beam: the lines end there)
    cut = np.einsum("ij,ij->i", field[pairs[:, 0]], field[pairs[:, 1]]) < _SEAM_COS
    loops = boundary_loops(faces)
    if not loops:
        return cut
    groups = np.zeros(n, np.int64) if groups is None else np.asarray(groups, np.int64)
    outer, seen = [], set()
    for i, loop in enumerate(loops):                               # longest first: the first of each patch is outer
        if int(groups[loop[0]]) not in seen:
            seen.add(int(groups[loop[0]]))
            outer.append(i)
    on_boundary = np.zeros(n, bool)
    on_boundary[np.concatenate(loops)] = True
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    graph = sparse.coo_matrix((np.linalg.norm(vertices[e[:, 0]] - vertices[e[:, 1]], axis=1), (e[:, 0], e[:, 1])),
                              shape=(n, n)).tocsr()
    dist, pred = _multi_source(graph, np.concatenate([loops[i] for i in outer]))
    seam_degree = np.bincount(edges[cut].ravel(), minlength=n)
    tips = np.flatnonzero((seam_degree == 1) & ~on_boundary & np.isfinite(dist))
    paths = [_trace(pred, int(t)) for t in tips]
    touched = np.zeros(n, bool)
    touched[edges[cut].ravel()] = True
    for path in paths:
        touched[path] = True
    circulation = _hole_circulation(vertices, faces, field)
    for hole in (loop for i, loop in enumerate(loops) if i not in outer):
        if (touched[hole].any() or abs(circulation[hole].sum()) > min_circulation) and np.isfinite(dist[hole]).any():
            paths.append(_trace(pred, int(hole[np.argmin(dist[hole])])))
    if paths:
        key = np.sort(edges, axis=1) @ np.array([n, 1])
        path_keys = np.concatenate([np.sort(np.stack([p[:-1], p[1:]], axis=1), axis=1) @ np.array([n, 1])
                                    for p in paths if len(p) > 1] or [np.zeros(0, np.int64)])
        cut |= np.isin(key, path_keys)
    return cut


def _trace(pred: IndexArray, v: int) -> IndexArray:
    """The vertices (k,) of the shortest path from v back to its Dijkstra source (pred = -1 there)."""
    path = [v]
    while pred[path[-1]] >= 0:
        path.append(int(pred[path[-1]]))
    return np.asarray(path, np.int64)


def _hole_circulation(vertices: FloatArray, faces: IndexArray, field: FloatArray) -> FloatArray:
    """Per vertex (n,), the circulation of the face field (m, 3) along the boundary edges that start there, in the
    faces' orientation (summed over a boundary loop: the field's circulation around it, mm)."""
    n = len(vertices)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    f = np.tile(np.arange(len(faces)), 3)
    key = np.minimum(e[:, 0], e[:, 1]) * n + np.maximum(e[:, 0], e[:, 1])
    _, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
    single = counts[inv] == 1
    along = np.einsum("ij,ij->i", field[f[single]], vertices[e[single, 1]] - vertices[e[single, 0]])
    return np.bincount(e[single, 0], weights=along, minlength=n)


def _multi_source(graph: sparse.csr_matrix, sources: IndexArray) -> tuple[FloatArray, IndexArray]:
    """Shortest distances (n,) from any of ``sources`` and the predecessor (n,) on that path (-1 at sources)."""
    dist, pred, _ = dijkstra(graph, directed=False, indices=sources, min_only=True, return_predecessors=True)
    pred = np.where(pred < 0, -1, pred)
    return dist, pred


def orient_line_field(lines: FloatArray, confidence: FloatArray, pairs: IndexArray) -> FloatArray:
    """Signs for a line field (m, 3) (each row defined up to sign) that agree along a spanning tree of the
    face pairs (k, 2) which prefers neighbours whose lines are parallel (a sign read across them is certain),
    then confident (m,) in [0, 1] ones; returns the field with consistent signs. Where no consistent sign
    exists (around singular points) the disagreement falls on the pairs left out of the tree, where neighbouring
    lines are furthest from parallel."""
    m = len(lines)
    if m == 0 or len(pairs) == 0:
        return lines.copy()
    a, b = pairs[:, 0], pairs[:, 1]
    cos = np.abs(np.einsum("ij,ij->i", lines[a], lines[b]))
    cost = 1e-6 + (1.0 - cos) + 1e-3 * (1.0 - np.minimum(confidence[a], confidence[b]))
    graph = sparse.coo_matrix((cost, (a, b)), shape=(m, m)).tocsr()
    tree = minimum_spanning_tree(graph).tocoo()
    _, label = connected_components(tree, directed=False)
    roots = np.unique(label, return_index=True)[1]
    # one breadth-first pass from a node m joined to a root of every tree of the forest
    rows = np.r_[tree.row, np.full(len(roots), m)]
    cols = np.r_[tree.col, roots]
    forest = sparse.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(m + 1, m + 1)).tocsr()
    _, pred = breadth_first_order(forest, m, directed=False, return_predecessors=True)
    pred = np.where((pred < 0) | (pred == m), -1, pred)[:m].astype(np.int64)
    # parity of sign flips from each face to its root, by pointer jumping over the tree
    has = pred >= 0
    parity = np.zeros(m, bool)
    parity[has] = np.einsum("ij,ij->i", lines[has], lines[pred[has]]) < 0
    anc = pred.copy()
    while True:
        live = np.flatnonzero(anc >= 0)
        if not len(live):
            break
        up = anc[live]
        parity[live] ^= parity[up]
        anc[live] = anc[up]
    return np.where(parity[:, None], -lines, lines)


def fit_potential(G: sparse.csr_matrix, target: FloatArray, weights: FloatArray, along: FloatArray | None = None,
                  stiffness: float = 0.0) -> FloatArray:
    """phi (n,) minimising sum_f w_f (|grad phi_f - target_f|^2 + stiffness (grad phi_f . along_f)^2) (G: the (3m, n)
    gradient operator), with a tiny Tikhonov term fixing the free constant.

    With unit directions ``along`` (m, 3) normal to the targets and a large ``stiffness`` the gradient's direction is
    held to the target's while its length may vary (a line field that converges has no potential of unit gradient,
    but in 2-D always one of varying gradient: its isolines still follow the lines).
    """
    m = len(weights)
    blocks = np.repeat(weights, 9).reshape(m, 3, 3) * np.eye(3)
    if along is not None and stiffness > 0:
        blocks += (stiffness * weights)[:, None, None] * np.einsum("fi,fj->fij", along, along)
    D = sparse.bsr_matrix((blocks, np.arange(m), np.arange(m + 1)), shape=(3 * m, 3 * m))
    K = (G.T @ (D @ G)).tocsc()
    rhs = G.T @ (np.repeat(weights, 3) * target.ravel())
    diag = K.diagonal()
    K = K + sparse.identity(K.shape[0], format="csc") * (1e-9 * float(diag.mean()) if len(diag) else 1.0)
    return np.asarray(spsolve(K, rhs), np.float64)


def dyadic_order(k: IndexArray, depth: int) -> IndexArray:
    """Number of times 2 divides each integer of k (n,), at most ``depth`` (0 counts as ``depth``)."""
    k = np.abs(np.asarray(k, np.int64))
    order = np.zeros(len(k), np.int64)
    rest = k.copy()
    for _ in range(depth):
        even = (rest % 2 == 0)
        order += even
        rest = np.where(even, rest // 2, rest)
    return np.where(k == 0, depth, np.minimum(order, depth))


@dataclass
class StressPotential:
    """The stress-following scalar of one patch (or of several, ``group``), on the patch cut open where the line field
    cannot be integrated.

    faces (m, 3): the patch's faces over the cut vertices; origin (n',): the patch vertex of each cut vertex;
    phi (n',): the fitted scalar (infill lines are its isolines); rho (n',): log2 of |grad phi| over the reference
    gradient of its patch; region (n,): per patch vertex, how much the in-layer stress prefers a direction over the
    significance threshold, minus 1 (>= 0: infill follows the stress there); ref_gradient (k,): each patch's
    reference |grad phi|; group (n,): the patch of each patch vertex (0 for one patch); n_cut_edges: edges cut open.
    """

    faces: IndexArray
    origin: IndexArray
    phi: FloatArray
    rho: FloatArray
    region: FloatArray
    ref_gradient: FloatArray
    group: IndexArray
    n_cut_edges: int = 0

    def pieces(self) -> list[tuple[IndexArray, StressPotential]]:
        """Every patch alone, in group order: its vertices (n_g,) among the patch vertices, and its potential over
        them."""
        face_group = self.group[self.origin[self.faces[:, 0]]]
        order = np.argsort(face_group, kind="stable")
        bounds = np.searchsorted(face_group[order], np.arange(len(self.ref_gradient) + 1))
        out = []
        for g in range(len(self.ref_gradient)):
            cut_used, faces = np.unique(self.faces[order[bounds[g]:bounds[g + 1]]], return_inverse=True)
            used, origin = np.unique(self.origin[cut_used], return_inverse=True)
            out.append((used, StressPotential(faces.reshape(-1, 3).astype(np.int64), origin.astype(np.int64),
                                              self.phi[cut_used], self.rho[cut_used], self.region[used],
                                              self.ref_gradient[[g]], np.zeros(len(used), np.int64))))
        return out


def smooth_face_tensors(tensors: FloatArray, areas: FloatArray, pairs: IndexArray, rounds: int) -> FloatArray:
    """Tensors per face (m, 3, 3) averaged ``rounds`` times with their edge neighbours (face pairs (k, 2)), weighted by
    area: the stress's own magnitude weighs each direction, so a strong coherent stress carries over weak noisy
    neighbours (voxel noise, small stress) while a strong one keeps its direction."""
    m = len(tensors)
    if rounds <= 0 or not len(pairs):
        return tensors
    w = sparse.coo_matrix((np.ones(2 * len(pairs)), (np.r_[pairs[:, 0], pairs[:, 1]], np.r_[pairs[:, 1], pairs[:, 0]])),
                          shape=(m, m)).tocsr() + sparse.identity(m, format="csr")
    w = w @ sparse.diags(areas)
    w = sparse.diags(1.0 / np.maximum(np.asarray(w.sum(axis=1)).ravel(), 1e-300)) @ w
    flat = tensors.reshape(m, 9)
    for _ in range(rounds):
        flat = w @ flat
    return flat.reshape(m, 3, 3)


def stress_potential(vertices: FloatArray, faces: IndexArray, lpd: FloatArray, tensors: FloatArray, reference: float,
                     threshold: float, spacing: float, groups: IndexArray | None = None, smoothing: int = 2
                     ) -> StressPotential | None:
    """The scalar whose isolines follow the in-plane principal stress (``tensors`` (n, 3, 3) at the vertices) on a
    patch, or on several at once (``groups`` (n,): the patch of each vertex; they share no vertex); None when no
    vertex has a significant in-plane stress (``threshold`` x the ``reference`` magnitude).

    The line field is oriented along a spanning tree and the patch cut open where it cannot be integrated
    (:func:`branch_cuts`: sign seams, paths from singular points and holes to the outer boundary; holes around
    which the field circulates by more than half a line ``spacing``), so that the least-squares fit sees an
    integrable field (up to its curl). One sparse solve serves all the patches.
    """
    if not reference > 0 or len(faces) == 0:
        return None
    groups = np.zeros(len(vertices), np.int64) if groups is None else np.asarray(groups, np.int64)
    region = stress_region(tensors, _unit(lpd), threshold, reference)
    if not (region >= 0).any():
        return None
    normals, areas = face_frames(vertices, faces)
    pairs, edges = face_adjacency(faces)
    face_tensors = smooth_face_tensors(tensors[faces].mean(axis=1), areas, pairs, smoothing)
    t_f, mag_f, decisive_f = in_plane_stress(face_tensors, normals)
    # where the larger in-plane principal stress is not clearly larger, the fit follows the neighbours
    confidence = np.minimum(1.0, mag_f / reference) * decisive_f
    u = orient_line_field(np.cross(normals, t_f), confidence, pairs)
    cut = branch_cuts(vertices, faces, pairs, edges, u, 0.5 * spacing, groups)
    cut_faces, origin = cut_mesh(faces, pairs, edges, cut, len(vertices))
    G = gradient_operator(vertices[origin], cut_faces, normals, areas)
    phi = fit_potential(G, u, areas * (_FLOOR_WEIGHT + confidence), along=t_f, stiffness=_DIRECTION_STIFFNESS)
    g_f = np.linalg.norm((G @ phi).reshape(-1, 3), axis=1)
    face_group = groups[faces[:, 0]]
    ref = _group_medians(g_f, areas, face_group, mag_f >= threshold * reference, int(groups.max()) + 1)
    n = len(origin)
    acc = np.bincount(cut_faces.ravel(), weights=np.repeat(areas * g_f, 3), minlength=n)
    wsum = np.bincount(cut_faces.ravel(), weights=np.repeat(areas, 3), minlength=n)
    g_v = acc / np.where(wsum > 0, wsum, 1.0)
    ref_v = ref[groups[origin]]
    rho = np.log2(np.maximum(g_v, 1e-12 * ref_v) / ref_v)
    return StressPotential(cut_faces, origin, phi, rho, region, ref, groups, int(cut.sum()))


def _group_medians(values: FloatArray, weights: FloatArray, group: IndexArray, preferred: np.ndarray, n_groups: int
                   ) -> FloatArray:
    """Per group (n_groups,), the weighted median of values (m,) over its ``preferred`` (m,) bool entries, over all of
    its entries where it has none (1 for an empty group)."""
    use = preferred | ~np.isin(group, np.unique(group[preferred]))
    out = np.ones(n_groups)
    order = np.lexsort((values[use], group[use]))
    v, w, g = values[use][order], weights[use][order], group[use][order]
    starts = np.flatnonzero(np.r_[True, g[1:] != g[:-1]])
    ends = np.r_[starts[1:], len(g)]
    for a, b in zip(starts, ends):
        c = np.cumsum(w[a:b])
        out[g[a]] = v[a + min(int(np.searchsorted(c, 0.5 * c[-1])), b - a - 1)] if c[-1] > 0 else np.median(v[a:b])
    return np.maximum(out, 1e-300)


@dataclass
class LevelSet:
    """Candidate isoline levels (L,) ascending and their dyadic order (L,) relative to the base step."""

    levels: FloatArray
    order: IndexArray


def dyadic_levels(pot: StressPotential, spacing: float, depth: int, phase: float, keep: np.ndarray) -> LevelSet:
    """The levels of ``phi`` that can carry a line somewhere on the (one) patch: multiples of the finest step
    ``spacing * ref / 2^j`` that the gradient range in ``keep`` (n',) bool (per cut vertex) needs (at most ``depth`` halvings and
    doublings), shifted by ``phase`` base steps; orders run from ``-j_fine`` (finest) to ``j_coarse``."""
    base = spacing * float(pot.ref_gradient[0])
    rho = pot.rho[keep] if keep.any() else pot.rho
    j_lo = int(np.clip(np.ceil(rho.min() - 0.5), -depth, 0))
    j_hi = int(np.clip(np.ceil(rho.max() - 0.5), 0, depth))
    step = base * 2.0 ** j_lo
    phi = pot.phi[keep] if keep.any() else pot.phi
    offset = phase * base + 1e-7 * step
    k = np.arange(int(np.floor((phi.min() - offset) / step)), int(np.ceil((phi.max() - offset) / step)) + 1)
    levels = offset + k * step
    return LevelSet(levels, j_lo + dyadic_order(k, j_hi - j_lo))
