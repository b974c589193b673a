"""Every number of "what could still be hiding" checked by injection (issue 21 item 2).

The diagnosis prints, per library effect not in the model, its minimal detectable size
(MDB) and the shift an undetected effect of that size leaves in the estimated parameters.
Here each claim is injected into the same simulated bag (same seed: the paired difference
cancels the noise) at the printed size and the current model is re-run:

* the shift of every quantity the report lists is within 30 % of the printed bias (the
  issue's case: a gyro misalignment's printed installation bias was ~60x what an injection
  of its MDB does);
* the score statistic's non-centrality, from the paired score difference, is the λ₀ the
  MDB was computed for (so the test has its stated power there; the power over seeds is
  ``benchmarks/reliability_injection.py``).

The reduced form of the benchmark: one 150 s bag, each candidate of PSCE once.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from stellar_cal_ros.diagnosis import (
    injection,
    printing,
    reliability,
    reliability_probe,
    screening,
)
from stellar_cal_ros.diagnosis.discover import ALPHA, rerun_prior
from stellar_cal_ros.diagnosis.run import diagnose
from stellar_cal_ros.diagnosis.screening import kernel_scores
from stellar_cal_ros.effects import registry
from stellar_cal_ros.methods.replay import bag_data_from_simulation, replay
from stellar_cal_ros.methods.screening import score_tests
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate

DURATION, SEED = 150.0, 5


def _data(effects=None):
    sim = simulate(get_scenario("psce_rotations"), duration=DURATION, seed=SEED,
                   effects=effects or {}, paired_with={} if effects else None)
    return sim, bag_data_from_simulation(sim)


EFFECTS = ["gyro_misalignment", "gyro_scale_factor", "time_offset", "pixel_aspect",
           "thermal_focal_length", "refraction", "aberration", "proper_motion", "radial_k3",
           "image_plane_tilt"]


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    sim, data = _data()
    summary = diagnose(data, sim.prior, "psce", [], tmp_path_factory.mktemp("clean"),
                       plots=False, verbose=False)
    prior = rerun_prior(sim.prior)
    # one run scores every candidate (consider parameters leave the filter alone, and each
    # candidate's score uses its own block: the same numbers as one run per candidate)
    base = replay(data, prior, "psce", [], consider=EFFECTS, keep_tables=False)
    return sim, data, summary, prior, base


def _score(result, eid):
    c = score_tests(result, [eid])[eid]
    return c.info @ c.estimate, c.info


def test_a_small_bias_beside_a_large_shift_is_a_first_order_remainder():
    """The tilt case below: at its MDB the installation moves ~100 sigma and the printed
    gyro-bias shift (1.2 sigma) is a remainder the filter does not reproduce.  A bias above
    its sigma but below FIRST_ORDER_SHARE of the same parameter's largest shift (in sigmas)
    is said apart, not listed; a bias beside shifts of its own size is listed."""
    det = reliability.detectability("image_plane_tilt", np.diag([4e5, 4e5]), 1e-3)
    size = min(det.mdb["tau_x"], det.plausible[0])
    assert size == min(det.mdb["tau_y"], det.plausible[1])
    sigma = {"installation.rx": 1e-4 * size, "gyro_bias.by": 1e-8 * size,
             "tangential.p1": 1.0e-6 * size}
    rows = {"installation.rx": np.array([30e-4, 0.0]),  # 30 sigma
            "gyro_bias.by": np.array([-1.2e-8, 0.0]),  # 1.2 sigma: 0.04 of the largest
            "tangential.p1": np.array([0.0, 2e-6])}  # 2 sigma: tau_y's largest
    out = reliability.external_reliability(det, rows, sigma)
    assert out["dominates"] == ["installation.rx", "tangential.p1"]
    assert out["remainders"] == ["gyro_bias.by"]
    assert out["largest_shift_sigma"]["tau_x"] == pytest.approx(30.0)
    assert out["sigma"]["gyro_bias.by"] == sigma["gyro_bias.by"]
    assert injection.claims(out) == {"tau_x": ["installation.rx"], "tau_y": ["tangential.p1"]}
    text = "\n".join(printing.reliability_lines([out]))
    assert "first-order remainders" in text and "gyro_bias.by" in text
    _same_words_in_the_report(out, text)


def test_a_probe_run_replaces_the_rows_the_first_order_does_not_hold():
    """The flagged rows of an entry take the probe's measured shifts at +-size.

    A row the probe confirms within 30 % at both signs keeps its first-order value; one it
    does not takes the measured shifts (the larger magnitude decides its listing, each
    sign's own value is what an injection of that sign is checked against); a row listed
    at first order and measured below its sigma at both signs is no longer listed."""
    det = reliability.detectability("image_plane_tilt", np.diag([4e5, 4e5]), 1e-3)
    size = min(det.mdb["tau_x"], det.plausible[0])
    sigma = {"installation.rx": 1e-4 * size, "gyro_bias.by": 1e-8 * size,
             "radial_k1k2.k2": 1e-2 * size}
    rows = {"installation.rx": np.array([30e-4, 0.0]),
            "gyro_bias.by": np.array([-1.2e-8, 0.0]),  # a remainder: flags tau_x
            "radial_k1k2.k2": np.array([1.4e-2, 0.0])}  # 1.4 sigma: a remainder too
    entry = reliability.external_reliability(det, rows, sigma)
    assert reliability_probe.flagged(entry) == ["tau_x"]
    plus = {"installation.rx": 31e-4 * size, "gyro_bias.by": 0.1e-8 * size,
            "radial_k1k2.k2": 0.5e-2 * size}
    minus = {"installation.rx": -29e-4 * size, "gyro_bias.by": 0.02e-8 * size,
             "radial_k1k2.k2": -1.5e-2 * size}
    reliability_probe.apply(entry, "tau_x", plus, minus, sigma)
    assert entry["biases_signed"]["installation.rx"] == pytest.approx(30e-4 * size)  # kept
    assert entry["dominates"] == ["installation.rx", "radial_k1k2.k2"]
    assert entry["remainders"] == []
    assert entry["probe"]["tau_x"]["unlisted"] == ["gyro_bias.by"]
    assert injection.printed_shift(entry, "radial_k1k2.k2", 1) == pytest.approx(0.5e-2 * size)
    assert injection.printed_shift(entry, "radial_k1k2.k2", -1) == pytest.approx(-1.5e-2 * size)
    assert injection.printed_shift(entry, "installation.rx", -1) == pytest.approx(-30e-4 * size)
    # claimed where the printed shift at that sign exceeds sigma
    assert injection.claims(entry, 1) == {"tau_x": ["installation.rx"]}
    assert injection.claims(entry, -1) == {"tau_x": ["installation.rx", "radial_k1k2.k2"]}
    text = "\n".join(printing.reliability_lines([entry]))
    assert "at -MDB" in text and "measured by a probe run" in text and "gyro_bias.by" in text
    _same_words_in_the_report(entry, text)


def test_the_probe_split_over_workers_gives_the_rows_of_one_call(monkeypatch):
    """On several workers the probe's (effect, parameter) pairs go out as parts (each with
    both signs, one ``Runs.later`` each: started before the line tests); the entries come
    out as from one call."""
    import copy
    from types import SimpleNamespace

    from stellar_cal_ros.diagnosis.runstats import RunSummary

    det = reliability.detectability("image_plane_tilt", np.diag([4e5, 4e5]), 1e-3)
    size = min(det.mdb["tau_x"], det.plausible[0])
    sigma = {"installation.rx": 1e-4 * size, "gyro_bias.by": 1e-8 * size}
    rows = {"installation.rx": np.array([30e-4, 0.0]), "gyro_bias.by": np.array([-1.2e-8, 0.0])}
    entry = reliability.external_reliability(det, rows, sigma)
    base = RunSummary(effects=(), names=list(sigma), theta=np.zeros(2), P=np.eye(2),
                      calibration=object(), prior=object())

    def measured(data, *args):  # a stand-in for the probe's runs: values of the injection
        return [{"installation.rx": 40.0 * d[0], "gyro_bias.by": 1e-6 * d[0] ** 2}
                for _, d in args[-1]]

    def entries() -> list:  # three pairs, each injected at its own size
        out = [copy.deepcopy(entry) for _ in range(3)]
        for k, e in enumerate(out):
            e["hidden_size"]["tau_x"] *= k + 1
        return out

    monkeypatch.setattr(reliability_probe, "measure_on_bag", measured)
    got, parts = [], []
    for workers in (1, 2, 3):
        def later(fn, *args, workers=workers):
            parts.append((workers, len(args[-1])))
            return lambda: fn(None, *args)

        runs = SimpleNamespace(workers=workers, spec=None, fraction=0.5, noise=None,
                               classes=(), later=later)
        made = entries()
        assert reliability_probe.probe_entries(made, base, runs) == 6
        got.append(made)
    assert parts == [(1, 6), (2, 2), (2, 4), (3, 2), (3, 2), (3, 2)]
    assert got[0][0]["biases_signed"] != got[0][2]["biases_signed"]  # the sizes show
    assert got[1] == got[0] and got[2] == got[0]


def _same_words_in_the_report(entry, text):
    """The report's row says the biases and first-order clauses in the terminal's words."""
    from stellar_cal_ros.diagnosis.report_html import _reliability_html

    row = _reliability_html({"reliability": [entry]})
    clauses = [printing.bias_phrase(entry, n) for n in entry["dominates"]]
    clauses += printing.first_order_phrases(entry)
    assert clauses
    for clause in clauses:
        assert clause in text and clause.replace("sigma", "σ") in row, clause


@pytest.mark.parametrize("effect", [e for e in EFFECTS if e != "image_plane_tilt"])
def test_printed_bias_and_mdb_hold_when_injected(clean, effect):
    sim, data, summary, prior, base = clean
    assert summary["recommendation"] is None  # a clean bag
    entry = next(e for e in summary["reliability"] if e["effect"] == effect)
    eff = registry.create(effect)
    groups = injection.claims(entry) or {eff.parameter_names[0]: []}
    s0, info = _score(base, effect)
    before = injection.run_values(base)
    sigma = dict(zip(base.filter.model.parameter_names(), np.sqrt(np.diag(
        base.filter.P)[base.filter.it]), strict=False))
    for parameter, listed in list(groups.items())[:2]:
        size = entry["hidden_size"][parameter]
        delta = injection.parameter_delta(effect, parameter, size)
        _, inj = _data({effect: injection.simulation_value(effect, delta)})
        run = replay(inj, prior, "psce", [], consider=[effect], keep_tables=False)
        shift = injection.paired_shift(before, injection.run_values(run),
                                       reliability_probe.own_shift(sim.truth, "psce", effect,
                                                                   delta))
        for q in listed:
            printed = injection.printed_shift(entry, q, 1)
            assert abs(printed) > sigma.get(q, 0.0)  # listed: above the parameter's σ
            assert shift[q] == pytest.approx(printed, rel=0.3), (parameter, q, shift[q],
                                                                 printed)
        if entry["testable"]:
            s1, _ = _score(run, effect)
            w, V = np.linalg.eigh(info)
            good = w > 1e-12 * w.max()
            lam = float((s1 - s0) @ (V[:, good] / w[good]) @ V[:, good].T @ (s1 - s0))
            assert lam == pytest.approx(entry["lam0"], rel=0.3), (parameter, lam)


def test_gyro_misalignment_blind_directions_are_reported_apart(clean):
    """The issue's ~60x: the antisymmetric misalignment (a rotation of the gyro axes) is
    absorbed one to one by the installation and carries no information.  Its shift is
    reported as a blind direction of plausible size, not as the bias of the MDB."""
    summary = clean[2]
    e = next(e for e in summary["reliability"] if e["effect"] == "gyro_misalignment")
    assert len(e["blind"]["directions"]) == 3
    assert all(" - " in d for d in e["blind"]["directions"])  # e01 - e10 and the like
    plausible = reliability.plausible_size("gyro_misalignment")[0]
    rz = e["blind"]["biases"]["installation.rz"]
    assert 0.3 * plausible < rz < 1.5 * plausible
    # the MDB's own bias is a few arcsec, not the blind direction's hundreds
    assert e["biases"]["installation.rz"] < 0.1 * rz


def test_image_plane_tilt_mdb_holds_in_the_scores_odd_part(clean):
    """The tilt's printed MDB: the score's response to +-MDB, odd part, is I b.

    A tilt is, to first order, a rotation of the tracker (installation) plus a principal
    point shift f tau plus the decentred distortion that shift implies (which p1, p2
    absorb): its information is what is left, and at its MDB the second-order term, even
    in tau, is as large (300 s, seed 300: the paired score response 0.55x I b at +MDB,
    1.47x at -MDB).  So a paired response at one sign says nothing about the MDB (it
    printed "implied power 29 %"); its odd part is the linear response the MDB is stated
    for.  The decision follows the response at each sign: on twins of two clean psce
    bags it flagged the tilt at +MDB in 8 and 13 of 20 rounds, at -MDB in 18 of 20 and 8
    of 10 (benchmarks/twin_mdb_power.py, doc/benchmarks.md); averaged over alternating signs
    (benchmarks/reliability_injection.py) it looked as stated.
    """
    sim, data, summary, prior, base = clean
    effect = "image_plane_tilt"
    entry = next(e for e in summary["reliability"] if e["effect"] == effect)
    assert entry["testable"]
    param, listed = injection.injected_parameter(entry)
    s0, info = _score(base, effect)
    before = injection.run_values(base)
    responses, shifts = [], []
    for sign in (1, -1):
        delta = injection.parameter_delta(effect, param, sign * entry["hidden_size"][param])
        _, inj = _data({effect: injection.simulation_value(effect, delta)})
        run = replay(inj, prior, "psce", [], consider=[effect], keep_tables=False)
        responses.append(_score(run, effect)[0] - s0)
        shifts.append(injection.paired_shift(before, injection.run_values(run),
                                             reliability_probe.own_shift(sim.truth, "psce",
                                                                         effect, delta)))
    odd = 0.5 * (responses[0] - responses[1])
    lam = float(odd @ np.linalg.solve(info, odd))
    assert lam == pytest.approx(entry["lam0"], rel=0.3)
    # every row the report lists at that sign holds within 30 %: the first-order rows and
    # the rows a probe run on the bag measured (the sensitivity recursion holds the gain
    # fixed; beside the ~100 sigma installation / principal-point shift the filter's gain
    # response at the slew after the 53 s hold carries what it misses, doc/benchmarks.md)
    off = {}
    for sign, shift in zip((1, -1), shifts, strict=True):
        for q in injection.claims(entry, sign).get(param, []):
            printed = injection.printed_shift(entry, q, sign)
            if not 0.7 <= shift[q] / printed <= 1.3:
                off[(sign, q)] = (printed, shift[q])
    assert listed and not off, off
    # the first-order gyro_bias.by (-3.3e-8 rad/s, 1.2 sigma; the injection moves it by
    # +3.5e-9 at +MDB and +4.6e-10 at -MDB) was measured by the probe and is not listed
    probe = entry["probe"][param]
    assert "gyro_bias.by" in probe["first_order"] and "gyro_bias.by" in probe["unlisted"]
    assert "gyro_bias.by" not in entry["dominates"] and not entry["remainders"]
    assert abs(shifts[0]["gyro_bias.by"]) < sigma_of(base, "gyro_bias.by")
    text = "\n".join(printing.reliability_lines([entry]))
    assert "measured by a probe run" in text and "gyro_bias.by" in text


def test_the_tilts_mdb_is_restated_where_one_sign_responds_below_lam0(clean):
    """Issue 21 item 2: a printed MDB holds at both signs.

    The first-order MDB is seen with λ₀ only where the score is linear in the effect; the
    tilt's second-order term makes +τx weaker (on twins of a clean psce bag 0.56 λ₀ at +MDB,
    found 8 of 20).  The probe runs at ±MDB also score the effect; where the weaker sign's
    response λ_w < λ₀ it runs that sign once more at sqrt(λ₀/λ_w) x the MDB and states the
    size a secant in log λ through the two reaches λ₀ at.  Checked on the simulator: the
    probe's responses are the paired responses of the same injections into the simulation
    (its renderer is the twin's, at the estimated calibration: within 30 %), and at the
    restated MDB the weaker sign's paired response is λ₀ within 30 % (on main the entry
    has no restated MDB: its response at the printed one is below 0.7 λ₀)."""
    sim, data, summary, prior, base = clean
    effect = "image_plane_tilt"
    entry = next(e for e in summary["reliability"] if e["effect"] == effect)
    lam0, first = entry["lam0"], entry["mdb_test"]
    assert entry["mdb_set_by"] == "probe"
    s0, info = _score(base, effect)
    restated = []
    for param, probe in entry["probe"].items():
        lam = {1: probe["lam_plus"], -1: probe["lam_minus"]}
        weak = min(lam, key=lam.get)
        assert lam[weak] < lam0 < lam[-weak]
        assert entry["hidden_size"][param] == first[param]
        step = np.sqrt(lam0 / lam[weak])
        assert probe["step"] == pytest.approx(step, rel=1e-12)
        power = np.log(probe["lam_step"] / lam[weak]) / np.log(step)
        factor = step * (lam0 / probe["lam_step"]) ** (1 / power)
        assert entry["mdb"][param] == pytest.approx(first[param] * factor, rel=1e-12)
        restated.append(param)
        got = {}
        for sign, f in ((weak, 1.0), (-weak, 1.0), (weak, step), (weak, factor)):
            delta = injection.parameter_delta(effect, param, sign * f * first[param])
            _, inj = _data({effect: injection.simulation_value(effect, delta)})
            run = replay(inj, prior, "psce", [], consider=[effect], keep_tables=False)
            d = _score(run, effect)[0] - s0
            got[f if sign == weak else -1.0] = float(d @ np.linalg.solve(info, d))
        assert got[1.0] == pytest.approx(lam[weak], rel=0.3), (param, got)
        assert got[-1.0] == pytest.approx(lam[-weak], rel=0.3), (param, got)
        assert got[step] == pytest.approx(probe["lam_step"], rel=0.3), (param, got)
        assert got[factor] == pytest.approx(lam0, rel=0.3), (param, got)
    assert restated
    text = printing.mdb_phrase(entry)
    assert "either sign, by probe runs; first order" in text


def test_both_signs_restates_only_a_response_below_lam0_at_the_mdb_itself():
    """The MDB moves only where the probe ran at the MDB (not a plausible size below it)
    and a sign responded below λ₀ (λ is the non-centrality of the decision's statistic
    LM / φ: Δsᵀ I⁻¹ Δs / φ; until H285 φ Δsᵀ I⁻¹ Δs, the information divided by φ and the
    score not, φ² too large); the secant through the responses at 1x and the step's size
    gives the size of λ₀."""
    info = np.diag([4.0, 1.0])
    screen = screening.ScreenResult(0.0, 2, info, dispersion=2.0)

    def entry(hidden=1.0):
        return {"mdb": {"a": 1.0}, "lam0": 10.0, "hidden_size": {"a": hidden},
                "probe": {"a": {}}}

    held = entry()  # λ₊ = 100 / 4 / 2 = 12.5, λ₋ = (16 / 4 + 16) / 2 = 10: none below λ₀
    assert reliability_probe.both_signs(held, "a", np.array([10.0, 0.0]),
                                        np.array([-4.0, 4.0]), screen) is None
    assert held["probe"]["a"] == {"lam_plus": pytest.approx(12.5),
                                  "lam_minus": pytest.approx(10.0)}
    assert held["mdb"] == {"a": 1.0} and "mdb_set_by" not in held
    weak = entry()  # λ₊ = 8 < λ₀ = 10 < λ₋ = 32: the step sqrt(10 / 8) at +
    step = np.sqrt(10.0 / 8.0)
    assert reliability_probe.both_signs(weak, "a", np.array([8.0, 0.0]),
                                        np.array([-16.0, 0.0]), screen) == (1.0, step)
    assert weak["mdb"]["a"] == pytest.approx(step)
    assert weak["mdb_test"] == {"a": 1.0} and weak["mdb_set_by"] == "probe"
    # a response growing as the size cubed (8 at 1x): the secant lands on (10 / 8)^(1/3)
    reliability_probe.secant(weak, "a", step, 8.0 * step ** 3)
    assert weak["mdb"]["a"] == pytest.approx((10.0 / 8.0) ** (1 / 3))
    flat = entry()  # a response that did not grow: the one step stands
    reliability_probe.both_signs(flat, "a", np.array([8.0, 0.0]), np.array([-16.0, 0.0]),
                                 screen)
    reliability_probe.secant(flat, "a", step, 7.0)
    assert flat["mdb"]["a"] == pytest.approx(step) and flat["probe"]["a"]["lam_step"] == 7.0
    capped = entry(hidden=0.5)  # probed at a plausible size below the MDB: kept
    assert reliability_probe.both_signs(capped, "a", np.array([8.0, 0.0]),
                                        np.array([-16.0, 0.0]), screen) is None
    assert capped["mdb"]["a"] == 1.0 and "mdb_set_by" not in capped
    missing = entry()  # a method without a score test: nothing measured
    assert reliability_probe.both_signs(missing, "a", None, None, screen) is None
    assert missing == entry()


def test_gate_secant_finds_the_gate_of_the_hard_sign_from_two_runs():
    """The gate MDB of the sign the misfit works against, restated from measured energies.

    Printed ``h`` and leaning ``l`` solve ``b² − (h − l) b = h l`` (units of I, ``q`` =
    ``lam_gate`` x ``dispersion``).  An energy whose quadratic term is ``κ`` x the first
    order's: the first run at ``h`` reads ``ρ = (κ h² − (h − l) h) / (h l)``, the step lands
    on the root of ``κ b² − (h − l) b = h l``; a run there reads ``ρ = 1`` and the secant
    keeps it.  A curvature that still falls moves it on; no positive curvature, or at least
    the stated energy at ``h`` (it passes there), keeps ``h``.
    """
    h, lean, q = 3.0, 0.25, 8.0 * 0.75  # I = q / (h l) = 8: lam_gate 0.75 at dispersion 8

    def entry():
        return {"mdb": {"a": h}, "mdb_test": {"a": 0.1}, "mdb_leaning": {"a": -lean},
                "lam_gate": 0.75, "dispersion": 8.0}

    def energy(b, kappa):  # whitened energy at the hard size b (I = 8)
        return 8.0 * (kappa * b * b - (h - lean) * b)

    kappa = 0.97
    e = entry()
    step = reliability_probe.gate_secant(e, "a", energy(h, kappa))
    want = ((h - lean) + np.sqrt((h - lean) ** 2 + 4 * kappa * h * lean)) / (2 * kappa)
    assert step == pytest.approx(want) and e["mdb"]["a"] == pytest.approx(want)
    assert e["gate_probe"]["a"] == {"size": h, "energy_ratio": pytest.approx(
        energy(h, kappa) / q)}
    assert reliability_probe.gate_secant(e, "a", energy(want, kappa)) is None
    assert e["mdb"]["a"] == pytest.approx(want)
    assert e["gate_probe"]["a"]["step_energy_ratio"] == pytest.approx(1.0)
    # the curvature falls further between the two runs: the secant through both at q
    e = entry()
    b1 = reliability_probe.gate_secant(e, "a", energy(h, kappa))
    e2 = energy(b1, 0.96)
    reliability_probe.gate_secant(e, "a", e2)
    rho1, rho2 = energy(h, kappa) / q, e2 / q
    assert e["mdb"]["a"] == pytest.approx(b1 + (1 - rho2) * (b1 - h) / (rho2 - rho1))
    assert e["mdb"]["a"] > b1
    flat = entry()  # the effect's energy fell: no positive curvature, h kept
    assert reliability_probe.gate_secant(flat, "a", energy(h, 0.0) * 3.0) is None
    assert flat["mdb"]["a"] == h
    held = entry()  # more energy than stated at h: it passes there, h kept, no run more
    assert reliability_probe.gate_secant(held, "a", energy(h, 1.02)) is None
    assert held["mdb"]["a"] == h and held["gate_probe"]["a"]["energy_ratio"] > 1.0
    # only a testable entry's gate-set parameters are run
    assert reliability_probe.gated({**entry(), "mdb_set_by": "explained_gate",
                                    "testable": True}) == ["a"]
    assert reliability_probe.gated({**entry(), "mdb_set_by": "explained_gate"}) == []
    assert reliability_probe.gated({**entry(), "testable": True}) == []


def sigma_of(result, name):
    names = result.filter.model.parameter_names()
    return float(np.sqrt(result.filter.P[names.index(name), names.index(name)]))


def test_the_equivalent_principal_points_own_shift_is_taken_out(clean):
    """The equivalent principal point's measured bias is the estimate's shift less what the
    effect does to the true point (reliability_probe.own_shift, as the printed rows are):
    the image of the nominal boresight, at the principal point, stays there under an effect
    acting about it and moves one to one with a principal-point offset.  So its rows are
    checked for camera effects too (on this bag none is listed: every camera effect's row
    is below its sigma, e.g. the tilt's 0.003 px against 0.012 px)."""
    sim = clean[0]
    own = reliability_probe.own_shift
    assert own(sim.truth, "psce", "principal_point", np.array([0.5, -0.3])) == pytest.approx(
        {"equivalent_principal_point.u": 0.5, "equivalent_principal_point.v": -0.3})
    for eid, d in (("image_plane_tilt", [1e-3, 2e-3]), ("pixel_aspect", [1e-3]),
                   ("radial_k3", [100.0]), ("thermal_focal_length", [1e-4])):
        assert max(map(abs, own(sim.truth, "psce", eid, np.array(d)).values())) < 1e-9, eid
    shift = injection.paired_shift({"equivalent_principal_point.u": 1.0},
                                   {"equivalent_principal_point.u": 1.7},
                                   {"equivalent_principal_point.u": 0.5})
    assert shift["equivalent_principal_point.u"] == pytest.approx(0.2)


def _steps_by_dict(user, plain, moved):
    """The per-frame dictionaries reliability_probe.with_effect used (the reference)."""
    import copy

    by_stamp = {a.stamp_ns: (a, b) for a, b in zip(plain, moved, strict=True)}
    out = []
    for f in user:
        pair = by_stamp.get(f.stamp_ns)
        if pair is None:
            out.append(f)
            continue
        rows_b = {int(c): i for i, c in enumerate(pair[1].catalog_id)}
        step = {int(c): pair[1].uv[rows_b[int(c)]] - pair[0].uv[i]
                for i, c in enumerate(pair[0].catalog_id) if int(c) in rows_b}
        uv = np.array(f.uv, dtype=float, copy=True)
        for i, c in enumerate(np.asarray(f.catalog_id)):
            if int(c) in step:
                uv[i] += step[int(c)]
        g = copy.copy(f)
        g.uv = uv
        out.append(g)
    return out


def test_the_probes_steps_in_arrays_are_the_per_frame_sums():
    """add_steps (whole-bag arrays) gives the per-frame dictionaries' centroids exactly:
    stars off one twin's detector, repeated ids and stamps, frames the twins do not hold."""
    from stellar_cal_ros.core.types import StarFrame

    rng = np.random.default_rng(4)

    def frame(stamp, ids):
        n = len(ids)
        return StarFrame(stamp_ns=stamp, frame_id="st", exposure_time=0.01,
                         catalog_id=np.asarray(ids, dtype=np.uint32),
                         right_ascension=rng.uniform(0, 6, n), declination=rng.uniform(-1, 1, n),
                         uv=rng.uniform(0, 1000, (n, 2)), magnitude=rng.uniform(2, 6, n),
                         sigma=np.full(n, 0.05))

    user, plain, moved = [], [], []
    for k in range(60):
        ids = list(rng.choice(np.arange(1, 40), size=rng.integers(0, 8), replace=False))
        if k % 7 == 3 and ids:
            ids.append(ids[0])  # an id twice in a frame
        stamp = 10**9 + (k - (k % 11 == 5)) * 10**8  # a stamp twice
        user.append(frame(stamp, ids + [0]))
        if k % 13 == 6:
            continue  # a frame the twins left out
        kept = [c for c in ids if rng.random() > 0.15]  # off the detector in one twin
        plain.append(frame(stamp, kept if k % 2 else ids))
        moved.append(frame(stamp, ids if k % 2 else kept))
    user.insert(17, frame(10**9 + 17 * 10**8 + 1, []))  # a frame without stars
    plain.insert(15, frame(10**9 + 17 * 10**8 + 1, []))
    moved.insert(15, frame(10**9 + 17 * 10**8 + 1, []))
    before = [np.array(f.uv, copy=True) for f in user]
    got = reliability_probe.add_steps(user, plain, moved)
    want = _steps_by_dict(user, plain, moved)
    assert len(got) == len(want)
    moved_any = False
    for g, w, u, b in zip(got, want, user, before, strict=True):
        assert np.array_equal(g.uv, w.uv) and g.uv.shape == w.uv.shape
        assert np.array_equal(u.uv, b)  # the user's frames are left as they were
        moved_any |= not np.array_equal(g.uv, u.uv)
    assert moved_any
    # the user's star columns made once (one probe call's injections) give the same steps
    steps = reliability_probe.star_steps(user, plain, moved)
    columns = reliability_probe.star_steps(reliability_probe.star_columns(user), plain, moved)
    assert all(np.array_equal(a, b) for a, b in zip(steps, columns, strict=True))


def test_a_re_run_candidate_prints_the_mdb_it_has_when_screened_out(tmp_path):
    """One MDB for one effect: the evaluation window's information (the screening's sum over
    the window), whether the candidate was screened out or re-run.

    Swaying 200 s, seed 23 (unseen case ``sway_twin_gsf1``'s base): gyro_scale_factor sz's
    information lies 98 % in the window, which holds 44 % of the stars.  The re-run's MDB
    was the augmented run's whole-run information times the stars' share: 20.9 ppm re-run
    against 14.0 ppm screened out; `stellar-cal twin` at 14.0 finds it 19 of 20 times
    (doc/benchmarks.md).  Here the bag with sz at 14 ppm (re-run) prints the clean bag's
    (screened out) MDB to 1 %.
    """
    out = {}
    for name, effects in (("clean", None), ("sz", {"gyro_scale_factor": [0.0, 0.0, 1.4e-5]})):
        sim, model = injection.clean_simulation("swaying_base", False, 23, 200.0, effects)
        summary = diagnose(bag_data_from_simulation(sim), sim.prior, "swaying_base", model,
                           tmp_path / name, plots=False, verbose=False)
        out[name] = next(c for c in summary["candidates"] + summary["screened_out"]
                         if c["effect"] == "gyro_scale_factor")
    assert "score test" in out["clean"]["reason"]  # screened out
    assert out["sz"]["p_value_score"] < 0.05 and "score test" not in (out["sz"].get("reason")
                                                                     or "")  # re-run
    mdb0, mdb1 = out["clean"]["detectability"]["mdb"], out["sz"]["detectability"]["mdb"]
    assert mdb0["sz"] == pytest.approx(14.0e-6, rel=0.02)
    for p in ("sx", "sy", "sz"):
        assert mdb1[p] == pytest.approx(mdb0[p], rel=0.01), p


def test_the_mdb_is_stated_for_the_decisions_score_test(clean):
    """The MDB's λ₀ is the one of the test that decides, at its dof and level.

    ``decide`` takes the smaller p of the screening's score test and the ratio test and
    multiplies it by the tested candidates and the 2 statistics; the score test's dof is the
    count of the directions it sums over: those of its window information that are not
    blind (:func:`reliability.tested_directions`).  Each printed MDB must be λ₀ at that dof
    and that level: a gyro misalignment's three directions the installation absorbs (an
    effect of plausible size there stays far below λ₀) are left out of both, 3 of 6
    (until H278 they counted in the 6).
    """
    sim, data, summary, prior, base = clean
    tested = summary["candidates"] + summary["implausible"] + summary["screened_out"]
    entries = summary["reliability"]
    assert {e["effect"] for e in entries} == set(EFFECTS)
    for e in entries:
        eid = e["effect"]
        score = screening.collect([SimpleNamespace(ok=True, scores=kernel_scores(base, [eid]),
                                                   window={"nis": {"mean": 2.0}},
                                                   lost_lock=False)],
                                  alpha=e["alpha"], calibration=sim.prior)[eid]
        size = registry.create(eid).size
        assert e["dof"] == score.dof == (3 if eid == "gyro_misalignment" else size), eid
        assert e["alpha"] == pytest.approx(ALPHA / (2 * len(tested)), rel=1e-12)
        assert e["lam0"] == pytest.approx(reliability.lambda0(e["alpha"], score.dof),
                                          rel=1e-12)
    # each test's dof beside its p; ``dof`` the parameter count (H285)
    for c in summary["candidates"]:
        assert c["dof"] == registry.create(c["effect"]).size, c["effect"]
        if c["p_value_score"] is not None:
            assert c["dof_score"] == c["detectability"]["dof"], c["effect"]
    for c in summary["screened_out"]:
        assert c["dof_score"] == c["detectability"]["dof"], c["effect"]
        assert 0.05 <= c["p_value_score"] <= 1.0, c["effect"]
    gm = next(c for c in summary["candidates"] + summary["screened_out"]
              if c["effect"] == "gyro_misalignment")
    assert gm["dof_score"] == 3


def test_the_test_mdb_is_restated_at_its_weaker_sign_from_twin_responses():
    """``twin_signs`` + ``restate_test``: the test's MDB where one sign responds below λ₀.

    A gate-set row (``mdb_set_by`` "explained_gate"): ``mdb_test`` grows by the secant's
    factor, the printed (gate's) MDB is at least it and the line says both sizes; a row the
    test set: ``mdb`` itself, ``mdb_set_by`` "probe" (as :func:`both_signs`).  The twin's
    ``I`` is its own (no dispersion).  ``stated_size``: the test's MDB over √dispersion, at
    most the plausible size (where ``--verify`` injects, :func:`verify.twin_scale`)."""
    from stellar_cal_ros.diagnosis import printing, verify

    info = np.diag([4.0, 1.0])  # λ = Δsᵀ I⁻¹ Δs
    gate = {"effect": "image_plane_tilt", "mdb": {"tau_y": 0.12}, "lam0": 10.0,
            "mdb_test": {"tau_y": 0.012}, "dispersion": 4.0, "mdb_set_by": "explained_gate",
            "mdb_leaning": {"tau_y": -0.07}, "hidden_size": {"tau_y": 0.01},
            "plausible_size": {"tau_y": 0.01}}
    assert reliability_probe.stated_size(gate, "tau_y") == pytest.approx(0.006)
    assert verify.twin_scale(gate, "tau_y") == pytest.approx(0.6)
    # λ₊ = 16, λ₋ = 4: the step sqrt(10 / 4) at the minus sign
    step = reliability_probe.twin_signs(gate, "tau_y", (np.array([8.0, 0.0]), info),
                                        (np.array([-4.0, 0.0]), info), 0.006)
    assert step == (-1.0, pytest.approx(np.sqrt(2.5)))
    assert gate["twin_probe"]["tau_y"] == {"size": 0.006, "lam_plus": pytest.approx(16.0),
                                           "lam_minus": pytest.approx(4.0)}
    # a response growing as the size squared from 4: λ₀ at the step itself
    reliability_probe.restate_test(gate, "tau_y", step[1], 4.0 * step[1] ** 2)
    assert gate["mdb_test"]["tau_y"] == pytest.approx(0.012 * np.sqrt(2.5))
    assert gate["mdb_first_order"] == {"tau_y": 0.012} and gate["mdb"]["tau_y"] == 0.12
    assert verify.twin_scale(gate, "tau_y") == pytest.approx(0.012 * np.sqrt(2.5) / 2 / 0.01)
    text = printing.mdb_phrase(gate)
    assert ("the test alone: tau_y 19 mrad (either sign, by probe runs on the bag's "
            "noise-free twin; first order tau_y 12 mrad)") in text, text
    # above the gate's: the printed MDB is the test's
    big = dict(gate, mdb={"tau_y": 0.013}, mdb_test={"tau_y": 0.012}, twin_probe={})
    reliability_probe.twin_signs(big, "tau_y", (np.array([8.0, 0.0]), info),
                                 (np.array([-4.0, 0.0]), info), 0.006)
    reliability_probe.restate_test(big, "tau_y", np.sqrt(2.5), 10.0)
    assert big["mdb"]["tau_y"] == big["mdb_test"]["tau_y"] > 0.013
    # a row the test set (no gate): the printed MDB, mdb_set_by "probe"
    test = {"effect": "image_plane_tilt", "mdb": {"tau_y": 0.004}, "lam0": 10.0,
            "hidden_size": {"tau_y": 0.004}, "plausible_size": {"tau_y": 0.01}}
    assert reliability_probe.stated_size(test, "tau_y") == 0.004
    step = reliability_probe.twin_signs(test, "tau_y", (np.array([8.0, 0.0]), info),
                                        (np.array([-4.0, 0.0]), info), 0.004)
    reliability_probe.restate_test(test, "tau_y", step[1], 4.0 * step[1] ** 3)
    assert test["mdb_set_by"] == "probe" and test["mdb_test"] == {"tau_y": 0.004}
    assert test["mdb"]["tau_y"] == pytest.approx(0.004 * 2.5 ** (1 / 3))
    assert verify.twin_scale(test, "tau_y") == pytest.approx(2.5 ** (1 / 3))
    assert "either sign, by probe runs on the bag's noise-free twin; first order 4 mrad" \
        in printing.mdb_phrase(test)
    # both signs at least λ₀: nothing restated
    held = {"mdb": {"a": 1.0}, "lam0": 10.0}
    assert reliability_probe.twin_signs(held, "a", (np.array([8.0, 0.0]), info),
                                        (np.array([-7.0, 0.0]), info), 1.0) is None
    assert held["mdb"] == {"a": 1.0} and "mdb_set_by" not in held


def test_even_energy_is_the_whitened_energy_of_the_increments_even_part():
    """(Δ₊ + Δ₋)/2 per star both twins hold, over the per-axis variance (half the
    variance per star), plus the IMU's over its σ; 0 for increments odd in the size."""
    hit = np.array([True, False, True])
    plus = reliability_probe.Injection(
        (np.zeros(1, int), hit, np.array([[1.0, 0.5], [2.0, 0.0]])),
        np.array([[0.1, 0.0, 0.0]]), None)
    minus = reliability_probe.Injection(
        (np.zeros(1, int), hit, np.array([[-0.8, -0.5], [-2.0, 0.0]])), None, None)
    got = reliability_probe.even_energy(plus, minus, 0.02, (0.05, 1.0))
    assert got == pytest.approx(0.1 ** 2 / 0.01 + 0.05 ** 2 / 0.05 ** 2)
    odd = reliability_probe.Injection(
        (np.zeros(1, int), hit, np.array([[-1.0, -0.5], [-2.0, 0.0]])),
        np.array([[-0.1, 0.0, 0.0]]), None)
    assert reliability_probe.even_energy(plus, odd, 0.02, (0.05, 1.0)) == 0.0


def test_the_score_test_and_its_mdb_leave_the_blind_directions_out():
    """A direction where an effect of plausible size stays below λ₀ adds a χ²₁ of no power
    to the score statistic (or, seen through a measurement whose error is not its stated
    noise, not even that): the test sums over the others, their count its dof, and the MDB
    is that test's (λ₀ at that dof, the information without the blind directions).  Fails
    on coord 0e2fd9e (the test and its λ₀ counted all 6)."""
    eid, alpha = "gyro_misalignment", 1e-3 / 24
    D = reliability.plausible_size(eid)
    rng = np.random.default_rng(3)
    U, _ = np.linalg.qr(rng.standard_normal((6, 6)))
    mu = np.array([2.0, 5.0, 8.0, 2e4, 5e4, 1e5])  # swaying's: 1.7-8.2 and 1.8e4-1e5
    info = (U / D[:, None] * mu) @ (U / D[:, None]).T
    z = np.array([0.3, -0.1, 0.2, 1.1, -0.7, 0.4])  # per direction, in units of its σ
    score = U @ (z * np.sqrt(mu)) / D  # s with (uᵢᵀ D s)² / μᵢ = zᵢ²
    full = screening.ScreenResult(float(score @ np.linalg.solve(info, score)), 6, info,
                                  score=score)
    assert full.lm == pytest.approx(np.sum(z ** 2), rel=1e-9)
    test = full.tested(eid, alpha)
    assert test.dof == 3
    assert test.lm == pytest.approx(np.sum(z[3:] ** 2), rel=1e-9)
    det = reliability.detectability(eid, info, alpha)
    assert det.dof == 3 and det.lam0 == pytest.approx(reliability.lambda0(alpha, 3))
    kept = (U[:, 3:] / D[:, None] * mu[3:]) @ (U[:, 3:] / D[:, None]).T
    for n, d in zip(registry.create(eid).parameter_names, np.diag(kept), strict=True):
        assert det.mdb[n] == pytest.approx(np.sqrt(det.lam0 / d), rel=1e-9), n
    # the same numbers from the tested information (what a screened-out candidate passes)
    again = reliability.detectability(eid, test.information, alpha)
    assert again.dof == 3 and again.mdb == pytest.approx(det.mdb, rel=1e-9)
    assert len(reliability.blind_directions(det).T) == 3
    # every direction seen: the whole test
    seen = screening.ScreenResult(1.0, 6, info * 1e3, score=score)
    assert seen.tested(eid, alpha) is seen


def test_the_blind_directions_are_those_the_test_leaves_out_at_any_dispersion():
    """One rule (:func:`reliability.split_directions`) for the directions a test sums over
    and those it is blind to, judged for residuals as stated: a direction is one or the
    other whatever the round's dispersion φ, and the MDB of a round whose statistic is
    divided by φ grows by √φ.  Here the fourth direction reaches λ₀ at 1.2x (seen, tested):
    at φ = 1.5 it stays tested and not blind.  Fails on coord 6c738a9 (4 blind directions
    at φ = 1.5: they were read from the information over φ against λ₀ at the tested
    dof)."""
    eid, alpha = "gyro_misalignment", 1e-3 / 24
    D = reliability.plausible_size(eid)
    U, _ = np.linalg.qr(np.random.default_rng(7).standard_normal((6, 6)))
    mu = np.array([2.0, 5.0, 8.0, 1.2 * reliability.lambda0(alpha, 6), 5e4, 1e5])
    info = (U / D[:, None] * mu) @ (U / D[:, None]).T
    one = reliability.detectability(eid, info, alpha)
    for phi in (1.0, 1.5, 3.0):
        det = reliability.detectability(eid, info, alpha, dispersion=phi)
        blind = reliability.blind_directions(det)
        assert det.dof == 3 and blind.shape == (6, 3), phi
        # the blind ones span the directions the test leaves out, none of those it sums over
        w = blind / D[:, None]
        assert np.abs(U[:, 3:].T @ w).max() < 1e-9, phi
        assert np.linalg.matrix_rank(U[:, :3].T @ w) == 3, phi
        assert det.testable, phi
        for n in det.mdb:
            assert det.mdb[n] == pytest.approx(one.mdb[n] * np.sqrt(phi), rel=1e-9), (phi, n)
    # every direction seen: none blind, at any dispersion
    assert reliability.blind_directions(
        reliability.detectability(eid, info * 1e3, alpha, dispersion=3.0)).shape == (6, 0)


def test_a_screened_rounds_mdb_is_stated_for_the_dispersion_its_score_is_divided_by():
    """A screened round divides its score statistic by the residuals' dispersion φ (mean
    NIS/dof, quasi-score), as its ratio statistic: the MDB it prints must be the size that
    test finds with 80 % power, ``sqrt(φ λ₀ / I)`` (Teunissen: the bias the printed test
    detects with the printed power).  A bag whose stars' stated σ is 0.8x their noise
    (φ ≈ 1.5, the round still screened): time_offset injected at ± the test's MDB into the
    same bag (same seed and noise), the paired response of the round's statistic is λ₀.
    (The printed MDB there is the excess gate's, 4.4x: the stars' excess variance, noise
    stated wrong, is taken for a misfit an effect must remove 10 % of; ``mdb_test`` is the
    test's.)  Fails on coord 6c738a9 (the test's MDB stated for φ = 1: the response
    λ₀ / φ, 0.65 λ₀)."""
    from stellar_cal_ros.core.noise import NoiseScales
    from stellar_cal_ros.diagnosis.discover import Round, method_spec, rank_round
    from stellar_cal_ros.diagnosis.parallel import Runs

    eid = "time_offset"

    def round_on(effects=None):
        sim, _ = injection.clean_simulation("psce", False, SEED, DURATION, effects)
        runs = Runs(bag_data_from_simulation(sim), method_spec("psce"), 0.5)
        runs.noise = NoiseScales(star=0.8)
        r = Round(runs, method_spec("psce"), runs.facts(), 0.5, sim.prior)
        _, results, _ = rank_round(r, sim.prior, [], [eid], condition=False,
                                   keep_residuals=False)
        return sim, results[0]

    sim, c0 = round_on()
    phi = c0.screen.dispersion
    assert c0.screen.local and 1.35 < phi < 1.75, phi
    assert c0.detect.dispersion == phi
    as_stated = reliability.detectability(eid, c0.screen.information, c0.detect.alpha,
                                          sim.prior)
    test_mdb = c0.detect.mdb_test["dt"]  # the gate's is printed (above)
    assert c0.detect.mdb["dt"] > 3 * test_mdb
    assert test_mdb == pytest.approx(as_stated.mdb["dt"] * np.sqrt(phi), rel=1e-9)
    lam = []
    for sign in (1, -1):
        delta = injection.parameter_delta(eid, "dt", sign * test_mdb)
        _, c1 = round_on({eid: injection.simulation_value(eid, delta)})
        lam.append(c0.screen.response(c1.screen.score - c0.screen.score))
    assert np.mean(lam) == pytest.approx(c0.detect.lam0, rel=0.1), (lam, c0.detect.lam0)


def test_a_gyro_misalignment_on_the_swaying_base_is_tested_where_the_score_is_noise():
    """On the swaying base the installation absorbs a gyro misalignment's rotation of the
    gyro axes from the stars; what is left of it is seen through the position reference,
    whose error is the base's sway, not noise: there the score scatters 0.04-0.24 σ around a
    value the sway sets (H278, 12 seeds of 300 s), and counting those 3 directions gave a χ²₆
    test a statistic of ~3 noise dof (power 71 % at the printed MDB, H272).  The test now
    sums over the 3 others: 6 clean 300-s bags, the tested statistic's mean is its dof
    (χ²₃ over 6 seeds: 3 ± 1), and the directions left out carry |z| < 0.6.  Fails on coord
    0e2fd9e (dof 6)."""
    eid = "gyro_misalignment"
    alpha = ALPHA / (2 * 12)
    lms, left = [], []
    for seed in range(4600, 4606):
        sim, model = injection.clean_simulation("swaying_base", False, seed, 300.0)
        run = replay(bag_data_from_simulation(sim), rerun_prior(sim.prior), "swaying_base",
                     model, consider=[eid], keep_tables=False, eval_fraction=0.5)
        item = kernel_scores(run, [eid])[eid]
        full = screening.ScreenResult(item[0], item[1], item[2], score=item[5])
        test = full.tested(eid, alpha, sim.prior)
        assert full.dof == 6 and test.dof == 3, seed
        left.append(full.lm - test.lm)
        lms.append(test.lm)
    assert 0.5 < np.mean(lms) < 6.0, lms  # -2.5σ..+3σ of a mean of 6 χ²₃ (σ 1.0)
    assert np.max(np.abs(left)) < 0.6 ** 2 * 3, left


def test_the_paired_response_is_the_tested_statistics():
    """The paired response that checks an MDB (``--verify``'s twins, the probe's runs on the
    bag and on its twin) is the non-centrality of the test the MDB is stated for: on its
    directions that are not blind, ``Σ (uᵢᵀ D Δs)² / μᵢ`` (``basis`` = D B), also where
    another run's information weighs them (a twin's: ``vᵀ (Wᵀ I W)⁻¹ v``).  Not the whole
    information's ``Δsᵀ I⁻¹ Δs`` (what verify computed until H285), nor in general the
    pseudo-inverse of the information without the blind directions (the probe's since H278;
    the same for a gyro misalignment, whose plausible sizes are alike, not where they
    differ: the directions ``D⁻¹ B`` it holds are then not orthogonal).  Fails on coord
    ea4f604 (no ``ScreenResult.response``)."""
    eid, alpha = "gyro_misalignment", 1e-3 / 24
    D = reliability.plausible_size(eid)
    rng = np.random.default_rng(5)
    U, _ = np.linalg.qr(rng.standard_normal((6, 6)))
    mu = np.array([2.0, 5.0, 8.0, 2e4, 5e4, 1e5])
    info = (U / D[:, None] * mu) @ (U / D[:, None]).T
    test = screening.ScreenResult(0.0, 6, info, score=np.zeros(6)).tested(eid, alpha)
    z = np.array([3.0, -2.0, 4.0, 0.5, 1.0, -0.7])  # the step along each direction, in σ
    d = U @ (z * np.sqrt(mu)) / D
    want = np.sum(z[3:] ** 2)
    assert test.response(d) == pytest.approx(want, rel=1e-9)
    assert test.response(d, info) == pytest.approx(want, rel=1e-9)  # the whole information
    assert test.response(d, dispersion=2.0) == pytest.approx(want / 2.0, rel=1e-9)
    # (gm's plausible sizes are alike: the information without the blind directions,
    # pseudo-inverted, reads the same; an effect whose sizes differ does not)
    assert reliability.score_response(d, test.information) == pytest.approx(want, rel=1e-9)
    D2 = reliability.plausible_size("radial_k1k2")  # k1 0.3, k2 1
    U2, _ = np.linalg.qr(rng.standard_normal((2, 2)))
    info2 = (U2 / D2[:, None] * [2.0, 5e4]) @ (U2 / D2[:, None]).T
    k1k2 = screening.ScreenResult(0.0, 2, info2, score=np.zeros(2)).tested("radial_k1k2",
                                                                            alpha)
    d2 = U2 @ (np.array([3.0, 1.0]) * np.sqrt([2.0, 5e4])) / D2
    assert k1k2.dof == 1 and k1k2.response(d2) == pytest.approx(1.0, rel=1e-9)
    assert abs(reliability.score_response(d2, k1k2.information) - 1.0) > 0.02  # 0.947
    assert reliability.score_response(d, info) == pytest.approx(np.sum(z ** 2), rel=1e-9)
    # a twin's information weighs the same directions: v (Wᵀ I W)⁻¹ v
    twin = info * 1.25
    assert test.response(d, twin) == pytest.approx(want / 1.25, rel=1e-9)
    # every direction seen: the whole information's response, as before
    seen = screening.ScreenResult(0.0, 6, info * 1e4, score=np.zeros(6))
    assert seen.tested(eid, alpha) is seen
    assert seen.response(d) == pytest.approx(reliability.score_response(d, info * 1e4),
                                             rel=1e-12)


def test_a_gyro_misalignment_at_its_mdb_responds_lam0_on_the_tested_directions():
    """Clean 300-s psce bag (seed 4600) and the same bag with a gyro misalignment at its
    printed MDB along e10 (+): the score's paired response on the test's 3 directions is λ₀
    (23.8; the score is linear in the effect there), while the whole information's (what
    ``--verify`` computed until H285) reads 30.5 = 1.28 λ₀: the 3 blind directions (μ ≪ λ₀)
    respond at second order.  Fails on coord ea4f604 (no ``ScreenResult.response``)."""
    eid, alpha = "gyro_misalignment", ALPHA / (2 * 12)

    def scored(effects):
        sim, model = injection.clean_simulation("psce", False, 4600, 300.0, effects)
        run = replay(bag_data_from_simulation(sim), rerun_prior(sim.prior), "psce", model,
                     consider=[eid], keep_tables=False, eval_fraction=0.5)
        item = kernel_scores(run, [eid])[eid]
        return sim, screening.ScreenResult(item[0], item[1], item[2], score=item[5])

    sim, clean0 = scored(None)
    test = clean0.tested(eid, alpha, sim.prior)
    det = reliability.detectability(eid, clean0.information, alpha, sim.prior)
    assert test.dof == det.dof == 3
    delta = injection.parameter_delta(eid, "e10", det.mdb["e10"])
    _, hit = scored({eid: injection.simulation_value(eid, delta)})
    d = hit.score - clean0.score
    assert test.response(d, dispersion=1.0) == pytest.approx(det.lam0, rel=0.02)
    # the injected run's information weighs the same directions alike
    assert test.response(d, hit.information, 1.0) == pytest.approx(det.lam0, rel=0.03)
    assert reliability.score_response(d, clean0.information) > 1.15 * det.lam0
