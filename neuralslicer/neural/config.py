"""Configuration of the neural optimisation (SPEC steps 5-9), with documented defaults."""
from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from neuralslicer.motion.profile import Nozzle


class NetworkConfig(BaseModel):
    """Parameterisation of q and s: SIREN networks (size, initialisation) or free per-element values."""

    model_config = ConfigDict(extra="forbid")

    kind: Literal["siren", "per_element"] = Field(
        "siren",
        description="'siren': q(x), s(x) are SIREN networks (the paper); 'per_element': q and s are free "
        "parameters per cage tet, optimised directly (the ablation; the SIREN sizes below are unused)",
    )
    hidden_layers: int = Field(3, ge=1, description="number of hidden sine layers")
    hidden_features: int = Field(64, ge=4, description="neurons per hidden layer")
    omega_0: float = Field(
        10.0, gt=0, description="SIREN frequency of the first layer (Sitzmann/paper: 30)"
    )
    omega_hidden: float = Field(30.0, gt=0, description="SIREN frequency of hidden layers")
    max_scale: float = Field(
        5.0, gt=1, description="scale ratios are bounded to [1/max_scale, max_scale]"
    )


#: Network presets: ``default`` converges well on a CPU; ``paper`` is the published 10 x 512;
#: ``per_element`` optimises q, s per cage tet directly (the ablation "Q-S networks vs per-element q, s").
NETWORK_PRESETS: dict[str, NetworkConfig] = {
    "default": NetworkConfig(),
    "paper": NetworkConfig(hidden_layers=10, hidden_features=512, omega_0=30.0),
    "small": NetworkConfig(hidden_layers=2, hidden_features=32),
    "per_element": NetworkConfig(kind="per_element"),
}


class DeformationConfig(BaseModel):
    """Scale-controlled ARAP deformation of the cage (SPEC step 6)."""

    model_config = ConfigDict(extra="forbid")

    gamma: float = Field(1e-4, gt=0, description="weight of the regularisation sum |v^d - v|^2")
    pin_platform: bool = Field(
        False,
        description="keep the height of cage vertices at/below the platform (hard, by elimination)",
    )
    platform_tolerance: float = Field(
        0.0, ge=0, description="mm above the platform still counted as 'on the platform'"
    )
    solver: Literal["auto", "cholmod", "cholespy", "splu"] = Field(
        "auto",
        description="sparse factorisation: 'auto' = CHOLMOD (scikit-sparse), else cholespy, else SuperLU",
    )


