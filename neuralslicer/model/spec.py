"""The model spec: a YAML file listing the components of a model, its up axis, units, platform, FEA.

Minimal form (paths are relative to the spec file's folder)::

    up: z
    components:
      - type: shell
        file: surface.stl
        thickness: 3.0
      - type: mesh
        file: part.stl

Every length in the spec (thickness, radius, wall, smooth_union, platform z, surface_voxel) is in
``units``, like the coordinates of the files; everything is converted to millimetres on load. The
``k`` and ``resolution`` of a ``points`` component are counts, not lengths.
"""
from __future__ import annotations

import hashlib
import re
from pathlib import Path
from typing import Annotated, Any, Literal, Union

import yaml
from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, ValidationError, model_validator

from neuralslicer.fileio import json_sha256
from neuralslicer.errors import InputError, unknown_key_message
from neuralslicer.fea.spec import FEASpec
from neuralslicer.model.io import (
    POINT_SUFFIXES, SURFACE_SUFFIXES, TET_SUFFIXES, VOLUME_SUFFIXES, ply_face_count, threemf_units,
)

#: Length of one spec unit in millimetres.
UNIT_SCALE = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}
SPEC_SUFFIXES = (".yaml", ".yml")


class _Strict(BaseModel):
    """Rejects unknown keys: a typo in a spec is an error, not a silently ignored key."""

    model_config = ConfigDict(extra="forbid")


class MeshComponentSpec(_Strict):
    """A closed triangle mesh (STL/3MF/OBJ/PLY/OFF): signed distance, sign by winding number."""

    type: Literal["mesh"]
    file: Path = Field(description="Mesh file, relative to the spec's folder.")


class TetComponentSpec(_Strict):
    """A tetrahedral mesh (``.tet`` or any meshio volume format): signed distance to its boundary."""

    type: Literal["tet"]
    file: Path = Field(description="Volume mesh file, relative to the spec's folder.")


class ShellComponentSpec(_Strict):
    """An (open) surface thickened into a shell: ``H = dist(x, S) - thickness/2``."""

    type: Literal["shell"]
    file: Path = Field(description="Triangle mesh of the mid surface S.")
    thickness: float = Field(gt=0, description="Shell thickness t (spec units), > 0.")


class StrutsComponentSpec(_Strict):
    """Line segments as capsules of a radius: ``H = dist(x, segments) - radius``."""

    type: Literal["struts"]
    file: Path = Field(description="Segments file (`x0 y0 z0 x1 y1 z1` lines) or polyline OBJ.")
    radius: float = Field(gt=0, description="Capsule radius r (spec units), > 0.")


class TubesComponentSpec(_Strict):
    """Convolution surface of skeleton segments with the Cauchy kernel ``1/(1+c²d²)²``.

    Give ``radius`` (the radius of the tube around a long straight segment; the iso threshold is
    then ``T = π / (2c (1 + c²R²)^{3/2})``) or ``threshold`` T directly, not both.
    """

    type: Literal["tubes"]
    file: Path = Field(description="Skeleton segments file or polyline OBJ.")
    radius: float | None = Field(None, gt=0, description="Tube radius R (spec units); "
                                 "exactly one of radius / threshold.")
    threshold: float | None = Field(None, gt=0, description="Iso threshold T of the field F "
                                    "(units of length, the field is ∫ds); exactly one of "
                                    "radius / threshold.")
    c: float | None = Field(None, gt=0, description="Kernel sharpness c (1 / spec unit); "
                            "default 1/radius (1/R when threshold is given requires c).")
    wall: float | None = Field(None, gt=0, description="Wall thickness of a hollow tube "
                               "(spec units); default None = solid tube.")

    @model_validator(mode="after")
    def _radius_or_threshold(self) -> "TubesComponentSpec":
        """Exactly one of radius / threshold, and c with threshold."""
        if (self.radius is None) == (self.threshold is None):
            raise ValueError("give exactly one of 'radius' and 'threshold'")
        if self.threshold is not None and self.c is None:
            raise ValueError("'threshold' needs the kernel parameter 'c'")
        if self.threshold is not None and self.threshold >= 3.141592653589793 / (2 * self.c):
            raise ValueError(f"'threshold' must be below π/(2c) = {3.141592653589793 / (2 * self.c):.6g} "
                             "(the field on the axis of an infinite line)")
        return self


