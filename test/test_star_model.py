"""StarModel: effects composed into the star measurement and gyro models.

Every column of ``H_parameters`` and ``H_attitude`` is checked against central finite
differences of ``uv`` (attitude perturbed on the left, ``Exp(φ) · R_i_b``), with all effects
at once and with subsets; the truth calibration reproduces noise-free simulated centroids;
``corrected_rates`` inverts the sensor model; a user effect loads from a file.
"""

from __future__ import annotations

import copy
import textwrap

import numpy as np
import pytest

from stellar_cal_ros.core.catalog import load_catalog, radec_to_unit
from stellar_cal_ros.core.earth import Site
from stellar_cal_ros.core.rotation import so3_exp
from stellar_cal_ros.effects import registry
from stellar_cal_ros.effects.base import FrameContext, Stage
from stellar_cal_ros.errors import ModelError
from stellar_cal_ros.methods.star_model import StarModel
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import default_prior_sigma, simulate

T0 = 1795348800.0
SITE = Site(36.07, 120.38, 10.0)
OMEGA = np.array([0.02, -0.05, 0.08])
OFFSETS = np.array([2.0, -3.0, 2.5, -1.5, 3.0, -2.0, 1.7, -2.6, 2.2])
BASELINE = ["installation", "focal_length", "principal_point", "radial_k1k2", "tangential",
            "gyro_bias"]
SUBSETS = {
    "all": registry.available(),
    "psce_baseline": BASELINE,
    "baseline+time+astrometry": BASELINE + ["time_offset", "aberration", "refraction",
                                            "proper_motion"],
    "camera_chain": ["focal_length", "pixel_aspect", "thermal_focal_length", "radial_k3",
                     "image_plane_tilt", "time_offset"],
    # the prior's effects block fixes thermal_focal_length and aberration (not estimated)
    "with_fixed_prior_effects": BASELINE + ["pixel_aspect", "time_offset"],
}


def _noise_free(name="psce_rotations"):
    sc = get_scenario(name)
    sc.centroid_noise_px = sc.gyro_arw_deg_sqrth = sc.accel_vrw_mps_sqrth = 0.0
    return sc


@pytest.fixture(scope="module")
def sim():
    return simulate(_noise_free(), duration=110.0, seed=3)


@pytest.fixture(scope="module")
def stars(sim):
    frame = min(sim.star_frames, key=lambda f: abs(f.stamp_ns * 1e-9 - T0 - 100.0))
    ids = frame.catalog_id.astype(np.int64)
    cat = load_catalog(mag_limit=None)
    return ids, cat.subset(cat.index_of(ids)).directions(2000.0)


def make_ctx(ids, stamp=T0 + 100.0, head=25.0) -> FrameContext:
    return FrameContext(stamp=stamp, catalog_id=ids, site=SITE, head_temperature_c=head,
                        air_temperature_c=5.0, pressure_pa=101200.0, omega_b=OMEGA.copy())


def rotating_attitude(R0, t_ref, omega=OMEGA, phi=None):
    """``s -> (Exp(φ) R0 Exp(ω s), ω)``: ``s`` seconds after the stamp ``t_ref``."""
    L = np.eye(3) if phi is None else so3_exp(phi)
    return lambda s: (L @ R0 @ so3_exp(omega * s), omega)


def theta_of(model: StarModel) -> np.ndarray:
    reps = int(np.ceil(model.size / OFFSETS.size)) + 1
    return model.initial_value + np.tile(OFFSETS, reps)[: model.size] * model.initial_sigma


