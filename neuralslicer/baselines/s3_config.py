"""Settings of the S3-Slicer baseline (no torch: the CLI reads them before any computation starts)."""
from __future__ import annotations

from typing import Iterable, Literal

from pydantic import BaseModel, ConfigDict, Field

from neuralslicer.neural.config import DeformationConfig, LossConfig, NeuralConfig


class S3Config(BaseModel):
    """Weights, budget and stop test of the S3 baseline; the deformation is the neural method's."""

    model_config = ConfigDict(extra="forbid")

    w_sf: float = Field(1.0, ge=0, description="support-free weight (rotated normals vs +z)")
    w_sr: float = Field(1.0, ge=0, description="strength weight (rotated tau_max vs the horizontal plane)")
    w_smooth: float = Field(
        0.1, ge=0, description="weight of the harmonic smoothness L_H of the rotation field (unit-free)")
    alpha_deg: float = Field(45.0, gt=0, lt=90, description="self-supporting angle alpha")
    beta_deg: float = Field(10.0, gt=0, lt=90, description="strength tolerance beta")
    k_sf: float = Field(
        10.0, gt=0, description="logistic growth rate of L_SF (below the neural default 30: per-element rotations "
        "have no network coupling, and a saturated logistic leaves a flat overhang stuck at the identity)")
    k_sr: float = Field(15.0, gt=0, description="logistic growth rate of L_SR")
    steps: int = Field(2000, ge=0, description="step budget (Adam on the per-element quaternions)")
    lr: float = Field(1e-2, gt=0, description="Adam learning rate (quaternion components per step)")
    tol: float = Field(
        1e-4, ge=0, description="converged when the best loss improved by less than this fraction over `window` steps")
    window: int = Field(100, ge=2, description="steps compared by the stop test")
    jitter: float = Field(
        1e-3, ge=0, description="tilt (rad) of the starting rotations about a seeded random horizontal axis when "
        "steps > 0: a face pointing straight down is a saddle of L_SF at the identity (zero gradient), as on a flat "
        "overhang")
    seed: int = Field(0, description="seed of the starting tilt's axis")
    deformation: DeformationConfig = Field(
        default_factory=DeformationConfig, description="ARAP deformation that realises the rotations (s = 1)")
    device: str = Field("auto", description="'auto' (CUDA if available), 'cpu', 'cuda', 'cuda:1'")
    dtype: Literal["float32", "float64"] = Field("float64", description="precision of the rotation optimisation")

    def for_objectives(self, objectives: Iterable[str]) -> "S3Config":
        """This config with the weights of the objectives not asked for (sf, sr) set to zero."""
        objectives = set(objectives)
        return self.model_copy(update={"w_sf": self.w_sf if "sf" in objectives else 0.0,
                                       "w_sr": self.w_sr if "sr" in objectives else 0.0})

    def neural_config(self) -> NeuralConfig:
        """The NeuralConfig whose FieldProblem maps B and T to the cage and judges the field (no NS terms)."""
        loss = LossConfig(w_sf=self.w_sf, w_sr=self.w_sr, w_po=0.0, w_hs=0.0, w_hq=0.0, alpha_deg=self.alpha_deg,
                          beta_deg=self.beta_deg, k_sf=self.k_sf, k_sr=self.k_sr, collision=False)
        return NeuralConfig(loss=loss, deformation=self.deformation, device=self.device, dtype=self.dtype)


#: rows of S3-Slicer's ``MainWindow::_updateFrameworkParameter`` (zhangty019/S3_DeformFDM, ShapeLab/MainWindow.cpp):
#: model name -> (line, outer loops, inner loops, critical SL, critical SR, neighbour scale, regular scale, smooth,
#: support-free angle). The surface-quality weights (SQC, SQV) and the SR region ratios of those rows are not used here.
S3_PRESETS: dict[str, tuple[int, int, int, float, float, float, float, float, float]] = {
    "ring": (733, 2, 7, 15.0, 0.0, 5.0, 1.0, 40.0, 30.0),
    "tube": (737, 1, 7, 15.0, 0.0, 3.0, 1.0, 40.0, 30.0),
    "bunny": (735, 1, 7, 15.0, 0.0, 3.0, 1.0, 40.0, 30.0),
    "topopt_new4": (806, 1, 7, 15.0, 8.0, 3.0, 1.0, 50.0, 30.0),
    "topopt_new": (758, 1, 7, 0.0, 8.0, 3.0, 1.0, 50.0, 0.0),
    "bridgeSmall": (753, 1, 7, 0.0, 8.0, 3.0, 1.0, 50.0, 0.0),
    "GEbracket": (756, 1, 7, 0.0, 8.0, 3.0, 1.0, 50.0, 0.0),
}
#: what a field left None becomes without a row: the SL row 'tube' (MainWindow.cpp:737) and the SR weight of the SR rows
S3_DEFAULTS: dict[str, float | int] = {"outer_loops": 1, "inner_loops": 7, "w_critical_sl": 15.0, "w_critical_sr": 8.0,
                                       "w_neighbor_scale": 3.0, "w_regular_scale": 1.0, "w_smooth": 40.0,
                                       "support_free_angle_deg": 30.0}
PRESET_FIELDS = ("outer_loops", "inner_loops", "w_critical_sl", "w_critical_sr", "w_neighbor_scale", "w_regular_scale",
                 "w_smooth", "support_free_angle_deg")


