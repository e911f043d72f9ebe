"""Nozzle collisions: a planted collision is found, convex parts are clean, the scans' geometry is sound."""
from __future__ import annotations

import numpy as np
import trimesh

from neuralslicer.motion import check_collisions, load_profile, platform_clearance
from neuralslicer.motion.collision import PART, PLATFORM, head_collisions
from neuralslicer.motion.head import cone_ball, holder_ball
from neuralslicer.motion.profile import Nozzle
from neuralslicer.toolpath import toolpaths
from neuralslicer.toolpath.synthetic import cap_stack, planar_stack, square_layer
from neuralslicer.toolpath.types import Toolpaths

from head_reference import NOZZLE, inside_head


def test_planted_collision_is_found():
    tower = [square_layer(0.5 * (i + 1), size=4.0, n=9) for i in range(20)]          # up to z = 10
    late = square_layer(0.5, size=4.0, n=9, center=(8.0, 0.0))                       # printed after, low
    tp = toolpaths(tower + [late], platform_z=0.0)
    rep = check_collisions(tp, NOZZLE, platform_z=0.0)
    assert rep.count > 0
    assert set(tp.layer[rep.indices]) == {20}
    assert np.all(rep.kind == PART)
    # the reported location is material of the tower, inside the head at that waypoint
    assert rep.locations[:, 0].max() <= 2.0 + 1e-9
    for i, loc in zip(rep.indices[:50], rep.locations[:50]):
        assert inside_head(loc[None], tp.xyz[i], tp.axis[i], NOZZLE)[0]
    # exact brute force agrees that most of the late layer's on-layer waypoints collide
    on = np.flatnonzero((tp.layer == 20) & (tp.path >= 0))
    material = tp.xyz[(tp.layer < 20) & (tp.path >= 0)]
    exact = np.array([inside_head(material, tp.xyz[i], tp.axis[i], NOZZLE).any() for i in on])
    found = np.isin(on, rep.indices)
    assert np.array_equal(found, exact)


def test_simple_convex_parts_are_clean():
    profile = load_profile("table_bc_linuxcnc")
    tp = toolpaths(planar_stack(10), platform_z=0.0)
    assert check_collisions(tp, profile.nozzle, platform_z=0.0).count == 0
    tp = toolpaths(cap_stack(5, r0=10.0, theta_max_deg=35.0, subdivisions=4), platform_z=0.0)
    assert check_collisions(tp, profile.nozzle, platform_z=0.0).count == 0


def test_platform_collision_when_tilted_low():
    tp = toolpaths(cap_stack(1, r0=10.0, theta_max_deg=85.0, subdivisions=4), platform_z=0.0)
    rep = check_collisions(tp, NOZZLE, platform_z=0.0)
    assert rep.count > 0 and np.all(rep.kind == PLATFORM)
    # analytic: holder bottom edge = z + h a_z - R sqrt(1 - a_z^2) over the head
    az = tp.axis[:, 2]
    low = np.minimum.reduce([np.zeros_like(az), 8 * az - 8 * np.tan(np.radians(30)) * np.sqrt(1 - az ** 2),
                             8 * az - 15 * np.sqrt(1 - az ** 2), 38 * az - 15 * np.sqrt(1 - az ** 2)])
    expected = np.flatnonzero(tp.xyz[:, 2] + low < -1e-6)
    assert np.array_equal(np.sort(rep.indices), expected)
    assert np.allclose(platform_clearance(tp.xyz, tp.axis, NOZZLE, 0.0), tp.xyz[:, 2] + low)
    # a subset (in any order, repeats allowed) is judged at its own waypoints only
    some = np.concatenate([expected[::2], np.arange(len(tp))[::5]])[::-1]
    part = check_collisions(tp, NOZZLE, platform_z=0.0, only=some)
    mine = np.isin(rep.indices, some)
    assert np.array_equal(part.indices, rep.indices[mine]) and np.array_equal(part.kind, rep.kind[mine])
    assert np.allclose(part.locations, rep.locations[mine]) and 0 < part.count < rep.count


