"""Marching tetrahedra, trimming and isovalue choice against analytic shapes."""
import numpy as np
import pytest

from neuralslicer.layers import LayerConfig, choose_isovalues, extract_layers, marching_tets, trim
from neuralslicer.tetmesh import barycentric_gradients
from neuralslicer.tetmesh import box_tet_grid as cube_grid


def sphere_H(r: float, c: np.ndarray):
    """Signed distance of a sphere."""
    return lambda x: np.linalg.norm(x - c, axis=1) - r


def field_lpd(V, T, G):
    g = np.einsum("mi,mij->mj", G[T], barycentric_gradients(V, T))
    return g / np.linalg.norm(g, axis=1, keepdims=True)


def test_marching_tets_plane_is_exact_and_oriented():
    V, T = cube_grid(6)
    G = V @ np.array([0.2, 0.3, 1.0])
    lpd = field_lpd(V, T, G)
    pts, faces, src = marching_tets(V, T, G, 0.7, lpd)
    assert np.allclose(pts @ np.array([0.2, 0.3, 1.0]), 0.7, atol=1e-12)
    p = pts[faces]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert np.all(n @ np.array([0.2, 0.3, 1.0]) > 0)
    # watertight inside the cube: every interior edge shared by two faces
    import trimesh

    m = trimesh.Trimesh(pts, faces, process=False)
    assert len(trimesh.graph.split(m, only_watertight=False)) == 1


def test_trim_by_sphere_keeps_inside_and_measures_disc_area():
    V, T = cube_grid(12)
    G = V[:, 2].copy()
    lpd = field_lpd(V, T, G)
    H = sphere_H(0.4, np.array([0.5, 0.5, 0.5]))
    pts, faces, _ = marching_tets(V, T, G, 0.5, lpd)
    tp, tf, src = trim(pts, faces, H, iterations=40)
    assert np.all(H(tp) <= 1e-9)
    import trimesh

    area = trimesh.Trimesh(tp, tf, process=False).area
    assert area == pytest.approx(np.pi * 0.4**2, rel=0.01)
    # the boundary of the trimmed disc lies on H = 0
    m = trimesh.Trimesh(tp, tf, process=False)
    bnd = np.unique(m.edges_sorted[trimesh.grouping.group_rows(m.edges_sorted, require_count=1)])
    assert np.abs(H(tp[bnd])).max() <= 1e-7


def test_extract_layers_in_print_order_with_lpd():
    V, T = cube_grid(10)
    G = V[:, 2].copy()
    lpd = field_lpd(V, T, G)
    H = sphere_H(0.45, np.array([0.5, 0.5, 0.5]))
    cfg = LayerConfig(layer_height=0.1, t_min=0.05, t_max=0.2, min_area=1e-4)
    isos = np.arange(0.1, 0.95, 0.1)
    layers = extract_layers(V, T, G, lpd, H, isos, cfg)
    assert np.all(np.diff(layers.isovalues) > 0)
    for m in layers.meshes:
        assert np.all(H(m.vertices) <= 1e-8)
        assert np.allclose(m.vertex_attributes["lpd"], [0, 0, 1])
        assert np.allclose(m.vertices[:, 2], m.metadata["isovalue"])
    arrays, attrs = layers.to_arrays()
    again = type(layers).from_arrays(arrays, attrs)
    assert len(again.meshes) == len(layers.meshes)
    assert np.allclose(again.meshes[3].vertices, layers.meshes[3].vertices)


def test_choose_isovalues_uniform_and_graded_fields():
    rng = np.random.default_rng(0)
    z = rng.uniform(0, 10, 20000)
    cfg = LayerConfig(layer_height=0.5, t_min=0.4, t_max=1.0)
    isos, rep = choose_isovalues(z, np.ones_like(z), cfg)
    assert np.allclose(np.diff(isos), 0.5)
    assert rep["fraction_outside_range"] == 0.0
    # |grad G| from 1 to 2 in every slab: a spacing keeps every thickness in [0.4, 1.0]
    gn = 1 + rng.uniform(size=z.size)
    isos, rep = choose_isovalues(z, gn, cfg)
    assert rep["thickness_min"] >= 0.4 - 1e-9 and rep["thickness_max"] <= 1.0 + 1e-9
    assert rep["fraction_outside_range"] == 0.0
    # |grad G| from 1 to 3: no spacing can; thickness is capped at t_max and 1/gn < 0.4 where gn > 2.5
    gn = 1 + 2 * rng.uniform(size=z.size)
    isos, rep = choose_isovalues(z, gn, cfg)
    assert rep["thickness_max"] <= 1.0 + 1e-9
    assert rep["fraction_outside_range"] == pytest.approx(0.25, abs=0.02)


