"""Where the faithful S3 (``baselines/s3_deform.py``) leaves overhang, per outer iteration (docs/baselines.md,
"Where S3's residual is").

    python benchmarks/bench_s3_residual.py ring 4      # S3's ring on its own mesh, 4 outer iterations (~3-5 min)
    python benchmarks/bench_s3_residual.py sphere 4    # the ball of tests/baselines/test_baselines_s3_iterative.py (1 s)

For each outer iteration: the boundary overhang at 45 deg in the deformed space and realised (grad G), and the
held-out overhang (the tests' helpers: area-uniform surface points, the LPD of the tet they lie in), split into
points within 5 mm of the floor and above. For the ring also where the residual is (its angle from the top of
the ring) and where the heat-method growth direction from the bottom band meets itself on the inner top arch.
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests"), str(ROOT / "tests" / "baselines")]

import neuralslicer.baselines.s3_deform as d  # noqa: E402
from neuralslicer.baselines.s3_config import S3DeformConfig  # noqa: E402
from neuralslicer.neural.initial_guess import heat_geodesic  # noqa: E402
from neuralslicer.tetmesh import orient_tets  # noqa: E402
from test_baselines_s3_iterative import boundary_samples, l_part, sphere  # noqa: E402


def load(which: str) -> tuple[np.ndarray, np.ndarray, int]:
    """(vertices, tets, number of held-out points) of the ring (up y) or a test model."""
    if which == "ring":
        from neuralslicer.frames import apply_up
        from neuralslicer.model.io import read_volume

        V, T = read_volume(str(Path(__file__).resolve().parents[1] / "neuralslicer" / "data" / "ring.tet"))
        return apply_up(V, "y"), T, 20000
    return {"sphere": sphere, "lpart": l_part}[which]() + (3000,)


def overhanging(V: np.ndarray, T: np.ndarray, G: np.ndarray, held) -> np.ndarray:
    """Mask of the held-out points that overhang at 45 deg under the LPD grad G of the tet they lie in."""
    lpd = d._unit(np.einsum("ei,eij->ej", G[T], d.barycentric_gradients(V, T)))
    idx, _ = d.TetLocator(V, T).locate(held.points)
    idx = np.where(idx < 0, d.cKDTree(V[T].mean(axis=1)).query(held.points)[1], idx)
    return (-np.einsum("ij,ij->i", held.normals, lpd[idx]) > math.sin(math.radians(45))) & ~held.on_platform


def main(which: str = "ring", outer: int = 2) -> None:
    """Run S3 with ``outer`` outer iterations and print the residual per iteration."""
    V, T, n_held = load(which)
    T = orient_tets(V, T)
    held = boundary_samples(V, T, n=n_held, seed=7)
    states: list[np.ndarray] = []
    solve = d._asap_solve

    def record(mesh: d.S3Mesh, X: np.ndarray, R: np.ndarray, w: np.ndarray, cfg: S3DeformConfig
               ) -> tuple[np.ndarray, np.ndarray, float]:
        """The ASAP solve, keeping the positions it returns."""
        out = solve(mesh, X, R, w, cfg)
        states.append(out[0].copy())
        return out

    d._asap_solve = record
    cfg = S3DeformConfig(outer_loops=outer).resolve(which, ["sf"])
    res = d.s3_deform(V, T, cfg)
    d._asap_solve = solve
    print(f"{which}: {len(T)} tets, {cfg.outer_loops} x {cfg.inner_loops}, {res.wall_time_s:.0f} s; energy "
          f"{[round(e, 1) for e in res.history['fabrication_sl']]}, critical {res.history['critical']}")
    mesh = d.S3Mesh.build(V, T, cfg.bottom_height_mm)
    area = held.areas[~held.on_platform].sum()
    near = held.points[:, 2] < V[:, 2].min() + 5.0
    for k, X in enumerate(states):
        G = X[:, 2] - X[:, 2].min()
        sat = d._satisfaction(mesh, X, G)
        over = overhanging(V, T, G, held)
        print(f"outer {k + 1}: deformed space {100 * sat['deformed_space_overhang_area_fraction']:.2f} %, realised "
              f"{100 * sat['overhang_area_fraction']:.2f} %, held out {100 * held.areas[over].sum() / area:.2f} % "
              f"({100 * held.areas[over & near].sum() / area:.2f} % within 5 mm of the floor)")
    if which != "ring":
        return
    over = overhanging(V, T, res.G, held)
    c = np.array([(V[:, 0].min() + V[:, 0].max()) / 2, (V[:, 2].min() + V[:, 2].max()) / 2])
    p = held.points[over]
    angle = np.degrees(np.arctan2(p[:, 0] - c[0], p[:, 2] - c[1]))
    print(f"residual: angle from the top {angle.min():.0f}..{angle.max():.0f} deg, normal z median "
          f"{np.median(held.normals[over][:, 2]):.2f}")
    bottom = np.unique(mesh.tets[mesh.bottom])
    phi = heat_geodesic(V, mesh.tets, bottom)
    normals, _ = mesh.face_normals(V)
    tri = V[mesh.tets[mesh.face_tet][np.arange(len(mesh.face_tet))[:, None], d.TET_FACES[mesh.face_local]]]
    top = (normals[:, 2] < -0.9) & (tri.mean(axis=1)[:, 2] > 60)
    x = tri[top].mean(axis=1)[:, 0]
    dist = phi[mesh.tets[mesh.face_tet[top]]].mean(axis=1)
    deformed, _ = mesh.face_normals(res.deformed)
    print(f"bottom band x {V[bottom, 0].min():.1f}..{V[bottom, 0].max():.1f} mm; the growth direction meets itself "
          f"on the inner top at x = {x[np.argmax(dist)]:.1f} mm")
    bins = np.linspace(x.min(), x.max(), 10)
    k = np.digitize(x, bins)
    print("inner top, deformed normal z by x:", ", ".join(f"{x[k == i].mean():.0f} mm: {deformed[top][k == i, 2].mean():.2f}"
                                                         for i in np.unique(k)))


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "ring", int(sys.argv[2]) if len(sys.argv) > 2 else 2)
