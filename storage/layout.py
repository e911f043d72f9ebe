"""The store's layout for its readers: the named dimensions of every array a step writes, and how arrays are
chunked and compressed (docs/store.md describes every group)."""
from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
from zarr.codecs import BloscCodec, BloscShuffle

#: the x, y, z components of a vector in the build frame (not ``xyz``: the toolpaths' ``xyz`` array has the name)
SPATIAL = "spatial"
#: uncompressed bytes a chunk aims at: whole rows, split along the first axis only
CHUNK_BYTES = 4 * 2**20
#: Blosc, zstd at a low level after a bit shuffle: as fast as zarr's default (zstd alone), up to a fifth smaller on
#: large float arrays (a byte shuffle did worse on (n, 3) ones), read by every zarr v3 implementation (docs/store.md)
BLOSC_CNAME, BLOSC_CLEVEL, BLOSC_SHUFFLE = "zstd", 3, BloscShuffle.bitshuffle

_MESH = {"vertices": ("vertex", SPATIAL), "faces": ("face", "face_corner")}
_FEA = {
    "ijk": ("voxel", SPATIAL), "nodes": ("node", SPATIAL), "elements": ("voxel", "voxel_corner"),
    "centres": ("voxel", SPATIAL), "displacement": ("node", SPATIAL),
    "strain": ("voxel", "tensor_row", "tensor_column"), "stress": ("voxel", "tensor_row", "tensor_column"),
    "principal_stress": ("voxel", "principal"), "principal_directions": ("voxel", SPATIAL, "principal"),
    "tau_max": ("voxel", SPATIAL), "max_principal": ("voxel",), "von_mises": ("voxel",),
}
_FIELD = {"G": ("vertex",), "lpd": ("tet", SPATIAL), "deformed_vertices": ("vertex", SPATIAL), "history/*": ("step",)}

#: dimension names by group kind (the ``<step>`` of ``<model>/<step>/<digest>``) and array name; a ``*`` in a
#: name matches any text, which a ``{0}`` in the dimension names repeats (``c*_vertices`` -> ``c0_vertex``)
DIMENSIONS: dict[str, dict[str, tuple[str, ...]]] = {
    "model": {
        "c*_vertices": ("c{0}_vertex", SPATIAL), "c*_faces": ("c{0}_face", "face_corner"),
        "c*_tets": ("c{0}_tet", "tet_corner"), "c*_segments": ("c{0}_segment", "endpoint", SPATIAL),
    },
    "surface": _MESH,
    "samples": {"points": ("sample", SPATIAL), "normals": ("sample", SPATIAL), "areas": ("sample",),
                "knn": ("sample", "neighbour"), "on_platform": ("sample",)},
    "cage": {"vertices": ("vertex", SPATIAL), "tets": ("tet", "tet_corner")},
    "fea": _FEA,
    "fea_printed": {**_FEA, "turn/*": ("top_voxel",)},
    "stress_samples": {"points": ("sample", SPATIAL), "volumes": ("sample",), "tau_max": ("sample", SPATIAL),
                       "stress": ("sample",)},
    "field": {**_FIELD, "quaternions": ("tet", "quaternion"), "scales": ("tet", SPATIAL),
              "pretrain_history": ("pretrain_step",)},
    "field_blend": _FIELD,
    "field_s3": {**_FIELD, "deformed_vertices": ("deformed_vertex", SPATIAL),
                 "element_scales": ("deformed_tet", SPATIAL), "history/*": ("iteration",)},
    "field_s3_oneshot": {**_FIELD, "quaternions": ("tet", "quaternion"), "intended_lpd": ("tet", SPATIAL)},
    "layers": {"vertices": ("layer_vertex", SPATIAL), "lpd": ("layer_vertex", SPATIAL),
               "faces": ("layer_face", "face_corner"), "vertex_offsets": ("layer_offset",),
               "face_offsets": ("layer_offset",), "isovalues": ("layer",)},
    "toolpaths": {
        **{k: ("waypoint",) for k in ("layer", "path", "thickness", "width", "extrude")},
        "xyz": ("waypoint", SPATIAL), "axis": ("waypoint", SPATIAL),
    },
    "motion": {
        **{f"toolpaths/{k}": ("waypoint",) for k in ("layer", "path", "thickness", "width", "extrude")},
        "toolpaths/xyz": ("waypoint", SPATIAL), "toolpaths/axis": ("waypoint", SPATIAL),
        **{f"program/{k}": ("move",) for k in ("extruder", "time_s", "kind", "source", "layer")},
        "program/machine": ("move", "machine_axis"),
        "collisions/indices": ("collision",), "collisions/kind": ("collision",),
        "collisions/locations": ("collision", SPATIAL),
        # a released print (tasks/release.py): the waypoints that collide and the collision map its figure draws
        "collisions/xyz": ("collision", SPATIAL), "collision_map/clear": ("map_clear", SPATIAL),
        "collision_map/hit": ("map_hit", SPATIAL), "collision_map/bounds": ("bound", SPATIAL),
    },
    "program": {"gcode": ("byte",)},
    "verify": {"centres": ("voxel", SPATIAL), "strain/*": ("voxel",), "angles/*": ("{0}_segment",),
               "angle_weights/*": ("{0}_segment",)},
    "checkpoints": {"blob": ("byte",)},
    "user_field": {"points": ("point", SPATIAL), "values": ("point",)},
}