# ------------------------------------------------------------------ measurement Jacobians
@pytest.mark.parametrize("subset", list(SUBSETS))
def test_predict_jacobians_match_finite_differences(subset, sim, stars):
    ids, u_i = stars
    prior = sim.prior
    if subset == "with_fixed_prior_effects":
        prior = copy.deepcopy(prior)
        prior.effects = {"thermal_focal_length": {"coefficient_per_c": 3e-5,
                                                  "reference_temperature_c": 18.0},
                         "aberration": {"scale": 1.0}}
    model = StarModel(registry.create_many(SUBSETS[subset]), prior)
    assert len(model.fixed_effects) == len(prior.effects)
    theta = theta_of(model)
    ctx = make_ctx(ids)
    R0 = sim.truth_world.R_i_b(np.array([100.0]))[0]
    att = rotating_attitude(R0, ctx.stamp)
    # the model's first frame is the run's start (its prior's stamp): clock_drift counts its
    # rate from there, not from this frame 100 s later (effects.clock_drift.START_LEAD)
    start = float(prior.stamp) + 0.5
    model.predict(theta, u_i, make_ctx(ids, stamp=start), rotating_attitude(R0, start))
    pred = model.predict(theta, u_i, ctx, att)
    n = len(u_i)
    assert pred.uv.shape == (n, 2) and pred.H_attitude.shape == (n, 2, 3)
    assert pred.H_parameters.shape == (n, 2, model.size)
    assert np.all(np.isfinite(pred.uv)) and np.all(pred.directions_st[:, 2] > 0.9)
    again = model.predict(theta, u_i, ctx, att)  # camera chain and column mask reused
    assert np.array_equal(again.H_parameters, pred.H_parameters)

    def uv(th, phi=None):
        return model.predict(th, u_i, ctx, rotating_attitude(R0, ctx.stamp, phi=phi)).uv

    names = model.parameter_names()
    stages = [e.stage for e in model.effects for _ in range(e.size)]
    for k, sigma in enumerate(model.initial_sigma):
        stage = stages[k]
        h = 1e-3 * sigma
        # The exposure time is POSIX seconds in float64 (quantum 2.4e-7 s at 1.8e9 s): a
        # time step needs to be large, and the difference quotient carries quantum/h.
        time_tol = 0.0
        if stage is Stage.TIME:
            # a 10-ms shift of the exposure (a clock's rate: over its stamp's distance from
            # the reference stamp)
            lever = max(abs(model.time_shift(theta, ctx)[1][k]), 1.0)  # s of shift a unit
            h = 1e-2 / lever
            time_tol = 2.0 * np.spacing(ctx.stamp) / (h * lever)
        e = np.zeros(model.size)
        e[k] = h
        fd = (uv(theta + e) - uv(theta - e)) / (2 * h)
        # px per 1-sigma change of the parameter: 1e-6 relative, or 1e-7 px absolute
        err = np.max(np.abs(pred.H_parameters[:, :, k] - fd)) * sigma
        scale = np.max(np.abs(fd)) * sigma
        assert err <= max((1e-6 + time_tol) * scale, 1e-7), \
            f"{names[k]}: {err:.2e} px of {scale:.2e} px"
        if stage in (Stage.GYRO, Stage.ACCEL):
            assert not np.any(pred.H_parameters[:, :, k])
        else:
            assert scale > 1e-4, f"{names[k]} does not move the stars"
    h = 1e-6
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        fd = (uv(theta, e) - uv(theta, -e)) / (2 * h)
        err = np.max(np.abs(pred.H_attitude[:, :, k] - fd))
        assert err <= 1e-6 * np.max(np.abs(fd)), f"attitude {k}: {err:.2e}"


def test_time_offset_jacobian_is_the_rate(sim, stars):
    """∂uv/∂Δt = H_attitude · (R_i_b ω): a time shift is a rotation by ω Δt."""
    ids, u_i = stars
    model = StarModel(registry.create_many(["time_offset"]), sim.prior)
    ctx = make_ctx(ids)
    R0 = sim.truth_world.R_i_b(np.array([100.0]))[0]
    pred = model.predict(np.array([0.04]), u_i, ctx, rotating_attitude(R0, ctx.stamp))
    R = R0 @ so3_exp(OMEGA * 0.04)
    np.testing.assert_allclose(pred.H_parameters[:, :, 0], pred.H_attitude @ (R @ OMEGA),
                               rtol=1e-12, atol=1e-9)
    assert pred.t_exposure == ctx.stamp + 0.04


