"""Configuration of the voxel finite-element analysis (the ``fea:`` key of a model spec).

Units are MPa, N and mm throughout; boxes and planes are in the build frame (+z up, after the
spec's ``up`` rotation).  Every field has a default so that the minimal form below is complete::

    fea:
      material: {youngs_modulus_mpa: 2000, poisson_ratio: 0.3}
      supports:
        - box: [[-1, -1, -1], [0.5, 11, 11]]
      loads:
        - box: [[99.5, -1, -1], [101, 11, 11]]
          force_n: [0, 0, -10]
"""
from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

Vec3 = tuple[float, float, float]


class _Strict(BaseModel):
    """Base model that rejects unknown keys (a typo in a spec is an error, not a silent default)."""

    model_config = ConfigDict(extra="forbid")


class IsotropicMaterial(_Strict):
    """Isotropic linear elastic material for the stress analysis (defaults: PLA-like, 2 GPa)."""

    youngs_modulus_mpa: float = Field(2000.0, gt=0, description="Young's modulus E [MPa].")
    poisson_ratio: float = Field(0.3, gt=-1.0, lt=0.5, description="Poisson ratio nu.")


class AnisotropicMaterial(_Strict):
    """Transversely isotropic material of a printed part (direction 1 = toolpath tangent).

    Defaults follow the paper (Sec. 6.2): ``Y1 = 3.5 GPa`` along the filament, ``Y2 = Y3 = 1.2 GPa``
    across it (the layer normal, i.e. the LPD, is one weak direction).  ``nu12 = nu13 = 0.3`` (strain
    across / strain along, for a stress along the filament), ``nu23 = 0.35``; ``G23 = Y2 / (2 (1 +
    nu23))`` (the 2-3 plane is isotropic); ``G12 = G13`` defaults to Saint-Venant's estimate
    ``1/G12 = 1/Y1 + 1/Y2 + 2 nu12/Y1`` (= 775 MPa for the defaults).
    """

    y1_mpa: float = Field(3500.0, gt=0, description="Young's modulus along the toolpath [MPa].")
    y2_mpa: float = Field(1200.0, gt=0, description="Young's modulus across it, Y2 = Y3 [MPa].")
    nu12: float = Field(0.3, description="Poisson ratio nu12 = nu13.")
    nu23: float = Field(0.35, gt=-1.0, lt=1.0, description="Poisson ratio in the weak plane.")
    g12_mpa: float | None = Field(None, gt=0, description="Shear modulus G12 = G13 [MPa]; "
                                  "None: Saint-Venant estimate.")

    @property
    def shear_12(self) -> float:
        """G12 = G13 in MPa (given, or Saint-Venant's estimate)."""
        if self.g12_mpa is not None:
            return float(self.g12_mpa)
        return 1.0 / (1.0 / self.y1_mpa + 1.0 / self.y2_mpa + 2.0 * self.nu12 / self.y1_mpa)

    @property
    def shear_23(self) -> float:
        """G23 = Y2 / (2 (1 + nu23)) in MPa."""
        return self.y2_mpa / (2.0 * (1.0 + self.nu23))

    @model_validator(mode="after")
    def _positive_definite(self) -> "AnisotropicMaterial":
        """Reject constants whose compliance matrix is not positive definite."""
        nu21 = self.nu12 * self.y2_mpa / self.y1_mpa
        if not (1.0 - self.nu23 ** 2 - 2.0 * self.nu12 * nu21 * (1.0 + self.nu23) > 0
                and self.nu12 * nu21 < 1.0):
            raise ValueError("anisotropic constants give a non positive-definite stiffness "
                             "(check nu12, nu23 against y1_mpa/y2_mpa)")
        return self


class PlaneRegion(_Strict):
    """The nodes (or boundary faces) with ``|x[axis] - value| <= tol``."""

    axis: Literal["x", "y", "z"]
    value: float
    tol: float | None = Field(None, ge=0, description="Half thickness [mm]; None: half a voxel "
                               "for nodes, a quarter for pressure faces.")


