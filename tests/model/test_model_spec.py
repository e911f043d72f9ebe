"""Model spec: loading, defaults, units/up handling, digests and every malformed-input error."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from neuralslicer.data import DATA_DIR
from neuralslicer.errors import InputError
from neuralslicer.model import implicit_solid, load_spec, spec_digest, spec_for_file


@pytest.fixture()
def folder(tmp_path: Path) -> Path:
    """A folder with a closed box, an open square patch and a segments file."""
    trimesh.creation.box(extents=(4, 6, 8)).export(tmp_path / "part.stl")
    patch = trimesh.Trimesh([[0, 0, 0], [10, 0, 0], [10, 10, 0], [0, 10, 0]], [[0, 1, 2], [0, 2, 3]])
    patch.export(tmp_path / "surface.stl")
    (tmp_path / "lattice.txt").write_text("# a comment\n0 0 0 10 0 0\n\n10 0 0 10 10 0  # end\n")
    return tmp_path


def write(folder: Path, text: str, name: str = "spec.yaml") -> Path:
    """Write a spec file and return its path."""
    path = folder / name
    path.write_text(text)
    return path


MINIMAL = """up: z
components:
  - type: shell
    file: surface.stl
    thickness: 3.0
  - type: mesh
    file: part.stl
"""


def test_minimal_spec_exactly_as_documented(folder: Path) -> None:
    spec = load_spec(write(folder, MINIMAL))
    assert spec.up == "z" and spec.units == "mm" and spec.platform == "auto" and spec.fea is None
    assert [c.type for c in spec.components] == ["shell", "mesh"]
    assert spec.components[0].file == (folder / "surface.stl").resolve()
    solid = implicit_solid(spec)
    # the shell's slab z in [-1.5, 1.5] and the box z in [-4, 4]: point above the patch is outside
    assert solid.H(np.array([[5.0, 5.0, 1.0]]))[0] == pytest.approx(-0.5)
    assert solid.H(np.array([[0.0, 0.0, 0.0]]))[0] == pytest.approx(-2.0)  # inside the box
    assert solid.platform_z == pytest.approx(-4.0)


def test_units_up_platform_and_tubes(folder: Path) -> None:
    spec = load_spec(write(folder, """up: y
units: cm
platform: {z: -10}
smooth_union: 0.1
components:
  - {type: struts, file: lattice.txt, radius: 0.5}
  - {type: tubes, file: lattice.txt, radius: 0.4, wall: 0.1}
