"""Calibrator fed message by message (the live node's way) equals the replay of the bag.

The reference is ``replay_psce`` over a simulated 120 s bag.  The same messages are streamed
in log-time order, shuffled within the reorder window, and with a checkpoint / restore half
way; all must give the replay's calibration to ~1e-9.
"""

from __future__ import annotations

import dataclasses
import random
from pathlib import Path

import numpy as np
import pytest
from sim_bags import psce_bag

from stellar_cal_ros.errors import CheckpointError
from stellar_cal_ros.io.bag import BagReader
from stellar_cal_ros.io.calibration import calibration_to_dict, load_calibration
from stellar_cal_ros.methods.checkpoint import load_checkpoint, save_checkpoint
from stellar_cal_ros.methods.driver import Calibrator, DriverConfig
from stellar_cal_ros.methods.frames import (
    TOPIC_AIR_TEMPERATURE,
    TOPIC_FIX,
    TOPIC_HEAD_TEMPERATURE,
    TOPIC_IMU,
    TOPIC_PRESSURE,
    TOPIC_STARS,
)
from stellar_cal_ros.methods.psce import FilterCounters, PsceConfig
from stellar_cal_ros.methods.replay import replay_psce

EXCERPT_S = 120.0
WINDOW_S = 0.2


def bag_events(path: Path) -> list[tuple[int, int, str, object]]:
    """Every message of the bag as (log time, index, kind, payload), log-time order."""
    ev: list[tuple[int, int, str, object]] = []
    with BagReader(path) as r:
        topics = r.topics()
        imu = r.read_imu(TOPIC_IMU)
        for i in range(len(imu.stamp_ns)):
            ev.append((int(imu.log_time_ns[i]), 0, "imu",
                       (int(imu.stamp_ns[i]), imu.angular_velocity[i], imu.frame_id)))
        for f in r.read_star_frames(TOPIC_STARS):
            ev.append((int(f.log_time_ns), 1, "stars", f))
        if TOPIC_FIX in topics:
            fx = r.read_navsat(TOPIC_FIX)
            for i in range(len(fx.stamp_ns)):
                ev.append((int(fx.log_time_ns[i]), 2, "fix",
                           (int(fx.stamp_ns[i]), fx.latitude_deg[i], fx.longitude_deg[i],
                            fx.altitude_m[i], int(fx.status[i]))))
        for kind, topic in (("head", TOPIC_HEAD_TEMPERATURE), ("air", TOPIC_AIR_TEMPERATURE),
                            ("pressure", TOPIC_PRESSURE)):
            if topic in topics:
                s = r.read_scalar(topic)
                for i in range(len(s.stamp_ns)):
                    ev.append((int(s.log_time_ns[i]), 3, kind,
                               (int(s.stamp_ns[i]), float(s.value[i]))))
    ev.sort(key=lambda e: (e[0], e[1]))
    return ev


def feed(cal: Calibrator, events) -> list:
    """Push ``(log time, index, kind, payload)`` events; kind ``imu_block``: (stamps, rates)."""
    out = []
    for _, _, kind, p in events:
        if kind == "imu":
            out += cal.push_imu(p[0], p[1], frame_id=p[2])
        elif kind == "imu_block":
            out += cal.push_imu_block(p[0], p[1], frame_id="imu_link")
        elif kind == "stars":
            out += cal.push_stars(p)
        elif kind == "fix":
            out += cal.push_fix(*p)
        else:
            out += cal.push_scalar(kind, *p)
    return out


def shuffled(events, window_s: float, seed: int = 7):
    """Arrival order: each message delayed by a random fraction of the window."""
    rng = random.Random(seed)
    delayed = [(e[0] + int(rng.uniform(0.0, 0.9 * window_s) * 1e9), k, e)
               for k, e in enumerate(events)]
    delayed.sort(key=lambda d: (d[0], d[1]))
    return [d[2] for d in delayed]


