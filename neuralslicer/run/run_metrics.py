"""The headline figures of a run, typed: one schema of ``metrics.json``'s keys that the report's summary, the study
tables and ``neuralslicer compare`` read, each figure with its key, label and meaning (docs/outputs.md lists them)."""
from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from neuralslicer.fileio import to_json


def _figure(key: str, label: str, description: str) -> Any:  # noqa: ANN401 - a pydantic Field
    """A figure of the schema: its metrics.json key (the alias), its table label and what it means."""
    return Field(None, alias=key, description=description, json_schema_extra={"label": label})


class RunMetrics(BaseModel):
    """The figures a user looks at first, read from a run's metrics (None where the run has no such figure)."""

    model_config = ConfigDict(populate_by_name=True, extra="ignore", frozen=True)

    n_layers: int | None = _figure("n_layers", "layers", "printing layers of the kept print")
    estimated_print_time_s: float | None = _figure(
        "estimated_print_time_s", "estimated print time", "the machine program's duration at its feeds (s)")
    material_mm3: float | None = _figure("material_mm3", "material", "volume of the extruded beads (mm³)")
    n_collisions: int | None = _figure(
        "n_collisions", "collisions", "waypoints of the printed program where the head or nozzle hits earlier "
        "layers or the platform")
    overhang: float | None = _figure(
        "sf.overhang_area_fraction", "overhang", "area fraction of the surface samples B overhanging by more than "
        "alpha, with the field's printing directions")
    overhang_planar: float | None = _figure(
        "sf.overhang_area_fraction_planar", "overhang planar", "the same with planar layers")
    overhang_held_out: float | None = _figure(
        "sf.heldout.overhang_area_fraction", "overhang held out", "the overhang fraction on held-out surface "
        "samples the optimisation never saw, with the field's printing directions")
    overhang_layers: float | None = _figure(
        "sf.heldout.overhang_area_fraction_layers", "overhang of the layers", "the overhang fraction on held-out "
        "samples with the exported layers' own normals: what prints")
    overhang_layers_planar: float | None = _figure(
        "sf.heldout.overhang_area_fraction_planar", "overhang held out, planar", "the held-out samples' overhang "
        "fraction with planar layers")
    sr_satisfied: float | None = _figure(
        "sr.satisfied_fraction", "SR satisfied", "volume fraction of the stress samples T whose tau_max lies in "
        "the layer, within beta")
    max_strain: float | None = _figure(
        "fea.max_strain", "max strain", "maximum principal strain of the part as printed (anisotropic FEA of its "
        "filaments, --verify)")
    strain_p99: float | None = _figure(
        "fea.max_strain_p99", "strain p99", "99th percentile of the printed part's maximum principal strain")
    max_strain_planar_zigzag: float | None = _figure(
        "fea.planar_zigzag.max_strain", "max strain, planar + zig-zag", "the same for planar layers with zig-zag "
        "infill: the reference a print is judged against")
    aligned_fraction: float | None = _figure(
        "fea.aligned_fraction", "filaments along tau_max", "length fraction of the filaments in the most stressed "
        "voxels that run along tau_max (projected into the layer), within a band of angles")
    field_steps: int | None = _figure("field.steps", "steps", "optimisation steps of the kept field")
    field_stop: str | None = _figure(
        "field.stop", "stop", "why the optimisation stopped: constraints (met), loss (converged or at its target), "
        "progress (the overhang stalled) or budget (its step budget; empty for a field that was not optimised)")

    @classmethod
    def of(cls, metrics: dict[str, Any]) -> RunMetrics:
        """The figures of a metrics mapping, as metrics.json holds it or as the export makes it (numpy scalars too;
        figures it lacks are None)."""
        return cls.model_validate(to_json({k: v for k, v in metrics.items() if k in KEYS.values()}))

    @classmethod
    def label(cls, name: str) -> str:
        """The table label of a figure."""
        return cls.model_fields[name].json_schema_extra["label"]

    def present(self) -> dict[str, Any]:
        """The figures this run has, by name, in the schema's order."""
        return {k: v for k, v in self if v is not None}


#: figure name -> metrics.json key
KEYS: dict[str, str] = {name: f.alias for name, f in RunMetrics.model_fields.items()}
