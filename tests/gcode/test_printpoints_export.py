"""compas_slicer printpoints export: the nested JSON compas_slicer writes, field by field, and its geometry.

The format is compas_slicer's (not installed here, so written out below from its source):
``utils.save_to_json(print_organizer.output_nested_printpoints_dict(), ...)`` writes
``{"layer_i": {"path_j": {"k": PrintPoint.to_data()}}}``, numbers contiguous from 0 (its Grasshopper loader walks
``range(len(...))``); ``to_data`` gives ``point`` [x, y, z] (``pt`` in 0.7), vectors as [x, y, z], ``frame`` as
compas' ``Frame.__data__`` ``{"point", "xaxis", "yaxis"}``, a non-zero ``layer_height`` (``PrintPoint`` refuses 0).
"""
from __future__ import annotations

import dataclasses
import itertools
import json
import numbers

import numpy as np
import pytest

from neuralslicer.gcode import parse_gcode, printpoint_layers
from neuralslicer.motion import PRINT, forward_kinematics, load_profile, plan_print
from neuralslicer.run.outputs import write_print_outputs
from neuralslicer.toolpath.synthetic import cap_stack

#: PrintPoint.to_data() of compas_slicer (src/compas_slicer/geometry/print_point.py)
PRINTPOINT_KEYS = {"point", "layer_height", "mesh_normal", "up_vector", "frame", "extruder_toggle", "velocity",
                   "wait_time", "blend_radius", "closest_support_pt", "distance_to_support", "is_feasible", "attributes"}
#: compas.geometry.Frame.__data__
FRAME_KEYS = {"point", "xaxis", "yaxis"}


@pytest.fixture(scope="module")
def printed(tmp_path_factory):
    """A tiny curved print (three caps, rotary motion, lifted travels) and its output folder with --robot."""
    layers = cap_stack(3, r0=8.0, theta_max_deg=40.0, center=(3.0, -2.0, 0.0), subdivisions=4)
    profile = load_profile("table_bc_linuxcnc").model_copy(deep=True)
    profile.kinematics.pivot = (5.0, -7.0, 60.0)
    tp, prog, metrics, _ = plan_print(layers, platform_z=0.0, profile=profile)
    out = tmp_path_factory.mktemp("printpoints")
    files = write_print_outputs(out, tp, prog, metrics, robot=True, vtp=False, png=False)
    return tp, prog, files


def _is_vec3(v) -> bool:
    return isinstance(v, list) and len(v) == 3 and all(isinstance(x, float) for x in v)


def _is_number(v) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, bool)


def _flat(data: dict) -> list[tuple[int, int, dict]]:
    """(layer, path, printpoint) in file order, walked as compas_slicer's Grasshopper loader walks it."""
    out = []
    for i in range(len(data)):
        layer = data[f"layer_{i}"]
        for j in range(len(layer)):
            path = layer[f"path_{j}"]
            assert len(path) > 0
            out += [(i, j, path[str(k)]) for k in range(len(path))]
    return out


def test_printpoints_file_has_compas_slicers_nesting_and_fields(printed):
    tp, _, files = printed
    path = files["printpoints"]
    assert path.name == "printpoints.json"
    data = json.loads(path.read_text())
    # nesting: layer_i > path_j > "k", every number contiguous from 0, nothing else
    assert list(data) == [f"layer_{i}" for i in range(len(data))]
    for layer in data.values():
        assert list(layer) == [f"path_{j}" for j in range(len(layer))]
        for pts in layer.values():
            assert list(pts) == [str(k) for k in range(len(pts))]
    flat = _flat(data)
    assert len(flat) == len(tp) and len(data) == len(np.unique(tp.layer))
    for _, _, pp in flat:
        assert PRINTPOINT_KEYS <= set(pp) and set(pp) - PRINTPOINT_KEYS == {"pt"}
        assert _is_vec3(pp["point"]) and pp["pt"] == pp["point"]
        assert _is_vec3(pp["up_vector"]) and _is_vec3(pp["mesh_normal"])
        assert isinstance(pp["frame"], dict) and set(pp["frame"]) == FRAME_KEYS
        assert all(_is_vec3(pp["frame"][k]) for k in FRAME_KEYS) and pp["frame"]["point"] == pp["point"]
        assert isinstance(pp["extruder_toggle"], bool) and isinstance(pp["is_feasible"], bool)
        for key in ("velocity", "wait_time", "blend_radius", "layer_height"):
            assert _is_number(pp[key]) and pp[key] >= 0
        assert pp["layer_height"] > 0 and pp["velocity"] > 0
        assert _is_vec3(pp["closest_support_pt"])      # compas_slicer 0.7 reads it with Point.from_data
        assert pp["distance_to_support"] is None or _is_number(pp["distance_to_support"])
        assert isinstance(pp["attributes"], dict)
    assert json.loads(json.dumps(data)) == data


