"""Marching triangles: isolines of a per-vertex scalar on a triangle mesh, chained into polylines.

Isoline points lie on mesh edges and consecutive points of a polyline lie in one triangle, so a
polyline (and any point linearly interpolated along it) lies exactly on the mesh.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import connected_components

from neuralslicer.types import BoolArray, FloatArray, IndexArray


@dataclass
class IsolinePoints:
    """Crossing points of isolines with mesh edges.

    edge : (k, 2) int64 vertex ids (a < b); t : (k,) in [0, 1): point = (1-t) v_a + t v_b;
    level : (k,) int64 index into the levels; segments : (s, 2) int64 point ids, oriented so that
    values above the level are on the left (with respect to the face normal).
    """

    edge: IndexArray
    t: FloatArray
    level: IndexArray
    segments: IndexArray

    def interpolate(self, values: np.ndarray) -> np.ndarray:
        """Linear interpolation of per-vertex ``values`` (n, ...) at the points -> (k, ...)."""
        va, vb = values[self.edge[:, 0]], values[self.edge[:, 1]]
        t = self.t.reshape((-1,) + (1,) * (va.ndim - 1))
        return (1.0 - t) * va + t * vb


def isoline_points(faces: IndexArray, values: FloatArray, levels: FloatArray) -> IsolinePoints:
    """Isolines ``values == levels[j]`` on a triangle mesh, all levels at once (vectorised).

    faces : (m, 3) int64; values : (n,) float64 per vertex; levels : (L,) float64 ascending.
    A vertex counts as above a level when its value is strictly greater.
    """
    faces = np.asarray(faces, dtype=np.int64)
    levels = np.asarray(levels, dtype=np.float64)
    empty = IsolinePoints(np.zeros((0, 2), np.int64), np.zeros(0), np.zeros(0, np.int64),
                          np.zeros((0, 2), np.int64))
    if len(faces) == 0 or len(levels) == 0:
        return empty
    fv = values[faces]
    lo = np.searchsorted(levels, fv.min(axis=1), side="left")
    hi = np.searchsorted(levels, fv.max(axis=1), side="left")
    counts = hi - lo
    total = int(counts.sum())
    if total == 0:
        return empty
    face_rep = np.repeat(np.arange(len(faces)), counts)
    starts = np.cumsum(counts) - counts
    level_idx = lo[face_rep] + (np.arange(total) - starts[face_rep])
    c = levels[level_idx]
    above = fv[face_rep] > c[:, None]                      # (k, 3)
    nxt = np.roll(above, -1, axis=1)                         # vertex k+1 of edge k
    e_in = np.argmax(above & ~nxt, axis=1)                   # above -> below edge
    e_out = np.argmax(~above & nxt, axis=1)                  # below -> above edge
    # crossing points are shared per (edge, level): key them by the edge's vertex pair and the level,
    # for the crossed faces only (no edge table of the whole mesh)
    fr = faces[face_rep]
    r = np.arange(total)
    n_vert = np.int64(faces.max()) + 1
    n_levels = len(levels)
    edge_key = []
    for e in (e_in, e_out):
        a, b = fr[r, e], fr[r, (e + 1) % 3]
        edge_key.append(np.minimum(a, b) * n_vert + np.maximum(a, b))
    edge_key, level2 = np.concatenate(edge_key), np.concatenate([level_idx, level_idx])
    if float(n_vert) ** 2 * n_levels < 2.0 ** 62:
        keys, inv = np.unique(edge_key * n_levels + level2, return_inverse=True)
        edge_key, p_level = keys // n_levels, keys % n_levels
    else:                                                     # the combined key would overflow int64
        keys, inv = np.unique(np.stack([edge_key, level2], axis=1), axis=0, return_inverse=True)
        edge_key, p_level = keys[:, 0], keys[:, 1]
    inv = inv.reshape(-1)
    p_edge = np.stack([edge_key // n_vert, edge_key % n_vert], axis=1)
    fa, fb = values[p_edge[:, 0]], values[p_edge[:, 1]]
    denom = fb - fa
    t = np.where(np.abs(denom) > 0, (levels[p_level] - fa) / np.where(denom == 0, 1, denom), 0.0)
    segments = np.stack([inv[:total], inv[total:]], axis=1)
    return IsolinePoints(p_edge, np.clip(t, 0.0, 1.0), p_level, segments)


@dataclass
class Polylines:
    """Ragged polylines as flat point ids + offsets; closed loops repeat their first point last."""

    ids: IndexArray
    offsets: IndexArray
    closed: BoolArray

    def __len__(self) -> int:
        """Number of polylines."""
        return len(self.offsets) - 1


def chain_segments(segments: IndexArray, n_points: int) -> Polylines:
    """Chain oriented segments (s, 2) into polylines (paths and closed loops), vectorised.

    Each point keeps at most one outgoing and one incoming segment; segments that would break this
    (inconsistently oriented faces) are dropped, which only splits polylines.
    """
    segments = np.asarray(segments, dtype=np.int64).reshape(-1, 2)
    segments = segments[segments[:, 0] != segments[:, 1]]
    if len(segments) == 0:
        return Polylines(np.zeros(0, np.int64), np.zeros(1, np.int64), np.zeros(0, bool))
    succ = np.full(n_points, -1, np.int64)
    pred = np.full(n_points, -1, np.int64)
    succ[segments[:, 0]] = segments[:, 1]
    pred[segments[:, 1]] = segments[:, 0]
    ok = (succ[segments[:, 0]] == segments[:, 1]) & (pred[segments[:, 1]] == segments[:, 0])
    seg = segments[ok]
    succ[:] = -1
    pred[:] = -1
    succ[seg[:, 0]] = seg[:, 1]
    pred[seg[:, 1]] = seg[:, 0]
    used = np.zeros(n_points, bool)
    used[seg.ravel()] = True
    graph = sparse.coo_matrix((np.ones(len(seg)), (seg[:, 0], seg[:, 1])), shape=(n_points, n_points))
    n_comp, label = connected_components(graph, directed=False)
    label = np.where(used, label, -1)
    nodes = np.flatnonzero(used)
    has_head = np.zeros(n_comp, bool)
    has_head[label[nodes[pred[nodes] < 0]]] = True
    comp_of_nodes = label[nodes]
    # cycles: break before the smallest node id of the component
    cyc_nodes = nodes[~has_head[comp_of_nodes]]
    closed_comp = np.zeros(n_comp, bool)
    if len(cyc_nodes):
        first = np.full(n_comp, n_points, np.int64)
        np.minimum.at(first, label[cyc_nodes], cyc_nodes)
        heads = first[first < n_points]
        tails = pred[heads]
        succ[tails] = -1
        pred[heads] = -1
        closed_comp[label[heads]] = True
    # distance to the tail by pointer jumping
    dist = (succ >= 0).astype(np.int64)
    nxt = succ.copy()
    while True:
        m = nxt >= 0
        if not m.any():
            break
        idx = np.flatnonzero(m)
        dist_new = dist.copy()
        dist_new[idx] += dist[nxt[idx]]
        nxt_new = nxt.copy()
        nxt_new[idx] = nxt[nxt[idx]]
        dist, nxt = dist_new, nxt_new
    order = nodes[np.lexsort((-dist[nodes], label[nodes]))]
    lab = label[order]
    bounds = np.flatnonzero(np.diff(lab)) + 1
    offsets = np.concatenate([[0], bounds, [len(order)]]).astype(np.int64)
    closed = closed_comp[lab[offsets[:-1]]]
    # closed loops: repeat the first point at the end
    if closed.any():
        pieces, new_off = [], [0]
        for i in range(len(offsets) - 1):
            part = order[offsets[i]:offsets[i + 1]]
            if closed[i]:
                part = np.append(part, part[0])
            pieces.append(part)
            new_off.append(new_off[-1] + len(part))
        order = np.concatenate(pieces)
        offsets = np.asarray(new_off, np.int64)
    lengths = np.diff(offsets)
    keep = lengths >= 2
    if not keep.all():
        parts = [order[offsets[i]:offsets[i + 1]] for i in np.flatnonzero(keep)]
        order = np.concatenate(parts) if parts else np.zeros(0, np.int64)
        offsets = np.concatenate([[0], np.cumsum(lengths[keep])]).astype(np.int64)
        closed = closed[keep]
    return Polylines(order, offsets, closed)


def resample_polylines(points: FloatArray, offsets: IndexArray, spacing: float,
                       attributes: FloatArray | None = None, corner_angle_deg: float = 30.0
                       ) -> tuple[FloatArray, IndexArray, FloatArray | None]:
    """Arc-length resampling of flat polylines at ``spacing`` (ends and sharp corners kept).

    points : (N, 3); offsets : (P+1,); attributes : (N, k) interpolated the same way.
    Each polyline of length L gets ceil(L / spacing) equal pieces, plus its original vertices
    that turn by more than ``corner_angle_deg``. Returns (points, offsets, attributes).
    """
    points = np.asarray(points, np.float64)
    offsets = np.asarray(offsets, np.int64)
    n_poly = len(offsets) - 1
    if n_poly == 0:
        return points[:0], offsets[:1], None if attributes is None else attributes[:0]
    poly = np.repeat(np.arange(n_poly), np.diff(offsets))
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    same = poly[1:] == poly[:-1]
    seg = np.where(same, seg, 0.0)
    local = np.concatenate([[0.0], np.cumsum(seg)])
    local = local - local[offsets[:-1]][poly]                    # arc length within each polyline
    length = local[offsets[1:] - 1]
    start = np.concatenate([[0.0], np.cumsum(length[:-1] + 1.0)])  # gap of 1 between polylines
    u_vert = start[poly] + local
    n_piece = np.maximum(1, np.ceil(length / spacing - 1e-9)).astype(np.int64)
    cnt = n_piece + 1
    tp = np.repeat(np.arange(n_poly), cnt)
    k = np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    u = start[tp] + length[tp] * k / n_piece[tp]
    # sharp corners
    if len(points) > 2:
        d_prev = points[1:-1] - points[:-2]
        d_next = points[2:] - points[1:-1]
        interior = same[:-1] & same[1:]
        nprev = np.linalg.norm(d_prev, axis=1)
        nnext = np.linalg.norm(d_next, axis=1)
        cosang = np.einsum("ij,ij->i", d_prev, d_next) / np.maximum(nprev * nnext, 1e-300)
        corner = interior & (cosang < np.cos(np.radians(corner_angle_deg))) & (nprev > 0) & (nnext > 0)
        ci = np.flatnonzero(corner) + 1
        u = np.concatenate([u, u_vert[ci]])
        tp = np.concatenate([tp, poly[ci]])
    order = np.argsort(u, kind="stable")
    u, tp = u[order], tp[order]
    keep = np.ones(len(u), bool)
    keep[1:] = ~((np.diff(u) < 1e-9 * max(spacing, 1.0)) & (tp[1:] == tp[:-1]))
    u, tp = u[keep], tp[keep]
    # strictly increasing abscissa for interpolation (drop repeated vertices)
    dup = np.zeros(len(u_vert), bool)
    dup[1:] = np.diff(u_vert) <= 0
    uv = u_vert[~dup]
    out = np.stack([np.interp(u, uv, points[~dup, d]) for d in range(points.shape[1])], axis=1)
    attr_out = None
    if attributes is not None:
        a = np.asarray(attributes, np.float64).reshape(len(points), -1)[~dup]
        attr_out = np.stack([np.interp(u, uv, a[:, d]) for d in range(a.shape[1])], axis=1)
    counts = np.bincount(tp, minlength=n_poly)
    new_off = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    return out, new_off, attr_out
