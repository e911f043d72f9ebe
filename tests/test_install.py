"""`pip install .` adds one top-level name, `neuralslicer`, with every module of the tree under it."""
from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

from conftest import REPO

#: the repository's folders that install as neuralslicer's subpackages (pyproject.toml's package-dir)
OUTER = ("cli", "flows", "tasks", "storage", "deployments")


def tracked_files() -> list[str]:
    """The files git tracks (what a clone has)."""
    done = subprocess.run(["git", "ls-files"], cwd=REPO, capture_output=True, text=True, check=True)
    return done.stdout.split()


def test_pip_install_adds_only_neuralslicer(tmp_path: Path) -> None:
    """Installed from a copy of the tracked tree into an empty folder: the only top-level module is neuralslicer,
    and every module of the core and of the outer layers is inside it (cli/main.py as neuralslicer/cli/main.py)."""
    clone = tmp_path / "clone"
    for name in tracked_files():
        if (REPO / name).is_file():
            (clone / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / name, clone / name)
    site = tmp_path / "site"
    done = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation",
                           "--no-compile", "--target", str(site), str(clone)], capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    top = {p.name for p in site.iterdir() if not p.name.endswith(".dist-info") and p.name != "bin"}
    assert top == {"neuralslicer"}, top
    modules = [n for n in tracked_files() if n.endswith(".py") and n.split("/")[0] in ("neuralslicer", *OUTER)
               and "/examples/" not in n]
    missing = [n for n in modules
               if not (site / (n if n.startswith("neuralslicer/") else f"neuralslicer/{n}")).is_file()]
    assert not missing, missing
    assert (site / "neuralslicer" / "deployments" / "prefect.yaml").is_file()
    assert (site / "neuralslicer" / "data" / "ring.tet").is_file()
    # the installed package imports from there, outer layers included, and finds nothing beside it to add
    probe = subprocess.run([sys.executable, "-c", "import neuralslicer, neuralslicer.storage, neuralslicer.tasks.codec; "
                            "print(neuralslicer.storage.__file__, len(neuralslicer.__path__))"],
                           cwd=tmp_path, env={"PYTHONPATH": str(site), "PATH": "/usr/bin:/bin"},
                           capture_output=True, text=True, timeout=300)
    assert probe.returncode == 0, probe.stderr[-3000:]
    where, n_path = probe.stdout.split()
    assert Path(where).is_relative_to(site) and n_path == "1"


def test_constraints_pin_every_dependency_within_its_range() -> None:
    """pyproject.toml gives ranges, constraints.txt the exact versions `make` installs: every dependency (extras
    too) has a pin there, and the pin lies in the range."""
    import tomllib

    from packaging.requirements import Requirement
    from packaging.utils import canonicalize_name

    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    wanted = [Requirement(r) for r in project["dependencies"]]
    wanted += [Requirement(r) for extra in project["optional-dependencies"].values() for r in extra]
    pins = {}
    for line in (REPO / "constraints.txt").read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            name, version = line.split("==")
            pins[canonicalize_name(name)] = version.strip()
    for req in wanted:
        pin = pins.get(canonicalize_name(req.name))
        assert pin is not None, f"{req.name} has no pin in constraints.txt"
        assert req.specifier.contains(pin, prereleases=True), f"{req.name}=={pin} is outside {req.specifier}"
        assert len(req.specifier) >= 1 and not any(s.operator == "==" for s in req.specifier), f"{req}: a range, not a pin"


def test_another_checkout_runs_alone_through_checkout_env(tmp_path: Path) -> None:
    """benchmarks/checkout_env.py: a subprocess imports the other checkout's core and outer layers (mapped as its
    pyproject.toml says), not this editable install's, and so do the processes it starts."""
    sys.path.insert(0, str(REPO / "benchmarks"))
    try:
        from checkout_env import checkout_environ
    finally:
        sys.path.remove(str(REPO / "benchmarks"))
    other = tmp_path / "before"
    for folder in ("neuralslicer", "tasks", "storage"):
        (other / folder).mkdir(parents=True)
        (other / folder / "__init__.py").write_text(f"WHICH = 'before/{folder}'\n")
    (other / "tasks" / "steps.py").write_text("from neuralslicer.storage import WHICH as STORE\n")
    (other / "pyproject.toml").write_text('[tool.setuptools.package-dir]\n"neuralslicer.tasks" = "tasks"\n'
                                          '"neuralslicer.storage" = "storage"\n')
    probe = ("import neuralslicer, neuralslicer.tasks.steps as s, neuralslicer.storage as st; "
             "print(neuralslicer.WHICH, s.STORE, st.__file__)")
    child = f"import subprocess, sys; subprocess.run([sys.executable, '-c', {probe!r}], check=True)"
    for code in (probe, child):
        done = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=checkout_environ(other),
                              capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr[-3000:]
        which, store, where = done.stdout.split()
        assert (which, store) == ("before/neuralslicer", "before/storage") and Path(where).is_relative_to(other)
