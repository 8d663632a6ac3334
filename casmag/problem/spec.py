"""Problem files: schema, validation and loading.

A problem file is YAML with a top-level integer ``seed`` and the sections ``simulation``
(where the data come from), ``model`` (what the MAP problem assumes) and ``solver`` (IPOPT).
Every key is validated before anything is built; an unknown key or a bad value raises
:class:`~casmag.errors.ProblemError` naming the file, the dotted key and the reason.

Model settings left out (``null``) default to the simulation's truth, so a file states only
where the model deliberately differs from the world (the paper's "wrong sigma_f" rows).
"""

from __future__ import annotations

import copy
import difflib
import json
import os
import re
import sys
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar

import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from casmag.errors import ProblemError

KernelName = Literal["se", "curl_free", "div_free"]
HyperName = Literal["sigma_f", "lengthscale", "sigma_m"]
PositiveFloat = Annotated[float, Field(gt=0)]
NonNegativeFloat = Annotated[float, Field(ge=0)]


class Strict(BaseModel):
    """Base of every casmag document section: unknown keys, type coercion and inf/nan are
    refused."""

    # No inf or nan anywhere: no model can carry them (they passed validation and failed in
    # CasADi or the kernels).
    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)


# --------------------------------------------------------------------------- simulation
class TrajectorySpec(Strict):
    """The true path, walked at constant speed with one magnetometer sample per pose.

    kind ``spiral``: planar Archimedean spiral (paper Section 3.1); start_radius: radius of
    the first sample [m]; pitch: radial distance between successive turns [m].
    kind ``walk``: a smooth random walk that loops inside a rectangle of side lengths
    ``area`` [m] centred on the origin, its heading a random walk of ``heading_noise``
    rad per square-root metre, turned back from within ``wall_margin`` of the edges; long
    walks revisit every part of the area many times (loop closures).
    samples: number of poses N; step: path length between samples [m].
    """

    kind: Literal["spiral", "walk"] = "spiral"
    samples: Annotated[int, Field(ge=3, le=1_000_000)] = 81
    step: PositiveFloat = 0.05
    start_radius: NonNegativeFloat = 0.05
    pitch: PositiveFloat = 0.05
    area: Annotated[list[PositiveFloat], Field(min_length=2, max_length=2)] = [6.0, 6.0]
    heading_noise: NonNegativeFloat = 0.6
    wall_margin: NonNegativeFloat = 0.5


class FieldSpec(Strict):
    """The true field, drawn from the GP prior with these hyperparameters.

    method ``exact``: a joint Gaussian draw at the samples (O(N^3), for N up to a few
    thousand); ``fourier``: random Fourier features (``features`` cosines with frequencies
    drawn from the kernel's spectral density), a smooth field defined everywhere, for long
    walks. ``fourier`` supports the se and curl_free kernels. ``dipoles``: not a GP draw but
    physics (casmag.data.simulate.dipole_floor_field): magnetic dipoles under the floor,
    ``dipole_density`` per square metre at depths uniform in ``dipole_depth`` [m] (null:
    1.5 to 3 lengthscales) below the path's plane, scaled so that each component's standard
    deviation along the path is the GP's (sigma_f; curl_free: sigma_f / l); the kernel,
    sigma_f and lengthscale are then what a model with null values assumes.
    """

    kernel: KernelName = "se"
    sigma_f: PositiveFloat = 0.1
    lengthscale: PositiveFloat = 0.1
    method: Literal["exact", "fourier", "dipoles"] = "exact"
    features: Annotated[int, Field(ge=10, le=100_000)] = 2000
    dipole_density: PositiveFloat = 1.0
    dipole_depth: Annotated[list[PositiveFloat], Field(min_length=2, max_length=2)] | None = None


class OdometrySimSpec(Strict):
    """Odometry increments = true increments + bias + white noise, per step and axis [m]."""

    noise: NonNegativeFloat = 1.0e-4
    bias: Annotated[list[float], Field(min_length=2, max_length=2)] = [1.0e-3, 1.0e-3]


class MagnetometerSimSpec(Strict):
    """Magnetometer = true field + white noise of this standard deviation (field units)."""

    noise: NonNegativeFloat = 2.0e-3


class SimulationSpec(Strict):
    trajectory: TrajectorySpec = TrajectorySpec()
    field: FieldSpec = FieldSpec()
    odometry: OdometrySimSpec = OdometrySimSpec()
    magnetometer: MagnetometerSimSpec = MagnetometerSimSpec()


# --------------------------------------------------------------------------- model
class GPSpec(Strict):
    """GP prior on the field. ``null`` hyperparameters take the simulation's true values.

    form: ``exact`` (dense kernel matrix over the samples, paper Eq. 6), ``reduced_rank``
    (Hilbert-space basis on a box around the initial trajectory, casmag.model.rrmap) or
    ``tiled`` (curl-free only: reduced-rank potentials on a grid of tiles blended smoothly,
    casmag.gp.tiles; each sample touches the tiles around it, for areas much larger than
    the lengthscale). tile_basis: ``bumps`` (casmag.gp.bumps: compactly supported bumps on a
    lattice, each sample touching the nodes within a few lengthscales) or ``hilbert`` (a
    reduced-rank basis per tile) (null: casmag.model.tiledmap.TILE_BASIS, bumps, as for
    every motion model); tile_spacing:
    the tiles' or lattice's spacing [m] (null: 4 l for hilbert; for bumps
    casmag.model.tiledmap.bump_spacing, 0.5-0.75 l from the field's strength); margin
    is then how far beyond the initial trajectory the tiles reach.
    num_basis, margin: reduced-rank basis size and box margin [m] (null: frequencies up to
    5 / l, margin 3 l). sigma_lin: prior standard deviation of a constant field added to the
    reduced-rank map (null: no constant term).
    jitter: added to the kernel diagonal, relative to the prior variance k(0).
    logdet: include 0.5 log|K(P, theta)| in the objective; null (default) includes it only
    when sigma_f or lengthscale is estimated. On the base case with fixed hyperparameters,
    including it made positions no more accurate and the solve about 2.5 times slower.
    """

    form: Literal["exact", "reduced_rank", "tiled"] = "exact"
    kernel: KernelName | None = None
    sigma_f: PositiveFloat | None = None
    lengthscale: PositiveFloat | None = None
    jitter: Annotated[float, Field(ge=0, le=1)] = 1.0e-6
    logdet: bool | None = None
    num_basis: Annotated[int, Field(ge=1, le=20_000)] | None = None
    margin: PositiveFloat | None = None
    sigma_lin: PositiveFloat | None = None
    tile_spacing: PositiveFloat | None = None
    tile_basis: Literal["bumps", "hilbert"] | None = None


