"""Box or tiles: the map ``casmag slam`` gives a recording whose problem does not choose one.

The reduced-rank box (casmag.model.rrmap) makes every sample touch every weight, so its
KKT system holds a dense block of n_w weights and a dense border against the n_s pose
unknowns (knots, or one pose per sample for planar and pose recordings). Factoring it
costs about

    n_w^3 / 3 + n_s n_w^2  flops,

n_w = M (curl-free) or 3 M (squared exponential) plus the constant field, M the functions
with frequencies up to casmag.model.rrmap.OMEGA_FACTOR / l on the box around the dead
reckoning. On this project's 2-core machine that model matched IPOPT's measured time per
iteration at 3-5 GFLOP/s (README, Tiled map): a 2,000-sample translational walk with a
4,000-function curl-free box (2.8e10 flops, 6.8 s per iteration), the 1,586-sample
handheld ``library`` recording with a 4,000-function curl-free box (9.7e10, 30.4 s), and
the 747-sample ``square`` with a 580-function SE box (8.5e9, 1.7 s in the linear solves).
The tiles (casmag.gp.tiles) took 2.6-5.4 s per iteration on those recordings and on a
10,000-sample walk, whatever the area.

:func:`choose_map` keeps the box unless

1. its basis would be capped (more than casmag.gp.reduced_rank.MAX_NUM_BASIS functions):
   the box then holds only the lower frequencies, a map smoother than the field, while
   each tile holds frequencies up to casmag.model.tiledmap.TILE_OMEGA / l wherever the
   path goes; or
2. its factor would cost more than :data:`BOX_FLOPS_LIMIT` (about 12 s per iteration
   here, 2-5 times what the tiles took); or
3. its Hessian would not fit the memory budget (casmag.memory).

It keeps the box where the tiles measured slower: on the real robot sequences
(``results/real``: SE boxes of 580-1,185 functions over about 5 x 4 m with knots, at most
2e10 flops) the box solved sequence 5 (0.5 m drift) in 25 s to 0.012 m where the tiles
took 6:26 to 0.017 m; on sequence 2 the tiles reached 0.107 m against the box's 0.168 m,
but in 14:40 (README, Tiled map); in a room of a few metres the box has fewer unknowns than
the four tiles around a sample. The tiles need the curl-free
kernel, so choosing them changes an SE default to curl-free (and the caller estimates the
hyperparameters again for it); a kernel the user chose, several sessions, a saved map,
the filter baseline and sliding windows keep the box (``box_only``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from casmag import memory
from casmag.gp.kernels import FIELD_DIM
from casmag.gp.reduced_rank import MAX_NUM_BASIS, default_num_basis, domain_for
from casmag.model.rrmap import OMEGA_FACTOR

#: Largest factor cost [flops] of a box map's KKT system :func:`choose_map` keeps: about
#: 12 s per IPOPT iteration at the 4 GFLOP/s measured here (module docstring).
BOX_FLOPS_LIMIT = 5.0e10

#: The same for the translational model's box (casmag.model.rrmap), whose Hessian and KKT
#: solve ran at about 10 GFLOP/s of this cost model on 16,000-sample walks in a dipole field
#: over 6 x 6 m (casmag.experiments.dipolewalk, 2026-12-01, each run alone): 2.2e10 flops
#: 4.1 s per iteration (seed 1), 5.4e10 flops 5.8 s (seed 2), where the tiles took 12.8 s
#: per iteration on seed 2 and ended at 0.113 m (not trusted) against the box's 0.017 m.
#: 1e11 is about 10-11 s per iteration, below the tiles' time on that walk; the planar and
#: pose models' rotated box is slower per flop (library: 9.7e10 flops, 30.4 s) and keeps
#: :data:`BOX_FLOPS_LIMIT`.
TRANSLATIONAL_BOX_FLOPS_LIMIT = 1.0e11

#: ``model.gp.form`` value that asks for this choice (the default of ``casmag slam``).
AUTO = "auto"


@dataclass(frozen=True)
class BoxCost:
    """What the box around a path would hold: ``functions`` the basis functions with
    frequencies up to OMEGA_FACTOR / l (None: ``count_limit`` or more), ``weights`` the
    unknowns of the map (capped basis, constant field included), ``flops`` its KKT
    factor's cost, ``hessian_nonzeros`` its Hessian's upper triangle."""

    functions: int | None
    weights: int
    flops: float
    hessian_nonzeros: int

    @property
    def capped(self) -> bool:
        return self.functions is None or self.functions > MAX_NUM_BASIS


def box_cost(
    kernel: str,
    X: np.ndarray,
    lengthscale: float,
    state_unknowns: int,
    margin: float | None = None,
    count_limit: int = 1 << 20,
) -> BoxCost:
    """The box map's size and cost (module docstring) around positions X (N, d), for
    ``state_unknowns`` pose unknowns."""
    domain = domain_for(kernel, np.asarray(X, dtype=float), float(lengthscale), margin)
    count = default_num_basis(
        domain, float(lengthscale), omega_factor=OMEGA_FACTOR, max_basis=count_limit
    )
    functions = None if count >= count_limit else count
    M = MAX_NUM_BASIS if functions is None else min(functions, MAX_NUM_BASIS)
    n_w = M * (FIELD_DIM if kernel == "se" else 1) + FIELD_DIM
    n_s = int(state_unknowns)
    flops = n_w**3 / 3.0 + n_s * float(n_w) ** 2
    nonzeros = n_w * (n_w + 1) // 2 + n_s * n_w + 10 * n_s
    return BoxCost(functions, n_w, flops, nonzeros)


@dataclass(frozen=True)
class MapChoice:
    """The map chosen: ``form`` (``reduced_rank`` or ``tiled``), ``kernel``, the ``reason``
    in words and the box's figures it was chosen on."""

    form: str
    kernel: str
    reason: str
    box: BoxCost | None = None

    @property
    def tiled(self) -> bool:
        return self.form == "tiled"

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"form": self.form, "kernel": self.kernel, "reason": self.reason}
        if self.box is not None:
            out["box"] = {
                "functions_needed": self.box.functions,
                "function_cap": MAX_NUM_BASIS,
                "weights": self.box.weights,
                "factor_flops": self.box.flops,
                "flops_limit": BOX_FLOPS_LIMIT,
                "hessian_nonzeros": self.box.hessian_nonzeros,
            }
        return out