class LossConfig(BaseModel):
    """Loss weights and parameters (SPEC step 8); every term is normalised by its sample weight."""

    model_config = ConfigDict(extra="forbid")

    w_sf: float = Field(1.0, ge=0, description="support-free (surface normal) weight")
    w_sr: float = Field(0.0, ge=0, description="strength-reinforcement weight")
    w_po: float = Field(1.0, ge=0, description="point-overhang weight")
    w_hs: float = Field(1.0, ge=0, description="harmonic weight on scale ratios")
    w_hq: float = Field(1.0, ge=0, description="harmonic weight on quaternions")
    alpha_deg: float = Field(45.0, gt=0, lt=90, description="self-supporting angle alpha")
    beta_deg: float = Field(10.0, gt=0, lt=90, description="strength tolerance beta")
    k_sf: float = Field(30.0, gt=0, description="logistic growth rate of L_SF")
    k_sr: float = Field(15.0, gt=0, description="logistic growth rate of L_SR")
    collision: bool = Field(True, description="enforce L_CA = 0 by a DC3-style correction")
    phi_deg: float | None = Field(
        None, gt=0, lt=180,
        description="printer-head cone apex angle phi of L_CA (default: twice the head's cone half angle)")
    w_gc: float = Field(0.0, ge=0, description="global collision weight (the 'gc' objective sets 1 when it is 0)")
    head: Nozzle = Field(
        default_factory=Nozzle,
        description="print head of L_GC and L_CA (the pipeline takes it from the machine profile's nozzle)")
    head_min_height: float = Field(
        0.5, ge=0, description="material closer than this to the tip along the axis is the bead itself (mm)")
    gc_points: int = Field(
        2000, ge=100, description="points of the jittered grid that stands for the solid in L_GC (surface "
        "samples, one per grid cell, come on top)")
    gc_spacing: float | None = Field(
        None, gt=0, description="pool spacing (mm; default: (solid volume / gc_points)^(1/3))")
    gc_clearance: float | None = Field(
        None, ge=0, description="head clearance of L_GC (mm; default: 1.5 x the pool spacing, which covers tips "
        "and material between pool points and the smoothing of the tool axis along the toolpaths, at most the "
        "cone's length)")
    gc_front_margin: float = Field(
        0.1, ge=0,
        description="mm: pool points up to this far ahead of the printing front count as printed, with the head "
        "lifted as far along its axis (so points straight ahead never do)")
    gc_floor: bool = Field(
        True, description="L_GC's platform term also at every cage tet with solid within the head's reach of the "
        "platform, at its lowest solid point along its LPD (the floor; off: at the pool's points only)")
    gc_platform_turn_deg: float = Field(
        0.0, ge=0, le=45,
        description="L_GC's platform and floor terms judge the head with its axis turned toward +z by up to this "
        "(deg), as the motion planner turns axes whose head would dip below the platform; the pipeline sets it to "
        "toolpath.collision_tilt_deg (0: the head along the LPD itself)")
    gc_floor_weight: float = Field(
        10.0, ge=0, description="weight of the floor's platform penalties within L_GC, relative to a pool cell of "
        "solid (its penalties are quadratic, so a settled field's platform shortfall falls about as 1/weight; the "
        "200 mm bunny's first print, with the platform turn: weight 1 left 43,462 colliding waypoints, 10 left 4,765, "
        "and the clean print kept 72 % of the overhang reduction)")
    gc_vertical_head: bool = Field(
        False, description="L_GC places the head along +z at every point instead of along the LPD: a three-axis "
        "printer's nozzle never tilts (with_tilt_bound sets it for a three-axis machine profile)")
    tilt_bound_deg: float | None = Field(
        None, gt=0, lt=90,
        description="largest angle (deg) between the LPD and +z anywhere in the solid (None: unbounded, five "
        "axes). The pipeline sets it from a three-axis machine profile's clearance unless it is set here: L_TB "
        "penalises the excess (w_tb) and the final weights are corrected until no solid cage tet exceeds it")
    w_tb: float = Field(
        100.0, ge=0, description="weight of L_TB, the tilt bound's penalty (only with tilt_bound_deg)")
    tilt_margin_deg: float = Field(
        0.5, ge=0, description="the final correction aims at LPDs this far (deg) inside tilt_bound_deg")
    tilt_correction_steps: int = Field(
        200, ge=0, description="max correction steps of the final weights until no solid cage tet's LPD exceeds "
        "tilt_bound_deg (checked in float64; 0: the penalty alone)")

    correction_steps: int = Field(
        20, ge=0, description="max DC3 correction steps before one loss evaluation (stops when feasible)"
    )
    correction_lr: float = Field(
        1.0, gt=0, description="fraction of the first-order step to L_CA = 0 (L_CA/|grad|^2 grad)"
    )
    correction_max_step: float = Field(
        0.05, gt=0, description="cap of one correction step, relative to the weight norm"
    )
    correction_tol: float = Field(
        0.0, ge=0,
        description="a pair violates L_CA = 0 when its excess angle theta - (pi - phi) exceeds this (rad); "
        "feasible = no violating pair",
    )
    correction_margin: float = Field(
        1e-3, ge=0,
        description="the correction aims at excess <= -margin (rad) so that the next step and float64 "
        "re-evaluation keep the pair feasible",
    )
    final_correction_steps: int = Field(
        200, ge=0,
        description="max correction steps on the final weights until no pair violates (checked in float64)",
    )


