"""Reproducibility record of a run: exact inputs (hashes), parameters, seeds, package versions and device."""
from __future__ import annotations

import json
import os
import platform
import socket
import subprocess
import sys
import time
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

from pydantic import BaseModel

from neuralslicer.fileio import json_sha256, write_json_atomic

PACKAGES = (
    "neuralslicer", "numpy", "scipy", "torch", "trimesh", "pytetwild", "libigl", "zarr", "prefect",
    "prefect-dask", "dask", "distributed", "pyvista", "scikit-image", "potpourri3d", "pyamg", "pydantic",
)


def package_versions() -> dict[str, str]:
    """Installed versions of the packages that shape the results, and the Python version."""
    out = {"python": platform.python_version()}
    for name in PACKAGES:
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            continue
    return out


def device_info(device: str = "auto", used: dict[str, Any] | None = None) -> dict[str, Any]:
    """The machine and the torch device a run with this device setting uses: ``used`` when the step that optimised
    the field recorded it (``device``, ``torch_threads``, ``cuda_name``, ``cuda_version``; a cached rerun then
    records the device of the run that did the work, without importing torch), else probed."""
    info: dict[str, Any] = {
        "hostname": socket.gethostname(),
        "platform": platform.platform(),
        "machine": platform.machine(),
        "cpu_count": os.cpu_count(),
        "requested": device,
    }
    if used and used.get("device"):
        info["torch_device"] = str(used["device"])
        info["torch_threads"] = used.get("torch_threads")
        info.update({k: used[k] for k in ("cuda_name", "cuda_version") if used.get(k)})
        return info
    try:
        import torch

        from neuralslicer.neural.device import resolve_device

        dev = resolve_device(device)
        info["torch_device"] = str(dev)
        info["torch_threads"] = torch.get_num_threads()
        if dev.type == "cuda":
            info["cuda_name"] = torch.cuda.get_device_name(dev)
            info["cuda_version"] = torch.version.cuda
    except Exception as exc:  # a record, never a failure
        info["torch_device_error"] = str(exc)
    return info


def git_commit(path: Path | None = None) -> str | None:
    """The git commit (with '+dirty' for local changes) of the source tree this package runs from."""
    root = path or Path(__file__).resolve().parents[2]
    try:
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10)
        if head.returncode != 0:
            return None
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=10)
        return head.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return None


def seeds(config: BaseModel) -> dict[str, int]:
    """Every seed of a slicing configuration, by its dotted key."""
    out: dict[str, int] = {}

    def walk(prefix: str, value: Any) -> None:
        if isinstance(value, dict):
            for k, v in value.items():
                walk(f"{prefix}.{k}" if prefix else k, v)
        elif prefix.endswith("seed") and isinstance(value, int):
            out[prefix] = value

    walk("", config.model_dump(mode="json"))
    return out


def input_hashes(spec: BaseModel, extra_files: dict[str, str | Path] | None = None) -> dict[str, Any]:
    """sha256 of every input file (spec components, spec file, extra inputs such as a user field) and the spec digest."""
    from neuralslicer.model.spec import file_sha256, spec_digest

    files: dict[str, str] = {}
    for f in getattr(spec, "files", lambda: [])():
        files[str(Path(f))] = file_sha256(Path(f))
    source = getattr(spec, "source", None)
    if source is not None and Path(source).is_file():
        files[str(source)] = file_sha256(Path(source))
    for label, f in (extra_files or {}).items():
        files[f"{label}:{f}"] = file_sha256(Path(f))
    return {"spec_sha256": spec_digest(spec), "files": files}


def provenance(spec: BaseModel, config: BaseModel, extra_files: dict[str, str | Path] | None = None,
               extra: dict[str, Any] | None = None, device_used: dict[str, Any] | None = None) -> dict[str, Any]:
    """The full record of a run: inputs by hash, spec and config, seeds, package versions, device (``device_used``:
    as the field's optimisation recorded it, see ``device_info``), code, command."""
    cfg = config.model_dump(mode="json")
    device = cfg.get("neural", {}).get("device", "auto") if isinstance(cfg.get("neural"), dict) else "auto"
    return {
        "inputs": input_hashes(spec, extra_files),
        "spec": spec.model_dump(mode="json"),
        "config": cfg,
        "config_sha256": json_sha256(cfg),
        "seeds": seeds(config),
        "versions": package_versions(),
        "device": device_info(device, device_used),
        "code": {"git_commit": git_commit()},
        "command": list(sys.argv),
        "recorded_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        **(extra or {}),
    }


def flatten(data: Any, prefix: str = "") -> dict[str, Any]:
    """Nested dicts to dotted keys (`{"a": {"b": 1}}` -> `{"a.b": 1}`); lists are kept as values."""
    if not isinstance(data, dict):
        return {prefix: data}
    out: dict[str, Any] = {}
    for k, v in data.items():
        key = f"{prefix}.{k}" if prefix else str(k)
        if isinstance(v, dict) and v:
            out.update(flatten(v, key))
        else:
            out[key] = v
    return out


def metrics_entries(record: dict[str, Any]) -> dict[str, Any]:
    """The scalar `provenance.*` entries of a record for metrics.json (no spec/config bodies, no command)."""
    keep = {k: record[k] for k in ("inputs", "config_sha256", "cage_sha256", "seeds", "versions", "device", "code")
            if k in record}
    return {f"provenance.{k}": v for k, v in flatten(keep).items() if not isinstance(v, (list, dict))}


def record_digest(record: dict[str, Any]) -> str:
    """Content key of a record (time and command excluded): the same run gives the same key."""
    return json_sha256({k: v for k, v in record.items() if k not in ("recorded_at", "command")})[:20]


def add_to_metrics(out_dir: str | Path, record: dict[str, Any]) -> None:
    """Merge the `provenance.*` entries into `out_dir/metrics.json` (atomic rewrite)."""
    path = Path(out_dir) / "metrics.json"
    metrics = json.loads(path.read_text()) if path.is_file() else {}
    metrics = {k: v for k, v in metrics.items() if not k.startswith("provenance.")}
    metrics.update(metrics_entries(record))
    write_json_atomic(path, metrics)