def test_the_exposure_shift_builds_a_context_only_for_a_time_effect(sim, stars):
    """The one no-time-effect rule: the prior's offset, and a lazy context never built."""
    ctx = make_ctx(stars[0])
    built = []

    def lazy():
        built.append(ctx)
        return ctx

    plain = StarModel(registry.create_many(BASELINE), sim.prior)
    theta = theta_of(plain)
    assert plain.exposure_shift(theta, lazy) == plain.time_shift(theta, ctx)[0] \
        == sim.prior.time_offset
    assert not built
    timed = StarModel(registry.create_many(["time_offset"]), sim.prior)
    assert timed.exposure_shift(np.array([0.04]), lazy) == pytest.approx(0.04, abs=1e-15)
    assert built == [ctx]


def test_subset_prediction_with_a_shared_context(sim, stars):
    """A subset u_i[mask] predicted with the same context (as the filters do) is exact."""
    ids, u_i = stars
    model = StarModel(registry.create_many(["aberration", "refraction", "proper_motion"]),
                      sim.prior)
    theta = np.array([0.9, 1.1, 1.0])
    ctx = make_ctx(ids)
    att = rotating_attitude(sim.truth_world.R_i_b(np.array([100.0]))[0], ctx.stamp)
    full = model.predict(theta, u_i, ctx, att)
    for mask in (slice(0, 5), slice(3, 11), slice(None, None, 2)):
        ctx.catalog_id = ids[mask]
        sub = model.predict(theta, u_i[mask], ctx, att)
        np.testing.assert_allclose(sub.uv, full.uv[mask], rtol=0, atol=1e-9)
        np.testing.assert_allclose(sub.H_parameters, full.H_parameters[mask], rtol=1e-12)


@pytest.mark.parametrize("subset", [*SUBSETS, "flexure"])
def test_predict_frames_is_predict_frame_by_frame(subset, sim, stars):
    """The twin's render of many frames at once (``predict_frames``) is ``predict`` per frame.

    Frames at different stamps, head temperatures (a camera chain per frame) and gravity
    (a tracker rotation per frame: the simulator's mount flexure), star counts (one
    without stars) and attitudes; centroids and directions to rounding (1e-9 px).
    """
    from stellar_cal_ros.sim.world import MountFlexure

    ids, u_i = stars
    if subset == "flexure":
        effs = [*registry.create_many(BASELINE), MountFlexure()]
    else:
        effs = registry.create_many(SUBSETS[subset])
    model = StarModel(effs, sim.prior)
    theta = theta_of(model) if subset != "flexure" else np.r_[theta_of(
        StarModel(effs[:-1], sim.prior)), 40.0]
    picks = [slice(None), slice(2, 9), slice(0, 0), slice(None, None, 2), slice(1, 5)]
    ctxs, us, attitudes = [], [], []
    for j, sel in enumerate(picks):
        ctx = make_ctx(ids[sel], stamp=T0 + 100.0 + 0.5 * j, head=20.0 + 3.0 * j)
        ctx.gravity_st = np.array([0.1 * j, -0.05, 0.99])
        R0 = sim.truth_world.R_i_b(np.array([100.0 + 0.5 * j]))[0]
        ctxs.append(ctx)
        us.append(u_i[sel])
        attitudes.append(rotating_attitude(R0, ctx.stamp, omega=OMEGA * (1.0 + 0.2 * j)))

    def many(shifts):
        out = [a(s) for a, s in zip(attitudes, shifts, strict=True)]
        return np.array([r for r, _ in out]), np.array([w for _, w in out])

    many_ctx, one_ctx = [copy.copy(c) for c in ctxs], [copy.copy(c) for c in ctxs]
    uv, d = model.predict_frames(theta, us, many_ctx, many)
    one = [model.predict(theta, u, c, a, jacobians=False)
           for u, c, a in zip(us, one_ctx, attitudes, strict=True)]
    np.testing.assert_allclose(uv, np.concatenate([p.uv for p in one]), rtol=0, atol=1e-9)
    np.testing.assert_allclose(d, np.concatenate([p.directions_st for p in one]), rtol=0,
                               atol=1e-14)
    assert len(uv) == sum(len(u) for u in us)
    # the contexts' motion as predict sets it (issue 21: predict_frames had left the
    # identity and zero rate, which an effect reading them would have used in the twin)
    for a, b in zip(many_ctx, one_ctx, strict=True):
        for name in ("R_i_b", "omega_b", "R_i_st"):
            np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=0, atol=1e-15)
        assert np.linalg.norm(a.omega_b) > 0 and not np.allclose(a.R_i_st, np.eye(3))


