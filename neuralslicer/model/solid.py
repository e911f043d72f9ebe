"""The implicit solid ``H`` of a model: union of its components, in the build frame (+z up, mm)."""
from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np

from neuralslicer.errors import InputError
from neuralslicer.frames import up_rotation
from neuralslicer.model import io
from neuralslicer.model.components import (
    Component, MeshComponent, ShellComponent, StrutsComponent, TubesComponent,
    component_from_arrays, enclosed_volume,
)
from neuralslicer.model.convolution import radius_from_threshold
from neuralslicer.model.grid import level_set_mesh
from neuralslicer.model.spec import ModelSpec
from neuralslicer.topology import genus
from neuralslicer.types import FloatArray

if TYPE_CHECKING:  # trimesh (and scipy.spatial, networkx) only where a mesh is made: not on a cached rerun
    import trimesh

    from neuralslicer.fea.spec import FEASpec


SCHEMA_VERSION = 1
#: Most grid cells used by :meth:`Solid.surface` when the voxel size is not given.
MAX_SURFACE_CELLS = 16_000_000
#: A closed mesh may have holes (the winding number bridges them) but no boundary loop longer
#: than this fraction of its bounding-box diagonal: that is an open surface (use a shell).
OPEN_LOOP_FRACTION = 0.2
#: Points per batch when evaluating H on a grid.
_GRID_BATCH = 250_000


