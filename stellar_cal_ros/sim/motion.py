"""Analytic motion profiles of the IMU w.r.t. the local level frame.

Every profile gives, at arbitrary times ``t`` (s since the start of the scenario), the body
attitude ``R_n_b`` (body ``b`` = IMU frame to the local level frame ``n`` = ENU at the site),
the body rate w.r.t. ``n`` expressed in the body (``omega_nb_b``), and the position,
velocity and acceleration of the IMU in ``n`` relative to the site.  Rates are closed-form
derivatives of the attitudes so that the simulator can integrate them exactly into gyro
samples; ``test/test_sim.py`` checks the pair by strapdown propagation.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from stellar_cal_ros.core.rotation import so3_exp

_AXES = {"x": 0, "y": 1, "z": 2}


class Motion:
    """Interface of a motion profile (all arrays vectorized over ``t``)."""

    duration: float

    def attitude(self, t: np.ndarray) -> np.ndarray:
        """Return ``R_n_b`` (N, 3, 3)."""
        raise NotImplementedError

    def rate(self, t: np.ndarray) -> np.ndarray:
        """Return ``omega_nb_b`` (N, 3) in rad/s."""
        raise NotImplementedError

    def position(self, t: np.ndarray) -> np.ndarray:
        """Return the position in ``n`` relative to the site (N, 3), m."""
        return np.zeros((np.size(t), 3))

    def velocity(self, t: np.ndarray) -> np.ndarray:
        """Return the velocity w.r.t. the Earth in ``n`` (N, 3), m/s."""
        return np.zeros((np.size(t), 3))

    def acceleration(self, t: np.ndarray) -> np.ndarray:
        """Return d(velocity)/dt in ``n`` (N, 3), m/s^2."""
        return np.zeros((np.size(t), 3))


@dataclass
class _Segment:
    start: float
    axis: np.ndarray  # (3,) unit vector in the body
    angle: float  # rad, signed
    rate: float  # rad/s, peak (positive)
    ramp: float  # s


def _trapezoid_angle_rate(tau: np.ndarray, seg: _Segment) -> tuple[np.ndarray, np.ndarray]:
    """Angle and rate of a trapezoidal-rate slew at local times ``tau`` (0 = slew start).

    The rate rises linearly to ``seg.rate`` in ``seg.ramp`` s, stays, and falls linearly so
    that the slew turns by ``seg.angle``.
    """
    total = abs(seg.angle)
    w, a = seg.rate, seg.ramp
    cruise = total / w - a  # time at full rate
    if cruise < 0:  # never reaches full rate: symmetric triangle
        w = np.sqrt(total * w / a)
        a = total / w
        cruise = 0.0
    acc = w / a
    t1, t2, t3 = a, a + cruise, 2 * a + cruise
    tau = np.clip(tau, 0.0, t3)
    ang = np.where(
        tau < t1,
        0.5 * acc * tau**2,
        np.where(
            tau < t2,
            0.5 * acc * t1**2 + w * (tau - t1),
            total - 0.5 * acc * (t3 - tau) ** 2,
        ),
    )
    rate = np.where(tau < t1, acc * tau, np.where(tau < t2, w, acc * (t3 - tau)))
    sign = np.sign(seg.angle)
    return sign * ang, sign * rate


@dataclass
class StepRotations(Motion):
    """Step rotations about body axes (Tan et al. Table 2), repeated.

    Each step starts with a trapezoidal slew about a body axis and then holds until the next
    step, ``step_s`` later.  Slew corners fall on multiples of ``grid`` so that gyro sample
    intervals never straddle a rate kink.
    """

    initial: np.ndarray  # R_n_b at t = 0 (3, 3)
    steps: list[tuple[str, float]]  # (axis name, angle rad)
    step_s: float = 60.0
    slew_rate: float = np.deg2rad(5.0)
    ramp_s: float = 1.0
    duration: float = 7200.0
    _segments: list[_Segment] = field(default_factory=list, init=False)
    _start_attitudes: np.ndarray = field(default=None, init=False)

    def __post_init__(self) -> None:
        n = int(np.ceil(self.duration / self.step_s)) + 1
        R = np.asarray(self.initial, dtype=float)
        starts = []
        for k in range(n):
            axis_name, angle = self.steps[k % len(self.steps)]
            axis = np.zeros(3)
            axis[_AXES[axis_name]] = 1.0
            seg = _Segment(k * self.step_s, axis, angle, self.slew_rate, self.ramp_s)
            self._segments.append(seg)
            starts.append(R)
            R = R @ so3_exp(axis * angle)
        self._start_attitudes = np.array(starts)

    def _index(self, t: np.ndarray) -> np.ndarray:
        return np.clip((np.asarray(t) // self.step_s).astype(int), 0, len(self._segments) - 1)

    def _angle_rate(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = np.atleast_1d(np.asarray(t, dtype=float))
        idx = self._index(t)
        ang = np.empty_like(t)
        rate = np.empty_like(t)
        for k in np.unique(idx):
            sel = idx == k
            seg = self._segments[k]
            ang[sel], rate[sel] = _trapezoid_angle_rate(t[sel] - seg.start, seg)
        axes = np.array([self._segments[k].axis for k in idx])
        return idx, axes * ang[:, None], axes * rate[:, None]

    def attitude(self, t: np.ndarray) -> np.ndarray:  # noqa: D102
        idx, rotvec, _ = self._angle_rate(t)
        return self._start_attitudes[idx] @ so3_exp(rotvec)

    def rate(self, t: np.ndarray) -> np.ndarray:  # noqa: D102
        # Rotation about a body-fixed axis: omega_nb_b = axis * d(angle)/dt.
        return self._angle_rate(t)[2]


@dataclass
class Sway(Motion):
    """Ship sway of Zhang et al. eqs. 18-19 about a sequence of base orientations.

    Euler angles (deg) ``pitch = 3 cos(2 pi t / 10 + pi/3)``, ``roll = 4 cos(2 pi t/8 + pi/4)``,
    ``yaw = 2 cos(2 pi t / 6 + pi/5)`` (the paper's phi, theta, gamma), applied as
    ``R_n_b = R_base · Rz(yaw) · Rx(pitch) · Ry(roll)`` (the 3-1-2 sequence of Chinese SINS
    texts).  Linear velocity in ``n`` per eq. 19.  The base orientation changes between
    holds with a trapezoidal slew about the level-frame vertical / body axes.
    """

    bases: list[np.ndarray]  # R_n_base for each hold (3, 3)
    hold_s: float = 120.0
    transition_s: float = 13.0
    duration: float = 386.0
    amplitude_deg: tuple[float, float, float] = (3.0, 4.0, 2.0)  # pitch, roll, yaw
    period_s: tuple[float, float, float] = (10.0, 8.0, 6.0)
    phase: tuple[float, float, float] = (np.pi / 3, np.pi / 4, np.pi / 5)
    velocity_amplitude: tuple[float, float, float] = (0.5, 1.0, 1.5)
    velocity_period_s: tuple[float, float, float] = (6.0, 7.0, 8.0)
    velocity_phase: tuple[float, float, float] = (np.pi / 8, np.pi / 7, np.pi / 6)

    def _base(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Base attitude and its rate (in the base frame) at ``t``.

        Between holds, the base turns from one orientation to the next about the fixed axis
        of their relative rotation with a smooth (cosine) profile.
        """
        t = np.atleast_1d(np.asarray(t, dtype=float))
        cycle = self.hold_s + self.transition_s
        k = np.clip((t // cycle).astype(int), 0, len(self.bases) - 1)
        tau = t - k * cycle
        R = np.empty((t.size, 3, 3))
        w = np.zeros((t.size, 3))
        for i in np.unique(k):
            sel = k == i
            Rb = self.bases[i]
            if i + 1 < len(self.bases):
                rel = Rotation.from_matrix(Rb.T @ self.bases[i + 1]).as_rotvec()
            else:
                rel = np.zeros(3)
            s = np.clip((tau[sel] - self.hold_s) / self.transition_s, 0.0, 1.0)
            frac = 0.5 - 0.5 * np.cos(np.pi * s)
            dfrac = 0.5 * np.pi * np.sin(np.pi * s) / self.transition_s
            R[sel] = Rb @ so3_exp(rel[None, :] * frac[:, None])
            w[sel] = rel[None, :] * dfrac[:, None]
        return R, w

    def _euler(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = np.atleast_1d(np.asarray(t, dtype=float))
        amp = np.deg2rad(np.array(self.amplitude_deg))
        om = 2 * np.pi / np.array(self.period_s)
        ph = np.array(self.phase)
        arg = om[None, :] * t[:, None] + ph[None, :]
        return amp * np.cos(arg), -amp * om * np.sin(arg)  # (pitch, roll, yaw), rates

    def attitude(self, t: np.ndarray) -> np.ndarray:  # noqa: D102
        Rb, _ = self._base(t)
        e, _ = self._euler(t)
        pitch, roll, yaw = e[:, 0], e[:, 1], e[:, 2]
        return Rb @ _rz(yaw) @ _rx(pitch) @ _ry(roll)

    def rate(self, t: np.ndarray) -> np.ndarray:  # noqa: D102
        _, wb = self._base(t)
        e, de = self._euler(t)
        pitch, roll, yaw = e[:, 0], e[:, 1], e[:, 2]
        Ry_T = np.swapaxes(_ry(roll), 1, 2)
        Rx_T = np.swapaxes(_rx(pitch), 1, 2)
        Rsway_T = Ry_T @ Rx_T @ np.swapaxes(_rz(yaw), 1, 2)
        z = np.zeros_like(yaw)
        w = (
            np.einsum("nij,nj->ni", Ry_T @ Rx_T, np.stack([z, z, de[:, 2]], 1))
            + np.einsum("nij,nj->ni", Ry_T, np.stack([de[:, 0], z, z], 1))
            + np.stack([z, de[:, 1], z], 1)
        )
        # base rotation rate (in the base frame) seen from the body
        return w + np.einsum("nij,nj->ni", Rsway_T, wb)

    def _lin(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = np.atleast_1d(np.asarray(t, dtype=float))
        a = np.array(self.velocity_amplitude)
        om = 2 * np.pi / np.array(self.velocity_period_s)
        ph = np.array(self.velocity_phase)
        arg = om[None, :] * t[:, None] + ph[None, :]
        vel = a * np.cos(arg)
        pos = a / om * (np.sin(arg) - np.sin(ph))
        acc = -a * om * np.sin(arg)
        return pos, vel, acc

    def position(self, t: np.ndarray) -> np.ndarray:  # noqa: D102
        return self._lin(t)[0]

    def velocity(self, t: np.ndarray) -> np.ndarray:  # noqa: D102
        return self._lin(t)[1]

    def acceleration(self, t: np.ndarray) -> np.ndarray:  # noqa: D102
        return self._lin(t)[2]


@dataclass
class ConstantRateSweep(Motion):
    """Constant-rate sweep about a fixed body axis (Liu et al.: 0.5 deg/s)."""

    initial: np.ndarray
    axis: np.ndarray
    rate_rad_s: float = np.deg2rad(0.5)
    duration: float = 60.0

    def attitude(self, t: np.ndarray) -> np.ndarray:  # noqa: D102
        t = np.atleast_1d(np.asarray(t, dtype=float))
        ax = np.asarray(self.axis, dtype=float) / np.linalg.norm(self.axis)
        return self.initial @ so3_exp(ax[None, :] * (self.rate_rad_s * t)[:, None])

    def rate(self, t: np.ndarray) -> np.ndarray:  # noqa: D102
        t = np.atleast_1d(np.asarray(t, dtype=float))
        ax = np.asarray(self.axis, dtype=float) / np.linalg.norm(self.axis)
        return np.tile(ax * self.rate_rad_s, (t.size, 1))


def _rx(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    rows = [np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)]
    return np.stack(rows, -2)


def _ry(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    rows = [np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)]
    return np.stack(rows, -2)


def _rz(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    rows = [np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)]
    return np.stack(rows, -2)
