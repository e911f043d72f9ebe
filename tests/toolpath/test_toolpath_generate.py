"""Toolpaths on synthetic layers: on-layer, volume, thickness, axes, inside the solid, files."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from neuralslicer.errors import InputError
from neuralslicer.toolpath import (ToolpathConfig, Toolpaths, read_waypoints_csv, toolpath_config_from_dict,
                                   toolpaths, write_toolpaths_vtp, write_waypoints_csv)
from neuralslicer.toolpath.synthetic import cap_stack, disc_layer, planar_stack, square_layer, tilted_stack


@pytest.fixture(scope="module")
def box_paths():
    layers = planar_stack(8, thickness=0.5, size=10.0)
    return layers, toolpaths(layers, platform_z=0.0)


@pytest.fixture(scope="module")
def cap_paths():
    layers = cap_stack(5, thickness=0.5, r0=10.0, theta_max_deg=35.0, subdivisions=4)
    return layers, toolpaths(layers, platform_z=-20.0)


def _distance_to_layers(tp: Toolpaths, layers) -> np.ndarray:
    on = tp.path >= 0
    dist = np.zeros(len(tp))
    for li, layer in enumerate(layers):
        m = on & (tp.layer == li)
        if m.any():
            _, d, _ = trimesh.proximity.closest_point(layer, tp.xyz[m])
            dist[m] = d
    return dist[on]


def test_waypoints_lie_on_their_layers(box_paths, cap_paths):
    for layers, tp in (box_paths, cap_paths):
        assert _distance_to_layers(tp, layers).max() < 1e-3


def test_box_volume_at_full_infill_matches_the_solid(box_paths):
    _, tp = box_paths
    volume = 10.0 * 10.0 * 4.0
    assert abs(tp.deposited_volume() / volume - 1.0) < 0.15
    on = tp.path >= 0
    assert np.allclose(tp.thickness[on], 0.5, atol=1e-9)
    assert np.allclose(tp.axis[on], [0, 0, 1], atol=1e-12)
    # waypoints stay half a line inside the square's edge
    assert np.abs(tp.xyz[on, :2]).max() <= 5.0 - 0.25 + 0.05


@pytest.mark.parametrize("infill", ["contour", "zigzag"])
def test_cylinder_volume_and_inside_solid(infill):
    layers = [disc_layer(0.4 * (i + 1), radius=6.0, n_rings=12, n_sectors=64) for i in range(5)]
    tp = toolpaths(layers, platform_z=0.0, config=ToolpathConfig(infill=infill))
    volume = np.pi * 6.0 ** 2 * 2.0
    assert abs(tp.deposited_volume() / volume - 1.0) < 0.15
    on = tp.path >= 0
    H = np.maximum(np.linalg.norm(tp.xyz[on, :2], axis=1) - 6.0, -tp.xyz[on, 2])   # cylinder, H<0 inside
    assert H.max() <= 1e-3


def test_sparse_infill_deposits_less():
    layers = planar_stack(3, size=12.0)
    full = toolpaths(layers, 0.0, ToolpathConfig(n_shells=1)).deposited_volume()
    half = toolpaths(layers, 0.0, ToolpathConfig(n_shells=1, infill_density=0.5)).deposited_volume()
    shells = toolpaths(layers, 0.0, ToolpathConfig(n_shells=1, infill="none")).deposited_volume()
    assert shells < half < full
    assert abs((half - shells) / (full - shells) - 0.5) < 0.1


def test_curved_layers_axis_and_thickness(cap_paths):
    layers, tp = cap_paths
    on = tp.path >= 0
    radial = tp.xyz[on] / np.linalg.norm(tp.xyz[on], axis=1, keepdims=True)
    ang = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", radial, tp.axis[on]), -1, 1)))
    assert ang.max() < 1.0
    later = on & (tp.layer > 0)
    assert np.allclose(tp.thickness[later], 0.5, atol=0.01)
    first = on & (tp.layer == 0)
    assert np.allclose(tp.thickness[first], 1.0)  # capped at t_max (default 1 mm)
    # the caps follow the layers' t_max, the one place the thickness limits are set
    thin = toolpaths(layers, platform_z=-20.0, t_max=0.8)
    assert np.allclose(thin.thickness[(thin.path >= 0) & (thin.layer == 0)], 0.8)
    assert thin.thickness[thin.path >= 0].max() <= 1.5 * 0.8 + 1e-12


def test_tilted_stack_thickness_along_the_normal():
    layers = tilted_stack(4, tilt_deg=30.0, thickness=0.5)
    tp = toolpaths(layers, platform_z=0.0)
    on = (tp.path >= 0) & (tp.layer > 0)
    assert np.allclose(tp.thickness[on], 0.5, atol=1e-6)
    assert _distance_to_layers(tp, layers).max() < 1e-3


@pytest.mark.parametrize("stack", ["box_paths", "cap_paths"])
def test_travel_lifts_along_the_tool_axis(stack, request):
    _, tp = request.getfixturevalue(stack)
    lift = np.flatnonzero(tp.path < 0)
    assert len(lift) > 0 and not tp.extrude[lift].any()
    # first lift point of a pair sits travel_lift above the end of the previous path, along the axis that printed
    # it, and keeps that axis (the head turns to the next path's axis on the way, not at the part): between
    # layers too, where the next layer's first axis differs from the last one's
    pairs = lift[tp.path[lift - 1] >= 0]
    d = tp.xyz[pairs] - tp.xyz[pairs - 1]
    assert np.allclose(d, ToolpathConfig().travel_lift * tp.axis[pairs - 1])
    assert np.allclose(tp.axis[pairs], tp.axis[pairs - 1])
    if stack == "cap_paths":   # the lifts at a layer change (lift points carry the next layer's index)
        layer_change = pairs[tp.layer[pairs] != tp.layer[pairs - 1]]
        assert len(layer_change) and not np.allclose(tp.axis[layer_change + 2], tp.axis[layer_change - 1])
    # every path starts with a travel
    starts = np.flatnonzero(np.diff(tp.path, prepend=-2) != 0) 
    assert not tp.extrude[starts].any()


def test_round_trips(tmp_path, box_paths):
    _, tp = box_paths
    arrays, attrs = tp.to_arrays()
    back = Toolpaths.from_arrays(arrays, attrs)
    assert np.array_equal(back.xyz, tp.xyz) and np.array_equal(back.extrude, tp.extrude)
    assert attrs["schema_version"] == 1
    csv = write_waypoints_csv(tmp_path / "toolpaths" / "waypoints.csv", tp)
    assert csv.read_text().splitlines()[0] == "layer,path,x,y,z,nx,ny,nz,thickness,width,extrude"
    again = read_waypoints_csv(csv)
    assert np.allclose(again.xyz, tp.xyz, atol=1e-6) and np.array_equal(again.path, tp.path)
    import pyvista as pv
    vtp = write_toolpaths_vtp(tmp_path / "toolpaths.vtp", tp)
    mesh = pv.read(vtp)
    assert mesh.n_points == len(tp) and mesh.n_lines == len(np.unique(tp.path[tp.path >= 0]))
    assert not list(tmp_path.glob(".*"))   # no temporary files left


def test_files_of_a_large_print_are_written_in_chunks(tmp_path, box_paths, monkeypatch):
    """The CSV is formatted a few rows at a time (bounded memory) and reads the same bytes as written whole; the VTP's
    polylines are runs of extruding waypoints with the travel waypoint before each, as a loop over them builds."""
    import neuralslicer.toolpath.io as io

    _, tp = box_paths
    whole = write_waypoints_csv(tmp_path / "whole.csv", tp).read_bytes()
    monkeypatch.setattr(io, "CSV_CHUNK_ROWS", 7)
    assert write_waypoints_csv(tmp_path / "chunked.csv", tp).read_bytes() == whole
    assert whole.count(b"\n") == len(tp) + 1
    lines, first = io._polylines(tp)
    expected, starts, current = [], [], []
    for i in range(len(tp)):
        if not tp.extrude[i]:
            if len(current) > 1 or (current and tp.extrude[current[-1]]):
                expected += [len(current), *current]
                starts.append(current[0])
            current = [i] if i + 1 < len(tp) and tp.extrude[i + 1] else []
        else:
            current.append(i)
    if current:
        expected += [len(current), *current]
        starts.append(current[0])
    assert lines.tolist() == expected and first.tolist() == starts


def test_user_errors():
    with pytest.raises(InputError):
        toolpaths([], platform_z=0.0)
    with pytest.raises(InputError, match="line_width"):
        toolpath_config_from_dict({"line_width": -1})
    with pytest.raises(InputError, match="too small"):
        toolpaths(planar_stack(1, size=0.2, n=3), 0.0)


def test_triangle_soup_with_flipped_faces_gives_the_same_paths():
    layers = planar_stack(2, size=8.0, n=9)
    ref = toolpaths(layers, 0.0)
    soup = []
    rng = np.random.default_rng(0)
    for m in layers:
        f = m.faces.copy()
        flip = rng.random(len(f)) < 0.5
        f[flip] = f[flip][:, ::-1]
        v = m.vertices[f.ravel()]                      # every face has its own vertices
        s = trimesh.Trimesh(v, np.arange(len(v)).reshape(-1, 3), process=False)
        s.vertex_attributes["lpd"] = np.tile([0, 0, 1.0], (len(v), 1))
        soup.append(s)
    tp = toolpaths(soup, 0.0)
    assert np.isclose(tp.deposited_volume(), ref.deposited_volume(), rtol=1e-6)
    assert tp.attrs["n_paths"] == ref.attrs["n_paths"]


def _bowl_layers(isovalues: tuple[float, ...]) -> list[trimesh.Trimesh]:
    """Bowl layers G = z - 0.03 r^2 by marching cubes (irregular triangles), trimmed to a cylinder of radius 9,
    with their analytic LPDs."""
    from skimage.measure import marching_cubes

    h = 0.5
    xs = np.arange(-11, 11.01, h)
    zs = np.arange(-1, 9, h)
    X, Y, Z = np.meshgrid(xs, xs, zs, indexing="ij")
    G = Z - 0.03 * (X ** 2 + Y ** 2)
    layers = []
    for iso in isovalues:
        v, f, _, _ = marching_cubes(G, iso, spacing=(h, h, h))
        v = v + [xs[0], xs[0], zs[0]]
        f = f[(np.linalg.norm(v[:, :2], axis=1) <= 9.0)[f].all(axis=1)]
        grad = np.column_stack([-0.06 * v[:, 0], -0.06 * v[:, 1], np.ones(len(v))])
        m = trimesh.Trimesh(v, f, process=False)
        m.vertex_attributes["lpd"] = grad / np.linalg.norm(grad, axis=1, keepdims=True)
        layers.append(m)
    return layers


def test_irregular_curved_layers_from_marching_cubes():
    """Bowl layers G = z - 0.03 r^2 (irregular triangles), trimmed to a cylinder: analytic thickness."""
    layers = _bowl_layers((0.6, 1.2, 1.8))
    tp = toolpaths(layers, platform_z=0.0)
    assert _distance_to_layers(tp, layers).max() < 1e-3
    on = (tp.path >= 0) & (tp.layer > 0)
    r = np.linalg.norm(tp.xyz[on, :2], axis=1)
    inner = r < 7.0
    expected = 0.6 / np.sqrt(1 + (0.06 * r) ** 2)
    assert np.allclose(tp.thickness[on][inner], expected[inner], rtol=0.03)
    lpd = np.column_stack([-0.06 * tp.xyz[on, 0], -0.06 * tp.xyz[on, 1], np.ones(on.sum())])
    lpd /= np.linalg.norm(lpd, axis=1, keepdims=True)
    assert np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", lpd, tp.axis[on]), -1, 1))).max() < 1.0
    assert np.linalg.norm(tp.xyz[tp.path >= 0, :2], axis=1).max() <= 9.0


def _edge_use(faces: np.ndarray) -> np.ndarray:
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0, return_counts=True)[1]


def test_band_refinement_is_conforming_and_only_near_the_boundary():
    from neuralslicer.toolpath.geometry import Patch, boundary_vertices, refine_patch

    layer = disc_layer(1.0, radius=20.0, n_rings=4, n_sectors=24)          # coarse: edges ~5 mm
    patch = Patch(np.asarray(layer.vertices), np.asarray(layer.faces), layer.vertex_attributes["lpd"])
    band, h = 2.0, 0.5
    fine = refine_patch(patch, h, band=band)
    full = refine_patch(patch, h)
    for p in (fine, full):
        assert _edge_use(p.faces).max() == 2                               # no T-junction: no edge used 3 times
        assert abs(p.area - patch.area) < 1e-9 * patch.area
        tri = p.vertices[p.faces]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        assert (normal[:, 2] > 0).all()                                    # orientation kept
        bverts, _ = boundary_vertices(p.faces)                             # boundary = the same 24-gon
        r = np.linalg.norm(p.vertices[bverts, :2], axis=1)
        assert r.min() > 20.0 * np.cos(np.pi / 24) - 1e-9 and r.max() < 20.0 + 1e-9
    tri = fine.vertices[fine.faces]
    longest = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(axis=1)
    outer = np.linalg.norm(tri[..., :2], axis=2).max(axis=1) > 20.0 - band   # faces reaching into the band
    assert longest[outer].max() <= h + 1e-12
    assert len(fine.vertices) < 0.3 * len(full.vertices)


def test_clipped_boundary_distance_is_exact_below_the_clip():
    from neuralslicer.toolpath.geometry import boundary_vertices, euclidean_boundary_distance

    layer = square_layer(0.0, size=10.0, n=41)
    v = np.asarray(layer.vertices)
    _, bedges = boundary_vertices(np.asarray(layer.faces))
    exact = np.min(5.0 - np.abs(v[:, :2]), axis=1)
    assert np.allclose(euclidean_boundary_distance(v, bedges), exact, atol=1e-9)
    assert np.allclose(euclidean_boundary_distance(v, bedges, upper=1.3), np.minimum(exact, 1.3), atol=1e-9)


def test_band_limited_paths_match_fully_refined_ones(monkeypatch):
    import neuralslicer.toolpath.generate as generate

    layers = [disc_layer(0.5 * (i + 1), radius=15.0, n_rings=3, n_sectors=40) for i in range(2)]
    band_tp = toolpaths(layers, platform_z=0.0)
    monkeypatch.setattr(generate, "distance_band", lambda cfg: np.inf)
    full_tp = toolpaths(layers, platform_z=0.0)
    shells = [np.sort(np.linalg.norm(tp.xyz[tp.path >= 0, :2], axis=1))[::-1] for tp in (band_tp, full_tp)]
    for r in shells:
        assert r[0] <= 15.0 - 0.25 + 1e-6                                  # half a line inside the 40-gon
    n = min(len(shells[0]), len(shells[1])) // 4                           # the outer shells agree
    assert np.allclose(shells[0][:n], shells[1][:n], atol=0.05)
    assert abs(len(band_tp) / len(full_tp) - 1.0) < 0.02
    assert abs(band_tp.deposited_volume() / full_tp.deposited_volume() - 1.0) < 0.01


def test_thickness_is_exact_on_irregular_triangulations():
    """Planar layers 0.5 mm apart, each a Delaunay triangulation of its own random points (slivers next to
    large triangles): the ray to the layer below must find it under every waypoint."""
    from scipy.spatial import Delaunay

    rng = np.random.default_rng(3)
    layers = []
    for i in range(4):
        pts = np.vstack([rng.random((150, 2)) * 40 - 20, [[-20, -20], [20, -20], [20, 20], [-20, 20]]])
        v = np.column_stack([pts, np.full(len(pts), 0.5 * (i + 1))])
        m = trimesh.Trimesh(v, Delaunay(pts).simplices, process=False)
        m.vertex_attributes["lpd"] = np.tile([0.0, 0.0, 1.0], (len(v), 1))
        layers.append(m)
    tp = toolpaths(layers, platform_z=0.0)
    on = (tp.path >= 0) & (tp.layer > 0)
    assert np.abs(tp.thickness[on] - 0.5).max() < 1e-6


def _rim_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Brute-force straight-line distance from points (k, 3) to the segments a-b (m, 3)."""
    ab = b - a
    u = np.clip(np.einsum("kmj,mj->km", points[:, None] - a, ab) / np.maximum(np.einsum("mj,mj->m", ab, ab), 1e-300),
                0, 1)
    return np.linalg.norm(points[:, None] - (a + u[..., None] * ab), axis=2).min(axis=1)


