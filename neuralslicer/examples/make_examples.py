"""Generate the shipped example models (run once; outputs are committed next to this script).

    .venv/bin/python -m neuralslicer.examples.make_examples

Writes, each in its own folder with a ``model.yaml`` spec:

- ``bracket/``: a small closed L-bracket mesh with three bolt holes (genus 3, ~3k faces) and an
  FEA block (fixed against the wall, loaded at the free end): the fast demo model.
- ``lattice/``: a body-centred-cubic strut lattice (``struts``, segments text file).
- ``tubes/``: branching bent tubes as a convolution surface (``tubes``, polyline OBJ skeleton).
- ``shell/``: an open wavy vase surface thickened into a 2 mm shell (``shell``).
- ``hybrid/``: a closed base plate (``mesh``), an open arch (``shell``), a strut lattice
  (``struts``) and two tube loops (``tubes``) in one model, genus > 5.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

HERE = Path(__file__).resolve().parent


def _box_sdf(p: np.ndarray, lo, hi) -> np.ndarray:
    """Exact signed distance to an axis-aligned box."""
    c, h = (np.asarray(lo) + hi) / 2, (np.asarray(hi) - lo) / 2
    q = np.abs(p - c) - h
    return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)


def _cyl_sdf(p: np.ndarray, centre, axis: int, radius: float) -> np.ndarray:
    """Distance to an infinite cylinder along a coordinate axis (negative inside)."""
    other = [i for i in range(3) if i != axis]
    return np.linalg.norm(p[:, other] - np.asarray(centre)[other], axis=1) - radius


def bracket_mesh(voxel: float = 0.5, target_faces: int = 3000) -> trimesh.Trimesh:
    """L-bracket 60 x 40 x 40 mm, plates 6 mm, bolt holes: marching cubes + quadric decimation."""
    import pyvista as pv

    from neuralslicer.model.grid import level_set_mesh

    def sdf(p: np.ndarray) -> np.ndarray:
        """Signed distance of the bracket (plates minus bolt holes)."""
        base = _box_sdf(p, [0, 0, 0], [60, 40, 6])
        wall = _box_sdf(p, [0, 0, 0], [60, 6, 40])
        solid = np.minimum(base, wall)
        holes = np.minimum.reduce([_cyl_sdf(p, [15, 25, 0], 2, 4.0), _cyl_sdf(p, [45, 25, 0], 2, 4.0),
                                   _cyl_sdf(p, [30, 0, 26], 1, 5.0)])
        return np.maximum(solid, -holes)

    lo = np.array([-3.0, -3.0, -3.0])
    n = np.ceil((np.array([63.0, 43.0, 43.0]) - lo) / voxel).astype(int) + 1
    grid = np.stack(np.meshgrid(*[lo[i] + voxel * np.arange(n[i]) for i in range(3)], indexing="ij"), -1)
    values = sdf(grid.reshape(-1, 3)).reshape(tuple(n))
    v, f = level_set_mesh(values, lo, voxel)
    poly = pv.PolyData(v, np.hstack([np.full((len(f), 1), 3), f]).ravel())
    poly = poly.decimate(1.0 - target_faces / len(f), volume_preservation=True)
    faces = poly.faces.reshape(-1, 4)[:, 1:]
    mesh = trimesh.Trimesh(np.asarray(poly.points, dtype=np.float64), faces, process=True)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def bcc_lattice(cells: tuple[int, int, int], size: float, origin=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Segments ``(k, 2, 3)`` of a body-centred-cubic lattice: cube edges plus body diagonals."""
    nx, ny, nz = cells
    o = np.asarray(origin, dtype=np.float64)
    idx = np.stack(np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), np.arange(nz + 1), indexing="ij"), -1).reshape(-1, 3)
    segs = []
    for axis in range(3):
        step = np.eye(3, dtype=int)[axis]
        a = idx[idx[:, axis] < cells[axis]]
        segs.append(np.stack([a, a + step], 1) * size)
    cell = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"), -1).reshape(-1, 3)
    centre = (cell + 0.5) * size
    for corner in np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 0, 1], [1, 0, 1], [0, 1, 1], [1, 1, 1]]):
        segs.append(np.stack([centre, (cell + corner) * size], 1))
    return np.concatenate(segs).astype(np.float64) + o


def write_segments(path: Path, segments: np.ndarray, comment: str) -> None:
    """Segments text file, one ``x0 y0 z0 x1 y1 z1`` line per segment."""
    lines = [f"# {comment}", "# x0 y0 z0 x1 y1 z1"]
    lines += [" ".join(f"{v:.6g}" for v in s.ravel()) for s in segments]
    path.write_text("\n".join(lines) + "\n")


def write_polyline_obj(path: Path, polylines: list[np.ndarray], comment: str) -> None:
    """Polyline OBJ: ``v`` records and one ``l`` record per polyline."""
    lines, offset = [f"# {comment}"], 0
    for poly in polylines:
        lines += [f"v {x:.6g} {y:.6g} {z:.6g}" for x, y, z in poly]
        lines.append("l " + " ".join(str(offset + i + 1) for i in range(len(poly))))
        offset += len(poly)
    path.write_text("\n".join(lines) + "\n")


def tube_skeleton() -> list[np.ndarray]:
    """Bent branching tubes rising from the platform (mm)."""
    t = np.linspace(0.0, 1.0, 25)
    trunk = np.stack([12 * np.sin(np.pi * t), 6 * np.sin(2 * np.pi * t), 60 * t], 1)
    s = np.linspace(0.0, 1.0, 15)
    start = trunk[12]
    branch1 = start + np.stack([25 * s, -5 * s, 25 * s ** 2], 1)
    branch2 = start + np.stack([-20 * s, 12 * s, 18 * s - 10 * s ** 2], 1)
    return [trunk, branch1, branch2]


