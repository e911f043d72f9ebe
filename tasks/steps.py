"""One Prefect task per pipeline step: read inputs from the store, call the core, return what to store."""
from __future__ import annotations

import hashlib
from typing import Any

import numpy as np
from prefect import get_run_logger

from neuralslicer.cage import Cage, CageConfig, build_cage, interior_points
from neuralslicer.config import SampleConfig
from neuralslicer.layers import LayerConfig, Layers, choose_isovalues, extract_layers
from neuralslicer.model.solid import Solid, implicit_solid
from neuralslicer.motion.pipeline import plan_print
from neuralslicer.motion.planning import MachineProgram
from neuralslicer.motion.profile import MachineProfile
from neuralslicer.model.spec import ModelSpec
from neuralslicer.neural.config import NeuralConfig
from neuralslicer.samples import SurfaceSamples, surface_samples
from neuralslicer.scalar_field import ScalarField
from neuralslicer.tetmesh import tet_volumes
from neuralslicer.toolpath.config import ToolpathConfig
from neuralslicer.toolpath.types import Toolpaths
from neuralslicer.topology import genus, tet_boundary_genus
from neuralslicer.errors import InputError
from storage import ArtifactRef, ArtifactStore, digest
from tasks.common import pipeline_task
from tasks.progress import Progress


def read_solid(ref: ArtifactRef) -> Solid:
    """The implicit solid stored by the model step."""
    return Solid.from_arrays(*ArtifactStore(ref.store).read(ref.path))


def read_samples(ref: ArtifactRef) -> SurfaceSamples:
    """Surface samples B from the store."""
    return SurfaceSamples.from_arrays(*ArtifactStore(ref.store).read(ref.path))


def read_cage(ref: ArtifactRef) -> Cage:
    """The cage from the store."""
    return Cage.from_arrays(*ArtifactStore(ref.store).read(ref.path))


def read_field(cage: Cage, ref: ArtifactRef) -> ScalarField:
    """The printing field G on its cage."""
    arrays, attrs = ArtifactStore(ref.store).read(ref.path, ["G"])
    return ScalarField.from_arrays(cage.vertices, cage.tets, arrays, attrs)


@pipeline_task("model", exclude=("spec",), retries=0)
def load_model(out: ArtifactRef, store: str, name: str, spec: ModelSpec, content: str) -> tuple[dict, dict]:
    """Read every file of the spec and store the solid's components in the build frame."""
    solid = implicit_solid(spec)
    arrays, attrs = solid.to_arrays()
    get_run_logger().info("model %s: %s, bounds %s", name, solid, np.round(solid.bounds, 3).tolist())
    return arrays, {**attrs, "spec": spec.model_dump(mode="json"), "content_sha256": content}


@pipeline_task("solid")
def solid_surface(out: ArtifactRef, store: str, model: ArtifactRef) -> tuple[dict, dict]:
    """The boundary surface H = 0 of the solid, its genus, volume and bounds."""
    solid = read_solid(model)
    surface = solid.surface()
    return {"vertices": np.asarray(surface.vertices), "faces": np.asarray(surface.faces, dtype=np.int64)}, {
        "bounds": solid.bounds,
        "platform_z": solid.platform_z,
        "volume_mm3": solid.volume(),
        "genus": genus(np.asarray(surface.faces)),
        "feature_size": solid.feature_size,
    }


@pipeline_task("samples")
def sample_surface(out: ArtifactRef, store: str, model: ArtifactRef, config: SampleConfig) -> tuple[dict, dict]:
    """Surface samples B with normals, area weights, kNN lists and platform flags."""
    samples = surface_samples(read_solid(model), config.n_samples, k=config.k, seed=config.seed)
    get_run_logger().info("B: %d samples, %d on the platform, residual %.2e", len(samples), samples.on_platform.sum(), samples.residual)
    return samples.to_arrays()


@pipeline_task("cage")
def make_cage(
    out: ArtifactRef, store: str, model: ArtifactRef, samples: ArtifactRef, config: CageConfig
) -> tuple[dict, dict]:
    """Tetrahedralized offset of the solid at the target element count, containing B and interior points."""
    solid = read_solid(model)
    check = np.concatenate([read_samples(samples).points, interior_points(solid.H, solid.bounds, 20_000, config.seed)])
    cage = build_cage(solid.H, solid.bounds, solid.volume(), config, check)
    arrays, attrs = cage.to_arrays()
    attrs["genus"] = tet_boundary_genus(cage.tets)
    attrs["volume_mm3"] = float(tet_volumes(cage.vertices, cage.tets).sum())
    get_run_logger().info("cage: %d tets, %d vertices, genus %d", len(cage.tets), len(cage.vertices), attrs["genus"])
    return arrays, attrs


@pipeline_task("field")
def optimise_field_task(
    out: ArtifactRef,
    store: str,
    model: ArtifactRef,
    cage: ArtifactRef,
    samples: ArtifactRef,
    stress: ArtifactRef | None,
    objectives: list[str],
    config: NeuralConfig,
    user_field: ArtifactRef | None = None,
) -> tuple[dict, dict]:
    """The printing field G: the height field without objectives, else the neural optimisation (checkpointed)."""
    c = read_cage(cage)
    if not objectives:
        field = ScalarField.height(c.vertices, c.tets)
        arrays, attrs = field.to_arrays()
        return arrays, {**attrs, "objectives": [], "steps": 0}
    from tasks.optimise import run_optimisation

    b, _ = ArtifactStore(store).read(samples.path)
    t = ArtifactStore(store).read(stress.path)[0] if stress is not None else None
    user = ArtifactStore(store).read(user_field.path)[0] if user_field is not None else {}
    return run_optimisation(out, c, b, t, objectives, config, read_solid(model), user.get("values"), user.get("points"))


