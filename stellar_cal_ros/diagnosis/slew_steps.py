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
#: at most this many slews' steps fitted (the window's and the one before it); more: no test
MAX_STEPS = 4
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
    :data:`MIN_SLEWS` slews in the window or more than :data:`MAX_STEPS` to fit, or where
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
    if len(inside) < MIN_SLEWS or len(inside) + len(before) > MAX_STEPS:
        return None
    return before + inside


class SlewSteps(Effect):
    """The installation rotated by ``δ_i`` from each slew's start ``T_i`` on (fitted).

    Not a library effect and never offered (:mod:`~stellar_cal_ros.diagnosis.slew_steps`):
    a rival of a rate-shaped candidate.  :data:`MAX_STEPS` steps of 3 components; the
    times travel in the prior (``effects[STEPS_ID]["t_posix"]``: a list, a step without a
    time never acts), as :class:`~.installation_step.StepNuisance`'s.
    """

    id = STEPS_ID
    stage = Stage.TRACKER
    order = 16
    parameter_names = tuple(f"d{i}{x}" for i in range(MAX_STEPS) for x in "xyz")
    units = ("rad",) * (3 * MAX_STEPS)
    default_sigma = (100.0 * ARCSEC,) * (3 * MAX_STEPS)
    explanation = "a lag at each slew, fitted as a nuisance (not a library effect)"
    T: tuple[float, ...] = ()

    def initial(self, prior):  # noqa: D102
        block = (prior.effects or {}).get(self.id) or {}
        self.T = tuple(float(x) for x in block.get("t_posix", ()))
        return super().initial(prior)

    def store(self, value, sigma, cal):  # noqa: D102
        super().store(value, sigma, cal)
        cal.effects[self.id]["t_posix"] = list(self.T)

    def _on(self, stamp: float) -> np.ndarray:
        on = np.zeros(MAX_STEPS)
        on[:len(self.T)] = [stamp >= T for T in self.T]
        return on

    def tracker_rotation(self, value, ctx):  # noqa: D102
        return self._on(ctx.stamp) @ np.asarray(value, dtype=float).reshape(MAX_STEPS, 3)

    def tracker_rotation_jacobian(self, value, ctx):  # noqa: D102
        return np.kron(self._on(ctx.stamp)[None, :], np.eye(3))


def with_steps(prior, slews: list[dict]):
    """``prior`` with :class:`SlewSteps` at ``slews``' starts (a copy; zero ± 100″)."""
    out = copy.deepcopy(prior)
    out.effects[STEPS_ID] = {"t_posix": [s["t_posix"] for s in slews]}
    return out


def fitted(est: dict[str, list[float]], slews: list[dict]) -> list[dict]:
    """Each slew's fitted step (arcsec, the stars' sign) and its part along the slew's axis.

    ``est``: the nuisance's ``{param: [value, sigma]}`` in a run (rad).
    ``[{"t", "step_arcsec", "sigma_arcsec", "along_arcsec"}]`` (``t`` POSIX s);
    ``along``: the rotation's component about the slew's own axis (a lag: opposite to it).
    """
    out = []
    for i, s in enumerate(slews):
        d = np.array([-est[f"d{i}{x}"][0] / ARCSEC for x in "xyz"])
        out.append({"t": s["t_posix"], "step_arcsec": [float(x) for x in d],
                    "sigma_arcsec": [est[f"d{i}{x}"][1] / ARCSEC for x in "xyz"],
                    "along_arcsec": float(d @ np.asarray(s["axis"]))})
    return out


def lag(steps: list[dict], slews: list[dict]) -> tuple[float, float]:
    """The lag ``λ`` (arcsec) the fitted steps say, and its σ.

    A tracker kept turned by ``λ`` about each slew's axis until the next slew.
    Such a tracker jumps at slew ``i`` by ``λ (a_i − a_{i−1})`` (``a`` the slews' axes,
    tracker frame; :func:`slew_starts`' ``axis_before``): ``λ`` by least squares over the
    steps, each component weighted by its σ (their correlation not kept).  Negative: the
    tracker lags the slew (unseen case ``backlash``: −8″).
    """
    b = np.array([np.subtract(s["axis"], s["axis_before"]) for s in slews])
    d = np.array([x["step_arcsec"] for x in steps])
    w = 1.0 / np.square(np.array([x["sigma_arcsec"] for x in steps]))
    info = float(np.sum(w * b * b))
    if not info > 0:
        return math.nan, math.nan
    return float(np.sum(w * b * d)) / info, 1.0 / math.sqrt(info)


def finding(test: dict) -> stats.RegressorFinding:
    """The steps' 'unexplained' line: the jumps at the slews, read as a lag kept after each.

    ``test``: :func:`~stellar_cal_ros.diagnosis.auto._beside_slews`' (``steps`` from
    :func:`fitted`, ``lag_arcsec`` / ``lag_sigma_arcsec`` from :func:`lag`, the steps' own
    ratio ``steps_statistic`` / ``steps_dof`` / ``steps_p_value``, ``first_t``: the
    table's first time, ``focal_px``).  Its size the lag at the detector's centre.
    """
    steps = test["steps"]
    lam, sig = test["lag_arcsec"], test["lag_sigma_arcsec"]
    times = ", ".join(f"{s['t'] - test['first_t']:.0f}" for s in steps)
    jumps = ", ".join(f"{np.linalg.norm(s['step_arcsec']):.2g}" for s in steps)
    kind = "lags" if lam < 0 else "leads"
    text = (f"the attitude jumps at each slew's start and stays until the next (slews at "
            f"t~{times} s: {jumps}\" each; fitted as steps of the installation, "
            f"{test['steps_statistic']:.0f} chi2 / {test['steps_dof']} dof): the tracker "
            f"{kind} each slew by {abs(lam):.2g} +- {sig:.1g}\" about the slew's axis (a lag "
            "that persists, e.g. a mount's backlash): not a library effect (its installation "
            "is a constant; a gyro scale or a time offset leaves nothing at rest)")
    px = abs(lam) * ARCSEC * float(test["focal_px"])
    return stats.p_finding(text, COMPONENT, test["steps_p_value"], px,
                           detail={"slew_steps": {k: test[k] for k in (
                               "steps", "lag_arcsec", "lag_sigma_arcsec", "steps_statistic",
                               "steps_dof", "steps_p_value")}})
