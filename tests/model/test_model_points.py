"""Point-cloud input: readers, reconstruction against closed forms, errors, the shipped example."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

import neuralslicer
from neuralslicer.errors import InputError
from neuralslicer.model import Solid, implicit_solid, load_spec, spec_for_file
from neuralslicer.model.io import read_points
from neuralslicer.model.points import reconstruct
from neuralslicer.topology import genus

EXAMPLE = Path(neuralslicer.__file__).parent / "examples" / "points"
R_SPHERE, R_MAJOR, R_MINOR = 10.0, 12.0, 4.0


def sphere_cloud(n: int, seed: int = 0, radius: float = R_SPHERE) -> tuple[np.ndarray, np.ndarray]:
    """``n`` uniform points on a sphere and their outward normals."""
    normals = np.random.default_rng(seed).normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return radius * normals, normals


def torus_cloud(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points uniform by area on a z-axis torus (rejection on the area element) and their normals."""
    rng = np.random.default_rng(seed)
    u, v = rng.uniform(0, 2 * np.pi, (2, 4 * n))
    keep = rng.uniform(0, 1, 4 * n) < (R_MAJOR + R_MINOR * np.cos(v)) / (R_MAJOR + R_MINOR)
    u, v = u[keep][:n], v[keep][:n]
    ring = R_MAJOR + R_MINOR * np.cos(v)
    points = np.stack([ring * np.cos(u), ring * np.sin(u), R_MINOR * np.sin(v)], axis=1)
    normals = np.stack([np.cos(v) * np.cos(u), np.cos(v) * np.sin(u), np.sin(v)], axis=1)
    return points, normals


def sphere_sdf(x: np.ndarray) -> np.ndarray:
    """Exact signed distance to the sphere."""
    return np.linalg.norm(x, axis=1) - R_SPHERE


def torus_sdf(x: np.ndarray) -> np.ndarray:
    """Exact signed distance to the torus."""
    return np.hypot(np.linalg.norm(x[:, :2], axis=1) - R_MAJOR, x[:, 2]) - R_MINOR


def write_xyz(path: Path, points: np.ndarray, normals: np.ndarray | None = None) -> Path:
    """An .xyz file with a comment line, comma separated, with or without normals."""
    rows = points if normals is None else np.hstack([points, normals])
    path.write_text("# test cloud\n" + "\n".join(", ".join(f"{v:.6f}" for v in r) for r in rows) + "\n")
    return path


def points_spec(folder: Path, filename: str, extra: str = "") -> Path:
    """A spec with one points component."""
    path = folder / "spec.yaml"
    path.write_text(f"components:\n  - type: points\n    file: {filename}\n{extra}")
    return path


@pytest.mark.parametrize("shape", ["sphere", "torus"])
@pytest.mark.parametrize("with_normals", [True, False])
def test_reconstruction_matches_the_closed_form(tmp_path: Path, shape: str, with_normals: bool) -> None:
    points, normals = sphere_cloud(4000) if shape == "sphere" else torus_cloud(4000)
    sdf = sphere_sdf if shape == "sphere" else torus_sdf
    path = write_xyz(tmp_path / f"{shape}.xyz", points, normals if with_normals else None)
    solid = implicit_solid(spec_for_file(path))
    assert solid.components[0].attrs() == {"type": "points"}
    surface = solid.surface()
    diag = float(np.linalg.norm(np.ptp(points, axis=0)))
    error = np.abs(sdf(surface.vertices))
    assert error.max() < 0.01 * diag and error.mean() < 0.002 * diag
    assert surface.is_watertight and genus(surface.faces) == (0 if shape == "sphere" else 1)
    # the sign is right wherever the analytic solid is clearly inside or outside
    x = np.random.default_rng(1).uniform(points.min(0) - 3, points.max(0) + 3, (4000, 3))
    d = sdf(x)
    clear = np.abs(d) > 0.02 * diag
    assert np.array_equal(solid.H(x[clear]) < 0, d[clear] < 0)


