"""What a user can get wrong is refused before any work starts: one line, exit 2, nothing left behind."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import trimesh
import yaml

from neuralslicer.cli.main import main
from conftest import l_part_mesh


def refuse(capsys: pytest.CaptureFixture, argv: list[str], *expected: str) -> str:
    """Run the CLI; it must exit 2 with one error line containing every expected text."""
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("neuralslicer: error: "), err
    for text in expected:
        assert text in err, err
    return err


@pytest.fixture(scope="module")
def part(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The L part (20 mm) as an STL file."""
    path = tmp_path_factory.mktemp("pre") / "part.stl"
    l_part_mesh().export(path)
    return path


def scaled(tmp_path: Path, factor: float) -> Path:
    """The L part with its coordinates multiplied by factor."""
    mesh = l_part_mesh()
    mesh.apply_scale(factor)
    path = tmp_path / f"part_x{factor:g}.stl"
    mesh.export(path)
    return path


def test_output_folder_that_is_a_file(tmp_path, part, capsys):
    out = tmp_path / "out"
    out.write_text("not a folder")
    refuse(capsys, ["slice", str(part), "--out", str(out)], "--out", "is a file")
    assert out.read_text() == "not a folder"


def test_output_folder_holding_the_input(tmp_path, capsys):
    model = tmp_path / "part.stl"
    l_part_mesh().export(model)
    refuse(capsys, ["slice", str(model), "--out", str(tmp_path)], "--out", "holds the input")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["part.stl"]


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_output_folder_in_a_read_only_folder(tmp_path, part, capsys):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    try:
        refuse(capsys, ["slice", str(part), "--out", str(locked / "out")], "--out", "not writable")
    finally:
        locked.chmod(0o755)


def test_output_folder_on_a_read_only_file_system(part, capsys):
    """/proc is read-only for root too: the same refusal where the permission test above cannot run."""
    refuse(capsys, ["slice", str(part), "--out", "/proc/neuralslicer-out"], "--out")
    assert not os.path.exists("/proc/neuralslicer-out")


def test_store_that_is_a_file(tmp_path, part, capsys):
    store = tmp_path / "store.zarr"
    store.write_text("x")
    refuse(capsys, ["slice", str(part), "--out", str(tmp_path / "out"), "--store", str(store)], "--store", "is a file")
    assert not (tmp_path / "out").exists()


def test_millimetres_read_as_metres_suggest_the_unit(tmp_path, capsys):
    tiny = scaled(tmp_path, 0.001)
    err = refuse(capsys, ["slice", str(tiny), "--out", str(tmp_path / "out")], "implausible", "--units m")
    assert "0.0" in err and not (tmp_path / "out").exists()


def test_a_model_too_large_for_millimetres(tmp_path, capsys):
    huge = scaled(tmp_path, 1000.0)
    refuse(capsys, ["slice", str(huge), "--out", str(tmp_path / "out")], "implausible")
    assert not (tmp_path / "out").exists()


def test_units_option_rescales_the_model(tmp_path):
    from neuralslicer.model.solid import implicit_solid
    from neuralslicer.model.spec import spec_for_file

    tiny = scaled(tmp_path, 0.001)
    solid = implicit_solid(spec_for_file(tiny, "z", "m"))
    size = solid.bounds[1] - solid.bounds[0]
    assert size == pytest.approx([20.0, 10.0, 16.0], abs=0.5)


def test_layer_height_beyond_the_model_or_the_thickness_range(tmp_path, part, capsys):
    refuse(capsys, ["slice", str(part), "--out", str(tmp_path / "a"), "--layer-height", "50"], "--layer-height",
           "model's height")
    refuse(capsys, ["slice", str(part), "--out", str(tmp_path / "b"), "--layer-height", "0.2"], "--layer-height",
           "thickness range")
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_too_many_layers_need_force(tmp_path, capsys):
    from neuralslicer.config import SliceConfig
    from neuralslicer.errors import InputError
    from neuralslicer.model.solid import implicit_solid
    from neuralslicer.model.spec import spec_for_file
    from neuralslicer.run.preflight import check_layer_count

    solid = implicit_solid(spec_for_file(scaled(tmp_path, 100.0), "z"))   # 1.6 m tall: 2,000 layers of 0.8 mm
    config = SliceConfig()
    assert check_layer_count(solid, config) == pytest.approx(2000, abs=2)
    with pytest.raises(InputError, match="or pass force"):   # the core names the flow's parameters...
        check_layer_count(solid, config, limit=1000)
    from neuralslicer.cli.options import cli_names

    with pytest.raises(InputError, match="or pass --force") as err:   # ...the command line its flags
        check_layer_count(solid, config, limit=1000, names=cli_names())
    assert err.value.where == "--layer-height"


