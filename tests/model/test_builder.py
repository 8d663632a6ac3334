"""The one builder (casmag.model.builder): every motion model with every field model."""

import casadi as ca
import numpy as np
import pytest

from casmag.gp.fieldmap import field_at
from casmag.gp.kernels import get_kernel
from casmag.gp.reduced_rank import Domain, HilbertBasis
from casmag.model.builder import LoopClosures, MotionModel, NoField, Pose, build_slam
from casmag.model.field import ExactField, ReducedRankField
from casmag.model.imu import ImuMotion
from casmag.model.knots import Knots
from casmag.model.planar import PlanarMotion
from casmag.model.translational import TranslationalMotion
from casmag.nlp import NLPBuilder
from casmag.problem.spec import SolverSpec

N = 7
BASIS = ((0.0, 0.0, 0.0), (1.0, 1.0, 0.8), 12)


def _basis(dim):
    return (BASIS[0][:dim], BASIS[1][:dim], BASIS[2])


MOTIONS = {
    "translational": lambda: TranslationalMotion(N, 2, estimate_bias=True, bias_prior="sigma"),
    "translational-knots": lambda: TranslationalMotion(N, 2, knot_every=3, estimate_bias=True),
    "planar": lambda: PlanarMotion(N, "random_walk"),
    "imu": lambda: ImuMotion(N, 4, 0.01, "random_walk", zero_position=True),
}
MOTION_BLOCKS = {
    "translational": {"odometry", "anchor", "bias_prior"},
    "translational-knots": {"odometry", "anchor"},
    "planar": {"odometry", "bias_walk", "bias_prior", "anchor"},
    "imu": {"imu", "bias_walk", "bias_prior", "initial_state", "zero_position"},
}
DIM = {"translational": 2, "translational-knots": 2, "planar": 2, "imu": 3}
FIELDS = {
    "none": lambda dim: NoField(),
    "closures": lambda dim: LoopClosures(((0, 3), (1, 5), (2, 6))),
    "exact": lambda dim: ExactField("curl_free", 0.05, constant_field=True),
    "exact-estimated": lambda dim: ExactField(
        "se", 0.05, estimate=("sigma_f", "lengthscale"), logdet=True
    ),
    # The curl-free potential lives on a 3-D box whatever the positions' dimension.
    "reduced-rank": lambda dim: ReducedRankField("curl_free", BASIS, constant_field=True),
    "reduced-rank-se": lambda dim: ReducedRankField("se", _basis(dim), constant_field=True),
}
FIELD_BLOCKS = {
    "none": set(),
    "closures": {"closure"},
    "exact": {"magnetometer", "gp_prior", "constant_field_prior"},
    "exact-estimated": {"magnetometer", "gp_prior", "gp_logdet"},
    "reduced-rank": {"magnetometer", "gp_prior", "constant_field_prior"},
    "reduced-rank-se": {"magnetometer", "gp_prior", "constant_field_prior"},
}


def _point(nlp, rng):
    """A random point and positive parameters (every sigma and the nominal rotations)."""
    x = rng.normal(scale=0.3, size=nlp.x_layout.size)
    p = rng.uniform(0.5, 1.5, size=nlp.p_layout.size)
    if "RNOM" in nlp.p_layout.entries:  # nominal rotations: proper rotation matrices
        e = nlp.p_layout.entries["RNOM"]
        K = e.shape[0]
        R = np.stack([_rotation(rng) for _ in range(K)]).reshape(K, 9)
        p[e.offset : e.offset + e.size] = R.reshape(-1, order="F")
    return x, p


def _rotation(rng):
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


