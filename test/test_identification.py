"""Star identification through tetra3rs (stellar_cal_ros.sky.identify) against known truth.

Centroids are Hipparcos stars projected through a distorted camera at random attitudes
(the truth: their HIP numbers); a simulated bag with its identifications stripped
(catalog_id 0, RA/Dec NaN, contract §2) must calibrate like the identified one.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from sim_bags import psce_bag

from stellar_cal_ros.core.camera import CameraModel
from stellar_cal_ros.core.catalog import load_catalog, radec_to_unit
from stellar_cal_ros.core.rotation import so3_exp, so3_log
from stellar_cal_ros.io.calibration import load_calibration
from stellar_cal_ros.methods.acf import run_acf
from stellar_cal_ros.methods.replay import read_bag_data, replay
from stellar_cal_ros.sky.identify import Identifier, needs_identification, predicted_attitude

W = H = 1024
F = W / 2 / np.tan(np.radians(12.0) / 2)
CAMERA = CameraModel(W, H, F, F * 1.0002, 515.3, 508.1, [-0.05, 0.01, 1e-4, -2e-4, 0])


def _field(rng, R_i_st, noise_px=0.1, mag=6.5):
    cat = load_catalog(mag)
    d = radec_to_unit(*cat.message_radec()) @ R_i_st
    vis = d[:, 2] > 0.95
    uv = CAMERA.project(d[vis])
    ok = CAMERA.in_image(uv)
    return uv[ok] + rng.normal(0, noise_px, (ok.sum(), 2)), cat.hip[vis][ok]


def test_lost_in_space_then_tracking_identifies_hipparcos_truth():
    rng = np.random.default_rng(3)
    ident = Identifier(CAMERA)
    n_true = n_stars = 0
    for _ in range(6):
        R = so3_exp(rng.normal(size=3))
        uv, hip = _field(rng, R)
        fake = rng.uniform(0, W, (3, 2))  # hot pixels / noise blobs
        uv_all = np.vstack([uv, fake])
        res = ident.identify(uv_all)
        assert res.status == "lost_in_space"
        ok = res.identified[:len(uv)]
        # no false identification, and (almost) every real star identified
        assert np.all(res.catalog_id[:len(uv)][ok] == hip[ok])
        assert not res.identified[len(uv):].any()
        n_true += ok.sum()
        n_stars += len(uv)
        # the attitude of the solve: within 5 sigma of roll about the boresight (0.1 px)
        assert np.degrees(np.linalg.norm(so3_log(res.R_i_st.T @ R))) * 3600 < 60
        # tracking with a hint 0.05 deg off; a hint 3 deg off falls back to lost-in-space
        near = ident.identify(uv_all, R @ so3_exp(np.radians([0.03, -0.03, 0.02])))
        assert near.status == "tracking"
        assert np.array_equal(near.catalog_id, res.catalog_id)
        far = ident.identify(uv_all, R @ so3_exp(np.radians([3.0, 0.0, 0.0])))
        assert far.status == "reidentified"
        flagged = res.ambiguous | res.conflicting | res.gated | res.not_hipparcos
        assert not (flagged & res.identified).any()
    assert n_true >= 0.85 * n_stars
    c = ident.counters
    assert (c.frames, c.lost_in_space, c.tracking, c.reidentified, c.failed) == (18, 6, 6, 6, 0)


def test_too_few_stars_is_a_counted_failure():
    ident = Identifier(CAMERA)
    res = ident.identify(np.array([[100.0, 200.0], [300.0, 400.0]]))
    assert res.status == "failed" and not res.identified.any()
    assert np.isnan(res.right_ascension).all() and ident.counters.failed == 1


def test_predicted_attitude_integrates_rates():
    t = np.arange(1, 101) * 0.01
    w = np.tile([0.0, 0.0, 0.2], (100, 1))
    R = predicted_attitude(np.eye(3), 0.1, 0.6, t, w)
    assert np.allclose(so3_log(R), [0, 0, 0.1], atol=1e-12)


def _strip(frames):
    return [dataclasses.replace(f, catalog_id=np.zeros_like(f.catalog_id),
                                right_ascension=np.full(len(f), np.nan),
                                declination=np.full(len(f), np.nan),
                                magnitude=np.full(len(f), np.nan)) for f in frames]


@pytest.fixture(scope="module")
def bag_pair():
    bag, prior, _ = psce_bag(120.0)
    data = read_bag_data(bag)
    stripped = dataclasses.replace(data, frames=_strip(data.frames))
    assert needs_identification(stripped.frames[0])
    return data, stripped, load_calibration(prior)


def test_unidentified_bag_replays_like_the_identified_one(bag_pair):
    data, stripped, prior = bag_pair
    a = replay(data, prior)
    b = replay(stripped, prior)
    c = b.counters
    assert c["identify_frames"] == len(data.frames) and c["identify_failed"] == 0
    assert c["identify_lost_in_space"] == 1  # then IMU-aided tracking
    assert c["identify_tracking"] == len(data.frames) - 1
    assert c["identify_stars_identified"] >= 0.9 * c["identify_stars"]
    flags = b.calibration.extra["identification"]  # written into the result YAML
    assert flags["frames"] == len(data.frames) and flags["ambiguous"] == c["identify_ambiguous"]
    assert "identification" not in a.calibration.extra
    names, cov = a.covariance
    sa = np.sqrt(np.diag(cov))
    sb = np.sqrt(np.diag(b.covariance[1]))
    xa = a.filter.theta[:len(sa)]
    xb = b.filter.theta[:len(sa)]
    _assert_nested(xa, sa, xb, sb, names)


def _assert_nested(xa, sa, xb, sb, names):
    """The stripped run uses a subset of the stars (the flagged ones dropped): the two
    estimates differ by sqrt(σb² − σa²) (nested estimators); 4 of that, at least 0.1 σa."""
    bound = 4.0 * np.sqrt(np.maximum(sb ** 2 - sa ** 2, (0.1 * sa) ** 2))
    assert np.all(np.abs(xb - xa) < bound), dict(zip(names, (xb - xa) / bound, strict=True))

def test_unidentified_bag_batch_like_the_identified_one(bag_pair):
    data, stripped, prior = bag_pair
    from stellar_cal_ros.core.types import ImuSeries
    from stellar_cal_ros.methods.acf_data import AcfData

    imu = ImuSeries(data.imu_stamp_ns, data.imu_w, data.imu_f)
    half = slice(0, len(data.frames) // 2)  # 60 s of frames: the test's time
    a = run_acf(AcfData(frames=data.frames[half], imu=imu, t0_ns=data.t0_ns), prior)
    b = run_acf(AcfData(frames=stripped.frames[half], imu=imu, t0_ns=data.t0_ns), prior)
    assert b.calibration.extra["identification"]["failed"] == 0
    ca, cb = a.calibration.camera, b.calibration.camera
    sa = np.asarray(a.calibration.sigma["camera"]["camera_matrix"]["data"])[[0, 2, 5]]
    sb = np.asarray(b.calibration.sigma["camera"]["camera_matrix"]["data"])[[0, 2, 5]]
    _assert_nested(np.array([ca.fx, ca.cx, ca.cy]), sa, np.array([cb.fx, cb.cx, cb.cy]), sb,
                   ["fx", "cx", "cy"])
