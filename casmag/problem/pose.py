"""Settings of the pose-odometry model (casmag.model.pose) for ``casmag slam`` on a recording
with ``dpx,dpy,dpz,dqw,dqx,dqy,dqz`` columns: a problem file's ``model`` and ``solver``
sections, or ``--set model.KEY=VALUE``."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field, model_validator

from casmag.problem.imu import (
    PLANAR_SOLVER_DEFAULTS,
    RecordingGPSpec,
    RecordingMagnetometerSpec,
    StartsSpec,
    flat_options,
    load_recording_spec,
    nest_field_keys,
)
from casmag.problem.spec import PositiveFloat, SolverSpec, Strict

#: Solver settings of pose recordings that differ from SolverSpec's defaults: those of the
#: planar recordings (growing prefixes of 150, 300, ... samples on long recordings).
POSE_SOLVER_DEFAULTS: dict[str, Any] = PLANAR_SOLVER_DEFAULTS


class PoseGPSpec(RecordingGPSpec):
    """The pose model's map (``model.gp``): :class:`~casmag.problem.imu.RecordingGPSpec`
    with the curl-free kernel by default."""

    kernel: Literal["se", "curl_free"] = "curl_free"


class PoseModelSpec(StartsSpec):
    """The pose-odometry model: the fields of :class:`PoseOptions` (metres, radians,
    seconds; field units of the recording), the map's in ``gp`` (:class:`PoseGPSpec`) and
    the magnetometer's noise in ``magnetometer``."""

    sigma_p: PositiveFloat = 0.01
    sigma_r: PositiveFloat = 0.002
    estimate_bias_p: bool = False
    estimate_bias_w: bool = True
    bias_p_prior: PositiveFloat = 0.01
    bias_w_prior: PositiveFloat = 0.05
    gp: PoseGPSpec = PoseGPSpec()
    magnetometer: RecordingMagnetometerSpec = RecordingMagnetometerSpec()
    map_dim: Literal["auto", 2, 3] = "auto"
    height_sigma: PositiveFloat | None = 0.2
    sigma_anchor: PositiveFloat = 1.0e-3
    sigma_att0: PositiveFloat = 1.0e-3
    curvature: Literal["hybrid", "exact", "gauss-newton"] = "hybrid"
    displacement_bias: Annotated[float, Field(ge=0.0, le=0.5)] = 0.01

    _nest = model_validator(mode="before")(nest_field_keys)


class PoseSpec(Strict):
    """A problem file for a pose recording: ``model`` (:class:`PoseModelSpec`) and
    ``solver`` (IPOPT; defaults :data:`POSE_SOLVER_DEFAULTS`)."""

    model: PoseModelSpec = PoseModelSpec()
    solver: SolverSpec = SolverSpec(**POSE_SOLVER_DEFAULTS)


@dataclass(frozen=True)
class PoseOptions:
    """Settings of the pose-odometry problem (defaults in brackets).

    sigma_p: displacement noise per step and axis [m] [0.01]; sigma_r: rotation increment
    noise per step and axis [rad] [0.002].

    estimate_bias_p: estimate a constant body-frame displacement bias [m per step] [false]:
    for a platform that moves forwards at a steady speed it is a scale factor of the whole
    path, which the magnetometer cannot see (a map stretched with the path fits the same
    samples), and the GP prior of a stretched map is lower: on the bench's walk (seed 1)
    the estimate stretched the path by 16 % (RMSE 3.59 m from 0.41 m), the same from the
    truth; estimate_bias_w: estimate a constant rotation-rate bias [rad/s] [true];
    bias_p_prior [0.01], bias_w_prior [0.05, the planar model's]: their zero-mean priors;
    displacement_bias: when the displacement bias is not estimated, the standard deviation
    per body axis the position covariance allows for it, a fraction of the median step
    (taken in as a consider parameter, as the planar model's; 0: none) [0.01].

    sigma_m, sigma_f, lengthscale: values or ``estimate`` (windowed marginal likelihood on
    the dead-reckoned path, the magnetometer turned into the map frame by the dead-reckoned
    orientation) [estimate]; kernel [curl_free: the field is the gradient of a potential];
    sigma_lin: constant-field prior (None: from the data); num_basis, margin: reduced-rank
    basis; curvature: Hessian mode of the magnetometer block (casmag.model.rotated) under
    ``solver.hessian: auto`` (another value there chooses instead) [hybrid]; form: the map,
    ``reduced_rank`` (one box around the dead reckoning) or ``tiled`` (casmag.gp.tiles:
    tiles only where the path goes, each sample touching the 2^map_dim around it; kernel
    ``curl_free``; its Hessian ``hybrid`` whatever ``curvature`` says) or ``auto``
    (chosen once the lengthscale is known, casmag.model.mapchoice; ``casmag slam``'s
    default) [reduced_rank]; tile_basis: the tiles' basis (None:
    casmag.model.tiledmap.TILE_BASIS); bump_spacing: the bumps' lattice in lengthscales
    (None: from the field's strength, casmag.model.tiledmap.bump_spacing).

    map_dim: 3, 2 (the field a function of x and y only: motion near a plane) or ``auto``
    (2 when the dead reckoning's height varies by less than one lengthscale over stretches
    of a few lengthscales of travel: casmag.solver.pose.choose_map_dim) [auto];
    height_sigma [m]: with a planar map, a prior on every sample's height about the first's
    (the magnetometer cannot see height; the hand-held ARKit recordings' heights have
    standard deviations 0.04 and 0.16 m), None: none [0.2]; sigma_anchor [m], sigma_att0
    [rad]: priors on the known first pose [1e-3 each]; starts: number of starts (odd: the
    dead reckoning and pairs with +-heading-rate biases removed about the vertical,
    casmag.strapdown.turn_heading, each running ``solver.warm_start``'s strategy, the lowest
    MAP cost kept) [1]; start_heading_deg: the heading the first pair's bias turns over the
    recording [10]; solver: IPOPT settings."""

    sigma_p: float = 0.01
    sigma_r: float = 0.002
    estimate_bias_p: bool = False
    estimate_bias_w: bool = True
    bias_p_prior: float = 0.01
    bias_w_prior: float = 0.05
    sigma_m: float | str = "estimate"
    kernel: str = "curl_free"
    sigma_f: float | str = "estimate"
    lengthscale: float | str = "estimate"
    sigma_lin: float | None = None
    num_basis: int | None = None
    margin: float | None = None
    tile_basis: str | None = None
    bump_spacing: float | None = None
    map_dim: int | str = "auto"
    height_sigma: float | None = 0.2
    sigma_anchor: float = 1e-3
    sigma_att0: float = 1e-3
    curvature: str = "hybrid"
    displacement_bias: float = 0.01
    starts: int = 1
    start_heading_deg: float = 10.0
    form: str = "reduced_rank"
    solver: SolverSpec = dataclasses.field(
        default_factory=lambda: SolverSpec(**POSE_SOLVER_DEFAULTS)
    )


def load_pose_options(
    problem: str | Path | Mapping[str, Any] | None = None,
    overrides: Iterable[str] = (),
    source: str | None = None,
) -> PoseOptions:
    """:class:`PoseOptions` from an optional problem file (its ``model`` and ``solver``
    sections) and ``key.path=value`` overrides. Raises ProblemError naming the file (or
    ``--set``), the key and the reason."""
    spec = load_recording_spec(PoseSpec, problem, overrides, source)
    return PoseOptions(**flat_options(spec.model), solver=spec.solver)