def group_kind(path: str) -> str:
    """The kind of a group: the step of ``<model>/<step>/...`` ('' for a path without one)."""
    parts = path.split("/")
    return parts[1] if len(parts) > 1 else ""


def _match(pattern: str, name: str) -> str | None:
    """The text a pattern's ``*`` matched in ``name`` ('' for an exact match), None when it does not match."""
    if "*" not in pattern:
        return "" if pattern == name else None
    head, tail = pattern.split("*", 1)
    if len(name) >= len(head) + len(tail) and name.startswith(head) and name.endswith(tail):
        return name[len(head):len(name) - len(tail)]
    return None


def dimension_names(kind: str, name: str, ndim: int) -> tuple[str, ...]:
    """The named dimensions of array ``name`` in a group of this kind; ``<array>_dim_<i>`` where the table has no
    entry of that rank (the array's last path component stands for it)."""
    for pattern, dims in DIMENSIONS.get(kind, {}).items():
        found = _match(pattern, name)
        if found is not None and len(dims) == ndim:
            return tuple(d.format(found) for d in dims)
    leaf = name.rsplit("/", 1)[-1]
    return tuple(f"{leaf}_dim_{i}" for i in range(ndim))


def group_dimensions(kind: str, shapes: Mapping[str, tuple[int, ...]]) -> dict[str, tuple[str, ...]]:
    """Dimension names of every array of one group (its subgroups included); a name the table gives two sizes
    in one group (xarray needs one size per name, across a tree of groups too) becomes ``<array>_<name>`` for the
    arrays after the first (``<path with dots>_<name>`` if that is taken too)."""
    sizes: dict[str, int] = {}
    out: dict[str, tuple[str, ...]] = {}
    for name, shape in shapes.items():
        dims = []
        for dim, size in zip(dimension_names(kind, name, len(shape)), shape):
            for candidate in (dim, f"{name.rsplit('/', 1)[-1]}_{dim}", f"{name.replace('/', '.')}_{dim}"):
                if sizes.setdefault(candidate, size) == size:
                    break
            dims.append(candidate)
        out[name] = tuple(dims)
    return out


def chunk_shape(shape: tuple[int, ...], itemsize: int) -> tuple[int, ...]:
    """Chunks of whole rows along the first axis, about CHUNK_BYTES each (the whole array when smaller)."""
    if not shape:
        return ()
    row = itemsize * math.prod(shape[1:])
    rows = max(1, CHUNK_BYTES // max(row, 1))
    return (max(1, min(shape[0], rows)), *(max(1, s) for s in shape[1:]))


def compressor(dtype: np.dtype) -> BloscCodec:
    """The codec of an array of this dtype (every dtype the same: Blosc zstd after a bit shuffle, the item size
    taken from the dtype)."""
    return BloscCodec(cname=BLOSC_CNAME, clevel=BLOSC_CLEVEL, shuffle=BLOSC_SHUFFLE, typesize=np.dtype(dtype).itemsize)