def test_one_flat_point_does_not_multiply_the_layers():
    rng = np.random.default_rng(1)
    z = rng.uniform(0, 50, 20000)
    gn = np.ones_like(z)
    cfg = LayerConfig()                                         # 0.8 mm layers in [0.4, 1.0]
    isos, rep = choose_isovalues(z, gn, cfg)
    gn[123] = 1e-4                                              # one point where the field is nearly flat
    again, rep_low = choose_isovalues(z, gn, cfg)
    assert len(again) == len(isos) == pytest.approx(50 / 0.8, abs=1)
    assert rep_low["low_gradient_fraction"] == pytest.approx(1 / z.size)
    assert rep_low["low_gradient_thickness_max"] > 1000       # reported, not hidden
    assert rep_low["thickness_max"] <= 1.0 + 1e-9


def test_first_slab_counts_and_the_top_gap_is_reported():
    z = np.linspace(0, 10, 20001)
    cfg = LayerConfig(layer_height=0.5, t_min=0.4, t_max=1.0)
    isos, rep = choose_isovalues(z, np.ones_like(z), cfg)
    assert isos[0] == pytest.approx(0.4)                        # half a layer (0.25) is below t_min: 0.4
    assert rep["thickness_min"] == pytest.approx(0.4) and rep["fraction_outside_range"] == 0.0
    assert rep["top_gap_max"] == pytest.approx(10 - isos[-1], abs=1e-3)


def test_too_many_layers_is_a_clear_error():
    from neuralslicer.errors import InputError

    z = np.linspace(0, 10_000, 20001)                           # 10 m read as mm: 12,500 layers
    with pytest.raises(InputError, match="more than 5,000 layers"):
        choose_isovalues(z, np.ones_like(z), LayerConfig())


def test_edge_crossings_converge_inside_for_a_nonlinear_H():
    from neuralslicer.layers import edge_crossings

    rng = np.random.default_rng(3)
    H = lambda x: np.sum(x**2, axis=1) ** 2 - 1.0  # not a distance: quartic along segments
    p_in = rng.uniform(-0.5, 0.5, size=(2000, 3))
    p_out = p_in + rng.normal(size=(2000, 3))
    p_out *= (2.0 / np.linalg.norm(p_out, axis=1))[:, None]
    c = edge_crossings(p_in, p_out, H(p_in), H(p_out), H, iterations=60, tol=1e-10)
    assert np.all(H(c) <= 0)
    assert np.abs(H(c)).max() <= 1e-10
    # on the segment
    d = np.cross(c - p_in, p_out - p_in)
    assert np.abs(d).max() < 1e-9


def test_layers_of_a_curved_field_are_level_sets_and_do_not_intersect():
    from neuralslicer.scalar_field import ScalarField

    V, T = cube_grid(10)
    # a curved field: G = z + 0.3 sin(2 pi x), its level sets are wavy sheets
    G = V[:, 2] + 0.3 * np.sin(2 * np.pi * V[:, 0])
    field = ScalarField(V, T, G)
    H = sphere_H(0.45, np.array([0.5, 0.5, 0.5]))
    isos = np.arange(0.1, 1.2, 0.08)
    layers = extract_layers(V, T, G, field.lpd(), H, isos, LayerConfig(layer_height=0.08, t_min=0.01, t_max=1, min_area=0))
    for m in layers.meshes:
        g, d, _ = field.sample(m.vertices)
        # every layer vertex carries its own isovalue, so two layers (two values of G) never meet
        assert np.allclose(g, m.metadata["isovalue"], atol=1e-9)
        assert np.all(H(m.vertices) <= 1e-7)
    pairs = list(zip(layers.meshes[:-1], layers.meshes[1:]))
    assert all(a.metadata["isovalue"] < b.metadata["isovalue"] for a, b in pairs)


