"""`neuralslicer compare` and the provenance record."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from neuralslicer.config import SliceConfig
from neuralslicer.errors import InputError
from neuralslicer.model.spec import spec_for_file
from neuralslicer.run.compare import compare_runs
from neuralslicer.run.provenance import metrics_entries, provenance
from neuralslicer.tasks.provenance import record_provenance
from neuralslicer.storage import ArtifactStore
from studies_common import torus_file

REPO = Path(__file__).resolve().parents[2]


def _run_folder(path: Path, metrics: dict, prov: dict | None = None) -> Path:
    """An output folder with metrics.json (and provenance.json)."""
    path.mkdir(parents=True)
    (path / "metrics.json").write_text(json.dumps(metrics))
    if prov is not None:
        (path / "provenance.json").write_text(json.dumps(prov))
    return path


def test_provenance_records_inputs_seeds_versions_and_device(tmp_path: Path) -> None:
    """The record hashes the input file's bytes, lists every seed, the versions and the torch device."""
    import hashlib

    model = torus_file(tmp_path)
    spec = spec_for_file(model)
    config = SliceConfig.model_validate({"neural": {"optim": {"seed": 7}}, "samples": {"seed": 3}})
    record = provenance(spec, config)
    assert record["inputs"]["files"][str(model.resolve())] == hashlib.sha256(model.read_bytes()).hexdigest()
    assert record["seeds"] == {"samples.seed": 3, "cage.seed": 0, "neural.optim.seed": 7, "s3_oneshot.seed": 0}
    assert record["versions"]["torch"] and record["versions"]["prefect"] == "3.9.1"
    assert record["device"]["torch_device"] in ("cpu", "cuda")
    assert record["config"]["neural"]["optim"]["seed"] == 7
    entries = metrics_entries(record)
    assert entries["provenance.seeds.neural.optim.seed"] == 7
    assert all(not isinstance(v, (dict, list)) for v in entries.values())
    # the store copy is keyed by the record's content (time and command excluded): the same run, the same key
    store = tmp_path / "store.zarr"
    key1 = record_provenance(tmp_path / "a", str(store), "torus", record)
    key2 = record_provenance(tmp_path / "b", str(store), "torus", {**provenance(spec, config), "command": ["x"]})
    assert key1 == key2
    assert ArtifactStore(store).attrs(f"torus/provenance/{key1}")["provenance"]["seeds"]["samples.seed"] == 3
    other = provenance(spec, config.model_copy(update={"alpha_deg": 40.0}))
    assert record_provenance(tmp_path / "c", str(store), "torus", other) != key1


def test_compare_lists_only_what_differs(tmp_path: Path) -> None:
    """Different parameters and metrics are listed with both values and the delta; equal entries are not."""
    a = _run_folder(tmp_path / "a", {"n_layers": 10, "loss.total": 0.5, "model": "ring", "provenance.seeds.x": 1},
                    {"config": {"cage": {"n_elements": 4000}, "alpha_deg": 45.0}, "recorded_at": "t1"})
    b = _run_folder(tmp_path / "b", {"n_layers": 12, "loss.total": 0.5, "model": "ring", "provenance.seeds.x": 2},
                    {"config": {"cage": {"n_elements": 8000}, "alpha_deg": 45.0}, "recorded_at": "t2"})
    diffs = {(d.section, d.key): d for d in compare_runs(a, b)}
    assert set(diffs) == {("metrics", "n_layers"), ("parameters", "config.cage.n_elements"),
                          ("parameters", "provenance.seeds.x")}
    assert diffs[("metrics", "n_layers")].delta == 2.0
    assert (diffs[("parameters", "config.cage.n_elements")].a, diffs[("parameters", "config.cage.n_elements")].b) == (4000, 8000)
    everything = compare_runs(a, b, include_all=True)
    assert {d.key for d in everything if d.equal} == {"loss.total", "model", "config.alpha_deg"}
    # a relative tolerance makes near-equal numbers equal
    c = _run_folder(tmp_path / "c", {"n_layers": 10, "loss.total": 0.5000001, "model": "ring", "provenance.seeds.x": 1})
    assert [d.key for d in compare_runs(a, c, rtol=1e-5) if d.section == "metrics"] == []
    assert [d.key for d in compare_runs(a, c) if d.section == "metrics"] == ["loss.total"]


