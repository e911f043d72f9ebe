"""Readers for the discrete representations a model is built from.

Every reader returns plain float64 / int64 arrays in the *input* frame (the up rotation is applied by
the caller) and raises :class:`neuralslicer.errors.InputError` naming the file, and the line where
one applies, when the input cannot be used.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from neuralslicer.errors import InputError
from neuralslicer.types import FloatArray, IndexArray

#: Closed or open triangle meshes, read with trimesh (3MF: every build item, placed by its transform).
SURFACE_SUFFIXES = (".stl", ".obj", ".ply", ".off", ".3mf")
#: A 3MF model's ``unit`` attribute -> our unit names (3MF's default: millimeter).
THREEMF_UNITS = {"millimeter": "mm", "centimeter": "cm", "meter": "m", "inch": "in"}
#: Our own tetrahedral format (see :func:`read_tet`).
TET_SUFFIXES = (".tet",)
#: Volume formats read with meshio (anything with tetra cells).
VOLUME_SUFFIXES = (".msh", ".vtu", ".vtk", ".mesh", ".xdmf", ".med", ".inp", ".ele", ".node")
#: Point clouds: ``x y z [nx ny nz]`` text, PCD (ascii / binary), and PLY (a PLY with faces is a mesh).
POINT_SUFFIXES = (".xyz", ".pcd", ".ply")
#: PCD field TYPE + SIZE -> numpy type.
_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4",
              ("U", 8): "u8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4", ("I", 8): "i8"}


def _existing(path: str | Path) -> Path:
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such file")
    return path


def threemf_units(path: str | Path) -> str:
    """The unit a 3MF file declares (``<model unit="...">``, default millimeter) as ``mm``, ``cm``, ``m`` or ``in``;
    an InputError for micron and foot, which a model spec cannot state."""
    import zipfile
    from xml.etree import ElementTree

    path = _existing(path)
    try:
        with zipfile.ZipFile(path) as archive:
            name = next((n for n in archive.namelist() if n.lower().endswith(".model")), None)
            if name is None:
                raise InputError(path, "not a 3MF file: no 3D/3dmodel.model part in the archive")
            with archive.open(name) as part:
                _, root = next(ElementTree.iterparse(part, events=("start",)))
    except (zipfile.BadZipFile, ElementTree.ParseError, StopIteration) as exc:
        raise InputError(path, f"not a 3MF file ({exc})") from None
    unit = root.get("unit", "millimeter")
    if unit not in THREEMF_UNITS:
        raise InputError(path, f"the 3MF's unit is {unit!r}; export it in millimeter, centimeter, meter or inch")
    return THREEMF_UNITS[unit]


def read_surface(path: str | Path) -> tuple[FloatArray, IndexArray]:
    """Triangle mesh from STL/OBJ/PLY/OFF/3MF: ``vertices (n, 3) float64``, ``faces (m, 3) int64``.

    A 3MF's build items are placed by their transforms and joined into one mesh, in the file's own unit
    (:func:`threemf_units`: the unit its spec takes by default).

    Duplicate vertices (as in STL) are merged; faces are kept as they are, holes and all.
    """
    import trimesh

    path = _existing(path)
    if path.suffix.lower() not in SURFACE_SUFFIXES:
        raise InputError(path, f"unknown mesh format {path.suffix!r}; expected one of "
                               f"{', '.join(SURFACE_SUFFIXES)}")
    try:  # process=False: trimesh would silently drop NaN vertices
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise InputError(path, f"cannot read as a triangle mesh ({exc})") from exc
    faces = np.asarray(getattr(loaded, "faces", np.empty((0, 3))), dtype=np.int64)
    vertices = np.asarray(getattr(loaded, "vertices", np.empty((0, 3))), dtype=np.float64)
    if faces.ndim != 2 or len(faces) == 0:
        cloud = path.suffix.lower() == ".ply" and ply_face_count(path) == 0
        raise InputError(path, "the file holds no triangles" + (
            ": it is a point cloud, use 'type: points'" if cloud else ""))
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise InputError(path, f"{int(bad.sum())} vertices have NaN or infinite coordinates "
                               f"(first: vertex {int(np.flatnonzero(bad)[0]) + 1})")
    mesh = trimesh.Trimesh(vertices, faces, process=True)  # merge duplicates (STL)
    mesh.update_faces(mesh.nondegenerate_faces())
    if len(mesh.faces) == 0:
        raise InputError(path, "the file holds no non-degenerate triangles")
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)


def read_tet(path: str | Path) -> tuple[FloatArray, IndexArray]:
    """Tetrahedral mesh in the ``.tet`` format: ``vertices (n, 3) float64``, ``tets (m, 4) int64``.

    The format: line 1 ``N vertices``, line 2 ``M tets``, then N lines ``x y z`` and M lines
    ``4 a b c d`` with 0-based vertex indices (1-based files, whose indices run 1..N, are detected and
    shifted). Blank lines at the end are ignored.
    """
    path = _existing(path)
    try:
        lines = path.read_text().splitlines()
    except UnicodeDecodeError as exc:
        raise InputError(path, "not a text .tet file") from exc
    counts = []
    for lineno, word in ((1, "vertices"), (2, "tets")):
        fields = lines[lineno - 1].split() if len(lines) >= lineno else []
        if not fields or not fields[0].isdigit():
            raise InputError(f"{path}:{lineno}", f"expected 'COUNT {word}', found {' '.join(fields)!r}")
        counts.append(int(fields[0]))
    n, m = counts
    body = lines[2:]
    while body and not body[-1].strip():
        body.pop()
    if len(body) < n + m:
        raise InputError(path, f"header promises {n} vertices and {m} tets ({n + m} lines) "
                               f"but only {len(body)} lines follow")
    vertices = _parse_rows(path, body[:n], first_line=3, width=3, dtype=np.float64, what="x y z")
    rows = _parse_rows(path, body[n:n + m], first_line=3 + n, width=5, dtype=np.int64, what="4 a b c d")
    if m and (rows[:, 0] != 4).any():
        bad = int(np.flatnonzero(rows[:, 0] != 4)[0])
        raise InputError(f"{path}:{3 + n + bad}", f"a tet line must start with 4, found {rows[bad, 0]}")
    tets = rows[:, 1:]
    if m and tets.min() >= 1 and tets.max() == n:
        tets = tets - 1  # 1-based file
    if m and (tets.min() < 0 or tets.max() >= n):
        bad = int(np.flatnonzero((tets < 0).any(1) | (tets >= n).any(1))[0])
        raise InputError(f"{path}:{3 + n + bad}", f"vertex index out of range 0..{n - 1}")
    if m == 0:
        raise InputError(path, "the file holds no tets")
    return vertices, tets


def _parse_rows(path: Path, lines: list[str], first_line: int, width: int, dtype, what: str) -> np.ndarray:
    """Parse whitespace rows fast; on failure find and name the first bad line."""
    try:
        out = np.array(" ".join(lines).split(), dtype=dtype)
        if out.size == len(lines) * width:
            out = out.reshape(len(lines), width)
            if dtype is np.float64 and not np.isfinite(out).all():
                raise ValueError
            return out
    except ValueError:
        pass
    for i, line in enumerate(lines):
        fields = line.split()
        try:
            ok = len(fields) == width and all(np.isfinite(dtype(f)) for f in fields)
        except (ValueError, OverflowError):
            ok = False
        if not ok:
            raise InputError(f"{path}:{first_line + i}", f"expected '{what}', found {line.strip()!r}")
    raise InputError(path, f"cannot parse the '{what}' lines")  # pragma: no cover


def read_volume(path: str | Path) -> tuple[FloatArray, IndexArray]:
    """Tetrahedral mesh from ``.tet`` or any volume format meshio reads (its ``tetra`` cells)."""
    path = _existing(path)
    if path.suffix.lower() in TET_SUFFIXES:
        return read_tet(path)
    import meshio

    try:
        mesh = meshio.read(path)
    except Exception as exc:
        raise InputError(path, f"cannot read as a volume mesh ({exc})") from exc
    blocks = [c.data for c in mesh.cells if c.type == "tetra"]
    if not blocks:
        kinds = ", ".join(sorted({c.type for c in mesh.cells})) or "none"
        raise InputError(path, f"the file holds no tetrahedra (cell types: {kinds})")
    return np.asarray(mesh.points[:, :3], dtype=np.float64), np.concatenate(blocks).astype(np.int64)


def _shape_of(line: str) -> str:
    """What a bad line of an auxiliary file looks like, without its content (a struts file named by mistake may
    be anything, the environment of a process included): its number of fields and how many are numbers."""
    fields = line.replace(",", " ").split()
    numbers = 0
    for f in fields:
        try:
            numbers += np.isfinite(float(f))
        except ValueError:
            pass
    return f"{len(fields)} field(s), {numbers} of them finite numbers"


def read_segments(path: str | Path) -> FloatArray:
    """Skeleton segments ``(k, 2, 3) float64`` from a segments text file or a polyline OBJ.

    A segments file has one ``x0 y0 z0 x1 y1 z1`` line per segment; blank lines and ``#`` comments
    are skipped and commas count as spaces.  An ``.obj`` file is read as a polyline OBJ: ``v x y z``
    vertices and ``l i j [k ...]`` lines (1-based, negative = relative), each polyline giving one
    segment per consecutive pair of vertices.
    """
    path = _existing(path)
    if path.suffix.lower() == ".obj":
        return read_polyline_obj(path)
    numbers = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        text = line.split("#", 1)[0].replace(",", " ").strip()
        if not text:
            continue
        try:
            values = [float(v) for v in text.split()]
        except ValueError:
            values = []
        if len(values) != 6 or not np.isfinite(values).all():
            raise InputError(f"{path}:{lineno}", f"expected 'x0 y0 z0 x1 y1 z1', found {_shape_of(text)}")
        numbers.append(values)
    if not numbers:
        raise InputError(path, "the file holds no segments")
    return np.asarray(numbers, dtype=np.float64).reshape(-1, 2, 3)


def read_polyline_obj(path: str | Path) -> FloatArray:
    """Segments ``(k, 2, 3) float64`` from the ``v`` and ``l`` records of an OBJ file."""
    path = _existing(path)
    vertices: list[list[float]] = []
    pairs: list[tuple[int, int, int]] = []  # (a, b, line number), 0-based after resolution
    for lineno, line in enumerate(path.read_text(errors="replace").splitlines(), start=1):
        fields = line.split("#", 1)[0].split()
        if not fields:
            continue
        if fields[0] == "v":
            try:
                xyz = [float(v) for v in fields[1:4]]
            except ValueError:
                xyz = []
            if len(xyz) != 3 or not np.isfinite(xyz).all():
                raise InputError(f"{path}:{lineno}", f"expected 'v x y z', found {_shape_of(line)}")
            vertices.append(xyz)
        elif fields[0] == "l":
            try:
                ids = [int(f.split("/")[0]) for f in fields[1:]]
            except ValueError:
                ids = []
            if len(ids) < 2:
                raise InputError(f"{path}:{lineno}", f"expected 'l i j ...', found {_shape_of(line)}")
            n = len(vertices)
            ids = [i - 1 if i > 0 else n + i for i in ids]
            if min(ids) < 0 or max(ids) >= n:
                raise InputError(f"{path}:{lineno}", f"vertex index out of range 1..{n}")
            pairs.extend((a, b, lineno) for a, b in zip(ids[:-1], ids[1:]))
    if not pairs:
        raise InputError(path, "the file holds no polyline ('l') records")
    v = np.asarray(vertices, dtype=np.float64)
    ab = np.asarray(pairs, dtype=np.int64)[:, :2]
    return v[ab]


def check_segments(path: str | Path, segments: FloatArray) -> FloatArray:
    """Segments with zero length removed; raises InputError if nothing is left."""
    lengths = np.linalg.norm(segments[:, 1] - segments[:, 0], axis=1)
    keep = lengths > 1e-12 * max(1.0, float(np.abs(segments).max()))
    if not keep.any():
        raise InputError(path, "all segments have zero length")
    return segments[keep]


# -------------------------------------------------------------------------------- point clouds

def read_points(path: str | Path) -> tuple[FloatArray, FloatArray | None]:
    """Point cloud from .xyz/.pcd/.ply: ``points (n, 3) float64`` and ``normals (n, 3) float64`` or None.

    Normals are returned as stored (not normalised) when the file has them: the ``nx ny nz``
    columns of an .xyz file, the ``normal_x normal_y normal_z`` fields of a PCD, the ``nx ny nz``
    vertex properties of a PLY. A PLY's faces, if any, are ignored.
    """
    path = _existing(path)
    readers = {".xyz": _read_xyz, ".pcd": _read_pcd, ".ply": _read_ply_points}
    if path.suffix.lower() not in readers:
        raise InputError(path, f"unknown point cloud format {path.suffix!r}; expected one of "
                               f"{', '.join(POINT_SUFFIXES)}")
    try:
        points, normals = readers[path.suffix.lower()](path)
    except OSError as exc:
        raise InputError(path, f"cannot read the file ({exc.strerror or exc})") from None
    if len(points) == 0:
        raise InputError(path, "the file holds no points")
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise InputError(path, f"{int(bad.sum())} points have NaN or infinite coordinates "
                               f"(first: point {int(np.flatnonzero(bad)[0]) + 1}); remove them")
    return points, normals


def _read_xyz(path: Path) -> tuple[FloatArray, FloatArray | None]:
    """``x y z [nx ny nz]`` rows, whitespace or comma separated, ``#`` comments, blank lines skipped."""
    try:
        text = path.read_text()
    except UnicodeDecodeError:
        raise InputError(path, "not a text file; an .xyz point cloud has 'x y z [nx ny nz]' lines") from None
    rows, numbers = [], []
    for lineno, line in enumerate(text.splitlines(), start=1):
        data = line.split("#", 1)[0].replace(",", " ").strip()
        if data:
            rows.append(lineno)
            numbers.append(data)
    if not rows:
        return np.empty((0, 3)), None
    width = len(numbers[0].split())
    what = "x y z nx ny nz" if width == 6 else "x y z"
    if width not in (3, 6):
        raise InputError(f"{path}:{rows[0]}", f"expected 'x y z' or 'x y z nx ny nz', found {numbers[0]!r}")
    try:
        values = np.array(" ".join(numbers).split(), dtype=np.float64)
        ok = values.size == len(rows) * width
    except ValueError:
        ok = False
    if ok:
        values = values.reshape(len(rows), width)
        bad = np.flatnonzero(~np.isfinite(values).all(axis=1))
        if len(bad):
            more = f" (and {len(bad) - 1} more lines)" if len(bad) > 1 else ""
            raise InputError(f"{path}:{rows[bad[0]]}", f"NaN or infinite value in {numbers[bad[0]]!r}{more}")
    else:
        for lineno, data in zip(rows, numbers):
            fields = data.split()
            try:
                good = len(fields) == width and np.isfinite([float(f) for f in fields]).all()
            except ValueError:
                good = False
            if not good:
                raise InputError(f"{path}:{lineno}", f"expected '{what}' like the first line, found {data!r}")
        raise InputError(path, f"cannot parse the '{what}' lines")  # pragma: no cover
    return values[:, :3].copy(), (values[:, 3:].copy() if width == 6 else None)


