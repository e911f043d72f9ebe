"""Device selection for the neural optimisation."""
from __future__ import annotations

import math
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import torch

CGROUP_CPU_MAX = Path("/sys/fs/cgroup/cpu.max")


#: files of a GPU driver on Linux (CUDA's control device and its proc entry, ROCm's kfd, WSL's GPU): without one, a
#: GPU build of torch (all PyPI has for Python 3.12 and 3.13) finds no GPU either
GPU_DRIVER_FILES = ("/dev/nvidiactl", "/proc/driver/nvidia", "/dev/kfd", "/dev/dxg")


def cuda_possible() -> bool:
    """Whether torch could use a GPU here, decided without importing it: not with a CPU build (local version
    ``+cpu``), nor on Linux without a GPU driver's files; elsewhere a GPU build may."""
    import sys
    from importlib.metadata import PackageNotFoundError, version

    try:
        if version("torch").endswith("+cpu"):
            return False
    except PackageNotFoundError:
        return False
    return not sys.platform.startswith("linux") or any(Path(f).exists() for f in GPU_DRIVER_FILES)


def resolve_device(device: str = "auto") -> torch.device:
    """'auto' -> CUDA when available, else CPU; any other string is passed to torch.device."""
    import torch

    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def resolve_dtype(name: str) -> torch.dtype:
    """'float32' | 'float64' -> torch dtype."""
    import torch

    return {"float32": torch.float32, "float64": torch.float64}[name]


def available_cpus(cpu_max: Path = CGROUP_CPU_MAX) -> int:
    """CPUs this process may use: its affinity mask, capped by a cgroup v2 CPU quota when one is set
    (a container or a batch-scheduler slot), not the machine's count."""
    n = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    try:
        quota, period = cpu_max.read_text().split()[:2]
        if quota != "max":
            n = min(n, max(1, math.ceil(int(quota) / int(period))))
    except (OSError, ValueError):
        pass
    return max(1, n)


#: spins an idle OpenMP worker makes before it sleeps (libgomp's default is 300,000). On a node where another
#: job wants the cores, spinning workers take the time slices the working ones need: two optimisations at once ran
#: 27x slower each with the default, 2.3x with 5,000, and a quiet one loses under 4 % (benchmarks/bench_neural.py
#: loaded).
GOMP_SPINCOUNT = 5000


def limit_threads() -> int:
    """Torch's intra-op threads set to the CPUs available (never more than torch chose); the count. Before torch is
    imported (the command line calls this before it knows whether a field is optimised at all), a process allowed
    fewer CPUs than the machine has gets ``OMP_NUM_THREADS``, and every process a short ``GOMP_SPINCOUNT`` (each
    unless set), which torch's OpenMP reads on import."""
    import sys

    n = available_cpus()
    if "torch" not in sys.modules:
        os.environ.setdefault("GOMP_SPINCOUNT", str(GOMP_SPINCOUNT))
        if n < (os.cpu_count() or n):
            os.environ.setdefault("OMP_NUM_THREADS", str(n))
        return n
    import torch

    n = min(torch.get_num_threads(), n)
    torch.set_num_threads(n)
    return n


def device_record(device: torch.device) -> dict[str, Any]:
    """What an optimisation records of the device it ran on (the run's provenance reads it back)."""
    import torch

    out: dict[str, Any] = {"device": str(device), "torch_threads": torch.get_num_threads()}
    if device.type == "cuda":
        out.update(cuda_name=torch.cuda.get_device_name(device), cuda_version=torch.version.cuda)
    return out
