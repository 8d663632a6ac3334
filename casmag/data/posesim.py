"""Simulated pose-odometry recordings: a walker (or a vessel) on the translational
simulation's path, facing where it goes with a small roll and pitch wobble, the field of
that simulation (dipoles below the floor, casmag.data.simulate) read by a body-fixed
magnetometer, and body-frame odometry increments (dp, dq) with noise and constant biases
(casmag.model.pose for the convention)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from casmag import strapdown as sd
from casmag.data.simulate import simulate
from casmag.problem.spec import SimulationSpec


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
    P2 = np.asarray(data.P_true, dtype=float)
    if P2.shape[1] != 2:
        raise ValueError("the pose simulation takes a planar (2-D) path")
    n = P2.shape[0]
    rng_att, rng_odo, rng_mag = (
        np.random.default_rng(s) for s in np.random.SeedSequence([seed, 7]).spawn(3)
    )
    step = np.diff(P2, axis=0)
    yaw = np.unwrap(np.arctan2(step[:, 1], step[:, 0]))
    yaw = np.r_[yaw, yaw[-1]]
    tilt = np.radians(tilt_deg)
    roll = smooth_noise(n, tilt, 5, rng_att)
    pitch = smooth_noise(n, tilt, 5, rng_att)
    Q = sd.quat_from_euler(roll, pitch, yaw)
    P = np.column_stack([P2, np.full(n, float(height))])
    M = data.M_true  # the field at the path, world frame
    Y = sd.rotate(sd.quat_conj(Q), M) + spec.magnetometer.noise * rng_mag.standard_normal((n, 3))
    dt = 1.0 / rate_hz
    true = sd.pose_increments(P, Q)
    b = np.asarray(spec.odometry.bias if bias_p is None else bias_p, dtype=float).ravel()
    bias_p = np.zeros(3)
    bias_p[: b.size] = b
    bw = np.asarray(bias_w, dtype=float)
    dp = true[:, :3] + bias_p + spec.odometry.noise * rng_odo.standard_normal((n - 1, 3))
    rot = bw * dt + rotation_noise * rng_odo.standard_normal((n - 1, 3))
    dq = sd.quat_mul(true[:, 3:], sd.quat_exp(rot))
    return PoseRecording(
        t=dt * np.arange(n), Y=Y, U=np.column_stack([dp, dq]), P_true=P, q_true=Q,
        bias_p=bias_p, bias_w=bw,
    )  # fmt: skip