def _pcd_header(path: Path, raw: bytes) -> tuple[list[tuple[str, str, int, int]], int, str, int, int]:
    """A PCD header: fields ``(name, TYPE, SIZE, COUNT)``, point count, DATA mode, data offset and line."""
    header: dict[str, list[str]] = {}
    offset, lineno = 0, 0
    while "DATA" not in header:
        end = raw.find(b"\n", offset)
        if end < 0:
            raise InputError(path, "not a PCD file: no 'DATA' line in the header")
        lineno += 1
        line = raw[offset:end].decode("ascii", errors="replace").split("#", 1)[0].split()
        offset = end + 1
        if line:
            header[line[0].upper()] = line[1:]
    names = header.get("FIELDS", [])
    try:
        sizes = [int(v) for v in header.get("SIZE", [])]
        counts = [int(v) for v in header.get("COUNT", ["1"] * len(names))]
        n = (int(header["POINTS"][0]) if "POINTS" in header
             else int(header["WIDTH"][0]) * int(header.get("HEIGHT", ["1"])[0]))
    except (KeyError, IndexError, ValueError):
        raise InputError(path, "not a usable PCD header: SIZE, COUNT and POINTS (or WIDTH and HEIGHT) "
                               "must be integers") from None
    types = [v.upper() for v in header.get("TYPE", [])]
    if not {"x", "y", "z"} <= set(names) or not len(names) == len(sizes) == len(types) == len(counts):
        raise InputError(path, "not a usable PCD header: need FIELDS with x y z and matching SIZE, TYPE, COUNT")
    mode = (header["DATA"] or ["?"])[0].lower()
    return list(zip(names, types, sizes, counts)), n, mode, offset, lineno


