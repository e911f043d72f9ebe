"""The artifact store: atomic groups, completion flags, checkpoints, cache keys, and a layout people can open
(named dimensions, chosen chunks and codecs, consolidated groups, docs/store.md)."""
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
import zarr
from zarr.codecs import BloscCodec

from neuralslicer.storage import ArtifactRef, ArtifactStore, atomic_path, digest, groups_used
from neuralslicer.storage.layout import CHUNK_BYTES, DIMENSIONS, chunk_shape, dimension_names, group_dimensions

REPO = Path(__file__).resolve().parents[2]


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


def test_a_record_of_artifacts_keys_as_the_tuple_of_its_fields():
    from neuralslicer.run.pipeline import RoundPrint, TriedPrint

    a, m, f = ArtifactRef("/s1", "m/f/1", "d1"), ArtifactRef("/s1", "m/m/1", "d2"), ArtifactRef("/s1", "m/p/1", "d3")
    # the export's key from before the records were typed: its caches stay valid
    assert digest("export", [TriedPrint("first", a, m)], [RoundPrint("r", a, m, f)]) == \
        digest("export", [("first", a, m)], [("r", a, m, f)])
    # by the artifacts' digests, not their stores or paths
    assert digest(TriedPrint("first", a, m)) == digest(TriedPrint("first", ArtifactRef("/s2", "x", "d1"), m))
    assert digest(TriedPrint("first", a, m)) != digest(TriedPrint("second", a, m))


def test_an_artifact_is_content_addressed_in_any_store():
    from neuralslicer.tasks.steps import surface_task

    model = ArtifactRef("memory://a/store.zarr", "part/model/abc", "abc")
    out = lambda store: surface_task.pipeline.output({"store": store, "model": model})  # noqa: E731
    assert out("memory://a/store.zarr").digest == out("memory://b/store.zarr").digest
    assert out("memory://a/store.zarr").store != out("memory://b/store.zarr").store


def _lock_file(store: ArtifactStore, path: str) -> Path:
    """Where the store keeps the lock file of an artifact path."""
    from neuralslicer.storage.store import STAGING

    f = Path(str(store.root), STAGING, "locks", path.replace("/", "__") + ".lock")
    f.parent.mkdir(parents=True, exist_ok=True)
    return f


def test_locks_name_host_and_pid_and_are_taken_over_only_when_abandoned(tmp_path, monkeypatch):
    import json
    import os
    import socket
    import time

    import neuralslicer.storage.store as S

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


def _open_store_and_write(args: tuple[str, int]) -> str:
    """Open (creating) the store and write one group under a shared model group; the error's name if any."""
    root, i = args
    try:
        ArtifactStore(root).write(f"model/step{i}", {"x": np.arange(3)})
        return "ok"
    except Exception as exc:  # noqa: BLE001 - the test counts them
        return type(exc).__name__


def test_processes_creating_one_store_at_once_all_succeed(tmp_path):
    """Runs started together on a fresh --store: zarr's check-then-create loses the race with
    ContainsGroupError (measured: 72 of 240 openings failed before the fix); the store absorbs it."""
    import multiprocessing

    with multiprocessing.get_context("fork").Pool(8) as pool:
        for trial in range(10):
            root = str(tmp_path / f"s{trial}.zarr")
            assert pool.map(_open_store_and_write, [(root, i) for i in range(8)]) == ["ok"] * 8
            assert ArtifactStore(root, create=False).children("model") == sorted(f"step{i}" for i in range(8))


