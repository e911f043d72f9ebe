"""Shared fixtures: one Prefect test server for the whole session, in a temporary PREFECT_HOME."""
from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import trimesh

_HOME = tempfile.mkdtemp(prefix="neuralslicer-prefect-")
os.environ.setdefault("PREFECT_HOME", _HOME)
# the cage cache shared across stores (storage/content_cache.py): one per test session, never ~/.cache
os.environ["NEURALSLICER_CACHE_DIR"] = tempfile.mkdtemp(prefix="neuralslicer-cache-")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("DO_NOT_TRACK", "1")
os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
os.environ.setdefault("PREFECT_SERVER_LOGGING_LEVEL", "WARNING")
# a command's own Prefect server stops with it (flows/local_api.py; tests of the server left up set their own)
os.environ["NEURALSLICER_API_IDLE_S"] = "0"

REPO = Path(__file__).resolve().parents[1]
#: what a Dask Nanny sets in the environment of the process that starts its worker, and never takes back
#: (``distributed.nanny.pre-spawn-environ``)
DASK_SPAWN_ENVIRON = ("MALLOC_TRIM_THRESHOLD_", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


@pytest.fixture(autouse=True)
def _dask_spawn_environ_undone() -> Iterator[None]:
    """After a test that started Dask workers, the session's environment as it was: a CLI subprocess of a later test
    would inherit ``OMP_NUM_THREADS=1`` and optimise on one torch thread, where the run it is compared with used two."""
    saved = {k: os.environ.get(k) for k in DASK_SPAWN_ENVIRON}
    yield
    for k, v in saved.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


@pytest.fixture(scope="session")
def prefect_server() -> Iterator[None]:
    """One ephemeral Prefect server (SQLite) for all flow tests of the session."""
    from prefect.testing.utilities import prefect_test_harness

    with prefect_test_harness(server_startup_timeout=120):
        yield


@pytest.fixture(scope="session")
def ring_path() -> Path:
    """The Ring of the paper (y-up .tet), shipped in neuralslicer/data."""
    from neuralslicer.data import sample

    return sample("ring.tet")


def l_part_mesh() -> trimesh.Trimesh:
    """An L-shaped prism, 20 x 10 x 16 mm, z-up: a 12 mm arm at z 12..16 overhangs the platform."""
    uv = np.array([[0, 0], [8, 0], [8, 12], [20, 12], [20, 16], [0, 16]], dtype=float)
    tri = np.array([[0, 1, 2], [0, 2, 5], [2, 3, 4], [2, 4, 5]])
    prism = trimesh.creation.extrude_triangulation(uv, tri, height=10.0)
    v = prism.vertices[:, [0, 2, 1]]  # extrusion along y; swapping axes mirrors, so flip the faces
    return trimesh.Trimesh(v, prism.faces[:, ::-1], process=True)


@pytest.fixture(scope="session")
def small_part(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The L-shaped part as an STL file."""
    path = tmp_path_factory.mktemp("models") / "lpart.stl"
    l_part_mesh().export(path)
    return path


def fast_config(**overrides: object) -> dict:
    """A configuration that slices a small part in seconds (few samples, a small cage, few steps)."""
    cfg: dict = {
        "samples": {"n_samples": 2000},
        "cage": {"n_elements": 1500},
        "neural": {"optim": {"max_steps": 20, "checkpoint_every": 5}},
        "layers": {"layer_height": 1.0, "thickness_samples": 2000},
        "toolpath": {"line_width": 1.0, "spacing": 1.0, "n_shells": 1, "infill_density": 0.5},
        # collisions are resolved in tests/flows/test_flow.py::test_collisions_fall_back_to_a_collision_free_blend
        "collision_refinements": 0,
        "collision_retries": 0,
        "collision_fallback": "none",
    }
    for key, value in overrides.items():
        cfg[key] = value
    return cfg


@pytest.fixture(scope="session")
def planar_run(prefect_server: None, small_part: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One tiny slice of the L part for the whole session (planar field, ``--objectives none``, fast_config): its
    output folder, the store at ``store.zarr``. Read it only: a test that reruns or changes a run makes its own."""
    import yaml

    from neuralslicer.cli.main import main

    root = tmp_path_factory.mktemp("planar_run")
    cfg = root / "cfg.yaml"
    cfg.write_text(yaml.safe_dump(fast_config()))
    out = root / "run"
    assert main(["slice", str(small_part), "--out", str(out), "--config", str(cfg), "--objectives", "none"]) == 0
    return out


@pytest.fixture
def rng() -> np.random.Generator:
    """A seeded random generator."""
    return np.random.default_rng(0)


class Planted:
    """An object whose unpickling runs a command (what a planted checkpoint or task record would carry)."""

    def __init__(self, marker: str) -> None:
        self.marker = marker

    def __reduce__(self):
        import os
        return (os.system, (f"touch {self.marker}",))