class RefineConfig(BaseModel):
    """Collision-driven refinement of L_GC's pool and the warm-started run that follows it
    (``optimise_for_solid(..., refine=Refinement(...))``; see docs/neural.md)."""

    model_config = ConfigDict(extra="forbid")

    steps: int = Field(
        300, ge=0,
        description="step budget of a warm-started refinement run (a run refined without earlier weights starts "
        "afresh and keeps optim.max_steps)")
    spacing_factor: float = Field(
        1.0 / 3.0, gt=0, le=1,
        description="spacing of the added lattice, as a fraction of the pool spacing: a third puts a point within "
        "0.3 pool spacings of any point of a strut at least a third of a pool spacing thick, finer than the "
        "clearance (1.5 spacings) that carries the discretisation")
    radius_factor: float = Field(
        2.0, gt=0,
        description="points are added within this many pool spacings of each colliding waypoint and each point "
        "it hit: the Voronoi cell of the nearest base point and its neighbours, where the base pool could not "
        "tell the collision apart")
    max_points: int = Field(20_000, ge=0, description="at most this many points are added by one refinement")
    max_pairs: int = Field(
        10_000_000, ge=0,
        description="at most this many ordered pairs along the refinement's links (the ring's whole pool has "
        "6.2 M); beyond it every link keeps an equal share of them (a random subset of its points), with a warning")
    lr: float | None = Field(
        1e-4, gt=0,
        description="Adam learning rate of a warm-started run (None: optim.lr). A fresh Adam moves every weight by "
        "about lr per step whatever the gradient's scale: at 1e-3 a warm start leaves the optimum it starts from "
        "(the lattice's overhang went from 3.2 % to 6.2 % in 300 steps); 1e-4 keeps it close")
    floor_weight_factor: float = Field(
        3.0, ge=1,
        description="a refinement after a print whose head still dips below the platform (beyond the planner's "
        "turn, toolpath.collision_tilt_deg) multiplies loss.gc_floor_weight by this (the 200 mm bunny: weight 1 "
        "left 9,962 such waypoints, 3 left 108, 10 none)")
    overhang_slack: float = Field(
        0.005, ge=0,
        description="a warm-started run's constraint stop accepts the overhang area fraction it started from plus "
        "this (besides target_overhang): it is there to clear the collisions, not to improve the overhang of a "
        "run that stopped above the target")