class Solid:
    """Implicit solid ``H(x) < 0`` inside: union (min, or smooth min) of implicit components.

    Parameters
    ----------
    components : the parts, data in the build frame (mm).
    platform_z : height of the platform plane; None = the solid's lowest point.
    smooth_union : blend radius k of the polynomial smooth minimum; None = plain min.
    surface_voxel : marching-cubes voxel size for :meth:`surface`; None = ``feature_size / 4``,
        coarsened so that the grid has at most ``MAX_SURFACE_CELLS`` cells.
    meta : JSON-able provenance (up, units, spec digest) kept through :meth:`to_arrays`.
    """

    def __init__(self, components: list[Component], platform_z: float | None = None,
                 smooth_union: float | None = None, surface_voxel: float | None = None,
                 meta: dict | None = None) -> None:
        """Assemble a solid from built components (see the class docstring)."""
        if not components:
            raise ValueError("a solid needs at least one component")
        self.components = list(components)
        self._platform_z = None if platform_z is None else float(platform_z)
        self.smooth_union = None if smooth_union is None else float(smooth_union)
        self.surface_voxel = None if surface_voxel is None else float(surface_voxel)
        self.meta = dict(meta or {})

    # ---------------------------------------------------------------- evaluation
    def value_and_grad(self, x: FloatArray) -> tuple[FloatArray, FloatArray]:
        """``H (n,)`` and ``∇H (n, 3)`` at ``x (n, 3)``."""
        x = np.ascontiguousarray(x, dtype=np.float64).reshape(-1, 3)
        H, G = self.components[0].value_and_grad(x)
        for comp in self.components[1:]:
            h, g = comp.value_and_grad(x)
            if self.smooth_union is None:
                take = h < H
                H = np.where(take, h, H)
                G = np.where(take[:, None], g, G)
            else:  # polynomial smooth min (Quilez); its gradient is the blend of the gradients
                k = self.smooth_union
                t = np.clip(0.5 + 0.5 * (H - h) / k, 0.0, 1.0)  # weight of h
                H = h * t + H * (1.0 - t) - k * t * (1.0 - t)
                G = t[:, None] * g + (1.0 - t)[:, None] * G
        return H, G

    def H(self, x: FloatArray) -> FloatArray:
        """Signed implicit value ``(n,)``, < 0 inside, distance-like near the surface."""
        x = np.ascontiguousarray(x, dtype=np.float64).reshape(-1, 3)
        H = self.components[0].value(x)
        for comp in self.components[1:]:
            h = comp.value(x)
            if self.smooth_union is None:
                H = np.minimum(H, h)
            else:
                k = self.smooth_union
                t = np.clip(0.5 + 0.5 * (H - h) / k, 0.0, 1.0)
                H = h * t + H * (1.0 - t) - k * t * (1.0 - t)
        return H

    def grad_H(self, x: FloatArray) -> FloatArray:
        """Gradient ``(n, 3)`` of H (outward, unit length for distance components)."""
        return self.value_and_grad(x)[1]

    # ---------------------------------------------------------------- geometry
    @property
    def exact_boxes(self) -> bool:
        """True when the union of the components' boxes is the solid's exact bounding box."""
        return self.smooth_union is None and all(c.exact_box for c in self.components)

    @cached_property
    def bounds(self) -> FloatArray:
        """Bounding box ``(2, 3)`` of the solid ``H <= 0`` (exact, or from the extracted surface)."""
        if self.exact_boxes:
            boxes = np.stack([c.box for c in self.components])
            return np.stack([boxes[:, 0].min(0), boxes[:, 1].max(0)])
        v = self.surface().vertices
        return np.stack([v.min(0), v.max(0)])

    @property
    def platform_z(self) -> float:
        """Height of the platform plane ``z = platform_z`` (default: the solid's lowest z)."""
        if self._platform_z is not None:
            return self._platform_z
        return float(self.bounds[0, 2])

    @cached_property
    def feature_size(self) -> float:
        """Smallest meaningful feature (mm): the minimum of the components' feature sizes."""
        return float(min(c.feature_size for c in self.components))

    def _single_mesh(self) -> MeshComponent | None:
        """The component when the solid is one closed mesh / tet boundary."""
        if len(self.components) == 1 and isinstance(self.components[0], MeshComponent):
            return self.components[0]
        return None

    def default_voxel(self) -> float:
        """Marching-cubes voxel size used by :meth:`surface` when none is given (mm)."""
        if self.surface_voxel is not None:
            return self.surface_voxel
        boxes = np.stack([c.box for c in self.components])
        extent = boxes[:, 1].max(0) - boxes[:, 0].min(0)
        voxel = self.feature_size / 4.0
        return float(max(voxel, (np.prod(extent) / MAX_SURFACE_CELLS) ** (1.0 / 3.0)))

    def surface(self, voxel: float | None = None) -> trimesh.Trimesh:
        """Boundary ``H = 0`` as a triangle mesh in the build frame, outward normals.

        For a single closed mesh / tet component: the input boundary itself.  Otherwise marching
        cubes (scikit-image) of H on a grid of ``voxel`` (default :meth:`default_voxel`), with the
        vertices moved onto ``H = 0`` by two Newton steps along ∇H.
        """
        import trimesh

        single = self._single_mesh()
        if single is not None and voxel is None:
            return trimesh.Trimesh(single.vertices.copy(), single.faces.copy(), process=False)
        if voxel is None:
            if "_surface" not in self.__dict__:
                self.__dict__["_surface"] = self._marching_cubes(self.default_voxel())
            return self.__dict__["_surface"].copy()
        return self._marching_cubes(float(voxel))

    def grid_values(self, origin: FloatArray, voxel: float, shape: tuple[int, int, int],
                    block: int = 8) -> np.ndarray:
        """H on the grid ``origin + voxel * (i, j, k)``, exact only in a narrow band (float32).

        The grid is cut into blocks of ``block³`` voxels; H is first evaluated at the block
        centres and a block is evaluated point by point only when ``|H(centre)|`` is within 1.5×
        its half-diagonal (H is distance-like, so the surface cannot pass through other blocks).
        Other blocks are filled with ``±inf`` by the sign at their centre.
        """
        shape = tuple(int(s) for s in shape)
        nb = [(s - 1) // block + 1 for s in shape]
        centres_idx = np.stack(np.meshgrid(*[np.arange(n) for n in nb], indexing="ij"), -1).reshape(-1, 3)
        centres = origin + voxel * block * (centres_idx + 0.5)
        hc = np.concatenate([self.H(centres[i:i + _GRID_BATCH]) for i in range(0, len(centres), _GRID_BATCH)])
        reach = 1.5 * (0.5 * block * np.sqrt(3.0) + 1.0) * voxel
        fill = np.where(hc > 0, np.inf, -np.inf).astype(np.float32).reshape(nb)
        out = np.repeat(np.repeat(np.repeat(fill, block, 0), block, 1), block, 2)
        out = np.ascontiguousarray(out[:shape[0], :shape[1], :shape[2]])
        active = centres_idx[np.abs(hc) <= reach]
        local = np.stack(np.meshgrid(*[np.arange(block)] * 3, indexing="ij"), -1).reshape(-1, 3)
        per_batch = max(1, _GRID_BATCH // len(local))
        for i in range(0, len(active), per_batch):
            idx = (active[i:i + per_batch, None, :] * block + local[None]).reshape(-1, 3)
            idx = idx[(idx < np.asarray(shape)).all(axis=1)]
            out[idx[:, 0], idx[:, 1], idx[:, 2]] = self.H(origin + voxel * idx)
        self.__dict__["_last_grid_evaluations"] = len(centres) + len(active) * len(local)
        return out

    def _marching_cubes(self, voxel: float) -> trimesh.Trimesh:
        """Marching cubes of H at level 0 on a narrow-band grid that covers the solid with a margin."""
        import trimesh

        boxes = np.stack([c.box for c in self.components])
        lo, hi = boxes[:, 0].min(0), boxes[:, 1].max(0)
        if self.smooth_union is not None:
            lo, hi = lo - self.smooth_union, hi + self.smooth_union
        for _ in range(4):
            # an odd offset keeps grid nodes off axis-aligned faces at round coordinates
            origin = lo - (2.0 + 0.1234567) * voxel
            shape = tuple(int(s) for s in np.ceil((hi - lo) / voxel).astype(int) + 5)
            values = self.grid_values(origin, voxel, shape)
            border = np.concatenate([values[[0, -1]].ravel(), values[:, [0, -1]].ravel(),
                                     values[:, :, [0, -1]].ravel()])
            if border.min() > 0:
                break
            pad = 0.25 * (hi - lo)
            lo, hi = lo - pad, hi + pad
        if values.min() >= 0:
            raise InputError("components", "the model is empty: H > 0 everywhere on the grid")
        # marching cubes interpolates: replace the ±inf fill by a finite value beyond the band
        big = np.float32(4.0 * voxel * 8)
        np.clip(values, -big, big, out=values)
        values[values == 0] = np.float32(1e-6 * voxel)  # exact zeros make non-manifold cases
        verts, faces = level_set_mesh(values, origin, voxel)
        mesh = trimesh.Trimesh(self.project(verts, steps=2), faces, process=False)
        if enclosed_volume(mesh.vertices, mesh.faces) < 0:  # projected onto H = 0: check the winding again
            mesh.invert()
        return mesh

    def project(self, points: FloatArray, steps: int = 3) -> FloatArray:
        """Points moved onto ``H = 0`` by Newton steps ``x -= H ∇H / |∇H|²``."""
        x = np.array(points, dtype=np.float64, copy=True)
        for _ in range(steps):
            h, g = self.value_and_grad(x)
            gg = np.einsum("ij,ij->i", g, g)
            ok = gg > 1e-12
            x[ok] -= (h[ok] / gg[ok])[:, None] * g[ok]
        return x

    def volume(self) -> float:
        """Volume of the solid (mm³): exact for one closed mesh, else the extracted surface's."""
        single = self._single_mesh()
        if single is not None:
            return single.volume
        s = self.surface()
        return abs(enclosed_volume(s.vertices, s.faces))

    # ---------------------------------------------------------------- storage
    def surface_record(self) -> tuple[dict[str, np.ndarray], dict]:
        """The boundary surface as arrays, with its genus, the volume, bounds, platform and feature size."""
        surface = self.surface()
        faces = np.asarray(surface.faces, dtype=np.int64)
        return {"vertices": np.asarray(surface.vertices), "faces": faces}, {
            "bounds": self.bounds, "platform_z": self.platform_z, "volume_mm3": self.volume(),
            "genus": genus(faces), "feature_size": self.feature_size,
        }

    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict]:
        """Plain arrays (``c{i}_{name}``, build frame) and JSON attrs that rebuild the same solid."""
        arrays: dict[str, np.ndarray] = {}
        for i, comp in enumerate(self.components):
            for name, arr in comp.arrays().items():
                arrays[f"c{i}_{name}"] = np.asarray(arr)
        attrs = {
            "schema_version": SCHEMA_VERSION,
            "components": [c.attrs() for c in self.components],
            "platform_z": self._platform_z,
            "platform_z_resolved": None if not self.exact_boxes else self.platform_z,
            "smooth_union": self.smooth_union,
            "surface_voxel": self.surface_voxel,
            "feature_size": self.feature_size,
            "units": "mm",
            "meta": self.meta,
        }
        json.dumps(attrs)  # must be JSON-able
        return arrays, attrs

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], attrs: dict) -> "Solid":
        """Rebuild a solid written by :meth:`to_arrays` (no original files needed)."""
        if attrs.get("schema_version") != SCHEMA_VERSION:
            raise ValueError(f"unsupported solid schema_version {attrs.get('schema_version')}")
        comps = []
        for i, cattrs in enumerate(attrs["components"]):
            prefix = f"c{i}_"
            data = {k[len(prefix):]: np.asarray(v) for k, v in arrays.items() if k.startswith(prefix)}
            comps.append(component_from_arrays(data, cattrs))
        return cls(comps, platform_z=attrs.get("platform_z"), smooth_union=attrs.get("smooth_union"),
                   surface_voxel=attrs.get("surface_voxel"), meta=attrs.get("meta"))

    def __repr__(self) -> str:
        """Short description."""
        kinds = ", ".join(c.attrs()["type"] for c in self.components)
        return f"Solid([{kinds}], smooth_union={self.smooth_union})"


