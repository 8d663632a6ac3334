"""Warm-start strategies written once for every motion model.

A motion model is seen by the strategies as a :class:`StagedModel` (the translational
model: casmag.solver.translational.TranslationalStaged; planar, pose and IMU:
casmag.solver.planar, pose and imu) whose solve starts from its own states (positions,
heading or orientation, biases):

- :meth:`StagedModel.start`: the dead reckoning of the first k samples, with a heading-rate
  bias removed (a start of its own, :func:`solve_starts`);
- :meth:`StagedModel.continue_from`: a solve of the first m samples continued to k >= m
  samples by the odometry with the biases it estimated removed (a growing prefix's start,
  or with k = m the same states again: a coarse-to-fine stage's);
- :meth:`StagedModel.solve`: the first k samples' MAP problem from a start, with given IPOPT
  settings and lengthscale; the full problem's map box is laid around the dead reckoning
  (its basis is fixed by the assumed lengthscale), a prefix's around its start.

On that interface the strategies of ``solver.warm_start`` are written once
(:func:`solve_strategy`): ``none`` (one batch from the dead reckoning), ``growing``
(prefixes ``growth`` times longer, casmag.solver.windowing.grow), ``coarse-to-fine``
(the full problem with the lengthscale shrinking geometrically from ``lengthscale_start``
times the assumed one to it, each stage from the previous one's states with the map fitted
again at the new lengthscale) and ``sliding`` (:func:`solve_sliding`: a fixed-lag smoother
whose windows carry the map as a Gaussian prior, through the window methods of
:class:`StagedModel`: the model's window NLP is its own motion model with a
casmag.model.field.WindowField read through its rotation); and several starts kept by MAP
cost run the strategy from each start (:func:`solve_starts`); several sessions of one field
(``session_starts``) share one map, added one at a time (:func:`solve_sessions`). Every
stage before the last stops after ``stage_max_iter`` iterations. With truth,
:func:`truth_check` solves a poor estimate's problem again from the true states and flags
``wrong_basin`` when that costs less.
"""

from __future__ import annotations

import dataclasses
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from casmag.model.knots import Knots
from casmag.model.rotated import rotated_design, window_unknowns
from casmag.model.tiledmap import home_points
from casmag.nlp import NLP, STALLED, Solution, lowest_cost, merge_rounds
from casmag.problem.imu import STAGED_STRATEGIES
from casmag.problem.spec import SolverSpec, WarmStartSpec
from casmag.result.metrics import rmse_and_max
from casmag.solver.uncertainty import sample_state_uncertainty, saved_field_map
from casmag.solver.windowing import (
    ACCEPTED,
    continues,
    grow,
    laplace_block,
    lengthscale_schedule,
    stage_lengths,
    window_size,
    window_starts,
)

#: What a start removes from the odometry before its dead reckoning: a heading-rate bias
#: [rad/s] for the models with a heading, a per-step odometry bias ((d,) [m per step],
#: casmag.solver.biasscan) for the translational model; 0 the dead reckoning itself.
StartBias = float | np.ndarray

#: With truth (evaluation), an estimate whose position RMSE is above this fraction of the
#: dead reckoning's (the real-data criterion of 1/4) is solved again from the truth; a
#: lower MAP cost there flags it ``wrong_basin``. Measured on the handheld ``square``
#: recording: estimate 1.15 m from 2.33 m at cost 1,379.4; from the truth 0.22 m at cost
#: 1,349.2 in 37 iterations (about 45 s beside the 4.1 min solve).
TRUTH_START_RATIO = 0.25


#: A tiled stage whose samples moved beyond the Hessian pattern laid around their
#: ``home`` grid points is stopped and solved on from where it stopped with the pattern
#: laid around the samples' new places, at most this many times (the last round keeps
#: the dropped products' stand-ins, casmag.model.tiledmap.add_own_tiles).
REHOMES = 4


def solve_rehomed(
    structure: Any,
    nlp_of: Callable[..., NLP],
    params: dict[str, Any],
    x0: dict[str, np.ndarray],
    where: int | Callable[[Solution], np.ndarray],
    **solve: Any,
) -> tuple[Solution, NLP, Any]:
    """Solve ``nlp_of(structure)`` from x0 (``solve``: :meth:`NLP.solve`'s options); for a
    tiled map (``structure.tiled``) stop as soon as a Hessian evaluation drops samples'
    border products and solve on from there with ``home`` moved to the samples' nearest
    grid points (``where``: the samples' positions in a solution, or the number of leading
    coordinates of its ``P`` that are), up to :data:`REHOMES` times;
    those rounds' NLPs are built with ``nlp_of(structure, cache=False)``, so that none
    outlives its use (measured on ``square``: 6.3 GiB peak when the process's NLP cache
    held them). Returns the rounds' merged solution, the last NLP and its structure."""
    nlp = nlp_of(structure)
    rounds: list[Solution] = []
    for r in range(REHOMES + 1):
        watch = structure.tiled and nlp.keep is not None and r < REHOMES
        sol = nlp.solve(params, x0, stop_when=_dropped(nlp) if watch else None, **solve)
        rounds.append(sol)
        if not (watch and sol.status == STALLED and _dropped(nlp)()):
            break
        at = sol.x["P"][:, :where] if isinstance(where, int) else where(sol)
        home = home_points(structure.grid, at)
        structure = dataclasses.replace(structure, home=home)
        nlp, x0 = None, sol.x  # the last round's NLP freed before the next is built
        nlp = nlp_of(structure, cache=False)
    return (rounds[0] if len(rounds) == 1 else merge_rounds(rounds)), nlp, structure


def _dropped(nlp: NLP) -> Callable[[], bool]:
    """Whether the tiled Hessian callback's last evaluation dropped border products."""
    hess = nlp.keep[1]
    return lambda: bool(hess.dropped) and hess.dropped[-1] > 0


@dataclass
class StageProblem:
    """A stage's MAP problem set up from a start (:meth:`StagedModel.stage_problem`): the
    structure its NLP is built from, the builder ``nlp_of(structure, cache=...)``, the
    parameters, the initial guess x0 (the start with its map fitted), where the samples'
    positions are (:func:`solve_rehomed`) and the unknowns held at x0."""

    structure: Any
    nlp_of: Callable[..., NLP]
    params: dict[str, Any]
    x0: dict[str, np.ndarray]
    where: int | Callable[[Solution], np.ndarray]
    fixed: tuple[str, ...] = ()

    def cost(self, nlp: NLP | None = None) -> float:
        """The MAP cost at x0 (every cost block), from ``nlp`` (default: the structure's,
        built for this and not kept)."""
        nlp = self.nlp_of(self.structure, cache=False) if nlp is None else nlp
        x, p = nlp.x_layout.pack(self.x0), nlp.p_layout.pack(self.params)
        return float(sum(nlp.evaluate_blocks(x, p).values()))

    def solve(self, progress: Any = None) -> tuple[Solution, NLP, Any]:
        """:func:`solve_rehomed` from x0."""
        return solve_rehomed(
            self.structure, self.nlp_of, self.params, self.x0, self.where,
            progress=progress, fixed=self.fixed,
        )  # fmt: skip