class OptimConfig(BaseModel):
    """Adam + ReduceLROnPlateau, budget and convergence test (SPEC step 8)."""

    model_config = ConfigDict(extra="forbid")

    lr: float = Field(1e-3, gt=0, description="initial Adam learning rate")
    betas: tuple[float, float] = Field(
        (0.9, 0.99),
        description="Adam (beta1, beta2); beta2 = 0.99 adapts faster than torch's 0.999 where the "
        "gradient scale changes by orders of magnitude (fewer loss spikes near the optimum)",
    )
    min_lr: float = Field(1e-6, gt=0, description="ReduceLROnPlateau floor")
    plateau_factor: float = Field(0.5, gt=0, lt=1, description="ReduceLROnPlateau factor")
    plateau_patience: int = Field(100, ge=1, description="ReduceLROnPlateau patience (steps)")
    trend_smoothing: float = Field(
        0.05, gt=0, le=1,
        description="weight of the newest step in the exponential moving average of log(loss) that the "
        "plateau scheduler and the stall test see (1: the raw loss). Near the optimum the loss jitters "
        "by tens of % from step to step (L_PO's kinks); on the raw loss both react to the jitter",
    )
    divergence_factor: float = Field(
        3.0, ge=0,
        description="a step whose loss exceeds this multiple of the best loss so far is undone: weights "
        "and Adam state go back to the best iterate and the learning rate is halved (0: off)",
    )
    grad_clip: float = Field(
        5.0, ge=0,
        description="a step's gradient norm is capped at this multiple of the running average of the "
        "recent (capped) norms (0: off). When new collisions enter L_GC's active set the loss can jump a "
        "thousandfold for one step; uncapped, that gradient fills Adam's second moments and the run "
        "coasts along the spike's direction, then stalls for hundreds of steps",
    )
    restart_from_best: bool = Field(
        True,
        description="when the plateau scheduler lowers the learning rate, go on from the best iterate "
        "(weights and Adam state) rather than from wherever the last, noisier steps left the weights",
    )
    return_best: bool = Field(True, description="return the best iterate (lowest total loss), not the last")
    max_steps: int = Field(3000, ge=0, description="step budget")
    convergence_window: int = Field(200, ge=2, description="steps compared by the stop test")
    convergence_rtol: float = Field(
        1e-3, ge=0,
        description="stop when the smoothed loss (its running minimum) improved less than this over the window",
    )
    convergence_atol: float = Field(
        0.0, ge=0,
        description="... or less than this in absolute terms (losses are unit-free; final losses reach "
        "1e-7, so any fixed floor above that stops a run early)",
    )
    target_loss: float = Field(
        1e-6, ge=0,
        description="converged once the best total loss is at or below this (0: off). The ring's loss has "
        "no floor within reach (it keeps falling, ~geometrically, by trading SF margin against "
        "ever smaller harmonic terms), so a run stopped by the budget or a stall test ends wherever "
        "its start left it; a target gives every start the same end point",
    )
    target_overhang: float = Field(
        1e-3, ge=0,
        description="converged once the overhang area fraction of B is at most this, no pool point's head "
        "(grown by stop_head_growth x the L_GC clearance) reaches earlier material or the platform, and the "
        "corrected step has L_CA = 0: the constraints are met (0: off; not with a strength objective, which has "
        "no such state)")
    stop_head_growth: float = Field(
        0.0, ge=0,
        description="the head of the constraint stop grown by this fraction of the L_GC clearance (0: the "
        "machine's head itself; the loss keeps its full clearance, and the toolpaths' exact check stays the judge)")
    target_overhang_late: float = Field(
        1e-2, ge=0,
        description="from step late_after on, the constraint stop accepts this overhang fraction instead (still "
        "with no head collision and L_CA = 0): a bound on runs whose overhang creeps down slowly (0: off)")
    late_after: int = Field(500, ge=0, description="step from which target_overhang_late applies")
    progress_window: int = Field(
        300, ge=0,
        description="from step late_after on, stop once the best overhang fraction of B over the last this many "
        "steps is within progress_rtol of the best before them and the pool's head hits have not dropped below "
        "their best before them either (0: off; not with a strength objective). The loss-based stall test never "
        "fires while L_GC keeps trading penalties (the lattice ran its whole budget at 3.4 % overhang); this one "
        "watches what the stop is for")
    progress_rtol: float = Field(0.05, ge=0, lt=1, description="relative overhang improvement the progress "
                                 "stall test asks for over progress_window steps")
    progress_every: int = Field(50, ge=1, description="steps between the progress stall test's measurements")
    check_every: int = Field(
        10, ge=1, description="steps between searches for L_GC's pairs near collision and constraint checks")
    checkpoint_every: int = Field(50, ge=1, description="steps between checkpoints")
    seed: int = Field(0, description="seed of torch, numpy and python RNGs")
    refine: RefineConfig = Field(default_factory=RefineConfig, description="collision-driven refinement of L_GC")