def test_cavity_keeps_its_inward_normals() -> None:
    outer, _ = sphere_cloud(3000, seed=2)
    inner, _ = sphere_cloud(1500, seed=3, radius=5.0)
    vertices, faces = reconstruct(np.vstack([outer, inner]), None, resolution=64)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    assert mesh.volume == pytest.approx(4 / 3 * np.pi * (10 ** 3 - 5 ** 3), rel=0.03)
    assert len(mesh.split(only_watertight=False)) == 2


def test_readers_give_points_and_normals(tmp_path: Path) -> None:
    points, normals = sphere_cloud(300)
    ascii_pcd = tmp_path / "a.pcd"
    ascii_pcd.write_text("# comment\nVERSION .7\nFIELDS x y z normal_x normal_y normal_z curvature\n"
                         "SIZE 4 4 4 4 4 4 4\nTYPE F F F F F F F\nCOUNT 1 1 1 1 1 1 1\nWIDTH 300\nHEIGHT 1\n"
                         "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 300\nDATA ascii\n"
                         + "\n".join(" ".join(f"{v:.6f}" for v in r) + " 0" for r in np.hstack([points, normals])))
    records = np.zeros(300, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")])
    records["x"], records["y"], records["z"] = points.T
    binary_pcd = tmp_path / "b.pcd"
    binary_pcd.write_bytes(b"VERSION .7\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F U\nCOUNT 1 1 1 1\n"
                           b"WIDTH 300\nHEIGHT 1\nPOINTS 300\nDATA binary\n" + records.tobytes())
    import meshio

    ply = tmp_path / "c.ply"
    meshio.write_points_cells(ply, points, [], point_data={"nx": normals[:, 0], "ny": normals[:, 1],
                                                           "nz": normals[:, 2]}, binary=True)
    for path, has_normals in [(ascii_pcd, True), (binary_pcd, False), (ply, True),
                              (write_xyz(tmp_path / "d.xyz", points, normals), True)]:
        p, n = read_points(path)
        assert np.allclose(p, points, atol=1e-5), path
        assert (n is not None) == has_normals and (n is None or np.allclose(n, normals, atol=1e-5)), path


def test_ply_with_faces_stays_a_mesh(tmp_path: Path) -> None:
    trimesh.creation.icosphere(radius=10.0).export(tmp_path / "mesh.ply")
    assert spec_for_file(tmp_path / "mesh.ply").components[0].type == "mesh"
    cloud = tmp_path / "cloud.ply"
    trimesh.PointCloud(sphere_cloud(2000)[0]).export(cloud)
    assert spec_for_file(cloud).components[0].type == "points"
    assert spec_for_file(write_xyz(tmp_path / "s.xyz", sphere_cloud(200)[0])).components[0].type == "points"
    with pytest.raises(InputError, match="use 'type: points'"):
        (tmp_path / "spec.yaml").write_text("components:\n  - {type: mesh, file: cloud.ply}\n")
        implicit_solid(load_spec(tmp_path / "spec.yaml"))


def test_units_and_up_apply_to_points_and_normals(tmp_path: Path) -> None:
    points, normals = sphere_cloud(2000)
    write_xyz(tmp_path / "s.xyz", points / 10 + [0, 2, 0], normals)  # cm, centre at y = 2 cm
    spec = points_spec(tmp_path, "s.xyz", "    resolution: 48\nunits: cm\nup: y\n")
    solid = implicit_solid(load_spec(spec))
    assert solid.volume() == pytest.approx(4 / 3 * np.pi * 1000, rel=0.03)
    assert solid.bounds[:, 2] == pytest.approx([10.0, 30.0], abs=0.5)  # +y became +z, in mm
    again = Solid.from_arrays(*solid.to_arrays())
    x = np.array([[0.0, 0.0, 20.0], [0.0, 0.0, 35.0]])
    assert np.array_equal(again.H(x), solid.H(x)) and again.H(x)[0] < 0 < again.H(x)[1]


def _flat(n: int = 1000) -> np.ndarray:
    xy = np.random.default_rng(0).uniform(-10, 10, (n, 2))
    return np.c_[xy, np.zeros(n)]


def _dish(n: int = 1500) -> np.ndarray:
    points, _ = sphere_cloud(8 * n)
    return points[points[:, 2] < -8][:n]


@pytest.mark.parametrize("filename, content, extra, expect", [
    ("empty.xyz", "# nothing\n\n", "", "holds no points"),
    ("junk.xyz", b"\xff\xfe\x00garbage\x81", "", "not a text file"),
    ("junk.pcd", "garbage", "", "not a PCD file"),
    ("junk.ply", "garbage", "", "not a PLY file"),
    ("packed.pcd", "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nPOINTS 200\nDATA binary_compressed\n",
     "", "'DATA binary_compressed' is not supported"),
    ("few.xyz", "\n".join("1 2 3" for _ in range(99)), "", "only 99 points"),
    ("nan.xyz", "# x y z\n" + "\n".join(["1 2 3"] * 50 + ["1 nan 3"] + ["1 2 3"] * 60), "",
     "nan.xyz:52: NaN or infinite value"),
    ("bad.xyz", "\n".join(["1 2 3"] * 5 + ["1 2 three"] + ["1 2 3"] * 200), "",
     "bad.xyz:6: expected 'x y z' like the first line"),
    ("short.xyz", "\n".join(["1 2 3 0 0 1"] * 5 + ["1 2 3"] + ["1 2 3 0 0 1"] * 200), "",
     "short.xyz:6: expected 'x y z nx ny nz'"),
    ("flat.xyz", _flat(), "", "the points enclose no volume"),
    ("dish.xyz", _dish(), "", "the points enclose no volume"),
    ("zero.xyz", np.hstack([sphere_cloud(500)[0], np.zeros((500, 3))]), "", "normals have zero length"),
    ("plain.xyz", sphere_cloud(500)[0], "    normals: given\n", "the file has no normals"),
])
def test_bad_point_clouds(tmp_path: Path, filename: str, content, extra: str, expect: str) -> None:
    path = tmp_path / filename
    if isinstance(content, np.ndarray):
        write_xyz(path, content)
    elif isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content)
    with pytest.raises(InputError) as info:
        implicit_solid(load_spec(points_spec(tmp_path, filename, extra)))
    message = str(info.value)
    assert str(path) in message and expect in message and "components[0]" in message


