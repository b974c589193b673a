"""Which data a result was computed from: a bag's content identity and a file's digest.

A result's ``provenance`` block names the bag by path, which says little once files move or
are converted.  :func:`bag_identity` is a short digest of the bag's *content* — message
counts and log-time span of the IMU and star topics and the first star frames' stamps,
catalogue ids and centroids (of a bag of star images: the first images' stamps and
pixels) — so the same recording as ``.mcap``, rosbag2 (MCAP or sqlite3)
or ROS 1 ``.bag`` gives the same identity, and two recordings of one scenario (equal
counts and times, different stars) do not.  :func:`file_digest` is the SHA-256 of a file
(the residual table a run wrote).  ``report`` and ``compare`` check both before they put
files of different runs side by side (:mod:`stellar_cal_ros.results_cli`).
"""

from __future__ import annotations

import hashlib
import os
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np

from stellar_cal_ros.io.reader import DEFAULT_TOPICS, BagReader

#: star frames read into the identity (enough to tell recordings apart, cheap to read)
IDENTITY_FRAMES = 5
IMAGE_TOPIC = "/star_tracker/image"


def bag_identity(path: str | os.PathLike[str], frames: int = IDENTITY_FRAMES) -> str:
    """Content identity of a bag (16 hex digits; the same for every container format).

    Raises
    ------
    BagError
        The bag cannot be opened or read.
    """
    h = hashlib.sha256()
    with warnings.catch_warnings(), BagReader(path, on_error="skip") as reader:
        warnings.simplefilter("ignore")  # damage is the reading command's to report
        topics = reader.topics()
        for role in ("imu", "stars"):
            info = topics.get(DEFAULT_TOPICS[role])
            h.update(f"{role}:{info.message_count if info else -1};".encode())
        h.update(f"{reader.start_ns}:{reader.end_ns};".encode())
        if DEFAULT_TOPICS["stars"] in topics:
            for k, f in enumerate(reader.iter_star_frames(DEFAULT_TOPICS["stars"])):
                if k >= frames:
                    break
                h.update(np.int64(f.stamp_ns).tobytes())
                h.update(np.asarray(f.catalog_id, np.int64).tobytes())
                h.update(np.round(np.asarray(f.uv, np.float64), 6).tobytes())
        elif IMAGE_TOPIC in topics:  # a bag of star images: the first images' stamps, pixels
            h.update(f"image:{topics[IMAGE_TOPIC].message_count};".encode())
            for k, img in enumerate(reader.iter_images(IMAGE_TOPIC)):
                if k >= frames:
                    break
                h.update(np.int64(img.stamp_ns).tobytes())
                h.update(f"{img.encoding}:{img.width}x{img.height};".encode())
                h.update(np.asarray(img.data))
    return h.hexdigest()[:16]


def file_digest(path: str | os.PathLike[str]) -> str:
    """SHA-256 of a file's bytes (hex)."""
    h = hashlib.sha256()
    with open(Path(path), "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def deferred_bag_identity(path: str | os.PathLike[str] | None) -> Callable[[], str | None] | None:
    """Return a callable giving :func:`bag_identity` of ``path`` (None if unreadable).

    For :func:`~stellar_cal_ros.io.calibration.set_provenance`: computed only when a
    result is written, after the command has read the bag.
    """
    if path is None or not Path(path).exists():
        return None

    def identity() -> str | None:
        from stellar_cal_ros.errors import StellarCalError

        try:
            return bag_identity(path)
        except (StellarCalError, OSError, ValueError):
            return None

    return identity
