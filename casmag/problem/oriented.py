"""Problem files of the models whose magnetometer turns with the body, on simulated data: a
``motion`` section says which odometry the simulated walker carries (``kind: planar`` or
``kind: pose``) and how it errs; ``simulation`` is the translational problem's (path, field,
displacement noise and bias, magnetometer noise: casmag.problem.spec.SimulationSpec);
``model`` and ``solver`` are those of a recording of that motion (``casmag slam``,
:class:`casmag.problem.imu.PlanarModelSpec`, :class:`casmag.problem.pose.PoseModelSpec`).

A hyperparameter of the model (``sigma_m``, ``sigma_f``, ``lengthscale``) takes a number,
``estimate`` (the windowed marginal likelihood on the dead-reckoned path, the default) or
``null``: the simulation's value (``simulation.magnetometer.noise``,
``simulation.field.sigma_f``, ``simulation.field.lengthscale``), with the simulation's kernel.

    seed: 1
    motion: {kind: pose, rate: 2.0, rotation_noise: 3.0e-3}
    simulation: {trajectory: {kind: walk, samples: 300, step: 0.5}, ...}
    model: {starts: 1}
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field

from casmag.errors import ProblemError
from casmag.problem.imu import (
    STAGED_SOLVER_KEYS,
    PlanarOptions,
    PlanarSpec,
    load_planar_options,
    nest_field_keys,
    refuse_unused_solver_keys,
)
from casmag.problem.pose import PoseOptions, PoseSpec, load_pose_options
from casmag.problem.spec import (
    MOTION_KINDS,
    NonNegativeFloat,
    PositiveFloat,
    SimulationSpec,
    Strict,
    apply_overrides,
    as_overrides,
    problem_name,
    read_yaml,
    validate_spec,
)

#: The kernels of the planar and pose models (PlanarModelSpec, PoseModelSpec).
MODEL_KERNELS = ("se", "curl_free")

#: The model's hyperparameters that ``null`` sets to the simulation's value (as
#: ``model.SECTION.KEY``), and where that value is (``simulation.SECTION.KEY``).
TRUTH_OF = {
    ("magnetometer", "sigma_m"): ("magnetometer", "noise"),
    ("gp", "sigma_f"): ("field", "sigma_f"),
    ("gp", "lengthscale"): ("field", "lengthscale"),
}


class PlanarMotionSpec(Strict):
    """Planar odometry (dfwd, dleft, dyaw) at ``rate`` [Hz]: heading-increment noise
    ``heading_noise`` [rad per step] and a constant heading-rate bias ``heading_bias``
    [rad/s]; the displacement's noise and (forward, left) bias are ``simulation.odometry``'s."""

    kind: Literal["planar"]
    rate: PositiveFloat = 2.0
    heading_noise: NonNegativeFloat = 1.0e-3
    heading_bias: float = 0.0


class PoseMotionSpec(Strict):
    """Pose odometry (dp, dq) at ``rate`` [Hz]: rotation noise ``rotation_noise`` [rad per
    step and axis], a constant rate bias ``rate_bias`` [rad/s, body frame], a body-frame
    displacement bias ``displacement_bias`` [m per step] (null: ``simulation.odometry.bias``
    with a zero vertical), roll and pitch a smooth wobble of ``tilt_deg`` [deg] (standard
    deviation), the path at ``height`` [m]; the displacement noise is
    ``simulation.odometry.noise``."""

    kind: Literal["pose"]
    rate: PositiveFloat = 2.0
    rotation_noise: NonNegativeFloat = 3.0e-3
    rate_bias: Annotated[list[float], Field(min_length=3, max_length=3)] = Field(
        default_factory=lambda: [0.0, 0.0, 0.0]
    )
    displacement_bias: Annotated[list[float], Field(min_length=3, max_length=3)] | None = None
    tilt_deg: NonNegativeFloat = 3.0
    height: float = 0.0


class _Oriented(Strict):
    seed: Annotated[int, Field(ge=0, le=2**32 - 1)]
    name: str | None = None
    description: str | None = None
    simulation: SimulationSpec = SimulationSpec()


class PlanarProblemSpec(_Oriented, PlanarSpec):
    """A planar problem file: seed, name, description, motion, simulation, model, solver."""

    motion: PlanarMotionSpec


class PoseProblemSpec(_Oriented, PoseSpec):
    """A pose problem file: seed, name, description, motion, simulation, model, solver."""

    motion: PoseMotionSpec


_SPECS: dict[str, type[Strict]] = {"planar": PlanarProblemSpec, "pose": PoseProblemSpec}


@dataclass(frozen=True)
class OrientedProblem:
    """A validated planar or pose problem file: the spec (:class:`PlanarProblemSpec` or
    :class:`PoseProblemSpec`), where it came from, and the model's options."""

    spec: Any
    source: str = "<dict>"

    @property
    def motion(self) -> str:
        return str(self.spec.motion.kind)

    @property
    def name(self) -> str:
        return problem_name(self.spec.name, self.source, self.motion)

    @property
    def sections(self) -> dict[str, Any]:
        """The ``model`` and ``solver`` sections, as a recording's problem file gives them
        (``casmag slam``'s options loader reads them again); the model's keys only where
        the file gave them, so that what it left to the data (``model.gp.form: auto`` and
        its kernel) is chosen as for a recording."""
        return {
            "model": self.spec.model.model_dump(mode="python", exclude_unset=True),
            "solver": self.spec.solver.model_dump(mode="python"),
        }

    @property
    def options(self) -> PlanarOptions | PoseOptions:
        load = load_planar_options if self.motion == "planar" else load_pose_options
        return load(self.sections, source=self.source)


