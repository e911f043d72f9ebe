"""Layer-patch geometry: components, refinement, boundary distance, closest points, thickness."""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import connected_components, dijkstra

from neuralslicer.types import FloatArray, IndexArray

if TYPE_CHECKING:  # trimesh (and scipy.spatial, networkx) only where a mesh is made: not on a cached rerun
    import trimesh


@dataclass
class Patch:
    """One connected component of a layer: vertices (n,3), faces (m,3), unit LPD per vertex (n,3)."""

    vertices: FloatArray
    faces: IndexArray
    lpd: FloatArray
    #: straight-line distance of each vertex to the boundary (n,), where already measured
    distance: FloatArray | None = None
    #: per-vertex values (n,) or (n, k) that refinement interpolates linearly (a midpoint gets its edge's mean)
    values: FloatArray | None = None

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


def _length2(vectors: FloatArray) -> FloatArray:
    """Squared lengths of vectors (n, 3) -> (n,)."""
    return np.einsum("ij,ij->i", vectors, vectors)


def _split_edges(v: FloatArray, f: IndexArray, lpd: FloatArray, split_face: np.ndarray, max_edge: float,
                 values: FloatArray | None = None) -> tuple[FloatArray, IndexArray, FloatArray, FloatArray | None]:
    """Split at their midpoints the edges longer than ``max_edge`` of the faces in ``split_face``.

    Conforming: a split edge is split in both of its faces, and each face is cut by the template of
    its split-edge count (one edge: 2 triangles, two: 3, three: 4), keeping its orientation.
    """
    m = len(f)
    f_next = f[:, [1, 2, 0]]                                      # edge k = (k, k+1)
    ukey, eid = np.unique(np.minimum(f, f_next) * len(v) + np.maximum(f, f_next), return_inverse=True)
    eid = eid.reshape(m, 3)
    ua, ub = ukey // len(v), ukey % len(v)
    long_edge = _length2(v[ua] - v[ub]) > max_edge * max_edge
    split = np.zeros(len(ukey), bool)
    split[eid[split_face].ravel()] = True
    split &= long_edge
    if not split.any():
        return v, f, lpd, values
    mid = np.full(len(ukey), -1, np.int64)
    mid[split] = len(v) + np.arange(int(split.sum()))
    v = np.concatenate([v, 0.5 * (v[ua[split]] + v[ub[split]])])
    lpd = np.concatenate([lpd, _normalise(lpd[ua[split]] + lpd[ub[split]])])
    if values is not None:
        values = np.concatenate([values, 0.5 * (values[ua[split]] + values[ub[split]])])
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
    return v, np.concatenate(out).astype(np.int64), lpd, values


def refine_patch(patch: Patch, max_edge: float, band: float = np.inf, max_rounds: int = 12) -> Patch:
    """Split edges longer than ``max_edge`` in the faces that reach within ``band`` of the patch boundary.

    Distances beyond the band are never needed to full resolution (zig-zag infill lines are
    isolines of a linear function, exact on the layer's own triangles), so the work grows with the
    boundary length times the band, not with the patch area. ``band = inf`` refines everything.
    A face reaches into the band when its smallest vertex distance is below ``band`` plus
    ``longest edge / sqrt(3)`` (no point of a triangle is further than that from all its vertices).
    With a finite band the result carries the straight-line boundary distance of its vertices
    (``Patch.distance``): the input's vertices are measured once, each round only its midpoints.
    """
    v, f, lpd, values = patch.vertices, patch.faces, patch.lpd, patch.values
    d: FloatArray | None = None
    if np.isfinite(band):
        _, bedges = boundary_vertices(f)
        if len(bedges) == 0:
            return patch
        nearest = ElementSet(v, bedges)
        d = patch.distance if patch.distance is not None else nearest.distance(v)
    # a face without a long edge never changes again (only long edges are split), so each round
    # handles the faces that still have one
    done: list[IndexArray] = []
    for _ in range(max_rounds):
        p0, p1, p2 = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
        longest2 = np.maximum(np.maximum(_length2(p1 - p0), _length2(p2 - p1)), _length2(p0 - p2))
        long_face = longest2 > max_edge * max_edge
        done.append(f[~long_face])
        f = f[long_face]
        if not len(f):
            break
        todo = np.ones(len(f), bool)
        if d is not None:
            # a point of the face is within longest / sqrt(3) of one of its vertices, and d is 1-Lipschitz
            todo = d[f].min(axis=1) < band + np.sqrt(longest2[long_face] / 3.0)
        if not todo.any():
            break
        n_old = len(v)
        v, f, lpd, values = _split_edges(v, f, lpd, todo, max_edge, values)
        if len(v) == n_old:
            break
        if d is not None:
            d = np.concatenate([d, nearest.distance(v[n_old:])])
    f = np.concatenate(done + [f])
    return Patch(np.asarray(v, np.float64), np.asarray(f, np.int64), lpd, d, values)


