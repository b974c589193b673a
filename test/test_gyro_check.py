"""The gyro against the stars (issue 13), and clocks that disagree.

``stellar_cal_ros.core.gyro_check`` compares the gyro's rotation between star frames with the
stars' own; the filters run it while they stream (``methods/kernel.py``), the ACF over the
whole run.  First on synthetic rotation vectors (each fault class and a sound gyro), then
through ``replay`` on a simulated 150 s ``psce_rotations`` run (±30° steps about x, y, z)
and variants of it from ``stellar_cal_ros.sim.faults``: swapped axes, a dead gyro and a gyro
in deg/s are refused over the first frames, a gyro whose z axis is dead is flagged when the
z steps show it (t = 120 s), the clean run raises no alarm, and an IMU clock 1 h off the
tracker's is a DataError naming the offset.
"""

from __future__ import annotations

import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stellar_cal_ros.core import gyro_check
from stellar_cal_ros.errors import DataError
from stellar_cal_ros.io.calibration import load_calibration
from stellar_cal_ros.methods.replay import replay
from stellar_cal_ros.sim.faults import catalogue, make_base

#: the installation used for the synthetic pairs (IMU ← tracker)
R_IMU_ST = Rotation.from_rotvec([0.3, -0.2, 0.1]).as_matrix()