class S3DeformConfig(BaseModel):
    """S3-Slicer's iterative deformation (``DeformTet.cpp``); defaults: its support-less row for most models
    (MainWindow.cpp:737, 'tube', the same as bunny, curved_Bar, teapot1, ...), the other rows by model name."""

    model_config = ConfigDict(extra="forbid")

    preset: str = Field(
        "auto", description="'auto': the row of S3's parameter table named like the model file (ring, topopt_new4, "
        "tube, ...) when there is one; 'none': the fields as given; or a row's name")
    on: Literal["model", "cage"] = Field(
        "model", description="the mesh S3 deforms: the input .tet itself when the model is one (S3's own setting), "
        "else the cage; 'cage': always the cage")
    # The fields S3's table sets are None by default, meaning "S3's row": a value is explicit exactly when it is not
    # None (pydantic's model_fields_set does not survive the dict round trips configs go through: a config read back
    # from its dump marks every field as set, and the row would never apply).
    outer_loops: int | None = Field(None, ge=0, le=50, description="outer (ASAP) iterations, m_loopTime "
                                    "(spinBox_shapeUpIterNum); None: S3's row (1, ring 2)")
    inner_loops: int | None = Field(None, ge=1, le=100, description="rotation/smoothing passes per outer iteration, "
                                    "m_innerLoopTime (spinBox_innerIterNum); None: S3's row (7)")
    w_critical_sl: float | None = Field(None, ge=0, description="ASAP weight of overhang tets, m_criticalTet_weight_SL; "
                                        "None: S3's row (15)")
    w_critical_sr: float | None = Field(None, ge=0, description="ASAP weight of stress-critical tets, "
                                        "m_criticalTet_weight_SR; None: S3's row (8)")
    w_neighbor_scale: float | None = Field(None, ge=0, description="weight of s_i - s_j across shared faces, "
                                           "m_neighborScale_weight; None: S3's row (3, ring 5)")
    w_regular_scale: float | None = Field(None, gt=0, description="weight of s_e - 1, m_regularScale_weight; None: "
                                          "S3's row (1)")
    w_smooth: float | None = Field(None, gt=0, description="quaternion Laplacian weight, m_globalSmooth_weight; None: "
                                   "S3's row (40 SL, 50 SR and SL + SR)")
    keep_weight: float = Field(1.0, gt=0, description="weight keeping critical/bottom tets' quaternions, m_keep_SL "
                               "(DeformTet.h:180)")
    support_free_angle_deg: float | None = Field(
        None, gt=0, lt=90, description="overhang detection and target angle below the horizontal, m_supportFreeAngle; "
        "None: S3's row (30)")
    bottom_height_mm: float = Field(1.0, ge=0, description="tets with a vertex this close to the floor are never "
                                    "overhanging and keep their rotation, m_bottom_height (DeformTet.h:185)")
    layer_field: Literal["height", "inverse_deformation"] = Field(
        "height", description="the field the layers are level sets of: 'height', the deformed height "
        "(_cal_virtual_Vfield, DeformTet.cpp:2584); 'inverse_deformation', what S3's GUI slices after its inverse "
        "deformation step (MainWindow.cpp:1540-1576): that height's unit gradient, smoothed 10 times over face "
        "neighbours and integrated back by least squares")

    def resolve(self, name: str, objectives: Iterable[str]) -> "S3DeformConfig":
        """The parameters S3 would run with: the row of its table for the model name (preset 'auto') or the named
        row, else the row of the case (SL: 'tube', SR: 'GEbracket', SL + SR: 'topopt_new4'); fields given (not None)
        win over the row; the SL (SR) weight is 0 without 'sf' ('sr'). Preset 'none': the fields given, the rest
        S3's SL defaults (:meth:`filled`)."""
        objectives = set(objectives)
        key = self.preset_row(name, objectives)
        values = dict(zip(PRESET_FIELDS, S3_PRESETS[key][1:])) if key else {}
        values = {k: v for k, v in values.items() if getattr(self, k) is None}
        if key and not S3_PRESETS[key][4]:  # an SL row has no SR weight: S3's SR rows use 8
            values.pop("w_critical_sr", None)
        if key and not S3_PRESETS[key][8]:  # an SR row has no support-free angle: S3's SL rows use 30
            values.pop("support_free_angle_deg", None)
        if "sf" not in objectives:
            values["w_critical_sl"] = 0.0
        if "sr" not in objectives:
            values["w_critical_sr"] = 0.0
        return self.model_copy(update=values).filled()

    def filled(self) -> "S3DeformConfig":
        """This config with every field left None set to S3's default (its SL row, MainWindow.cpp:737, and SR weight
        8 of its SR rows)."""
        return self.model_copy(update={k: v for k, v in S3_DEFAULTS.items() if getattr(self, k) is None})

    def preset_row(self, name: str, objectives: Iterable[str]) -> str:
        """The name of the row :meth:`resolve` takes ('' with preset 'none')."""
        if self.preset == "none":
            return ""
        if self.preset != "auto" and self.preset not in S3_PRESETS:
            raise ValueError(f"s3.preset: unknown row {self.preset!r}; known: {', '.join(sorted(S3_PRESETS))}")
        key = name if self.preset == "auto" else self.preset
        if key in S3_PRESETS:
            return key
        return {frozenset({"sf"}): "tube", frozenset({"sr"}): "GEbracket"}.get(
            frozenset(set(objectives) & {"sf", "sr"}), "topopt_new4")
