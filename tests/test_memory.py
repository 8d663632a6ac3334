"""casmag.memory and solver.memory_budget: a solve that would not fit is refused before IPOPT
starts, one that outgrows the budget is stopped, and both fail with their own status."""

import casadi as ca
import numpy as np
import pytest
from click.testing import CliRunner
from small_problems import tiny_walk

import casmag
from casmag import memory
from casmag.cli.main import main
from casmag.errors import MemoryBudgetError
from casmag.nlp import MEMORY_STATUS, NLPBuilder
from casmag.problem.spec import SolverSpec


def _nlp(budget_gib):
    b = NLPBuilder()
    x = b.variable("x", (3, 1))
    b.cost("quadratic", ca.sumsqr(x - 1.0))
    return b.build(SolverSpec(memory_budget=budget_gib))


def test_budget_defaults_to_a_fraction_of_the_machine():
    machine = memory.machine_bytes()
    assert 0 < memory.rss_bytes() < machine
    assert memory.budget_bytes(None) == int(memory.BUDGET_FRACTION * machine)
    assert memory.budget_bytes(2.5) == int(2.5 * memory.GIB)


def test_estimate_grows_with_the_hessian():
    small, large = memory.solve_estimate(0), memory.solve_estimate(10**7)
    assert large - small >= memory.HESSIAN_NONZERO_BYTES * 10**7 - 2**24  # RSS may move


def test_a_solve_over_budget_is_refused_before_ipopt_starts():
    nlp = _nlp(1e-4)  # 0.1 MiB: less than the interpreter itself
    sol = nlp.solve({}, {"x": np.zeros(3)})
    assert sol.status == MEMORY_STATUS and not sol.success and sol.iterations == 0
    assert "solver.memory_budget" in sol.stats["memory"]
    np.testing.assert_array_equal(sol.x["x"].ravel(), np.zeros(3))  # x0 unchanged


def test_a_solve_that_outgrows_its_budget_is_stopped(monkeypatch):
    """The pre-flight estimate passes (made zero here); the per-iteration check then finds
    the process above the budget and stops IPOPT at its first iteration."""
    nlp = _nlp(1e-4)
    monkeypatch.setattr(memory, "solve_estimate", lambda nonzeros: 0)
    sol = nlp.solve({}, {"x": np.zeros(3)})
    assert sol.status == MEMORY_STATUS and not sol.success
    assert sol.iterations <= 1
    assert "while solving" in sol.stats["memory"]


def test_within_budget_solves_as_before():
    sol = _nlp(None).solve({}, {"x": np.zeros(3)})
    assert sol.status == "Solve_Succeeded"
    np.testing.assert_allclose(sol.x["x"].ravel(), np.ones(3), atol=1e-8)
    assert _nlp(None).hessian_nonzeros() == 3  # the diagonal


def test_a_problem_over_budget_is_refused_while_its_nlp_is_built():
    """The map's Hessian pattern is held against the budget before CasADi copies it: the
    build raises, naming the budget, and nothing is solved."""
    with pytest.raises(MemoryBudgetError, match=r"solver\.memory_budget"):
        casmag.solve(tiny_walk(["solver.memory_budget=0.0001"]))
    assert casmag.solve(tiny_walk()).success  # the default budget: the machine's


def test_the_command_line_says_what_to_change(root, tmp_path):
    out = tmp_path / "out"
    r = CliRunner().invoke(
        main,
        [
            "run",
            str(root / "problems/paper/base.yaml"),
            "--out",
            str(out),
            "--set",
            "solver.memory_budget=0.0001",
        ],
    )
    assert r.exit_code == 1
    lines = r.output.splitlines()
    assert len(lines) == 1
    assert "base.yaml" in lines[0] and "solver.memory_budget" in lines[0]
    assert not out.exists()  # refused before anything was solved or written