def _assert_exact(tips: np.ndarray, axes: np.ndarray, pts: np.ndarray) -> None:
    """head_collisions agrees with a brute-force test of every point in every head (some hit, some not), and
    each reported location lies in its head."""
    hit, loc = head_collisions(tips, axes, pts, NOZZLE, min_height=0.4)
    exact = np.array([inside_head(pts, t, a, NOZZLE, 0.4).any() for t, a in zip(tips, axes)])
    assert np.array_equal(hit, exact) and 0 < hit.sum() < len(hit)
    for t, a, q in zip(tips[hit], axes[hit], loc[hit]):
        assert inside_head(q[None], t, a, NOZZLE, 0.4)[0]


def test_head_check_is_exact_on_random_clouds():
    rng = np.random.default_rng(3)
    pts = rng.uniform(-40, 40, size=(150, 3)) + [0, 0, 15]
    tips = rng.uniform(-5, 5, size=(60, 3))
    axes = rng.normal(size=(60, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    _assert_exact(tips, axes, pts)
    # the enclosing balls cover the head's parts (dense samples of both)
    h = rng.uniform(0.4, 38.0, 20000)
    radial = rng.uniform(0, 1, 20000) ** 0.5 * np.where(h <= 8.0, h * np.tan(np.radians(30.0)), 15.0)
    ang = rng.uniform(0, 2 * np.pi, 20000)
    head_pts = np.c_[radial * np.cos(ang), radial * np.sin(ang), h]
    assert inside_head(head_pts, np.zeros(3), np.array([0, 0, 1.0]), NOZZLE, 0.4).all()
    for (c, r), part in ((cone_ball(NOZZLE, 0.4), h <= 8.0), (holder_ball(NOZZLE), h > 8.0)):
        assert np.all(np.linalg.norm(head_pts[part] - [0, 0, c], axis=1) <= r + 1e-9)


def _boundary_samples(nz: Nozzle, min_height: float, part: str, n: int = 400) -> np.ndarray:
    """Dense samples (h, radial) of the boundary of the cone or the holder in the half-plane."""
    t = np.linspace(0.0, 1.0, n)
    ta, L = np.tan(np.radians(nz.cone_half_angle_deg)), nz.cone_length
    if part == "cone":
        m = min_height
        edges = [(np.full(n, m), t * m * ta), (m + t * (L - m), (m + t * (L - m)) * ta), (np.full(n, L), t * L * ta)]
    else:
        top, R = L + nz.holder_length, nz.holder_radius
        edges = [(np.full(n, L), t * R), (L + t * (top - L), np.full(n, R)), (np.full(n, top), t * R)]
    return np.concatenate([np.c_[a, b] for a, b in edges])


def test_the_scans_part_bounds_are_exact_inside_and_below_the_distance_outside():
    """The half-plane bound a scan classifies cubes with: exactly minus the distance to the boundary inside the part,
    never more than the distance to it outside (distances to densely sampled boundaries)."""
    from neuralslicer.motion.material import PrintedMaterial
    from neuralslicer.motion.scan import HeadPart

    material = PrintedMaterial.of_points(np.zeros((1, 3)), np.zeros(1, np.int64))
    rng = np.random.default_rng(2)
    for name, part, (h_lo, h_hi, r_hi) in (("cone", HeadPart.cone(NOZZLE, 0.4, material), (-2.0, 11.0, 7.0)),
                                           ("holder", HeadPart.holder(NOZZLE, material), (3.0, 43.0, 20.0))):
        pts = np.c_[rng.uniform(h_lo, h_hi, 4000), rng.uniform(0, r_hi, 4000)]
        edge = _boundary_samples(NOZZLE, 0.4, name)
        dist = np.min(np.hypot(pts[:, None, 0] - edge[None, :, 0], pts[:, None, 1] - edge[None, :, 1]), axis=1)
        bound = part.bound(pts[:, 0], pts[:, 1])
        inside = part.inside(pts[:, 0], pts[:, 1])
        assert 100 < inside.sum() < len(pts) - 100
        assert np.all(bound[inside] <= 1e-9) and np.all(bound[~inside] >= -1e-9)
        assert np.allclose(-bound[inside], dist[inside], atol=0.2)          # the sampling's resolution
        assert np.all(bound[~inside] <= dist[~inside] + 1e-9)


def _tower_and_two_pads():
    """A tower up to z = 5, then one layer with two pads at x = -10 and +10 (a travel crosses the tower)."""
    tower = [square_layer(0.5 * (i + 1), size=4.0, n=9) for i in range(10)]             # up to z = 5
    left, right = square_layer(0.5, size=3.0, n=7, center=(-10.0, 0.0)), square_layer(0.5, size=3.0, n=7, center=(10.0, 0.0))
    both = trimesh.Trimesh(np.vstack([left.vertices, right.vertices]),
                           np.vstack([left.faces, right.faces + len(left.vertices)]), process=False)
    both.vertex_attributes["lpd"] = np.tile([0.0, 0.0, 1.0], (len(both.vertices), 1))
    return tower + [both]


def test_a_travel_through_a_tower_is_found_where_its_ends_are_clear():
    from neuralslicer.motion.collision import TRAVEL_PATH

    tp = toolpaths(_tower_and_two_pads(), platform_z=0.0)
    ends_only = check_collisions(tp, NOZZLE, platform_z=0.0, travel_spacing=0.0)
    assert ends_only.count == 0
    rep = check_collisions(tp, NOZZLE, platform_z=0.0)
    assert rep.count >= 1 and set(rep.kind) == {TRAVEL_PATH}
    for i, loc in zip(rep.indices, rep.locations):
        assert tp.layer[i] == 10 and not tp.extrude[i]
        assert np.abs(loc[:2]).max() <= 2.0 + 1e-9 and loc[2] <= 5.0 + 1e-9                     # tower material
        # brute force: some pose on the move arriving at i has that material inside the head
        t = np.linspace(0, 1, 201)[:, None]
        tips = (1 - t) * tp.xyz[i - 1] + t * tp.xyz[i]
        assert any(inside_head(loc[None], tip, tp.axis[i], NOZZLE, 0.5)[0] for tip in tips)


def test_a_colliding_travel_is_lifted_over_the_tower():
    from neuralslicer.motion.travel import raise_travels

    tp = toolpaths(_tower_and_two_pads(), platform_z=0.0)
    rep = check_collisions(tp, NOZZLE, platform_z=0.0)
    out, left, summary = raise_travels(tp, rep, NOZZLE, platform_z=0.0, min_height=0.5)
    assert summary["n_travels_lifted"] == rep.count and summary["n_travels_unresolved"] == 0 and left.count == 0
    assert len(out) == len(tp) + 2 * rep.count
    assert check_collisions(out, NOZZLE, platform_z=0.0).count == 0                       # the judge agrees
    # the detour goes over the tower: its top (z = 5) plus the head's min height is below the lifted chord
    lifted = out.xyz[(out.layer == 10) & (out.path == -1) & (out.xyz[:, 2] > 1.6) & (np.abs(out.xyz[:, 0]) > 7)]
    assert len(lifted) == 2 * rep.count and lifted[:, 2].min() >= 5.0
    # printing waypoints are untouched, in the same order
    on = out.path >= 0
    assert np.array_equal(out.xyz[on], tp.xyz[tp.path >= 0])


def test_lifting_travels_in_place_gives_the_same_print_and_empties_the_input():
    """``consume`` (the motion step's way: the print is not held twice) makes the same toolpaths and report as a
    copy, column by column, and leaves the toolpaths it was given without waypoints."""
    from neuralslicer.motion.travel import raise_travels

    tp = toolpaths(_tower_and_two_pads(), platform_z=0.0)
    rep = check_collisions(tp, NOZZLE, platform_z=0.0)
    ref, ref_left, ref_summary = raise_travels(tp, rep, NOZZLE, platform_z=0.0, min_height=0.5)
    given = Toolpaths(**{name: getattr(tp, name).copy() for name in Toolpaths.ARRAYS}, attrs=dict(tp.attrs))
    out, left, summary = raise_travels(given, rep, NOZZLE, platform_z=0.0, min_height=0.5, consume=True)
    assert rep.count and summary == ref_summary and np.array_equal(left.indices, ref_left.indices)
    for name in Toolpaths.ARRAYS:
        assert np.array_equal(getattr(out, name), getattr(ref, name))
        assert getattr(out, name).dtype == getattr(ref, name).dtype
        assert len(getattr(given, name)) == 0
    assert len(tp) == len(ref) - 2 * rep.count                                   # the copy's input is untouched


def test_a_travel_no_lift_clears_goes_by_the_clearance_plane():
    """With only a 2 mm lift on offer (too low for the 5 mm tower), the travel goes up to the plane above all
    earlier material and across it; the exact check finds the new program clear, the printing moves are untouched."""
    from neuralslicer.motion.travel import raise_travels

    tp = toolpaths(_tower_and_two_pads(), platform_z=0.0)
    rep = check_collisions(tp, NOZZLE, platform_z=0.0)
    out, left, summary = raise_travels(tp, rep, NOZZLE, platform_z=0.0, min_height=0.5, lifts=(2.0,))
    assert summary["n_travels_by_clearance_plane"] == rep.count == summary["n_travels_lifted"]
    assert summary["n_travels_unresolved"] == 0 and left.count == 0
    assert len(out) == len(tp) + 4 * rep.count                                  # up, up to the plane, across, down
    assert check_collisions(out, NOZZLE, platform_z=0.0).count == 0
    across = (out.layer == 10) & (out.path == -1) & (out.xyz[:, 2] > 5.0) & (np.abs(out.xyz[:, 0]) > 7)
    assert across.sum() == 2 * rep.count and np.allclose(out.xyz[across, 2], 5.0 + 2 * 0.5 + 1.0)
    assert np.allclose(out.axis[across], [0.0, 0.0, 1.0])
    assert np.array_equal(out.xyz[out.path >= 0], tp.xyz[tp.path >= 0])


def test_lifted_travels_shift_the_other_collisions_by_their_detours():
    """A part collision after two lifted travels keeps pointing at its own waypoint (detours of 2 and 4 points)."""
    from neuralslicer.motion.collision import PART, TRAVEL_PATH, CollisionReport
    from neuralslicer.motion.travel import raise_travels

    tp = toolpaths(_tower_and_two_pads(), platform_z=0.0)
    rep = check_collisions(tp, NOZZLE, platform_z=0.0)
    last = len(tp) - 1
    fake = CollisionReport(np.r_[rep.indices, last], np.vstack([rep.locations, tp.xyz[last]]),
                           np.r_[rep.kind, PART].astype(np.int8))
    out, left, _ = raise_travels(tp, fake, NOZZLE, platform_z=0.0, min_height=0.5, lifts=(2.0, 64.0))
    assert list(left.kind) == [PART] and TRAVEL_PATH not in left.kind
    assert np.array_equal(out.xyz[left.indices[0]], tp.xyz[last])


def test_cube_classified_holder_test_is_exact_on_a_dense_cloud():
    """Thousands of material points in few cubes (whole cubes inside the holder, outside, on its boundary): the
    hits and their witnesses agree with the brute-force membership test at every pose."""
    rng = np.random.default_rng(11)
    pts = np.vstack([rng.uniform([-30, -30, 15], [30, 30, 25], size=(6000, 3)),   # a dense slab
                     np.stack(np.meshgrid(*[np.arange(-12.0, 12.1, 1.0)] * 2, [8.0, 20.0], indexing="ij"), -1).reshape(-1, 3)])
    tips = rng.uniform([-20, -20, -50], [20, 20, 5], size=(300, 3))
    axes = rng.normal(size=(300, 3)) + [0, 0, 2.0]
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    axes[:20] = [0.0, 0.0, 1.0]                       # grid points exactly on the holder's bottom face
    tips[:20, 2] = 0.0
    hit, loc = head_collisions(tips, axes, pts, NOZZLE, min_height=0.4)
    exact = np.array([inside_head(pts, t, a, NOZZLE, 0.4).any() for t, a in zip(tips, axes)])
    assert np.array_equal(hit, exact) and 20 < hit.sum() < len(hit) - 20
    for t, a, q in zip(tips[hit], axes[hit], loc[hit]):
        assert inside_head(q[None], t, a, NOZZLE, 0.4)[0]


def test_head_lowest_z_is_the_lowest_point_of_the_head():
    from neuralslicer.motion.collision import head_lowest_z
    rng = np.random.default_rng(5)
    axes = rng.normal(size=(40, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    tips = rng.uniform(-5, 5, size=(40, 3))
    low = head_lowest_z(tips, axes, NOZZLE, 0.4)
    # the rims of the cone above min_height and of the holder, densely sampled, in the frame of each axis
    ang = np.linspace(0, 2 * np.pi, 3601)
    ta = np.tan(np.radians(30.0))
    rims = [(0.4, 0.4 * ta), (8.0, 8.0 * ta), (8.0, 15.0), (38.0, 15.0)]
    for t, a, lo in zip(tips, axes, low):
        u = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
        u /= np.linalg.norm(u)
        v = np.cross(a, u)
        z = min((t[2] + h * a[2] + r * (np.cos(ang) * u[2] + np.sin(ang) * v[2])).min() for h, r in rims)
        assert lo <= z + 1e-12 and z - lo < 1e-4


def test_poses_above_the_material_are_skipped_exactly():
    rng = np.random.default_rng(7)
    pts = rng.uniform(-20, 20, size=(400, 3)) * [1, 1, 0.25]                 # a slab, top near z = 5
    tips = np.c_[rng.uniform(-15, 15, size=(300, 2)), rng.uniform(-2, 12, 300)]
    axes = rng.normal(size=(300, 3)) * [0.4, 0.4, 1] + [0, 0, 1.5]
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    _assert_exact(tips, axes, pts)


def test_holder_anchors_clear_nearby_poses_soundly(monkeypatch):
    """Along a dense sweep the anchors' clearance bounds clear most poses without a scan of their own, the bound
    never exceeds the holder's true distance to the material, and the hits are those of the brute-force test."""
    from neuralslicer.motion import collision as coll
    from neuralslicer.motion import scan as sc
    from neuralslicer.motion.material import PrintedMaterial

    rng = np.random.default_rng(5)
    pts = rng.uniform([-40, -40, 20], [40, 40, 28], size=(8000, 3))
    s = np.linspace(0.0, 1.0, 400)
    tips = np.c_[-30 + 60 * s, 10 * np.sin(6 * s), -24.0 + 7.0 * np.sin(9 * s)]        # 0.15 mm apart
    tilt = np.radians(35.0) * np.sin(2 * s)
    axes = np.c_[np.sin(tilt), np.zeros_like(s), np.cos(tilt)]
    scanned: list[tuple[int, float]] = []
    scan = sc.scan

    def counting_scan(material, part, tips_, axes_, visible, margin=0.0):
        scanned.append((len(tips_), margin))
        return scan(material, part, tips_, axes_, visible, margin)

    monkeypatch.setattr(coll, "scan", counting_scan)
    hit, loc = head_collisions(tips, axes, pts, NOZZLE, min_height=0.4)
    exact = np.array([inside_head(pts, t, a, NOZZLE, 0.4).any() for t, a in zip(tips, axes)])
    assert np.array_equal(hit, exact) and 30 < hit.sum() < len(hit) - 100
    for t, a, q in zip(tips[hit], axes[hit], loc[hit]):
        assert inside_head(q[None], t, a, NOZZLE, 0.4)[0]
    # cone, holder anchors (with a margin), holder one by one: beside the hits, most poses were cleared by an anchor
    holder = [n for n, m in scanned[1:] if m == 0.0]
    assert len(scanned) == 3 and scanned[1][1] == coll.HOLDER_MARGIN
    assert holder[0] <= hit.sum() + 0.25 * (len(tips) - hit.sum())
    # the anchors' bound is a lower bound on the distance from the holder to the material, capped at the margin
    material = PrintedMaterial.of_points(pts, np.zeros(len(pts), np.int64))
    _, _, bound = scan(material, sc.HeadPart.holder(NOZZLE, material), tips, axes, np.ones(len(tips), np.int64), 5.0)
    d = pts[None, :, :] - tips[:, None, :]
    h = np.einsum("pkj,pj->pk", d, axes)
    radial = np.sqrt(np.maximum(np.einsum("pkj,pkj->pk", d, d) - h * h, 0.0))
    dh, dr = np.abs(h - 23.0) - 15.0, radial - 15.0            # capped cylinder: exact signed distance
    true = (np.minimum(np.maximum(dr, dh), 0.0) + np.hypot(np.maximum(dr, 0.0), np.maximum(dh, 0.0))).min(axis=1)
    inside = true < 0
    free = ~inside
    assert free.sum() > 100 and np.all(bound[free] <= true[free] + 1e-9) and np.all(bound[free] <= 5.0)
    assert np.all(np.isneginf(bound[inside]))
    assert np.mean(bound[free] > 0.5 * np.minimum(true[free], 5.0)) > 0.5   # and a useful one


def test_the_check_in_blocks_is_the_check_of_the_whole(monkeypatch):
    """The waypoints checked a block at a time (a long print's temporaries are a block's) give the report of the
    whole print checked at once: every index, kind and witness, with and without ``only``."""
    import dataclasses

    from neuralslicer.motion import collision
    from neuralslicer.toolpath.plan import plan_toolpaths

    tp = plan_toolpaths(cap_stack(6, thickness=0.6, r0=6.0, theta_max_deg=75.0, subdivisions=3), platform_z=-12.0)
    tilt = np.radians(50.0)       # one tilted tool axis everywhere: the head reaches back into the caps and below
    tp = dataclasses.replace(tp, axis=np.tile([0.0, np.sin(tilt), np.cos(tilt)], (len(tp), 1)))
    platform_z = float(tp.xyz[:, 2].min()) - 4.0
    only = np.random.default_rng(3).choice(len(tp), 700, replace=False)
    whole, some = check_collisions(tp, NOZZLE, platform_z), check_collisions(tp, NOZZLE, platform_z, only=only)
    summary = whole.summary()
    assert summary["n_part_collisions"] > 100 and summary["n_platform_collisions"] > 100
    assert summary["n_travel_collisions"] >= 1 and some.count > 10
    monkeypatch.setattr(collision, "CHECK_BLOCK", 97)
    for a, b in ((whole, check_collisions(tp, NOZZLE, platform_z)),
                 (some, check_collisions(tp, NOZZLE, platform_z, only=only))):
        assert np.array_equal(a.indices, b.indices) and np.array_equal(a.kind, b.kind)
        assert np.array_equal(a.locations, b.locations)


def test_the_scan_answers_the_same_in_any_chunks_and_threads(monkeypatch):
    """The compiled scan gives every pose its own answer: hits, witnesses and clearance bounds are the same bits
    whatever the chunks and the number of threads, with and without a margin."""
    from neuralslicer.motion import scan as sc
    from neuralslicer.motion.material import PrintedMaterial

    rng = np.random.default_rng(8)
    pts = rng.uniform([-30, -30, 0], [30, 30, 12], size=(20000, 3))
    material = PrintedMaterial.of_points(pts, rng.integers(0, 500, len(pts)), 500)
    tips = rng.uniform([-25, -25, 4], [25, 25, 14], size=(900, 3))
    axes = rng.normal(size=(900, 3)) + [0, 0, 2.0]
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    visible = rng.integers(0, 501, len(tips))
    for part, margin in ((sc.HeadPart.cone(NOZZLE, 0.4, material), 0.0), (sc.HeadPart.holder(NOZZLE, material), 5.0)):
        monkeypatch.setattr(sc, "WORKERS", 1)
        monkeypatch.setattr(sc, "CHUNK", 4096)
        one = sc.scan(material, part, tips, axes, visible, margin)
        monkeypatch.setattr(sc, "WORKERS", 3)
        monkeypatch.setattr(sc, "CHUNK", 7)
        many = sc.scan(material, part, tips, axes, visible, margin)
        assert 50 < one[0].sum() < len(tips) - 50
        for a, b in zip(one, many):
            assert np.array_equal(a, b)
        d = material.points[one[1][one[0]]] - tips[one[0]]            # each witness is inside the part
        h = np.einsum("ij,ij->i", d, axes[one[0]])
        assert part.inside(h, np.sqrt(np.maximum(np.einsum("ij,ij->i", d, d) - h * h, 0.0))).all()
        assert np.all(material.time[one[1][one[0]]] < visible[one[0]])   # laid before the pose