def _read_pcd(path: Path) -> tuple[FloatArray, FloatArray | None]:
    """Point Cloud Library PCD, ``DATA ascii`` or ``DATA binary`` (not ``binary_compressed``)."""
    raw = path.read_bytes()
    fields, n, mode, offset, lineno = _pcd_header(path, raw)
    names = [f[0] for f in fields]
    width = sum(f[3] for f in fields)
    column = {name: sum(f[3] for f in fields[:i]) for i, name in enumerate(names)}
    if mode == "ascii":
        lines = [(lineno + 1 + i, line) for i, line in
                 enumerate(raw[offset:].decode("ascii", errors="replace").splitlines()) if line.strip()][:n]
        if len(lines) < n:
            raise InputError(path, f"the header promises {n} points but only {len(lines)} data lines follow")
        data = np.empty((n, width))
        for row, (number, line) in enumerate(lines):
            try:
                data[row] = [float(v) for v in line.split()]
            except ValueError:
                raise InputError(f"{path}:{number}", f"expected {width} numbers ({' '.join(names)}), "
                                                     f"found {line.strip()!r}") from None
        get = {name: data[:, column[name]] for name in names}
    elif mode == "binary":
        try:
            dtype = np.dtype([(f"f{i}", _PCD_TYPES[(t, size)], (c,)) for i, (_, t, size, c) in enumerate(fields)])
        except KeyError:
            raise InputError(path, f"unsupported PCD field TYPE/SIZE {[f[1:3] for f in fields]}") from None
        if len(raw) - offset < n * dtype.itemsize:
            raise InputError(path, f"the header promises {n} points ({n * dtype.itemsize} bytes) but only "
                                   f"{len(raw) - offset} bytes follow")
        records = np.frombuffer(raw, dtype=dtype, count=n, offset=offset)
        get = {name: records[f"f{i}"][:, 0].astype(np.float64) for i, name in enumerate(names)}
    else:
        raise InputError(path, f"PCD 'DATA {mode}' is not supported; save it as 'ascii' or 'binary'")
    points = np.stack([get["x"], get["y"], get["z"]], axis=1)
    keys = ("normal_x", "normal_y", "normal_z")
    return points, (np.stack([get[k] for k in keys], axis=1) if all(k in get for k in keys) else None)


