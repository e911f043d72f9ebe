"""Curved layers: isosurfaces of G on the cage (marching tetrahedra), trimmed by H <= 0, in print order."""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import trimesh
from pydantic import BaseModel, Field

# local edges of a tet and, per sign case (bit i set when vertex i has G >= c), its triangles as local edges
TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]], dtype=np.int64)
_EDGE_ID = {tuple(e): i for i, e in enumerate(TET_EDGES.tolist())}


def _edge(a: int, b: int) -> int:
    """Local edge index of the tet edge (a, b)."""
    return _EDGE_ID[(min(a, b), max(a, b))]


def _case_table() -> np.ndarray:
    """Triangles (16, 2, 3) of local edge ids per sign case; -1 rows are unused."""
    table = -np.ones((16, 2, 3), dtype=np.int64)
    for case in range(1, 15):
        above = [i for i in range(4) if case >> i & 1]
        below = [i for i in range(4) if not case >> i & 1]
        if len(above) == 1 or len(below) == 1:
            lone = above[0] if len(above) == 1 else below[0]
            others = [i for i in range(4) if i != lone]
            table[case, 0] = [_edge(lone, o) for o in others]
        else:
            (a, b), (c, d) = above, below
            quad = [_edge(a, c), _edge(a, d), _edge(b, d), _edge(b, c)]
            table[case, 0] = [quad[0], quad[1], quad[2]]
            table[case, 1] = [quad[0], quad[2], quad[3]]
    return table


CASES = _case_table()


class LayerConfig(BaseModel):
    """How layers are chosen and trimmed."""

    layer_height: float = Field(0.8, gt=0, description="target layer thickness, mm")
    t_min: float = Field(0.4, gt=0, description="smallest acceptable local thickness, mm")
    t_max: float = Field(1.0, gt=0, description="largest acceptable local thickness, mm")
    min_area: float = Field(0.5, ge=0, description="connected layer pieces smaller than this (mm^2) are dropped")
    trim_iterations: int = Field(30, ge=1, description="bisection steps that put trimmed edges on H = 0")
    thickness_samples: int = Field(20_000, ge=100, description="interior points used to measure layer thickness")


@dataclass
class Layers:
    """Layers in print order: one triangle mesh each (faces oriented along +grad G), with their isovalues."""

    meshes: list[trimesh.Trimesh]
    isovalues: np.ndarray
    report: dict = field(default_factory=dict)

    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict]:
        """Concatenated vertices/faces/lpd with per-layer offsets, for the store."""
        nv = np.cumsum([0] + [len(m.vertices) for m in self.meshes])
        nf = np.cumsum([0] + [len(m.faces) for m in self.meshes])
        empty3 = np.zeros((0, 3))
        arrays = {
            "vertices": np.concatenate([m.vertices for m in self.meshes]) if self.meshes else empty3,
            "faces": np.concatenate([m.faces for m in self.meshes]).astype(np.int64) if self.meshes else empty3.astype(np.int64),
            "lpd": np.concatenate([m.vertex_attributes["lpd"] for m in self.meshes]) if self.meshes else empty3,
            "vertex_offsets": nv.astype(np.int64),
            "face_offsets": nf.astype(np.int64),
            "isovalues": np.asarray(self.isovalues, dtype=np.float64),
        }
        return arrays, {"n_layers": len(self.meshes), "report": self.report}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], attrs: dict) -> Layers:
        """Rebuild from store arrays."""
        nv, nf = arrays["vertex_offsets"], arrays["face_offsets"]
        meshes = []
        for i, iso in enumerate(arrays["isovalues"]):
            m = trimesh.Trimesh(arrays["vertices"][nv[i] : nv[i + 1]], arrays["faces"][nf[i] : nf[i + 1]], process=False)
            m.vertex_attributes["lpd"] = arrays["lpd"][nv[i] : nv[i + 1]]
            m.metadata["isovalue"] = float(iso)
            meshes.append(m)
        return cls(meshes, arrays["isovalues"], attrs.get("report", {}))


