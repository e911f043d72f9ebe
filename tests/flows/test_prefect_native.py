"""Deployed flows as Prefect runs them (issue 33): the command line's preflight with one-line failures, a spec's own up
axis, the served and scheduled deployments, the gpu tag, the report's figures embedded, run logs at INFO."""
from __future__ import annotations

import base64
import io
import logging
import re
from pathlib import Path

import pytest
import yaml
from PIL import Image

from conftest import fast_config
from neuralslicer.config import SliceConfig
from neuralslicer.errors import InputError
from neuralslicer.run.report_embed import embed_figures


def _spec(folder: Path, part: Path, up: str) -> Path:
    """A spec of the part with its own up axis."""
    path = folder / "part.yaml"
    path.write_text(yaml.safe_dump({"up": up, "components": [{"type": "mesh", "file": str(part)}]}))
    return path


def test_the_preflight_keeps_a_specs_own_up_axis_and_names_the_flows_parameters(small_part: Path, tmp_path: Path
                                                                                ) -> None:
    """check_slice (the command line's and the deployed flow's checks): a spec's up stays unless one is given; an
    error names the parameter (Names() by default), not a flag."""
    from neuralslicer.run.preflight import check_slice

    spec = _spec(tmp_path, small_part, "y")
    config = SliceConfig.model_validate(fast_config())
    out, store = tmp_path / "out", str(tmp_path / "out" / "store.zarr")
    assert check_slice(spec, out, store, config).up == "y"
    assert check_slice(spec, out, store, config, up="z").up == "z"
    assert check_slice(small_part, out, store, config).up == "z"
    tall = SliceConfig.model_validate(fast_config(layers={"layer_height": 100.0}))
    with pytest.raises(InputError, match=r"^layers\.layer_height: 100 mm is at least the model's height"):
        check_slice(small_part, out, store, tall)
    with pytest.raises(InputError, match="no such file"):
        check_slice(tmp_path / "missing.stl", out, store, config)


def test_a_deployed_slice_fails_on_bad_input_with_one_line_in_its_state(prefect_server: None, small_part: Path,
                                                                        tmp_path: Path) -> None:
    """slice_model runs the preflight first: bad input ends the run Failed, its message the one line (the parameter
    it names), and nothing is written."""
    from neuralslicer.flows.studies import slice_model

    out = tmp_path / "out"
    missing = tmp_path / "missing.stl"
    state = slice_model(model=str(missing), out_dir=str(out), return_state=True)
    assert state.is_failed() and state.message == f"{missing}: no such file"
    state = slice_model(model=str(small_part), out_dir=str(out), config=fast_config(layers={"layer_height": 100.0}),
                        return_state=True)
    assert state.is_failed() and state.message.startswith("layers.layer_height: 100 mm is at least the model's height")
    with pytest.raises(InputError, match="no such file"):      # called from Python: the error itself
        slice_model(model=str(missing), out_dir=str(out))
    assert not out.exists()


def test_bad_input_drops_prefects_traceback_records_only() -> None:
    """The filter quiet_input_errors installs: a record carrying an InputError (or a parameter that failed validation)
    is dropped, any other record passes."""
    from prefect.exceptions import ParameterTypeError

    from neuralslicer.flows.settings import _OneLineInputErrors

    def record(exc: BaseException | None) -> logging.LogRecord:
        return logging.LogRecord("prefect.flow_runs", logging.ERROR, __file__, 1, "failed", None,
                                 (type(exc), exc, None) if exc else None)

    keep = _OneLineInputErrors().filter
    assert not keep(record(InputError("model", "no such file")))
    assert not keep(record(ParameterTypeError("up: not one of x, y, z")))
    assert keep(record(RuntimeError("a bug"))) and keep(record(None))


def test_the_terminal_stays_quiet_while_the_run_log_gets_info(monkeypatch: pytest.MonkeyPatch) -> None:
    """The command line's Prefect defaults: the console handler at WARNING, the loggers (and so the API handler) at
    Prefect's INFO; a user's own settings win."""
    from neuralslicer.flows.settings import CONSOLE_LEVEL, prefect_environment

    monkeypatch.delenv("PREFECT_LOGGING_LEVEL", raising=False)
    monkeypatch.delenv(CONSOLE_LEVEL, raising=False)
    prefect_environment()
    import os

    assert os.environ[CONSOLE_LEVEL] == "WARNING" and "PREFECT_LOGGING_LEVEL" not in os.environ
    monkeypatch.setenv(CONSOLE_LEVEL, "INFO")
    prefect_environment()
    assert os.environ[CONSOLE_LEVEL] == "INFO"


