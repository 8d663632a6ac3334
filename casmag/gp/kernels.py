"""Covariance functions for the magnetic field (paper Eq. 7 and 8).

Each kernel is written once against a small array "backend", so the same code builds a numpy
matrix (simulation, tests) and a CasADi SX/MX matrix (the NLP). Matrices of 3-component
kernels are ordered component-major: rows 0..N-1 are the x components of the N points, then
y, then z, which is ``vec`` of an (N, 3) field matrix in CasADi's column-major order.

Positions may be 2-D (a plane) or 3-D. The field always has three components; the curl-free
and divergence-free kernels embed 2-D positions in the plane z = 0.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any

import casadi as ca
import numpy as np

FIELD_DIM = 3


# --------------------------------------------------------------------------- backends
class _NumpyBackend:
    @staticmethod
    def diff(X1: np.ndarray, X2: np.ndarray, axis: int) -> np.ndarray:
        """(N1, N2) matrix of X1[i, axis] - X2[j, axis]; zero for a missing axis."""
        if axis >= X1.shape[1]:
            return np.zeros((X1.shape[0], X2.shape[0]))
        return X1[:, axis][:, None] - X2[:, axis][None, :]

    exp = staticmethod(np.exp)

    @staticmethod
    def block(rows: list[list[Any]]) -> np.ndarray:
        return np.block(rows)

    @staticmethod
    def ones_like(A: np.ndarray) -> np.ndarray:
        return np.ones_like(A)


class _CasadiBackend:
    @staticmethod
    def diff(X1: Any, X2: Any, axis: int) -> Any:
        n1, n2 = X1.shape[0], X2.shape[0]
        if axis >= X1.shape[1]:
            return ca.DM.zeros(n1, n2)
        return ca.repmat(X1[:, axis], 1, n2) - ca.repmat(X2[:, axis].T, n1, 1)

    exp = staticmethod(ca.exp)

    @staticmethod
    def block(rows: list[list[Any]]) -> Any:
        return ca.blockcat(rows)

    @staticmethod
    def ones_like(A: Any) -> Any:
        return ca.DM.ones(A.shape[0], A.shape[1])


def _backend(X: Any) -> type[_NumpyBackend] | type[_CasadiBackend]:
    return _NumpyBackend if isinstance(X, np.ndarray) else _CasadiBackend


# --------------------------------------------------------------------------- kernels
class Kernel(ABC):
    """A stationary kernel k(x, x') = k(r), r = x - x', with hyperparameters sigma_f, l.

    output_dim: 1 if the kernel models each field component independently with the same
    scalar covariance (the covariance matrix is block diagonal with three equal blocks),
    3 if it couples the components (a 3N x 3N matrix).
    """

    name: str
    output_dim: int
    input_dim: int | None = None  # forced input dimension (3 for curl/div-free), else any

    def matrix(self, X1: Any, X2: Any, sigma_f: Any, lengthscale: Any) -> Any:
        """Covariance matrix between point sets X1 (N1, d) and X2 (N2, d).

        Returns (N1, N2) for output_dim 1, (3 N1, 3 N2) component-major for output_dim 3.
        Works on numpy arrays and on CasADi symbols alike.
        """
        be = _backend(X1)
        d = self.input_dim or X1.shape[1]
        R = [be.diff(X1, X2, a) for a in range(d)]
        r2 = sum(Ra * Ra for Ra in R)
        return self._assemble(be, R, r2, sigma_f, lengthscale, d)

    @abstractmethod
    def _assemble(self, be: Any, R: list[Any], r2: Any, sigma_f: Any, ell: Any, d: int) -> Any:
        """Matrix from per-axis difference matrices R and squared distances r2."""

    def variance(self, sigma_f: float, lengthscale: float) -> float:
        """Prior variance of one field component at a point, k(0)[0, 0]."""
        return float(
            np.asarray(self.matrix(np.zeros((1, 2)), np.zeros((1, 2)), sigma_f, lengthscale))[0, 0]
        )

    @abstractmethod
    def spectral_density(
        self, omega: np.ndarray, sigma_f: float, lengthscale: float, d: int
    ) -> np.ndarray:
        """Spectral density S(|omega|) of the scalar covariance that generates the kernel
        (the kernel itself for ``se``; the scalar potential for ``curl_free``), in d dims."""


def _se_profile(be: Any, r2: Any, sigma_f: Any, ell: Any) -> Any:
    # Eq. 7: sigma_f^2 exp(-|r|^2 / (2 l^2)); r2 enters squared, so the gradient at r = 0 is 0
    # and no square root is ever taken (no NaN derivatives at coincident points).
    return sigma_f**2 * be.exp(-r2 / (2 * ell**2))


def _se_spectral_density(omega: np.ndarray, sigma_f: float, ell: float, d: int) -> np.ndarray:
    # S(w) = sigma_f^2 (2 pi l^2)^(d/2) exp(-l^2 w^2 / 2)  (Rasmussen & Williams Eq. 4.20)
    return (
        sigma_f**2
        * (2 * np.pi * ell**2) ** (d / 2)
        * np.exp(-0.5 * ell**2 * np.asarray(omega) ** 2)
    )


class SquaredExponential(Kernel):
    """Squared exponential per field component (paper Eq. 7):

        k(x, x') = sigma_f^2 exp(-|x - x'|^2 / (2 l^2)),

    applied independently to each of the three field components.
    """

    name = "se"
    output_dim = 1

    def _assemble(self, be: Any, R: list[Any], r2: Any, sigma_f: Any, ell: Any, d: int) -> Any:
        return _se_profile(be, r2, sigma_f, ell)

    def spectral_density(
        self, omega: np.ndarray, sigma_f: float, lengthscale: float, d: int
    ) -> np.ndarray:
        return _se_spectral_density(omega, sigma_f, lengthscale, d)


class CurlFree(Kernel):
    """Curl-free kernel (paper Eq. 8, K_H), the covariance of the gradient of a scalar
    potential with SE covariance sigma_f^2 exp(-|r|^2 / (2 l^2)):

        K_H(r) = (1 / l^2) (I - (r / l)(r / l)^T) sigma_f^2 exp(-|r|^2 / (2 l^2)).

    The variance of each field component is sigma_f^2 / l^2.
    """

    name = "curl_free"
    output_dim = 3
    input_dim = 3

    def _assemble(self, be: Any, R: list[Any], r2: Any, sigma_f: Any, ell: Any, d: int) -> Any:
        k = _se_profile(be, r2, sigma_f, ell) / ell**2
        rows = []
        for a in range(3):
            row = []
            for b in range(3):
                delta = 1.0 if a == b else 0.0
                row.append((delta - R[a] * R[b] / ell**2) * k)
            rows.append(row)
        return be.block(rows)

    def spectral_density(
        self, omega: np.ndarray, sigma_f: float, lengthscale: float, d: int
    ) -> np.ndarray:
        return _se_spectral_density(omega, sigma_f, lengthscale, d)


class DivergenceFree(Kernel):
    """Divergence-free kernel (paper Eq. 8, K_B), with n_x = 3:

    K_B(r) = (1 / l^2) ((n_x - 1 - |r / l|^2) I + (r / l)(r / l)^T)
             sigma_f^2 exp(-|r|^2 / (2 l^2)).
    """

    name = "div_free"
    output_dim = 3
    input_dim = 3

    def _assemble(self, be: Any, R: list[Any], r2: Any, sigma_f: Any, ell: Any, d: int) -> Any:
        k = _se_profile(be, r2, sigma_f, ell) / ell**2
        diag = (d - 1) - r2 / ell**2
        rows = []
        for a in range(3):
            row = []
            for b in range(3):
                term = R[a] * R[b] / ell**2
                row.append(((diag + term) if a == b else term) * k)
            rows.append(row)
        return be.block(rows)

    def spectral_density(
        self, omega: np.ndarray, sigma_f: float, lengthscale: float, d: int
    ) -> np.ndarray:
        raise NotImplementedError("the divergence-free kernel has no scalar spectral density here")


KERNELS: dict[str, type[Kernel]] = {
    SquaredExponential.name: SquaredExponential,
    CurlFree.name: CurlFree,
    DivergenceFree.name: DivergenceFree,
}


def get_kernel(name: str) -> Kernel:
    """Kernel instance by name: ``se``, ``curl_free`` or ``div_free``."""
    try:
        return KERNELS[name]()
    except KeyError:
        raise ValueError(f"unknown kernel {name!r}; choose one of {sorted(KERNELS)}") from None


def field_covariance(
    kernel: Kernel, X: np.ndarray, sigma_f: float, lengthscale: float
) -> np.ndarray:
    """Full 3N x 3N covariance of the stacked (component-major) field at points X (numpy)."""
    K = kernel.matrix(X, X, sigma_f, lengthscale)
    if kernel.output_dim == 1:
        return np.kron(np.eye(FIELD_DIM), K)
    return K
