"""A tracker that jumps at each slew and stays there (a mount's lag): the slews' steps, fitted.

The library's installation is one constant rotation of the tracker against the IMU; a knock
(:mod:`~stellar_cal_ros.diagnosis.installation_step`) turns it once.  A mount with backlash
(unseen case ``backlash``: the tracker lags each slew by 8″ about the slew's axis and stays
there until the next) turns it at every slew, by a rotation that depends on that slew only.
On psce's ±30° steps about the IMU axes a lag kept after each slew is, slew by slew, what a
gyro scale error leaves (8″ / 30° ≈ 74 ppm), and within a slew what a time offset leaves
(8″ / 5 °/s ≈ 0.4 ms): both were added on coord 0e2fd9e (seeds 21, 22), while the
installation step test saw one step at most.

Here the installation is rotated by a free ``δ_i`` (3 components, tracker axes) from the
start of each slew ``i`` on (:class:`SlewSteps`, a nuisance never offered as an effect):
the slews within the evaluation window and the last one before it (:func:`slew_starts`:
frames whose gyro rate exceeds half the frames' 95th percentile, a slew starting half way
between its first such frame and the frame before).  A library effect acts within a slew
as well: a gyro scale error grows with the angle turned through the slew, a time offset is
the rate × the offset and vanishes at rest; steps held from each slew's start take
neither.  A lag that persists takes the steps entirely: a rate-shaped candidate
(:data:`RIVALS`) that explains nothing beside them is refused
(:func:`~stellar_cal_ros.diagnosis.auto._beside_slews`), and the steps' line names the
jumps (:func:`finding`).

The steps are one 3-vector in the filter, their sum so far, whose variance grows by a
step's prior at each slew's start (H297; H289 fitted a 3-vector per slew, at most 4: a
2-h psce bag has 60 slews in its window): the same model, marginalized slew by slew, at
the cost of 6 states whatever the bag's length (3 more keep the sum before the last step,
refined by the next slew).  The lag ``λ`` is fitted to the offsets held over the slews'
intervals, and so is each slew's own ``λ_i`` (a lag that differs from slew to slew is
said so, :func:`lag`).
"""

from __future__ import annotations

import copy
import math

import numpy as np

from stellar_cal_ros.core.units import ARCSEC
from stellar_cal_ros.diagnosis import stats
from stellar_cal_ros.effects.base import Effect, Stage

#: the nuisance's private id (a leading ``_``: never listed by the registry)
STEPS_ID = "_slew_steps"
#: one lag at every slew (:class:`SlewLag`), the steps' special case
LAG_ID = "_slew_lag"
#: each step's prior σ per component (rad): the variance the filter adds at a slew's start
STEP_SIGMA = 100.0 * ARCSEC
#: the steps' sum's σ before the first slew fitted (rad: ~zero, a covariance kept positive)
STILL = 1e-4 * ARCSEC
#: a frame is in a slew where its gyro rate is above this share of the frames' 95th
#: percentile
FAST = 0.5
#: fewer slews in the evaluation window than this: no test (one step is the knock's test)
MIN_SLEWS = 2
#: candidates a lag that persists may stand in for (slew by slew a gyro rate error, within
#: a slew a time offset or a drifting clock: ``backlash`` s21 added clock_drift with its
#: time_offset once time_offset alone was refused)
RIVALS = ("gyro_scale_factor", "gyro_misalignment", "time_offset", "clock_drift")
#: the 'unexplained' line's component
COMPONENT = "slew steps"
#: the remainder a candidate is refused beside (auto's ``beyond_remainder``)
REMAINDER = ("the attitude jumps at the slews' starts", "a lag at each slew")


