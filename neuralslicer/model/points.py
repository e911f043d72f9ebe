"""Point clouds to closed surfaces: normals, winding number, marching cubes, MLS projection.

The method (``P : (n, 3)`` points in the build frame, mm):

1. **Normals**, when the file has none (or ``normals: estimate``): PCA over the ``k`` nearest
   neighbours (the eigenvector of the smallest eigenvalue of the local covariance), oriented
   consistently by propagation along a minimum spanning tree of the symmetric kNN graph with edge
   weights ``1 - |n_i · n_j|`` (Hoppe et al. 1992), seeded at each connected part's highest point
   with its normal turned up.
2. **Global sign**: each connected part is flipped as a whole so that it encloses positive volume
   (``Σ a_i (p_i - c) · n_i > 0``), or negative volume when it lies inside a larger part (a
   cavity: winding number > 1/2 of the larger parts at its points). Given normals get this check too.
3. **Areas** ``a_i = π r_i² / 8`` with ``r_i`` the distance to the 8th neighbour: the area each
   point stands for.
4. **Inside / outside** from the generalized winding number of the oriented points (Barill et al.
   2018), ``w(x) = Σ a_i (p_i - x) · n_i / (4π |p_i - x|³)`` (libigl's Barnes-Hut evaluation): 1
   inside, 0 outside, and it bridges holes in the sampling. It is scaled so that its median on the
   surface (the mean of ``w`` just in front of and behind the points) is 1/2, its value on a closed
   surface; a median below ``MIN_POINT_WINDING`` means the points enclose no volume (a flat patch,
   an open sheet).
5. **Near the points**, where the point sum is spiky, the implicit function is the moving
   least-squares distance of Kolluri (2008), ``f(x) = Σ φ_j n_j · (x - p_j) / Σ φ_j`` with
   Gaussian weights ``φ_j`` of the local spacing over the ``k`` nearest points.
6. **Grid** of ``resolution`` cells along the longest side: ``f`` in a band around the points,
   ``1/2 - w`` elsewhere (once per connected region of the grid when its samples agree, node by
   node where a hole is bridged); marching cubes of the zero level, then each vertex is projected
   onto ``f = 0`` along the weighted mean normal.
"""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree
from scipy.spatial import cKDTree

from neuralslicer.errors import InputError
from neuralslicer.model.grid import level_set_mesh
from neuralslicer.types import FloatArray, IndexArray

#: Fewest points accepted: fewer cannot describe a closed surface.
MIN_POINTS = 100
#: Default neighbour count for normal estimation.
DEFAULT_K = 16
#: Default grid cells along the longest side of the cloud's bounding box.
DEFAULT_RESOLUTION = 96
#: The median winding number at the points must reach this (1/2 on a closed surface).
MIN_POINT_WINDING = 0.3
#: Neighbour rank whose distance gives a point's area.
_AREA_RANK = 8
#: Neighbours of the moving least-squares distance.
_MLS_NEIGHBOURS = 16
#: Gaussian width of the moving least-squares weights, in local point spacings.
_MLS_WIDTH = 0.8
#: Queries per batch of the neighbour searches.
_BATCH = 65_536


def check_cloud(where: str | Path, points: FloatArray, normals: FloatArray | None = None
                ) -> tuple[FloatArray, FloatArray | None]:
    """Validated ``points (n, 3)`` and unit ``normals (n, 3)`` (or None); InputError names ``where``."""
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) < MIN_POINTS:
        raise InputError(where, f"only {len(points)} points; a point cloud needs at least {MIN_POINTS}")
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise InputError(where, f"{int(bad.sum())} points have NaN or infinite coordinates "
                                f"(first: point {int(np.flatnonzero(bad)[0]) + 1})")
    if np.ptp(points, axis=0).max() <= 0:
        raise InputError(where, "all points coincide")
    if normals is None:
        return points, None
    normals = np.ascontiguousarray(normals, dtype=np.float64).reshape(-1, 3)
    length = np.linalg.norm(normals, axis=1)
    bad = ~(np.isfinite(length) & (length > 1e-12))
    if bad.any():
        raise InputError(where, f"{int(bad.sum())} normals have zero length or are not finite "
                                f"(first: point {int(np.flatnonzero(bad)[0]) + 1}); fix them or use "
                                f"'normals: estimate'")
    return points, normals / length[:, None]


