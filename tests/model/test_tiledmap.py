"""The tiled map in the NLP (casmag.model.tiledmap, casmag.model.field.TiledField)."""

import numpy as np
import pytest
from small_problems import tiny_walk

import casmag
from casmag.data.simulate import simulate_problem
from casmag.model.builder import build_slam
from casmag.model.field import TiledField
from casmag.model.tiledmap import home_points, left_map_tiles, tile_grid
from casmag.model.translational import TranslationalMotion
from casmag.problem.spec import SolverSpec
from casmag.solver.translational import solve_translational

N = 40
ELL = 0.3


def _problem(knot_every, seed=0):
    rng = np.random.default_rng(seed)
    P0 = np.cumsum(rng.normal(scale=0.15, size=(N, 2)), axis=0)
    grid = tile_grid(P0, ELL)
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


@pytest.mark.parametrize("knot_every", [1, 3])
def test_gradient_and_gauss_newton_hessian(knot_every):
    """The objective's gradient (the numpy magnetometer block's included) matches central
    differences, and the magnetometer block's Hessian callback is J^T J of its residuals
    (J by central differences) on every entry of J^T J: the pattern misses none while the
    samples stay near where the NLP was built."""
    nlp, _, x, p = _problem(knot_every)
    f_of = nlp.solver.get_function("nlp_f")
    grad = np.asarray(nlp.solver.get_function("nlp_grad_f")(x, p)[1]).ravel()
    rng = np.random.default_rng(1)
    for i in rng.choice(x.size, size=40, replace=False):
        h = 1e-6
        up, down = x.copy(), x.copy()
        up[i] += h
        down[i] -= h
        fd = (float(f_of(up, p)) - float(f_of(down, p))) / (2 * h)
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
        h = 1e-6
        up, down = x.copy(), x.copy()
        up[i] += h
        down[i] -= h
        J[:, k] = (residual(up) - residual(down)) / (2 * h)
    G = np.triu(J.T @ J)
    H = np.zeros((x.size, x.size))
    H[hess._rows, hess._cols] = hess.values(x, p)
    H = H[np.ix_(cols, cols)]
    assert np.abs(H - G).max() < 1e-6 * np.abs(G).max()
    assert hess.dropped[-1] == 0


def test_tiled_map_locates_like_the_exact_gp():
    """The 120-sample walk (curl-free field) solved with the tiled map: converges in a few
    dozen Gauss-Newton iterations (18 measured), and its positions are as close to the
    truth as the exact GP's (seeds 2, 3, 4: 0.0098 / 0.0111 / 0.0148 m against 0.0102 /
    0.0105 / 0.0150 m; dead reckoning 0.034 / 0.051 / 0.0097 m)."""
    rmse = {}
    for form in ("tiled", "exact"):
        prob = tiny_walk(
            [
                "model.gp.kernel=curl_free",
                "simulation.field.kernel=curl_free",
                f"model.gp.form={form}",
            ]
        )
        data = simulate_problem(prob)
        sol, _, _, _, s = solve_translational(prob, data)
        assert sol.success, sol.status
        assert s.form == form
        if form == "tiled":
            assert sol.iterations <= 40
        rmse[form] = np.sqrt(np.mean(np.sum((sol.x["P"] - data.P_true) ** 2, axis=1)))
    before = np.sqrt(np.mean(np.sum((data.dead_reckoning() - data.P_true) ** 2, axis=1)))
    assert rmse["tiled"] < 1.15 * rmse["exact"]
    assert rmse["tiled"] < before / 3


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