def slew_starts(res: stats.Table, R_imu_st: np.ndarray | None, fraction: float
                ) -> list[dict] | None:
    """The slews to fit a step at: ``[{"t_posix", "axis", "angle_deg", "axis_before"}]``.

    From the residual table's gyro rate columns (IMU frame, turned into the tracker's by
    ``R_imu_st``): per frame the mean rate of its rows; a frame is in a slew where its
    speed exceeds :data:`FAST` × the frames' 95th percentile.  A slew starts half way
    between its first such frame and the one before; its axis (tracker frame) and angle
    are the frames' rates summed over it × their spacing (``axis_before``: the slew's before
    it, zero for the table's first).  Kept: the slews starting within
    the evaluation window (the last ``fraction`` of the table's time) and the last one
    before it.  ``None`` without the rate columns or the installation, with fewer than
    :data:`MIN_SLEWS` slews in the window, or where
    the platform never rests (fewer than half of the frames out of a slew): ``None``.
    """
    if R_imu_st is None or not all(f"omega_{x}" in res for x in "xyz") or not len(res["t"]):
        return None
    fr, kk = stats.frames_of(np.asarray(res["frame"]))
    w = np.stack([np.asarray(res[f"omega_{x}"], dtype=float) for x in "xyz"], 1)
    ok = stats.finite_rows(w)
    n = np.bincount(kk[ok], minlength=len(fr))
    if not np.all(n > 0):
        return None
    rate = np.stack([np.bincount(kk[ok], w[ok, i], minlength=len(fr)) for i in range(3)],
                    1) / n[:, None] @ np.asarray(R_imu_st, dtype=float)  # tracker frame
    t = stats.frame_times(res, fr)
    speed = np.linalg.norm(rate, axis=1)
    fast = speed > FAST * np.percentile(speed, 95)
    if fast.mean() > 0.5 or not fast.any():
        return None
    edge = np.flatnonzero(np.diff(fast.astype(int)) != 0) + 1
    bounds = np.concatenate([[0], edge, [len(fr)]])
    slews: list[dict] = []
    dt = np.gradient(t)
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        if not fast[a] or a == 0:
            continue
        turned = (rate[a:b] * dt[a:b, None]).sum(0)
        angle = float(np.linalg.norm(turned))
        slews.append({"t_posix": float(0.5 * (t[a - 1] + t[a])),
                      "axis": [float(x) for x in turned / max(angle, 1e-300)],
                      "angle_deg": math.degrees(angle),
                      "axis_before": slews[-1]["axis"] if slews else [0.0, 0.0, 0.0]})
    t0, t1 = float(np.min(res["t"])), float(np.max(res["t"]))
    cut = t0 + (1.0 - fraction) * (t1 - t0)
    inside = [s for s in slews if s["t_posix"] >= cut]
    before = [s for s in slews if s["t_posix"] < cut][-1:]
    if len(inside) < MIN_SLEWS:
        return None
    return before + inside


