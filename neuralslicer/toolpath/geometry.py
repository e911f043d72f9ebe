"""Layer-patch geometry: components, refinement, boundary distance, closest points, thickness."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy import sparse
from scipy.sparse.csgraph import connected_components, dijkstra
from scipy.spatial import cKDTree

from neuralslicer.types import FloatArray, IndexArray


@dataclass
class Patch:
    """One connected component of a layer: vertices (n,3), faces (m,3), unit LPD per vertex."""

    vertices: FloatArray
    faces: IndexArray
    lpd: FloatArray

    @property
    def area(self) -> float:
        """Surface area (mm^2)."""
        tri = self.vertices[self.faces]
        return float(0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]),
                                          axis=1).sum())


def _normalise(v: FloatArray) -> FloatArray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


def layer_lpd(layer: trimesh.Trimesh) -> FloatArray:
    """Unit LPD per vertex: ``vertex_attributes['lpd']``, else the area-weighted vertex normals."""
    lpd = layer.vertex_attributes.get("lpd") if hasattr(layer, "vertex_attributes") else None
    if lpd is None:
        lpd = np.asarray(layer.vertex_normals, dtype=np.float64)
    return _normalise(np.asarray(lpd, dtype=np.float64).reshape(-1, 3))


def clean_layer(vertices: FloatArray, faces: IndexArray, lpd: FloatArray, rel_tol: float = 1e-9
                ) -> tuple[FloatArray, IndexArray, FloatArray]:
    """Merge coincident vertices, drop degenerate faces, orient faces along the LPD.

    Returns (vertices, faces, lpd); a face whose normal points against the mean LPD of its
    vertices is flipped, so isolines chain consistently.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    size = float(np.ptp(v, axis=0).max()) if len(v) else 1.0
    q = np.round(v / max(rel_tol * size, 1e-300)).astype(np.int64)
    _, first, inv = np.unique(q, axis=0, return_index=True, return_inverse=True)
    inv = inv.reshape(-1)
    if len(first) < len(v):
        lpd_sum = np.zeros((len(first), 3))
        np.add.at(lpd_sum, inv, lpd)
        v, lpd, f = v[first], _normalise(lpd_sum), inv[f]
    tri = v[f]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area2 = np.linalg.norm(normal, axis=1)
    ok = (area2 > 1e-12 * size * size) & (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    f, normal = f[ok], normal[ok]
    flip = np.einsum("ij,ij->i", normal, lpd[f].sum(axis=1)) < 0
    f[flip] = f[flip][:, ::-1]
    return v, f, lpd


def split_patches(vertices: FloatArray, faces: IndexArray, lpd: FloatArray) -> list[Patch]:
    """Connected components (through shared vertices) of a layer mesh, unreferenced vertices dropped."""
    vertices, faces, lpd = clean_layer(vertices, faces, lpd)
    n = len(vertices)
    if len(faces) == 0:
        return []
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    g = sparse.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    _, lab = connected_components(g, directed=False)
    flab = lab[faces[:, 0]]
    patches = []
    order = np.argsort(flab, kind="stable")
    bounds = np.flatnonzero(np.diff(flab[order])) + 1
    for group in np.split(order, bounds):
        f = faces[group]
        used, inv = np.unique(f, return_inverse=True)
        patches.append(Patch(np.asarray(vertices[used], np.float64), inv.reshape(-1, 3).astype(np.int64),
                             lpd[used]))
    return patches


def _split_edges(v: FloatArray, f: IndexArray, lpd: FloatArray, split_face: np.ndarray, max_edge: float
                 ) -> tuple[FloatArray, IndexArray, FloatArray]:
    """Split at their midpoints the edges longer than ``max_edge`` of the faces in ``split_face``.

    Conforming: a split edge is split in both of its faces, and each face is cut by the template of
    its split-edge count (one edge: 2 triangles, two: 3, three: 4), keeping its orientation.
    """
    m = len(f)
    e = np.sort(np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], axis=1), axis=2)    # (m, 3, 2)
    ukey, eid = np.unique(e[..., 0] * len(v) + e[..., 1], return_inverse=True)
    eid = eid.reshape(m, 3)
    ua, ub = ukey // len(v), ukey % len(v)
    long_edge = np.linalg.norm(v[ua] - v[ub], axis=1) > max_edge
    split = np.zeros(len(ukey), bool)
    split[eid[split_face].ravel()] = True
    split &= long_edge
    if not split.any():
        return v, f, lpd
    mid = np.full(len(ukey), -1, np.int64)
    mid[split] = len(v) + np.arange(int(split.sum()))
    v = np.concatenate([v, 0.5 * (v[ua[split]] + v[ub[split]])])
    lpd = np.concatenate([lpd, _normalise(lpd[ua[split]] + lpd[ub[split]])])
    mf = mid[eid]                                                 # (m, 3): midpoint of edge k = (k, k+1)
    count = (mf >= 0).sum(axis=1)
    # rotate each face so that its template is canonical: one split edge at slot 0, or the one
    # unsplit edge at slot 2
    r = np.zeros(m, np.int64)
    one, two = count == 1, count == 2
    r[one] = np.argmax(mf[one] >= 0, axis=1)
    r[two] = (np.argmax(mf[two] < 0, axis=1) + 1) % 3
    roll = (np.arange(3)[None, :] + r[:, None]) % 3
    F = np.take_along_axis(f, roll, axis=1)
    M = np.take_along_axis(mf, roll, axis=1)
    v0, v1, v2, m0, m1, m2 = F[:, 0], F[:, 1], F[:, 2], M[:, 0], M[:, 1], M[:, 2]
    out = [f[count == 0]]
    out += [np.stack(t, axis=1)[one] for t in ((v0, m0, v2), (m0, v1, v2))]
    # two split edges: the corner triangle at v1 and the quad v0-m0-m1-v2 cut along its shorter diagonal
    short = np.linalg.norm(v[v0] - v[m1], axis=1) <= np.linalg.norm(v[m0] - v[v2], axis=1)
    out.append(np.stack((m0, v1, m1), axis=1)[two])
    for sel, tris in ((two & short, ((v0, m0, m1), (v0, m1, v2))), (two & ~short, ((v0, m0, v2), (m0, m1, v2)))):
        out += [np.stack(t, axis=1)[sel] for t in tris]
    three = count == 3
    out += [np.stack(t, axis=1)[three] for t in ((v0, m0, m2), (m0, v1, m1), (m2, m1, v2), (m0, m1, m2))]
    return v, np.concatenate(out).astype(np.int64), lpd