class OrientedPoints:
    """Points ``(n, 3)`` with unit outward normals ``(n, 3)`` and the area ``(n,)`` each stands for.

    The operations on the cloud live here: the winding number, the moving least-squares distance
    and the projection onto it.
    """

    def __init__(self, points: FloatArray, normals: FloatArray, areas: FloatArray | None = None) -> None:
        """Keep the arrays; areas default to :func:`point_areas`."""
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        self.normals = np.ascontiguousarray(normals, dtype=np.float64)
        self.tree = cKDTree(self.points)
        self.areas = (point_areas(self.points, self.tree) if areas is None
                      else np.asarray(areas, dtype=np.float64))
        self.spacing = np.sqrt(self.areas)

    def winding_number(self, x: FloatArray, order: int = 1) -> FloatArray:
        """Generalized winding number ``(m,)`` at ``x (m, 3)`` (libigl, Barnes-Hut of Taylor ``order``)."""
        import igl

        x = np.ascontiguousarray(x, dtype=np.float64).reshape(-1, 3)
        if len(x) == 0:
            return np.empty(0)
        return np.asarray(igl.fast_winding_number(self.points, self.normals, self.areas, x, order, 2.0))

    def winding_at_points(self, count: int = 1024, seed: int = 0) -> FloatArray:
        """Winding number ``(count,)`` on the surface at random points: the mean just in front and behind.

        The mean of ``w(p ± s n / 2)`` (s the spacing) is 1/2 at a point of a closed surface, between 0
        and 1/2 on an open sheet, 0 on a flat patch; the neighbours' near terms cancel in it.
        """
        pick = np.random.default_rng(seed).choice(len(self.points), size=min(len(self.points), count),
                                                  replace=False)
        step = 0.5 * self.spacing[pick, None] * self.normals[pick]
        p = self.points[pick]
        w = self.winding_number(np.concatenate([p + step, p - step]), order=2)
        return 0.5 * (w[:len(pick)] + w[len(pick):])

    def mls(self, x: FloatArray, k: int = _MLS_NEIGHBOURS) -> tuple[FloatArray, FloatArray]:
        """Moving least-squares distance ``f (m,)`` and weighted mean unit normal ``(m, 3)`` at ``x``.

        ``f(x) = Σ φ_j n_j · (x - p_j) / Σ φ_j``, ``φ_j = exp(-|x - p_j|² / σ²)`` over the
        nearest ``k`` points, σ the mean spacing of those points. The normal is zero where they disagree.
        """
        x = np.ascontiguousarray(x, dtype=np.float64).reshape(-1, 3)
        f, normal = np.empty(len(x)), np.empty((len(x), 3))
        k = min(k, len(self.points))
        for i in range(0, len(x), _BATCH):
            q = x[i:i + _BATCH]
            dist, idx = self.tree.query(q, k=k)
            sigma = _MLS_WIDTH * self.spacing[idx].mean(axis=1, keepdims=True)
            weight = np.exp(-(dist ** 2 - dist[:, :1] ** 2) / sigma ** 2)  # relative to the nearest
            n = self.normals[idx]
            offset = np.einsum("mkj,mkj->mk", q[:, None, :] - self.points[idx], n)
            f[i:i + _BATCH] = (weight * offset).sum(axis=1) / weight.sum(axis=1)
            mean = np.einsum("mk,mkj->mj", weight, n) / weight.sum(axis=1, keepdims=True)
            length = np.linalg.norm(mean, axis=1, keepdims=True)
            normal[i:i + _BATCH] = np.where(length > 0.5, mean / np.maximum(length, 1e-300), 0.0)
        return f, normal

    def project(self, x: FloatArray, max_step: float, steps: int = 3) -> FloatArray:
        """Points ``(m, 3)`` moved onto ``f = 0`` along the mean normal, each step at most ``max_step``."""
        x = np.array(x, dtype=np.float64, copy=True).reshape(-1, 3)
        for _ in range(steps):
            f, normal = self.mls(x)
            x -= np.clip(f, -max_step, max_step)[:, None] * normal
        return x