class MagnetometerModelSpec(Strict):
    """Magnetometer noise standard deviation sigma_m assumed by the model (null: truth)."""

    sigma_m: PositiveFloat | None = None


class OdometryModelSpec(Strict):
    """Odometry noise per step and axis assumed by the model [m] (null: truth).

    estimate_bias: estimate a constant per-step odometry bias b (m per step, per axis) as
    part of the MAP problem, the translational analogue of the paper's IMU biases.
    bias_prior_sigma: standard deviation of a zero-mean prior on b [m]; null for none.
    """

    sigma: PositiveFloat | None = None
    estimate_bias: bool = True
    bias_prior_sigma: PositiveFloat | None = None


class AnchorSpec(Strict):
    """Soft anchor of the first position at its known value, standard deviation [m]."""

    sigma: PositiveFloat = 1.0e-4


class TrajectoryModelSpec(Strict):
    """How the estimated trajectory is represented (casmag.model.knots).

    knot_every: the positions are the dead reckoning plus a drift correction that is free at
    a knot every this many samples and linear in between. 1 (default) gives every sample
    its own position, the paper's formulation; larger values shrink the problem for long
    recordings (``casmag slam`` uses about one knot per second).
    """

    knot_every: Annotated[int, Field(ge=1, le=100_000)] = 1


#: Where a hyperparameter's value sits in a translational ``model`` section (``estimate``
#: there lists it under ``model.estimate``).
ESTIMATE_AS_VALUE = {
    "sigma_f": ("gp", "sigma_f"),
    "lengthscale": ("gp", "lengthscale"),
    "sigma_m": ("magnetometer", "sigma_m"),
}


class ModelSpec(Strict):
    """What the MAP problem assumes. ``estimate`` lists hyperparameters to estimate
    (log-parameterised, started from the values given or defaulted above, or from the
    marginal likelihood, as ``estimate_start`` says); writing ``estimate`` as the value of
    ``gp.sigma_f``, ``gp.lengthscale`` or ``magnetometer.sigma_m`` lists it too, with the
    start a null value has (the simulation's truth).

    estimate_start: where the joint MAP starts the estimated sigma_f and lengthscale.
    ``assumed``: at the assumed values. ``marginal_likelihood``: at the windowed GP marginal
    likelihood's maximum (paper Eq. 5, casmag.gp.hyper.estimate_conditional) at the initial
    (dead-reckoned) positions over the estimated hyperparameters only, searched from their
    assumed values with the others fixed at theirs. ``both`` (default): solve from each and
    keep the solution with the lower MAP cost (twice the solve time). Measured on the
    paper's Tables 2 and 4 (20 seeds): from an assumed l = 0.005 m the MAP stopped at a
    local optimum (l 0.007-0.026 m, RMSE 7-10 cm) on 17 seeds; from the marginal-likelihood
    start (l 0.020-0.030 m: drift makes the field look rougher) every seed reached
    l = 0.10-0.11 m, never at a higher cost (80 runs). For sigma_f the marginal likelihood at
    the drifted positions favours sigma_f of 3-1000 (truth 0.1), from where the MAP stopped
    at a local optimum on 5 of 20 seeds (cost -185 to -309 against -1346 to -1392; seed 1:
    RMSE 0.10 m), while the assumed starts from 0.001 to 10 reached the optimum at every
    seed: neither start alone is safe.
    The start does not change the built problem.
    """

    gp: GPSpec = GPSpec()
    trajectory: TrajectoryModelSpec = TrajectoryModelSpec()
    magnetometer: MagnetometerModelSpec = MagnetometerModelSpec()
    odometry: OdometryModelSpec = OdometryModelSpec()
    anchor: AnchorSpec = AnchorSpec()
    estimate: list[HyperName] = []
    estimate_start: Literal["both", "marginal_likelihood", "assumed"] = "both"

    @model_validator(mode="before")
    @classmethod
    def _estimate_as_a_value(cls, data: Any) -> Any:
        """``gp.sigma_f: estimate``, ``gp.lengthscale: estimate`` and
        ``magnetometer.sigma_m: estimate`` (the IMU and recording models' spelling) list the
        hyperparameter under ``estimate``, started as for a null value."""
        if not isinstance(data, dict):
            return data
        for name, (section, key) in ESTIMATE_AS_VALUE.items():
            part = data.get(section)
            if isinstance(part, dict) and part.get(key) == "estimate":
                data = {**data, section: {**part, key: None}}
                listed = data.get("estimate", [])
                if isinstance(listed, list) and name not in listed:
                    data["estimate"] = [*listed, name]
        return data

    @field_validator("estimate")
    @classmethod
    def _unique_estimates(cls, value: list[str]) -> list[str]:
        if len(set(value)) != len(value):
            raise ValueError("lists a hyperparameter twice")
        return value


