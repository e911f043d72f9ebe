"""The cage: encloses the whole solid, element count near the target, positively oriented tets, the same cage from
the same inputs and seed."""
import sys

import numpy as np
import pytest
import trimesh

from conftest import l_part_mesh
from neuralslicer.cage import CageConfig, build_cage, check_containment, interior_points
from neuralslicer.model.components import MeshComponent
from neuralslicer.model.solid import Solid
from neuralslicer.samples import surface_samples
from neuralslicer.tetmesh import TetLocator, tet_volumes
from neuralslicer.topology import tet_boundary_genus


@pytest.mark.parametrize(
    "mesh, target, genus",
    [
        (l_part_mesh(), 1500, 0),
        (trimesh.creation.torus(major_radius=10, minor_radius=3, major_sections=48, minor_sections=16), 3000, 1),
    ],
    ids=["l-part", "torus"],
)
def test_cage_contains_surface_samples_and_interior_points(mesh, target, genus):
    solid = Solid([MeshComponent(np.asarray(mesh.vertices), np.asarray(mesh.faces))])
    B = surface_samples(solid, 3000, seed=2)
    inside = interior_points(solid.H, solid.bounds, 5000, seed=3)
    assert len(inside) == 5000 and np.all(solid.H(inside) < 0)
    cage = build_cage(solid.H, solid.bounds, solid.volume(), CageConfig(n_elements=target), np.concatenate([B.points, inside]))
    assert np.all(tet_volumes(cage.vertices, cage.tets) > 0)
    assert 0.6 * target <= len(cage.tets) <= 1.5 * target
    # an independent check with fresh points: every surface sample and interior point lies in a cage tet
    fresh = np.concatenate([surface_samples(solid, 4000, seed=9).points, interior_points(solid.H, solid.bounds, 4000, seed=11)])
    tet, bary = TetLocator(cage.vertices, cage.tets).locate(fresh)
    assert np.all(tet >= 0)
    assert np.allclose(np.einsum("ni,nij->nj", bary, cage.vertices[cage.tets[tet]]), fresh, atol=1e-8)
    assert len(check_containment(cage, fresh)) == 0
    # the cage is an offset of the solid: its genus is at most the model's (the torus keeps its hole)
    assert tet_boundary_genus(cage.tets) == genus


def test_cage_element_count_follows_the_target():
    mesh = l_part_mesh()
    solid = Solid([MeshComponent(np.asarray(mesh.vertices), np.asarray(mesh.faces))])
    pts = interior_points(solid.H, solid.bounds, 2000)
    counts = [len(build_cage(solid.H, solid.bounds, solid.volume(), CageConfig(n_elements=n), pts).tets) for n in (800, 3200)]
    assert counts[1] > 2.5 * counts[0]


def _torus_cage(seed: int):
    """The cage of a 26 mm torus at 1500 tets, fTetWild seeded with ``seed``."""
    mesh = trimesh.creation.torus(major_radius=10, minor_radius=3, major_sections=48, minor_sections=16)
    solid = Solid([MeshComponent(np.asarray(mesh.vertices), np.asarray(mesh.faces))])
    points = interior_points(solid.H, solid.bounds, 2000)
    return build_cage(solid.H, solid.bounds, solid.volume(), CageConfig(n_elements=1500, seed=seed), points)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="fTetWild's draw is seeded on Linux only")
def test_cage_is_a_function_of_its_inputs_and_seed():
    # unseeded, fTetWild draws its triangle order anew on every call, and the second mesh of a process differs from
    # the first even with that draw fixed (its generators keep their state): each call is a fresh, seeded process
    first, again, other = _torus_cage(0), _torus_cage(0), _torus_cage(1)
    assert first.seeded and again.seeded
    assert np.array_equal(first.vertices, again.vertices) and np.array_equal(first.tets, again.tets)
    assert other.sha256() != first.sha256()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="an ELF extension on Linux only")
def test_the_seeded_slot_is_pytetwilds_random_device_draw():
    from pytetwild import PyfTetWildWrapper

    from neuralslicer.tetwild_seed import got_slots

    assert len(got_slots(PyfTetWildWrapper.__file__)) == 1
    assert got_slots(PyfTetWildWrapper.__file__, b"no_such_symbol") == []
    assert got_slots(__file__) == []  # not an ELF file
