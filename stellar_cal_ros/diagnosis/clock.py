"""A frame clock that steps or drifts against the IMU: the time offset × time test.

The library's time_offset is one constant ``Δt``: the tracker's stamps late or early by a
fixed time.  A clock that steps (a resynchronisation, a driver restart) or drifts (two
free-running oscillators) against the IMU has no library name.  A model with the constant
reads the window's mean of the change (unseen case ``dt_step``, a 4-ms step at 75 % of the
run: −1.33 ms ± 0.0067, the ± that of a constant) and leaves the rest; a model without it
may lose lock (``sky_clock_drift``, 0 → 30 ms).  The remainder's sign follows each star's
motion, so no time line sees it, and the stamp-noise test (:func:`~stellar_cal_ros.
diagnosis.stats.motion_spread`) reads the filter's catch-up after the step as a noise.

A stamp late by ``δ`` moves every star by its image velocity ``u_i = J_i ω`` (px/s) times
``δ``: the offset's pattern, whose per-frame score ``g_k = Σ uᵀ S⁻¹ ν`` and information
``I_k = Σ uᵀ S⁻¹ u`` :func:`~stellar_cal_ros.diagnosis.stats.frame_offsets` gives (the
innovations, not the within-frame residuals: the pattern is a rotation, the attitude error
the frame's stars share). The test (:func:`clock_change`): the window's moving frames
(:data:`MOVING`) in :data:`SEGMENTS` consecutive parts of equal count, the offset each part
says ``d_s = Σ g / Σ I``, their covariance from the frames' scores about it (the frames the
units, neighbouring frames sharing an error: the Newey–West window of
:func:`~stellar_cal_ros.diagnosis.stats.frame_robust_t`, across the parts' borders too; and
:data:`FLOOR_S` for the filter's error along a slew, which lasts longer than that window),
and the Wald χ² of their equality with ``SEGMENTS − 1`` dof. The parts' offsets are
fitted jointly with a mount flexure's turn and the filter's catch-up on it (:data:`GRAVITY`,
one coefficient each for the run): a flexure turns the tracker as the motion turns gravity,
along the motion, and alone the parts' offsets read it as a changing clock (psce 200 s,
40″/g: χ² 142 / 5 dof; with the gravity columns 10.4, p 0.064 unadjusted, no line). A constant
offset, in the model or not, passes it where the filter leaves it alike in every part; a
stepped or drifting clock fails it. Read on the round's residuals whatever the model holds;
it joins the 'unexplained' family (Bonferroni over its tests) and is ranked with the others
by its p (not forced first: a gyro scale factor that differs between the motions reads
alike, unseen case ``gsf_asym``).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from stellar_cal_ros.core import distributions as dist
from stellar_cal_ros.core.units import ARCSEC
from stellar_cal_ros.diagnosis import stats

#: consecutive parts of the window whose offsets are compared (equal frame counts)
SEGMENTS = 6
#: the frames tested move at least this share of the window's 95th percentile image speed
MOVING = 0.1
#: the 'unexplained' line's regressor begins with this (its parts' offsets follow)
CLOCK = "the frames' time offset to the IMU changes over the run"
#: the offset's spread a constant leaves between the parts (s, added in quadrature to each
#: part's σ): the filter's along-motion error, shared by a slew's frames beyond the frames'
#: lag window (clean psce 300 s, the moving frames' parts: −0.066 to 0.061 ms, ~0.03 ms
#: rms, over seeds 21-27; doc/benchmarks.md), and what a knock's catch-up leaves along a
#: slew (unseen case ``knock``: 0.1 ms)
FLOOR_S = 0.05e-3
#: a mount that bends with gravity (a turn ``c (z × g_st)``, ``g_st`` the unit gravity in
#: the tracker frame) and the filter's catch-up when gravity turns (its recent change,
#: :func:`~stellar_cal_ros.diagnosis.context.add_gravity_regressors`): fitted with the
#: parts' offsets, one coefficient each for the run. A flexure turns the tracker as the
#: motion turns gravity, so along the motion: alone, the parts' offsets read it as a
#: clock that changes (psce, 40″/g: χ² 142 / 5 dof; test_discovery_effects)
GRAVITY = (("gravity_x_st", "gravity_y_st"), ("gravity_x_st change", "gravity_y_st change"))
#: the gravity direction must change by at least this much over the frames (unit vector;
#: :data:`~stellar_cal_ros.diagnosis.flexure.MIN_GRAVITY_CHANGE`'s value) for its columns
MIN_GRAVITY_CHANGE = 0.01
#: the line's component (:func:`~stellar_cal_ros.diagnosis.printing.unexplained_phrase`)
COMPONENT = "time offset"


@dataclasses.dataclass
class ClockChange:
    """The parts' offsets and the test of their equality (:func:`clock_change`)."""

    t0: list[float]  #: each part's first frame time (s from the run's first frame)
    t1: list[float]  #: each part's last frame time
    dt: list[float]  #: each part's offset (s, the sign of time_offset's dt: remainder)
    sigma: list[float]  #: its standard deviation from the frames' scores (s, no floor)
    chi2: float  #: Wald statistic of their equality
    dof: int  #: its degrees of freedom (parts − 1)
    p_value: float  #: unadjusted
    size_px: float  #: the change's size: the spans' offsets' range × the image speed
    speed: float  #: 95th percentile of the stars' image speed (px/s)

    def as_json(self) -> dict:
        """The summary's entry (``diagnosis.json`` ``clock_change``)."""
        return dataclasses.asdict(self)

    def spans(self) -> list[tuple[float, float, float]]:
        """``(t0, t1, dt)`` of the runs of parts one offset fits, for the line.

        The parts joined where neighbours agree (their difference within 3σ, the pooled
        offset); a step leaves two runs, a drift its parts.
        """
        out: list[list[float]] = []
        for a, b, d, s in zip(self.t0, self.t1, self.dt, self.sigma, strict=True):
            w = 1.0 / (s**2 + FLOOR_S**2)
            if out:
                p = out[-1]
                if abs(d - p[2]) <= 3.0 * math.sqrt(1.0 / w + 1.0 / p[3]):
                    p[2] = (p[2] * p[3] + d * w) / (p[3] + w)
                    p[1], p[3] = b, p[3] + w
                    continue
            out.append([a, b, d, w])
        return [(a, b, d) for a, b, d, _ in out]

    def regressor(self) -> str:
        """The line's regressor: the offsets and their spans, in ms and s."""
        parts = ", ".join(f"{d * 1e3:.3g} ms over {a:.0f}-{b:.0f} s"
                          for a, b, d in self.spans())
        return (f"{CLOCK}: dt {parts} (outside the library: its time_offset is constant; "
                f"{self.chi2:.0f} chi2 / {self.dof} dof over {len(self.dt)} parts of the "
                "moving frames; a gyro scale error that differs between the motions reads "
                "alike)")

    def finding(self) -> stats.RegressorFinding:
        """The 'unexplained' test (unadjusted p; its statistic the one-sided p's normal score)."""
        return stats.p_finding(self.regressor(), COMPONENT, self.p_value, self.size_px,
                               detail={"clock_change": self.as_json()})


