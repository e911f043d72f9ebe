"""The paper's Bridge: our voxel FEA of its 3-point bending load case against S3-Slicer's own stress result.

S3-Slicer's dataset ships ``DataSet/fem_result/bridgeSmall_new.txt``: 47,520 lines ``index, s1, sxx, syy, szz, sxy,
sxz, syz`` (``PrincipleStressField::InputFEMResult``, ShapeLab/PrincipleStressField.cpp:43-54: column 1 is the largest
principal stress, columns 2-7 the tensor, which :124-126 assembles as [[sxx sxy sxz] [sxy syy syz] [sxz syz szz]]),
one line per tet of the mesh ``bridgeSmall_new``. That mesh (47,520 tets, the paper's Bridge cage size) is not in
the dataset: only ``bridgeSmall.tet`` (100,420 tets) is, so the stresses cannot be matched element by element. They
are compared as distributions, in the .tet's own frame (y up): von Mises percentiles (the load that gives S3's
stress level), the share of elements whose largest-magnitude principal stress is tensile, the share of tau_max
(direction of that stress) within 20 degrees of each axis and of the truss diagonals, over all elements and over
the top 10 % of |sigma_max| (the SR samples T). S3's figures are per element (its tets' volumes are unknown), ours
per voxel (equal volumes).

Cases: the shipped load case (``neuralslicer/examples/paper_bridge/model.yaml``: a pin under the left end of the
bottom chords, a roller (z only) under the right end, 1000 N down on the top chord's middle joint) and two other
readings of the paper's "the bottom of the model is fixed": both ends held in x, y, z (``ends``) and the whole
bottom chord held (``bottom``); the load stays the shipped one.

Usage: python benchmarks/bench_paper_bridge_stress.py [--s3-result PATH] [--cases shipped,ends,bottom]
Writes benchmarks/results/bench_paper_bridge_stress.json.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
EXAMPLE = HERE.parent / "neuralslicer" / "examples" / "paper_bridge" / "model.yaml"
#: a clone (or bare mirror) of github.com/zhangty019/S3_DeformFDM, where --s3-result is not given
S3_REPO_ENV = "S3_DEFORMFDM_REPO"
S3_RESULT = "DataSet/fem_result/bridgeSmall_new.txt"

#: the other readings of the support (build frame, mm); the load stays the shipped one
BOTTOM = [{"box": [[-32, -34, -10.5], [94, 12, -8.4]]}]
ENDS = [{"box": [[-32, -34, -10.5], [-24, 12, -8.4]]}, {"box": [[86, -34, -10.5], [94, 12, -8.4]]}]
#: the truss diagonals of the side frames lie at +-60 degrees from x in the x-y plane of the .tet
AXES = {"x": [1, 0, 0], "y (up)": [0, 1, 0], "z": [0, 0, 1],
        "diagonal +60": [0.5, np.sqrt(3) / 2, 0], "diagonal -60": [0.5, -np.sqrt(3) / 2, 0]}


def read_s3(path: str | None) -> np.ndarray:
    """S3's result as (n, 8): index, s1, sxx, syy, szz, sxy, sxz, syz."""
    if path:
        text = Path(path).read_text()
    elif os.environ.get(S3_REPO_ENV):
        text = subprocess.run(["git", "-C", os.environ[S3_REPO_ENV], "show", f"HEAD:{S3_RESULT}"], check=True,
                              capture_output=True, text=True).stdout
    else:
        raise SystemExit(f"give S3's result file (--s3-result PATH/{S3_RESULT}) or {S3_REPO_ENV}=a clone of "
                         "github.com/zhangty019/S3_DeformFDM")
    return np.loadtxt(text.splitlines(), delimiter=",")


def s3_tensors(rows: np.ndarray) -> np.ndarray:
    """(n, 3, 3) stress tensors of S3's columns."""
    s = rows[:, 2:8]
    t = np.zeros((len(s), 3, 3))
    t[:, 0, 0], t[:, 1, 1], t[:, 2, 2] = s[:, 0], s[:, 1], s[:, 2]
    t[:, 0, 1] = t[:, 1, 0] = s[:, 3]
    t[:, 0, 2] = t[:, 2, 0] = s[:, 4]
    t[:, 1, 2] = t[:, 2, 1] = s[:, 5]
    return t