def point_areas(points: FloatArray, tree: cKDTree | None = None, rank: int = _AREA_RANK) -> FloatArray:
    """Area each point stands for ``(n,)``: ``π r² / rank``, r the distance to its rank-th neighbour."""
    tree = cKDTree(points) if tree is None else tree
    dist, _ = tree.query(points, k=min(rank + 1, len(points)))
    r = dist[:, -1]
    positive = r[r > 0]
    r = np.where(r > 0, r, np.median(positive) if len(positive) else 1.0)
    return np.pi * r ** 2 / rank


# ------------------------------------------------------------------------------------ normals

def estimate_normals(points: FloatArray, k: int = DEFAULT_K) -> FloatArray:
    """Unoriented unit normals ``(n, 3)``: smallest principal axis of each point's k neighbours."""
    _, idx = cKDTree(points).query(points, k=min(k, len(points)))
    local = points[idx] - points[idx].mean(axis=1, keepdims=True)
    _, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", local, local))
    return np.ascontiguousarray(vectors[:, :, 0])


def knn_graph(points: FloatArray, normals: FloatArray, k: int = DEFAULT_K) -> csr_matrix:
    """Symmetric kNN graph ``(n, n)``, weights ``1 - |n_i · n_j|`` (+1e-6: csgraph drops zeros)."""
    n = len(points)
    _, idx = cKDTree(points).query(points, k=min(k + 1, n))
    rows = np.repeat(np.arange(n), idx.shape[1] - 1)
    cols = idx[:, 1:].ravel()
    weight = 1.0 - np.abs(np.einsum("ij,ij->i", normals[rows], normals[cols])) + 1e-6
    graph = coo_matrix((weight, (rows, cols)), shape=(n, n)).tocsr()
    return graph.maximum(graph.T)


def propagate_orientation(points: FloatArray, normals: FloatArray, graph: csr_matrix) -> FloatArray:
    """Normals ``(n, 3)`` flipped to agree along a minimum spanning tree of ``graph``, per connected part."""
    normals = normals.copy()
    count, labels = connected_components(graph, directed=False)
    tree = minimum_spanning_tree(graph)
    flip = [False] * len(points)
    for part in range(count):
        members = np.flatnonzero(labels == part)
        root = int(members[np.argmax(points[members, 2])])  # the highest point's normal points up
        flip[root] = bool(normals[root, 2] < 0)
        order, parent = breadth_first_order(tree, root, directed=False, return_predecessors=True)
        child, par = order[1:], parent[order[1:]]
        disagree = np.einsum("ij,ij->i", normals[child], normals[par]) < 0
        for c, p, d in zip(child.tolist(), par.tolist(), disagree.tolist()):  # parents come first
            flip[c] = flip[p] ^ d
    normals[np.asarray(flip)] *= -1.0
    return normals


def orient_parts(points: FloatArray, normals: FloatArray, areas: FloatArray, labels: IndexArray,
                 max_nested: int = 16) -> FloatArray:
    """Flip whole parts (``labels (n,)``) to enclose positive volume, negative for a cavity.

    Parts are taken largest (bounding box) first; a part whose points have winding number > 1/2
    with respect to the larger parts lies inside material and is a cavity. Only the ``max_nested``
    largest parts are tested for nesting; smaller ones are turned outward.
    """
    normals = normals.copy()
    parts = [np.flatnonzero(labels == p) for p in np.unique(labels)]
    parts.sort(key=lambda m: float(np.prod(np.ptp(points[m], axis=0))), reverse=True)
    done = np.zeros(len(points), dtype=bool)
    for rank, members in enumerate(parts):
        p = points[members]
        volume = float(np.sum(areas[members] * np.einsum("ij,ij->i", p - p.mean(0), normals[members])))
        cavity = False
        if 0 < rank < max_nested and done.sum() >= MIN_POINTS:
            outer = OrientedPoints(points[done], normals[done], areas[done])
            cavity = float(np.median(outer.winding_number(p))) > 0.5
        if (volume < 0) != cavity:
            normals[members] *= -1.0
        done[members] = True
    return normals


def oriented_points(points: FloatArray, normals: FloatArray | None = None,
                    k: int = DEFAULT_K) -> OrientedPoints:
    """The cloud with consistent outward normals: estimated and propagated when ``normals`` is None."""
    areas = point_areas(points)
    if normals is None:
        normals = estimate_normals(points, k)
        graph = knn_graph(points, normals, k)
        normals = propagate_orientation(points, normals, graph)
    else:
        graph = knn_graph(points, normals, k)
    labels = connected_components(graph, directed=False)[1]
    return OrientedPoints(points, orient_parts(points, normals, areas, labels), areas)