def test_the_field_step_takes_the_gpu_tag_on_cuda_only() -> None:
    """device_tags: the tag a CUDA optimisation carries (a tag concurrency limit 'gpu' throttles it), none on the
    CPU or without an optimisation."""
    from neuralslicer.flows.slice import GPU_TAG, device_tags

    assert GPU_TAG == "gpu"
    assert device_tags("cuda") == ("gpu",) and device_tags("cuda:1") == ("gpu",)
    assert device_tags("cpu") == () and device_tags(None) == ()


def test_auto_resolves_without_torch_on_a_cpu_build(monkeypatch) -> None:
    """``auto`` on a CPU build of torch (its distribution's version ends in +cpu) is the CPU, decided without importing
    torch (a cached rerun never needs it); on another build torch decides."""
    import sys

    from neuralslicer.flows import slice as slice_flow_module
    from neuralslicer.neural import device

    monkeypatch.setattr("importlib.metadata.version", lambda name: "2.13.0+cpu")
    monkeypatch.setitem(sys.modules, "torch", None)          # importing torch now fails
    assert device.cuda_possible() is False and slice_flow_module.device_tags("auto") == ()
    monkeypatch.setattr("importlib.metadata.version", lambda name: "2.13.0")      # a CUDA build (PyPI's for 3.12)
    monkeypatch.setattr(device, "GPU_DRIVER_FILES", ())                          # on a machine without a GPU driver
    assert device.cuda_possible() is (not sys.platform.startswith("linux"))
    monkeypatch.setattr(device, "GPU_DRIVER_FILES", (__file__,))                 # with one
    assert device.cuda_possible() is True
    with pytest.raises(ImportError):
        slice_flow_module.device_tags("auto")


