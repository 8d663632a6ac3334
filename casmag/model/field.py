"""Field models: the second plug-in point of the one builder (casmag.model.builder).

- :class:`ExactField`: the field at every sample as unknowns under the exact GP prior
  (Eq. 6, casmag.model.exact), hyperparameters optionally estimated inside the NLP.
- :class:`ReducedRankField`: a Hilbert-space reduced-rank map (weights on a box around the
  path) with an optional constant field; read in the map frame through the knot-interpolated
  positions (numpy blocks of casmag.model.rrmap, O(1) to build in the samples) or through
  the pose's rotation (casmag.model.rotated).
- :class:`TiledField`: the curl-free map as a blend of reduced-rank potentials on a grid of
  tiles (casmag.gp.tiles): each sample touches the tiles around it, so the Hessian grows
  with the tiles the path visits, not with the area of one box (map frame).
- :class:`WindowField`: the reduced-rank map of one window of the fixed-lag smoother, whose
  prior is the Gaussian carried from the earlier windows (casmag.solver.staged.slide).
- :class:`casmag.model.builder.NoField`: no map.

Each declares its unknowns and blocks on the :class:`~casmag.model.builder.Pose` a motion
model gives it, so every motion model gets every field model.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from casmag.gp.kernels import FIELD_DIM, get_kernel
from casmag.gp.localmaps import cached_tiles
from casmag.gp.reduced_rank import HilbertBasis, cached_basis
from casmag.gp.tiles import TiledBasis, TileGrid
from casmag.model.builder import FieldModel, HessianPart, Pose
from casmag.model.exact import add_exact_prior
from casmag.model.rotated import add_rotated_map, rotated_gauss_newton, rotated_layout
from casmag.model.rrmap import (
    GaussNewtonHessian,
    MagnetometerCost,
    MapLayout,
    MapModel,
    NumpyCost,
)
from casmag.model.tiledmap import (
    RotatedTiledGaussNewton,
    RotatedTiledModel,
    TiledGaussNewton,
    TiledMapModel,
)
from casmag.nlp import NLPBuilder
from casmag.problem.spec import SolverSpec

HYPERPARAMETERS = ("sigma_f", "lengthscale", "sigma_m")


def hyperparameter(b: NLPBuilder, name: str, estimated: bool) -> ca.MX:
    """A positive hyperparameter: exp of a variable ``log_<name>`` when estimated, else the
    parameter ``<name>``."""
    if estimated:
        return ca.exp(b.variable(f"log_{name}", (1, 1)))
    return b.parameter(name, (1, 1))


def left_map_box(
    center: Sequence[float], half_width: Sequence[float], P: np.ndarray
) -> dict[str, Any] | None:
    """The ``left_map_box`` flag of an estimate whose positions P (n, d) leave the box of the
    reduced-rank map it was solved with (None when every position is inside). The Hilbert
    basis is fitted on that box (zero potential on its faces), so beyond it the map is not
    the GP model's, and nothing stops the joint optimum from moving the path out there: on
    a 4-s desk rectangle with one dipole (tests/small_problems.tiny_imu, seed 11, 400
    iterations) the first GP-SLAM pass ended up to 0.15 m beyond the box built around the
    IMU-only path, with the path spread 6-9 times its true extent (0.27 m from the truth
    against the IMU-only 0.029 m). Needs no truth. It checks the final solve's own box: an
    IMU pass rebuilds the box around the previous pass's path, so there (as in that case)
    a path that spread step by step stays inside and is not flagged."""
    d = P.shape[1]
    beyond = np.abs(P - np.asarray(center)[:d]) - np.asarray(half_width)[:d]  # > 0: outside
    worst = beyond.max(axis=1)
    tol = 1e-9 * (1.0 + float(np.max(np.abs(half_width))))  # a position on a face is inside
    if worst.max() <= tol:
        return None
    n_out = int(np.sum(worst > tol))
    return {
        "name": "left_map_box",
        "reason": (
            f"{n_out} of {P.shape[0]} estimated positions lie outside the map's box, up to "
            f"{worst.max():.3g} m beyond its face: the reduced-rank map is the GP model only "
            "inside its box, so the estimate there is an artefact of the approximation"
        ),
        "evidence": {
            "positions_outside": n_out,
            "positions": int(P.shape[0]),
            "max_beyond_m": float(worst.max()),
            "box_center": [float(v) for v in center],
            "box_half_width": [float(v) for v in half_width],
        },
    }


def map_frame_block(
    b: NLPBuilder,
    pose: Pose,
    constant_field: bool,
    name: str,
    make: Callable[[MapLayout], MapModel],
) -> MapModel:
    """The map-frame magnetometer block (a numpy callback, casmag.model.rrmap) reading the
    knot corrections, the weights ``W`` (and ``c``) from x and the dead reckoning, Y and
    sigma_m from p: every symbol is declared before it. ``make`` builds the block's model
    (the global basis or the tiles) on the layout."""
    b.parameter("Y", (pose.n, FIELD_DIM))
    n_x, n_p = b.sizes
    layout = MapLayout(
        n_x=n_x,
        n_p=n_p,
        C=b.offset(pose.variable),
        Q=None if pose.nominal is None else b.offset(pose.nominal, "p"),
        Y=b.offset("Y", "p"),
        W=b.offset("W"),
        c=b.offset("c") if constant_field else None,
        sigma_m=b.offset("sigma_m", "p"),
    )
    model = make(layout)
    mag = b.retain(MagnetometerCost(name, model))
    b.cost("magnetometer", mag(b.x_vector(), b.p_vector()))
    return model


def with_metis(solver: SolverSpec) -> SolverSpec:
    """MUMPS with METIS ordering unless the problem chose one: it keeps a map's dense
    sample-weight border from filling the trajectory's chain. One factorisation of a
    4,000-knot x 650-weight arrow took 1.35 s against 7.0 s with MUMPS's default ordering
    (and AMD, AMF, PORD, QAMD); on a 747-sample handheld planar recording (752 basis
    functions) the same iterates at 2.2 instead of 2.7 s per iteration. The tiles keep it
    too (IPOPT's search directions over the first iterations, the same iterates, each run
    alone, 2026-12-07): the planar floor walk (1,500 samples over 30 x 20 m, two solves of
    8 iterations) 11.0 + 11.6 s with METIS against 14.9 + 20.0 (AMD) and 21.5 + 23.1 s
    (QAMD); translational walks over 50 x 70 m favour AMD a little (2,000 samples, 8
    iterations: 20.0 s against 16.0 AMD, 16.2 AMF, 16.1 QAMD, 19.6 PORD, 18.9 MUMPS's own
    choice; 4,000 samples, 6 iterations: 24.1 s against 21.4 AMD, 22.0 QAMD)."""
    if solver.linear_solver == "mumps" and "mumps_pivot_order" not in solver.ipopt:
        return solver.model_copy(update={"ipopt": {**solver.ipopt, "mumps_pivot_order": 5}})
    return solver


@dataclass(frozen=True)
class ExactField(FieldModel):
    """The exact GP prior on the field values at the samples, ``M`` (n, 3).

    estimate: hyperparameters that are unknowns (``log_<name>``); logdet: add
    ``gp_logdet``; constant_field: a constant ``c`` (Earth's field) under ``sigma_lin`` and
    the GP on the variation. The magnetometer block is a plain cost in the map frame (its
    Hessian then exact in an estimated sigma_m) and a residual through a rotation."""

    kernel: str
    jitter: float
    estimate: tuple[str, ...] = ()
    logdet: bool = False
    constant_field: bool = False
    name = "exact"

    def declare(self, b: NLPBuilder, pose: Pose, solver: SolverSpec) -> HessianPart | None:
        sigma_f, ell, sigma_m = (hyperparameter(b, h, h in self.estimate) for h in HYPERPARAMETERS)
        del sigma_f, ell  # the prior reads them from x or p
        M = b.variable("M", (pose.n, FIELD_DIM))
        c = b.variable("c", (FIELD_DIM, 1)) if self.constant_field else None
        sigma_lin = b.parameter("sigma_lin", (1, 1)) if self.constant_field else None
        Y = b.parameter("Y", (pose.n, FIELD_DIM))
        rot = pose.rotation
        if rot is None:
            field = M if c is None else M + ca.repmat(c.T, pose.n, 1)
            b.cost("magnetometer", 0.5 * ca.sumsqr((Y - field) / sigma_m))
        else:
            d = ca.SX.sym("o", rot.unknowns.shape[1])
            aux = ca.SX.sym("aux", 0 if rot.aux is None else rot.aux.shape[1])
            m_, y_, c_, sg = (
                ca.SX.sym("m", 3), ca.SX.sym("y", 3), ca.SX.sym("c", 3), ca.SX.sym("s")
            )  # fmt: skip
            c_arg = c if c is not None else ca.MX.zeros(FIELD_DIM, 1)
            e = (y_ - ca.mtimes(rot.function(d, aux).T, m_ + c_)) / sg
            f = ca.Function("mag_exact", [d, aux, m_, c_, y_, sg], [e]).map(pose.n, "serial")
            aux_arg = rot.aux.T if rot.aux is not None else ca.MX(0, pose.n)
            b.residual("magnetometer", f(rot.unknowns.T, aux_arg, M.T, c_arg, Y.T, sigma_m))
        if c is not None:
            b.cost("constant_field_prior", 0.5 * ca.sumsqr(c / sigma_lin))
        # Every symbol is declared: the numpy prior (casmag.model.exact) sees the full vectors.
        return add_exact_prior(
            b,
            get_kernel(self.kernel),
            pose.knots,
            pose.dim,
            self.jitter,
            self.estimate,
            self.logdet,
            positions=pose.variable,
            dead_reckoning=pose.nominal,
        )


@dataclass(frozen=True)
class ReducedRankField(FieldModel):
    """A reduced-rank map: weights ``W`` on the Hilbert basis ``basis`` (center, half
    width, number of functions), a constant field ``c`` when ``constant_field``.

    In the map frame (no rotation) the weights are the map's own and the magnetometer,
    its gradient and Gauss-Newton Hessian are numpy blocks over the samples
    (casmag.model.rrmap); hyperparameters in ``estimate`` are unknowns, with ``gp_logdet``.
    Through a rotation the unknowns are whitened weights and the residual is symbolic per
    sample (casmag.model.rotated); ``curvature`` sets its Hessian callback's mode
    (``hybrid``, ``exact`` or ``gauss-newton``) unless ``solver.hessian`` names one
    (:meth:`mode`; the map-frame block takes its mode from ``solver.hessian``, ``auto``
    being ``hybrid``). ``metis``: MUMPS with METIS ordering unless the problem chose one."""

    kernel: str
    basis: tuple
    estimate: tuple[str, ...] = ()
    constant_field: bool = False
    curvature: str = "hybrid"
    metis: bool = True
    name = "rr"

    def hilbert_basis(self) -> HilbertBasis:
        return cached_basis(self.basis)

    def solver(self, solver: SolverSpec) -> SolverSpec:
        return with_metis(solver) if self.metis else solver

    def declare(self, b: NLPBuilder, pose: Pose, solver: SolverSpec) -> HessianPart | None:
        basis = self.hilbert_basis()
        if pose.rotation is not None:
            if not self.constant_field or self.estimate:
                raise ValueError(
                    "a rotated reduced-rank map has a constant field and fixed hyperparameters"
                )
            add_rotated_map(b, basis, self.kernel, pose)
            if solver.hessian == "limited-memory":
                return None
            return rotated_gauss_newton(b, basis, self.kernel, pose, self.mode(solver))
        sigma_f, ell, _ = (hyperparameter(b, h, h in self.estimate) for h in HYPERPARAMETERS)
        W, c = self._weights(b, basis)
        sigma_lin = b.parameter("sigma_lin", (1, 1)) if c is not None else None
        model = self._magnetometer(b, basis, pose, "magnetometer")
        S = basis.prior_variances(self.kernel, sigma_f, ell)  # (M, 1)
        n_cols = W.shape[1]
        b.cost("gp_prior", 0.5 * ca.sum1(ca.sum2(W**2 / ca.repmat(S, 1, n_cols))))
        if {"sigma_f", "lengthscale"} & set(self.estimate):
            b.cost("gp_logdet", 0.5 * n_cols * ca.sum1(ca.log(S)))
        if c is not None:
            b.cost("constant_field_prior", 0.5 * ca.sumsqr(c / sigma_lin))
        return self._hessian(solver, model, "mag_hessian")

    def mode(self, solver: SolverSpec) -> str:
        """The rotated block's Hessian mode: ``solver.hessian`` when it names one
        (``exact``, ``hybrid``, ``gauss-newton``), else (``auto``) the model's own
        ``curvature``."""
        return solver.hessian_mode(self.curvature)

    def _weights(self, b: NLPBuilder, basis: HilbertBasis) -> tuple[ca.MX, ca.MX | None]:
        M = basis.num_basis
        W = b.variable("W", (M, FIELD_DIM) if self.kernel == "se" else (M, 1))
        c = b.variable("c", (FIELD_DIM, 1)) if self.constant_field else None
        return W, c

    def _magnetometer(self, b: NLPBuilder, basis: HilbertBasis, pose: Pose, name: str) -> MapModel:
        return map_frame_block(
            b, pose, self.constant_field, name,
            lambda layout: MapModel(basis, self.kernel, pose.knots, pose.dim, layout),
        )  # fmt: skip

    @staticmethod
    def _hessian(solver: SolverSpec, model: MapModel, name: str) -> HessianPart | None:
        if solver.hessian == "limited-memory":
            return None
        mode = {"auto": "hybrid"}.get(solver.hessian, solver.hessian)
        return ("magnetometer", GaussNewtonHessian(name, model, mode=mode))


@dataclass(frozen=True)
class WindowField(ReducedRankField):
    """The reduced-rank map of one window of the fixed-lag smoother: block ``map_prior``,
    0.5 (z - mu)^T Lambda (z - mu) on the unknowns z of shape ``prior_shape`` (the weights
    W (M, 3) when ``shared_prior``: the three columns share one precision; else the stacked
    [vec(W); c]), with the mean ``map_mean`` and precision ``map_precision`` carried from
    earlier windows; its Hessian is the precision placed as it is (NLPBuilder.quadratic: a
    symbolic Hessian of the dense form took minutes to build at the real field's box). Read
    through the pose's rotation (planar with heading), the unknowns are
    the whitened weights and the constant field, z = [vec(V); c]
    (casmag.model.rotated.add_rotated_map)."""

    prior_shape: tuple[int, int] = (0, 0)
    shared_prior: bool = False
    name = "window"

    def declare(self, b: NLPBuilder, pose: Pose, solver: SolverSpec) -> HessianPart | None:
        basis = self.hilbert_basis()
        if pose.rotation is not None:
            if not self.constant_field or self.estimate:
                raise ValueError(
                    "a rotated window map has a constant field and fixed hyperparameters"
                )
            add_rotated_map(b, basis, self.kernel, pose, window=True)
            if solver.hessian == "limited-memory":
                return None
            return rotated_gauss_newton(b, basis, self.kernel, pose, self.mode(solver))
        W, c = self._weights(b, basis)
        b.parameter("sigma_m", (1, 1))
        n_r, n_c = self.prior_shape
        mu = b.parameter("map_mean", (n_r, n_c))
        Lam = b.parameter("map_precision", (n_r, n_r))
        model = self._magnetometer(b, basis, pose, "window_magnetometer")
        # z = [vec(W); c], x entries from W on; a shared precision serves each column of W.
        z = ca.vertcat(ca.vec(W), *([c] if c is not None else []))
        precision = ca.kron(ca.MX.eye(W.shape[1]), Lam) if self.shared_prior else Lam
        b.quadratic("map_prior", "W", z, ca.vec(mu), precision)
        return self._hessian(solver, model, "window_mag_hessian")


@dataclass(frozen=True)
class TiledField(FieldModel):
    """A tiled map (casmag.gp.tiles, casmag.model.tiledmap): the curl-free field of a blend
    of reduced-rank potentials on a grid of tiles, weights ``W`` (m, T) (one column per
    tile), a constant field ``c`` when ``constant_field``. Read in the map frame, or through
    the pose's rotation when the motion model has one (y = R^T (m + c): planar with heading,
    IMU; casmag.model.tiledmap.RotatedTiledModel); the magnetometer block's Hessian is
    sparse in the tiles (``home``: each sample's nearest grid point when the NLP was built,
    which fixes the pose-weight pattern), Gauss-Newton and then exact in each sample's pose
    (``hybrid``, casmag.model.tiledmap; ``solver.hessian`` ``gauss-newton`` or ``exact``
    keeps one of them throughout). Hyperparameters are parameters.

    ``saved_prior``: the map of a saved map's update (casmag.solver.localize, and the
    staged models' casmag.solver.staged.PriorMap): block ``map_prior``, 0.5 (z - mu)^T
    Lambda (z - mu) on z = [vec(W); c] with the saved posterior's mean ``map_mean`` (n_z, 1)
    and precision ``map_precision`` (n_z, n_z), in place of the GP prior on the weights and
    the constant field's; read through a rotation, W are the whitened weights and the
    caller gives the posterior in their units."""

    grid: TileGrid
    home: tuple[int, ...]
    constant_field: bool = False
    metis: bool = True
    saved_prior: bool = False
    name = "tiled"

    def tiles(self) -> TiledBasis:
        return cached_tiles(self.grid)

    def solver(self, solver: SolverSpec) -> SolverSpec:
        return with_metis(solver) if self.metis else solver

    def declare(self, b: NLPBuilder, pose: Pose, solver: SolverSpec) -> HessianPart | None:
        tiles = self.tiles()
        # The tiled blocks' Hessians are numpy callbacks in every mode (no CasADi one).
        mode = {"auto": "hybrid"}.get(solver.hessian, solver.hessian)
        sigma_f, ell, _ = (hyperparameter(b, h, False) for h in HYPERPARAMETERS)
        W = b.variable("W", (tiles.per_tile, tiles.num_tiles))
        c = b.variable("c", (FIELD_DIM, 1)) if self.constant_field else None
        sigma_lin = b.parameter("sigma_lin", (1, 1)) if c is not None else None
        S = tiles.prior_variances(sigma_f, ell)  # (m, 1)
        if self.saved_prior:  # declared before the blocks' callbacks fix the sizes of p
            z = ca.vertcat(ca.vec(W), *([c] if c is not None else []))
            mu = b.parameter("map_mean", (z.numel(), 1))
            Lam = b.parameter("map_precision", (z.numel(), z.numel()))
        if pose.rotation is None:
            model: Any = map_frame_block(
                b, pose, self.constant_field, "magnetometer",
                lambda layout: TiledMapModel(tiles, pose.knots, pose.dim, layout),
            )  # fmt: skip
            hessian: Any = lambda: TiledGaussNewton(  # noqa: E731
                "tiled_mag_hessian", model, self.home, mode=mode
            )
        else:
            # Read through the body's rotation (planar with heading, IMU): y = R^T (m + c).
            b.parameter("Y", (pose.n, FIELD_DIM))
            layout = rotated_layout(b, pose, whitened=True)
            model = RotatedTiledModel(tiles, pose.rotation.function, layout)
            mag = b.retain(
                NumpyCost("rotated_tiled_magnetometer", *b.sizes, model.cost, model.gradient)
            )
            b.cost("magnetometer", mag(b.x_vector(), b.p_vector()))
            hessian = lambda: RotatedTiledGaussNewton(  # noqa: E731
                "rotated_tiled_hessian", model, self.home, mode=mode
            )
        if self.saved_prior:
            b.quadratic("map_prior", "W", z, mu, Lam)
        elif pose.rotation is None:
            b.cost("gp_prior", 0.5 * ca.sum1(ca.sum2(W**2) / S))
        else:  # whitened weights (RotatedTiledModel)
            b.cost("gp_prior", 0.5 * ca.sumsqr(W))
        if c is not None and not self.saved_prior:
            b.cost("constant_field_prior", 0.5 * ca.sumsqr(c / sigma_lin))
        if solver.hessian == "limited-memory":
            return None
        return ("magnetometer", hessian())


class BoxOrTiles:
    """The map of a recording model's structure (the planar and pose models'), one of two:
    a reduced-rank box, ``basis`` its key (center, half width, number of functions), or
    tiles, ``grid`` with each sample's ``home`` grid point (which fixes the Hessian's
    pose-weight pattern). A mixin of frozen dataclasses that declare those three fields."""

    basis: tuple | None
    grid: TileGrid | None
    home: tuple[int, ...]

    @property
    def tiled(self) -> bool:
        return self.grid is not None

    def hilbert_basis(self) -> HilbertBasis:
        assert self.basis is not None, "a tiled map has no global basis"
        return cached_basis(self.basis)

    def tiles(self) -> TiledBasis:
        assert self.grid is not None
        return cached_tiles(self.grid)

    @property
    def map_unknowns(self) -> int:
        """The map's weights: the tiles' (every tile's functions) or the box's functions."""
        return self.tiles().num_weights if self.tiled else self.hilbert_basis().num_basis

    def tiled_field(self, window: bool) -> TiledField:
        """The tiles with a constant field; ``window``: under a given Gaussian prior (block
        ``map_prior``: a saved map's posterior, casmag.solver.staged.PriorMap) in place of
        the GP prior. The sliding windows' carried prior stays the box's."""
        assert self.grid is not None
        return TiledField(self.grid, self.home, constant_field=True, saved_prior=window)