def clock_change(res: stats.Table, mask: np.ndarray, focal: tuple[float, float],
                 centre: tuple[float, float], R_imu_st: np.ndarray | None,
                 parts: int = SEGMENTS) -> ClockChange | None:
    """The time offset × time test on ``mask``'s accepted stars (module docstring).

    ``None`` without the installation or the rate columns, or with fewer than 10 frames
    with motion a part.
    """
    found = stats.accepted_offsets(res, mask, focal, centre, R_imu_st)
    if found is None:
        return None
    sub, got = found
    frames, g, info, _, _, speed = got
    # a frame at rest says an offset only through its tiny rate, where any attitude error
    # the model leaves reads as seconds (unseen case ``knock``: 23-34 ms in the dwells
    # after the jump)
    use = stats.moving_frames(sub, frames, info, MOVING)
    if use.sum() < 3 * parts:
        return None
    frames, g, info = frames[use], g[use], info[use]
    t = stats.frame_times(sub, frames) - float(np.min(res["t"]))
    seg = np.zeros(len(frames), dtype=int)
    for s, idx in enumerate(np.array_split(np.arange(len(frames)), parts)):
        seg[idx] = s
    # the parts' offsets fitted jointly with a mount flexure's (GRAVITY): per frame its
    # scores h (q) and information with the offset (c, q) and with itself (F, q × q)
    h, cross, F = flexure_products(sub, frames, focal, centre, R_imu_st)
    q = h.shape[1]
    P = parts + q
    H = np.zeros((P, P))
    H[np.arange(parts), np.arange(parts)] = np.bincount(seg, info, minlength=parts)
    for j in range(q):
        H[:parts, parts + j] = H[parts + j, :parts] = np.bincount(seg, cross[:, j],
                                                                  minlength=parts)
    H[parts:, parts:] = F.sum(0)
    S = np.zeros((len(frames), P))  # each frame's scores
    S[np.arange(len(frames)), seg] = g
    S[:, parts:] = h
    try:
        Hi = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return None
    beta = Hi @ S.sum(0)
    # each frame's scores about the fit
    E = S.copy()
    E[np.arange(len(frames)), seg] -= info * beta[seg] + cross @ beta[parts:]
    E[:, parts:] -= cross * beta[seg][:, None] + F @ beta[parts:]
    d = beta[:parts]
    e = E[np.arange(len(frames)), seg]  # the offset's (the lag window's autocorrelation)
    L = min(stats.plugin_bandwidth(e), max(len(e) // (4 * parts), 1))
    omega = E.T @ E
    for lag in range(1, L + 1):
        c = E[lag:].T @ E[:-lag]
        omega += (1.0 - lag / (L + 1.0)) * (c + c.T)
    hac = (Hi @ omega @ Hi)[:parts, :parts]
    # a constant offset's parts differ by the filter's lag along each slew as well
    cov = hac + np.eye(parts) * FLOOR_S**2
    try:
        ci = np.linalg.inv(cov)
    except np.linalg.LinAlgError:
        return None
    one = np.ones(parts)
    mean = float(one @ ci @ d) / float(one @ ci @ one)
    r = d - mean
    chi2 = float(r @ ci @ r)
    dof = parts - 1
    p = float(dist.chi2.sf(chi2, dof))
    t0 = [float(t[seg == s].min()) for s in range(parts)]
    t1 = [float(t[seg == s].max()) for s in range(parts)]
    sig = np.sqrt(np.maximum(np.diag(hac), 0.0))
    # (the innovation is the image velocity × the offset the model lacks: its sign is the
    # opposite of time_offset's dt, t_true = stamp + dt)
    out = ClockChange(t0, t1, [-float(x) for x in d], [float(x) for x in sig], chi2, dof,
                      p, math.nan, float(speed))
    # (the spans', not the parts': a part without a slew says little, at a large σ)
    out.size_px = float(np.ptp([s[2] for s in out.spans()])) * float(speed)
    return out


def flexure_products(sub: stats.Table, frames: np.ndarray, focal: tuple[float, float],
                     centre: tuple[float, float], R_imu_st: np.ndarray | None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per frame of ``frames`` the :data:`GRAVITY` columns' products (``q`` of them).

    ``(h (n, q), c (n, q), F (n, q, q))``: ``Σ xᵀ S⁻¹ ν``, ``Σ xᵀ S⁻¹ u`` (``u`` the image
    velocity of :func:`~stellar_cal_ros.diagnosis.stats.frame_offsets`) and ``Σ xᵀ S⁻¹
    x``, ``x`` each column's image shift (px per arcsec of turn); ``q = 0`` without the
    gravity columns or with gravity (nearly) still over the frames.
    """
    n = len(frames)
    none = np.zeros((n, 0)), np.zeros((n, 0)), np.zeros((n, 0, 0))
    if not all(k in sub for pair in GRAVITY for k in pair):
        return none
    got = stats.motion_columns(sub, focal, centre, R_imu_st)
    if got is None:
        return none
    ok, vel, nu, Si = got
    fr = np.asarray(sub["frame"])[ok]
    on = np.isin(fr, frames)
    gx, gy = (np.asarray(sub[k], dtype=float)[ok] for k in GRAVITY[0])
    if not on.any() or max(float(np.ptp(gx[on])), float(np.ptp(gy[on]))) <= MIN_GRAVITY_CHANGE:
        return none
    J = stats.attitude_columns({k: np.asarray(sub[k])[ok] for k in ("x_st", "y_st", "z_st")},
                               *focal) * ARCSEC
    cols = []
    for kx, ky in GRAVITY:
        x, y = (np.asarray(sub[k], dtype=float)[ok] for k in (kx, ky))
        turn = np.stack([-y, x, np.zeros_like(x)], 1)  # z × g
        cols.append(np.einsum("nij,nj->ni", J, turn))
    X = np.stack(cols, 2)[on]  # (stars, 2, q)
    k = np.searchsorted(frames, fr[on])
    Si, vel, nu = Si[on], vel[on], nu[on]
    SX = np.einsum("nij,njq->niq", Si, X)
    q = X.shape[2]
    h = np.stack([np.bincount(k, np.einsum("ni,ni->n", SX[:, :, j], nu), minlength=n)
                  for j in range(q)], 1)
    c = np.stack([np.bincount(k, np.einsum("ni,ni->n", SX[:, :, j], vel), minlength=n)
                  for j in range(q)], 1)
    F = np.zeros((n, q, q))
    for i in range(q):
        for j in range(q):
            F[:, i, j] = np.bincount(k, np.einsum("ni,ni->n", X[:, :, i], SX[:, :, j]),
                                     minlength=n)
    return h, c, F
