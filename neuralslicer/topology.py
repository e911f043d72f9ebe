"""Topology of boundary surfaces: connected components, Euler characteristic, genus."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from neuralslicer.types import IndexArray


@dataclass
class SurfaceTopology:
    """Per connected component of a triangle surface: Euler characteristic, boundary loops, genus.

    euler : (c,) int64, ``V - E + F``
    boundary_loops : (c,) int64, number of boundary loops (0 for a closed component)
    genus : (c,) int64, ``(2 - euler - boundary_loops) / 2``
    """

    euler: IndexArray
    boundary_loops: IndexArray
    genus: IndexArray

    @property
    def total_genus(self) -> int:
        """Sum of the genera of the components (the number of handles of the whole surface)."""
        return int(self.genus.sum())

    @property
    def closed(self) -> bool:
        """True when no component has a boundary."""
        return bool((self.boundary_loops == 0).all())


def surface_topology(faces: IndexArray) -> SurfaceTopology:
    """Topology of a triangle surface ``faces (m, 3)`` (vertices not used by faces are ignored)."""
    from scipy.sparse import coo_matrix   # scipy.sparse only when a topology is computed (not on a cached rerun)
    from scipy.sparse.csgraph import connected_components

    faces = np.asarray(faces, dtype=np.int64)
    used, f = np.unique(faces, return_inverse=True)
    f = f.reshape(-1, 3)
    nv = len(used)
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    graph = coo_matrix((np.ones(len(uniq)), (uniq[:, 0], uniq[:, 1])), shape=(nv, nv))
    ncomp, label = connected_components(graph, directed=False)
    v_count = np.bincount(label, minlength=ncomp)
    e_count = np.bincount(label[uniq[:, 0]], minlength=ncomp)
    f_count = np.bincount(label[f[:, 0]], minlength=ncomp)
    euler = v_count - e_count + f_count
    # boundary loops: components of the graph of boundary edges (used by exactly one face)
    bnd = uniq[counts == 1]
    loops = np.zeros(ncomp, dtype=np.int64)
    if len(bnd):
        bverts, b = np.unique(bnd, return_inverse=True)
        b = b.reshape(-1, 2)
        g = coo_matrix((np.ones(len(b)), (b[:, 0], b[:, 1])), shape=(len(bverts),) * 2)
        nl, blabel = connected_components(g, directed=False)
        first_vertex = np.zeros(nl, dtype=np.int64)
        first_vertex[blabel] = bverts
        loops = np.bincount(label[first_vertex], minlength=ncomp).astype(np.int64)
    genus = (2 - euler - loops) // 2
    return SurfaceTopology(euler.astype(np.int64), loops, genus.astype(np.int64))


def genus(faces: IndexArray) -> int:
    """Total genus of a triangle surface (sum over its connected components)."""
    return surface_topology(faces).total_genus


def tet_boundary_genus(tets: IndexArray) -> int:
    """Genus of the boundary surface of a tetrahedral mesh ``tets (m, 4)``."""
    from neuralslicer.tetmesh import boundary_faces

    return genus(boundary_faces(np.asarray(tets, dtype=np.int64)))


def boundary_loop_lengths(vertices: np.ndarray, faces: IndexArray) -> np.ndarray:
    """Total edge length ``(loops,)`` of each connected set of boundary edges (edges of one face)."""
    from scipy.sparse import coo_matrix   # scipy.sparse only when a topology is computed (not on a cached rerun)
    from scipy.sparse.csgraph import connected_components

    faces = np.asarray(faces, dtype=np.int64)
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    bnd = uniq[counts == 1]
    if len(bnd) == 0:
        return np.zeros(0)
    bverts, b = np.unique(bnd, return_inverse=True)
    b = b.reshape(-1, 2)
    g = coo_matrix((np.ones(len(b)), (b[:, 0], b[:, 1])), shape=(len(bverts),) * 2)
    nl, label = connected_components(g, directed=False)
    length = np.linalg.norm(vertices[bnd[:, 0]] - vertices[bnd[:, 1]], axis=1)
    return np.bincount(label[b[:, 0]], weights=length, minlength=nl)
