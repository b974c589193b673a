"""A tracker that lags each slew and stays there (``diagnosis.slew_steps``, issue 21 item 3;
unseen case ``backlash``): no library effect is added for it, and the first line names the
jumps at the slews with their size.

psce's 300-s bag (seed 21) with the tracker turned by 8″ about each slew's axis from the
slew's start until the next (``tracker_errors.backlash``): on coord a4ea3be the discovery
added ``time_offset`` (0.20 ms, what a constant lag along the motion looks like within a
slew) and, seed 22, ``gyro_scale_factor`` (−41/−63/−80 ppm: slew by slew a lag kept is a
scale).  Steps of the installation fitted from each slew's start take it all; a gyro
scale error (growing through the slew) or a time offset (nothing at rest) they do not.
doc/benchmarks.md "A lag at each slew".
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from stellar_cal_ros.core.units import ARCSEC
from stellar_cal_ros.diagnosis import slew_steps
from stellar_cal_ros.effects.base import FrameContext

LAG_ARCSEC = 8.0


def test_the_steps_are_one_rotation_whose_variance_grows_at_each_slew(tmp_path):
    """:class:`~.slew_steps.SlewSteps` is 6 states however many slews: the filter adds a
    step's prior variance to the first 3 at each slew's start (the first frame at or after
    it), after copying them into the last 3 (the offset before the step); its rotation is
    the first 3.  Clean 120-s bag, 3 steps: an offset over each slew's interval, each
    within 4σ of zero.  (H289's form: a 3-vector per slew, at most 4.)"""
    from stellar_cal_ros.diagnosis import installation_step
    from stellar_cal_ros.diagnosis.injection import clean_simulation
    from stellar_cal_ros.methods.replay import bag_data_from_simulation, replay

    eff = slew_steps.SlewSteps()
    value = np.array([1e-6, -2e-6, 3e-6, 4e-6, 5e-6, 6e-6])
    ctx = FrameContext(stamp=5.0)
    assert np.allclose(eff.tracker_rotation(value, ctx), value[:3])
    assert np.allclose(eff.tracker_rotation_jacobian(value, ctx),
                       np.hstack([np.eye(3), np.zeros((3, 3))]))
    sim, _ = clean_simulation("psce", False, 21, 120.0)
    t0 = sim.star_frames[0].stamp_ns * 1e-9
    times = [t0 + 30.25, t0 + 60.25, t0 + 90.25]
    prior = slew_steps.with_steps(sim.prior, [{"t_posix": t} for t in times])
    installation_step.register_step(SimpleNamespace(classes=()), slew_steps.SlewSteps)
    got = replay(bag_data_from_simulation(sim), prior, "psce", [slew_steps.STEPS_ID],
                 keep_tables=False)
    block = got.calibration.effects[slew_steps.STEPS_ID]
    assert block["t_posix"] == times
    # three offsets, one over each slew's interval; no lag here: each within 4 sigma of 0
    assert len(block["offsets"]) == 3 and all(o is not None for o in block["offsets"])
    off, sig = np.array(block["offsets"]), np.array(block["offsets_sigma"])
    assert np.all(np.abs(off) < 4 * sig), (off, sig)
    # the sum's sigma before a step ~ the data's, after: the step's prior added
    assert np.all(sig < 0.1 * slew_steps.STEP_SIGMA)


def _table(t: np.ndarray, omega: np.ndarray) -> dict:
    """A residual table of one row per frame (only the columns :func:`slew_starts` reads)."""
    return {"t": t, "frame": np.arange(len(t)), "omega_x": omega[:, 0],
            "omega_y": omega[:, 1], "omega_z": omega[:, 2]}


def test_the_slews_are_found_with_their_axes_and_angles():
    """psce's pattern: 30° at 5°/s about x, y, z every 60 s (300 s at 2 Hz): the window's
    two slews (180, 240 s) and the last before it (120 s), half a frame before their first
    fast frame, axis and angle from the rates."""
    t = np.arange(0.0, 300.0, 0.5)
    omega = np.zeros((len(t), 3))
    axes = [0, 1, 2, 2, 1]
    signs = [1, 1, 1, -1, -1]
    for k, (a, s) in enumerate(zip(axes, signs, strict=True)):
        on = (t >= 60 * k) & (t < 60 * k + 6)
        omega[on, a] = s * np.deg2rad(5.0)
    got = slew_steps.slew_starts(_table(t, omega), np.eye(3), 0.5)
    assert [round(s["t_posix"], 2) for s in got] == [119.75, 179.75, 239.75]
    assert np.allclose([s["axis"] for s in got], [[0, 0, 1], [0, 0, -1], [0, -1, 0]])
    assert np.allclose([s["angle_deg"] for s in got], 30.0)
    # a platform that never rests, or no slew in the window: no steps
    assert slew_steps.slew_starts(_table(t, omega + 0.1), np.eye(3), 0.5) is None
    assert slew_steps.slew_starts(_table(t, omega), np.eye(3), 0.05) is None


def test_a_long_bags_slews_are_all_kept():
    """A 2-h psce-like pattern (a slew every 60 s, x y z −z −y −x): the window's 60 slews
    and the one before it, none dropped (H289: none fitted beyond 4 slews, no test)."""
    t = np.arange(0.0, 7200.0, 0.5)
    omega = np.zeros((len(t), 3))
    for k in range(120):
        on = (t >= 60 * k) & (t < 60 * k + 6)
        omega[on, [0, 1, 2, 2, 1, 0][k % 6]] = (1 if k % 6 < 3 else -1) * np.deg2rad(5.0)
    got = slew_steps.slew_starts(_table(t, omega), np.eye(3), 0.5)
    assert len(got) == 61
    assert round(got[0]["t_posix"], 2) == 3539.75 and round(got[-1]["t_posix"], 2) == 7139.75


def _offsets(slews: list[dict], lags: np.ndarray, sigma: float, seed: int) -> list[dict]:
    """Offsets a tracker lagging slew i by ``lags[i + 1]`` sits at (``lags[0]``: the slew
    before the first), drawn with ``sigma`` (arcsec) per component."""
    rng = np.random.default_rng(seed)
    ab = np.asarray(slews[0]["axis_before"])
    return [{"offset_arcsec": list(lags[i + 1] * np.asarray(s["axis"]) - lags[0] * ab
                                   + rng.normal(0.0, sigma, 3)),
             "offset_sigma_arcsec": [sigma] * 3} for i, s in enumerate(slews)]


def _psce_slews(n: int) -> list[dict]:
    axes = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, -1], [0, -1, 0], [-1, 0, 0]],
                    dtype=float)
    return [{"axis": list(axes[(k + 1) % 6]), "axis_before": list(axes[k % 6])}
            for k in range(n)]