class SlewSteps(Effect):
    """The installation rotated by ``Σ_{T_i ≤ t} δ_i``: a free step ``δ_i`` from each slew's start.

    Not a library effect and never offered (:mod:`~stellar_cal_ros.diagnosis.slew_steps`):
    a rival of a rate-shaped candidate.  One rotation of 3 components ``d``, the steps' sum
    so far; the filter adds each step's prior variance (:data:`STEP_SIGMA` per component)
    at its slew's start (:attr:`~stellar_cal_ros.effects.base.Effect.steps_at`):
    independent steps, marginalized one after the other.  Three more ``p`` hold ``d``'s
    value before the last step (:attr:`~.effects.base.Effect.keeps_before_step`): the
    offset over the slew before, refined by the next slew's frames, which tell an offset of
    the tracker from an error of the attitude.  6 states however many slews.  Before the
    first slew fitted the sum is zero (σ :data:`STILL`).  The times travel in the prior
    (``effects[STEPS_ID]["t_posix"]``: a list), as
    :class:`~.installation_step.StepNuisance`'s; the offsets over each slew's interval are
    stored (:meth:`store`: ``offsets`` / ``offsets_sigma``, rad, the installation
    rotation's sign): ``p`` as the filter shows it at the step after next (a slew's offset
    with the frames to the end of the next slew's interval), the last two the final ``p``
    and ``d``.
    """

    id = STEPS_ID
    stage = Stage.TRACKER
    order = 16
    parameter_names = ("dx", "dy", "dz", "px", "py", "pz")
    units = ("rad",) * 6
    default_sigma = (STEP_SIGMA,) * 6
    explanation = "a lag at each slew, fitted as a nuisance (not a library effect)"
    keeps_before_step = True

    def initial(self, prior):  # noqa: D102
        block = (prior.effects or {}).get(self.id) or {}
        self.steps_at = tuple(float(x) for x in block.get("t_posix", ()))
        self.held: dict[int, tuple[list[float], list[float]]] = {}
        return np.zeros(6), np.full(6, STILL)

    def stepped(self, k, value, sigma):  # noqa: D102
        if k >= 2:  # p: the offset over slew k − 2's interval, through slew k − 1's
            self.held[k - 2] = ([float(x) for x in value[3:]], [float(x) for x in sigma[3:]])

    def store(self, value, sigma, cal):  # noqa: D102
        super().store(value, sigma, cal)
        block = cal.effects[self.id]
        n = len(self.steps_at)
        block["t_posix"] = list(self.steps_at)
        held = dict(getattr(self, "held", {}))
        if n and len(held) == max(n - 2, 0):  # (else a run that ended before the last slew)
            if n >= 2:
                held[n - 2] = ([float(x) for x in value[3:]], [float(x) for x in sigma[3:]])
            held[n - 1] = ([float(x) for x in value[:3]], [float(x) for x in sigma[:3]])
        block["offsets"] = [held[k][0] if k in held else None for k in range(n)]
        block["offsets_sigma"] = [held[k][1] if k in held else None for k in range(n)]

    def tracker_rotation(self, value, ctx):  # noqa: D102
        return np.asarray(value[:3], dtype=float)

    def tracker_rotation_jacobian(self, value, ctx):  # noqa: D102
        return np.hstack([np.eye(3), np.zeros((3, 3))])


def with_steps(prior, slews: list[dict]):
    """``prior`` with :class:`SlewSteps` at ``slews``' starts (a copy; each step 0 ± 100″)."""
    out = copy.deepcopy(prior)
    out.effects[STEPS_ID] = {"t_posix": [s["t_posix"] for s in slews]}
    return out


def fitted(block: dict, slews: list[dict]) -> list[dict] | None:
    """Each slew's fitted offset and step (arcsec, the stars' sign) and the step along its axis.

    ``block``: the nuisance's stored calibration block in a run (:meth:`SlewSteps.store`).
    ``[{"t", "offset_arcsec", "offset_sigma_arcsec", "step_arcsec", "sigma_arcsec",
    "along_arcsec"}]`` (``t`` POSIX s): the offset held over the slew's interval (the
    filter's estimate at its end: the frames up to then), the step its change from the
    interval before (σ: the two offsets' σ in quadrature, their correlation not kept);
    ``along``: the step's component about the slew's own axis (a lag: opposite to it).
    None where a slew's offset is missing (a run that ended early).
    """
    off, sig = block.get("offsets") or [], block.get("offsets_sigma") or []
    if len(off) != len(slews) or any(x is None for x in off):
        return None
    out = []
    before, s_before = np.zeros(3), np.zeros(3)
    for s, o, so in zip(slews, off, sig, strict=True):
        d = -np.asarray(o, dtype=float) / ARCSEC
        sd = np.asarray(so, dtype=float) / ARCSEC
        step = d - before
        out.append({"t": s["t_posix"], "offset_arcsec": [float(x) for x in d],
                    "offset_sigma_arcsec": [float(x) for x in sd],
                    "step_arcsec": [float(x) for x in step],
                    "sigma_arcsec": [float(x) for x in np.hypot(sd, s_before)],
                    "along_arcsec": float(step @ np.asarray(s["axis"]))})
        before, s_before = d, sd
    return out


