"""Generate the shipped example models (run once; outputs are committed next to this script).

    .venv/bin/python -m neuralslicer.examples.make_examples [NAME ...]

Writes, each in its own folder with a ``model.yaml`` spec:

- ``bracket/``: a small closed L-bracket mesh with three bolt holes (genus 3, ~3k faces) and an
  FEA block (fixed against the wall, loaded at the free end): the fast demo model.
- ``bridge/``: a deck over an arch opening between two feet, in 3-point bending (supports under both feet,
  a load on top in the middle): the paper's Bridge test case for strength.
- ``lattice/``: a body-centred-cubic strut lattice (``struts``, segments text file).
- ``tubes/``: branching bent tubes as a convolution surface (``tubes``, polyline OBJ skeleton).
- ``shell/``: an open wavy vase surface thickened into a 2 mm shell (``shell``).
- ``hybrid/``: a closed base plate (``mesh``), an open arch (``shell``), a strut lattice
  (``struts``) and two tube loops (``tubes``) in one model, genus > 5.
- ``points/``: a point cloud of a small knob block with a through hole (``points``): 3500 points
  with normals (``part.xyz``, used by ``spec.yaml``) and a noisy 3000-point "scan" without normals
  (``part_scan.pcd``, to slice directly).
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


def sdf_mesh(sdf, lo, hi, voxel: float, target_faces: int) -> trimesh.Trimesh:
    """A closed mesh of ``sdf <= 0`` in the box lo..hi: marching cubes at ``voxel`` + quadric decimation."""
    import pyvista as pv

    from neuralslicer.model.grid import level_set_mesh

    lo = np.asarray(lo, np.float64)
    n = np.ceil((np.asarray(hi, np.float64) - lo) / voxel).astype(int) + 1
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


def bracket_mesh(voxel: float = 0.5, target_faces: int = 3000) -> trimesh.Trimesh:
    """L-bracket 60 x 40 x 40 mm, plates 6 mm, bolt holes: marching cubes + quadric decimation."""

    def sdf(p: np.ndarray) -> np.ndarray:
        """Signed distance of the bracket (plates minus bolt holes)."""
        base = _box_sdf(p, [0, 0, 0], [60, 40, 6])
        wall = _box_sdf(p, [0, 0, 0], [60, 6, 40])
        solid = np.minimum(base, wall)
        holes = np.minimum.reduce([_cyl_sdf(p, [15, 25, 0], 2, 4.0), _cyl_sdf(p, [45, 25, 0], 2, 4.0),
                                   _cyl_sdf(p, [30, 0, 26], 1, 5.0)])
        return np.maximum(solid, -holes)

    return sdf_mesh(sdf, [-3.0, -3.0, -3.0], [63.0, 43.0, 43.0], voxel, target_faces)


def bridge_mesh(voxel: float = 0.5, target_faces: int = 4000) -> trimesh.Trimesh:
    """Bridge 120 x 20 x 30 mm: a deck over a half-elliptic arch opening (semi-axes 50 x 16 mm) between two feet."""

    def sdf(p: np.ndarray) -> np.ndarray:
        """Signed distance (exact outside the arch) of the box minus the elliptic arch opening."""
        box = _box_sdf(p, [0, 0, 0], [120, 20, 30])
        q = (p[:, [0, 2]] - [60.0, 0.0]) / [50.0, 16.0]
        arch = (np.linalg.norm(q, axis=1) - 1.0) * 16.0          # an approximate distance, exact on the crown
        return np.maximum(box, -arch)

    return sdf_mesh(sdf, [-3.0, -3.0, -3.0], [123.0, 23.0, 33.0], voxel, target_faces)


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


def write_bridge(d: Path) -> None:
    """The 3-point-bending example (the paper's Bridge test): its mesh and model.yaml in folder d."""
    bridge_mesh().export(d / "bridge.stl")
    (d / "model.yaml").write_text("""# Bridge in 3-point bending (the paper's Bridge test case): a 120 x 20 x 30 mm deck over an arch opening,
# on supports under both feet (held left, a roller right), pressed down on top in the middle.
up: z
components:
  - type: mesh
    file: bridge.stl
fea:
  material: {youngs_modulus_mpa: 2000, poisson_ratio: 0.3}
  supports:
    - box: [[-1, -1, -1], [6, 21, 0.5]]
    - box: [[114, -1, -1], [121, 21, 0.5]]
      fix: [false, false, true]
  loads:
    - box: [[55, -1, 29.5], [65, 21, 31]]
      force_n: [0, 0, -300]
""")
    (d / "config.yaml").write_text("""# The paper's Bridge test: strength reinforcement only (sr), with the print head terms (gc, ca) so that the
# program is collision-free; the arch opening then needs supports, as the paper's Bridge had (PVA).
#   neuralslicer slice neuralslicer/examples/bridge/model.yaml --config neuralslicer/examples/bridge/config.yaml --verify
objectives: [sr, gc, ca]
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


def knob_block_sdf(p: np.ndarray) -> np.ndarray:
    """Signed distance (approximate near blends) of a 30 x 20 x 10 mm rounded block with a knob
    on top and a chamfered vertical through hole, z up from 0."""
    q = np.abs(p - [15.0, 10.0, 5.0]) - ([15.0, 10.0, 5.0] - np.float64(2.0))
    block = np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0) - 2.0
    knob = np.linalg.norm(p - [9.0, 10.0, 8.0], axis=1) - 6.0
    k = 2.0  # polynomial smooth union of block and knob
    h = np.clip(0.5 + 0.5 * (knob - block) / k, 0, 1)
    body = knob * (1 - h) + block * h - k * h * (1 - h)
    hole = _cyl_sdf(p, [22.0, 10.0, 0.0], 2, 3.5)
    k = 1.0  # smooth subtraction of the hole
    h = np.clip(0.5 - 0.5 * (body + hole) / k, 0, 1)
    return body * (1 - h) - hole * h + k * h * (1 - h)


def sample_sdf_surface(sdf, lo, hi, count: int, seed: int, voxel: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points ``(n, 3)`` uniformly (by area) on ``sdf = 0`` and their unit normals ``(n, 3)``."""
    from neuralslicer.model.grid import level_set_mesh

    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    n = np.ceil((hi - lo) / voxel).astype(int) + 1
    grid = np.stack(np.meshgrid(*[lo[i] + voxel * np.arange(n[i]) for i in range(3)], indexing="ij"), -1)
    v, f = level_set_mesh(sdf(grid.reshape(-1, 3)).reshape(tuple(n)), lo, voxel)
    tri = v[f]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    rng = np.random.default_rng(seed)
    face = rng.choice(len(f), size=count, p=area / area.sum())
    u, w = rng.random((2, count))
    flip = u + w > 1
    u, w = np.where(flip, 1 - u, u), np.where(flip, 1 - w, w)
    t = tri[face]
    p = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + w[:, None] * (t[:, 2] - t[:, 0])

    def gradient(x: np.ndarray) -> np.ndarray:
        """Central-difference gradient of the sdf."""
        e = 1e-4
        return np.stack([(sdf(x + e * d) - sdf(x - e * d)) / (2 * e) for d in np.eye(3)], axis=1)

    for _ in range(3):  # Newton steps onto the zero level
        g = gradient(p)
        p = p - (sdf(p) / np.maximum(np.einsum("ij,ij->i", g, g), 1e-12))[:, None] * g
    g = gradient(p)
    return p, g / np.linalg.norm(g, axis=1, keepdims=True)


def write_points(d: Path) -> None:
    """The point-cloud example: part.xyz (with normals), part_scan.pcd (noisy, no normals), spec.yaml."""
    lo, hi = [-1.0, -1.0, -1.0], [31.0, 21.0, 16.0]
    p, n = sample_sdf_surface(knob_block_sdf, lo, hi, 3500, seed=1)
    lines = ["# knob block with a through hole, 30 x 20 x 14 mm, z up: 3500 points with outward normals",
             "# x y z nx ny nz (mm)"]
    lines += [f"{a:.3f} {b:.3f} {c:.3f} {u:.4f} {v:.4f} {w:.4f}" for (a, b, c), (u, v, w) in zip(p, n)]
    (d / "part.xyz").write_text("\n".join(lines) + "\n")
    p, _ = sample_sdf_surface(knob_block_sdf, lo, hi, 3000, seed=2)
    p = p + np.random.default_rng(3).normal(scale=0.03, size=p.shape)
    header = ["# the same knob block as a noisy scan (sigma 0.03 mm), no normals", "VERSION .7",
              "FIELDS x y z", "SIZE 4 4 4", "TYPE F F F", "COUNT 1 1 1", f"WIDTH {len(p)}", "HEIGHT 1",
              "VIEWPOINT 0 0 0 1 0 0 0", f"POINTS {len(p)}", "DATA ascii"]
    (d / "part_scan.pcd").write_text("\n".join(header + [f"{a:.3f} {b:.3f} {c:.3f}" for a, b, c in p]) + "\n")
    (d / "spec.yaml").write_text("""# A point cloud of a knob block with a through hole, reconstructed into a closed solid
# (normals -> winding number -> marching cubes -> projection; see neuralslicer/model/points.py).
# The normal-free scan slices directly too: neuralslicer slice part_scan.pcd --out runs/scan
up: z
components:
  - type: points
    file: part.xyz        # x y z nx ny nz per line
    normals: auto         # the file's normals (estimate: PCA + spanning-tree orientation)
    resolution: 96        # grid cells along the longest side for the reconstruction
""")


EXAMPLES = {"bracket": write_bracket, "bridge": write_bridge, "lattice": write_lattice, "tubes": write_tubes,
            "shell": write_shell, "hybrid": write_hybrid, "points": write_points}


def main(names: list[str] | None = None) -> None:
    """Write the named example folders (all without names)."""
    for name in names or list(EXAMPLES):
        d = HERE / name
        d.mkdir(exist_ok=True)
        EXAMPLES[name](d)


if __name__ == "__main__":
    import sys

    main(sys.argv[1:])