def _rate_mount():
    """A TRACKER-stage effect that reads the frame's body rate (a plugin's mount that lags
    the motion): ``δ = k ω_b``."""
    from stellar_cal_ros.effects.base import Effect

    class RateMount(Effect):
        id = "rate_mount_test"
        stage = Stage.TRACKER
        parameter_names = ("k",)
        units = ("s",)
        default_sigma = (1.0,)

        def tracker_rotation(self, value, ctx):
            return float(value[0]) * np.asarray(ctx.omega_b, dtype=float)

    return RateMount()


@pytest.mark.parametrize("subset", [*SUBSETS, "flexure", "rate_mount"])
def test_predict_frames_of_stacked_stars_makes_the_contexts_only_where_read(subset, sim,
                                                                            stars):
    """The twin's render hands ``predict_frames`` its stars stacked (``counts``) and a
    function that makes the frames' contexts: the same floats, bit for bit, as with the
    frames' lists, and the contexts made (once) only where a stage reads them — not for the
    psce chain (installation: a constant affine form; the camera a plain copy), whose 14 400
    contexts were ~0.2 CPU-s of each of the 2-h round's eight renders; for a time effect,
    astrometry, a per-frame camera, the simulator's flexure and a rate-reading mount."""
    from stellar_cal_ros.sim.world import MountFlexure

    ids, u_i = stars
    extra = {"flexure": [MountFlexure()], "rate_mount": [_rate_mount()]}.get(subset)
    effs = [*registry.create_many(SUBSETS.get(subset, BASELINE)), *(extra or [])]
    model = StarModel(effs, sim.prior)
    theta = theta_of(model) if extra is None else np.r_[theta_of(
        StarModel(effs[:-1], sim.prior)), 40.0 if subset == "flexure" else 2.0]
    picks = [slice(None), slice(2, 9), slice(0, 0), slice(None, None, 2), slice(1, 5)]
    ctxs, us, attitudes = [], [], []
    for j, sel in enumerate(picks):
        ctx = make_ctx(ids[sel], stamp=T0 + 100.0 + 0.5 * j, head=20.0 + 3.0 * j)
        ctx.gravity_st = np.array([0.1 * j, -0.05, 0.99])
        ctxs.append(ctx)
        us.append(u_i[sel])
        attitudes.append(rotating_attitude(sim.truth_world.R_i_b(np.array([100.0 + 0.5 * j]))[0],
                                           ctx.stamp, omega=OMEGA * (1.0 + 0.2 * j)))

    def many(shifts):
        out = [a(s) for a, s in zip(attitudes, shifts, strict=True)]
        return np.array([r for r, _ in out]), np.array([w for _, w in out])

    asked = []

    def made():
        asked.append(1)
        return [copy.copy(c) for c in ctxs]

    uv, d = model.predict_frames(theta, us, [copy.copy(c) for c in ctxs], many)
    counts = np.array([len(u) for u in us])
    uv_s, d_s = model.predict_frames(theta, np.concatenate(us), made, many, counts=counts)
    assert uv_s.tobytes() == uv.tobytes() and d_s.tobytes() == d.tobytes()
    reads = subset not in ("psce_baseline",)
    assert len(asked) == (1 if reads else 0), subset
    if not reads:  # the psce chain's single δ is the installation's, as every frame's was
        assert model._camera_copy is not None
        assert all(e.affine_form() is not None for e in model._by_stage[Stage.TRACKER])