def test_compare_rejects_a_folder_without_metrics(tmp_path: Path) -> None:
    """A folder that is not a run output is an input error naming it."""
    a = _run_folder(tmp_path / "a", {"n_layers": 1})
    with pytest.raises(InputError, match="metrics.json"):
        compare_runs(a, tmp_path)


def test_compare_command_prints_a_table_and_exits_1_when_runs_differ(tmp_path: Path) -> None:
    """The command prints the headline figures of both runs, then the differing keys with both values; exit 1 when
    they differ, 0 when not; bad input exits 2."""
    a = _run_folder(tmp_path / "a", {"n_layers": 10, "sf.overhang_area_fraction": 0.25})
    b = _run_folder(tmp_path / "b", {"n_layers": 10, "sf.overhang_area_fraction": 0.125})
    env = {"COLUMNS": "200", "PATH": "/usr/bin:/bin"}
    done = subprocess.run([sys.executable, "-m", "neuralslicer.cli", "compare", str(a), str(b)], cwd=REPO,
                          capture_output=True, text=True, env=env, timeout=120)
    assert done.returncode == 1, done.stderr
    assert "sf.overhang_area_fraction" in done.stdout and "0.25" in done.stdout and "0.125" in done.stdout
    assert "1 difference(s)" in done.stdout
    figures, rest = done.stdout.split("parameters:", 1)
    assert "layers (n_layers)" in figures and "overhang (sf.overhang_area_fraction)" in figures
    assert "n_layers" not in rest and "sf.overhang_area_fraction" in rest   # equal: only among the figures
    same = subprocess.run([sys.executable, "-m", "neuralslicer.cli", "compare", str(a), str(a)], cwd=REPO,
                          capture_output=True, text=True, env=env, timeout=120)
    assert same.returncode == 0 and "0 difference(s)" in same.stdout
    bad = subprocess.run([sys.executable, "-m", "neuralslicer.cli", "compare", str(a), str(tmp_path / "x")],
                         cwd=REPO, capture_output=True, text=True, env=env, timeout=120)
    assert bad.returncode == 2 and "neuralslicer: error:" in bad.stderr


def _compare_json(capsys, *argv: str) -> tuple[int, dict]:
    """Exit status and parsed stdout of `neuralslicer compare ... --json`, in process."""
    from neuralslicer.cli.main import main

    code = main(["compare", *argv, "--json"])
    return code, json.loads(capsys.readouterr().out)


#: the fields of one entry of `compare --json`
ENTRY_KEYS = {"section", "key", "a", "b", "equal", "delta", "only_in"}


def test_compare_json_lists_the_differences_and_exits_1(tmp_path: Path, capsys) -> None:
    """--json: the schema's fields with their types; metrics beyond the tolerance, a parameter that differs and an
    entry in one run only all count (exit 1)."""
    a = _run_folder(tmp_path / "a", {"n_layers": 10, "loss.total": 0.5, "only_a": 1.0, "flags": [1.0, 2.0]},
                    {"config": {"alpha_deg": 45.0}, "seeds": {"samples.seed": 3}})
    b = _run_folder(tmp_path / "b", {"n_layers": 12, "loss.total": 0.5, "flags": [1.0, 2.0]},
                    {"config": {"alpha_deg": 45.0}, "seeds": {"samples.seed": 4}})
    code, doc = _compare_json(capsys, str(a), str(b))
    assert code == 1
    assert set(doc) == {"schema", "run_a", "run_b", "rtol", "atol", "ignore", "differ", "n_differences",
                        "n_by_section", "figures", "differences"}
    # the headline figures either run has (RunMetrics), with their labels, whether they differ or not
    assert doc["figures"] == [{"section": "figures", "key": "n_layers", "label": "layers", "a": 10, "b": 12,
                               "equal": False, "delta": 2.0, "only_in": None}]
    assert doc["schema"] == "neuralslicer.compare/1" and (doc["run_a"], doc["run_b"]) == (str(a), str(b))
    assert doc["rtol"] == 1e-6 and doc["atol"] == 1e-9 and doc["ignore"] == []
    assert doc["differ"] is True and doc["n_differences"] == 3 == len(doc["differences"])
    assert doc["n_by_section"] == {"parameters": 1, "metrics": 2}
    entries = {(d["section"], d["key"]): d for d in doc["differences"]}
    assert all(set(d) == ENTRY_KEYS for d in doc["differences"])
    layers = entries[("metrics", "n_layers")]
    assert (layers["a"], layers["b"], layers["delta"], layers["equal"], layers["only_in"]) == (10, 12, 2.0, False, None)
    assert entries[("metrics", "only_a")] == {"section": "metrics", "key": "only_a", "a": 1.0, "b": None,
                                              "equal": False, "delta": None, "only_in": "a"}
    seed = entries[("parameters", "seeds.samples.seed")]
    assert (seed["a"], seed["b"], seed["equal"]) == (3, 4, False)
    # --all lists the equal entries too, marked equal; they do not count
    code, everything = _compare_json(capsys, str(a), str(b), "--all")
    assert code == 1 and everything["n_differences"] == 3
    assert {d["key"] for d in everything["differences"] if d["equal"]} == {"loss.total", "flags", "config.alpha_deg"}