def refine_patch(patch: Patch, max_edge: float, band: float = np.inf, max_rounds: int = 12) -> Patch:
    """Split edges longer than ``max_edge`` in the faces within ``band`` of the patch boundary.

    Distances beyond the band are never needed to full resolution (zig-zag infill lines are
    isolines of a linear function, exact on the layer's own triangles), so the work grows with the
    boundary length times the band, not with the patch area. ``band = inf`` refines everything.
    """
    v, f, lpd = patch.vertices, patch.faces, patch.lpd
    bverts, bedges = boundary_vertices(f)
    for _ in range(max_rounds):
        tri = v[f]
        longest = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(axis=1)
        todo = longest > max_edge
        if np.isfinite(band) and todo.any():
            if len(bedges) == 0:
                break
            d = euclidean_boundary_distance(v, bedges, upper=band + float(longest.max()))
            todo &= d[f].min(axis=1) < band + longest
        if not todo.any():
            break
        v, f, lpd = _split_edges(v, f, lpd, todo, max_edge)
    return Patch(np.asarray(v, np.float64), np.asarray(f, np.int64), lpd)


def boundary_vertices(faces: IndexArray) -> tuple[IndexArray, IndexArray]:
    """Vertices on the boundary and the boundary edges (edges used by exactly one face)."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    n = int(faces.max()) + 1 if len(faces) else 1
    ukey, counts = np.unique(e[:, 0] * n + e[:, 1], return_counts=True)
    ukey = ukey[counts == 1]
    bedges = np.stack([ukey // n, ukey % n], axis=1)
    return np.unique(bedges), bedges


def _segment_distance(points: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    """Distance from points (n,3) to segments a-b (n,k,3) -> (n,k)."""
    ab = b - a
    t = np.einsum("nkj,nkj->nk", points[:, None, :] - a, ab) / np.maximum(np.einsum("nkj,nkj->nk", ab, ab), 1e-300)
    q = a + np.clip(t, 0.0, 1.0)[..., None] * ab
    return np.linalg.norm(points[:, None, :] - q, axis=2)


def euclidean_boundary_distance(vertices: FloatArray, bedges: IndexArray, k: int = 6,
                                upper: float = np.inf) -> FloatArray:
    """Straight-line distance from each vertex to the nearest boundary edge (n,), at most ``upper``.

    Exact geodesic distance to the boundary on planar patches; a chord (slight under-estimate,
    relative error ~ d^2 / (24 R^2)) on patches of curvature radius R. Vertices further than
    ``upper`` from every boundary sample get ``upper`` (the search stops there, which is what
    keeps it cheap on large patches).
    """
    va, vb = vertices[bedges[:, 0]], vertices[bedges[:, 1]]
    lengths = np.linalg.norm(vb - va, axis=1)
    step = max(float(np.median(lengths)) * 0.5, 1e-9)
    n_s = np.maximum(1, np.ceil(lengths / step)).astype(np.int64)
    seg = np.repeat(np.arange(len(bedges)), n_s)
    t = (np.arange(len(seg)) - np.repeat(np.cumsum(n_s) - n_s, n_s) + 0.5) / n_s[seg]
    samples = va[seg] + t[:, None] * (vb - va)[seg]
    kk = int(min(k, len(samples)))
    # a sample lies within half a sample spacing of its edge: search that much further
    reach = upper + step if np.isfinite(upper) else np.inf
    _, idx = cKDTree(samples).query(vertices, k=kk, distance_upper_bound=reach)
    idx = np.asarray(idx).reshape(len(vertices), kk)
    found = idx < len(samples)
    out = np.full(len(vertices), float(upper))
    near = found[:, 0]
    if near.any():
        cand = seg[np.where(found[near], idx[near], idx[near][:, :1])]
        dist = _segment_distance(vertices[near], va[cand], vb[cand]).min(axis=1)
        out[near] = np.minimum(dist, upper)
    return out


def is_planar(vertices: FloatArray, rel_tol: float = 1e-9) -> bool:
    """True when all vertices lie on one plane (within rel_tol x the patch size)."""
    c = vertices - vertices.mean(axis=0)
    size = float(np.ptp(vertices, axis=0).max()) if len(vertices) else 0.0
    if size == 0.0:
        return True
    sv = np.linalg.svd(c, compute_uv=False)
    return bool(sv[-1] / np.sqrt(len(vertices)) <= rel_tol * size)


def boundary_distance(patch: Patch, upper: float = np.inf) -> FloatArray:
    """Distance of every vertex from the patch boundary along the patch (n,).

    The geodesic distance by the heat method (potpourri3d, intrinsic-Delaunay "robust" mode;
    Dijkstra along edges if the solver rejects the mesh) over-estimates near the sources by up
    to ~h, so wherever the straight-line distance to the boundary edges is at least half of it
    (no fold of the patch in between) the straight-line distance is used: it is exact on planar
    patches and a chord on curved ones. Planar patches skip the heat method (the straight-line
    distance is the exact geodesic distance there). All +inf when the patch has no boundary;
    distances are clipped at ``upper``.
    """
    bverts, bedges = boundary_vertices(patch.faces)
    n = len(patch.vertices)
    if len(bverts) == 0:
        return np.full(n, np.inf)
    euclid = euclidean_boundary_distance(patch.vertices, bedges, upper=upper)
    if is_planar(patch.vertices):
        euclid[bverts] = 0.0
        return euclid
    try:
        import potpourri3d as pp3d

        solver = pp3d.MeshHeatMethodDistanceSolver(patch.vertices, patch.faces, t_coef=1.0,
                                                   use_robust=True)
        d = np.asarray(solver.compute_distance_multisource(bverts.tolist()), np.float64)
        if not np.all(np.isfinite(d)):
            raise ValueError("non-finite heat distance")
    except Exception:  # noqa: BLE001 - any solver failure: use the graph distance
        f = patch.faces
        e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        w = np.linalg.norm(patch.vertices[e[:, 0]] - patch.vertices[e[:, 1]], axis=1)
        g = sparse.coo_matrix((w, (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
        d = np.asarray(dijkstra(g, directed=False, indices=bverts, min_only=True), np.float64)
    d = np.maximum(d, 0.0)
    d = np.minimum(np.where(euclid >= 0.5 * d, euclid, d), upper)
    d[bverts] = 0.0
    return d


_CHUNK = 20000


class TriangleSet:
    """Closest points and ray hits against a triangle soup, candidates from a centroid KD-tree."""

    def __init__(self, vertices: FloatArray, faces: IndexArray, k: int = 12) -> None:
        """Index the triangles ``vertices[faces]`` (m, 3, 3)."""
        self.triangles = np.asarray(vertices, np.float64)[np.asarray(faces, np.int64)]
        self.k = int(min(k, len(self.triangles)))
        self.tree = cKDTree(self.triangles.mean(axis=1))

    def _candidates(self, points: FloatArray) -> IndexArray:
        _, idx = self.tree.query(points, k=self.k)
        return np.asarray(idx, np.int64).reshape(len(points), self.k)

    def closest(self, points: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Closest point on the triangles to each point, and the distance: (n,3), (n,)."""
        points = np.asarray(points, np.float64).reshape(-1, 3)
        if len(points) == 0:
            return points.copy(), np.zeros(0)
        if len(points) > _CHUNK:
            parts = [self.closest(points[i:i + _CHUNK]) for i in range(0, len(points), _CHUNK)]
            return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
        cand = self._candidates(points)
        tri = self.triangles[cand.ravel()]
        rep = np.repeat(points, self.k, axis=0)
        cp = trimesh.triangles.closest_point(tri, rep).reshape(len(points), self.k, 3)
        d = np.linalg.norm(cp - points[:, None, :], axis=2)
        best = np.argmin(d, axis=1)
        r = np.arange(len(points))
        return cp[r, best], d[r, best]

    def ray_distance(self, origins: FloatArray, directions: FloatArray, near: FloatArray
                     ) -> FloatArray:
        """Distance along unit ``directions`` to the first hit (inf if none), candidates near ``near``."""
        origins = np.asarray(origins, np.float64).reshape(-1, 3)
        if len(origins) == 0:
            return np.zeros(0)
        cand = self._candidates(near)
        tri = self.triangles[cand]                          # (n, k, 3, 3)
        o = origins[:, None, :]
        dvec = np.asarray(directions, np.float64)[:, None, :]
        e1 = tri[:, :, 1] - tri[:, :, 0]
        e2 = tri[:, :, 2] - tri[:, :, 0]
        p = np.cross(dvec, e2)
        det = np.einsum("nkj,nkj->nk", e1, p)
        ok = np.abs(det) > 1e-14
        inv = 1.0 / np.where(ok, det, 1.0)
        s = o - tri[:, :, 0]
        u = np.einsum("nkj,nkj->nk", s, p) * inv
        q = np.cross(s, e1)
        v = np.einsum("nkj,nkj->nk", np.broadcast_to(dvec, q.shape), q) * inv
        t = np.einsum("nkj,nkj->nk", e2, q) * inv
        tol = 1e-9
        hit = ok & (u >= -tol) & (v >= -tol) & (u + v <= 1 + tol) & (t > 1e-9)
        t = np.where(hit, t, np.inf)
        return t.min(axis=1)


