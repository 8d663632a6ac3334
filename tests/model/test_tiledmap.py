"""The tiled map in the NLP (casmag.model.tiledmap, casmag.model.field.TiledField)."""

from pathlib import Path

import numpy as np
import pytest
from small_problems import planar_room_field, tiny_walk

import casmag
from casmag.data.imusim import simulate_planar
from casmag.data.simulate import simulate_problem
from casmag.model.builder import build_slam
from casmag.model.field import TiledField
from casmag.model.planar import PlanarMotion
from casmag.model.rrmap import HessianCallback
from casmag.model.tiledmap import (
    BUMP_SPACING,
    TiledGaussNewton,
    bump_spacing,
    home_points,
    left_map_tiles,
    ridge_tile_weights,
    tile_grid,
    tile_normal_equations,
)
from casmag.model.translational import TranslationalMotion
from casmag.problem.imu import load_planar_options
from casmag.problem.oriented import load_oriented_problem
from casmag.problem.spec import SolverSpec
from casmag.solver.api import solve
from casmag.solver.planar import solve_planar

N = 40
ELL = 0.3


def _central(f, x, i, h):
    """Central difference of f (a scalar or an array) in x[i]."""
    up, down = x.copy(), x.copy()
    up[i] += h
    down[i] -= h
    return (np.asarray(f(up)) - np.asarray(f(down))) / (2 * h)


def _problem(knot_every, seed=0, basis="hilbert"):
    rng = np.random.default_rng(seed)
    P0 = np.cumsum(rng.normal(scale=0.15, size=(N, 2)), axis=0)
    grid = tile_grid(P0, ELL, basis=basis)
    field = TiledField(grid, home_points(grid, P0), constant_field=True)
    nlp = build_slam(
        TranslationalMotion(N, 2, knot_every=knot_every, estimate_bias=True), field, SolverSpec()
    )
    tiles = field.tiles()
    S = tiles.prior_variances(1.0, ELL)
    W = np.sqrt(S)[None, :] * rng.normal(size=(tiles.num_tiles, tiles.per_tile))
    x = {
        "C": rng.normal(scale=0.05, size=(nlp.x_layout.entries["C"].shape)),
        "W": W.T,
        "c": rng.normal(size=(3, 1)),
        "bias": rng.normal(scale=0.01, size=(1, 2)),
    }
    Y = tiles.field(P0, W) + rng.normal(scale=0.3, size=(N, 3))
    p = {
        "Q": P0, "Y": Y, "anchor": P0[:1], "sigma_o": 0.05, "sigma_anchor": 0.01,
        "sigma_m": 0.2, "sigma_f": 1.0, "lengthscale": ELL, "sigma_lin": 10.0,
    }  # fmt: skip
    return nlp, field, nlp.x_layout.pack(x), nlp.p_layout.pack(p)


