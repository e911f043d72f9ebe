"""Ordinary nozzles: the layer thickness, line width and bead ranges follow the machine profile's nozzle, the
configuration's own values win, and a combination the nozzle can't print is one line naming the keys."""
from __future__ import annotations

from argparse import Namespace
from pathlib import Path

import pytest

from neuralslicer.cli.main import main
from neuralslicer.cli.options import build_config
from neuralslicer.config import SliceConfig
from neuralslicer.errors import InputError
from neuralslicer.motion.profile import NOZZLE_RULES, Nozzle, load_profile, profile_names
from conftest import l_part_mesh


def _options(**given: object) -> Namespace:
    """The slice command's options as argparse leaves them when only ``given`` are on the command line."""
    from neuralslicer.cli.options import CONFIG_KEYS

    base = {name: None for name in CONFIG_KEYS} | {"config": None, "objectives": None, "verify": False,
                                                   "robot": False, "init": None}
    return Namespace(**(base | given))


def test_a_04_nozzle_prints_ordinary_layers_and_lines() -> None:
    n = Nozzle(diameter_mm=0.4)
    assert (n.layer_height_mm, n.layer_thickness_mm, n.line_width_mm) == (0.2, (0.1, 0.3), 0.45)
    assert (n.bead_thickness_mm, n.bead_width_mm) == ((0.05, 0.4), (0.3, 0.8))
    for name, rule in NOZZLE_RULES.items():       # every value scales with the bore
        big = getattr(Nozzle(diameter_mm=0.8), name)
        small = getattr(n, name)
        assert big == pytest.approx(tuple(2 * v for v in small) if isinstance(rule, tuple) else 2 * small)


def test_a_nozzle_without_a_diameter_is_the_papers() -> None:
    n = Nozzle(cone_half_angle_deg=40.0)             # a profile written before nozzles had a diameter
    assert (n.diameter_mm, n.layer_height_mm, n.layer_thickness_mm, n.line_width_mm) == (1.0, 0.8, (0.4, 1.0), 0.5)
    assert (n.bead_thickness_mm, n.bead_width_mm) == ((0.15, 1.2), (0.3, 1.0))
    assert Nozzle(**n.model_dump()) == n             # the filled values survive a round trip
    assert Nozzle(diameter_mm=1.0).layer_height_mm == 0.5      # a diameter given: the ordinary rules


def test_the_shipped_profiles_nozzles() -> None:
    nozzles = {name: load_profile(name).nozzle for name in profile_names()}
    for name in ("reprap_5axis", "table_head_bc_reprap", "three_axis_reprap"):
        assert nozzles[name].diameter_mm == 0.4 and nozzles[name].layer_height_mm == 0.2
    for name in ("table_bc_linuxcnc", "table_ac_linuxcnc", "head_bc_linuxcnc"):      # the paper's settings
        n = nozzles[name]
        assert (n.diameter_mm, n.layer_height_mm, n.layer_thickness_mm, n.line_width_mm) == (1.0, 0.8, (0.4, 1.0), 0.5)
        assert (n.bead_thickness_mm, n.bead_width_mm) == ((0.15, 1.2), (0.3, 1.0))


@pytest.mark.parametrize("given, key", [
    ({"diameter_mm": 0.4, "layer_height_mm": 0.35}, "layer_height_mm"),
    ({"diameter_mm": 0.4, "layer_thickness_mm": (0.1, 0.6)}, "layer_thickness_mm"),
    ({"diameter_mm": 0.4, "line_width_mm": 1.2}, "line_width_mm"),
    ({"diameter_mm": 0.4, "bead_width_mm": (0.5, 0.4)}, "bead_width_mm"),
])
def test_a_nozzle_that_contradicts_itself_is_refused(given: dict, key: str) -> None:
    with pytest.raises(ValueError, match=key):
        Nozzle(**given)


