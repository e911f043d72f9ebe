"""Beads held to the nozzle's range: thin gaps carried to the bead above, thick ones capped, all reported."""
from __future__ import annotations

import numpy as np
import pytest

from neuralslicer.errors import InputError
from neuralslicer.motion import load_profile, plan_print
from neuralslicer.toolpath.beads import bead_summary, hold_beads
from neuralslicer.toolpath.config import ToolpathConfig
from neuralslicer.toolpath.synthetic import planar_stack
from neuralslicer.toolpath.types import Toolpaths


def _columns(tops: list[np.ndarray], x: np.ndarray) -> Toolpaths:
    """One straight path per layer along x (axis +z) at heights ``tops[k]`` (per waypoint): the measured
    thickness is the gap to the layer below (to the platform z = 0 for the first)."""
    rows, below = [], np.zeros_like(x)
    for k, z in enumerate(tops):
        rows.append((k, np.column_stack([x, np.zeros_like(x), z]), z - below))
        below = z
    n = sum(len(r[1]) for r in rows)
    return Toolpaths(layer=np.concatenate([np.full(len(x), k) for k, _, _ in rows]).astype(np.int64),
                     path=np.concatenate([np.full(len(x), k) for k, _, _ in rows]).astype(np.int64),
                     xyz=np.concatenate([p for _, p, _ in rows]), axis=np.tile([0.0, 0.0, 1.0], (n, 1)),
                     thickness=np.concatenate([t for _, _, t in rows]), width=np.full(n, 0.5),
                     extrude=np.concatenate([np.r_[False, np.ones(len(x) - 1, bool)] for _ in rows]))


def test_a_thin_gap_is_carried_to_the_bead_above_and_the_material_is_kept():
    x = np.arange(0.0, 10.01, 0.5)
    left = x < 5.0
    tops = [np.full_like(x, 0.5), np.where(left, 0.6, 0.9), np.full_like(x, 1.3)]  # layer 1: 0.1 mm on the left
    tp = _columns(tops, x)
    out, s = hold_beads(tp, (0.15, 1.2))
    l1, l2 = tp.layer == 1, tp.layer == 2
    # layer 1 does not extrude where its gap is 0.1 mm; layer 2 lays 0.7 + 0.1 there, 0.4 elsewhere
    assert not out.extrude[l1 & (tp.xyz[:, 0] < 5.0)].any() and out.extrude[l1 & (tp.xyz[:, 0] > 5.0)].all()
    assert np.allclose(out.thickness[l2], np.where(left, 0.8, 0.4))
    assert s["n_skipped"] == s["n_carried"] == int(left[1:].sum())      # the path start does not extrude anyway
    n_print = int(tp.extrude.sum())
    assert s["fraction_thin"] == pytest.approx(left[1:].sum() / n_print) and s["fraction_thick"] == 0.0
    # the columns still reach 1.3 mm: the material of each layer's bead adds up to the part's height
    assert out.deposited_volume() == pytest.approx(tp.deposited_volume(), rel=0.03)
    assert sum(s["hist_counts"]) == n_print


def test_thick_gaps_are_capped_and_a_chain_of_thin_ones_adds_up():
    x = np.arange(0.0, 5.01, 0.5)
    tops = [np.full_like(x, 2.0), np.full_like(x, 2.1), np.full_like(x, 2.2), np.full_like(x, 2.8)]
    out, s = hold_beads(_columns(tops, x), (0.15, 1.2))
    layer = out.layer
    assert np.allclose(out.thickness[layer == 0], 1.2) and s["n_capped"] == int(out.extrude[layer == 0].sum())
    assert not out.extrude[layer == 1].any()                                      # 0.1: skipped
    assert out.extrude[layer == 2][1:].all() and np.allclose(out.thickness[layer == 2], 0.2)  # 0.1 + 0.1
    assert np.allclose(out.thickness[layer == 3], 0.6)


def test_nothing_changes_when_every_gap_fits():
    x = np.arange(0.0, 5.01, 0.5)
    tp = _columns([np.full_like(x, 0.5), np.full_like(x, 1.0)], x)
    out, s = hold_beads(tp, (0.15, 1.2))
    assert out is tp and s["fraction_outside_range"] == 0.0 and s == {**bead_summary(tp, (0.15, 1.2))}


def test_plan_print_reports_beads_and_refuses_a_line_width_the_nozzle_cannot_lay():
    layers = planar_stack(3, thickness=0.5, size=6.0, n=7)
    _, _, metrics, _ = plan_print(layers, platform_z=0.0)
    beads = metrics["beads"]
    assert beads["thickness_range_mm"] == [0.15, 1.2] and beads["fraction_outside_range"] == 0.0
    assert beads["n_extruding"] > 100
    with pytest.raises(InputError, match="toolpath.line_width.*outside the bead widths"):
        plan_print(layers, platform_z=0.0, toolpath_cfg=ToolpathConfig(line_width=1.5))
    profile = load_profile("table_bc_linuxcnc").model_copy(deep=True)
    profile.nozzle.bead_thickness_mm = (0.6, 1.2)                                # 0.5 mm layers are too thin
    _, _, thin, _ = plan_print(layers, platform_z=0.0, profile=profile)
    assert thin["beads"]["fraction_thin"] > 0.5 and thin["beads"]["n_skipped"] > 0
    _, _, printed, _ = plan_print(layers, platform_z=0.0, profile=profile, toolpath_cfg=ToolpathConfig(thin_beads="print"))
    assert printed["beads"]["n_skipped"] == 0 and printed["beads"]["fraction_thin"] == 1.0
    # carried: layer 2 lays the 1.0 mm gap over layer 1's skipped beads, so fewer beads are thin
    assert thin["beads"]["n_carried"] > 0 and thin["beads"]["fraction_thin"] < 0.7