def test_shells_on_irregular_curved_layers_lie_at_their_offsets():
    """Bowl layers from marching cubes (irregular triangles, jagged trimmed rim): each layer has one closed
    loop per shell, every shell waypoint at (k + 1/2) w from the rim (no stray loops where a distance
    estimate is noisy)."""
    layers = _bowl_layers((0.63, 1.23, 1.83))
    cfg = ToolpathConfig()
    tp = toolpaths(layers, platform_z=0.0, config=cfg)
    for li, m in enumerate(layers):
        e = np.sort(np.concatenate([m.faces[:, [0, 1]], m.faces[:, [1, 2]], m.faces[:, [2, 0]]]), axis=1)
        edges, count = np.unique(e, axis=0, return_counts=True)
        rim = edges[count == 1]
        loops = []
        for k in np.unique(tp.path[(tp.layer == li) & (tp.path >= 0)]):
            q = tp.xyz[tp.path == k]
            if np.allclose(q[0], q[-1]):
                loops.append(_rim_distance(q, m.vertices[rim[:, 0]], m.vertices[rim[:, 1]]))
        assert len(loops) == cfg.n_shells
        for d in loops:
            level = (np.round(np.median(d) / cfg.line_width - 0.5) + 0.5) * cfg.line_width
            assert np.abs(d - level).max() < cfg.line_width / 6


