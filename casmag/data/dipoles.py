"""A physical magnetic field for the simulator: Earth's field plus point dipoles.

Units: the field is in arbitrary units (a.u.) with Earth's field of magnitude 1, as the
paper's magnetometer reports it; positions in metres; a dipole moment is given in
a.u. m^3, so a dipole of moment m at distance r along its axis adds 2 |m| / r^3 a.u.

The field of a dipole with moment m at position c is

    B(x) = (3 (m . r_hat) r_hat - m) / |r|^3,   r = x - c,

curl-free and divergence-free away from c, like the ambient field indoors (the sources are
steel and electronics off the path). The simulator uses it so the GP map is tested on a field
it did not generate.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np


def earth_field(inclination_deg: float = 67.0, declination_deg: float = 2.0) -> np.ndarray:
    """(3,) Earth's field of magnitude 1 a.u. in the local frame (x east, y north, z up):
    pointing to magnetic north (declination east of north) and down by the inclination."""
    inc, dec = np.radians(inclination_deg), np.radians(declination_deg)
    return np.array([np.cos(inc) * np.sin(dec), np.cos(inc) * np.cos(dec), -np.sin(inc)])


@dataclass(frozen=True)
class Dipole:
    """A point dipole: position (3,) [m], moment (3,) [a.u. m^3], a label."""

    position: np.ndarray
    moment: np.ndarray
    name: str = ""

    def field(self, X: np.ndarray) -> np.ndarray:
        """(N, 3) field of this dipole at points X (N, 3)."""
        r = np.atleast_2d(np.asarray(X, dtype=float)) - np.asarray(self.position, dtype=float)
        d2 = np.sum(r * r, axis=1, keepdims=True)
        d = np.sqrt(d2)
        m = np.asarray(self.moment, dtype=float)
        mr = r @ m
        return (3.0 * mr[:, None] * r / d2 - m) / (d2 * d)

    def strength_at(self, distance: float) -> float:
        """On-axis field magnitude 2 |m| / r^3 at a distance [m]."""
        return float(2.0 * np.linalg.norm(self.moment) / distance**3)


@dataclass(frozen=True)
class DipoleField:
    """Earth's (uniform) field plus dipoles. ``earth``: (3,) a.u. (zeros for none)."""

    earth: np.ndarray
    dipoles: Sequence[Dipole] = field(default_factory=tuple)

    def __call__(self, X: np.ndarray) -> np.ndarray:
        """(N, 3) field at points X (N, 3) [a.u.]."""
        X = np.atleast_2d(np.asarray(X, dtype=float))
        B = np.tile(np.asarray(self.earth, dtype=float), (X.shape[0], 1))
        for d in self.dipoles:
            B += d.field(X)
        return B

    def jacobian(self, X: np.ndarray, h: float = 1e-6) -> np.ndarray:
        """(N, 3, 3) dB_i/dx_j by central differences (for tests and diagnostics)."""
        X = np.atleast_2d(np.asarray(X, dtype=float))
        J = np.empty((X.shape[0], 3, 3))
        for j in range(3):
            e = np.zeros(3)
            e[j] = h
            J[:, :, j] = (self(X + e) - self(X - e)) / (2 * h)
        return J


def moment_for(strength: float, distance: float, direction: Sequence[float]) -> np.ndarray:
    """The moment [a.u. m^3] whose on-axis field at ``distance`` [m] has magnitude
    ``strength`` [a.u.], along ``direction``."""
    u = np.asarray(direction, dtype=float)
    u = u / np.linalg.norm(u)
    return 0.5 * strength * distance**3 * u
