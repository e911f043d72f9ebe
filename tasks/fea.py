"""FEA tasks: the isotropic stress analysis, the stress samples T, and the anisotropic verification of layers."""
from __future__ import annotations

import numpy as np
from prefect import get_run_logger

from neuralslicer.layers import LayerConfig
from neuralslicer.toolpath.config import ToolpathConfig
from neuralslicer.storage import ArtifactRef
from neuralslicer.tasks.codec import read_cage, read_fea, read_fea_spec, read_field, read_motion, read_solid
from neuralslicer.tasks.common import pipeline_task


@pipeline_task("fea", version="1")
def fea_task(out: ArtifactRef, store: str, model: ArtifactRef) -> tuple[dict, dict]:
    """Isotropic linear elasticity on the voxels of the solid: stresses, principal directions, tau_max."""
    from neuralslicer.fea import run_fea   # the solver (scipy.sparse): only when the step runs, not on a cached rerun

    arrays, attrs = run_fea(read_solid(model), read_fea_spec(model)).to_arrays()
    get_run_logger().info("FEA: %d voxels, max von Mises %.3g MPa", len(arrays["centres"]), float(np.max(arrays["von_mises"])))
    return arrays, attrs


@pipeline_task("stress_samples", version="1")
def stress_samples_task(out: ArtifactRef, store: str, model: ArtifactRef, fea: ArtifactRef) -> tuple[dict, dict]:
    """T: voxel centres in the top fraction of max principal stress magnitude, with volume and tau_max."""
    from neuralslicer.fea import stress_samples

    return stress_samples(read_fea(fea), read_fea_spec(model).top_fraction).to_arrays()


@pipeline_task("verify", version="3")
def verify_task(out: ArtifactRef, store: str, model: ArtifactRef, fea: ArtifactRef, cage: ArtifactRef,
                field: ArtifactRef, motion: ArtifactRef | None = None, layer_config: LayerConfig | None = None,
                toolpath_config: ToolpathConfig | None = None) -> tuple[dict, dict]:
    """Max strain of the part printed with planar layers and with the computed layers (transversely isotropic).
    With ``motion`` (a print) the filaments lie along the printed toolpaths: the computed layers' own, and toolpaths of
    planar layers made here with the same settings; without, along the ideal direction for both."""
    from neuralslicer.verify import verify_field, verify_print

    solid, computed = read_solid(model), read_field(read_cage(cage), field)
    if motion is None:
        return verify_field(solid, read_fea_spec(model), computed, read_fea(fea))
    return verify_print(solid, read_fea_spec(model), computed, read_motion(motion)[0], layer_config, toolpath_config,
                        read_fea(fea))


@pipeline_task("fea_printed", version="1")
def printed_fea_task(out: ArtifactRef, store: str, model: ArtifactRef, fea: ArtifactRef, cage: ArtifactRef,
                     field: ArtifactRef, motion: ArtifactRef) -> tuple[dict, dict]:
    """The FEA of the printed part (transversely isotropic, filaments along the printed toolpaths, layers of the
    field): stored like the isotropic FEA (a strength round samples its T from it), with the print's strain and how
    far tau_max turned."""
    from neuralslicer.verify import printed_fea_record

    arrays, attrs = printed_fea_record(read_solid(model), read_fea_spec(model), read_field(read_cage(cage), field),
                                       read_motion(motion)[0], read_fea(fea))
    get_run_logger().info("printed part: max strain %.4g, tau_max turned %.1f° (median) by the printed material",
                          attrs["max_strain"], attrs["tau_turn_median_deg"])
    return arrays, attrs