def ply_face_count(path: str | Path) -> int | None:
    """Number of faces a PLY header declares (0 without a face element); None if it is not a PLY header."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(1 << 16)
    except OSError:
        return None
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        return None
    for line in head[:end].decode("ascii", errors="replace").splitlines():
        fields = line.split()
        if len(fields) == 3 and fields[0] == "element" and fields[1] == "face":
            return int(fields[2]) if fields[2].isdigit() else None
    return 0


def _read_ply_points(path: Path) -> tuple[FloatArray, FloatArray | None]:
    """Vertices (and ``nx ny nz`` properties) of a PLY file, ascii or binary, read with meshio."""
    import meshio

    if ply_face_count(path) is None:
        raise InputError(path, "not a PLY file (no 'ply ... end_header' header)")
    try:
        mesh = meshio.read(path, file_format="ply")
    except Exception as exc:  # meshio raises many types for corrupt files
        raise InputError(path, f"cannot read as a PLY point cloud ({exc})") from exc
    points = np.asarray(mesh.points, dtype=np.float64)[:, :3]
    data = mesh.point_data
    normals = (np.stack([np.asarray(data[k], dtype=np.float64).reshape(-1) for k in ("nx", "ny", "nz")], axis=1)
               if all(k in data for k in ("nx", "ny", "nz")) else None)
    return points, normals
