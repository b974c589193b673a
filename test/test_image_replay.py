"""Replay with the IMU on a simulated image stream reaches the calibration of the equivalent
centroid bag: the truth world's frames rendered as images (sim/render.py), centroided and
identified by the project (sky/extract.py; the driver's IMU-aided identification), against
the same world's centroid messages (0.05 px Gaussian noise, identified)."""

from __future__ import annotations

import dataclasses

import numpy as np

from stellar_cal_ros.core.types import StarFrame
from stellar_cal_ros.methods.frames import bag_data_from_simulation
from stellar_cal_ros.methods.replay import replay
from stellar_cal_ros.sim.render import SensorConfig, render_image, without_noise
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate
from stellar_cal_ros.sky.extract import extract_stars

DURATION_S = 30.0


def test_image_stream_calibrates_like_the_centroid_bag():
    sc = get_scenario("psce_rotations")
    truth_world = simulate(without_noise(sc), duration=DURATION_S, seed=3)
    centroids = simulate(sc, duration=DURATION_S, seed=3)  # same IMU draws, noisy centroids
    rng = np.random.default_rng(0)
    frames = []
    for f in truth_world.star_frames:
        c = extract_stars(render_image(f.uv, f.magnitude, sc.width, sc.height, SensorConfig(),
                                       rng).image)
        n = len(c)
        frames.append(StarFrame(f.stamp_ns, f.frame_id, f.exposure_time,
                                np.zeros(n, np.uint32), np.full(n, np.nan), np.full(n, np.nan),
                                c.uv, np.full(n, np.nan), c.sigma))
    images = dataclasses.replace(bag_data_from_simulation(truth_world), frames=frames)
    prior = centroids.prior
    a = replay(bag_data_from_simulation(centroids), prior)
    b = replay(images, prior)
    c = b.counters
    assert c["identify_failed"] == 0 and c["identify_lost_in_space"] == 1
    assert c["identify_stars_identified"] >= 0.8 * c["identify_stars"]
    cons = b.calibration.extra["consistency"]  # honest extractor σ: no false "mismatch"
    lo, hi = cons["interval"]
    assert cons["verdict"] == "consistent" and lo < cons["nis_per_dof"] < hi, cons
    names, cov_a = a.covariance
    sa = np.sqrt(np.diag(cov_a))
    sb = np.sqrt(np.diag(b.covariance[1]))
    xa = a.filter.theta[:len(sa)]
    xb = b.filter.theta[:len(sa)]
    # independent noise in the two streams: the difference has σ √(σa² + σb²)
    z = (xb - xa) / np.hypot(sa, sb)
    assert np.all(np.abs(z) < 4.0), dict(zip(names, z, strict=True))
    # and the image stream's own σ is honest against the truth
    truth = centroids.truth
    cam_t, cam_b = truth.camera, b.calibration.camera
    i = {n: k for k, n in enumerate(names)}
    for name, t_val, e_val in (("principal_point.cx", cam_t.cx, cam_b.cx),
                               ("principal_point.cy", cam_t.cy, cam_b.cy),
                               ("focal_length.f", cam_t.fx, cam_b.fx)):
        assert abs(e_val - t_val) < 4.0 * sb[i[name]], (name, e_val, t_val, sb[i[name]])
