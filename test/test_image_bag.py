"""Bags recorded with star images (``/star_tracker/image`` + ``camera_info``) replay like
centroid bags: ``stellar-cal simulate --images`` renders the truth world's stars
(sim/image_bag.py), the one data path (methods/frames.py) makes each image a frame of
unidentified centroids as the star_extractor node does, the driver identifies them with the
IMU's hint, and the calibration equals the centroid bag's within the combined σ.  Content
damage is a counted skip, memory holds a chunk of images, not the bag."""

from __future__ import annotations

import logging
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from stellar_cal_ros.cli import main
from stellar_cal_ros.errors import MessageDecodeError
from stellar_cal_ros.io.bag import BagReader, BagWriter
from stellar_cal_ros.io.identity import bag_identity
from stellar_cal_ros.io.image_msgs import (
    camera_from_info,
    encode_camera_info,
    encode_image,
    encode_image_fields,
    image_pixels,
)
from stellar_cal_ros.io.schemas import IMAGE, IMAGE_SCHEMA
from stellar_cal_ros.methods.frames import read_bag_data
from stellar_cal_ros.methods.replay import replay
from stellar_cal_ros.sim.image_bag import TOPIC_IMAGE, sensor_for, write_image_simulation
from stellar_cal_ros.sim.render import render_image, without_noise
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate, write_simulation

DURATION_S = 30.0
SEED = 3


@pytest.fixture(scope="module")
def bags(tmp_path_factory) -> dict[str, Path]:
    """The same world as a centroid bag and as a mono16 image bag (30 s, 60 frames)."""
    d = tmp_path_factory.mktemp("imagebag")
    sc = get_scenario("psce_rotations")
    centroids = write_simulation(simulate(sc, duration=DURATION_S, seed=SEED), d / "c.mcap")
    images = write_image_simulation(simulate(without_noise(sc), duration=DURATION_S,
                                             seed=SEED), d / "i.mcap", "mono16", seed=SEED)
    return {"centroids": centroids["bag"], "images": images["bag"],
            "prior": centroids["prior"], "truth": centroids["truth"]}


def _truth_frames(duration: float):
    return simulate(without_noise(get_scenario("psce_rotations")), duration=duration,
                    seed=SEED).star_frames


def test_image_bag_replays_to_the_centroid_bags_calibration(bags):
    from stellar_cal_ros.io.calibration import load_calibration

    prior = load_calibration(bags["prior"])
    a = replay(bags["centroids"], prior, keep_tables=False)
    b = replay(bags["images"], prior, keep_tables=False)
    c = b.counters
    assert c["images_received"] == 60 and c["images_bad"] == 0
    assert c["identify_failed"] == 0 and c["identify_lost_in_space"] == 1
    assert c["identify_stars_identified"] >= 0.8 * c["identify_stars"]
    assert b.calibration.extra["identification"]["frames"] == 60
    # the extractor's σ is the centroids' true scatter, so the clean image bag is
    # "consistent" (NIS/dof inside its χ² interval; 1.22 "model mismatch" when the σ were
    # 10 % too small)
    cons = b.calibration.extra["consistency"]
    lo, hi = cons["interval"]
    assert cons["verdict"] == "consistent" and lo < cons["nis_per_dof"] < hi, cons
    names, cov_a = a.covariance
    sa, sb = np.sqrt(np.diag(cov_a)), np.sqrt(np.diag(b.covariance[1]))
    xa, xb = a.filter.theta[:len(sa)], b.filter.theta[:len(sa)]
    # independent centroid noise in the two bags: the difference has σ √(σa² + σb²)
    z = (xb - xa) / np.hypot(sa, sb)
    assert np.all(np.abs(z) < 4.0), dict(zip(names, np.round(z, 2), strict=True))
    # the images' centroids are ~4x better than the centroid bag's 0.05 px: σ shrinks
    i = {n: k for k, n in enumerate(names)}
    assert sb[i["focal_length.f"]] < 0.5 * sa[i["focal_length.f"]]
    truth = load_calibration(bags["truth"]).camera
    cam = b.calibration.camera
    for name, t_val, e_val in (("principal_point.cx", truth.cx, cam.cx),
                               ("principal_point.cy", truth.cy, cam.cy),
                               ("focal_length.f", truth.fx, cam.fx)):
        assert abs(e_val - t_val) < 4.0 * sb[i[name]], (name, e_val, t_val, sb[i[name]])


def test_info_on_an_image_bag(bags, capsys):
    assert main(["info", str(bags["images"])]) == 0
    out = capsys.readouterr().out
    assert "/star_tracker/image" in out and "sensor_msgs/msg/Image" in out
    assert "star images: 60 on /star_tracker/image (mono16, 1024 x 1024); camera_info " \
           "1024 x 1024, fx 3968.99" in out
    assert "extract and identify their stars" in out