def test_predict_frames_gives_tracker_effects_the_frames_motion(sim, stars):
    """A TRACKER-stage effect that reads the frame's body rate (a plugin's mount that
    lags the motion) renders the same centroids through ``predict_frames`` as through
    ``predict``: before, ``predict_frames`` left ``ctx.omega_b`` at zero there (up to 520 px
    apart at k = 2 s in this test's frames)."""
    ids, u_i = stars
    model = StarModel([*registry.create_many(BASELINE), _rate_mount()], sim.prior)
    theta = np.r_[theta_of(StarModel(registry.create_many(BASELINE), sim.prior)), 2.0]
    ctxs, us, attitudes = [], [], []
    for j in range(3):
        ctxs.append(make_ctx(ids, stamp=T0 + 100.0 + 0.5 * j))
        us.append(u_i)
        attitudes.append(rotating_attitude(sim.truth_world.R_i_b(np.array([100.0]))[0],
                                           ctxs[-1].stamp, omega=OMEGA * (1.0 + 0.5 * j)))

    def many(shifts):
        out = [a(s) for a, s in zip(attitudes, shifts, strict=True)]
        return np.array([r for r, _ in out]), np.array([w for _, w in out])

    uv, _ = model.predict_frames(theta, us, [copy.copy(c) for c in ctxs], many)
    one = np.concatenate([model.predict(theta, u, copy.copy(c), a, jacobians=False).uv
                          for u, c, a in zip(us, ctxs, attitudes, strict=True)])
    np.testing.assert_allclose(uv, one, rtol=0, atol=1e-9)


# ------------------------------------------------------------------ the truth reproduces the data
def _residuals(result, model, theta, frames, bound=False):
    """Centroids − predictions; with ``bound``, also a per-star bound of the float64 time.

    Stamps are POSIX seconds in float64 (quantum 2.4e-7 s), so during a slew at rate ω the
    prediction carries up to ~ω·f·2·quantum px (7e-5 px at 5 deg/s) from time rounding alone.
    """
    w = result.truth_world
    out, bounds = [], []
    for f in frames:
        stamp = f.stamp_ns * 1e-9
        ctx = make_ctx(f.catalog_id.astype(np.int64), stamp=stamp)
        t_true = stamp - T0 + result.truth.time_offset
        # the head temperature at the frame stamp, as a filter interpolates its topic
        ctx.head_temperature_c = float(w.head_temperature(np.array([stamp - T0]))[0])

        def att(s, rel=(f.stamp_ns - int(T0 * 1e9)) * 1e-9):
            tr = np.array([rel + s])  # exact relative time (see StarModel.predict)
            return w.R_i_b(tr)[0], w.omega_ib_b(tr)[0]

        u_i = radec_to_unit(f.right_ascension, f.declination)
        out.append(f.uv - model.predict(theta, u_i, ctx, att).uv)
        rate = np.linalg.norm(w.omega_ib_b(np.array([t_true]))[0])
        quantum = 2.0 * np.spacing(stamp) * rate * result.truth.camera.fx
        bounds.append(np.full(out[-1].shape, 1e-6 + quantum))
    return (np.concatenate(out), np.concatenate(bounds)) if bound else np.concatenate(out)


def test_truth_calibration_reproduces_noise_free_centroids():
    """No estimated effects: the truth prior's camera, installation, time offset and
    thermal focal drift (an ``effects`` block entry) are applied as fixed values."""
    r = simulate(_noise_free(), duration=40.0, seed=2,
                 effects={"time_offset": [0.03], "thermal_focal_length": [2e-5],
                          "pixel_aspect": [3e-4], "image_plane_tilt": [1e-3, -2e-3],
                          "radial_k3": [0.5]})
    model = StarModel([], r.truth)
    assert model.size == 0 and [e.id for e, _ in model.fixed_effects] == [
        "thermal_focal_length"]
    res, bound = _residuals(r, model, np.zeros(0), r.star_frames[::4], bound=True)
    at_rest = bound < 1.5e-6  # Earth rate only
    assert len(res) > 100 and np.mean(at_rest) > 0.5
    worst = np.max(np.abs(res) / bound)
    assert worst < 1.0, f"residual {worst:.2f} x bound, max {np.max(np.abs(res)):.2e} px"
    assert np.max(np.abs(res[at_rest])) < 1e-6
    # the same truth without its effects block misses the thermal drift
    cal = copy.deepcopy(r.truth)
    cal.effects = {}
    res = _residuals(r, StarModel([], cal), np.zeros(0), r.star_frames[::4])
    assert np.max(np.abs(res)) > 1e-3


