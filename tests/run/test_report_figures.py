"""The operator's pictures of the report: overhang map, bead thickness, layer toolpaths, 3D layer preview."""
from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import matplotlib.image as mpimg
import numpy as np
import pytest

from neuralslicer.metrics import overhang_area_fraction
from neuralslicer.motion.collision import CollisionMap
from neuralslicer.run import report
from neuralslicer.run.outputs import draw_figures
from neuralslicer.run.report import (_layer_frame, offscreen_rendering_available, plot_layer_toolpaths, plot_layers_3d,
                                     plot_overhang_map, plot_thickness_map, representative_layers)
from neuralslicer.samples import SurfaceSamples
from neuralslicer.toolpath.beads import bead_summary
from neuralslicer.toolpath.generate import toolpaths
from neuralslicer.toolpath.synthetic import cap_stack, planar_stack
from neuralslicer.toolpath.types import Toolpaths

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def assert_picture(path: Path) -> None:
    """A non-empty PNG file whose pixels are not all one colour."""
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC, path
    image = mpimg.imread(path)
    assert image.ndim == 3 and min(image.shape[:2]) > 100
    assert float(image[..., :3].std()) > 0.02, f"{path} looks blank"


def fibonacci_sphere(n: int, radius: float = 10.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points (n, 3), outward normals (n, 3) and equal areas (n,) of a sphere centred at (0, 0, radius)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    r = np.sqrt(1.0 - z ** 2)
    normals = np.column_stack([r * np.cos(phi), r * np.sin(phi), z])
    return normals * radius + [0.0, 0.0, radius], normals, np.full(n, 4 * np.pi * radius ** 2 / n)


@pytest.fixture(scope="module")
def cap_toolpaths() -> Toolpaths:
    """Toolpaths of six concentric spherical caps (curved layers, tool axes radial)."""
    return toolpaths(cap_stack(6, thickness=0.5, r0=6.0, theta_max_deg=35.0, subdivisions=4), platform_z=-20.0)


@pytest.mark.slow   # over 10 s: the full suite runs it, `make test-fast` does not
def test_overhang_map_shows_the_metric(tmp_path: Path) -> None:
    """The fractions in the titles are overhang_area_fraction's, and the planar one is the closed form
    (1 - sin α) / 2 of a sphere (the cap below z = -R sin α)."""
    points, normals, areas = fibonacci_sphere(6000)
    on_platform = normals[:, 2] < -0.99
    planar = np.tile([0.0, 0.0, 1.0], (len(points), 1))
    tilted = np.tile([np.sin(0.3), 0.0, np.cos(0.3)], (len(points), 1))
    out = tmp_path / "overhang_map.png"
    shown = plot_overhang_map(out, points, normals, {"planar": planar, "tilted": tilted, "radial": normals}, 45.0,
                              areas, on_platform, max_points=3000)
    assert_picture(out)
    for label, d in (("planar", planar), ("tilted", tilted), ("radial", normals)):
        assert shown[label] == pytest.approx(overhang_area_fraction(normals, areas, on_platform, d, 45.0), abs=1e-12)
    plain = plot_overhang_map(tmp_path / "plain.png", points, normals, {"planar": planar}, 45.0, areas)
    assert plain["planar"] == pytest.approx((1 - np.sin(np.radians(45.0))) / 2, abs=5e-3)
    assert shown["radial"] == 0.0


def test_thickness_map_counts_beads_outside_the_range(tmp_path: Path, cap_toolpaths: Toolpaths) -> None:
    """Fractions below / above the bead range are those of the extruding waypoints, counted directly."""
    tp = cap_toolpaths
    t = tp.thickness[tp.extrude]
    lo, hi = np.quantile(t, [0.1, 0.8]) if np.ptp(t) > 0 else (0.9 * t[0], 1.1 * t[0])
    out = tmp_path / "bead_thickness.png"
    stats = plot_thickness_map(out, tp.xyz, tp.thickness, tp.extrude, (lo, hi), max_points=2000)
    assert_picture(out)
    assert stats["n"] == int(tp.extrude.sum())
    assert stats["below"] == pytest.approx(np.mean(t < lo))
    assert stats["above"] == pytest.approx(np.mean(t > hi))
    assert stats["outside"] == pytest.approx(stats["below"] + stats["above"])


@pytest.mark.slow   # over 10 s: the full suite runs it, `make test-fast` does not
def test_layer_toolpaths_pick_first_thirds_and_last(tmp_path: Path) -> None:
    """Four layers drawn, first and last among them, projected on planes of their mean tool axis."""
    tp = toolpaths(planar_stack(7, thickness=0.5, size=10.0), platform_z=0.0)
    assert representative_layers(tp.layer, tp.path) == [0, 2, 4, 6]
    out = tmp_path / "layer_toolpaths.png"
    assert plot_layer_toolpaths(out, tp) == [0, 2, 4, 6]
    assert_picture(out)
    assert plot_layer_toolpaths(tmp_path / "two.png", tp, [1, 3]) == [1, 3]
    assert_picture(tmp_path / "two.png")


def test_layer_frame_is_orthonormal_around_the_mean_axis() -> None:
    """(u, v, a) is a right-handed orthonormal frame with a the mean tool axis; +z keeps x and y."""
    rng = np.random.default_rng(1)
    axes = np.array([0.3, -0.2, 0.9]) + 0.05 * rng.standard_normal((50, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    frame = _layer_frame(axes)
    np.testing.assert_allclose(frame @ frame.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(frame) == pytest.approx(1.0)
    mean = axes.mean(axis=0)
    np.testing.assert_allclose(frame[2], mean / np.linalg.norm(mean), atol=1e-12)
    np.testing.assert_allclose(_layer_frame(np.tile([0.0, 0.0, 1.0], (3, 1))), np.eye(3), atol=1e-12)


def test_layer_preview_renders_or_falls_back(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """pyvista draws the preview wherever off-screen rendering is available; matplotlib when told to."""
    layers = cap_stack(30, thickness=0.3, r0=6.0, theta_max_deg=45.0, subdivisions=3)
    out = tmp_path / "layers.png"
    renderer = plot_layers_3d(out, layers)
    assert renderer == ("pyvista" if offscreen_rendering_available() else "matplotlib")
    assert_picture(out)
    monkeypatch.setenv("NEURALSLICER_RENDERER", "matplotlib")
    assert plot_layers_3d(tmp_path / "mpl.png", layers) == "matplotlib"
    assert_picture(tmp_path / "mpl.png")


def test_large_layers_are_coarsened_keeping_their_print_order() -> None:
    """Layers over their share of the face budget are vertex-clustered; every face keeps its layer index."""
    layers = cap_stack(4, thickness=0.5, r0=6.0, theta_max_deg=60.0, subdivisions=6)
    vertices, faces, order = report._merged_layers(layers, [0, 2, 3], max_faces=3000)
    full = sum(len(layers[i].faces) for i in (0, 2, 3))
    assert len(faces) < full / 2 and len(faces) == len(order)
    assert set(order.tolist()) == {0, 2, 3} and np.all(np.diff(order) >= 0)
    assert faces.min() >= 0 and faces.max() < len(vertices)
    radii = np.linalg.norm(vertices, axis=1)
    assert radii.min() > 6.0 and radii.max() < 8.1  # the clustered vertices stay near the caps (r = 6.5 .. 8)


def test_layer_preview_falls_back_without_a_backend_or_on_failure(tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """No display and no loadable EGL/OSMesa: matplotlib without touching VTK; a render error: matplotlib too."""
    layers = cap_stack(8, thickness=0.3, r0=6.0, theta_max_deg=45.0, subdivisions=3)
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.setattr(report, "_loadable", lambda name: False)
    monkeypatch.setattr(report, "_render_views", lambda *args: pytest.fail("VTK used without a backend"))
    assert report.offscreen_backend() is None
    assert plot_layers_3d(tmp_path / "none.png", layers) == "matplotlib"
    assert_picture(tmp_path / "none.png")
    monkeypatch.setenv("DISPLAY", ":99")

    def broken(*args: object) -> None:
        raise RuntimeError("no GL context")

    monkeypatch.setattr(report, "_render_views", broken)
    with pytest.warns(UserWarning, match="no GL context"):
        assert plot_layers_3d(tmp_path / "broken.png", layers) == "matplotlib"
    assert_picture(tmp_path / "broken.png")


def test_draw_figures_embeds_the_operator_pictures(tmp_path: Path, cap_toolpaths: Toolpaths) -> None:
    """draw_figures writes every picture it lists, the four new ones among them."""
    points, normals, areas = fibonacci_sphere(3000)
    samples = SurfaceSamples(points, normals, areas, np.zeros((len(points), 1), np.int64), normals[:, 2] < -0.99)
    tp = cap_toolpaths
    nozzle = SimpleNamespace(bead_thickness_mm=(0.15, 1.2))
    run = SimpleNamespace(
        samples=samples, lpd_b=normals, layers=SimpleNamespace(meshes=cap_stack(6, 0.5, 6.0, 35.0, 4)),
        toolpaths=tp, program=SimpleNamespace(profile=SimpleNamespace(nozzle=nozzle)), stress_samples=None, verify=None,
        strength_rounds=[],
        field_history={}, collision_maps={"printed": CollisionMap.of(tp.xyz, np.zeros(len(tp), bool))},
        print_metrics={"beads": bead_summary(tp, nozzle.bead_thickness_mm)})
    figures = draw_figures(tmp_path / "figures", run, 45.0, 30.0)
    for caption in ("Overhang map (planar vs computed)", "Bead thickness", "Toolpaths of representative layers"):
        assert caption in figures
    assert {"Layers (pyvista)", "Layers (matplotlib)"} & set(figures)
    for rel in figures.values():
        assert_picture(tmp_path / rel)


def test_the_report_opens_with_what_a_user_looks_for_first() -> None:
    """report.md: a summary (layers, time, material, collisions, overhang and strain against planar) before the
    alphabetical table of every metric; a run without an FEA or held-out figures leaves those rows out."""
    metrics = {"n_layers": 56, "estimated_print_time_s": 9574.7, "material_mm3": 24_600.0, "n_collisions": 0,
               "sf.heldout.overhang_area_fraction_layers": 0.0025, "sf.heldout.overhang_area_fraction_planar": 0.0046,
               "fea.max_strain": 1.813e-3, "fea.planar_zigzag.max_strain": 2.572e-3, "beads.n_capped": 63}
    text = report.markdown_report("t", metrics, {})
    summary = text[text.index("## Summary"):text.index("## All metrics")]
    for row in ("| layers | 56 |", "| estimated print time | 2 h 39 min |", "| material | 24.6 cm³ |",
                "| nozzle collisions | 0 |", "(0.46 %)", "0.001813 (0.002572, -29.5 %)"):
        assert row in summary, row
    assert "beads" not in summary and "| `beads.n_capped` | 63 |" in text
    bare = report.summary_rows({"n_layers": 3})
    assert bare == [("layers", "3")]


def _write(path: Path, text: str) -> dict[str, str]:
    """A job: write a file, name it as a figure."""
    path.write_text(text)
    return {text: path.name}


@pytest.mark.parametrize("helper", ["1", "0"])
def test_export_jobs_give_every_result_in_order_with_or_without_a_helper(tmp_path: Path, helper: str,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """The export's independent jobs (figures, the toolpaths' files) shared with a forked helper process: every job
    runs once, its files are written, and the figures come back in the jobs' order whoever did them."""
    from neuralslicer.forked import FORK_ENV
    from neuralslicer.run.outputs import ExportJobs

    monkeypatch.setenv(FORK_ENV, helper)
    jobs = [(float(i % 3), (lambda i=i: _write(tmp_path / f"f{i}.txt", f"job {i}"))) for i in range(7)]
    figures = ExportJobs(jobs).finish()
    assert [next(iter(f)) for f in figures] == [f"job {i}" for i in range(7)]
    assert all((tmp_path / f"f{i}.txt").read_text() == f"job {i}" for i in range(7))


def test_a_job_that_fails_in_the_helper_fails_the_export_with_its_error(tmp_path: Path) -> None:
    """A job the helper process could not do is done again by the exporting process, which raises its error."""
    from neuralslicer.run.outputs import ExportJobs

    def broken() -> dict[str, str]:
        raise ValueError("no such layer")

    import time

    jobs = ExportJobs([(9.0, broken)] + [(0.0, lambda: {})] * 3)
    time.sleep(1.0)   # what the exporting process writes meanwhile: the helper takes every job
    with pytest.warns(UserWarning, match="no such layer"), pytest.raises(ValueError, match="no such layer"):
        jobs.finish()


def test_a_collision_map_keeps_what_its_figure_draws():
    """A print's collision map keeps every ``n // MAP_POINTS``-th clear and colliding waypoint, the counts and the
    bounds of all waypoints: what ``plot_collision_map`` drew from the whole print."""
    from neuralslicer.motion.collision import MAP_POINTS

    rng = np.random.default_rng(3)
    xyz = rng.normal(size=(3 * MAP_POINTS + 123, 3)) * [30.0, 20.0, 40.0]     # 2.99 clear a kept one
    hit = np.zeros(len(xyz), bool)
    hit[rng.choice(len(xyz), 300, replace=False)] = True
    m = CollisionMap.of(xyz, hit)
    assert m.n_waypoints == len(xyz) and m.n_hit == 300
    assert np.array_equal(m.hit, xyz[hit])                                   # few: every colliding one
    assert np.array_equal(m.clear, xyz[~hit][::2])                           # many: every other clear one
    assert np.array_equal(m.bounds, [xyz.min(axis=0), xyz.max(axis=0)])
    assert np.array_equal(CollisionMap.of_indices(xyz, np.flatnonzero(hit)).hit, m.hit)
    empty = CollisionMap.of(np.zeros((0, 3)), np.zeros(0, bool))
    assert empty.n_waypoints == 0 and empty.bounds.shape == (0, 3)