# -------------------------------------------------------------------- building from a spec

def _closed_mesh(path, vertices: FloatArray, faces, what: str) -> None:
    """Raise InputError when a mesh that must be closed encloses (almost) no volume."""
    extent = np.ptp(vertices, axis=0)
    diag = float(np.linalg.norm(extent))
    vol = abs(enclosed_volume(vertices, faces))
    if diag == 0 or vol <= 1e-6 * diag ** 3:
        raise InputError(path, f"the {what} encloses no volume ({vol:.3g} mm³ for a bounding-box "
                               f"diagonal of {diag:.3g} mm): it is flat or open; use "
                               f"'type: shell' with a thickness for an open surface")
    from neuralslicer.topology import boundary_loop_lengths

    loops = boundary_loop_lengths(vertices, faces)
    if len(loops) and loops.max() > OPEN_LOOP_FRACTION * diag:
        raise InputError(path, f"the {what} is open: a boundary loop {loops.max():.3g} mm long "
                               f"(> {OPEN_LOOP_FRACTION:g} x the bounding-box diagonal {diag:.3g} mm); "
                               f"close it, or use 'type: shell' with a thickness")


def _tet_boundary(path, vertices: FloatArray, tets) -> tuple[FloatArray, np.ndarray, np.ndarray]:
    """Oriented tets and their outward boundary faces; checks the volume."""
    from neuralslicer.tetmesh import boundary_faces, orient_tets, tet_volumes

    tets = orient_tets(vertices, tets)
    vol = tet_volumes(vertices, tets)
    diag = float(np.linalg.norm(np.ptp(vertices, axis=0)))
    if diag == 0 or vol.sum() <= 1e-6 * diag ** 3:
        raise InputError(path, "the tetrahedral mesh has no volume (degenerate tets)")
    return vertices, tets, boundary_faces(tets)


