"""FEA tasks: the isotropic stress analysis, the stress samples T, and the anisotropic verification of layers."""
from __future__ import annotations

import numpy as np
from prefect import get_run_logger

from neuralslicer.fea import FEAResult, run_fea, stress_samples, verify_layers
from neuralslicer.fea.spec import FEASpec
from neuralslicer.errors import InputError
from storage import ArtifactRef, ArtifactStore
from tasks.common import pipeline_task
from tasks.steps import read_cage, read_field, read_solid


def fea_spec_of(model: ArtifactRef) -> FEASpec:
    """The FEA block of the model's spec (an error naming the spec when it has none)."""
    attrs = ArtifactStore(model.store).attrs(model.path)
    fea = attrs["spec"].get("fea")
    if fea is None:
        raise InputError(attrs["spec"].get("source") or model.model, "the model spec has no 'fea' block (supports and loads)")
    return FEASpec.model_validate(fea)


def read_fea(ref: ArtifactRef) -> FEAResult:
    """The FEA result from the store."""
    return FEAResult.from_arrays(*ArtifactStore(ref.store).read(ref.path))


@pipeline_task("fea")
def fea_task(out: ArtifactRef, store: str, model: ArtifactRef) -> tuple[dict, dict]:
    """Isotropic linear elasticity on the voxels of the solid: stresses, principal directions, tau_max."""
    result = run_fea(read_solid(model), fea_spec_of(model))
    arrays, attrs = result.to_arrays()
    get_run_logger().info("FEA: %d voxels, max von Mises %.3g MPa", len(arrays["centres"]), float(np.max(arrays["von_mises"])))
    return arrays, attrs


@pipeline_task("stress_samples")
def stress_samples_task(out: ArtifactRef, store: str, model: ArtifactRef, fea: ArtifactRef) -> tuple[dict, dict]:
    """T: voxel centres in the top fraction of max principal stress magnitude, with volume and tau_max."""
    samples = stress_samples(read_fea(fea), fea_spec_of(model).top_fraction)
    return samples.to_arrays()


@pipeline_task("verify")
def verify_task(
    out: ArtifactRef, store: str, model: ArtifactRef, fea: ArtifactRef, cage: ArtifactRef, field: ArtifactRef
) -> tuple[dict, dict]:
    """Max strain of the part printed with planar layers and with the computed layers (transversely isotropic)."""
    solid = read_solid(model)
    spec = fea_spec_of(model)
    reference = read_fea(fea)
    f = read_field(read_cage(cage), field)

    def lpd_at(points: np.ndarray) -> np.ndarray:
        """LPD of the computed field (planar where a voxel centre lies outside the cage)."""
        d = f.sample(points)[1]
        bad = ~np.all(np.isfinite(d), axis=1)
        d[bad] = [0.0, 0.0, 1.0]
        return d

    planar = verify_layers(solid, spec, lambda p: np.tile([0.0, 0.0, 1.0], (len(p), 1)), reference=reference)
    curved = verify_layers(solid, spec, lpd_at, reference=reference)
    return {"strain_planar": planar["strain"], "strain": curved["strain"], "centres": curved["centres"]}, {
        "max_strain_planar": planar["max_strain"],
        "max_strain": curved["max_strain"],
        "max_strain_p99_planar": planar["max_strain_p99"],
        "max_strain_p99": curved["max_strain_p99"],
    }