def boundary_vertices(faces: IndexArray) -> tuple[IndexArray, IndexArray]:
    """Vertices on the boundary and the boundary edges (edges used by exactly one face)."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    n = int(faces.max()) + 1 if len(faces) else 1
    ukey, counts = np.unique(e[:, 0] * n + e[:, 1], return_counts=True)
    ukey = ukey[counts == 1]
    bedges = np.stack([ukey // n, ukey % n], axis=1)
    return np.unique(bedges), bedges


class ElementSet:
    """Exact closest points on a set of triangles (m, 3) or segments (m, 2) of ``vertices`` (n, 3).

    A libigl AABB tree over the elements: a query costs O(log m), whatever the distance, so no
    search radius or candidate count is needed.
    """

    def __init__(self, vertices: FloatArray, elements: IndexArray) -> None:
        """Index the elements ``vertices[elements]``."""
        import igl

        self.vertices = np.ascontiguousarray(vertices, np.float64)
        self.elements = np.ascontiguousarray(elements, np.int64)
        self.tree = igl.AABB()
        if len(self.elements):
            self.tree.init(self.vertices, self.elements)

    def closest(self, points: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Closest point on the elements to each point, and the distance: (n, 3), (n,)."""
        points = np.ascontiguousarray(points, np.float64).reshape(-1, 3)
        if len(points) == 0 or len(self.elements) == 0:
            return points.copy(), np.full(len(points), np.inf)
        sqr, _, cp = self.tree.squared_distance(self.vertices, self.elements, points)
        return np.asarray(cp, np.float64).reshape(-1, 3), np.sqrt(np.maximum(sqr, 0.0))

    def distance(self, points: FloatArray) -> FloatArray:
        """Distance from each point (n, 3) to the nearest element (n,)."""
        return self.closest(points)[1]


def euclidean_boundary_distance(vertices: FloatArray, bedges: IndexArray, upper: float = np.inf) -> FloatArray:
    """Straight-line distance from each vertex to the nearest boundary edge (n,), at most ``upper``.

    Exact (an AABB tree over the boundary segments). It is the geodesic distance to the boundary
    on planar patches and a chord (slight under-estimate, relative error ~ d^2 / (24 R^2)) on
    patches of curvature radius R.
    """
    if len(bedges) == 0:
        return np.full(len(vertices), float(upper))
    return np.minimum(ElementSet(vertices, bedges).distance(vertices), upper)


def is_planar(vertices: FloatArray, rel_tol: float = 1e-9) -> bool:
    """True when all vertices lie on one plane (within rel_tol x the patch size)."""
    c = vertices - vertices.mean(axis=0)
    size = float(np.ptp(vertices, axis=0).max()) if len(vertices) else 0.0
    if size == 0.0:
        return True
    sv = np.linalg.svd(c, compute_uv=False)
    return bool(sv[-1] / np.sqrt(len(vertices)) <= rel_tol * size)


def _submesh(faces: IndexArray, keep_face: np.ndarray) -> tuple[IndexArray, IndexArray]:
    """Faces ``keep_face`` renumbered over their own vertices: (faces (k, 3), vertex ids (n_k,))."""
    f = faces[keep_face]
    used, inv = np.unique(f, return_inverse=True)
    return inv.reshape(-1, 3).astype(np.int64), used