def test_bad_points_keys(tmp_path: Path) -> None:
    write_xyz(tmp_path / "s.xyz", sphere_cloud(200)[0])
    with pytest.raises(InputError, match=r"spec.yaml:4: components\[0\]\.k: must be >= 4"):
        load_spec(points_spec(tmp_path, "s.xyz", "    k: 2\n"))
    with pytest.raises(InputError, match=r"components\[0\]\.normals: Input should be 'auto', 'given' or"):
        load_spec(points_spec(tmp_path, "s.xyz", "    normals: flip\n"))


def test_example_spec_loads_as_a_solid() -> None:
    spec = load_spec(EXAMPLE / "spec.yaml")
    assert spec.components[0].type == "points"
    solid = implicit_solid(spec)
    surface = solid.surface()
    assert solid.volume() > 0 and surface.is_watertight and genus(surface.faces) == 1
    assert np.allclose(solid.bounds, [[0, 0, 0], [30, 20, 14]], atol=0.6)
    # inside the block, in the through hole, outside
    H = solid.H(np.array([[5.0, 5.0, 3.0], [22.0, 10.0, 5.0], [15.0, 10.0, 20.0]]))
    assert H[0] < -2.0 and H[1] > 2.0 and H[2] > 5.0
    scan = spec_for_file(EXAMPLE / "part_scan.pcd")
    assert scan.components[0].type == "points" and read_points(EXAMPLE / "part_scan.pcd")[1] is None