def choose_map(
    kernel: str,
    X: np.ndarray,
    lengthscale: float,
    state_unknowns: int,
    *,
    margin: float | None = None,
    memory_budget: float | None = None,
    box_only: str | None = None,
    flops_limit: float = BOX_FLOPS_LIMIT,
) -> MapChoice:
    """Box or tiles for a map around positions X (N, d) at ``lengthscale`` with
    ``state_unknowns`` pose unknowns (module docstring). ``kernel``: the one the problem
    would use with the box; ``memory_budget``: ``solver.memory_budget`` [GiB] (None: the
    machine's default); ``box_only``: why the tiles cannot serve (a kernel the user
    chose, several sessions, a saved map, the filter), which keeps the box and says why;
    ``flops_limit``: the largest factor cost of the box kept (the motion model's:
    :data:`BOX_FLOPS_LIMIT`, :data:`TRANSLATIONAL_BOX_FLOPS_LIMIT`)."""
    box = box_cost(kernel, X, lengthscale, state_unknowns, margin)
    needed = f"more than {MAX_NUM_BASIS:,}" if box.functions is None else f"{box.functions:,}"
    if box_only is not None:
        return MapChoice("reduced_rank", kernel, f"one box: {box_only}", box)
    if box.capped:
        why = (
            f"the box around the path would need {needed} basis functions for frequencies "
            f"up to {OMEGA_FACTOR:g} / l (l = {lengthscale:.3g} m) and holds {MAX_NUM_BASIS:,}, "
            "a map smoother than the field"
        )
    elif box.flops > flops_limit:
        why = (
            f"the box's {box.weights:,} weights, each touched by every sample, make a KKT "
            f"factor of about {box.flops:.2g} flops per iteration (limit {flops_limit:.2g})"
        )
    elif memory.solve_estimate(box.hessian_nonzeros) > memory.budget_bytes(memory_budget):
        why = (
            f"the box's Hessian ({box.hessian_nonzeros:,} non-zeros) would not fit the "
            f"memory budget of {memory.budget_bytes(memory_budget) / memory.GIB:.3g} GiB"
        )
    else:
        return MapChoice(
            "reduced_rank",
            kernel,
            f"one box of {box.functions:,} functions ({box.flops:.2g} flops per factor)",
            box,
        )
    return MapChoice("tiled", "curl_free", f"tiles: {why}", box)


def resolve_options(
    options: Any, X: np.ndarray, lengthscale: float, state_unknowns: int, box_only: str | None
) -> tuple[Any, MapChoice | None]:
    """The options of a planar or pose recording (PlanarOptions, PoseOptions) with
    ``form`` ``auto`` turned into the map :func:`choose_map` picks for positions X and the
    kernel it needs; other forms are returned unchanged, with no choice."""
    if options.form != AUTO:
        return options, None
    given = [h for h in ("sigma_f", "lengthscale") if getattr(options, h) != "estimate"]
    if box_only is None and options.kernel != "curl_free" and given:
        box_only = f"{' and '.join(given)} given for the {options.kernel} kernel"
    choice = choose_map(
        options.kernel,
        X,
        lengthscale,
        state_unknowns,
        margin=options.margin,
        memory_budget=options.solver.memory_budget,
        box_only=box_only,
    )
    return replace(options, form=choice.form, kernel=choice.kernel), choice


def box_needed(sessions: int, method: str, saved_map: bool) -> str | None:
    """Why a recording's solve needs the box whatever its size (None: it does not): a
    saved map to locate against, several sessions, or the filter baseline."""
    if saved_map:
        return "located against a saved map, which is one box"
    if sessions > 1:
        return "several sessions share one box"
    if method != "map":
        return f"the filter baseline ({method}) carries one box in its state"
    return None