def test_printpoints_match_the_waypoints_and_the_gcode(printed):
    tp, prog, files = printed
    flat = _flat(json.loads(files["printpoints"].read_text()))
    col = lambda key: np.array([pp[key] for _, _, pp in flat], np.float64)  # noqa: E731
    point, up, normal = col("point"), col("up_vector"), col("mesh_normal")
    x = np.array([pp["frame"]["xaxis"] for _, _, pp in flat])
    y = np.array([pp["frame"]["yaxis"] for _, _, pp in flat])
    # the waypoints, in print order; the tool axis (printing direction) as the up vector, unit length
    assert np.abs(point - tp.xyz).max() <= 1e-6
    assert np.abs(np.linalg.norm(up, axis=1) - 1.0).max() < 1e-8
    assert np.abs(up - tp.axis / np.linalg.norm(tp.axis, axis=1, keepdims=True)).max() < 1e-8
    # the frame: orthonormal, x and y across the tool axis, z = x cross y into the material (compas_slicer's
    # frame of a planar print points down); compas_slicer's get_frame(up, mesh_normal) gives the same frame
    for v in (x, y):
        assert np.abs(np.linalg.norm(v, axis=1) - 1.0).max() < 1e-8 and np.abs(np.einsum("ij,ij->i", v, up)).max() < 1e-8
    assert np.abs(np.einsum("ij,ij->i", x, y)).max() < 1e-8
    assert np.abs(np.cross(x, y) + up).max() < 1e-7
    assert np.abs(np.cross(up, normal) - x).max() < 1e-7 and np.array_equal(normal, y)
    # layer height: the local thickness; the support point down the tool axis by it
    on = (tp.path >= 0) & (tp.thickness > 0)
    assert np.allclose(col("layer_height")[on], tp.thickness[on], atol=1e-6)
    support = np.array([pp["closest_support_pt"] for (_, _, pp), o in zip(flat, on) if o])
    dist = np.array([pp["distance_to_support"] for (_, _, pp), o in zip(flat, on) if o])
    assert np.allclose(support, point[on] - dist[:, None] * up[on], atol=1e-5) and np.allclose(dist, tp.thickness[on])
    # no material below (lifted travels): the point itself, distance null
    assert not on.all() and all(pp["closest_support_pt"] == pp["point"] and pp["distance_to_support"] is None
                                for (_, _, pp), o in zip(flat, on) if not o)
    # the extruder is on for the move leaving a point: exactly the moves that deposit; the last point is off
    toggle = np.array([pp["extruder_toggle"] for _, _, pp in flat])
    assert np.array_equal(toggle[:-1], tp.extrude[1:]) and not toggle[-1]
    # the G-code: forward kinematics of the parsed program at each waypoint's move gives the point and the up vector
    lx, ly, lz, lb, lc, le = prog.axis_letters
    moves = parse_gcode(files["gcode"], axes=lx + ly + lz + lb + lc + le)
    xyz = np.column_stack([moves.axes[lx], moves.axes[ly], moves.axes[lz]])
    p, a = forward_kinematics(xyz, moves.axes[lb], moves.axes[lc], prog.profile.kinematics, prog.part_offset)
    w = prog.source >= 0
    assert np.abs(p[w] - point[prog.source[w]]).max() < 1e-3
    assert np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", a[w], up[prog.source[w]]), -1, 1))).max() < 0.1
    filament = sum(pp["attributes"]["filament_mm"] for _, _, pp in flat)
    assert filament == pytest.approx(np.diff(moves.axes[le])[prog.kind[1:] == PRINT].sum(), rel=1e-3)
    # speeds of the profile (mm/s) on the moves arriving
    f = prog.profile.feeds
    v = col("velocity")
    assert set(np.unique(v)) <= {f.first_layer_mm_s, f.print_mm_s, f.travel_mm_s}
    assert np.all(v[~tp.extrude] == f.travel_mm_s)