def tet_edges(tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique edges (E,2) of a tet mesh and the global edge id of each tet's six local edges (m,6)."""
    pairs = np.sort(tets[:, TET_EDGES].reshape(-1, 2), axis=1)
    edges, inverse = np.unique(pairs, axis=0, return_inverse=True)
    return edges, inverse.reshape(-1, 6)


def marching_tets(
    vertices: np.ndarray, tets: np.ndarray, values: np.ndarray, iso: float, lpd: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Isosurface values = iso: vertices, faces oriented along +grad (lpd per tet), and the source tet of each face."""
    edges, tet_edge = tet_edges(tets)
    return _marching(vertices, tets, values, np.array([iso]), lpd, edges, tet_edge)[0]


def _marching(
    vertices: np.ndarray,
    tets: np.ndarray,
    values: np.ndarray,
    isovalues: np.ndarray,
    lpd: np.ndarray,
    edges: np.ndarray,
    tet_edge: np.ndarray,
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Marching tetrahedra for several isovalues sharing the edge tables."""
    tv = values[tets]
    tmin, tmax = tv.min(axis=1), tv.max(axis=1)
    out = []
    for iso in isovalues:
        active = np.flatnonzero((tmin < iso) & (tmax >= iso))
        case = ((tv[active] >= iso) * (1 << np.arange(4))).sum(axis=1)
        tri_local = CASES[case]  # (k,2,3)
        valid = tri_local[:, :, 0] >= 0
        tri_tet = np.repeat(active, 2).reshape(-1, 2)[valid]
        tri_edges = np.take_along_axis(tet_edge[active][:, None, :].repeat(2, axis=1), tri_local.clip(0), axis=2)[valid]
        used, inv = np.unique(tri_edges, return_inverse=True)
        a, b = edges[used, 0], edges[used, 1]
        fa, fb = values[a], values[b]
        t = np.clip((iso - fa) / (fb - fa), 0.0, 1.0)
        # a crossing exactly at a cage vertex is that vertex: merge, then drop the collapsed triangles
        key = np.where(t <= 0, a, np.where(t >= 1, b, len(vertices) + used))
        ukey, kinv = np.unique(key, return_inverse=True)
        first = np.unique(kinv, return_index=True)[1]
        pts = (vertices[a] * (1 - t)[:, None] + vertices[b] * t[:, None])[first]
        faces = kinv[inv.reshape(-1, 3)]
        nondegenerate = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
        faces, tri_tet = faces[nondegenerate], tri_tet[nondegenerate]
        p = pts[faces]
        normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        flip = np.einsum("ij,ij->i", normal, lpd[tri_tet]) < 0
        faces[flip] = faces[flip][:, ::-1]
        out.append((pts, faces, tri_tet))
    return out


def split_edges_crossing_out(
    pts: np.ndarray, faces: np.ndarray, H: Callable[[np.ndarray], np.ndarray], rounds: int = 4, tol: float = 1e-4
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bisect edges whose endpoints are inside but whose midpoint is outside the solid (before trimming).

    Vertex signs miss the boundary where it passes between two inside vertices (a concave fillet or a
    thin gap narrower than the cage elements); a midpoint vertex outside lets `trim` cut there. Only
    edges near the surface (an endpoint closer than the edge length) are tested. Both triangles of an
    edge are split, so the mesh stays conforming; the midpoints of a planar triangle stay on the layer.
    Returns the new points, faces and, per face, the index of the face it came from.
    """
    src = np.arange(len(faces))
    for _ in range(rounds):
        edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
        uniq, inverse = np.unique(edges, axis=0, return_inverse=True)
        inverse = inverse.ravel().reshape(3, -1).T  # (f, 3): unique edge id of edge k = (v_k, v_k+1)
        h = H(pts)
        length = np.linalg.norm(pts[uniq[:, 0]] - pts[uniq[:, 1]], axis=1)
        near = (h[uniq[:, 0]] <= 0) & (h[uniq[:, 1]] <= 0) & (np.minimum(-h[uniq[:, 0]], -h[uniq[:, 1]]) < length)
        cand = np.flatnonzero(near)
        if len(cand) == 0:
            break
        h_mid = np.full(len(uniq), -np.inf)
        h_mid[cand] = H(0.5 * (pts[uniq[cand, 0]] + pts[uniq[cand, 1]]))
        bad_edge = h_mid > tol
        if not bad_edge.any():
            break
        score = np.where(bad_edge[inverse], h_mid[inverse], -np.inf)
        k = np.argmax(score, axis=1)
        rows = np.arange(len(faces))
        chooses = np.isfinite(score[rows, k])
        chosen = np.where(chooses, inverse[rows, k], 0)
        n_faces = np.bincount(inverse.ravel(), minlength=len(uniq))
        n_chose = np.bincount(chosen[chooses], minlength=len(uniq))
        split = bad_edge & (n_chose == n_faces)  # every triangle of the edge splits it this round
        if not split.any():
            break
        new_id = np.full(len(uniq), -1, dtype=np.int64)
        new_id[split] = len(pts) + np.arange(int(split.sum()))
        pts = np.concatenate([pts, 0.5 * (pts[uniq[split, 0]] + pts[uniq[split, 1]])])
        f = np.flatnonzero(chooses & split[chosen])
        kf = k[f]
        a, b, c = faces[f, kf], faces[f, (kf + 1) % 3], faces[f, (kf + 2) % 3]
        m = new_id[chosen[f]]
        faces = faces.copy()
        faces[f] = np.stack([a, m, c], axis=1)
        faces = np.concatenate([faces, np.stack([m, b, c], axis=1)])
        src = np.concatenate([src, src[f]])
    return pts, faces, src


def trim(
    pts: np.ndarray, faces: np.ndarray, H: Callable[[np.ndarray], np.ndarray], iterations: int = 30
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keep the part of a triangle mesh where H <= 0, splitting triangles on H = 0 (bisection on the edges)."""
    h = H(pts)
    inside = h <= 0
    fin = inside[faces]
    count = fin.sum(axis=1)
    keep = faces[count == 3]
    src = np.flatnonzero(count == 3)
    mixed = np.flatnonzero((count == 1) | (count == 2))
    if len(mixed) == 0:
        return _compact(pts, keep, src)
    mf = faces[mixed]
    # rotate each mixed triangle so that vertex 0 is the lone one (inside for count 1, outside for count 2)
    lone_inside = fin[mixed].sum(axis=1) == 1
    lone = np.where(lone_inside[:, None], fin[mixed], ~fin[mixed]).argmax(axis=1)
    roll = (np.arange(3)[None, :] + lone[:, None]) % 3
    mf = np.take_along_axis(mf, roll, axis=1)
    # crossing points on edges (0,1) and (0,2), shared between neighbours through a unique edge table
    e = np.concatenate([np.sort(mf[:, [0, 1]], axis=1), np.sort(mf[:, [0, 2]], axis=1)])
    ue, einv = np.unique(e, axis=0, return_inverse=True)
    einv = einv.ravel()
    ins = np.where(inside[ue[:, 0]], ue[:, 0], ue[:, 1])
    out = np.where(inside[ue[:, 0]], ue[:, 1], ue[:, 0])
    cross = edge_crossings(pts[ins], pts[out], h[ins], h[out], H, iterations)
    base = len(pts)
    allpts = np.concatenate([pts, cross])
    c01 = base + einv[: len(mixed)]
    c02 = base + einv[len(mixed) :]
    one = lone_inside
    tri_a = np.stack([mf[one, 0], c01[one], c02[one]], axis=1)
    two = ~one
    tri_b = np.stack([c01[two], mf[two, 1], mf[two, 2]], axis=1)
    tri_c = np.stack([c01[two], mf[two, 2], c02[two]], axis=1)
    new_faces = np.concatenate([keep, tri_a, tri_b, tri_c])
    new_src = np.concatenate([src, mixed[one], mixed[two], mixed[two]])
    return refine_boundary(*_compact(allpts, new_faces, new_src), H, iterations=iterations)


def refine_boundary(
    pts: np.ndarray, faces: np.ndarray, src: np.ndarray, H: Callable[[np.ndarray], np.ndarray],
    rounds: int = 3, tol: float = 1e-4, iterations: int = 30,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split boundary triangles whose boundary chord leaves the solid (concave borders) at a point on H = 0.

    A trimmed layer's boundary vertices lie on H = 0, but a straight boundary edge along a concave part
    of the surface cuts outside by its sagitta. Each round moves the midpoint of such an edge towards the
    opposite vertex, to H = 0 (within the triangle, so on the layer), and splits the triangle in two; a
    boundary edge belongs to one triangle only, so the mesh stays conforming. Each round divides the
    sagitta by about four.
    """
    for _ in range(rounds):
        edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
        _, inverse, counts = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
        boundary = (counts[inverse.ravel()] == 1).reshape(3, -1).T  # (f, 3): edge k = (v_k, v_k+1)
        face_id, k = np.nonzero(boundary)
        if len(face_id) == 0:
            break
        a = faces[face_id, k]
        b = faces[face_id, (k + 1) % 3]
        c = faces[face_id, (k + 2) % 3]
        mid = 0.5 * (pts[a] + pts[b])
        h_mid = H(mid)
        bad = h_mid > tol
        # one split per triangle and round: the worst boundary edge
        order = np.lexsort((-h_mid, face_id))
        first = order[np.r_[True, face_id[order][1:] != face_id[order][:-1]]]
        pick = first[bad[first]]
        if len(pick) == 0:
            break
        h_c = H(pts[c[pick]])
        ok = h_c <= 0
        pick = pick[ok]
        if len(pick) == 0:
            break
        new = edge_crossings(pts[c[pick]], mid[pick], h_c[ok], h_mid[pick], H, iterations)
        m = len(pts) + np.arange(len(pick))
        pts = np.concatenate([pts, new])
        f = face_id[pick]
        first_half = np.stack([a[pick], m, c[pick]], axis=1)
        second_half = np.stack([m, b[pick], c[pick]], axis=1)
        faces = faces.copy()
        faces[f] = first_half
        faces = np.concatenate([faces, second_half])
        src = np.concatenate([src, src[f]])
    return pts, faces, src


def edge_crossings(
    p_in: np.ndarray, p_out: np.ndarray, h_in: np.ndarray, h_out: np.ndarray,
    H: Callable[[np.ndarray], np.ndarray], iterations: int = 30, tol: float = 1e-7,
) -> np.ndarray:
    """Points on segments [p_in, p_out] (H <= 0 at p_in, > 0 at p_out) with H <= 0 and |H| <= tol where reachable.

    Illinois false position on the segment parameter (a few H evaluations for a distance-like H), then
    bisection for whatever has not converged; the returned point is always the inside end of the bracket.
    """
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
    return best


def _compact(pts: np.ndarray, faces: np.ndarray, src: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Drop unreferenced vertices."""
    used, inv = np.unique(faces, return_inverse=True)
    return pts[used], inv.reshape(-1, 3).astype(np.int64), src


def choose_isovalues(
    g_points: np.ndarray, grad_norm: np.ndarray, config: LayerConfig
) -> tuple[np.ndarray, dict]:
    """Isovalues so that the local thickness dG/|grad G| at interior points stays in [t_min, t_max] as far as possible."""
    order = np.argsort(g_points)
    g, gn = g_points[order], grad_norm[order]
    lo, hi = float(g[0]), float(g[-1])
    isos = [lo + 0.5 * config.layer_height * float(np.median(gn))]
    while isos[-1] < hi:
        c = isos[-1]
        i0, i1 = np.searchsorted(g, [c, c + 2 * config.t_max * float(gn.max())])
        slab = gn[i0:max(i1, i0 + 1)] if i0 < len(g) else gn[-1:]
        dg = config.layer_height * float(np.median(slab))
        dg = max(dg, config.t_min * float(slab.max()))
        dg = min(dg, config.t_max * float(slab.min()))
        isos.append(c + max(dg, 1e-9))
    isos = np.asarray(isos[:-1] if len(isos) > 1 and isos[-1] >= hi else isos)
    # thickness of the slab each interior point lies in
    slab_id = np.searchsorted(isos, g)
    edges = np.concatenate([[lo], isos, [hi]])
    dgs = edges[slab_id + 1] - edges[slab_id]
    inner = (slab_id > 0) & (slab_id < len(isos))
    thick = (dgs / gn)[inner] if inner.any() else dgs / gn
    report = {
        "thickness_min": float(thick.min()),
        "thickness_median": float(np.median(thick)),
        "thickness_max": float(thick.max()),
        "fraction_outside_range": float(np.mean((thick < config.t_min - 1e-9) | (thick > config.t_max + 1e-9))),
    }
    return isos, report


def extract_layers(
    cage_vertices: np.ndarray,
    cage_tets: np.ndarray,
    G: np.ndarray,
    lpd: np.ndarray,
    H: Callable[[np.ndarray], np.ndarray],
    isovalues: np.ndarray,
    config: LayerConfig,
    progress: Callable[[int, int], None] | None = None,
    batch: int = 64,
) -> Layers:
    """Isosurfaces of G at the isovalues, trimmed by H <= 0, small pieces dropped, in print order.

    Layers are trimmed in batches (one H evaluation per batch and crossing iteration, not per layer).
    """
    edges, tet_edge = tet_edges(cage_tets)
    meshes, kept_iso = [], []
    dropped_pieces, dropped_area = 0, 0.0
    for start in range(0, len(isovalues), batch):
        isos = np.asarray(isovalues[start : start + batch])
        parts = _marching(cage_vertices, cage_tets, G, isos, lpd, edges, tet_edge)
        offsets = np.cumsum([0] + [len(p) for p, _, _ in parts])
        pts = np.concatenate([p for p, _, _ in parts])
        faces = np.concatenate([f + o for (_, f, _), o in zip(parts, offsets)]).astype(np.int64)
        src_tet = np.concatenate([t for _, _, t in parts])
        face_layer = np.concatenate([np.full(len(f), i) for i, (_, f, _) in enumerate(parts)])
        if len(faces):
            pts, faces, parent = split_edges_crossing_out(pts, faces, H)
            pts, faces, src = trim(pts, faces, H, config.trim_iterations)
            src = parent[src]
            src_tet, face_layer = src_tet[src], face_layer[src]
        for i, iso in enumerate(isos):
            mesh, n_drop, a_drop = _layer_mesh(pts, faces[face_layer == i], lpd[src_tet[face_layer == i]], config.min_area)
            dropped_pieces += n_drop
            dropped_area += a_drop
            if mesh is not None:
                mesh.metadata["isovalue"] = float(iso)
                meshes.append(mesh)
                kept_iso.append(float(iso))
        if progress is not None:
            progress(min(start + batch, len(isovalues)), len(isovalues))
    report = {"dropped_pieces": int(dropped_pieces), "dropped_area_mm2": float(dropped_area)}
    return Layers(meshes, np.asarray(kept_iso), report)


def _layer_mesh(
    pts: np.ndarray, faces: np.ndarray, face_lpd: np.ndarray, min_area: float
) -> tuple[trimesh.Trimesh | None, int, float]:
    """One layer's mesh with per-vertex LPD (area-weighted), small pieces dropped; None when nothing is left."""
    if len(faces) == 0:
        return None, 0, 0.0
    used, inv = np.unique(faces, return_inverse=True)
    mesh = trimesh.Trimesh(pts[used], inv.reshape(-1, 3), process=False)
    vlpd = np.zeros((len(used), 3))
    np.add.at(vlpd, mesh.faces.ravel(), np.repeat(face_lpd * mesh.area_faces[:, None], 3, axis=0))
    vlpd /= np.maximum(np.linalg.norm(vlpd, axis=1, keepdims=True), 1e-300)
    mesh.vertex_attributes["lpd"] = vlpd
    mesh, n_drop, a_drop = _drop_small_pieces(mesh, min_area)
    return (mesh if len(mesh.faces) else None), n_drop, a_drop


def _drop_small_pieces(mesh: trimesh.Trimesh, min_area: float) -> tuple[trimesh.Trimesh, int, float]:
    """Remove connected pieces whose area is below min_area."""
    if min_area <= 0 or len(mesh.faces) == 0:
        return mesh, 0, 0.0
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
    area = np.bincount(labels, weights=mesh.area_faces)
    small = area < min_area
    if not small.any():
        return mesh, 0, 0.0
    keep = ~small[labels]
    lpd = mesh.vertex_attributes["lpd"]
    faces = mesh.faces[keep]
    used, inv = np.unique(faces, return_inverse=True)
    out = trimesh.Trimesh(mesh.vertices[used], inv.reshape(-1, 3), process=False)
    out.vertex_attributes["lpd"] = lpd[used]
    return out, int(small.sum()), float(area[small].sum())