class PointsComponentSpec(_Strict):
    """A point cloud (.xyz, .pcd, .ply without faces) reconstructed into a closed surface.

    See :mod:`neuralslicer.model.points` for the method: normals (given or estimated by PCA and
    oriented along a spanning tree), winding number for inside/outside, marching cubes, projection.
    """

    type: Literal["points"]
    file: Path = Field(description="Point cloud file: .xyz ('x y z [nx ny nz]' lines), .pcd or .ply.")
    normals: Literal["auto", "given", "estimate"] = Field(
        "auto", description="auto: the file's normals when it has them, else estimated; given: the "
        "file's (an error without); estimate: ignore the file's normals.")
    k: int = Field(16, ge=4, le=100, description="Neighbours for normal estimation. Default 16.")
    resolution: int = Field(96, ge=16, le=512, description="Grid cells along the longest side of the "
                            "cloud's bounding box for the reconstruction. Default 96.")


ComponentSpec = Annotated[
    Union[MeshComponentSpec, TetComponentSpec, ShellComponentSpec, StrutsComponentSpec,
          TubesComponentSpec, PointsComponentSpec],
    Field(discriminator="type"),
]
COMPONENT_TAGS = ("mesh", "tet", "shell", "struts", "tubes", "points")


class PlatformPlane(_Strict):
    """The platform as the plane ``z = value`` of the build frame (spec units)."""

    z: float = Field(description="Height of the platform plane in the build frame.")


class ModelSpec(_Strict):
    """A model: components (union = min), up axis, units, platform, FEA (``None`` = no FEA)."""

    up: Literal["x", "y", "z", "-x", "-y", "-z"] = Field(
        "z", description="Input axis that becomes +z (build direction). Default z.")
    units: Literal["mm", "cm", "m", "in"] = Field(
        "mm", description="Unit of the files' coordinates and of every length in the spec. Default mm.")
    platform: Literal["auto"] | PlatformPlane = Field(
        "auto", description="'auto' = the plane through the solid's lowest point, or {z: value}.")
    components: list[ComponentSpec] = Field(min_length=1, description="The parts, at least one.")
    smooth_union: float | None = Field(
        None, gt=0, description="Blend radius of a polynomial smooth union of the components "
        "(spec units). Default None: plain union H = min.")
    surface_voxel: float | None = Field(
        None, gt=0, description="Voxel size for extracting the surface by marching cubes (spec "
        "units). Default None: feature_size / 4, coarsened so the grid has at most 16M cells.")
    fea: FEASpec | None = Field(None, description="Supports, loads, material; None: no FEA.")
    _source: Path | None = PrivateAttr(None)

    @property
    def source(self) -> Path | None:
        """The spec file this spec was read from (set by :func:`load_spec`; not a YAML key)."""
        return self._source

    @source.setter
    def source(self, path: Path | None) -> None:
        """Record the spec file."""
        self._source = path

    @property
    def scale(self) -> float:
        """Millimetres per spec unit."""
        return UNIT_SCALE[self.units]

    def files(self) -> list[Path]:
        """Every file the spec references (absolute once loaded)."""
        return [c.file for c in self.components]


# --------------------------------------------------------------------------------------------
# loading and error reporting

def _key(loc: tuple) -> str:
    """``('components', 1, 'shell', 'thickness')`` -> ``components[1].thickness``."""
    out = ""
    previous = None
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        elif isinstance(previous, int) and part in COMPONENT_TAGS:
            pass  # the discriminated-union tag pydantic inserts
        elif part in ("literal['auto']", "PlatformPlane", "function-after[_radius_or_threshold()]"):
            pass
        else:
            out += ("." if out else "") + str(part)
        previous = part
    return out or "(top level)"


