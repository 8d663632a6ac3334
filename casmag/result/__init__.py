"""The result of a GP-SLAM solve and how it is saved.

A result holds ``info`` (what was solved), scalar statistics and arrays. It is saved as
``result.json`` (everything but the arrays), ``arrays.npz`` (the arrays, exactly),
``trajectory.csv`` (the trajectories as text), ``map.npz`` when the run has a reduced-rank
box map (casmag.gp.savedmap) and figures, written into a temporary folder
that replaces the output folder only once complete, so an interrupted or failed write never
leaves a half-written output. :meth:`Result.load` reads a saved result back.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import MISSING, asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from casmag.errors import DataError
from casmag.gp.savedmap import MAP_FILE, SavedMap, load_map
from casmag.result.evaluation import evaluate_result
from casmag.result.metrics import rmse_and_max
from casmag.result.outdir import save_atomic
from casmag.result.verdict import verdict

#: The motion models a result can come from (``Result.motion``).
MOTIONS = ("translational", "planar", "imu", "pose")


@dataclass
class Result:
    """Outcome of one solve, of any motion model (``motion``: translational, planar, imu).

    Errors are position errors in metres against the truth without alignment (None when the
    data have no truth, or the solve failed): ``rmse_before``/``max_before`` of the path the
    solve started from (the dead reckoning; for the IMU model the IMU-only adjustment, the
    motion model without a map), ``rmse_after``/``max_after`` of the estimate.
    ``cost_blocks`` maps each named block of the final solve to its value at the initial
    guess ("before") and at the solution ("after").

    Fields: ``info`` (name, source, seed, sample count, model settings, versions, the
    ``warm_start`` strategy whose solves are in ``stages``, for recordings ``defaults`` and
    ``recording``); ``status`` (IPOPT's return
    status, or ``Odometry_Only``) and ``success``; ``iterations`` (of the final solve plus
    any start solves); ``build_seconds``, ``solve_seconds`` [s]; ``hyperparameters``:
    sigma_f and sigma_m [field units], lengthscale [m]; ``hyperparameters_initial``: the
    values the MAP started from (the assumed ones, except estimated sigma_f and
    lengthscale, which start where ``info["estimate_start"]`` says: casmag.model.translational.
    estimate_start; with both of its starts ``solve_seconds`` is their sum);
    ``odometry_bias`` and ``odometry_bias_true``: the motion model's
    constant bias (translational: m per step, per axis and session; planar: the
    heading-rate bias in rad/s, rad per step without times, one value per step for a
    random walk); ``cost_per_iteration``, ``constraint_violation_per_iteration`` (the final
    solve's; ``convergence`` has every solve's objective, primal and dual infeasibility:
    casmag.nlp.Solution.trace); ``stages``: one record per partial or earlier solve, in
    order, each with its ``name``, status, iterations and seconds: ``start`` (one of
    several starts, with ``start``, ``cost`` and ``kept``: the two starts of a recording,
    the sessions' starts, the planar heading-bias starts), ``prefix`` (a growing prefix,
    with ``samples``), ``window``, ``lengthscale`` and ``batch`` (the sliding and
    coarse-to-fine warm starts), ``imu_only`` and ``gp_slam`` (the IMU model's stages, with
    cost blocks; a grown pass lists its prefixes under ``grow``); :meth:`stage`,
    :meth:`stages_named`; ``details``: the figures only this motion model reports
    (planar: heading errors; IMU: errors and biases per estimate, the map decision and the
    field evidence; see :data:`DETAILS`); ``uncertainty`` (sigma_mean, sigma_max [m], NEES
    against the truth, or ``error``); ``warnings`` (casmag.data.checks: ``check``, ``column``,
    ``reason``); ``flags``: what the model's own checks raised against the estimate, each
    ``{"name", "reason", "evidence"}`` (casmag.solver.planar, casmag.solver.imu);
    ``evaluation``: the errors again after an optional alignment to the truth
    (casmag.result.evaluation); ``verdict``: whether the estimate can be trusted, the
    reasons and the checks (casmag.result.verdict); ``field_map``: the estimated map with
    its posterior (casmag.gp.savedmap.SavedMap; None when the model has none to save, or
    until :meth:`saved_map` computes it).

    Arrays (N samples or keyframes, d = 2 or 3 dimensions, a G x G map grid; absent or None
    when not computed): ``t`` (N,) [s]; ``P_odometry`` (the dead reckoning),
    ``P_strapdown`` and ``P_imu_only`` (IMU), ``P_estimate``, ``P_true`` (N, d) [m];
    ``psi_odometry``, ``psi_estimate``, ``psi_true`` (N,) [rad] (planar headings);
    ``Q_odometry``, ``Q_estimate``, ``Q_true`` (N, 4) (pose and IMU: unit quaternions, w
    first, sensor to map);
    ``att_err_imu_only_deg``, ``att_err_est_deg`` (N,) [deg] (IMU orientation errors);
    ``P_gp_slam_map`` (IMU: the map pass not used when the field was found homogeneous);
    ``P_cov``, ``P_cov_uninflated`` (N, d, d) [m^2], the position covariance drawn and
    reported and the plain Laplace one; ``M_estimate`` (N, 3) the field at the estimate,
    ``Y`` (N, 3) the magnetometer [field units]; ``map_x``, ``map_y`` (G, G) [m],
    ``map_z`` (IMU: the grid's height [m]); ``map_field``, ``map_std``, ``map_prior_std``
    (G, G, 3) [field units], the map, its posterior std given the estimated path and its
    prior std.
    """

    info: dict[str, Any]
    status: str
    success: bool
    iterations: int
    build_seconds: float
    solve_seconds: float
    rmse_before: float | None
    max_before: float | None
    rmse_after: float | None
    max_after: float | None
    hyperparameters: dict[str, float]
    cost_blocks: dict[str, dict[str, float]]
    cost_per_iteration: list[float]
    motion: str = "translational"
    hyperparameters_initial: dict[str, float] = field(default_factory=dict)
    odometry_bias: list[float] | None = None
    odometry_bias_true: list[float] | None = None
    constraint_violation_per_iteration: list[float] = field(default_factory=list)
    stages: list[dict[str, Any]] = field(default_factory=list)
    details: dict[str, Any] = field(default_factory=dict)
    uncertainty: dict[str, Any] | None = None
    convergence: list[dict[str, Any]] = field(default_factory=list)
    warnings: list[dict[str, Any]] = field(default_factory=list)
    flags: list[dict[str, Any]] = field(default_factory=list)
    evaluation: dict[str, Any] | None = None
    verdict: dict[str, Any] | None = None
    arrays: dict[str, np.ndarray] = field(repr=False, default_factory=dict)
    field_map: SavedMap | None = field(default=None, repr=False, compare=False)
    map_maker: Callable[[], tuple[SavedMap | None, dict[str, Any]]] | None = field(
        default=None, repr=False, compare=False
    )

    def __post_init__(self) -> None:
        if self.motion not in MOTIONS:
            raise ValueError(f"motion {self.motion!r} is not one of {', '.join(MOTIONS)}")
        if self.verdict is None:
            self.judge()

    def judge(self) -> None:
        """The verdict (casmag.result.verdict) of the result as it stands, and its
        consequence for the covariance (:meth:`withhold_untrusted_covariance`): run when a
        result is made, and again by whatever changes what the verdict reads (flags added,
        the sessions' errors)."""
        self.verdict = verdict(self)
        self.withhold_untrusted_covariance()

    def __getstate__(self) -> dict[str, Any]:
        """Pickled (a sweep's worker hands results back) without ``map_maker``, a closure
        over the solver: a pickled result carries only a map already computed."""
        return {**self.__dict__, "map_maker": None}

    def withhold_untrusted_covariance(self) -> None:
        """When the verdict does not trust the estimate, its Laplace covariance (the
        curvature at an optimum the checks reject) is not given as one: ``uncertainty``
        becomes ``{"error": "withheld: ...", "computed": <the summary>}`` (kept to show how
        far off it was, e.g. its NEES against the truth) and the covariance arrays are
        dropped, so no figure, trajectory.csv column or library user reads a confident
        covariance of a wrong result, whatever the motion model or the method (the
        filter's own covariance too). :meth:`judge` applies it."""
        u = self.uncertainty
        if not u or "error" in u or (self.verdict or {}).get("trusted", True):
            return
        first = (self.verdict or {}).get("reasons") or ["not trusted"]
        self.uncertainty = {
            "error": f"withheld: the verdict does not trust the estimate ({first[0]})",
            "computed": u,
        }
        for key in ("P_cov", "P_cov_uninflated"):
            self.arrays[key] = None

    def saved_map(self) -> SavedMap | None:
        """The estimated map with its posterior (``field_map``), computed on first use by
        ``map_maker`` (a factorisation of the Hessian: only results that are saved or asked
        pay for it), which also records ``info["map"]`` (saved, or why not)."""
        if self.field_map is None and self.map_maker is not None:
            maker, self.map_maker = self.map_maker, None
            self.field_map, self.info["map"] = maker()
        return self.field_map

    @property
    def trusted(self) -> bool:
        """Solved, and the verdict found nothing against the estimate (casmag.result.verdict)."""
        return bool(self.verdict and self.verdict["trusted"])

    @classmethod
    def odometry_only(
        cls,
        motion: str,
        info: dict[str, Any],
        P: np.ndarray,
        P_true: np.ndarray | None,
        arrays: dict[str, Any] | None = None,
        **fields: Any,
    ) -> Result:
        """The dead reckoning P as the result, no solve (status ``Odometry_Only``): its
        errors before and after are the same; ``arrays`` and ``fields`` add the rest."""
        e = (None, None) if P_true is None else rmse_and_max(P, P_true)
        return cls(
            motion=motion,
            info=info,
            status="Odometry_Only",
            success=True,
            iterations=0,
            build_seconds=0.0,
            solve_seconds=0.0,
            rmse_before=e[0],
            max_before=e[1],
            rmse_after=e[0],
            max_after=e[1],
            hyperparameters=fields.pop("hyperparameters", {}),
            cost_blocks={},
            cost_per_iteration=[],
            arrays={"P_odometry": P, "P_estimate": P, "P_true": P_true, **(arrays or {})},
            **fields,
        )

    def stages_named(self, name: str) -> list[dict[str, Any]]:
        """The records in ``stages`` with this name (e.g. ``gp_slam``: every pass)."""
        return [s for s in self.stages if s.get("name") == name]

    def stage(self, name: str) -> dict[str, Any] | None:
        """The first record in ``stages`` with this name (e.g. ``imu_only``), else None."""
        found = self.stages_named(name)
        return found[0] if found else None

    @classmethod
    def load(cls, folder: str | Path) -> Result:
        """A result saved by :meth:`save`: result.json and, when saved, arrays.npz (arrays
        saved as None come back absent). A result.json written by casmag 0.x before the one
        Result (its IMU and planar layouts) is read in today's layout. Raises DataError
        naming the file when it is missing or not a casmag result."""
        folder = Path(folder)
        path = folder / "result.json"
        data = read_result_json(path)
        names = {f.name for f in fields(cls)} - {"arrays", "field_map", "map_maker"}
        required = [
            f.name
            for f in fields(cls)
            if f.name in names and f.default is MISSING and f.default_factory is MISSING
        ]
        absent = [n for n in required if n not in data]
        if absent:
            raise DataError(f"{path}: not a casmag result (no {', '.join(absent[:3])})")
        arrays: dict[str, np.ndarray] = {}
        if (folder / ARRAYS_FILE).is_file():
            with np.load(folder / ARRAYS_FILE, allow_pickle=False) as npz:
                arrays = {k: npz[k] for k in npz.files}
        saved = load_map(folder / MAP_FILE) if (folder / MAP_FILE).is_file() else None
        return cls(**{k: v for k, v in data.items() if k in names}, arrays=arrays, field_map=saved)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary of everything but the arrays (non-finite floats as None)."""
        d = asdict(replace(self, arrays={}, field_map=None, map_maker=None))
        for name in ("arrays", "field_map", "map_maker"):
            d.pop(name)
        d["evaluation"] = evaluation_of(self)
        d["units"] = UNITS[self.motion]
        return finite_json(d)

    def save(self, out_dir: str | Path, figures: bool = True) -> Path:
        """Write result.json, trajectory.csv, arrays.npz, map.npz (``field_map``), for IMU
        results biases.md, and (if figures) PNGs into out_dir atomically
        (:func:`casmag.result.outdir.save_atomic`: an existing out_dir is replaced only when
        it holds a previous casmag result)."""
        self.saved_map()  # computed before the swap's lock is taken
        return save_atomic(out_dir, lambda tmp: self.write_into(tmp, figures))

    def write_into(self, folder: Path, figures: bool = True) -> None:
        """The files of :meth:`save` into an existing folder, not atomically: for a writer
        that makes a whole output atomically itself (several results side by side,
        casmag.report.methods)."""
        saved = self.saved_map()  # before result.json: it records info["map"]
        (folder / "result.json").write_text(json.dumps(self.to_dict(), indent=2) + "\n")
        if "biases" in self.details:
            (folder / "biases.md").write_text(bias_table(self.details, self.stages))
        if any(self.arrays.get(key) is not None for key, _ in TRAJECTORIES):
            write_trajectory_csv(self, folder / "trajectory.csv")
            write_tum_files(self, folder)
        write_arrays(folder, self.arrays)
        if saved is not None:
            saved.save(folder / MAP_FILE)
        if figures and self.arrays:
            from casmag.result import plotting

            plotting.result_figures(self, folder)


#: What ``Result.details`` holds per motion model. Planar: ``heading_rms_deg_before``,
#: ``heading_rms_deg_after`` [deg]. IMU: ``errors`` per estimate (``strapdown``,
#: ``imu_only``, ``gp_slam``, and ``gp_slam_map`` when the map pass was not used), each
#: ``rmse``, ``max`` [m], ``orientation_rms_deg``, ``orientation_max_deg`` [deg], at
#: keyframes; ``biases`` (``gyro`` [deg/s] and ``acc`` [m/s^2], each ``truth``,
#: ``imu_only``, ``gp_slam``: per-axis means over the run, the paper's Table 6);
#: ``failed_stage`` (None, ``imu_only`` or ``gp_slam``); ``map_decision`` (``map``,
#: ``homogeneous: IMU only`` or ``none``); ``field_evidence`` (casmag.gp.hyper.FieldEvidence);
#: ``hyperparameters_source``; ``schedules`` (each GP-SLAM schedule tried, its cost and
#: whether it was kept). Pose: ``attitude_rms_deg_before``, ``attitude_rms_deg_after``
#: [deg], ``bias_p`` (displacement bias, m per step, body frame), ``bias_w`` (rotation-rate
#: bias, rad/s).
DETAILS = {
    "translational": (),
    "planar": ("heading_rms_deg_before", "heading_rms_deg_after"),
    "imu": (
        "errors",
        "biases",
        "failed_stage",
        "map_decision",
        "field_evidence",
        "hyperparameters_source",
        "schedules",
    ),
    "pose": ("attitude_rms_deg_before", "attitude_rms_deg_after", "bias_p", "bias_w"),
}

#: The units written into result.json, per motion model.
UNITS = {
    "translational": {"errors": "m, no alignment", "seconds": "wall-clock s"},
    "planar": {
        "errors": "position m, heading deg, no alignment",
        "odometry_bias": "heading-rate bias rad/s (rad per step without times)",
        "seconds": "wall-clock s",
    },
    "imu": {
        "errors": "position m, orientation deg, at keyframes, no alignment",
        "gyro_bias": "deg/s",
        "acc_bias": "m/s^2",
        "seconds": "wall-clock s",
    },
    "pose": {
        "errors": "position m, attitude deg, no alignment",
        "odometry_bias": "displacement bias m per step, body frame",
        "bias_w": "rotation-rate bias rad/s (rad per step without times)",
        "seconds": "wall-clock s",
    },
}


def bias_table(details: dict[str, Any], stages: list[dict[str, Any]]) -> str:
    """Markdown table of an IMU result's true and recovered biases (the paper's Table 6
    layout) from its ``details`` and ``stages``, with a line saying when the GP-SLAM columns
    are the IMU-only adjustment."""
    b = details["biases"]
    cols = [("true", "truth"), ("IMU only", "imu_only"), ("GP-SLAM", "gp_slam")]
    head = (
        "| axis | "
        + " | ".join(f"gyro bias {c} [deg/s]" for c, _ in cols)
        + " | "
        + " | ".join(f"acc bias {c} [m/s^2]" for c, _ in cols)
        + " |"
    )
    lines = [head, "|" + "---|" * (1 + 2 * len(cols))]

    def cell(v: list[float] | None, i: int) -> str:
        return "-" if v is None else f"{v[i]:.4f}"

    for i, ax in enumerate("XYZ"):
        g = [cell(b["gyro"][k], i) for _, k in cols]
        a = [cell(b["acc"][k], i) for _, k in cols]
        lines.append(f"| {ax} | " + " | ".join(g + a) + " |")
    if str(details.get("map_decision", "")).startswith("homogeneous"):
        lines.append("")
        rest = (
            "the GP-SLAM pass's own biases are under gp_slam_map in result.json."
            if any(s.get("name") == "gp_slam" for s in stages)
            else "no map was solved (homogeneous already on the IMU-only path)."
        )
        lines.append(
            "The field carries no position information (field_evidence in result.json): "
            f"the GP-SLAM columns are the IMU-only adjustment; {rest}"
        )
    return "\n".join(lines) + "\n"


#: The arrays of a saved result (numpy's npz; names as in Result.arrays).
ARRAYS_FILE = "arrays.npz"


def read_result_json(path: Path) -> dict[str, Any]:
    """A result.json as a mapping in today's layout (:func:`upgrade_layout`); DataError
    naming the file when it cannot be read."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise DataError(f"{path}: cannot read a casmag result ({exc})") from None
    if not isinstance(data, dict):
        raise DataError(f"{path}: not a casmag result (not a JSON object)")
    return upgrade_layout(data)


def upgrade_layout(data: dict[str, Any]) -> dict[str, Any]:
    """A result.json mapping in today's layout. Results saved before the one Result had an
    IMU layout (errors per stage at the top level, ``status_imu_only``, ``gp_slam_passes``,
    cost blocks per stage), a planar one (``heading_rms_deg_*``, ``bias``, ``num_basis``,
    ``info.starts``) and stage records in ``info`` (``warm_start``, ``two_starts``,
    ``session_stages``); they are moved to where :class:`Result` keeps them. Anything else is
    returned as it is."""
    if "motion" in data:
        return data
    if isinstance(data.get("errors"), dict) and "gp_slam" in data["errors"]:
        d = dict(data)
        details = {k: d.pop(k) for k in DETAILS["imu"] if k in d}
        blocks = d.pop("cost_blocks", {}) or {}
        imu_only = {
            "name": "imu_only",
            "status": d.pop("status_imu_only", None),
            "iterations": d.pop("iterations_imu_only", None),
            "rounds": d.pop("rounds_imu_only", None),
            "solve_seconds": d.pop("solve_seconds_imu_only", None),
            "cost_per_iteration": d.pop("cost_per_iteration_imu_only", []),
            "cost_blocks": blocks.get("imu_only", {}),
        }
        passes = [{"name": "gp_slam", **p} for p in d.pop("gp_slam_passes", [])]
        if passes:
            passes[-1]["cost_blocks"] = blocks.get("gp_slam", {})
        e = details.get("errors", {}).get("imu_only") or {}
        e_after = details.get("errors", {}).get("gp_slam") or {}
        return {
            **d,
            "motion": "imu",
            "rmse_before": e.get("rmse"),
            "max_before": e.get("max"),
            "rmse_after": e_after.get("rmse"),
            "max_after": e_after.get("max"),
            "cost_blocks": blocks.get("gp_slam", blocks.get("imu_only", {})),
            "stages": [imu_only, *passes],
            "details": details,
        }
    if "heading_rms_deg_before" in data:
        d = dict(data)
        details = {k: d.pop(k) for k in DETAILS["planar"] if k in d}
        info = {**(d.get("info") or {}), "num_basis": d.pop("num_basis", None)}
        name = "prefix" if info.get("warm_start") == "growing" else "start"
        stages = [{"name": name, **s} for s in info.pop("starts", None) or []]
        bias = d.pop("bias", None)
        return {
            **d,
            "info": info,
            "motion": "planar",
            "odometry_bias": bias,
            "stages": stages,
            "details": details,
        }
    info = dict(data.get("info") or {})
    stages = [{"name": "start", **s} for s in info.pop("two_starts", None) or []]
    stages += [{"name": "start", **s} for s in info.pop("session_stages", None) or []]
    if isinstance(info.get("warm_start"), list):
        records = [{"name": s.pop("kind", "prefix"), **s} for s in map(dict, info["warm_start"])]
        names = {s["name"] for s in records}
        strategy = {"window": "sliding", "lengthscale": "coarse-to-fine", "prefix": "growing"}
        info["warm_start"] = next((v for k, v in strategy.items() if k in names), "none")
        stages += records
    return {**data, "info": info, "motion": "translational", "stages": stages}


def evaluation_of(result: Any) -> dict[str, Any]:
    """A result's ``evaluation``: the one set (``casmag solve --align``, or
    ``result.evaluation = casmag.evaluate(result, "se")``), else without alignment."""
    return result.evaluation if result.evaluation is not None else evaluate_result(result)


def write_arrays(folder: Path, arrays: dict[str, Any]) -> None:
    """The arrays a result holds (those not None) into folder/arrays.npz, exactly."""
    present = {k: np.asarray(v) for k, v in arrays.items() if v is not None}
    if present:
        np.savez_compressed(folder / ARRAYS_FILE, **present)


def finite_json(obj: Any) -> Any:
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: finite_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_json(v) for v in obj]
    return obj