def test_one_lag_and_each_slews_own():
    """:func:`~.slew_steps.lag` on drawn offsets (σ 0.3″ per component, 25 slews): one lag
    of −8″ is found within 4σ (seeds 0–9); lags drawn −8 ± 3″ per slew are each found
    within 4σ."""
    slews = _psce_slews(25)
    sig = 0.3
    for seed in range(10):
        got = slew_steps.lag(_offsets(slews, np.full(26, -8.0), sig, seed), slews)
        assert abs(got["lag_arcsec"] + 8.0) < 4 * got["lag_sigma_arcsec"], got
    lags = -8.0 + 3.0 * np.random.default_rng(99).standard_normal(26)
    got = slew_steps.lag(_offsets(slews, lags, sig, 5), slews)
    each = np.array(got["lags_arcsec"])
    assert np.all(np.abs(each - lags) < 4 * np.array(got["lags_sigma_arcsec"])), (each, lags)


def test_a_lag_at_each_slew_is_no_library_effect_and_is_said_first(tmp_path):
    """Fails on coord a4ea3be (``time_offset`` added, 0.20 ms; no line names the slews)."""
    from stellar_cal_ros.diagnosis.auto import discover
    from stellar_cal_ros.diagnosis.injection import clean_simulation
    from stellar_cal_ros.methods.replay import bag_data_from_simulation
    from stellar_cal_ros.sim import tracker_errors

    sim, model = clean_simulation("psce", False, 21, 300.0)
    tracker_errors.backlash(sim, LAG_ARCSEC)
    got = discover(bag_data_from_simulation(sim), sim.prior, "psce", model, tmp_path,
                   candidates=["gyro_scale_factor", "time_offset"], plots=False,
                   verbose=False, workers=0)
    assert got["added"] == [], got["added"]
    first = got["unexplained"][0]
    assert first["component"] == slew_steps.COMPONENT, got["unexplained"]
    assert "not a library effect" in first["regressor"]
    got_lag = first["detail"]["slew_steps"]
    # the lag (truth -8"): since H297 the filter's one-lag nuisance (``SlewLag``), within 4
    # sigma (seed 21: -7.93 +- 0.14"; H289's from the steps, 8.1 +- 0.1", was held to 20 %)
    assert abs(got_lag["lag_arcsec"] + LAG_ARCSEC) < 4 * got_lag["lag_sigma_arcsec"], got_lag
    assert got_lag["lag_sigma_arcsec"] < 0.3, got_lag
    assert "lags each slew by" in first["regressor"]
    # one lag: not said to differ from slew to slew (its test: p 1 here)
    assert "differs from slew to slew" not in first["regressor"]
    assert len(got_lag["steps"]) == 3 and len(got_lag["lags_arcsec"]) == 4, got_lag
    px = LAG_ARCSEC * ARCSEC * sim.prior.camera.fx
    assert abs(first["change_px"] - px) < 4 * got_lag["lag_sigma_arcsec"] * ARCSEC * \
        sim.prior.camera.fx, (first["change_px"], px)


