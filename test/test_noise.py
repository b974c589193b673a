"""Noise as a hypothesis (issue 21 item 1): the scales of the stated noise, measured.

Bags are simulated with known noise and their stated noise rewritten (the stars' sigma
field, the gyro's random walk against the filter's default), as a user's bag states its
noise wrongly.  Every measured scale is checked against the truth within 3 of its σ; the
diagnosis must name the noise, with the value to use, and no physical effect.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy import stats as sps

from stellar_cal_ros.core.noise import NoiseScales
from stellar_cal_ros.diagnosis import noise, noise_stars, noise_structure
from stellar_cal_ros.diagnosis.run import diagnose, measure_bag
from stellar_cal_ros.io.calibration import load_calibration
from stellar_cal_ros.methods.psce import PsceConfig
from stellar_cal_ros.methods.replay import bag_data_from_simulation
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate, write_simulation

DURATION = 200.0


def _sim(seed=3, gyro=1.0):
    sc = get_scenario("psce_rotations")
    sc = dataclasses.replace(sc, gyro_arw_deg_sqrth=sc.gyro_arw_deg_sqrth * gyro)
    return simulate(sc, duration=DURATION, seed=seed)


def _stated(sim, factor=1.0, faint_factor=None, zero=False):
    """The sim's bag data with the stars' sigma field rewritten."""
    data = bag_data_from_simulation(sim)
    for f in data.frames:
        s = np.asarray(f.sigma, dtype=float) * factor
        if faint_factor is not None:
            s = np.where(np.asarray(f.magnitude) > 5.0, s * faint_factor, s)
        f.sigma = np.zeros_like(s) if zero else s
    return data


def test_noise_scales_parse_store_and_apply():
    s = NoiseScales.parse("star=1.67,gyro=5,unknown=0.05")
    assert (s.star, s.gyro, s.accel, s.unknown_sigma_px) == (1.67, 5.0, 1.0, 0.05)
    assert NoiseScales.from_dict(s.as_dict()) == s
    g = NoiseScales(star=2.0, group_by="magnitude", edges=(5.0,), factors=(1.0, 3.0))
    assert NoiseScales.from_dict(g.as_dict()) == g
    sig = g.star_sigma(np.array([0.01, 0.01, 0.0]), 0.05, np.array([4.0, 6.0, 4.0]),
                       np.zeros((3, 2)), (0.0, 0.0))
    assert sig == pytest.approx([0.02, 0.06, 0.1])  # message x star x group; 0: default
    cfg = s.apply(PsceConfig())
    assert cfg.gyro_arw_deg_sqrth == pytest.approx(5 * PsceConfig().gyro_arw_deg_sqrth)
    assert cfg.noise is s and NoiseScales().identity and not s.identity
    for bad in ("star=-1", "star=x", "speed=2", "edges=4.5,factors=1/2", "by=magnitude,"
                "edges=4.5,factors=1", "by=colour,edges=1,factors=1/2", "by=row,edges=a",
                "by=magnitude,edges=4.5/4.0,factors=1/2/3", "by=row,edges=nan,factors=1/2"):
        with pytest.raises(ValueError):
            NoiseScales.parse(bad)
    # the groups as the diagnosis advises them (each group's factor of the messages' σ)
    p = NoiseScales.parse("by=magnitude,edges=4.02/4.8,factors=0.9/1.3/1.6,unknown=0.1")
    assert (p.group_by, p.edges, p.factors, p.star, p.unknown_sigma_px) == \
        ("magnitude", (4.02, 4.8), (0.9, 1.3, 1.6), 1.0, 0.1)
    g2 = g.replace(unknown_sigma_px=0.07)
    assert NoiseScales.parse(g2.advice()).star_sigma(
        np.array([0.01, 0.01, 0.0]), 0.05, np.array([4.0, 6.0, 4.0]), np.zeros((3, 2)),
        (0.0, 0.0)) == pytest.approx([0.02, 0.06, 0.07])
    # later groups compose with the kept ones: the bins of both, products
    c = g.times_groups("magnitude", (4.5, 5.5), (1.0, 2.0, 4.0))
    assert (c.edges, c.factors) == ((4.5, 5.0, 5.5), (1.0, 2.0, 6.0, 12.0))


def test_noise_scale_help_and_errors_say_what_a_group_spec_looks_like():
    """``replay --noise-scale`` with groups: a spec missing its edges or factors said "star
    groups need one factor per bin (len(edges) + 1)", a wrong grouping "star groups by
    'mag': use one of (...)" (neither naming the option nor the form), factors separated
    by ',' "takes star=S,...,unknown=PX,...; got '0.5'", and the help's metavar was
    ``star=S,gyro=G,accel=A``.  Now each is one line that names the option, what is wrong,
    and the form (``core.noise.GROUP_SPEC``), which the help states too; a group spec needs
    no ``unknown=`` (the diagnosis's advice without σ-0 stars parses back)."""
    import argparse

    from stellar_cal_ros.cli import _replay_noise, build_parser
    from stellar_cal_ros.core.noise import GROUP_SPEC
    from stellar_cal_ros.errors import StellarCalError

    form = "by=magnitude|radius|column|row,edges=E1/E2,factors=F0/F1/F2"
    assert form in GROUP_SPEC
    replay = next(a for a in build_parser()._subparsers._group_actions[0].choices[
        "replay"]._actions if "--noise-scale" in a.option_strings)
    assert form in replay.help and "needs no unknown=" in replay.help, replay.help
    assert replay.metavar == "KEY=VALUE,..."
    for bad, why in (("by=magnitude", "factors= is missing"),
                     ("by=magnitude,factors=1/0.5", "edges= is missing"),
                     ("edges=4.5,factors=1/0.5", "by= is missing"),
                     ("by=mag,edges=4.5,factors=1/0.5", "by='mag' is not a grouping"),
                     ("by=magnitude,edges=4.5/5,factors=1/0.5", "2 edges need 3 factors, got 2"),
                     ("by=magnitude,edges=4.5,factors=1,0.5", "factors: numbers separated by "
                      "'/', not ','"),
                     ("by=magnitude,edges=5/4.5,factors=1/0.5/2", "increasing")):
        with pytest.raises(StellarCalError) as err:
            _replay_noise(argparse.Namespace(noise_scale=bad, estimate_noise=False), None,
                          [], None)
        msg = str(err.value)
        assert msg.startswith("--noise-scale") and why in msg and GROUP_SPEC in msg and \
            "\n" not in msg, (bad, msg)
    # what the diagnosis advises for groups where no message says 0: no unknown=
    g = NoiseScales(star=1.2, group_by="column", edges=(640.0,), factors=(1.0, 0.5))
    assert "unknown" not in g.advice() and NoiseScales.parse(g.advice()) == \
        g.replace(star=1.0, factors=(1.2, 0.6))
    ok = _replay_noise(argparse.Namespace(noise_scale="by=radius,edges=300/600,"
                                          "factors=1/1.2/1.5", estimate_noise=False),
                       None, [], None)
    assert (ok.group_by, ok.edges, ok.factors, ok.unknown_sigma_px) == \
        ("radius", (300.0, 600.0), (1.0, 1.2, 1.5), 0.0)


@pytest.mark.parametrize("stated", [1.0, 0.6, 1.6])
def test_star_sigma_scale_from_within_frame_residuals(stated):
    """A sigma field 0.6x / 1.6x the truth: the scale 1/0.6, 1/1.6 within 3σ (the common
    attitude error, hence the gyro noise, drops out: a 5x gyro noise changes nothing)."""
    sim = _sim(gyro=5.0 if stated == 1.0 else 1.0)
    v = measure_bag(_stated(sim, stated), sim.prior, "psce", [], NoiseScales(),
                          components=())
    assert v.star == pytest.approx(1.0 / stated, abs=3 * v.star_sigma)
    assert v.star_sigma < 0.02 / stated
    assert ("star" in v.rejected) == (stated != 1.0)
    if stated != 1.0:
        assert v.applied.star == pytest.approx(v.star)
        assert f"{v.stated_sigma_px:.3g} -> {v.stated_sigma_px * v.star:.3g} px" in \
            v.lines()[0]


def test_gyro_noise_scale_from_its_samples_checked_by_maximum_likelihood():
    """5x the gyro random walk the filter assumes: the gyro's own samples measure it within
    3σ, it is named and applied, and the stars' ML (re-runs with it applied) agrees."""
    sim = _sim(gyro=5.0)
    v = measure_bag(_stated(sim), sim.prior, "psce", [], NoiseScales())
    s, e = v.scale_of("gyro")
    assert v.samples["gyro"]["white"] and s == pytest.approx(5.0, abs=3 * e) and e < 0.1
    assert v.rejected == ["gyro"] and v.applied.gyro == pytest.approx(s)
    g = v.imu["gyro"]  # relative to the samples' scale
    assert g.measurable and g.value == pytest.approx(1.0, abs=3 * g.sigma) and not v.beyond
    assert "gyro noise (angle random walk) looks" in " ".join(v.lines())
    assert "the stars agree" in " ".join(v.lines())
    # a check the stars do not pass is not called agreement (one noisy gyro axis: x0.754)
    v.imu["gyro"] = dataclasses.replace(g, value=1.0 - 5 * g.sigma)
    assert "the stars see: x" in " ".join(v.lines()) and "agree" not in " ".join(v.lines())


def test_a_gyro_noise_far_above_the_stated_is_measured_not_called_a_missing_effect():
    """The gyro's ARW configured in the wrong unit (a rad value read as deg: the true ARW
    57.3x the stated, unseen case ``gyro_x57``): with the stated gyro noise the model's run
    is too far off (NIS/dof ~6.4) and the verdict said "not measured: ... a missing effect
    shapes the residuals", beside the gyro's own samples' x57 (no effect is missing).  Now
    the run is made again with the samples' scale: the stars are measured (as stated,
    within 3σ), the gyro's x57 stands within 3σ, and no line speaks of a missing effect
    (fails on 423125a: ``v.skipped`` holds the NIS line).  The stars' check of the
    samples' scale (the likelihood's search around it) reads the truth over that scale
    within 3σ and the line says they agree (fails on f4c055a: the unrefined vertex of
    x1/3, x1, x3, "the stars see: x0.7 ... of it", H248)."""
    sim = _sim(gyro=57.3)
    v = measure_bag(_stated(sim), sim.prior, "psce", [], NoiseScales())
    assert not v.skipped, v.lines()
    s, e = v.scale_of("gyro")
    assert v.samples["gyro"]["white"] and s == pytest.approx(57.3, abs=3 * e)
    assert v.applied.gyro == pytest.approx(s) and "star" not in v.rejected
    assert v.star == pytest.approx(1.0, abs=3 * v.star_sigma) and v.star_sigma < 0.02
    assert "missing effect" not in " ".join(v.lines()), v.lines()
    g = v.imu["gyro"]
    assert g.measurable and g.value == pytest.approx(57.3 / s, abs=3 * g.sigma), g
    assert g.sigma < 0.1, g
    assert f"the stars agree: x{g.value:.3g} +- {g.sigma:.2g} of it" in " ".join(v.lines())


def test_a_sigma_field_in_arcsec_is_measured_and_its_runs_field_not_called_a_missing_effect():
    """The stars' σ field in arcsec where px was meant (unseen case ``sigma_arcsec``: 2.6
    for 0.05 px, 51.97x the truth): with that σ the filter's camera hardly leaves the prior
    and its stars repeat a field (cell means chi2 283 / 94 dof, p 7e-21), which the
    verdict called "a missing effect" (IMU noise taken as stated) beside the stars' x0.0191.
    Now the model is run again at the stars' measured σ and judged on that run: the field
    is gone, the gyro is measured (x1 within 3σ), and the stars' scale stays the truth's
    1/51.97 within 3σ (seed 3: 0.01909 ± 0.00016 for 0.01924).  Fails on main
    (``v.imu_skipped`` holds the field's line)."""
    sim = _sim()
    v = measure_bag(_stated(sim, factor=51.97), sim.prior, "psce", [], NoiseScales())
    assert not v.imu_skipped and not v.skipped, v.lines()
    assert "missing effect" not in " ".join(v.lines()), v.lines()
    assert v.applied.star == pytest.approx(1.0 / 51.97, abs=3.0 * v.star_sigma * v.stated.star)
    assert v.star == pytest.approx(1.0, abs=3.0 * v.star_sigma) and v.star_sigma < 0.02
    s, e = v.scale_of("gyro")
    assert s == pytest.approx(1.0, abs=3.0 * e), (s, e)
    assert v.applied.gyro == 1.0


def test_gyro_noise_the_stars_cannot_see_prints_a_bound_above_the_truth():
    """A gyro 10x quieter than stated whose samples are smoothed (a [1 2 1]/4 filter: not
    white, so the stars' likelihood search speaks for the gyro): the likelihood rises to a
    plateau below the stated noise, and the verdict prints the one-sided 95 % bound "gyro
    at most x B", which must hold the truth (seed 3: at most x0.616 for x0.1, the
    likelihood flat within 0.02 from x0.037 down; x0.505 before the crossing was bisected:
    a straight line between x0.333 and x1 put it inside the 95 % interval; seeds 4, 6:
    x0.431, x0.717)."""
    sim = _sim(gyro=0.1)
    data = _stated(sim)
    k = np.array([0.25, 0.5, 0.25])  # centred: no delay
    data.imu_w = np.stack([np.convolve(data.imu_w[:, i], k, "same") for i in range(3)], 1)
    v = measure_bag(data, sim.prior, "psce", [], NoiseScales())
    assert not v.samples["gyro"]["white"]
    g = v.imu["gyro"]
    assert not g.measurable and g.bound == "upper", g
    assert 0.1 < g.value < 1.0, g.value
    assert f"gyro at most x{g.value:.3g}" in " ".join(v.lines())


def test_star_scale_sigma_is_the_spread_of_the_scale_over_draws_on_a_bag():
    """The printed ``x s +- e`` of the stars on a bag's own rows (its frames, stars, cells,
    the attitude fit of each frame): the run's innovations replaced by 60 draws of white
    noise at the stated σ (truth 1), the window's z = (s − 1)/e has mean 0 and SD 1
    within 3 of their standard errors (seed 3: mean -0.04, SD 0.98).  Over 100 clean bags
    per method (``benchmarks/star_scale_z.py --seeds 1000-1099``) the bags' own z read
    +0.05 +- 0.09, SD 0.94 +- 0.07 (psce)."""
    from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
    from stellar_cal_ros.diagnosis.runstats import quiet

    sim = _sim()
    data = _stated(sim)
    with quiet():
        result = method_spec("psce").runner(data, rerun_prior(sim.prior), [],
                                            keep_tables=True, eval_fraction=0.5)
    res0 = dict(result.residuals)
    rng = np.random.default_rng(5)
    m, z = len(res0["du"]), []
    for _ in range(60):
        result.residuals = dict(res0, du=0.05 * rng.standard_normal(m),
                                dv=0.05 * rng.standard_normal(m), gated=np.zeros(m, bool))
        sn = noise.measure_stars(result, data, "psce", 0.5, None)
        s, e, _ = sn.group(~sn.unknown)
        z.append((s - 1.0) / e)
    z = np.array(z)
    assert abs(z.mean()) < 3.0 / np.sqrt(len(z)), z.mean()
    assert abs(z.std(ddof=1) - 1.0) < 3.0 / np.sqrt(2 * (len(z) - 1)), z.std(ddof=1)


def test_star_sigma_by_magnitude_group():
    """Faint stars (mag > 5) state half their noise: the magnitude groups are found and
    applied, the bright ones stay as stated.  Each printed group scale ``x s +- e (bin)``
    whose bin lies on one side of the step is its truth (1 bright, 2 faint) within 3 e
    (seed 4: x1.018 +- 0.018 below 5.0025 mag, x1.966 +- 0.021 above; since the step of
    the messages' σ is an edge, x1.018 +- 0.018 below 4.98 mag, x1.966 +- 0.021 above)."""
    sim = _sim(seed=4)
    data = _stated(sim, faint_factor=0.5)
    v = measure_bag(data, sim.prior, "psce", [], NoiseScales(), components=())
    assert v.group is not None and v.group["by"] == "magnitude", v.groups
    sc = np.asarray(v.group["scales"])
    assert sc.max() / sc.min() > 1.5
    edges = [-np.inf, *v.group["edges"], np.inf]
    # (the step of the stated σ is an edge: midway between the magnitudes of the accepted
    # stars beside 5.0: 4.98 here)
    mags = np.concatenate([np.asarray(f.magnitude, dtype=float) for f in data.frames])
    above = mags[mags > 5.0].min()
    sides = set()
    for lo, hi, scale, e in zip(edges[:-1], edges[1:], sc, v.group["sigma"], strict=True):
        truth = 1.0 if hi <= above else 2.0 if lo >= 4.97 else None
        if truth is not None:
            sides.add(truth)
            assert abs(scale - truth) < 3.0 * e, (lo, hi, scale, e)
    assert sides == {1.0, 2.0}, v.group
    s = v.applied
    bright = s.star_sigma(np.array([0.05]), 0.05, np.array([3.5]), np.zeros((1, 2)), (0, 0))
    assert bright[0] == pytest.approx(0.05, rel=0.1)


def test_a_sigma_field_that_varies_star_by_star_is_said_as_its_range():
    """The messages state 0.05 px for bright stars and 0.1 px (2x the truth) for faint ones
    (unseen case ``mag_faint_over2``): the group line gave the median, "the stars' sigma
    (0.1 px stated) depends on magnitude", a σ no bright star's message holds; now it
    gives the stated range and says the factors are of each star's own.  A constant field
    keeps its one value (the test above)."""
    sim = _sim(seed=4)
    v = measure_bag(_stated(sim, faint_factor=2.0), sim.prior, "psce", [],
                    NoiseScales(), components=())
    assert v.group is not None and v.group["by"] == "magnitude", v.groups
    line = next(x for x in v.lines() if "depends on" in x)
    assert "(0.05-0.1 px stated, the factors of each star's own)" in line, line


def test_a_later_rounds_scale_on_kept_groups_advises_the_groups_not_one_scale():
    """A later round measures the stars' σ relative to the scales applied before; when those
    hold σ groups (an earlier round's magnitude groups, kept), its one scale multiplies
    them.  The line said "use --noise-scale star=1.56" (unseen case ``sigma0_faint``, seed
    22), which a replay applies to every star alike: the bright stars' σ then 1.56x the
    messages' where the run used 0.9x.  Now it gives each group's factor of the messages'
    σ; without kept groups the one scale stays the advice."""
    before = NoiseScales(star=1.84, group_by="magnitude", edges=(4.02, 4.8),
                         factors=(0.58, 0.87, 1.07))
    v = noise.NoiseVerdict(before, before.replace(star=1.84 / 1.18))
    v.star, v.star_sigma, v.rejected = 1.0 / 1.18, 0.015, ["star"]
    v.stated_sigma_px, v.stated_sigma_range = 0.036, (0.029, 0.0435)
    line = next(x for x in v.lines() if "looks 1.18" in x)
    assert "--noise-scale star=" not in line, line
    assert "x0.904 (< 4.02 mag), x1.36 (4.02-4.8 mag), x1.67 (>= 4.8 mag)" in line, line
    v.stated = v.applied = NoiseScales(star=2.0)
    v.applied = NoiseScales(star=2.0 / 1.18)
    assert "use --noise-scale star=1.69" in " ".join(v.lines())
    # the σ it leads to is the messages' times the composed scale (sigma0_faint 300 s, its
    # second round: "looks 1.07 x too large (0.05 -> 0.0468 px): use star=0.993")
    v.stated, v.applied = NoiseScales(star=1.062), NoiseScales(star=1.062 / 1.07)
    v.star, v.stated_sigma_px, v.stated_sigma_range = 1 / 1.07, 0.05, (0.05, 0.05)
    line = next(x for x in v.lines() if "looks 1.07" in x)
    assert "too large for the x1.06 applied before (0.05 -> 0.0496 px): use --noise-scale " \
        "star=0.993" in line, line


def _step_bag(seed, sigma0):
    """150 s psce bag with a step of the messages' σ at 4.5 mag (unseen cases sigma0_faint,
    mag_faint_over2): ``sigma0``, faint stars say σ = 0 and are truly 0.1 px (bright 0.05
    px, stated); else every star truly 0.05 px, faint ones stated 0.1 px."""
    from stellar_cal_ros.sim import tracker_errors

    sc = dataclasses.replace(get_scenario("psce_rotations"), centroid_noise_px=0.0)
    sim = simulate(sc, duration=150.0, seed=seed)
    faint = 0.1 if sigma0 else 0.05
    tracker_errors.renoise(sim, lambda m, uv: np.where(m < 4.5, 0.05, faint), 0.05, seed)
    for f in sim.star_frames:
        f.sigma = np.where(np.asarray(f.magnitude) < 4.5, 0.05, 0.0 if sigma0 else 0.1)
    return sim, bag_data_from_simulation(sim)


def test_sigma_zero_stars_keep_their_own_sigma_beside_the_groups():
    """Faint stars say σ = 0 and are truly 0.1 px, bright ones state their 0.05 px (unseen
    case ``sigma0_faint``).  The magnitude groups were measured over all stars, the σ-0
    ones in them, and applied on top of the σ-0 stars' own measured σ (seed 4: groups
    x1.12 / x1.96 at 4.56 mag, a σ-0 star then 0.1025 px where 0.0981 was measured; on the
    300 s case rounds compounded to "x0.582 (< 4.02 mag)" for bright stars stated right).
    Now the groups are of the stated stars only: no grouping (they all state right), and a
    σ-0 star's σ is its measured one, the truth 0.1 px within 3 of its σ.  (The bright
    stars' one scale reads x1.12 +- 0.034 here: the frames' attitude fit weights the σ-0
    stars at the 0.05 px default in this first run, not yet at their 0.1 px.)"""
    sim, data = _step_bag(4, sigma0=True)
    v = measure_bag(data, sim.prior, "psce", [], NoiseScales(), components=())
    assert v.group is None, v.group
    assert v.unknown_sigma_px == pytest.approx(0.1, abs=3 * v.unknown_sigma_sigma)
    a = v.applied
    got = a.star_sigma(np.array([0.0, 0.0]), 0.05, np.array([4.6, 5.5]), np.zeros((2, 2)),
                       (0, 0))
    assert got == pytest.approx([v.unknown_sigma_px] * 2, rel=1e-12)
    # kept groups (as a replay given them) leave a measured σ-0 star's σ alone too
    g = a.replace(group_by="magnitude", edges=(4.5,), factors=(1.0, 2.0))
    got = g.star_sigma(np.array([0.0, 0.05]), 0.05, np.array([5.5, 5.5]), np.zeros((2, 2)),
                       (0, 0))
    assert got == pytest.approx([v.unknown_sigma_px, 0.1 * a.star], rel=1e-12)


def test_a_step_of_the_stated_sigma_is_a_group_edge_and_no_heavy_tail():
    """Every star truly 0.05 px; the messages state 0.05 px below 4.5 mag and 0.1 px above
    (unseen case ``mag_faint_over2``).  The tails were judged at the stars' one scale
    (x0.573) while groups x0.958 / x0.508 were applied: the bright stars, 1.67x that one
    scale, read "heavy-tailed: 1.1 % beyond the 99.9 % bound, p = 1.2e-17" (seed 4) for
    Gaussian noise.  Now the tails are judged at each star's group's scale, and the step of
    the messages' σ is an edge of the groups (the 300 s case's quantile edges 4.02 and 4.8
    mixed the two under one factor): each group lies on one side of the step and reads
    its truth (x1 bright, x0.5 faint) within 3 of its σ."""
    sim, data = _step_bag(4, sigma0=False)
    v = measure_bag(data, sim.prior, "psce", [], NoiseScales(), components=())
    assert v.tails is None and not any("heavy-tailed" in x for x in v.lines()), v.lines()
    assert v.group is not None and v.group["by"] == "magnitude", v.groups
    mags = np.concatenate([np.asarray(f.magnitude, dtype=float) for f in data.frames])
    below, above = mags[mags < 4.5].max(), mags[mags >= 4.5].min()
    assert any(below < e <= above for e in v.group["edges"]), v.group["edges"]
    edges = [-np.inf, *v.group["edges"], np.inf]
    for lo, hi, scale, e in zip(edges[:-1], edges[1:], v.group["scales"], v.group["sigma"],
                                strict=True):
        truth = 1.0 if hi <= above else 0.5 if lo > below else None
        assert truth is not None, (lo, hi)
        assert abs(scale - truth) < 3.0 * e, (lo, hi, scale, e)


def test_the_stated_sigmas_steps_along_a_variable():
    """:func:`noise_stars._stated_steps`: the midpoints where the messages' σ steps along a
    variable, none where it is constant or varies star by star."""
    x = np.array([3.0, 3.5, 4.2, 4.8, 5.0, 6.0])
    use = np.ones(6, dtype=bool)

    def sn(stated):
        return dataclasses.replace(_star_noise(n=6), stated_px=np.asarray(stated, dtype=float))

    assert noise_stars._stated_steps(sn([.05, .05, .05, .1, .1, .1]), x, use) == \
        pytest.approx([4.5])
    assert len(noise_stars._stated_steps(sn([.05] * 6), x, use)) == 0
    steps = noise_stars._stated_steps(sn([.05, .1] * 3), x, use)
    assert len(steps) == 5  # five steps (<= GROUP_BINS - 1): still a step function of x
    rng = np.random.default_rng(1)
    xs = np.sort(rng.uniform(3, 6, 200))
    wild = dataclasses.replace(_star_noise(n=200), stated_px=rng.choice([.05, .1], 200))
    assert len(noise_stars._stated_steps(wild, xs, np.ones(200, dtype=bool))) == 0


def _magfield_noise(stated, seed=21, stars=81, n=12000):
    """Rows of ``stars`` stars (magnitudes 2-6.3) whose true σ is 0.05·2^((mag − 4)/2) px
    and whose messages state ``stated(mag, true)`` (float32, as messages carry it)."""
    rng = np.random.default_rng(seed)
    mags = np.sort(rng.uniform(2.0, 6.3, stars))
    star = rng.integers(0, stars, n)
    true = 0.05 * 2.0 ** ((mags - 4.0) / 2.0)
    said = np.asarray(stated(mags, true, rng), dtype=np.float32).astype(float)
    r = (true / said)[star, None] * rng.standard_normal((n, 2))
    uv = rng.uniform(0, 1024, (n, 2))
    sn = noise_stars.StarNoise(0.0, 0.0, 2.0 * n, n // 30, (r**2).sum(1), 2 * np.ones(n),
                               mags[star], np.hypot(uv[:, 0] - 511.5, uv[:, 1] - 511.5),
                               np.zeros(n, bool), said[star], uv=uv, stated_px=said[star])
    sn.scale, sn.sigma, _ = sn.group(np.ones(n, bool))
    return sn, mags


def test_a_stated_sigma_field_that_jumps_from_its_trend_has_its_edge_there():
    """unseen case ``magfield_faint``: the messages' σ per magnitude, right below 5 mag and
    half the truth from 5 on.  The field varies star by star (no few-level step,
    :data:`~.noise_stars.STATED_STEPS`), so on 01729e2 no edge came of it and the groups'
    edge was a quantile's (5.18 on the bag: the 5.0-5.18 stars' x2 read as per-star
    spread).  Its jump from its own trend is an edge: at 5.0 within the neighbours'
    spacing, and the magnitude groups x1 / x2 about it (the one edge).  A smooth field
    (right, or 0.8x the truth everywhere) and one off per star by a random ±20 % give
    none, along magnitude, radius, column or row."""
    use = np.ones(12000, dtype=bool)
    for seed in (21, 22):
        sn, mags = _magfield_noise(lambda m, t, rng: np.where(m < 5.0, t, 0.5 * t), seed)
        steps = noise_stars._stated_steps(sn, sn.magnitude, use)
        lo, hi = mags[mags < 5.0].max(), mags[mags >= 5.0].min()
        assert len(steps) == 1 and lo < steps[0] < hi, (steps, lo, hi)
        g = next(g for g in noise_stars.star_groups(sn) if g["by"] == "magnitude")
        assert g["edges"] == pytest.approx([steps[0]]), g
        # (the scales within 5 %: over seeds 21-28 x0.988-1.003 and x1.949-2.032)
        assert g["scales"] == pytest.approx([1.0, 2.0], rel=0.05), g
    # two opposite jumps on a dense field of gentle trend (ln σ 0.35 per mag, 400 values:
    # under 1 % a gap): both edges.  The field's scatter was read over the jumps alone
    # (SD ~ 1: "no trend") and none came back (reviewer RE); one or two alike still found
    x = np.linspace(2.0, 6.3, 400)
    half = np.exp(0.35 * x) * np.where(x >= 5.0, 0.5, 1.0)
    for stated, at in ((half * np.where(x >= 3.0, 2.0, 1.0), (3.0, 5.0)),
                       (half * np.where(x < 3.0, 2.0, 1.0), (3.0, 5.0)), (half, (5.0,))):
        steps = noise_stars._trend_steps(x, stated)
        assert len(steps) == len(at), (steps, at)
        for s, e in zip(steps, at, strict=True):
            assert x[x < e].max() < s < x[x >= e].min(), (steps, e)
    level = {"right": lambda m, t, rng: t, "0.8x": lambda m, t, rng: 0.8 * t,
             "20 % per star": lambda m, t, rng: t * rng.uniform(0.8, 1.2, len(m))}
    for name, stated in level.items():
        for seed in range(21, 26):
            sn, _ = _magfield_noise(stated, seed)
            for x in (sn.magnitude, sn.radius, sn.uv[:, 0], sn.uv[:, 1]):
                assert len(noise_stars._stated_steps(sn, x, use)) == 0, (name, seed)


def test_diagnose_names_the_noise_not_an_effect(tmp_path):
    """The issue's first row: a clean bag whose sigma field states 0.6x the noise.  The
    diagnosis says the stars' sigma is 1.67x too small, with the value to use, and names no
    effect and no 'unexplained' lead; its noise block follows the contract."""
    sim = _sim(seed=6)
    s = diagnose(_stated(sim, 0.6), sim.prior, "psce", [], tmp_path, plots=False,
                 verbose=False)
    n = s["noise"]
    assert n["star_sigma_scale"] == pytest.approx(1 / 0.6, abs=3 * n["sigma"]["star_sigma_scale"])
    assert n["rescaled"] and not n["as_stated"]["star_sigma_scale"]
    assert n["as_stated"]["gyro_noise_scale"] and n["accel_noise_scale"] == 1.0
    assert "too small" in n["verdict"][0] and "--noise-scale star=1.6" in n["verdict"][0]
    assert s["recommendation"] is None and not s["unexplained"]
    assert not any(c["significant"] for c in s["candidates"])


def test_replay_measures_a_sigma_of_zero(tmp_path, capsys):
    """Stars whose message says sigma = 0 ("unknown"): replay measures their noise from the
    run and the result says the noise was rescaled (the CLI in-process: no interpreter
    start-up)."""
    from stellar_cal_ros.cli import main

    sim = _sim(seed=7)
    for f in sim.star_frames:
        f.sigma = np.zeros(len(f.sigma), dtype=np.float32)
    bag = tmp_path / "zero.mcap"
    write_simulation(sim, bag)
    capsys.readouterr()
    rc = main(["replay", str(bag), "--method", "psce", "--prior",
               str(tmp_path / "zero.prior.yaml"), "-o", str(tmp_path / "r.yaml"), "-q"])
    out = capsys.readouterr()
    assert rc == 0, out.err[-2000:]
    assert "stars carry sigma 0 (unknown): measured from the run" in out.out
    cons = load_calibration(tmp_path / "r.yaml").extra["consistency"]
    assert cons["noise_rescaled"] and cons["verdict"] == "consistent"
    # true 0.05 px; the measurement's σ is ~0.0004 px
    assert cons["noise"]["unknown_star_sigma_px"] == pytest.approx(0.05, abs=0.0015)


def test_repeating_field_is_structure_and_defers_the_imu_noise():
    """The cell means' χ² is χ²(dof) for noise alone and flags a field that repeats."""
    rng = np.random.default_rng(5)
    n = 20000
    uv = rng.uniform(0, 1024, (n, 2))
    mag = rng.uniform(2, 6, n)
    cell, keep = noise_stars._cells(uv, mag, (511.5, 511.5))
    r = rng.standard_normal((n, 2))
    _, _, chi2, dof = noise_stars._minus_cell_means(r, cell, keep)
    assert abs(chi2 - dof) < 4 * np.sqrt(2 * dof)  # χ²(dof): mean dof, σ √(2 dof)
    field = np.stack([(uv[:, 0] - 511.5) / 511.5 * 0.2, np.zeros(n)], 1)  # 0.2 σ at the edge
    _, _, chi2_f, _ = noise_stars._minus_cell_means(r + field, cell, keep)
    assert chi2_f - dof > 10 * np.sqrt(2 * dof)
    sn = noise_stars.StarNoise(1.0, 0.01, 2.0 * n, 1, np.ones(n), 2 * np.ones(n), mag,
                         np.zeros(n), np.zeros(n, bool), np.ones(n), chi2_f, dof)
    assert "repeating field" in noise.structured(sn)
    assert "across the stars' tracks" not in noise.structured(sn)  # (flips not drawn)
    sn.structure_flip_p = 0.114
    assert "p = 0.0085" not in noise.structured(sn) and \
        "; across the stars' tracks p = 0.11, " in noise.structured(sn)
    sn.structure = float(dof)
    assert noise.structured(sn) == ""


def _star_noise(n=20000, seed=8, factor=None):
    """A synthetic StarNoise: whitened residuals of scale ``factor(mag, uv)`` (1 = as stated)."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform(0, 1024, (n, 2))
    mag = rng.uniform(2, 6, n)
    s = np.ones(n) if factor is None else factor(mag, uv)
    r = s[:, None] * rng.standard_normal((n, 2))
    sn = noise_stars.StarNoise(0.0, 0.0, 2.0 * n, n // 30, (r**2).sum(1), 2 * np.ones(n), mag,
                         np.hypot(uv[:, 0] - 511.5, uv[:, 1] - 511.5), np.zeros(n, bool),
                         0.05 * np.ones(n), uv=uv)
    sn.scale, sn.sigma, _ = sn.group(np.ones(n, bool))
    return sn


def test_noise_that_changes_advises_no_scale_it_did_not_apply():
    """The stars' σ x1.45 before the window and x1.07 in it, few stars (the window's scale
    ±0.03, not told from the stated at ALPHA / 3): the change over the run is said, rejects
    "as stated", and the window's scale is not applied -- so no line may advise a scale.
    Before: "the stars' sigma looks 1.08 +- 0.03 x too small (0.05 -> 0.054 px): use
    --noise-scale star=1" (the advice was the applied scale, the stated 1) beside "(the
    window's is applied ...)".  With more stars the window's x1.07 is significant: applied,
    and advised as applied."""
    for n, applied_window in ((300, False), (1000, True)):
        sn = _star_noise(n=n, seed=0, factor=lambda m, uv: np.full(len(m), 1.07))
        sn.before = {"scale": 1.45, "sigma": 0.02, "from_s": 75.0, "to_s": 150.0}
        v = noise.NoiseVerdict(NoiseScales(), NoiseScales())
        v.applied = noise.judge_stars(v, sn, 0.05, (1024, 1024), 3)
        assert v.changes is not None and "star" in v.rejected and v.group is None
        assert abs(v.star - 1.07) < 3 * v.star_sigma
        assert (v.applied.star != 1.0) == applied_window, (v.star, v.star_sigma, v.star_p)
        lines = v.lines()
        advice = [x for x in lines if "--noise-scale star=" in x]
        change = next(x for x in lines if "changes over the run" in x)
        if applied_window:
            assert advice and advice[0].endswith(f"star={v.applied.star:.3g}"), lines
            assert "the window's is applied" in change
        else:
            assert not advice, lines
            assert "the window's is not told from the stated, which is kept" in change


def test_star_sigma_groups_find_the_region_and_the_step():
    """Unseen cases (benchmarks/unseen_cases.py 'region', 'mag2x'): the right third of the
    detector, or the stars fainter than 4.5 mag, twice as noisy as stated.  The grouping
    named is the true one (column, magnitude), its groups split near the true edge, each
    group's scale within 3σ of the truth (or of the mixture in the one bin the edge cuts);
    noise as stated is no grouping."""
    v = noise.NoiseVerdict(NoiseScales(), NoiseScales())
    region = _star_noise(factor=lambda m, uv: np.where(uv[:, 0] > 683, 2.0, 1.0))
    applied = noise.judge_stars(v, region, 0.05, (1024, 1024), 1)
    assert applied.group_by == "column", v.groups
    g = v.group
    assert g["scales"][0] == pytest.approx(1.0, abs=3 * g["sigma"][0])
    assert g["scales"][-1] == pytest.approx(2.0, abs=3 * g["sigma"][-1])
    assert all(640 <= e <= 768 for e in g["edges"])  # the bin the true edge (683) cuts
    assert "depends on column" in v.lines()[0] and "looks" not in v.lines()[0]
    v = noise.NoiseVerdict(NoiseScales(), NoiseScales())
    step = _star_noise(factor=lambda m, uv: np.where(m >= 4.5, 2.0, 1.0))
    assert noise.judge_stars(v, step, 0.05, (1024, 1024), 1).group_by == "magnitude"
    assert v.group["scales"][0] == pytest.approx(1.0, abs=3 * v.group["sigma"][0])
    assert v.group["scales"][-1] == pytest.approx(2.0, abs=3 * v.group["sigma"][-1])
    v = noise.NoiseVerdict(NoiseScales(), NoiseScales())
    assert noise.judge_stars(v, _star_noise(), 0.05, (1024, 1024), 1).identity
    assert v.group is None and v.lines()[0].startswith("noise as stated")


def test_error_repeating_star_by_star_is_not_noise():
    """Unseen case 'catalogue': each star's catalogue position off by its own error.  The
    per-star means' χ² is χ²(dof) for noise alone, flags the repeat, and the scale is
    measured without it (as stated, not 'sigma too small')."""
    rng = np.random.default_rng(9)
    stars, seen = 300, 40
    star = np.repeat(np.arange(stars), seen)
    r = rng.standard_normal((stars * seen, 2))
    share = np.ones(len(star))
    chi2, dof, _, _ = noise_stars.star_means(r, share, star)
    assert dof == pytest.approx(2 * stars)
    assert abs(chi2 - dof) < 4 * np.sqrt(2 * dof)
    off = 0.5 * rng.standard_normal((stars, 2))[star]  # 0.5 σ per star and axis
    chi2, dof, rest, share2 = noise_stars.star_means(r + off, share, star)
    assert (chi2 - dof) / np.sqrt(2 * dof) > 20
    # the excess is the offsets' variance: Σ n ‖δ‖² = (χ² − dof), within 10 %
    assert chi2 - dof == pytest.approx(float((off**2).sum()), rel=0.1)
    s2 = float((rest**2).sum() / (2 * share2.sum()))
    assert s2 == pytest.approx(1.0, abs=0.03)  # the scale without the repeat: as stated


def test_star_repeat_after_the_cells_is_chi2_of_its_exact_dof():
    """The per-star repeat is tested after the detector cells' means, which take most of a
    star's mean: its dof is 2 (stars − star/cell groups), not Σ 2 (1 − 1/n_s).  White
    tracks crossing 1-3 random cells (5 stars a cell on average): the χ² mean equals the
    dof within 4 σ and p is uniform (mean 0.5 within 4 σ; benchmarks/ar1_level.py's white
    draws, 150 stars, 200 draws: χ² 288.6 for
    288.1, p 0.494; the old count 177.6 for 295.2); one star a cell leaves no dof; a
    per-star error of 0.15 σ (a catalogue error, ~7 σ of the χ²) is detected at 1 %
    (0.1 σ, ~3.5 σ of the χ²: 29 of 40)."""
    rng = np.random.default_rng(3)
    reps, P, chi2s, dofs, hits = 40, [], [], [], 0
    for _ in range(reps):
        n = rng.integers(10, 60, size=120)
        star = np.repeat(np.arange(120), n)
        cell = np.concatenate([rng.integers(0, 24, size=3)[np.minimum(
            np.arange(k) * rng.integers(1, 4) // k, 2)] for k in n])
        r = rng.standard_normal((len(star), 2))
        keep = np.ones(len(star), dtype=bool)
        chi2, dof = noise_stars.star_after_cells(r, cell, keep, star)
        P.append(sps.chi2.sf(chi2, dof))
        chi2s.append(chi2)
        dofs.append(dof)
        off = 0.15 * rng.standard_normal((120, 2))[star]
        hits += sps.chi2.sf(*noise_stars.star_after_cells(r + off, cell, keep, star)) < 0.01
    assert abs(np.mean(chi2s) - np.mean(dofs)) < 4 * np.sqrt(2 * np.mean(dofs) / reps)
    assert abs(np.mean(P) - 0.5) < 4 / np.sqrt(12 * reps)
    assert hits >= 0.9 * reps, hits
    one = np.repeat(np.arange(30), 20)  # one star a cell: the cells take all
    chi2, dof = noise_stars.star_after_cells(rng.standard_normal((600, 2)), one,
                                             np.ones(600, dtype=bool), one)
    assert dof == 0 and chi2 == pytest.approx(0.0, abs=1e-8)


def test_star_means_after_the_cells_take_their_exact_share():
    """When an error that repeats star by star is removed, the star means are taken from
    residuals the detector cells' means have already left: a track that stays in its cell
    has had most of its mean taken.  Each row's share left is its expected square after
    both, the diagonal of ``(I − P_S)(I − P_C)(I − P_S)`` (``r'' = (I − P_S)(I − P_C) r``;
    checked on a dense layout to 1e-12; the other order, ``(I − P_C)(I − P_S)(I − P_C)``,
    has the same trace but is up to 0.009 off a row here), not ``(1 − 1/n_c)(1 − 1/n_s)``,
    which counted up to a whole dof twice a track (here 1.6 % of the rows' dof on 12
    tracks in 1-2 of 8 cells).  On a 150 s psce bag (seed 23, iid draws,
    the removal forced; ``benchmarks/star_scale_z.py``'s estimator) the scale read 1.0055
    (z +0.50 +- 0.07 over 200 draws), now 0.9993 (z -0.08, as without the removal)."""
    rng = np.random.default_rng(4)
    n = rng.integers(5, 30, size=12)
    star = np.repeat(np.arange(12), n)
    cell = np.concatenate([rng.integers(0, 8, size=2)[(np.arange(k) * 2) // k] for k in n])
    S = (star[:, None] == star[None, :]) / np.bincount(star)[star][None, :].astype(float)
    C = (cell[:, None] == cell[None, :]) / np.bincount(cell)[cell][None, :].astype(float)
    proj = (np.eye(len(star)) - S) @ (np.eye(len(star)) - C)
    exact = np.einsum("ij,ij->i", proj, proj)  # E ‖row i‖² of white unit residuals
    share_cells = 1.0 - np.diag(C)
    got = noise_stars.star_shares_after_cells(share_cells, np.ones(len(star)), star, cell)
    assert got == pytest.approx(exact, abs=1e-12)
    old = share_cells * (1.0 - 1.0 / np.bincount(star)[star])
    assert (exact.sum() - old.sum()) / exact.sum() > 0.01  # the old count: 1.6 % short
    # rows of share 0 (cells too small to count) take part in neither mean
    share0 = np.where(cell == cell[0], 0.0, share_cells)
    got0 = noise_stars.star_shares_after_cells(share0, np.ones(len(star)), star, cell)
    assert np.all(got0[cell == cell[0]] == 0.0) and np.all(got0 >= 0.0)


def test_spread_left_by_the_noise_groups_is_noise_not_a_lead():
    """Unseen case 'mag2x': after the magnitude groups are applied, the residuals' spread
    still varies with magnitude inside the bin the true step cuts; that line goes with the
    noise, while a bias (u, v) along magnitude stays an 'unexplained' lead."""
    from stellar_cal_ros.diagnosis.stats import RegressorFinding

    size = RegressorFinding("magnitude", "size", 4.2, 1e-3, 0.06)
    bias = RegressorFinding("magnitude", "u", 6.0, 1e-6, 0.1)
    other = RegressorFinding("u (column)", "size", 5.0, 1e-4, 0.07)
    v = noise.NoiseVerdict(NoiseScales(), NoiseScales())
    assert noise.within_groups([size, bias], v) == ([size, bias], [])
    v.group = {"by": "magnitude"}
    assert noise.within_groups([size, bias, other], v) == ([bias, other], [size])
    v.group = {"by": "column"}
    assert noise.within_groups([size, bias, other], v) == ([size, bias], [other])


def test_imu_sample_noise_sees_white_noise_through_motion_and_refuses_filtered_samples():
    """The IMU's own samples: white noise of σ 0.01 on a smooth motion with slew corners is
    measured within 3 of its σ and looks white; the same noise low-pass filtered (an IMU
    that filters its output) does not look white, so it is not used."""
    from stellar_cal_ros.diagnosis.noise_imu import sample_noise

    rng = np.random.default_rng(11)
    t = np.arange(30000) * 0.01
    motion = np.stack([np.sin(0.3 * t), np.where((t % 60) < 10, 0.5, 0.0), 0.1 * t], 1)
    x = motion + 0.01 * rng.standard_normal((len(t), 3))
    s, e, white = sample_noise(x)
    assert white and s == pytest.approx(0.01, abs=3 * e) and e < 2e-4
    kernel = np.ones(4) / 4.0
    filtered = np.stack([np.convolve(x[:, k], kernel, "same") for k in range(3)], 1)
    assert not sample_noise(filtered)[2]


def test_correlated_noise_line_names_both_factors_of_the_scale_to_use():
    """Unseen case 'ar1' (each star's noise an AR(1) over frames, lag-1 ρ 0.81): the line
    printed 'sigma x3.08: use --noise-scale star=2.97' without saying why two numbers.  The
    scale to use is the stars' scatter within frames times √((1+ρ)/(1−ρ)); the line names
    both and their product, each number the one it comes from.  The two rounds of the case:
    the scatter (0.964) within 5 % of the stated, kept (x1); then measured again with the
    x3.08 applied (0.313 of it), and applied (0.964 x 3.08 = 2.97)."""
    import re

    rho, scatter = 0.81, 0.964
    k = np.sqrt((1 + rho) / (1 - rho))
    for stated, kept in ((1.0, 1.0), (k, scatter)):
        sn = _star_noise(factor=lambda m, uv, s=stated: np.full(len(m), scatter / s))
        sn.magnitude = np.full(len(sn.q), np.nan)  # no groups: one scatter
        sn.radius, sn.uv = np.zeros(len(sn.q)), None
        sn.track_rho, sn.track_pairs = rho, 5000
        v = noise.NoiseVerdict(NoiseScales(star=stated), NoiseScales(star=stated))
        applied = v.applied = noise.judge_stars(v, sn, 0.05, (1024, 1024), 1)  # as measure()
        assert v.correlated["sigma_scale"] == pytest.approx(k, rel=1e-12)
        assert v.star * stated == pytest.approx(scatter, abs=3 * v.star_sigma * stated)
        assert applied.star == pytest.approx(kept * k, rel=0.01)  # kept: the measured within 1 %
        line = next(x for x in v.lines() if "correlated from frame to frame" in x)
        # no second line of the scatter alone ('x1.03 too large: use star=3.09')
        assert not any("sigma looks" in x for x in v.lines()), v.lines()
        got = re.search(r"needs the sigma x([\d.]+)(?: \+- [\d.e-]+)? \(= sqrt\(([\d.]+)\)\) "
                        r"on top of the stars' scatter within frames \(([\d.]+) x the "
                        r"messages' sigma\): use --noise-scale star=([\d.]+),rho=([\d.]+) "
                        r"\(their product", line)
        assert got, line
        shown_k, infl, white, use, shown_rho = (float(g) for g in got.groups())
        # the advice carries ρ (issue 21.3): `replay --noise-scale star=K,rho=R` judges its
        # NIS against the correlation (test_unseen_cases, the CLI from end to end)
        assert shown_rho == float(f"{rho:.2f}")
        assert shown_k == float(f"{k:.3g}") and infl == float(f"{(1 + rho) / (1 - rho):.3g}")
        assert use == float(f"{applied.star:.3g}")
        assert white == float(f"{applied.star / k:.3g}")
        assert white == pytest.approx(kept, rel=0.01)
        assert white * shown_k == pytest.approx(use, rel=0.005)  # the product, as printed
    # the terminal and report.html show the same line (diagnosis.json's noise.verdict)
    import html

    from stellar_cal_ros.diagnosis.printing import noise_lines
    from stellar_cal_ros.diagnosis.report_html import _discovery_html

    summary = {"noise": v.as_json()}
    assert f"noise: {line}" in noise_lines(summary)
    assert line in html.unescape(_discovery_html(summary))


def test_star_repeat_after_the_cells_holds_its_level_on_ar1_tracks():
    """The per-star repeat after the cells' means on pure AR(1) tracks (ρ 0.82, 10-80
    frames, 150 stars crossing 1-3 cells; ``benchmarks/ar1_level.py``'s draws): its χ²
    referred to the exact trace of the AR(1) covariance through the projection
    (``noise_stars._trace_after_cells``, ρ read about the star means) gives uniform p: mean
    0.5 within 4 σ (σ = 1/√(12 R)); 200 draws: 0.465 ± 0.020, ρ 0.5: 0.471.  The ratio of
    the star means' lagged and plain χ² (H52's factor) read 0.87 (the cells take the long
    parts of a track's mean), the dof count 2 mean(1 − 1/n) of main before it ~1.0."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from ar1_level import draw, pvalues

    rng, reps = np.random.default_rng(11), 60
    P = np.array([pvalues(*draw(rng, np.exp(-0.2)))[0] for _ in range(reps)])
    assert abs(P.mean() - 0.5) < 4.0 / np.sqrt(12.0 * reps), P.mean()


def test_trace_after_cells_is_the_projections_trace_of_the_ar1_covariance():
    """``noise_stars._trace_after_cells`` (what one axis of the repeat expects under AR(1)
    along each star's rows) equals ``tr((P_{S+C} − P_C) Σ)`` built densely on a small case
    (12 stars, 1-3 cells each of 5), and ``stars − groups`` for white noise; white +
    AR(1) noise, ``Σ = (1 − w) I + w Σ_AR``, the same (issue 21, H59)."""
    from scipy.linalg import block_diag

    rng = np.random.default_rng(4)
    n = rng.integers(3, 15, size=12)
    star = np.repeat(np.arange(12), n)
    cell = np.concatenate([rng.integers(0, 5, size=3)[np.minimum(np.arange(k) * 3 // k, 2)]
                           for k in n])
    S, C = np.eye(12)[star], np.eye(5)[cell]
    proj = lambda X: X @ np.linalg.pinv(X.T @ X) @ X.T  # noqa: E731
    Q = proj(np.hstack([S, C])) - proj(C)
    ns_, nc = np.bincount(star).astype(float), np.bincount(cell, minlength=5).astype(float)
    A = np.diag(nc) - (C.T @ S) @ np.diag(1.0 / ns_) @ (S.T @ C)
    Ap = np.linalg.pinv(A, rcond=1e-10, hermitian=True)
    for rho in (0.0, 0.5, 0.82):
        cov = block_diag(*[rho ** np.abs(np.subtract.outer(np.arange(k), np.arange(k)))
                           for k in n])
        got = noise_stars._trace_after_cells(star, cell, ns_, nc, Ap, rho)
        assert got == pytest.approx(float(np.trace(Q @ cov)), rel=1e-9)
        # white + AR(1) (the AR carrying w of the variance): linear in Σ; w 1 is the AR(1)
        w = 0.3
        assert noise_stars._trace_after_cells(star, cell, ns_, nc, Ap, rho, w) == \
            pytest.approx(float(np.trace(Q @ ((1 - w) * np.eye(len(star)) + w * cov))),
                          rel=1e-9)
        assert noise_stars._trace_after_cells(star, cell, ns_, nc, Ap, rho, 1.0) == got
    assert noise_stars._trace_after_cells(star, cell, ns_, nc, Ap, 0.0) == pytest.approx(
        np.linalg.matrix_rank(Q))


def test_sigma_zero_stars_take_the_correlation_factor_too():
    """Issue 21.4: stars whose message says σ = 0 ('unknown', measured from the run) carry
    the same AR(1) noise along their tracks as the others: the scale a white-noise filter
    needs is their measured scatter x √((1+ρ)/(1−ρ)), as for the stated stars (before, they
    kept the white scatter, 1/3.08 of it at ρ 0.81).  A quarter of the stars at σ 0 (the
    run's 0.05 px default), all with a true scatter of 0.964 x the σ used; the twin's
    within-frame scales take the factor off again, and the line names what is used."""
    rho, scatter = 0.81, 0.964
    k = np.sqrt((1 + rho) / (1 - rho))
    sn = _star_noise(factor=lambda m, uv: np.full(len(m), scatter))
    sn.magnitude = np.full(len(sn.q), np.nan)  # no groups: one scatter
    sn.radius, sn.uv = np.zeros(len(sn.q)), None
    sn.unknown = np.arange(len(sn.q)) % 4 == 0
    sn.track_rho, sn.track_pairs = rho, 5000
    v = noise.NoiseVerdict(NoiseScales(), NoiseScales())
    applied = v.applied = noise.judge_stars(v, sn, 0.05, (1024, 1024), 1)
    assert v.correlated["sigma_scale"] == pytest.approx(k, rel=1e-12)
    # the measured scatter of the σ-0 stars: the truth within 3 of its σ
    assert v.unknown_sigma_px == pytest.approx(0.05 * scatter, abs=3 * v.unknown_sigma_sigma)
    assert applied.unknown_sigma_px == pytest.approx(v.unknown_sigma_px * k, rel=1e-12)
    assert applied.star_inflation == pytest.approx(k, rel=1e-12)
    white = applied.within_frames()
    assert white.unknown_sigma_px == pytest.approx(v.unknown_sigma_px, rel=1e-12)
    assert white.star == pytest.approx(applied.star / k, rel=1e-12)
    line = next(x for x in v.lines() if "carry sigma 0" in x)
    assert f"{v.unknown_sigma_px * k:.3g} px" in line and f"x{k:.3g}" in line, line


def test_trace_after_cells_is_linear_in_a_track_length():
    """``_trace_after_cells`` sums the AR(1) covariance over the runs of a track's cells in
    closed form (``noise_stars._run_sums``), not as a dense ``n × n`` matrix a star, whose
    cost grew as n² (4 000 rows: 1.6 CPU-s and 0.46 GB a star; a star held for 2 h on a
    still base has 7 200 rows in the evaluation half): the dense form's numbers on tracks
    of up to 900 rows that leave and re-enter their cells (1e-9 relative), and on tracks
    of 50 000 rows (dense: 20 GB a star) a trace within the AR(1) covariance's eigenvalue
    bounds ``(1 ∓ ρ)/(1 ± ρ)`` times ``stars − groups``."""
    rng = np.random.default_rng(8)

    def case(n_stars, lo, hi, cells, flip=0.0):
        # each track crosses up to 3 cells; with ``flip`` a row's centroid is in another of
        # them (a star jittering across a boundary: runs that return to a cell)
        n = rng.integers(lo, hi, size=n_stars)
        star = np.repeat(np.arange(n_stars), n)
        seg = [np.where(rng.random(k) < flip, rng.integers(0, 3, size=k),
                        np.minimum(np.arange(k) * 3 // k, 2)) for k in n]
        cell = np.concatenate([rng.integers(0, cells, size=3)[g] for g in seg])
        _, cell = np.unique(cell, return_inverse=True)
        ns_, nc = np.bincount(star).astype(float), np.bincount(cell).astype(float)
        N = np.zeros((n_stars, len(nc)))
        np.add.at(N, (star, cell), 1.0)
        A = np.diag(nc) - N.T @ np.diag(1.0 / ns_) @ N
        return star, cell, ns_, nc, np.linalg.pinv(A, rcond=1e-10, hermitian=True)

    def dense(si, ci, ns_, nc, Ap, rho):  # the form it replaces
        B, within = np.zeros((len(nc), len(nc))), np.zeros(len(nc))
        for s in range(len(ns_)):
            rows = np.flatnonzero(si == s)
            cu, loc = np.unique(ci[rows], return_inverse=True)
            E = np.zeros((len(rows), len(cu)))
            E[np.arange(len(rows)), loc] = 1.0
            k = np.arange(len(rows), dtype=float)
            cov = rho ** np.abs(k[:, None] - k[None, :])
            within[cu] += np.einsum("ij,ik,kj->j", E, cov, E)
            ME = E - E.mean(0)
            B[np.ix_(cu, cu)] += ME.T @ cov @ ME
        return float(np.sum(noise_structure.mean_factor(ns_, rho)) + np.sum(Ap * B.T)
                     - np.sum(within / nc))

    args = case(8, 200, 900, 6, flip=0.05)
    for rho in (0.0, 0.5, 0.82, 0.95):
        assert noise_stars._trace_after_cells(*args, rho) == pytest.approx(
            dense(*args, rho), rel=1e-9)
    args = case(4, 40_000, 50_000, 5)
    rank = noise_stars._trace_after_cells(*args, 0.0)
    rho = 0.82
    got = noise_stars._trace_after_cells(*args, rho)
    assert rank >= 1
    assert (1 - rho) / (1 + rho) * rank <= got <= (1 + rho) / (1 - rho) * rank, (got, rank)


def _frames_of_few_stars(rng, frames=200, stars=60, per=(3, 5), f=1000.0, c=512.0):
    """A residual table of frames of ``per`` stars from a field of ``stars`` (pinhole)."""
    uv0 = rng.uniform(50, 974, size=(stars, 2))
    mag = rng.uniform(3, 6, size=stars)
    fr, ids = [], []
    for t in range(frames):
        k = rng.choice(stars, size=rng.integers(per[0], per[1] + 1), replace=False)
        fr += [t] * len(k)
        ids += list(k)
    fr, ids = np.array(fr), np.array(ids)
    x, y = (uv0[ids, 0] - c) / f, (uv0[ids, 1] - c) / f
    nrm = np.sqrt(x * x + y * y + 1.0)
    return {"frame": fr, "catalog_id": ids, "u": uv0[ids, 0], "v": uv0[ids, 1],
            "magnitude": mag[ids], "x_st": x / nrm, "y_st": y / nrm, "z_st": 1.0 / nrm,
            "t": 0.5 * fr, "gated": np.zeros(len(fr), dtype=bool)}


def test_star_scale_sigma_counts_the_frames_shared_attitude_fit():
    """White noise in frames of 3-5 stars: the scale's printed σ is its scatter over 200
    draws within 3/√(2·200) (measured 1.07), and √(1/(2 dof)) within 10 % (0.95; not
    exact: the cells' means act after the frames' fits).  Each frame's attitude fit takes 3
    of its 6-10 dof, so its stars' ‖r‖² covary: summed row by row (main) the σ read 0.78x
    the scatter (0.80x √(1/(2 dof))); the scores are now summed per frame first."""
    rng = np.random.default_rng(5)
    res = _frames_of_few_stars(rng)
    n = len(res["t"])
    sig = np.full(n, 0.05)
    got = []
    for _ in range(200):
        res["du"], res["dv"] = (0.05 * rng.standard_normal((2, n)))
        sn = noise_stars.star_noise(res, sig, sig, np.ones(n, dtype=bool), 1000.0, 1000.0,
                                    (512.0, 512.0))
        got.append((sn.scale, sn.sigma, sn.dof))
    s, e, dof = np.array(got).T
    printed = math.sqrt(np.mean(e**2))
    assert s.std(ddof=1) / printed == pytest.approx(1.0, abs=3.0 / math.sqrt(2.0 * len(s)))
    assert printed == pytest.approx(math.sqrt(1.0 / (2.0 * dof.mean())), rel=0.1)
    assert s.mean() == pytest.approx(1.0, abs=4 * s.std() / math.sqrt(len(s)))


# ----------------------------------------------------------------------------- printed numbers
def test_noise_as_measured_before_prints_both_factors_of_the_true_scale():
    """A later round, the stars' 0.6x sigma already rescaled (star x1.67 applied): "noise as
    measured before: stars' sigma 0.03 -> 0.0496 px (x1.65 +- 0.014 of the stated) (this
    round: stars' sigma x s +- e, gyro x g +- e from its samples of the scales applied
    before, ...): use --noise-scale star=1.653".  The composed scale must be the truth 1/0.6
    within 3 of its σ, and the gyro's (stated right) 1 within 3σ (seed 3: x1.67 * x0.992 +-
    0.0084 = 1.653 for 1.667; gyro x1 +- 0.0052)."""
    import re

    sim = _sim()
    v = measure_bag(_stated(sim, 0.6), sim.prior, "psce", [], NoiseScales(star=1 / 0.6))
    line = next(x for x in v.lines() if x.startswith("noise as measured before"))
    # (the composed scale and its σ now, the σ it leads to and the scale to use: H106)
    m = re.search(r"stars' sigma 0.03 -> (\S+) px \(x(\S+) \+- (\S+) of the stated\)", line)
    px, k, e = (float(x) for x in m.groups())
    assert k == pytest.approx(1 / 0.6, abs=3 * e) and px == pytest.approx(0.03 * k, rel=5e-3)
    assert f"use --noise-scale star={k:.3g}" in line, line
    g = re.search(r"gyro x(\S+) \+- (\S+) from its samples", line)
    assert float(g[1]) == pytest.approx(1.0, abs=3 * float(g[2])), line


def test_far_off_line_prints_the_nis_per_dof_at_the_true_sigma():
    """The model far off (a gyro random walk 100x the filter's) on a bag whose stars state
    half their noise: the far-off line's NIS/dof must be the model's misfit, the NIS/dof
    computed with each star's innovation covariance holding the true 0.05 px (seed 3:
    printed 11.19 for 11.20).  It printed the run's own NIS/dof, 44.5: the stated
    sigma's error (x4) that the decision itself had divided out."""
    import re

    from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
    from stellar_cal_ros.diagnosis.runstats import evaluate
    from stellar_cal_ros.diagnosis.stats import accepted, evaluation_mask

    sim = _sim(gyro=100.0)
    data = _stated(sim, 0.5)
    base = evaluate(data, method_spec("psce"), rerun_prior(sim.prior), (), 0.5,
                    keep_residuals=True, star_noise=True)
    line = noise.far_off(base, base.star_noise)
    printed = float(re.search(r"NIS/dof (\S+?)[ ,)]", line)[1])
    r = base.residuals
    k = evaluation_mask(r, 0.5) & accepted(r)
    du, dv, b = r["du"][k], r["dv"][k], r["s_uv"][k]
    extra = 0.05**2 - (0.5 * 0.05) ** 2  # the true σ² for the stated
    a, c = r["s_uu"][k] + extra, r["s_vv"][k] + extra
    truth = float(np.mean((c * du**2 - 2 * b * du * dv + a * dv**2) / (a * c - b * b)) / 2)
    assert truth > 2 * noise.MAX_DISPERSION  # far off indeed
    assert printed == pytest.approx(truth, rel=0.05), (printed, truth, line)


def test_imu_scale_search_finds_the_maximum_of_a_likelihood_far_from_a_parabola():
    """The ML search's printed "x s +- e" on a noise-free variance-component likelihood
    ``-n/2 (ln v + v_true / v)``, ``v = floor + s²`` (what the stars see of the gyro beside
    their own noise): steep toward large scales, flat toward small ones, so a parabola
    through the search's factor-of-3 steps misses its maximum.  The value must be the truth
    within 0.3 of the printed σ (before: a parabola through the coarse points and one run
    at its vertex: x2.88 +- 0.10 for x4, x19.3 +- 1.9 for x10), and σ of ln s the
    likelihood's own, 1 / sqrt(curvature) (a likelihood without frames: no sandwich),
    within 20 %."""
    from stellar_cal_ros.diagnosis.noise_imu import search_scale

    for truth, n, floor in [(4.0, 2000, 25.0), (10.0, 50, 0.0), (3.0, 200, 4.0),
                            (7.0, 2000, 25.0)]:
        def loglik(xs, truth=truth, n=n, floor=floor):
            v = floor + np.exp(2 * np.asarray(xs))
            return list(-0.5 * n * (np.log(v) + (floor + truth**2) / v))

        s = search_scale("gyro", loglik)
        # -d²ℓ/d(ln s)² at the maximum: 2 n (s²/v)²
        curv = 2 * n * (truth**2 / (floor + truth**2)) ** 2
        assert s.measurable and s.value == pytest.approx(truth, abs=0.3 * s.sigma), (truth, s)
        assert s.sigma / s.value == pytest.approx(1 / np.sqrt(curv), rel=0.2), \
            (truth, s)


def test_imu_search_sigma_is_the_sandwich_of_a_composite_likelihood():
    """The search's σ of ln s when its log-likelihood is a composite one (issue 21): 300
    frames, each a 2-d draw of variance 4 + s² (truth s = 4) whose term is counted 4 times
    (as a frame's stars share one attitude error, each star's own NIS counts it again), 150
    draws.  The score then varies 4x more than the curvature says: the printed σ must be
    the sandwich's, the SD of ln s over the draws within 3 SE of the rms printed σ (1.006
    +- 0.058; 1 / sqrt(curvature) alone: ~0.5), and the dispersion 4 within 10 % (4.14)."""
    from stellar_cal_ros.diagnosis.noise_imu import search_scale

    rng = np.random.default_rng(5)
    n, m, truth, floor = 300, 4, 4.0, 4.0
    ids = np.arange(n, dtype=float)
    ln, sig, disp = [], [], []
    for _ in range(150):
        y2 = (floor + truth**2) * rng.chisquare(2, n)

        def loglik(xs, y2=y2):
            out = []
            for x in xs:
                v = floor + np.exp(2 * x)
                terms = -0.5 * m * (2 * np.log(v) + y2 / v)
                out.append((float(terms.sum()), np.stack([ids, terms])))
            return out

        s = search_scale("gyro", loglik)
        assert s.measurable and not s.frames, s
        ln.append(np.log(s.value))
        sig.append(s.sigma / s.value)
        disp.append(s.dispersion)
    ratio = np.std(ln, ddof=1) / np.sqrt(np.mean(np.square(sig)))
    assert abs(ratio - 1.0) < 3 / np.sqrt(2 * (len(ln) - 1)), ratio
    assert np.mean(disp) == pytest.approx(m, rel=0.1), np.mean(disp)


def test_imu_search_at_the_stated_scale_reads_the_maximum_not_the_coarse_vertex():
    """Where "as stated" is the best of the search's first three runs (a factor of 3
    apart), the value is the maximum refined by a triple around it, as elsewhere, not the
    coarse parabola's vertex (H209's "settled" shortcut), and its σ takes the sandwich's
    dispersion at least 1, as the p does.  The white gyro samples' check on a clean bag
    is such a search: a variance component v = 4 + s² (the stars' share 4, the gyro's s²,
    truth x1) over 300 2-d draws, 200 draws: ln s mean −0.008 ± 0.009, its SD 0.130
    against a printed 0.150 (z SD 1.05), 5.6 runs.  On main 17d7d23 the coarse vertex
    read ln s −0.471 ± 0.003 (x0.62) with σ 0.052: z mean −11 (clean psce 300 s seeds
    2000-2041 through ``benchmarks/imu_search_spread.py --gyro 1 --white``: x0.859 → x0.884,
    doc/benchmarks.md, H221)."""
    from stellar_cal_ros.diagnosis.noise_imu import search_scale

    rng = np.random.default_rng(3)
    n, floor = 300, 4.0
    ids = np.arange(n, dtype=float)
    ln, sig = [], []
    for _ in range(200):
        y2 = (floor + 1.0) * rng.chisquare(2, n)

        def loglik(xs, y2=y2):
            out = []
            for x in xs:
                terms = -(np.log(floor + np.exp(2 * x)) + 0.5 * y2 / (floor + np.exp(2 * x)))
                out.append((float(terms.sum()), np.stack([ids, terms])))
            return out

        s = search_scale("gyro", loglik, bound=False)
        if s.measurable:  # (~5 %: the likelihood open toward 0)
            ln.append(np.log(s.value))
            sig.append(s.sigma / s.value)
    ln, sig = np.array(ln), np.array(sig)
    se = ln.std(ddof=1) / np.sqrt(len(ln))
    assert abs(ln.mean()) < 3 * se, (ln.mean(), se)
    assert len(ln) > 180
    z = ln / sig
    assert 0.85 < z.std(ddof=1) < 1.2, z.std(ddof=1)
    assert abs(z.mean()) < 0.25, z.mean()


def test_imu_search_reads_a_sharp_maximum_from_a_triple_a_few_sigma_wide():
    """Where the likelihood's maximum is sharp (σ of ln s well below the refinement's
    ±0.2), the ±0.2 triple's parabola misses it by a deterministic part of σ (the
    likelihood in ln s is skewed, steep toward large scales), which grows as √n: the
    maximum is read again from a triple ±2σ wide.  The expected log-likelihood of a
    variance component v = 1 + s² (truth x1, the maximum exactly at ln s = 0) over 20 000
    2-d draws (σ of ln s 0.007): ln s −0.0132 (−1.86σ) from the ±0.2 triple (f4c055a + H221's
    refinement), now within 0.1σ.  The stars' check of the samples' x57.1 on unseen case
    ``gyro_x57`` s21: x1.00 (±0.2) → x1.02 (±0.03), the likelihood's maximum x1.018
    (doc/benchmarks.md, H248)."""
    from stellar_cal_ros.diagnosis.noise_imu import search_scale

    n, floor = 20000, 1.0
    ids = np.arange(n, dtype=float)

    def loglik(xs):
        out = []
        for x in xs:
            v = floor + np.exp(2 * x)
            terms = np.full(n, -(np.log(v) + (floor + 1.0) / v))  # E[y²] / 2 = floor + 1
            out.append((float(terms.sum()), np.stack([ids, terms])))
        return out

    s = search_scale("gyro", loglik, bound=False)
    assert s.measurable and 0.005 < s.sigma < 0.01, s
    assert abs(np.log(s.value)) < 0.1 * s.sigma / s.value, s


def test_a_noise_scale_on_the_capped_likelihood_is_not_biased_low_by_the_cap():
    """The window log-likelihood caps each star's NIS at 13.8 (a misidentified star must
    not dominate a comparison of models); a star's ``log det S`` beside it is weighted by
    ``P(χ²₄ < 13.8)`` = 0.992 (``results.logdet_weight``), which makes the capped score's
    mean 0 at the truth for a noise scale.  Innovations ν ~ N(0, S), S = R + s² Q (the
    gyro's share Q of 5 %, a few % as on a clean psce bag, and 50x as under a gyro 57x the
    stated), truth s = 1, stars beyond the gate (χ²₂ 0.9999) gated, 20 draws of 20 000
    stars through ``RunStats`` (the search's likelihood) and ``stats.log_likelihood``: ln s
    of the maximum within 2 SE of 0 (at weight 1, as on main 884abd3: −0.093 ± 0.022 at
    the 5 % share with ``RunStats``, fails; 400 draws by hand: −0.102 ± 0.005 and −0.0046 ±
    0.0002 at weight 1, +0.0002 ± 0.004 and −0.0003 ± 0.0002 weighted, doc/benchmarks.md
    H264)."""
    from types import SimpleNamespace

    from scipy import optimize

    from stellar_cal_ros.diagnosis import stats
    from stellar_cal_ros.methods.results import LOGDET_WEIGHT, NIS_CAP, RunStats

    assert LOGDET_WEIGHT == pytest.approx(sps.chi2.cdf(NIS_CAP, 4), rel=1e-12)
    rng = np.random.default_rng(11)
    n, gate = 20000, sps.chi2.ppf(0.9999, 2)
    for share in (0.05, 50.0):
        got = {"runstats": [], "table": []}
        for _ in range(20):
            r = rng.uniform(0.5, 2.0, n)  # each star's own noise, its gyro part share x r
            rho = rng.uniform(-0.5, 0.5, n)
            nu = rng.standard_normal((n, 2))

            def cov(x, r=r, rho=rho, share=share):
                v = r * (1.0 + share * math.exp(2 * x))
                S = np.empty((n, 2, 2))
                S[:, 0, 0], S[:, 1, 1] = v, v
                S[:, 0, 1] = S[:, 1, 0] = rho * v
                return S

            L = np.linalg.cholesky(cov(0.0))
            y = np.einsum("nij,nj->ni", L, nu)

            def ell(x, how, y=y, cov=cov):
                S = cov(x)
                nis = np.einsum("ni,nij,nj->n", y, np.linalg.inv(S), y)
                acc = nis <= gate
                if how == "table":
                    res = {"s_uu": S[:, 0, 0], "s_vv": S[:, 1, 1], "s_uv": S[:, 0, 1],
                           "nis": nis, "gated": ~acc}
                    return stats.log_likelihood(res, np.ones(n, dtype=bool))
                rs = RunStats()
                rs.add(SimpleNamespace(stamp=0.0, uv=y, uv_pred=np.zeros_like(y), S=S,
                                       nis_stars=nis, accepted=acc, nis=float(nis.sum()),
                                       dof=2 * n))
                return rs.log_likelihood()

            for how, out in got.items():
                fit = optimize.minimize_scalar(lambda x, how=how: -ell(x, how),
                                               bounds=(-1.0, 1.0), method="bounded",
                                               options={"xatol": 1e-5})
                out.append(fit.x)
        for how, xs in got.items():
            xs = np.array(xs)
            se = xs.std(ddof=1) / math.sqrt(len(xs))
            assert abs(xs.mean()) < 2 * se, (share, how, xs.mean(), se)


def test_imu_search_p_value_holds_its_level_on_a_composite_likelihood():
    """The search's p of "as stated" (issue 21) when its log-likelihood is a composite one:
    100 frames, each frame's term -m (x - e_i)² / 2τ² counted m = 2 times (as a frame's stars
    share one attitude error), e_i ~ N(0, τ²), the truth at ln s = 0 (the stated noise), σ
    of ln s 0.4 (a clean 100 s psce bag's, where the search's factor-of-3 grid does not
    hide the tail), 400 draws.  The ratio 2 Δℓ is then 2 χ²₁: the p must come from the
    ratio over its dispersion, its share below 0.05 within 3 SE of 0.05 and below 0.01
    within 3 SE above 0.01 (2000 draws: 0.056, 0.0085; the ratio on χ²₁ alone: 0.153,
    0.071, and 400 draws' 0.17, 0.07 fail both, checked)."""
    from stellar_cal_ros.diagnosis.noise_imu import search_scale

    rng = np.random.default_rng(2)
    n, m, sd, draws = 100, 2.0, 0.4, 400
    tau = sd * np.sqrt(n)
    ids = np.arange(n, dtype=float)
    p, disp = [], []
    for _ in range(draws):
        e = rng.normal(0.0, tau, n)

        def loglik(xs, e=e):
            terms = [-0.5 * m * (x - e) ** 2 / tau**2 for x in xs]
            return [(float(t.sum()), np.stack([ids, t])) for t in terms]

        s = search_scale("gyro", loglik)
        p.append(s.p_value)
        if s.statistic > 0:
            disp.append(s.dispersion)
    p = np.array(p)
    for level in (0.05, 0.01):
        se = np.sqrt(level * (1 - level) / draws)
        assert np.mean(p < level) < level + 3 * se, (level, np.mean(p < level))
    assert np.mean(p < 0.05) > 0.05 - 3 * np.sqrt(0.05 * 0.95 / draws), np.mean(p < 0.05)
    # the dispersion the ratio was divided by: the frames' own, m within its spread
    assert np.median(disp) == pytest.approx(m, rel=0.1), np.median(disp)


def test_frame_log_likelihood_is_the_windows_star_terms_by_frame():
    """RunStats.frame_log_likelihood (the search's sandwich reads it): a run inside
    keeping_frames gives each window frame's terms, the same as its residual table's stars'
    (min(NIS, 13.8) + w log det S + 2 ln 2π, × -1/2, w = P(χ²₄ < 13.8)) summed by frame, and
    they sum to the run's log-likelihood; a run outside keeps none.  Gyro 5x, stated gyro x3,
    the stars stating 0.6 of their σ: 5 of the window's stars gated (their terms at the cap
    with the window's mean log det), the window's 200 frames all present."""
    from stellar_cal_ros.diagnosis.discover import method_spec
    from stellar_cal_ros.methods.results import LOGDET_WEIGHT, NIS_CAP, keeping_frames

    sim = _sim(seed=4, gyro=5.0)
    data = _stated(sim, 0.6)
    spec = method_spec("psce")
    with keeping_frames():
        r = spec.runner(data, sim.prior, [], keep_tables=True, eval_fraction=0.5,
                        noise=NoiseScales(gyro=3.0), gyro_fault="off")
    f = r.stats.frame_log_likelihood()
    res = r.residuals
    win = res["t"] >= r.stats.eval_start
    ok = ~res["gated"].astype(bool)
    det = res["s_uu"] * res["s_vv"] - res["s_uv"] ** 2
    w = sps.chi2.cdf(NIS_CAP, 4)
    assert w == pytest.approx(LOGDET_WEIGHT, rel=1e-12)
    fill = w * np.mean(np.log(det[win & ok]))
    terms = -0.5 * (np.where(ok, np.minimum(res["nis"], NIS_CAP)
                             + w * np.log(np.where(ok, det, 1)), NIS_CAP + fill)
                    + 2 * np.log(2 * np.pi))
    stamps, inv = np.unique(res["t"][win], return_inverse=True)
    assert len(stamps) > 150 and np.array_equal(f[0], stamps), (f.shape, len(stamps))
    assert np.any(win & ~ok), "no gated star: the fill term is not checked"
    np.testing.assert_allclose(f[1], np.bincount(inv, weights=terms[win]), rtol=1e-9)
    assert f[1].sum() == pytest.approx(r.stats.log_likelihood(), rel=1e-12)
    r2 = spec.runner(data, sim.prior, [], eval_fraction=0.5, noise=NoiseScales(gyro=3.0),
                     gyro_fault="off")
    assert r2.stats.frame_log_likelihood() is None


def test_imu_search_sigma_covers_the_spread_of_its_value_over_seeds():
    """The search's printed "x s +- e" over seeds (issue 21): gyro 5x, samples smoothed
    (not white: the stars' likelihood speaks), psce 200 s, seeds 3-14.  z = ln(s / 5) /
    (e / s) must look N(0, 1): the sum of z² below the χ²₁₂ 99 % quantile, 26.2.  With σ
    from the curvature alone the sum was 28.0 (z -1.68 ... -3.24: the likelihood's score
    varies ~1.4x more over seeds than its curvature says, doc/benchmarks.md); with the
    sandwich over the window's frames 22.1 (seed 9: z -3.0 under every σ tried; seeds 3-10
    alone sum to 21.5, above χ²₈'s 20.1).  The sandwich's factor on σ² must reach the
    search from the runs' frames: its mean over the seeds above 1.1 (1.29, SD 0.22).  Too
    large a σ is the composite-likelihood test's to catch (too few seeds here)."""
    k = np.array([0.25, 0.5, 0.25])
    z, disp = [], []
    for seed in range(3, 15):
        sim = _sim(seed=seed, gyro=5.0)
        data = _stated(sim)
        data.imu_w = np.stack([np.convolve(data.imu_w[:, i], k, "same") for i in range(3)], 1)
        g = measure_bag(data, sim.prior, "psce", [], NoiseScales()).imu["gyro"]
        assert g.measurable, (seed, g)
        z.append(np.log(g.value / 5.0) / (g.sigma / g.value))
        disp.append(g.dispersion)
    z = np.array(z)
    assert np.sum(z**2) < sps.chi2.ppf(0.99, len(z)), z
    assert np.mean(disp) > 1.1, disp


def test_beyond_line_prints_what_the_stars_need_over_the_white_samples():
    """The 'beyond' line: a gyro whose samples carry its stated white noise plus a wandering
    part (white noise k x the stated, averaged over 10 samples: a drift the second
    differences barely see, ~ white to the stars at 2 Hz).  The stars need sqrt(1 + k²) x
    the stated noise, the samples show sqrt(1 + 4 k² / (6 * 10²)): the line prints the first
    over the second.  k = 8: 8.06 / 1.194 = 6.75.  One seed cannot check that number (its
    printed σ is ~12 %): over seeds 3-12 the mean of ln(need / 6.75) must be 0 within 3 x
    the rms of e / need over sqrt(10), 0.115 (it reads -0.044: printed x1.2 or /1.2 it
    reads +0.138 or -0.226 and the test fails, also with the printed ± scaled alike, as
    a wrong factor in the search would scale both; at k = 3 the printed σ is ~19 % and 12
    seeds did not tell x1.2); the samples' factor within 3 of its printed σ (~0.5 %) plus
    its printed half step on every seed, and the noise kept at the samples'.  k = 3 (seed
    3), where the samples' 1.03 is within 5 % of the stated and the noise is applied as
    stated: the search's scale (of the stated) is printed over the samples' 1.03 as the
    words say (it was printed as is, 3 % high)."""
    import re
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from beyond_need import with_drift

    n = 10

    def line(seed, k):
        sim = _sim(seed=seed)
        data = _stated(sim)
        with_drift(sim, data, k, seed, n)
        v = measure_bag(data, sim.prior, "psce", [], NoiseScales())
        samples = np.sqrt(1 + 4 * k**2 / (6 * n**2))
        assert v.beyond == ["gyro"], (seed, v.beyond)
        text = next(x for x in v.lines() if x.startswith("the stars see more attitude motion"))
        m = re.search(r"need x(\S+) \+- (\S+) the noise its own samples show \(x(\S+) \+- "
                      r"(\S+) of the stated\)", text)
        need, e_need, smp, e_smp = (float(x) for x in m.groups())
        # (printed to 3 digits: its half step, 0.005, beside its 3 σ)
        assert smp == pytest.approx(samples, abs=3 * e_smp + 0.005), (seed, text)
        return v, need, e_need, np.sqrt(1 + k**2) / samples

    ln_need, rel = [], []
    for seed in range(3, 13):
        v, need, e_need, truth = line(seed, 8.0)
        assert v.applied.gyro == pytest.approx(v.samples["gyro"]["scale"]), v.applied
        ln_need.append(np.log(need / truth))
        # (σ of ln need: its printed relative σ, which a need mis-scaled with its σ -- a
        # wrong factor in the search -- leaves as it is; over the truth it widened with it)
        rel.append(e_need / need)
    band = 3 * np.sqrt(np.mean(np.square(rel)) / len(rel))
    assert abs(np.mean(ln_need)) < band, (np.mean(ln_need), band, ln_need)
    v, need, _, _ = line(3, 3.0)
    assert v.applied.gyro == 1.0
    assert need == pytest.approx(v.imu["gyro"].value / v.samples["gyro"]["scale"], rel=0.005)


def test_residual_spread_line_holds_its_level_and_reads_an_injected_spread():
    """The 'residual spread (size) vs X' line's t and p on a clean bag's own rows (frames,
    stars, regressors), its innovations replaced by white draws at 0.05 px: over 40 draws
    each regressor's t has mean 0 and SD 1 within 3 of their standard errors (seed 3: means
    -0.29..0.25, SDs 0.86..1.16), and the unadjusted p (the printed p is Bonferroni over
    the family) is below 1 % in 1 % of the tests within 3 binomial σ (5 of 440, 4.4
    expected; at 2 % it was 14 of 440, 8.8 expected, before the ripple tests made the family
    ~80, beyond 1 / 2 %, where the adjusted p no longer gives the unadjusted back).  Then a
    spread that grows 20 % per magnitude, 20 draws: the magnitude line is printed in every
    draw, and its size, |du, dv|'s change across the 5-95 % range (the
    innovations', read through the frames' fit: stats.size_through_fit), within 3 of its
    standard error (the draws' SD / sqrt(20), 0.0014 px) of the 0.0226 px injected
    (sqrt(pi/2) x 0.01 px/mag x 1.80 mag): it reads 0.0220 (100 other draws: 1.005 ± 0.008
    of the truth).  Printed x1.2 or /1.2 (0.0264, 0.0183) it fails, as does the straight
    line of the within-frame sizes it replaces (0.0181 on 10 draws, 0.846 of the truth on
    100: the fit spreads each star's noise over its frame, ~16 stars)."""
    from stellar_cal_ros.diagnosis import stats
    from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
    from stellar_cal_ros.diagnosis.runstats import evaluate

    sim = _sim()
    base = evaluate(_stated(sim), method_spec("psce"), rerun_prior(sim.prior), (), 0.5,
                    keep_residuals=True)
    res0, cam = dict(base.residuals), base.calibration.camera
    mask = stats.evaluation_mask(res0, 0.5)
    mag, n = np.asarray(res0["magnitude"], dtype=float), len(res0["du"])
    rng = np.random.default_rng(5)

    def draws(k, per_mag):
        out = []
        for _ in range(k):
            sig = 0.05 * (1.0 + per_mag * (mag - mag[mask].mean()))
            res = dict(res0, du=sig * rng.standard_normal(n), dv=sig * rng.standard_normal(n),
                       gated=np.zeros(n, bool))
            found = stats.regressor_tests(
                res, mask, (cam.cx, cam.cy), alpha=1.01, focal=(cam.fx, cam.fy),
                R_imu_st=base.calibration.R_imu_st, height=cam.height)
            out.append({f.regressor: (f.statistic, f.p_value, f.slope_px, len(found))
                        for f in found if f.component == "size"})
        return out

    null = draws(40, 0.0)
    small = 0
    for reg in null[0]:
        t = np.array([d[reg][0] for d in null])
        assert abs(t.mean()) < 3 / np.sqrt(len(t)), (reg, t.mean())
        assert abs(t.std(ddof=1) - 1) < 3 / np.sqrt(2 * (len(t) - 1)), (reg, t.std(ddof=1))
        # the unadjusted p below 1 % (< 1 / the family's size, ~80 with the ripple tests:
        # the adjusted p, min(1, p x size), is not capped there)
        small += sum(d[reg][1] < 0.01 * d[reg][3] for d in null)
    tests = len(null) * len(null[0])
    assert abs(small - 0.01 * tests) < 3 * np.sqrt(0.01 * 0.99 * tests), (small, tests)
    spread = draws(20, 0.2)
    lo, hi = np.percentile(mag[mask], [5, 95])
    truth = np.sqrt(np.pi / 2) * 0.05 * 0.2 * (hi - lo)
    assert all(d["magnitude"][1] < 0.01 for d in spread)
    size = np.array([d["magnitude"][2] for d in spread])
    assert abs(size.mean() - truth) < 3 * size.std(ddof=1) / np.sqrt(len(size)), (size, truth)


def test_a_spread_line_beside_a_noise_that_grows_is_sized_over_the_time_trend():
    """A spread line found beside the noise's time trend is sized over that trend, as its
    test reads it (:func:`~stellar_cal_ros.diagnosis.stats.size_through_fit`'s ``times``).
    The psce rows of the test above, the noise's σ x1 -> x2 over the window (a ramp,
    unseen case ``noise_ramp``'s shape), 20 % more per magnitude, and the stars in view
    1.5 mag fainter at the window's end than at its start (a regressor that changes with
    time): the structure at the window's mean level (σ x rms of the ramp, 1.53) is
    sqrt(pi/2) x 0.01 px/mag x 1.53 x the magnitudes' 5-95 % range.  On coord 46e1a18 the
    magnitude line took the noise's growth as its own: 0.128 px for 0.049 (8 draws);
    now 0.053 +- 0.002 (8 draws).  Asserted within 3 of the draws' standard errors."""
    from stellar_cal_ros.diagnosis import stats
    from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
    from stellar_cal_ros.diagnosis.runstats import evaluate

    sim = _sim()
    base = evaluate(_stated(sim), method_spec("psce"), rerun_prior(sim.prior), (), 0.5,
                    keep_residuals=True)
    res0, cam = dict(base.residuals), base.calibration.camera
    mask = stats.evaluation_mask(res0, 0.5)
    t = np.asarray(res0["t"], dtype=float)
    n = len(t)
    along = np.clip((t - t[mask].min()) / np.ptp(t[mask]), 0.0, 1.0)
    mag = np.asarray(res0["magnitude"], dtype=float) + 1.5 * along
    ramp = 1.0 + along
    rng = np.random.default_rng(5)
    sizes = []
    for _ in range(8):
        sig = 0.05 * (1.0 + 0.2 * (mag - mag[mask].mean())) * ramp
        res = dict(res0, magnitude=mag, du=sig * rng.standard_normal(n),
                   dv=sig * rng.standard_normal(n), gated=np.zeros(n, bool))
        found = {f.regressor: f for f in stats.regressor_tests(
            res, mask, (cam.cx, cam.cy), alpha=1.01, focal=(cam.fx, cam.fy),
            R_imu_st=base.calibration.R_imu_st, height=cam.height) if f.component == "size"}
        assert found["time"].p_value < 1e-4, found["time"]
        sizes.append(found["magnitude"].slope_px)
    lo, hi = np.percentile(mag[mask], [5, 95])
    truth = np.sqrt(np.pi / 2) * 0.05 * 0.2 * (hi - lo) * np.sqrt(np.mean(ramp[mask] ** 2))
    size = np.array(sizes)
    assert abs(size.mean() - truth) < 3 * size.std(ddof=1) / np.sqrt(len(size)), (size, truth)


def test_imu_search_states_no_value_where_the_likelihood_is_open_toward_small_scales():
    """The search's "x s +- e" only where its 95 % likelihood interval closes on both sides
    (issue 21, H209).  The likelihood is the one the final model of unseen case
    ``sway_knock_gsf_early`` (seed 21, the gyro noise as stated) gave the swaying bag's gyro:
    a noise-free variance component of n = 12.08 observations, v = 46.46 + s², its maximum
    at x5.91 and only 1.15 above its plateau toward small scales (fitted to that run's 13
    points within 0.045; at x1 1.04 below the maximum).  Main printed "gyro x5.96 +- 1.7"
    (the vertex's parabola) while the ratio's p of "as stated" was 0.15: the scale is not
    measured, the bound "at most x B" is, B the likelihood's own 95 % crossing above the
    maximum within 5 % (x12.55; 6 runs more: the open side once further, the crossing
    bisected).  (Main: measured, x6.00 +- 2.38.)"""
    from stellar_cal_ros.diagnosis.noise_imu import search_scale

    cut = 0.5 * float(sps.chi2.isf(0.05, 1))  # the 95 % interval's drop
    n, floor, top = 12.08, 46.46, 5.91

    def ell(s):
        v = floor + np.asarray(s, dtype=float) ** 2
        return -0.5 * n * (np.log(v) + (floor + top**2) / v)

    s = search_scale("gyro", lambda xs: list(ell(np.exp(np.asarray(xs)))))
    assert not s.measurable and s.bound == "upper", s
    grid = np.exp(np.linspace(np.log(top), np.log(300.0), 20001))
    crossing = grid[np.argmax(ell(grid) < ell(top) - cut)]
    assert s.value == pytest.approx(crossing, rel=0.05), (s.value, crossing)
    assert ell(0.0) > ell(top) - cut  # the interval reaches 0: no lower end to state
    assert s.p_value > 0.05  # "as stated" (x1) is inside it too
    # a likelihood closed on both sides is still measured: the same with 10x the
    # observations (its plateau 11.5 below the maximum), the vertex within 0.3 of its σ
    s = search_scale("gyro", lambda xs: list(10 * ell(np.exp(np.asarray(xs)))))
    assert s.measurable and s.value == pytest.approx(top, abs=0.3 * s.sigma), s


def test_imu_search_as_a_check_stops_where_x3_fits_no_better_else_is_the_whole_search():
    """White IMU samples that keep the stated scale: the stars' search is read only where it
    measures above 1 + BEYOND (motion beyond the samples' noise, ``noise_runs.checks_only``),
    so ``search_scale(check=True)`` runs x3 first (x1 is the model's own run) and stops
    where it fits no better: one run, not two (the 2-h round's gyro, x1.1 +- 0.04: 1.8
    CPU-s).  A variance-component likelihood of 200 frames (v = 4 + s²): at maxima x1.1
    and x0.3 the check stops after x3 (statistic 0, p 1) and the whole search measures
    below 1.5, the only value the verdict would read; at x3 (and without x1 known) it goes
    on and is the whole search exactly: points in the same order, their frames' sandwich,
    value, σ, p."""
    from stellar_cal_ros.diagnosis.noise_imu import search_scale
    from stellar_cal_ros.diagnosis.noise_runs import BEYOND

    rng = np.random.default_rng(5)
    w = rng.chisquare(2, 200) / 2  # each frame's share of the variance's draw

    def ell(x, top):
        v = 4.0 + np.exp(2 * x)
        terms = -0.5 * (np.log(v) + (4.0 + top**2) * w / v)
        return float(terms.sum()), np.stack([np.arange(200.0), terms])

    for top, stops, x1 in [(1.1, True, True), (0.3, True, True), (3.0, False, True),
                           (3.0, False, False), (1.1, True, False)]:
        calls = []

        def loglik(xs, top=top, calls=calls):
            calls.append(list(xs))
            return [ell(x, top) for x in xs]

        known = {0.0: ell(0.0, top)[0]} if x1 else {}
        checked = search_scale("gyro", loglik, known=known, bound=False, check=True)
        whole = search_scale("gyro", lambda xs, top=top: [ell(x, top) for x in xs],
                             known=known, bound=False)
        assert calls[0] == ([math.log(3.0)] if x1 else [0.0, math.log(3.0)]), calls
        if stops:
            assert calls == calls[:1] and checked.checked, (top, calls)
            assert not checked.measurable and checked.statistic == 0.0
            assert checked.p_value == 1.0
            assert not (whole.measurable and whole.value > 1.0 + BEYOND), whole
            continue
        assert not checked.checked and calls[1] == [-math.log(3.0)], calls
        assert list(checked.points.items()) == list(whole.points.items())
        assert (checked.value, checked.sigma, checked.p_value, checked.dispersion,
                checked.statistic, checked.measurable) == (
            whole.value, whole.sigma, whole.p_value, whole.dispersion, whole.statistic,
            whole.measurable)
        assert whole.measurable and whole.value > 1.0 + BEYOND and whole.dispersion != 1.0


def test_imu_search_lower_bound_holds_the_truth_at_its_confidence():
    """The search's "at least x" (95 %), on a likelihood that has the plateau the bound is
    for: n observations whose variance saturates as the scale grows, v(s) = 2 s² / (1 +
    s²) (a noise that stops mattering once it is far larger than what the observations
    pin down), truth x10, 200 draws.  No simulated bag reaches the bound (the innovations'
    likelihood falls without bound toward large scales: doc/benchmarks.md), so this is the
    bound's own logic.  It must hold the truth in 95 % of the draws that print it, within 3
    binomial σ (after: 87 of 87, bounds x2.7-x7.2; before, a straight line between points a
    factor of 3-9 apart put the crossing at x13-x19: 14 %)."""
    from stellar_cal_ros.diagnosis.noise_imu import search_scale

    rng = np.random.default_rng(1)
    n, truth, held = 2000, 10.0, []

    def v(x):
        return 2.0 / (1.0 + np.exp(-2.0 * np.asarray(x)))

    for _ in range(200):
        y2 = v(np.log(truth)) * rng.chisquare(n)
        s = search_scale("gyro", lambda xs, y2=y2: list(-0.5 * (n * np.log(v(xs)) + y2 / v(xs))))
        if s.bound == "lower":
            held.append(s.value <= truth)
    assert len(held) > 50, len(held)
    assert np.mean(held) > 0.95 - 3 * np.sqrt(0.95 * 0.05 / len(held)), np.mean(held)


def test_quadratic_variance_is_the_dense_traces():
    """noise_stars.quadratic_variance (Hutchinson over Rademacher probes, Σ along tracks, the
    steps applied forward and back) against the dense ``tr(X Σ Y Σ)`` of a small table: 60
    rows, 12 frames of 5 stars on 7 tracks, the frames' attitude fit, 3 cells' means and a
    symmetric non-projection last step (the lag-1 ratio's form).  20 000 probes: each trace
    within 2 % (they read within 0.4 %)."""
    rng = np.random.default_rng(4)
    n = 60
    frame = np.repeat(np.arange(12), 5)
    track = np.concatenate([rng.permutation(7)[:5] for _ in range(12)])
    A = rng.standard_normal((n, 2, 3))
    cell = rng.integers(0, 3, n)
    keep = cell != 2
    lags = (0.8, 0.7)
    fit = noise_stars._minus_frame_fit(A, frame)
    cells = noise_stars._minus_means(cell, keep)
    form = noise_stars._lag1_form(noise_structure.along_tracks(
        rng.standard_normal((n, 2)), track, (1.0, 0.8)), track, 0.3)
    assert form is not None
    forms = [[fit, cells], [fit, form[0]]]
    eye = np.eye(2 * n).reshape(n, 2, 2 * n)

    def dense(steps):
        z = eye
        for st in steps:
            z = st(z)
        for st in steps[-2::-1]:
            z = st(z)
        return z.reshape(2 * n, 2 * n)

    X, Y = dense(forms[0]), dense(forms[1])
    assert np.allclose(X, X.T) and np.allclose(Y, Y.T)
    S = noise_structure.along_tracks(eye, track, lags).reshape(2 * n, 2 * n)
    want = [np.trace(X @ S @ X @ S), np.trace(X @ S @ Y @ S), np.trace(Y @ S @ Y @ S)]
    got = noise_stars.quadratic_variance(forms, track, lags, probes=20000)
    assert np.allclose(got, want, rtol=0.02), (got, want)
    assert noise_stars.quadratic_variance(forms[:1], track, lags, probes=20000)[0] == \
        pytest.approx(want[0], rel=0.02)


def test_repeating_field_sign_flip_p_holds_its_level_and_finds_a_field():
    """The repeating-field line's "across the stars' tracks p" (the cell means' χ² against
    sign flips of whole tracks: noise_structure.flip_p) on a clean bag's own rows (frames,
    stars, cells), its innovations replaced by draws at 0.05 px.  White draws: 40 p
    uniform, mean 0.5 within 3 / sqrt(12 x 40) (0.444; the χ² p beside it 0.669: the
    frames' fit leaves each row 1 - lev/2 of its variance); AR(1) along each star's track
    (φ 0.82, τ 5 frames), 20 draws: 0.471 (χ² 0.765).  A field that repeats, u shifted by
    σ x the column's offset from the centre over the half width, 10 draws: flips p at most
    0.002 (χ² below 1e-140); 0.5 σ: flips 0.0005-0.073, χ² below 1e-18 (why the flips are
    not the decision: a cell here holds the tracks of one or two stars)."""
    from stellar_cal_ros.diagnosis import stats
    from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
    from stellar_cal_ros.diagnosis.runstats import evaluate

    sim = _sim()
    base = evaluate(_stated(sim), method_spec("psce"), rerun_prior(sim.prior), (), 0.5,
                    keep_residuals=True)
    res0, cam = dict(base.residuals), base.calibration.camera
    mask = stats.evaluation_mask(res0, 0.5) & ~np.asarray(res0["gated"], bool)
    n = len(res0["du"])
    star = np.asarray(res0["catalog_id"])
    order = np.lexsort((np.asarray(res0["frame"]), star))  # each star's rows in time order
    new = np.r_[True, star[order][1:] != star[order][:-1]]
    rng = np.random.default_rng(9)
    u0 = np.asarray(res0["u"], dtype=float)

    def draw(phi=0.0, field=0.0):
        e = rng.standard_normal((n, 2))
        if phi:
            x = e[order].copy()
            for i in range(1, n):  # AR(1) along the track, stationary at its start
                if not new[i]:
                    x[i] = phi * x[i - 1] + np.sqrt(1 - phi**2) * x[i]
            e[order] = x
        du = 0.05 * e[:, 0] + field * 0.05 * (u0 - cam.cx) / cam.cx
        res = dict(res0, du=du, dv=0.05 * e[:, 1])
        sn = noise_stars.star_noise(res, np.full(n, 0.05), np.ones(n), mask, cam.fx, cam.fy,
                                    (cam.cx, cam.cy), base.calibration.R_imu_st, flips=True)
        return sn.structure_flip_p, sn.structure_p

    white = np.array([draw() for _ in range(40)])
    ar1 = np.array([draw(np.exp(-0.2)) for _ in range(20)])
    for p in (white, ar1):
        assert abs(p[:, 0].mean() - 0.5) < 3 / np.sqrt(12 * len(p)), p.mean(0)
    field = np.array([draw(field=1.0) for _ in range(10)])
    assert np.all(field[:, 0] < 0.01) and np.all(field[:, 1] < 1e-6), field


def test_frame_fit_is_the_per_frame_loop_bit_for_bit():
    """``stats.FrameFit`` stacks the frames of one star count (issue 24.2: ``within_frame``
    was a Python loop over 14 400 frames, 22 times a 2-h round, 0.35 CPU-s each): its
    residuals and leverages equal the loop over the frames it replaces bit for bit, on
    frames of 1-30 stars out of order, one frame whose stars are one direction (``AᵀA``
    singular: left out, NaN, leverage 2) and frames of fewer than 3 stars (the same)."""
    from stellar_cal_ros.diagnosis.stats import FrameFit, attitude_columns, within_frame

    rng = np.random.default_rng(24)
    sizes = rng.integers(1, 31, size=400)
    frame = np.repeat(np.arange(len(sizes)), sizes)
    n = len(frame)
    d = rng.normal(size=(n, 3)) * [0.05, 0.05, 0.0] + [0.0, 0.0, 1.0]
    bad = frame == np.flatnonzero(sizes >= 3)[0]
    d[bad] = [0.0, 0.0, 1.0]  # on the axis: no roll column, a singular attitude fit
    d /= np.linalg.norm(d, axis=1)[:, None]
    perm = rng.permutation(n)  # rows out of frame order
    res = {"frame": frame[perm], "x_st": d[perm, 0], "y_st": d[perm, 1], "z_st": d[perm, 2],
           "du": rng.normal(size=n), "dv": rng.normal(size=n)}
    sigma = rng.uniform(0.03, 0.08, size=n)
    fx, fy = 3968.0, 3969.0

    A = attitude_columns(res, fx, fy) / sigma[:, None, None]
    y = np.stack([res["du"], res["dv"]], 1) / sigma[:, None]
    r0, lev0, used0 = np.full((n, 2), np.nan), np.full(n, 2.0), 0
    order = np.argsort(res["frame"], kind="stable")
    for part in np.split(order, np.flatnonzero(np.diff(res["frame"][order])) + 1):
        if len(part) < 3:
            continue
        Ak, yk = A[part].reshape(-1, 3), y[part].reshape(-1)
        try:
            Gi = np.linalg.inv(Ak.T @ Ak)
        except np.linalg.LinAlgError:
            continue
        r0[part] = (yk - Ak @ (Gi @ (Ak.T @ yk))).reshape(-1, 2)
        lev0[part] = np.einsum("ij,jk,ik->i", Ak, Gi, Ak).reshape(-1, 2).sum(1)
        used0 += 1

    r, lev, used = within_frame(res, sigma, fx, fy)
    assert used == used0 == int(np.sum(sizes >= 3)) - 1
    assert np.array_equal(r, r0, equal_nan=True) and np.array_equal(lev, lev0)
    assert np.isnan(r[perm.argsort()[bad]]).all() and (lev[perm.argsort()[bad]] == 2.0).all()
    c = rng.normal(size=(n, 2))  # another column through the same fit
    fit = FrameFit(res, sigma, fx, fy)
    r1, _, _ = within_frame(dict(res, du=c[:, 0], dv=c[:, 1]), sigma, fx, fy)
    assert np.array_equal(fit.residual(c[:, 0], c[:, 1]), r1, equal_nan=True)


def test_used_sigma_joins_the_messages_as_a_dict_filled_in_order():
    """``noise_stars.used_sigma`` joins the residual rows to the bag's stars on (stamp in µs,
    catalogue id) with arrays (a dict of 228 000 tuples on the 2-h bag held ≈ 100 MB): a
    row without its star is NaN, a key twice in the bag takes its last star (a dict's
    overwrite), a star of another stamp or id does not match."""
    from types import SimpleNamespace

    from stellar_cal_ros.diagnosis.noise_stars import used_sigma

    def frame(stamp_ns, ids, sig):
        n = len(ids)
        return SimpleNamespace(stamp_ns=stamp_ns, catalog_id=np.array(ids, dtype=np.uint32),
                               sigma=np.array(sig, float), magnitude=np.arange(n) + 3.0,
                               uv=np.arange(2.0 * n).reshape(n, 2) + 100.0)

    t0 = 1_795_000_000_000_000_000
    frames = [frame(t0, [5, 7, 9], [0.01, 0.02, 0.03]),
              frame(t0 + 500_000_000, [7, 7], [0.04, 0.05]),  # id 7 twice: the last counts
              frame(t0 + 1_000_000_400, [9], [0.0]),  # σ 0: the default
              frame(t0 + 2_000_000_000, [], [])]
    res = {"t": np.array([t0, t0, t0 + 5e8, t0 + 1_000_000_400, t0 + 2e9, t0]) / 1e9,
           "catalog_id": np.array([9, 5, 7, 9, 9, 8])}
    out, msg = used_sigma(res, SimpleNamespace(frames=frames), NoiseScales(), 0.07, 1024, 1024)
    assert np.array_equal(msg, [0.03, 0.01, 0.05, 0.0, np.nan, np.nan], equal_nan=True)
    assert np.array_equal(out, [0.03, 0.01, 0.05, 0.07, np.nan, np.nan], equal_nan=True)


def test_the_fits_weights_at_the_measured_sigma_put_each_group_within_2_sigma():
    """The frames' attitude fit weighted each star by the σ being measured: where it is wrong
    for part of the stars, Helmert's estimate takes from each star's residual a share of
    the others' noise at the wrong weight, and the first round's groups read ~3σ off
    (unseen case ``mag_faint_over2`` 300 s: bright x0.949 +- 0.016 for 1.0).  Now the fit
    is made again at the measured σ (``noise_stars.star_noise``'s passes).  150 s bags,
    every star truly 0.05 px: faint ones stated 0.1 px (seeds 4, 5: main read x0.958 +-
    0.031 / x0.508 +- 0.0051 and x0.935 +- 0.029 / x0.52 +- 0.0055, the faint group 3.6σ
    off; now x1.02 / x0.494 and x1.000 / x0.505); faint ones σ 0 and truly 0.1 px (seed 4:
    the bright stars read x1.12 +- 0.034 and were rescaled 1.12; now x1.045, as stated).
    Each group within 2 of its printed σ of its truth."""
    for seed in (4, 5):
        sim, data = _step_bag(seed, sigma0=False)
        v = measure_bag(data, sim.prior, "psce", [], NoiseScales(), components=())
        assert v.group is not None and v.group["by"] == "magnitude", v.groups
        mags = np.concatenate([np.asarray(f.magnitude, dtype=float) for f in data.frames])
        below, above = mags[mags < 4.5].max(), mags[mags >= 4.5].min()
        edges = [-np.inf, *v.group["edges"], np.inf]
        for lo, hi, scale, e in zip(edges[:-1], edges[1:], v.group["scales"],
                                    v.group["sigma"], strict=True):
            truth = 1.0 if hi <= above else 0.5 if lo > below else None
            assert truth is not None and abs(scale - truth) < 2.0 * e, (seed, lo, hi, scale, e)
    sim, data = _step_bag(4, sigma0=True)
    v = measure_bag(data, sim.prior, "psce", [], NoiseScales(), components=())
    assert abs(v.star - 1.0) < 2.0 * v.star_sigma and "star" not in v.rejected, v.lines()
    assert v.unknown_sigma_px == pytest.approx(0.1, abs=2 * v.unknown_sigma_sigma)


def test_the_fits_weights_are_not_touched_where_the_stated_sigma_is_right():
    """Where every message states the right σ (and none says 0) nothing is significant, no
    second fit is made, and the estimate is the one fit's bit for bit (clean bags'
    diagnosis.json unchanged)."""
    from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
    from stellar_cal_ros.diagnosis.runstats import quiet

    sim = _sim()
    data = _stated(sim)
    with quiet():
        result = method_spec("psce").runner(data, rerun_prior(sim.prior), [],
                                            keep_tables=True, eval_fraction=0.5)
    sn = noise.measure_stars(result, data, "psce", 0.5, None)
    res, cam = result.residuals, result.calibration.camera
    sig, msg = noise_stars.used_sigma(res, data, NoiseScales(), 0.05, cam.width, cam.height)
    assert noise_stars.fit_weights(sn, res, sig, msg, (cam.cx, cam.cy),
                                   (cam.width, cam.height)) is None
    from stellar_cal_ros.diagnosis.stats import evaluation_mask

    one = noise_stars.star_noise(res, sig, msg, evaluation_mask(res, 0.5), cam.fx, cam.fy,
                                 (cam.cx, cam.cy), result.calibration.R_imu_st)
    assert np.array_equal(one.q, sn.q) and np.array_equal(one.m, sn.m)
    assert (one.scale, one.sigma) == (sn.scale, sn.sigma)


def test_the_window_and_the_stretch_before_it_share_the_detectors_pattern_tests(monkeypatch):
    """measure_stars makes the detector's fixed-pattern tests once (they read the table's
    last part whatever the mask) for the window's estimate and the stretch's before it:
    the same estimates as each star_noise making its own (main made them twice)."""
    from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
    from stellar_cal_ros.diagnosis.runstats import quiet

    sim = _sim()
    data = _stated(sim)
    with quiet():
        result = method_spec("psce").runner(data, rerun_prior(sim.prior), [],
                                            keep_tables=True, eval_fraction=0.5)
    calls = []
    made = noise_stars.detector_patterns

    def counted(*a, **k):
        calls.append(1)
        return made(*a, **k)

    monkeypatch.setattr(noise_stars, "detector_patterns", counted)
    monkeypatch.setattr(noise, "detector_patterns", counted)
    shared = noise.measure_stars(result, data, "psce", 0.5, None)
    assert len(calls) == 1 and shared.before is not None
    # each estimate making its own (star_noise without ``patterns``)
    monkeypatch.setattr(noise, "detector_patterns", lambda *a, **k: None)
    own = noise.measure_stars(result, data, "psce", 0.5, None)
    assert len(calls) == 3
    assert np.array_equal(shared.q, own.q) and np.array_equal(shared.m, own.m)
    assert (shared.scale, shared.sigma, shared.before) == (own.scale, own.sigma, own.before)
    assert repr(shared.patterns) == repr(own.patterns)


def test_a_later_rounds_groups_compose_with_the_groups_kept():
    """A later round measures the stars' σ relative to the σ applied so far; groups it finds
    replaced the kept ones, whose factors were then lost (kept magnitude groups x1 below
    4 mag, x0.6 above, on a bag whose stars are truly 0.05 px and state 0.1 px above 4.5
    mag: the round's groups x1.53 (< 4.48 mag), x0.84, applied alone, put the stars of
    4-4.48 mag at 1.53x their σ).  Now the applied factors are the products, the line
    prints the composed factors of the messages' σ, each within 3 of its σ of its truth
    (x1 bright, x0.5 faint), and its --noise-scale advice gives the same σ."""
    sim, data = _step_bag(5, sigma0=False)
    kept = NoiseScales(group_by="magnitude", edges=(4.0,), factors=(1.0, 0.6))
    v = measure_bag(data, sim.prior, "psce", [], kept, components=())
    assert v.group is not None, v.lines()
    mags = np.concatenate([np.asarray(f.magnitude, dtype=float) for f in data.frames])
    # every star's applied σ is the truth, 0.05 px, within 3 of the largest group's σ (main:
    # the stars of 4-4.48 mag at 0.076 px)
    msg = np.concatenate([np.asarray(f.sigma, dtype=float) for f in data.frames])
    uv = np.concatenate([np.asarray(f.uv, dtype=float).reshape(-1, 2) for f in data.frames])
    got = v.applied.star_sigma(msg, 0.05, mags, uv, (511.5, 511.5))
    c = getattr(v, "composed", None) or v.group
    worst = 0.05 * 3.0 * max(c["sigma"])  # (seed 5: x0.907 +- 0.062 below 3.93 mag)
    assert np.all(np.abs(got - 0.05) < worst), (got.min(), got.max())
    below, above = mags[mags < 4.5].max(), mags[mags >= 4.5].min()
    edges = [-np.inf, *c["edges"], np.inf]
    for lo, hi, scale, e in zip(edges[:-1], edges[1:], c["scales"], c["sigma"], strict=True):
        truth = 1.0 if hi <= above else 0.5 if lo > below else None
        assert truth is not None and abs(scale - truth) < 3.0 * e, (lo, hi, scale, e)
    line = next(x for x in v.lines() if "depends on magnitude" in x)
    assert "with the scales measured before" in line, line
    advice = line.split("use --noise-scale ")[1].split(";")[0]
    parsed = NoiseScales.parse(advice)
    again = parsed.star_sigma(msg, 0.05, mags, uv, (511.5, 511.5))
    assert again == pytest.approx(got, rel=2e-3), advice


def test_the_last_rounds_line_gives_the_composed_sigma_and_the_scale_to_use():
    """A later round that keeps the scale of an earlier one said "noise as measured before
    (star x1.73 of the stated; now stars' sigma x0.97 +- 0.0042 of that)", the product left
    to the user (the independent ``psce_sky_900s`` with its σ field 0.6x).  Now it gives
    the σ to use and the composed scale, the truth 1/0.6 within 3 of its σ (seed 3, 200 s,
    an earlier round's x1.73 kept: x1.65 +- 0.014, 0.03 -> 0.0496 px), and the
    --noise-scale a replay applies as it is printed."""
    sim = _sim(seed=3)
    data = _stated(sim, 0.6)
    v = measure_bag(data, sim.prior, "psce", [], NoiseScales(star=1.73), components=())
    assert "star" not in v.rejected, v.lines()
    line = next(x for x in v.lines() if x.startswith("noise as measured before"))
    k = 1.73 * v.star
    assert abs(k - 1.0 / 0.6) < 3.0 * 1.73 * v.star_sigma, (k, v.star_sigma)
    assert f"0.03 -> {0.03 * k:.3g} px (x{k:.3g} +- {1.73 * v.star_sigma:.2g} of the stated)" \
        in line, line
    assert line.endswith(f"use --noise-scale star={k:.4g}"), line
    assert NoiseScales.parse(line.split("use --noise-scale ")[1]).star == \
        pytest.approx(k, rel=1e-3)
    # another component rejected on that round: the stars' kept σ is still said
    v.rejected = ["gyro"]
    assert any(x.startswith("noise as measured before: stars' sigma 0.03 -> ") for x in
               v.lines()), v.lines()


def _per_star(data, spread=0.3, seed=7):
    """Each catalogue star's σ field off by its own lognormal factor (right on average)."""
    rng = np.random.default_rng(seed)
    fac: dict[int, float] = {}
    for f in data.frames:
        f.sigma = np.asarray(f.sigma, dtype=float) * np.array(
            [fac.setdefault(int(c), float(np.exp(spread * rng.standard_normal()
                                                 - spread**2 / 2.0)))
             for c in np.asarray(f.catalog_id).tolist()])
    return data, fac


def test_sigma_wrong_star_by_star_is_said_once_not_as_groups_tails_or_leads():
    """Unseen case ``sigma_per_star``: each star's σ field off by its own 30 % lognormal
    factor, right on average.  Each star's whitened variance is its factor⁻², carried
    along its whole track: the rows' Bartlett named magnitude groups x0.89-1.2 (at
    random), the mixture read heavy-tailed, and the size tests, whose frames' window is ~5
    frames long, took the stars in view for 'spread vs time / head temperature / gravity'
    (t 6-8).  Now the verdict says it star by star (``noise_stars.star_spread``), with the
    spread of the stars' σ factors within 30 % of the truth of the stars seen (their
    variance factors' SD over mean, halved), no groups, no tail line, and the line tests
    take each star's level (``stats.frame_robust_t``'s ``track_level``): no size line.
    On main 319db59 this bag's verdict grouped the stars by column, x0.873-1.19 (random);
    its run's own rows showed no size line (the next test's draws do)."""
    from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
    from stellar_cal_ros.diagnosis.output import line_tests
    from stellar_cal_ros.diagnosis.runstats import evaluate
    from stellar_cal_ros.diagnosis.stats import evaluation_mask

    sim = _sim(seed=3)
    data, fac = _per_star(_stated(sim))
    v = measure_bag(data, sim.prior, "psce", [], NoiseScales(), components=())
    assert v.per_star is not None and v.group is None and v.tails is None, v.lines()
    base = evaluate(data, method_spec("psce"), rerun_prior(sim.prior), (), 0.5,
                    keep_residuals=True)
    res = base.residuals
    seen, n = np.unique(np.asarray(res["catalog_id"])[evaluation_mask(res, 0.5)
                                                      & ~np.asarray(res["gated"], bool)],
                        return_counts=True)
    w = np.array([fac[int(c)] ** -2.0 for c in seen])
    truth = 0.5 * w.std() / w.mean()
    assert abs(0.5 * v.per_star["spread"] - truth) < 0.3 * truth, (v.per_star, truth)
    line = next(x for x in v.lines() if "star by star" in x)
    assert f"~{100 * 0.5 * v.per_star['spread']:.2g} %" in line, line
    found = line_tests(base.residuals, base.calibration, 0.5)
    assert not [f for f in found if f.component == "size"], found


@pytest.mark.parametrize("seed", [4, 5])
def test_sigma_wrong_star_by_star_prints_the_rows_ml_scale(seed):
    """The scale printed beside a σ wrong star by star is the ML scale of the stated σ on
    the window's rows, ``sqrt(mean(factor⁻²))`` (the case's truth; each row's true σ over
    its stated), within its σ.  Two causes made it read low (unseen case
    ``sigma_per_star``, seeds 21-23: x1.02 / 1.22 / 1.12 for the rows' 1.062 / 1.257 /
    1.148): the frames' fit weighted by the stated σ leans on the stars stated too small
    (their leverage takes more of their larger variance, −1.7 % on s21's rows with iid
    draws), and the filter's χ² gate at the stated σ cut those stars' tails (−2.2 %).
    Now the passes weight each star by its own measured scale
    (:func:`~stellar_cal_ros.diagnosis.noise_stars.own_scales`) and count the rows the
    gate took at the wrong σ (:func:`~stellar_cal_ros.diagnosis.noise_stars.readmitted`).
    On main ca41024 this fails: seeds 4 / 5 read x1.233 +- 0.014 / 1.159 +- 0.014 for the
    rows' 1.275 / 1.222 (z −3.0 / −4.6; seeds 3 / 6: −2.7 / +0.3); now 1.280 / 1.228 (z
    +0.4 / +0.4; seeds 3 / 6: −0.5 / +1.6)."""
    from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
    from stellar_cal_ros.diagnosis.runstats import evaluate
    from stellar_cal_ros.diagnosis.stats import evaluation_mask

    sim = _sim(seed=seed)
    data, fac = _per_star(_stated(sim), seed=seed + 4)
    v = measure_bag(data, sim.prior, "psce", [], NoiseScales(), components=())
    assert v.per_star is not None, v.lines()
    base = evaluate(data, method_spec("psce"), rerun_prior(sim.prior), (), 0.5,
                    keep_residuals=True)
    res = base.residuals
    ids = np.asarray(res["catalog_id"])[evaluation_mask(res, 0.5)]
    truth = math.sqrt(np.mean([fac[int(c)] ** -2.0 for c in ids]))
    assert abs(v.star - truth) < 2.5 * v.star_sigma, (v.star, v.star_sigma, truth)


def test_the_rows_the_gate_took_are_counted_at_the_runs_own_gate():
    """The rows re-admitted beside a σ wrong star by star are those the run's own gate
    rejected (:func:`~stellar_cal_ros.diagnosis.noise_stars.readmitted`): a gate set in
    the filter's config (``gate_probability``), not the default policy's.  On the
    ``sigma_per_star`` simulation (seed 5, 200 s) replayed with ``gate_probability`` 0.999
    (threshold 13.8 against the default's 18.4: 60 window rows gated, 32 at the default),
    the scale read x1.2266 against x1.2280 from the run at the default gate (the rows' ML
    scale 1.2220, σ 0.014); with the default's threshold the rows between the two were
    never counted: x1.2138, 1.2 % under (seed 6: 1.1212 / 1.1125 against 1.1244).  Fails
    on main 17d7d23 (the default policy's threshold)."""
    from stellar_cal_ros.diagnosis.discover import rerun_prior
    from stellar_cal_ros.methods.replay import replay

    sim = _sim(seed=5)
    data, _ = _per_star(_stated(sim), seed=9)
    prior = rerun_prior(sim.prior)
    scale = {}
    for p in (0.9999, 0.999):
        r = replay(data, prior, "psce", [], PsceConfig(gate_probability=p), keep_tables=True,
                   eval_fraction=0.5)
        assert r.filter.gate.probability == p
        scale[p] = noise.measure_stars(r, data, "psce", 0.5, None).scale
    assert scale[0.999] == pytest.approx(scale[0.9999], rel=0.005), scale


def test_the_rows_the_gate_took_are_read_at_their_frames_scaled_threshold():
    """The filter's gate scales each frame's threshold by its median NIS
    (:meth:`~stellar_cal_ros.core.gating.GatePolicy.decide`); the rows re-admitted at the σ
    measured (:func:`~stellar_cal_ros.diagnosis.noise_stars.readmitted`) are read at that
    frame's threshold, at the σ used and again at the σ measured.  Frames of 5 stars:
    (a) median NIS 1.4 (threshold 18.4): a star at NIS 20 measured x1.2 comes back (as on
    coord); (b) median NIS 2.77 (x2, threshold 36.8): a star at NIS 40 measured x1.3 (23.7
    there, the frame's median unchanged) comes back, coord read it against 18.4 x 1.69 =
    31.1 and left it out; (c) the same with every star x1.3: the frame's median falls too
    (threshold 21.8): it stays out; (d) a lost-lock frame (median NIS 2e5): its star at
    NIS 20 measured x1.2 stays out, coord took it back (20 < 18.4 x 1.44).  On coord
    46e1a18 rows [0, 15] came back for [0, 5].  The frames' scales equal ``decide``'s."""
    from stellar_cal_ros.core.gating import GatePolicy
    from stellar_cal_ros.diagnosis.noise_stars import readmitted

    nis = np.array([20.0, 1.4, 1.4, 1.4, 1.0,
                    40.0, 2.77, 2.77, 2.77, 1.0,
                    40.0, 2.77, 2.77, 2.77, 1.0,
                    20.0, 2e5, 2e5, 2e5, 2e5])
    frames = np.repeat([0, 1, 2, 3], 5)
    gate = GatePolicy()
    gated = np.zeros(20, bool)
    for f in range(4):
        d = gate.decide(nis[frames == f], np.tile([0.0, 0.0, 1.0], (5, 1)))
        gated[frames == f] = ~d.accepted
        assert np.all(gate.frame_scales(nis, frames)[frames == f] == d.scale)
    assert gated.tolist() == [True] + [False] * 4 + ([True] + [False] * 4) * 2 + [True] * 5
    scale = np.ones(20)
    scale[[0, 5, 15]] = [1.2, 1.3, 1.2]
    scale[10:15] = 1.3
    res = {"nis": nis, "frame": frames, "gated": gated}
    assert np.flatnonzero(readmitted(res, scale, gate)).tolist() == [0, 5]


def test_the_star_by_star_test_reads_the_fit_before_the_stars_own_weights():
    """The passes that weight each star by its own measured scale (H211, the scale's fix
    above) lean each frame's fit on the stars that read small, which then read smaller:
    the stars' spread grows with the weights it made, and the F test's reference no longer
    holds.  On the clean swaying false-alarm bag seed 2047 (`benchmarks/false_alarms.py
    --first-seed 2047 --seeds 1 --cases swaying`) the line read F 1.57, p 0.00016 on the
    weighted fit for 1.39, p 0.0051 before it.  The verdict's star-by-star test is now the
    last fit's before those weights (`noise_stars.levels_fit`), the scale the weighted
    fit's.  On the sigma_per_star simulation (seed 4) the weighted fit's F is the larger,
    and the verdict prints the unweighted one's."""
    from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
    from stellar_cal_ros.diagnosis.runstats import evaluate

    sim = _sim(seed=4)
    data, _ = _per_star(_stated(sim), seed=8)
    base = evaluate(data, method_spec("psce"), rerun_prior(sim.prior), (), 0.5,
                    keep_residuals=True)
    sn = noise.measure_stars(base, data, "psce", 0.5, NoiseScales())
    assert sn is not None and sn.levels is not None  # a pass weighted by the own scales
    plain = noise_stars.levels_fit(sn)
    f_plain = noise_stars.star_spread(plain, noise_stars.grouped_stars(plain))["F"]
    f_weighted = noise_stars.star_spread(sn, noise_stars.grouped_stars(sn))["F"]
    assert f_weighted > 1.05 * f_plain, (f_weighted, f_plain)
    v = measure_bag(data, sim.prior, "psce", [], NoiseScales(), components=())
    assert v.per_star is not None
    assert v.per_star["F"] == pytest.approx(f_plain, rel=0.02), (v.per_star, f_plain)


def _clean_rows():
    """The clean 200 s seed-3 bag's run (its residual table kept), its rows and window."""
    from stellar_cal_ros.diagnosis import stats
    from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
    from stellar_cal_ros.diagnosis.runstats import evaluate

    sim = _sim()
    base = evaluate(_stated(sim), method_spec("psce"), rerun_prior(sim.prior), (), 0.5,
                    keep_residuals=True)
    res0 = dict(base.residuals)
    return base, res0, stats.evaluation_mask(res0, 0.5)


def test_size_tests_take_each_stars_level_and_still_find_a_spread_along_time():
    """``stats.regressor_tests``' ``star_levels`` on a clean bag's own rows, innovations
    replaced by draws at 0.05 px x each star's own factor (30 % lognormal): without it the
    size tests read the stars in view as 'spread vs gravity / row / magnitude' (a size line
    in 5 of 10 draws, seed 9), with it in none of 10.  A noise that doubles over the
    window on top of the stars' levels is still found along time in 10 of 10 draws (a 60 %
    growth in 8 of 10, 10 of 10 without the levels' term: what the stars' own levels cost
    a trend the stars in view share)."""
    from stellar_cal_ros.diagnosis import stats

    base, res0, mask = _clean_rows()
    cam = base.calibration.camera
    n = len(res0["du"])
    cid = np.asarray(res0["catalog_id"])
    t = np.asarray(res0["t"], dtype=float)
    tw = (t - t[mask].min()) / np.ptp(t[mask])
    rng = np.random.default_rng(9)

    def size_lines(grow, levels):
        ids = np.unique(cid)
        f = dict(zip(ids.tolist(), np.exp(0.3 * rng.standard_normal(len(ids))), strict=True))
        sig = 0.05 * np.array([f[c] for c in cid.tolist()]) * (1.0 + grow * tw)
        res = dict(res0, du=sig * rng.standard_normal(n), dv=sig * rng.standard_normal(n),
                   gated=np.zeros(n, bool))
        found = stats.regressor_tests(res, mask, (cam.cx, cam.cy), focal=(cam.fx, cam.fy),
                                      R_imu_st=base.calibration.R_imu_st, height=cam.height,
                                      star_levels=levels)
        return {x.regressor for x in found if x.component == "size"}

    plain = [size_lines(0.0, False) for _ in range(10)]
    assert sum(map(bool, plain)) >= 3, plain
    leveled = [size_lines(0.0, True) for _ in range(10)]
    assert not any(leveled), leveled
    grown = [size_lines(1.0, True) for _ in range(10)]
    assert all("time" in s for s in grown), grown


def test_a_noise_that_grows_over_the_window_is_no_spread_line_of_what_changes_with_time():
    """Unseen case ``noise_ramp`` reduced: the clean 200 s seed-3 bag's rows, innovations
    replaced by draws whose σ grows x1.5 -> x2 across the window (as the case's).  The spread
    line along time is found in 6 of 6 draws; the spread's other lines are tested beside its
    time trend (:func:`~.stats.time_trend`) and none is left: on coord2 (4193ce7) the head
    temperature, which falls all run, read the same trend in 6 of 6 (ranked before time at
    draws 4 and 5, t -8.2 / -7.0), and 'gravity_y_st change' at draw 5 (t 5.0, p 0.0045)."""
    from stellar_cal_ros.diagnosis import stats

    base, res0, mask = _clean_rows()
    cam = base.calibration.camera
    n = len(res0["du"])
    t = np.asarray(res0["t"], dtype=float)
    tw = (t - t[mask].min()) / np.ptp(t[mask])
    for seed in range(1, 7):
        rng = np.random.default_rng(seed)
        sig = 0.05 * (1.5 + 0.5 * tw)
        res = dict(res0, du=sig * rng.standard_normal(n), dv=sig * rng.standard_normal(n),
                   gated=np.zeros(n, bool))
        found = stats.regressor_tests(res, mask, (cam.cx, cam.cy), focal=(cam.fx, cam.fy),
                                      R_imu_st=base.calibration.R_imu_st, height=cam.height)
        size = [f.regressor for f in found if f.component == "size"]
        assert size == ["time"], (seed, [(f.regressor, f.component, f.statistic)
                                         for f in found])


def _ramp_rows(seed, rows_x2=False, n=12000, per=20):
    """Rows of frames of ``per`` stars whose σ grows x1 -> x2 over the run while the stars'
    columns drift with time (200 -> 800 px: the attitude changing), with ``rows_x2`` rows
    above 700 px 1.5x noisier besides."""
    rng = np.random.default_rng(seed)
    frame = np.repeat(np.arange(n // per), per)
    tw = frame / frame.max()
    uv = np.stack([200 + 600 * tw + rng.uniform(-150, 150, n), rng.uniform(0, 1024, n)], 1)
    sig = (1.0 + tw) * np.where(rows_x2 & (uv[:, 1] > 700), 1.5, 1.0)
    r = sig[:, None] * rng.standard_normal((n, 2))
    sn = noise_stars.StarNoise(0.0, 0.0, 2.0 * n, n // per, (r**2).sum(1), 2 * np.ones(n),
                               rng.uniform(2, 6.3, n), np.hypot(uv[:, 0] - 511.5,
                                                                uv[:, 1] - 511.5),
                               np.zeros(n, bool), np.full(n, 0.05), uv=uv,
                               stated_px=np.full(n, 0.05), star=rng.integers(0, 300, n),
                               frame=frame)
    sn.t = 0.1 * frame  # (set after: coord2's StarNoise has no ``t``, and then fails below)
    sn.scale, sn.sigma, _ = sn.group(np.ones(n, bool))
    return sn


def test_the_stars_groups_are_tested_beside_a_noise_that_grows_over_the_run():
    """Unseen case ``noise_ramp``: the σ grows over the run while the stars in view move
    across the detector, and the groupings read the time trend as theirs (coord2, 4193ce7:
    column groups x0.99 .. x1.95 here at p 0 in 3 of 3 seeds; on the case's bags column
    groups at p 4e-7, s22, radius ones at s24, applied).  Tested beside the time trend
    (:func:`~.noise_stars.beside_time`, the bins' levels and the trend fitted jointly) no
    grouping is significant (column p 0.18-0.34), and a real one beside the trend (rows
    above 700 px 1.5x) is still found, its groups' ratio 1.5 within 5 % (1.49, 1.45, 1.51:
    the middle group 640-768 px mixes the two; at 2x its Bartlett p and another
    grouping's underflow to 0 alike, and the first of them is taken)."""
    for seed in (21, 22, 23):
        sn = _ramp_rows(seed)
        groups = noise_stars.star_groups(sn, (1024, 1024))
        assert noise_stars.significant_grouping(groups, 1) is None, (seed, groups)
        sn = _ramp_rows(seed, rows_x2=True)
        best = noise_stars.significant_grouping(noise_stars.star_groups(sn, (1024, 1024)), 1)
        assert best is not None and best["by"] == "row", (seed, best)
        assert best["scales"][-1] / best["scales"][0] == pytest.approx(1.5, rel=0.05), best


def _zero_share(data, share=0.4, seed=8):
    """A share of the catalogue stars carry σ = 0 (unknown) in every message."""
    rng = np.random.default_rng(seed)
    zero: dict[int, bool] = {}
    for f in data.frames:
        f.sigma = np.where([zero.setdefault(int(c), bool(rng.random() < share))
                            for c in np.asarray(f.catalog_id).tolist()], 0.0,
                           np.asarray(f.sigma, dtype=float))
    return data, zero


def test_sigma_wrong_star_by_star_is_said_beside_sigma_zero_stars():
    """The per-star hypothesis was skipped wherever a message said σ = 0: the previous
    test's bag with 40 % of its stars σ-0 (truly 0.05 px, the default) read random column
    groups x0.841-1.26 on main eacb4e8 (no per-star line).  Now the stated stars are tested
    among themselves (the σ-0 ones measured as their own σ, 0.05 px within 3 of its σ):
    the per-star line, its spread within 30 % of the truth of the stated stars seen, no
    groups, no tail line."""
    from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
    from stellar_cal_ros.diagnosis.runstats import evaluate
    from stellar_cal_ros.diagnosis.stats import evaluation_mask

    sim = _sim(seed=3)
    data, fac = _per_star(_stated(sim))
    data, zero = _zero_share(data)
    v = measure_bag(data, sim.prior, "psce", [], NoiseScales(), components=())
    assert v.per_star is not None and v.group is None and v.tails is None, v.lines()
    assert v.unknown and v.unknown_sigma_px == pytest.approx(0.05, abs=3 * v.unknown_sigma_sigma)
    base = evaluate(data, method_spec("psce"), rerun_prior(sim.prior), (), 0.5,
                    keep_residuals=True)
    res = base.residuals
    seen = np.unique(np.asarray(res["catalog_id"])[evaluation_mask(res, 0.5)
                                                   & ~np.asarray(res["gated"], bool)])
    w = np.array([fac[int(c)] ** -2.0 for c in seen if not zero[int(c)]])
    truth = 0.5 * w.std() / w.mean()
    assert abs(0.5 * v.per_star["spread"] - truth) < 0.3 * truth, (v.per_star, truth)
    assert any("wrong star by star" in x for x in v.lines()), v.lines()


def test_star_spread_holds_its_level_with_few_stated_stars_a_frame():
    """Beside σ-0 stars the stated ones may be few in each frame (the 150 s seed-4 bag:
    4 bright stars stated right, 2-4 a frame, beside faint σ-0 ones truly 0.1 px).  The
    one-way F on the stars' means of the rows about their frame's mean took those means
    as independent: they share the frames' means, and these draws read p < 1 % in 5 of
    100, p < 5 % in 15 on main eacb4e8 (the test was skipped beside σ-0 stars).  The
    two-way layout's F (``noise_stars._adjusted_ss``): at most 3 and 9 of 100 draws at the
    true σ (1 and 4 read), the frames' fit weighted as the verdict weights it."""
    from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
    from stellar_cal_ros.diagnosis.runstats import quiet
    from stellar_cal_ros.diagnosis.stats import evaluation_mask

    sim, data = _step_bag(4, sigma0=True)
    with quiet():
        result = method_spec("psce").runner(data, rerun_prior(sim.prior), [],
                                            keep_tables=True, eval_fraction=0.5)
    res0, cam = dict(result.residuals), result.calibration.camera
    n = len(res0["du"])
    true = np.where(np.asarray(res0["magnitude"], dtype=float) < 4.5, 0.05, 0.1)
    sig, msg = noise_stars.used_sigma(res0, data, NoiseScales(), 0.05, cam.width, cam.height)
    mask = evaluation_mask(res0, 0.5)
    rng = np.random.default_rng(5)
    p = []
    for _ in range(100):
        res = dict(res0, du=true * rng.standard_normal(n), dv=true * rng.standard_normal(n),
                   gated=np.zeros(n, bool))
        sn = noise_stars.star_noise(res, sig, msg, mask, cam.fx, cam.fy, (cam.cx, cam.cy),
                                    result.calibration.R_imu_st, size=(cam.width, cam.height),
                                    passes=noise.FIT_PASSES)
        d = noise_stars.star_spread(sn, ~sn.unknown)
        assert d["stars"] == 4
        p.append(d["p_value"])
    assert sum(x < 0.01 for x in p) <= 3 and sum(x < 0.05 for x in p) <= 9, sorted(p)[:12]


def test_group_sigma_beside_a_per_star_verdict_takes_the_stars_as_units():
    """A σ wrong star by star (30 % lognormal) and a region stated 2x (u >= 640 px): the
    groups printed beside the per-star verdict carried the rows' σ, which holds none of the
    stars' own levels (main eacb4e8: x0.08-0.19 of the groups' scatter over draws, and the
    bins, merged by it, kept random steps: 4.9 column groups a draw).  Now merged and their
    σ with the stars as units (``StarNoise.group(stars=True)``): over draws of the stars'
    factors and noise on one bag's rows, where the two groups split at 640 px are printed,
    each group's scale scatters by 0.65-1.5x the RMS of its printed σ."""
    base, res0, mask = _clean_rows()
    cam = base.calibration.camera
    n = len(res0["du"])
    cid = np.asarray(res0["catalog_id"])
    u = np.asarray(res0["u"], dtype=float)
    ids = np.unique(cid)
    rng = np.random.default_rng(13)
    two = []
    for _ in range(40):
        f = dict(zip(ids.tolist(), np.exp(0.3 * rng.standard_normal(len(ids)) - 0.045),
                     strict=True))
        stated = 0.05 * np.array([f[c] for c in cid.tolist()]) * np.where(u >= 640, 2.0, 1.0)
        res = dict(res0, du=0.05 * rng.standard_normal(n), dv=0.05 * rng.standard_normal(n),
                   gated=np.zeros(n, bool))
        sn = noise_stars.star_noise(res, stated, stated, mask, cam.fx, cam.fy,
                                    (cam.cx, cam.cy), base.calibration.R_imu_st,
                                    size=(cam.width, cam.height), passes=noise.FIT_PASSES,
                                    kept=NoiseScales())
        v = noise.NoiseVerdict(stated=NoiseScales(), applied=NoiseScales())
        noise.judge_stars(v, sn, 0.05, (cam.width, cam.height), 1)
        g = v.group
        if v.per_star is not None and g is not None and g["by"] == "column" and \
                list(g["edges"]) == [640.0]:
            two.append((g["scales"], g["sigma"]))
    assert len(two) >= 15, len(two)
    sc, sg = np.array([t[0] for t in two]), np.array([t[1] for t in two])
    ratio = sc.std(0, ddof=1) / np.sqrt(np.mean(sg**2, 0))
    assert np.all((ratio > 0.65) & (ratio < 1.5)), (ratio, len(two))
@pytest.mark.parametrize("stated", [NoiseScales(), NoiseScales(star=3.87, star_rho=0.95,
                                                               star_ar_share=0.27)])
def test_the_per_star_line_of_a_later_round_says_the_scale_to_use_not_as_stated(stated):
    """A later round measures the stars relative to the scales applied before: its per-star
    line says the --noise-scale to keep (the one the first round gave), not "their average
    is as stated (x0.298)" under a first round's star=3.77 (unseen case ``columns``)."""
    v = noise.NoiseVerdict(stated, stated, star=0.298 if not stated.identity else 1.01,
                           star_sigma=0.003)
    v.per_star = {"spread": 0.34, "stars": 81, "F": 4.72, "p_value": 1.8e-38}
    line = v._per_star_line()
    if stated.identity:
        assert "their average is as stated (x1.01" in line, line
    else:
        assert "as stated" not in line and "--noise-scale star=3.87,rho=0.95" in line, line


@pytest.mark.parametrize("added", [[], ["tangential"]])
def test_noise_is_the_cause_names_the_effects_discover_added(added):
    """After `discover` added an effect, the noise line does not say "no effect is missing"
    as if none were (unseen case ``bundle_s06``: tangential added, then the σ 1.67x)."""
    from stellar_cal_ros.diagnosis.printing import noise_lines

    summary = {"noise": {"verdict": ["x"], "rescaled": True}, "added": added,
               "recommendation": None, "unexplained": [], "candidates": []}
    last = noise_lines(summary)[-1]
    if added:
        assert "noise is the cause of the rest" in last and "(tangential)" in last, last
    else:
        assert last.startswith("noise is the cause: with the measured noise the model fits")


def test_star_spread_with_one_stated_star_a_frame_says_nothing_rather_than_crash():
    """One stated star a frame beside σ-0 ones leaves no frame with two tested stars: the
    two-way F's sums (``_adjusted_ss``) ran on no row and raised ``ValueError: zero-size
    array`` (reviewer RB on main f52b5c4: 50 frames of 1 stated + 3 σ-0 stars); no test."""
    rng = np.random.default_rng(3)
    frames, per = 50, 4
    n = frames * per
    frame = np.repeat(np.arange(frames), per)
    star = np.tile(np.arange(per), frames)
    unknown = star > 0
    sn = noise_stars.StarNoise(1.0, 0.01, 2.0 * n, frames, rng.chisquare(2, n),
                               2 * np.ones(n), np.full(n, 5.0), np.zeros(n), unknown,
                               np.ones(n), star=star, frame=frame)
    assert noise_stars.star_spread(sn, ~unknown) is None
    assert noise_stars.star_spread(sn) is not None  # every star tested: 4 a frame


def _uneven_tracks(rng: np.random.Generator, dof: float, factor_sd: float = 0.0,
                   shortest: float = 3.0):
    """A synthetic table of 80 stars over 200 frames, tracks of 3-150 rows (log-uniform).

    Each row's residual two draws (Gaussian, or Student-t of ``dof`` scaled to unit RMS),
    times its star's lognormal factor of SD ``factor_sd`` (0: the σ right star by star).
    """
    lay = np.random.default_rng(1)
    frames, S = 200, 80
    L = np.round(np.exp(lay.uniform(np.log(shortest), np.log(150.0), S))).astype(int)
    a = lay.integers(0, frames - L + 1)
    frame = np.concatenate([np.arange(a[s], a[s] + L[s]) for s in range(S)])
    star = np.repeat(np.arange(S), L)
    n = len(frame)
    e = rng.standard_normal((n, 2)) if not dof else \
        rng.standard_t(dof, (n, 2)) * np.sqrt((dof - 2.0) / dof)
    e = e * np.exp(factor_sd * rng.standard_normal(S))[star][:, None]
    return noise_stars.StarNoise(1.0, 0.01, 2.0 * n, frames, (e**2).sum(1), 2 * np.ones(n),
                                 np.full(n, 5.0), np.zeros(n), np.zeros(n, bool),
                                 np.ones(n), star=star, frame=frame)


@pytest.mark.parametrize("dof", [4.0, 3.0, 0.0])
def test_star_spread_holds_its_level_under_heavy_tails(dof):
    """Student-t noise (unseen case ``sway_t4`` seed 23: a false "wrong star by star ~7.6 %,
    p = 0.0045" beside the right heavy-tail line): a star's term of the F's numerator varies
    as ``2 + κ / n`` (``κ`` the squared residuals' excess kurtosis, unbounded for t4), the
    rows' mean square as ``2 + κ``, and on tracks of 10-150 rows main aa494f5 read p < 1 %
    in 20 (t4) and 34 (t3) of these 300 draws.  With both mean squares' dof divided by
    :func:`noise_stars.tail_factor` (1 and 0 read): at most α + 2σ of the binomial (6).
    Gaussian noise (``dof`` 0) keeps its level (2 read, as on main)."""
    rng = np.random.default_rng(7)
    draws = 300
    p = np.array([noise_stars.star_spread(_uneven_tracks(rng, dof, shortest=10.0))["p_value"]
                  for _ in range(draws)])
    bound = 0.01 * draws + 2.0 * math.sqrt(draws * 0.01 * 0.99)
    assert np.sum(p < 0.01) <= bound, (np.sum(p < 0.01), np.sort(p)[:10])


def test_star_spread_keeps_its_power():
    """A σ wrong star by star by 10 % (lognormal) is still found in every draw."""
    rng = np.random.default_rng(8)
    p = [noise_stars.star_spread(_uneven_tracks(rng, 0.0, 0.1, shortest=10.0))["p_value"]
         for _ in range(50)]
    assert max(p) < 0.01, max(p)


def test_a_fixed_pattern_of_the_columns_is_told_not_read_as_correlated_noise():
    """Unseen case ``columns``: stars whose centroid falls on 8 bands of 8 detector columns
    read 0.15 px further along u (a CCD's fixed pattern).  A star dwells on a band for many
    frames, so its track jumped by 0.15 px: the tracks' model read it as AR(1) noise
    ('use --noise-scale star=3.87,rho=0.95') and the star spread as σ wrong star by star
    (~17 %), and no line said the columns.  Now the residuals' mean by 8-px bands of the
    predicted column, each less its neighbours, is tested on the run's last 90 % first
    (``noise_stars.detector_patterns``: a coincidence across the stars' tracks, p from sign
    flips of whole tracks) and, where significant, the columns' means are taken out before
    the noise is read: no correlated or per-star verdict, the 'unexplained' line 'u vs u
    (column) (fixed pattern, bands of 8 px)' among the lines of u vs the column, its size
    within the bands' 0.15 px and half of it (a band straddling a defect's edge reads part
    of it); v is not flagged.
    (200 s, seed 8: the test's p 3.9e-5; over seeds 3-8 at 200 s it spans 4e-5 .. 6e-3,
    the case's 300 s seeds 21-26 all fire.)  Fails on main: the AR(1) verdict.
    The size printed is the pattern's 0.15 px within 4 of its σ over seeds (H157: the band
    slid to the defect's phase, the offsets fitted through the frames' attitude fit;
    ``columns`` 300 s seeds 21-30: 0.148 +- 0.0035 px, here 0.150; before, the test's
    fixed band, 7/8 of a defect, less the stars' means and the frames' fit, read 0.103 +-
    0.0055, here 0.102: fails on main b9b645c)."""
    from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
    from stellar_cal_ros.diagnosis.output import line_tests
    from stellar_cal_ros.diagnosis.runstats import evaluate

    sim = _sim(seed=8)
    data = _stated(sim)
    bad = (97, 211, 388, 459, 602, 731, 846, 950)  # benchmarks/unseen_cases.BAD_COLUMNS
    for f in data.frames:
        uv = np.asarray(f.uv, dtype=float).copy()
        uv[np.isin(np.floor(uv[:, 0]), [c + k for c in bad for k in range(8)]), 0] += 0.15
        f.uv = uv
    v = measure_bag(data, sim.prior, "psce", [], NoiseScales(), components=())
    assert v.correlated is None and v.per_star is None, v.lines()
    assert any(x.startswith("noise as stated") for x in v.lines()), v.lines()
    base = evaluate(data, method_spec("psce"), rerun_prior(sim.prior), (), 0.5,
                    keep_residuals=True)
    found = line_tests(base.residuals, base.calibration, 0.5)
    # the pattern's line first, and the other lines read less the pattern: its echoes are
    # not lines of their own (read with it, a ripple 'u vs u (column) (periodic 256 px)'
    # t -6.6 ranked first, then 'size vs u (column)' t 5.4 and 'radial vs radius' t 4.9,
    # the pattern's own line fourth: fails on main and on H161's branch)
    line = [f for f in found if f.regressor == "u (column) (fixed pattern, bands of 8 px)"]
    assert line and found[0] is line[0], found
    assert line[0].component == "u" and abs(line[0].slope_px - 0.15) < 0.017, found
    assert not [f for f in found if f.regressor.startswith(("u (column)", "v (row) (fixed"))
                and f is not line[0]], found


def _patterns_of(data, sim):
    """``(run, {axis: (FixedPattern, removed)})``: ``data``'s psce run (``evaluate``, half
    the run) and :func:`~.noise_stars.detector_patterns` on its residuals at their σ."""
    from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
    from stellar_cal_ros.diagnosis.runstats import evaluate

    base = evaluate(data, method_spec("psce"), rerun_prior(sim.prior), (), 0.5,
                    keep_residuals=True)
    res, cam = base.residuals, base.calibration.camera
    sig = np.sqrt(0.5 * (np.asarray(res["s_uu"], dtype=float)
                         + np.asarray(res["s_vv"], dtype=float)))
    return base, {a: (fp, removed) for a, fp, removed, *_ in
                  noise_stars.detector_patterns(res, sig, cam.fx, cam.fy, (cam.cx, cam.cy))}


def test_a_fixed_pattern_of_the_rows_is_found_between_the_stars():
    """Unseen case ``rows``: the ``columns`` case turned (8 bands of 8 detector rows read
    0.15 px further along v).  On PSCE a star crosses the columns as the tracker turns but
    its v spans ~6 px: it dwells in a row band, and the flips of whole tracks (each track
    free to carry any pattern of its own) test only a coincidence of 2-3 stars a band: p
    8e-4 .. 0.06 over the case's seeds 21-30 (H157), never below 1e-4.  The residuals about
    the stars' means hold the offset where a star crosses a band's edge (0.07-0.19 px steps
    on 19 of 19 crossing stars, seed 21) and the stars' means hold the rest: now ``T`` is
    also referred to the residuals' own noise (Gaussian, their variance, AR(1) along the
    tracks at most; ``FixedPattern.model_p``), which finds it (the case's seeds 21-30: p
    4e-13 .. 1.8e-9; clean psce none below 0.017), and, found so, the pixels' offsets are
    read with the stars' means in them: size 0.150 +- 0.016 px over seeds 21-30 (here,
    200 s seed 8: 0.157).  Its line is the first, and the other lines are read less the
    pattern (no ripple over the rows: its echo).  The same run without the pattern:
    nothing removed, no pattern line.  Fails on main: v is not removed (the flips' p 1e-3
    or so)."""
    from stellar_cal_ros.diagnosis.output import line_tests

    bad = (97, 211, 388, 459, 602, 731, 846, 950)  # benchmarks/unseen_cases.BAD_ROWS
    for shift in (0.15, 0.0):
        sim = _sim(seed=8)
        data = _stated(sim)
        for f in data.frames:
            uv = np.asarray(f.uv, dtype=float).copy()
            uv[np.isin(np.floor(uv[:, 1]), [c + k for c in bad for k in range(8)]), 1] += shift
            f.uv = uv
        base, found = _patterns_of(data, sim)
        assert not found["u"][1], found
        lines = line_tests(base.residuals, base.calibration, 0.5)
        if shift:
            fp, removed = found["v"]
            # (3 of the σ 0.016 px over seeds 21-30)
            assert removed and abs(fp.size_px - 0.15) < 0.048, found
            # its line first, and the other lines read less the pattern: no echo of it as
            # a ripple over the rows (read with it, 'v vs v (row) (periodic 341 px)' t 5.9;
            # the case end to end, seed 21: 'periodic 512 px' t -7.1 ranked first)
            assert lines and lines[0].regressor == "v (row) (fixed pattern, bands of 8 px)", \
                lines
            assert not [f for f in lines if f.regressor.startswith("v (row) (periodic")], lines
        else:
            assert not found["v"][1], found
            assert not [f for f in lines if "(fixed pattern" in f.regressor], lines


def _rate_noise_run(seed: int = 8):
    """Unseen case ``rate_noise``'s error (200 s psce, σ 0.05 √(1 + (2 v / v95)²) px, the
    messages' 0.05): its psce run (half), :func:`_patterns_of`'s patterns and the truth's
    ``b`` in px per deg/s of the image's speed."""
    from stellar_cal_ros.sim import tracker_errors

    sim = simulate(dataclasses.replace(get_scenario("psce_rotations"), centroid_noise_px=0.0),
                   duration=DURATION, seed=seed)
    vel = tracker_errors.image_velocity(sim)
    v95 = float(np.percentile(np.concatenate([np.linalg.norm(v, axis=1) for v in vel]), 95))
    rng = np.random.default_rng(15409)
    data = bag_data_from_simulation(sim)
    for f, v in zip(data.frames, vel, strict=True):
        s = 0.05 * np.sqrt(1.0 + (2.0 * np.linalg.norm(v, axis=1) / v95) ** 2)
        f.uv = np.asarray(f.uv, dtype=float) + s[:, None] * rng.standard_normal((len(s), 2))
        f.sigma = np.full(len(s), 0.05)
    base, found = _patterns_of(data, sim)
    # (px/s at the detector's scale over deg/s: the focal length in px per degree)
    return base, found, 0.1 / v95 * sim.prior.camera.fx * np.pi / 180.0


def test_a_noise_growing_with_the_image_speed_is_no_fixed_pattern_nor_a_per_star_error():
    """Unseen case ``rate_noise`` (H261): each centroid's σ 0.05 √(1 + (2 v / v95)²) px with
    its image speed ``v`` (smear: the slews' frames noisy, the frames at rest as stated),
    the messages' 0.05 constant.  The fixed pattern's Gaussian null took one variance for
    every row, and the few frames of large noise read as bands of 8 columns ('u (column)
    (fixed pattern, bands of 8 px)', case 300 s s21 z 24.4, p 1e-44; s22 t 19.5) though
    the flips' exact p was 0.08; the per-star repeat's χ² (one σ for every row) read the
    stars seen in the slews as a per-star error ('repeating vs catalogue star', s21 χ² 443
    / 150, p 1e-30).  Now, where the frames' noise differs
    (``noise_structure.frame_variances``), the pattern's null also takes each row's
    frame's variance and the repeat's χ² is also read with each row in its frame's σ, the
    larger p said: nothing removed, the model's z below 3 on both axes, the repeat's p
    above 1e-3 (s21 300 s: 0.13).  The frame variances are not used on the ``columns`` and
    ``rows`` runs nor the clean ones (the tests above, unchanged).  Fails on coord 884abd3
    (u z 14.7, v 6.9: both removed)."""
    base, found, _ = _rate_noise_run()
    for axis in "uv":
        fp, removed = found[axis]
        assert not removed and fp.model_z < 3.0, found
    from stellar_cal_ros.diagnosis.stats import evaluation_mask

    cam = base.calibration.camera
    sn = noise.line_noise(base.residuals, evaluation_mask(base.residuals, 0.5), cam.fx, cam.fy,
                          (cam.cx, cam.cy), None)
    assert sn.repeat_p > 1e-3, (sn.repeat, sn.repeat_dof, sn.repeat_p)


def _bright_quant_noise(duration: float, seed: int):
    """Unseen case ``bright_quant``'s stars: those brighter than mag 4 report centroids on a
    0.5 px grid (0.144 px rms), the rest 0.05 px as stated; the psce run's (half)
    :func:`~.noise.line_noise` and the detector's size."""
    from stellar_cal_ros.diagnosis.stats import evaluation_mask

    sim = simulate(dataclasses.replace(get_scenario("psce_rotations"), centroid_noise_px=0.0),
                   duration=duration, seed=seed)
    rng = np.random.default_rng(15411)
    data = bag_data_from_simulation(sim)
    for f in data.frames:
        uv = np.asarray(f.uv, dtype=float) + 0.05 * rng.standard_normal((len(f.uv), 2))
        bright = np.nan_to_num(np.asarray(f.magnitude, dtype=float), nan=5.0) < 4.0
        uv[bright] = np.round(uv[bright] / 0.5) * 0.5
        f.uv, f.sigma = uv, np.full(len(uv), 0.05)
    base, _ = _patterns_of(data, sim)
    cam = base.calibration.camera
    return noise.line_noise(base.residuals, evaluation_mask(base.residuals, 0.5), cam.fx,
                            cam.fy, (cam.cx, cam.cy), base.calibration.R_imu_st), \
        (cam.width, cam.height)


def test_one_star_whose_error_holds_still_is_no_grouping_of_the_sigma():
    """H274: a quantised star's error holds still while the tracker rests (its sub-pixel
    phase does not change), and Bartlett's test of the σ groupings took each of its rows as
    a draw: here (unseen case ``bright_quant``'s error, 200 s seed 8: one star brighter
    than mag 4, 2 % of the rows) the column its dwells sat in read "x1.46" at p 3e-28 and
    the σ was grouped by column.  Now each bin's dof are at most its scale's effective dof
    with the stars as units (``noise_stars._bins``): one star's level is no grouping
    (every p above 0.05).  Fails on coord fe2191f (column, p 1e-28)."""
    sn, size = _bright_quant_noise(DURATION, 8)
    groups = noise_stars.star_groups(sn, size, noise_stars.grouped_stars(sn))
    assert noise_stars.significant_grouping(groups, 1) is None, groups
    assert min(g["p_value"] for g in groups) > 0.05, groups


def test_a_kept_grouping_is_ranked_of_the_sigma_the_others_are_measured_of():
    """Unseen case ``bright_quant`` (H274), 300 s s21: round 1 groups the σ by magnitude
    (x3.1 / x1.0, right); round 2, with those groups kept, measured the other groupings of
    the σ *before* the kept factors (``noise_stars.star_groups``: they replace the kept
    groups), which still held the bright stars' excess wherever they sat, and the kept
    magnitude grouping of the σ *used*, flat (p 0.12): the smallest p was a row (s21, 1e-161)
    or column (s22) grouping, and "the stars' sigma depends on row" replaced the magnitude
    groups.  Now the kept grouping is ranked by its p of the σ before too (``p_before``,
    what the others are of): magnitude first, its own p (of the σ used) decides, nothing
    replaces it.  Here (the case's error, 300 s seed 21, 8 bright stars): round 1 magnitude
    (p 4e-13), round 2 (the σ used = the stated x round 1's factors) none; fails on coord
    fe2191f (round 2: row, p 4e-53)."""
    sn, size = _bright_quant_noise(300.0, 21)
    grouped = noise_stars.grouped_stars(sn)
    first = noise_stars.significant_grouping(noise_stars.star_groups(sn, size, grouped), 1)
    assert first is not None and first["by"] == "magnitude", first
    assert first["scales"][0] > 1.5 * first["scales"][-1], first
    kept = NoiseScales(group_by="magnitude", edges=tuple(first["edges"]),
                       factors=tuple(first["scales"]))
    f = np.asarray(kept.factors)[noise_stars.group_index(sn, first)]
    used = dataclasses.replace(sn, q=sn.q / f**2, sigma_px=sn.sigma_px * f, groups_made=None)
    groups = noise_stars.star_groups(used, size, grouped, kept)
    best = noise_stars.significant_grouping(groups, 1)
    assert best is None or best["by"] == "magnitude", best
    mag = next(g for g in groups if g["by"] == "magnitude")
    assert mag["p_before"] < min(g["p_value"] for g in groups if g["by"] != "magnitude"), groups


def test_a_noise_growing_with_the_image_speed_is_said_as_such_not_wrong_star_by_star():
    """Unseen case ``rate_noise`` s21 (H274): after the frames' levels
    (``noise_structure.frame_variances``) the star-by-star test still read "the stars'
    sigma is wrong star by star ~6 % (F 1.77, p 0.0021)": in a roll the stars far from its
    axis move faster than those near it, so a frame's level does not take a σ that grows
    with each star's own speed.  Now the rows' variance is fitted in the image's speed
    (``noise_stars.speed_variance``, σ² = a² + (b v)²), said as the noise line a user
    needs (the verdict's ``speed``) and the star-by-star test reads the rows over it.
    Here (200 s seed 8): a within 15 % of 0.05 px, b within 25 % of the truth's 0.1 px
    over the 95th-percentile speed, the star spread's p above 0.01.  Fails on coord fe2191f
    (no ``speed_variance``; its star spread here: F 3.0, p 3e-9)."""
    from stellar_cal_ros.diagnosis.stats import evaluation_mask

    base, _, b_true = _rate_noise_run()
    cam = base.calibration.camera
    sn = noise.line_noise(base.residuals, evaluation_mask(base.residuals, 0.5), cam.fx, cam.fy,
                          (cam.cx, cam.cy), base.calibration.R_imu_st)
    v = noise.NoiseVerdict(NoiseScales(), NoiseScales())
    v.applied = noise.judge_stars(v, sn, 0.05, (cam.width, cam.height), 3)
    d = v.speed
    assert d is not None and d["p_value"] < 1e-4, d
    assert abs(d["rest_px"] / 0.05 - 1.0) < 0.15, d
    assert abs(d["per_deg_s_px"] / b_true - 1.0) < 0.25, (d, b_true)
    lines = v.lines()
    assert [x for x in lines if x.startswith("the stars' sigma grows with their image's speed")]
    assert not [x for x in lines if "wrong star by star" in x], lines
    assert v.as_json()["star_speed"]["rest_px"] == d["rest_px"]


def test_a_ripple_over_the_columns_is_not_a_fixed_pattern():
    """Unseen case ``ripple`` (``0.08 sin(2π 3 u / width)`` px along u): the fixed
    pattern's bands cancel a field linear over their neighbours only, and the ripple's
    curvature leaks 8 % of it into every band (1 − cos over ±4 bands of 8 px at a period
    of 341 px).  Read by the residuals' Gaussian null (``FixedPattern.model_p``), that was
    a 'fixed pattern, bands of 8 px' of 0.1 px (the unseen ripple test, 150 s seed 21: p
    4e-5, size 0.098), and its pixels' offsets, taken out of the residuals the other lines
    read, took the ripple with them: 'v vs v (row)' first.  Now the pattern is tested less
    the smooth function of the position the ripple lines test
    (``noise_structure.less_smooth``): not removed, and the ripple's line first with its
    amplitude.  Here (200 s, seed 8, the run's own noise) the leak reads z 4.3 (p 0.0024,
    not removed; clean runs z <= 2.1), less the smooth fit -0.38: fails on H178's branch
    on the z."""
    from stellar_cal_ros.diagnosis.output import line_tests

    sim = _sim(seed=8)
    data = _stated(sim)
    width = sim.prior.camera.width
    for f in data.frames:
        uv = np.asarray(f.uv, dtype=float).copy()
        uv[:, 0] += 0.08 * np.sin(2.0 * np.pi * 3.0 * uv[:, 0] / width)
        f.uv = uv
    base, found = _patterns_of(data, sim)
    assert not found["u"][1] and not found["v"][1], found
    # (the u test as clean (z <= 2.1 on clean psce, H161): here -0.38; read with the
    # ripple's leak 4.31, seeds 3/5/21: 3.8-4.1)
    assert found["u"][0].z < 3.0, found
    lines = line_tests(base.residuals, base.calibration, 0.5)
    assert lines and lines[0].regressor.startswith("u (column) (periodic 341 px"), lines[:3]
    assert 0.85 * 0.08 < lines[0].slope_px < 1.1 * 0.08, lines[0]
    assert not [f for f in lines if "(fixed pattern" in f.regressor], lines


def _tracks(rng, frames: int, stars: tuple[int, int], life: tuple[int, int]):
    """Stars' tracks over ``frames`` frames: each frame tops up to a draw of ``stars``
    (integers' range) live stars, each at a uniform (u, v) in 20-1000 px and live a draw
    of ``life`` frames.  ``(frame, star, u, v, left)`` per row (``left``: the frame less
    the star's last, ≤ 0, for a drift)."""
    rows, live, sid = [], [], 0
    for f in range(frames):
        live = [s for s in live if s[3] > f]
        while len(live) < rng.integers(*stars):
            live.append([sid, rng.uniform(20, 1000), rng.uniform(20, 1000),
                         f + rng.integers(*life)])
            sid += 1
        rows += [(f, s[0], s[1], s[2], f - s[3]) for s in live]
    a = np.array(rows)
    return a[:, 0].astype(int), a[:, 1].astype(int), a[:, 2], a[:, 3], a[:, 4]


def _sparse_columns(seed: int, size: float, frames: int = 300, dwell: float = 55.0):
    """A sparse run for the fixed pattern's size: 20-40 stars a frame, each tracked 300-600
    frames drifting 1 px along u every ``dwell`` frames (σ 0.1 px), the ``columns`` case's
    8 bands of 8 columns reading ``size`` px further along u.  ``(fit, offset, u, star,
    σ, at_px)`` as :func:`~.noise_stars.detector_patterns` makes them for u."""
    from stellar_cal_ros.diagnosis.stats import FrameFit

    rng = np.random.default_rng(seed)
    frame, star, u, v, left = _tracks(rng, frames, (20, 41), (300, 600))
    u = u + left / dwell
    x, y = (u - 512) / 1000.0, (v - 512) / 1000.0
    n = np.sqrt(1 + x * x + y * y)
    bad = [c + k for c in (97, 211, 388, 459, 602, 731, 846, 950) for k in range(8)]
    du = rng.normal(0, 0.1, len(u)) + size * np.isin(np.floor(u), bad)
    sub = dict(frame=frame, du=du, dv=rng.normal(0, 0.1, len(u)), x_st=x / n, y_st=y / n,
               z_st=1 / n)
    sig = np.full(len(u), 0.1)
    fit = FrameFit(sub, sig, 1000.0, 1000.0)
    r = fit.residual(sub["du"], sub["dv"])
    offset, _ = noise_structure.pixel_means(r[:, 0], u, star, scale=sig)
    fp = noise_structure.fixed_pattern(r[:, 0], np.ones(len(u)), u, star, scale=sig)
    return fit, offset, u, star, sig, fp.at_px


def test_the_pattern_size_fit_that_does_not_settle_gives_the_direct_size():
    """Reviewer RF on H157's ``noise_stars._pattern_size``: its 10 fixed passes of
    ``c ← c + (offset − A c)`` settle on the ``columns`` case (0.146 px) but on sparse data
    keep inflating (here, 0.15 px at band 96: the direct size 0.136, after 1/10/30 passes
    0.145/0.169/0.191).  Not settled (the size changing by 0.1 % a pass or more) after the
    passes, the size is the direct one.  Fails on main 590c6dc: 0.169."""
    fit, offset, u, star, sig, at = _sparse_columns(3, 0.15)
    assert at == 96.0
    direct = noise_structure.band_offset_size(offset, u, at)
    size = noise_stars._pattern_size(fit, 0, offset, u, star, sig, at)
    assert size == direct and abs(size - 0.15) < 0.02, (size, direct)


def _rows_through_frames(seed: int, frames: int = 600):
    """A noise-free run of 8-12 stars a frame, each drifting 1 px along v every 5 frames
    over 100-300 frames, the ``rows`` case's 8 bands of 8 rows reading 0.15 px further
    along v.  ``(fit, offset, v, star, σ, at_px)`` as :func:`~.noise_stars.detector_patterns`
    makes them for v where the Gaussian null found the pattern (the pixels' offsets read
    without the stars' means)."""
    from stellar_cal_ros.diagnosis.stats import FrameFit

    frame, star, u, v, left = _tracks(np.random.default_rng(seed), frames, (8, 13), (100, 300))
    v = v + left / 5.0
    x, y = (u - 512) / 1000.0, (v - 512) / 1000.0
    n = np.sqrt(1 + x * x + y * y)
    bad = [c + k for c in (97, 211, 388, 459, 602, 731, 846, 950) for k in range(8)]
    sub = dict(frame=frame, du=np.zeros(len(u)), dv=0.15 * np.isin(np.floor(v), bad),
               x_st=x / n, y_st=y / n, z_st=1 / n)
    sig = np.full(len(u), 0.1)
    fit = FrameFit(sub, sig, 1000.0, 1000.0)
    r = fit.residual(sub["du"], sub["dv"])
    offset, _ = noise_structure.pixel_means(r[:, 1], v, star, scale=sig, star_means=False)
    fp = noise_structure.fixed_pattern(r[:, 1], np.ones(len(u)), v, star, scale=sig)
    return fit, offset, v, star, sig, fp.at_px


def test_the_rows_pattern_size_is_read_through_the_frames_fit():
    """Issue 21 item 3 (H190): a pattern the Gaussian null found (``rows``) had its size
    read from the pixels' offsets directly, but each frame's attitude fit takes ~1/N of a
    band's offset (N stars a frame): noise-free, 8-12 stars a frame, the direct size reads
    0.123-0.143 px for 0.15 (seeds 1-3), through the frames' fit (without the stars'
    means, as they were read) 0.150 within 0.001.  Fails on main: the rows' size was the
    direct one (unseen case ``rows`` end to end, seed 22: 0.116 px)."""
    for seed in (1, 2, 3):
        fit, offset, v, star, sig, at = _rows_through_frames(seed)
        direct = noise_structure.band_offset_size(offset, v, at)
        size = noise_stars._pattern_size(fit, 1, offset, v, star, sig, at, star_means=False)
        assert direct < 0.145 and abs(size - 0.15) < 0.002, (seed, direct, size)


def test_band_offset_size_reads_a_band_at_any_phase_and_at_the_detector_edges():
    """``noise_structure.band_offset_size`` (reviewer RF, N5): a defect of 8 columns read
    0.15 px further, at the test's band's phase 1 (columns 97-104, band 96) or at the
    detector's edges (0-7, 1016-1023), reads 0.15 px; no finite row, nan; no offset, 0."""
    rng = np.random.default_rng(1)
    pos = rng.uniform(0, 1024, 20000)
    for first, at in ((97, 96.0), (0, 0.0), (1016, 1016.0)):
        offset = np.where((pos >= first) & (pos < first + 8), 0.15, 0.0)
        assert noise_structure.band_offset_size(offset, pos, at) == pytest.approx(0.15), first
    assert math.isnan(noise_structure.band_offset_size(np.zeros(0), np.zeros(0), 96.0))
    assert math.isnan(noise_structure.band_offset_size(np.full(5, np.nan), pos[:5], 96.0))
    assert math.isnan(noise_structure.band_offset_size(np.ones(5), np.full(5, np.nan), 96.0))
    assert noise_structure.band_offset_size(np.zeros(len(pos)), pos, 96.0) == 0.0


def test_an_unmeasured_gyro_is_not_said_as_stated():
    """The swaying bags (unseen cases ``sway_gyro_over3``, ``sway_gyro3``: the gyro's ARW a
    third or 3x the stated): the gyro's samples carry the sway (not white) and the stars'
    fit does not move over a factor of 9 of it.  The line said "noise as stated (stars'
    sigma x0.979 +- 0.0091, accel x0.991 +- 0.0052 (its samples), gyro not measurable on
    this bag)", read as the gyro as stated; now what was measured, then the gyro's why.
    A measured gyro keeps the line as before; diagnosis.json's fields are unchanged."""
    from stellar_cal_ros.diagnosis.noise_imu import ScaleSearch

    ln3 = math.log(3.0)
    flat = ScaleSearch("gyro", {-ln3: -10.0, 0.0: -10.1, ln3: -10.3}, measurable=False,
                       sigma=math.inf)
    v = noise.NoiseVerdict(NoiseScales(), NoiseScales(), star=0.979, star_sigma=0.0091,
                           imu={"gyro": flat})
    v.samples = {"accel": {"scale": 0.991, "sigma": 0.0052, "white": True},
                 "gyro": {"scale": 14.0, "sigma": 0.5, "white": False}}
    assert v.lines() == [
        "noise as stated where measured (stars' sigma x0.979 +- 0.0091, accel x0.991 +- "
        "0.0052 from its samples); the gyro noise (angle random walk) cannot be measured on "
        "this bag (its own samples are not white: they carry the motion; the stars' fit does "
        "not change between a third and 3x of it: a noise below what the stars see on this "
        "motion): kept as stated, not confirmed"], v.lines()
    js = v.as_json()
    assert js["measured"]["gyro_noise_scale"] is False and js["as_stated"]["gyro_noise_scale"]
    # no maximum in range (not flat), no samples: said so
    v.imu = {"gyro": ScaleSearch("gyro", {-ln3: -10.0, 0.0: -13.0, ln3: -10.0},
                                 measurable=False, sigma=math.inf)}
    v.samples = {}
    assert v.lines()[0].endswith("; the gyro noise (angle random walk) cannot be measured on "
                                 "this bag (the stars' fit has no maximum in its range): "
                                 "kept as stated, not confirmed"), v.lines()
    # measured: as before
    v.imu = {"gyro": ScaleSearch("gyro", {0.0: -10.0}, value=1.02, sigma=0.05)}
    assert v.lines() == ["noise as stated (stars' sigma x0.979 +- 0.0091, gyro x1.02 +- "
                         "0.05)"], v.lines()


def test_an_unmeasured_gyro_is_said_beside_other_components_rejected():
    """Unseen case ``sway_three`` (H301; swaying base: the stars' σ field 1.5x the truth,
    the accelerometer 3x the stated, the gyro a third of it), s22: the verdict said the
    stars x0.662 and the accel x3 and nothing of the gyro, whose scale was not measurable
    (its samples carry the sway): no summary line follows rejected components, where the
    unmeasured one had its phrase.  Now its line follows theirs; fails on main 6c738a9."""
    from stellar_cal_ros.diagnosis.noise_imu import ScaleSearch

    ln3 = math.log(3.0)
    flat = ScaleSearch("gyro", {-ln3: -10.0, 0.0: -10.1, ln3: -10.3}, measurable=False,
                       sigma=math.inf)
    v = noise.NoiseVerdict(NoiseScales(), NoiseScales(star=0.662, accel=3.0), star=0.662,
                           star_sigma=0.0061, imu={"gyro": flat}, rejected=["accel", "star"])
    v.samples = {"accel": {"scale": 3.0, "sigma": 0.016, "white": True},
                 "gyro": {"scale": 9.07, "sigma": 0.05, "white": False}}
    said = [x for x in v.lines() if "gyro" in x]
    assert said == [
        "the gyro noise (angle random walk) cannot be measured on this bag (its own samples "
        "are not white: they carry the motion; the stars' fit does not change between a "
        "third and 3x of it: a noise below what the stars see on this motion): kept as "
        "stated, not confirmed"], v.lines()
    # measured (or rejected): no such line
    v.imu = {"gyro": ScaleSearch("gyro", {0.0: -10.0}, value=1.02, sigma=0.05)}
    assert not [x for x in v.lines() if "cannot be measured" in x], v.lines()

@pytest.mark.parametrize("seed", [21, 22, 23])
def test_a_noise_in_the_frames_stamps_is_named_as_noise_with_its_size(seed):
    """Frames stamped N(0, 1 ms) off their exposure on the 300-s swaying base (unseen case
    ``sway_jitter``): the baseline model is far off (NIS/dof 5.9-6.3) and the noise was
    'not measured: ... a missing effect shapes the residuals' -- a noise, named as an
    effect.  The reason now names the stamps' noise and its size, read back within 3σ of
    the 1 ms simulated (estimates 0.97-1.04 ms over seeds 21-26, σ ≈ 0.05), and the NIS/dof
    it leaves ≈ 1 (s22: 5.86 -> 0.97).  A constant 3-ms stamp offset (a missing time
    offset, NIS/dof 48.9) keeps the missing effect's reason.  Fails on main (no
    ``stamp_jitter``)."""
    from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
    from stellar_cal_ros.diagnosis.injection import clean_simulation
    from stellar_cal_ros.diagnosis.runstats import evaluate
    from stellar_cal_ros.sim import tracker_errors

    def verdict(jitter_s: float, offset_s: float):
        sim, _ = clean_simulation("swaying_base", False, seed, 300.0)
        if jitter_s:
            tracker_errors.stamp_jitter(sim, jitter_s, seed)
        for f in sim.star_frames:
            f.stamp_ns = int(f.stamp_ns + round(offset_s * 1e9))
        run = evaluate(bag_data_from_simulation(sim), method_spec("swaying_base"),
                       rerun_prior(sim.prior), (), 0.5, keep_residuals=True,
                       star_noise=True)
        v = noise.NoiseVerdict(NoiseScales(), NoiseScales())
        return noise.far_off(run, run.star_noise, sim.prior, 0.5, v), v

    why, v = verdict(1e-3, 0.0)
    got = v.stamp_jitter
    assert got is not None, why
    assert got["ms"] == pytest.approx(1.0, abs=0.15) and got["p_value"] < 1e-50, got
    nis = float(why.split("it makes NIS/dof ")[1].split(",")[0])
    assert nis > 2 * noise.MAX_DISPERSION
    assert nis - got["nis_share"] == pytest.approx(1.0, abs=0.35), (nis, got)
    assert why.startswith(f"the frames' stamps jitter {got['ms']:.2g} ms rms ")
    v.skipped = why
    assert "a missing effect" not in why and v.as_json()["stamp_jitter"] == got
    if seed == 23:
        why, v = verdict(0.0, 3e-3)
        assert why.startswith("the model is too far off") and v.stamp_jitter is None, why


def test_a_rounds_progress_lines_leave_the_repeats_source_to_the_report():
    """A round prints the noise verdict as it goes (discover's progress,
    ``NoiseVerdict.lines(pending=True)``), before the 'unexplained' lines are tested; the
    report's lines are made after them and say the source the repeat follows, if any
    (``NoiseVerdict.following``).  Unseen case ``stray_light`` s21 (its repeat: chi2 328 /
    156, 0.0061 px): the progress said 'from the catalogue positions or the
    identification' and 'the attitude follows the per-star errors of the stars in view'
    while the report's first line was the rows' field and its noise lines followed it.  Now
    the progress lines name no source: they say the 'unexplained' lines tell it, and every
    other word is the report's.  Fails on main 6c738a9 (no ``pending``)."""
    rep = {"chi2": 328.0, "dof": 156.0, "p_value": 2.4e-14, "rms_px": 0.0061}
    v = noise.NoiseVerdict(NoiseScales(), NoiseScales(), repeat=rep,
                           imu_skipped=noise.repeat_reason(rep["rms_px"]))
    live = v.lines(pending=True)
    cause = "smooth structure over the detector's rows (v)"
    for report in (v.lines(), v.following(cause).lines()):
        assert len(live) == len(report)
        for a, b in zip(live, report, strict=True):
            if "repeat star by star" not in b:
                assert a == b
                continue
            assert "per-star errors" not in a and "from the catalogue positions" not in a, a
            assert "'unexplained' lines" in a and cause not in a, a
            head = b.split(" that follows ")[0].split(" from the catalogue")[0].split(
                ": the attitude follows ")[0]
            assert a.startswith(head), (a, b)
    said = [x for x in live if "repeat star by star" in x]
    assert len(said) == 2 and said[1].startswith("IMU noise taken as stated: "), said
    assert noise.PENDING_SOURCE in said[0], said
    # (a repeat the lines have told the source of: the progress says it as the report)
    told = v.following(cause)
    assert told.lines(pending=True) == told.lines()
