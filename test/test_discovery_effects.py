"""Model discovery, effect by effect (issue 5).

For every library effect that is a candidate for the PSCE method, the demo scenario
(``psce_rotations``, 0.05 px, 200 s -- 120 s where the power allows, ``SHORT_S`` --, fixed
seed) is simulated with the effect at 5-7 times
its minimum detectable size (MDS at 300 s from ``benchmarks/detectability.py``: 6-10 times,
scaled to 200 s as 1/sqrt(duration), the thermal drift's as duration^-1.5); the baseline model is
calibrated and diagnosed over **all** applicable candidates.  The effect must rank first and
be significant; a fresh calibration with it added must bring the innovation RMS to the noise
floor (≤ 1.05 × 0.05 px) and its parameters within 3 σ of the truth.

Exceptions, with the measured reason:

- ``radial_k3`` is absorbed by ``k1, k2`` on the demo's narrow field (14.7°): no size up to
  k3 = 240 (120 datasheet σ) is detectable there (MDS table).  It is tested on a wide-field
  variant of the scenario (``fx`` = 1500 px, 37.7°, stars to magnitude 4.5).
- ``aberration``, ``refraction``, ``proper_motion`` exist only at physical size (scale 1);
  they are tested there, which is 1 / MDS times their detectability (MDS table).
- ``thermal_focal_length`` is seen only through the head-temperature change (30 °C decaying
  toward 10 °C, τ = 3600 s: 1.1 °C in 200 s); 1e-4 /°C is two datasheet σ.
- ``image_plane_tilt``: 6 × its MDS is 5 datasheet σ, so the fresh calibration uses a
  prior that allows it (σ = 0.05 rad), see ``_check_found_and_fixed``.
- ``gyro_misalignment`` is simulated symmetric (all six entries equal): the antisymmetric
  part is a rotation of the gyro triad, which the installation absorbs (unobservable).
- Mount flexure (not in the library) is aliased with a gyro scale factor by this motion
  (~98 %): discover adds the gyro scale factor flagged as its stand-in, says the
  gravity-shaped remainder and adds no further gyro effect that explains nothing beyond it
  (:mod:`~stellar_cal_ros.diagnosis.flexure`).
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

from stellar_cal_ros.diagnosis import flexure, stats
from stellar_cal_ros.diagnosis.discover import (
    ALPHA,
    DiagnosisSpec,
    method_spec,
    rank_candidates,
)
from stellar_cal_ros.diagnosis.run import diagnose
from stellar_cal_ros.effects import registry
from stellar_cal_ros.methods.replay import bag_data_from_simulation, replay_psce, truth_parameters
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate

NOISE = 0.05
#: the bags' length in the default suite (300 s until the suite had to get shorter: the
#: diagnosis time is proportional to it); the benchmarks below keep FULL_S
DURATION = 200.0
FULL_S = 300.0

#: effect → (simulated size, seed); the size in units of the MDS at 300 s
#: (benchmarks/detectability.py), then at 200 s (scaled), then the case's Bonferroni-adjusted
#: p-value measured at 200 s (significance needs < 0.01) is given in the comment
CASES = {
    "pixel_aspect": (1e-4, 41),  # 6.3 × MDS; 5.1 ×; p 5e-97
    "image_plane_tilt": (0.025, 42),  # 6.3 ×; 5.1 ×; p 0 (underflow)
    "thermal_focal_length": (1e-4, 43),  # 10 ×; 5.4 ×; p 6e-106
    "gyro_scale_factor": (1e-4, 44),  # 9.1 ×; 7.4 ×; p 2e-10
    "gyro_misalignment": (1e-4, 45),  # 7.7 ×; 6.3 ×; p 3e-30
    "time_offset": (4e-4, 46),  # 7.5 ×; 6.1 ×; p 7e-40
    "aberration": (1.0, 47),  # physical: 7.1 ×; 5.8 ×; p 6e-16
    "refraction": (1.0, 48),  # physical: 31 ×; 25 ×; p 0
    "proper_motion": (1.0, 49),  # physical: 22 ×; 18 ×; p 0
}
#: cases whose power allows a 120 s bag (the others keep DURATION).  Measured at 120 s: the
#: decision statistic's margin over its Bonferroni critical value (one-sided normal
#: equivalents, ≥ 5 σ asked) and the RMS after adding the effect / noise (≤ 1.05 asked):
#: pixel_aspect 12.5 σ, 1.029; gyro_misalignment 16.6 σ, 1.017; proper_motion p 0
#: (underflow), 0.996.  Not shortened: image_plane_tilt and time_offset (RMS after 1.12
#: and 1.051 × noise at 120 s: the fixed run settles later than that), thermal_focal_length
#: (3.6 σ), radial_k3 (RMS after 1.047), gyro_scale_factor, aberration and refraction (they
#: rank first ahead of each other by a small gap in the statistic).
SHORT_S = {"pixel_aspect": 120.0, "gyro_misalignment": 120.0, "proper_motion": 120.0}


def _simulate(effects, seed, scenario=None, duration=DURATION):
    sim = simulate(scenario or get_scenario("psce_rotations"), duration=duration, seed=seed,
                   effects=effects)
    return sim, bag_data_from_simulation(sim)


def _wide_field():
    """psce_rotations with a 38° field: fx = 1500 px, stars to magnitude 4.5."""
    sc = get_scenario("psce_rotations")
    sc.focal_length_px = 1500.0
    sc.mag_limit = 4.5
    return sc


def _broad_tilt_prior(prior, sigma=0.05):
    """The prior with a tilt sigma of ``sigma`` rad (OpenCV distortion entries 12, 13)."""
    prior = copy.deepcopy(prior)
    D = prior.sigma["camera"]["distortion_coefficients"]
    D["data"] = list(D["data"]) + [0.0] * (12 - len(D["data"])) + [sigma, sigma]
    D["cols"] = 14
    return prior


def _check_found_and_fixed(tmp_path, effect, size, seed, scenario=None, duration=DURATION):
    sim, data = _simulate({effect: size}, seed, scenario, duration)
    base = replay_psce(data, sim.prior)
    summary = diagnose(data, base.calibration, "psce", [], tmp_path / "rep", plots=False,
                       verbose=False)
    ranked = [c["effect"] for c in summary["candidates"]]
    # every applicable library candidate was tried
    spec = method_spec("psce")
    tried = set(ranked) | {u["effect"] for u in summary["unobservable"]
                           + summary["implausible"] + summary["screened_out"]}
    expected = {e for e in registry.candidates() if e not in spec.baseline
                and registry.create(e).stage.value != "accel"}
    assert tried == expected, tried ^ expected
    first = summary["candidates"][0]
    assert first["effect"] == effect, ranked[:3]
    assert first["significant"], first
    assert summary["recommendation"] == effect
    # the flexure-shaped remainder test (after a non-camera effect): no false remainder
    assert "remainder" not in summary, summary["remainder"]
    if effect in ("gyro_scale_factor", "gyro_misalignment", "time_offset"):
        # then the round bounds a flexure instead (its MDB): the bag holds none, so the
        # test's estimate lies within 3 of the sigma the MDB is made of
        h = summary["flexure_hiding"]
        assert h is not None and h["after"] == [effect], h
        assert abs(h["estimate_arcsec_per_g"]) < 3.0 * h["sigma_arcsec_per_g"], h
        assert "could still hide with this motion" in "\n".join(summary["terminal"])
        # and the HTML report's hiding table carries it, in the terminal's words
        from stellar_cal_ros.diagnosis.report_html import _reliability_html

        page = _reliability_html(summary)
        mdb, test = flexure.hiding_phrases(h, "±")
        assert flexure.HIDING_NAME in page and mdb in page and test in page
    # add it: a fresh calibration from the prior
    prior = sim.prior
    if effect == "image_plane_tilt":
        # 6 x its MDS is 5 datasheet sigmas (5e-3 rad): a datasheet prior would pull the
        # estimate toward zero along the tilt / principal point / installation / tangential
        # near-degeneracy (measured: 8-16 sigma).  Adding a larger effect than the datasheet
        # allows calls for a prior that allows it.
        prior = _broad_tilt_prior(prior)
    fixed = replay_psce(data, prior, [effect])
    res = fixed.residuals
    rms = stats.rms(res, stats.evaluation_mask(res))
    assert max(rms) <= 1.05 * NOISE, rms
    flt = fixed.filter
    sl = flt.model.slices[effect]
    est, sig = flt.theta[sl], flt.sigma()[3:][sl]
    truth = truth_parameters(flt.model, sim.truth)[sl]
    z = (est - truth) / sig
    print(f"\n{effect}: rank 1 of {len(ranked)}, score {first['score']:.1f}, p_adj "
          f"{first['p_value']:.2g}, RMS before {max(summary['residual_rms_px']) / NOISE:.2f} "
          f"x noise, after {max(rms) / NOISE:.3f} x noise, parameter error/sigma "
          f"{np.array2string(z, precision=2)}")
    assert np.all(np.abs(z) < 3.0), (est, truth, sig)
    return summary, rms, z


@pytest.mark.parametrize("effect", list(CASES))
def test_missing_effect_ranks_first_and_adding_it_fixes(tmp_path, effect):
    size, seed = CASES[effect]
    _check_found_and_fixed(tmp_path, effect, size, seed, duration=SHORT_S.get(effect, DURATION))


def test_radial_k3_wide_field(tmp_path):
    """k3 on a 38° field (on the demo's 14.6° field k1, k2 absorb it, see the MDS table)."""
    _check_found_and_fixed(tmp_path, "radial_k3", 0.3, 50, scenario=_wide_field())


def test_magnitude_bias_is_unexplained_among_all_candidates(tmp_path):
    """A magnitude-dependent centroid bias: no library effect claimed, 'magnitude' listed."""
    sim, data = _simulate({"magnitude_bias": [0.1, 30.0]}, 51)
    base = replay_psce(data, sim.prior)
    summary = diagnose(data, base.calibration, "psce", [], tmp_path / "rep", plots=False,
                       verbose=False)
    assert not any(c["significant"] for c in summary["candidates"])
    assert summary["unexplained"][0]["regressor"] == "magnitude"


FLEXURE = 40.0  #: arcsec per unit lateral gravity: the flexure tests' mount


@pytest.fixture(scope="module")
def flexure_bag():
    """A 40"/g mount flexure on 200 s of psce_rotations (seed 52) and its baseline replay."""
    sim, data = _simulate({"mount_flexure": FLEXURE}, 52, duration=200.0)  # its power: 200 s
    return sim, data, replay_psce(data, sim.prior)


def test_single_diagnose_round_says_the_recommendation_stands_in_for_a_flexure(
        tmp_path, flexure_bag):
    """One ``diagnose`` round (no discover) on the flexure: it recommends the gyro scale
    factor that takes up ~98 % of it, tests that model for the gravity-shaped remainder
    (one probe run), finds it, tests the recommendation beyond a flexure as discover does
    (one more probe run: the current model) and says it stands in for it, with the flexure
    that would leave the remainder within 3 sigma of the truth.  Reduced: the one candidate
    that absorbs it.
    """
    sim, data, base = flexure_bag
    summary = diagnose(data, base.calibration, "psce", [], tmp_path / "rep",
                       candidates=["gyro_scale_factor"], plots=False, verbose=False,
                       noise="stated", workers=0)
    assert summary["recommendation"] == "gyro_scale_factor", summary["candidates"]
    rem = summary["remainder"]
    assert rem["like"] == ["gyro_scale_factor"], rem
    assert rem["regressor"].startswith("gravity_st (mount-flexure shape") and \
        rem["p_value"] < 0.01, rem
    assert summary["unexplained"][0]["regressor"] == rem["regressor"], summary["unexplained"]
    d = rem["detail"]
    assert abs(d["arcsec_per_g"] - FLEXURE) < 3.0 * d["sigma_arcsec_per_g"], d
    # beyond a flexure, both terms NIS-capped (flexure.beyond): discover's test on this
    # bag measured 10.6 (chi2, 3 dof, p 0.014; -314.7 with the flexure's chi2 uncapped).
    # The claim is the decision the text prints, "not needed" at the diagnosis's alpha
    # (p >= discover.ALPHA; the literal 0.01 here was the same test, written twice).  Its
    # margin on this seed is thin because seed 52 is the largest of ten: seeds 52-61 read
    # -11.1 to 10.6 against the critical 11.34, the stand-in verdict on all 10
    # (doc/benchmarks.md, flexure.beyond table); a true null is rejected at alpha per bag,
    # so that seed table, not this seed's p, is the level claim
    b = d["beyond"]
    assert not b["needed"] and b["p_value"] >= ALPHA and not b["negative"], b
    assert "stands in for it" in rem["text"] and "outside the library" in rem["text"], rem
    assert "stands in for it" in "\n".join(summary["terminal"])


def test_flexure_mdb_shift_is_the_t_nu_tests_power():
    """``reliability.delta_t`` (the flexure MDB's shift in sigmas): a two-sided t_nu test
    at alpha rejects a shift of delta_t sigmas with power 80 % (simulated: the normal
    estimate over an independent chi2_nu scale, 40 000 draws, 3 binomial sigmas), and tends
    to the normal's sqrt(lambda0) as nu grows."""
    from scipy import stats as sps

    from stellar_cal_ros.diagnosis import reliability

    rng = np.random.default_rng(7)
    n = 40_000
    for alpha, nu in ((0.01, 11.0), (0.01, 30.0), (0.005, 60.0)):
        d = reliability.delta_t(alpha, nu)
        t = (rng.standard_normal(n) + d) / np.sqrt(rng.chisquare(nu, n) / nu)
        power = np.mean(np.abs(t) > sps.t.isf(alpha / 2.0, nu))
        assert abs(power - 0.8) < 3.0 * np.sqrt(0.16 / n), (alpha, nu, d, power)
        assert d > np.sqrt(reliability.lambda0(alpha, 1))
    assert reliability.delta_t(0.01, 1e6) == pytest.approx(
        np.sqrt(reliability.lambda0(0.01, 1)), rel=2e-3)


def test_remainder_text_says_what_the_beyond_test_found():
    """The three verdicts of the remainder line: no beyond test (its extra run failed),
    needed beyond a flexure, and a stand-in."""
    from stellar_cal_ros.diagnosis.flexure import remainder_text

    f = {"change_px": 0.033, "statistic": 7.8, "p_value": 2.6e-5,
         "detail": {"arcsec_per_g": 40.8, "sigma_arcsec_per_g": 4.3}}
    said = remainder_text(["gyro_scale_factor"], f)
    assert "0.033 px" in said and "40.8 +- 4.3 arcsec" in said
    assert said.endswith("gyro_scale_factor improves the fit but may stand in for it"), said
    for stat, needed, words in (
            (469.4, True, "improves the fit beyond such a flexure too"),
            (10.6, False, "explains nothing beyond such a flexure (its ratio with a flexure "
                          "fitted beside it 10.6, chi2 with 3, p=0.014)"),
            (-29.7, False, "explains nothing beyond such a flexure (its ratio with a flexure "
                           "fitted beside it -29.7 < 0 for 3 dof: with a flexure fitted the "
                           "model predicts worse with it than without it, no chi2 test)")):
        b = flexure.beyond(stat, 3, 1.0, {"chi2_capped": 0.0}, {"chi2_capped": 0.0})
        assert b["needed"] is needed and b["negative"] is (stat < 0), b
        said = remainder_text(["gyro_scale_factor"], {**f, "detail": {**f["detail"],
                                                                        "beyond": b}})
        assert words in said and ("stands in for it" in said) is not needed, said


def test_beyond_adds_the_flexures_gain_in_the_currency_of_the_ratio(monkeypatch):
    """``flexure.beyond``: Λ (NIS capped at 13.8 per star) plus the flexure's gain with the
    effect minus without it, that gain too with each star's NIS capped
    (``stats.capped_gain``); the uncapped ``chi2`` is not used.  On white innovations with a
    pattern of known size the capped gain tends to the uncapped ``c² info`` as the cap
    grows, is below it at 13.8 when stars exceed the cap, and is never negative (a
    least-squares ``c`` that loses in the capped sum is not what a fitted flexure gains)."""
    rng = np.random.default_rng(5)
    sub = _table(rng, frames=80)
    n = len(sub["du"])
    x = 0.01 * rng.standard_normal((n, 2))
    sub["du"] = sub["du"] + 3.0 * x[:, 0]
    sub["dv"] = sub["dv"] + 3.0 * x[:, 1]
    t, _, c, info = stats.whitened_fit(sub, x)
    assert stats.capped_gain(sub, x, c, cap=1e12) == pytest.approx(c * c * info, rel=1e-9)
    assert 0.0 < stats.capped_gain(sub, x, c) <= c * c * info
    # a few stars far beyond the cap: the least-squares fit chases them, the capped gain
    # is what a fit gains where Λ counts (>= the gain at 0, i.e. 0, and at c)
    far = sub.copy()
    far["du"] = np.where(np.arange(n) < 5, 40.0 * x[:, 0] / 0.01 * 0.05, far["du"])
    _, _, c_far, info_far = stats.whitened_fit(far, x)
    got = stats.capped_gain(far, x, c_far)
    assert 0.0 <= got < c_far * c_far * info_far
    w = stats.whitened(far)
    wx = stats.whitened({"du": x[:, 0], "dv": x[:, 1], **{k: far[k] for k in ("s_uu", "s_uv",
                                                                              "s_vv")}})
    capped = [float(np.minimum(np.sum(w**2, 1), 13.8).sum()
                    - np.minimum(np.sum((w - k * wx) ** 2, 1), 13.8).sum())
              for k in np.linspace(0.0, 2.0 * c_far, 401)]
    assert got >= max(capped) - 1e-6 * abs(max(capped)) - 1e-9
    # the cap is the run's own (results.NIS_CAP, what Λ's log-likelihood caps at), not a
    # copy of its value: moved, the gain moves with it
    from stellar_cal_ros.methods import results

    assert got == stats.capped_gain(far, x, c_far, cap=results.NIS_CAP)
    monkeypatch.setattr(results, "NIS_CAP", 5.0)
    assert stats.capped_gain(far, x, c_far) == stats.capped_gain(far, x, c_far, cap=5.0) != got
    # beyond uses the capped gains only
    b = flexure.beyond(20.0, 3, 2.0, {"chi2": 1e6, "chi2_capped": 30.0},
                       {"chi2": 5.0, "chi2_capped": 10.0})
    assert b["statistic"] == pytest.approx(30.0) and b["needed"] and not b["negative"]


def _table(rng, frames: int = 60, stars: int = 8, offset: float = 0.0) -> dict:
    """A residual table of ``frames`` x ``stars`` innovations, 0.05 px white, accepted."""
    n = frames * stars
    return {"t": np.repeat(np.arange(frames, dtype=float), stars),
            "frame": np.repeat(np.arange(frames), stars),
            "catalog_id": np.tile(np.arange(1, stars + 1), frames),
            "du": 0.05 * rng.standard_normal(n) + offset,
            "dv": 0.05 * rng.standard_normal(n) + offset,
            "s_uu": np.full(n, 0.0025), "s_uv": np.zeros(n), "s_vv": np.full(n, 0.0025),
            "gated": np.zeros(n, dtype=bool)}


def test_flexure_robust_sigma_is_that_of_the_slope_t_is_of():
    """The flexure MDB's frame-robust sigma (seed 317 printed 112"/g from |c / t| with
    t = -0.027): ``t`` is a centred slope, ``c`` the fit through the origin, so ``|c/t|``
    blows up where t ~ 0 when the innovations and the pattern have a mean.  The sigma used
    is ``|b / t|``, ``b`` the centred slope (computed here independently), and on white
    innovations it is b's i.i.d. sigma within the scatter of its frame-robust estimate."""
    rng = np.random.default_rng(3)
    sub = _table(rng, offset=0.02)
    S = np.stack([0.01 + 0.002 * rng.standard_normal(len(sub["du"])),
                  0.01 + 0.002 * rng.standard_normal(len(sub["du"]))], 1)
    t, _, c, info = stats.whitened_fit(sub, S)
    x, y = (S / 0.05).ravel(), np.stack([sub["du"], sub["dv"]], 1).ravel() / 0.05
    b = float((x - x.mean()) @ (y - y.mean()) / ((x - x.mean()) @ (x - x.mean())))
    robust = stats.robust_sigma(sub, S, t, info)
    assert robust == pytest.approx(abs(b / t), rel=1e-6)
    centred = 1.0 / np.sqrt((x - x.mean()) @ (x - x.mean()))  # white: the iid sigma of b
    assert 0.7 < robust / centred < 1.4, (robust, centred)
    assert abs(c / t) > 3.0 * robust, (c, t, robust)  # the old sigma here
    h = flexure.hiding({"t": t, "arcsec_per_g": c, "p_value": 0.5, "nu": 30.0,
                        "sigma_arcsec_per_g": 1 / np.sqrt(info),
                        "robust_sigma_arcsec_per_g": robust}, ["gyro_scale_factor"], 1, 0.01)
    assert h["sigma_arcsec_per_g"] == pytest.approx(max(robust, 1 / np.sqrt(info)))


def test_flexure_printed_sigma_holds_the_error_a_frames_stars_share():
    """The flexure's printed σ against its scatter over seeds (issue 21 item 2).  The
    response is a turn of the whole tracker, alike on every star of a frame, and a frame's
    stars share part of their innovation (the predicted attitude error), which the
    whitening star by star does not see: ``1/√info`` (printed until 2026-11-28) was 4 %
    small on swaying 200 s, 9 % on psce (doc/benchmarks.md).  Here 100 null tables of 120
    frames x 12 stars whose stated variance is right but a tenth of it is the frame's (1 +
    11 x 0.1 = 2.1 times the variance the whitened σ assumes), the response a sway of 14
    frames: the printed σ is the estimate's scatter (main: 0.77 of it); the whitened one is
    kept, and the MDB's σ is still the larger of the two."""
    from stellar_cal_ros.core.units import ARCSEC

    rng = np.random.default_rng(123)
    frames, stars, sd, share = 120, 12, 0.05, 0.1
    k = np.repeat(np.arange(frames), stars)
    n = len(k)
    per = flexure.PROBE / ARCSEC
    pattern = np.stack([np.sin(2 * np.pi * k / 14.0), np.cos(2 * np.pi * k / 14.0)], 1) * sd
    pattern *= 1.0 + 0.05 * rng.standard_normal((n, 1))  # not exactly alike on every star
    base = {"t": k * 0.5, "frame": k, "catalog_id": np.tile(np.arange(stars), frames),
            "gated": np.zeros(n, bool), "s_uu": np.full(n, sd**2), "s_uv": np.zeros(n),
            "s_vv": np.full(n, sd**2), "gravity_x_st": np.linspace(-0.3, 0.3, n),
            "gravity_y_st": np.zeros(n)}
    got = []
    for _ in range(100):
        shared = np.sqrt(share) * sd * rng.standard_normal((frames, 2))[k]
        white = np.sqrt(1.0 - share) * sd * rng.standard_normal((n, 2))
        res = dict(base, du=shared[:, 0] + white[:, 0], dv=shared[:, 1] + white[:, 1])
        moved = dict(res, du=res["du"] + per * pattern[:, 0], dv=res["dv"] + per * pattern[:, 1])
        got.append(flexure.remainder_statistics(res, moved, 1.0))
    c = np.array([g["arcsec_per_g"] for g in got])
    printed = np.array([g["sigma_arcsec_per_g"] for g in got])
    # the scatter's own error over 100 seeds is 7 %; main printed 1/sqrt(info): ratio 1.30
    assert 0.85 < c.std(ddof=1) / printed.mean() < 1.15, (c.std(ddof=1), printed.mean())
    whitened = np.array([g["whitened_sigma_arcsec_per_g"] for g in got])
    assert np.allclose(whitened, 1.0 / np.sqrt(float(np.sum((pattern / sd) ** 2))))
    assert np.sqrt(2.1) * 0.9 < printed.mean() / whitened.mean() < np.sqrt(2.1) * 1.1
    h = flexure.hiding(got[0], ["gyro_scale_factor"], 1, 0.01)
    assert h["sigma_arcsec_per_g"] == max(whitened[0], got[0]["robust_sigma_arcsec_per_g"])


def test_an_add_that_takes_the_flexure_tests_power_is_marked():
    """``flexure.alias``: an add that took up a significant gravity-shaped remainder is
    that remainder's explanation only if the test after it could still see a flexure of
    the size found before it (its MDB below it); else it is marked "could be a mount
    flexure (outside the library): this motion cannot separate them", in the terminal's
    and the report's one phrasing.  The numbers: the 200 s flexure + true gyro scale
    factor bag's tests (``benchmarks/flexure_beyond_discover.py mixed``)."""
    from stellar_cal_ros.diagnosis import printing

    before = {"t": 7.7, "p_value": 2.9e-5, "nu": 12.0, "arcsec_per_g": 40.9,
              "sigma_arcsec_per_g": 4.3, "robust_sigma_arcsec_per_g": 5.3}
    blind = {"t": -1.2, "p_value": 0.27, "nu": 12.0, "arcsec_per_g": -40.0,
             "sigma_arcsec_per_g": 28.6, "robust_sigma_arcsec_per_g": 33.0}
    a = flexure.alias(before, blind, 2, 0.01)
    from stellar_cal_ros.diagnosis.reliability import delta_t

    assert a["mdb_after_arcsec_per_g"] == pytest.approx(33.0 * delta_t(0.005, 12.0, 0.5)) \
        and a["mdb_after_arcsec_per_g"] > 40.9 and a["power"] == 0.5, a
    # the test after it sees 40.9"/g with power > 50 % (its robust sigma 12: 50 % power
    # at ~3.35 sigma): the remainder was the effect's, nothing is marked; at 13 it is
    for sigma, marked in ((12.0, False), (13.0, True)):
        after = dict(blind, sigma_arcsec_per_g=2.0, robust_sigma_arcsec_per_g=sigma)
        got = flexure.alias(before, after, 2, 0.01)
        assert (got is not None) is marked, (sigma, got)
    a["text"] = text = flexure.alias_text("gyro_misalignment", a)
    assert text.startswith("gyro_misalignment could be a mount flexure (outside the "
                           "library): this motion cannot separate them"), text
    summary = {"remainder": {"could_be_flexure": {"gyro_misalignment": a}}}
    assert printing.added_caveat(summary, "gyro_misalignment").endswith(flexure.ALIAS_TEXT)
    assert printing.added_caveat(summary, "gyro_scale_factor") == ""
    step = {"action": "add", "could_be_flexure": a, "added": {
        "effect": "gyro_misalignment", "score": 80.0, "p_value": 1e-12}}
    assert "could be a mount flexure" in printing.describe(step)


def test_a_field_that_loses_power_beside_a_candidate_has_not_vanished():
    """The stand-in rule (``rolling.stand_in`` through ``leads.stand_in``) on the numbers of
    ``benchmarks/flexure_remainder.py --sizes 80`` and ``--sizes 40`` (300 s, seed 52,
    doc/benchmarks.md).  80″/g, round 2 (gyro_scale_factor in the model): the gravity field
    reads 83.27 ± 3.44″/g; beside gyro_misalignment (Λ 919.8, ratio beyond the field −2.59
    for 6 dof) it reads 57.71 ± 23.19″/g, t 2.50, p 0.029, ν 11.5: not significant, but
    1.1 σ from what it was: the pair gsf + misalignment spans the flexure and the test lost
    its power, the flexure did not go.  Until this rule the candidate was added (main
    eacb4e8: discover ended on gyro_scale_factor + gyro_misalignment, no 'unexplained'
    line).  40″/g, round 1: 40.03 -> 18.89 ± 4.42″/g beside gyro_misalignment, t 4.10, p
    0.035 on ν 2.59: the fall toward 0, 4.8 σ, is p 0.012 on that ν (one-sided), not
    significant at 1 % either: refused.  A true gyro scale factor after a time offset
    (``test_auto_with_two_dask_workers_chooses_as_one_worker``'s bag, 120 s): −26.48 ->
    −5.98 ± 5.77″/g on ν 6.45, p 0.0053: gone, the true effect is added.  A field
    that is gone (a true cause beside it: the size at 0, far from the size before) still
    lets the candidate in, and a fit without a comparable
    size keeps the old reading (not significant is gone)."""
    from types import SimpleNamespace

    from stellar_cal_ros.diagnosis import leads, rolling

    lead = {"t": 24.217, "p_value": 3.56e-11, "chi2_capped": 984.05, "size_px": 0.0829,
            "coef": 83.265, "coef_sigma": 3.440, "coef_nu": 11.42}
    beside = {"t": 2.4956, "p_value": 0.02888, "chi2_capped": 5.47, "coef": 57.707,
              "coef_sigma": 23.191, "coef_nu": 11.514}
    disp = (984.05 - 5.47) / (919.8 + 2.59)  # the run's ratio beyond the field: -2.59
    c = SimpleNamespace(statistic=919.8, dof=6)
    b = leads.stand_in(c, disp, beside, lead, "gravity", 0.01)
    assert b is not None and not b["needed"] and b["negative"], b
    assert b["statistic"] == pytest.approx(-2.59, abs=0.01) and b["lead"] == "gravity", b
    assert not rolling.vanished(beside, lead, 0.01)
    assert stats.size_changed(beside, lead, 0.01) is False
    # the old rule (not significant beside it = gone) let it in
    old = {k: v for k, v in beside.items() if not k.startswith("coef")}
    assert leads.stand_in(c, disp, old, lead, "gravity", 0.01) is None
    # 40"/g: half the field taken, the rest 4.1 sigma from 0 and 4.8 from before, on nu 2.6
    before40 = dict(lead, coef=40.034, coef_sigma=3.46, coef_nu=11.0)
    beside40 = dict(beside, t=4.1045, p_value=0.03457, coef=18.890, coef_sigma=4.419,
                    coef_nu=2.588)
    assert not rolling.vanished(beside40, before40, 0.01)
    assert rolling.vanished(dict(beside40, coef_nu=30.0), before40, 0.01)  # on 30 dof: gone
    true = {"t": -1.322, "p_value": 0.231, "coef": -5.977, "coef_sigma": 5.771,
            "coef_nu": 6.446}
    assert rolling.vanished(true, {"coef": -26.476}, 0.01)
    # grown beside it (away from 0) is not gone
    assert not rolling.vanished(dict(true, coef=-47.0), {"coef": -26.476}, 0.01)
    # a true cause: the field at 0 beside it
    gone = dict(beside, t=0.3, p_value=0.77, coef=1.2, coef_sigma=4.0)
    assert rolling.vanished(gone, lead, 0.01)
    assert leads.stand_in(c, disp, gone, lead, "gravity", 0.01) is None
    # still significant beside it: refused whatever its size
    assert not rolling.vanished(dict(gone, p_value=1e-4), lead, 0.01)


def test_a_field_of_many_columns_no_longer_significant_beside_a_library_effect_is_gone():
    """Issue 21 items 2/3: a library effect at its printed MDB, refused beside a cells lead.
    Unseen case ``twin_s07_aspect1`` seed 22 (``benchmarks/unseen_cases.py``: pixel_aspect
    at 1x its MDB, 14.8 ppm, on a twin whose σ field is 0.7x the truth): pixel_aspect
    significant alone (35.8, p 4.3e-9), its ratio beyond the per-cell field 0.64 (1 dof);
    the field's lead t 3.79 (p 4.7e-4) -> 1.75 beside it (p 0.088, 0.26 over the 3
    fields), its size 0.271 -> 0.159 ± 0.073 on ν 43: a 1.5 σ fall, not 'fallen' at 1 %,
    so main refused the aspect ('not vanished') and printed 'v residual vs v (row)' t 5.3,
    the aspect's own shape.  The nested question is whether the field (288 columns over
    the window's quarters) is still significant beside the effect (1 dof) at the level that
    made it a lead: it is not, so the aspect is added (now: 17.6 ± 2.3 ppm, nothing
    unexplained).  Fails on main (refused).  The same rule keeps refusing where the field
    stays (unseen case ``quadrant`` s21: image_plane_tilt beside the cells field t 27.1 ->
    20.8, p 1.8e-29) and says so in the refusal's line; a one-pattern field (the gravity
    field, ``test_a_field_that_loses_power_beside_a_candidate_has_not_vanished``) keeps the
    size rule.  The synthetic half: a row-proportional shift (an aspect) of 0.012 px at the
    detector's edge read by the cells field (t 3.61, family p 0.0028), half of it left
    beside a candidate (t 1.97, family p 0.17, size 0.367 -> 0.295 ± 0.11): gone."""
    from types import SimpleNamespace

    from stellar_cal_ros.diagnosis import leads, rolling

    def measured(stat, ratio, lead_t, lead_p, coef, beside_t, beside_p, beside_coef, sigma,
                 nu, columns=288):
        lead = {"t": lead_t, "p_value": lead_p, "chi2_capped": 400.0, "size_px": 0.0077,
                "coef": coef, "coef_sigma": 0.07, "coef_nu": 43.0, "columns": columns}
        beside = {"t": beside_t, "p_value": beside_p, "chi2_capped": 400.0 + ratio - stat,
                  "coef": beside_coef, "coef_sigma": sigma, "coef_nu": nu,
                  "columns": columns}
        return lead, beside

    aspect = SimpleNamespace(statistic=35.8, dof=1)
    lead, beside = measured(35.8, 0.6446, 3.7858, 4.694e-4, 0.27142, 1.74695, 0.087786,
                            0.15927, 0.073316, 43.087)
    b = flexure.beyond(aspect.statistic, aspect.dof, 1.0, beside, lead)
    assert b["statistic"] == pytest.approx(0.6446, abs=1e-6) and not b["needed"], b
    assert stats.size_changed(beside, lead, 0.01) is False  # main's reading: not vanished
    assert not rolling.vanished(beside, lead, 0.01)  # (the one-pattern rule)
    assert leads.stand_in(aspect, 1.0, beside, lead, "cells", 0.01) is None  # main: refused
    assert leads.vanished(beside, lead, 1, 0.01)
    held, kept = lead, beside
    # significant beside it at 1 %, not at the fields' level (x4, leads.NAMES): still gone
    assert leads.vanished(dict(beside, p_value=0.005), lead, 1, 0.01)
    assert not leads.vanished(dict(beside, p_value=0.002), lead, 1, 0.01)
    # quadrant s21: the field stays beside the tilt: refused, and the line says so
    tilt = SimpleNamespace(statistic=40.0, dof=2)
    lead, beside = measured(40.0, -3.25, 27.12, 1e-40, 0.863, 20.81, 1.79e-29, 0.627, 0.033,
                            40.0)
    assert not leads.vanished(beside, lead, 2, 0.01)
    b = leads.stand_in(tilt, 1.0, beside, lead, "cells", 0.01)
    assert b is not None and b["lead"] == "cells" and b["negative"], b
    assert b["beside"] == {"t": 20.81, "p_value": pytest.approx(4 * 1.79e-29),
                           "kept": "significant"}
    assert rolling.beside_text(b, "a per-cell offset field") == (
        "; a per-cell offset field still significant beside it (t=20.81, p=7.2e-29)")
    # a field of no more columns than the candidate's dof: the size rule
    assert not leads.vanished(kept, dict(held, columns=1), 1, 0.01)

    rng = np.random.default_rng(4)

    def run(shift: float) -> dict:
        res = _table(rng, frames=240, stars=16)
        n = len(res["du"])
        res["u"], res["v"] = rng.uniform(0.0, 1024.0, n), rng.uniform(0.0, 1024.0, n)
        res["dv"] = res["dv"] + shift * (res["v"] - 512.0) / 512.0
        return res

    base = run(0.012)
    own = leads.field_fit(base, 0.5, "cells")
    assert leads.significant({"cells": own}, 0.01) and own["columns"] == 288, own
    half = leads.field_fit(run(0.006), 0.5, "cells", along=leads.direction(base, 0.5, "cells"))
    assert 3 * half["p_value"] > 0.01 and stats.size_changed(half, own, 0.01) is False, half
    assert leads.vanished(half, own, 1, 0.01) and not rolling.vanished(half, own, 0.01)


def test_a_field_that_keeps_its_size_beside_a_stand_in_still_refuses_it():
    """A guard on the stand-in rule (``leads.stand_in``): a field whose size along its
    pattern does not fall beside a candidate still refuses it.  Unseen case ``sway_flex``
    s21 (a 10″/g mount flexure on the swaying base, no library effect): round 1's gravity
    lead t 20.06, 8.557 ± 0.426″/g; beside gyro_scale_factor (Λ 85.1, ratio beyond the
    field −12.89 for 3 dof) it reads 9.123 ± 0.644″/g, t 14.17, and beside
    gyro_misalignment (Λ 24.4, −2.83 for 6 dof) 8.930 ± 0.481″/g, t 18.59: both larger,
    and both stand-ins (the flexure is the truth; naming it gyro_scale_factor −46 ppm was
    the bug the gravity lead fixed).  A rule "a field the candidate took none of refuses
    nothing" (tried for ``sway_sky_twin_gsf1`` s21, H303) would add them; so would it
    ``flex20`` s22's gyro_scale_factor (19.67 → 21.35″/g beside it).  The dispersion is
    taken as 1, the capped gain beside the candidate set to give the run's ratio."""
    from types import SimpleNamespace

    from stellar_cal_ros.diagnosis import leads, rolling

    lead = {"t": 20.063, "p_value": 6.15e-22, "nu": 38.35, "chi2_capped": 260.965,
            "size_px": 0.0320, "coef": 8.5574, "coef_sigma": 0.4261, "coef_nu": 38.35}
    for stat, dof, ratio, t, coef, sigma, nu in ((85.1, 3, -12.887, 14.166, 9.1225, 0.6443,
                                                  46.00),
                                                 (24.4, 6, -2.834, 18.586, 8.9303, 0.4807,
                                                  39.43)):
        c = SimpleNamespace(statistic=stat, dof=dof)
        beside = {"t": t, "p_value": 1e-15, "chi2_capped": 260.965 + ratio - stat,
                  "coef": coef, "coef_sigma": sigma, "coef_nu": nu}
        assert (beside["coef"] - lead["coef"]) > 0  # the field no smaller beside it
        assert not rolling.vanished(beside, lead, 0.01)
        b = leads.stand_in(c, 1.0, beside, lead, "gravity", 0.01)
        assert b is not None and b["lead"] == "gravity" and b["negative"], b
        assert b["statistic"] == pytest.approx(ratio, abs=1e-6), b
        assert b["beside"]["kept"] == "significant", b


@pytest.mark.parametrize("size, named", [(80.0, ["gyro_scale_factor"]), (40.0, [])])
def test_a_large_flexure_is_not_named_as_two_gyro_effects(tmp_path, size, named):
    """Issue 21 item 3: a 40″/g and an 80″/g flexure, 300 s of psce_rotations (seed 52),
    discover.  Main eacb4e8 named the 80″/g one gyro_scale_factor + gyro_misalignment with
    no 'unexplained' line, and the 40″/g one gyro_scale_factor (gyro_misalignment added
    beside a field that lost power, then exchanged for the gyro_scale_factor refused
    beside it).  Now gyro_misalignment is refused at both (the field beside it is not
    gone, only weaker: ``rolling.vanished``) and the first 'unexplained' line is the
    gravity field, its flexure within 2 σ (robust) of the truth: measured 83.27 ± 3.44 and
    40.03 ± 3.46″/g.  At 80″/g gyro_scale_factor is still added: it explains 60.9 (3 dof)
    beyond the linear field, the filter's response to 80″/g being second order in part
    (``benchmarks/flexure_read.py``; doc/benchmarks.md, cause 1); no exchange brings back
    a refused stand-in.

    Reduced (~6 CPU-s each): the noise as stated and the two candidates that take the
    flexure up (all candidates, noise estimated: ``benchmarks/flexure_remainder.py
    --sizes 80,40``, the same adds)."""
    sim, data = _simulate({"mount_flexure": size}, 52, duration=300.0)
    base = replay_psce(data, sim.prior)
    summary = diagnose(data, base.calibration, "psce", [], tmp_path / "rep", auto=True,
                       candidates=["gyro_scale_factor", "gyro_misalignment"], plots=False,
                       verbose=False, noise="stated")
    assert summary["added"] == named, summary["added"]
    assert not any(s["action"] == "exchange" for s in summary["path"]), summary["path"]
    refused = summary["path"][-1]["beyond_remainder"]
    assert "gyro_misalignment" in refused and refused["gyro_misalignment"]["lead"] == \
        "gravity", refused
    first = summary["unexplained"][0]
    assert first["regressor"].startswith("gravity_st") and first["p_value"] < 0.01, first
    d = first["detail"]
    sigma = d["robust_sigma_arcsec_per_g"]
    assert abs(d["arcsec_per_g"] - size) < 2.0 * sigma, (d["arcsec_per_g"], sigma)


def test_mount_flexure_is_unexplained_and_no_stand_in_is_added_for_it(tmp_path, flexure_bag):
    """Mount bending with gravity (outside the library), ``discover``: the gyro scale factor
    that takes up ~98 % of it on this motion is significant alone, but the gravity field
    (the flexure probe's response on the baseline, ``leads.gravity_of``) is a lead and the
    scale factor explains nothing beyond it (ratio 8.7 for 3 dof, p 0.034): it is *not*
    added, nothing is, and the field is the first 'unexplained' line, sized in px, with the
    flexure that would leave it within 3 sigma of the truth.  Until 2026-11-27 (main
    ea90b97) the scale factor was added and flagged as standing in for the remainder the
    test after it found (the rule acted only after an add).

    Reduced (~4 CPU-s): 200 s, the noise as stated and the two candidates that absorb it
    (all candidates, 300 s, noise estimated: ``benchmarks/flexure_remainder.py``,
    doc/benchmarks.md).  The nulls: a true gyro scale factor / misalignment is added with
    no remainder (every ``test_missing_effect_ranks_first_and_adding_it_fixes`` case of a
    non-camera effect asserts no remainder; doc/benchmarks.md for discover on them).
    """
    truth = FLEXURE
    sim, data, base = flexure_bag
    summary = diagnose(data, base.calibration, "psce", [], tmp_path / "rep", auto=True,
                       candidates=["gyro_scale_factor", "gyro_misalignment"], plots=False,
                       verbose=False, noise="stated")
    assert summary["added"] == [], summary["added"]
    first = summary["unexplained"][0]
    assert first["regressor"].startswith("gravity_") and first["p_value"] < 0.01, first
    # the time offset x time test fitted with the flexure's gravity columns (diagnosis.clock):
    # measured chi2 10.4 / 5 dof, p 0.064 unadjusted (alone, without them: 142, p 7e-27)
    assert summary["clock_change"]["p_value"] > 1e-3, summary["clock_change"]
    assert 0.1 < first["change_px"] < 0.3, first  # measured 0.19 px (the whole flexure)
    d = first["detail"]
    assert d["field"] == "gravity", d
    assert abs(d["arcsec_per_g"] - truth) < 3.0 * d["sigma_arcsec_per_g"], d  # 39.8 +- 0.69
    # gyro_scale_factor beside the fitted flexure, both terms NIS-capped: measured 8.7
    # (chi2, 3 dof, p 0.034: not significant at 1 %), the field still t 7.7 beside it
    step = summary["path"][-1]
    b = step["beyond_remainder"]["gyro_scale_factor"]
    assert not b["needed"] and b["lead"] == "gravity", b
    beside = step["beside_leads"]["gyro_scale_factor"]["gravity"]
    assert beside["beside_p_value"] < 0.01 and beside["lead_t"] > 10, beside
    assert summary["recommendation"] is None and summary["reliability"], summary.keys()
    rejected = {r["effect"]: r["reason"] for r in summary["rejected"]}
    assert "beyond the gravity-shaped remainder" in rejected["gyro_scale_factor"], rejected
    text = "\n".join(summary["terminal"])
    assert "outside the library" in text and "arcsec per unit lateral gravity" in text, text
    # the remainder is said, so no "could still hide" bound is printed; the bound the
    # report prints when the test finds nothing (flexure.hiding: its MDB in "/g), on this
    # bag's test: the estimate is within 3 of the sigma the MDB is made of
    assert summary["flexure_hiding"] is None and "could still hide with this motion" not in text
    h = flexure.hiding(d, [], 1, 0.01)
    assert h["sigma_arcsec_per_g"] >= d["sigma_arcsec_per_g"], h
    assert abs(h["estimate_arcsec_per_g"] - truth) < 3.0 * h["sigma_arcsec_per_g"], h
    assert 2.5 * h["sigma_arcsec_per_g"] < h["arcsec_per_g"] < truth, h
    # that the MDB is the size this test detects with power 80 % is checked by injecting a
    # flexure of the printed size (test_flexure_power.py); the t_nu power at MDB / sigma
    # asserted here until 2026-11-27 held by construction (MDB = sigma delta_80)
    assert 5.0 < d["nu"] < 200.0, d["nu"]
    said = flexure.hiding_text(h)
    assert said.startswith("a mount flexure (outside the library) up to ") and \
        "could still hide with this motion" in said, said


def test_gravity_regressor_follows_the_tracker_attitude():
    """The added gravity columns equal the true lateral gravity in the tracker frame."""
    from stellar_cal_ros.diagnosis.context import add_gravity_regressors
    from stellar_cal_ros.sim.world import TruthWorld

    sim, data = _simulate({}, 53, duration=150.0)
    base = replay_psce(data, sim.prior)
    res = add_gravity_regressors(base.residuals, data, sim.truth)
    world = TruthWorld(sim.scenario, 150.0, sim.effects)
    t_rel = res["t"] - data.t0
    R_i_st = world.R_i_b(t_rel) @ world.installation().as_matrix()
    g_i = world.R_i_e(t_rel) @ world.gravity_e
    g_st = np.einsum("nji,nj->ni", R_i_st, g_i)
    g_st /= np.linalg.norm(g_st, axis=1, keepdims=True)
    # the specific force includes the slews' accelerations (frames within a slew)
    for k, col in enumerate(("gravity_x_st", "gravity_y_st")):
        err = np.abs(res[col] - g_st[:, k])
        assert np.percentile(err, 90) < 2e-4, col  # at rest
        assert np.max(err) < 1e-2, col  # within a slew
    assert np.ptp(res["gravity_y_st"]) > 0.3  # the steps do move gravity in the image


def _reduced_spec(dropped):
    """The PSCE method with ``dropped`` removed from its baseline."""
    spec = method_spec("psce")
    baseline = tuple(e for e in spec.baseline if e != dropped)
    return DiagnosisSpec(spec.name, baseline, spec.stages,
                      lambda d, p, e, **kw: replay_psce(d, p, e, baseline=baseline, **kw))


@pytest.mark.parametrize("dropped", [
    "tangential", pytest.param("radial_k1k2", marks=pytest.mark.benchmark)])
def test_dropped_baseline_effect_ranks_first(dropped):
    """A model lacking a baseline effect: the diagnosis names that effect."""
    sim, data = _simulate({}, 54)  # the scenario has Tan et al.'s radial + tangential terms
    spec = _reduced_spec(dropped)
    base = spec.runner(data, sim.prior, [])
    assert dropped not in base.filter.model.slices
    _, results = rank_candidates(data, base.calibration, spec, [])
    ranked = [c for c in results if c.status == "ranked"]
    assert ranked[0].effect == dropped and ranked[0].significant, [
        (c.effect, c.statistic) for c in ranked[:3]]
    assert max(ranked[0].rms_after_px) <= 1.05 * NOISE


@pytest.mark.benchmark
def test_clean_data_false_alarm_rate_all_candidates(tmp_path):
    """Clean data, every applicable candidate: nothing significant in >= 95 % of seeds."""
    seeds = range(30, 50)
    false = 0
    for seed in seeds:
        sim, data = _simulate({}, seed, duration=FULL_S)
        base = replay_psce(data, sim.prior)
        s = diagnose(data, base.calibration, "psce", [], tmp_path / str(seed), plots=False,
                     verbose=False)
        false += any(c["significant"] for c in s["candidates"])
    print(f"\nfalse alarms: {false} of {len(seeds)}")
    assert false <= 0.05 * len(seeds) + 1e-9


def test_a_catalogue_at_another_epoch_is_said_with_its_epoch(tmp_path):
    """Proper motion at 0.4 of the motion since J2000.0 (messages' places at epoch 2016: a
    Gaia catalogue) is fitted at its fraction and the line says the epoch it means (unseen
    case ``sky_epoch2016``: "has another cause" alone before)."""
    from stellar_cal_ros.core.catalog import posix_to_jyear

    sim, data = _simulate({"proper_motion": 0.4}, 49, duration=SHORT_S["proper_motion"])
    base = replay_psce(data, sim.prior)
    summary = diagnose(data, base.calibration, "psce", [], tmp_path / "rep", plots=False,
                       verbose=False, candidates=["proper_motion"])
    pm = next(c for c in summary["implausible"] if c["effect"] == "proper_motion")
    f, sf = pm["estimate"]["scale"], pm["sigma"]["scale"]
    assert abs(f - 0.4) < 3 * sf, (f, sf)
    date = float(posix_to_jyear(base.calibration.stamp))
    epoch = float(pm["reason"].split("epoch J")[1].split(",")[0])
    assert epoch == pytest.approx(date - f * (date - 2000.0), abs=0.05)
    assert abs(epoch - (date - 0.4 * (date - 2000.0))) < 3 * sf * (date - 2000.0) + 0.05


def test_a_cells_field_measured_along_the_current_models_direction_on_a_candidates_rows():
    """The stand-in rule's cells half (``leads.field_fit(along=)``, ``leads.direction``):
    along its own direction a run's size is its plain fit's; a candidate's run where the
    field is gone reads ~0 and has vanished (``rolling.vanished``); one where it is intact
    has not, though on the same rows (a reviewer's synthetic check, now a test)."""
    from stellar_cal_ros.diagnosis import leads, rolling

    rng = np.random.default_rng(11)

    def run(step: float, low: bool = False) -> dict:
        res = _table(rng, frames=240, stars=16)
        n = len(res["du"])
        res["u"] = rng.uniform(0.0, 1024.0, n)
        res["v"] = rng.uniform(0.0, 1024.0, n)
        on = (res["u"] < 512) & (res["v"] < 512) if low else (res["u"] > 512) & (res["v"] > 512)
        res["du"] = res["du"] + step * on
        return res

    base = run(0.03)  # 0.6 σ on a quadrant
    own = leads.field_fit(base, 0.5, "cells")
    assert own is not None and own["p_value"] < 1e-6, own
    d = leads.direction(base, 0.5, "cells")
    along = leads.field_fit(base, 0.5, "cells", along=d)
    assert along["coef"] == own["coef"] and along["coef_sigma"] == own["coef_sigma"]
    gone = leads.field_fit(run(0.0), 0.5, "cells", along=d)
    assert abs(gone["coef"]) < 4 * gone["coef_sigma"], gone
    assert rolling.vanished(gone, own, 0.01) is True
    kept = leads.field_fit(run(0.03), 0.5, "cells", along=d)
    assert abs(kept["coef"] - own["coef"]) < 4 * kept["coef_sigma"], (kept, own)
    assert rolling.vanished(kept, own, 0.01) is False
    # the size is the one along ``along``: along another quadrant's field it is ~0
    other = leads.field_fit(kept_rows := run(0.03), 0.5, "cells",
                            along=leads.direction(run(0.03, low=True), 0.5, "cells"))
    plain = leads.field_fit(kept_rows, 0.5, "cells")
    assert abs(other["coef"]) < 4 * other["coef_sigma"] < abs(plain["coef"]), (other, plain)
