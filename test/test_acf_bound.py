"""Cramér–Rao bounds of the ACF and IAC calibrations (Liu et al. Table 1 setting, issue 7).

Setting: the ``acf_sweep`` scenario (60 frames, 0.5 °/s single-axis sweep, ARW 0.005 °/√h,
gyro bias 0.03 °/h not estimated), noise-free centroids plus 0.1 px Gaussian noise, wide
prior σ (installation 5°, Liu's distortion range).  At 0.1 px the bound is σ(x0, y0, f) ≈
(1.00, 1.10, 0.23) px for ACF and (1.03, 1.13, 0.23) px for IAC.

Tolerances:

* the solver's reported σ uses σ̂ from ~2200 residuals (relative SE ~1.5 %) and the Jacobian
  at the estimate instead of the truth (immaterial at 1 px): within 5 % of the σ predicted
  for its least squares (``estimator``), within 20 % of the bound (the least squares ignores
  the random-walk correlation in its weights: measured 1-4 % above the bound on the
  intrinsics, ~8 % on the installation);
* errors over ``RUNS`` independent runs (centroid and gyro noise): Σ eᵀ C⁻¹ e with C the
  bound's covariance is χ² with 3·RUNS (ACF: 5·RUNS with the two observable installation
  axes) degrees of freedom for an efficient unbiased estimator; accepted between the
  0.1 % and 99.9 % quantiles.  The unestimated gyro bias shifts x0 / y0 by ~0.1 px (≈ 0.1 σ:
  +0.01 per run to the χ²).  An estimator 1.5× the bound exceeds the upper limit with
  probability ~0.9; the IAC check uses the bound of IAC's own weighting (``estimator``).
"""

import copy

import numpy as np
import pytest
from scipy.stats import chi2

from stellar_cal_ros.methods.acf import AcfData, run_acf
from stellar_cal_ros.methods.acf_bound import (
    crlb_acf,
    installation_error_arcsec,
    installation_error_covariance,
)
from stellar_cal_ros.methods.iac import crlb_iac, run_iac
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate

NOISE = 0.1
RUNS = 5
CAM = ["focal_length.f", "principal_point.cx", "principal_point.cy"]


def _sim(seed):
    sc = get_scenario("acf_sweep")
    sc.centroid_noise_px = 0.0
    sim = simulate(sc, seed=seed)
    prior = copy.deepcopy(sim.prior)
    prior.sigma["installation"]["rotation_vector"] = [float(np.deg2rad(5.0))] * 3
    prior.sigma["camera"]["distortion_coefficients"]["data"] = [3.0, 10.0, 0.02, 0.02, 100.0]
    arw = np.deg2rad(sc.gyro_arw_deg_sqrth) / 60.0
    return sim, prior, arw


def _noisy(frames, seed):
    rng = np.random.default_rng(seed)
    out = copy.deepcopy(frames)
    for f in out:
        f.uv = f.uv + NOISE * rng.standard_normal(f.uv.shape)
        f.sigma = np.full(len(f.uv), NOISE)
    return out


def _data(frames, sim):
    return AcfData(frames=frames, imu=sim.imu, t0_ns=int(sim.imu.stamp_ns[0]))


@pytest.fixture(scope="module")
def bounds():
    sim, prior, arw = _sim(100)
    b = crlb_acf(_data(sim.star_frames, sim), prior, sim.truth, sigma_px=NOISE, gyro_arw=arw)
    bi = crlb_iac(sim.star_frames, prior, sim.truth, sigma_px=NOISE)
    return sim, prior, arw, b, bi


def _idx(names, wanted):
    return [names.index(n) for n in wanted]


def _psd(A, rel=1e-6):
    d = 1.0 / np.sqrt(np.abs(np.diag(A)).max())
    return np.linalg.eigvalsh(A * d * d).min() > -rel


