"""The result of a GP-SLAM solve and how it is saved.

A result holds ``info`` (what was solved), scalar statistics and arrays. It is saved as
``result.json`` (everything but the arrays), ``arrays.npz`` (the arrays, exactly),
``trajectory.csv`` (the trajectories as text) and figures, written into a temporary folder
that replaces the output folder only once complete, so an interrupted or failed write never
leaves a half-written output. :meth:`Result.load` reads a saved result back.
"""

from __future__ import annotations

import json
import math
from dataclasses import MISSING, asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from casmag.errors import DataError
from casmag.evaluation import evaluate_result
from casmag.outdir import save_atomic
from casmag.verdict import verdict


class Judged:
    """What every result class shares: its ``verdict`` made on construction when not given
    (casmag.verdict), ``trusted``, and :meth:`load`."""

    #: What :func:`result_kind` calls a saved result of this class.
    KIND = "translational"
    verdict: dict[str, Any] | None

    @classmethod
    def load(cls, folder: str | Path) -> Any:
        """A result saved by ``save``: result.json and, when saved, arrays.npz (arrays
        saved as None come back absent). Raises DataError naming the file when it is
        missing, not a casmag result, or a result of another class (named; the library's
        ``casmag.load_result`` reads any)."""
        folder = Path(folder)
        path = folder / "result.json"
        data = read_result_json(path)
        kind = result_kind(data)
        if kind != cls.KIND:
            raise DataError(f"{path}: a {kind} result; read it with casmag.load_result")
        names = {f.name for f in fields(cls)} - {"arrays"}  # type: ignore[arg-type]
        required = [
            f.name
            for f in fields(cls)  # type: ignore[arg-type]
            if f.name in names and f.default is MISSING and f.default_factory is MISSING
        ]
        absent = [n for n in required if n not in data]
        if absent:
            raise DataError(f"{path}: not a casmag result (no {', '.join(absent[:3])})")
        arrays: dict[str, np.ndarray] = {}
        if (folder / ARRAYS_FILE).is_file():
            with np.load(folder / ARRAYS_FILE, allow_pickle=False) as npz:
                arrays = {k: npz[k] for k in npz.files}
        return cls(**{k: v for k, v in data.items() if k in names}, arrays=arrays)

    def __post_init__(self) -> None:
        if self.verdict is None:
            self.verdict = verdict(self)

    @property
    def trusted(self) -> bool:
        """Solved, and the verdict found nothing against the estimate (casmag.verdict)."""
        return bool(self.verdict and self.verdict["trusted"])


