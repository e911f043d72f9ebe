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

#: Closed or open triangle meshes, read with trimesh.
SURFACE_SUFFIXES = (".stl", ".obj", ".ply", ".off")
#: Our own tetrahedral format (see :func:`read_tet`).
TET_SUFFIXES = (".tet",)
#: Volume formats read with meshio (anything with tetra cells).
VOLUME_SUFFIXES = (".msh", ".vtu", ".vtk", ".mesh", ".xdmf", ".med", ".inp", ".ele", ".node")


def _existing(path: str | Path) -> Path:
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such file")
    return path


def read_surface(path: str | Path) -> tuple[FloatArray, IndexArray]:
    """Triangle mesh from STL/OBJ/PLY/OFF: ``vertices (n, 3) float64``, ``faces (m, 3) int64``.

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
        raise InputError(path, "the file holds no triangles")
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
            raise InputError(f"{path}:{lineno}", f"expected 'x0 y0 z0 x1 y1 z1', found {line.strip()!r}")
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
                raise InputError(f"{path}:{lineno}", f"expected 'v x y z', found {line.strip()!r}")
            vertices.append(xyz)
        elif fields[0] == "l":
            try:
                ids = [int(f.split("/")[0]) for f in fields[1:]]
            except ValueError:
                ids = []
            if len(ids) < 2:
                raise InputError(f"{path}:{lineno}", f"expected 'l i j ...', found {line.strip()!r}")
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
