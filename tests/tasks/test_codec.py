"""A stored print read back for the export: its program's moves only when asked (``StoredProgram``), the same as
reading the whole group."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from neuralslicer.motion import plan_print
from neuralslicer.motion.output import Motion
from neuralslicer.motion.planning import ProgramMoves
from neuralslicer.storage import ArtifactStore
from neuralslicer.tasks.codec import StoredProgram, read_motion
from neuralslicer.toolpath.synthetic import cap_stack


def test_a_stored_program_reads_its_moves_only_when_asked_and_the_same_as_the_whole_group(tmp_path: Path) -> None:
    tp, program, metrics, report = plan_print(cap_stack(4), platform_z=0.0)
    store = ArtifactStore(tmp_path / "store.zarr")
    ref = store.ref("part/motion/abc", "abc")
    store.write(ref.path, *Motion(tp, program, metrics, report).to_arrays())

    stored = StoredProgram(ref)
    assert stored.profile == program.profile and np.array_equal(stored.part_offset, program.part_offset)
    assert stored.attrs["safe_z"] == program.attrs["safe_z"] and "profile" not in stored.attrs
    assert all(np.size(v) <= 3 for v in vars(stored).values() if isinstance(v, np.ndarray))   # no moves held yet
    moves = stored.read()
    whole_tp, whole, whole_metrics = read_motion(ref, ProgramMoves)
    none_tp, alone, _ = read_motion(ref, ProgramMoves, toolpaths=False)
    assert none_tp is None and whole_metrics == metrics and np.array_equal(whole_tp.xyz, tp.xyz)
    for name in ProgramMoves.ARRAYS:
        assert np.array_equal(getattr(moves, name), getattr(program, name))
        assert np.array_equal(getattr(moves, name), getattr(whole, name))
        assert np.array_equal(getattr(alone, name), getattr(whole, name))
    assert moves.attrs == whole.attrs == stored.attrs and moves.read() is moves