def test_image_bag_memory_holds_a_chunk_not_the_bag(bags):
    with BagReader(bags["images"]) as r:
        n = r.topics()[TOPIC_IMAGE].message_count
    raw = n * 1024 * 1024 * 2
    tracemalloc.start()
    try:
        data = read_bag_data(bags["images"])
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert len(data.frames) == n == 60 and data.images_bad == 0
    # 126 MB of pixels went through; a few images' worth at most were held at once
    assert peak < 16 * 1024 * 1024 < raw / 7, (peak, raw)


def test_mono8_bag_from_the_command_line(tmp_path, capsys):
    bag = tmp_path / "m8.mcap"
    assert main(["simulate", "--scenario", "psce_rotations", "-o", str(bag), "--duration",
                 "10", "--seed", str(SEED), "--images", "mono8"]) == 0
    assert "20 mono8 images 1024x1024" in capsys.readouterr().out
    with BagReader(bag) as r:
        img = next(r.iter_images(TOPIC_IMAGE))
        assert img.encoding == "mono8" and image_pixels(img).dtype == np.uint8
        info = next(r.iter_camera_info())
    assert camera_from_info(info).fx == pytest.approx(3968.99, abs=0.01)
    data = read_bag_data(bag)
    truth = _truth_frames(10.0)
    z, err = [], []
    for f, t in zip(data.frames, truth, strict=True):
        assert f.stamp_ns == t.stamp_ns and np.all(f.catalog_id == 0)
        dist, j = cKDTree(t.uv).query(f.uv)
        m = dist < 1.0
        err.append(f.uv[m] - t.uv[j[m]])
        z.append(err[-1] / f.sigma[m, None])
    err, z = np.concatenate(err), np.concatenate(z)
    assert len(err) > 300
    # 8-bit quantization included: unbiased centroids, σ from the fit honest within 15 %
    assert np.all(np.abs(err.mean(axis=0)) < 4 * err.std(axis=0) / np.sqrt(len(err)))
    assert np.all((z.std(axis=0) > 0.85) & (z.std(axis=0) < 1.15)), z.std(axis=0)
    from stellar_cal_ros.io.calibration import load_calibration

    res = replay(bag, load_calibration(tmp_path / "m8.prior.yaml"), keep_tables=False)
    c = res.counters
    assert c["images_received"] == 20 and c["identify_failed"] == 0
    assert c["identify_stars_identified"] >= 0.8 * c["identify_stars"]


def _bag_with_bad_images(path: Path) -> dict[str, Path]:
    """10 s of images; frame 3 in bgr8, frame 5 short of data, frame 7 of another size,
    frame 9's payload cut inside its CDR."""
    sc = without_noise(get_scenario("psce_rotations"))
    result = simulate(sc, duration=10.0, seed=SEED)
    sensor = sensor_for("mono16")

    def write_frames(w: BagWriter) -> None:
        for k, f in enumerate(result.star_frames):
            px = render_image(f.uv, f.magnitude, sc.width, sc.height, sensor,
                              np.random.default_rng([SEED, k])).image
            data = px.astype("<u2").tobytes()
            fields = [f.stamp_ns, f.frame_id, sc.height, sc.width, "mono16", 0,
                      2 * sc.width, data]
            if k == 3:
                fields[4] = "bgr8"
            elif k == 5:
                fields[7] = data[:-2 * sc.width]
            elif k == 7:
                fields[2], fields[7] = sc.height // 2, data[:len(data) // 2]
            payload = encode_image_fields(*fields)
            w.write_raw(TOPIC_IMAGE, IMAGE, IMAGE_SCHEMA, f.stamp_ns,
                        payload[:40] if k == 9 else payload)

    return write_simulation(result, path, write_frames)


def test_damaged_images_are_counted_skips(tmp_path, caplog):
    from stellar_cal_ros.io.calibration import load_calibration

    paths = _bag_with_bad_images(tmp_path / "bad.mcap")
    prior = load_calibration(paths["prior"])
    # content damage (encoding, data size, image size) is a counted skip in any mode; a
    # message whose CDR is cut follows --on-error as every malformed message does
    with pytest.raises(MessageDecodeError, match="/star_tracker/image"):
        replay(paths["bag"], prior, keep_tables=False)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="stellar_cal_ros"), \
            pytest.warns(UserWarning, match="skipped 1 malformed message"):
        res = replay(paths["bag"], prior, keep_tables=False, on_error="skip")
    c = res.counters
    assert c["messages_skipped"] == 1
    assert c["images_received"] == 19 and c["images_bad"] == 3
    assert c["frames_received"] == 16 and c["identify_failed"] == 0 and c["updates"] >= 14
    warned = [r.getMessage() for r in caplog.records if "image stamped" in r.getMessage()]
    assert len(warned) == 1 and "'bgr8' is not mono8 or mono16" in warned[0], warned
    with pytest.warns(UserWarning, match="skipped 1 malformed message"):
        data = read_bag_data(paths["bag"], on_error="skip")
    assert data.images_bad == 3 and len(data.frames) == 16


