"""Does the gyro turn as the stars do?  One check for the batch method and the filters.

The stars of one frame give the tracker's attitude ``R_i_st`` by themselves (a Wahba fit);
the gyro gives the body's rotation between two times.  Between two star frames both
rotations have the same angle, and their axes (tracker frame, IMU frame) map onto each other
by one fixed rotation, the installation.  Data that break this break the contract:

* the gyro turns 57.3× as far as the stars: rates in deg/s (1/57.3×: converted twice);
* it turns almost not at all: a dead, stuck or disconnected gyro;
* the angles agree but no fixed rotation maps the axes: swapped, mirrored or mislabelled
  IMU axes.

:func:`judge` compares rotation vectors of frame pairs (star vs gyro);
:func:`check_gyro_against_stars` runs it over a whole run (the ACF batch method);
:func:`new_watch` / :func:`watch_frame` run it while a filter streams its frames (the
kernel: refused over the first frames, flagged when it only shows later).  Numpy and scipy
only.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from stellar_cal_ros.core.attitude import batched_wahba, wahba
from stellar_cal_ros.errors import DataError

#: frame-index lags of the pairs compared (each anchor frame with the frames this far on)
LAGS = (1, 2, 4, 8, 16, 32, 64, 128, 256)
#: star rotation of the pairs in the angle ratio, rad (a gyro 57× too fast stays < 180°)
RATIO_RANGE = (np.deg2rad(0.05), np.deg2rad(2.0))
#: star rotation of the pairs in the axis test, rad
AXIS_RANGE = (np.deg2rad(2.0), np.deg2rad(170.0))
#: the median angle ratio must lie inside this (a focal length tens of % off moves it)
RATIO_LIMITS = (0.5, 2.0)
#: 95th percentile of the axis misfit beyond this, deg: no fixed rotation maps the axes
AXIS_MISFIT_DEG = 5.0
#: ... and from the axes seen through the prior installation, beyond this, deg
PRIOR_MISFIT_DEG = 10.0
#: share of the pairs rotated AXIS_RANGE whose angle ratio may lie outside RATIO_LIMITS
OFF_SHARE = 0.05
#: ... and at least this many of them
MIN_OFF_PAIRS = 5
#: pairs needed before the ratio is judged
MIN_RATIO_PAIRS = 5
#: pairs (spanning two directions) needed before the axes are judged
MIN_AXIS_PAIRS = 3


#: frames fitted in this process, by their directions' bytes: every re-run of a diagnosis
#: round records the same early frames (the same centroids through the same prior camera,
#: ~10 000 fits in one ``discover``); cleared when full (the live node's frames never repeat)
_FITS: dict[tuple, tuple[np.ndarray | None, float]] = {}
#: ... at most this many (a few MB)
FITS_KEPT = 4096


def frame_rotation(v_st: np.ndarray, u_i: np.ndarray) -> tuple[np.ndarray | None, float]:
    """``R_i_st`` of one frame and the RMS error of its inliers, rad (inf if < 3 stars).

    A frame fitted before in this process returns its earlier fit (the same floats:
    :func:`_frame_rotation` of equal inputs; the rotation read-only).
    """
    v, u = np.asarray(v_st, dtype=float), np.asarray(u_i, dtype=float)
    key = (v.shape, u.shape, v.tobytes(), u.tobytes())
    fit = _FITS.get(key)
    if fit is None:
        if len(_FITS) >= FITS_KEPT:
            _FITS.clear()
        fit = _FITS[key] = _frame_rotation(v, u)
    return fit


def _frame_rotation(v_st: np.ndarray, u_i: np.ndarray) -> tuple[np.ndarray | None, float]:
    """:func:`frame_rotation`'s fit.

    Wahba's solution (SVD), refitted (up to 4 times) without the stars more than 4 × the inliers'
    median error (at least 20") off, until the inliers do not change: wrong identities do
    not tilt it.

    Parameters
    ----------
    v_st : ndarray (n, 3)
        Measured star directions in the tracker frame (unit vectors).
    u_i : ndarray (n, 3)
        Their catalogue directions, inertial frame.
    """
    v, u = np.asarray(v_st, dtype=float), np.asarray(u_i, dtype=float)
    if not (math.isfinite(v.sum()) and math.isfinite(u.sum())):  # (else: all finite)
        ok = np.all(np.isfinite(v), axis=1) & np.all(np.isfinite(u), axis=1)
        v, u = v[ok], u[ok]
    if len(v) < 3:
        return None, float("inf")

    def errors(R: np.ndarray) -> np.ndarray:
        return np.arccos(np.clip(np.einsum("ij,ij->i", v @ R.T, u), -1, 1))

    inl = None  # every star an inlier
    R = batched_wahba(v[None], u[None])[0]
    for _ in range(4):
        err = errors(R)
        new = err <= max(4.0 * _median(err if inl is None else err[inl]), 1e-4)
        n_new = int(np.count_nonzero(new))
        if n_new < 3 or (n_new == len(new) if inl is None else np.array_equal(new, inl)):
            break  # (``err``: the errors of this ``R``)
        inl = new
        R = batched_wahba(v[inl][None], u[inl][None])[0]
    else:  # refitted after the last errors
        err = errors(R)
    R.flags.writeable = False  # kept by frame_rotation
    return R, float(np.sqrt(np.mean((err if inl is None else err[inl]) ** 2)))


def _median(x: np.ndarray) -> float:
    """``np.median`` of finite values, without its general machinery.

    The same float: the middle one, or the mean of the two middle ones.
    """
    s = np.sort(x)
    m = len(s) // 2
    return float(s[m]) if len(s) % 2 else float((s[m - 1] + s[m]) / 2.0)


def rotvecs(mats: Any) -> np.ndarray:
    """Rotation vectors (k, 3) of rotation matrices (k, 3, 3).

    From the skew part (``sin θ · axis``) and the trace (``cos θ``), vectorized; rotations
    beyond 120° (where the skew part loses the axis) through scipy.
    """
    m = np.asarray(mats, dtype=float).reshape(-1, 3, 3)
    sk = 0.5 * np.stack([m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0],
                         m[:, 1, 0] - m[:, 0, 1]], axis=1)
    c = 0.5 * (np.trace(m, axis1=1, axis2=2) - 1.0)
    sn = np.linalg.norm(sk, axis=1)
    th = np.arctan2(sn, c)
    out = sk * np.where(sn > 1e-12, th / np.maximum(sn, 1e-300), 1.0)[:, None]
    far = c < -0.5
    if far.any():
        from scipy.spatial.transform import Rotation

        out[far] = Rotation.from_matrix(m[far]).as_rotvec()
    return out


def frame_pairs(n: int, anchors: int = 200,
                segment: np.ndarray | None = None) -> np.ndarray:
    """Index pairs ``(i, i + lag)`` (m, 2) of ``n`` frames.

    Up to ``anchors`` anchors spread over the frames, each with the frames :data:`LAGS`
    later; only pairs inside one ``segment`` (e.g. between IMU gaps the gyro could not
    bridge) when given.
    """
    first = np.unique(np.linspace(0, n - 1, min(n, anchors)).astype(int)) if n else \
        np.zeros(0, int)
    i, j = np.meshgrid(first, np.asarray(LAGS), indexing="ij")
    pairs = np.stack([i.ravel(), (i + j).ravel()], axis=1)
    pairs = pairs[pairs[:, 1] < n]
    if segment is not None and len(pairs):
        seg = np.asarray(segment)
        pairs = pairs[seg[pairs[:, 0]] == seg[pairs[:, 1]]]
    return pairs


def judge(a_s: np.ndarray, a_g: np.ndarray, R_imu_st: np.ndarray | None = None,
          prior_misfit_deg: float = PRIOR_MISFIT_DEG) -> dict[str, Any]:
    """Compare the stars' and the gyro's rotation over the same frame pairs.

    Parameters
    ----------
    a_s : ndarray (m, 3)
        Rotation vectors of the tracker between the two frames of each pair (from the
        stars; tracker frame), rad.
    a_g : ndarray (m, 3)
        The gyro's rotation vectors over the same pairs (IMU frame), rad.
    R_imu_st : ndarray (3, 3), optional
        The prior installation.  With it the axes are also compared through it, which
        needs no rotation about a second direction: a mirror that a rotation 90° away from
        the prior could explain is found too (beyond ``prior_misfit_deg``).
    prior_misfit_deg : float
        Largest 95th-percentile angle between the gyro axes and ``R_imu_st`` · star axes.

    Returns
    -------
    dict
        ``ratio`` (median gyro angle / star angle over the pairs rotated
        :data:`RATIO_RANGE`; NaN if none), ``pairs`` (their number), ``axis_misfit_deg``
        (95th percentile of the angle between the gyro axes and the star axes after the
        best fixed rotation, pairs rotated :data:`AXIS_RANGE`; NaN if not tested),
        ``prior_misfit_deg`` (the same through ``R_imu_st``), ``axis_pairs``,
        ``pairs_off`` (pairs rotated :data:`AXIS_RANGE` whose angle ratio lies outside
        :data:`RATIO_LIMITS`: more than :data:`OFF_SHARE` of them is a dead or stuck axis),
        ``ratio_ok`` / ``axes_ok`` / ``prior_ok`` (True, False, or None: not decided yet)
        and ``cause`` (one line naming the fault, '' if none).
    """
    a_s, a_g = np.asarray(a_s, dtype=float).reshape(-1, 3), np.asarray(a_g, float).reshape(-1, 3)
    th_s, th_g = np.linalg.norm(a_s, axis=1), np.linalg.norm(a_g, axis=1)
    in_ratio = (th_s >= RATIO_RANGE[0]) & (th_s <= RATIO_RANGE[1])
    # axes only where the angles agree (a gyro 57× too fast wraps past 180° there)
    in_axes = (th_s >= AXIS_RANGE[0]) & (th_s <= AXIS_RANGE[1]) & \
        (th_g > RATIO_LIMITS[0] * th_s) & (th_g < RATIO_LIMITS[1] * th_s)
    out: dict[str, Any] = {"ratio": float("nan"), "pairs": int(in_ratio.sum()),
                           "axis_misfit_deg": float("nan"), "prior_misfit_deg": float("nan"),
                           "axis_pairs": int(in_axes.sum()), "pairs_off": 0, "ratio_ok": None,
                           "axes_ok": None, "prior_ok": None, "cause": ""}
    if out["pairs"] >= MIN_RATIO_PAIRS:
        ratio = float(np.median(th_g[in_ratio] / th_s[in_ratio]))
        out["ratio"] = ratio
        out["ratio_ok"] = bool(RATIO_LIMITS[0] < ratio < RATIO_LIMITS[1])
        if not out["ratio_ok"]:
            out["cause"] = _ratio_cause(ratio, out["pairs"])
            return out
    big = (th_s >= AXIS_RANGE[0]) & (th_s <= AXIS_RANGE[1])
    off = big & ((th_g <= RATIO_LIMITS[0] * th_s) | (th_g >= RATIO_LIMITS[1] * th_s))
    out["pairs_off"] = int(off.sum())
    # most pairs off and no angle ratio yet: the whole gyro (units, dead) — wait for the
    # ratio, which names the cause (a gyro 57× too fast wraps past 180° on these pairs)
    whole = off.sum() > 0.5 * big.sum() and out["ratio_ok"] is None
    if off.sum() >= MIN_OFF_PAIRS and off.sum() > OFF_SHARE * big.sum() and not whole:
        out["ratio_ok"] = False
        out["cause"] = (
            f"on {off.sum()} of {big.sum()} frame pairs rotated more than "
            f"{np.degrees(AXIS_RANGE[0]):g} deg the gyro turns less than half or more than twice "
            f"as far as the stars (median {np.median(th_g[off] / th_s[off]):.3g} x): a dead, "
            "stuck or mis-scaled gyro axis")
        return out
    if out["axis_pairs"] < MIN_AXIS_PAIRS:
        return out
    A_s = a_s[in_axes] / th_s[in_axes, None]
    A_g = a_g[in_axes] / th_g[in_axes, None]
    sv = np.linalg.svd(A_g, compute_uv=False)
    if sv[1] > 0.2 * sv[0]:  # the axes span more than one direction: a rotation is fixed
        R = wahba(A_s, A_g)  # R_imu_st: gyro axes (IMU) ≈ R · star axes (tracker)
        out["axis_misfit_deg"] = _misfit(A_s @ R.T, A_g)
        out["axes_ok"] = bool(out["axis_misfit_deg"] <= AXIS_MISFIT_DEG)
        if not out["axes_ok"]:
            out["cause"] = (
                f"the gyro's rotation axes between star frames match the stars' by no fixed "
                f"rotation (95 % of {len(A_s)} frame pairs within "
                f"{out['axis_misfit_deg']:.1f} deg): IMU axes swapped, mirrored or mislabelled")
            return out
    if R_imu_st is not None:
        out["prior_misfit_deg"] = _misfit(A_s @ np.asarray(R_imu_st).T, A_g)
        out["prior_ok"] = bool(out["prior_misfit_deg"] <= prior_misfit_deg)
        if not out["prior_ok"]:
            out["cause"] = (
                f"the gyro's rotation axes between star frames are "
                f"{out['prior_misfit_deg']:.1f} deg (95 % of {len(A_s)} frame pairs) from the "
                "stars' seen through the prior installation: IMU axes swapped, mirrored or "
                "mislabelled (or the prior installation is that far off)")
    return out


def _misfit(a: np.ndarray, b: np.ndarray) -> float:
    """95th percentile of the angles between unit vectors ``a[k]`` and ``b[k]``, deg."""
    return float(np.percentile(np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", a, b),
                                                             -1, 1))), 95))


def _ratio_cause(ratio: float, pairs: int) -> str:
    head = (f"the gyro turns {ratio:.4g} x as far as the stars between star frames (median "
            f"over {pairs} frame pairs)")
    deg = 180.0 / np.pi
    if abs(ratio / deg - 1.0) < 0.1:
        return head + ": /imu/data looks like deg/s, the contract (sensor_msgs/Imu) says rad/s"
    if abs(ratio * deg - 1.0) < 0.1:
        return head + ": the rates look converted from deg/s to rad/s twice"
    if ratio < 0.05:
        return head + ": the gyro shows almost no rotation (dead, disconnected or stuck)"
    return head + ": wrong gyro units or scale"


def _good_fits(rms: np.ndarray) -> np.ndarray:
    """Frames whose stars fit: RMS within 5 × the median frame's (finite ones)."""
    rms = np.asarray(rms, dtype=float)
    fin = rms[np.isfinite(rms)]
    worst = 5.0 * max(float(np.median(fin)), 1e-5) if len(fin) else np.inf
    return np.isfinite(rms) & (rms <= worst)


def check_gyro_against_stars(times: Sequence[float], directions_st: Sequence[np.ndarray],
                             directions_i: Sequence[np.ndarray],
                             attitude: Callable[[float], np.ndarray],
                             R_imu_st: np.ndarray | None = None) -> dict[str, Any]:
    """Compare the gyro's rotation between star frames with the stars' rotation (a run).

    Each frame's tracker attitude comes from its own fit (:func:`frame_rotation`); frames
    whose stars fit worse than 5 × the median frame's are not used.  Pairs: up to 200
    anchor frames, each with the frames :data:`LAGS` later (:func:`frame_pairs`), judged
    by :func:`judge`.

    Parameters
    ----------
    times : sequence of float
        Relative time of each frame, s (increasing).
    directions_st : sequence of ndarray (n_k, 3)
        Measured star directions in the tracker frame (centroids unprojected with the
        prior camera).
    directions_i : sequence of ndarray (n_k, 3)
        Their catalogue directions (inertial).
    attitude : callable
        ``t → R_n0_b(t)`` (3, 3) from the gyro alone.
    R_imu_st : ndarray (3, 3), optional
        The prior installation (see :func:`judge`).

    Returns
    -------
    dict
        :func:`judge`'s numbers.

    Raises
    ------
    DataError
        The gyro's rotation is not the stars' (wrong units, a dead gyro, swapped or
        mirrored axes); the message names the likely cause.
    """
    n = len(times)
    pairs = frame_pairs(n)
    needed = np.unique(pairs) if len(pairs) else np.zeros(0, int)
    fits = {int(k): frame_rotation(directions_st[k], directions_i[k]) for k in needed}
    keys = list(fits)
    good = dict(zip(keys, _good_fits(np.array([fits[k][1] for k in keys])), strict=True))
    pairs = np.array([p for p in pairs.tolist() if good[p[0]] and good[p[1]]],
                     dtype=int).reshape(-1, 2)
    if not len(pairs):
        return judge(np.zeros((0, 3)), np.zeros((0, 3)))
    use = np.unique(pairs)
    R_g = {int(k): attitude(float(times[k])) for k in use}
    a_s = rotvecs([fits[i][0].T @ fits[j][0] for i, j in pairs])
    a_g = rotvecs([R_g[i].T @ R_g[j] for i, j in pairs])
    out = judge(a_s, a_g, R_imu_st)
    if out["cause"]:
        raise DataError(out["cause"])
    return out


# ---------------------------------------------------------------------------- streaming
#: every frame is recorded until this many were seen; a fault found by then is refused
EARLY_FRAMES = 200
#: later, one frame per this many seconds is recorded (a fault then: the result is flagged)
LATE_SPACING_S = 5.0
#: records kept at most (then every other one is dropped and the spacing doubled)
MAX_RECORDS = 400
#: records between two judgements (and one more at the end of the data:
#: :func:`judge_pending`)
JUDGE_EVERY = 10


_F8 = np.dtype(float)


def new_watch() -> dict[str, Any]:
    """The state of a streaming check (plain arrays and numbers: checkpoints save it).

    Keys: ``t``, ``R_star`` (k, 3, 3), ``rms``, ``G`` (k, 3, 3) the gyro chain at each
    recorded frame, ``segment`` (k,), ``frames`` seen, ``G_now`` and ``R_post`` (the
    filter's attitude after the last frame), ``spacing`` (s), ``result`` (the last
    :func:`judge`), ``done``; ``since`` (records since the last judgement), ``judged_at``
    (frames seen at the last judgement); deferred (``defer``): ``pending`` frames.
    """
    return {"t": np.zeros(0), "R_star": np.zeros((0, 3, 3)), "rms": np.zeros(0),
            "G": np.zeros((0, 3, 3)), "segment": np.zeros(0, dtype=int), "seg": 0,
            "frames": 0, "G_now": np.eye(3), "R_post": None, "spacing": LATE_SPACING_S,
            "result": None, "done": False, "since": 0}


def watch_frame(state: dict[str, Any], t: float,
                v_st: np.ndarray | Callable[[], np.ndarray], u_i: np.ndarray,
                R_prior: np.ndarray | None, R_post: np.ndarray,
                R_imu_st: np.ndarray | None = None) -> str:
    """Add one processed star frame to a streaming check; the fault it reveals ('' none).

    The gyro chain advances by ``R_postᵀ(previous frame) · R_prior`` — the filter's attitude
    propagated by the gyro alone from the last frame to this one, with no update in it —
    so star updates and re-acquisitions do not enter it.

    Parameters
    ----------
    state : dict
        :func:`new_watch`'s state (updated in place).
    t : float
        The frame's exposure time, s (relative).
    v_st, u_i : ndarray (n, 3)
        Measured directions (tracker frame) and catalogue directions of its stars;
        ``v_st`` may be a callable returning them (called only for a frame recorded).
        With ``state["defer"]`` set, ``v_st`` is the frame's pixel centroids (n, 2),
        kept for :func:`record_pending` (which fits and judges between frames; a frame
        whose fit fails there still sets the late spacing, the only difference).
    R_prior : ndarray (3, 3) or None
        The filter's ``R_i_b`` propagated to the frame before its update; None: the chain
        starts again here (first frame, or an IMU gap the gyro could not bridge).
    R_post : ndarray (3, 3)
        ``R_i_b`` after the frame was processed.
    R_imu_st : ndarray (3, 3), optional
        The prior installation (see :func:`judge`).

    Returns
    -------
    str
        The cause (:func:`judge`) when this frame's judgement finds a fault, else ''.
    """
    # the one-frame case of watch_frames; R_post copied (the caller's array changes later)
    R_post = R_post.copy() if type(R_post) is np.ndarray and R_post.dtype is _F8 \
        else np.array(R_post, dtype=float)
    if state.get("defer") or not callable(v_st):
        unproject = _same
    else:
        def unproject(_uv: np.ndarray) -> np.ndarray:
            return v_st()
    return watch_frames(state, (t,), (v_st,), (u_i,), (R_prior,), (R_post,), R_imu_st,
                        unproject, 0, 1)[1]


def _same(x: np.ndarray) -> np.ndarray:
    """The directions as given (:func:`watch_frame`'s ``v_st`` when not a callable)."""
    return x


def watch_frames(state: dict[str, Any], t: list, uv: list, u_i: list, R_prior: np.ndarray,
                 R_post: np.ndarray, R_imu_st: np.ndarray | None,
                 unproject: Callable[[np.ndarray], np.ndarray], start: int,
                 stop: int) -> tuple[int, str]:
    """:func:`watch_frame` of frames ``start .. stop - 1`` in a row (a replay's batch).

    The same chain (the same products, in the same order), records and verdicts: frame
    ``i`` has exposure ``t[i]``, pixel centroids ``uv[i]`` (``unproject``: to tracker
    directions, for a frame recorded) and catalogue directions ``u_i[i]``, attitudes
    ``R_prior[i]`` and ``R_post[i]`` (arrays the caller no longer writes).  Returns after
    the first frame recorded — its judgement's cause goes to the caller's verdict before
    the next frame — ``(the next frame, cause)``; ``(stop, '')`` when none is.
    ``R_prior[i]`` None: the chain starts again at frame ``i`` (:func:`watch_frame`).
    """
    s = state
    G, R_last, frames = s["G_now"], s["R_post"], s["frames"]
    pending = s.get("pending")
    last = pending[-1][0] if pending else (s["t"][-1] if len(s["t"]) else None)
    spacing = s["spacing"]
    for i in range(start, stop):
        R_pr = R_prior[i]
        if R_last is None or R_pr is None:
            G = np.eye(3)
            s["seg"] += 1
        else:
            # ``dot``: the same BLAS product as ``@`` (bit for bit, test_gyro_check), 2.5x
            # cheaper a call on 3 x 3
            G = G.dot(R_last.T.dot(R_pr))
        R_last = R_post[i]
        frames += 1
        if frames > EARLY_FRAMES and last is not None and t[i] - last < spacing:
            continue
        s["G_now"], s["R_post"], s["frames"] = G, R_last, frames
        if s.get("defer"):
            s.setdefault("pending", []).append(
                (float(t[i]), np.asarray(uv[i]), np.asarray(u_i[i]), G, s["seg"], frames))
            return i + 1, ""
        if _record(s, t[i], unproject(uv[i]), u_i[i], G, s["seg"]):
            s["judged_at"] = frames
            return i + 1, _judge(s, R_imu_st)
        return i + 1, ""
    s["G_now"], s["R_post"], s["frames"] = G, R_last, frames
    return stop, ""


def _record(s: dict[str, Any], t: float, v_st: np.ndarray, u_i: np.ndarray, G: np.ndarray,
            seg: int) -> bool:
    """Record one frame (its star rotation and gyro chain); True when a judgement is due."""
    R, rms = frame_rotation(v_st, u_i)
    if R is None:
        return False
    s["t"] = np.append(s["t"], t)
    s["R_star"] = np.concatenate([s["R_star"], R[None]])
    s["rms"] = np.append(s["rms"], rms)
    s["G"] = np.concatenate([s["G"], G[None]])
    s["segment"] = np.append(s["segment"], seg)
    if len(s["t"]) > MAX_RECORDS:
        for key in ("t", "R_star", "rms", "G", "segment"):
            s[key] = s[key][::2]
        s["spacing"] *= 2.0
    s["since"] = s.get("since", 0) + 1
    return s["since"] >= JUDGE_EVERY


def record_pending(state: dict[str, Any], unproject: Callable[[np.ndarray], np.ndarray],
                   R_imu_st: np.ndarray | None = None) -> str:
    """Record and judge what a deferred watch (``state["defer"]``) left pending.

    With ``state["defer"]`` set (the live node) :func:`watch_frame` only keeps a frame's
    centroids (``v_st`` are then pixel centroids) and gyro chain; this does, between
    frames, what :func:`watch_frame` would have done frame by frame — the Wahba fit
    (``unproject``: pixels → tracker directions) and a judgement at every
    :data:`JUDGE_EVERY` th record — so the records and verdicts are the same.
    ``state["judged_at"]``: the frame count of the last judgement.  The fault ('' none).
    """
    s = state
    pending = s.get("pending") or []
    s["pending"] = []
    for t, uv, u_i, G, seg, frames in pending:
        if s["done"]:
            break
        if _record(s, t, unproject(uv), u_i, G, seg):
            s["judged_at"] = frames
            cause = _judge(s, R_imu_st)
            if cause:
                return cause
    return ""


def judge_pending(state: dict[str, Any], R_imu_st: np.ndarray | None = None,
                  unproject: Callable[[np.ndarray], np.ndarray] | None = None) -> str:
    """Judge the records of a streaming check (:func:`watch_frame`); the fault ('' none).

    :func:`watch_frame` judges every :data:`JUDGE_EVERY` records; call this at the end of
    the data for the records since the last judgement (nothing to do: '').  A deferred
    watch's pending frames are recorded first (:func:`record_pending`, ``unproject``).
    """
    s = state
    if s.get("pending") and unproject is not None:
        cause = record_pending(s, unproject, R_imu_st)
        if cause:
            return cause
    if not s.get("since", 0) or s["done"]:
        return ""
    s["judged_at"] = s["frames"]
    return _judge(s, R_imu_st)


def _judge(s: dict[str, Any], R_imu_st: np.ndarray | None) -> str:
    """Judge every record pair (:func:`judge`); the cause ('' none)."""
    s["since"] = 0
    good = _good_fits(s["rms"])
    pairs = frame_pairs(len(s["t"]), segment=s["segment"])
    pairs = pairs[good[pairs[:, 0]] & good[pairs[:, 1]]] if len(pairs) else pairs
    Rs, G = s["R_star"], s["G"]
    a_s = rotvecs(Rs[pairs[:, 0]].transpose(0, 2, 1) @ Rs[pairs[:, 1]])
    a_g = rotvecs(G[pairs[:, 0]].transpose(0, 2, 1) @ G[pairs[:, 1]])
    res = judge(a_s, a_g, R_imu_st)
    s["result"] = {k: v for k, v in res.items() if k != "cause"}
    # a gyro found sound goes on being watched (sparsely): an axis that breaks, or one
    # that only a later rotation exercises, shows later
    s["done"] = bool(res["cause"])
    return res["cause"]