def test_truth_with_astrometric_effects_fixed_from_the_prior():
    """Aberration, refraction and proper motion in the truth's effects block are applied.

    The chain adds corrections computed on the catalogue direction (not one after the
    other) at the reported stamp, which differs from the simulator by < 1e-3 px.
    """
    r = simulate(_noise_free(), duration=20.0, seed=2,
                 effects={"aberration": [1.0], "refraction": [1.0], "proper_motion": [1.0]})
    model = StarModel([], r.truth)
    assert {e.id for e, _ in model.fixed_effects} == {"aberration", "refraction",
                                                     "proper_motion"}
    res = _residuals(r, model, np.zeros(0), r.star_frames[::4])
    assert np.max(np.abs(res)) < 1e-3, f"max residual {np.max(np.abs(res)):.2e} px"
    # estimated instead of fixed, at the truth scale 1: the same prediction
    est = StarModel(registry.create_many(["aberration", "refraction", "proper_motion"]),
                    r.truth)
    assert est.fixed_effects == [] and np.array_equal(est.initial_value, np.ones(3))
    np.testing.assert_allclose(_residuals(r, est, est.initial_value, r.star_frames[::4]),
                               res, rtol=0, atol=1e-12)


# ------------------------------------------------------------------ sensor model
SENSOR_IDS = ["gyro_bias", "gyro_scale_factor", "gyro_misalignment"]


def _sensor_prior(sim):
    cal = copy.deepcopy(sim.truth)
    rng = np.random.default_rng(11)
    cal.gyro_bias = np.array([3e-7, -2e-7, 1e-7])
    cal.gyro_error_matrix = 2e-4 * rng.standard_normal((3, 3))
    cal.accel_bias = np.array([1e-3, -2e-3, 5e-4])
    cal.accel_error_matrix = 2e-4 * rng.standard_normal((3, 3))
    cal.sigma = default_prior_sigma()
    return cal


def test_corrected_rates_invert_the_sensor_model(sim):
    prior = _sensor_prior(sim)
    model = StarModel(registry.create_many(SENSOR_IDS), prior)
    assert model.size == 12
    theta = theta_of(model) + 1e-3 * np.r_[np.zeros(3), np.ones(9)]  # E of a few 1e-3
    b, E, Jb, JE = model.sensor_model(theta, Stage.GYRO)
    np.testing.assert_array_equal(b, theta[:3])
    np.testing.assert_array_equal(np.diag(E), theta[3:6])
    off = [(0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1)]
    np.testing.assert_array_equal([E[i, j] for i, j in off], theta[6:12])
    rng = np.random.default_rng(5)
    w = rng.standard_normal((50, 3)) * 0.1
    w_meas = w @ (np.eye(3) + E).T + b
    np.testing.assert_allclose(model.corrected_rates(theta, w_meas), w, rtol=0, atol=1e-15)

    # ∂ω/∂θ = −(I+E)⁻¹ [Jb + JE·ω̂] against finite differences, one measured sample
    wm = w_meas[7]
    w_hat = model.corrected_rates(theta, wm[None])[0]
    J = -np.linalg.solve(np.eye(3) + E, Jb + np.einsum("ijk,j->ik", JE, w_hat))
    fd = np.zeros_like(J)
    for k in range(model.size):
        h = 1e-5  # ω ~ 0.1 rad/s: smaller steps lose digits; ω is quadratic in θ at most
        e = np.zeros(model.size)
        e[k] = h
        fd[:, k] = (model.corrected_rates(theta + e, wm[None])[0]
                    - model.corrected_rates(theta - e, wm[None])[0]) / (2 * h)
    np.testing.assert_allclose(J, fd, rtol=1e-7, atol=1e-14)


