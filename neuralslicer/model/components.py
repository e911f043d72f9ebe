"""Implicit components: each gives ``H(x)`` (< 0 inside) and ``∇H(x)`` for ``(n, 3)`` point batches.

All data is held in the build frame (already rotated by ``up`` and scaled to mm).  Every component
can be written to plain arrays + JSON attributes (:meth:`Component.to_arrays`) and rebuilt from them
(:func:`component_from_arrays`), which is how a model travels between pipeline processes.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from functools import cached_property
from typing import Any, ClassVar

import numpy as np

from neuralslicer.model import convolution
from neuralslicer.types import FloatArray, IndexArray

#: Relative distance (of the bounding-box diagonal) under which a point counts as on the surface,
#: where the gradient falls back from ``(x - closest) / d`` to the closest face's normal.
_ON_SURFACE = 1e-12


def _points(x: FloatArray) -> FloatArray:
    """C-contiguous float64 (n, 3) copy-free view of the query points."""
    x = np.ascontiguousarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"points must have shape (n, 3), got {x.shape}")
    return x


def face_normals(vertices: FloatArray, faces: IndexArray) -> FloatArray:
    """Unit normals ``(m, 3)`` of triangles (right-hand rule); degenerate faces give zeros."""
    tri = vertices[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)


def enclosed_volume(vertices: FloatArray, faces: IndexArray) -> float:
    """Signed volume enclosed by a triangle surface (divergence theorem; > 0 when normals point out)."""
    tri = vertices[faces]
    return float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0)


def surface_area(vertices: FloatArray, faces: IndexArray) -> float:
    """Total area of a triangle surface."""
    tri = vertices[faces]
    return float(0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum())


class Component(ABC):
    """One implicit part of a model (H < 0 inside); subclasses hold their data in the build frame."""

    kind: ClassVar[str]

    @abstractmethod
    def value_and_grad(self, x: FloatArray) -> tuple[FloatArray, FloatArray]:
        """``H (n,)`` and ``∇H (n, 3)`` at ``x (n, 3)``."""

    def value(self, x: FloatArray) -> FloatArray:
        """``H (n,)`` at ``x (n, 3)``."""
        return self.value_and_grad(x)[0]

    @property
    @abstractmethod
    def box(self) -> FloatArray:
        """``(2, 3)`` box that contains every point with H <= 0 (tight where :attr:`exact_box`)."""

    exact_box: ClassVar[bool] = True

    @property
    @abstractmethod
    def feature_size(self) -> float:
        """Smallest meaningful feature of this component, mm."""

    @property
    @abstractmethod
    def min_z(self) -> float:
        """Lowest z of the component's solid (exact, or from the box when not known exactly)."""

    @abstractmethod
    def arrays(self) -> dict[str, np.ndarray]:
        """The component's data as plain arrays (build frame)."""

    @abstractmethod
    def attrs(self) -> dict:
        """JSON-able parameters, with ``type``."""

    @classmethod
    @abstractmethod
    def from_data(cls, arrays: dict[str, np.ndarray], attrs: dict) -> "Component":
        """Rebuild from :meth:`arrays` and :meth:`attrs`."""


class _TriangleDistance:
    """Unsigned distance to a triangle set with an AABB tree (libigl), closest points and faces."""

    def __init__(self, vertices: FloatArray, faces: IndexArray) -> None:
        """The AABB tree is built once, at the first query (a solid only checked, as a cached rerun's, needs none);
        queries are O(log m) each."""
        self.vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        self.normals = face_normals(self.vertices, self.faces)
        self.scale = float(np.linalg.norm(np.ptp(self.vertices, axis=0)))

    @cached_property
    def tree(self) -> Any:
        """libigl's AABB tree of the triangles."""
        import igl

        tree = igl.AABB()
        tree.init(self.vertices, self.faces)
        return tree

    def query(self, x: FloatArray) -> tuple[FloatArray, FloatArray, IndexArray]:
        """Distance ``(n,)``, unit direction from the closest point to x ``(n, 3)``, closest face ``(n,)``."""
        sq, face, closest = self.tree.squared_distance(self.vertices, self.faces, x)
        d = np.sqrt(np.maximum(sq, 0.0))
        diff = x - closest
        on = d <= _ON_SURFACE * self.scale
        direction = np.where(on[:, None], self.normals[face],
                             diff / np.where(on, 1.0, d)[:, None])
        return d, direction, face


