"""Readers (.tet, meshio volumes, segments, polyline OBJ) and the shipped ring.tet."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from neuralslicer.data import DATA_DIR
from neuralslicer.errors import InputError
from neuralslicer.model import implicit_solid, read_segments, read_tet, read_volume, spec_for_file
from neuralslicer.topology import genus, surface_topology, tet_boundary_genus

RING = DATA_DIR / "ring.tet"

CUBE_V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 0, 1], [1, 0, 1], [0, 1, 1], [1, 1, 1]], float)
# Kuhn subdivision of the unit cube into 6 tets along the 0-7 diagonal
CUBE_T = np.array([[0, 1, 3, 7], [0, 1, 5, 7], [0, 2, 3, 7], [0, 2, 6, 7], [0, 4, 5, 7], [0, 4, 6, 7]])


def write_tet(path: Path, V: np.ndarray, T: np.ndarray, header: tuple[int, int] | None = None) -> Path:
    """Write the .tet text format."""
    n, m = header or (len(V), len(T))
    lines = [f"{n} vertices", f"{m} tets"] + [" ".join(map(str, v)) for v in V]
    lines += ["4 " + " ".join(map(str, t)) for t in T]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_read_tet_cube_and_signed_distance(tmp_path: Path) -> None:
    path = write_tet(tmp_path / "cube.tet", CUBE_V * 10, CUBE_T)
    V, T = read_tet(path)
    assert V.dtype == np.float64 and T.dtype == np.int64 and np.array_equal(T, CUBE_T)
    solid = implicit_solid(spec_for_file(path))
    x = np.array([[5.0, 5.0, 5.0], [5.0, 5.0, 12.0], [1.0, 5.0, 5.0]])
    assert np.allclose(solid.H(x), [-5.0, 2.0, -1.0])
    assert solid.volume() == pytest.approx(1000.0)
    assert genus(solid.surface().faces) == 0


def test_read_tet_one_based_and_meshio(tmp_path: Path) -> None:
    import meshio

    V1, T1 = read_tet(write_tet(tmp_path / "one.tet", CUBE_V, CUBE_T + 1))
    assert np.array_equal(T1, CUBE_T)
    meshio.write(tmp_path / "cube.vtu", meshio.Mesh(CUBE_V, [("tetra", CUBE_T)]))
    V2, T2 = read_volume(tmp_path / "cube.vtu")
    assert np.allclose(V2, CUBE_V) and np.array_equal(T2, CUBE_T)
    meshio.write(tmp_path / "tri.vtu", meshio.Mesh(CUBE_V, [("triangle", [[0, 1, 2]])]))
    with pytest.raises(InputError, match="no tetrahedra"):
        read_volume(tmp_path / "tri.vtu")


@pytest.mark.parametrize("row, value, line", [(0, 20, 11), (3, -1, 14)])
def test_read_tet_bad_indices(tmp_path: Path, row: int, value: int, line: int) -> None:
    T = CUBE_T.copy()
    T[row, 2] = value
    path = write_tet(tmp_path / "bad.tet", CUBE_V, T)
    with pytest.raises(InputError, match=rf"bad\.tet:{line}: vertex index out of range 0\.\.7"):
        read_tet(path)


def test_read_tet_malformed_lines(tmp_path: Path) -> None:
    path = write_tet(tmp_path / "nan.tet", CUBE_V, CUBE_T)
    lines = path.read_text().splitlines()
    lines[4] = "1 nan 0"
    path.write_text("\n".join(lines))
    with pytest.raises(InputError, match=r"nan\.tet:5: expected 'x y z'"):
        read_tet(path)
    short = write_tet(tmp_path / "short.tet", CUBE_V, CUBE_T, header=(8, 9))
    with pytest.raises(InputError, match="header promises 8 vertices and 9 tets"):
        read_tet(short)
    (tmp_path / "nohead.tet").write_text("hello\n")
    with pytest.raises(InputError, match=r"nohead\.tet:1"):
        read_tet(tmp_path / "nohead.tet")
    with pytest.raises(InputError, match="no such file"):
        read_tet(tmp_path / "missing.tet")


def test_segments_and_polyline_obj(tmp_path: Path) -> None:
    (tmp_path / "s.txt").write_text("# skeleton\n0 0 0 1 0 0\n1,0,0, 1,1,0 # comma separated\n")
    seg = read_segments(tmp_path / "s.txt")
    assert seg.shape == (2, 2, 3) and np.allclose(seg[1], [[1, 0, 0], [1, 1, 0]])
    (tmp_path / "p.obj").write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 1\nl 1 2 3\nl -1 -4\n")
    seg = read_segments(tmp_path / "p.obj")
    assert seg.shape == (3, 2, 3) and np.allclose(seg[2], [[0, 1, 1], [0, 0, 0]])
    (tmp_path / "q.obj").write_text("v 0 0 0\nl 1 5\n")
    with pytest.raises(InputError, match=r"q\.obj:2: vertex index out of range"):
        read_segments(tmp_path / "q.obj")


@pytest.fixture(scope="module")
def ring():
    """The shipped ring.tet, y-up."""
    return implicit_solid(spec_for_file(RING, up="y"))


def test_ring_tet_loads_in_build_frame(ring) -> None:
    V, T = read_tet(RING)
    assert V.shape == (8150, 3) and T.shape == (40064, 4)
    comp = ring.components[0]
    # y-up: the input's y extent becomes the build z extent
    assert np.allclose(np.ptp(comp.vertices, axis=0), np.ptp(V, axis=0)[[0, 2, 1]])
    centroids = comp.vertices[comp.tets].mean(axis=1)
    assert np.all(ring.H(centroids) < 0)
    assert ring.platform_z == pytest.approx(comp.vertices[:, 2].min())
    assert tet_boundary_genus(comp.tets) == 1 and genus(ring.surface().faces) == 1
    # a point at the ring's centre (the hole) is outside
    centre = 0.5 * (ring.bounds[0] + ring.bounds[1])
    assert ring.H(centre[None])[0] > 0


def test_topology_counts() -> None:
    import trimesh

    sphere = trimesh.creation.icosphere(2)
    torus = trimesh.creation.torus(5, 1)
    both = np.concatenate([sphere.faces, torus.faces + len(sphere.vertices)])
    topo = surface_topology(both)
    assert sorted(topo.genus.tolist()) == [0, 1] and topo.closed
    # two tori joined into nothing: genus adds up; an annulus has two boundary loops
    assert genus(np.concatenate([torus.faces, torus.faces + len(torus.vertices)])) == 2
    annulus = trimesh.creation.annulus(1, 2, 1)
    open_top = annulus.faces[annulus.face_normals[:, 2] < 0.99]  # drop the top ring faces
    t = surface_topology(open_top)
    assert t.boundary_loops.tolist() == [2] and t.genus.tolist() == [0]


def test_the_sample_models_ship_with_the_package_and_an_unknown_name_is_a_clear_error() -> None:
    """ring.tet resolves inside the package (no ../shared needed); an unknown name lists the shipped ones."""
    from neuralslicer.data import sample

    assert sample("ring.tet") == DATA_DIR / "ring.tet" and read_tet(sample("ring.tet"))[1].shape == (40064, 4)
    with pytest.raises(FileNotFoundError, match="topopt_new4.tet"):
        sample("missing.tet")


def test_no_tracked_file_names_a_machine_path_or_the_shared_data_folder() -> None:
    """Every tracked text file (code, tests, benchmarks and their results, docs, the studies' run records,
    deployments) names paths relative to the repository or as placeholders: no /work, /home or /tmp path of the
    machine it was written on, and no shared data folder outside the package."""
    import subprocess

    repo = Path(__file__).resolve().parents[2]
    # split, so that this file does not match itself
    patterns = ("/" + "work/", "/" + "home/", "/" + "tmp/", "shared" + "/data")
    files = subprocess.run(["git", "ls-files", "-z"], cwd=repo, capture_output=True, check=True).stdout
    bad = []
    for name in files.decode().split("\0"):
        path = repo / name
        if not name or not path.is_file():
            continue
        data = path.read_bytes()
        if b"\0" in data[:8192]:          # binary (figures, meshes, archives): no text paths to check
            continue
        bad += [f"{name}:{i}" for i, line in enumerate(data.decode(errors="replace").splitlines(), 1)
                if any(p in line for p in patterns)]
    assert not bad, bad


def _with_unit(src: Path, dst: Path, unit: str) -> Path:
    """A copy of a 3MF whose model part declares ``unit``."""
    import zipfile

    with zipfile.ZipFile(src) as a, zipfile.ZipFile(dst, "w") as b:
        for item in a.infolist():
            data = a.read(item.filename)
            if item.filename.endswith(".model"):
                data = data.replace(b'unit="millimeter"', f'unit="{unit}"'.encode(), 1)
            b.writestr(item, data)
    return dst


def test_3mf_written_by_trimesh_reads_as_the_stl_placed_by_its_build_item(tmp_path: Path) -> None:
    import trimesh

    from neuralslicer.model.io import read_surface, threemf_units
    from neuralslicer.model.spec import load_model

    stl = DATA_DIR / "bunny_closed_low_res.stl"
    mesh = trimesh.load(stl)
    scene = trimesh.Scene()
    scene.add_geometry(mesh, transform=trimesh.transformations.translation_matrix([100.0, -20.0, 5.0]))
    path = tmp_path / "bracket.3mf"
    scene.export(path)
    V, F = read_surface(path)
    V0, F0 = read_surface(stl)
    # the same triangles, moved by the build item's transform (a 3MF places every item in the build frame)
    assert V.dtype == np.float64 and F.dtype == np.int64 and len(F) == len(F0) > 100
    assert np.allclose(np.sort(V0 + [100.0, -20.0, 5.0], axis=0), np.sort(V, axis=0))
    assert trimesh.Trimesh(V, F).volume == pytest.approx(mesh.volume, rel=1e-9)
    # the CLI's path: a mesh component in the file's own unit
    spec = load_model(path)
    assert spec.components[0].type == "mesh" and spec.units == "mm" == threemf_units(path)
    solid = implicit_solid(spec)
    assert solid.volume() == pytest.approx(mesh.volume, rel=0.02)
    assert np.allclose(solid.surface().bounds, mesh.bounds + [100.0, -20.0, 5.0], atol=0.5)


def test_3mf_unit_comes_from_the_file(tmp_path: Path) -> None:
    import trimesh

    from neuralslicer.model.spec import load_model

    path = tmp_path / "box.3mf"
    trimesh.creation.box(extents=[2.0, 1.0, 0.5]).export(path)
    inch = _with_unit(path, tmp_path / "box_in.3mf", "inch")
    assert load_model(inch).units == "in" and load_model(inch, units="in").units == "in"
    assert implicit_solid(load_model(inch)).volume() == pytest.approx(2.0 * 1.0 * 0.5 * 25.4 ** 3, rel=0.02)
    with pytest.raises(InputError, match="states its unit, in"):
        load_model(inch, units="mm")
    with pytest.raises(InputError, match="micron"):
        load_model(_with_unit(path, tmp_path / "box_um.3mf", "micron"))
    not_zip = tmp_path / "broken.3mf"
    not_zip.write_bytes(b"solid nothing\nendsolid\n")
    with pytest.raises(InputError, match="not a 3MF file"):
        load_model(not_zip)
