"""Sparse symmetric positive-definite solves with MUMPS, the multifrontal solver casadi's
wheel ships (the one IPOPT uses), through casadi's ``Linsol``; SuperLU where that plugin
is missing. And the product of a sparse matrix with a dense one, sparse or by BLAS as its
fill decides (:func:`dense_product`).

SuperLU (scipy) factors the tiled map's weight normal equations in one front at a time;
MUMPS's dense fronts use the wheel's OpenBLAS. Measured on this project's 2-core machine
(casadi 3.8.2), each run alone, the same right-hand side, relative residuals 1e-14 to
1e-15 for both; MUMPS given both triangles and, as here, the upper one (casadi's symmetric
interface reads that one; the last column's walks: the whole initial-weight solve less
its assembly):

| system | unknowns | non-zeros | SuperLU (COLAMD) | MUMPS, both | MUMPS, upper |
|---|---|---|---|---|---|
| 10,000-sample walk over 6 x 6 m, 49 tiles | 8,134 | 4.7 M | 1.9 s | 2.3 s | 0.8 s |
| ``library`` (ARKit), 74 tiles | 12,284 | 10.0 M | 14.3 s | 3.7 s | 2.9 s |
| 10,000-sample walk over 20 x 20 m, 261 tiles | 43,326 | 43.7 M | 189.5 s | 32.5 s | 16.7 s |

SuperLU with minimum degree on A^T + A in symmetric mode took 13.9 s on ``library``, and
CSparse's Cholesky (casadi's ``csparsecholesky``) 14.1 s.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import scipy.sparse as sps
import scipy.sparse.linalg as spla


@contextmanager
def _quiet_stdout() -> Iterator[None]:
    """File descriptor 1 sent to the null device: MUMPS writes a line to the process's
    standard output when casadi's interface ends it (``JOB = -2``), past Python's
    ``sys.stdout``. Without a descriptor 1 (or one that cannot be duplicated), as is."""
    try:
        sys.stdout.flush()
        saved = os.dup(1)
    except (OSError, ValueError):
        yield
        return
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(null, 1)
        yield
    finally:
        os.close(null)
        os.dup2(saved, 1)
        os.close(saved)


def solve_spd(G: sps.spmatrix, b: np.ndarray, upper: bool = False) -> np.ndarray:
    """x with G x = b for a sparse symmetric positive-definite G (both triangles given, or
    with ``upper`` its upper triangle alone) and a vector b: MUMPS (casadi's ``mumps``
    Linsol, symmetric positive definite), or SuperLU with COLAMD when this casadi has no
    such plugin."""
    import casadi as ca

    b = np.asarray(b, dtype=float).ravel()
    if not ca.has_linsol("mumps"):
        full = sps.csc_matrix(G)
        if upper:
            full = (full + sps.triu(full, 1).T).tocsc()
        return spla.splu(full, permc_spec="COLAMD").solve(b)
    U = sps.csc_matrix(G if upper else sps.triu(sps.csc_matrix(G)))
    U.sort_indices()
    n = U.shape[0]
    sp = ca.Sparsity(n, n, U.indptr.tolist(), U.indices.tolist())
    with _quiet_stdout():
        solver = ca.Linsol("spd", "mumps", sp, {"symmetric": True, "posdef": True})
        x = np.asarray(solver.solve(ca.DM(sp, U.data), ca.DM(b))).ravel()
        del solver  # MUMPS's closing line goes to the null device too
    return x


#: Bytes of one dense slab of rows of a sparse matrix in :func:`dense_product`, and the
#: fraction of non-zeros below which it multiplies the sparse matrix as it is (above, it
#: expands it in slabs). Measured on this project's 2-core machine, a 5,620 x 4,501 sparse
#: matrix times a dense 4,501 x 5,620 one (a tiled map's border against its solve): 2.1 /
#: 3.8 / 8.0 s sparse at 2 / 4 / 8 % fill against 3.9 / 4.0 / 3.3 s dense.
DENSE_SLAB_BYTES = 64 * 2**20
DENSE_PRODUCT_FILL = 0.04


def dense_product(S: Any, Z: np.ndarray) -> np.ndarray:
    """S @ Z for a dense or sparse S (n, m) and a dense Z (m, k): a sparse S filled above
    :data:`DENSE_PRODUCT_FILL` is expanded to dense slabs of rows (:data:`DENSE_SLAB_BYTES`
    each) and multiplied by BLAS. The Hessian corrections of casmag.solver.uncertainty are
    dense in their map blocks, where scipy's sparse product runs on one core without
    blocking: 39 s against 1.7 s for a 16,000-sample walk's correction (5,570 unknowns,
    3,200 knot columns)."""
    if not hasattr(S, "tocsr"):
        return np.asarray(S) @ Z
    S = S.tocsr()
    n = S.shape[0]
    if S.nnz < DENSE_PRODUCT_FILL * n * S.shape[1]:  # e.g. the exact GP's diagonal
        return np.asarray(S @ Z)
    rows = max(1, DENSE_SLAB_BYTES // (8 * max(S.shape[1], 1)))
    out = np.empty((n, Z.shape[1]))
    for i in range(0, n, rows):
        out[i : i + rows] = S[i : i + rows].toarray() @ Z
    return out