@pytest.mark.parametrize("basis", ["hilbert", "bumps"])
@pytest.mark.parametrize("knot_every", [1, 3])
def test_gradient_and_gauss_newton_hessian(knot_every, basis):
    """The objective's gradient (the numpy magnetometer block's included) matches central
    differences, and the magnetometer block's Hessian callback is J^T J of its residuals
    (J by central differences) on every entry of J^T J: the pattern misses none while the
    samples stay near where the NLP was built. For both tile bases."""
    nlp, _, x, p = _problem(knot_every, basis=basis)
    f_of = nlp.solver.get_function("nlp_f")
    grad = np.asarray(nlp.solver.get_function("nlp_grad_f")(x, p)[1]).ravel()
    rng = np.random.default_rng(1)
    for i in rng.choice(x.size, size=40, replace=False):
        fd = _central(lambda v: float(f_of(v, p)), x, i, 1e-6)
        assert grad[i] == pytest.approx(fd, rel=1e-5, abs=1e-5)
    hess = nlp.keep[1]
    model = hess.model

    def residual(xv):
        P, w, c, Y, sigma = model.unpack(xv, p)
        return ((Y - model.tiles.field(P, model.weights(w)) - c) / sigma).ravel()

    cols = np.sort(
        np.concatenate([np.arange(nlp.x_layout.entries["C"].size), rng.choice(x.size, 150)])
    )
    cols = np.unique(cols)
    J = np.empty((3 * N, cols.size))
    for k, i in enumerate(cols):
        J[:, k] = _central(residual, x, i, 1e-6)
    G = np.triu(J.T @ J)
    # The residuals' Jacobian the Laplace covariance's correction uses, on every column.
    e, J_all = hess.residual_jacobian(x, p)
    np.testing.assert_allclose(e.ravel(), residual(x), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(J_all[:, cols].toarray(), J, rtol=0, atol=1e-6 * np.abs(J).max())
    hess.set_mode("gauss-newton")
    H = np.zeros((x.size, x.size))
    H[hess._rows, hess._cols] = hess.values(x, p)
    H = H[np.ix_(cols, cols)]
    assert np.abs(H - G).max() < 1e-6 * np.abs(G).max()
    assert hess.dropped[-1] == 0
    # Exact mode: the knot columns are the block's exact second derivatives (central
    # differences of its gradient), which differ from J^T J.
    hess.set_mode("exact")
    H = np.zeros((x.size, x.size))
    H[hess._rows, hess._cols] = hess.values(x, p)
    H = H + np.triu(H, 1).T
    knots = nlp.x_layout.entries["C"].offset + np.arange(nlp.x_layout.entries["C"].size)
    exact = np.empty((x.size, knots.size))
    for k, i in enumerate(knots):
        # a step of 1e-6: a sample may lie within 1e-5 of a bump's edge, where the fourth
        # derivative jumps (seen with step 1e-5: 1e-5 relative)
        exact[:, k] = _central(lambda v: model.gradient(v, p), x, i, 1e-6)
    assert np.abs(H[:, knots] - exact).max() < 1e-7 * np.abs(exact).max()
    gn = np.zeros((x.size, x.size))
    gn[np.ix_(cols, cols)] = G + np.triu(G, 1).T
    assert (
        np.abs(H[np.ix_(cols, knots)] - gn[np.ix_(cols, knots)]).max() > 1e-3 * np.abs(exact).max()
    )


def test_ridge_weights_are_the_posterior_mean():
    """The tiles' initial weights are the posterior mean given the field at the start
    positions: the normal equations assembled from the dense group products equal the
    design's A^T A and A^T r (a missing or mis-transposed off-diagonal block fails here),
    and the weights solve them to 1e-9 of the largest weight."""
    rng = np.random.default_rng(3)
    P = np.cumsum(rng.normal(scale=0.15, size=(N, 2)), axis=0)
    tiles = TiledField(tile_grid(P, ELL), home_points(tile_grid(P, ELL), P)).tiles()
    R = rng.normal(size=(N, 3))
    A = tiles.design(P)
    AtA, Atr = tile_normal_equations(tiles, P, R)
    ref = (A.T @ A).toarray()
    assert np.abs(AtA.toarray() - ref).max() < 1e-12 * np.abs(ref).max()
    np.testing.assert_allclose(Atr, A.T @ R.ravel(order="F"), rtol=1e-12, atol=1e-12)
    upper = tile_normal_equations(tiles, P, R, upper=True)[0].toarray()
    assert np.abs(upper - np.triu(ref)).max() < 1e-12 * np.abs(ref).max()
    c0, sigma_m, sigma_f = np.array([0.3, -0.2, 0.5]), 0.2, 1.5
    S = np.tile(tiles.prior_variances(sigma_f, ELL), tiles.num_tiles)
    G = ref / sigma_m**2 + np.diag(1.0 / S)
    mean = np.linalg.solve(G, A.T @ R.ravel(order="F") / sigma_m**2)
    W = ridge_tile_weights(tiles, P, R + c0, c0, sigma_m, sigma_f, ELL)
    assert W.shape == (tiles.per_tile, tiles.num_tiles)
    np.testing.assert_allclose(W.T.ravel(), mean, rtol=0, atol=1e-9 * np.abs(mean).max())


@pytest.mark.parametrize("cls", [HessianCallback, TiledGaussNewton])
def test_hybrid_switch_counts_slow_evaluations(cls):
    """The hybrid Hessian adds the exact terms once the block's cost has fallen by less
    than SWITCH (20 %) at SWITCH_AFTER evaluations in a row: the global box at the first
    slow one, the tiles at the second (a lone slow step, then a fast one, keeps
    Gauss-Newton), and a fast step starts the count again."""
    hess = cls.__new__(cls)
    hess.set_mode("hybrid")
    costs = [10.0, 9.0, 5.0, 4.5, 4.4, 2.0, 1.9, 1.89]  # falls 10, 44, 10, 2, 55, 5, 0.5 %
    used = [hess._use_exact(c) for c in costs]
    if cls is HessianCallback:
        assert used == [False, True, False, True, True, False, True, True]
    else:
        assert used == [False, False, False, False, True, False, False, True]
    assert hess.exact_used == used
    hess.reset()
    assert not hess._use_exact(18.0)  # a new solve starts with Gauss-Newton


@pytest.mark.parametrize("cls", [HessianCallback, TiledGaussNewton])
def test_hybrid_switch_of_the_tiles_waits_for_a_fall_under_one_unit(cls):
    """A large cost that falls by a few per cent an evaluation (a large map, whose cost is
    mostly the noise's) is slow for the global box's 20 % but not for the tiles, which also
    ask for a fall under SWITCH_UNITS (one unit of the cost) before the exact terms."""
    hess = cls.__new__(cls)
    hess.set_mode("hybrid")
    costs = [5000.0, 4900.0, 4850.0, 4849.5, 4849.2, 4800.0, 4799.9, 4799.8]
    used = [hess._use_exact(c) for c in costs]  # falls 100, 50, 0.5, 0.3, 49.2, 0.1, 0.1
    if cls is HessianCallback:
        assert used == [False, True, True, True, True, True, True, True]
    else:
        assert used == [False, False, False, False, True, False, False, True]


@pytest.mark.slow
@pytest.mark.parametrize("basis", ["hilbert", "bumps"])
def test_tiled_map_locates_like_the_exact_gp(basis):
    """The 120-sample walk (curl-free field) solved with the tiled map (either basis):
    converges in a few iterations with the hybrid Hessian (5 and 6 on seeds
    2 and 3; the Hilbert tiles 4-6 on seeds 2-4, Gauss-Newton alone 11-18), and its
    positions are as close to the truth as the exact GP's (seeds 2, 3: 0.0106 / 0.0104 m,
    the Hilbert tiles 0.0098 / 0.0111 m, against 0.0102 / 0.0105 m; dead reckoning 0.034 /
    0.051 m). Its Laplace covariance is the exact GP's (mean 1-sigma 0.0131 / 0.0101 m
    against 0.0132 / 0.0101 m; mean NEES 1.19 / 2.21 against 1.10 / 2.23)."""
    rmse, sigma = {}, {}
    for form in ("tiled", "exact"):
        prob = tiny_walk(
            [
                "model.gp.kernel=curl_free",
                "simulation.field.kernel=curl_free",
                f"model.gp.form={form}",
                *([f"model.gp.tile_basis={basis}"] if form == "tiled" else []),
            ]
        )
        data = simulate_problem(prob)
        r = solve(prob, data)
        assert r.success, r.status
        assert r.info["gp_form"] == form
        if form == "tiled":
            assert r.iterations <= 12
        rmse[form] = r.rmse_after
        sigma[form] = r.uncertainty["sigma_mean"]
        assert r.uncertainty["nees_mean"] < 5.0
    before = np.sqrt(np.mean(np.sum((data.dead_reckoning() - data.P_true) ** 2, axis=1)))
    assert rmse["tiled"] < 1.15 * rmse["exact"]
    assert rmse["tiled"] < before / 3
    assert sigma["tiled"] == pytest.approx(sigma["exact"], rel=0.05)


@pytest.mark.slow
def test_tiled_map_positions_agree_with_the_exact_gp_on_the_base_case():
    """The paper's base case (81 samples on a spiral, l = 0.1 m) with a curl-free field:
    the tiled map's positions within 1 mm of the exact GP's. Measured 2026-12-07, seeds
    1-5: at most 0.14 / 0.21 / 0.16 / 0.29 / 0.17 mm apart (lattice 0.05 m, 975 nodes),
    both 0.15-0.34 mm from the truth."""
    P = {}
    for form in ("exact", "tiled"):
        prob = casmag.load_problem(
            Path(__file__).resolve().parents[2] / "problems/paper/base.yaml",
            [
                "simulation.field.kernel=curl_free",
                "model.gp.kernel=curl_free",
                f"model.gp.form={form}",
                "solver.uncertainty=false",
            ],
        )
        r = solve(prob, simulate_problem(prob))
        assert r.success, r.status
        assert r.info["gp_form"] == form
        P[form] = r.arrays["P_estimate"]
    assert np.linalg.norm(P["tiled"] - P["exact"], axis=1).max() < 1e-3


@pytest.mark.parametrize(
    ("document", "reason"),
    [
        ({"model": {"gp": {"form": "tiled", "kernel": "se"}}}, "needs model.gp.kernel: curl_free"),
        (
            {
                "model": {"gp": {"form": "tiled", "kernel": "curl_free"}},
                "solver": {"warm_start": {"strategy": "sliding"}},
            },
            "sliding carries the reduced-rank map",
        ),
        (
            {"model": {"gp": {"form": "tiled", "kernel": "curl_free"}, "estimate": ["sigma_f"]}},
            "unbounded",
        ),
    ],
)
def test_tiled_problem_errors(document, reason):
    with pytest.raises(casmag.ProblemError, match=reason):
        casmag.load_problem({"seed": 1, **document})


def test_left_map_tiles_flag():
    """Positions where the map lacks a corner tile are flagged, with the count."""
    rng = np.random.default_rng(3)
    P0 = np.cumsum(rng.normal(scale=0.15, size=(N, 2)), axis=0)
    tiles = TiledField(tile_grid(P0, ELL), ()).tiles()
    assert left_map_tiles(tiles, P0) is None
    far = np.vstack([P0, P0[-1] + 10.0])
    flag = left_map_tiles(tiles, far)
    assert flag["name"] == "left_map_tiles"
    assert flag["evidence"] == {"positions_outside": 1, "positions": N + 1}


@pytest.mark.parametrize("basis", ["hilbert", "bumps"])
def test_tiled_map_read_through_a_rotation(basis):
    """The tiled map as the field of a motion model whose magnetometer turns with the body
    (the planar model, y = Rz(psi)^T (m(p) + c)): the objective's gradient matches central
    differences, and the block's Hessian callback is J^T J of its residuals (J by central
    differences) on every position, heading and constant-field column and on sampled
    weight columns. For both tile bases."""
    rng = np.random.default_rng(0)
    n = 30
    P0 = np.cumsum(rng.normal(scale=0.15, size=(n, 2)), axis=0)
    grid = tile_grid(P0, ELL, basis=basis)
    field = TiledField(grid, home_points(grid, P0), constant_field=True)
    nlp = build_slam(PlanarMotion(n, "random_walk"), field, SolverSpec())
    assert set(nlp.block_names) >= {"magnetometer", "gp_prior", "constant_field_prior", "odometry"}
    x = rng.normal(scale=0.3, size=nlp.x_layout.size)
    p = rng.uniform(0.5, 1.5, size=nlp.p_layout.size)
    values = {"sigma_f": 1.0, "lengthscale": ELL, "sigma_m": 0.2}
    for name, v in values.items():
        p[nlp.p_layout.entries[name].offset] = v
    e = nlp.x_layout.entries["P"]
    x[e.offset : e.offset + e.size] = (P0 + rng.normal(scale=0.05, size=P0.shape)).ravel(order="F")
    f_of = nlp.solver.get_function("nlp_f")
    grad = np.asarray(nlp.solver.get_function("nlp_grad_f")(x, p)[1]).ravel()
    hess = next(k for k in nlp.keep if hasattr(k, "dropped"))
    model = hess.model
    checked = np.concatenate(
        [model.lay.pos.ravel(), model.lay.rot.ravel(), rng.choice(x.size, 60, replace=False)]
    )
    for i in checked:
        fd = _central(lambda v: float(f_of(v, p)), x, i, 1e-6)
        assert grad[i] == pytest.approx(fd, rel=1e-4, abs=1e-4)

    def residual(xv):
        return (model.residuals(xv, p) / values["sigma_m"]).ravel()

    c = model.lay.c + np.arange(3)
    cols = np.unique(np.concatenate([checked, c]))
    J = np.empty((3 * n, cols.size))
    for k, i in enumerate(cols):
        J[:, k] = _central(residual, x, i, 1e-6)
    G = np.triu(J.T @ J)
    e, J_all = hess.residual_jacobian(x, p)
    np.testing.assert_allclose(e.ravel(), residual(x), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(J_all[:, cols].toarray(), J, rtol=0, atol=1e-6 * np.abs(J).max())
    hess.set_mode("gauss-newton")
    H = np.zeros((x.size, x.size))
    H[hess._rows, hess._cols] = hess.values(x, p)
    assert np.abs(H[np.ix_(cols, cols)] - G).max() < 1e-6 * np.abs(G).max()
    assert hess.dropped[-1] == 0
    # Exact mode: every column of a position or heading is the block's exact second
    # derivative (central differences of the block's gradient), not J^T J.
    hess.set_mode("exact")
    H = np.zeros((x.size, x.size))
    H[hess._rows, hess._cols] = hess.values(x, p)
    H = H + np.triu(H, 1).T
    local = np.concatenate([model.lay.pos.ravel(), model.lay.rot.ravel()])
    exact = np.empty((x.size, local.size))
    for k, i in enumerate(local):
        exact[:, k] = _central(lambda v: model.gradient(v, p), x, i, 1e-6)
    assert np.abs(H[:, local] - exact).max() < 1e-7 * np.abs(exact).max()
    gn = np.zeros((x.size, x.size))
    gn[np.ix_(cols, cols)] = G + np.triu(G, 1).T
    assert np.abs(H[:, local] - gn[:, local]).max() > 1e-3 * np.abs(exact).max()


def _planar_room_walk(loops: int, *sets: str):
    """The planar walk of the tests (loops of 2 x 1.5 m, heading-rate bias 0.5 deg/s, seed
    2) solved with the tiled map and ``sets``."""
    d = simulate_planar(
        2, planar_room_field(), size=(2.0, 1.5), loops=loops, heading_bias_deg=0.5,
        disp_noise=0.002,
    )  # fmt: skip
    base = [
        "model.sigma_disp=0.002",
        f"model.sigma_dyaw={np.radians(0.05)}",
        "model.gp.kernel=curl_free",
        "model.gp.form=tiled",
    ]
    opts = load_planar_options(None, [*base, *sets])
    return solve_planar(*d.U.T, d.Y, opts, truth={"P": d.P, "psi": d.psi}, t=d.t)


@pytest.mark.slow
def test_planar_walk_with_the_tiled_map():
    """The planar walk of the tests (three loops of 2 x 1.5 m, heading-rate bias 0.5
    deg/s, seed 2) with ``model.gp.form: tiled``: converges to the tolerance in a few
    iterations with the hybrid Hessian and locates about as the box does. Measured
    2026-12-02 with the bumps (the default) on seeds 2, 1, 4: 0.0114 / 0.0096 / 0.0082 m
    in 16 / 18 / 17 iterations, mean NEES 2.70 / 1.94 / 1.41 at the lattice of 0.75 l, and
    with the lattice bump_spacing lays for this field (32.6-33 times the noise: 0.528 l)
    0.0108 / 0.0113 / 0.0102 m in 15 / 21 / 19 iterations, NEES 2.41 / 2.44 / 2.05; the
    Hilbert tiles 0.0111 /
    0.0121 / 0.0108 m in 13 / 16 / 15 (Gauss-Newton alone stopped at the iteration
    limit); the box 0.0108 / 0.0115 / 0.0059 m; dead reckoning 0.0966 / 0.0865 / 0.0913 m."""
    r = _planar_room_walk(3)
    assert r.status == "Solve_Succeeded" and r.iterations <= 30
    assert r.rmse_after <= 0.2 * r.rmse_before
    assert r.info["map"]["form"] == "tiled" and r.info["map"]["tiles"] >= 4
    assert r.flags == []
    assert r.arrays["map_field"].shape[-1] == 3
    # The Laplace covariance of the positions (seeds 1, 2, 4: mean 1-sigma 0.0094-0.0098 m,
    # the box's 0.0090-0.0099 m; mean NEES 2.3-2.8, the box's 0.85-2.5, expected 2).
    u = r.uncertainty
    assert 0.5 < u["sigma_mean"] / r.rmse_after < 2.0 and 0.8 < u["inside_95"]
    # The saved map: the tiles' own weights (unwhitened) with their posterior, marginal over
    # the path; the true field within its std (seed 2, 2026-12-03: std 0.009 uT, at most
    # 0.12 of the prior's, mean squared error over it 0.64-0.79 per component).
    saved = r.saved_map()
    assert r.info["map"]["saved"] and saved.form == "tiled" and saved.dim == 2
    a = r.arrays
    pts = np.column_stack([a["map_x"].ravel(), a["map_y"].ravel()])
    drawn = a["map_field"].reshape(-1, 3)
    on = np.isfinite(drawn).all(axis=1)
    np.testing.assert_array_equal(on, saved.inside(pts))
    np.testing.assert_allclose(saved.field(pts[on]), drawn[on], atol=1e-10)
    P = a["P_true"][:, :2]
    std = saved.std(P)
    assert np.all(std < 0.25 * saved.prior_std(P))
    err = saved.field(P) - planar_room_field()(np.column_stack([P, np.zeros(len(P))]))
    assert np.mean((err / std) ** 2) < 1.5


def test_planar_tiled_map_needs_the_curl_free_kernel():
    with pytest.raises(casmag.ProblemError, match="form tiled needs kernel: curl_free"):
        load_planar_options(None, ["model.gp.form=tiled", "model.gp.kernel=se"])
    sets = ["model.gp.form=tiled", "model.gp.kernel=curl_free"]
    assert load_planar_options(None, sets).form == "tiled"
    # The tiles asked for without a kernel take theirs, as when form auto chooses them.
    options = load_planar_options(None, ["model.gp.form=tiled"])
    assert (options.form, options.kernel) == ("tiled", "curl_free")


def test_samples_beyond_their_home_keep_the_hessian_positive():
    """A sample that moved more than a tile from the grid point its NLP was built around
    (its ``home``) loses its border against the tiles outside the pattern. Those products
    dropped alone leave the Gauss-Newton matrix indefinite (J^T J on the pattern, below);
    the callback replaces each by the two factors' own products, so its matrix stays
    positive semi-definite and equals J^T J on every entry no moved sample touches."""
    rng = np.random.default_rng(3)
    n = 30
    P0 = np.cumsum(rng.normal(scale=0.04, size=(n, 2)), axis=0)
    moved = np.arange(n) % 2 == 1
    P1 = P0 + moved[:, None] * np.array([1.9, 0.8])  # 1.6 and 0.7 tile spacings
    grid = tile_grid(np.vstack([P0, P1]), ELL)
    field = TiledField(grid, home_points(grid, P0), constant_field=True)
    nlp = build_slam(PlanarMotion(n, "random_walk"), field, SolverSpec())
    x = rng.normal(scale=0.3, size=nlp.x_layout.size)
    p = rng.uniform(0.5, 1.5, size=nlp.p_layout.size)
    for name, v in {"sigma_f": 1.0, "lengthscale": ELL, "sigma_m": 0.2}.items():
        p[nlp.p_layout.entries[name].offset] = v
    e = nlp.x_layout.entries["P"]
    x[e.offset : e.offset + e.size] = P1.ravel(order="F")
    hess = next(k for k in nlp.keep if hasattr(k, "dropped"))
    H, G = _gauss_newton_where_samples_moved(hess, x, p)
    lay = hess.model.lay
    still = np.flatnonzero(~moved)
    free = np.concatenate([lay.pos[still].ravel(), lay.rot[still].ravel()])
    # every position and heading of a sample that did not move is J^T J's
    atol = 1e-9 * np.abs(G).max()
    np.testing.assert_allclose(H[np.ix_(free, free)], G[np.ix_(free, free)], atol=atol)


def _gauss_newton_where_samples_moved(hess, x, p):
    """The callback's Gauss-Newton matrix H at x (both triangles) and J^T J = G of its
    residuals. Asserts that it dropped products, that G on the callback's pattern alone
    (the dropped products left out) is indefinite, and that H is positive semi-definite
    (both on the unknowns some sample touches)."""
    hess.set_mode("gauss-newton")
    H = np.zeros((x.size, x.size))
    H[hess._rows, hess._cols] = hess.values(x, p)
    assert hess.dropped[-1] > 0
    H = H + np.triu(H, 1).T
    G = hess.residual_jacobian(x, p)[1].toarray()
    G = G.T @ G
    on = np.zeros(G.shape, dtype=bool)
    on[hess._rows, hess._cols] = True
    on |= on.T
    _indefinite_alone_positive_kept(G, H, on)
    return H, G


def _indefinite_alone_positive_kept(G, H, on):
    live = np.flatnonzero((np.abs(G).sum(axis=0) > 0) | (np.abs(H).sum(axis=0) > 0))
    G, H, on = (a[np.ix_(live, live)] for a in (G, H, on))
    scale, eye = np.abs(G).max(), np.eye(live.size)
    with pytest.raises(np.linalg.LinAlgError):  # an eigenvalue below -1e-3 scale
        np.linalg.cholesky(np.where(on, G, 0.0) + 1e-3 * scale * eye)
    np.linalg.cholesky(H + 1e-10 * scale * eye)  # none below -1e-10 scale


@pytest.mark.parametrize("knot_every", [1, 3])
def test_translational_samples_beyond_their_home_keep_the_hessian_positive(knot_every):
    """As above for the translational model, whose positions interpolate knots: each
    dropped (knot, tile) product is replaced by the knot's and the tile's own."""
    rng = np.random.default_rng(4)
    P0 = np.cumsum(rng.normal(scale=0.04, size=(N, 2)), axis=0)
    moved = (np.arange(N) // 6) % 2 == 1  # runs of samples, so whole knots move
    P1 = P0 + moved[:, None] * np.array([1.9, 0.8])
    grid = tile_grid(np.vstack([P0, P1]), ELL)
    field = TiledField(grid, home_points(grid, P0), constant_field=True)
    nlp = build_slam(
        TranslationalMotion(N, 2, knot_every=knot_every, estimate_bias=True), field, SolverSpec()
    )
    hess = nlp.keep[1]
    x = rng.normal(scale=0.3, size=nlp.x_layout.size)
    p = {
        "Q": P0, "Y": rng.normal(size=(N, 3)), "anchor": P0[:1], "sigma_o": 0.05,
        "sigma_anchor": 0.01, "sigma_m": 0.2, "sigma_f": 1.0, "lengthscale": ELL,
        "sigma_lin": 10.0,
    }  # fmt: skip
    p = nlp.p_layout.pack(p)
    e = nlp.x_layout.entries["C"]
    knots = hess.knots
    C = np.linalg.lstsq(
        knots.matrix.toarray() if hasattr(knots.matrix, "toarray") else knots.matrix,
        P1 - P0,
        rcond=None,
    )[0]
    x[e.offset : e.offset + e.size] = C.ravel(order="F")
    _gauss_newton_where_samples_moved(hess, x, p)


@pytest.mark.parametrize("basis", ["hilbert", "bumps"])
def test_a_translational_solve_laid_around_the_wrong_tiles_is_laid_again(basis):
    """The tiny walk's tiled NLP with every sample's home three tiles (and the pattern's
    slack) away: the first Hessian evaluation drops the samples' border products, so the
    solve stops and goes on in an NLP laid around where the samples are
    (casmag.solver.staged.solve_rehomed via the translational solve), and reaches the
    optimum of the NLP laid right from the start."""
    import dataclasses

    from casmag.gp.localmaps import cached_tiles
    from casmag.model.translational import cached_nlp, parameters_and_guess
    from casmag.solver.translational import _solve, solve_translational

    prob = tiny_walk(
        [
            "model.gp.kernel=curl_free",
            "simulation.field.kernel=curl_free",
            "model.gp.form=tiled",
            f"model.gp.tile_basis={basis}",
        ]
    )
    data = simulate_problem(prob)
    right, _, _, _, s = solve_translational(prob, data)
    assert right.success and right.rounds == 1, right.status
    DR = data.dead_reckoning()
    slack = cached_tiles(s.grid).home_slack
    far = DR + np.array([(3 + slack) * s.grid.spacing, 0.0])
    wrong = dataclasses.replace(s, home=home_points(s.grid, far))
    params, x0 = parameters_and_guess(prob, data, wrong)
    sol, nlp, laid = _solve(wrong, cached_nlp(wrong), params, x0, None)
    assert sol.success and sol.rounds >= 2, (sol.status, sol.rounds)
    P = s.knots.positions(DR, sol.x["C"])
    moved = np.subtract(laid.home, home_points(s.grid, P))
    assert np.abs(moved).max() <= slack and nlp.keep[1].dropped[-1] == 0
    np.testing.assert_allclose(P, right.x["P"], atol=1e-4)
    assert sol.objective == pytest.approx(right.objective, rel=1e-6)


@pytest.mark.parametrize("basis", ["hilbert", "bumps"])
def test_coarse_to_fine_lays_the_tiles_for_each_stage(basis):
    """solver.warm_start.strategy coarse-to-fine with the tiled map (translational): each
    stage's tiles are laid for its own lengthscale (casmag.solver.staged.map_lengthscale;
    a lattice of bumps is its lengthscale), each stage after the first starts from the
    previous one's positions, and the last stage is the problem at the assumed lengthscale,
    so it ends where a batch from those positions ends."""
    from casmag.solver.staged import solve_strategy
    from casmag.solver.translational import TranslationalStaged, solve_translational

    prob = tiny_walk(
        [
            "model.gp.kernel=curl_free",
            "simulation.field.kernel=curl_free",
            "model.gp.form=tiled",
            f"model.gp.tile_basis={basis}",
            "solver.warm_start.strategy=coarse-to-fine",
            "solver.warm_start.lengthscale_start=2.0",
            "solver.warm_start.lengthscale_stages=2",
        ]
    )
    data = simulate_problem(prob)
    ell = prob.assumed_lengthscale
    stages = solve_strategy(TranslationalStaged(prob, data), prob.spec.solver.warm_start)
    assert [st.lengthscale for st in stages] == pytest.approx([2 * ell, ell])
    spacing = [st.solved.structure.grid.spacing for st in stages]
    if basis == "hilbert":
        assert spacing[0] == pytest.approx(2 * spacing[1])
    else:  # a lattice of bump_spacing(the stage's field over the noise) lengthscales
        sigma_f, sigma_m = prob.assumed_sigma_f, prob.assumed_sigma_m
        lattice = [bump_spacing(sigma_f, l, sigma_m) * l for l in (2 * ell, ell)]
        assert spacing == pytest.approx(lattice)
        assert spacing[0] > 2 * spacing[1]  # the coarse stage's field is weaker per l
    assert all(st.solved.sol.success for st in stages), [st.status for st in stages]
    # The last stage: the assumed lengthscale's problem from the coarse stage's positions,
    # with the bias it estimated removed (its tiles' weights fitted again, not carried).
    last, coarse = stages[-1].solved, stages[0].solved
    removed = last.nominal.debias
    assert np.any(removed) and np.allclose(removed, np.reshape(coarse.sol.x["bias"], (1, -1)))
    again, *_ = solve_translational(
        prob, data.debiased(removed), initial_positions=coarse.sol.x["P"]
    )
    np.testing.assert_allclose(last.sol.x["P"], again.x["P"], atol=1e-6)
    before = np.sqrt(np.mean(np.sum((data.dead_reckoning() - data.P_true) ** 2, axis=1)))
    after = np.sqrt(np.mean(np.sum((last.sol.x["P"] - data.P_true) ** 2, axis=1)))
    assert after < before / 3


def test_planar_coarse_to_fine_lays_the_tiles_for_each_stage(monkeypatch):
    """The planar model's coarse-to-fine stages (casmag.solver.planar.PlanarStaged) lay
    their tiles for each stage's lengthscale, as the translational ones do, and converge
    (seed 2, two loops, 2026-12-02: 0.0730 -> 0.0118 m in 9 + 11 iterations; the default
    strategy's one batch reaches the same 0.0118 m), each stage's lattice from its own
    field against the noise (casmag.model.tiledmap.bump_spacing), as the translational
    stages lay theirs."""
    import casmag.solver.planar as planar

    laid: dict[float, float] = {}
    original = planar.planar_structure

    def recording(options, k, around, ell, *args, **kwargs):
        s = original(options, k, around, ell, *args, **kwargs)
        laid[round(ell, 12)] = s.grid.spacing
        return s

    monkeypatch.setattr(planar, "planar_structure", recording)
    r = _planar_room_walk(
        2,
        "solver.warm_start.strategy=coarse-to-fine",
        "solver.warm_start.lengthscale_start=2.0",
        "solver.warm_start.lengthscale_stages=2",
        "solver.warm_start.evidence=false",  # the strategy's stages alone
    )
    assert r.status == "Solve_Succeeded"
    ell = r.hyperparameters["lengthscale"]
    scales = [st["lengthscale"] for st in r.stages]
    assert scales[-2:] == pytest.approx([2 * ell, ell])
    assert set(laid) == set(np.round([2 * ell, ell], 12))
    sigma_f, sigma_m = r.hyperparameters["sigma_f"], r.hyperparameters["sigma_m"]
    for l in (2 * ell, ell):
        assert laid[round(l, 12)] == pytest.approx(bump_spacing(sigma_f, l, sigma_m) * l)
    assert laid[round(2 * ell, 12)] > 2 * laid[round(ell, 12)]
    assert r.rmse_after <= 0.5 * r.rmse_before


@pytest.mark.parametrize("motion", ["planar", "pose"])
def test_growing_prefixes_lay_the_coarsest_lattice(monkeypatch, motion):
    """A growing prefix lays its bumps at BUMP_SPACING (casmag.solver.staged.lattice_field)
    and the full problem the lattice its field asks for (bump_spacing), for the planar and
    the pose model alike; the solve still reaches its optimum (problems/<motion>/walk.yaml,
    120 samples in 10 x 3 m, a dipole field about 20 times the noise)."""
    import casmag.solver.planar as planar
    import casmag.solver.pose as pose

    module, name = (planar, "planar_structure") if motion == "planar" else (pose, "pose_structure")
    laid: list[tuple[int, float, float]] = []
    original = getattr(module, name)

    def recording(options, k, around, ell, *args, **kwargs):
        s = original(options, k, around, ell, *args, **kwargs)
        if s.grid is not None:
            laid.append((k, ell, s.grid.spacing))
        return s

    monkeypatch.setattr(module, name, recording)
    root = Path(__file__).resolve().parents[2]
    problem = load_oriented_problem(
        root / f"problems/{motion}/walk.yaml",
        [
            "seed=2", "simulation.trajectory.samples=120", "model.gp.form=tiled",
            "model.gp.kernel=curl_free",
            "solver.warm_start.strategy=growing", "solver.warm_start.first_samples=40",
            "solver.warm_start.growth=3.0", "solver.warm_start.evidence=false",
        ],
    )  # fmt: skip
    r = casmag.solve(problem)
    assert r.status == "Solve_Succeeded"
    assert [st["samples"] for st in r.stages] == [40, 120]
    ks = sorted({k for k, _, _ in laid})
    assert ks == [40, 120]
    h = r.hyperparameters
    rule = bump_spacing(h["sigma_f"], h["lengthscale"], h["sigma_m"])
    assert rule < 0.9 * BUMP_SPACING  # the field asks for a finer lattice than a prefix's
    for k, ell, spacing in laid:  # the full problem's turn search compares its starts on
        # a prefix's lattice (casmag.solver.staged.best_turn), and the full problem is solved
        # on the rule's, laid last
        expected = (BUMP_SPACING,) if k < 120 else (BUMP_SPACING, rule)
        assert any(spacing == pytest.approx(e * ell) for e in expected), (k, ell, spacing)
    assert laid[-1][0] == 120 and laid[-1][2] == pytest.approx(rule * laid[-1][1])
    assert r.rmse_after < 0.5 * r.rmse_before