def test_prior_sensor_values_not_estimated_stay_fixed(sim):
    prior = _sensor_prior(sim)
    b0, E0 = prior.gyro_bias, prior.gyro_error_matrix
    # nothing estimated: the prior's bias and matrix
    m = StarModel([], prior)
    b, E, Jb, JE = m.sensor_model(np.zeros(0))
    np.testing.assert_array_equal(b, b0)
    np.testing.assert_array_equal(E, E0)
    w = np.array([[0.1, -0.2, 0.3]])
    np.testing.assert_allclose(m.corrected_rates(np.zeros(0), w @ (np.eye(3) + E0).T + b0), w,
                               rtol=0, atol=1e-16)
    # scale factors estimated: the prior bias and off-diagonal entries are kept
    m = StarModel(registry.create_many(["gyro_scale_factor"]), prior)
    theta = np.array([1e-4, -2e-4, 3e-4])
    b, E, Jb, JE = m.sensor_model(theta)
    np.testing.assert_array_equal(b, b0)
    np.testing.assert_array_equal(np.diag(E), theta)
    np.testing.assert_array_equal(E - np.diag(np.diag(E)), E0 - np.diag(np.diag(E0)))
    assert not np.any(Jb)
    # bias estimated: the prior matrix is kept whole, the bias is θ (not prior + θ)
    m = StarModel(registry.create_many(["gyro_bias"]), prior)
    np.testing.assert_array_equal(m.initial_value, b0)
    b, E, _, _ = m.sensor_model(np.array([1e-6, 2e-6, 3e-6]))
    np.testing.assert_array_equal(b, [1e-6, 2e-6, 3e-6])
    np.testing.assert_array_equal(E, E0)
    # the accelerometer stage is separate
    m = StarModel(registry.create_many(["gyro_bias", "accel_bias"]), prior)
    b, E, _, _ = m.sensor_model(m.initial_value, Stage.ACCEL)
    np.testing.assert_array_equal(b, prior.accel_bias)
    np.testing.assert_array_equal(E, prior.accel_error_matrix)


# ------------------------------------------------------------------ user effects
USER_EFFECT = '''
import numpy as np

from stellar_cal_ros.effects.base import CAMERA_INDEX, Effect, Stage

CX = CAMERA_INDEX["cx"]


class CxScale(Effect):
    """cx' = cx (1 + s)."""

    id = "test_user_cx_scale"
    stage = Stage.CAMERA
    parameter_names = ("s",)
    units = ("1",)
    default_sigma = (1e-3,)
    explanation = "A test effect: the principal point column scales by 1 + s."

    def camera_parameters(self, value, p, ctx):
        out = p.copy()
        out[CX] = p[CX] * (1.0 + value[0])
        return out

    def camera_jacobian(self, value, p, ctx):
        J = np.zeros((18, 1))
        J[CX, 0] = p[CX]
        D = np.eye(18)
        D[CX, CX] = 1.0 + value[0]
        return J, D
'''


@pytest.fixture
def user_effect_file(tmp_path):
    path = tmp_path / "my_effect.py"
    path.write_text(textwrap.dedent(USER_EFFECT))
    yield path
    registry.EFFECTS.pop("test_user_cx_scale", None)