def test_trimmed_layer_follows_a_concave_border():
    """A plane trimmed by a solid with a cylindrical hole: the boundary chords along the hole are refined."""
    import trimesh

    V, T = cube_grid(6)  # coarse: 1/6 edges against a hole of radius 0.25
    G = V[:, 2].copy()
    lpd = field_lpd(V, T, G)
    H = lambda x: 0.25 - np.linalg.norm(x[:, :2] - 0.5, axis=1)  # inside = outside the hole
    pts, faces, _ = marching_tets(V, T, G, 0.5, lpd)
    tp, tf, _ = trim(pts, faces, H, iterations=40)
    m = trimesh.Trimesh(tp, tf, process=False)
    assert m.area == pytest.approx(1 - np.pi * 0.25**2, rel=2e-3)
    rng = np.random.default_rng(0)
    w = rng.dirichlet(np.ones(3), size=(len(tf), 20))
    inside_faces = np.einsum("fsk,fkj->fsj", w, tp[tf]).reshape(-1, 3)
    sagitta_unrefined = (1 / 6) ** 2 / (8 * 0.25)
    assert H(inside_faces).max() < sagitta_unrefined / 30
    assert np.allclose(tp[:, 2], 0.5)
    # conforming: every edge is shared by two faces or lies on the border
    edges = m.edges_sorted
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert counts.max() <= 2


def test_a_hole_between_the_vertices_is_found_and_cut_out():
    """A thin vertical hole centred on a layer edge's midpoint: no vertex is in it, trimming still cuts it out."""
    import trimesh

    V, T = cube_grid(6)
    G = V[:, 2].copy()
    lpd = field_lpd(V, T, G)
    pts, faces, _ = marching_tets(V, T, G, 0.5, lpd)
    m0 = trimesh.Trimesh(pts, faces, process=False)
    e = m0.edges_unique[np.argmin(np.linalg.norm(pts[m0.edges_unique].mean(axis=1)[:, :2] - 0.5, axis=1))]
    centre = pts[e].mean(axis=0)[:2]
    H = lambda x: 0.03 - np.linalg.norm(x[:, :2] - centre, axis=1)
    assert np.all(H(pts) < 0)  # every vertex is in the solid: trimming by vertex signs alone sees no hole
    tp, tf, src = trim(pts, faces, H, iterations=40)
    assert np.all(np.isin(src, np.arange(len(faces)))) and len(tf) > len(faces)
    m = trimesh.Trimesh(tp, tf, process=False)
    assert m.area < 1 - 0.9 * np.pi * 0.03**2
    assert np.all(H(tp) <= 1e-9)
    assert np.allclose(tp[:, 2], 0.5)


# ---------------------------------------------------------------- layers inside a solid with concave parts
def _box_sdf(x, lo, hi):
    """Signed distance of an axis-aligned box."""
    c, r = 0.5 * (lo + hi), 0.5 * (hi - lo)
    q = np.abs(x - c) - r
    return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)


def _concave_solid(x):
    """A box with a vertical cylindrical hole (a smooth concave wall) and a notch (a re-entrant edge)."""
    box = _box_sdf(x, np.array([0.03, 0.03, 0.03]), np.array([0.97, 0.97, 0.97]))
    hole = 0.19 - np.linalg.norm(x[:, :2] - [0.42, 0.47], axis=1)
    notch = -_box_sdf(x, np.array([0.62, 0.55, -1.0]), np.array([2.0, 0.8, 2.0]))
    return np.maximum(np.maximum(box, hole), notch)


def _tri_samples(p: np.ndarray, n: int = 8, n_random: int = 16, seed: int = 0) -> np.ndarray:
    """Dense points on triangles p (f,3,3): a barycentric grid of step 1/n (vertices included) and random points."""
    i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    ok = i + j <= n
    w = np.stack([i[ok], j[ok], n - i[ok] - j[ok]], axis=1) / n
    w = np.concatenate([np.broadcast_to(w, (len(p),) + w.shape),
                        np.random.default_rng(seed).dirichlet(np.ones(3), size=(len(p), n_random))], axis=1)
    return np.einsum("fsk,fkj->fsj", w, p).reshape(-1, 3)


def _min_angle_deg(p: np.ndarray) -> np.ndarray:
    """Smallest angle of each triangle (f,3,3), degrees."""
    e = [p[:, (k + 1) % 3] - p[:, k] for k in range(3)]
    ang = []
    for k in range(3):
        a, b = -e[(k + 2) % 3], e[k]
        c = np.einsum("ij,ij->i", a, b) / np.maximum(np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-300)
        ang.append(np.degrees(np.arccos(np.clip(c, -1, 1))))
    return np.min(ang, axis=0)