def _with_truths(data: dict[str, Any], kind: str, source: str) -> dict[str, Any]:
    """``null`` model hyperparameters replaced by the simulation's values (module
    docstring); the model's kernel is then the simulation's (a different one is refused:
    sigma_f means a different thing for it)."""
    try:
        model = nest_field_keys(data.get("model"))
    except ValueError as exc:
        raise ProblemError(source, "model", str(exc)) from None
    if not isinstance(model, dict):
        return data
    sections = {s: model.get(s) for s in ("gp", "magnetometer")}
    nulls = [
        (s, k)
        for s, k in TRUTH_OF
        if isinstance(sections[s], dict) and k in sections[s] and sections[s][k] is None
    ]
    if not nulls:
        return data
    where = f"model.{nulls[0][0]}.{nulls[0][1]}"
    simulation = {"seed": 0, "simulation": data.get("simulation", {})}
    sim = validate_spec(_Oriented, simulation, (), source)[0]
    kernel = sim.simulation.field.kernel
    if kernel not in MODEL_KERNELS:
        raise ProblemError(
            source, where, f"null is the simulation's value, for its kernel {kernel}, which "
            f"the {kind} model does not take ({', '.join(MODEL_KERNELS)})"
        )  # fmt: skip
    gp = dict(sections["gp"] or {})
    given = gp.get("kernel", kernel)
    if given != kernel:
        raise ProblemError(
            source, where, f"null is the simulation's value, for its kernel {kernel}, not "
            f"model.gp.kernel {given}: give a number or estimate"
        )  # fmt: skip
    model = {**model, "gp": {**gp, "kernel": kernel}}
    for (section, key), (sim_section, sim_key) in TRUTH_OF.items():
        if (section, key) in nulls:
            value = getattr(getattr(sim.simulation, sim_section), sim_key)
            model[section] = {**model.get(section, {}), key: value}
    return {**data, "model": model}


def load_oriented_problem(
    problem: str | Path | Mapping[str, Any] | OrientedProblem,
    overrides: str | Iterable[str] | Mapping[str, Any] = (),
    source: str | None = None,
) -> OrientedProblem:
    """Load and validate a planar or pose problem file (a YAML path or a dictionary) with
    ``key.path=value`` overrides. Raises ProblemError naming the file, the key and the
    reason."""
    if isinstance(problem, OrientedProblem):
        if not as_overrides(overrides):
            return problem
        problem, source = problem.spec.model_dump(mode="python"), problem.source
    if isinstance(problem, Mapping):
        data, src = dict(problem), source or "<dict>"
    else:
        data, src = read_yaml(Path(problem)), source or str(problem)
    data = apply_overrides(data, overrides, src)
    motion = data.get("motion")
    kind = motion.get("kind") if isinstance(motion, Mapping) else None
    if kind not in _SPECS:
        where = "motion.kind" if isinstance(motion, Mapping) else "motion"
        raise ProblemError(
            src,
            where,
            f"the motion model: {', '.join(MOTION_KINDS[:-1])} or {MOTION_KINDS[-1]} "
            f"(got {kind!r})",
        )
    refuse_unused_solver_keys(overrides, f"a {kind} problem", STAGED_SOLVER_KEYS)
    data = _with_truths(data, kind, src)
    spec_class, solver = _SPECS[kind], data.get("solver")
    defaults = spec_class.model_fields["solver"].default.model_dump(exclude_unset=True)
    if solver is None or isinstance(solver, dict):
        data["solver"] = {**defaults, **(solver or {})}
    spec, _ = validate_spec(spec_class, data, (), src)
    oriented = OrientedProblem(spec=spec, source=src)
    oriented.options  # noqa: B018  (the model's loader: the warm-start strategies it takes)
    return oriented