# ------------------------------------------------------------------------------------ reconstruction

def near_band(cloud: OrientedPoints, origin: FloatArray, voxel: float, shape: tuple[int, int, int]
              ) -> tuple[np.ndarray, float]:
    """Grid nodes ``(nx, ny, nz) bool`` near the points, and the largest band width.

    A node is near when within ``2 voxel + min(1.5 spacing, 4 voxel)`` of the nearest node holding a
    point (a Euclidean distance transform), the spacing being that point's.
    """
    owner = np.full(shape, -1, dtype=np.int64)
    cell = np.clip(np.rint((cloud.points - origin) / voxel).astype(np.int64), 0, np.asarray(shape) - 1)
    owner[cell[:, 0], cell[:, 1], cell[:, 2]] = np.arange(len(cell))
    distance, nearest = ndimage.distance_transform_edt(owner < 0, return_indices=True)
    width = 2.0 * voxel + np.minimum(1.5 * cloud.spacing, 4.0 * voxel)
    near = distance * voxel <= width[owner[tuple(nearest)]]
    return near, float(width.max())


def implicit_grid(cloud: OrientedPoints, inside: Callable[[FloatArray], FloatArray], origin: FloatArray,
                  voxel: float, shape: tuple[int, int, int], coarse: int = 4) -> np.ndarray:
    """The implicit function ``(nx, ny, nz)`` (< 0 inside) on the grid ``origin + voxel (i, j, k)``.

    In the :func:`near_band` of the points: the moving least-squares distance ``f``. Elsewhere
    ``(1/2 - w) · width`` with ``w = inside(x)``, evaluated on the lattice of every ``coarse``-th
    node first: the grid outside the band falls into connected regions, and a region whose lattice
    samples all lie on one side of 1/2 is filled with their mean. In a region with samples on both
    sides (a hole bridged away from the points) or none, a node is evaluated when the lattice
    corners around it come within 0.1 of 1/2 or are missing, and takes their mean otherwise
    (``w`` is harmonic away from the points).
    """
    def node(flat: IndexArray) -> FloatArray:
        """Positions ``(m, 3)`` of flat node indices."""
        return origin + voxel * np.stack(np.unravel_index(flat, shape), axis=-1)

    near, width = near_band(cloud, origin, voxel, shape)
    near = near.reshape(-1)
    values = np.empty(near.shape, dtype=np.float64)
    values[near] = cloud.mls(node(np.flatnonzero(near)), k=8)[0]
    labels, count = ndimage.label(~near.reshape(shape))
    labels = labels.reshape(-1)
    if count == 0:
        return values.reshape(shape)
    lattice = np.zeros(shape, dtype=bool)
    lattice[::coarse, ::coarse, ::coarse] = True
    sample = np.flatnonzero(lattice.reshape(-1) & (labels > 0))
    w = inside(node(sample))
    per = np.bincount(labels[sample], minlength=count + 1)
    above = np.bincount(labels[sample], weights=w > 0.5, minlength=count + 1)
    mean = np.bincount(labels[sample], weights=w, minlength=count + 1) / np.maximum(per, 1)
    mixed = (per == 0) | ((above > 0) & (above < per))
    mixed[0] = False
    far = np.flatnonzero(labels > 0)
    values[far] = (0.5 - mean[labels[far]]) * width
    todo = np.flatnonzero(mixed[labels])
    if len(todo):
        coarse_shape = tuple((n - 1) // coarse + 1 for n in shape)
        on_lattice = np.full(coarse_shape, np.nan)
        on_lattice[tuple(np.stack(np.unravel_index(sample, shape)) // coarse)] = w
        safe, guess = _lattice_cells(on_lattice)
        cells = np.ravel_multi_index(tuple(np.stack(np.unravel_index(todo, shape)) // coarse), coarse_shape)
        estimate = guess[cells]
        unsafe = ~safe[cells]
        estimate[unsafe] = inside(node(todo[unsafe]))
        values[todo] = (0.5 - estimate) * width
    return values.reshape(shape)


def _lattice_cells(on_lattice: np.ndarray, margin: float = 0.1) -> tuple[np.ndarray, FloatArray]:
    """Per lattice cell (flat): whether its known corners (>= 2) all lie ``margin`` off 1/2; their mean."""
    shape = on_lattice.shape
    padded = np.pad(on_lattice, 1, constant_values=np.nan)[1:, 1:, 1:]
    corners = np.stack([padded[i:i + shape[0], j:j + shape[1], k:k + shape[2]]
                        for i in (0, 1) for j in (0, 1) for k in (0, 1)], axis=-1).reshape(-1, 8)
    finite = np.isfinite(corners)
    known = finite.sum(axis=1)
    lo = np.where(finite, corners, np.inf).min(axis=1)
    hi = np.where(finite, corners, -np.inf).max(axis=1)
    mean = np.where(finite, corners, 0.0).sum(axis=1) / np.maximum(known, 1)
    return (known >= 2) & ((lo > 0.5 + margin) | (hi < 0.5 - margin)), mean


def reconstruct(points: FloatArray, normals: FloatArray | None = None, k: int = DEFAULT_K,
                resolution: int = DEFAULT_RESOLUTION, where: str | Path = "points"
                ) -> tuple[FloatArray, IndexArray]:
    """Closed surface of a point cloud: ``vertices (m, 3) float64``, ``faces (f, 3) int64``, outward.

    Parameters
    ----------
    points : (n, 3) float64, at least ``MIN_POINTS``.
    normals : (n, 3) float64 outward normals, or None to estimate and orient them (see the module).
    k : neighbours for normal estimation.
    resolution : grid cells along the longest side of the cloud's bounding box.
    where : the file named by the InputError raised for a bad cloud.
    """
    points, normals = check_cloud(where, points, normals)
    cloud = oriented_points(points, normals, k)
    at_points = float(np.median(cloud.winding_at_points()))
    if at_points < MIN_POINT_WINDING:
        raise InputError(where, f"the points enclose no volume: the winding number at the points is "
                                f"{at_points:.2f} (1/2 on a closed surface, 0 on a flat patch); an open "
                                f"sheet or a flat patch cannot be printed as a solid")
    factor = min(1.5, 0.5 / at_points)  # calibrates the areas: 1/2 at the points

    def inside(x: FloatArray) -> FloatArray:
        """Calibrated winding number."""
        return factor * cloud.winding_number(x, order=2)

    lo, hi = points.min(0), points.max(0)
    voxel = float((hi - lo).max()) / resolution
    pad = 6.0 * voxel + min(2.0 * float(np.percentile(cloud.spacing, 95)), 6.0 * voxel)
    origin = lo - pad - 0.1234567 * voxel  # an odd offset keeps nodes off round coordinates
    shape = tuple(int(s) for s in np.ceil((hi + pad - origin) / voxel).astype(int) + 1)
    values = implicit_grid(cloud, inside, origin, voxel, shape)
    if values.min() >= 0:
        raise InputError(where, "the points enclose no volume: the winding number never exceeds 1/2 "
                                "(a flat patch or an open sheet cannot be printed as a solid)")
    for axis in range(3):  # the border is outside, so the surface is closed
        for end in (0, -1):
            edge = [slice(None)] * 3
            edge[axis] = end
            values[tuple(edge)] = np.maximum(values[tuple(edge)], voxel)
    vertices, faces = drop_specks(*level_set_mesh(values, origin, voxel), min_volume=8.0 * voxel ** 3)
    if len(faces) == 0:
        raise InputError(where, "the points enclose no volume: nothing larger than a few grid cells is "
                                "inside their winding number")
    near = cloud.tree.query(vertices, distance_upper_bound=4.0 * voxel)[0] < np.inf
    vertices[near] = cloud.project(vertices[near], max_step=voxel)
    return vertices, faces


def drop_specks(vertices: FloatArray, faces: IndexArray, min_volume: float) -> tuple[FloatArray, IndexArray]:
    """The mesh without connected pieces enclosing less than ``min_volume`` (unused vertices removed)."""
    n = len(vertices)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    count, labels = connected_components(graph, directed=False)
    tri = vertices[faces]
    piece = labels[faces[:, 0]]
    signed = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])) / 6.0
    volume = np.bincount(piece, weights=signed, minlength=count)
    faces = faces[np.abs(volume[piece]) >= min_volume]
    used = np.unique(faces)
    remap = np.full(n, -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return vertices[used], remap[faces]