def test_a_stream_is_written_as_it_comes_and_read_back_in_slices(tmp_path, monkeypatch):
    """An ArrayStream's parts (any sizes) land as one array in whole chunks; the attributes are read after it, so the
    producer can complete them; read_slices gives it back piece by piece; a producer that fails leaves no group."""
    import neuralslicer.storage.store as store_module
    from neuralslicer.storage import ArrayStream

    monkeypatch.setattr(store_module, "CHUNK_BYTES", 64)
    rng = np.random.default_rng(0)
    parts = [rng.integers(0, 255, n, dtype=np.uint8) for n in (0, 5, 64, 100, 1, 300, 63)]
    attrs: dict = {"dialect": "linuxcnc"}

    def produce():
        yield from parts
        attrs["bytes"] = sum(len(p) for p in parts)

    store = ArtifactStore(tmp_path / "s.zarr")
    store.write("m/program/a", {"gcode": ArrayStream(np.dtype(np.uint8), produce()), "other": np.arange(4)}, attrs)
    arrays, back = store.read("m/program/a")
    assert np.array_equal(arrays["gcode"], np.concatenate(parts)) and back["bytes"] == 533
    assert np.array_equal(arrays["other"], np.arange(4))
    assert zarr.open_array(str(tmp_path / "s.zarr" / "m/program/a/gcode")).chunks == (64,)
    pieces = list(store.read_slices("m/program/a", "gcode", 100))
    assert [len(p) for p in pieces] == [100] * 5 + [33]
    assert np.array_equal(np.concatenate(pieces), arrays["gcode"])

    def broken():
        yield parts[3]
        raise RuntimeError("the producer failed")

    with pytest.raises(RuntimeError, match="producer failed"):
        store.write("m/program/b", {"gcode": ArrayStream(np.dtype(np.uint8), broken())})
    assert not store.exists("m/program/b") and store.children("m/program") == ["a"]


def test_reading_never_creates_a_store(tmp_path):
    from neuralslicer.tasks.codec import read

    missing = tmp_path / "moved" / "store.zarr"
    with pytest.raises(FileNotFoundError, match="no artifact store there"):
        ArtifactStore(missing, create=False)
    with pytest.raises(FileNotFoundError):
        read(ArtifactRef(str(missing), "m/cage/abc", "abc"))
    assert not missing.exists() and not missing.parent.exists()
    st = ArtifactStore(tmp_path / "s.zarr")                       # a writer creates it
    st.write("m/x/1", {"a": np.arange(3)}, {"k": 1})
    assert ArtifactStore(tmp_path / "s.zarr", create=False).read("m/x/1")[1]["k"] == 1