@pytest.mark.parametrize("field", sorted(FIELDS))
@pytest.mark.parametrize("motion", sorted(MOTIONS))
def test_every_motion_model_builds_with_every_field_model(motion, field):
    """One builder: each motion model's blocks and each field model's blocks in one NLP
    whose objective is their sum and whose gradient (CasADi's, with the field's numpy
    blocks) matches central differences of the objective."""
    m, f = MOTIONS[motion](), FIELDS[field](DIM[motion])
    nlp = build_slam(m, f, SolverSpec())
    assert set(nlp.block_names) == MOTION_BLOCKS[motion] | FIELD_BLOCKS[field]
    rng = np.random.default_rng(3)
    x, p = _point(nlp, rng)
    blocks = nlp.evaluate_blocks(x, p)
    objective = float(nlp.solver.get_function("nlp_f")(x, p))
    assert objective == pytest.approx(sum(blocks.values()), rel=1e-12)
    grad = np.asarray(nlp.solver.get_function("nlp_grad_f")(x, p)[1]).ravel()
    f_of = nlp.solver.get_function("nlp_f")
    for i in rng.choice(x.size, size=min(12, x.size), replace=False):
        h = 1e-6 * max(1.0, abs(x[i]))
        up, down = x.copy(), x.copy()
        up[i] += h
        down[i] -= h
        fd = (float(f_of(up, p)) - float(f_of(down, p))) / (2 * h)
        assert grad[i] == pytest.approx(fd, rel=1e-5, abs=1e-6 * max(1.0, abs(objective)))


def test_exact_prior_on_a_planar_pose_is_the_gp_density():
    """The exact field on the planar model (a pair no stack offered before): its
    ``gp_prior`` is 0.5 m^T K(P)^-1 m with K the kernel at the planar positions P, the
    variables themselves (no dead reckoning added)."""
    nlp = build_slam(PlanarMotion(N), ExactField("se", 1e-8), SolverSpec())
    rng = np.random.default_rng(4)
    x, p = _point(nlp, rng)
    P = nlp.x_layout.unpack(x)["P"]
    M = nlp.x_layout.unpack(x)["M"]
    params = nlp.p_layout.unpack(p)
    sf, ell = params["sigma_f"].item(), params["lengthscale"].item()
    kernel = get_kernel("se")
    K = kernel.matrix(P, P, sf, ell) + 1e-8 * kernel.variance(sf, ell) * np.eye(N)
    expected = 0.5 * np.sum(M * np.linalg.solve(K, M))
    assert nlp.evaluate_blocks(x, p)["gp_prior"] == pytest.approx(expected, rel=1e-8)


@pytest.mark.parametrize("motion", sorted(MOTIONS))
def test_loop_closures_pull_the_paired_positions_of_any_motion_model(motion):
    """The ``closure`` block is 0.5 sum |(p_j - p_i) / sigma_closure|^2 over the pairs, on the
    positions the motion model gives (dead reckoning plus corrections, or knots)."""
    pairs = ((0, 3), (2, 6))
    nlp = build_slam(MOTIONS[motion](), LoopClosures(pairs), SolverSpec())
    rng = np.random.default_rng(6)
    x, p = _point(nlp, rng)
    pose = MOTIONS[motion]().declare(NLPBuilder())  # the names of its position symbols
    xs, ps = nlp.x_layout.unpack(x), nlp.p_layout.unpack(p)
    C = xs[pose.variable]
    if pose.knots.every != 1:  # the closure reads the samples interpolated from the knots
        C = pose.knots.matrix @ C
    P = C + (0.0 if pose.nominal is None else ps[pose.nominal])
    sigma = ps["sigma_closure"].item()
    expected = 0.5 * sum(np.sum((P[j] - P[i]) ** 2) for i, j in pairs) / sigma**2
    assert nlp.evaluate_blocks(x, p)["closure"] == pytest.approx(expected, rel=1e-10)