def test_user_effect_module(user_effect_file, sim, stars):
    assert registry.load_effect_module(user_effect_file) == ["test_user_cx_scale"]
    # after every library effect of its stage (order 100 > the library's 10-90)
    ids = registry.available()
    camera = [i for i in ids if registry.EFFECTS[i].stage is Stage.CAMERA]
    assert camera[-1] == "test_user_cx_scale"
    assert ids.index("test_user_cx_scale") == ids.index(camera[-2]) + 1
    # the same file again (a second command in one process) is the same effect ...
    assert registry.load_effect_module(user_effect_file) == ["test_user_cx_scale"]
    other = user_effect_file.with_name("other_effect.py")
    other.write_text(user_effect_file.read_text())
    with pytest.raises(ModelError, match="already registered"):
        registry.load_effect_module(other)  # ... another file with the same id is not
    effects = registry.create_many(["test_user_cx_scale", "principal_point"])
    assert [e.id for e in effects] == ["principal_point", "test_user_cx_scale"]
    ids, u_i = stars
    model = StarModel(effects, sim.prior)
    theta = np.array([520.0, 510.0, 2e-3])
    ctx = make_ctx(ids)
    att = rotating_attitude(sim.truth_world.R_i_b(np.array([100.0]))[0], ctx.stamp)
    pred = model.predict(theta, u_i, ctx, att)
    assert model.camera_at(theta, ctx).cx == pytest.approx(520.0 * 1.002, rel=1e-15)
    for k, h in enumerate([1e-2, 1e-2, 1e-6]):
        e = np.zeros(3)
        e[k] = h
        fd = (model.predict(theta + e, u_i, ctx, att).uv
              - model.predict(theta - e, u_i, ctx, att).uv) / (2 * h)
        np.testing.assert_allclose(pred.H_parameters[:, :, k], fd, rtol=1e-6, atol=1e-7)
    # the principal point column goes through the user's scaling: ∂u/∂cx = 1 + s
    np.testing.assert_allclose(pred.H_parameters[:, 0, 0], 1.002, rtol=1e-12)


def test_bad_effect_modules(tmp_path):
    empty = tmp_path / "empty.py"
    empty.write_text("X = 1\n")
    with pytest.raises(ModelError, match="defines no Effect"):
        registry.load_effect_module(empty)
    broken = tmp_path / "broken.py"
    broken.write_text("raise RuntimeError('boom')\n")
    with pytest.raises(ModelError, match="boom"):
        registry.load_effect_module(broken)
    with pytest.raises(ModelError, match="does not exist"):
        registry.load_effect_module(tmp_path / "missing.py")
    private = tmp_path / "private.py"  # an id the registry never lists or prints
    private.write_text(textwrap.dedent(USER_EFFECT).replace('"test_user_cx_scale"',
                                                            '"_test_user_cx_scale"'))
    with pytest.raises(ModelError, match="reserved"):
        registry.load_effect_module(private)
    assert "_test_user_cx_scale" not in registry.EFFECTS
    with pytest.raises(ModelError, match="unknown effect"):
        registry.create("no_such_effect")


def test_stacked_stars_from_columns_are_the_frames_lists():
    """The direction effects' stacked stars (``Stacked``) made from the bag's columns in one
    pass (``counts``; ``StarModel.prepare_frames``) equal, array for array, those made from a
    list per frame: frames with a zero or repeated number left out, empty frames (also the
    last), a stamp that repeats (its last frame found)."""
    from stellar_cal_ros.effects._direction import Stacked

    rng = np.random.default_rng(8)
    ids = [np.array([5, 9, 2]), np.zeros(0, np.int64), np.array([4, 0, 7]), np.array([3, 8]),
           np.array([6, 6, 1]), np.array([11]), np.array([12, 13, 14, 15]), np.zeros(0, np.int64)]
    u = [rng.normal(size=(len(i), 3)) for i in ids]
    stamps = np.array([1.0, 2.0, 3.0, 4.0, 5.0, 5.0, 7.0, 8.0])
    p, t = rng.normal(size=8), rng.normal(size=8)
    lists = Stacked(stamps, ids, u, p, t)
    cols = Stacked(stamps, np.concatenate(ids), np.concatenate(u), p, t,
                   counts=np.array([len(i) for i in ids]))
    for name in ("count", "stamps", "weather", "ids", "u", "start"):
        a, b = getattr(lists, name), getattr(cols, name)
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), name
    assert lists.ids.tolist() == [5, 9, 2, 3, 8, 11, 12, 13, 14, 15]
    assert lists._row == cols._row and len(cols) == 4  # stamp 5.0: its last frame
    empty = Stacked(np.zeros(0), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0),
                    np.zeros(0), counts=np.zeros(0, np.int64))
    assert len(empty) == 0 and empty.u.shape == (0, 3)