class WarmStartSpec(Strict):
    """How the initial trajectory of the full problem is found (casmag.solver.staged,
    casmag.solver.windowing).

    strategy ``none``: the dead reckoning. ``growing``: solve the first ``first_samples``
    samples, then prefixes ``growth`` times longer up to all samples; each stage starts from
    the previous stage's trajectory (extended by the odometry) with the odometry bias
    estimated so far removed, and fits its map box around that start. A long recording's
    dead reckoning can drift by several lengthscales, which a single batch does not recover
    from, and it would inflate the map's box (and so the basis) with it.
    ``sliding``: a fixed-lag smoother over windows of ``window`` samples that overlap by
    ``overlap`` (in ``unit``: samples, or seconds with ``sample_period`` [s] per sample),
    with a reduced-rank map carried from window to window as a Gaussian prior on its
    weights (and, for the planar and pose models, each window's first state under the
    previous window's Laplace marginal of it); one NLP serves every window; each window
    stops after ``window_max_iter`` iterations; its trajectory starts the full batch.
    ``window: auto`` (the default) takes the samples the dead reckoning needs to travel
    ``window_lengthscales`` assumed lengthscales at its median speed, clamped to
    casmag.solver.windowing.AUTO_WINDOW; ``overlap: auto`` is half the window.
    ``window_bias_prior``: ``laplace`` gives each window the previous window's bias
    estimate as a Gaussian prior (its Laplace marginal covariance at the previous solve),
    ``none`` only the model's ``bias_prior_sigma`` on every window.
    ``turn`` (planar and pose models, one session): each prefix after the first starts
    turned about the vertical by the heading-rate correction of lowest MAP cost
    (casmag.solver.staged.best_turn).
    ``evidence`` (``casmag slam`` on one translational recording of 801-4,000 samples, and
    the planar and pose models on one session without a saved map): one more start, one
    batch from the dead reckoning with the odometry bias the field's evidence chooses
    removed (casmag.solver.biasscan), kept when its MAP cost is the lowest; ``false``
    leaves it out (the strategy alone, as before 2026-12-07).
    ``coarse-to-fine``: ``lengthscale_stages`` batch solves with the lengthscale shrinking
    geometrically from ``lengthscale_start`` times the assumed one to the assumed one, each
    started from the previous (at most ``stage_max_iter`` iterations before the last); a
    tiled map is laid again for each stage's lengthscale
    (casmag.solver.staged.map_lengthscale).
    ``auto``: the model's own default: ``none`` for the translational model, the solver
    defaults' ``growing`` for the planar and pose models, and for the IMU model (whose
    default it is) its schedule ladder (casmag.solver.imu: sigma_m annealed, then
    coarse-to-fine and growing-prefix schedules when a schedule fails or fits badly). The
    IMU model counts samples in keyframes and takes ``none``, ``growing``,
    ``coarse-to-fine`` and ``sliding`` besides (its windows hold the biases at the IMU-only
    adjustment's; ``window_bias_prior`` does not apply to it).

    Defaults: first_samples 4000, growth 4.0, stage_max_iter 25, turn true, evidence true,
    window auto,
    overlap auto, window_lengthscales 1.375, window_bias_prior laplace, unit samples,
    sample_period null, window_max_iter 50, lengthscale_start 3.0, lengthscale_stages 3.
    """

    strategy: Literal["none", "growing", "sliding", "coarse-to-fine", "auto"] = "none"
    first_samples: Annotated[int, Field(ge=10)] = 4000
    growth: Annotated[float, Field(gt=1)] = 4.0
    stage_max_iter: Annotated[int, Field(ge=1)] = 25
    turn: bool = True
    evidence: bool = True
    window: PositiveFloat | Literal["auto"] = "auto"
    overlap: NonNegativeFloat | Literal["auto"] = "auto"
    window_lengthscales: PositiveFloat = 1.375
    window_bias_prior: Literal["laplace", "none"] = "laplace"
    unit: Literal["samples", "seconds"] = "samples"
    sample_period: PositiveFloat | None = None
    window_max_iter: Annotated[int, Field(ge=1)] = 50
    lengthscale_start: Annotated[float, Field(gt=1)] = 3.0
    lengthscale_stages: Annotated[int, Field(ge=2, le=20)] = 3

    @field_validator("window", "overlap", mode="before")
    @classmethod
    def _number(cls, value: Any) -> Any:
        # Strict mode refuses an int for a float field; a window of 20 samples is an int.
        return float(value) if isinstance(value, int) and not isinstance(value, bool) else value

    @model_validator(mode="after")
    def _window_fits(self) -> WarmStartSpec:
        if self.unit == "seconds" and self.sample_period is None:
            raise ValueError("unit: seconds needs sample_period (seconds per sample)")
        if self.unit == "samples" and self.sample_period is not None:
            raise ValueError("sample_period is only used with unit: seconds")
        if self.unit == "samples" and any(
            v != "auto" and round(v) != v for v in (self.window, self.overlap)
        ):
            raise ValueError("window and overlap in samples must be whole numbers")
        window, overlap = self.window_samples, self.overlap_samples
        if window is not None and window < 3:
            raise ValueError(f"window must span at least 3 samples (got {window})")
        if overlap is not None and overlap < 1:
            raise ValueError(f"overlap must be at least 1 sample (got {overlap})")
        if window is not None and overlap is not None and overlap >= window:
            raise ValueError(
                f"overlap must be at least 1 sample and shorter than the window "
                f"(got {overlap} of {window} samples)"
            )
        return self

    def _samples(self, value: float) -> int:
        if self.unit == "samples":
            return round(value)
        return round(value / (self.sample_period or 1.0))

    @property
    def window_samples(self) -> int | None:
        """The window length in samples (None for ``auto``: casmag.solver.windowing.window_size)."""
        return None if self.window == "auto" else self._samples(self.window)

    @property
    def overlap_samples(self) -> int | None:
        """The overlap of consecutive windows in samples (``auto``: half the window; None
        while the window is ``auto``)."""
        if self.overlap != "auto":
            return self._samples(self.overlap)
        window = self.window_samples
        return None if window is None else max(1, window // 2)


#: ``solver.hessian`` values only a map read with numpy has (not the exact GP).
NUMPY_HESSIANS = ("gauss-newton", "hybrid")

#: ``solver.hessian`` values that name the mode of a numpy magnetometer block.
HESSIAN_MODES = ("exact", "hybrid", "gauss-newton")


class SolverSpec(Strict):
    """IPOPT settings. ``ipopt`` passes further options through unchanged.

    hessian (one key for every motion model): the Hessian of the magnetometer block that a
    map read with numpy has (reduced rank, tiled, rotated or not; the other blocks' is
    CasADi's exact one, except the IMU residuals and loop closures, J^T J unless ``exact``,
    and under ``gauss-newton`` the planar and pose odometry too): ``gauss-newton`` J^T J
    alone; ``exact`` with the residuals' second-order terms; ``hybrid`` Gauss-Newton
    while the block's cost falls fast, the exact terms once it falls by less than 20 % an
    iteration (the translational tiles: and by less than 1 unit, twice in a row; 1 %
    through a rotation); ``auto`` the model's own choice
    (translational and tiled maps ``hybrid``; planar ``model.curvature``, pose
    ``model.curvature``, IMU ``model.gp.curvature``). The exact GP takes CasADi's exact
    Hessian (``auto`` or ``exact``). ``limited-memory`` is IPOPT's L-BFGS (no Laplace
    covariance).
    uncertainty: compute the Laplace covariance of every position at the solution
    (casmag.solver.uncertainty): a 1-sigma column in trajectory.csv, ellipses in trajectory.png, the
    NEES against truth in result.json.
    memory_budget: GiB of resident memory a solve may use (null: 80 % of the machine's memory,
    or of the process's control-group limit when lower; casmag.memory). A solve whose
    estimate (what the process holds plus 200 bytes per Hessian non-zero, measured) is
    above it is refused while its NLP is built (MemoryBudgetError) or before IPOPT starts
    (status ``Memory_Budget_Exceeded``), and a solve that passes it is stopped (the same
    status); each says what to change.
    uncertainty_inflation: how that covariance accounts for magnetometer residuals that are
    correlated along the path (casmag.solver.uncertainty): ``long-run`` (default), the sandwich
    covariance with the residuals' long-run variance per session and component (measured
    on the real five-session problems: mean NEES 0.78-2.94 per session for an expected 2,
    against 5.2-16.7 without; factor 1 on white noise); ``correlation``, the same with
    sigma_m^2 times the autocorrelation time; ``none``, the plain Laplace covariance.
    """

    def hessian_mode(self, own: str) -> str:
        """The mode of a numpy magnetometer block: the one ``hessian`` names, else (``auto``)
        the model's ``own``."""
        return self.hessian if self.hessian in HESSIAN_MODES else own

    max_iter: Annotated[int, Field(ge=1, le=100_000)] = 200
    tol: PositiveFloat = 1.0e-6
    hessian: Literal["auto", "exact", "gauss-newton", "hybrid", "limited-memory"] = "auto"
    linear_solver: str = "mumps"
    print_level: Annotated[int, Field(ge=0, le=12)] = 0
    ipopt: dict[str, float | int | str] = {}
    warm_start: WarmStartSpec = WarmStartSpec()
    uncertainty: bool = True
    memory_budget: PositiveFloat | None = None
    uncertainty_inflation: Literal["none", "correlation", "long-run"] = "long-run"

    @field_validator("linear_solver")
    @classmethod
    def _linear_solver_available(cls, value: str) -> str:
        # Only what the casadi wheel ships (casmag.problem.ipopt.LINEAR_SOLVERS), checked by a
        # solve: another name fails every solve with Invalid_Option, or crashes IPOPT.
        from casmag.problem.ipopt import linear_solver_error

        reason = linear_solver_error(value)
        if reason is not None:
            raise ValueError(reason)
        return value

    @field_validator("ipopt", mode="before")
    @classmethod
    def _switches(cls, value: Any) -> Any:
        # YAML reads yes/no/true/false as booleans; IPOPT's switches are "yes" and "no".
        if isinstance(value, dict):
            return {
                k: ("yes" if v else "no") if isinstance(v, bool) else v for k, v in value.items()
            }
        return value

    @field_validator("ipopt")
    @classmethod
    def _ipopt_accepts(cls, value: dict[str, Any]) -> dict[str, Any]:
        # Each option as IPOPT itself checks it (name, type, range), so that a bad one is
        # refused here, naming it, instead of stopping the build or failing every solve.
        from casmag.problem.ipopt import option_error

        for name, v in value.items():
            reason = option_error(name, v)
            if reason is not None:
                raise ValidationError.from_exception_data(
                    "ipopt",
                    [
                        {
                            "type": PydanticCustomError(
                                "ipopt_option", "{reason}", {"reason": reason}
                            ),
                            "loc": (name,),
                            "input": v,
                        }
                    ],
                )
        return value


#: The motion models a problem file names in ``motion.kind`` (:func:`document_kind`).
MOTION_KINDS = ("translational", "planar", "pose", "imu")


class TranslationalMotionSpec(Strict):
    """``motion`` of a translational problem: the kind alone (a file without a ``motion``
    section is translational unless its simulation is an IMU's)."""

    kind: Literal["translational"] = "translational"


class ProblemSpec(Strict):
    seed: Annotated[int, Field(ge=0, le=2**32 - 1)]  # numpy's generators take 0 .. 2^32 - 1
    name: str | None = None
    description: str | None = None
    motion: TranslationalMotionSpec = TranslationalMotionSpec()
    simulation: SimulationSpec = SimulationSpec()
    model: ModelSpec = ModelSpec()
    solver: SolverSpec = SolverSpec()

    @model_validator(mode="after")
    def _consistent(self) -> ProblemSpec:
        gp = self.model.gp
        if self.solver.hessian in NUMPY_HESSIANS and gp.form == "exact":
            raise ValueError(
                f"solver.hessian: {self.solver.hessian} needs model.gp.form: reduced_rank or tiled"
            )
        kernel = gp.kernel or self.simulation.field.kernel
        field = self.simulation.field
        if field.dipole_depth is not None and field.dipole_depth[0] > field.dipole_depth[1]:
            raise ValueError("simulation.field.dipole_depth: [shallowest, deepest] in metres")
        if field.method == "dipoles" and field.kernel == "div_free":
            raise ValueError("simulation.field.method: dipoles gives a curl-free field")
        if field.method == "fourier" and field.kernel == "div_free":
            raise ValueError(
                "simulation.field.method: fourier supports the se and curl_free kernels"
            )
        if gp.form == "reduced_rank" and kernel == "div_free":
            raise ValueError("model.gp.kernel: div_free has no reduced-rank form (se, curl_free)")
        if "sigma_m" in self.model.estimate:
            # The field unknowns can fit every sample exactly, so 0.5 |e|^2 / sigma_m^2 +
            # 3 N log sigma_m falls without bound as sigma_m -> 0 (measured: 1e-233 after 78
            # iterations). Estimating it needs the field integrated out (paper Eq. 5).
            raise ValueError(
                "model.estimate: sigma_m cannot be estimated in the joint MAP (the field "
                "unknowns fit every sample, so the objective is unbounded as sigma_m -> 0); "
                "set model.magnetometer.sigma_m"
            )
        samples = self.simulation.trajectory.samples
        if field.method == "exact":
            need = exact_field_bytes(samples)
            have = physical_memory()
            if have is not None and need > have:
                raise ValueError(
                    f"simulation.trajectory.samples: {samples} samples with "
                    f"simulation.field.method: exact need about {_bytes(need)} for the field's "
                    f"{3 * samples} x {3 * samples} covariance, more than this machine's "
                    f"{_bytes(have)} of memory; use simulation.field.method: fourier or fewer "
                    "samples"
                )
        if gp.form == "tiled" and kernel != "curl_free":
            raise ValueError("model.gp.form: tiled needs model.gp.kernel: curl_free")
        ws = self.solver.warm_start
        if ws.strategy == "auto":  # the translational model's own default
            self.solver = self.solver.model_copy(
                update={"warm_start": ws.model_copy(update={"strategy": "none"})}
            )
        if gp.form == "tiled" and self.solver.warm_start.strategy == "sliding":
            raise ValueError(
                "solver.warm_start.strategy: sliding carries the reduced-rank map "
                "(model.gp.form: reduced_rank), not the tiled one"
            )
        if gp.form != "exact" and {"sigma_f", "lengthscale"} & set(self.model.estimate):
            # Weights the data leave free drive 0.5 w^2 / S + 0.5 log S to -inf as S -> 0:
            # the joint MAP over weights and hyperparameters is unbounded.
            raise ValueError(
                "model.estimate: sigma_f and lengthscale cannot be estimated with the reduced-rank "
                "map yet (the joint MAP over weights and hyperparameters is unbounded); use "
                "model.gp.form: exact, or give their values (casmag slam estimates them "
                "beforehand by the windowed marginal likelihood)"
            )
        return self


def exact_field_bytes(samples: int) -> int:
    """Memory [bytes] the exact field draw (casmag.data.simulate.draw_field) holds at once: the
    3N x 3N covariance, its jittered copy and its Cholesky factor, float64."""
    return 3 * 8 * (3 * samples) ** 2


def physical_memory() -> int | None:
    """This machine's physical memory [bytes] (None where the system does not say)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):
        return None


def _bytes(n: float) -> str:
    for unit in ("bytes", "kB", "MB", "GB", "TB"):
        if n < 1000 or unit == "TB":
            return f"{n:.0f} {unit}" if unit == "bytes" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} TB"  # pragma: no cover


# --------------------------------------------------------------------------- resolved values
def problem_name(name: str | None, source: str, default: str) -> str:
    """A problem's name: its ``name`` key, else its file's stem, else ``default`` (a
    problem built in Python)."""
    if name:
        return name
    return Path(source).stem if source != "<dict>" else default


@dataclass(frozen=True)
class Problem:
    """A validated problem: the spec plus where it came from.

    The ``assumed_*`` properties resolve model settings left ``null`` to the truth.
    """

    spec: ProblemSpec
    source: str = "<dict>"

    @property
    def name(self) -> str:
        return problem_name(self.spec.name, self.source, "problem")

    @property
    def assumed_kernel(self) -> str:
        return self.spec.model.gp.kernel or self.spec.simulation.field.kernel

    @property
    def assumed_sigma_f(self) -> float:
        return self.spec.model.gp.sigma_f or self.spec.simulation.field.sigma_f

    @property
    def assumed_lengthscale(self) -> float:
        return self.spec.model.gp.lengthscale or self.spec.simulation.field.lengthscale

    @property
    def assumed_sigma_m(self) -> float:
        return self._resolve(
            self.spec.model.magnetometer.sigma_m,
            self.spec.simulation.magnetometer.noise,
            "model.magnetometer.sigma_m",
        )

    @property
    def assumed_hyperparameters(self) -> dict[str, float]:
        """The GP hyperparameters the model assumes, by name (casmag.model.translational's
        HYPERPARAMETERS): sigma_f, lengthscale, sigma_m."""
        return {
            "sigma_f": self.assumed_sigma_f,
            "lengthscale": self.assumed_lengthscale,
            "sigma_m": self.assumed_sigma_m,
        }

    @property
    def assumed_sigma_odometry(self) -> float:
        return self._resolve(
            self.spec.model.odometry.sigma,
            self.spec.simulation.odometry.noise,
            "model.odometry.sigma",
        )

    def _resolve(self, value: float | None, truth: float, field: str) -> float:
        if value is not None:
            return value
        if truth <= 0:
            raise ProblemError(
                self.source,
                field,
                "must be set when the simulated noise is 0 (cannot default to it)",
            )
        return truth

    def with_overrides(self, overrides: str | Iterable[str] | Mapping[str, Any]) -> Problem:
        """A new problem with ``key.path=value`` overrides applied and re-validated."""
        data = self.spec.model_dump(mode="python", exclude_unset=False)
        return load_problem(data, overrides, source=self.source)


# --------------------------------------------------------------------------- loading
class _Loader(yaml.SafeLoader):
    """SafeLoader that also reads exponent floats without a dot (1e-3) as numbers."""


class DuplicateKeyError(yaml.YAMLError):
    """A mapping gives the same key twice; ``path`` is the dotted key, ``line`` (1-based)
    where it is repeated and ``first`` where it was given first."""

    def __init__(self, path: str, line: int, first: int):
        self.path, self.line, self.first = path, line, first
        super().__init__(f"duplicate key {path!r} on line {line} (first on line {first})")


class YAMLInputError(yaml.YAMLError):
    """YAML that parses but that casmag will not take (too deep, too large, a number Python
    will not convert); ``problem`` says why, ``problem_mark`` where (None: the document)."""

    def __init__(self, problem: str, mark: Any = None):
        self.problem, self.problem_mark = problem, mark
        super().__init__(problem)


#: Nesting and size a problem file may have: far beyond any real one (a few levels, a few
#: hundred values), well within what the parser's recursion and memory allow. Aliases
#: count as often as they are used (a few nested aliases can stand for billions of values).
MAX_YAML_DEPTH = 64
MAX_YAML_VALUES = 100_000


def _check_document(root: yaml.Node) -> None:
    """Check a composed YAML document: a key given twice in a mapping (YAML keeps the last
    silently, so a setting would be dropped without a word) raises DuplicateKeyError;
    nesting deeper than MAX_YAML_DEPTH, more than MAX_YAML_VALUES values with aliases
    expanded, or an alias inside its own anchor raise YAMLInputError."""
    sizes: dict[int, int] = {}
    open_nodes: set[int] = set()
    stack: list[tuple[yaml.Node, tuple[str, ...], int, bool]] = [(root, (), 0, False)]
    while stack:
        node, path, depth, closing = stack.pop()
        children: list[yaml.Node] = []
        if isinstance(node, yaml.MappingNode):
            children = [n for pair in node.value for n in pair]
        elif isinstance(node, yaml.SequenceNode):
            children = list(node.value)
        if closing:
            open_nodes.discard(id(node))
            sizes[id(node)] = 1 + sum(sizes.get(id(c), 1) for c in children)
            if sizes[id(node)] > MAX_YAML_VALUES:
                raise YAMLInputError(
                    f"more than {MAX_YAML_VALUES} values (with aliases expanded)", node.start_mark
                )
            continue
        if id(node) in open_nodes:
            raise YAMLInputError("an alias refers to a node that contains it", node.start_mark)
        if id(node) in sizes:  # an alias of a node already checked
            continue
        if depth > MAX_YAML_DEPTH:
            raise YAMLInputError(f"nested deeper than {MAX_YAML_DEPTH} levels", node.start_mark)
        open_nodes.add(id(node))
        stack.append((node, path, depth, True))
        if isinstance(node, yaml.MappingNode):
            seen: dict[tuple[str, str], int] = {}
            for key, value in node.value:
                here = path
                if isinstance(key, yaml.ScalarNode) and key.tag != "tag:yaml.org,2002:merge":
                    here = (*path, key.value)
                    ident = (key.tag, key.value)
                    line = key.start_mark.line + 1
                    if ident in seen:
                        raise DuplicateKeyError(".".join(here), line, seen[ident])
                    seen[ident] = line
                stack.append((key, path, depth + 1, False))
                stack.append((value, here, depth + 1, False))
        elif isinstance(node, yaml.SequenceNode):
            for i, item in enumerate(node.value):
                stack.append((item, (*path, str(i)), depth + 1, False))


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(
        r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
        |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
        |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
        |[-+]?\.(?:inf|Inf|INF)
        |\.(?:nan|NaN|NAN))$""",
        re.X,
    ),
    list("-+0123456789."),
)