class InitConfig(BaseModel):
    """Initial guess (SPEC step 9) and its pre-training."""

    model_config = ConfigDict(extra="forbid")

    kind: Literal["height", "heat", "user"] = Field("height", description="initial field")
    pretrain_steps: int = Field(300, ge=0, description="Adam steps fitting G to the field (MSE)")
    pretrain_lr: float = Field(1e-3, gt=0, description="learning rate of the pre-training")
    pretrain_harmonic: float = Field(
        10.0, ge=0,
        description="pre-training minimises MSE + this * (w_hs L_HS + w_hq L_HQ): the guess is fitted "
        "with smooth q, s instead of whatever rotations/scales fit G (0: plain MSE)",
    )
    heat_time_factor: float = Field(1.0, gt=0, description="heat time t = factor * h^2")


class NeuralConfig(BaseModel):
    """Everything the neural optimisation needs besides the geometry."""

    model_config = ConfigDict(extra="forbid")

    network: str | NetworkConfig = Field("default", description="preset name or explicit size")
    deformation: DeformationConfig = Field(default_factory=DeformationConfig)
    loss: LossConfig = Field(default_factory=LossConfig)
    optim: OptimConfig = Field(default_factory=OptimConfig)
    init: InitConfig = Field(default_factory=InitConfig)
    device: str = Field("auto", description="'auto' (CUDA if available), 'cpu', 'cuda', 'cuda:1'")
    dtype: Literal["float32", "float64"] = Field("float32", description="network/loss precision")

    def with_head(self, nozzle: Nozzle, min_height: float, platform_turn_deg: float = 0.0) -> "NeuralConfig":
        """This config with the machine's print head for L_GC and L_CA; material closer than min_height
        (the line width, at least 0.3 mm, as in the motion planner's check) to the tip is the bead; the planner
        turns axes at the platform by up to platform_turn_deg (``toolpath.collision_tilt_deg``)."""
        loss = self.loss.model_copy(update={"head": nozzle, "head_min_height": max(0.3, float(min_height)),
                                            "gc_platform_turn_deg": float(platform_turn_deg)})
        return self.model_copy(update={"loss": loss})

    def with_tilt_bound(self, bound_deg: float | None) -> "NeuralConfig":
        """This config for a machine whose printing direction is bounded to ``bound_deg`` from +z (a three-axis
        profile's ``printing_direction_bound_deg()``; None: unbounded, this config itself): ``loss.tilt_bound_deg``
        set to it unless already set, and L_GC's head kept vertical."""
        if bound_deg is None:
            return self
        bound = self.loss.tilt_bound_deg if self.loss.tilt_bound_deg is not None else float(bound_deg)
        loss = self.loss.model_copy(update={"tilt_bound_deg": bound, "gc_vertical_head": True})
        return self.model_copy(update={"loss": loss})

    def for_objectives(self, objectives: list[str]) -> "NeuralConfig":
        """This config with the weights of the objectives not asked for set to zero (sf, po, sr, gc), and
        the local collision constraint on when ca is asked for."""
        loss = self.loss.model_copy(update={
            "w_sf": self.loss.w_sf if "sf" in objectives else 0.0,
            "w_po": self.loss.w_po if "po" in objectives else 0.0,
            "w_sr": (self.loss.w_sr or 1.0) if "sr" in objectives else 0.0,
            "w_gc": (self.loss.w_gc or 1.0) if "gc" in objectives else 0.0,
            "collision": "ca" in objectives,
        })
        return self.model_copy(update={"loss": loss})

    def apex_deg(self) -> float:
        """The cone apex angle of L_CA: set explicitly, or twice the head's cone half angle."""
        cl = self.loss
        return cl.phi_deg if cl.phi_deg is not None else 2.0 * cl.head.cone_half_angle_deg

    def network_config(self) -> NetworkConfig:
        """The resolved network size (preset names looked up in NETWORK_PRESETS)."""
        if isinstance(self.network, NetworkConfig):
            return self.network
        if self.network not in NETWORK_PRESETS:
            from neuralslicer.errors import InputError

            raise InputError(
                "neural.network",
                f"unknown preset {self.network!r}; expected one of {', '.join(NETWORK_PRESETS)}",
            )
        return NETWORK_PRESETS[self.network]