def figures(stress: np.ndarray) -> dict:
    """Distribution figures of (n, 3, 3) tensors in the .tet frame."""
    w, v = np.linalg.eigh(stress)
    k = np.abs(w).argmax(axis=1)
    idx = np.arange(len(w))
    sig = w[idx, k]
    tau = v[idx, :, k]
    vm = np.sqrt(0.5 * ((w[:, 0] - w[:, 1]) ** 2 + (w[:, 1] - w[:, 2]) ** 2 + (w[:, 2] - w[:, 0]) ** 2))
    top = np.abs(sig) >= np.quantile(np.abs(sig), 0.9)

    def along(mask: np.ndarray) -> dict:
        out = {}
        for name, a in AXES.items():
            a = np.asarray(a, float) / np.linalg.norm(a)
            out[name] = float(np.mean(np.abs(tau[mask] @ a) >= np.cos(np.radians(20))))
        return out

    return {"n": int(len(stress)),
            "von_mises_pct": dict(zip(("p50", "p90", "p99", "max"),
                                      map(float, np.percentile(vm, [50, 90, 99, 100])))),
            "abs_sigma_max_p99": float(np.percentile(np.abs(sig), 99)),
            "tensile_share": float(np.mean(sig > 0)),
            "tensile_share_top10": float(np.mean(sig[top] > 0)),
            "tau_within_20deg": along(np.ones(len(sig), bool)),
            "tau_within_20deg_top10": along(top)}


def our_case(name: str) -> tuple[dict, float]:
    """Our FEA of the example with the case's supports: figures in the .tet frame, and the time."""
    from neuralslicer.fea import run_fea
    from neuralslicer.frames import up_rotation
    from neuralslicer.model.solid import implicit_solid
    from neuralslicer.model.spec import load_model

    spec = load_model(EXAMPLE)
    fea = spec.fea
    if name != "shipped":
        fea = fea.model_validate({**fea.model_dump(), "supports": BOTTOM if name == "bottom" else ENDS})
    t0 = time.perf_counter()
    res = run_fea(implicit_solid(spec), fea)
    seconds = time.perf_counter() - t0
    r = up_rotation(spec.up)                       # build = r @ tet; back: tet = r.T @ build
    stress_tet = np.einsum("ji,njk,kl->nil", r, res.stress, r)
    out = figures(stress_tet)
    out.update(voxels=int(res.grid.n_voxels), voxel_mm=float(res.grid.spacing),
               max_displacement_mm=float(np.abs(res.displacement).max()), supports=fea.model_dump()["supports"])
    return out, seconds


def compare(ours: dict, s3: dict) -> dict:
    """How far our figures are from S3's: the load factor that matches S3's median von Mises, the differences."""
    def diff(a: dict, b: dict) -> dict:
        return {k: round(a[k] - b[k], 4) for k in a}

    return {"load_factor_to_s3_p50": s3["von_mises_pct"]["p50"] / ours["von_mises_pct"]["p50"],
            "load_factor_to_s3_p99": s3["von_mises_pct"]["p99"] / ours["von_mises_pct"]["p99"],
            "tensile_share_diff": ours["tensile_share"] - s3["tensile_share"],
            "tau_within_20deg_diff": diff(ours["tau_within_20deg"], s3["tau_within_20deg"]),
            "tau_within_20deg_top10_diff": diff(ours["tau_within_20deg_top10"], s3["tau_within_20deg_top10"])}


def main() -> None:
    """Run the cases, print the comparison, write the JSON."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--s3-result", help=f"S3's {S3_RESULT} (default: from the clone ${S3_REPO_ENV} names)")
    ap.add_argument("--cases", default="shipped,ends,bottom")
    args = ap.parse_args()
    s3 = figures(s3_tensors(read_s3(args.s3_result)))
    out = {"s3": s3, "cases": {}, "machine": platform.node(), "when": time.strftime("%Y-%m-%d %H:%M")}
    print(f"S3 {S3_RESULT}: {s3['n']} elements, von Mises {s3['von_mises_pct']}, tensile {s3['tensile_share']:.3f}")
    print(f"   tau within 20 deg: {s3['tau_within_20deg']}\n   top 10 %: {s3['tau_within_20deg_top10']}")
    for name in args.cases.split(","):
        ours, seconds = our_case(name)
        cmp = compare(ours, s3)
        out["cases"][name] = {"ours": ours, "vs_s3": cmp, "seconds": seconds}
        print(f"{name}: {ours['voxels']} voxels ({ours['voxel_mm']:.3f} mm), {seconds:.0f} s, von Mises "
              f"{ours['von_mises_pct']}, tensile {ours['tensile_share']:.3f}\n   tau within 20 deg: "
              f"{ours['tau_within_20deg']}\n   top 10 %: {ours['tau_within_20deg_top10']}\n   vs S3: {cmp}")
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "bench_paper_bridge_stress.json").write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