def _geodesic_distance(vertices: FloatArray, faces: IndexArray, sources: IndexArray) -> FloatArray:
    """Geodesic distance from ``sources`` by the heat method (Dijkstra on edges if the solver fails) (n,).

    Vertices not connected to a source get +inf.
    """
    n = len(vertices)
    try:
        import potpourri3d as pp3d

        solver = pp3d.MeshHeatMethodDistanceSolver(vertices, faces, t_coef=1.0, use_robust=True)
        d = np.asarray(solver.compute_distance_multisource(sources.tolist()), np.float64)
        if not np.all(np.isfinite(d)):
            raise ValueError("non-finite heat distance")
        return np.maximum(d, 0.0)
    except Exception:  # noqa: BLE001 - any solver failure: use the graph distance
        e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
        w = np.linalg.norm(vertices[e[:, 0]] - vertices[e[:, 1]], axis=1)
        g = sparse.coo_matrix((w, (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
        return np.asarray(dijkstra(g, directed=False, indices=sources, min_only=True), np.float64)


def boundary_distance(patch: Patch, upper: float = np.inf, surface: TriangleSet | None = None) -> FloatArray:
    """Distance of every vertex from the patch boundary along the patch (n,), clipped at ``upper``.

    The straight-line distance to the boundary edges, which is the geodesic distance on planar
    patches and a chord on curved ones (relative error ~ d^2 / (24 R^2) at curvature radius R),
    except where the chord from a vertex to its nearest boundary point leaves the patch (its
    midpoint is further from the patch than a quarter of its length: the patch folds back near
    its boundary). There the geodesic distance decides: by the heat method (potpourri3d,
    intrinsic-Delaunay "robust" mode; Dijkstra along edges if the solver rejects the mesh) on the
    faces within ``upper`` of the boundary (a geodesic of length at most ``upper`` never leaves
    them), used where the straight-line distance is less than half of it. ``surface``: the
    patch's triangles for the chord test (default: the patch itself; the unrefined patch is the
    same surface and cheaper). All +inf when the patch has no boundary.
    """
    bverts, bedges = boundary_vertices(patch.faces)
    n = len(patch.vertices)
    if len(bverts) == 0:
        return np.full(n, np.inf)
    nearest = ElementSet(patch.vertices, bedges)
    if patch.distance is not None and len(patch.distance) == n:
        euclid = np.minimum(patch.distance, upper)
    else:
        euclid = np.minimum(nearest.distance(patch.vertices), upper)
    euclid[bverts] = 0.0
    if is_planar(patch.vertices):
        return euclid
    cand = np.flatnonzero((euclid < upper) & (euclid > 0.0))
    foot, chord = nearest.closest(patch.vertices[cand])
    surface = surface if surface is not None else TriangleSet(patch.vertices, patch.faces)
    sag = surface.distance(0.5 * (patch.vertices[cand] + foot))
    fold = cand[sag > 0.25 * chord]
    if len(fold) == 0:
        return euclid
    near = euclid[patch.faces].min(axis=1) < upper
    if not near.all():
        # pieces of the band cut off from the boundary (the fold brought them near it) are further
        # than ``upper`` along the patch
        f = patch.faces[near]
        e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]]])
        _, label = connected_components(sparse.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)),
                                        directed=False)
        reached = np.zeros(label.max() + 1, bool)
        reached[label[bverts]] = True
        near[near] = reached[label[f[:, 0]]]
    faces, ids = _submesh(patch.faces, near)
    local = np.full(n, -1, np.int64)
    local[ids] = np.arange(len(ids))
    geo = np.full(n, np.inf)
    geo[ids] = _geodesic_distance(patch.vertices[ids], faces, local[bverts])
    d = euclid.copy()
    d[fold] = np.minimum(np.where(euclid[fold] >= 0.5 * geo[fold], euclid[fold], geo[fold]), upper)
    return d


class TriangleSet(ElementSet):
    """Closest points and first ray hits on a triangle mesh (libigl AABB tree)."""

    def __init__(self, vertices: FloatArray, faces: IndexArray) -> None:
        """Index the triangles ``vertices[faces]`` (m, 3, 3)."""
        super().__init__(vertices, faces)

    def ray_distance(self, origins: FloatArray, directions: FloatArray, reach: float = np.inf) -> FloatArray:
        """Distance along unit ``directions`` (n, 3) to the first hit within ``reach`` (n,), inf if none."""
        origins = np.ascontiguousarray(origins, np.float64).reshape(-1, 3)
        if len(origins) == 0 or len(self.elements) == 0:
            return np.full(len(origins), np.inf)
        directions = np.ascontiguousarray(directions, np.float64).reshape(-1, 3)
        hit, t, _ = self.tree.intersect_ray_first(self.vertices, self.elements, origins, directions, float(reach))
        return np.where(np.asarray(hit) >= 0, np.asarray(t, np.float64), np.inf)


def layer_thickness(points: FloatArray, axis: FloatArray, below: TriangleSet | None,
                    platform_z: float, max_thickness: float, first_layer_max: float) -> FloatArray:
    """Local layer thickness at waypoints: distance along ``-axis`` to the layer below.

    The ray along ``-axis`` is cast at the layer below (first hit within twice ``max_thickness``:
    a hit further along the ray is not the layer below this point) and at the platform plane; the
    nearer hit wins. Where the ray misses the layer below (near trimmed boundaries), the
    closest-point distance to it is used instead of the ray hit (still bounded by the platform
    distance). Everything is capped at ``max_thickness``; on the first layer (``below`` None) the
    platform distance is capped at ``first_layer_max``.
    """
    points = np.asarray(points, np.float64).reshape(-1, 3)
    axis = np.asarray(axis, np.float64).reshape(-1, 3)
    down = -axis
    az = down[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_plat = np.where(az < -1e-9, (platform_z - points[:, 2]) / az, np.inf)
    t_plat = np.where(t_plat >= 0, t_plat, np.inf)
    if below is None:
        t = np.where(np.isfinite(t_plat), t_plat, points[:, 2] - platform_z)
        return np.clip(t, 0.0, first_layer_max)
    t_ray = below.ray_distance(points, down, reach=2.0 * max_thickness)
    t = np.minimum(t_ray, t_plat)
    miss = ~np.isfinite(t_ray)
    if miss.any():
        t[miss] = np.minimum(below.distance(points[miss]), t_plat[miss])
    return np.clip(t, 0.0, max_thickness)