@dataclass
class Result(Judged):
    """Outcome of one solve.

    Errors are position errors in metres against the truth without alignment (None when the
    data have no truth, or the solve failed). ``cost_blocks`` maps each named block to its
    value at the initial guess ("before") and at the solution ("after").
    ``hyperparameters_initial`` are the values the MAP started from: the assumed ones, except
    estimated sigma_f and lengthscale, which start where ``info["estimate_start"]`` says
    (``method``: both, marginal_likelihood or assumed; ``values``, ``assumed``, the marginal
    likelihood's details and, for both, each start's solve and the one ``chosen``; see
    casmag.translational.estimate_start). With both starts ``solve_seconds`` is their sum.

    Fields: ``info`` (name, source, seed, sample count, model settings, versions, warm-start
    stages, for recordings ``defaults`` and ``recording``); ``status`` (IPOPT's return
    status, or ``Odometry_Only``) and ``success``; ``iterations`` (of the final solve plus
    any start solves); ``build_seconds``, ``solve_seconds`` [s]; ``rmse_before``,
    ``max_before``, ``rmse_after``, ``max_after`` [m]; ``hyperparameters``: sigma_f and
    sigma_m [field units], lengthscale [m]; ``odometry_bias`` and ``odometry_bias_true``
    [m per step, per axis and session]; ``cost_per_iteration``,
    ``constraint_violation_per_iteration`` (the final solve's; ``convergence`` has every
    solve's objective, primal and dual infeasibility: casmag.nlp.Solution.trace);
    ``uncertainty`` (sigma_mean, sigma_max [m], NEES against the truth, or ``error``);
    ``warnings`` (casmag.checks: ``check``, ``column``, ``reason``); ``evaluation``: the
    errors again after an optional alignment to the truth, with the anchor that fixed the
    frame (casmag.evaluation; computed without alignment when not set); ``verdict``:
    whether the estimate can be trusted, the reasons and the checks (casmag.verdict).

    Arrays (N samples, d = 2 or 3 dimensions, a G x G map grid; absent or None when not
    computed): ``P_odometry``, ``P_estimate``, ``P_true`` (N, d) [m]; ``P_cov``,
    ``P_cov_uninflated`` (N, d, d) [m^2], the position covariance drawn and reported and the
    plain Laplace one; ``M_estimate`` (N, 3) the field at the estimate, ``Y`` (N, 3) the
    magnetometer [field units]; ``map_x``, ``map_y`` (G, G) [m]; ``map_field``, ``map_std``,
    ``map_prior_std`` (G, G, 3) [field units], the map, its posterior std given the
    estimated path and its prior std.
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
    hyperparameters_initial: dict[str, float]
    odometry_bias: list[float] | None
    odometry_bias_true: list[float] | None
    cost_blocks: dict[str, dict[str, float]]
    cost_per_iteration: list[float]
    constraint_violation_per_iteration: list[float]
    uncertainty: dict[str, Any] | None = None
    convergence: list[dict[str, Any]] = field(default_factory=list)
    warnings: list[dict[str, Any]] = field(default_factory=list)
    evaluation: dict[str, Any] | None = None
    verdict: dict[str, Any] | None = None
    arrays: dict[str, np.ndarray] = field(repr=False, default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary of everything but the arrays (non-finite floats as None)."""
        d = asdict(self)
        d.pop("arrays")
        d["evaluation"] = evaluation_of(self)
        d["units"] = {"errors": "m, no alignment", "seconds": "wall-clock s"}
        return finite_json(d)

    def save(self, out_dir: str | Path, figures: bool = True) -> Path:
        """Write result.json, trajectory.csv and (if figures) PNGs into out_dir atomically
        (:func:`casmag.outdir.save_atomic`: an existing out_dir is replaced only when it
        holds a previous casmag result)."""

        def write(tmp: Path) -> None:
            (tmp / "result.json").write_text(json.dumps(self.to_dict(), indent=2) + "\n")
            if self.arrays:
                write_trajectory_csv(self, tmp / "trajectory.csv")
                write_arrays(tmp, self.arrays)
            if figures and self.arrays:
                from casmag import plotting

                plotting.trajectory_figure(self, tmp / "trajectory.png")
                if self.info.get("sessions"):
                    plotting.sessions_figure(self, tmp / "sessions.png")
                if self.cost_per_iteration:
                    plotting.cost_figure(self, tmp / "cost.png")
                if self.arrays.get("map_field") is not None:
                    plotting.map_figure(self, tmp / "map.png")

        return save_atomic(out_dir, write)


#: The arrays of a saved result (numpy's npz; names as in Result.arrays).
ARRAYS_FILE = "arrays.npz"


def read_result_json(path: Path) -> dict[str, Any]:
    """A result.json as a mapping; DataError naming the file when it cannot be read."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise DataError(f"{path}: cannot read a casmag result ({exc})") from None
    if not isinstance(data, dict):
        raise DataError(f"{path}: not a casmag result (not a JSON object)")
    return data


def result_kind(data: dict[str, Any]) -> str:
    """``imu`` (errors per stage), ``planar`` (heading errors) or ``translational``: which
    result class a result.json was saved from."""
    if isinstance(data.get("errors"), dict) and "gp_slam" in data["errors"]:
        return "imu"
    if "heading_rms_deg_before" in data:
        return "planar"
    return "translational"


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


TRAJECTORY_COLUMNS = ("x", "y", "z")


def write_trajectory_csv(result: Result, path: Path) -> None:
    """One row per sample: index, odometry-only, estimate and (if known) true positions,
    and (when computed) the Laplace 1-sigma of the estimate per axis [m] and, in the plane,
    the x-y covariance [m^2]."""
    a = result.arrays
    dim = a["P_estimate"].shape[1]
    cols, names = [np.arange(a["P_estimate"].shape[0])], ["k"]
    for key, tag in (("P_odometry", "odo"), ("P_estimate", "est"), ("P_true", "true")):
        if key in a and a[key] is not None:
            cols.extend(a[key].T)
            names.extend(f"{c}_{tag}" for c in TRAJECTORY_COLUMNS[:dim])
    cov = a.get("P_cov")
    if cov is not None:
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
