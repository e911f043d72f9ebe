"""A resumable step's checkpoints in the store: the field's optimisation resumes from the newest complete one."""
from __future__ import annotations

from neuralslicer.storage import ArtifactStore
from neuralslicer.tasks.progress import say

KEEP_CHECKPOINTS = 2


class StoreCheckpoints:
    """Checkpoints of one optimisation as groups `<root>/step_<n>`; the newest complete one resumes a run."""

    def __init__(self, store: ArtifactStore, root: str) -> None:
        """Checkpoints under `root` in `store`."""
        self.store, self.root = store, root
        self.resumed_from: int | None = None

    def save(self, blob: bytes, step: int) -> None:
        """Write a checkpoint atomically, then prune all but the newest few."""
        self.store.write_blob(f"{self.root}/step_{step:08d}", blob, {"step": step})
        for name in self.store.children(self.root)[:-KEEP_CHECKPOINTS]:
            self.store.remove(f"{self.root}/{name}")

    def load(self) -> bytes | None:
        """The newest complete checkpoint, if any."""
        names = self.store.children(self.root)
        if not names:
            return None
        self.resumed_from = int(self.store.attrs(f"{self.root}/{names[-1]}")["step"])
        say(f"resuming the optimisation from step {self.resumed_from}")
        return self.store.read_blob(f"{self.root}/{names[-1]}")