@dataclass
class Solved:
    """One solve of a staged model: IPOPT's solution, the NLP, the structure it was built
    from (its map box or tiles), the lengthscale it ran with, and what the model needs
    besides (``nominal``: the orientations a pose solve is linearised about; ``first``: a
    window's first sample)."""

    sol: Solution
    nlp: NLP
    structure: Any
    lengthscale: float
    nominal: Any = None
    first: int = 0


class StagedModel(ABC):
    """A motion model's MAP problem on one recording, as the warm-start strategies see it
    (module docstring). ``n``: samples; ``solver``: the full problem's IPOPT settings;
    ``lengthscale``: the assumed lengthscale [m]."""

    n: int
    solver: SolverSpec
    lengthscale: float
    #: The first sample of each session (several recordings of one field, one map:
    #: :func:`solve_sessions`); a model with more than one continues a session it has not
    #: reached from that session's known start (:meth:`extend`).
    session_starts: tuple[int, ...] = (0,)

    @abstractmethod
    def start(self, k: int, bias: StartBias = 0.0) -> dict[str, np.ndarray]:
        """The dead reckoning of the first k samples with a start's ``bias`` (StartBias: a
        heading-rate bias [rad/s] for the models with a heading) removed, as the states a
        solve starts from."""

    def world_readings(self, states: dict[str, np.ndarray]) -> np.ndarray:
        """The magnetometer readings of the samples ``states`` holds, turned into the world
        frame by their heading or attitude (a start's scan, casmag.solver.biasscan)."""
        raise NotImplementedError(f"{type(self).__name__} turns no readings")

    @abstractmethod
    def states(self, solved: Solved) -> dict[str, np.ndarray]:
        """A solve's estimate as states (positions ``P``, the orientation, the biases)."""

    @abstractmethod
    def extend(self, states: dict[str, np.ndarray], k: int) -> dict[str, np.ndarray]:
        """States of the first m samples continued to k >= m samples by the odometry with
        their biases removed."""

    def sessions(self, k: int) -> list[tuple[int, int]]:
        """(first, end) of each session the first k samples reach, cut at k."""
        ends = [*self.session_starts[1:], self.n]
        return [(a, min(e, k)) for a, e in zip(self.session_starts, ends, strict=True) if a < k]

    def continue_from(self, previous: Solved, k: int) -> dict[str, np.ndarray]:
        """The previous solve's states, continued to k samples by the odometry with the
        biases it estimated removed."""
        return self.extend(self.states(previous), k)

    @abstractmethod
    def solve(
        self, k: int, start: dict[str, np.ndarray], solver: SolverSpec, lengthscale: float
    ) -> Solved:
        """The first k samples' problem from ``start`` (module docstring for its box)."""

    #: Whether :meth:`turned` and :meth:`stage_problem` are there (a heading about the
    #: vertical to turn), for :func:`best_turn`.
    turns: bool = False

    #: A saved map the recording is located against (planar and pose models), or None.
    prior_map: PriorMap | None = None
    #: (sigma_m, s) of the whole recording located against a held saved map
    #: (:meth:`PriorMap.held_noise`), fixed by its first problem (:meth:`held_sigma_m`).
    noise_on_held_map: tuple[float, float] | None = None

    def held_sigma_m(self, P: np.ndarray) -> float:
        """The magnetometer noise of the whole recording located against the saved map held
        at its mean, widened by the map's uncertainty along P, the first start of that
        stage (every later problem of it, the turn search's trials too, keeps it, so their
        costs compare)."""
        assert self.prior_map is not None
        if self.noise_on_held_map is None:
            self.noise_on_held_map = self.prior_map.held_noise(P)
        return self.noise_on_held_map[0]

    def final_sigma_m(self, sigma_m: float) -> float:
        """The magnetometer noise of the whole recording's solve: :meth:`held_sigma_m`'s
        when the map was held, else ``sigma_m``."""
        held = self.noise_on_held_map
        return sigma_m if held is None else held[0]

    def turned(self, states: dict[str, np.ndarray], k: int, turn: float) -> dict[str, np.ndarray]:
        """States of the first k samples turned about the vertical, about the first
        position, by an angle growing linearly in time from 0 at the first sample to
        ``turn`` [rad] at the last: a heading-rate -turn / duration removed, as
        :meth:`start` removes one from the dead reckoning."""
        raise NotImplementedError(f"{type(self).__name__} has no heading to turn")

    def stage_problem(
        self, k: int, start: dict[str, np.ndarray], solver: SolverSpec, lengthscale: float,
        structure: Any = None, coarse: bool = False,
    ) -> StageProblem:  # fmt: skip
        """The first k samples' problem from ``start`` as :meth:`solve` sets it up, on
        ``structure`` when one is given (the map laid around another start); ``coarse``
        (a problem whose cost compares starts, :func:`best_turn`): a lattice of bumps at a
        prefix's spacing (:func:`lattice_field`) whatever k, and a saved map to locate
        against held at its mean (:meth:`PriorMap.solve_inputs`; the whole recording's
        costs then differ from those of its update by a constant)."""
        raise NotImplementedError(f"{type(self).__name__} sets up no stage problem")

    # Sliding windows (:func:`solve_sliding`); a model without them refuses the strategy.
    #: Names of the states with one row per sample (the rest are biases).
    sample_states: tuple[str, ...] = ("P",)

    def step_lengths(self) -> np.ndarray:
        """Length of each odometry step [m] (the automatic window length)."""
        raise NotImplementedError(f"{type(self).__name__} has no sliding windows")

    def window_prior(self) -> WindowPrior:
        """The prior of the windows' map (one box around the whole recording)."""
        raise NotImplementedError(f"{type(self).__name__} has no sliding windows")

    def window_start(
        self, a: int, k: int, anchor: dict[str, np.ndarray] | None,
        carried: dict[str, np.ndarray] | None, bias: dict[str, np.ndarray],
    ) -> dict[str, np.ndarray]:  # fmt: skip
        """The window of samples [a, a + k): the states ``carried`` from the previous window
        (samples a, a + 1, ...; None for the first) continued by the odometry with the
        total ``bias`` removed, from ``anchor`` (the state at a; None: the model's start)."""
        raise NotImplementedError(f"{type(self).__name__} has no sliding windows")

    def solve_window(self, w: Window) -> Solved:
        """The window ``w`` (:class:`Window`): its samples with the total ``w.bias`` removed
        from their odometry, its own bias unknowns the increments on it (prior: zero mean,
        covariance ``w.bias_cov[name]``, the previous window's Laplace marginal of each; None
        for the model's own prior), its first state under a prior at ``w.anchor`` with
        standard deviations ``w.anchor_sigma`` or the whole covariance ``w.anchor_cov`` (its
        states in the order of :meth:`anchor_indices`; None: the model's known start and its
        own priors), the map under ``w.prior``; its states are those of :meth:`states` with
        the increments as biases."""
        raise NotImplementedError(f"{type(self).__name__} has no sliding windows")

    def anchor_indices(self, solved: Solved, j: int) -> dict[str, np.ndarray]:
        """Where the state of the window's sample j sits in its NLP's x vector, per state."""
        raise NotImplementedError(f"{type(self).__name__} has no sliding windows")

    def window_design(self, solved: Solved, m: int) -> tuple[np.ndarray, np.ndarray]:
        """(J, y): the first m samples' magnetometer readings y = J z + noise, linear in
        the window map's unknowns z at the solved poses."""
        raise NotImplementedError(f"{type(self).__name__} has no sliding windows")

    def window_inside(self, solved: Solved) -> bool:
        """The window's positions (those the map reads) stayed inside its map's box."""
        domain = solved.structure.hilbert_basis().domain
        center, half = np.asarray(domain.center), np.asarray(domain.half_width)
        P = np.asarray(self.states(solved)["P"])
        d = min(P.shape[1], center.size, getattr(solved.structure, "map_dim", P.shape[1]))
        P, lo, hi = P[:, :d], center[:d] - half[:d], center[:d] + half[:d]
        return bool(np.all(np.isfinite(P)) and np.all(P >= lo) and np.all(P <= hi))

    def joined(self, states: dict[str, np.ndarray], bias: dict[str, np.ndarray]) -> dict:
        """The whole recording's states (as :meth:`states`) from the windows' per-sample
        states and the total ``bias``: the start of the full problem."""
        raise NotImplementedError(f"{type(self).__name__} has no sliding windows")