def layer_thickness(points: FloatArray, axis: FloatArray, below: TriangleSet | None,
                    platform_z: float, max_thickness: float, first_layer_max: float) -> FloatArray:
    """Local layer thickness at waypoints: distance along ``-axis`` to the layer below.

    The ray along ``-axis`` is cast at the layer below (candidate triangles from a KD-tree around
    the closest point) and at the platform plane; the nearer hit wins. Where the ray misses the
    layer below (near trimmed boundaries), the closest-point distance to it is used instead of
    the ray hit (still bounded by the platform distance). Everything is capped at ``max_thickness``;
    on the first layer (``below`` None) the platform distance is capped at ``first_layer_max``.
    """
    points = np.asarray(points, np.float64).reshape(-1, 3)
    axis = np.asarray(axis, np.float64).reshape(-1, 3)
    if below is not None and len(points) > _CHUNK:
        return np.concatenate([
            layer_thickness(points[i:i + _CHUNK], axis[i:i + _CHUNK], below, platform_z,
                            max_thickness, first_layer_max)
            for i in range(0, len(points), _CHUNK)])
    down = -axis
    az = down[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_plat = np.where(az < -1e-9, (platform_z - points[:, 2]) / az, np.inf)
    t_plat = np.where(t_plat >= 0, t_plat, np.inf)
    if below is None:
        t = np.where(np.isfinite(t_plat), t_plat, points[:, 2] - platform_z)
        return np.clip(t, 0.0, first_layer_max)
    _, d_close = below.closest(points)
    near = points + down * d_close[:, None]
    t_ray = below.ray_distance(points, down, near)
    t = np.where(np.isfinite(t_ray), np.minimum(t_ray, t_plat), np.minimum(d_close, t_plat))
    return np.clip(t, 0.0, max_thickness)