def test_compare_exits_0_within_the_tolerances(tmp_path: Path, capsys) -> None:
    """Numbers within --rtol/--atol are equal (exit 0, no entries); tighter tolerances make them differ; --ignore
    leaves keys out of the comparison and of the exit status."""
    a = _run_folder(tmp_path / "a", {"loss.total": 0.5, "tiny": 0.0, "curve": [1.0, 2.0]},
                    {"device": {"hostname": "a"}})
    b = _run_folder(tmp_path / "b", {"loss.total": 0.5 * (1 + 1e-8), "tiny": 1e-12, "curve": [1.0, 2.0 + 1e-9]},
                    {"device": {"hostname": "b"}})
    code, doc = _compare_json(capsys, str(a), str(b), "--ignore", "device")
    assert code == 0 and doc["differ"] is False and doc["differences"] == [] and doc["ignore"] == ["device"]
    code, doc = _compare_json(capsys, str(a), str(b))
    assert code == 1 and [d["key"] for d in doc["differences"]] == ["device.hostname"]
    code, doc = _compare_json(capsys, str(a), str(b), "--ignore", "device*", "--rtol", "0", "--atol", "0")
    assert code == 1 and {d["key"] for d in doc["differences"]} == {"loss.total", "tiny", "curve"}
    code, doc = _compare_json(capsys, str(a), str(b), "--ignore", "device", "--rtol", "1e-9", "--atol", "1e-11")
    assert code == 1 and {d["key"] for d in doc["differences"]} == {"loss.total"}


def test_values_equal_tolerances() -> None:
    """|a - b| <= max(rtol * max(|a|, |b|), atol); NaN equals NaN; lists element-wise; bools and strings exactly."""
    from neuralslicer.run.compare import values_equal

    assert values_equal(1.0, 1.0 + 1e-7, rtol=1e-6) and not values_equal(1.0, 1.0 + 1e-5, rtol=1e-6)
    assert values_equal(0.0, 1e-10, atol=1e-9) and not values_equal(0.0, 1e-10, rtol=0.5)
    assert values_equal(float("nan"), float("nan")) and not values_equal(float("nan"), 1.0, atol=1e9)
    assert values_equal([1.0, [2.0]], [1.0, [2.0 + 1e-9]], atol=1e-8) and not values_equal([1.0], [1.0, 2.0])
    assert not values_equal(True, 1) and values_equal("x", "x") and not values_equal("x", "y", atol=1.0)


def test_tables_written_to_a_file_or_log_are_not_cut(monkeypatch, capsys) -> None:
    """Redirected output (no terminal, no COLUMNS) keeps every cell whole: a scheduler's log stays readable."""
    from neuralslicer.run.compare import Difference, print_comparison

    monkeypatch.delenv("COLUMNS", raising=False)
    key = "sf.heldout.overhang_area_fraction_layers." + "x" * 80
    print_comparison([Difference(section="metrics", key=key, a=0.25, b=0.125, equal=False, delta=-0.125)],
                     "runs/" + "a" * 60, "runs/" + "b" * 60)
    out = capsys.readouterr().out
    assert key in out and "…" not in out and "0.125" in out