def _message(err: dict) -> str:
    """Short human message for one pydantic error."""
    kind, ctx = err["type"], err.get("ctx", {})
    if kind == "greater_than":
        return f"must be > {ctx.get('gt')}"
    if kind == "greater_than_equal":
        return f"must be >= {ctx.get('ge')}"
    if kind == "less_than_equal":
        return f"must be <= {ctx.get('le')}"
    if kind == "missing":
        return "missing required key"
    if kind == "extra_forbidden":
        return "unknown key"
    if kind == "union_tag_invalid":
        return f"unknown component type {ctx.get('tag')!r}; expected one of {', '.join(COMPONENT_TAGS)}"
    if kind == "union_tag_not_found":
        return f"missing 'type'; expected one of {', '.join(COMPONENT_TAGS)}"
    if kind == "too_short":
        return "must list at least one component"
    msg = err["msg"]
    return msg.removeprefix("Value error, ")


def _yaml_line(root: yaml.Node | None, loc: tuple) -> int | None:
    """1-based line of the YAML node at ``loc`` (or of its deepest existing parent)."""
    node, line = root, None
    for part in loc:
        if node is None:
            break
        line = node.start_mark.line + 1
        if isinstance(node, yaml.MappingNode) and isinstance(part, str):
            match = [(k, v) for k, v in node.value if getattr(k, "value", None) == part]
            if match:
                line = match[0][0].start_mark.line + 1
                node = match[0][1]
            elif part in COMPONENT_TAGS:
                continue
            else:
                node = None
        elif isinstance(node, yaml.SequenceNode) and isinstance(part, int):
            node = node.value[part] if part < len(node.value) else None
        else:
            node = None
    if node is not None:
        line = node.start_mark.line + 1
    return line


def _where(path: Path, line: int | None) -> str:
    return f"{path}:{line}" if line else str(path)


def spec_from_dict(data: Any, where: str | Path = "spec", folder: Path | None = None,
                   yaml_root: yaml.Node | None = None) -> ModelSpec:
    """Validate a spec mapping; errors name ``where`` (file[:line]) and the key; paths made absolute."""
    where = Path(where)
    if not isinstance(data, dict):
        raise InputError(where, "a model spec must be a mapping with at least 'components'")
    try:
        spec = ModelSpec.model_validate(data)
    except ValidationError as exc:
        errors = exc.errors()
        first = tuple(errors[0]["loc"])
        # within one key, the deepest error is the most specific (e.g. a union's matching branch); of equally deep
        # ones an unknown key first (a misspelt required key is also missing: the misspelling is the news)
        err = max((e for e in errors if tuple(e["loc"])[:1] == first[:1]),
                  key=lambda e: (len(e["loc"]), e["type"] == "extra_forbidden"))
        loc = tuple(err["loc"])
        if loc[0] == "platform" and "z" not in loc:
            err = {"type": "platform", "msg": "must be 'auto' or {z: <height>}"}
        if err["type"] in ("union_tag_invalid", "union_tag_not_found"):
            loc = loc + ("type",)
        message = unknown_key_message(ModelSpec, loc) if err["type"] == "extra_forbidden" else _message(err)
        raise InputError(_where(where, _yaml_line(yaml_root, loc)), f"{_key(loc)}: {message}") from None
    folder = folder if folder is not None else Path.cwd()
    for i, comp in enumerate(spec.components):
        comp.file = (folder / comp.file).resolve() if not comp.file.is_absolute() else comp.file
        if not comp.file.is_file():
            line = _yaml_line(yaml_root, ("components", i, "file"))
            raise InputError(_where(where, line), f"components[{i}].file: no such file {comp.file}")
    return spec


