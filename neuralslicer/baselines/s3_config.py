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
