"""``stellar-cal simulate --images``: a bag of star images rendered from the truth world.

The scenario runs with noise-free centroids (:func:`~stellar_cal_ros.sim.render.without_noise`:
the same IMU, GNSS and temperature draws as the centroid bag of the same seed), and each
frame's stars are rendered (:func:`~stellar_cal_ros.sim.render.render_image`: PSF, sky
background, shot and read noise, hot pixels, saturation) into a ``sensor_msgs/msg/Image`` on
``/star_tracker/image`` stamped at mid-exposure, with the prior's camera on
``/star_tracker/camera_info`` (what a camera driver publishes beside its images).
``BAG.truth.yaml`` and ``BAG.prior.yaml`` are the centroid bag's, so an image bag and the
centroid bag of one seed are the same world seen through two inputs (a test bench for
extraction and identification).

Images are rendered when the writer assembles their chunk, each from its own random stream
(``seed``, frame index): memory holds a chunk, whatever the bag's length.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from stellar_cal_ros.io.bag import BagWriter
from stellar_cal_ros.io.image_msgs import encode_camera_info, encode_image, image_payload_size
from stellar_cal_ros.io.schemas import CAMERA_INFO, CAMERA_INFO_SCHEMA, IMAGE, IMAGE_SCHEMA
from stellar_cal_ros.sim.render import SensorConfig, render_image
from stellar_cal_ros.sim.world import SimulationResult, write_simulation

__all__ = ["ENCODINGS", "TOPIC_CAMERA_INFO", "TOPIC_IMAGE", "sensor_for",
           "write_image_simulation"]

TOPIC_IMAGE = "/star_tracker/image"
TOPIC_CAMERA_INFO = "/star_tracker/camera_info"
#: image encodings ``--images`` writes
ENCODINGS = ("mono16", "mono8")


def sensor_for(encoding: str) -> SensorConfig:
    """The detector of an encoding: a 12-bit sensor in mono16, an 8-bit one in mono8.

    The 8-bit sensor keeps the 12-bit one's photometry (full well, read noise, sky) with a
    gain that spreads its range over 8 bits (60 e⁻/ADU, bias 10 ADU): the background is then
    below one ADU and quantization is part of the noise, as on 8-bit cameras.
    """
    if encoding == "mono16":
        return SensorConfig()
    if encoding == "mono8":
        return SensorConfig(bits=8, gain_e_per_adu=60.0, bias_adu=10.0, hot_pixel_adu=50.0)
    raise ValueError(f"image encoding {encoding!r}: one of {', '.join(ENCODINGS)}")


def write_image_simulation(result: SimulationResult, bag_path: str | Path,
                           encoding: str = "mono16", sensor: SensorConfig | None = None,
                           seed: int = 0) -> dict[str, Path]:
    """Write ``result`` as an image bag (see the module docstring) and its YAML files.

    ``result`` should come from a scenario with noise-free centroids (they are the stars'
    true places in the images).
    """
    sensor = sensor or sensor_for(encoding)
    if (encoding == "mono8") != (sensor.dtype == np.uint8):
        raise ValueError(f"a {sensor.bits}-bit sensor does not fit {encoding}")
    frames = result.star_frames
    cam = result.prior.camera
    w, h = cam.width, cam.height
    stamps = np.array([int(f.stamp_ns) for f in frames], dtype=np.int64)
    frame_id = frames[0].frame_id if frames else "star_tracker_optical_frame"
    size = image_payload_size(frame_id, encoding, w * h * np.dtype(sensor.dtype).itemsize)

    def images(idx: np.ndarray) -> np.ndarray:
        out = np.empty(len(idx) * size, np.uint8)
        for j, k in enumerate(idx.tolist()):
            f = frames[k]
            r = render_image(f.uv, f.magnitude, w, h, sensor, np.random.default_rng([seed, k]))
            out[j * size:(j + 1) * size] = np.frombuffer(
                encode_image(int(f.stamp_ns), f.frame_id, r.image, encoding), np.uint8)
        return out

    info_size = len(encode_camera_info(0, frame_id, cam))

    def infos(idx: np.ndarray) -> bytes:
        return b"".join(encode_camera_info(int(stamps[k]), frame_id, cam) for k in idx.tolist())

    def write_frames(writer: BagWriter) -> None:
        writer.write_encoded(TOPIC_IMAGE, IMAGE, IMAGE_SCHEMA, stamps,
                             np.full(len(stamps), size), images)
        writer.write_encoded(TOPIC_CAMERA_INFO, CAMERA_INFO, CAMERA_INFO_SCHEMA, stamps,
                             np.full(len(stamps), info_size), infos)

    meta = result.meta
    counts = dict(meta.get("counts", {}))
    counts.pop("/star_tracker/stars", None)
    counts[TOPIC_IMAGE] = counts[TOPIC_CAMERA_INFO] = len(frames)
    result = dataclasses.replace(result, meta=dict(
        meta, counts=counts, images={"encoding": encoding, "width": w, "height": h,
                                     "seed": seed, "sensor": dataclasses.asdict(sensor)}))
    return write_simulation(result, bag_path, write_frames)