def assert_same(online, offline, rtol=1e-9):
    a, b = calibration_to_dict(online), calibration_to_dict(offline)
    a.pop("extra", None)
    for d in (a, b):  # statistics over an evaluation window (the live run has none) and
        for key in ("consistency", "covariance_file", "provenance"):  # file bookkeeping
            d.pop(key, None)

    def walk(x, y, where):
        if isinstance(x, dict):
            assert set(x) == set(y), where
            for k in x:
                walk(x[k], y[k], f"{where}.{k}")
        elif isinstance(x, list):
            assert len(x) == len(y), where
            for i, (u, v) in enumerate(zip(x, y, strict=True)):
                walk(u, v, f"{where}[{i}]")
        elif isinstance(x, float):
            assert x == pytest.approx(y, rel=rtol, abs=1e-300), where
        else:
            assert x == y, where

    walk(a, b, "cal")


@pytest.fixture(scope="module")
def excerpt(tmp_path_factory):
    path, prior_path, _ = psce_bag(EXCERPT_S)
    prior = load_calibration(prior_path)
    ref = replay_psce(path, prior, config=live_psce())
    return path, prior, ref, bag_events(path)


def live_psce() -> PsceConfig:
    """The live filter's settings: the replay's defaults (fast propagation included)."""
    return PsceConfig()


def make(prior, window=WINDOW_S, effects=None):
    return Calibrator(prior, "psce", effects, PsceConfig(),
                      DriverConfig(reorder_window_s=window))


def test_time_order_equals_replay(excerpt):
    _, prior, ref, events = excerpt
    cal = make(prior, window=0.0)
    outcomes = feed(cal, events) + cal.finish()
    assert cal.filter_counters()["updates"] == ref.counters["updates"] > 100
    fc = cal.filter_counters()
    for k in vars(FilterCounters()):
        if k != "extra":
            assert fc[k] == ref.counters[k], k
    assert sum(o.status == "updated" for o in outcomes) == ref.counters["updates"]
    assert_same(cal.calibration(), ref.calibration)
    d1 = cal.calibration().extra["derived"]["equivalent_principal_point_px"]
    assert d1 == pytest.approx(ref.derived["equivalent_principal_point_px"], rel=1e-9)
    # the IMU history the filter holds stays bounded
    assert len(cal.filter.imu_t) < 2 * 4096 + 200


def test_shuffled_within_window_equals_replay(excerpt):
    _, prior, ref, events = excerpt
    arrival = shuffled(events, WINDOW_S)
    assert arrival != events
    cal = make(prior)
    feed(cal, arrival)
    cal.finish()
    c = cal.counters
    assert c.imu_late == c.frames_late == c.imu_duplicate == 0
    assert cal.filter_counters()["updates"] == ref.counters["updates"]
    assert_same(cal.calibration(), ref.calibration)


def test_effect_needing_temperature_waits_for_it(excerpt):
    """thermal_focal_length needs the head temperature interpolated at the frame stamp."""
    path, prior, _, events = excerpt
    ref = replay_psce(path, prior, ["thermal_focal_length"], config=live_psce())
    cal = make(prior, effects=["thermal_focal_length"])
    feed(cal, shuffled(events, WINDOW_S, seed=11))
    cal.finish()
    # only the last frames, after the last temperature sample of the excerpt, wait in vain
    assert cal.counters.env_stale <= 2
    assert_same(cal.calibration(), ref.calibration)


def test_checkpoint_half_way_resumes_without_loss(excerpt, tmp_path):
    _, prior, ref, events = excerpt
    arrival = shuffled(events, WINDOW_S, seed=3)
    half = len(arrival) // 2
    first = make(prior)
    feed(first, arrival[:half])
    ck = tmp_path / "state" / "calibrator.npz"
    save_checkpoint(first, ck)
    assert ck.exists() and not list(ck.parent.glob("*.tmp"))
    second = make(prior)
    load_checkpoint(second, ck)
    assert second.pending() == first.pending()
    feed(second, arrival[half:])
    second.finish()
    feed(first, arrival[half:])
    first.finish()
    np.testing.assert_array_equal(second.filter.theta, first.filter.theta)
    np.testing.assert_array_equal(second.filter.P, first.filter.P)
    assert second.filter_counters() == first.filter_counters()
    assert_same(second.calibration(), ref.calibration)


