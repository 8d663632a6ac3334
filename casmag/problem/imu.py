"""IMU problem files (``problems/imu/*.yaml``): schema, validation and loading.

A file has a top-level integer ``seed`` and the sections ``simulation`` (scenario, IMU
errors, magnetometer, physical field), ``model`` (what the MAP problem assumes) and
``solver`` (IPOPT, the same settings as translational problems). Every key is validated
before anything is built; a bad file raises :class:`~casmag.errors.ProblemError` naming the
file, the dotted key and the reason, on one line. Units are in the key names' docs: angles
in degrees, rates in deg/s, accelerations in m/s^2, field in a.u. (Earth = 1).

Model noise settings left ``null`` take the simulation's true values.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from casmag.errors import ProblemError
from casmag.problem.spec import (
    NUMPY_HESSIANS,
    SolverSpec,
    Strict,
    WarmStartSpec,
    as_overrides,
    parse_override,
    problem_name,
    read_yaml,
    validate_spec,
)

PositiveFloat = Annotated[float, Field(gt=0)]
NonNegativeFloat = Annotated[float, Field(ge=0)]
Vector3 = Annotated[list[float], Field(min_length=3, max_length=3)]

#: The letters a handwriting scenario can write: those casmag.data.imusim has strokes for.
HANDWRITING_LETTERS = "acegmnsx"


# --------------------------------------------------------------------------- scenarios
class _Motion(Strict):
    """Common to every scenario: speed [m/s] (slower in tight curves), static [s] at rest
    before and after, corner_radius [m] of the hand's rounding, attitude_deg (roll, pitch,
    yaw) of the device [deg], wobble_deg amplitudes of smooth random roll, pitch, yaw [deg]."""

    speed: PositiveFloat = 0.12
    static: NonNegativeFloat = 1.0
    corner_radius: NonNegativeFloat = 0.02
    attitude_deg: Vector3 = [0.0, 0.0, 0.0]
    wobble_deg: Vector3 = [3.0, 3.0, 8.0]


class RectangleScenario(_Motion):
    """A rectangle of ``size`` [m] (x, y) traced ``loops`` times on a plane."""

    kind: Literal["rectangle"]
    size: Annotated[list[PositiveFloat], Field(min_length=2, max_length=2)] = [0.4, 0.25]
    loops: Annotated[int, Field(ge=1, le=50)] = 4


class SpiralScenario(_Motion):
    """An Archimedean spiral out for ``turns`` turns and back in between its own turns:
    start_radius [m], pitch [m] between outward turns."""

    kind: Literal["spiral"]
    start_radius: NonNegativeFloat = 0.02
    pitch: PositiveFloat = 0.05
    turns: Annotated[float, Field(gt=0, le=30)] = 3.0


class HandwritingScenario(_Motion):
    """A word written with a pen-held device, ``passes`` times over itself: height [m] of
    one em (x-height is half), lift [m] of the pen on the way back between passes."""

    kind: Literal["handwriting"]
    speed: PositiveFloat = 0.05
    corner_radius: NonNegativeFloat = 0.003
    word: str = "casmag"
    height: PositiveFloat = 0.06
    passes: Annotated[int, Field(ge=1, le=10)] = 2
    lift: NonNegativeFloat = 0.01

    @model_validator(mode="after")
    def _letters(self) -> HandwritingScenario:
        # The letters casmag.data.imusim has strokes for (tests/solver/test_imu.py checks the two
        # agree): the problem layer checks a word before any data module is imported.

        bad = sorted(set(self.word) - set(HANDWRITING_LETTERS))
        if not self.word or bad:
            raise ValueError(
                f"word must use the letters {HANDWRITING_LETTERS!r}"
                + (f", not {''.join(bad)!r}" if bad else "")
            )
        return self


Scenario = Annotated[
    RectangleScenario | SpiralScenario | HandwritingScenario, Field(discriminator="kind")
]


class ImuSimSpec(Strict):
    """The IMU: rate [Hz]; white-noise densities gyro [deg/s/sqrt(Hz)] and acc
    [m/s^2/sqrt(Hz)]; constant biases gyro [deg/s] and acc [m/s^2]; bias random walks gyro
    [deg/s/sqrt(s)] and acc [m/s^2/sqrt(s)] (paper Eq. 2); levelling_seconds [s] at rest at
    the start whose mean specific force gives the initial roll and pitch. Defaults: an
    industrial MEMS IMU of the MTi-300 class."""

    rate: Annotated[float, Field(gt=0, le=2000)] = 100.0
    gyro_noise_density: NonNegativeFloat = 0.01
    acc_noise_density: NonNegativeFloat = 6.0e-4
    gyro_bias: Vector3 = [0.05, -0.08, 0.12]
    acc_bias: Vector3 = [0.02, -0.015, 0.03]
    gyro_bias_walk: NonNegativeFloat = 3.0e-4
    acc_bias_walk: NonNegativeFloat = 2.0e-5
    levelling_seconds: PositiveFloat = 0.5


class DipoleSpec(Strict):
    """A magnetic dipole: position [m] in the local frame, moment [a.u. m^3] (the on-axis
    field at distance r is 2 |moment| / r^3 a.u.)."""

    name: str = ""
    position: Vector3
    moment: Vector3


class FieldSimSpec(Strict):
    """The physical field: Earth's field of magnitude earth_intensity [a.u.] with the given
    inclination and declination [deg], plus dipoles."""

    earth_intensity: NonNegativeFloat = 1.0
    inclination_deg: Annotated[float, Field(ge=-90, le=90)] = 67.0
    declination_deg: Annotated[float, Field(ge=-180, le=180)] = 2.0
    dipoles: list[DipoleSpec] = []


class MagnetometerSimSpec(Strict):
    """Magnetometer white noise per component [a.u.], sampled with the IMU."""

    noise: NonNegativeFloat = 0.004


class ImuSimulationSpec(Strict):
    scenario: Scenario
    imu: ImuSimSpec = ImuSimSpec()
    magnetometer: MagnetometerSimSpec = MagnetometerSimSpec()
    field: FieldSimSpec = FieldSimSpec()


# --------------------------------------------------------------------------- model
class ImuModelSpec(Strict):
    """IMU noise the model assumes (null: the simulation's), in the simulation's units.

    bias: ``random_walk`` (a bias per keyframe, Eq. 2) or ``constant`` (one per run).
    gyro_bias_prior [deg/s], acc_bias_prior [m/s^2]: standard deviation of a zero-mean prior
    on the initial biases. Bias random-walk strengths cannot be estimated in the joint MAP
    (0.5 |db|^2 / s^2 + n log s falls without bound as the walk flattens and s -> 0): set them.
    """

    gyro_noise_density: PositiveFloat | None = None
    acc_noise_density: PositiveFloat | None = None
    gyro_bias_walk: PositiveFloat | None = None
    acc_bias_walk: PositiveFloat | None = None
    bias: Literal["random_walk", "constant"] = "random_walk"
    gyro_bias_prior: PositiveFloat = 0.5
    acc_bias_prior: PositiveFloat = 0.1


class InitialStateSpec(Strict):
    """Priors on the first keyframe: position [m] and velocity [m/s] standard deviations
    (known start, at rest), tilt and heading [deg] about the levelled initial attitude (the
    heading defines the local frame)."""

    position_sigma: PositiveFloat = 1.0e-4
    velocity_sigma: PositiveFloat = 1.0e-3
    tilt_sigma_deg: PositiveFloat = 1.0
    yaw_sigma_deg: PositiveFloat = 0.01


class ZeroPositionSpec(Strict):
    """Weak zero-position update (the paper's "within a one metre sphere"): every keyframe
    position gets a prior N(centre, sigma^2 I) [m]; null switches it off. centre: ``start``
    (the known first position) or ``free`` (an unknown centre, estimated)."""

    sigma: PositiveFloat | None = 1.0
    centre: Literal["start", "free"] = "start"


#: Keyframes per marginal-likelihood window and the most windows used (``casmag.gp.hyper``):
#: the defaults of ``model.gp.hyper_window`` and ``hyper_windows``.
HYPER_WINDOW = 30
HYPER_WINDOWS = 16
#: Seconds of keyframes per window of the re-estimate on short windows
#: (``model.gp.drift_ratio``).
HYPER_SECONDS = 2.0


class ImuGPSpec(Strict):
    """The field map. The measurements behind these defaults are in
    ``problems/imu/README.md`` (section "Measurements behind the map settings").

    form: ``reduced_rank`` (Hilbert-space basis on a 3-D box around the IMU-only
    trajectory), ``exact`` (dense GP over the keyframes; a few hundred at most), or ``none``
    (no magnetometer: the IMU-only adjustment). sigma_f, lengthscale [m]: a value, or
    ``estimate`` for the windowed marginal likelihood (paper Eq. 5) on the IMU-only
    trajectory with the magnetometer rotated into the local frame. sigma_lin: prior standard
    deviation of a constant field [a.u.] (Earth's). num_basis, margin [m]: as for
    translational problems (null: frequencies up to 5 / l, at most max_num_basis, margin
    3 l); an iteration costs about keyframes x num_basis^2. max_lengthscale [m]: upper limit
    on an estimated lengthscale.

    curvature (true, false or auto): the magnetometer's second-order terms in orientation
    and position-weight on top of its Gauss-Newton Hessian
    (``casmag.model.rotated.RotatedFieldGaussNewton``): true always (``exact``), false never
    (``gauss-newton``); ``auto``: always when the field varies little (sigma_f / l below 5
    sigma_m for curl-free, sigma_f below 5 sigma_m for se); otherwise ``hybrid``:
    Gauss-Newton while the magnetometer cost falls fast and the exact terms once it falls by
    less than 1 % between iterations. It chooses under ``solver.hessian: auto``;
    ``exact``, ``hybrid`` or ``gauss-newton`` there choose instead.

    anneal: factors on sigma_m of successive GP-SLAM passes, each starting from the previous
    one (a softer magnetometer first widens the basin of the global optimum).

    homogeneous: what to do when the field turns out to carry no position information
    (``casmag.solver.imu.field_evidence``: the windowed marginal likelihood of a field with
    spatial structure does not beat a constant field by the BIC penalty of its two extra
    hyperparameters). ``imu_only`` (default): the result is the IMU-only adjustment (the
    GP-SLAM pass is still reported, as ``gp_slam_map``); ``keep``: the GP-SLAM estimate.
    The check runs only when sigma_f or the lengthscale is ``estimate``, first on the
    IMU-only path (no map is solved when the field is homogeneous already there), then on
    the last GP-SLAM pass's path.

    refine: further GP-SLAM passes, each with the hyperparameters re-estimated on the
    previous pass's trajectory (only when some are ``estimate``).

    grow: null (default) or increasing fractions in (0, 1] ending in 1, e.g. [0.25, 0.5,
    0.75, 1]: the first GP-SLAM pass is solved on growing prefixes of the keyframes (the
    first round(f K)), each started from the previous prefix's solution and, for its new
    keyframes, the IMU-only trajectory continued from the previous prefix's last state
    (positions and velocities shifted to join it, orientations turned by its orientation
    correction, biases its last ones); the map basis is that of the full problem, so the map
    weights carry over. Each stage's keyframes, iterations, status and seconds are recorded
    under ``grow`` in the pass's record in the result's ``stages``; a stage before the last that
    stops at the iteration limit still starts the next, any other failure stops the
    pipeline with its IPOPT status. grow_anneal: with grow, run the whole anneal schedule on
    every prefix before growing it (one GP-SLAM pass, whose ``grow`` lists every solve).

    coarse_to_fine: lengthscale factors of a second GP-SLAM schedule (null: none), each a
    pass from the previous one (the first from the start: the IMU-only adjustment, with its
    loops closed when there are closures) with the lengthscale
    and sigma_m both scaled by the factor (sigma_f so that the field's variance stays the
    estimated one); the last factor must be 1, so that both schedules end with the same
    hyperparameters and sigma_m. It runs when the anneal schedule's final solve failed or
    its MAP cost per magnetometer component (``misfit``) is above ``refit_misfit`` (0: run
    both always), and is kept when its final MAP cost is lower by more than
    ``casmag.solver.imu.SCHEDULE_MARGIN``; both are recorded under ``details.schedules``.

    fallback_grow: prefix fractions of a third schedule (null: none), run when the
    schedule kept so far failed or fits clearly badly (misfit above
    ``casmag.solver.imu.GROW_MISFIT``): the anneal factors on each growing prefix (as ``grow``
    with ``grow_anneal``), from the same start, kept by the same rule.

    closures: true (default) or false: before GP-SLAM, find the places the path returns
    to by the field's signature along it (``casmag.solver.closures``) and, when there are
    any, start every schedule from the IMU-only adjustment with those pairs pulled together
    (``closure`` block); GP-SLAM itself does not carry them. Recorded under
    ``details.closures``.

    hyper_window, hyper_windows: keyframes per window of the windowed marginal likelihood
    (``estimate``, and the field check) and the most windows, evenly spread (``all``: every
    whole window, K // hyper_window). drift_ratio: null (default) or a ratio: when the
    estimate's magnetometer noise exceeds this many times the assumed keyframe noise
    (sigma_m / sqrt(samples)), the hyperparameters are estimated again on windows of
    ``HYPER_SECONDS`` of keyframes (at least 3), all of them, and those are used, for the
    field check too.
    """

    form: Literal["reduced_rank", "exact", "none"] = "reduced_rank"
    kernel: Literal["se", "curl_free"] = "curl_free"
    sigma_f: PositiveFloat | Literal["estimate"] = "estimate"
    lengthscale: PositiveFloat | Literal["estimate"] = "estimate"
    sigma_lin: PositiveFloat = 2.0
    num_basis: Annotated[int, Field(ge=1, le=5000)] | None = None
    margin: PositiveFloat | None = None
    jitter: Annotated[float, Field(ge=0, le=1)] = 1.0e-6
    max_lengthscale: PositiveFloat = 5.0
    curvature: bool | Literal["auto"] = "auto"
    refine: Annotated[int, Field(ge=0, le=5)] = 0
    anneal: Annotated[list[PositiveFloat], Field(min_length=1, max_length=6)] = [4.0, 1.0]
    max_num_basis: Annotated[int, Field(ge=1, le=5000)] = 900
    homogeneous: Literal["imu_only", "keep"] = "imu_only"
    grow: Annotated[list[float], Field(min_length=1, max_length=10)] | None = None
    grow_anneal: bool = False
    fallback_grow: Annotated[list[float], Field(min_length=1, max_length=10)] | None = [
        0.125, 0.25, 0.375, 0.5, 0.625, 0.75, 0.875, 1.0,
    ]  # fmt: skip
    coarse_to_fine: Annotated[list[PositiveFloat], Field(min_length=1, max_length=6)] | None = [
        4.0,
        2.0,
        1.0,
    ]
    refit_misfit: Annotated[float, Field(ge=0.0, le=1.0e6)] = 0.55
    closures: bool = True
    hyper_window: Annotated[int, Field(ge=3, le=10000)] = HYPER_WINDOW
    hyper_windows: Annotated[int, Field(ge=1, le=10000)] | Literal["all"] = HYPER_WINDOWS
    drift_ratio: Annotated[float, Field(gt=1.0, le=1.0e6)] | None = None

    @field_validator("sigma_f", "lengthscale", mode="before")
    @classmethod
    def _no_true_value(cls, v: Any) -> Any:
        if v is None:
            raise ValueError(
                "null means the simulation's true value, and an IMU simulation's field "
                "(Earth's and dipoles') has no GP hyperparameters: give a number or estimate"
            )
        return v

    @field_validator("coarse_to_fine")
    @classmethod
    def _coarse_to_fine_ends_at_one(cls, v: list[float] | None) -> list[float] | None:
        if v is not None and v[-1] != 1.0:
            raise ValueError("the last factor must be 1")
        return v

    @field_validator("grow", "fallback_grow")
    @classmethod
    def _grow_fractions(cls, v: list[float] | None) -> list[float] | None:
        if v is None:
            return v
        if any(not 0.0 < f <= 1.0 for f in v):
            raise ValueError("fractions must be in (0, 1]")
        if any(b <= a for a, b in itertools.pairwise(v)):
            raise ValueError("fractions must be increasing")
        if v[-1] != 1.0:
            raise ValueError("the last fraction must be 1")
        return v


class MagnetometerModelSpec(Strict):
    """Magnetometer noise sigma_m [a.u.] the model assumes per sample (null: truth), and
    ``samples``: how many consecutive magnetometer samples (odd) make one keyframe's
    measurement, each rotated into the keyframe's body frame by the gyro increments and
    averaged, with noise sigma_m / sqrt(samples) (the window is shifted inside the recording
    at its ends). Default 5: the averaging's own error (the field's variation over the
    window, gyro bias and noise) measured on the simulated scenarios' noise-free
    magnetometer, seed 1, at 100 Hz, RMS per component against sigma_m / sqrt(samples) with
    sigma_m 0.004: 5 samples 1e-5..9e-5 against 1.8e-3 on every scenario; 11 samples
    1.4e-5..4.2e-4 against 1.2e-3 (handwriting 12 % of the noise variance); 21 samples
    1.9e-5..1.3e-3 against 8.7e-4 (the error larger than the noise on the handwriting desk).
    1: the keyframe's own sample only."""

    sigma_m: PositiveFloat | None = None
    samples: Annotated[int, Field(ge=1)] = 5

    @field_validator("samples")
    @classmethod
    def _odd(cls, v: int) -> int:
        if v % 2 == 0:
            raise ValueError(f"must be odd (centred on the keyframe), got {v}")
        return v


class StartsSpec(Strict):
    """Several starts (a model section's keys): ``starts`` (odd: the start itself and pairs
    of +-heading-rate biases removed from it, casmag.solver.staged.heading_bias_starts,
    each running ``solver.warm_start``'s strategy, the lowest MAP cost kept) [1];
    ``start_heading_deg``: the heading the first pair's bias turns over the recording
    [10]."""

    starts: Annotated[int, Field(ge=1, le=21)] = 1
    start_heading_deg: PositiveFloat = 10.0

    @field_validator("starts")
    @classmethod
    def _odd(cls, v: int) -> int:
        if v % 2 == 0:
            raise ValueError("must be odd (the start and pairs of +-biases)")
        return v


class ImuProblemModelSpec(StartsSpec):
    """keyframe_rate [Hz]: states are kept at this rate, the IMU increments between them
    composed (the IMU rate must be a whole multiple); the magnetometer is used at keyframes,
    averaged over ``magnetometer.samples`` samples around each."""

    keyframe_rate: PositiveFloat = 10.0
    imu: ImuModelSpec = ImuModelSpec()
    initial: InitialStateSpec = InitialStateSpec()
    zero_position: ZeroPositionSpec = ZeroPositionSpec()
    gp: ImuGPSpec = ImuGPSpec()
    magnetometer: MagnetometerModelSpec = MagnetometerModelSpec()
    # starts, start_heading_deg (StartsSpec): several starts turned from the IMU-only
    # adjustment (casmag.solver.imu.ImuStaged), with a strategy other than auto.


class ImuMotionSpec(Strict):
    """``motion`` of an IMU problem: the kind alone (the IMU's errors are
    ``simulation.imu``'s, the model's ``model.imu``'s)."""

    kind: Literal["imu"] = "imu"


def auto_warm_start(data: Any) -> Any:
    """An IMU document with its model's default warm start, the schedule ladder (``auto``),
    also when it gives a solver section without a strategy."""
    solver = data.get("solver") if isinstance(data, dict) else None
    if isinstance(solver, dict):
        ws = solver.get("warm_start", {})
        if isinstance(ws, dict) and "strategy" not in ws:
            data = {**data, "solver": {**solver, "warm_start": {**ws, "strategy": "auto"}}}
    return data


class ImuProblemSpec(Strict):
    seed: Annotated[int, Field(ge=0, le=2**32 - 1)]  # numpy's generators: 0 .. 2^32 - 1
    name: str | None = None
    description: str | None = None
    motion: ImuMotionSpec = ImuMotionSpec()
    simulation: ImuSimulationSpec
    model: ImuProblemModelSpec = ImuProblemModelSpec()
    solver: SolverSpec = SolverSpec(warm_start=WarmStartSpec(strategy="auto"))

    _auto = model_validator(mode="before")(auto_warm_start)

    @model_validator(mode="after")
    def _consistent(self) -> ImuProblemSpec:
        check_imu_settings(self.model, self.solver)
        sim = self.simulation
        if sim.imu.levelling_seconds > sim.scenario.static:
            raise ValueError(
                f"simulation.imu.levelling_seconds: the attitude is levelled while at rest, so "
                f"it must not exceed simulation.scenario.static ({sim.scenario.static:g} s), "
                f"got {sim.imu.levelling_seconds:g} s"
            )
        ratio = self.simulation.imu.rate / self.model.keyframe_rate
        if ratio < 1 or abs(ratio - round(ratio)) > 1e-9:
            raise ValueError(
                "model.keyframe_rate: must divide simulation.imu.rate "
                f"({self.simulation.imu.rate:g}"
                f" Hz) a whole number of times, got {self.model.keyframe_rate:g} Hz"
            )
        check_magnetometer_samples(self.model, self.simulation.imu.rate, round(ratio))
        return self


def check_imu_settings(model: ImuProblemModelSpec, solver: SolverSpec) -> None:
    """The IMU model's settings that only make sense together (ValueError naming the key):
    sliding windows carry one reduced-rank map from the IMU-only adjustment alone; several
    starts each run a strategy other than the schedule ladder; the numpy Hessians need the
    reduced-rank map."""
    if solver.warm_start.strategy == "sliding":
        if model.gp.form != "reduced_rank":
            raise ValueError(
                "solver.warm_start.strategy: sliding windows carry a reduced-rank map; "
                f"set model.gp.form to reduced_rank (got {model.gp.form})"
            )
        if model.starts > 1:
            raise ValueError(
                "model.starts: the IMU model's sliding windows start from the IMU-only "
                "adjustment alone; set model.starts to 1 or choose another strategy"
            )
    if model.starts > 1 and solver.warm_start.strategy == "auto":
        raise ValueError(
            "model.starts: each start runs solver.warm_start's strategy, and auto (the "
            "schedule ladder) runs once; set solver.warm_start.strategy to none, growing "
            "or coarse-to-fine"
        )
    if solver.hessian in NUMPY_HESSIANS and model.gp.form != "reduced_rank":
        raise ValueError(f"solver.hessian: {solver.hessian} needs model.gp.form: reduced_rank")


def check_magnetometer_samples(model: ImuProblemModelSpec, rate: float, substeps: int) -> None:
    """``model.magnetometer.samples`` spans at most one keyframe interval's IMU samples plus
    one (``substeps`` intervals at ``rate`` Hz), so that neighbouring keyframes do not share
    noise (ValueError naming the key)."""
    samples = model.magnetometer.samples
    if samples > substeps + 1:
        raise ValueError(
            "model.magnetometer.samples: at most one keyframe interval's samples plus one "
            f"({substeps + 1} at {rate:g} Hz and {rate / substeps:g} Hz keyframes; "
            f"neighbouring keyframes would share noise), got {samples}"
        )


class RecordingInitialSpec(InitialStateSpec):
    """The first keyframe's priors (:class:`InitialStateSpec`) and ``rest_seconds`` [s]: how
    long a recording lies still at its start. Those samples level the initial attitude and
    give the noise the model assumes when ``model.imu`` or ``model.magnetometer`` leave it
    null (casmag.data.imurec.rest_noise)."""

    rest_seconds: PositiveFloat = 0.5


class RecordingImuSpec(ImuModelSpec):
    """A recording's ``model.imu`` (:class:`ImuModelSpec`) with constant biases by default,
    also when the section gives other keys."""

    bias: Literal["random_walk", "constant"] = "constant"


class ImuRecordingModelSpec(ImuProblemModelSpec):
    """The IMU model of a recording (``casmag slam`` on ``dqw..dvz`` columns): the keys of an
    IMU problem's ``model``, with these differences. Noise densities and
    ``magnetometer.sigma_m`` left null are estimated from the rest at the start (there is no
    simulation to take them from). The biases are ``constant`` by default: random-walk
    strengths cannot be estimated in the joint MAP (:class:`ImuModelSpec`), so
    ``bias: random_walk`` needs ``gyro_bias_walk`` and ``acc_bias_walk`` (the datasheet's
    bias instability). Keyframes at 5 Hz, as in every measured IMU problem file
    (problems/imu/README.md)."""

    keyframe_rate: PositiveFloat = 5.0
    imu: RecordingImuSpec = RecordingImuSpec()
    initial: RecordingInitialSpec = RecordingInitialSpec()


#: Solver settings of IMU recordings that differ from SolverSpec's defaults: those of every
#: IMU problem file, under which problems/imu/README.md's figures were measured.
IMU_RECORDING_SOLVER: dict[str, Any] = {
    "max_iter": 150,
    "tol": 1.0e-5,
    "warm_start": {"strategy": "auto"},
}


class ImuRecordingSpec(Strict):
    """A problem file for an IMU recording: ``model`` (:class:`ImuRecordingModelSpec`) and
    ``solver`` (the IMU model's default warm start, its schedule ladder ``auto``, with the
    tolerance and iteration limit every measured IMU problem file gives:
    :data:`IMU_RECORDING_SOLVER`)."""

    model: ImuRecordingModelSpec = ImuRecordingModelSpec()
    solver: SolverSpec = SolverSpec(**IMU_RECORDING_SOLVER)

    _auto = model_validator(mode="before")(auto_warm_start)

    @model_validator(mode="after")
    def _consistent(self) -> ImuRecordingSpec:
        check_imu_settings(self.model, self.solver)
        return self


# --------------------------------------------------------------------------- resolved
@dataclass(frozen=True)
class ImuProblem:
    """A validated IMU problem and where it came from, with model values resolved (SI units:
    rad, rad/s, m/s^2). ``spec``: a simulated problem (:class:`ImuProblemSpec`) or a
    recording's model and solver (:class:`ImuRecordingSpec`, with the recording's IMU
    ``rate`` [Hz]: :func:`recording_imu_problem`)."""

    spec: ImuProblemSpec | ImuRecordingSpec
    source: str = "<dict>"
    rate: float | None = None

    @property
    def name(self) -> str:
        return problem_name(getattr(self.spec, "name", None), self.source, "imu")

    @property
    def simulation(self) -> ImuSimulationSpec | None:
        """The simulation the data come from (None for a recording)."""
        return getattr(self.spec, "simulation", None)

    @property
    def imu_rate(self) -> float:
        """The IMU's sample rate [Hz]: the simulation's, or the recording's."""
        sim = self.simulation
        return float(sim.imu.rate if sim is not None else self.rate)

    @property
    def substeps(self) -> int:
        """IMU intervals per keyframe interval."""
        return max(1, round(self.imu_rate / self.spec.model.keyframe_rate))

    def _resolve(self, value: float | None, section: str, key: str, field: str) -> float:
        if value is not None:
            return value
        sim = self.simulation
        if sim is None:
            raise ProblemError(self.source, field, "needs a value for a recording (no simulation)")
        truth = getattr(getattr(sim, section), key)
        if truth <= 0:
            raise ProblemError(
                self.source,
                field,
                "must be set when the simulated value is 0 (cannot default to it)",
            )
        return truth

    @property
    def gyro_density(self) -> float:
        """Assumed gyroscope noise density [rad/s/sqrt(Hz)]."""
        m = self.spec.model.imu
        v = self._resolve(
            m.gyro_noise_density, "imu", "gyro_noise_density", "model.imu.gyro_noise_density"
        )
        return float(np.radians(v))

    @property
    def acc_density(self) -> float:
        m = self.spec.model.imu
        return self._resolve(
            m.acc_noise_density, "imu", "acc_noise_density", "model.imu.acc_noise_density"
        )

    @property
    def gyro_walk(self) -> float:
        """Assumed gyroscope bias random walk [rad/s/sqrt(s)]."""
        m = self.spec.model.imu
        if m.bias == "constant":
            return 0.0
        v = self._resolve(m.gyro_bias_walk, "imu", "gyro_bias_walk", "model.imu.gyro_bias_walk")
        return float(np.radians(v))

    @property
    def acc_walk(self) -> float:
        m = self.spec.model.imu
        if m.bias == "constant":
            return 0.0
        return self._resolve(m.acc_bias_walk, "imu", "acc_bias_walk", "model.imu.acc_bias_walk")

    @property
    def sigma_m(self) -> float:
        return self._resolve(
            self.spec.model.magnetometer.sigma_m, "magnetometer", "noise",
            "model.magnetometer.sigma_m",
        )  # fmt: skip

    def resolve_all(self) -> None:
        """Resolve every defaulted value now, so a bad file fails before anything is built."""
        for name in ("gyro_density", "acc_density", "gyro_walk", "acc_walk"):
            getattr(self, name)
        if self.spec.model.gp.form != "none":
            self.sigma_m  # noqa: B018


def recording_imu_problem(spec: ImuRecordingSpec, source: str, rate: float) -> ImuProblem:
    """The IMU problem of a recording sampled at ``rate`` Hz, its values resolved: the
    keyframes take the whole number of IMU intervals nearest to ``model.keyframe_rate``
    (at least one), and ``model.magnetometer.samples`` must fit one keyframe interval
    (ProblemError naming the key)."""
    out = ImuProblem(spec=spec, source=source, rate=float(rate))
    try:
        check_magnetometer_samples(spec.model, out.imu_rate, out.substeps)
    except ValueError as exc:
        key, _, reason = str(exc).partition(": ")
        raise ProblemError(source, key, reason) from None
    out.resolve_all()
    return out


def load_imu_problem(
    problem: str | Path | Mapping[str, Any] | ImuProblem,
    overrides: Iterable[str] = (),
    source: str | None = None,
) -> ImuProblem:
    """Load and validate an IMU problem from a YAML path, a dictionary or an ImuProblem,
    with ``key.path=value`` overrides (YAML values) applied before validation."""
    if isinstance(problem, ImuProblem):
        if not overrides:
            return problem
        problem, source = problem.spec.model_dump(mode="python"), problem.source
    spec, src = validate_spec(ImuProblemSpec, problem, overrides, source)
    out = ImuProblem(spec=spec, source=src)
    out.resolve_all()
    return out


# --------------------------------------------------------------------------- planar recordings
def no_truth_on_a_recording(value: Any) -> Any:
    """Refuse null for a recording model's hyperparameter: null is a simulation's truth."""
    if value is None:
        raise ValueError(
            "null means a simulation's true value, and a recording has none: give a number "
            "or estimate"
        )
    return value


class RecordingGPSpec(Strict):
    """The field map of a planar recording (a pose recording's is PoseGPSpec, with other
    defaults) in ``model.gp``, the section translational and IMU problems spell it in:
    ``form`` ``auto`` (the default: the box, or the tiles where the box would be capped,
    too costly or over the memory budget, casmag.model.mapchoice; a kernel other than
    ``curl_free`` given here, or ``num_basis``, keeps the box), ``reduced_rank`` (one box
    around the dead reckoning) or ``tiled`` (casmag.gp.tiles; kernel ``curl_free``, taken
    when none is given);
    ``kernel``; ``sigma_f``, ``lengthscale``:
    a value or ``estimate`` (the windowed marginal likelihood on the dead-reckoned path);
    ``sigma_lin``: the constant field's prior (None: from the data); ``num_basis``,
    ``margin``: the reduced-rank basis (None: casmag.model.rrmap's); ``tile_basis``: the
    tiled map's basis, ``bumps`` or ``hilbert`` (None: casmag.model.tiledmap.TILE_BASIS);
    ``bump_spacing``: the bumps' lattice in lengthscales (None: from the field's strength
    against the noise, casmag.model.tiledmap.bump_spacing)."""

    form: Literal["auto", "reduced_rank", "tiled"] = "auto"
    kernel: Literal["se", "curl_free"] = "se"
    sigma_f: PositiveFloat | Literal["estimate"] = "estimate"
    lengthscale: PositiveFloat | Literal["estimate"] = "estimate"
    sigma_lin: PositiveFloat | None = None
    num_basis: Annotated[int, Field(ge=1, le=5000)] | None = None
    margin: PositiveFloat | None = None
    tile_basis: Literal["bumps", "hilbert"] | None = None
    bump_spacing: Annotated[float, Field(ge=0.2, le=2.0)] | None = None

    _no_truth = field_validator("sigma_f", "lengthscale", mode="before")(no_truth_on_a_recording)

    @model_validator(mode="after")
    def _tiled_is_curl_free(self) -> RecordingGPSpec:
        if self.form == "tiled" and "kernel" not in self.model_fields_set:
            self.kernel = "curl_free"  # the tiles' kernel, as when form auto chooses them
        if self.form == "tiled" and self.kernel != "curl_free":
            raise ValueError(
                "form tiled needs kernel: curl_free (the tiles blend a scalar potential)"
            )
        chosen_kernel = "kernel" in self.model_fields_set and self.kernel != "curl_free"
        if self.form == "auto" and (chosen_kernel or self.num_basis is not None):
            self.form = "reduced_rank"  # the tiles cannot keep what was chosen
        return self


class RecordingMagnetometerSpec(Strict):
    """``model.magnetometer.sigma_m`` of a recording model: the magnetometer noise the model
    assumes [field units], a value or ``estimate``."""

    sigma_m: PositiveFloat | Literal["estimate"] = "estimate"

    _no_truth = field_validator("sigma_m", mode="before")(no_truth_on_a_recording)


#: The keys of a planar or pose model that live in its ``gp`` and ``magnetometer``
#: sections, as every model spells them. Earlier problem files gave them at the top of
#: ``model`` (``model.sigma_f``); that spelling still loads (:func:`nest_field_keys`).
FIELD_SECTIONS = {
    "sigma_m": "magnetometer",
    **{
        k: "gp"
        for k in (
            "form",
            "kernel",
            "sigma_f",
            "lengthscale",
            "sigma_lin",
            "num_basis",
            "margin",
            "tile_basis",
            "bump_spacing",
        )
    },
}


def nest_field_keys(model: Any) -> Any:
    """A planar or pose ``model`` section with the earlier top-level spelling of its field
    keys (``sigma_m``, ``sigma_f``, ...) moved into ``gp`` and ``magnetometer``
    (:data:`FIELD_SECTIONS`); a key given both ways is refused. Anything but a mapping is
    left for validation to name."""
    if not isinstance(model, Mapping) or not any(k in model for k in FIELD_SECTIONS):
        return model
    out = {k: v for k, v in model.items() if k not in FIELD_SECTIONS}
    for key, section in FIELD_SECTIONS.items():
        if key not in model:
            continue
        inner = out.get(section, {})
        if not isinstance(inner, Mapping):
            return model
        if key in inner:
            raise ValueError(
                f"{section}.{key} is given twice, also as {key} (the earlier spelling); "
                f"keep {section}.{key}"
            )
        out[section] = {**inner, key: model[key]}
    return out


def flat_options(model: Strict) -> dict[str, Any]:
    """A planar or pose model section as the keyword arguments of its options dataclass
    (the ``gp`` and ``magnetometer`` keys beside the others)."""
    data = model.model_dump()
    for section in ("gp", "magnetometer"):
        data.update(data.pop(section))
    return data


class PlanarModelSpec(StartsSpec):
    """The planar odometry-with-heading model for ``casmag slam`` on a recording with
    ``dfwd,dleft,dyaw`` columns: the fields of :class:`PlanarOptions` (units
    there: metres, radians, seconds; field units of the recording), the map's in ``gp``
    (:class:`RecordingGPSpec`) and the magnetometer's noise in ``magnetometer``."""

    sigma_disp: PositiveFloat = 0.01
    sigma_dyaw: PositiveFloat = 0.002
    bias: Literal["constant", "random_walk"] = "constant"
    bias_walk: PositiveFloat = 1.0e-4
    bias_prior: PositiveFloat = 0.05
    gp: RecordingGPSpec = RecordingGPSpec()
    magnetometer: RecordingMagnetometerSpec = RecordingMagnetometerSpec()
    sigma_anchor: PositiveFloat = 1.0e-3
    sigma_psi0: PositiveFloat = 1.0e-3
    curvature: bool = True
    displacement_bias: Annotated[float, Field(ge=0.0, le=0.5)] = 0.01

    _nest = model_validator(mode="before")(nest_field_keys)


#: Solver settings of planar recordings that differ from SolverSpec's defaults (keys a
#: problem file or ``--set solver.KEY=...`` does not give keep these values).
PLANAR_SOLVER_DEFAULTS: dict[str, Any] = {
    "max_iter": 150,
    "tol": 1.0e-5,
    "ipopt": {"acceptable_tol": 1.0e-4, "acceptable_iter": 5},
    # Growing prefixes of 150, 300, ... samples (casmag.solver.windowing.grow) on recordings longer
    # than about 212 samples; shorter ones are one batch. Measured on the handheld square
    # recording (747 samples, ARKit truth, RMSE 2.33 m before): the batch from the dead
    # reckoning stopped at the iteration limit (150, 6.4 min); growing converged (118
    # iterations in the last stage, 4.1 min) to 1.15 m and a heading error of 6.2 from
    # 42 deg. The simulated 186-sample loop walks are one batch either way.
    "warm_start": {"strategy": "growing", "first_samples": 150, "growth": 2.0},
}


class PlanarSpec(Strict):
    """A problem file for a planar recording: ``model`` (:class:`PlanarModelSpec`) and
    ``solver`` (IPOPT; defaults :data:`PLANAR_SOLVER_DEFAULTS`)."""

    model: PlanarModelSpec = PlanarModelSpec()
    solver: SolverSpec = SolverSpec(**PLANAR_SOLVER_DEFAULTS)


@dataclass(frozen=True)
class PlanarOptions:
    """Settings of the planar odometry-with-heading problem (defaults in brackets).

    sigma_disp: displacement noise per step and axis [m] (0.01); sigma_dyaw: heading
    increment noise per step [rad] (0.002); bias: heading-rate bias ``constant`` or
    ``random_walk`` [constant]; bias_walk: its random walk [rad/s/sqrt(s)] (1e-4);
    bias_prior: zero-mean prior on the (first) bias [rad/s] (0.05); sigma_m, sigma_f,
    lengthscale: magnetometer noise [field units], field variation [field units] and
    lengthscale [m]: values or ``estimate`` (windowed marginal likelihood on the
    dead-reckoned path, short windows) [estimate]; kernel: ``se`` or ``curl_free`` [se];
    sigma_lin: constant-field prior [field units] (None: from the data, the largest
    |mean| of a field component plus the field's standard deviation, as for translational
    recordings); num_basis, margin: reduced-rank basis
    (None: defaults of ``casmag.model.rrmap``); sigma_anchor [m] (1e-3) and sigma_psi0 [rad] (1e-3):
    priors on the known first position and heading; starts: number of starts (odd: the dead
    reckoning and pairs of +-heading-rate biases, each running ``solver.warm_start``'s
    strategy, the lowest MAP cost kept: casmag.solver.staged) [1];
    start_heading_deg: the heading the first pair's bias turns over the recording [10];
    form: the map, ``reduced_rank`` (one box around the dead reckoning), ``tiled``
    (casmag.gp.tiles: tiles only where the path goes, each sample touching the four
    around it; needs kernel ``curl_free``; the Hessian is Gauss-Newton, ``curvature``
    applies to the box only) or ``auto`` (chosen once the lengthscale is known,
    casmag.model.mapchoice; ``casmag slam``'s default) [reduced_rank]; tile_basis: the
    tiles' basis (None: casmag.model.tiledmap.TILE_BASIS); bump_spacing: the bumps' lattice
    in lengthscales (None: from the field's strength once the hyperparameters are known,
    casmag.model.tiledmap.bump_spacing); solver: IPOPT
    settings. ``curvature``: the box's magnetometer block with its exact Hessian (true)
    or Gauss-Newton (false) under ``solver.hessian: auto`` (another value there chooses
    instead) [true]. ``displacement_bias``: the body-frame displacement bias per step
    (forward and left) the position covariance allows for, a fraction of the median step
    [0.01]: not estimated (a constant forward bias is a scale of the whole path, which the
    map cannot see), taken in as a consider parameter (casmag.solver.planar.
    displacement_bias_consider); 0: none."""

    sigma_disp: float = 0.01
    sigma_dyaw: float = 0.002
    bias: str = "constant"
    bias_walk: float = 1e-4
    bias_prior: float = 0.05
    sigma_m: float | str = "estimate"
    kernel: str = "se"
    sigma_f: float | str = "estimate"
    lengthscale: float | str = "estimate"
    sigma_lin: float | None = None
    num_basis: int | None = None
    margin: float | None = None
    tile_basis: str | None = None
    bump_spacing: float | None = None
    sigma_anchor: float = 1e-3
    sigma_psi0: float = 1e-3
    curvature: bool = True
    displacement_bias: float = 0.01
    starts: int = 1
    start_heading_deg: float = 10.0
    form: str = "reduced_rank"
    solver: SolverSpec = dataclasses.field(
        default_factory=lambda: SolverSpec(**PLANAR_SOLVER_DEFAULTS)
    )


#: The warm-start strategies the planar and pose models take (casmag.solver.staged).
STAGED_STRATEGIES = ("none", "growing", "coarse-to-fine", "sliding")


def load_planar_options(
    problem: str | Path | Mapping[str, Any] | None = None,
    overrides: Iterable[str] = (),
    source: str | None = None,
) -> PlanarOptions:
    """:class:`PlanarOptions` from an optional problem file (only its
    ``model`` and ``solver`` sections are read; other sections are ignored) and
    ``key.path=value`` overrides such as ``model.sigma_disp=0.002``. Raises ProblemError
    naming the file (or ``--set``), the key and the reason."""
    spec = load_recording_spec(PlanarSpec, problem, overrides, source)
    return PlanarOptions(**flat_options(spec.model), solver=spec.solver)


def load_recording_spec(
    spec_class: type[Strict],
    problem: str | Path | Mapping[str, Any] | None = None,
    overrides: Iterable[str] = (),
    source: str | None = None,
) -> Any:
    """A recording model's problem file (planar, pose: only its ``model`` and ``solver``
    sections are read; the solver's defaults are the class's own) with ``key.path=value``
    overrides, validated; warm starts :data:`STAGED_STRATEGIES` (sliding windows need the
    reduced-rank map). Raises ProblemError naming the file (or ``--set``), the key and the
    reason."""
    if problem is None:
        data: dict[str, Any] = {}
        source = source or "--set"
    elif isinstance(problem, Mapping):
        data = dict(problem)
    else:
        data, source = read_yaml(Path(problem)), source or str(problem)
    data = {k: v for k, v in data.items() if k in ("model", "solver")}
    solver = data.get("solver")
    defaults = spec_class.model_fields["solver"].default.model_dump(exclude_unset=True)
    data["solver"] = {**defaults, **(solver if isinstance(solver, dict) else {})}
    if solver is not None and not isinstance(solver, dict):
        data["solver"] = solver  # let validation name the bad value
    spec, _ = validate_spec(spec_class, data, overrides, source)
    ws = spec.solver.warm_start
    if ws.strategy == "auto":  # the model's own default, with the keys the file gives
        default = spec_class.model_fields["solver"].default.warm_start
        given = {key: getattr(ws, key) for key in ws.model_fields_set - {"strategy"}}
        spec.solver = spec.solver.model_copy(
            update={"warm_start": default.model_copy(update=given)}
        )
    if spec.solver.warm_start.strategy == "sliding" and spec.model.gp.form == "auto":
        spec.model.gp.form = "reduced_rank"  # a window's map is one box
    if spec.solver.warm_start.strategy == "sliding" and spec.model.gp.form == "tiled":
        raise ProblemError(
            source,
            "solver.warm_start.strategy",
            "sliding windows need model.gp.form: reduced_rank (a window's map is one box)",
        )
    return spec


#: Solver settings the IMU model does not use (the Laplace covariance) and those it does
#: (the warm starts); the IMU model reads :data:`IMU_SOLVER_KEYS` of them, the planar and
#: pose models :data:`STAGED_SOLVER_KEYS`.
UNUSED_SOLVER_KEYS = ("solver.warm_start", "solver.uncertainty", "solver.uncertainty_inflation")


#: The keys under :data:`UNUSED_SOLVER_KEYS` the IMU model reads: its warm starts (its
#: schedule ladder, one batch, growing prefixes, coarse-to-fine, sliding windows;
#: casmag.solver.imu, casmag.solver.staged).
IMU_SOLVER_KEYS = tuple(
    f"solver.warm_start.{k}"
    for k in (
        "strategy", "first_samples", "growth", "stage_max_iter", "lengthscale_start",
        "lengthscale_stages", "window", "overlap", "window_lengthscales", "window_bias_prior",
        "unit", "sample_period", "window_max_iter",
    )
)  # fmt: skip


#: The keys under :data:`UNUSED_SOLVER_KEYS` the planar and pose models read: the IMU
#: model's, the start of the field's evidence and the Laplace covariance.
STAGED_SOLVER_KEYS = (
    *IMU_SOLVER_KEYS, "solver.warm_start.evidence", "solver.uncertainty",
    "solver.uncertainty_inflation",
)  # fmt: skip


def refuse_unused_solver_keys(
    overrides: Iterable[str], command: str, used: tuple[str, ...] = ()
) -> None:
    """Refuse ``--set`` keys a model would ignore (ProblemError naming the key), so that a
    setting never silently does nothing; ``used``: keys under :data:`UNUSED_SOLVER_KEYS`
    that the model reads."""
    for text in as_overrides(overrides):
        key = ".".join(parse_override(text)[0])
        if key in used:
            continue
        for unused in UNUSED_SOLVER_KEYS:
            if key == unused or key.startswith(unused + "."):
                raise ProblemError("--set", key, f"{command} does not use {key}")