def test_the_flow_and_its_tasks_load_without_the_heavy_libraries() -> None:
    """What a cached rerun loads (the command, the flow, the tasks, the field's device tag on this CPU build): none of
    torch, the plotting, mesh, FEA and point-cloud libraries, which cost it 3.5 s (6.4 against 2.9 s wall)."""
    import subprocess
    import sys

    heavy = ("torch", "matplotlib", "trimesh", "scipy", "pyvista", "igl", "pytetwild", "PIL")
    code = ("import sys; from neuralslicer.cli.main import main; import neuralslicer.flows.slice as s; "
            "import neuralslicer.tasks.steps, neuralslicer.tasks.export; s.device_tags('auto'); "
            f"print(sorted(m for m in {heavy!r} if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "[]"


def test_the_served_deployments_keep_a_specs_up_and_carry_the_slice_schedule(tmp_path: Path) -> None:
    """neuralslicer serve's deployments: every flow of the table, loaded by module path, no up axis unless given, the
    cron schedule on the slice (what --schedule names)."""
    from neuralslicer.flows.serve import DeploymentDefaults, runner_deployments

    defaults = DeploymentDefaults(model=str(tmp_path / "ring.yaml"), out=str(tmp_path / "runs"), cron="0 3 * * *")
    deployments = {d.name: d for d in runner_deployments(defaults)}
    assert set(deployments) == {"slice", "initial-guess", "cages", "batch"}
    slice_ = deployments["slice"]
    assert slice_.entrypoint == "neuralslicer.flows.studies.slice_model"
    assert slice_.parameters == {"model": str(tmp_path / "ring.yaml"), "out_dir": str(tmp_path / "runs" / "slice")}
    assert [s.schedule.cron for s in slice_.schedules] == ["0 3 * * *"]
    assert not deployments["cages"].schedules
    assert deployments["batch"].parameters["models"] == [str(tmp_path / "ring.yaml")]


def test_prefect_yaml_sets_no_up_axis_and_schedules_the_slice() -> None:
    """deployments/prefect.yaml: the spec's own up axis (no deployment sets up or units), the slice scheduled."""
    doc = yaml.safe_load((Path(__file__).resolve().parents[2] / "deployments" / "prefect.yaml").read_text())
    deployments = {d["name"]: d for d in doc["deployments"]}
    assert all("up" not in d["parameters"] and "units" not in d["parameters"] for d in deployments.values())
    assert deployments["slice"]["parameters"]["model"] == "neuralslicer/data/ring.yaml"
    assert deployments["slice"]["schedules"][0]["cron"] == "0 3 * * *"


def _png(path: Path, width: int, height: int) -> Path:
    """A noisy RGB picture (it does not compress away)."""
    import numpy as np

    rng = np.random.default_rng(0)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(rng.integers(0, 255, (height, width, 3), dtype=np.uint8)).save(path)
    return path


def test_the_reports_figures_are_embedded_downscaled_and_within_a_budget(tmp_path: Path) -> None:
    """embed_figures: no relative image link is left; the pictures are PNG data URIs at most 720 px wide; past the
    budget a figure is named instead; links that are not images stay."""
    _png(tmp_path / "figures" / "a.png", 1400, 700)
    _png(tmp_path / "figures" / "b.png", 300, 200)
    markdown = "# r\n\n[metrics](https://example.org/m)\n\n![A](figures/a.png)\n\n![B](figures/b.png)\n\n![C](figures/c.png)\n"
    out = embed_figures(markdown, tmp_path)
    assert not re.search(r"!\[[^\]]*\]\((?!data:)", out)
    uris = re.findall(r"!\[[^\]]*\]\(data:image/png;base64,([^)]+)\)", out)
    sizes = [Image.open(io.BytesIO(base64.b64decode(u))).size for u in uris]
    assert sizes == [(720, 360), (300, 200)]
    assert "[metrics](https://example.org/m)" in out and "figures/c.png` (not readable)" in out
    small = embed_figures(markdown, tmp_path, budget_bytes=len(uris[0]) + 100)
    assert small.count("data:image/png") == 1 and "(not embedded" in small


def test_a_deployed_study_checks_its_models_first(prefect_server: None, small_part: Path, tmp_path: Path,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """A study run by a deployment (its runtime's deployment id set) runs the slice's checks on every model before any
    branch: bad input fails it with one line; called from the command line (no deployment) it does not repeat them."""
    from neuralslicer.flows.studies import check_deployed, StudyOptions, cage_study

    tall = fast_config(layers={"layer_height": 100.0})
    options = StudyOptions(out_dir=str(tmp_path / "study"), config=SliceConfig.model_validate(tall))
    check_deployed([str(small_part)], options)                      # not a deployment's run: nothing checked
    monkeypatch.setenv("PREFECT__RUNTIME__DEPLOYMENT__ID", "6f1c1d4e-0000-4000-8000-000000000000")
    state = cage_study(model=str(small_part), out_dir=str(tmp_path / "study"), cage_elements=[1000], config=tall,
                       return_state=True)
    assert state.is_failed() and state.message.startswith("layers.layer_height: 100 mm is at least the model's height")
    assert not (tmp_path / "study" / "study.json").exists()


def test_a_step_line_reaches_a_workers_output_once() -> None:
    """console_prints_info: a run logger whose INFO records a Prefect console handler prints (a worker's output) makes
    say() leave its own stderr line out; the command line's console (WARNING) does not."""
    from prefect.logging.handlers import PrefectConsoleHandler

    from neuralslicer.tasks.progress import console_prints_info

    parent, child = logging.getLogger("ns-test-console"), logging.getLogger("ns-test-console.runs")
    parent.setLevel(logging.INFO)
    parent.propagate = False                      # the root's handlers are whatever Prefect's set-up left there
    handler = PrefectConsoleHandler(level=logging.WARNING)
    parent.addHandler(handler)
    try:
        assert not console_prints_info(child)
        handler.setLevel(logging.INFO)
        assert console_prints_info(child)
        parent.setLevel(logging.WARNING)          # PREFECT_LOGGING_LEVEL=WARNING: no INFO record at all
        assert not console_prints_info(child)
    finally:
        parent.removeHandler(handler)
