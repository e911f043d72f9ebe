"""Toolpaths parked on disk while the program is planned: the same bytes back, the same program, nothing left behind."""
from __future__ import annotations

import numpy as np
import pytest

import neuralslicer.motion.park as park
from neuralslicer.motion import load_profile, plan_print
from neuralslicer.motion.park import parked
from neuralslicer.toolpath.synthetic import cap_stack
from neuralslicer.toolpath.types import Toolpaths


def _print() -> Toolpaths:
    """A small curved print's toolpaths (caps: tilted axes, travels between paths)."""
    from neuralslicer.toolpath import toolpaths

    return toolpaths(cap_stack(6), platform_z=0.0)


def _copy(tp: Toolpaths) -> Toolpaths:
    return Toolpaths(**{name: getattr(tp, name).copy() for name in Toolpaths.ARRAYS}, attrs=dict(tp.attrs))


def test_parked_toolpaths_come_back_byte_for_byte_and_the_folder_goes(tmp_path):
    tp = _print()
    given = _copy(tp)
    with parked(given, tmp_path, min_waypoints=0) as waiting:
        assert waiting.on_disk and len(waiting) == len(tp)
        assert all(len(getattr(given, name)) == 0 for name in Toolpaths.ARRAYS)   # not held twice
        xyz = waiting.xyz
        assert isinstance(xyz, np.memmap) and not xyz.flags.writeable           # mapped, read-only
        assert np.array_equal(xyz, tp.xyz)
        del xyz
        back = waiting.load()
        folders = list(tmp_path.iterdir())
        assert len(folders) == 1 and sorted(f.name for f in folders[0].iterdir()) == sorted(
            f"{name}.npy" for name in Toolpaths.ARRAYS)
    assert list(tmp_path.iterdir()) == []
    for name in Toolpaths.ARRAYS:
        assert getattr(back, name).dtype == getattr(tp, name).dtype
        assert getattr(back, name).tobytes() == getattr(tp, name).tobytes()
    assert back.attrs == tp.attrs


def test_a_small_print_stays_in_memory_and_a_failed_block_leaves_no_folder(tmp_path):
    tp = _print()
    with parked(tp, tmp_path) as waiting:                       # far below PARK_WAYPOINTS
        assert not waiting.on_disk and waiting.load() is tp and waiting.xyz is tp.xyz
    with pytest.raises(RuntimeError, match="planning failed"):
        with parked(_copy(tp), tmp_path, min_waypoints=0):
            raise RuntimeError("planning failed")
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(AttributeError):
        waiting.not_a_column  # noqa: B018


def test_the_motion_step_plans_the_same_program_from_parked_toolpaths(monkeypatch, tmp_path):
    """plan_print with every print parked (the threshold at 0) and in memory: the same toolpaths, program and
    metrics (timings aside), and the scratch folder empty afterwards."""
    from neuralslicer.motion.plan import plan_motion_of
    from neuralslicer.toolpath.plan import plan_toolpaths

    profile = load_profile("table_bc_linuxcnc")
    layers = cap_stack(6)
    ref_tp, ref_prog, ref_metrics, _ = plan_print(layers, platform_z=0.0, profile=profile)
    monkeypatch.setattr(park, "PARK_WAYPOINTS", 0)
    tp = plan_toolpaths(layers, platform_z=0.0, profile=profile)
    out_tp, prog, metrics, _ = plan_motion_of(tp, platform_z=0.0, profile=profile, consume=True, scratch=tmp_path)
    assert list(tmp_path.iterdir()) == []
    for name in Toolpaths.ARRAYS:
        assert np.array_equal(getattr(out_tp, name), getattr(ref_tp, name))
    for name in prog.ARRAYS:
        assert np.array_equal(getattr(prog, name), getattr(ref_prog, name))
    metrics.pop("timings_s"), ref_metrics.pop("timings_s")
    assert metrics == ref_metrics and prog.attrs == ref_prog.attrs