def test_boundary_distance_follows_the_patch_across_a_fold():
    """A strip bent into a hairpin (bend radius 0.4 mm): the short arm's free edge is 0.8 mm above the long
    arm, but 2-3 mm away along the strip, so the long arm there is beyond the distance band; the short arm
    itself has its exact distance."""
    from neuralslicer.toolpath.geometry import Patch, boundary_distance, refine_patch

    rad, short = 0.4, 1.0
    arc = np.pi * rad
    u = np.linspace(0.0, short + arc + 10.0, 200)                   # arc length along the profile
    x = np.where(u < short, short - u, np.where(u < short + arc, -rad * np.sin((u - short) / rad), u - short - arc))
    z = np.where(u < short, 2 * rad, np.where(u < short + arc, rad + rad * np.cos((u - short) / rad), 0.0))
    y = np.linspace(0.0, 6.0, 25)
    U, Yg = np.meshgrid(np.arange(len(u)), y, indexing="ij")
    v = np.column_stack([x[U.ravel()], Yg.ravel(), z[U.ravel()]])
    idx = np.arange(len(v)).reshape(len(u), len(y))
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    patch = refine_patch(Patch(v, faces, np.tile([0.0, 0.0, 1.0], (len(v), 1))), 0.5, band=1.75)
    dist = boundary_distance(patch, upper=1.75)
    p = patch.vertices
    middle = np.abs(p[:, 1] - 3.0) < 1.0                            # far from the strip's sides
    long_arm = middle & (p[:, 2] < 1e-9) & (p[:, 0] > 0.3) & (p[:, 0] < 1.5)
    assert long_arm.sum() > 5 and np.allclose(dist[long_arm], 1.75)   # chord 0.8-1.0 mm, along the strip > 2 mm
    short_arm = middle & (np.abs(p[:, 2] - 2 * rad) < 1e-9) & (p[:, 0] > 0.1)
    assert short_arm.sum() > 5 and np.allclose(dist[short_arm], short - p[short_arm, 0], atol=1e-6)
