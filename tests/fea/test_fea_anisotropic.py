"""Anisotropic verification: a bar loaded along and across the stiff (toolpath) direction."""
from __future__ import annotations

import numpy as np
import pytest

from neuralslicer.fea import FEASpec
from neuralslicer.verify import verify_layers
from neuralslicer.fea.element import rotate_D, stress_rotation, transversely_isotropic_D
from neuralslicer.fea.shapes import BoxSolid
from neuralslicer.verify import material_frames

Y1, Y2, NU12 = 3500.0, 1200.0, 0.3
SIGMA = 2.0          # MPa: pressure -2 MPa on the 10 x 10 end face


def _const(v: tuple[float, float, float]):
    """A constant direction field."""
    return lambda p: np.tile(np.asarray(v, dtype=np.float64), (len(p), 1))


def _bar_spec() -> FEASpec:
    """40x10x10 bar, symmetry supports (free lateral contraction), tension by a face pressure."""
    return FEASpec.model_validate(dict(
        supports=[dict(plane=dict(axis="x", value=0.0), fix=[True, False, False]),
                  dict(plane=dict(axis="y", value=0.0), fix=[False, True, False]),
                  dict(plane=dict(axis="z", value=0.0), fix=[False, False, True])],
        loads=[dict(plane=dict(axis="x", value=40.0), pressure_mpa=-SIGMA)],
        voxels=40 * 10 * 10 // 8))


def test_rotated_constitutive_matrix_is_a_change_of_frame() -> None:
    """D rotated by R equals the strain energy in the rotated frame (and R = I is the identity)."""
    Dm = transversely_isotropic_D(Y1, Y2, NU12, 0.35, 775.0)
    assert np.allclose(rotate_D(Dm, np.eye(3)[None])[0], Dm)
    rng = np.random.default_rng(1)
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    T = stress_rotation(R[None])[0]
    sig_m = rng.normal(size=6)
    # sigma_global = R sigma_m R^T, compared through the Voigt transform
    from neuralslicer.fea.element import voigt_to_tensor
    assert np.allclose(voigt_to_tensor(T @ sig_m), R @ voigt_to_tensor(sig_m) @ R.T)


@pytest.mark.parametrize("tangent, lpd, modulus, lateral", [
    ((1, 0, 0), (0, 0, 1), Y1, NU12 * SIGMA / Y1),      # filaments along the load
    ((0, 1, 0), (0, 0, 1), Y2, None),                   # across, load in the weak 3-direction
    ((0, 1, 0), (1, 0, 0), Y2, None),                   # load along the LPD (layer normal)
])
def test_bar_strain_along_and_across_filaments(tangent, lpd, modulus, lateral) -> None:
    """Uniaxial stress sigma gives axial strain sigma / Y (Y1 along the toolpath, Y2 across)."""
    out = verify_layers(BoxSolid((0, 0, 0), (40, 10, 10)), _bar_spec(), _const(lpd),
                        _const(tangent))
    res = out["result"]
    assert np.allclose(res.stress[:, 0, 0], SIGMA, rtol=1e-6)
    assert np.allclose(res.strain[:, 0, 0], SIGMA / modulus, rtol=0.02)
    assert out["max_strain"] == pytest.approx(SIGMA / modulus, rel=0.02)
    if lateral is not None:
        assert np.allclose(res.strain[:, 1, 1], -lateral, rtol=0.02)
    tip = res.grid.nodes[:, 0] > 40 - 1e-9
    assert res.displacement[tip, 0].mean() == pytest.approx(40 * SIGMA / modulus, rel=0.02)


def test_default_tangent_follows_stress_projected_on_layers() -> None:
    """Without a toolpath, planar layers get filaments along tau_max (x) for an x-loaded bar."""
    spec = _bar_spec()
    out = verify_layers(BoxSolid((0, 0, 0), (40, 10, 10)), spec, _const((0, 0, 1)))
    assert out["tangent"].startswith("tau_max")
    assert out["max_strain"] == pytest.approx(SIGMA / Y1, rel=0.02)


def test_material_frames_orthonormal_and_fallback() -> None:
    """Frames are rotations with e2 = LPD; a tangent along the LPD falls back to the x axis."""
    lpd = np.array([[0, 0, 2.0], [0, 0, 1.0], [1.0, 0, 0]])
    tan = np.array([[1.0, 1.0, 5.0], [0, 0, 3.0], [1.0, 0, 0]])
    R = material_frames(lpd, tan)
    assert np.allclose(np.einsum("nji,njk->nik", R, R), np.eye(3))
    assert np.allclose(np.linalg.det(R), 1.0)
    assert np.allclose(R[:, :, 1], lpd / np.linalg.norm(lpd, axis=1)[:, None])
    assert np.allclose(R[0, :, 0], [2 ** -0.5, 2 ** -0.5, 0])
    assert np.allclose(R[1, :, 0], [1, 0, 0])            # x axis projected
    assert np.allclose(R[2, :, 0], [0, 1, 0])            # x degenerate too: y axis


def _lines_along_y(n_lines: int = 20):
    """Printed lines along +y across the 40 x 10 x 10 bar (one path per line, on five heights)."""
    from neuralslicer.toolpath.types import Toolpaths

    rows = []
    for z in np.linspace(1.0, 9.0, 5):
        for x in np.linspace(1.0, 39.0, n_lines):
            y = np.linspace(0.5, 9.5, 10)
            rows.append(np.column_stack([np.full_like(y, x), y, np.full_like(y, z)]))
    xyz = np.concatenate(rows)
    n, k = len(xyz), len(rows)
    return Toolpaths(layer=np.repeat(np.arange(k) // n_lines, 10), path=np.repeat(np.arange(k), 10), xyz=xyz,
                     axis=np.tile([0.0, 0.0, 1.0], (n, 1)), thickness=np.full(n, 2.0), width=np.full(n, 2.0),
                     extrude=np.tile(np.r_[False, np.ones(9, bool)], k))


def test_printed_toolpaths_set_the_stiff_axis_where_the_ideal_one_would_flatter() -> None:
    """An x-loaded bar printed with lines along y is as weak as Y2 says, though tau_max lies along x: the
    verification on printed tangents and the ideal one differ by Y1 / Y2."""
    from neuralslicer.verify import printed_tangents

    tp = _lines_along_y()
    tangent_at = printed_tangents(tp)
    probe = np.array([[5.0, 5.0, 5.0], [20.0, 2.0, 8.0]])
    assert np.allclose(tangent_at(probe), [[0.0, 1.0, 0.0]] * 2)
    solid, spec = BoxSolid((0, 0, 0), (40, 10, 10)), _bar_spec()
    printed = verify_layers(solid, spec, _const((0, 0, 1)), tangent_at=tangent_at)
    ideal = verify_layers(solid, spec, _const((0, 0, 1)))
    assert printed["tangent"] == "given" and ideal["tangent"].startswith("tau_max")
    assert printed["max_strain"] == pytest.approx(SIGMA / Y2, rel=0.02)
    assert ideal["max_strain"] == pytest.approx(SIGMA / Y1, rel=0.02)


def _field_z():
    """The height field G = z on a cage around the 40 x 10 x 10 bar: planar layers."""
    from scipy.spatial import Delaunay

    from neuralslicer.scalar_field import ScalarField

    g = np.stack(np.meshgrid(np.linspace(-1, 41, 8), np.linspace(-1, 11, 4), np.linspace(-1, 11, 4), indexing="ij"), -1)
    verts = g.reshape(-1, 3) + np.random.default_rng(0).normal(scale=1e-3, size=(g.size // 3, 3))   # no flat tets
    return ScalarField(verts, Delaunay(verts).simplices.astype(np.int64), verts[:, 2].copy())


def test_verify_field_is_the_ideal_best_case_for_both_parts() -> None:
    """verify_field (verify_tangents: ideal) gives planar layers and the field's layers tau_max as stiff axis: an
    x-loaded bar with planar layers strains sigma / Y1 in both, and the parts say how they were verified."""
    from neuralslicer.verify import verify_field

    strains, figures = verify_field(BoxSolid((0, 0, 0), (40, 10, 10)), _bar_spec(), _field_z())
    assert figures["parts"] == ["planar", "printed"]
    for part in figures["parts"]:
        assert figures[f"{part}.tangent"].startswith("ideal")
        assert figures[f"{part}.max_strain"] == pytest.approx(SIGMA / Y1, rel=0.02)
        assert strains[f"strain/{part}"].shape == strains["centres"][:, 0].shape


def test_a_part_printed_across_the_load_has_none_of_its_filaments_aligned() -> None:
    """The printed part of lines along y in the x-loaded bar: strain sigma / Y2 and 0 % of the filament length within
    20 degrees of tau_max (x); the same lines turned to x: sigma / Y1 and 100 %."""
    from neuralslicer.fea import run_fea
    from neuralslicer.verify import _part

    solid, spec = BoxSolid((0, 0, 0), (40, 10, 10)), _bar_spec()
    reference = run_fea(solid, spec)
    across = _lines_along_y()
    arrays, figures = _part(solid, spec, _const((0, 0, 1)), across, reference)
    assert figures["max_strain"] == pytest.approx(SIGMA / Y2, rel=0.02)
    assert figures["aligned_fraction"] == 0.0 and np.allclose(arrays["angles"], 90.0, atol=1e-6)
    along = _lines_along_y()
    along.xyz = along.xyz[:, [1, 0, 2]] * [4.0, 0.25, 1.0]          # the same rows of lines, turned along x
    arrays, figures = _part(solid, spec, _const((0, 0, 1)), along, reference)
    assert figures["max_strain"] == pytest.approx(SIGMA / Y1, rel=0.05)
    assert figures["aligned_fraction"] == 1.0


def test_filament_alignment_weighs_filaments_by_length() -> None:
    """Hand-made filaments in the x-loaded bar (tau_max = x everywhere, every voxel counted): 10 mm at 0°, 5 mm at 15°,
    8 mm at 30° and 5 mm at 90°: 15 of the 28 mm lie within 20° of tau_max."""
    from neuralslicer.fea import run_fea
    from neuralslicer.verify import filament_alignment
    from neuralslicer.toolpath.types import Toolpaths

    solid, spec = BoxSolid((0, 0, 0), (40, 10, 10)), _bar_spec()
    reference = run_fea(solid, spec)
    lines = [((5.0, 2.0), 0.0, 10.0), ((5.0, 4.0), 15.0, 5.0), ((20.0, 1.0), 30.0, 8.0), ((32.0, 2.0), 90.0, 5.0)]
    rows = []
    for (x, y), angle, length in lines:
        d = np.array([np.cos(np.radians(angle)), np.sin(np.radians(angle)), 0.0])
        rows.append(np.array([x, y, 5.0]) + np.linspace(0.0, length, 11)[:, None] * d)
    xyz = np.concatenate(rows)
    n = len(xyz)
    tp = Toolpaths(layer=np.zeros(n, np.int64), path=np.repeat(np.arange(4), 11), xyz=xyz,
                   axis=np.tile([0.0, 0.0, 1.0], (n, 1)), thickness=np.ones(n), width=np.ones(n),
                   extrude=np.tile(np.r_[False, np.ones(10, bool)], 4))
    out = filament_alignment(tp, reference, top_fraction=1.0)
    assert np.allclose(np.sort(out["angles_deg"]), np.repeat([0.0, 15.0, 30.0, 90.0], 10), atol=0.5)
    assert out["lengths"].sum() == pytest.approx(28.0)
    assert out["aligned_fraction"] == pytest.approx(15.0 / 28.0, rel=1e-6)


def test_strain_gains_split_the_gain_into_filaments_and_layers() -> None:
    """Hand-computed: planar + zig-zag 4e-3, planar + stress infill 3e-3, printed 2.4e-3 (max strain): the
    filaments earn 25 %, the layers 20 % on top, 40 % in all; a missing part gives no gain."""
    from neuralslicer.verify import strain_gains

    figures = {"planar_zigzag.max_strain": 4e-3, "planar_stress.max_strain": 3e-3, "printed.max_strain": 2.4e-3,
               "planar_zigzag.max_strain_p99": 2e-3, "planar_stress.max_strain_p99": 2e-3,
               "printed.max_strain_p99": 2.2e-3}
    gains = strain_gains(figures)
    assert gains["gain.filaments.max_strain"] == pytest.approx(0.25)
    assert gains["gain.layers.max_strain"] == pytest.approx(0.20)
    assert gains["gain.total.max_strain"] == pytest.approx(0.40)
    assert gains["gain.filaments.max_strain_p99"] == pytest.approx(0.0)
    assert gains["gain.layers.max_strain_p99"] == pytest.approx(-0.10)
    assert strain_gains({"printed.max_strain": 1.0}) == {}