def _points_component(cs, frame, s: float) -> MeshComponent:
    """Read a point cloud, reconstruct its closed surface (:mod:`neuralslicer.model.points`), as a mesh."""
    from neuralslicer.model.points import check_cloud, reconstruct   # scipy.ndimage and friends: point clouds only

    path = cs.file
    p, n = io.read_points(path)
    if cs.normals == "given" and n is None:
        raise InputError(path, "'normals: given' but the file has no normals; add nx ny nz or use "
                               "'normals: auto' to estimate them")
    if cs.normals == "estimate":
        n = None
    p, n = check_cloud(path, p, n)
    if n is not None:  # rotate with the points (frame scales by s too)
        n = frame(n) / s
    v, f = reconstruct(frame(p), n, k=cs.k, resolution=cs.resolution, where=path)
    return MeshComponent(v, f, source_kind="points")


def implicit_solid(spec: ModelSpec) -> Solid:
    """Build the implicit solid H of a model spec: read every file, rotate to the build frame, scale to mm."""
    rot = up_rotation(spec.up)
    s = spec.scale

    def frame(points: FloatArray) -> FloatArray:
        """Input-frame points in spec units -> build-frame points in mm."""
        return (np.asarray(points, dtype=np.float64) * s) @ rot.T

    comps: list[Component] = []
    for i, cs in enumerate(spec.components):
        try:
            comps.append(_build_component(cs, frame, s))
        except InputError as exc:
            origin = f"{spec.source.name}: " if spec.source is not None else ""
            raise InputError(exc.where, f"{exc.message} ({origin}components[{i}], type {cs.type})") from None
    platform = None if spec.platform == "auto" else spec.platform.z * s
    meta = {"up": spec.up, "input_units": spec.units,
            "source": None if spec.source is None else str(spec.source)}
    return Solid(comps, platform_z=platform,
                 smooth_union=None if spec.smooth_union is None else spec.smooth_union * s,
                 surface_voxel=None if spec.surface_voxel is None else spec.surface_voxel * s,
                 meta=meta)