def _yaml(text: str) -> Any:
    """Parse YAML text (casmag's loader); a key given twice in a mapping raises
    DuplicateKeyError, a document casmag will not take YAMLInputError (_check_document;
    also a number Python will not convert)."""
    loader = _Loader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        _check_document(node)
        return loader.construct_document(node)
    except RecursionError:
        raise YAMLInputError(f"nested deeper than {MAX_YAML_DEPTH} levels") from None
    except ValueError as exc:  # e.g. an integer of more digits than Python converts
        reason = str(exc).splitlines()[0] if str(exc) else "a value cannot be read"
        if "integer string conversion" in reason:
            reason = (
                f"an integer has more digits than Python converts ({sys.get_int_max_str_digits()})"
            )
        raise YAMLInputError(reason) from None
    finally:
        loader.dispose()


#: Parts of a pydantic error location that name the member of a union (``float`` in
#: ``solver.ipopt.mu_init.float``), not a key.
_UNION_TAG = re.compile(
    r"(float|int|str|bool|none|(literal|list|dict|function-\w+|constrained-\w+|is-instance)\[.*\])"
)


def _is_key(i: int, part: Any) -> bool:
    """Whether a location part names a key or an index, not a union member's type tag."""
    if i == 0 or isinstance(part, int):
        return True
    text = str(part)  # no casmag key holds any of "-[]'(" (constrained-float, literal[...])
    return not (_UNION_TAG.fullmatch(text) or any(ch in text for ch in "-[]'("))