def test_bound_ordering(bounds):
    """Information ordering: tied attitudes ≥ random-walk attitudes ≥ free attitudes (IAC)."""
    sim, prior, arw, b, bi = bounds
    assert b.arw_q == pytest.approx(arw ** 2)
    assert _psd(b.crlb - b.crlb_white) and _psd(b.estimator - b.crlb)
    assert _psd(bi.estimator - bi.crlb)
    # IAC's per-frame attitudes contain ACF's φ + installation + random walk: less information
    ia, ii = _idx(b.parameter_names, bi.parameter_names), list(range(len(bi.parameter_names)))
    assert _psd(bi.crlb[np.ix_(ii, ii)] - b.crlb[np.ix_(ia, ia)])
    # ... but in this setting hardly less (the issue-7 finding): the principal point trades
    # against the installation tilt in ACF as against each frame's attitude in IAC
    ratio = bi.sigma()[_idx(bi.parameter_names, CAM)] / b.sigma()[_idx(b.parameter_names, CAM)]
    assert np.all(ratio < 1.1), ratio
    # with the installation known, the gyro-tied frames pin the principal point
    known = copy.deepcopy(prior)
    known.installation = sim.truth.installation
    known.sigma["installation"]["rotation_vector"] = [float(np.deg2rad(1.0 / 3600.0))] * 3
    bk = crlb_acf(_data(sim.star_frames, sim), known, sim.truth, sigma_px=NOISE, gyro_arw=arw)
    i_cx = bk.parameter_names.index("principal_point.cx")
    assert bk.sigma()[i_cx] < 0.3 * bi.sigma()[1]


def test_solver_covariance_matches_bound(bounds):
    sim, prior, arw, b, bi = bounds
    noisy = _noisy(sim.star_frames, 7)
    r = run_acf(_data(noisy, sim), prior, gyro_arw=arw)
    assert r.parameter_names == b.parameter_names
    sel = _idx(b.parameter_names, CAM + ["radial_k1k2.k1", "installation.ry"])
    np.testing.assert_allclose(r.sigma[sel], b.sigma("estimator")[sel], rtol=0.05)
    np.testing.assert_allclose(r.sigma[sel], b.sigma("crlb")[sel], rtol=0.2)
    i = run_iac(noisy, prior)
    # IAC reports the pair-correlation sandwich (scaled by its residuals: ~2200 pairs'
    # worth, relative SE of the scale a few %), not the 2x optimistic independent-pair σ
    np.testing.assert_allclose(i.sigma, bi.sigma("reported"), rtol=0.08)
    assert np.all(bi.sigma("naive")[:3] < 0.7 * bi.sigma("reported")[:3])


def test_errors_within_chi2_of_bound(bounds):
    sim0, prior0, arw, b, bi = bounds
    ia, ii = _idx(b.parameter_names, CAM), _idx(bi.parameter_names, CAM)
    Ca = b.crlb[np.ix_(ia, ia)]
    Ci = bi.estimator[np.ix_(ii, ii)]
    # the two observable installation axes (principal axes of the bound but the largest)
    Cinst = installation_error_covariance(b.crlb, b.model, b.theta_true)
    _, V = np.linalg.eigh(Cinst)
    V = V[:, :2]  # the third (largest) is the rotation about the sweep axis
    Cv = V.T @ Cinst @ V
    qa = qi = 0.0
    for k in range(RUNS):
        sim, prior, _ = _sim(200 + k)
        noisy = _noisy(sim.star_frames, 300 + k)
        r = run_acf(_data(noisy, sim), prior, gyro_arw=arw)
        i = run_iac(noisy, prior)
        t, ca, ci = sim.truth.camera, r.calibration.camera, i.calibration.camera
        ea = np.array([ca.fx - t.fx, ca.cx - t.cx, ca.cy - t.cy])
        ei = np.array([ci.fx - t.fx, ci.cx - t.cx, ci.cy - t.cy])
        ev_inst = V.T @ installation_error_arcsec(r.calibration, sim.truth)
        qa += ea @ np.linalg.solve(Ca, ea) + ev_inst @ np.linalg.solve(Cv, ev_inst)
        qi += ei @ np.linalg.solve(Ci, ei)
    lo, hi = chi2.ppf([0.001, 0.999], 5 * RUNS)
    assert lo < qa < hi, (qa, lo, hi)
    lo, hi = chi2.ppf([0.001, 0.999], 3 * RUNS)
    assert lo < qi < hi, (qi, lo, hi)
