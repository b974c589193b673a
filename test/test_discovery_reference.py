"""The model-discovery loop on the independent generator's sky bag, as a user runs it.

``psce_sky_900s`` hides three astrometric effects at their physical size (aberration,
refraction, proper motion) behind a prior that knows none of them.  The loop — replay the
current model, diagnose, add the recommended effect, repeat — must name all three, one per
round, and end at the noise floor with nothing significant left.

Measured (2026-11-22): refraction (RMS 0.100 → 0.069 px), proper_motion (→ 0.0512),
aberration (→ 0.0502); the last diagnosis recommends nothing.  In round 1 aberration fits
−2.8 × its physical size (the other two missing effects bend it) and is reported as
implausible rather than claimed; once they are in, it is found at its physical size.
"""

from __future__ import annotations

import pytest
import refdata

from stellar_cal_ros.diagnosis import stats
from stellar_cal_ros.diagnosis.run import diagnose
from stellar_cal_ros.io.calibration import load_calibration
from stellar_cal_ros.methods.replay import read_bag_data, replay_psce

BAG = refdata.DATA / "psce_sky_900s.mcap"
NOISE = 0.05
HIDDEN = {"aberration", "refraction", "proper_motion"}


@pytest.mark.benchmark  # ~7 min serial; one command with 2 workers: test_discovery_cases.py
@refdata.needs("psce_sky_900s.mcap")
def test_sky_bag_loop_finds_every_hidden_effect(tmp_path):
    data = read_bag_data(BAG)
    prior = load_calibration(BAG.with_suffix(".prior.yaml"))
    effects: list[str] = []
    history = []
    for round_ in range(5):
        run = replay_psce(data, prior, effects)
        rms = max(stats.rms(run.residuals, stats.evaluation_mask(run.residuals)))
        summary = diagnose(data, run.calibration, "psce", effects, tmp_path / str(round_),
                           plots=False, verbose=False)
        rec = summary["recommendation"]
        history.append((list(effects), round(rms, 4), rec))
        if rec is None:
            break
        assert rec in HIDDEN and rec not in effects, history
        effects.append(rec)
    assert set(effects) == HIDDEN, history
    assert rms <= 1.03 * NOISE, history
    assert not any(c["significant"] for c in summary["candidates"]), summary["candidates"][:3]
    # the residual RMS fell at every round
    rmss = [h[1] for h in history]
    assert all(b < a for a, b in zip(rmss, rmss[1:], strict=False)), history
    # the final model's astrometric scales are physical (1) within 4 sigma
    flt = run.filter
    for eff in HIDDEN:
        sl = flt.model.slices[eff]
        est, sig = float(flt.theta[sl][0]), float(flt.sigma()[3:][sl][0])
        assert abs(est - 1.0) <= 4 * sig, (eff, est, sig)