def validation_error(
    source: str, err: ValidationError, schema: type[BaseModel] | None = None
) -> ProblemError:
    """One ProblemError for a pydantic ValidationError of any casmag document: the source,
    the dotted key (without union members' type tags) and the reason. A value that fits
    none of a union's forms gets what each form wanted; a whole-file check (no location)
    names the key its message starts with. With the document's ``schema``, an unknown key
    gets the known key it most likely means (:func:`key_suggestion`)."""
    errors = err.errors()
    first = errors[0]
    loc = tuple(part for i, part in enumerate(first["loc"]) if _is_key(i, part))
    where = ".".join(str(part) for part in loc)
    if first["type"] == "extra_forbidden":
        found = key_suggestion(schema, where, first.get("input")) if schema else None
        if found is None:
            return ProblemError(source, where, "unknown key")
        return ProblemError(source, found[0], f"unknown key (did you mean {found[1]!r}?)")
    if first["type"] == "missing":
        return ProblemError(source, where, "required key is missing")
    if not loc:
        # A whole-file consistency check: its message starts with the key it is about, and
        # the input (the whole file) is not repeated.
        msg = first["msg"].removeprefix("Value error, ")
        key, sep, reason = msg.partition(": ")
        if sep and key and " " not in key:
            return ProblemError(source, key, reason)
        return ProblemError(source, "", msg)
    msgs: list[str] = []
    for e in errors:
        if tuple(part for i, part in enumerate(e["loc"]) if _is_key(i, part)) == loc:
            m = e["msg"].removeprefix("Value error, ")
            if m not in msgs:
                msgs.append(m)
    value = first.get("input")
    if isinstance(value, Mapping):  # a section's own check: its message names the keys
        return ProblemError(source, where, " or ".join(msgs))
    return ProblemError(source, where, f"{' or '.join(msgs)} (got {_short_repr(value)})")