def test_a_lag_at_many_slews_is_fitted_by_the_filter():
    """600 s of psce (9 slews; 5 in the window and the one before it: more than H289's 4,
    no test on main 6c738a9) with the 8″ backlash: the steps (6 states) give an offset over
    each of the 6 slews' intervals, λ (a_i − a_b) from the installation before; the one-lag
    run (``SlewLag``) finds λ = −8″ within 4σ (seed 21: offsets 0.7–3.3″ off, λ −7.91″
    from them, −7.93 ± 0.07″ from the filter)."""
    from stellar_cal_ros.diagnosis import installation_step
    from stellar_cal_ros.diagnosis.injection import clean_simulation
    from stellar_cal_ros.methods.replay import bag_data_from_simulation, replay
    from stellar_cal_ros.sim import tracker_errors

    sim, model = clean_simulation("psce", False, 21, 600.0)
    tracker_errors.backlash(sim, LAG_ARCSEC)
    data = bag_data_from_simulation(sim)
    base = replay(data, sim.prior, "psce", list(model))
    slews = slew_steps.slew_starts(base.residuals, sim.prior.R_imu_st, 0.5)
    assert len(slews) == 6, [s["t_posix"] for s in slews]
    for cls in (slew_steps.SlewSteps, slew_steps.SlewLag):
        installation_step.register_step(SimpleNamespace(classes=()), cls)
    steps = replay(data, slew_steps.with_steps(sim.prior, slews), "psce",
                   list(model) + [slew_steps.STEPS_ID], keep_tables=False)
    got = slew_steps.fitted(steps.calibration.effects[slew_steps.STEPS_ID], slews)
    assert got is not None and len(got) == 6
    # each offset λ (a_i − a_b): within 4″ of it (the filter's catch-up on each jump
    # scatters them: seed 21 at most 3.3″ off), and λ fitted to them within 10 %
    want = [-LAG_ARCSEC * (np.subtract(s["axis"], slews[0]["axis_before"])) for s in slews]
    off = np.linalg.norm(np.array([s["offset_arcsec"] for s in got]) - np.array(want), axis=1)
    assert np.all(off < 0.5 * LAG_ARCSEC), off
    fit = slew_steps.lag(got, slews)
    assert abs(fit["lag_arcsec"] + LAG_ARCSEC) < 0.1 * LAG_ARCSEC, fit
    one = replay(data, slew_steps.with_lag(sim.prior, slews), "psce",
                 list(model) + [slew_steps.LAG_ID], keep_tables=False)
    lam = one.calibration.effects[slew_steps.LAG_ID]["lag"] / ARCSEC
    sig = one.calibration.sigma["effects"][slew_steps.LAG_ID]["lag"] / ARCSEC
    assert abs(lam + LAG_ARCSEC) < 4 * sig and sig < 0.2, (lam, sig)
