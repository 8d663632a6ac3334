"""Simulated recordings whose magnetometer turns with the body: a walker (or a vehicle) on
the translational simulation's path (casmag.data.simulate), facing where it goes, the field
of that simulation read by a body-fixed magnetometer, and body-frame odometry with noise and
constant biases.

- :func:`simulate_pose`: pose odometry, increments (dp, dq) with a small roll and pitch
  wobble (casmag.model.pose for the convention);
- :func:`simulate_planar`: planar odometry, increments (dfwd, dleft, dyaw) in the plane
  with a heading-rate bias (casmag.model.planar).

Both give a :class:`casmag.data.recording.Recording` (``recording``), the input of
``casmag slam``'s solve, as a recording file read back would be."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from casmag import strapdown as sd
from casmag.data.recording import Recording
from casmag.data.simulate import simulate
from casmag.problem.spec import SimulationSpec

#: The recording columns of each motion input (casmag.data.recording).
POSE_COLUMNS = ("dpx", "dpy", "dpz", "dqw", "dqx", "dqy", "dqz")
PLANAR_COLUMNS = ("dfwd", "dleft", "dyaw")


@dataclass(frozen=True)
class PoseRecording:
    """Arrays of a pose recording (``write_recording(path, t, Y, pose=U, P_true=P_true,
    q_true=q_true)``) and the true biases."""

    t: np.ndarray  # (N,) [s]
    Y: np.ndarray  # (N, 3) body-frame magnetometer
    U: np.ndarray  # (N-1, 7) measured dp, dq
    P_true: np.ndarray  # (N, 3)
    q_true: np.ndarray  # (N, 4)
    bias_p: np.ndarray  # (3,) m per step, body frame
    bias_w: np.ndarray  # (3,) rad/s

    def recording_arrays(self) -> dict[str, np.ndarray]:
        return {"t": self.t, "Y": self.Y, "pose": self.U, "P_true": self.P_true,
                "q_true": self.q_true}  # fmt: skip

    def recording(self, name: str) -> Recording:
        """The recording ``read_recording`` would give of these arrays written as ``name``."""
        return Recording(
            path=name, t=self.t, motion="pose", increments=self.U,
            increment_names=POSE_COLUMNS, Y=self.Y, P_true=self.P_true, q_true=self.q_true,
        )  # fmt: skip


@dataclass(frozen=True)
class PlanarRecording:
    """Arrays of a planar recording (``write_recording(path, t, Y, planar=U, P_true=P_true,
    yaw_true=psi_true)``) and the true biases."""

    t: np.ndarray  # (N,) [s]
    Y: np.ndarray  # (N, 3) magnetometer in the heading-rotated body frame
    U: np.ndarray  # (N-1, 3) measured dfwd, dleft [m], dyaw [rad]
    P_true: np.ndarray  # (N, 2)
    psi_true: np.ndarray  # (N,) [rad]
    bias_p: np.ndarray  # (2,) m per step, body frame
    bias_w: float  # rad/s

    def recording_arrays(self) -> dict[str, np.ndarray]:
        return {"t": self.t, "Y": self.Y, "planar": self.U, "P_true": self.P_true,
                "yaw_true": self.psi_true}  # fmt: skip

    def recording(self, name: str) -> Recording:
        """The recording ``read_recording`` would give of these arrays written as ``name``."""
        return Recording(
            path=name, t=self.t, motion="planar", increments=self.U,
            increment_names=PLANAR_COLUMNS, Y=self.Y, P_true=self.P_true,
            yaw_true=self.psi_true,
        )  # fmt: skip


def smooth_noise(n: int, scale: float, width: int, rng: np.random.Generator) -> np.ndarray:
    """(n,) zero-mean noise of standard deviation ``scale``, smoothed over ``width`` samples."""
    raw = rng.standard_normal(n + 2 * width)
    kernel = np.hanning(2 * width + 1)
    out = np.convolve(raw, kernel / kernel.sum(), mode="same")[width : width + n]
    return scale * out / max(float(out.std()), 1e-12)


def simulate_pose(
    spec: SimulationSpec,
    seed: int,
    rate_hz: float = 2.0,
    rotation_noise: float = 3e-3,
    bias_w: tuple[float, float, float] = (0.0, 0.0, 0.0),
    bias_p: tuple[float, float, float] | None = None,
    tilt_deg: float = 3.0,
    height: float = 0.0,
) -> PoseRecording:
    """A pose recording of the translational simulation ``spec`` with ``seed``: its path
    (at ``height``) and field, samples ``rate_hz`` apart; heading along the path, roll and
    pitch a smooth wobble of ``tilt_deg`` (standard deviation); displacement noise
    ``spec.odometry.noise`` per step and axis and bias ``bias_p`` (body frame; None:
    ``spec.odometry.bias`` padded with zeros to three axes); rotation noise
    ``rotation_noise`` rad per step and axis and rate bias ``bias_w`` rad/s; magnetometer
    noise ``spec.magnetometer.noise``."""
    data = simulate(spec, seed)
    P2, yaw = _path_and_heading(data.P_true, "pose")
    n = P2.shape[0]
    rng_att, rng_odo, rng_mag = (
        np.random.default_rng(s) for s in np.random.SeedSequence([seed, 7]).spawn(3)
    )
    tilt = np.radians(tilt_deg)
    roll = smooth_noise(n, tilt, 5, rng_att)
    pitch = smooth_noise(n, tilt, 5, rng_att)
    Q = sd.quat_from_euler(roll, pitch, yaw)
    P = np.column_stack([P2, np.full(n, float(height))])
    M = data.M_true  # the field at the path, world frame
    Y = sd.rotate(sd.quat_conj(Q), M) + spec.magnetometer.noise * rng_mag.standard_normal((n, 3))
    dt = 1.0 / rate_hz
    true = sd.pose_increments(P, Q)
    bp = _body_bias(spec, bias_p, 3)
    bw = np.asarray(bias_w, dtype=float)
    dp = true[:, :3] + bp + spec.odometry.noise * rng_odo.standard_normal((n - 1, 3))
    rot = bw * dt + rotation_noise * rng_odo.standard_normal((n - 1, 3))
    dq = sd.quat_mul(true[:, 3:], sd.quat_exp(rot))
    return PoseRecording(
        t=dt * np.arange(n), Y=Y, U=np.column_stack([dp, dq]), P_true=P, q_true=Q,
        bias_p=bp, bias_w=bw,
    )  # fmt: skip


def _path_and_heading(P_true: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    """The simulation's planar path (N, 2) and the heading along it [rad], unwrapped (the
    last sample keeps the last step's)."""
    P2 = np.asarray(P_true, dtype=float)
    if P2.shape[1] != 2:
        raise ValueError(f"the {what} simulation takes a planar (2-D) path")
    step = np.diff(P2, axis=0)
    yaw = np.unwrap(np.arctan2(step[:, 1], step[:, 0]))
    return P2, np.r_[yaw, yaw[-1]]