def load_spec(path: str | Path) -> ModelSpec:
    """Read and validate a YAML model spec; component file paths become absolute."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such file")
    text = path.read_text(errors="replace")
    try:
        root = yaml.compose(text)
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = mark.line + 1 if mark is not None else None
        raise InputError(_where(path, line), f"not valid YAML: {getattr(exc, 'problem', exc)}") from None
    spec = spec_from_dict(data, path, path.parent.resolve(), root)
    spec.source = path.resolve()
    return spec


def spec_for_file(path: str | Path, up: str = "z", units: str | None = None) -> ModelSpec:
    """Spec for a single model file given on the command line (type from the extension).

    ``.stl/.obj/.off/.3mf`` and ``.ply`` with faces -> ``mesh``; ``.xyz/.pcd`` and ``.ply`` without
    faces -> ``points``; ``.tet`` and meshio volume formats -> ``tet``; ``.yaml/.yml`` ->
    :func:`load_spec` (``up``/``units`` then come from the file). ``units`` defaults to mm, for a 3MF to the
    unit the file declares; a 3MF given another unit is an error (the file states its own).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in SPEC_SUFFIXES:
        return load_spec(path)
    if suffix == ".ply":
        kind = "points" if ply_face_count(path) == 0 else "mesh"
    elif suffix in SURFACE_SUFFIXES:
        kind = "mesh"
    elif suffix in POINT_SUFFIXES:
        kind = "points"
    elif suffix in TET_SUFFIXES or suffix in VOLUME_SUFFIXES:
        kind = "tet"
    else:
        raise InputError(path, f"unknown model format {suffix!r}; expected a mesh "
                               f"({', '.join(SURFACE_SUFFIXES)}), a point cloud "
                               f"({', '.join(POINT_SUFFIXES)}), a volume mesh "
                               f"({', '.join(TET_SUFFIXES + VOLUME_SUFFIXES)}) or a spec (.yaml)")
    if not path.is_file():
        raise InputError(path, "no such file")
    if suffix == ".3mf":
        declared = threemf_units(path)
        if units not in (None, declared):
            raise InputError(path, f"the 3MF states its unit, {declared}; leave out the units or give {declared}")
        units = declared
    return spec_from_dict({"up": up, "units": units or "mm", "components": [{"type": kind, "file": str(path)}]},
                          where="command line", folder=Path.cwd())


def file_sha256(path: Path) -> str:
    """sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def load_model(path: str | Path, up: str | None = None, units: str | None = None) -> ModelSpec:
    """The spec of a model file or spec YAML (:func:`spec_for_file`), with ``up`` / ``units`` where given overriding
    the spec's own (left alone when None: a spec's ``up`` is never replaced by a default)."""
    spec = spec_for_file(path, up or "z", units)
    update = {k: v for k, v in (("up", up), ("units", units)) if v is not None and getattr(spec, k) != v}
    if update:
        source = spec.source
        spec = spec.model_copy(update=update)
        spec.source = source
    return spec


def model_name(spec: ModelSpec) -> str:
    """A store-safe model name from the spec's source file (its folder's name for ``model.yaml`` / ``spec.yaml``)."""
    source = Path(getattr(spec, "source", None) or spec.components[0].file)
    stem = source.parent.name if source.stem in ("model", "spec") and source.parent.name else source.stem
    return re.sub(r"[^A-Za-z0-9_.-]", "_", stem) or "model"


def spec_digest(spec: ModelSpec) -> str:
    """Content hash (sha256 hex) of the spec's normalised JSON with each file replaced by its bytes' hash.

    Independent of where the files are (moving a model folder keeps the key), changes when any
    value or any referenced file's content changes.
    """
    data = spec.model_dump(mode="json")
    for comp, model in zip(data["components"], spec.components):
        comp["file"] = {"sha256": file_sha256(Path(model.file)), "suffix": Path(model.file).suffix.lower()}
    return json_sha256(data)
