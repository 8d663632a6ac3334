"""casmag.linalg: the sparse symmetric positive-definite solve (MUMPS through casadi)."""

import os
import subprocess
import sys
import textwrap

import casadi as ca
import numpy as np
import scipy.sparse as sps

from casmag.linalg import solve_spd


def _spd(n: int, seed: int) -> sps.csc_matrix:
    A = sps.random(n, n, density=0.05, random_state=np.random.default_rng(seed))
    return (A @ A.T + sps.eye(n)).tocsc()


def test_solve_spd_matches_a_dense_solve():
    G = _spd(300, 1)
    b = np.random.default_rng(2).normal(size=300)
    x = solve_spd(G, b)
    assert np.allclose(x, np.linalg.solve(G.toarray(), b), rtol=1e-10, atol=1e-12)


def test_solve_spd_from_the_upper_triangle_alone():
    G = _spd(300, 4)
    b = np.random.default_rng(5).normal(size=300)
    x = solve_spd(sps.triu(G).tocsc(), b, upper=True)
    assert np.allclose(x, np.linalg.solve(G.toarray(), b), rtol=1e-10, atol=1e-12)


def test_solve_spd_without_the_mumps_plugin_falls_back_to_superlu(monkeypatch):
    G = _spd(120, 3)
    b = np.arange(120, dtype=float)
    monkeypatch.setattr(ca, "has_linsol", lambda name: False)
    assert np.allclose(G @ solve_spd(G, b), b, atol=1e-9)
    assert np.allclose(G @ solve_spd(sps.triu(G).tocsc(), b, upper=True), b, atol=1e-9)


def test_solve_spd_writes_nothing_to_standard_output(tmp_path):
    """MUMPS's closing line is not in a redirected standard output, even when the process
    exits (gfortran buffers that unit when it is not a terminal)."""
    script = textwrap.dedent(
        """
        import numpy as np, scipy.sparse as sps
        from casmag.linalg import solve_spd
        G = (sps.random(50, 50, density=0.1, random_state=1) + 2 * sps.eye(50)).tocsc()
        x = solve_spd(G @ G.T, np.ones(50))
        print("solved")
        """
    )
    env = {k: v for k, v in os.environ.items() if not k.startswith("GFORTRAN_")}
    out = tmp_path / "stdout.txt"
    with out.open("w") as fh:
        subprocess.run([sys.executable, "-c", script], stdout=fh, check=True, env=env)
    assert out.read_text() == "solved\n"
