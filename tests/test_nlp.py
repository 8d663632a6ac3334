"""casmag.nlp: the stall stop that lets a caller re-centre and solve again; a quadratic
block whose Hessian is its precision parameter."""

import casadi as ca
import numpy as np

from casmag.nlp import STALLED, NLPBuilder
from casmag.problem.spec import SolverSpec


def _tiny_nlp(tol):
    b = NLPBuilder()
    x = b.variable("x", (2, 1))
    a = b.parameter("a", (1, 1))
    # Two stiff terms pulling apart: no double zeroes their gradient exactly.
    stiff = a * ((x[0] - 0.1) ** 2 + np.pi * (x[0] - 0.2) ** 2)
    b.cost("stiff", stiff + (x[1] - 0.1) ** 2 + 10.0)
    # No tiny-step exit: IPOPT then iterates on at the optimum (as on the IMU problems,
    # whose steps there are not tiny relative to the variables).
    return b.build(SolverSpec(tol=tol, max_iter=200, ipopt={"tiny_step_tol": 0.0}))


def test_stop_when_stalled_stops_ipopt_where_the_objective_no_longer_moves():
    """A tolerance below what double precision can reach (1e-30): without the stall stop
    IPOPT runs on at the optimum until its acceptable-level exit; with it, it stops with
    STALLED a few iterations after the objective stopped changing, at the optimum."""
    nlp = _tiny_nlp(1e-30)
    plain = nlp.solve({"a": 1e12}, {"x": np.array([0.5, 1.0])})
    stopped = nlp.solve({"a": 1e12}, {"x": np.array([0.5, 1.0])}, stop_when_stalled=True)
    assert plain.status != "Solve_Succeeded"
    assert stopped.status == STALLED and not stopped.success
    assert stopped.iterations < plain.iterations
    optimum = [(0.1 + 0.2 * np.pi) / (1 + np.pi), 0.1]
    np.testing.assert_allclose(stopped.x["x"].ravel(), optimum, atol=1e-8)


def test_stop_when_stalled_leaves_a_converging_solve_alone():
    nlp = _tiny_nlp(1e-8)
    sol = nlp.solve({"a": 1e12}, {"x": np.array([0.5, 1.0])}, stop_when_stalled=True)
    assert sol.status == "Solve_Succeeded" and sol.rounds == 1
    assert ca.__version__  # the solver ran in this CasADi


def test_an_ipopt_opt_file_in_the_working_folder_is_not_read(tmp_path, monkeypatch):
    """Options come from the problem file only (where they are checked): an ipopt.opt in
    the working folder that would stop IPOPT after one iteration is ignored."""
    monkeypatch.chdir(tmp_path)
    b = NLPBuilder()
    x = b.variable("x", (2, 1))
    a = b.parameter("a", (1, 1))
    b.cost("rosenbrock", (1 - x[0]) ** 2 + a * (x[1] - x[0] ** 2) ** 2)
    nlp = b.build(SolverSpec(tol=1e-8, max_iter=200))
    plain = nlp.solve({"a": 100.0}, {"x": np.array([-1.2, 1.0])})
    (tmp_path / "ipopt.opt").write_text("max_iter 1\n")
    again = nlp.solve({"a": 100.0}, {"x": np.array([-1.2, 1.0])})
    assert plain.status == again.status == "Solve_Succeeded"
    assert again.iterations == plain.iterations > 1


def test_a_quadratic_block_gives_its_precision_as_its_hessian():
    """NLPBuilder.quadratic: the block 0.5 (z - mu)^T L (z - mu) on consecutive variables,
    its Hessian the parameter L placed at their offset (upper triangle), beside another
    block's CasADi Hessian; IPOPT then solves the quadratic exactly in one step."""
    rng = np.random.default_rng(5)
    b = NLPBuilder()
    a = b.variable("a", (2, 1))
    u = b.variable("u", (2, 1))
    v = b.variable("v", (1, 1))
    mu, L = b.parameter("mu", (3, 1)), b.parameter("L", (3, 3))
    b.cost("other", 0.5 * ca.sumsqr(a - 1.0) + ca.sum1(a) * 0.0)
    b.quadratic("prior", "u", ca.vertcat(u, v), mu, L)
    nlp = b.build(SolverSpec(), name="quad")
    G = rng.normal(size=(3, 3))
    Lv, mv = G @ G.T + 3 * np.eye(3), rng.normal(size=3)
    params = {"mu": mv, "L": Lv}
    x = {"a": np.zeros(2), "u": np.ones(2), "v": np.ones(1)}
    H = nlp.hessian(x, params).toarray()
    expected = np.zeros((5, 5))
    expected[:2, :2] = np.eye(2)
    expected[2:, 2:] = Lv
    np.testing.assert_allclose(H, expected, atol=1e-12)
    sol = nlp.solve(params, x)
    assert sol.success
    np.testing.assert_allclose(
        np.concatenate([sol.x["u"].ravel(), sol.x["v"].ravel()]), mv, atol=1e-8
    )