def test_unknown_machine_profile(tmp_path, part, capsys):
    refuse(capsys, ["slice", str(part), "--out", str(tmp_path / "out"), "--machine", "no_such_machine"],
           "--machine", "no such machine profile")
    assert not (tmp_path / "out").exists()


def test_a_line_width_the_nozzle_cannot_lay(tmp_path, part, capsys):
    cfg = tmp_path / "wide.yaml"
    cfg.write_text("toolpath: {line_width: 1.6}\n")
    refuse(capsys, ["slice", str(part), "--out", str(tmp_path / "out"), "--config", str(cfg)],
           "toolpath.line_width", "1.6 mm is outside the bead widths", "nozzle.bead_width_mm")
    assert not (tmp_path / "out").exists()


def test_fea_regions_that_select_nothing(tmp_path, capsys):
    mesh = tmp_path / "part.stl"
    l_part_mesh().export(mesh)
    spec = tmp_path / "part.yaml"
    spec.write_text(yaml.safe_dump({
        "components": [{"type": "mesh", "file": "part.stl"}],
        "fea": {"material": {"youngs_modulus_mpa": 2000, "poisson_ratio": 0.3}, "voxels": 20000,
                "supports": [{"box": [[100, 100, 100], [110, 110, 110]]}],
                "loads": [{"box": [[15, -1, 12], [21, 11, 17]], "force_n": [0, 0, -10]}]},
    }))
    refuse(capsys, ["slice", str(spec), "--out", str(tmp_path / "out")], "fea.supports")
    assert not (tmp_path / "out").exists()


def test_a_mesh_with_inverted_winding_is_the_same_solid(tmp_path):
    from neuralslicer.model.solid import implicit_solid
    from neuralslicer.model.spec import spec_for_file

    mesh = l_part_mesh()
    inverted = trimesh.Trimesh(mesh.vertices, mesh.faces[:, ::-1], process=False)
    a, b = tmp_path / "a.stl", tmp_path / "b.stl"
    mesh.export(a)
    inverted.export(b)
    sa, sb = implicit_solid(spec_for_file(a, "z")), implicit_solid(spec_for_file(b, "z"))
    probe = [[4.0, 5.0, 6.0], [15.0, 5.0, 14.0], [15.0, 5.0, 6.0], [-1.0, 5.0, 5.0]]
    assert (sa.H(probe) < 0).tolist() == (sb.H(probe) < 0).tolist() == [True, True, False, False]


def test_numeric_options_are_named_in_their_errors(tmp_path, part, capsys):
    refuse(capsys, ["slice", str(part), "--out", str(tmp_path / "o"), "--max-steps", "-3"], "--max-steps", "greater than or equal to 0")
    refuse(capsys, ["slice", str(part), "--out", str(tmp_path / "o"), "--cage-elements", "10"], "--cage-elements")
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("layers: {t_max: -1}\n")
    refuse(capsys, ["slice", str(part), "--out", str(tmp_path / "o"), "--config", str(cfg)], "cfg.yaml", "layers.t_max")
    assert not (tmp_path / "o").exists()


def test_threads_follow_the_cpus_available(tmp_path, monkeypatch):
    from neuralslicer.neural import device

    monkeypatch.setattr(device.os, "sched_getaffinity", lambda pid: {0})
    assert device.available_cpus(tmp_path / "none") == 1        # pinned to one core
    monkeypatch.setattr(device.os, "sched_getaffinity", lambda pid: set(range(8)))
    quota = tmp_path / "cpu.max"
    quota.write_text("150000 100000\n")                           # a cgroup quota of 1.5 CPUs
    assert device.available_cpus(quota) == 2
    quota.write_text("max 100000\n")
    assert device.available_cpus(quota) == 8


def _fresh_env(code: str, **env: str) -> str:
    """What a fresh interpreter prints running ``code`` (GOMP_SPINCOUNT unset unless given)."""
    base = {k: v for k, v in os.environ.items() if k != "GOMP_SPINCOUNT"}
    return subprocess.run([sys.executable, "-c", code], env={**base, **env}, capture_output=True, text=True,
                          check=True).stdout.strip()


def test_the_command_shortens_openmp_spinning_before_torch_loads():
    """Idle OpenMP workers spinning 300,000 times starve a second job on a shared node (two optimisations ran 27x
    slower each); the command sets a short spin before torch (and its libgomp) is imported, and a user's value
    stands."""
    code = ("import os, sys; from neuralslicer.cli.main import main; "
            "main(['slice', 'no-such-model.stl', '--out', 'never-made']); "
            "print(os.environ.get('GOMP_SPINCOUNT'), 'torch' in sys.modules)")
    assert _fresh_env(code) == "5000 False"
    assert _fresh_env(code, GOMP_SPINCOUNT="123") == "123 False"
    late = "import os, torch; from neuralslicer.neural.device import limit_threads; limit_threads(); " \
           "print(os.environ.get('GOMP_SPINCOUNT'))"
    assert _fresh_env(late) == "None"      # too late to matter once torch is loaded: left alone