#: The trajectories of a result, in trajectory.csv's order, with their column tags.
TRAJECTORIES = (
    ("P_strapdown", "strapdown"),
    ("P_odometry", "odo"),
    ("P_imu_only", "imu_only"),
    ("P_estimate", "est"),
    ("P_gp_slam_map", "gp_slam_map"),
    ("P_true", "true"),
)

TRAJECTORY_COLUMNS = ("x", "y", "z")


#: The TUM files of a result: trajectory key -> file name (``write_tum_files``).
TUM_FILES = {
    "P_estimate": "trajectory.tum",
    "P_true": "truth.tum",
    "P_odometry": "odometry.tum",
    "P_strapdown": "strapdown.tum",
    "P_imu_only": "imu_only.tum",
    "P_gp_slam_map": "gp_slam_map.tum",
}


def tum_rows(result: Result, key: str) -> np.ndarray | None:
    """The rows ``t x y z qx qy qz qw`` of one trajectory of a result (None when it has
    none): times ``t`` when the result has them, else the sample index; 2-D positions with
    z = 0; the orientation (sensor to map frame) from the IMU quaternions, the planar
    heading (a rotation about z), or identity where the model has none (translational, or a
    heading not known)."""
    a = result.arrays
    P = a.get(key)
    if P is None:
        return None
    P = np.asarray(P, dtype=float)
    n = P.shape[0]
    t = np.asarray(a["t"], dtype=float) if a.get("t") is not None else np.arange(n, dtype=float)
    xyz = np.zeros((n, 3))
    xyz[:, : P.shape[1]] = P
    q = np.zeros((n, 4))
    q[:, 3] = 1.0  # TUM order: qx qy qz qw
    Q = a.get(key.replace("P_", "Q_", 1))
    psi = a.get(key.replace("P_", "psi_", 1))
    if Q is not None:
        Q = np.asarray(Q, dtype=float)
        q = np.column_stack([Q[:, 1:], Q[:, 0]])
    elif psi is not None:
        psi = np.asarray(psi, dtype=float)
        known = np.isfinite(psi)
        q[known, 2], q[known, 3] = np.sin(psi[known] / 2), np.cos(psi[known] / 2)
    return np.column_stack([t, xyz, q])