def lag(steps: list[dict], slews: list[dict]) -> dict:
    """The lag ``λ`` (arcsec) the fitted offsets say, its σ, and each slew's own.

    A tracker kept turned by ``λ_i`` about slew ``i``'s axis ``a_i`` until the next slew
    sits, over slew ``i``'s interval, at ``λ_i a_i − λ_b a_b`` from the installation fitted
    before the first slew (``a_b``, ``λ_b``: the slew before it, :func:`slew_starts`'
    ``axis_before``).  One ``λ`` for all: weighted least squares of the offsets on
    ``a_i − a_b`` (each component by its σ, their correlation not kept); each its own:
    ``λ_b, λ_0 … λ_{n−1}`` together.  Negative: the tracker lags the slew (unseen case
    ``backlash``: −8″).  ``{"lag_arcsec", "lag_sigma_arcsec", "lags_arcsec",
    "lags_sigma_arcsec"}`` (the per-slew lags, the first the slew before the first fitted;
    their σ the offsets' formal ones: the filter's catch-up on each jump scatters them more,
    ~1–2″ at 8″ on ``backlash``; whether they differ is the filter's test,
    :class:`SlewLag`).
    """
    n = len(slews)
    a = np.array([s["axis"] for s in slews], dtype=float)
    ab = np.asarray(slews[0]["axis_before"], dtype=float)
    d = np.array([x["offset_arcsec"] for x in steps], dtype=float).reshape(-1)
    w = 1.0 / np.square(np.array([x["offset_sigma_arcsec"] for x in steps],
                                 dtype=float)).reshape(-1)
    out = {"lag_arcsec": math.nan, "lag_sigma_arcsec": math.nan, "lags_arcsec": [],
           "lags_sigma_arcsec": []}
    if not np.all(np.isfinite(w)):
        return out
    b = (a - ab).reshape(-1)
    info = float(np.sum(w * b * b))
    if not info > 0:
        return out
    out.update(lag_arcsec=float(np.sum(w * b * d)) / info, lag_sigma_arcsec=1 / math.sqrt(info))
    # each slew its own: columns λ_b (−a_b in every interval), λ_i (a_i in interval i)
    A = np.zeros((3 * n, n + 1))
    A[:, 0] = -np.tile(ab, n)
    for i in range(n):
        A[3 * i:3 * i + 3, i + 1] = a[i]
    N = (A * w[:, None]).T @ A
    if np.linalg.matrix_rank(N) < n + 1:
        return out
    cov = np.linalg.inv(N)
    return dict(out, lags_arcsec=[float(x) for x in cov @ (A.T @ (w * d))],
                lags_sigma_arcsec=[float(math.sqrt(x)) for x in np.diag(cov)])


class SlewLag(Effect):
    """The installation rotated by ``−λ (a_i − a_b)`` over slew ``i``'s interval: one lag.

    The steps' special case a tracker kept turned by the same ``λ`` about each slew's
    axis makes (:func:`lag`); its run against the steps' (:class:`SlewSteps`, nested: one
    parameter for 3 per slew) tests whether the lag differs from slew to slew, the filter
    weighing every frame, and fits ``λ`` (rad, the stars' sign: negative a lag).  The
    slews' times and ``a_i − a_b`` (tracker frame) travel in the prior
    (``effects[LAG_ID]``: ``t_posix``, ``axes``; :func:`with_lag`); zero before the first.
    Not a library effect, never offered.
    """

    id = LAG_ID
    stage = Stage.TRACKER
    order = 16
    parameter_names = ("lag",)
    units = ("rad",)
    default_sigma = (STEP_SIGMA,)
    explanation = "one lag at each slew, fitted as a nuisance (not a library effect)"

    def initial(self, prior):  # noqa: D102
        block = (prior.effects or {}).get(self.id) or {}
        self.T = np.asarray(block.get("t_posix", ()), dtype=float)
        self.axes = np.asarray(block.get("axes", ()), dtype=float).reshape(-1, 3)
        return np.zeros(1), np.array([STEP_SIGMA])

    def store(self, value, sigma, cal):  # noqa: D102
        super().store(value, sigma, cal)
        cal.effects[self.id].update(t_posix=self.T.tolist(), axes=self.axes.tolist())

    def _axis(self, stamp: float) -> np.ndarray:
        i = int(np.searchsorted(self.T, stamp, side="right")) - 1
        return self.axes[i] if i >= 0 else np.zeros(3)

    def tracker_rotation(self, value, ctx):  # noqa: D102
        return -float(value[0]) * self._axis(ctx.stamp)

    def tracker_rotation_jacobian(self, value, ctx):  # noqa: D102
        return -self._axis(ctx.stamp)[:, None]