@dataclass(frozen=True)
class Window:
    """What a window's solve is given (:meth:`StagedModel.solve_window`, :func:`slide`):
    its samples [first, first + samples), the states it starts from, its anchor (the state
    at its first sample; None for the first window) with that state's Laplace marginal
    standard deviations and whole covariance from the previous window (None: none), the
    total biases removed from its odometry with the covariance blocks of the previous
    window's increments (None: none), the map's prior and the IPOPT settings."""

    first: int
    samples: int
    start: dict[str, np.ndarray]
    anchor: dict[str, np.ndarray] | None
    anchor_sigma: dict[str, np.ndarray] | None
    anchor_cov: np.ndarray | None
    bias: dict[str, np.ndarray]
    bias_cov: dict[str, np.ndarray] | None
    prior: WindowPrior
    solver: SolverSpec


@dataclass
class WindowPrior:
    """The windows' map prior in information form: 0.5 z^T Lam z - eta^T z on its unknowns
    z, updated by each window's committed samples (:meth:`observe`)."""

    eta: np.ndarray
    Lam: np.ndarray
    sigma_m: float

    @classmethod
    def gp(cls, basis: Any, kernel: str, sigma_lin: float, sigma_m: float) -> WindowPrior:
        """The GP prior of a rotated map's unknowns z = [vec(V); c]
        (casmag.model.rotated.rotated_design): unit precision on the whitened weights,
        1 / sigma_lin^2 on the constant field, zero mean."""
        nz = window_unknowns(basis, kernel)
        diag = np.ones(nz)
        diag[nz - 3 :] = sigma_lin**-2.0
        return cls(np.zeros(nz), np.diag(diag), sigma_m)

    @property
    def mean(self) -> np.ndarray:
        return np.linalg.solve(self.Lam, self.eta)

    def posterior_mean(self, J: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The mean given the readings y = J z (not committed): a window's map start."""
        s2 = self.sigma_m**2
        return np.linalg.solve(self.Lam + J.T @ J / s2, self.eta + J.T @ y / s2)

    def start(self, J: np.ndarray, y: np.ndarray, num_basis: int) -> dict[str, np.ndarray]:
        """A window's map unknowns ``W`` (whitened weights, num_basis rows) and ``c`` at
        :meth:`posterior_mean` of its readings y = J z at its start."""
        z = self.posterior_mean(J, y)
        nv = z.size - 3
        return {"W": z[:nv].reshape(num_basis, -1, order="F"), "c": z[nv:].reshape(3, 1)}

    def observe(self, J: np.ndarray, y: np.ndarray) -> None:
        s2 = self.sigma_m**2
        self.Lam = self.Lam + J.T @ J / s2
        self.eta = self.eta + J.T @ y / s2


@dataclass(frozen=True)
class PriorMap:
    """A saved map (casmag.gp.savedmap.SavedMap, ``saved``: its box's basis key or tile
    grid, kernel and sigma_m) as the prior of a staged model's map, to locate a recording
    against it, and the saved posterior of the NLP's map unknowns z = [vec(V); c]
    (whitened weights, casmag.model.rotated and casmag.model.tiledmap.RotatedTiledModel),
    mean and precision. A map saved without a constant field holds c at zero (a precision
    of 1 / (1e-9 sigma_m)^2). ``held``: every solve holds the map at its mean
    (``--hold-map``: the recording located, the map not updated), the whole recording's
    with the magnetometer's noise widened by the map's own uncertainty
    (:meth:`held_noise`)."""

    saved: Any
    mean: np.ndarray
    precision: np.ndarray
    held: bool = False

    @classmethod
    def of(cls, saved: Any, held: bool = False) -> PriorMap:
        if saved.tiles is None:
            S = saved.basis().prior_variances(saved.kernel, saved.sigma_f, saved.lengthscale)
        else:  # every tile's functions have the same prior variances
            S = saved.tiled_basis().prior_variances(saved.sigma_f, saved.lengthscale)
        cols = saved.num_weights // saved.num_basis
        d = np.concatenate([np.tile(np.sqrt(np.ravel(S)), cols), np.ones(3)])
        mean, precision = np.zeros(d.size), np.zeros((d.size, d.size))
        n = saved.size
        mean[:n], precision[:n, :n] = saved.mean, saved.precision
        if not saved.constant_field:
            precision[n:, n:] = np.eye(3) * (1e-9 * saved.sigma_m) ** -2
        # W = sqrt(S) V: the mean divided by d, the precision scaled by d on both sides
        return cls(saved, mean / d, d[:, None] * precision * d, held)

    @property
    def basis(self) -> tuple | None:
        """The saved box's basis key (None: tiles)."""
        return None if self.tiled else self.saved.basis_key

    @property
    def grid(self) -> Any:
        """The saved tiles' grid (casmag.gp.tiles.TileGrid; None: a box)."""
        return self.saved.tiles

    @property
    def kernel(self) -> str:
        return self.saved.kernel

    @property
    def sigma_m(self) -> float:
        return self.saved.sigma_m

    @property
    def tiled(self) -> bool:
        return self.saved.tiles is not None

    def held_noise(self, P: np.ndarray) -> tuple[float, float]:
        """(sigma_m widened, s) for the whole recording located against the map held at its
        mean: sqrt(sigma_m^2 + s^2), s the RMS of the map's posterior standard deviation at
        positions P (k, d) (as casmag.solver.localize's step 2), so that a map that knows
        little does not give a confident path."""
        s = float(np.sqrt(np.mean(self.saved.std(P[:, : self.saved.dim]) ** 2)))
        return float(np.hypot(self.sigma_m, s)), s

    def window_prior(self) -> WindowPrior:
        """The windows' prior (:func:`slide`), a copy each call (the windows update it)."""
        return WindowPrior(self.precision @ self.mean, self.precision.copy(), self.sigma_m)

    def _on_map(self, structure: Any, P: np.ndarray, **changes: Any) -> Any:
        """The structure on the saved box, or on the saved tiles with each sample's home
        grid point at P (which fixes the Hessian's pattern)."""
        if self.tiled:
            home = home_points(self.grid, P)
            return dataclasses.replace(structure, basis=None, grid=self.grid, home=home, **changes)
        return dataclasses.replace(structure, basis=self.basis, **changes)

    def _held(self) -> dict[str, np.ndarray]:
        """The NLP's map unknowns at the saved mean: W (the box's functions, or each tile's,
        a column per tile or field component) and c."""
        nv = self.mean.size - 3
        return {
            "W": self.mean[:nv].reshape(self.saved.num_basis, -1, order="F"),
            "c": self.mean[nv:].reshape(3, 1),
        }

    def solve_inputs(
        self, structure: Any, P: np.ndarray, R: np.ndarray, Y: np.ndarray, sigma_f: float,
        lengthscale: float, hold: bool,
    ) -> tuple[Any, dict[str, np.ndarray], dict[str, np.ndarray], tuple[str, ...]]:  # fmt: skip
        """What a staged model's solve changes under this prior: its structure on the saved
        box or tiles, the parameters of its map block, the map's start and the map's
        unknowns to hold fixed.

        ``hold`` (a prefix of the recording, :func:`solve_strategy`; every solve when
        :attr:`held`): the map is held at the saved mean (the structure's own GP prior is
        then a constant), so IPOPT factorises the path alone, and the NLP carries no dense
        block to build; the path is located against the map. Else (the whole recording)
        the block ``map_prior`` (a window structure; the tiles' ``saved_prior``) puts the
        saved posterior in place of the GP prior, and the map is free: the box's from its
        mean given the readings Y (k, 3) at positions P (k, d) with body-to-map rotations
        R (k, 3, 3), the tiles' from the saved mean. The map is updated by the recording
        (at the real field's 3,675 unknowns the dense prior costs about 6 s an
        iteration)."""
        if hold or self.held:
            return self._on_map(structure, P), {}, self._held(), ("W", "c")
        s = self._on_map(structure, P, window=True)
        params = {"map_mean": self.mean.reshape(-1, 1), "map_precision": self.precision}
        if self.tiled:
            return s, params, self._held(), ()
        basis = s.hilbert_basis()
        J = rotated_design(basis, self.kernel, P, R, sigma_f, lengthscale)
        return s, params, self.window_prior().start(J, np.reshape(Y, -1), basis.num_basis), ()


#: Status of a window whose states left its map's box (IPOPT itself stopped normally).
LEFT_BOX = "Left_Map_Box"


@dataclass
class Stage:
    """One solve of a strategy: its kind (``prefix``, ``lengthscale``, ``window``,
    ``batch``), samples, lengthscale, the solve, and its first sample (a window's);
    a window's ``handed``: the Laplace marginal standard deviations of its bias increments
    it hands the next window as prior (None: none handed), ``left_box``: its states left
    the map's box (the smoother ended there)."""

    kind: str
    samples: int
    lengthscale: float
    solved: Solved
    first: int = 0
    handed: dict[str, np.ndarray] | None = None
    left_box: bool = False
    turn: dict[str, Any] | None = None

    @property
    def status(self) -> str:
        """IPOPT's status, or :data:`LEFT_BOX`."""
        return LEFT_BOX if self.left_box else self.solved.sol.status


def map_lengthscale(tiled: bool, assumed: float, stage: float) -> float:
    """The lengthscale a stage's map is laid for. Tiles follow the stage's lengthscale
    (coarse-to-fine): a lattice of bumps is its lengthscale (casmag.gp.bumps), and a coarser
    lattice smooths the field that stage sees, which widens the basin the dead reckoning
    starts in. A box keeps the assumed lengthscale's basis, with its prior at the stage's."""
    return float(stage) if tiled else float(assumed)


def lattice_field(k: int, n: int, field: tuple[float, float] | None) -> tuple[float, float] | None:
    """The field (sigma_f, sigma_m) a stage of k of the n samples lays its bump lattice
    from (casmag.model.tiledmap.bump_spacing): the full problem's, and none for a growing
    prefix, which takes the coarsest lattice (BUMP_SPACING). A prefix only starts the next
    stage, and a sample's Hessian costs the square of the nodes it touches, so the rule's
    finer lattice is paid once, in the full problem. Measured 2026-12-02 (Intel Xeon, 2
    cores, each run alone) on ``problems/planar/walk.yaml`` with tiles and the curl-free
    kernel: the 1,500-sample floor walk over 30 x 20 m (dipoles; the rule 0.53 l) solved
    in 283 s against 430 s, 2.9 against 3.4 GB, the same optimum (cost 2,848.061, RMSE
    0.1753 m); the same walk in a field drawn from the GP (``simulation.field.method:
    fourier``, the rule 0.53 l) 147 s against 207 s, the same optimum (2,015.068, 0.1257 m;
    the full problem took two re-homed rounds, 39 iterations, against one of 29, and the
    prefixes 13 s against 80 s); 750 samples over 15 x 10 m, seeds 1 / 2 / 3: 23.1 / 21.2
    / 17.8 s against 32.4 / 27.0 / 21.7 s, RMSE unchanged (0.0506 / 0.0685 / 0.0530 m)."""
    return field if k == n else None


def solve_strategy(
    model: StagedModel, ws: WarmStartSpec, bias: StartBias = 0.0, n: int | None = None
) -> list[Stage]:
    """The strategy ``ws.strategy`` from the dead reckoning with ``bias`` removed; the
    stages solved, the last being the full problem (or the first ``n`` samples) with the
    full settings unless a stage ended the strategy
    (:func:`casmag.solver.windowing.continues`)."""
    n, ell = model.n if n is None else n, model.lengthscale
    stage_solver = model.solver.model_copy(update={"max_iter": ws.stage_max_iter})
    if ws.strategy == "growing":
        sizes = stage_lengths(n, ws.first_samples, ws.growth)

        turns: dict[int, dict[str, Any] | None] = {}

        def prefix(k: int, prev: Solved | None, last: bool) -> tuple[Solution, Solved]:
            solver_k = model.solver if last else stage_solver
            start = model.start(k, bias) if prev is None else model.continue_from(prev, k)
            if prev is not None and ws.turn:
                start, turns[k] = best_turn(model, k, start, solver_k, ell)
            solved = model.solve(k, start, solver_k, ell)
            return solved.sol, solved

        return [
            Stage("prefix", k, ell, solved, turn=turns.get(k))
            for k, _, solved in grow(sizes, prefix)
        ]
    if ws.strategy == "coarse-to-fine":
        schedule = lengthscale_schedule(ell, ws.lengthscale_start, ws.lengthscale_stages)
        stages: list[Stage] = []
        start = model.start(n, bias)
        for i, ell_i in enumerate(schedule):
            last = i == len(schedule) - 1
            solved = model.solve(n, start, model.solver if last else stage_solver, ell_i)
            stages.append(Stage("batch" if last else "lengthscale", n, ell_i, solved))
            if not continues(solved.sol, last):
                break
            start = model.continue_from(solved, n)
        return stages
    if ws.strategy == "sliding":
        if n != model.n:
            raise ValueError("sliding windows solve a whole recording, not its first samples")
        return solve_sliding(model, ws, bias)
    if ws.strategy != "none":
        raise ValueError(f"warm start {ws.strategy!r}: staged models take {STAGED_STRATEGIES}")
    return [Stage("batch", n, ell, model.solve(n, model.start(n, bias), model.solver, ell))]


#: The turn search of a continued start (:func:`best_turn`): its first trial turns the
#: start by this angle at its last sample [deg], each further trial doubles it up to
#: TURN_MAX_DEG, then golden-section steps narrow the bracket to TURN_TOL_DEG, or until
#: its ends cost within TURN_COST_TOL (a MAP cost difference) of its best.
TURN_FIRST_DEG = 1.0
TURN_MAX_DEG = 32.0
TURN_TOL_DEG = 0.5
TURN_COST_TOL = 1.0


def best_turn(
    model: StagedModel, k: int, start: dict[str, np.ndarray], solver: SolverSpec, ell: float
) -> tuple[dict[str, np.ndarray], dict[str, Any] | None]:
    """The start of a continued stage (a growing prefix from the previous one's estimate)
    turned about the vertical (:meth:`StagedModel.turned`: a heading-rate correction, the
    drift of heading odometry) by the angle of lowest MAP cost, each trial's map fitted to
    it on the map laid around the start as it came (bumps on a prefix's lattice, whose fit
    costs a quarter of the finest's: the search only compares starts; a saved map to locate
    against is held at its mean, which skips its dense prior: on the 300-sample planar walk
    located on its tiled map, 2,079 unknowns, seed 1, the search took 0.3 s instead of 8.5
    s and found the same turn); the turn found (None:
    no search, a model without a heading or with several sessions). The cost only falls:
    the start is kept when neither first trial lowers it.

    Why: a prefix's estimate continued by the odometry carries the prefix's heading-rate
    error into the new samples, and the next solve then turns the whole path and map
    together by Newton steps that cover about a tenth of the remaining turn each (the map
    lives on a fixed lattice, so a turn is curved in its weights). Measured 2026-12-03
    (Intel Xeon, 2 cores, each run alone, each pair one after the other) with
    ``problems/planar/walk.yaml``, tiles and the curl-free kernel, before -> after, the
    same optimum each: 1,500 samples over 30 x 20 m in the dipole field, the full problem
    15 + 33 iterations in two re-homed rounds -> 31 in one (turned 12.9 deg; the search
    6 s), 6:06 -> 2:48 wall, 2.94 -> 2.32 GB; the same walk in a field drawn from the GP
    18 + 21 -> 22 iterations, 4:06 -> 3:00, 2.81 -> 2.43 GB; 750 samples over 15 x 10 m,
    seeds 1 / 2 / 3: 13 / 13 / 11 -> 9 / 12 / 9 iterations, 0:43 / 0:38 / 0:33 -> 0:39 /
    0:46 / 0:39 wall (the search, about 5 s, costs what it saves); the 300-sample planar
    and pose walks with the box (seeds 1-10 each): the same optimum and iterations on 19
    of 20, the search 0.2-0.5 s (planar) and 1.1-4.8 s (pose)."""
    if not model.turns or len(model.sessions(k)) > 1:
        return start, None
    t0 = time.perf_counter()
    base = model.stage_problem(k, start, solver, ell, coarse=True)
    nlp = base.nlp_of(base.structure, cache=False)
    costs: dict[float, float] = {0.0: base.cost(nlp)}

    def f(turn: float) -> float:
        if turn not in costs:
            cand = model.turned(start, k, turn)
            trial = model.stage_problem(k, cand, solver, ell, base.structure, coarse=True)
            costs[turn] = trial.cost(nlp)
        return costs[turn]

    step, top, tol = (np.radians(v) for v in (TURN_FIRST_DEG, TURN_MAX_DEG, TURN_TOL_DEG))
    if min(f(step), f(-step)) < costs[0.0]:
        b = step if f(step) < f(-step) else -step
        a, c = 0.0, float(np.clip(2.0 * b, -top, top))
        while c != b and f(c) < f(b):  # downhill, doubling, up to the largest turn
            a, b, c = b, c, float(np.clip(2.0 * c, -top, top))
        if c == b and f(0.5 * (a + b)) < f(b):  # at the largest turn: is the lowest before?
            b, c = 0.5 * (a + b), b
        # f(a) > f(b) <= f(c): golden-section steps in the wider side, down to TURN_TOL_DEG
        # or until the ends cost within TURN_COST_TOL of the best
        g = 0.381966
        while c != b and abs(c - a) > tol and max(f(a), f(c)) - f(b) > TURN_COST_TOL:
            right = abs(c - b) > abs(b - a)
            x = b + g * ((c if right else a) - b)
            if f(x) < f(b):
                a, b, c = (b, x, c) if right else (a, x, b)
            elif right:
                c = x
            else:
                a = x
    best = min(costs, key=costs.__getitem__)
    record = {
        "turn_deg": float(np.degrees(best)),
        "cost_before": costs[0.0],
        "cost_after": costs[best],
        "evaluations": len(costs),
        "seconds": time.perf_counter() - t0,
    }
    return (start if best == 0.0 else model.turned(start, k, best)), record


def window_length(model: StagedModel, ws: WarmStartSpec) -> tuple[int, int]:
    """(window, overlap) in samples (casmag.solver.windowing.window_size, from the model's
    odometry step lengths and assumed lengthscale)."""
    return window_size(ws, model.step_lengths(), model.lengthscale, model.n)


def _rows(states: dict[str, np.ndarray], keys: tuple[str, ...], rows: slice) -> dict:
    return {key: states[key][rows] for key in keys}


@dataclass
class Windows:
    """The sliding windows alone (:func:`slide`): every window solved (``stages``); when
    ``completed`` (every window reached an accepted IPOPT outcome inside its map's box), the
    whole recording's states joined from the samples each window committed (``states``,
    as :meth:`StagedModel.joined`: the full problem's start) and the map's prior after
    every sample (``prior``); otherwise ``states`` is None and the failing window is the
    last stage."""

    stages: list[Stage]
    states: dict[str, np.ndarray] | None
    prior: WindowPrior

    @property
    def completed(self) -> bool:
        return self.states is not None


def slide(model: StagedModel, ws: WarmStartSpec, bias: StartBias = 0.0) -> Windows:
    """Sliding windows, a fixed-lag smoother written once for every staged model. Windows
    of ``k`` samples overlapping by ``o`` (:func:`window_length`) are solved in time
    order; the map is a reduced-rank box around the whole recording whose unknowns carry a
    Gaussian prior from window to window (:class:`WindowPrior`), which the samples a window
    commits (those before the next window starts) enter as linear-Gaussian observations at
    their solved poses, so no sample counts twice. Each window removes the total bias
    estimated so far from its odometry and estimates the increment, under (with
    ``window_bias_prior: laplace``) the previous window's Laplace marginal of it as a
    zero-mean prior; it is anchored at the previous window's state at its first sample and
    starts from the previous window's states on the overlap, continued by the odometry.
    A window that fails (IPOPT, or its path leaves the map's box) ends the smoother.
    ``bias``: the heading-rate bias of the start (:func:`solve_starts`)."""
    n = model.n
    k, overlap = window_length(model, ws)
    firsts = window_starts(n, k, overlap)
    window_solver = model.solver.model_copy(update={"max_iter": ws.window_max_iter})
    prior = model.window_prior()
    total = model.start(2, bias)
    keys = model.sample_states
    total = {key: v for key, v in total.items() if key not in keys}
    bias_cov: dict[str, np.ndarray] | None = None
    anchor: dict[str, np.ndarray] | None = None
    anchor_sigma: dict[str, np.ndarray] | None = None
    anchor_cov: np.ndarray | None = None
    carried: dict[str, np.ndarray] | None = None
    parts: list[dict[str, np.ndarray]] = []
    stages: list[Stage] = []
    for i, a in enumerate(firsts):
        nxt = firsts[i + 1] if i + 1 < len(firsts) else n
        start = model.window_start(a, k, anchor, carried, total)
        window = Window(a, k, start, anchor, anchor_sigma, anchor_cov, total, bias_cov, prior,
                        window_solver)  # fmt: skip
        solved = model.solve_window(window)
        stage = Stage("window", k, model.lengthscale, solved, first=a)
        stages.append(stage)
        if solved.sol.status not in ACCEPTED or not model.window_inside(solved):
            stage.left_box = solved.sol.status in ACCEPTED
            return Windows(stages, None, prior)
        states = model.states(solved)
        m = nxt - a
        # The Laplace marginals of the bias increments and of the next window's anchor state
        # (its first sample): the next window's priors on them.
        layout = solved.nlp.x_layout.entries
        # The estimated ones (a state the window holds as a parameter is not in its layout).
        names = tuple(key for key in total if key in layout and key not in solved.sol.fixed)
        blocks = {key: layout[key].offset + np.arange(layout[key].size) for key in names}
        if nxt < n:
            blocks |= {f"anchor_{k_}": v for k_, v in model.anchor_indices(solved, m).items()}
        sizes = [v.size for v in blocks.values()]
        cov = (  # none: the last window of a model whose biases are per-sample states
            laplace_block(solved.nlp, solved.sol, solved.sol.params,
                          np.concatenate(list(blocks.values())), solved.sol.fixed)
            if blocks else np.zeros((0, 0))
        )  # fmt: skip
        var = np.diag(cov)
        ends = np.cumsum([0, *sizes])
        rows = {key: slice(ends[j], ends[j + 1]) for j, key in enumerate(blocks)}
        informative = bool(np.all(np.isfinite(var)) and np.all(var > 0))
        if ws.window_bias_prior == "laplace":  # a singular Hessian hands on no information
            bias_cov = {key: cov[rows[key], rows[key]] for key in names} if informative else None
            if bias_cov:
                stage.handed = {key: np.sqrt(np.diag(c)) for key, c in bias_cov.items()}
        anchor_sigma = (
            {key[7:]: np.sqrt(var[r]) for key, r in rows.items() if key.startswith("anchor_")}
            if informative else None
        )  # fmt: skip
        at = np.repeat([key.startswith("anchor_") for key in blocks], sizes).astype(bool)
        anchor_cov = cov[np.ix_(at, at)] if informative and at.any() else None
        total = {
            key: v + np.reshape(states[key], np.shape(v)) if key in names else v
            for key, v in total.items()
        }
        prior.observe(*model.window_design(solved, m))
        parts.append(_rows(states, keys, slice(0, m)))
        anchor = _rows(states, keys, slice(m, m + 1))
        carried = _rows(states, keys, slice(m, None))
    joined = {key: np.concatenate([p[key] for p in parts], axis=0) for key in keys}
    return Windows(stages, model.joined(joined, total), prior)


def solve_sliding(model: StagedModel, ws: WarmStartSpec, bias: StartBias = 0.0) -> list[Stage]:
    """Sliding windows (:func:`slide`), then the full problem from their states. When a
    window failed the full problem starts from the dead reckoning instead (measured on the
    planar drift table's seed 5, a window left the box at sample 168: from the dead
    reckoning the batch ended at 5.0 m, from the committed states continued by the
    odometry at 6.9 m; both flagged ``wrong_basin``)."""
    windows = slide(model, ws, bias)
    n = model.n
    start = windows.states if windows.completed else model.start(n, bias)
    final = model.solve(n, start, model.solver, model.lengthscale)
    return [*windows.stages, Stage("batch", n, model.lengthscale, final)]


def _record(st: Stage) -> dict[str, Any]:
    """What a result's ``stages`` record of every solve: samples, lengthscale, MAP cost,
    IPOPT's status, iterations, seconds and rounds (IPOPT runs: more than one when a
    tiled map was laid again around where its samples went, :func:`solve_rehomed`)."""
    so = st.solved.sol
    return {
        "samples": st.samples,
        "lengthscale": st.lengthscale,
        "cost": so.objective,
        "status": st.status,
        "iterations": so.iterations,
        "solve_seconds": so.solve_seconds,
        "rounds": so.rounds,
        **({"turn": st.turn} if st.turn is not None else {}),
    }


@dataclass
class StagedRun:
    """The strategy run from each start: ``runs[i]`` the stages from ``biases[i]``;
    ``kept`` the start whose last stage has the lowest MAP cost among the successful
    ones (the first start when none succeeded); ``apart[i]``: the RMS distance [m] of
    start i's estimated path from the kept one's (:func:`paths_apart`; None where start
    i's last solve failed or did not solve every sample)."""

    biases: list[StartBias]
    runs: list[list[Stage]]
    kept: int
    apart: list[float | None] = field(default_factory=list)

    @property
    def final(self) -> Solved:
        return self.runs[self.kept][-1].solved

    @property
    def solves(self) -> list[Solved]:
        return [st.solved for run in self.runs for st in run]

    def records(self) -> list[dict[str, Any]]:
        """A result's ``stages``: every solve, with its start's bias, the kept one marked.
        One solve per start is named ``start`` (the heading-bias starts' records)."""
        out = []
        for i, (bias, run) in enumerate(zip(self.biases, self.runs, strict=True)):
            for j, st in enumerate(run):
                last = j == len(run) - 1
                out.append(
                    {
                        "name": "start" if len(run) == 1 else st.kind,
                        "bias": float(bias) if np.ndim(bias) == 0 else np.ravel(bias).tolist(),
                        **_record(st),
                        "kept": i == self.kept and last,
                        **({"first": st.first} if st.kind == "window" else {}),
                        **({"path_rms_from_kept": self.apart[i]} if last and self.apart else {}),
                    }
                )
        return out


def heading_bias_starts(starts: int, heading_deg: float, duration: float) -> list[float]:
    """The heading-rate biases of ``starts`` starts [rad/s]: 0 (the dead reckoning), then
    pairs +-k delta, delta turning the heading by ``heading_deg`` over ``duration`` [s]."""
    delta = np.radians(heading_deg) / max(duration, 1e-12)
    k = np.arange(1, (starts - 1) // 2 + 1)
    return [0.0, *(float(v) for v in np.ravel(np.column_stack([k * delta, -k * delta])))]


def solve_starts(
    model: StagedModel,
    ws: WarmStartSpec,
    biases: list[StartBias],
    n: int | None = None,
    strategies: list[WarmStartSpec] | None = None,
) -> StagedRun:
    """The strategy from each start (the dead reckoning with each start's bias removed,
    StartBias), the lowest MAP cost of the full problem kept (casmag.nlp.lowest_cost over
    the starts whose last stage is the full problem); ``n``: of the first n samples;
    ``strategies``: a strategy of each start's own (default ``ws`` for every one)."""
    n = model.n if n is None else n
    strategies = [ws] * len(biases) if strategies is None else strategies
    if len(strategies) != len(biases):
        raise ValueError(f"{len(strategies)} strategies for {len(biases)} starts")
    runs = [solve_strategy(model, w, b, n) for w, b in zip(strategies, biases, strict=True)]
    kept = _kept(runs, n)
    return StagedRun(list(biases), runs, kept, paths_apart(model, runs, kept, n))


def paths_apart(
    model: StagedModel, runs: list[list[Stage]], kept: int, n: int
) -> list[float | None]:
    """The RMS distance [m] between each run's estimated path (its last solve's positions)
    and the kept run's: None for a run whose last solve failed or did not solve all n
    samples, and for every run when the kept one's did not succeed. The verdict's
    ``starts`` check (casmag.result.verdict) reads it: optima far apart at nearly the same
    MAP cost mean the data do not decide between them."""
    base = runs[kept][-1]
    if not (base.samples == n and base.solved.sol.success):
        return [None] * len(runs)
    P0 = np.asarray(model.states(base.solved)["P"], dtype=float)
    out: list[float | None] = []
    for run in runs:
        last = run[-1]
        if not (last.samples == n and last.solved.sol.success):
            out.append(None)
            continue
        P = np.asarray(model.states(last.solved)["P"], dtype=float)
        out.append(float(np.sqrt(np.mean(np.sum((P - P0) ** 2, axis=1)))))
    return out


def _kept(runs: list[list[Stage]], n: int) -> int:
    """The run whose last stage solved n samples at the lowest MAP cost (the first when
    none did)."""
    finals = [run[-1].solved.sol for run in runs]
    costs = [
        so.objective if run[-1].samples == n else np.inf
        for so, run in zip(finals, runs, strict=True)
    ]
    best = lowest_cost(finals, costs)
    return 0 if best is None else best


@dataclass
class SessionsRun:
    """Sessions added one at a time (:func:`solve_sessions`): ``first`` the first session's
    run from each start; ``added[j]`` the starts tried when session j + 1 joined, each a
    name and its stages; ``kept[j]`` the one whose estimate went on."""

    first: StagedRun
    added: list[list[tuple[str, list[Stage]]]]
    kept: list[int]

    @property
    def final(self) -> Solved:
        if not self.added:
            return self.first.final
        return self.added[-1][self.kept[-1]][1][-1].solved

    @property
    def solves(self) -> list[Solved]:
        more = [st.solved for tried in self.added for _, run in tried for st in run]
        return self.first.solves + more

    def records(self) -> list[dict[str, Any]]:
        """:meth:`StagedRun.records` of the first session (``session`` 0), then every
        solve of each session added, with its start and whether it was kept; only the
        last session's kept solve is the result's (``kept``)."""
        out = [{**r, "session": 0} for r in self.first.records()]
        last = len(self.added) - 1
        if self.added:
            for r in out:
                r["kept"] = False
        for j, (tried, kept) in enumerate(zip(self.added, self.kept, strict=True)):
            for i, (start, run) in enumerate(tried):
                for k, st in enumerate(run):
                    out.append(
                        {
                            "name": st.kind,
                            "session": j + 1,
                            "start": start,
                            **_record(st),
                            "chosen": i == kept and k == len(run) - 1,
                            "kept": j == last and i == kept and k == len(run) - 1,
                        }
                    )
        return out


def solve_sessions(
    model: StagedModel,
    ws: WarmStartSpec,
    biases: list[StartBias],
    strategies: list[WarmStartSpec] | None = None,
) -> SessionsRun:
    """Several sessions of one field with one map (``model.session_starts``), added one at
    a time (casmag.solver.multisession runs it on the translational model): a joint solve
    from every session's dead reckoning can stop in a poor optimum, and each later stage
    starting from the earlier sessions' estimate brings their map to the new one. The
    first session alone runs the strategy of ``ws`` from each start (:func:`solve_starts`);
    each later session is tried from two starts beside the estimate so far, the lower MAP
    cost kept: its dead reckoning from its known start, and (when it is longer than twice
    ``ws.first_samples``) its growing prefixes of ``ws.first_samples``, x ``ws.growth``,
    ... samples, each continued by the odometry with the bias estimated so far removed and
    stopped after ``ws.stage_max_iter`` iterations before the last. ``strategies``: the
    first session's strategy of each start (:func:`solve_starts`)."""
    bounds = model.sessions(model.n)
    ell = model.lengthscale
    if ws.strategy == "sliding" and len(bounds) > 1:
        raise ValueError("sliding windows: one session at a time, not several")
    first = solve_starts(model, ws, biases, n=bounds[0][1], strategies=strategies)
    capped = model.solver.model_copy(update={"max_iter": ws.stage_max_iter})
    base = first.final  # the estimate so far
    added: list[list[tuple[str, list[Stage]]]] = []
    kept: list[int] = []
    for a, e in bounds[1:]:
        tried = [
            (
                "dead reckoning",
                [Stage("session", e, ell, model.solve(e, model.continue_from(base, e),
                                                      model.solver, ell))],
            )
        ]  # fmt: skip
        if e - a > 2 * ws.first_samples:
            sizes = [a + k for k in stage_lengths(e - a, ws.first_samples, ws.growth)]

            def prefix(
                k: int, p: Solved | None, last: bool, base: Solved = base
            ) -> tuple[Solution, Solved]:
                start = model.continue_from(base if p is None else p, k)
                solved = model.solve(k, start, model.solver if last else capped, ell)
                return solved.sol, solved

            grown = [Stage("prefix", k, ell, sv) for k, _, sv in grow(sizes, prefix)]
            tried.append(("growing prefixes", grown))
        best = _kept([run for _, run in tried], e)
        added.append(tried)
        kept.append(best)
        base = tried[best][1][-1].solved
    return SessionsRun(first, added, kept)


def solve_staged(
    model: StagedModel,
    ws: WarmStartSpec,
    biases: list[StartBias],
    batch: StartBias | None = None,
) -> tuple[StagedRun | SessionsRun, str]:
    """A staged model's solve and what ``info["warm_start"]`` records of it: its sessions
    (:func:`solve_sessions`, ``sessions``) when it has several, else the strategy from each
    start (:func:`solve_starts`; ``none`` when the kept start ran one batch). ``batch``:
    one more start solved as one batch (the field's evidence's, casmag.solver.biasscan:
    its growing prefixes would go back to the dead reckoning's, since a short prefix
    hardly feels a heading-rate bias; measured on robot sequence 5 as pose odometry, where
    they reached the same cost to 1e-9)."""
    if len(model.session_starts) > 1:
        return solve_sessions(model, ws, biases), "sessions"
    strategies = [ws] * len(biases)
    if batch is not None:
        biases = [*biases, batch]
        strategies.append(ws.model_copy(update={"strategy": "none"}))
    run = solve_starts(model, ws, biases, strategies=strategies)
    return run, ws.strategy if len(run.runs[run.kept]) > 1 else "none"


def wrong_basin_flag(
    cost: float, true_start: Any, P_true: np.ndarray, ratio: float
) -> dict[str, Any] | None:
    """The ``wrong_basin`` flag (as the IMU model's) when the solve from the truth
    (``true_start``, a Solution) reaches a MAP cost lower by more than one (a likelihood
    ratio of e) than the estimate's ``cost``."""
    if true_start is None or not true_start.success:
        return None
    cost, truth_cost = float(cost), float(true_start.objective)
    if not truth_cost < cost - 1.0:
        return None
    rmse_truth = rmse_and_max(true_start.x["P"], P_true)[0]
    return {
        "name": "wrong_basin",
        "reason": (
            f"RMSE {ratio:.2f} of the dead reckoning's, and the same problem started from the "
            f"truth reaches a lower MAP cost ({truth_cost:.6g} < {cost:.6g}) at RMSE "
            f"{rmse_truth:.4g} m: the search ended in a worse local optimum"
        ),
        "evidence": {
            "ratio": ratio,
            "threshold": TRUTH_START_RATIO,
            "map_cost": cost,
            "map_cost_from_truth": truth_cost,
            "rmse_from_truth": rmse_truth,
            "iterations_from_truth": int(true_start.iterations),
            "status_from_truth": true_start.status,
        },
    }


def anchored_at_truth(anchors: np.ndarray, true_first: np.ndarray) -> bool:
    """Whether each session's anchor (rows: the first state of a session) is its first true
    state, to 1e-9."""
    return bool(np.allclose(anchors, true_first, rtol=0.0, atol=1e-9))


def truth_check(
    model: StagedModel,
    final: Solved,
    true_states: dict[str, np.ndarray],
    P_true: np.ndarray,
    P_dr: np.ndarray,
) -> dict[str, Any] | None:
    """With truth (evaluation): when the final solve succeeded at a position RMSE above
    :data:`TRUTH_START_RATIO` of the dead reckoning's ``P_dr``, the same problem (its map
    box) solved again from the true states ``true_states`` (the per-sample states; the
    biases are the final solve's); :func:`wrong_basin_flag` of the two. The caller runs it
    only where the estimate is anchored at the truth (:func:`anchored_at_truth`): anchored
    elsewhere (``--anchor origin``) the true states are in another frame, so neither the
    ratio nor the start means anything (as for the translational model)."""
    sol = final.sol
    if not sol.success:
        return None
    ratio = rmse_and_max(sol.x["P"], P_true)[0] / max(rmse_and_max(P_dr, P_true)[0], 1e-12)
    if ratio <= TRUTH_START_RATIO:
        return None
    start = {**model.states(final), **true_states}
    true_start = model.solve(model.n, start, model.solver, model.lengthscale).sol
    return wrong_basin_flag(sol.objective, true_start, P_true, ratio)


def displacement_bias_sigma(
    displacements: np.ndarray, fraction: float, starts: tuple[int, ...] = (0,)
) -> float | None:
    """The standard deviation [m per step] a consider parameter gives a body-frame
    displacement bias: ``fraction`` of the median step length of the increments
    ``displacements`` (n - 1, axes) within the sessions; None for a fraction of 0 or no
    step."""
    if fraction <= 0.0:
        return None
    D = np.asarray(displacements, dtype=float)
    steps = [i for a, e in Knots(D.shape[0] + 1, 1, starts).bounds for i in range(a, e - 1)]
    if not steps:
        return None
    return float(fraction) * float(np.median(np.linalg.norm(D[steps], axis=1)))


def uncertainty(
    final: Solved,
    P_true: np.ndarray | None,
    sigma_m: float,
    solver: SolverSpec,
    consider: Callable[[Solved], np.ndarray | None] | None = None,
    consider_fixed: dict[str, float] | None = None,
) -> tuple[dict[str, Any] | None, np.ndarray | None, np.ndarray | None]:
    """The Laplace position covariance of a staged model's final solve
    (casmag.solver.uncertainty.sample_state_uncertainty, with ``solver.uncertainty_inflation``):
    (summary, covariance, plain covariance); None for each when ``solver.uncertainty`` is off
    or the solve failed. ``consider(final)``: the consider parameters' C, or None;
    ``consider_fixed``: held variables taken in as consider parameters, with their prior
    standard deviations (casmag.solver.uncertainty.position_uncertainty)."""
    if not (final.sol.success and solver.uncertainty):
        return None, None, None
    C = None if consider is None else consider(final)
    return sample_state_uncertainty(
        final.nlp, final.sol, final.sol.x["P"], P_true, sigma_m, solver.uncertainty_inflation,
        consider=C, consider_fixed=consider_fixed,
    )  # fmt: skip


def record_consider(summary: dict[str, Any] | None, sigma: float | None, fraction: float) -> None:
    """``uncertainty.consider`` of a result whose covariance took in a displacement bias of
    standard deviation ``sigma`` [m per step] (:func:`displacement_bias_sigma`); nothing
    when there is none or no covariance."""
    if summary is not None and sigma is not None and "error" not in summary:
        summary["consider"] = {
            "displacement_bias": {"sigma_per_step_m": sigma, "fraction_of_step": fraction},
            "method": "consider parameter: H^-1 H_xb S_b H_bx H^-1 added, not estimated",
        }


#: ``info["map"]`` of a result until :meth:`casmag.result.Result.saved_map` computes it.
MAP_NOT_YET = {"saved": False, "reason": "not computed yet (Result.saved_map())"}


@dataclass(frozen=True)
class StagedMap:
    """The ``map_maker`` of a staged model's result (casmag.result.Result.saved_map): the
    final solve's map (whitened weights: casmag.model.rotated) with its posterior,
    marginal over the path and conditioned on what the solve held
    (casmag.solver.uncertainty.saved_field_map), in the frame described by ``frame``, read
    at positions of ``position_dim``. The record it gives ``info["map"]`` keeps ``form``
    (the map's description); a tiled map is saved with its tile grid."""

    final: Solved
    kernel: str
    hyper: dict[str, float]
    frame: str
    form: dict[str, Any]
    position_dim: int

    def __call__(self) -> tuple[Any, dict[str, Any]]:
        form, sol = self.form, self.final.sol
        structure = self.final.structure
        basis = structure.grid if structure.tiled else structure.basis  # BoxOrTiles
        if sol.params is None:
            return None, {**form, "saved": False, "reason": "the solution records no parameters"}
        saved, record = saved_field_map(
            self.final.nlp, sol, dict(sol.params), self.kernel, basis, self.hyper, self.frame,
            whitened=True, position_dim=self.position_dim,
        )  # fmt: skip
        return saved, {**form, **record}
