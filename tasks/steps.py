"""One Prefect task per pipeline step, named after the store group it writes: read inputs, one core call,
return what to store."""
from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from neuralslicer.baselines.s3_config import S3Config, S3DeformConfig
from neuralslicer.cage import Cage, CageConfig, make_cage
from neuralslicer.config import SampleConfig
from neuralslicer.fea.samples import stress_field
from neuralslicer.layers import LayerConfig, slice_layers
from neuralslicer.model.solid import implicit_solid
from neuralslicer.model.spec import ModelSpec
from neuralslicer.field_step import blend_record, height_record, s3_oneshot_record, s3_record
from neuralslicer.motion.profile import MachineProfile
from neuralslicer.neural.config import NeuralConfig
from neuralslicer.samples import surface_samples
from neuralslicer.toolpath.config import ToolpathConfig
from neuralslicer.storage import ArrayStream, ArtifactRef
from neuralslicer.storage.content_cache import ContentCache, cache_root
from neuralslicer.tasks.codec import (encode_motion, read, read_cage, read_fea, read_fea_spec, read_field, read_layers, read_machine_program,
                         read_part_collisions, read_samples, read_solid, read_stress, read_toolpaths, read_user_field)
from neuralslicer.tasks.common import pipeline_task
from neuralslicer.tasks.isolate import large_print
from neuralslicer.tasks.progress import Progress, run_logger, say


@pipeline_task("model", version="1", exclude=("spec",), retries=0)
def model_task(out: ArtifactRef, store: str, name: str, spec: ModelSpec, content: str) -> tuple[dict, dict]:
    """Read every file of the spec and store the solid's components in the build frame."""
    solid = implicit_solid(spec)
    arrays, attrs = solid.to_arrays()
    run_logger().info("model %s: %s, bounds %s", name, solid, np.round(solid.bounds, 3).tolist())
    return arrays, {**attrs, "spec": spec.model_dump(mode="json"), "content_sha256": content}


@pipeline_task("surface", version="1")
def surface_task(out: ArtifactRef, store: str, model: ArtifactRef) -> tuple[dict, dict]:
    """The boundary surface H = 0 of the solid, its genus, volume and bounds."""
    return read_solid(model).surface_record()


@pipeline_task("samples", version="1")
def samples_task(out: ArtifactRef, store: str, model: ArtifactRef, config: SampleConfig) -> tuple[dict, dict]:
    """Surface samples B with normals, area weights, kNN lists and platform flags."""
    samples = surface_samples(read_solid(model), config.n_samples, k=config.k, seed=config.seed)
    run_logger().info("B: %d samples, %d on the platform, residual %.2e", len(samples), samples.on_platform.sum(),
                          samples.residual)
    return samples.to_arrays()


@pipeline_task("cage", version="2")
def cage_task(out: ArtifactRef, store: str, model: ArtifactRef, samples: ArtifactRef, config: CageConfig
              ) -> tuple[dict, dict]:
    """Tetrahedralized offset of the solid at the target element count, containing B and interior points."""
    cache = ContentCache(cache_root())
    hit = cache.load("cage", out.digest)
    if hit is not None and _intact_cage(*hit):
        arrays, attrs = hit
        say(f"cage: the cage of these inputs from the cage cache ({cache.root}), {attrs['n_elements']} tets")
        return arrays, {**{k: v for k, v in attrs.items() if k != "cache_key"}, "from_cage_cache": True}
    cage = make_cage(read_solid(model), read_samples(samples).points, config)
    arrays, attrs = cage.to_arrays()
    attrs.update(cage.summary())
    run_logger().info("cage: %d tets, %d vertices, genus %d", len(cage.tets), len(cage.vertices), attrs["genus"])
    if not cage.seeded:
        run_logger().warning("cage: fTetWild's random draw could not be seeded here (neuralslicer/tetwild_seed.py): "
                                 "another machine builds another cage from these inputs")
    cache.save("cage", out.digest, arrays, attrs)  # the same inputs reuse this cage (unseeded, fTetWild's varies)
    return arrays, attrs


def _intact_cage(arrays: dict, attrs: dict) -> bool:
    """True when a cached cage's content matches the digest recorded with it."""
    try:
        return Cage.from_arrays(arrays, attrs).sha256() == attrs["sha256"]
    except (KeyError, TypeError, ValueError):
        return False


@pipeline_task("field", version="4")
def field_task(out: ArtifactRef, store: str, model: ArtifactRef, cage: ArtifactRef, samples: ArtifactRef,
               stress: ArtifactRef | None, objectives: list[str], config: NeuralConfig,
               user_field: ArtifactRef | None = None, refine_prints: list[ArtifactRef] | None = None,
               warm_start: ArtifactRef | None = None) -> tuple[dict, dict]:
    """The printing field G: the height field without objectives, else the neural optimisation (checkpointed);
    with ``refine_prints``, L_GC's pool refined around those prints' collisions, started from ``warm_start``'s
    weights (the field that printed the last of them); with ``warm_start`` alone, started from its weights (a
    strength round with new stress samples)."""
    c = read_cage(cage)
    if not objectives:
        return height_record(c)
    from neuralslicer.neural.optimise import FieldResult, Refinement   # torch: only when a field is optimised
    from neuralslicer.tasks.optimise import run_optimisation

    weights = FieldResult.weights_of(read(warm_start)[0]) if warm_start is not None else None
    refine = None
    if refine_prints:
        refine = Refinement.of_prints([read_part_collisions(p) for p in refine_prints], weights)
    return run_optimisation(out, c, read_samples(samples), read_stress(stress) if stress is not None else None,
                            objectives, config, read_solid(model), *read_user_field(user_field), refine=refine,
                            warm_start=weights if refine is None else None)