def with_lag(prior, slews: list[dict]):
    """``prior`` with :class:`SlewLag` at ``slews`` (a copy; λ 0 ± 100″)."""
    out = copy.deepcopy(prior)
    ab = np.asarray(slews[0]["axis_before"], dtype=float)
    out.effects[LAG_ID] = {"t_posix": [s["t_posix"] for s in slews],
                           "axes": [list(np.asarray(s["axis"], dtype=float) - ab)
                                    for s in slews]}
    return out


def _times(steps: list[dict], first_t: float) -> str:
    """The slews' times (s from the table's first), the first and last 3 of a long list."""
    t = [f"{s['t'] - first_t:.0f}" for s in steps]
    return ", ".join(t) if len(t) <= 6 else ", ".join(t[:3] + ["..."] + t[-3:])


def _sizes(steps: list[dict]) -> str:
    """The jumps' sizes (arcsec): each of up to 4, else their range."""
    j = [float(np.linalg.norm(s["step_arcsec"])) for s in steps]
    if len(j) <= 4:
        return ", ".join(f"{x:.2g}" for x in j) + '" each'
    return f'{min(j):.2g} to {max(j):.2g}" (median {np.median(j):.2g}")'


def finding(test: dict) -> stats.RegressorFinding:
    """The steps' 'unexplained' line: the jumps at the slews, read as a lag kept after each.

    ``test``: :func:`~stellar_cal_ros.diagnosis.auto._beside_slews`' (``steps`` from
    :func:`fitted`, :func:`lag`'s keys and the one lag's (:class:`SlewLag`), the steps' own
    ratio ``steps_statistic`` / ``steps_dof`` / ``steps_p_value``, ``first_t``: the
    table's first time, ``focal_px``).  Its size the lag at the detector's centre.  Whether
    the lag differs from slew to slew is not said: the steps' run against the one lag's
    (``lags_p_value``, in the detail) is too conservative to tell (unseen case
    ``backlash_vary``, 4″ and 12″ in turn: −150 against −320 for one 8″ lag, p 1 both).
    """
    steps = test["steps"]
    lam, sig = test["lag_arcsec"], test["lag_sigma_arcsec"]
    kind = "lags" if lam < 0 else "leads"
    text = (f"the attitude jumps at each slew's start and stays until the next ({len(steps)} "
            f"slews at t~{_times(steps, test['first_t'])} s: {_sizes(steps)}; fitted as "
            f"steps of the installation, {test['steps_statistic']:.0f} chi2 / "
            f"{test['steps_dof']} dof): the tracker {kind} each slew by {abs(lam):.2g} +- "
            f"{sig:.1g}\" about the slew's axis")
    text += (" (a lag that persists, e.g. a mount's backlash): not a library effect (its "
             "installation is a constant; a gyro scale or a time offset leaves nothing at "
             "rest)")
    px = abs(lam) * ARCSEC * float(test["focal_px"])
    return stats.p_finding(text, COMPONENT, test["steps_p_value"], px,
                           detail={"slew_steps": {k: test[k] for k in (
                               "steps", "lag_arcsec", "lag_sigma_arcsec", "lags_arcsec",
                               "lags_sigma_arcsec", "lags_statistic", "lags_dof",
                               "lags_p_value", "steps_statistic", "steps_dof",
                               "steps_p_value")}})