def _pairs(seed: int = 0) -> np.ndarray:
    """Star rotation vectors (tracker frame), rad: 60 pairs of 0.1–1.5°, 60 of 3–40°."""
    rng = np.random.default_rng(seed)
    axes = rng.normal(size=(120, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    ang = np.deg2rad(np.concatenate([rng.uniform(0.1, 1.5, 60), rng.uniform(3.0, 40.0, 60)]))
    return axes * ang[:, None]


def _gyro(a_s: np.ndarray, matrix: np.ndarray, noise: float = 1e-6,
          seed: int = 1) -> np.ndarray:
    """The gyro's rotation vectors (IMU frame) of the same pairs through ``matrix``."""
    rng = np.random.default_rng(seed)
    rot = Rotation.from_rotvec(a_s @ R_IMU_ST.T)  # what a sound gyro measures
    w = rot.as_rotvec() @ np.asarray(matrix).T  # its components mixed / scaled
    return Rotation.from_rotvec(w).as_rotvec() + rng.normal(scale=noise, size=w.shape)


def test_a_sound_gyro_passes_every_test():
    a_s = _pairs()
    out = gyro_check.judge(a_s, _gyro(a_s, np.eye(3)), R_IMU_ST)
    assert out["cause"] == ""
    assert abs(out["ratio"] - 1.0) < 1e-3 and out["pairs_off"] == 0
    assert out["axis_misfit_deg"] < 0.01 and out["prior_misfit_deg"] < 0.01


@pytest.mark.parametrize("matrix, pattern", [
    (np.eye(3) * 180.0 / np.pi, r"looks like deg/s"),
    (np.zeros((3, 3)), r"almost no rotation"),
    (np.diag([1.0, 1.0, 0.0]), r"dead, stuck or mis-scaled gyro axis"),
    (np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), r"swapped, mirrored"),
], ids=["deg_s", "dead", "dead_z_axis", "x_y_swapped"])
def test_each_gyro_fault_is_named(matrix, pattern):
    a_s = _pairs()
    out = gyro_check.judge(a_s, _gyro(a_s, matrix), R_IMU_ST)
    assert out["cause"], out
    assert re.search(pattern, out["cause"]), out["cause"]


def test_a_dead_axis_the_motion_never_exercises_cannot_be_seen():
    """Rotations about x and y only: a dead z axis changes nothing the stars can check."""
    a_s = _pairs()
    a_s[:, 2] = 0.0
    a_s_imu = a_s @ R_IMU_ST.T
    a_s_imu[:, 2] = 0.0  # rotations about IMU x, y only
    a_s = a_s_imu @ R_IMU_ST
    assert gyro_check.judge(a_s, _gyro(a_s, np.diag([1.0, 1.0, 0.0])), R_IMU_ST)["cause"] == ""


# ---------------------------------------------------------------------------- replays
@pytest.fixture(scope="module")
def base(tmp_path_factory):
    return make_base(tmp_path_factory.mktemp("gyro") / "base", duration=150.0, seed=1)


_VARIANTS = {v.name: v for v in catalogue()}


def _replay(base, name: str | None, tmp_path):
    bag = base.bag if name is None else _VARIANTS[name].make(base, tmp_path / name).bag
    return replay(bag, load_calibration(base.prior), "psce")


def test_clean_run_raises_no_alarm(base, tmp_path):
    res = _replay(base, None, tmp_path)
    assert "gyro_star_mismatch" not in res.counters
    assert "data_quality" not in res.calibration.extra
    assert res.counters["updates"] >= 295  # of 300 frames


@pytest.mark.parametrize("name, pattern", [
    ("imu_axes_swapped", r"IMU axes swapped, mirrored or mislabelled"),
    ("imu_dead", r"almost no rotation \(dead"),
    ("imu_deg_s", r"57\.\d+ x as far as the stars.*deg/s"),
])
def test_gyro_faults_are_refused_over_the_first_frames(base, tmp_path, name, pattern):
    with pytest.raises(DataError, match=pattern):
        _replay(base, name, tmp_path)


def test_dead_z_axis_is_flagged_when_the_z_steps_show_it(base, tmp_path):
    res = _replay(base, "imu_dead_axis", tmp_path)
    reasons = res.calibration.extra["data_quality"]["reasons"]
    assert res.calibration.extra["data_quality"]["degraded"] is True
    assert any("dead, stuck or mis-scaled gyro axis" in r for r in reasons), reasons
    assert res.counters["gyro_star_mismatch"] == 1


def test_the_check_off_changes_no_estimate(base, tmp_path):
    """``gyro_fault="off"`` (the reliability probe's re-runs): the check does not run — the
    dead z axis is neither counted nor flagged — and every estimate and σ is the checked
    run's, bit for bit (the check only counts and flags)."""
    bag = _VARIANTS["imu_dead_axis"].make(base, tmp_path / "dead_z").bag
    checked = replay(bag, load_calibration(base.prior), "psce", gyro_fault="flag")
    off = replay(bag, load_calibration(base.prior), "psce", gyro_fault="off")
    assert checked.counters["gyro_star_mismatch"] == 1
    assert "gyro_star_mismatch" not in off.counters
    assert "data_quality" not in off.calibration.extra
    np.testing.assert_array_equal(off.filter.theta, checked.filter.theta)
    np.testing.assert_array_equal(off.covariance[1], checked.covariance[1])
    with pytest.raises(ValueError, match="gyro_fault"):
        replay(bag, load_calibration(base.prior), "psce", gyro_fault="ignore")


@pytest.mark.parametrize("sign", ["+", "-"])
def test_imu_clock_an_hour_off_is_named(base, tmp_path, sign):
    # the IMU stamps +1 h: the tracker's start 3600 s before them, and the reverse
    expect = {"+": r"start 3599\.\d+ s before .* offset by about -3599\.\d s",
              "-": r"start 3600\.\d+ s after .* offset by about \+3600\.\d s"}[sign]
    with pytest.raises(DataError, match=expect):
        _replay(base, f"clock_imu_{sign}1h", tmp_path)


@pytest.mark.parametrize("jump_s, flagged", [(3600.0, True), (-3600.0, False)])
def test_live_imu_clock_jump_is_counted_not_raised(base, jump_s, flagged):
    """Live (``strict_clock`` off) the IMU clock jumping mid-run is counted; a leap ahead
    that the star frames do not follow flags the result, a jump back (the older samples are
    dropped as late, as data sent again after a restart) does not."""
    from test_online import bag_events, feed, make

    events = bag_events(base.bag)
    events = events[:len(events) // 3]  # 50 s
    t_mid = events[len(events) // 2][0]
    shift = int(jump_s * 1e9)
    moved = [(lt, i, k, (p[0] + shift, *p[1:]) if k == "imu" and lt >= t_mid else p)
             for lt, i, k, p in events]
    cal = make(load_calibration(base.prior))
    feed(cal, moved)
    cal.finish()
    assert cal.counters.imu_clock_jumps >= 1
    reasons = cal.calibration().extra.get("data_quality", {}).get("reasons", [])
    assert any("IMU clock jumped" in r for r in reasons) is flagged, reasons


@pytest.mark.parametrize("name", [None, "imu_deg_s"])
def test_deferred_judgement_gives_the_same_records_and_verdict(base, tmp_path, name):
    """The live node's mode (``DriverConfig.defer_checks``, issue 24.3): a frame's update
    only keeps its centroids; ``Calibrator.run_checks`` (the node's timer, between frames)
    fits and judges them.  Same records, same judgement and the same verdict as judging in
    the update: a gyro in deg/s is refused with the same DataError, a clean one passes."""
    from test_online import bag_events

    from stellar_cal_ros.methods.driver import Calibrator, DriverConfig
    from stellar_cal_ros.methods.psce import PsceConfig

    bag = base.bag if name is None else _VARIANTS[name].make(base, tmp_path / name).bag
    prior = load_calibration(base.prior)
    runs = []
    for defer in (False, True):
        cal = Calibrator(prior, "psce", None, PsceConfig(), DriverConfig(defer_checks=defer))
        raised, kept = [], 0
        for _, _, kind, p in bag_events(bag):
            try:
                if kind == "imu":
                    cal.push_imu(p[0], p[1], frame_id=p[2])
                elif kind == "stars":
                    cal.push_stars(p)
                w = cal.filter.gyro_watch if cal.filter is not None else None
                if defer and w is not None and w.get("pending"):
                    kept = max(kept, len(w["pending"]))
                    cal.run_checks()  # as the node's timer, between two messages
            except DataError as exc:
                raised.append(str(exc))
                break
        runs.append((cal, raised, kept))
    (inline, r0, _), (deferred, r1, kept) = runs
    assert kept >= 1  # the updates did defer
    assert r0 == r1 and len(r0) == (name is not None)
    if name is None:
        inline.finish()
        deferred.finish()
        a, b = inline.filter.gyro_watch, deferred.filter.gyro_watch
        for key in ("t", "R_star", "rms", "G", "segment"):
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)
        assert a["result"] == b["result"] and a["judged_at"] == b["judged_at"]
        assert "gyro_star_mismatch" not in deferred.filter_counters()
    else:
        assert re.search(r"57\.\d+ x as far as the stars", r1[0])


def test_the_live_node_flags_a_gyro_fault_it_cannot_refuse(base, tmp_path):
    """The node's configuration (``calibrator.live_configs``): a gyro in deg/s, judged between
    frames over the first frames, flags the result (``data_quality``, ERROR on /diagnostics)
    instead of raising in the node's timer (where it was only a counted callback error and
    the saved calibration carried no word of it)."""
    from test_online import bag_events

    from stellar_cal_ros.methods.driver import Calibrator
    from stellar_cal_ros.nodes.calibrator import PARAMETERS, live_configs
    from stellar_cal_ros.nodes.health import DiagnosticStatus, verdict_status

    params = {k: v[0] for k, v in PARAMETERS.items()}
    params["method"] = "psce"
    cfg, drv = live_configs(params)
    bag = _VARIANTS["imu_deg_s"].make(base, tmp_path / "deg").bag
    cal = Calibrator(load_calibration(base.prior), "psce", None, cfg, drv)
    for _, _, kind, p in bag_events(bag):  # no DataError may escape
        if kind == "imu":
            cal.push_imu(p[0], p[1], frame_id=p[2])
        elif kind == "stars":
            cal.push_stars(p)
        cal.run_checks()  # as the node's timer, between two messages
    cal.finish()
    reasons = cal.degraded()
    assert len(reasons) == 1 and re.search(r"57\.\d+ x as far as the stars", reasons[0])
    assert cal.calibration().extra["data_quality"] == {"degraded": True, "reasons": reasons}
    level, text = verdict_status({"verdict": "consistent"}, True, reasons)
    assert level == DiagnosticStatus.ERROR and text.startswith("result degraded: ")
    assert verdict_status({"verdict": "consistent"}, True, [])[0] == DiagnosticStatus.OK


def _frame_rotation_general(v_st, u_i):
    """The general form of ``frame_rotation`` (every star masked, ``np.median``): the
    reference its fast paths (all finite, every star an inlier) must equal bit for bit."""
    v, u = np.asarray(v_st, dtype=float), np.asarray(u_i, dtype=float)
    ok = np.all(np.isfinite(v), axis=1) & np.all(np.isfinite(u), axis=1)
    if ok.sum() < 3:
        return None, float("inf")
    v, u = v[ok], u[ok]

    def errors(R):
        return np.arccos(np.clip(np.einsum("ij,ij->i", v @ R.T, u), -1, 1))

    inl = np.ones(len(v), dtype=bool)
    R = gyro_check.batched_wahba(v[None], u[None])[0]
    for _ in range(4):
        err = errors(R)
        new = err <= max(4.0 * float(np.median(err[inl])), 1e-4)
        if new.sum() < 3 or np.array_equal(new, inl):
            break
        inl = new
        R = gyro_check.batched_wahba(v[inl][None], u[inl][None])[0]
    return R, float(np.sqrt(np.mean(errors(R)[inl] ** 2)))


def test_frame_rotation_fast_paths_equal_the_general_form_bit_for_bit():
    # the watch's records (and so its verdicts) must not move: clean frames, frames with
    # wrong identities (refits), non-finite stars, too few stars, odd and even counts
    rng = np.random.default_rng(5)
    kinds = {"clean": 0, "refit": 0, "masked": 0, "few": 0}
    for i in range(600):
        n = int(rng.integers(0, 30))
        R = Rotation.random(random_state=i).as_matrix()
        v = rng.standard_normal((n, 3))
        v /= np.linalg.norm(v, axis=1)[:, None]
        u = v @ R.T + 10 ** rng.uniform(-8, -4) * rng.standard_normal((n, 3))
        wrong = bool(n and rng.random() < 0.3)  # wrong identities: the fit refits
        if wrong:
            u[rng.integers(0, n, size=rng.integers(1, 4))] += 0.01 * rng.standard_normal(3)
        if n and rng.random() < 0.1:
            v[rng.integers(0, n)] = np.nan
        if n and rng.random() < 0.05:
            u[rng.integers(0, n), 1] = np.inf
        R_ref, rms_ref = _frame_rotation_general(v, u)
        R_new, rms_new = gyro_check.frame_rotation(v, u)
        if R_ref is None:
            kinds["few"] += 1
            assert R_new is None and rms_new == rms_ref
            continue
        kinds["masked" if not (np.isfinite(v).all() and np.isfinite(u).all()) else
              "refit" if wrong else "clean"] += 1
        assert np.array_equal(R_new, R_ref) and rms_new == rms_ref, i
    assert min(kinds.values()) >= 10, kinds  # every kind of frame was tried


def test_frame_rotation_kept_fits_are_the_fits_of_their_own_frame(monkeypatch):
    # every re-run of a diagnosis round records the same early frames: a frame seen before
    # returns its earlier fit; a frame that differs in any direction is fitted anew; the
    # kept rotation cannot be written; the store is emptied when full
    monkeypatch.setattr(gyro_check, "_FITS", {})
    monkeypatch.setattr(gyro_check, "FITS_KEPT", 3)
    rng = np.random.default_rng(9)
    R = Rotation.random(random_state=3).as_matrix()
    v = rng.standard_normal((12, 3))
    v /= np.linalg.norm(v, axis=1)[:, None]
    u = v @ R.T + 1e-6 * rng.standard_normal((12, 3))
    first = gyro_check.frame_rotation(v, u)
    again = gyro_check.frame_rotation(v.copy(), u.copy())
    assert again[0] is first[0] and again[1] == first[1]
    assert np.array_equal(first[0], gyro_check._frame_rotation(v, u)[0])
    with pytest.raises(ValueError):
        first[0][0, 0] = 0.0
    u2 = u.copy()
    u2[4, 2] += 1e-7  # one direction moved: its own fit
    other = gyro_check.frame_rotation(v, u2)
    assert other[0] is not first[0]
    assert np.array_equal(other[0], gyro_check._frame_rotation(v, u2)[0])
    assert not np.array_equal(other[0], first[0])
    gyro_check.frame_rotation(v[:6], u[:6])
    assert len(gyro_check._FITS) == 3
    gyro_check.frame_rotation(v[:7], u[:7])  # full: emptied, then this one kept
    assert len(gyro_check._FITS) == 1


def test_watch_gyro_chain_is_the_matmul_chain_bit_for_bit():
    # watch_frame advances the gyro chain with ``ndarray.dot`` (cheaper than ``@`` on 3 x 3):
    # over a long run of frames the chain it records is the ``@`` product's, bit for bit
    rng = np.random.default_rng(7)
    R = Rotation.random(3000, random_state=8).as_matrix()
    R_prior = R @ Rotation.from_rotvec(1e-4 * rng.standard_normal((3000, 3))).as_matrix()
    s = gyro_check.new_watch()
    G = np.eye(3)
    for k in range(3000):
        gyro_check.watch_frame(s, 0.1 * k, np.zeros((0, 3)), np.zeros((0, 3)),
                               R_prior[k] if k else None, R[k])
        if k:
            G = G @ (R[k - 1].T @ R_prior[k])
        assert np.array_equal(s["G_now"], G), k


@pytest.mark.parametrize("fault", [False, True])
def test_watch_frames_of_a_batch_are_the_frame_by_frame_watch_bit_for_bit(fault):
    # a replay's batch (arrays of attitudes, StarFilter.commit_batch) gives the same chain,
    # records, judgements and verdicts as watch_frame frame by frame (a gyro whose steps
    # turn 1.5x the stars' from frame 600 on: the same cause at the same frame)
    rng = np.random.default_rng(11)
    n = 3000
    steps = Rotation.from_rotvec(0.02 * rng.standard_normal((n, 3)))
    R = np.empty((n, 3, 3))
    R[0] = Rotation.random(random_state=4).as_matrix()
    for k in range(1, n):
        R[k] = R[k - 1] @ steps[k].as_matrix()
    gyro = steps.as_rotvec() * np.where(np.arange(n) >= 600, 1.5 if fault else 1.0, 1.0)[:, None]
    R_prior = np.empty_like(R)
    R_prior[0] = R[0]
    R_prior[1:] = R[:-1] @ Rotation.from_rotvec(gyro[1:]).as_matrix()
    t = (0.5 * np.arange(n)).tolist()
    v = rng.standard_normal((n, 8, 3))
    v /= np.linalg.norm(v, axis=2)[..., None]
    u = np.einsum("kij,knj->kni", R, v) + 2e-6 * rng.standard_normal((n, 8, 3))
    one, many = gyro_check.new_watch(), gyro_check.new_watch()
    causes_one = [gyro_check.watch_frame(one, t[k], v[k], u[k], R_prior[k] if k else None, R[k])
                  for k in range(n)]
    causes_many = [gyro_check.watch_frame(many, t[0], v[0], u[0], None, R[0])]
    k = 1
    while k < n:
        stop = min(n, k + int(rng.integers(1, 40)))
        while k < stop:
            nxt, cause = gyro_check.watch_frames(many, t, list(v), list(u), R_prior, R.copy(),
                                                 None, gyro_check._same, k, stop)
            causes_many += [""] * (nxt - k - 1) + [cause]
            k = nxt
    assert causes_many == causes_one
    assert any(causes_one) == fault
    for key in ("t", "R_star", "rms", "G", "segment", "G_now", "R_post"):
        assert np.array_equal(many[key], one[key]), key
    for key in ("frames", "spacing", "result", "done", "since", "judged_at"):
        assert repr(many[key]) == repr(one[key]), key  # (NaN: by its repr)
    assert fault or (len(one["t"]) > 200 and one["spacing"] > gyro_check.LATE_SPACING_S)