"""))
    solid = implicit_solid(spec)
    strut = solid.components[0]
    # cm -> mm and y-up: input (10, 10, 0) cm becomes (100, 0, 100) mm
    assert np.allclose(strut.segments[1, 1], [100.0, 0.0, 100.0])
    assert strut.radius == 5.0 and solid.components[1].wall == pytest.approx(1.0)
    assert solid.platform_z == -100.0 and solid.smooth_union == pytest.approx(1.0)


def test_tubes_threshold_form(folder: Path) -> None:
    from neuralslicer.model.convolution import line_field

    T = float(line_field(2.0, 0.3))
    spec = load_spec(write(folder, f"components:\n  - {{type: tubes, file: lattice.txt, threshold: {T}, c: 0.3}}\n"))
    assert implicit_solid(spec).components[0].radius == pytest.approx(2.0)


def test_spec_for_file_and_digest(folder: Path, tmp_path: Path) -> None:
    spec = spec_for_file(folder / "part.stl", up="x")
    assert spec.components[0].type == "mesh" and spec.up == "x"
    assert spec_for_file(DATA_DIR / "ring.tet", up="y").components[0].type == "tet"
    with pytest.raises(InputError, match="unknown model format"):
        spec_for_file(folder / "lattice.txt")
    d1 = spec_digest(load_spec(write(folder, MINIMAL)))
    assert d1 == spec_digest(load_spec(write(folder, MINIMAL)))
    assert d1 != spec_digest(load_spec(write(folder, MINIMAL.replace("3.0", "3.5"))))
    trimesh.creation.box(extents=(4, 6, 9)).export(folder / "part.stl")  # same name, new bytes
    assert d1 != spec_digest(load_spec(write(folder, MINIMAL)))


@pytest.mark.parametrize("text, key, line", [
    ("components:\n  - type: mesh\n    file: part.stl\n  - type: blob\n    file: part.stl\n",
     "components[1].type: unknown component type 'blob'", 4),
    ("components:\n  - type: shell\n    file: surface.stl\n    thickness: -3\n",
     "components[0].thickness: must be > 0", 4),
    ("components:\n  - type: mesh\n    file: nowhere.stl\n", "components[0].file: no such file", 3),
    ("components:\n  - type: struts\n    file: lattice.txt\n", "components[0].radius: missing", 2),
    ("up: q\ncomponents:\n  - {type: mesh, file: part.stl}\n", "up:", 1),
    ("components:\n  - {type: mesh, file: part.stl, colour: red}\n", "components[0].colour: unknown key", 2),
    ("components: []\n", "components: must list at least one", 1),
    ("components:\n  - {type: tubes, file: lattice.txt, radius: 1, threshold: 0.1}\n",
     "components[0]: give exactly one of 'radius' and 'threshold'", 2),
    ("components: [\n", "not valid YAML", None),
    ("platform: 5\ncomponents:\n  - {type: mesh, file: part.stl}\n", "platform: must be 'auto' or {z:", 1),
    ("platform: {z: low}\ncomponents:\n  - {type: mesh, file: part.stl}\n", "platform.z: Input should be a valid number", 1),
])
def test_malformed_specs_name_file_line_and_key(folder: Path, text: str, key: str, line) -> None:
    path = write(folder, text)
    with pytest.raises(InputError) as info:
        load_spec(path)
    message = str(info.value)
    assert str(path) in message and key in message
    if line is not None:
        assert f"{path}:{line}:" in message


@pytest.mark.parametrize("filename, content, expect", [
    ("bad.txt", "0 0 0 1 1 1\n0 0 0 1 1\n", "bad.txt:2: expected 'x0 y0 z0 x1 y1 z1'"),
    ("nan.txt", "0 0 0 1 1 1\n# c\n0 0 nan 1 1 1\n", "nan.txt:3:"),
    ("zero.txt", "1 1 1 1 1 1\n", "zero.txt: all segments have zero length"),
])
def test_bad_segment_files(folder: Path, filename: str, content: str, expect: str) -> None:
    (folder / filename).write_text(content)
    spec = load_spec(write(folder, f"components:\n  - {{type: struts, file: {filename}, radius: 1}}\n"))
    with pytest.raises(InputError) as info:
        implicit_solid(spec)
    assert expect in str(info.value) and "spec.yaml: components[0]" in str(info.value)


@pytest.mark.parametrize("filename, content, expect", [
    ("nan.obj", "v 0 0 0\nv 1 0 0\nv nan 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n",
     "NaN or infinite"),
    ("empty.stl", "", "holds no triangles"),
    ("flat.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3\nf 2 4 3\n", "encloses no volume"),
    ("junk.ply", "garbage", "cannot read as a triangle mesh"),
])
def test_bad_mesh_files(folder: Path, filename: str, content: str, expect: str) -> None:
    (folder / filename).write_text(content)
    spec = load_spec(write(folder, f"components:\n  - {{type: mesh, file: {filename}}}\n"))
    with pytest.raises(InputError) as info:
        implicit_solid(spec)
    assert str(folder / filename) in str(info.value) and expect in str(info.value)
    assert "components[0]" in str(info.value)


def test_fea_block_is_parsed(folder: Path) -> None:
    spec = load_spec(write(folder, MINIMAL + "fea:\n  material: {youngs_modulus_mpa: 1500}\n"))
    assert spec.fea is not None and spec.fea.material.youngs_modulus_mpa == 1500
    with pytest.raises(InputError, match=r"fea\.material\.youngs_modulus_mpa: must be > 0"):
        load_spec(write(folder, MINIMAL + "fea:\n  material: {youngs_modulus_mpa: -1}\n"))


DATA = DATA_DIR


def test_shared_meshes_open_vase_needs_a_shell(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="is open: a boundary loop"):
        implicit_solid(spec_for_file(DATA / "simple_vase_open_low_res.stl"))
    spec = load_spec(write(tmp_path, f"components:\n  - {{type: shell, file: {DATA / 'simple_vase_open_low_res.stl'}, thickness: 2}}\n"))
    solid = implicit_solid(spec)
    wall = solid.components[0].vertices[:50]
    assert np.allclose(solid.H(wall), -1.0)
    bunny = implicit_solid(spec_for_file(DATA / "bunny_closed_low_res.stl"))
    ref = trimesh.load(DATA / "bunny_closed_low_res.stl")
    assert bunny.volume() == pytest.approx(abs(ref.volume), rel=1e-9)
    assert bunny.platform_z == pytest.approx(ref.bounds[0, 2])
