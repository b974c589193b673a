"""Bad σ in the input (issue 13): counted and warned, never a crash, never silent.

A star whose message σ is negative or NaN gets the configured default σ and is counted
(``stars_bad_sigma``, one warning); a prior whose ``sigma`` block holds a negative or NaN
entry, or has no ``sigma`` block, is warned about one line per problem and a count, and
the calibration runs.  Data: a simulated 60 s ``psce_rotations`` run and variants of it
from ``stellar_cal_ros.sim.faults``.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest
import yaml

from stellar_cal_ros.cli import load_prior
from stellar_cal_ros.io.calibration import load_calibration
from stellar_cal_ros.methods.frames import read_bag_data
from stellar_cal_ros.methods.replay import replay
from stellar_cal_ros.sim.faults import catalogue, make_base

_VARIANTS = {v.name: v for v in catalogue()}


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    return make_base(tmp_path_factory.mktemp("sigma") / "base", duration=60.0, seed=2)


@pytest.fixture(scope="module")
def clean(base):
    return replay(base.bag, load_calibration(base.prior), "psce")


@pytest.mark.parametrize("name", ["stars_sigma_negative", "stars_sigma_nan"])
def test_bad_star_sigma_is_counted_and_the_default_used(base, clean, tmp_path, caplog, name):
    bag = _VARIANTS[name].make(base, tmp_path).bag
    sig = np.concatenate([f.sigma for f in read_bag_data(bag).frames])
    bad = int(np.sum(~(sig >= 0)))  # negative or NaN
    assert bad >= 5
    with caplog.at_level(logging.WARNING):
        res = replay(bag, load_calibration(base.prior), "psce")
    assert res.counters["stars_bad_sigma"] == bad
    warned = [r for r in caplog.records if "negative or NaN sigma" in r.getMessage()]
    assert len(warned) == 1, [r.getMessage() for r in caplog.records]
    # the default σ (0.05 px, the simulated noise) used: every frame updates as in the clean run
    assert res.counters["updates"] == clean.counters["updates"]
    # ... and the same calibration, to a fraction of its σ (fx, cx)
    sig_k = clean.calibration.sigma["camera"]["camera_matrix"]["data"]
    for i, name in ((0, "fx"), (2, "cx")):
        a, b = getattr(res.calibration.camera, name), getattr(clean.calibration.camera, name)
        assert abs(a - b) < 0.2 * sig_k[i], (name, a, b, sig_k[i])


def _prior(base, tmp_path, change):
    d = yaml.safe_load(base.prior.read_text())
    change(d)
    path = tmp_path / "prior.yaml"
    path.write_text(yaml.safe_dump(d))
    return path


def _negative_and_nan(d):
    data = d["sigma"]["camera"]["camera_matrix"]["data"]
    data[0], data[4] = -abs(data[0]), float("nan")


@pytest.mark.parametrize("change, lines", [
    (_negative_and_nan, [r"sigma\.camera\.camera_matrix\.data\[0\] = -[\d.e+-]+ is negative",
                         r"sigma\.camera\.camera_matrix\.data\[4\] is NaN",
                         r"2 problems \(above\): the run uses the defaults in their place"]),
    (lambda d: d.pop("sigma"), [r"no 'sigma' block: every estimated quantity starts from its "
                                r"effect's default σ"]),
], ids=["negative_and_nan", "no_sigma_block"])
def test_bad_prior_sigma_is_warned_and_the_run_goes_on(base, tmp_path, caplog, change, lines):
    import re

    path = _prior(base, tmp_path, change)
    with caplog.at_level(logging.WARNING):
        prior = load_prior(path)
    got = [r.getMessage() for r in caplog.records]
    assert len(got) == len(lines), got
    for pattern, line in zip(lines, got, strict=True):
        assert re.search(pattern, line), (pattern, line)
    res = replay(base.bag, prior, "psce")
    assert np.isfinite(res.calibration.camera.fx) and res.counters["updates"] > 100
