"""Quality measured where the optimiser never looked: held-out samples of the surface mesh, the layers' normals."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from neuralslicer.metrics import heldout_surface_samples, layer_lpd_at, overhang_area_fraction
from neuralslicer.toolpath.synthetic import cap_stack, planar_stack


def test_heldout_samples_of_a_floating_box_see_its_bottom_overhang():
    box = trimesh.creation.box(extents=(10.0, 10.0, 10.0))          # z from -5 to 5
    up = np.tile([0.0, 0.0, 1.0], (20000, 1))
    for platform_z, expected in ((-5.0, 0.0), (-20.0, 1.0 / 6.0)):  # on the platform / lifted above it
        pts, normals, areas, on_platform = heldout_surface_samples(box, 20000, platform_z)
        assert len(pts) == 20000 and areas.sum() == pytest.approx(box.area)
        assert np.abs(np.abs(box.nearest.signed_distance(pts[:200]))).max() < 1e-9     # on the mesh
        assert overhang_area_fraction(normals, areas, on_platform, up, 45.0) == pytest.approx(expected, abs=0.01)
    a, *_ = heldout_surface_samples(box, 100, -5.0)
    b, *_ = heldout_surface_samples(box, 100, -5.0, seed=7)
    assert not np.allclose(a, b) and np.allclose(a, heldout_surface_samples(box, 100, -5.0)[0])   # seeded


def test_layer_lpd_is_the_nearest_layer_vertex_normal():
    flat = planar_stack(3, thickness=0.5, size=6.0, n=7)
    pts = np.random.default_rng(0).uniform([-3, -3, 0], [3, 3, 1.5], (50, 3))
    assert np.allclose(layer_lpd_at(flat, pts), [0.0, 0.0, 1.0])
    caps = cap_stack(2, r0=5.0, theta_max_deg=40.0, subdivisions=3)       # radial LPD about the origin
    on = np.asarray(caps[1].vertices[:20]) * 1.001
    d = layer_lpd_at(caps, on)
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)
    assert np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", d, on / np.linalg.norm(on, axis=1)[:, None]), -1, 1))).max() < 1.0


def test_field_agreement_measures_lpd_angles_and_print_order():
    from scipy.spatial import Delaunay

    from neuralslicer.metrics import field_agreement
    from neuralslicer.scalar_field import ScalarField

    g = np.stack(np.meshgrid(*[np.linspace(0, 10, 6)] * 3, indexing="ij"), -1).reshape(-1, 3)
    g = g + np.random.default_rng(0).normal(scale=1e-3, size=g.shape)
    tets = Delaunay(g).simplices.astype(np.int64)
    fields = {"up": ScalarField(g, tets, g[:, 2].copy()),
              "tilted": ScalarField(g, tets, g[:, 2] + 0.1 * g[:, 0]),
              "down": ScalarField(g, tets, -g[:, 2].copy())}
    pts = np.random.default_rng(1).uniform(0.5, 9.5, (500, 3))
    rows = {(r["a"], r["b"]): r for r in field_agreement(fields, pts)}
    assert set(rows) == {("up", "tilted"), ("up", "down"), ("tilted", "down")}
    tilt = np.degrees(np.arctan(0.1))
    assert rows[("up", "tilted")]["lpd_angle_median_deg"] == pytest.approx(tilt, abs=0.05)
    assert rows[("up", "tilted")]["lpd_angle_p90_deg"] == pytest.approx(tilt, abs=0.05)
    assert rows[("up", "down")]["lpd_angle_median_deg"] == pytest.approx(180.0, abs=0.05)
    assert rows[("up", "down")]["print_order_spearman"] == pytest.approx(-1.0, abs=1e-9)
    assert 0.95 < rows[("up", "tilted")]["print_order_spearman"] < 1.0
    assert rows[("up", "tilted")]["n_points"] == 500