def _build_component(cs, frame, s: float) -> Component:
    """Read one component's file and build it in the build frame (lengths scaled by s)."""
    path = cs.file
    if cs.type == "mesh":
        v, f = io.read_surface(path)
        v = frame(v)
        _closed_mesh(path, v, f, "mesh")
        return MeshComponent(v, f)
    if cs.type == "tet":
        v, t = io.read_volume(path)
        v, t, f = _tet_boundary(path, frame(v), t)
        return MeshComponent(v, f, source_kind="tet", tets=t)
    if cs.type == "shell":
        v, f = io.read_surface(path)
        return ShellComponent(frame(v), f, cs.thickness * s)
    if cs.type == "points":
        return _points_component(cs, frame, s)
    seg = io.check_segments(path, io.read_segments(path))
    seg = frame(seg.reshape(-1, 3)).reshape(-1, 2, 3)
    if cs.type == "struts":
        return StrutsComponent(seg, cs.radius * s)
    if cs.type == "tubes":
        c = (cs.c / s) if cs.c is not None else None
        radius = cs.radius * s if cs.radius is not None else radius_from_threshold(cs.threshold * s, c)
        return TubesComponent(seg, radius, c, None if cs.wall is None else cs.wall * s)
    raise InputError(path, f"unknown component type {cs.type!r}")  # pragma: no cover


@dataclass(frozen=True)
class Model:
    """The model step's output: the spec, its implicit solid and the name its results are stored under."""

    spec: ModelSpec
    solid: Solid
    name: str = ""

    @property
    def label(self) -> str:
        """The model's name (``name``, else the spec's file's)."""
        from neuralslicer.model.spec import model_name

        return self.name or model_name(self.spec)

    @property
    def fea_spec(self) -> FEASpec:
        """The spec's FEA block (an error naming the spec when it has none)."""
        if self.spec.fea is None:
            raise InputError(getattr(self.spec, "source", None) or self.label,
                             "the model spec has no 'fea' block (supports and loads)")
        return self.spec.fea

    def to_arrays(self) -> tuple[dict[str, np.ndarray], dict]:
        """The solid's components and the spec, as the store keeps them."""
        arrays, attrs = self.solid.to_arrays()
        return arrays, {**attrs, "spec": self.spec.model_dump(mode="json")}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], attrs: dict, name: str = "") -> "Model":
        """Inverse of ``to_arrays`` (``name``: the model's name in the store)."""
        return cls(ModelSpec.model_validate(attrs["spec"]), Solid.from_arrays(arrays, attrs), name)
