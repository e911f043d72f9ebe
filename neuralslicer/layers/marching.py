"""Marching tetrahedra: isosurfaces of a piecewise-linear field on a tet mesh, batched over isovalues."""
from __future__ import annotations

import numpy as np

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
#: a marching-tetrahedra crossing this close to a cage vertex (edge parameter) is that vertex
MERGE_T = 1e-9


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
    return marching_batch(vertices, tets, values, np.array([iso]), lpd, edges, tet_edge)[0]


def marching_batch(
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
        # a crossing at a cage vertex (to rounding) is that vertex: merge, then drop the collapsed triangles
        t = np.where(t <= MERGE_T, 0.0, np.where(t >= 1 - MERGE_T, 1.0, t))
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


