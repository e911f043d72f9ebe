"""Bad FEA specs raise InputError with a message that says what is wrong."""
from __future__ import annotations

import numpy as np
import pydantic
import pytest

from neuralslicer.errors import InputError
from neuralslicer.fea import FEASpec, run_fea
from neuralslicer.fea.shapes import BoxSolid, UnionSolid

BEAM = BoxSolid((0, 0, 0), (40, 10, 10))
TIP = dict(box=[[39.9, -1, -1], [41, 11, 11]], force_n=[0, 0, -10])
ROOT = dict(box=[[-1, -1, -1], [0.1, 11, 11]])


def _run(solid: object, voxels: int = 500, **spec: object):
    """run_fea on a spec given as keywords (500 voxels)."""
    return run_fea(solid, FEASpec.model_validate(dict(voxels=voxels, **spec)))


def test_minimal_yaml_form_parses() -> None:
    """The documented minimal ``fea:`` block validates with its defaults."""
    spec = FEASpec.model_validate({
        "material": {"youngs_modulus_mpa": 2000, "poisson_ratio": 0.3},
        "supports": [{"box": [[-1, -1, -1], [0.5, 11, 11]]}],
        "loads": [{"box": [[99.5, -1, -1], [101, 11, 11]], "force_n": [0, 0, -10]}]})
    assert spec.voxels == 100_000 and spec.top_fraction == 0.10
    assert spec.anisotropic.y1_mpa == 3500 and spec.anisotropic.y2_mpa == 1200
    assert spec.supports[0].fix == (True, True, True)


@pytest.mark.parametrize("bad", [
    {"supports": [{"box": [[1, 0, 0], [0, 1, 1]]}]},                    # min > max
    {"supports": [{"box": [[0, 0, 0], [1, 1, 1]], "platform": True}]},  # two regions
    {"loads": [{"box": [[0, 0, 0], [1, 1, 1]]}]},                       # neither force nor pressure
    {"loads": [{"platform": True, "pressure_mpa": 1.0}]},               # pressure needs a region
    {"material": {"poisson_ratio": 0.5}},
    {"suports": []},                                                     # typo
])
def test_invalid_spec_is_rejected(bad: dict) -> None:
    """Malformed ``fea`` blocks fail validation."""
    with pytest.raises(pydantic.ValidationError):
        FEASpec.model_validate(bad)


def test_no_supports() -> None:
    """No supports: unconstrained model."""
    with pytest.raises(InputError, match="no supports.*unconstrained") as e:
        _run(BEAM, loads=[TIP])
    assert e.value.where == "fea.supports"


def test_support_selecting_nothing() -> None:
    """A support box away from the part names the support."""
    with pytest.raises(InputError, match="selects no node") as e:
        _run(BEAM, supports=[ROOT, {"box": [[100, 100, 100], [101, 101, 101]]}], loads=[TIP])
    assert e.value.where == "fea.supports[1]"


def test_load_selecting_nothing() -> None:
    """A load box away from the part names the load."""
    with pytest.raises(InputError, match="selects no node") as e:
        _run(BEAM, supports=[ROOT], loads=[TIP, {"box": [[50, 50, 50], [60, 60, 60]],
                                                 "force_n": [1, 0, 0]}])
    assert e.value.where == "fea.loads[1]"


def test_zero_volume_model() -> None:
    """A solid with no voxel centre inside is a zero-volume model."""
    class Empty:
        bounds = np.array([[0.0, 0, 0], [10, 10, 10]])
        platform_z = 0.0

        def H(self, x: np.ndarray) -> np.ndarray:
            return np.ones(len(x))
    with pytest.raises(InputError, match="zero volume"):
        _run(Empty(), supports=[ROOT], loads=[TIP])


@pytest.mark.parametrize("support", [
    {"box": [[-1, -1, -1], [0.1, 0.1, 11]]},          # one edge line: rotation about it is free
    {"box": [[-1, -1, -1], [0.1, 0.1, 0.1]]},         # one corner node: rotations free
    {"plane": {"axis": "x", "value": 0.0}, "fix": [True, False, False]},   # slides in y, z
])
def test_rigid_body_modes_remaining(support: dict) -> None:
    """Supports that do not stop all six rigid-body modes are reported."""
    with pytest.raises(InputError, match="rigid-body"):
        _run(BEAM, supports=[support], loads=[TIP])


def test_loaded_loose_part_and_dropped_unloaded_island() -> None:
    """A loaded part with no support is an error; an unloaded loose island is dropped."""
    island = BoxSolid((30, 20, 0), (40, 30, 10))
    solid = UnionSolid(BoxSolid((0, 0, 0), (40, 10, 10)), island)
    with pytest.raises(InputError, match="not connected to any support"):
        _run(solid, 3000, supports=[ROOT], loads=[{"box": [[29, 19, -1], [41, 31, 11]],
                                                  "force_n": [0, 0, -1]}])
    res = _run(solid, 3000, supports=[ROOT], loads=[TIP])
    assert res.info["dropped_voxels"] > 0
    assert res.centres[:, 1].max() < 10.0