@pytest.mark.parametrize("hessian", ["auto", "hybrid", "exact", "gauss-newton"])
def test_a_motion_model_is_one_class(hessian):
    """A new motion model needs only ``declare``: here positions that are unknowns under
    position fixes (a parameter) and a smoothness prior, with the reduced-rank map from the
    builder alone. Noise-free data of a map drawn from the GP prior in the basis: the solve
    fits them to their noise level in a few iterations, with every ``solver.hessian``
    that hands IPOPT a Hessian (``exact`` in more)."""

    class Fixes(MotionModel):
        name = "fixes"

        def declare(self, b):
            P = b.variable("P", (N, 3))
            fixes = b.parameter("fixes", (N, 3))
            b.cost("walk", 0.5 * ca.sumsqr(P[1:, :] - P[:-1, :]) / 0.1**2)
            b.cost("fixes", 0.5 * ca.sumsqr(P - fixes) / 1e-3**2)
            return Pose(P, N, 3, "P", None, Knots(N, 1))

    solver = SolverSpec(tol=1e-9, hessian=hessian)
    nlp = build_slam(Fixes(), ReducedRankField("curl_free", BASIS), solver)
    assert nlp.block_names == ["walk", "fixes", "magnetometer", "gp_prior"]
    rng = np.random.default_rng(5)
    P = np.cumsum(rng.normal(scale=0.05, size=(N, 3)), axis=0)
    basis = HilbertBasis(Domain(np.zeros(3), np.array(BASIS[1])), BASIS[2])
    S = np.asarray(basis.prior_variances("curl_free", 1.0, 0.5)).reshape(-1, 1)
    w = np.sqrt(S) * rng.normal(size=(BASIS[2], 1))
    Y = field_at(basis, "curl_free", P, w)
    params = {"Y": Y, "fixes": P, "sigma_m": 1e-3, "sigma_f": 1.0, "lengthscale": 0.5}
    sol = nlp.solve(params, {"P": P, "W": np.zeros_like(w)})
    assert sol.success, sol.status
    # The exact terms from the first iteration took 24 here (why ``auto`` is hybrid).
    assert sol.iterations <= (30 if hessian == "exact" else 10)
    fitted = field_at(basis, "curl_free", sol.x["P"], sol.x["W"])
    assert np.sqrt(np.mean((fitted - Y) ** 2)) < 1e-3


@pytest.mark.parametrize("hessian", ["auto", "gauss-newton", "exact", "hybrid"])
def test_solver_hessian_reaches_every_numpy_magnetometer_block(hessian):
    """``solver.hessian`` sets the mode of the magnetometer block's Hessian callback for
    every field model read with numpy, rotated or not: ``gauss-newton`` is J^T J alone
    (the rotated box's ``curvature`` does not add its terms back), ``exact`` and
    ``hybrid`` that mode whatever the model's own choice, ``auto`` the model's own choice
    (the box in the map frame and the tiles: ``hybrid``; the rotated box: its
    ``curvature``). IPOPT is handed the Hessian in every one."""
    from casmag.model.field import TiledField
    from casmag.model.tiledmap import home_points, tile_grid

    rng = np.random.default_rng(0)
    P0 = np.cumsum(rng.normal(scale=0.15, size=(N, 2)), axis=0)
    grid = tile_grid(P0, 0.3)
    tiled = TiledField(grid, home_points(grid, P0), constant_field=True)
    rotated = ReducedRankField("curl_free", BASIS, constant_field=True, curvature="exact")
    solver = SolverSpec(hessian=hessian)
    cases = {
        "translational box": (MOTIONS["translational"](), FIELDS["reduced-rank"](2), "hybrid"),
        "translational tiles": (MOTIONS["translational"](), tiled, "hybrid"),
        "planar box": (MOTIONS["planar"](), rotated, "exact"),
        "planar tiles": (MOTIONS["planar"](), tiled, "hybrid"),
    }
    for name, (motion, field, auto) in cases.items():
        nlp = build_slam(motion, field, solver)
        keep = nlp.keep[1] if nlp.keep is not None else None
        expected = auto if hessian == "auto" else hessian
        assert keep.mode == expected, (name, keep.mode)