def test_a_limited_memory_nlp_solves_under_a_memory_budget_and_has_no_covariance():
    """``solver.hessian: limited-memory`` builds no Hessian: the memory estimate before a
    solve counts the constraint Jacobian and a diagonal instead (it used to ask for the
    Hessian and raise), the solve runs, and the Laplace covariance says why it is not
    computed instead of raising."""
    from casmag import memory
    from casmag.solver.uncertainty import without_hessian

    b = NLPBuilder()
    x = b.variable("x", (3, 1))
    b.cost("quadratic", ca.sumsqr(x - 1.0))
    nlp = b.build(SolverSpec(hessian="limited-memory", max_iter=50))
    assert nlp.progress.budget == memory.budget_bytes(None)  # checked before every solve
    assert nlp.hessian_nonzeros() >= 3
    sol = nlp.solve({}, {"x": np.zeros(3)})
    assert sol.success, sol.status
    np.testing.assert_allclose(np.ravel(sol.x["x"]), 1.0, atol=1e-6)
    assert "limited-memory" in without_hessian(nlp)["error"]
    assert without_hessian(_tiny_nlp(1e-8)) is None


LIBRARY_CTRL_C = """
import os, signal
import numpy as np
from casmag.nlp import NLPBuilder
from casmag.problem.spec import SolverSpec

b = NLPBuilder()
x = b.variable("x", (2, 1))
a = b.parameter("a", (1, 1))
b.cost("stiff", a * ((x[0] - 0.1) ** 2 + np.pi * (x[0] - 0.2) ** 2) + (x[1] - 0.1) ** 2)
nlp = b.build(SolverSpec(tol=1e-30, max_iter=200, ipopt={"tiny_step_tol": 0.0}))
seen = []

def progress(k, cost, step, seconds):
    seen.append(k)
    if k == 2:
        os.kill(os.getpid(), signal.SIGINT)

try:
    nlp.solve({"a": 1e12}, {"x": np.array([0.5, 1.0])}, progress=progress)
except KeyboardInterrupt:
    print("KeyboardInterrupt after", len(seen))
"""


def test_ctrl_c_in_a_library_solve_stops_ipopt_then_raises_keyboard_interrupt():
    """Without casmag's own handler (a library caller), Ctrl-C during a solve is held back
    like the command line's: IPOPT stops at its next iteration (it would run on to 200
    here), then KeyboardInterrupt is raised, not a solver failure."""
    import subprocess
    import sys

    res = subprocess.run(
        [sys.executable, "-c", LIBRARY_CTRL_C], capture_output=True, text=True, timeout=120
    )
    assert res.returncode == 0, res.stderr
    assert res.stdout.split()[:2] == ["KeyboardInterrupt", "after"], res.stdout
    assert int(res.stdout.split()[2]) <= 4


def _one_residual_nlp(hessian, curvature):
    """0.5 r^2 with r = x^2 - 2: at x = 1, J^T J = 4 and the exact Hessian 4 + 2 r = 2."""
    b = NLPBuilder()
    x = b.variable("x", (1, 1))
    b.residual("r", x**2 - 2.0, curvature=curvature)
    return b.build(SolverSpec(hessian=hessian), residuals=b.gauss_newton_residuals(hessian))


def test_a_residual_block_keeps_its_curvature_unless_gauss_newton_is_asked_for():
    """NLPBuilder.residual(curvature=True) (the planar and pose odometry): the exact Hessian
    under auto, hybrid and exact, J^T J under gauss-newton; a residual declared without it
    (the IMU's) is J^T J under everything but exact."""
    for hessian in ("auto", "hybrid", "exact", "gauss-newton"):
        for curvature in (True, False):
            nlp = _one_residual_nlp(hessian, curvature)
            H = nlp.hessian({"x": np.ones(1)}, {}).toarray()
            exact = hessian == "exact" or (curvature and hessian != "gauss-newton")
            assert H[0, 0] == (2.0 if exact else 4.0), (hessian, curvature)


def test_the_planar_and_pose_odometry_keep_their_curvature():
    """The odometry turns its increments by the estimated heading or attitude, so its
    residual is not linear in the unknowns: J^T J alone made IPOPT converge linearly on a
    1,500-sample planar floor walk (131 iterations against 22)."""
    from casmag.model.planar import PlanarMotion
    from casmag.model.pose import PoseMotion

    for motion in (PlanarMotion(n=6), PoseMotion(n=6)):
        b = NLPBuilder()
        motion.declare(b)
        assert "odometry" in b.curved
        assert "odometry" not in b.gauss_newton_residuals("auto")
        assert "odometry" in b.gauss_newton_residuals("gauss-newton")
