"""A tracker installation that steps once (a knock on the mount): the attitude step test.

The library's installation is one constant rotation of the tracker against the IMU.  A
mount knocked once (unseen case ``knock``: 20″, 0.385 px along 30°, at 75 % of the run)
turns every star of every later frame by the same small rotation.  The filter takes it into
its attitude within ~15 s, so its innovations carry a pulse that decays, not a lasting
offset: no time line sees it (a linear trend through a 15-s transient, t −1.7 / −2.1), and
the noise verdict reads it as attitude motion the gyro's noise does not explain.

Per frame, the rotation its stars say against the attitude the model predicts (the
innovations' fit by :func:`~stellar_cal_ros.diagnosis.stats.attitude_columns`, 3
components in arcsec, :func:`~stellar_cal_ros.diagnosis.stats.frame_attitudes`).  At each
candidate frame ``k`` a step is fitted to the :data:`WINDOW` frames either side with a
straight line beside it (``a_j = α + β j + δ [j ≥ k]``, per component): the filter's
catch-up after a slew, or any error that changes smoothly, is the line; a step is
``δ``.  Only frames at rest are tested (:func:`~stellar_cal_ros.diagnosis.stats.
moving_frames`' complement, :data:`MARGIN` frames beyond the window at rest as well): a
stamp offset, a gyro scale error and the filter's lag turn the attitude along the motion,
and where the image moves they change abruptly with the rate (unseen cases ``dt_step``,
``gsf_asym``).  Each ``δ_k`` is whitened by its covariance from the frames' information
(``Σ c_j² I_j⁻¹``, ``c`` the fit's contrast), the whitened steps' common covariance is
read robustly from the frames themselves (trimmed at χ²₃ :data:`TRIM`: it takes the
filter's shared attitude error and a misstated noise), and the statistic is the largest
``δ̂ᵀ Σ⁻¹ δ̂`` over the candidates, its p the χ²₃ tail × their number (Bonferroni: the
candidates overlap, so it is conservative).  A noise in the frames' stamps turns each frame
by its rate × its stamp's error, an attitude noise that one common covariance cannot
whiten (the fastest frames' steps would read it as a knock): on a platform that never
rests, where the frames tested show one, its size is in each frame's covariance
(:func:`stamp_spread`).  It joins the 'unexplained' family (Bonferroni with its other
tests); a line that fires goes first: the lines a knock makes (the catch-up's time
structure) follow it.  A step within
:data:`WINDOW` + :data:`MARGIN` frames of motion is not tested where the platform rests.

A platform that never rests (the swaying base: fewer than :data:`MIN_CANDIDATES` frames at
rest) is tested over all its frames (``at_rest`` false): its motion is smooth, and what a
stamp offset, a gyro scale or the filter's lag make of it changes smoothly too, which the
line takes (the step's contrast is blind to a constant, a slope and any part even about
the step; on the 300-s swaying bag seed 21 χ²₃ 14.7 clean, 12.2 with mount flexure, 568
with ``knock``'s step, unseen case ``sway_knock``).  Where the platform rests and slews
(psce) the moving frames stay untested: the rate steps at a slew's ends, and so does a
stamp offset's attitude error (``dt_step`` χ²₃ 6160, a missing 0.5 ms time offset 123 at
the slews' ends; unseen case ``knock_slew`` is not found).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from stellar_cal_ros.core import distributions as dist
from stellar_cal_ros.core.units import ARCSEC
from stellar_cal_ros.diagnosis import stats
from stellar_cal_ros.effects.base import Effect, Stage

#: frames either side of a candidate step in its fit (6: 3 s at psce's 2 Hz frames)
WINDOW = 6
#: frames beyond the fit's window that must be at rest as well (the filter's catch-up
#: right after a slew bends faster than the fit's straight line: ``dt_step``, 2 frames:
#: χ²₃ 59 at 2.5 s after the slew, p 2.5e-10 over the frames)
MARGIN = 4
#: a frame at rest moves slower than this share of the frames' 95th percentile image speed
#: (:data:`~stellar_cal_ros.diagnosis.clock.MOVING`'s value)
REST = 0.1
#: the whitened steps beyond this χ²₃ tail are left out of their covariance (iterated)
TRIM = 1e-3
#: fewer candidate frames than this: no test
MIN_CANDIDATES = 20
#: a noise in the frames' stamps (:func:`~stellar_cal_ros.diagnosis.stats.stamp_noise` on
#: the frames tested, one-sided p below this) is in each frame's expected spread
STAMP_ALPHA = 0.01
#: the 'unexplained' line's component (:func:`~stellar_cal_ros.diagnosis.printing.
#: unexplained_phrase`)
COMPONENT = "installation step"


@dataclasses.dataclass
class InstallationStep:
    """The largest attitude step at rest and its test (:func:`installation_step`)."""

    t: float  #: the first frame after the step (s from the run's first frame)
    t_before: float  #: the last frame before it
    step_arcsec: list[float]  #: the rotation (tracker x, y, z; arcsec; the stars' sign)
    sigma_arcsec: list[float]  #: its standard deviation per component
    shift_px: float  #: the stars' shift at the detector's centre (px)
    sigma_px: float  #: its standard deviation
    angle_deg: float  #: the shift's direction in the image (from +u toward +v)
    chi2: float  #: the largest whitened step's χ² (3 dof)
    candidates: int  #: the frames tested
    p_value: float  #: unadjusted: the χ²₃ tail × ``candidates``
    at_rest: bool = True  #: the frames tested are those at rest (false: all, never at rest)
    #: the stamps' noise (ms rms) in each frame's spread (:func:`stamp_spread`), else None
    stamp_noise_ms: float | None = None

    def as_json(self) -> dict:
        """The summary's entry (``diagnosis.json`` ``installation_step``).

        ``stamp_noise_ms`` only where a stamp noise was in the frames' spread.
        """
        out = dataclasses.asdict(self)
        if out["stamp_noise_ms"] is None:
            del out["stamp_noise_ms"]
        return out

    def regressor(self, where: str = "", sized: str = "") -> str:
        """The line's text: when, how much, about which axis.

        ``where``: the frames tested; ``sized``: where the size comes from when not from the
        test (:meth:`fitted`).  The test's own size over frames that move (``where``, or a
        platform that never rests) is said for what it is (:data:`JUMP`).
        """
        if not sized and (where or not self.at_rest):
            sized = JUMP
        stamped = "" if self.stamp_noise_ms is None else \
            f"; each frame's spread with the stamps' noise, {self.stamp_noise_ms:.2g} ms rms"
        d = np.asarray(self.step_arcsec)
        size = float(np.linalg.norm(d))
        axis = ", ".join(f"{x:.2f}" for x in d / max(size, 1e-300))
        return (f"the tracker's installation steps at t~{self.t:.1f} s by {size:.3g}\" "
                f"({sized + '; ' if sized else ''}about the tracker's axis ({axis}); "
                f"x {d[0]:.3g}, y {d[1]:.3g}, z {d[2]:.3g}"
                f" +- {max(self.sigma_arcsec[:2]):.2g} / {self.sigma_arcsec[2]:.2g}\"): the "
                f"stars jump {self.shift_px:.3g} +- {self.sigma_px:.2g} px along "
                f"{self.angle_deg:.0f} deg at the detector's centre and the filter follows "
                f"(outside the library: its installation is a constant; {self.chi2:.0f} chi2"
                f" / 3 dof, the largest of {self.candidates} frames "
                f"{where or ('at rest' if self.at_rest else 'of a platform that never rests')}"
                f"{stamped})")

    def finding(self, where: str = "", sized: str = "") -> stats.RegressorFinding:
        """The 'unexplained' test (unadjusted p; its statistic the one-sided p's normal score)."""
        return stats.p_finding(self.regressor(where, sized), COMPONENT, self.p_value,
                               self.shift_px, detail={"installation_step": self.as_json()})

    def fitted(self, step_arcsec, sigma_arcsec, focal: tuple[float, float]
               ) -> InstallationStep:
        """The test with a run's fitted rotation as its size (arcsec, the stars' sign).

        The test's own step is the jump of the frames' attitudes at one frame; where the
        frames move (:data:`MOVING`, :data:`BEFORE`) it holds the filter's answer to the
        motion there as well (unseen case ``knock_gsf_run20`` seed 21, the knock's first
        frame 59.5 s where a slew starts: the largest step at 60.0 s, x 43.7, y 4.2, z 79.5
        ± 0.77 / 5.9″, against the true −10, 17.3, 0).  σ per component (their correlation
        not kept).
        """
        shift, sigma, angle = _at_centre(np.asarray(step_arcsec, dtype=float),
                                         np.diag(np.square(sigma_arcsec)), focal)
        return dataclasses.replace(self, step_arcsec=[float(x) for x in step_arcsec],
                                   sigma_arcsec=[float(x) for x in sigma_arcsec],
                                   shift_px=shift, sigma_px=sigma, angle_deg=angle)


def _at_centre(step: np.ndarray, cov: np.ndarray, focal: tuple[float, float]
               ) -> tuple[float, float, float]:
    """The stars' shift at the detector's centre (px) of a rotation and its σ.

    ``step`` (arcsec, the stars' sign) with covariance ``cov``: the shift's size, its σ
    along it and its direction (deg, from +u toward +v).
    """
    A = np.array([[0.0, focal[0], 0.0], [-focal[1], 0.0, 0.0]]) * ARCSEC  # px per arcsec
    shift = A @ step
    size = float(np.hypot(*shift))
    along = shift / max(size, 1e-300)
    return (size, float(math.sqrt(max(float(along @ A @ cov @ A.T @ along), 0.0))),
            float(np.degrees(np.arctan2(shift[1], shift[0]))))


def contrast(window: int = WINDOW) -> np.ndarray:
    """The step's row of the fit ``(1, j, [j ≥ 0])`` over ``j = −window … window − 1``."""
    j = np.arange(-window, window)
    X = np.stack([np.ones(2 * window), j, (j >= 0).astype(float)], 1)
    return np.linalg.pinv(X)[2]


def installation_step(res: stats.Table, mask: np.ndarray, focal: tuple[float, float],
                      centre: tuple[float, float], R_imu_st: np.ndarray | None,
                      everywhere: bool = False, shared: dict | None = None
                      ) -> InstallationStep | None:
    """The attitude step test on ``mask``'s accepted stars (module docstring).

    ``None`` without the installation or the rate columns (the frames at rest are not
    known), or with fewer than :data:`MIN_CANDIDATES` frames to test.  With fewer than
    :data:`MIN_CANDIDATES` at rest all frames are tested (a platform that never rests), and
    with ``everywhere`` (a gyro rate candidate's rival in ``discover``, not the line),
    unless the frames' stamps jitter where the platform rests (:func:`jittered`).
    ``shared``: as :func:`~stellar_cal_ros.diagnosis.stats.accepted_offsets`' (the clock
    test's on the same rows).
    """
    found = stats.accepted_offsets(res, mask, focal, centre, R_imu_st, shared)
    if found is None:
        return None
    sub, got = found
    fr_o, _, info = got[:3]
    still = fr_o[~stats.moving_frames(sub, fr_o, info, REST)]
    frames, g, info3 = stats.frame_attitudes(sub, focal)
    n = len(frames)
    if n < 2 * (WINDOW + MARGIN) + MIN_CANDIDATES:
        return None
    a = np.linalg.solve(info3, g[:, :, None])[:, :, 0]  # arcsec
    rest = np.isin(frames, still)
    c = contrast()
    j = np.arange(-WINDOW, WINDOW)
    k = np.arange(WINDOW + MARGIN, n - WINDOW - MARGIN + 1)
    k = k[frames[k + WINDOW - 1] - frames[k - WINDOW] == 2 * WINDOW - 1]  # consecutive
    cum = np.concatenate([[0], np.cumsum(~rest)])
    still_k = k[cum[k + WINDOW + MARGIN] == cum[k - WINDOW - MARGIN]]  # all at rest
    # (frames whose stamps jitter: where the platform rests, the moving frames' steps are
    # the filter's answer to the stamps' errors, :func:`jittered`)
    at_rest = len(still_k) >= MIN_CANDIDATES and (not everywhere or jittered(got))
    if at_rest:
        k = still_k
    if len(k) < MIN_CANDIDATES:
        return None
    idx = k[:, None] + j[None, :]
    step = np.einsum("j,njc->nc", c, a[idx])
    cov3, sig_t = np.linalg.inv(info3), None
    if len(still_k) < MIN_CANDIDATES:  # (a platform that never rests: stamp_spread)
        cov3, sig_t = stamp_spread(sub, got, frames, cov3, R_imu_st)
    V = np.einsum("j,njab->nab", c**2, cov3[idx])
    w, U = np.linalg.eigh(V)
    if not np.all(w > 0):
        return None
    half = np.einsum("nij,nj,nkj->nik", U, np.sqrt(w), U)  # V^½
    white = np.einsum("nij,nj->ni", np.einsum("nij,nj,nkj->nik", U, 1.0 / np.sqrt(w), U),
                      step)
    keep = np.ones(len(k), dtype=bool)
    cut = float(dist.chi2.isf(TRIM, 3))
    for _ in range(5):
        if keep.sum() < MIN_CANDIDATES:
            return None
        S = white[keep].T @ white[keep] / keep.sum()
        d2 = np.einsum("ni,ij,nj->n", white, np.linalg.inv(S), white)
        new = d2 < cut
        if np.array_equal(new, keep):
            break
        keep = new
    i = int(np.argmax(d2))
    p = min(1.0, float(dist.chi2.sf(d2[i], 3)) * len(k))
    cov = half[i] @ S @ half[i]
    size, sigma, angle = _at_centre(step[i], cov, focal)
    t = stats.frame_times(sub, frames[[k[i] - 1, k[i]]]) - float(np.min(res["t"]))
    return InstallationStep(
        float(t[1]), float(t[0]), [float(x) for x in step[i]],
        [float(x) for x in np.sqrt(np.diag(cov))], size, sigma, angle, float(d2[i]),
        int(len(k)), p, at_rest, None if sig_t is None else sig_t * 1e3)


def jittered(offsets: tuple) -> bool:
    """Whether the frames of ``offsets`` show a noise in their stamps.

    :func:`~stellar_cal_ros.diagnosis.stats.stamp_noise` on :func:`~stellar_cal_ros.
    diagnosis.stats.frame_offsets`' ``offsets``, one-sided p < :data:`STAMP_ALPHA`.

    Where the platform rests and slews, a test ``everywhere`` is then made over the frames
    at rest: during a slew each jittered frame turns the stars by the rate × its stamp's
    error, the filter (which does not model it) takes those turns into its attitude and
    installation, and at the slew's ends its answer steps across the rate too.  Unseen
    case ``jitter`` (psce, 1 ms), the test before the window: s21 χ²₃ 5583 at 64.0 s, 759
    with the stamps' noise in each frame's spread (:func:`stamp_spread`: x −18, z −38″
    across a rate about y are left), s22 7155 and 2971; over the frames at rest 13.4 and
    12.1 (p 0.77 / 1; clean s21 13.5).  A knock during a slew on such a bag is not
    tested there.
    """
    return stamp_sigma(offsets) is not None


def stamp_sigma(offsets: tuple) -> float | None:
    """:func:`jittered`'s stamp noise σ̂_t (s), or None where its p is not below it."""
    got = stats.stamp_noise(*offsets[:5])
    return got[1] if got is not None and got[0] < STAMP_ALPHA and got[1] > 0 else None


def stamp_spread(sub: stats.Table, offsets: tuple, frames: np.ndarray, cov3: np.ndarray,
                 R_imu_st: np.ndarray) -> tuple[np.ndarray, float | None]:
    """Each frame's attitude covariance (arcsec², ``(n, 3, 3)``) with a noise in its stamp.

    ``offsets``: :func:`~stellar_cal_ros.diagnosis.stats.frame_offsets` of ``sub``;
    ``frames``, ``cov3``: :func:`~stellar_cal_ros.diagnosis.stats.frame_attitudes`' frames
    and their ``I⁻¹``.  A frame stamped ``δ`` off its exposure turns all its stars by
    ``ω δ`` (``ω`` the tracker's rate): an attitude noise ``σ_t² ω ωᵀ``, large where the
    image moves fast.  Where :func:`~stellar_cal_ros.diagnosis.stats.stamp_noise` finds a
    stamp noise on these frames (one-sided p < :data:`STAMP_ALPHA`), its ``σ̂_t`` is added so:
    the robust common covariance of the whitened steps is one scale for all frames, and the
    fastest frames' steps would read the stamps' noise as a step (unseen case
    ``sway_jitter`` s22, 1 ms: χ²₃ 27 at 256.5 s, where the image moves at up to 405 px/s,
    its window's median 186).  Returns ``(cov, σ̂_t in s or None)``; ``cov3`` itself
    without a stamp noise.

    Asked only where the platform never rests (fewer than :data:`MIN_CANDIDATES` frames
    at rest).  Where it rests and slews (psce) the line tests the frames at rest, whose
    rate is ~0, and the test over moving frames too (``everywhere``, ``before``) reads the
    slews' ends, where the filter's catch-up steps whatever the stamps' noise: unseen case
    ``jitter`` s21 (1 ms), the test before the window χ²₃ 5583 at 64.0 s without this
    term, 759 at 59.5 s with it, both beyond :data:`~stellar_cal_ros.diagnosis.auto.
    STEP_BEFORE_ALPHA`; the step fitted at 59.5 s explained the window at p 0.0082 and was
    kept, its line said first (at 64.0 s: not kept).  There the term is left out, and a
    test over all frames is made at rest where the stamps jitter (:func:`jittered`).
    """
    sig_t = stamp_sigma(offsets)
    if sig_t is None:
        return cov3, None
    fr, kk = stats.frames_of(np.asarray(sub["frame"]))
    w = np.stack([np.asarray(sub[f"omega_{x}"], dtype=float) for x in "xyz"], 1) \
        @ np.asarray(R_imu_st, dtype=float) / ARCSEC  # arcsec/s, tracker frame
    ok = stats.finite_rows(w)
    n = np.bincount(kk[ok], minlength=len(fr))
    mean = np.stack([np.bincount(kk[ok], w[ok, i], minlength=len(fr)) for i in range(3)], 1) \
        / np.maximum(n, 1)[:, None]
    om = mean[np.searchsorted(fr, frames)]
    return cov3 + sig_t**2 * np.einsum("ni,nj->nij", om, om), sig_t


#: what the size of a step tested over frames that move is (:meth:`InstallationStep.
#: regressor`): the frames' attitude jump, in which the filter's answer to the motion there
#: is too (``knock_gsf_run20`` s21: 96.8" at 60.0 s for a true 20" knock at 59.5 s)
JUMP = ("the size is the frames' attitude jump the test found, the filter's answer to the "
        "motion included: no step fitted")
#: the frames a step tested over all frames of a platform that rests is said the largest of
MOVING = ("moving or not: where the platform moves, a knock and a clock that steps are not "
          "told apart")
#: the frames a step found before the evaluation window is said the largest of
#: (:func:`~stellar_cal_ros.diagnosis.auto._step_before`)
BEFORE = ("moving or not, before the evaluation window, which sees only what the filter "
          "had left of it")
#: fewer window frames than this before the step: a candidate's gain there is not tested
MIN_BEFORE = 20


def before_and_after(without: np.ndarray | None, with_c: np.ndarray | None, stamp: float,
                     dispersion: float, dof: int) -> dict | None:
    """A candidate's log-likelihood ratio on the window's frames before a step and after it.

    ``without``, ``with_c``: the window's log-likelihood frame by frame of the current
    model's run and of the candidate's (:attr:`~stellar_cal_ros.diagnosis.runstats.
    RunSummary.frame_loglik`, ``(2, frames)``: stamps, terms); ``stamp``: the first frame
    after the step (POSIX s); ``dispersion``: the current model's (the candidates' ratio
    test's).  ``{"before": ..., "after": ...}``, each ``2 Δℓ / dispersion`` over those
    frames (``statistic``), its χ²_dof tail (``p_value``) and ``frames``; ``None`` without
    both runs' frames or with fewer than :data:`MIN_BEFORE` frames before the step.  A
    library constant acts before a knock as after it; what the filter's catch-up on the
    knock leaves starts at it (:func:`~stellar_cal_ros.diagnosis.auto` refuses a gyro rate
    candidate that explains nothing before it).
    """
    if without is None or with_c is None or not without.shape[1] or not with_c.shape[1]:
        return None
    common = np.intersect1d(without[0], with_c[0])
    a = without[1, np.searchsorted(without[0], common)]
    b = with_c[1, np.searchsorted(with_c[0], common)]
    before = common < stamp
    if before.sum() < MIN_BEFORE:
        return None
    out = {}
    for name, m in (("before", before), ("after", ~before)):
        s = float(2.0 * (b[m].sum() - a[m].sum()) / dispersion)
        out[name] = {"statistic": s, "p_value": float(dist.chi2.sf(max(s, 0.0), dof)),
                     "frames": int(m.sum())}
    return out


#: the step fitted as a nuisance (:class:`StepNuisance`): a private id (a leading ``_``:
#: never listed by :func:`~stellar_cal_ros.effects.registry.available`)
STEP_ID = "_installation_step"


class StepNuisance(Effect):
    """The installation rotated by ``δ`` from ``T`` (POSIX s) on: a knock, fitted.

    Not a library effect and never offered: the discovery puts it beside a gyro rate
    candidate where the step test fires (:func:`~stellar_cal_ros.diagnosis.auto._top`) and
    keeps it, hidden, in the model once that candidate is added beside it (unseen cases
    ``knock_gsf_early``, ``sway_knock_gsf``: the scale's estimate is right only beside
    the step; doc/benchmarks.md, H205).  ``T`` travels in the prior
    (``effects[STEP_ID]["t_posix"]``, read by :meth:`initial`, kept by :meth:`store`): a
    run in a worker process builds its effects from the prior it is sent, and so does
    the σ it starts from where the prior's sigma block has none (``"sigma"``, rad: a
    re-run's prior keeps no sigma block).
    """

    id = STEP_ID
    stage = Stage.TRACKER
    order = 15
    parameter_names = ("dx", "dy", "dz")
    units = ("rad", "rad", "rad")
    default_sigma = (100.0 * ARCSEC,) * 3
    explanation = "a knock on the mount, fitted as a nuisance (not a library effect)"
    T = math.inf
    S: list[float] | None = None

    def initial(self, prior):  # noqa: D102
        block = (prior.effects or {}).get(self.id) or {}
        self.T = float(block.get("t_posix", math.inf))
        self.S = block.get("sigma")
        value, sigma = super().initial(prior)
        stated = ((prior.sigma or {}).get("effects") or {}).get(self.id)
        if self.S is not None and not stated:
            sigma = np.asarray(self.S, dtype=float)
        return value, sigma

    def store(self, value, sigma, cal):  # noqa: D102
        super().store(value, sigma, cal)
        cal.effects[self.id]["t_posix"] = self.T
        if self.S is not None:
            cal.effects[self.id]["sigma"] = list(self.S)

    def tracker_rotation(self, value, ctx):  # noqa: D102
        return np.asarray(value, dtype=float) if ctx.stamp >= self.T else np.zeros(3)

    def tracker_rotation_jacobian(self, value, ctx):  # noqa: D102
        return np.eye(3) if ctx.stamp >= self.T else np.zeros((3, 3))


#: the step's prior σ in :func:`with_step`: this many times the step test's σ
PRIOR_SIGMAS = 3.0


def with_step(prior, t_posix: float, step: InstallationStep | None = None):
    """``prior`` with :class:`StepNuisance` from ``t_posix`` on (a copy).

    Its start the step test's ``step`` (the rotation that turns the stars back, ± its σ ×
    :data:`PRIOR_SIGMAS`), else zero ± the class's σ (100″: the frame after the step would
    expect ~1.9 px, and a noise measured on that model reads the step's freedom).
    """
    import copy

    out = copy.deepcopy(prior)
    out.effects[STEP_ID] = {"t_posix": float(t_posix)}
    if step is not None:
        out.effects[STEP_ID].update(
            {n: -float(x) * ARCSEC for n, x in zip(StepNuisance.parameter_names,
                                                   step.step_arcsec, strict=True)},
            sigma=[PRIOR_SIGMAS * float(x) * ARCSEC for x in step.sigma_arcsec])
    return out


def register_step(runs, cls: type[Effect] | None = None) -> None:
    """Make :class:`StepNuisance` (or the nuisance ``cls``) known here and to ``runs``' workers.

    (:class:`~stellar_cal_ros.diagnosis.slew_steps.SlewSteps` too.)
    """
    from stellar_cal_ros.effects import registry

    cls = cls or StepNuisance
    if cls.id not in registry.EFFECTS:
        registry.register(cls)
    if cls not in tuple(runs.classes):
        runs.classes = (*tuple(runs.classes), cls)
