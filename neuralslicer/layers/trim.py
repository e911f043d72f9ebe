"""Trimming triangle meshes by an implicit solid: cut at H = 0, refine where a triangle leaves the solid."""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

#: a cut edge whose inside end is this close to H = 0 (mm) is cut at that end: no sliver beside it
SNAP_H = 1e-5
#: ... or whose crossing is this close to that end, relative to the edge length
SNAP_REL = 1e-6
#: a vertex at most this far outside (mm; the tolerance of `edge_crossings`) counts as inside
SNAP_OUT = 1e-7
#: refinement splits the longest edge of a triangle first when it is longer than this times the edges to
#: split, or when the cosine of the triangle's largest angle is below WIDE_COS (1: longest-edge bisection)
RIVARA_RATIO = 1.5
WIDE_COS = -0.5
#: edge parameters (coarse to fine) and barycentric weights where triangles are probed for points outside
EDGE_PROBES = (np.array([0.5]), np.array([0.25, 0.75]), np.array([1, 3, 5, 7]) / 8, np.array([1, 15]) / 16)
FACE_PROBES = np.array([[1, 1, 1], [2, 1, 1], [1, 2, 1], [1, 1, 2]], dtype=np.float64) / np.array([[3], [4], [4], [4]])


def trim(
    pts: np.ndarray, faces: np.ndarray, H: Callable[[np.ndarray], np.ndarray], iterations: int = 30,
    rounds: int = 12, tol: float = 5e-4, lipschitz: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keep the part of a triangle mesh where H <= 0: vertices inside, and no probed point of a triangle above tol.

    The triangles are cut on H = 0 (crossings on the edges by `edge_crossings`). Then, for up to `rounds`
    rounds, the edges and triangles near the surface are probed (`outside_probes`) for points with H > tol
    (a straight edge or a flat triangle across a concave part of the surface, or a thin hole between the
    vertices), refined by conforming bisection (`bisect`; a bad edge at its worst probe) and cut again;
    each round divides what is left outside by two (a crease) to four (a smooth concave wall). Every new
    vertex lies on an edge of the triangle it splits, so a mesh on a plane, or on a level set of a field
    linear per triangle, stays exactly on it. A vertex within SNAP_OUT of H = 0 counts as inside.
    `lipschitz` bounds |grad H| (1 for a signed distance): probes that the values of H at known points
    already bound by tol are skipped. Returns the points, faces (orientation kept) and, per face, the
    index of the input face it lies in.
    """
    pts = np.asarray(pts, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    h = np.asarray(H(pts), dtype=np.float64)
    src = np.arange(len(faces))
    pts, h, faces, src, fresh = _cut(pts, h, faces, src, np.ones(len(faces), dtype=bool), H, iterations)
    for _ in range(rounds):
        edges, face_edge = mesh_edges(faces, len(pts))
        split = outside_probes(pts, h, faces, edges, face_edge, fresh, H, tol, lipschitz)
        if not np.isfinite(split).any():
            break
        n_old = len(pts)
        pts, faces, parent, fresh = bisect(pts, faces, split, edges, face_edge)
        h = np.concatenate([h, H(pts[n_old:])])
        src = src[parent]
        pts, h, faces, src, fresh = _cut(pts, h, faces, src, fresh, H, iterations)
    return _compact(pts, faces, src)


def mesh_edges(faces: np.ndarray, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Unique edges (E,2) of a triangle mesh (sorted rows) and the edge ids (F,3) of each face: edge k = (v_k, v_k+1)."""
    a, b = faces, np.roll(faces, -1, axis=1)
    key = np.minimum(a, b) * np.int64(n_points) + np.maximum(a, b)
    ukey, inverse = np.unique(key.ravel(), return_inverse=True)
    return np.stack([ukey // n_points, ukey % n_points], axis=1), inverse.reshape(-1, 3)


def outside_probes(
    pts: np.ndarray, h: np.ndarray, faces: np.ndarray, edges: np.ndarray, face_edge: np.ndarray, check: np.ndarray,
    H: Callable[[np.ndarray], np.ndarray], tol: float = 5e-4, lipschitz: float = 1.0,
) -> np.ndarray:
    """Where to split edges so that triangles leaving the solid get refined: (E,) parameters along edges, NaN: no split.

    A parameter t splits edge (a, b) = edges[i] at (1 - t) a + t b.
    The edges of the faces in `check` are probed at EDGE_PROBES (coarse to fine), their interiors at
    FACE_PROBES. A probe is skipped where the points known so far bound H there by tol (H <= H(q) +
    lipschitz * |p - q|), which spares most of the points deep inside. An edge with a probe above tol is
    split at its worst probe; a triangle whose interior alone is above tol, at the midpoint of its longest edge.
    """
    split = np.full(len(edges), np.nan)
    f = np.flatnonzero(check)
    p, hv = pts[faces[f]], h[faces[f]]
    length = np.linalg.norm(np.roll(p, -1, axis=1) - p, axis=2)
    near = hv.max(axis=1) + lipschitz * length.max(axis=1) > tol
    f, p, hv, length = f[near], p[near], hv[near], length[near]
    if len(f) == 0:
        return split
    # edges: known values (or upper bounds) at the parameters probed so far, ends first
    e = np.unique(face_edge[f])
    a, b = pts[edges[e, 0]], pts[edges[e, 1]]
    span = np.linalg.norm(b - a, axis=1)
    known_t = np.array([0.0, 1.0])
    known_h = np.stack([h[edges[e, 0]], h[edges[e, 1]]], axis=1)
    for level in EDGE_PROBES:
        value = (known_h[:, None, :] + lipschitz * np.abs(level[:, None] - known_t) * span[:, None, None]).min(axis=2)
        ei, ti = np.nonzero(value > tol)
        if len(ei):
            value[ei, ti] = H(a[ei] + level[ti, None] * (b[ei] - a[ei]))
        known_t = np.concatenate([known_t, level])
        known_h = np.concatenate([known_h, value], axis=1)
    worst = np.argmax(known_h, axis=1)
    bad = known_h[np.arange(len(e)), worst] > tol  # only probed values exceed tol
    split[e[bad]] = known_t[worst[bad]]
    # triangle interiors, bounded by the vertices and the coarser probes of the triangle's edges
    x = np.einsum("sk,fkj->fsj", FACE_PROBES, p)
    fe = np.searchsorted(e, face_edge[f])  # (n, 3) rows of the edge probes
    k = 2 + sum(len(level) for level in EDGE_PROBES[:2])
    q = a[fe][:, :, None, :] + known_t[:k, None] * (b[fe] - a[fe])[:, :, None, :]  # (n, 3, k, 3)
    q, hq = q.reshape(len(f), -1, 3), known_h[fe][:, :, :k].reshape(len(f), -1)
    d = x[:, :, None, :] - q[:, None, :, :]
    bound = (hq[:, None, :] + lipschitz * np.sqrt(np.einsum("fsqj,fsqj->fsq", d, d))).min(axis=2)
    fi, si = np.nonzero(bound > tol)
    if len(fi):
        bad_face = np.unique(fi[H(x[fi, si]) > tol])
        bad_face = bad_face[~np.isfinite(split[face_edge[f[bad_face]]]).any(axis=1)]
        longest = np.argmax(length[bad_face], axis=1)
        split[face_edge[f[bad_face], longest]] = 0.5
    return split


def bisect(
    pts: np.ndarray, faces: np.ndarray, split: np.ndarray, edges: np.ndarray, face_edge: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Conforming bisection: split the edges where `split` (E,) is finite, at that parameter (see `outside_probes`).

    Every triangle with an edge to split is split along it, in both triangles of the edge, so the mesh
    stays conforming. As in longest-edge (Rivara) bisection, a triangle first splits its longest edge (at
    its midpoint unless given) when that edge is much longer than the ones to split (RIVARA_RATIO) or its
    largest angle is wide (WIDE_COS), which may propagate to the neighbour; so shapes stay bounded. Each
    triangle becomes 2, 3 or 4 of the same orientation, whose vertices lie on its edges. Returns the
    points (new ones appended), faces, the parent of each face and which faces are new.
    """
    p = pts[faces]
    length = np.linalg.norm(np.roll(p, -1, axis=1) - p, axis=2)
    rows = np.arange(len(faces))
    k = np.argmax(length, axis=1)
    long_edge = face_edge[rows, k]
    la, lb, lc = length[rows, k], length[rows, (k + 1) % 3], length[rows, (k + 2) % 3]
    wide = lb * lb + lc * lc - la * la < 2 * WIDE_COS * lb * lc  # law of cosines at the largest angle
    split = split.copy()
    marked = np.isfinite(split)
    while True:
        fm = marked[face_edge]
        longest_marked = np.where(fm, length, -1.0).max(axis=1)
        need = fm.any(axis=1) & ~marked[long_edge] & ((la > RIVARA_RATIO * longest_marked) | wide)
        if not need.any():
            break
        grow = np.unique(long_edge[need])
        marked[grow] = True
        split[grow] = 0.5
    longest = np.argmax(np.where(marked[face_edge], length, -1.0), axis=1)
    me = np.flatnonzero(marked)
    vid = np.full(len(edges), -1, dtype=np.int64)
    vid[me] = len(pts) + np.arange(len(me))
    t = split[me, None]
    pts = np.concatenate([pts, (1 - t) * pts[edges[me, 0]] + t * pts[edges[me, 1]]])
    f = np.flatnonzero(marked[face_edge].any(axis=1))
    roll = (np.arange(3)[None, :] + longest[f, None]) % 3
    a, b, c = np.take_along_axis(faces[f], roll, axis=1).T  # (a, b): the longest edge to split
    m0, m1, m2 = vid[np.take_along_axis(face_edge[f], roll, axis=1)].T  # on (a, b), (b, c), (c, a)
    s1, s2 = m1 >= 0, m2 >= 0
    first = np.stack([a, m0, np.where(s2, m2, c)], axis=1)
    second = np.stack([m0, b, np.where(s1, m1, c)], axis=1)
    third = np.stack([m0, m1, c], axis=1)[s1]
    fourth = np.stack([m2, m0, c], axis=1)[s2]
    keep = np.ones(len(faces), dtype=bool)
    keep[f] = False
    new_faces = np.concatenate([faces[keep], first, second, third, fourth])
    parent = np.concatenate([np.flatnonzero(keep), f, f, f[s1], f[s2]])
    fresh = np.arange(len(new_faces)) >= keep.sum()
    return pts, new_faces, parent, fresh


def _cut(
    pts: np.ndarray, h: np.ndarray, faces: np.ndarray, src: np.ndarray, fresh: np.ndarray,
    H: Callable[[np.ndarray], np.ndarray], iterations: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Cut the triangles with vertices outside on H = 0; the pieces inside are kept (and marked fresh).

    A vertex within SNAP_OUT outside counts as inside; a crossing whose inside end is within SNAP_H of
    H = 0, or within SNAP_REL of the edge from it, is that end, so no sliver is made beside it.
    """
    n = np.int64(len(pts))
    inside = h <= SNAP_OUT
    fin = inside[faces]
    count = fin.sum(axis=1)
    keep = count == 3
    mixed = np.flatnonzero((count == 1) | (count == 2))
    if len(mixed) == 0:
        return pts, h, faces[keep], src[keep], fresh[keep]
    # rotate each mixed triangle so that vertex 0 is the lone one (inside for count 1, outside for count 2)
    lone_inside = count[mixed] == 1
    lone = np.where(lone_inside[:, None], fin[mixed], ~fin[mixed]).argmax(axis=1)
    roll = (np.arange(3)[None, :] + lone[:, None]) % 3
    mf = np.take_along_axis(faces[mixed], roll, axis=1)
    one = lone_inside[:, None]
    # crossings on the edges (0, 1) and (0, 2), keyed by inside * n + outside and shared between neighbours
    ins = np.where(one, mf[:, :1], mf[:, 1:])
    out = np.where(one, mf[:, 1:], mf[:, :1])
    keys, inverse = np.unique(ins * n + out, return_inverse=True)
    ins, out = keys // n, keys % n
    at_vertex = h[ins] >= -SNAP_H
    c = np.flatnonzero(~at_vertex)
    cross, h_cross = _edge_crossings(pts[ins[c]], pts[out[c]], h[ins[c]], h[out[c]], H, iterations)
    near = np.linalg.norm(cross - pts[ins[c]], axis=1) <= SNAP_REL * np.linalg.norm(pts[out[c]] - pts[ins[c]], axis=1)
    at_vertex[c[near]] = True
    cid = ins.copy()
    cid[~at_vertex] = len(pts) + np.arange(int((~at_vertex).sum()))
    pts = np.concatenate([pts, cross[~near]])
    h = np.concatenate([h, h_cross[~near]])
    c01, c02 = cid[inverse.reshape(-1, 2)].T
    one, two = lone_inside, ~lone_inside
    tri_a = np.stack([mf[one, 0], c01[one], c02[one]], axis=1)
    # the quad (c01, v1, v2, c02) split along its shorter diagonal
    q0, q1, q2, q3 = c01[two], mf[two, 1], mf[two, 2], c02[two]
    d02 = np.linalg.norm(pts[q0] - pts[q2], axis=1) <= np.linalg.norm(pts[q1] - pts[q3], axis=1)
    tri_b = np.where(d02[:, None], np.stack([q0, q1, q2], axis=1), np.stack([q0, q1, q3], axis=1))
    tri_c = np.where(d02[:, None], np.stack([q0, q2, q3], axis=1), np.stack([q1, q2, q3], axis=1))
    new_faces = np.concatenate([faces[keep], tri_a, tri_b, tri_c])
    new_src = np.concatenate([src[keep], src[mixed[one]], src[mixed[two]], src[mixed[two]]])
    new_fresh = np.concatenate([fresh[keep], np.ones(len(new_faces) - keep.sum(), dtype=bool)])
    ok = (new_faces[:, 0] != new_faces[:, 1]) & (new_faces[:, 1] != new_faces[:, 2]) & (new_faces[:, 0] != new_faces[:, 2])
    return pts, h, new_faces[ok], new_src[ok], new_fresh[ok]


def edge_crossings(
    p_in: np.ndarray, p_out: np.ndarray, h_in: np.ndarray, h_out: np.ndarray,
    H: Callable[[np.ndarray], np.ndarray], iterations: int = 30, tol: float = 1e-7,
) -> np.ndarray:
    """Points on segments [p_in, p_out] (H <= 0 at p_in, > 0 at p_out) with H <= 0 and |H| <= tol where reachable.

    Illinois false position on the segment parameter (a few H evaluations for a distance-like H), then
    bisection for whatever has not converged; the returned point is always the inside end of the bracket.
    """
    return _edge_crossings(p_in, p_out, h_in, h_out, H, iterations, tol)[0]


def _edge_crossings(
    p_in: np.ndarray, p_out: np.ndarray, h_in: np.ndarray, h_out: np.ndarray,
    H: Callable[[np.ndarray], np.ndarray], iterations: int = 30, tol: float = 1e-7,
) -> tuple[np.ndarray, np.ndarray]:
    """`edge_crossings` and H at the points found."""
    lo_t, hi_t = np.zeros(len(p_in)), np.ones(len(p_in))
    lo_h, hi_h = h_in.astype(np.float64).copy(), h_out.astype(np.float64).copy()
    best = p_in.copy()
    best_h = lo_h.copy()
    active = np.flatnonzero(np.abs(best_h) > tol)
    side = np.zeros(len(p_in), dtype=np.int8)
    for it in range(iterations):
        if len(active) == 0:
            break
        a, b = lo_h[active], hi_h[active]
        if it < iterations // 2:
            t = lo_t[active] + (hi_t[active] - lo_t[active]) * np.clip(a / (a - b), 0.01, 0.99)
        else:
            t = 0.5 * (lo_t[active] + hi_t[active])
        pt = p_in[active] + t[:, None] * (p_out[active] - p_in[active])
        ht = H(pt)
        inside = ht <= 0
        i_in, i_out = active[inside], active[~inside]
        lo_t[i_in], lo_h[i_in] = t[inside], ht[inside]
        best[i_in], best_h[i_in] = pt[inside], ht[inside]
        hi_t[i_out], hi_h[i_out] = t[~inside], ht[~inside]
        # Illinois: halve the value of an end that stayed twice in a row
        hi_h[i_in[side[i_in] == 1]] *= 0.5
        lo_h[i_out[side[i_out] == -1]] *= 0.5
        side[i_in], side[i_out] = 1, -1
        active = active[(np.abs(best_h[active]) > tol) & ((hi_t[active] - lo_t[active]) > 1e-12)]
    return best, best_h


def _compact(pts: np.ndarray, faces: np.ndarray, src: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Drop unreferenced vertices."""
    used, inv = np.unique(faces, return_inverse=True)
    return pts[used], inv.reshape(-1, 3).astype(np.int64), src