def test_resumed_driver_drops_what_it_has(excerpt, tmp_path):
    """The node's restart after a kill: the checkpoint of the first k messages, then the
    WHOLE stream again; what the checkpoint holds is dropped (late or duplicate, counted),
    the rest used: the uninterrupted replay's result at every cut point (mid-window,
    beside a star frame, with IMU pending in the reorder window)."""
    _, prior, ref, events = excerpt
    arrival = shuffled(events, WINDOW_S, seed=5)
    n = len(arrival)
    stars = [i for i, e in enumerate(arrival) if e[2] == "stars"]
    for cut in (n // 3, n // 2, stars[len(stars) // 2], stars[len(stars) // 2] + 1, n - 7):
        first = make(prior)
        feed(first, arrival[:cut])
        ck = tmp_path / f"ck{cut}.npz"
        save_checkpoint(first, ck)
        second = make(prior)
        load_checkpoint(second, ck)
        feed(second, arrival)
        second.finish()
        c, c1 = second.counters, first.counters
        assert c.frames_received == c1.frames_received + len(stars)
        # the frames the first process had, released or pending, come back as already had
        assert c.frames_late + c.frames_duplicate == c1.frames_received, cut
        assert second.filter_counters()["updates"] == ref.counters["updates"], cut
        assert_same(second.calibration(), ref.calibration)


def test_checkpoint_of_another_model_is_refused(excerpt, tmp_path):
    _, prior, _, events = excerpt
    cal = make(prior)
    feed(cal, events[:500])
    ck = tmp_path / "ck.npz"
    save_checkpoint(cal, ck)
    other = make(prior, effects=["radial_k3"])
    with pytest.raises(CheckpointError, match="another model"):
        load_checkpoint(other, ck)
    (tmp_path / "junk.npz").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError):
        load_checkpoint(make(prior), tmp_path / "junk.npz")


def test_garbage_is_counted_not_fatal(excerpt):
    _, prior, ref, events = excerpt
    cal = make(prior)
    feed(cal, events[:3000])
    cal.push_imu(events[2990][3][0] if events[2990][2] == "imu" else 1, [np.nan, 0, 0])
    cal.push_imu(10, [0.0, 0.0, 0.0])  # far too old
    cal.push_imu(2_000_000_000_000_000_000, [0, 0, 0], frame_id="somewhere_else")
    cal.push_scalar("head", 5, float("nan"))
    cal.push_fix(5, float("nan"), 0.0, 0.0)
    frame = next(p for _, _, k, p in events[3000:] if k == "stars")
    empty = dataclasses.replace(frame, stamp_ns=frame.stamp_ns + 1, catalog_id=frame.catalog_id[:0],
                                right_ascension=frame.right_ascension[:0],
                                declination=frame.declination[:0], uv=frame.uv[:0],
                                magnitude=frame.magnitude[:0], sigma=frame.sigma[:0])
    nan_uv = dataclasses.replace(frame, stamp_ns=frame.stamp_ns + 2, uv=frame.uv * np.nan)
    wrong = dataclasses.replace(frame, stamp_ns=frame.stamp_ns + 3, frame_id="camera")
    for f in (empty, nan_uv, wrong):
        cal.push_stars(f)
    feed(cal, [e for e in events[3000:]])
    cal.finish()
    c = cal.counters
    assert c.imu_invalid >= 1 and c.imu_late >= 1 and c.imu_wrong_frame == 1
    assert c.env_invalid == 1 and c.fixes_invalid == 1 and c.frames_wrong_frame == 1
    assert cal.filter_counters()["stars_invalid"] >= len(frame.uv)
    assert cal.filter_counters()["updates"] >= ref.counters["updates"] - 3