@pipeline_task("field_s3", version="3")
def s3_field_task(out: ArtifactRef, store: str, model: ArtifactRef, cage: ArtifactRef, samples: ArtifactRef,
                  stress: ArtifactRef | None, objectives: list[str], config: S3DeformConfig) -> tuple[dict, dict]:
    """S3-Slicer's field G: its iterative deformation of the model's tet mesh (or the cage), carried to the cage."""
    with Progress("s3", total=config.resolve(model.model, objectives).outer_loops) as bar:
        arrays, attrs = s3_record(read_cage(cage), read_solid(model), read_samples(samples),
                                  read_stress(stress) if stress is not None else None, objectives, config, model.model,
                                  progress=lambda it, info: bar.update(it, total=float(info["fabrication_sl"])))
    run_logger().info("s3 on the %s mesh: %s", attrs.get("on"), attrs.get("satisfaction"))
    return arrays, attrs


@pipeline_task("field_s3_oneshot", version="1")
def s3_oneshot_field_task(out: ArtifactRef, store: str, model: ArtifactRef, cage: ArtifactRef, samples: ArtifactRef,
                          stress: ArtifactRef | None, objectives: list[str], config: S3Config) -> tuple[dict, dict]:
    """The one-shot S3 variant's field G: per-element rotations optimised in the deformed space, one ARAP solve."""
    with Progress("s3", total=config.steps) as bar:
        arrays, attrs = s3_oneshot_record(read_cage(cage), read_solid(model), read_samples(samples),
                                          read_stress(stress) if stress is not None else None, objectives, config,
                                          progress=lambda step, info: bar.update(step, total=float(info["total"])))
    run_logger().info("s3_oneshot: %s", attrs.get("satisfaction"))
    return arrays, attrs


@pipeline_task("field_blend", version="1")
def field_blend_task(out: ArtifactRef, store: str, cage: ArtifactRef, field: ArtifactRef, planar: float
                     ) -> tuple[dict, dict]:
    """The field blended toward planar layers, (1 - planar) G + planar z: the last resort against collisions."""
    run_logger().info("field blended toward planar layers: %.3g", planar)
    return blend_record(read_cage(cage), read(field), planar)


@pipeline_task("layers", version="5")
def layers_task(out: ArtifactRef, store: str, model: ArtifactRef, cage: ArtifactRef, field: ArtifactRef,
                config: LayerConfig) -> tuple[dict, dict]:
    """Isosurfaces of G trimmed by H <= 0, isovalues chosen for the thickness range, in print order."""
    with Progress("layers", total=1) as bar:
        layers = slice_layers(read_solid(model), read_field(read_cage(cage), field), config, progress=bar.update)
    run_logger().info("layers: %d, thickness %s", len(layers.meshes),
                          {k: round(v, 3) for k, v in layers.report.items() if k.startswith("thickness")})
    return layers.to_arrays()


@pipeline_task("toolpaths", version="13")
def toolpaths_task(out: ArtifactRef, store: str, model: ArtifactRef, layers: ArtifactRef, config: ToolpathConfig,
                   machine: MachineProfile, t_max: float, fea: ArtifactRef | None = None) -> tuple[dict, dict]:
    """Toolpaths on every layer (shells, infill, order, bead widths and heights); with ``fea`` the infill can
    follow its stress."""
    from neuralslicer.toolpath.plan import plan_toolpaths   # the planner (scipy): only when the step runs

    stress = stress_field(read_fea(fea), read_fea_spec(model).top_fraction) if fea is not None else None
    tp = plan_toolpaths(read_layers(layers).meshes, platform_z=read_solid(model).platform_z, toolpath_cfg=config,
                        profile=machine, t_max=t_max, stress=stress)
    run_logger().info("toolpaths: %d waypoints, %d paths", len(tp), int(tp.attrs.get("n_paths", 0)))
    return tp.to_arrays()


@pipeline_task("motion", version="1", isolate=large_print("toolpaths", "xyz"))
def motion_task(out: ArtifactRef, store: str, model: ArtifactRef, toolpaths: ArtifactRef, config: ToolpathConfig,
                machine: MachineProfile) -> tuple[dict, dict]:
    """The exact collision check of the head, travel lifts, tilts and reach, and the machine program (IK, extrusion)
    with the print's metrics."""
    from neuralslicer.motion.plan import plan_motion_of

    solid = read_solid(model)
    tp, program, metrics, collisions = plan_motion_of(read_toolpaths(toolpaths), platform_z=solid.platform_z,
                                                      solid_H=solid.H, toolpath_cfg=config, profile=machine,
                                                      consume=True)
    run_logger().info("motion: %d waypoints, %d collisions", metrics["n_waypoints"], metrics["n_collisions"])
    return encode_motion(tp, program, metrics, collisions)


@pipeline_task("program", version="1", isolate=large_print("motion", "toolpaths/xyz"))
def program_task(out: ArtifactRef, store: str, motion: ArtifactRef) -> tuple[dict, dict]:
    """The machine program as G-code in the profile's dialect, streamed into the store a layer at a time."""
    from neuralslicer.gcode.writers import gcode_chunks

    program = read_machine_program(motion)
    logger = run_logger()

    def parts() -> Iterator[np.ndarray]:
        """The G-code's chunks as bytes; logs its size at the end."""
        n = 0
        for chunk in gcode_chunks(program):
            n += len(chunk)
            yield np.frombuffer(chunk, np.uint8)
        logger.info("program: %s G-code, %.1f MB", program.profile.gcode.dialect, n / 1e6)

    return {"gcode": ArrayStream(np.dtype(np.uint8), parts())}, {"dialect": program.profile.gcode.dialect}
