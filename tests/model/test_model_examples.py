"""The shipped example models load, are closed, and have the documented topology."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import neuralslicer
from neuralslicer.model import Solid, implicit_solid, load_spec, spec_digest
from neuralslicer.model.components import MeshComponent, ShellComponent, StrutsComponent, TubesComponent
from neuralslicer.samples import surface_samples
from neuralslicer.topology import surface_topology

EXAMPLES = Path(neuralslicer.__file__).parent / "examples"


def test_bracket_is_a_small_closed_genus_3_mesh() -> None:
    spec = load_spec(EXAMPLES / "bracket" / "model.yaml")
    assert spec.fea is not None and len(spec.fea.loads) == 1
    solid = implicit_solid(spec)
    surf = solid.surface()
    assert surf.is_watertight and len(surf.faces) <= 5000
    assert surface_topology(surf.faces).genus.tolist() == [3]
    assert np.allclose(solid.bounds, [[0, 0, 0], [60, 40, 40]], atol=0.3)
    # inside a plate, in a bolt hole, outside
    H = solid.H(np.array([[5.0, 20.0, 3.0], [15.0, 25.0, 3.0], [30.0, 30.0, 20.0]]))
    assert H[0] < -2.0 and H[1] > 2.0 and H[2] > 10.0


@pytest.mark.parametrize("name, kind", [("lattice", StrutsComponent), ("tubes", TubesComponent),
                                        ("shell", ShellComponent)])
def test_single_component_examples(name: str, kind: type) -> None:
    solid = implicit_solid(load_spec(EXAMPLES / name / "model.yaml"))
    assert isinstance(solid.components[0], kind)
    seg = getattr(solid.components[0], "segments", None)
    if seg is not None:  # every skeleton point is inside
        assert np.all(solid.H(seg.reshape(-1, 3)) < 0)


def test_hybrid_combines_all_types_with_genus_above_5() -> None:
    spec = load_spec(EXAMPLES / "hybrid" / "model.yaml")
    solid = implicit_solid(spec)
    kinds = {type(c) for c in solid.components}
    assert kinds == {MeshComponent, ShellComponent, StrutsComponent, TubesComponent}
    surf = solid.surface()
    topo = surface_topology(surf.faces)
    assert surf.is_watertight and len(topo.genus) == 1 and topo.total_genus > 5
    assert solid.platform_z == pytest.approx(0.0, abs=1e-6)
    B = surface_samples(solid, 5000)
    diag = np.linalg.norm(solid.bounds[1] - solid.bounds[0])
    assert np.abs(solid.H(B.points)).max() < 1e-3 * diag
    # the base's bottom face (80 x 40 of ~this total area) lies on the platform
    assert B.on_platform.any() and np.all(B.normals[B.on_platform, 2] < -0.9)
    again = Solid.from_arrays(*solid.to_arrays())
    assert np.array_equal(again.H(B.points), solid.H(B.points))
    assert len(spec_digest(spec)) == 64
