"""The slicing configuration: one typed model per step, loaded from YAML and overridden by CLI options."""
from __future__ import annotations

from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, Field, ValidationError, model_validator

from neuralslicer.baselines.s3_config import S3Config, S3DeformConfig
from neuralslicer.cage import CageConfig
from neuralslicer.errors import InputError, validation_error_line
from neuralslicer.layers import LayerConfig
from neuralslicer.model.spec import ModelSpec
from neuralslicer.motion.profile import load_profile
from neuralslicer.neural.config import NeuralConfig
from neuralslicer.toolpath.config import ToolpathConfig

Objective = Literal["sf", "sr", "po", "gc", "ca"]


class SampleConfig(BaseModel):
    """Surface samples B."""

    model_config = {"extra": "forbid"}

    n_samples: int = Field(20_000, ge=100, description="number of surface samples B")
    k: int = Field(10, ge=2, description="nearest neighbours for area weights and the PO loss")
    seed: int = Field(0, description="sampling seed")


class SliceConfig(BaseModel):
    """Everything `neuralslicer slice` needs besides the model."""

    model_config = {"extra": "forbid"}

    method: Literal["neural", "s3", "s3_oneshot"] = Field(
        "neural", description="how the printing field is computed: the Neural Slicer (neural), the S3-Slicer "
        "baseline (s3: its iterative deformation as DeformTet.cpp runs it) or the one-shot variant (s3_oneshot: "
        "per-element rotations optimised in the deformed space, one ARAP solve of the cage)")
    objectives: list[Objective] | None = Field(
        None, description="default: sf, po, gc (global head collision) and ca (local collision constraint), "
        "+ sr when the spec has loads")
    samples: SampleConfig = Field(default_factory=SampleConfig)
    cage: CageConfig = Field(default_factory=CageConfig)
    neural: NeuralConfig = Field(default_factory=NeuralConfig)
    s3: S3DeformConfig = Field(default_factory=S3DeformConfig, description="the S3-Slicer baseline (method: s3)")
    s3_oneshot: S3Config = Field(default_factory=S3Config, description="the one-shot S3 variant (method: s3_oneshot)")
    layers: LayerConfig = Field(default_factory=LayerConfig)
    alpha_deg: float = Field(45.0, gt=0, lt=90, description="self-supporting angle for the SF metrics")
    toolpath: ToolpathConfig = Field(default_factory=ToolpathConfig)
    machine: str = Field("table_bc_linuxcnc", description="machine profile: a shipped name or a YAML file")
    robot: bool = Field(False, description="also write robot_waypoints.csv/.json (position, tool quaternion, extrusion) "
                        "and compas_slicer's printpoints.json")
    collision_refinements: int = Field(
        3, ge=0, le=8, description="while the print's exact check finds the head hitting the part or the platform "
        "(with the gc objective): refine L_GC's pool there and re-optimise from the field that printed it, at most "
        "this many times (each round adds the new hits to the earlier ones)")
    collision_retries: int = Field(2, ge=0, le=5, description="then re-optimise with smoother fields while the nozzle "
                                   "collides (the paper's answer)")
    collision_smoothness_factor: float = Field(100.0, gt=1, description="harmonic weights multiplied per retry")
    collision_fallback: Literal["blend", "none"] = Field(
        "blend", description="still colliding after the retries: blend the field toward planar layers "
        "((1-t) G + t z, the smallest t found by bisection that is collision-free; t = 1 is planar) or keep it")
    collision_blend_steps: int = Field(
        5, ge=1, le=8, description="bisection steps of the planar blend (t to within 2^-steps)")
    keep_attempts: bool = Field(
        False, description="keep every print of the collision resolution whole in the store; by default a print that "
        "will not be kept drops its toolpaths' and motion's per-waypoint arrays as soon as a later one replaces it "
        "(its metrics, collisions and collision map stay for the report)")
    verify: bool = Field(False, description="anisotropic FEA of the printed part beside planar layers with zig-zag and "
                         "with stress-following infill (needs the spec's fea block)")
    sr_rounds: int = Field(
        1, ge=1, le=5, description="with sr: after the print, re-run the FEA with its material (filaments along its "
        "toolpaths), re-sample T and tau_max from it and re-optimise from the current field, until this many rounds; "
        "1 is the paper (tau_max from the isotropic FEA only)")
    verify_tangents: Literal["printed", "ideal"] = Field(
        "printed", description="stiff material axis of the computed layers in --verify: the printed toolpaths' "
        "direction, or the ideal one (tau_max projected onto the layer, a best case)")

    @model_validator(mode="before")
    @classmethod
    def _nozzle_defaults(cls, data: object) -> object:
        """The layer thickness and line width the configuration leaves out: those of the machine profile's nozzle
        (``nozzle.layer_height_mm``, ``layer_thickness_mm``, ``line_width_mm``)."""
        if not isinstance(data, dict):
            return data
        try:
            nozzle = load_profile(data.get("machine") or cls.model_fields["machine"].default).nozzle
        except InputError:      # the preflight names the machine option and the profile's problem
            return data
        t_lo, t_hi = nozzle.layer_thickness_mm
        filled = dict(data)
        for section, values in (("layers", {"layer_height": nozzle.layer_height_mm, "t_min": t_lo, "t_max": t_hi}),
                                ("toolpath", {"line_width": nozzle.line_width_mm})):
            given = data.get(section)
            if isinstance(given, BaseModel):
                given = {k: getattr(given, k) for k in given.model_fields_set}
            if given is None or isinstance(given, dict):
                filled[section] = {**values, **(given or {})}
        return filled

    def objectives_for(self, spec: ModelSpec) -> list[str]:
        """The objectives asked for, or the default: sf, po, gc with the ca constraint, plus sr when the
        spec has an FEA load case."""
        if self.objectives is not None:
            return list(self.objectives)
        return ["sf", "po", "gc", "ca"] + (["sr"] if spec.fea is not None else [])

    def toolpath_for(self, spec: ModelSpec) -> ToolpathConfig:
        """The toolpath settings of this slice, ``infill: auto`` decided: stress-following when the spec has a load
        case and ``sr`` is among the objectives, else zig-zag."""
        return self.toolpath.resolved(spec.fea is not None and "sr" in self.objectives_for(spec))

    def needs_fea(self, spec: ModelSpec) -> bool:
        """Whether this slice runs the spec's FEA: for the sr objective, for --verify or for stress-following infill."""
        return self.verify or "sr" in self.objectives_for(spec) or self.toolpath_for(spec).infill == "stress"

    @classmethod
    def from_yaml(cls, path: str | Path) -> SliceConfig:
        """Load a configuration file; errors name the file and the key."""
        return cls.checked(cls.read_yaml(path), str(path))

    @staticmethod
    def read_yaml(path: str | Path) -> dict:
        """A configuration file's mapping of sections, not validated yet (to add options to before validation)."""
        path = Path(path)
        if not path.is_file():
            raise InputError(path, "no such configuration file")
        try:
            data = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as exc:
            raise InputError(path, f"not valid YAML: {exc}") from None
        if not isinstance(data, dict):
            raise InputError(path, "a configuration file must be a mapping of sections")
        return data

    @classmethod
    def checked(cls, data: dict, where: str) -> SliceConfig:
        """Validate a configuration mapping; an error names `where` and the offending key."""
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            key, msg = validation_error_line(cls, exc.errors())
            raise InputError(f"{where}: {key}", msg) from None