def test_site_and_environment_caches_follow_the_inputs(excerpt, tmp_path):
    """Site median (kept as an array, bounded by max_fixes) and interpolation caches."""
    _, prior, _, _ = excerpt
    cal = Calibrator(prior, "psce", None, PsceConfig(), DriverConfig(max_fixes=50))
    rng = np.random.default_rng(5)
    fixes = [(1_000_000_000 * (i + 1), *rng.normal([45.0, 7.0, 100.0], [1e-3, 1e-3, 5.0]))
             for i in range(120)]
    for i, f in enumerate(fixes):
        cal.push_fix(*f)
        tail = np.asarray([g[1:] for g in fixes[max(0, i + 1 - 50): i + 1]])
        s = cal.site
        assert (s.latitude_deg, s.longitude_deg, s.height_m) == tuple(
            float(x) for x in np.median(tail, axis=0))
    head = cal.env["head"]
    for t, v in ((3, 20.0), (1, 10.0), (2, np.nan), (5, 30.0)):  # out of order, a NaN
        cal.push_scalar("head", t * 1_000_000_000, v)
        st = np.asarray(head.stamp_ns)
        val = np.asarray(head.value)
        ok = np.isfinite(val)
        ref = head.ref_ns
        for q in (0.5, 2.5, 4.0, 9.0):
            expect = float(np.interp((q * 1e9 - ref) * 1e-9, (st[ok] - ref) * 1e-9, val[ok]))
            assert head.interp(int(q * 1e9)) == expect
    save_checkpoint(cal, tmp_path / "c.npz")
    back = Calibrator(prior, "psce", None, PsceConfig(), DriverConfig(max_fixes=50))
    load_checkpoint(back, tmp_path / "c.npz")
    assert back.site == cal.site
    assert back.env["head"].interp(2_500_000_000) == head.interp(2_500_000_000)
    extra = (200_000_000_000, 45.5, 7.5, 90.0)
    back.push_fix(*extra)
    tail = np.asarray([g[1:] for g in fixes[-49:]] + [extra[1:]])
    assert back.site.latitude_deg == float(np.median(tail[:, 0]))


