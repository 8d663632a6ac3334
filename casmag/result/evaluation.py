"""Trajectory errors against the truth, in the frame a user asks for.

Every solve fixes its frame by an anchor (a known first position, for IMU problems the
initial-state priors): ``info["anchor"]`` of a result says which. casmag's error fields
(``rmse_after`` and the like) are measured in that frame without alignment, as in the
paper's tables. :func:`evaluate` measures them again after an optional alignment of each
trajectory to the truth, as trajectory-evaluation tools do:

- ``none``: no alignment (the anchored frame);
- ``start``: translated so that the first position equals the first true position;
- ``se``: the rotation and translation (SE(2) in the plane, SE(3) in space, no scale) that
  minimise the squared position errors, in closed form (Umeyama 1991).

Each trajectory (the estimate, and the one it is compared with: the dead reckoning or the
IMU-only adjustment) is aligned on its own. The result goes to ``result.json`` as
``evaluation``; ``casmag report --align`` recomputes it from ``arrays.npz``.

Whatever the alignment asked for, ``evaluation["rigid"]`` also gives both errors after the
``se`` fit: the part of the error that is not one rotation and translation of the whole path.
A path whose heading went wrong in its first seconds and was right in shape afterwards has
a large RMSE and a small rigid one (measured on the hand-held ``square`` recording: 0.74 m,
and 0.098 m after the rigid fit, a rotation of 8.1 deg).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from casmag.errors import DataError
from casmag.result.metrics import rmse_and_max

#: The alignments :func:`evaluate` takes.
ALIGNMENTS = ("none", "start", "se")

#: The trajectory a result is compared with, by the first key present in its arrays.
BEFORE_KEYS = ("P_odometry", "P_imu_only")


def rigid_alignment(P: np.ndarray, P_true: np.ndarray, align: str) -> tuple[np.ndarray, np.ndarray]:
    """(R, t), d x d rotation and (d,) translation, with R p + t the aligned position of p.

    ``none``: identity; ``start``: t = P_true[0] - P[0]; ``se``: the least-squares rigid
    transform (Umeyama, no scale; a reflection is never returned)."""
    P, P_true = np.asarray(P, dtype=float), np.asarray(P_true, dtype=float)
    if P.shape != P_true.shape or P.ndim != 2:
        raise ValueError(f"shape mismatch: trajectory {P.shape}, truth {P_true.shape}")
    d = P.shape[1]
    if align == "none":
        return np.eye(d), np.zeros(d)
    if align == "start":
        return np.eye(d), P_true[0] - P[0]
    if align != "se":
        raise ValueError(f"align: expected one of {', '.join(ALIGNMENTS)}, got {align!r}")
    mu, mu_true = P.mean(axis=0), P_true.mean(axis=0)
    C = (P_true - mu_true).T @ (P - mu) / P.shape[0]
    U, _, Vt = np.linalg.svd(C)
    S = np.eye(d)
    S[-1, -1] = np.sign(np.linalg.det(U @ Vt)) or 1.0
    R = U @ S @ Vt
    return R, mu_true - R @ mu


def aligned_errors(P: np.ndarray | None, P_true: np.ndarray | None, align: str) -> dict[str, Any]:
    """RMSE and max position error [m] of P after its alignment to P_true, with the
    alignment (rotation angle [deg] about the vertical or its axis, translation [m]);
    values None when either trajectory is absent."""
    if P is None or P_true is None:
        return {"rmse": None, "max": None, "rotation_deg": None, "translation": None}
    R, t = rigid_alignment(P, P_true, align)
    rmse, worst = rmse_and_max(np.asarray(P, dtype=float) @ R.T + t, P_true)
    angle = float(np.degrees(np.arccos(np.clip((np.trace(R) - (R.shape[0] - 2)) / 2, -1, 1))))
    return {
        "rmse": rmse,
        "max": worst,
        "rotation_deg": angle,
        "translation": [float(v) for v in t],
    }


def evaluate(arrays: Mapping[str, Any], align: str = "none", anchor: Any = None) -> dict[str, Any]:
    """The ``evaluation`` of a result from its arrays (``P_estimate``, ``P_true`` and the
    first of :data:`BEFORE_KEYS`): ``{"anchor", "align", "before": {...}, "after": {...},
    "rigid": {"before": {...}, "after": {...}}}`` with each part as :func:`aligned_errors`
    returns it, ``rigid`` after the ``se`` fit whatever ``align`` is ("after" None-valued when
    the estimate is absent, as after a failed solve)."""
    if align not in ALIGNMENTS:
        raise DataError(f"align: expected one of {', '.join(ALIGNMENTS)}, got {align!r}")
    P_true = arrays.get("P_true")
    before_key = next((k for k in BEFORE_KEYS if arrays.get(k) is not None), None)
    P_before = None if before_key is None else arrays[before_key]
    P_after = arrays.get("P_estimate")
    return {
        "anchor": anchor,
        "align": align,
        "before_trajectory": before_key,
        "before": aligned_errors(P_before, P_true, align),
        "after": aligned_errors(P_after, P_true, align),
        "rigid": {
            "before": aligned_errors(P_before, P_true, "se"),
            "after": aligned_errors(P_after, P_true, "se"),
        },
    }


def evaluate_result(result: Any, align: str = "none") -> dict[str, Any]:
    """:func:`evaluate` on a result (any motion model): its arrays, its anchor
    (``info["anchor"]``). A failed solve has no estimate to align."""
    P_est = result.arrays.get("P_estimate") if result.success else None
    arrays = {**result.arrays, "P_estimate": P_est}
    return evaluate(arrays, align, result.info.get("anchor"))


def anchor_info(data: Any, sigma: float) -> dict[str, Any]:
    """How a translational data set fixes its frame: its anchor (one known first position
    per session, soft with standard deviation sigma [m]) and where the anchor comes from."""
    anchor = np.asarray(data.anchor, dtype=float).reshape(-1, np.shape(data.U)[1])
    kind = "given"
    if data.P_true is not None:
        firsts = np.asarray(data.P_true)[list(getattr(data, "starts", None) or [0])]
        if firsts.shape == anchor.shape and np.allclose(firsts, anchor):
            kind = "first true position"
    if kind == "given" and not anchor.any():
        kind = "origin (no truth)" if data.P_true is None else "origin"
    rows = [[float(v) for v in a] for a in anchor]
    return {"kind": kind, "position": rows[0] if len(rows) == 1 else rows, "sigma": sigma}
