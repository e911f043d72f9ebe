"""The artifact store: atomic groups, completion flags, checkpoints, cache keys."""
from pathlib import Path

import numpy as np
import pytest
import zarr

from storage import ArtifactRef, ArtifactStore, atomic_path, digest


def test_write_read_roundtrip_with_nested_names(tmp_path):
    store = ArtifactStore(tmp_path / "s.zarr")
    store.write("m/step/abc", {"x": np.arange(5.0), "history/total": np.ones(3)}, {"p": 1, "v": np.float64(2.5)})
    arrays, attrs = store.read("m/step/abc")
    assert np.array_equal(arrays["x"], np.arange(5.0))
    assert np.array_equal(arrays["history/total"], np.ones(3))
    assert attrs["p"] == 1 and attrs["v"] == 2.5
    assert store.exists("m/step/abc")
    assert not store.exists("m/step/other")


def test_crash_during_write_leaves_no_visible_group_and_keeps_previous(tmp_path):
    store = ArtifactStore(tmp_path / "s.zarr")
    store.write("m/step/k", {"x": np.zeros(3)}, {"version": 1})
    bad = np.array([object()], dtype=object)  # fails after the first array was written
    with pytest.raises(TypeError):
        store.write("m/step/k", {"x": np.ones(3), "y": bad}, {"version": 2})
    with pytest.raises(TypeError):
        store.write("m/step/new", {"x": np.ones(3), "y": bad}, {})
    arrays, attrs = store.read("m/step/k")
    assert attrs["version"] == 1 and np.array_equal(arrays["x"], np.zeros(3))
    assert not store.exists("m/step/new")
    assert store.children("m/step") == ["k"]


def test_incomplete_group_is_not_read_as_valid(tmp_path):
    store = ArtifactStore(tmp_path / "s.zarr")
    g = zarr.open_group(store.root, mode="w", path="m/step/half")
    g.create_array("x", data=np.ones(4))  # no completion flag: what a crash mid-write would leave on a remote store
    assert not store.exists("m/step/half")
    with pytest.raises(FileNotFoundError):
        store.read("m/step/half")


def test_blob_and_children_and_remove(tmp_path):
    store = ArtifactStore(tmp_path / "s.zarr")
    for step in (5, 10, 15):
        store.write_blob(f"m/ckpt/step_{step:08d}", bytes([step]) * 10, {"step": step})
    assert store.children("m/ckpt") == ["step_00000005", "step_00000010", "step_00000015"]
    assert store.read_blob("m/ckpt/step_00000010") == bytes([10]) * 10
    store.remove("m/ckpt/step_00000005")
    assert store.children("m/ckpt") == ["step_00000010", "step_00000015"]


def test_atomic_path_keeps_old_file_on_failure(tmp_path):
    target = tmp_path / "a.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("boom")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]


def test_digest_uses_artifact_digests_and_model_fields():
    from neuralslicer.cage import CageConfig

    a = ArtifactRef("/s1", "m/x/1", "d1")
    b = ArtifactRef("/s2", "other/path", "d1")
    assert digest("cage", a, CageConfig()) == digest("cage", b, CageConfig())
    assert digest("cage", a, CageConfig()) != digest("cage", a, CageConfig(n_elements=5000))
    assert digest("cage", a) != digest("cage", ArtifactRef("/s1", "m/x/1", "d2"))


def test_two_stores_never_share_a_cache_record():
    # remote (fsspec) stores keep their Prefect records in one shared folder: the store is in the key
    from tasks.steps import surface_task

    model = ArtifactRef("memory://a/store.zarr", "part/model/abc", "abc")
    key = lambda store: surface_task.pipeline.cache_key(None, {"store": store, "model": model})  # noqa: E731
    assert key("memory://a/store.zarr") == key("memory://a/store.zarr")
    assert key("memory://a/store.zarr") != key("memory://b/store.zarr")
    # the artifact itself is content-addressed: the same digest in either store
    out = lambda store: surface_task.pipeline.output({"store": store, "model": model})  # noqa: E731
    assert out("memory://a/store.zarr").digest == out("memory://b/store.zarr").digest


def _lock_file(store: ArtifactStore, path: str) -> Path:
    """Where the store keeps the lock file of an artifact path."""
    from storage.store import STAGING

    f = Path(str(store.root), STAGING, "locks", path.replace("/", "__") + ".lock")
    f.parent.mkdir(parents=True, exist_ok=True)
    return f


def test_locks_name_host_and_pid_and_are_taken_over_only_when_abandoned(tmp_path, monkeypatch):
    import json
    import os
    import socket
    import time

    import storage.store as S

    st = ArtifactStore(tmp_path / "s.zarr")
    f = _lock_file(st, "m/cage/x")
    # held by a live process on another host: waited for, not broken
    f.write_text(json.dumps({"host": "elsewhere", "pid": os.getpid()}))
    with pytest.raises(TimeoutError, match="elsewhere"):
        with st.lock("m/cage/x", timeout_s=0.3):
            pass
    # its heartbeat stopped long ago: abandoned, taken over
    old = time.time() - 2 * S.LOCK_STALE_S
    os.utime(f, (old, old))
    with st.lock("m/cage/x", timeout_s=5):
        holder = json.loads(f.read_text())
        assert holder == {"host": socket.gethostname(), "pid": os.getpid()}
    assert not f.exists()
    # a holder on this host that has exited: taken over at once
    f.write_text(json.dumps({"host": socket.gethostname(), "pid": 2 ** 22 + 12345}))
    with st.lock("m/cage/x", timeout_s=5):
        pass
    # while held, the heartbeat renews the file's time
    monkeypatch.setattr(S, "LOCK_HEARTBEAT_S", 0.05)
    with st.lock("m/cage/y", timeout_s=5):
        g = _lock_file(st, "m/cage/y")
        os.utime(g, (old, old))
        time.sleep(0.3)
        assert time.time() - g.stat().st_mtime < 5


def test_reading_never_creates_a_store(tmp_path):
    from tasks.codec import read

    missing = tmp_path / "moved" / "store.zarr"
    with pytest.raises(FileNotFoundError, match="no artifact store there"):
        ArtifactStore(missing, create=False)
    with pytest.raises(FileNotFoundError):
        read(ArtifactRef(str(missing), "m/cage/abc", "abc"))
    assert not missing.exists() and not missing.parent.exists()
    st = ArtifactStore(tmp_path / "s.zarr")                       # a writer creates it
    st.write("m/x/1", {"a": np.arange(3)}, {"k": 1})
    assert ArtifactStore(tmp_path / "s.zarr", create=False).read("m/x/1")[1]["k"] == 1