def _batch_events(events, damage: bool):
    """The events with consecutive IMU samples in blocks (a replay's reading), optionally
    damaged: a block sent twice, a late sample, a clock jump back, a non-finite sample."""
    out: list = []
    run: list = []

    def close() -> None:
        if run:
            out.append((0, 0, "imu_block", (np.array([p[0] for p in run], dtype=np.int64),
                                             np.array([p[1] for p in run], dtype=float))))
            run.clear()

    for _, _, kind, p in events:
        if kind == "imu":
            run.append(p)
            if len(run) >= 23:  # blocks cut also by size, as a chunk's end cuts them
                close()
            continue
        close()
        out.append((0, 0, kind, p))
    close()
    if damage:  # from the end, so that the positions found stay valid
        imu = [k for k, e in enumerate(out) if e[2] == "imu_block"]
        at = [imu[len(imu) * q // 5] for q in (1, 2, 3, 4)]
        t, w = out[at[3]][3]
        w = w.copy()
        w[3] = np.nan
        out[at[3]] = (0, 0, "imu_block", (t, w))
        t, w = out[at[2]][3]  # the clock jumps back 20 s
        out.insert(at[2] + 1, (0, 0, "imu_block", (t - 20 * 10**9, w)))
        t, w = out[at[1]][3]  # late by 0.3 s (within the window) and by 1.5 s (beyond)
        out.insert(at[1] + 1, (0, 0, "imu_block", (t[:2] - [3 * 10**8, 15 * 10**8], w[:2])))
        t, w = out[imu[imu.index(at[0]) - 10]][3]  # resent ~2 s later: duplicates
        out.insert(at[0] + 1, (0, 0, "imu_block", (t.copy(), w.copy())))
    return out


@pytest.mark.parametrize("damage", [False, True])
def test_replay_driver_deferred_imu_release_changes_nothing(excerpt, tmp_path, monkeypatch,
                                                            damage):
    """A replay's driver leaves the IMU release of in-order blocks for later
    (Calibrator._defer_release): outcomes, counters and estimates are those of the driver
    that releases at every block, on damaged input and across a checkpoint too."""
    _, prior, _, events = excerpt
    blocks = _batch_events(events, damage)

    def run(defer: bool, checkpoint: bool):
        drv = DriverConfig(reorder_window_s=1.0, batch_frames=True, imu_batch=300,
                           max_pending_frames=1_000_000)
        cal = Calibrator(prior, "psce", None, PsceConfig(), drv)
        if not defer:
            monkeypatch.setattr(cal, "_defer_release", lambda *a: False)
        half = len(blocks) // 2
        out = feed(cal, blocks[:half])
        if checkpoint:
            save_checkpoint(cal, tmp_path / "ck.npz")
            cal = Calibrator(prior, "psce", None, PsceConfig(), drv)
            load_checkpoint(cal, tmp_path / "ck.npz")
        out += feed(cal, blocks[half:]) + cal.finish()
        return cal, [(o.stamp_ns, o.status) for o in out]

    ref, ref_out = run(False, False)
    assert sum(s == "updated" for _, s in ref_out) > 100
    if damage:
        c = ref.counters
        assert c.imu_duplicate and c.imu_late and c.imu_clock_jumps and c.imu_invalid
    for checkpoint in (False, True):
        cal, out = run(True, checkpoint)
        assert out == ref_out
        assert cal.all_counters() == ref.all_counters()
        np.testing.assert_array_equal(cal.filter.theta, ref.filter.theta)
        np.testing.assert_array_equal(cal.filter.P, ref.filter.P)


def test_deferred_checks_leave_the_frame_updates_and_count_the_same(excerpt, monkeypatch):
    """The live node's driver (defer_checks) runs the covariance check in run_checks, not in
    a frame's update; the estimates and, once finished, every count are the driver's
    without it."""
    from stellar_cal_ros.methods.kernel import StarFilter

    _, prior, _, events = excerpt
    ref = make(prior)
    feed(ref, events)
    ref.finish()
    cal = Calibrator(prior, "psce", None, PsceConfig(),
                     DriverConfig(reorder_window_s=WINDOW_S, defer_checks=True))
    where: list[str] = []
    check = StarFilter._check_covariance
    monkeypatch.setattr(StarFilter, "_check_covariance",
                        lambda self: (where.append(phase[0]), check(self)))
    phase = ["update"]
    for k in range(0, len(events), 500):
        phase[0] = "update"
        feed(cal, events[k:k + 500])
        phase[0] = "timer"
        cal.run_checks()
    phase[0] = "finish"
    cal.finish()
    assert where and "update" not in where and where.count("timer") >= 1
    assert cal.all_counters() == ref.all_counters()
    assert cal.filter_counters()["covariance_checks"] == ref.filter.counters.updates // 50 > 1
    np.testing.assert_array_equal(cal.filter.theta, ref.filter.theta)
    np.testing.assert_array_equal(cal.filter.P, ref.filter.P)


def test_imu_blocks_handed_over_are_queued_without_a_copy_others_are_copied(excerpt):
    """``push_imu_block(..., owned=True)`` (a replay's decoded blocks) is held as it is; a
    caller's block (``owned`` False: the live node may reuse its buffer) is copied, so
    writing to it afterwards changes nothing pending."""
    from stellar_cal_ros.methods.imu_queue import ImuQueue

    q = ImuQueue()
    t = np.arange(1, 6, dtype=np.int64) * 10_000_000
    w, f = np.ones((5, 3)), np.zeros((5, 3))
    q.push(t, w, f)
    t2, w2, f2 = t + 50_000_000, 2 * w, f.copy()
    q.push(t2, w2, f2, True, copy=False)
    assert q._blocks[1][0] is t2 and q._blocks[1][1] is w2
    t[:] = 0
    w[:] = 9.0
    assert np.array_equal(q.t, np.concatenate([np.arange(1, 6) * 10_000_000, t2]))
    assert np.array_equal(q.w[:5], np.ones((5, 3)))
    # through the driver (nothing released yet: all of it pending)
    prior = excerpt[1]
    for owned in (False, True):
        cal = Calibrator(prior, "psce", None, PsceConfig(), DriverConfig(reorder_window_s=1.0))
        t = np.arange(1, 6, dtype=np.int64) * 10_000_000
        w, f = np.full((5, 3), 0.01), np.zeros((5, 3))
        cal.push_imu_block(t, w, f, owned=owned)
        assert np.shares_memory(cal._imu._blocks[0][1], w) == owned
        if not owned:
            w[:] = 9.0
        assert np.array_equal(cal._imu.w, np.full((5, 3), 0.01))


def test_bulk_environment_and_fix_pushes_are_those_one_at_a_time(excerpt):
    """``push_scalars`` / ``push_fixes`` (a replay's release of rows in one call) leave the
    driver as ``push_scalar`` / ``push_fix`` of each in their order do — counts, each series
    (values, order, interpolation origin), the site, what comes back — in bulk when none of
    them could pump, one at a time when one could (fixes before the filter starts; a thermal
    effect's frames wait for the head temperature)."""
    _, prior, _, events = excerpt
    rng = np.random.default_rng(3)
    t = events[2999][0]
    s = 10**9
    batches = [  # (kind, stamps, values): in order with a NaN and a stamp 0; in order after
        # the held ones; out of order (the one-at-a-time insertion); empty
        ("head", [t - 5 * s, t - 4 * s, 0, t - 2 * s], [20.0, np.nan, 21.0, 22.0]),
        ("air", [t + s, t + 2 * s], [3.0, 4.0]),
        ("head", [t + 3 * s, t + 4 * s], [23.0, 24.0]),
        ("head", [t + 6 * s, t - 3 * s, t + 5 * s], [26.0, 21.5, np.inf]),
        ("pressure", [], [])]
    lat, lon, alt = rng.normal([45.0, 7.0, 100.0], [1e-3, 1e-3, 5.0], (6, 3)).T
    lat[2] = np.nan
    fixes = (np.arange(6) * s + t, lat, lon, alt, np.array([0, 0, 0, -1, 0, 2]))
    for effects, started in ((None, True), (None, False), (["thermal_focal_length"], True)):
        one, bulk = make(prior, effects=effects), make(prior, effects=effects)
        if started:
            feed(one, events[:3000])
            feed(bulk, events[:3000])
        quiet = started and effects is None
        if quiet:  # nothing could pump: the bulk calls never take the one-at-a-time path
            bulk.push_scalar = bulk.push_fix = lambda *a: pytest.fail("not in bulk")
        before = dataclasses.asdict(one.counters)
        held = len(one.env["head"].stamp_ns)
        got, want = [], []
        for kind, st, v in batches:
            want += [o for a in zip(st, v, strict=True) for o in one.push_scalar(kind, *a)]
            got += bulk.push_scalars(kind, np.array(st, dtype=np.int64), np.array(v))
        want += [o for row in zip(*(np.asarray(a).tolist() for a in fixes), strict=True)
                 for o in one.push_fix(*row)]
        got += bulk.push_fixes(*fixes)
        assert got == want
        assert dataclasses.asdict(bulk.counters) == dataclasses.asdict(one.counters)
        after = dataclasses.asdict(one.counters)
        assert [after[k] - before[k] for k in ("env_received", "env_invalid", "fixes_received",
                                               "fixes_invalid")] == [11, 3, 6, 2]
        for kind in ("head", "air", "pressure"):
            a, b = one.env[kind], bulk.env[kind]
            assert (b.stamp_ns, b.value, b.ref_ns) == (a.stamp_ns, a.value, a.ref_ns), kind
            assert all(type(x) is int for x in b.stamp_ns) and \
                all(type(x) is float for x in b.value)
        assert len(one.env["head"].stamp_ns) == held + 6
        assert started or one.env["head"].ref_ns == t - 5 * s
        assert bulk.sites.stamp_ns == one.sites.stamp_ns and bulk.site == one.site
        assert np.array_equal(bulk.sites.values, one.sites.values)
