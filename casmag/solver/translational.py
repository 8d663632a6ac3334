"""Solving a translational problem: the batch MAP from the dead reckoning (or given
initial positions), with the estimated hyperparameters started from the windowed marginal
likelihood, the assumed values, or both kept by cost (``model.estimate_start``). The NLP
and its initial guess come from casmag.model.translational; the warm starts that call this
are casmag.solver.windowing, sliding and multisession.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from casmag.data.simulate import Dataset
from casmag.gp.hyper import estimate_conditional
from casmag.model.field import HYPERPARAMETERS
from casmag.model.translational import (
    Structure,
    cached_nlp,
    field_estimate,
    parameters_and_guess,
    positions,
)
from casmag.nlp import NLP, Solution, lowest_cost
from casmag.problem.spec import Problem


def estimate_start(
    problem: Problem, data: Dataset, s: Structure, initial_positions: np.ndarray | None = None
) -> dict[str, Any] | None:
    """Where the joint MAP starts the estimated sigma_f and lengthscale
    (``model.estimate_start``): None when neither is estimated; else a record with
    ``method``, ``values`` (the start of each estimated hyperparameter), ``assumed`` (the
    problem's values) and, for ``marginal_likelihood`` and ``both``, the estimate's details
    (casmag.gp.hyper.estimate_conditional at the initial positions, the other hyperparameters
    fixed at their assumed values, zero-mean field). With ``both`` the MAP is solved from
    ``values`` and from ``assumed`` (:func:`solve_translational`)."""
    free = [h for h in HYPERPARAMETERS if h in s.estimate and h != "sigma_m"]
    if not free:
        return None

    assumed = {
        "sigma_f": problem.assumed_sigma_f,
        "lengthscale": problem.assumed_lengthscale,
        "sigma_m": problem.assumed_sigma_m,
    }
    method = problem.spec.model.estimate_start
    record: dict[str, Any] = {"method": method, "assumed": {h: assumed[h] for h in free}}
    if method == "assumed":
        record["values"] = {h: assumed[h] for h in free}
        return record
    P0 = data.dead_reckoning() if initial_positions is None else initial_positions
    est = estimate_conditional(
        P0, data.Y, s.kernel, assumed, free, sigma_lin=problem.spec.model.gp.sigma_lin or 0.0
    )
    record["values"] = {h: est.values[h] for h in free}
    record["marginal_likelihood"] = {
        "neg_log_marginal": est.neg_log_marginal,
        "windows": est.n_windows,
        "samples": est.n_samples,
        "converged": est.converged,
        "iterations": est.iterations,
    }
    return record


def _better_of_two_starts(
    nlp: NLP,
    sol: Solution,
    params: dict[str, Any],
    x0: dict[str, Any],
    start: dict[str, Any],
    progress: Any,
) -> Solution:
    """``estimate_start: both``: ``sol`` was solved from the marginal-likelihood start; solve
    again from the assumed values and keep the solution with the lower MAP cost (a
    successful solve before a failed one). Records both solves in ``start`` (``solves``,
    ``chosen``; ``values`` becomes the chosen start); the kept solution's solve_seconds is
    the sum of both solves."""
    ml = dict(start["values"])
    x0_assumed = dict(x0)
    for h, value in start["assumed"].items():
        x0_assumed[f"log_{h}"] = np.log(value)
    other = nlp.solve(params, x0_assumed, progress=progress)
    solves = {"marginal_likelihood": (ml, sol), "assumed": (dict(start["assumed"]), other)}
    names = list(solves)
    best_ok = lowest_cost([solves[k][1] for k in names])
    chosen = (
        names[best_ok]
        if best_ok is not None
        else min(names, key=lambda k: solves[k][1].objective)  # both failed: the lower
    )
    start["solves"] = {
        k: {
            "start": v,
            "objective": s.objective,
            "status": s.status,
            "iterations": s.iterations,
            "solve_seconds": s.solve_seconds,
        }
        for k, (v, s) in solves.items()
    }
    start["chosen"] = chosen
    start["values"] = solves[chosen][0]
    best = solves[chosen][1]
    best.solve_seconds = sol.solve_seconds + other.solve_seconds
    return best


def solve_translational(
    problem: Problem,
    data: Dataset,
    progress: Any = None,
    initial_positions: np.ndarray | None = None,
) -> tuple[Solution, NLP, dict[str, float], np.ndarray, Structure]:
    """Solve the problem on a data set. Returns the solution (``sol.x["P"]`` holds the
    estimated positions), the NLP, the final hyperparameters (estimated or fixed), the
    (N, 3) field estimate at the samples and the problem's structure."""
    s = Structure.of(problem, data, initial_positions)
    nlp = cached_nlp(s)
    start = estimate_start(problem, data, s, initial_positions)
    params, x0 = parameters_and_guess(
        problem, data, s, initial_positions, None if start is None else start["values"]
    )
    sol = nlp.solve(params, x0, progress=progress)
    if start is not None and start["method"] == "both":
        sol = _better_of_two_starts(nlp, sol, params, x0, start, progress)
    if start is not None:
        sol.stats["estimate_start"] = start
    hyper = {
        h: float(np.exp(sol.x[f"log_{h}"][0, 0])) if h in s.estimate else float(params[h])
        for h in HYPERPARAMETERS
    }
    sol.x["P"] = positions(s, sol, params["Q"])
    return sol, nlp, hyper, field_estimate(s, sol, sol.x["P"]), s
