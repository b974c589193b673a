"""An IMU noise scale only the stars measured is measured again once the model changed.

Unseen case ``sway_sky_twin_dt1``'s base (issue 21: noise named as noise): the swaying
base (200 s, seed 21, its clean model) with the sky (aberration, refraction, proper motion
at 1x) and a prior without it.  ``discover --auto`` adds refraction and proper motion; the
round that measures the noise (round 3) still lacks aberration, and the stars' ML runs, the
only measure of the swaying gyro (its samples carry the motion), read the attitude wander
its remainder makes as gyro noise: x106 +- 15.  On coord 0e2fd9e nothing measured the gyro
again once aberration was added (the CLI's final verdict: "the gyro noise (angle random
walk) looks 106 +- 15 x larger than stated" and "noise is the cause of the rest", on a bag
whose noise is as stated); where it was measured again (the sky effects the only
candidates, below) its search went from the x106 applied and read "at most x0.0524" of it,
printed as "looks smaller than stated: at most x0.0524 ...: use --noise-scale gyro=5.56"
and kept x5.56.  Now such a scale is stale on another model than the one it was measured on
(:meth:`~stellar_cal_ros.diagnosis.noise.NoiseVerdict.imu_from_stars`): the next round
measures it again, from the scale it was measured from.
"""

from __future__ import annotations

from stellar_cal_ros.diagnosis.auto import discover
from stellar_cal_ros.diagnosis.injection import SKY, SWAY_CLEAN
from stellar_cal_ros.methods.replay import bag_data_from_simulation
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate


def test_a_gyro_scale_measured_with_an_effect_missing_is_measured_again(tmp_path):
    """The sky bag above, the sky effects the candidates: all three added and the gyro's
    noise not rescaled in the end (fails on coord 0e2fd9e: x5.56 applied and said)."""
    sim = simulate(get_scenario("swaying"), duration=200.0, seed=21,
                   effects={**SWAY_CLEAN, **SKY})
    got = discover(bag_data_from_simulation(sim), sim.prior, "swaying_base", [], tmp_path,
                   candidates=list(SKY), plots=False, verbose=False, workers=0)
    assert sorted(got["added"]) == sorted(SKY), got["added"]
    applied = got["noise"]["applied"]
    assert applied["gyro_noise_scale"] < 3.0, (applied, got["noise"]["verdict"])
    assert not any("gyro noise (angle random walk) looks" in line
                   for line in got["noise"]["verdict"]), got["noise"]["verdict"]
    # the gyro was measured from the stars with an effect missing, and again after
    actions = [s["action"] for s in got["path"]]
    assert "noise" in actions, actions