class MeshComponent(Component):
    """Closed triangle surface: signed distance, sign from the fast generalized winding number.

    ``H = ±dist(x, S)``, negative where the winding number exceeds 1/2, so small holes and
    self-intersections are tolerated; ``∇H = sign · (x - closest) / d`` (the face normal on S).
    """

    kind = "mesh"

    def __init__(self, vertices: FloatArray, faces: IndexArray, source_kind: str = "mesh",
                 tets: IndexArray | None = None) -> None:
        """Surface ``vertices (n, 3)``, ``faces (m, 3)`` in the build frame, oriented outward."""
        vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        faces = np.ascontiguousarray(faces, dtype=np.int64)
        if enclosed_volume(vertices, faces) < 0:
            faces = np.ascontiguousarray(faces[:, ::-1])
        self.vertices, self.faces = vertices, faces
        self.source_kind = source_kind  # "mesh", "tet" or "points" (reconstructed from a point cloud)
        self.tets = None if tets is None else np.asarray(tets, dtype=np.int64)
        self._dist = _TriangleDistance(vertices, faces)

    def winding_number(self, x: FloatArray) -> FloatArray:
        """Generalized winding number ``(n,)`` (fast, Barill et al. 2018) at ``x (n, 3)``."""
        if getattr(self, "_winding_bvh", None) is None:  # built once, reused by every query
            import igl

            self._winding_bvh = igl.FastWindingNumberBVH()
            self._winding_bvh.init(self.vertices, self.faces)
        return np.asarray(self._winding_bvh.winding_number(_points(x)))

    def value(self, x: FloatArray) -> FloatArray:
        """Signed distance ``(n,)``."""
        x = _points(x)
        sq, _, _ = self._dist.tree.squared_distance(self._dist.vertices, self._dist.faces, x)
        d = np.sqrt(np.maximum(sq, 0.0))
        return np.where(self.winding_number(x) > 0.5, -d, d)

    def value_and_grad(self, x: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Signed distance ``(n,)`` and its gradient ``(n, 3)``."""
        x = _points(x)
        d, direction, _ = self._dist.query(x)
        sign = np.where(self.winding_number(x) > 0.5, -1.0, 1.0)
        on = d <= _ON_SURFACE * self._dist.scale
        # on S the direction is the outward face normal already: no sign flip there
        grad = np.where(on[:, None], direction, sign[:, None] * direction)
        return sign * d, grad

    @property
    def box(self) -> FloatArray:
        """Vertex bounding box ``(2, 3)``."""
        return np.stack([self.vertices.min(0), self.vertices.max(0)])

    @property
    def min_z(self) -> float:
        """Lowest vertex z."""
        return float(self.vertices[:, 2].min())

    @property
    def volume(self) -> float:
        """Enclosed volume (mm³)."""
        return abs(enclosed_volume(self.vertices, self.faces))

    @property
    def feature_size(self) -> float:
        """Mean thickness ``2 V / A`` (= t for a plate, r for a long cylinder, 2r/3 for a ball)."""
        return 2.0 * self.volume / surface_area(self.vertices, self.faces)

    def arrays(self) -> dict[str, np.ndarray]:
        """``vertices``, ``faces`` (and ``tets`` for a tet component)."""
        out = {"vertices": self.vertices, "faces": self.faces}
        if self.tets is not None:
            out["tets"] = self.tets
        return out

    def attrs(self) -> dict:
        """``{"type": "mesh" | "tet" | "points"}``."""
        return {"type": self.source_kind}

    @classmethod
    def from_data(cls, arrays: dict[str, np.ndarray], attrs: dict) -> "MeshComponent":
        """Rebuild from :meth:`arrays` / :meth:`attrs`."""
        return cls(np.asarray(arrays["vertices"]), np.asarray(arrays["faces"]),
                   source_kind=attrs.get("type", "mesh"), tets=arrays.get("tets"))


class ShellComponent(Component):
    """Shell of thickness t around a (usually open) surface S: ``H = dist(x, S) - t/2``."""

    kind = "shell"

    def __init__(self, vertices: FloatArray, faces: IndexArray, thickness: float) -> None:
        """Mid surface ``vertices (n, 3)``, ``faces (m, 3)`` (build frame) and thickness t > 0."""
        self.vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        self.thickness = float(thickness)
        self._dist = _TriangleDistance(self.vertices, self.faces)

    def value_and_grad(self, x: FloatArray) -> tuple[FloatArray, FloatArray]:
        """``dist - t/2`` and ``(x - closest)/dist``."""
        d, direction, _ = self._dist.query(_points(x))
        return d - 0.5 * self.thickness, direction

    @property
    def box(self) -> FloatArray:
        """Mid-surface box grown by t/2."""
        half = 0.5 * self.thickness
        return np.stack([self.vertices.min(0) - half, self.vertices.max(0) + half])

    @property
    def min_z(self) -> float:
        """Lowest vertex z minus t/2 (exact: the lowest point of an offset is below a vertex)."""
        return float(self.vertices[:, 2].min() - 0.5 * self.thickness)

    @property
    def feature_size(self) -> float:
        """The thickness t."""
        return self.thickness

    def arrays(self) -> dict[str, np.ndarray]:
        """``vertices``, ``faces`` of the mid surface."""
        return {"vertices": self.vertices, "faces": self.faces}

    def attrs(self) -> dict:
        """``type`` and ``thickness``."""
        return {"type": "shell", "thickness": self.thickness}

    @classmethod
    def from_data(cls, arrays: dict[str, np.ndarray], attrs: dict) -> "ShellComponent":
        """Rebuild from :meth:`arrays` / :meth:`attrs`."""
        return cls(np.asarray(arrays["vertices"]), np.asarray(arrays["faces"]), attrs["thickness"])


class StrutsComponent(Component):
    """Union of capsules of radius r around segments: ``H = dist(x, segments) - r`` (AABB tree)."""

    kind = "struts"

    def __init__(self, segments: FloatArray, radius: float) -> None:
        """``segments (k, 2, 3)`` in the build frame and radius r > 0."""
        import igl

        self.segments = np.ascontiguousarray(segments, dtype=np.float64)
        self.radius = float(radius)
        self._v = np.ascontiguousarray(self.segments.reshape(-1, 3))
        self._e = np.arange(len(self._v), dtype=np.int64).reshape(-1, 2)
        self._tree = igl.AABB()
        self._tree.init(self._v, self._e)
        axis = self.segments[:, 1] - self.segments[:, 0]
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        # a unit vector perpendicular to each segment, used as gradient on the axis itself
        helper = np.where(np.abs(axis[:, [0]]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        perp = np.cross(axis, helper)
        self._perp = perp / np.linalg.norm(perp, axis=1, keepdims=True)
        self._scale = float(np.linalg.norm(np.ptp(self._v, axis=0))) + self.radius

    def value_and_grad(self, x: FloatArray) -> tuple[FloatArray, FloatArray]:
        """``dist - r`` and ``(x - closest)/dist``."""
        x = _points(x)
        sq, seg, closest = self._tree.squared_distance(self._v, self._e, x)
        d = np.sqrt(np.maximum(sq, 0.0))
        on = d <= _ON_SURFACE * self._scale
        grad = np.where(on[:, None], self._perp[seg], (x - closest) / np.where(on, 1.0, d)[:, None])
        return d - self.radius, grad

    @property
    def box(self) -> FloatArray:
        """Segment box grown by r (exact)."""
        return np.stack([self._v.min(0) - self.radius, self._v.max(0) + self.radius])

    @property
    def min_z(self) -> float:
        """Lowest end point z minus r (exact)."""
        return float(self._v[:, 2].min() - self.radius)

    @property
    def feature_size(self) -> float:
        """The strut diameter 2r."""
        return 2.0 * self.radius

    def arrays(self) -> dict[str, np.ndarray]:
        """``segments (k, 2, 3)``."""
        return {"segments": self.segments}

    def attrs(self) -> dict:
        """``type`` and ``radius``."""
        return {"type": "struts", "radius": self.radius}

    @classmethod
    def from_data(cls, arrays: dict[str, np.ndarray], attrs: dict) -> "StrutsComponent":
        """Rebuild from :meth:`arrays` / :meth:`attrs`."""
        return cls(np.asarray(arrays["segments"]), attrs["radius"])


class TubesComponent(Component):
    """Convolution surface of skeleton segments (Cauchy kernel), normalised to a distance-like H.

    ``F(x) = Σ ∫ k(|x - s|) ds`` in closed form (:mod:`neuralslicer.model.convolution`), iso threshold
    ``T = F_line(radius)``; ``H = D(F) - radius`` where ``D`` inverts the field of an infinite line,
    so H is the exact signed distance for a long straight tube and distance-like near any surface.
    With ``wall`` set, the tube is hollow: ``H_w = max(H, -H - wall)``.
    """

    kind = "tubes"
    exact_box = False

    def __init__(self, segments: FloatArray, radius: float, c: float | None = None,
                 wall: float | None = None) -> None:
        """Skeleton ``segments (k, 2, 3)`` (build frame), tube radius, kernel c (default 1/radius), wall."""
        self.segments = np.ascontiguousarray(segments, dtype=np.float64)
        self.radius = float(radius)
        self.c = float(c) if c is not None else 1.0 / self.radius
        self.wall = None if wall is None else float(wall)
        self.threshold = float(convolution.line_field(self.radius, self.c))

    def field(self, x: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Raw convolution field ``F (n,)`` and ``∇F (n, 3)``."""
        F, g = convolution.segment_field(_points(x), self.segments, self.c)
        return F, g

    def value(self, x: FloatArray) -> FloatArray:
        """Distance-normalised ``H (n,)`` (no gradient computed)."""
        F, _ = convolution.segment_field(_points(x), self.segments, self.c, gradient=False)
        H, _ = convolution.distance_from_field(F, self.c, self.radius)
        if self.wall is not None:
            H = np.maximum(H, -H - self.wall)
        return H

    def value_and_grad(self, x: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Distance-normalised ``H (n,)`` and exact ``∇H = dH/dF ∇F (n, 3)``."""
        F, gF = self.field(x)
        H, dH = convolution.distance_from_field(F, self.c, self.radius)
        grad = dH[:, None] * gF
        if self.wall is not None:
            inner = H < -0.5 * self.wall
            H = np.where(inner, -H - self.wall, H)
            grad = np.where(inner[:, None], -grad, grad)
        return H, grad

    @property
    def box(self) -> FloatArray:
        """Conservative box: skeleton box grown by 3 radii (blends at joints bulge beyond R)."""
        v = self.segments.reshape(-1, 3)
        pad = 3.0 * self.radius
        return np.stack([v.min(0) - pad, v.max(0) + pad])

    @property
    def min_z(self) -> float:
        """Lowest point of the skeleton minus the radius (exact for an isolated end cap)."""
        return float(self.segments[..., 2].min() - self.radius)

    @property
    def feature_size(self) -> float:
        """The tube diameter 2R, or the wall thickness when hollow."""
        return self.wall if self.wall is not None else 2.0 * self.radius

    def arrays(self) -> dict[str, np.ndarray]:
        """``segments (k, 2, 3)``."""
        return {"segments": self.segments}

    def attrs(self) -> dict:
        """``type``, ``radius``, ``c``, ``wall``."""
        return {"type": "tubes", "radius": self.radius, "c": self.c, "wall": self.wall}

    @classmethod
    def from_data(cls, arrays: dict[str, np.ndarray], attrs: dict) -> "TubesComponent":
        """Rebuild from :meth:`arrays` / :meth:`attrs`."""
        return cls(np.asarray(arrays["segments"]), attrs["radius"], attrs["c"], attrs.get("wall"))


COMPONENT_TYPES: dict[str, type[Component]] = {
    "mesh": MeshComponent, "tet": MeshComponent, "points": MeshComponent, "shell": ShellComponent,
    "struts": StrutsComponent, "tubes": TubesComponent,
}


def component_from_arrays(arrays: dict[str, np.ndarray], attrs: dict) -> Component:
    """Rebuild any component from its arrays and attrs (dispatch on ``attrs["type"]``)."""
    return COMPONENT_TYPES[attrs["type"]].from_data(arrays, attrs)