def test_arrays_carry_named_dimensions_chosen_chunks_and_codecs_in_a_consolidated_group(tmp_path):
    store = ArtifactStore(tmp_path / "s.zarr")
    rows = CHUNK_BYTES // 24 * 2 + 5                     # a float64 (n, 3) array of a little over two chunks
    store.write("m/cage/abc", {"vertices": np.zeros((rows, 3)), "tets": np.zeros((7, 4), np.int64)}, {})
    group = zarr.open_group(store.root, mode="r", path="m/cage/abc")
    assert group.metadata.consolidated_metadata is not None
    vertices, tets = group["vertices"], group["tets"]
    assert vertices.metadata.dimension_names == ("vertex", "spatial")
    assert tets.metadata.dimension_names == ("tet", "tet_corner")
    assert vertices.chunks == (CHUNK_BYTES // 24, 3) and tets.chunks == (7, 4)      # whole rows, ~CHUNK_BYTES
    blosc = [c for c in vertices.metadata.codecs if isinstance(c, BloscCodec)]
    assert blosc and blosc[0].cname.value == "zstd" and blosc[0].shuffle.value == "bitshuffle"
    assert store.read("m/cage/abc")[0]["vertices"].shape == (rows, 3)


def test_dimension_names_from_the_table_with_fallbacks():
    assert dimension_names("model", "c2_segments", 3) == ("c2_segment", "endpoint", "spatial")
    assert dimension_names("verify", "angles/printed", 1) == ("printed_segment",)
    assert dimension_names("motion", "program/machine", 2) == ("move", "machine_axis")
    assert dimension_names("field", "weights/net.0.weight", 2) == ("net.0.weight_dim_0", "net.0.weight_dim_1")
    assert dimension_names("nothing", "x", 1) == ("x_dim_0",)
    assert dimension_names("cage", "vertices", 1) == ("vertices_dim_0",)    # another rank than the table's
    assert chunk_shape((), 8) == () and chunk_shape((0, 3), 8) == (1, 3) and chunk_shape((5, 0), 8) == (5, 1)


def test_a_dimension_name_keeps_one_size_per_group():
    dims = group_dimensions("field", {"G": (5,), "history/total": (3,), "history/lr": (4,), "history/sf": (3,)})
    assert dims == {"G": ("vertex",), "history/total": ("step",), "history/lr": ("lr_step",),
                    "history/sf": ("step",)}


def test_no_dimension_is_named_after_an_array_of_its_group():
    # xarray turns an array named like one of its dimensions into a coordinate (or refuses it)
    for kind, table in DIMENSIONS.items():
        for pattern, dims in table.items():
            parent = pattern.rpartition("/")[0]
            leaves = {p.rpartition("/")[2] for p in table if p.rpartition("/")[0] == parent}
            assert not set(dims) & leaves, (kind, pattern)


def test_groups_written_before_dimension_names_still_read(tmp_path):
    store = ArtifactStore(tmp_path / "s.zarr")
    old = zarr.open_group(store.root, mode="w", path="m/field/old")     # zarr's defaults, no names, not consolidated
    old.create_array("G", data=np.arange(4.0))
    old.create_array("history/total", data=np.ones(2))
    old.attrs.update({"kind": "height", "_complete": True})
    assert store.exists("m/field/old") and store.children("m/field") == ["old"]
    arrays, attrs = store.read("m/field/old")
    assert np.array_equal(arrays["G"], np.arange(4.0)) and np.array_equal(arrays["history/total"], np.ones(2))
    assert attrs["kind"] == "height"
    assert list(store.read("m/field/old", ["G"])[0]) == ["G"]


def test_a_written_group_opens_with_xarray(tmp_path):
    import xarray as xr

    store = ArtifactStore(tmp_path / "s.zarr")
    store.write("m/field/abc", {"G": np.arange(5.0), "lpd": np.ones((7, 3)), "history/total": np.ones(3)}, {"k": 1})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        by_path = xr.open_zarr(store.root, group="m/field/abc", consolidated=False)
        own = xr.open_zarr(f"{store.root}/m/field/abc", group="history", consolidated=True)   # its own metadata
    assert by_path["G"].dims == ("vertex",) and by_path["lpd"].dims == ("tet", "spatial") and by_path.attrs["k"] == 1
    assert dict(by_path.sizes) == {"vertex": 5, "tet": 7, "spatial": 3} and own["total"].dims == ("step",)


def test_groups_used_lists_the_steps_a_run_used():
    refs = {"model": ArtifactRef("/s", "m/model/a", "a"), "fea": None, "field": ArtifactRef("/s", "m/field/b", "b")}
    assert groups_used(refs) == {"model": "m/model/a", "field": "m/field/b"}


def test_docs_describe_every_array_and_dimension():
    text = re.sub(r"```.*?```", "", (REPO / "docs" / "store.md").read_text(), flags=re.S)   # prose and tables
    names = set(re.findall(r"`([^`\n]+)`", text))
    for kind, table in DIMENSIONS.items():
        assert kind in names, kind
        for pattern, dims in table.items():
            assert pattern in names, (kind, pattern)
            assert all(d in names for d in dims), (kind, pattern, dims)


@pytest.mark.slow
def test_a_run_opens_with_xarray_by_named_dimensions(planar_run):
    import xarray as xr

    store = planar_run / "store.zarr"
    st = ArtifactStore(store, create=False)
    cage_path, field_path, print_path = (f"lpart/{step}/{st.children(f'lpart/{step}')[0]}"
                                         for step in ("cage", "field", "motion"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cage = xr.open_zarr(store, group=cage_path, consolidated=False)
        field = xr.open_zarr(store, group=field_path, consolidated=False)
        tree = xr.open_datatree(store / print_path, engine="zarr", consolidated=True)   # the group's own metadata
    assert field["G"].dims == ("vertex",) and field["lpd"].dims == ("tet", "spatial")
    assert field.sizes["vertex"] == cage.sizes["vertex"] == cage.attrs["n_vertices"]
    assert field.sizes["tet"] == cage.sizes["tet"] == cage.attrs["n_elements"]
    # the planar field is the height: G = z of the cage vertices; its LPD is +z
    np.testing.assert_array_equal(field["G"].values, cage["vertices"].isel(spatial=2).values)
    np.testing.assert_allclose(field["lpd"].values, np.tile([0.0, 0.0, 1.0], (field.sizes["tet"], 1)), atol=1e-9)
    waypoints, program = tree["toolpaths"].to_dataset(), tree["program"].to_dataset()
    assert waypoints["xyz"].dims == ("waypoint", "spatial") and waypoints["layer"].dims == ("waypoint",)
    assert waypoints.sizes["waypoint"] == tree.attrs["metrics"]["n_waypoints"]
    assert program["machine"].dims == ("move", "machine_axis") and program.sizes["machine_axis"] == 5
    assert program.sizes["move"] >= waypoints.sizes["waypoint"]
    assert int(waypoints["layer"].max()) < st.attrs(f"lpart/layers/{st.children('lpart/layers')[0]}")["n_layers"]