def test_a_bag_with_centroids_and_images_uses_the_centroids(tmp_path, caplog):
    sc = get_scenario("psce_rotations")
    result = simulate(sc, duration=5.0, seed=SEED)
    img = np.zeros((sc.height, sc.width), np.uint16)

    def write_frames(w: BagWriter) -> None:
        w.write_star_frames(result.star_frames)
        for f in result.star_frames[:3]:
            w.write_raw(TOPIC_IMAGE, IMAGE, IMAGE_SCHEMA, f.stamp_ns,
                        encode_image(f.stamp_ns, f.frame_id, img))

    paths = write_simulation(result, tmp_path / "both.mcap", write_frames)
    with caplog.at_level(logging.INFO, logger="stellar_cal_ros"):
        a = read_bag_data(paths["bag"])
        b = read_bag_data(paths["bag"])
    assert len(a.frames) == len(b.frames) == len(result.star_frames)
    assert all(np.array_equal(x.catalog_id, y.catalog_id)
               for x, y in zip(a.frames, result.star_frames, strict=True))
    said = [r.getMessage() for r in caplog.records if "the centroids are used" in
            r.getMessage()]
    assert len(said) == 1 and "/star_tracker/image" in said[0]


def test_image_messages_read_alike_from_every_bag_format(tmp_path):
    """Our CDR against rosbags' (an independent implementation), through rosbag2 sqlite3 and
    ROS 1 conversions of a short image bag."""
    from rosbags.convert import convert

    from stellar_cal_ros.io.rosbags_source import contract_typestore

    store = contract_typestore()
    px = (np.arange(7 * 13) * 700 % 65536).astype(np.uint16).reshape(7, 13)
    raw = encode_image(1_795_348_800_250_000_000, "star_tracker_optical_frame", px)
    msg = store.deserialize_cdr(raw, "sensor_msgs/msg/Image")
    assert (msg.encoding, msg.height, msg.width, msg.step) == ("mono16", 7, 13, 26)
    assert np.array_equal(image_pixels(msg), px)
    assert bytes(store.serialize_cdr(msg, "sensor_msgs/msg/Image")) == raw
    cam = get_scenario("psce_rotations")
    from stellar_cal_ros.core.camera import CameraModel

    camera = CameraModel(cam.width, cam.height, 3969.0, 3969.5, 515.0, 508.0,
                         [0.1, -0.3, 1e-4, 2e-4, 0.0])
    info = encode_camera_info(5, "star_tracker_optical_frame", camera)
    assert camera_from_info(store.deserialize_cdr(info, "sensor_msgs/msg/CameraInfo")) == \
        camera
    # a short image bag in three containers
    sc = without_noise(get_scenario("psce_rotations"))
    src = write_image_simulation(simulate(sc, duration=2.0, seed=SEED), tmp_path / "s.mcap",
                                 "mono8", seed=SEED)["bag"]
    convert([src], tmp_path / "rb2", "sqlite3", 8, None, "file", None, None, [], [], [], [])
    convert([src], tmp_path / "r1.bag", "sqlite3", 8, None, "file", None, None, [], [], [],
            [])

    def content(path):
        with BagReader(path) as r:
            imgs = [(m.stamp_ns, m.frame_id, image_pixels(m)) for m in r.iter_images()]
            infos = [camera_from_info(m) for m in r.iter_camera_info()]
        return imgs, infos

    ref_imgs, ref_infos = content(src)
    assert len(ref_imgs) == len(ref_infos) == 4
    for other in (tmp_path / "rb2", tmp_path / "r1.bag"):
        imgs, infos = content(other)
        assert infos == ref_infos
        assert [(s, f) for s, f, _ in imgs] == [(s, f) for s, f, _ in ref_imgs]
        assert all(np.array_equal(a[2], b[2]) for a, b in zip(imgs, ref_imgs, strict=True))
        assert bag_identity(other) == bag_identity(src)  # provenance: one recording


def test_batch_reads_the_images(bags, tmp_path):
    """batch acf and bundle (each its own loader) on the image bag: every image made into a
    frame, identified and used; diagnose/discover take the frames made once in the parent
    process (their re-runs get the centroids, not the images)."""
    import yaml

    from stellar_cal_ros.methods.frames import reads_star_images

    prior = str(bags["prior"])
    for method in ("acf", "bundle"):
        out = tmp_path / f"{method}.yaml"
        assert main(["batch", str(bags["images"]), "--method", method, "--prior", prior,
                     "-o", str(out), "-q"]) == 0
        res = yaml.safe_load(out.read_text())
        assert res["identification"]["frames"] == 60
        assert res["identification"]["failed"] == 0
    assert reads_star_images(bags["images"]) and not reads_star_images(bags["centroids"])