class _Region(_Strict):
    """A selection of mesh nodes: exactly one of ``box``, ``plane``, ``platform``."""

    box: tuple[Vec3, Vec3] | None = Field(None, description="[[xmin,ymin,zmin],[xmax,ymax,zmax]]")
    plane: PlaneRegion | None = None
    platform: bool = Field(False, description="The nodes within half a voxel of z = platform_z.")

    @model_validator(mode="after")
    def _one_region(self) -> "_Region":
        """Exactly one way of selecting nodes."""
        n = (self.box is not None) + (self.plane is not None) + bool(self.platform)
        if n != 1:
            raise ValueError("give exactly one of 'box', 'plane' or 'platform: true'")
        if self.box is not None and np.any(np.asarray(self.box[1]) < np.asarray(self.box[0])):
            raise ValueError("box must be [[xmin,ymin,zmin],[xmax,ymax,zmax]] with min <= max")
        return self

    def describe(self) -> str:
        """Short human description of the region, for error messages."""
        if self.box is not None:
            return f"box {[list(c) for c in self.box]}"
        if self.plane is not None:
            return f"plane {self.plane.axis}={self.plane.value}"
        return "platform"


class Support(_Region):
    """A Dirichlet support: the selected nodes have zero displacement in the fixed components."""

    fix: tuple[bool, bool, bool] = Field((True, True, True), description="Fixed components x,y,z.")


class Load(_Region):
    """A load: ``force_n`` total force spread evenly over the selected nodes, and/or a pressure."""

    force_n: Vec3 | None = Field(None, description="Total force [N] over the selected nodes.")
    pressure_mpa: float | None = Field(None, description="Pressure [MPa] on the boundary voxel "
                                       "faces whose centre is in the region; > 0 pushes inward.")

    @model_validator(mode="after")
    def _something(self) -> "Load":
        """A load must carry a force or a pressure."""
        if self.force_n is None and self.pressure_mpa is None:
            raise ValueError("a load needs 'force_n' and/or 'pressure_mpa'")
        if self.pressure_mpa is not None and self.platform:
            raise ValueError("a pressure needs a 'box' or 'plane' region")
        return self


class SolverOptions(_Strict):
    """Linear solver choice: a direct sparse factorisation when small, else preconditioned CG."""

    method: Literal["auto", "direct", "amg", "mg"] = Field(
        "auto", description="auto: direct up to direct_max_dofs DOFs, else mg (matrix-free "
        "geometric multigrid, isotropic material) or amg (assembled, per-voxel material).")
    direct_max_dofs: int = Field(
        3_000, ge=0, description="Largest system (DOFs) solved by SuperLU; its 3-D fill-in "
        "grows fast: on a compact part AMG-CG is already 10x quicker at 9k DOFs.")
    rtol: float = Field(1e-8, gt=0, lt=1, description="Relative residual of the CG solve.")
    maxiter: int = Field(2000, ge=1, description="Maximum CG iterations.")


class FEASpec(_Strict):
    """Voxel FEA configuration: material, supports, loads, resolution (units MPa, N, mm)."""

    material: IsotropicMaterial = Field(default_factory=IsotropicMaterial)
    anisotropic: AnisotropicMaterial = Field(default_factory=AnisotropicMaterial,
                                             description="Printed material for verify_layers.")
    supports: list[Support] = Field(default_factory=list)
    loads: list[Load] = Field(default_factory=list)
    voxels: int = Field(100_000, ge=8, description="Target number of voxels in the bounding box.")
    top_fraction: float = Field(0.10, gt=0.0, le=1.0, description="Fraction of voxels kept in T "
                                "(largest |max principal stress|).")
    solver: SolverOptions = Field(default_factory=SolverOptions)

    @field_validator("supports", "loads", mode="before")
    @classmethod
    def _none_is_empty(cls, v: object) -> object:
        """``supports:`` with no items in YAML reads as None: treat it as an empty list."""
        return [] if v is None else v