@pipeline_task("field_blend")
def blend_field_task(out: ArtifactRef, store: str, cage: ArtifactRef, field: ArtifactRef, planar: float) -> tuple[dict, dict]:
    """The field blended toward planar layers, (1 - planar) G + planar z: the last resort against collisions."""
    arrays, attrs = ArtifactStore(store).read(field.path)
    c = read_cage(cage)
    blended = ScalarField(c.vertices, c.tets, (1.0 - planar) * np.asarray(arrays["G"], np.float64) + planar * c.vertices[:, 2])
    arrays = {**arrays, "G": blended.G, "lpd": blended.lpd()}
    get_run_logger().info("field blended toward planar layers: %.3g", planar)
    return arrays, {**attrs, "blend_planar": float(planar)}


@pipeline_task("layers")
def make_layers(
    out: ArtifactRef, store: str, model: ArtifactRef, cage: ArtifactRef, field: ArtifactRef, config: LayerConfig
) -> tuple[dict, dict]:
    """Isosurfaces of G trimmed by H <= 0, isovalues chosen for the thickness range, in print order."""
    solid = read_solid(model)
    c = read_cage(cage)
    f = read_field(c, field)
    inside = interior_points(solid.H, solid.bounds, config.thickness_samples, seed=1)
    g, _, gn = f.sample(inside)
    ok = np.isfinite(g)
    isovalues, thickness = choose_isovalues(g[ok], gn[ok], config)
    with Progress("layers", total=len(isovalues)) as bar:
        layers = extract_layers(c.vertices, c.tets, f.G, f.lpd(), solid.H, isovalues, config, progress=bar.update)
    layers.report.update(thickness)
    get_run_logger().info("layers: %d, thickness %s", len(layers.meshes), {k: round(v, 3) for k, v in thickness.items()})
    return layers.to_arrays()


def read_layers(ref: ArtifactRef) -> Layers:
    """Layers from the store."""
    return Layers.from_arrays(*ArtifactStore(ref.store).read(ref.path))


def step_attrs(refs: dict[str, ArtifactRef | None]) -> dict[str, dict[str, Any]]:
    """Attributes of each stored step (wall times, reports)."""
    return {k: ArtifactStore(r.store).attrs(r.path) for k, r in refs.items() if r is not None}


@pipeline_task("toolpaths")
def plan_print_task(
    out: ArtifactRef, store: str, model: ArtifactRef, layers: ArtifactRef, config: ToolpathConfig, machine: MachineProfile
) -> tuple[dict, dict]:
    """Toolpaths on every layer, the machine program (IK, extrusion, collisions) and their metrics."""
    solid = read_solid(model)
    tp, program, metrics, collisions = plan_print(
        read_layers(layers).meshes, platform_z=solid.platform_z, solid_H=solid.H, toolpath_cfg=config, profile=machine
    )
    tp_arrays, tp_attrs = tp.to_arrays()
    prog_arrays, prog_attrs = program.to_arrays()
    arrays = {**{f"toolpaths/{k}": v for k, v in tp_arrays.items()}, **{f"program/{k}": v for k, v in prog_arrays.items()},
              "collisions/indices": collisions.indices, "collisions/kind": collisions.kind}
    get_run_logger().info("toolpaths: %d waypoints, %d collisions", metrics["n_waypoints"], metrics.get("collisions", 0))
    return arrays, {"toolpaths": tp_attrs, "program": prog_attrs, "metrics": metrics}


def read_print(ref: ArtifactRef) -> tuple[Toolpaths, MachineProgram, dict]:
    """Toolpaths, machine program and print metrics from the store."""
    arrays, attrs = ArtifactStore(ref.store).read(ref.path)
    part = {p: {k.split("/", 1)[1]: v for k, v in arrays.items() if k.startswith(p + "/")} for p in ("toolpaths", "program")}
    return (
        Toolpaths.from_arrays(part["toolpaths"], attrs["toolpaths"]),
        MachineProgram.from_arrays(part["program"], attrs["program"]),
        attrs["metrics"],
    )


def read_collision_map(ref: ArtifactRef) -> tuple[np.ndarray, np.ndarray]:
    """Waypoints (n,3) of a stored print and which of them collide (n,) bool."""
    arrays, _ = ArtifactStore(ref.store).read(ref.path, ["toolpaths/xyz", "collisions/indices"])
    hit = np.zeros(len(arrays["toolpaths/xyz"]), bool)
    hit[np.asarray(arrays["collisions/indices"], np.int64)] = True
    return arrays["toolpaths/xyz"], hit


def store_user_field(store: str, model: str, path: str) -> ArtifactRef:
    """Put a user field file (.npz: points (p,3) in the build frame, values (p,)) in the store, keyed by content."""
    try:
        with np.load(path) as data:
            points = np.asarray(data["points"], dtype=np.float64)
            values = np.asarray(data["values"], dtype=np.float64).ravel()
    except (OSError, KeyError, ValueError) as exc:
        raise InputError(path, f"a user field is an .npz with 'points' (p,3) and 'values' (p,): {exc}") from None
    if points.ndim != 2 or points.shape[1] != 3 or len(points) != len(values) or not np.isfinite(values).all():
        raise InputError(path, f"points {points.shape} and values {values.shape} do not match (p,3) and (p,)")
    key = digest("user_field", hashlib.sha256(points.tobytes() + values.tobytes()).hexdigest())
    ref = ArtifactStore(store).ref(f"{model}/user_field/{key}", key)
    ArtifactStore(store).write_once(ref.path, lambda: ({"points": points, "values": values}, {"source": str(path)}))
    return ref