_MMAPPED = ("import ctypes, sys, numpy as np\n"
            "class Info(ctypes.Structure):\n"
            "    _fields_ = [(n, ctypes.c_size_t) for n in ('arena ordblks smblks hblks hblkhd usmblks fsmblks "
            "uordblks fordblks keepcost').split()]\n"
            "mallinfo2 = ctypes.CDLL(None).mallinfo2\n"
            "mallinfo2.restype = Info\n"
            "from neuralslicer.allocator import keep_freed_memory\n"
            "kept = keep_freed_memory() if sys.argv[1] == 'keep' else None\n"
            "if sys.argv[1] == 'command':\n"
            "    from neuralslicer.cli.main import main\n"
            "    main(['slice', 'no-such-model.stl', '--out', 'never-made'])\n"
            "a = np.ones(50_000_000)\n"
            "print(kept, mallinfo2().hblkhd >= a.nbytes)\n")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator")
def test_big_arrays_come_from_the_heap_once_freed_memory_is_kept():
    """glibc maps every array above 32 MB afresh (and faults it in page by page on every use): with
    ``keep_freed_memory`` (the command calls it) a 400 MB array comes from the heap (no mapped block holds it);
    without it, and where the user set glibc's own ``MALLOC_*`` variables, it is mapped as before (mallinfo2, an
    independent count)."""
    def run(arg: str, **env: str) -> str:
        base = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
        return subprocess.run([sys.executable, "-c", _MMAPPED, arg], env={**base, **env}, capture_output=True,
                              text=True, check=True).stdout.strip()

    assert run("keep") == "True False"
    assert run("command") == "None False"           # the command keeps it, first thing
    assert run("default") == "None True"
    assert run("keep", MALLOC_ARENA_MAX="4") == "False True"
    assert run("keep", NEURALSLICER_KEEP_FREED_MEMORY="0") == "False True"


def test_studies_run_the_same_checks(tmp_path, part, capsys):
    out = tmp_path / "out"
    out.write_text("not a folder")
    refuse(capsys, ["study", "cages", str(part), "--out", str(out), "--cage-elements", "500,800"], "--out", "is a file")
    big = scaled(tmp_path, 1000.0)                               # m read as mm, in a batch
    refuse(capsys, ["study", "batch", str(part), str(big), "--out", str(tmp_path / "b")], "part_x1000")
    assert not (tmp_path / "b").exists()


@pytest.mark.parametrize("name, expected", [("environ.txt", ("environ.txt:1", "field(s)")),
                                            ("environ.obj", ("environ.obj", "no polyline"))])
def test_a_file_named_by_mistake_is_never_echoed(tmp_path, capsys, name, expected):
    """A spec naming the wrong file as struts (the environment of a process, say): refused by its line number and
    shape, never by its content."""
    secret = tmp_path / name
    secret.write_text("HOME=/root\x00TOKEN=hunter2-secret\x00PATH=/usr/bin\n")
    spec = tmp_path / "spec.yaml"
    spec.write_text(yaml.safe_dump({"components": [{"type": "struts", "file": name, "radius": 1.0}]}))
    err = refuse(capsys, ["slice", str(spec), "--out", str(tmp_path / "out")], *expected)
    assert "hunter2" not in err and "HOME" not in err and "TOKEN" not in err
    assert not (tmp_path / "out").exists()


def test_the_slice_help_names_the_preflights_layer_limit():
    """The --force help states the preflight's layer limit (written out: the command line does not import the
    preflight before it runs a slice)."""
    from neuralslicer.cli.main import make_parser
    from neuralslicer.run.preflight import MAX_LAYERS

    slice_parser = next(a for a in make_parser()._subparsers._group_actions).choices["slice"]
    assert f"{MAX_LAYERS:,}" in slice_parser.format_help().replace("\n", " ")


def test_version_prints_the_version_pyproject_declares(capsys) -> None:
    """`neuralslicer --version` prints the version of pyproject.toml (read here with tomllib) and exits 0."""
    import tomllib
    from pathlib import Path

    from neuralslicer.cli.main import make_parser

    declared = tomllib.loads((Path(__file__).resolve().parents[2] / "pyproject.toml").read_text())["project"]["version"]
    with pytest.raises(SystemExit) as stop:
        make_parser().parse_args(["--version"])
    assert stop.value.code == 0 and capsys.readouterr().out.strip() == f"neuralslicer {declared}"