def _check_layer_mesh(m, H, on_level, eps=1e-3):
    """Vertices inside, every point of every triangle inside within eps, on its level set, conforming, not degenerate."""
    p = m.vertices[m.faces]
    assert H(m.vertices).max() <= 1e-7
    assert H(_tri_samples(p)).max() <= eps
    assert np.abs(on_level(_tri_samples(p, n=4, n_random=4))).max() <= 1e-9
    # conforming and consistently oriented: an edge has one face, or two that run it in opposite directions,
    # and no vertex lies inside a border edge (a T-junction, a crack)
    directed = np.concatenate([m.faces[:, [0, 1]], m.faces[:, [1, 2]], m.faces[:, [2, 0]]])
    assert len(np.unique(directed, axis=0)) == len(directed)
    undirected, counts = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    assert counts.max() <= 2
    a, b = m.vertices[undirected[counts == 1, 0]], m.vertices[undirected[counts == 1, 1]]
    t = np.einsum("vej,ej->ve", m.vertices[:, None] - a, b - a) / np.einsum("ej,ej->e", b - a, b - a)
    off = np.linalg.norm(m.vertices[:, None] - (a + t[..., None] * (b - a)), axis=2)
    assert not np.any((t > 1e-9) & (t < 1 - 1e-9) & (off < 1e-9))
    # no degenerate triangles
    assert m.area_faces.min() > 1e-9 * m.area
    assert _min_angle_deg(p).min() > 1e-3


def test_layers_of_a_plane_stay_inside_a_solid_with_concave_walls():
    """Oblique planar layers through a coarse grid: chords along the hole and the notch are refined away."""
    V, T = cube_grid(7)
    a = np.array([0.25, -0.15, 1.0])
    G = V @ a
    lpd = field_lpd(V, T, G)
    isos = np.arange(0.12, 1.0, 0.09)
    layers = extract_layers(V, T, G, lpd, _concave_solid, isos,
                            LayerConfig(layer_height=0.09, t_min=0.01, t_max=1, min_area=0))
    assert len(layers.meshes) == len(isos)
    for m in layers.meshes:
        _check_layer_mesh(m, _concave_solid, lambda x: x @ a - m.metadata["isovalue"])
        n = np.cross(*(m.vertices[m.faces[:, k]] - m.vertices[m.faces[:, 0]] for k in (1, 2)))
        assert np.all(n @ a > 0)


def test_curved_layers_stay_inside_a_solid_with_concave_walls_and_on_their_level_sets():
    """A piecewise-linear curved field: each refined triangle stays inside one cage tet, on the level set."""
    from neuralslicer.scalar_field import ScalarField

    V, T = cube_grid(6)
    G = V[:, 2] + 0.15 * np.sin(2 * np.pi * V[:, 0]) + 0.1 * V[:, 1]
    field = ScalarField(V, T, G)
    isos = np.arange(0.1, 1.0, 0.11)
    layers = extract_layers(V, T, G, field.lpd(), _concave_solid, isos,
                            LayerConfig(layer_height=0.1, t_min=0.01, t_max=1, min_area=0))
    for m in layers.meshes:
        _check_layer_mesh(m, _concave_solid, lambda x: field.sample(x)[0] - m.metadata["isovalue"])


def test_trim_cuts_a_thin_pin_between_the_vertices_and_refines_its_border():
    """A thin hole through a triangle's interior (no vertex, no edge midpoint in it) is found and cut out."""
    import trimesh

    V, T = cube_grid(5)
    G = V[:, 2].copy()
    pts, faces, _ = marching_tets(V, T, G, 0.5, field_lpd(V, T, G))
    centre = pts[faces[7]].mean(axis=0)[:2]  # a triangle's centroid
    H = lambda x: np.maximum(_box_sdf(x, np.zeros(3), np.ones(3)), 0.02 - np.linalg.norm(x[:, :2] - centre, axis=1))
    tp, tf, src = trim(pts, faces, H)
    m = trimesh.Trimesh(tp, tf, process=False)
    # the hole is cut out, up to the trim tolerance (5e-4) on its border
    assert 1 - np.pi * 0.02**2 - 1e-9 <= m.area <= 1 - np.pi * (0.02 - 5e-4) ** 2
    assert np.all(np.isin(src, np.arange(len(faces))))
    _check_layer_mesh(m, H, lambda x: x[:, 2] - 0.5)