def write_tum_files(result: Result, folder: Path) -> None:
    """Each trajectory of a result as a TUM file (``TUM_FILES``: ``t x y z qx qy qz qw`` per
    line, space-separated, full precision), which trajectory tools such as evo read:
    ``evo_ape tum truth.tum trajectory.tum`` gives ``rmse_after`` (no alignment)."""
    for key, name in TUM_FILES.items():
        rows = tum_rows(result, key)
        if rows is not None:
            np.savetxt(
                folder / name,
                rows,
                fmt="%.17g",
                header="timestamp tx ty tz qx qy qz qw",
            )


def write_trajectory_csv(result: Result, path: Path) -> None:
    """One row per sample (keyframe, for IMU results): index, time when known, then each
    trajectory the result holds (strapdown, dead reckoning, IMU-only adjustment, estimate,
    the unused map pass, truth) as x, y[, z] and, for planar results, the heading psi [rad],
    for pose results the orientation qw, qx, qy, qz (sensor to map);
    the IMU orientation errors [deg]; and (when computed) the Laplace 1-sigma of the
    estimate per axis [m] and, in the plane, the x-y covariance [m^2]."""
    a = result.arrays
    present = [(k, tag) for k, tag in TRAJECTORIES if a.get(k) is not None]
    n = a[present[0][0]].shape[0]
    cols, names = [np.arange(n)], ["k"]
    if a.get("t") is not None:
        cols.append(np.asarray(a["t"], dtype=float))
        names.append("t")
    for key, tag in present:
        P = np.asarray(a[key])
        cols.extend(P.T)
        names.extend(f"{c}_{tag}" for c in TRAJECTORY_COLUMNS[: P.shape[1]])
        psi = a.get(key.replace("P_", "psi_", 1))
        if psi is not None:
            cols.append(np.asarray(psi, dtype=float))
            names.append(f"psi_{tag}")
        Q = a.get(key.replace("P_", "Q_", 1)) if result.motion == "pose" else None
        if Q is not None:
            cols.extend(np.asarray(Q, dtype=float).T)
            names.extend(f"{c}_{tag}" for c in ("qw", "qx", "qy", "qz"))
    for key in ("att_err_imu_only_deg", "att_err_est_deg"):
        if a.get(key) is not None:
            cols.append(a[key])
            names.append(key)
    cov = a.get("P_cov")
    if cov is not None:
        dim = cov.shape[1]
        for i in range(dim):
            cols.append(np.sqrt(cov[:, i, i]))
            names.append(f"sigma_{TRAJECTORY_COLUMNS[i]}")
        if dim == 2:
            cols.append(cov[:, 0, 1])
            names.append("cov_xy")
    fmt = ["%d"] + ["%.9g"] * (len(names) - 1)
    np.savetxt(
        path, np.column_stack(cols), delimiter=",", header=",".join(names), comments="", fmt=fmt
    )