def schema_keys(schema: type[BaseModel], prefix: str = "") -> list[str]:
    """Every dotted key of a document schema, sections and their keys."""
    keys = []
    for name, info in schema.model_fields.items():
        key = f"{prefix}{info.alias or name}"
        keys.append(key)
        for sub in _models_in(info.annotation):
            keys.extend(schema_keys(sub, key + "."))
    return sorted(set(keys))


def _models_in(annotation: Any) -> list[type[BaseModel]]:
    """The pydantic models an annotation holds (through Optional, unions, Annotated)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    return [m for arg in getattr(annotation, "__args__", ()) for m in _models_in(arg)]


def key_suggestion(schema: type[BaseModel], key: str, value: Any = None) -> tuple[str, str] | None:
    """(the key as the user wrote it, the known key it most likely means) for an unknown
    dotted ``key``: a close name in the same section (difflib ratio 0.75 or more), else in
    one of its sections (``model.gp.lengthscale`` for ``model.lenghtscale``); for an
    unknown section holding one key (``value``), that key looked up as below; else the key
    elsewhere whose last part is the same name, in the same top-level section when there
    are several (``model.gp.lengthscale`` for ``model.lengthscale`` in a schema with
    ``model.gp``). None when there is no such key."""
    known = schema_keys(schema)
    parent, _, name = key.rpartition(".")
    siblings = [k.rpartition(".")[2] for k in known if k.rpartition(".")[0] == parent]
    close = difflib.get_close_matches(name, siblings, n=1, cutoff=0.75)
    if close and close[0] != name:
        return key, f"{parent}.{close[0]}" if parent else close[0]
    below = {
        k.rpartition(".")[2]: k
        for k in known
        if k.count(".") == key.count(".") + 1 and k.startswith(f"{parent}.")
    }
    close = difflib.get_close_matches(name, list(below), n=1, cutoff=0.75)
    if close and close[0] != name:
        return key, below[close[0]]
    if isinstance(value, Mapping) and len(value) == 1:
        inner = f"{key}.{next(iter(value))}"
        found = key_suggestion(schema, inner)
        return found if found is not None and found[1].count(".") < inner.count(".") else None
    same = [k for k in known if k.rpartition(".")[2] == name and k != key]
    if len(same) > 1:
        same = [k for k in same if k.split(".")[0] == key.split(".")[0]]
    return (key, same[0]) if len(same) == 1 else None


def _short_repr(value: Any, limit: int = 200) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def parse_override(text: str, source: str = "--set") -> tuple[list[str], Any]:
    """Split ``a.b.c=value`` into the key path and the YAML-parsed value."""
    if "=" not in text:
        raise ProblemError(source, text, "override must look like key.path=value")
    key, raw = text.split("=", 1)
    key = key.strip()
    if not key or any(not part for part in key.split(".")):
        raise ProblemError(source, key or text, "empty key in override")
    try:
        value = _yaml(raw) if raw.strip() else None
    except DuplicateKeyError as exc:
        raise ProblemError(source, key, f"value gives the key {exc.path!r} twice") from None
    except yaml.YAMLError as exc:
        reason = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ProblemError(source, key, f"value is not valid YAML: {reason}") from None
    return key.split("."), value


def section_overrides(sections: Mapping[str, Any]) -> list[str]:
    """Settings given as nested sections, ``model={"gp": {"lengthscale": 0.3}}, seed=7``,
    as ``key.path=value`` overrides (one per leaf; a list is a value)."""

    def leaves(prefix: str, value: Any) -> list[tuple[str, Any]]:
        if isinstance(value, Mapping) and value:
            return [kv for k, v in value.items() for kv in leaves(f"{prefix}.{k}", v)]
        return [(prefix, value)]

    return as_overrides(dict(kv for k, v in sections.items() for kv in leaves(k, v)))


def as_overrides(
    overrides: str | Iterable[str] | Mapping[str, Any] | None,
) -> list[str]:
    """Overrides as a list of ``key.path=value`` strings: one string is one override (not
    its characters); a mapping ``{"model.gp.sigma_f": 1.0, ...}`` gives one per key, its
    value as JSON (which YAML reads back as the same value); None is none. Raises TypeError
    for anything else."""
    if overrides is None:
        return []
    if isinstance(overrides, str):
        return [overrides]
    if isinstance(overrides, Mapping):
        for key in overrides:
            if not isinstance(key, str):
                raise TypeError(f"override keys must be 'key.path' strings, got {key!r}")
        return [f"{k}={json.dumps(v)}" for k, v in overrides.items()]
    if isinstance(overrides, (bytes, bytearray)) or not isinstance(overrides, Iterable):
        raise TypeError(
            "overrides must be a 'key.path=value' string, a list of them or a mapping "
            f"{{'key.path': value}}, not {type(overrides).__name__}"
        )
    items = list(overrides)
    for item in items:
        if not isinstance(item, str):
            raise TypeError(
                f"overrides must be 'key.path=value' strings, got {type(item).__name__} {item!r}"
            )
    return items


def apply_overrides(
    data: dict[str, Any], overrides: str | Iterable[str] | Mapping[str, Any], source: str
) -> dict[str, Any]:
    """Apply ``key.path=value`` overrides to a nested dictionary (copied)."""
    data = copy.deepcopy(data)
    for text in as_overrides(overrides):
        path, value = parse_override(text)
        node = data
        for i, part in enumerate(path[:-1]):
            child = node.get(part)
            if child is None:
                child = node[part] = {}
            elif not isinstance(child, dict):
                where = ".".join(path[: i + 1])
                raise ProblemError(source, where, f"is a value, cannot set {'.'.join(path)}")
            node = child
        node[path[-1]] = value
    return data


#: The kinds of casmag document (:func:`document_kind`).
DOCUMENT_KINDS = ("translational", "imu", "oriented", "recording", "table")


def document_kind(data: Mapping[str, Any]) -> str:
    """Which casmag document a problem file's top-level mapping is, from its keys:
    ``table`` (``rows``: rows of overrides of a problem file, ``casmag sweep``),
    ``recording`` (``recording`` or ``sessions``: real data, casmag.experiments.realbench);
    else the motion model ``motion.kind`` names (:data:`MOTION_KINDS`): ``translational``
    (casmag.problem.spec), ``imu`` (casmag.problem.imu), ``oriented`` for planar and pose
    (casmag.problem.oriented, which also names a kind it does not know). A file without
    ``motion`` is ``imu`` when it has ``simulation.scenario`` or ``simulation.imu`` and
    ``translational`` otherwise. The file's own schema then names any bad key."""
    if "rows" in data:
        return "table"
    if "recording" in data or "sessions" in data:
        return "recording"
    motion = data.get("motion")
    kind = motion.get("kind") if isinstance(motion, Mapping) else None
    if kind in ("translational", "imu"):
        return str(kind)
    if "motion" in data:
        return "oriented"
    simulation = data.get("simulation")
    if isinstance(simulation, Mapping) and ("scenario" in simulation or "imu" in simulation):
        return "imu"
    return "translational"