def wavy_vase(radius: float = 20.0, height: float = 40.0, sections: int = 72, rings: int = 24) -> trimesh.Trimesh:
    """Open surface (no top, no bottom) of a wavy vase, z up from 0."""
    th = np.linspace(0, 2 * np.pi, sections, endpoint=False)
    z = np.linspace(0, height, rings + 1)
    r = radius * (1 + 0.25 * np.sin(np.pi * z / height)[:, None] + 0.05 * np.cos(5 * th)[None, :])
    v = np.stack([(r * np.cos(th)).ravel(), (r * np.sin(th)).ravel(), np.repeat(z, sections)], 1)
    i = np.arange(sections)
    j = (i + 1) % sections
    faces = []
    for k in range(rings):
        a, b = k * sections + i, k * sections + j
        c, d = (k + 1) * sections + j, (k + 1) * sections + i
        faces += [np.stack([a, b, c], 1), np.stack([a, c, d], 1)]
    return trimesh.Trimesh(v, np.concatenate(faces), process=False)


def arch_surface(span: float = 50.0, depth: float = 20.0, rise: float = 25.0, n: int = 40) -> trimesh.Trimesh:
    """Open half-cylinder arch over x in [0, span], y in [0, depth], feet at z = 0."""
    th = np.linspace(0, np.pi, n)
    x = span / 2 - span / 2 * np.cos(th)
    z = rise * np.sin(th)
    ys = np.linspace(0, depth, 6)
    v = np.stack([np.tile(x, len(ys)), np.repeat(ys, n), np.tile(z, len(ys))], 1)
    faces = []
    for k in range(len(ys) - 1):
        a = k * n + np.arange(n - 1)
        faces += [np.stack([a, a + 1, a + n + 1], 1), np.stack([a, a + n + 1, a + n], 1)]
    return trimesh.Trimesh(v, np.concatenate(faces), process=False)


def write_bracket(d: Path) -> None:
    """The bracket example: its model files and model.yaml in folder d."""
    bracket_mesh().export(d / "bracket.stl")
    (d / "model.yaml").write_text("""# L-bracket, fixed against a wall (the face y = 0), loaded down at its free end.
up: z
components:
  - type: mesh
    file: bracket.stl
fea:
  material: {youngs_modulus_mpa: 2000, poisson_ratio: 0.3}
  supports:
    - box: [[-1, -1, -1], [61, 0.5, 41]]
  loads:
    - box: [[-1, 38, -1], [61, 41, 7]]
      force_n: [0, 0, -50]
""")


def write_lattice(d: Path) -> None:
    """The lattice example: its model files and model.yaml in folder d."""
    write_segments(d / "lattice.txt", bcc_lattice((3, 3, 3), 10.0), "BCC lattice, 3x3x3 cells of 10 mm")
    (d / "model.yaml").write_text("""# Body-centred-cubic strut lattice: capsules of radius 1 mm.
up: z
components:
  - type: struts
    file: lattice.txt
    radius: 1.0
""")


def write_tubes(d: Path) -> None:
    """The tubes example: its model files and model.yaml in folder d."""
    write_polyline_obj(d / "skeleton.obj", tube_skeleton(), "skeleton of branching tubes (mm)")
    (d / "model.yaml").write_text("""# Branching tubes: convolution surface (Cauchy kernel) of a polyline skeleton.
up: z
components:
  - type: tubes
    file: skeleton.obj
    radius: 3.0        # tube radius around a long straight piece, mm
    c: 0.333           # kernel sharpness 1/mm (default 1/radius)
""")


def write_shell(d: Path) -> None:
    """The shell example: its model files and model.yaml in folder d."""
    wavy_vase().export(d / "vase_surface.stl")
    (d / "model.yaml").write_text("""# An open wavy vase surface thickened into a 2 mm shell.
up: z
components:
  - type: shell
    file: vase_surface.stl
    thickness: 2.0
""")


def write_hybrid(d: Path) -> None:
    """The hybrid example: its model files and model.yaml in folder d."""
    trimesh.creation.box(bounds=[[-5, -5, 0], [75, 35, 5]]).export(d / "base.stl")
    arch = arch_surface()
    arch.apply_translation([0, 5, 4])
    arch.export(d / "arch.stl")
    write_segments(d / "lattice.txt", bcc_lattice((2, 1, 2), 10.0, origin=(52.0, 10.0, 4.0)),
                   "BCC lattice block, 2x1x2 cells of 10 mm, standing on the base")
    loops = []
    for cx in (12.0, 38.0):
        a = np.linspace(0, 2 * np.pi, 25)
        loops.append(np.stack([cx + 9 * np.cos(a), 30 + 0 * a, 13 + 9 * np.sin(a)], 1))
    write_polyline_obj(d / "loops.obj", loops, "two vertical tube loops behind the arch")
    (d / "model.yaml").write_text("""# Hybrid model: closed mesh + open-surface shell + struts + convolution tubes (genus > 5).
up: z
surface_voxel: 0.5
components:
  - type: mesh
    file: base.stl
  - type: shell
    file: arch.stl
    thickness: 2.5
  - type: struts
    file: lattice.txt
    radius: 1.2
  - type: tubes
    file: loops.obj
    radius: 2.0
""")


EXAMPLES = {"bracket": write_bracket, "lattice": write_lattice, "tubes": write_tubes, "shell": write_shell,
            "hybrid": write_hybrid}


def main() -> None:
    """Write every example folder."""
    for name, write in EXAMPLES.items():
        d = HERE / name
        d.mkdir(exist_ok=True)
        write(d)


if __name__ == "__main__":
    main()