def _body_bias(spec: SimulationSpec, bias: Any, axes: int) -> np.ndarray:
    """A body-frame displacement bias of ``axes`` components [m per step]: ``bias``, or
    (None) ``spec.odometry.bias`` padded with zeros."""
    b = np.asarray(spec.odometry.bias if bias is None else bias, dtype=float).ravel()
    if b.size > axes:
        raise ValueError(f"a displacement bias of {b.size} axes, the odometry has {axes}")
    out = np.zeros(axes)
    out[: b.size] = b
    return out


def simulate_planar(
    spec: SimulationSpec,
    seed: int,
    rate_hz: float = 2.0,
    heading_noise: float = 1.0e-3,
    heading_bias: float = 0.0,
    bias_p: tuple[float, float] | None = None,
) -> PlanarRecording:
    """A planar recording of the translational simulation ``spec`` with ``seed``: its path
    and field, samples ``rate_hz`` apart, heading along the path; body-frame displacement
    noise ``spec.odometry.noise`` per step and axis and bias ``bias_p`` (forward, left; None:
    ``spec.odometry.bias``); heading-increment noise ``heading_noise`` rad per step and a
    constant heading-rate bias ``heading_bias`` rad/s; the magnetometer reads the field
    turned by the heading, Rz(psi)^T B(p), plus noise ``spec.magnetometer.noise``."""
    data = simulate(spec, seed)
    P, psi = _path_and_heading(data.P_true, "planar")
    n = P.shape[0]
    rng_odo, rng_mag = (
        np.random.default_rng(s) for s in np.random.SeedSequence([seed, 11]).spawn(2)
    )
    d = np.diff(P, axis=0)
    c, s = np.cos(psi[:-1]), np.sin(psi[:-1])
    body = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])
    dt = 1.0 / rate_hz
    noise = rng_odo.standard_normal((n - 1, 3))
    bias_p2 = _body_bias(spec, bias_p, 2)
    U = np.column_stack(
        [
            body + bias_p2 + spec.odometry.noise * noise[:, :2],
            np.diff(psi) + heading_bias * dt + heading_noise * noise[:, 2],
        ]
    )
    M = np.asarray(data.M_true, dtype=float)
    cp, sp = np.cos(psi), np.sin(psi)
    Y = np.column_stack([cp * M[:, 0] + sp * M[:, 1], -sp * M[:, 0] + cp * M[:, 1], M[:, 2]])
    Y = Y + spec.magnetometer.noise * rng_mag.standard_normal((n, 3))
    return PlanarRecording(
        t=dt * np.arange(n), Y=Y, U=U, P_true=P, psi_true=psi, bias_p=bias_p2,
        bias_w=float(heading_bias),
    )  # fmt: skip