def test_printpoints_group_our_paths_as_compas_slicer_does(printed):
    """A compas_slicer path is one of our paths with the lifted travel points after it (its safety points); a layer,
    one of our layers."""
    tp, _, files = printed
    assert (tp.path < 0).any()                       # the print has lifted travels to place
    flat = _flat(json.loads(files["printpoints"].read_text()))
    attrs = [pp["attributes"] for _, _, pp in flat]
    assert [a["index"] for a in attrs] == list(range(len(tp)))
    groups: dict[tuple[int, int], list[dict]] = {}
    for (i, j, _), a in zip(flat, attrs):
        groups.setdefault((i, j), []).append(a)
    assert len(groups) == len({a["path"] for a in attrs if a["path"] >= 0})
    layers: dict[int, set[int]] = {}
    for (i, j), g in groups.items():
        paths = [a["path"] for a in g]
        first = next(k for k, p in enumerate(paths) if p >= 0)
        assert first == 0 or (i, j) == (0, 0)                 # travels before the first path: in the first path
        run = len(list(itertools.takewhile(lambda p: p >= 0, paths[first:])))
        assert len(set(paths[first:first + run])) == 1          # one of our paths ...
        assert all(p < 0 for p in paths[first + run:])          # ... then the travels after it
        layers.setdefault(i, set()).update(a["layer"] for a in g if a["path"] >= 0)
    assert all(len(v) == 1 for v in layers.values()) and len({min(v) for v in layers.values()}) == len(layers)


def test_colliding_waypoints_are_not_feasible(printed):
    tp, prog, _ = printed
    hit = dataclasses.replace(tp, attrs={**tp.attrs, "collision_waypoints": [3, 17]})
    feasible = [pp["is_feasible"] for _, doc in printpoint_layers(hit, prog.profile) for pts in doc.values()
                for pp in pts.values()]
    assert [i for i, ok in enumerate(feasible) if not ok] == [3, 17]


#: compas_slicer 0.7.0's requirements (its METADATA) but pyclipper: its pin <1.3 has no wheel for Python >= 3.11
#: and its sdist no longer builds there (longintrepr.h moved); PrintPoint never uses it, the package imports it
COMPAS_SLICER_070_DEPS = ["attrs>=19.2.0", "compas>=1.16.0,<2.0.0", "networkx>=2.5,<3.2", "numpy<=1.23.2",
                          "progressbar2>=3.53,<4.4", "rdp==0.8", "libigl>=2.4.1,<2.5.0", "pyclipper"]

#: run in the compas_slicer 0.7.0 venv: every printpoint of a file through PrintPoint.from_data, in file order
LOAD_WITH_COMPAS_SLICER = """
import json, sys
import compas_slicer
from compas_slicer.geometry import PrintPoint
data = json.load(open(sys.argv[1]))
points, failed = [], []
for i in range(len(data)):
    layer = data["layer_%d" % i]
    for j in range(len(layer)):
        path = layer["path_%d" % j]
        for k in range(len(path)):
            try:
                pp = PrintPoint.from_data(path[str(k)])
            except Exception as exc:
                failed.append("layer_%d/path_%d/%d: %s: %s" % (i, j, k, type(exc).__name__, exc))
                continue
            points.append(list(pp.pt) + list(pp.closest_support_pt) + [pp.layer_height])
print(json.dumps({"version": compas_slicer.__version__, "points": points, "failed": failed[:5],
                  "n_failed": len(failed)}))
"""


@pytest.mark.slow
def test_every_printpoint_loads_with_compas_slicer_0_7_0(printed, tmp_path):
    """The released compas_slicer 0.7.0, in a throwaway venv, loads every point of the file (it reads
    ``closest_support_pt`` with ``Point.from_data`` unconditionally: a null raised a TypeError there)."""
    import subprocess
    import sys

    tp, _, files = printed
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, capture_output=True)
    pip = [str(venv / "bin" / "python"), "-m", "pip", "install", "--quiet", "--disable-pip-version-check"]
    for args in (["--no-deps", "compas_slicer==0.7.0"], COMPAS_SLICER_070_DEPS):
        done = subprocess.run(pip + args, capture_output=True, text=True, timeout=900)
        if done.returncode != 0:
            pytest.skip(f"pip cannot install compas_slicer 0.7.0 here: {(done.stderr or done.stdout).strip()[-300:]}")
    script = tmp_path / "load.py"
    script.write_text(LOAD_WITH_COMPAS_SLICER)
    done = subprocess.run([str(venv / "bin" / "python"), str(script), str(files["printpoints"])],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    result = json.loads(done.stdout)
    assert result["version"] == "0.7.0"
    assert result["n_failed"] == 0, result["failed"]
    loaded = np.array(result["points"])
    # every waypoint, in print order, where it is; supports on the layer below, travels their own support
    assert len(loaded) == len(tp) and np.abs(loaded[:, :3] - tp.xyz).max() <= 1e-6
    on = (tp.path >= 0) & (tp.thickness > 0)
    assert not on.all() and np.abs(loaded[~on, 3:6] - tp.xyz[~on]).max() <= 1e-6
    assert np.allclose(np.linalg.norm(loaded[on, :3] - loaded[on, 3:6], axis=1), tp.thickness[on], atol=1e-5)
    assert (loaded[:, 6] > 0).all()
