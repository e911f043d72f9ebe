"""The paper's Bridge example: S3-Slicer's bridgeSmall.tet in its own pose, its 3-point bending load case."""
from __future__ import annotations

from pathlib import Path

import numpy as np

import neuralslicer
from neuralslicer.config import SliceConfig
from neuralslicer.fea.grid import voxelize
from neuralslicer.fea.solver import fixed_dofs, load_vector
from neuralslicer.model import implicit_solid, load_spec
from neuralslicer.run.preflight import check_fea_regions

FOLDER = Path(neuralslicer.__file__).parent / "examples" / "paper_bridge"


def test_the_paper_bridge_loads_with_its_licence_and_settings() -> None:
    spec = load_spec(FOLDER / "model.yaml")
    assert spec.up == "y" and spec.units == "mm"
    assert "Redistribution and use in source and binary forms" in (FOLDER / "LICENSE-S3_DeformFDM.txt").read_text()
    solid = implicit_solid(spec)
    tet = solid.components[0]
    assert len(tet.vertices) == 31879 and len(tet.tets) == 100420
    # S3's pose, y up: 124 mm long (x), 43 mm deep (y), 37.6 mm tall (z), standing on its bottom chords
    assert np.allclose(solid.bounds, [[-31.02, -32.25, -9.41], [93.07, 10.75, 28.23]], atol=0.05)
    assert abs(solid.platform_z - solid.bounds[0, 2]) < 1e-6
    for name, objectives in (("config.yaml", ["sr"]), ("config_head.yaml", ["sr", "gc", "ca"])):
        config = SliceConfig.from_yaml(FOLDER / name)
        assert config.objectives == objectives and config.s3.preset == "bridgeSmall"   # S3's row for the model


def test_the_load_is_on_the_top_middle_and_the_supports_under_the_ends() -> None:
    spec = load_spec(FOLDER / "model.yaml")
    solid = implicit_solid(spec)
    fea = spec.fea.model_copy(update={"voxels": 150_000})     # the preflight's check, on a coarser grid
    check_fea_regions(solid, fea)
    grid = voxelize(solid, fea.voxels)
    (lo, hi), z0 = solid.bounds, float(solid.platform_z)
    force = load_vector(grid, fea.loads, z0).reshape(-1, 3)
    loaded = grid.nodes[np.abs(force).sum(axis=1) > 0]
    assert np.isclose(force[:, 2].sum(), -1000.0) and np.allclose(force[:, :2].sum(axis=0), 0.0)
    middle = 0.5 * (lo[0] + hi[0])
    assert abs(loaded[:, 0].mean() - middle) < 2.0 and np.ptp(loaded[:, 0]) <= 10.0
    assert loaded[:, 2].min() > hi[2] - 1.5                  # on the top chord
    assert np.ptp(loaded[:, 1]) > 0.9 * (hi[1] - lo[1])       # both side frames
    held = fixed_dofs(grid, fea.supports, z0).reshape(-1, 3)
    pin, roller = held.all(axis=1), held[:, 2] & ~held[:, 0] & ~held[:, 1]
    for nodes, end in ((grid.nodes[pin], lo[0]), (grid.nodes[roller], hi[0])):
        assert len(nodes) > 0 and nodes[:, 2].max() < lo[2] + 1.5   # under the bottom chords
        assert np.abs(nodes[:, 0] - end).max() < 8.0                # at one end
    assert held.sum() == 3 * pin.sum() + roller.sum()