def read_yaml(path: Path) -> dict[str, Any]:
    """Read a YAML mapping, turning I/O and syntax errors into one-line ProblemErrors."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ProblemError(str(path), "", f"cannot read file ({exc.strerror})") from None
    except UnicodeDecodeError as exc:
        raise ProblemError(
            str(path), "", f"not UTF-8 text (byte {exc.start}: {exc.reason}); save it as UTF-8"
        ) from None
    try:
        data = _yaml(text)
    except DuplicateKeyError as exc:
        raise ProblemError(
            str(path), exc.path, f"duplicate key on line {exc.line} (first on line {exc.first})"
        ) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}" if mark is not None else ""
        raise ProblemError(
            str(path), where, f"invalid YAML: {getattr(exc, 'problem', exc)}"
        ) from None
    if not isinstance(data, dict):
        raise ProblemError(str(path), "", "top level must be a mapping of keys to values")
    return data


SpecT = TypeVar("SpecT", bound=BaseModel)


def validate_spec(
    spec_class: type[SpecT],
    problem: str | Path | Mapping[str, Any],
    overrides: str | Iterable[str] | Mapping[str, Any] = (),
    source: str | None = None,
    to_error: Callable[[str, ValidationError], ProblemError] | None = None,
) -> tuple[SpecT, str]:
    """Read a YAML path (or take a dictionary), apply ``key.path=value`` overrides and
    validate against ``spec_class``. Returns the spec and its source name; raises
    ProblemError naming the file, the key and the reason (worded by ``to_error``)."""
    overrides = as_overrides(overrides)
    if isinstance(problem, Mapping):
        data, src = dict(problem), source or "<dict>"
    elif isinstance(problem, (str, os.PathLike)):
        path = Path(problem)
        data, src = read_yaml(path), source or str(path)
    else:
        raise TypeError(f"a problem is a YAML path or a dictionary, not {type(problem).__name__}")
    data = apply_overrides(data, overrides, src)
    try:
        return spec_class.model_validate(data), src
    except ValidationError as err:
        if to_error is not None:
            raise to_error(src, err) from None
        raise validation_error(src, err, spec_class) from None


def load_problem(
    problem: str | Path | Mapping[str, Any] | Problem | ProblemSpec,
    overrides: str | Iterable[str] | Mapping[str, Any] = (),
    source: str | None = None,
    **sections: Any,
) -> Problem:
    """Load and validate a problem from a YAML path, a dictionary, a Problem or a typed
    :class:`ProblemSpec` (built in Python, e.g. ``ProblemSpec(seed=3, model=ModelSpec(
    gp=GPSpec(form="reduced_rank")))``).

    overrides: ``key.path=value`` strings (values parsed as YAML), or a mapping
    ``{"key.path": value}``, applied before validation; one string is one override.
    sections: the same as keyword arguments, e.g. ``seed=7, model={"gp": {"sigma_f": 1.0}}``
    (:func:`section_overrides`), applied after ``overrides``. Raises ProblemError naming
    the file, the key and the reason (TypeError for overrides of another type).
    """
    overrides = [*as_overrides(overrides), *section_overrides(sections)]
    if isinstance(problem, ProblemSpec):
        problem = Problem(spec=problem, source=source or "<spec>")
    if isinstance(problem, Problem):
        return problem.with_overrides(overrides) if overrides else problem
    spec, src = validate_spec(ProblemSpec, problem, overrides, source)
    problem_obj = Problem(spec=spec, source=src)
    # Resolve defaults that can fail now, before anything is built.
    problem_obj.assumed_sigma_m  # noqa: B018
    problem_obj.assumed_sigma_odometry  # noqa: B018
    return problem_obj