def test_the_configuration_takes_what_it_leaves_out_from_the_nozzle() -> None:
    paper, small = SliceConfig(), SliceConfig(machine="reprap_5axis")
    assert (paper.layers.layer_height, paper.layers.t_min, paper.layers.t_max, paper.toolpath.line_width) == \
        (0.8, 0.4, 1.0, 0.5)
    assert (small.layers.layer_height, small.layers.t_min, small.layers.t_max, small.toolpath.line_width) == \
        (0.2, 0.1, 0.3, 0.45)
    own = SliceConfig.model_validate({"machine": "reprap_5axis", "layers": {"layer_height": 0.25, "t_max": 0.35},
                                      "toolpath": {"infill": "zigzag"}})
    assert (own.layers.layer_height, own.layers.t_min, own.layers.t_max) == (0.25, 0.1, 0.35)
    assert (own.toolpath.line_width, own.toolpath.infill) == (0.45, "zigzag")
    assert SliceConfig.model_validate(own.model_dump()) == own              # the round trip the flows make


def test_the_machine_option_brings_its_nozzle_over_a_config_file(tmp_path: Path) -> None:
    cfg = tmp_path / "c.yaml"
    cfg.write_text("cage: {n_elements: 5000}\n")
    config = build_config(_options(config=str(cfg), machine="three_axis_reprap", layer_height=0.15))
    assert (config.layers.layer_height, config.layers.t_min, config.layers.t_max) == (0.15, 0.1, 0.3)
    assert (config.toolpath.line_width, config.cage.n_elements) == (0.45, 5000)
    cfg.write_text("machine: reprap_5axis\ntoolpath: {line_width: 0.5}\n")
    config = build_config(_options(config=str(cfg)))
    assert (config.layers.layer_height, config.toolpath.line_width) == (0.2, 0.5)


@pytest.fixture(scope="module")
def part(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The L part (20 mm) as an STL file."""
    path = tmp_path_factory.mktemp("nozzle") / "part.stl"
    l_part_mesh().export(path)
    return path


def _one_error_line(capsys: pytest.CaptureFixture, argv: list[str]) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("neuralslicer: error: "), err
    return err


def test_02_mm_layers_on_the_papers_nozzle_name_the_keys_and_the_profiles_that_print_them(tmp_path, part, capsys):
    err = _one_error_line(capsys, ["slice", str(part), "--out", str(tmp_path / "o"), "--layer-height", "0.2"])
    assert "--layer-height: 0.2 mm is outside the layers' thickness range [0.4, 1] mm" in err
    assert "table_bc_linuxcnc's 1 mm nozzle" in err and "layers.t_min/t_max and toolpath.line_width" in err
    assert "reprap_5axis, table_head_bc_reprap, three_axis_reprap" in err
    assert not (tmp_path / "o").exists()


def test_a_layer_thicker_than_the_nozzle_lays_is_refused(tmp_path, part, capsys):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("layers: {t_max: 0.5}\n")
    err = _one_error_line(capsys, ["slice", str(part), "--out", str(tmp_path / "o"), "--config", str(cfg),
                                   "--machine", "reprap_5axis"])
    assert "layers.t_max: 0.5 mm is more than the thickest bead the 0.4 mm nozzle of reprap_5axis lays (0.4 mm" in err


def test_02_mm_layers_pass_the_preflight_on_a_04_nozzle(tmp_path, part):
    from neuralslicer.cli.options import cli_names
    from neuralslicer.run.preflight import check_slice

    config = build_config(_options(machine="reprap_5axis", layer_height=0.2))
    spec = check_slice(part, tmp_path / "o", str(tmp_path / "store"), config, up="z", names=cli_names())
    assert spec is not None and config.toolpath.line_width == 0.45


def test_a_profile_without_a_loadable_file_leaves_the_layers_to_the_preflight() -> None:
    config = SliceConfig(machine="no_such_machine")      # the preflight names --machine and the shipped profiles
    assert config.layers.layer_height == 0.8
    with pytest.raises(InputError, match="no such machine profile"):
        load_profile(config.machine)
