"""The cage: a tetrahedral mesh of an offset of the solid, with a user-chosen element count."""
from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from neuralslicer.errors import NeuralSlicerError
from neuralslicer.model.grid import level_set_mesh
from neuralslicer.model.solid import Solid
from neuralslicer.tetmesh import TetLocator, boundary_faces, orient_tets, tet_volumes
from neuralslicer.topology import tet_boundary_genus

if TYPE_CHECKING:  # trimesh (and scipy.spatial, networkx) only where a mesh is made, pytetwild (and pyvista) only
    import trimesh  # where a cage is: neither on a cached rerun


# fTetWild's envelope (how far its boundary may move from the offset surface), as a fraction of the edge
ENVELOPE = 0.25


class CageConfig(BaseModel):
    """How the cage is built."""

    model_config = ConfigDict(extra="forbid")

    n_elements: int = Field(10_000, ge=200, le=2_000_000, description="target number of cage tets")
    offset: float | None = Field(None, gt=0, description="offset of the cage surface from the solid, mm (default: auto)")
    tolerance: float = Field(0.35, gt=0, description="accepted relative deviation from n_elements before one retry")
    seed: int = Field(0, description="seed of fTetWild's triangle order and of the containment check's random "
                      "interior points")


@dataclass
class Cage:
    """A tet mesh enclosing the solid: vertices (n,3), positively oriented tets (m,4)."""

    vertices: np.ndarray
    tets: np.ndarray
    offset: float
    edge_length: float
    seeded: bool = False  # fTetWild's draw came from the seed (the same inputs give the same cage anywhere)

    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict]:
        """Store-able arrays and attributes."""
        return {"vertices": self.vertices, "tets": self.tets}, {
            "offset": self.offset,
            "edge_length": self.edge_length,
            "n_elements": int(len(self.tets)),
            "n_vertices": int(len(self.vertices)),
            "seeded": self.seeded,
        }

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], attrs: dict) -> Cage:
        """Rebuild from store arrays."""
        return cls(arrays["vertices"], arrays["tets"].astype(np.int64), attrs["offset"], attrs["edge_length"],
                   bool(attrs.get("seeded", False)))

    def summary(self) -> dict[str, float | int | str]:
        """Genus of the cage boundary, the cage volume (mm^3) and the content digest, for the record."""
        return {"genus": tet_boundary_genus(self.tets), "volume_mm3": float(tet_volumes(self.vertices, self.tets).sum()),
                "sha256": self.sha256()}

    def sha256(self) -> str:
        """Digest of the cage's content (vertices as float64, tets as int64): equal digests, equal cages."""
        h = hashlib.sha256(np.ascontiguousarray(self.vertices, dtype=np.float64).tobytes())
        h.update(np.ascontiguousarray(self.tets, dtype=np.int64).tobytes())
        return h.hexdigest()

    def surface(self) -> trimesh.Trimesh:
        """The cage boundary as a triangle mesh."""
        import trimesh

        return trimesh.Trimesh(self.vertices, boundary_faces(self.tets), process=True)


def offset_surface(H: Callable[[np.ndarray], np.ndarray], bounds: np.ndarray, offset: float, h: float) -> trimesh.Trimesh:
    """The level set H = offset by marching cubes on a grid of spacing h."""
    import trimesh

    lo = bounds[0] - offset - 2 * h
    hi = bounds[1] + offset + 2 * h
    shape = np.ceil((hi - lo) / h).astype(int) + 1
    axes = [lo[i] + h * np.arange(shape[i]) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    values = H(grid).reshape(shape)
    verts, faces = level_set_mesh(values, lo, h, level=offset, allow_degenerate=True)
    return trimesh.Trimesh(verts, faces, process=True)


def _tetrahedralize(surface: trimesh.Trimesh, edge: float, seed: int) -> tuple[np.ndarray, np.ndarray, bool]:
    """fTetWild, seeded (neuralslicer/tetwild_seed.py), on the offset surface at an absolute ideal edge length, with
    an envelope of ENVELOPE * edge: (vertices, tets, whether the seed took)."""
    from neuralslicer import tetwild_seed

    diag = float(np.linalg.norm(surface.bounds[1] - surface.bounds[0]))
    v, t, seeded = tetwild_seed.tetrahedralize(
        np.asarray(surface.vertices, dtype=np.float64),
        np.asarray(surface.faces, dtype=np.int32),
        seed,
        edge_length_abs=float(edge),
        epsilon=float(ENVELOPE * edge / diag),
        quiet=True,
        num_threads=1,   # on its OpenMP threads fTetWild gave another mesh for the same draw 2 calls in 40
    )
    t = t.astype(np.int64)
    t = orient_tets(v, t)
    keep = np.abs(tet_volumes(v, t)) > 0
    t = t[keep]
    used = np.unique(t)
    remap = np.full(len(v), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return v[used], remap[t], seeded


def check_containment(cage: Cage, points: np.ndarray) -> np.ndarray:
    """Indices of the points that no cage tet contains (empty when the cage encloses them all)."""
    tet, _ = TetLocator(cage.vertices, cage.tets).locate(points, tol=1e-7)
    return np.flatnonzero(tet < 0)


def build_cage(
    H: Callable[[np.ndarray], np.ndarray],
    bounds: np.ndarray,
    volume: float,
    config: CageConfig,
    check_points: np.ndarray,
) -> Cage:
    """Offset surface of the solid, tetrahedralized at the target element count, verified to contain `check_points`."""
    bounds = np.asarray(bounds, dtype=np.float64)
    diag = float(np.linalg.norm(bounds[1] - bounds[0]))
    # ideal edge of a regular tet from the target count over a first guess of the cage volume (twice the solid's)
    edge = (6 * np.sqrt(2) * 2 * volume / config.n_elements) ** (1 / 3)
    h = min(edge / 2, diag / 40)
    offset = config.offset if config.offset is not None else max(1.5 * h, 0.01 * diag) + ENVELOPE * edge
    for _attempt in range(4):
        surface = offset_surface(H, bounds, offset, h)
        edge = (6 * np.sqrt(2) * abs(surface.volume) / config.n_elements) ** (1 / 3)
        v, t, seeded = _tetrahedralize(surface, edge, config.seed)
        ratio = len(t) / config.n_elements
        if abs(ratio - 1) > config.tolerance:
            edge *= ratio ** (1 / 3)
            v, t, seeded = _tetrahedralize(surface, edge, config.seed)
        cage = Cage(v, t, float(offset), float(edge), seeded)
        missing = check_containment(cage, check_points)
        if len(missing) == 0:
            return cage
        offset += h
    raise NeuralSlicerError(f"cage: {len(missing)} points of the solid remain outside the cage after 4 offsets")


def make_cage(solid: Solid, surface_points: np.ndarray, config: CageConfig) -> Cage:
    """The cage step: a cage around the solid at the target element count, verified to contain the
    surface samples and random interior points (seeded by ``config.seed``)."""
    check = np.concatenate([surface_points, interior_points(solid.H, solid.bounds, 20_000, config.seed)])
    return build_cage(solid.H, solid.bounds, solid.volume(), config, check)


def interior_points(H: Callable[[np.ndarray], np.ndarray], bounds: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """Up to n random points with H < 0 (rejection sampling in the bounding box)."""
    rng = np.random.default_rng(seed)
    found = []
    total = 0
    for _ in range(20):
        p = rng.uniform(bounds[0], bounds[1], size=(4 * n, 3))
        p = p[H(p) < 0]
        found.append(p)
        total += len(p)
        if total >= n:
            break
    return np.concatenate(found)[:n]
