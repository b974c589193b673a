"""From bag messages to filter inputs: one set of rules for every method and every driver.

* **Relative time** (:func:`time_origin`): ``t0_ns`` = first IMU stamp − the median interval of
  the first ``T0_IMU_SAMPLES`` IMU samples; times inside the estimators are relative to it,
  from integer nanoseconds (float POSIX seconds only resolve 0.24 µs).
* **Stars** — the one rule of every method, filters and batch fits alike
  (:func:`star_masks`, :func:`star_sigma`, both in :func:`frame_inputs`): a star is used when
  it is identified (finite catalogue RA and Dec; ``catalog_id`` 0 with a finite direction is a
  star identified outside Hipparcos, 0 with NaN an unidentified centroid, contract §2), its
  centroid is finite and on the detector (the pixel area ``[-0.5, width − 0.5) ×
  [-0.5, height − 0.5)``); its σ is the message's when positive, the method's default when 0
  ("unknown", contract; counted as ``stars_sigma_unknown``: ``replay`` and the diagnosis
  measure it from the run), and the default — counted as ``stars_bad_sigma`` — when
  negative, infinite or NaN; times the run's noise scales
  (:class:`~stellar_cal_ros.core.noise.NoiseScales`) when it has any.
* **Site** (:class:`SiteEstimator`): the median of the valid fixes (finite, status ≥ 0).
* **Environment** (:class:`EnvSeries`): temperatures and pressure interpolated linearly at the
  frame stamp over their finite samples (in seconds from the earliest finite sample).
* **Context** (:func:`frame_context`): what an effect may use for one frame.
* **Star images** (:class:`ImageFrames`): a bag recorded with images on
  ``/star_tracker/image`` (mono8/mono16, stamp = mid-exposure) is read one image at a time;
  each becomes a frame of unidentified centroids through
  :func:`~stellar_cal_ros.sky.extract.centroid_frame` (the ``star_extractor`` node's very
  step), identified afterwards as any unidentified centroids are (the driver's IMU-aided
  tracking; :func:`~stellar_cal_ros.sky.identify.identify_frames` in the batch methods).
  An image whose content is unusable (encoding, size, row step) is a counted skip
  (``images_bad``).  A bag holding both centroids and images is read through its
  centroids (:func:`star_input`, said once).

Used by the streaming driver (:mod:`stellar_cal_ros.methods.driver`, replay and live) and
the whole-bag loader (:func:`read_bag_data`, for the batch methods and the diagnosis).
"""

from __future__ import annotations

import bisect
import logging
import math
import time
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from stellar_cal_ros.core.catalog import radec_to_unit
from stellar_cal_ros.core.covariance import compiled_kernels
from stellar_cal_ros.core.earth import Site
from stellar_cal_ros.core.types import ScalarSeries, StarFrame, TopicInfo
from stellar_cal_ros.effects.base import FrameContext
from stellar_cal_ros.errors import BagError
from stellar_cal_ros.io.bag import BagReader
from stellar_cal_ros.io.image_msgs import ImageMessage, image_pixels

if TYPE_CHECKING:
    from stellar_cal_ros.sky.extract import ExtractConfig

log = logging.getLogger(__name__)

TOPIC_IMU = "/imu/data"
TOPIC_STARS = "/star_tracker/stars"
TOPIC_FIX = "/gnss/fix"
TOPIC_HEAD_TEMPERATURE = "/star_tracker/temperature"
TOPIC_AIR_TEMPERATURE = "/environment/temperature"
TOPIC_PRESSURE = "/environment/pressure"
TOPIC_IMAGE = "/star_tracker/image"
TOPIC_CAMERA_INFO = "/star_tracker/camera_info"
#: default topic of each input role (``image``/``camera_info``: star images instead of
#: centroids, see :func:`star_input`)
TOPICS = {"imu": TOPIC_IMU, "stars": TOPIC_STARS, "fix": TOPIC_FIX,
          "head": TOPIC_HEAD_TEMPERATURE, "air": TOPIC_AIR_TEMPERATURE,
          "pressure": TOPIC_PRESSURE, "image": TOPIC_IMAGE,
          "camera_info": TOPIC_CAMERA_INFO}
ENV_KEYS = ("head", "air", "pressure")
#: IMU samples whose median interval sets t0 and the nominal interval
T0_IMU_SAMPLES = 1000


def time_origin(stamps_ns: np.ndarray, samples: int = T0_IMU_SAMPLES) -> tuple[int, float]:
    """``(t0_ns, nominal_dt)`` from the first ``samples`` IMU stamps (sorted, unique, ≥ 2)."""
    s = np.asarray(stamps_ns[:samples], dtype=np.int64)
    step = int(np.median(np.diff(s)))
    t0_ns = int(s[0]) - step
    rel = (s - t0_ns) * 1e-9
    return t0_ns, float(np.median(np.diff(rel)))


@dataclass
class StarMasks:
    """What the star rule makes of each star of a message (module docstring)."""

    usable: np.ndarray  #: identified, finite, on the detector
    unidentified: np.ndarray  #: catalog_id 0 and no direction: a centroid to identify
    off_detector: np.ndarray  #: identified and finite, but off the detector

    @property
    def invalid(self) -> np.ndarray:
        """Neither usable, unidentified nor off the detector: non-finite values."""
        return ~(self.usable | self.unidentified | self.off_detector)


def star_masks(frame: StarFrame, width: int, height: int) -> StarMasks:
    """The star rule (module docstring) applied to one message."""
    uv = np.asarray(frame.uv, dtype=float).reshape(-1, 2)
    ra, dec = np.asarray(frame.right_ascension), np.asarray(frame.declination)
    direction = np.isfinite(ra) & np.isfinite(dec)
    unidentified = (np.asarray(frame.catalog_id) == 0) & np.isnan(ra) & np.isnan(dec)
    ok = direction & np.all(np.isfinite(uv), axis=1)
    with np.errstate(invalid="ignore"):
        on = (uv[:, 0] >= -0.5) & (uv[:, 0] < width - 0.5) & (uv[:, 1] >= -0.5) & \
            (uv[:, 1] < height - 0.5)
    return StarMasks(ok & on, unidentified, ok & ~on)


def clean_frame(frame: StarFrame, width: int, height: int) -> np.ndarray:
    """Mask of usable stars: identified, finite, on the detector (:func:`star_masks`)."""
    return star_masks(frame, width, height).usable


def star_sigma(sigma: np.ndarray, default: float, noise=None, magnitude=None, uv=None,
               centre: tuple[float, float] = (0.0, 0.0)) -> tuple[np.ndarray, int]:
    """``(σ, n_bad)`` of usable stars: the message's when positive, else ``default``.

    0 means "unknown" (contract); a negative, infinite or NaN σ is a bad value, counted in
    ``n_bad``.  With ``noise`` (:class:`~stellar_cal_ros.core.noise.NoiseScales`, and the
    stars' ``magnitude``, ``uv`` and the image ``centre`` for its groups) the stated σ is
    scaled, and an unknown or bad one is the measured σ of unknown stars when there is one
    (never 0).
    """
    s = np.asarray(sigma, dtype=float)
    fine = np.isfinite(s)
    n_bad = int(np.count_nonzero(~(fine & (s >= 0))))
    if noise is None:
        return np.where(fine & (s > 0), s, default), n_bad
    n = len(s)
    mag = np.full(n, np.nan) if magnitude is None else np.asarray(magnitude, dtype=float)
    pos = np.zeros((n, 2)) if uv is None else np.asarray(uv, dtype=float)
    return noise.star_sigma(np.where(fine & (s > 0), s, 0.0), default, mag, pos, centre), n_bad


@dataclass
class FrameInputs:
    """The filter inputs of one frame's usable stars."""

    ok: np.ndarray  #: (n_all,) usable-star mask of the message
    uv: np.ndarray  #: (n, 2) px
    u_i: np.ndarray  #: (n, 3) catalogue unit vectors (ICRS)
    sigma: np.ndarray  #: (n,) px
    catalog_id: np.ndarray  #: (n,) int64
    magnitude: np.ndarray  #: (n,)
    bad_sigma: int  #: stars whose message σ was negative, infinite or NaN (default used)
    unidentified: int = 0  #: centroids without identity (catalog_id 0, NaN RA/Dec)
    unknown_sigma: int = 0  #: stars whose message σ was 0 ("unknown": default or measured)
    #: every star's centroid, direction and σ known finite (σ > 0): the filter's checks of
    #: them can be left out (:meth:`~stellar_cal_ros.methods.kernel.StarFilter.process_frame`)
    valid: bool = False


def frame_inputs(frame: StarFrame, width: int, height: int, default_sigma: float,
                 noise=None, compiled: bool = False) -> FrameInputs:
    """Usable stars of a message and their filter inputs (see the module docstring).

    ``noise`` (:class:`~stellar_cal_ros.core.noise.NoiseScales`): the measured scales of
    the stated σ, and the measured σ of stars whose message says 0.
    ``compiled``: in one compiled call (:func:`stellar_cal_ros.core.jit.star_inputs`, the
    same rules and formulas as :func:`star_masks` and :func:`star_sigma`) when numba is there
    and the noise leaves the stars' σ as stated (its IMU scales may differ: the IMU noise
    search's runs; the same inputs bit for bit on the 2-h psce bag's 14 400 frames).
    """
    jit = compiled_kernels() if compiled and (noise is None or noise.stars_as_stated) else None
    if jit is not None:
        arrays = (np.asarray(frame.uv, dtype=float).reshape(-1, 2),
                  np.asarray(frame.right_ascension, dtype=float),
                  np.asarray(frame.declination, dtype=float), np.asarray(frame.catalog_id),
                  np.asarray(frame.sigma, dtype=float), np.asarray(frame.magnitude, dtype=float))
        ok, uv, u_i, sigma, cid, mag, bad, unid, unknown = jit.star_inputs(
            *arrays, float(width), float(height), float(default_sigma))
        # bad −1: arrays of unequal lengths, which take the numpy path (it raises as it
        # always did); else finite centroids and directions (the rule), σ the message's
        # finite positive one or the default, σ = 0 counted among the usable stars
        if bad >= 0:
            return FrameInputs(ok, uv, u_i, sigma, cid, mag, bad, unid, unknown,
                               valid=0.0 < default_sigma < math.inf)
    masks = star_masks(frame, width, height)
    ok = masks.usable
    s = np.asarray(frame.sigma, dtype=float)[ok]
    mag = np.asarray(frame.magnitude, dtype=float)[ok]
    sigma, bad = star_sigma(s, default_sigma, noise, mag, frame.uv[ok],
                            ((width - 1) / 2.0, (height - 1) / 2.0))
    return FrameInputs(ok, frame.uv[ok],
                       radec_to_unit(frame.right_ascension[ok], frame.declination[ok]),
                       sigma, frame.catalog_id[ok].astype(np.int64), mag, bad,
                       int(np.count_nonzero(masks.unidentified)), int(np.count_nonzero(s == 0)))


#: the per-star columns of a message beside its centroids (:func:`frame_inputs_many`)
_STAR_COLUMNS = ("right_ascension", "declination", "catalog_id", "sigma", "magnitude")


def frame_inputs_many(frames, width: int, height: int, default_sigma: float, noise=None,
                      compiled: bool = False) -> list[FrameInputs] | None:
    """:func:`frame_inputs` of several messages (``compiled``) in one compiled call.

    Each message's inputs equal, bit for bit, what :func:`frame_inputs` with ``compiled``
    gives it (:func:`stellar_cal_ros.core.jit.star_inputs_many`: the same per-star
    functions as :func:`~stellar_cal_ros.core.jit.star_inputs`); its arrays are slices of
    the call's.  None when that compiled path does not apply to them all (no numba, not
    ``compiled``, stars' σ scaled by ``noise``, a message whose arrays differ in length):
    the caller then asks :func:`frame_inputs` a message at a time.  A replay's frames
    (:func:`stellar_cal_ros.methods.replay._release_items`) take this: one call a release
    instead of a call a message (≈ 10 µs each).
    """
    got = frame_inputs_columns(frames, width, height, default_sigma, noise, compiled)
    if got is None:
        return None
    ok, uv_o, u_i, s_o, c_o, m_o = got[:6]
    valid = 0.0 < default_sigma < math.inf
    out = []
    j = 0
    a = got.bounds.tolist()
    for f, (k, bad, unid, unknown) in enumerate(got.counts.tolist()):
        e = j + k
        out.append(FrameInputs(ok[a[f]:a[f + 1]], uv_o[j:e], u_i[j:e], s_o[j:e], c_o[j:e],
                               m_o[j:e], bad, unid, unknown, valid=valid))
        j = e
    return out


class InputColumns(NamedTuple):
    """:func:`frame_inputs_columns`: the inputs of several messages, not cut into messages.

    Message ``f`` holds the rows ``bounds[f]:bounds[f + 1]`` of ``ok``, ``message_ids``
    and ``message_sigma``; its usable rows (``counts[f, 0]`` of them) follow the previous
    message's in the other columns.
    """

    ok: np.ndarray  #: (n,) every message star: usable
    uv: np.ndarray | None  #: (k, 2) the usable stars' centroids (px)
    u_i: np.ndarray  #: (k, 3) their catalogue directions
    sigma: np.ndarray | None  #: (k,) their σ (px; the default where the message has none)
    catalog_id: np.ndarray  #: (k,) int64
    magnitude: np.ndarray  #: (k,)
    counts: np.ndarray  #: (F, 4) per message: usable, bad_sigma, unidentified, unknown_sigma
    bounds: np.ndarray  #: (F + 1,) int64
    message_ids: np.ndarray  #: (n,) every message star's catalogue id, as the message has it
    message_sigma: np.ndarray  #: (n,) float, every message star's σ as the message states it


def frame_inputs_columns(frames, width: int, height: int, default_sigma: float, noise=None,
                         compiled: bool = False) -> InputColumns | None:
    """:func:`frame_inputs_many`'s one compiled call, its columns not cut into messages.

    The columns of :func:`stellar_cal_ros.core.jit.star_inputs_many` with the messages'
    bounds and their stars' ids and stated σ (:class:`InputColumns`); None where
    :func:`frame_inputs_many` gives None.  For a caller that wants columns (the twin's
    scene, :func:`~stellar_cal_ros.diagnosis.twin.twin_scene`: the messages'
    :class:`FrameInputs` made and stacked again cost ≈ 0.3 CPU-s a 2-h bag's scene).
    """
    jit = compiled_kernels() if compiled and (noise is None or noise.stars_as_stated) else None
    if jit is None or not len(frames):
        return None
    uv = [np.asarray(fr.uv, dtype=float).reshape(-1, 2) for fr in frames]
    cols = [[getattr(fr, name) for fr in frames] for name in _STAR_COLUMNS]
    n = list(map(len, uv))
    if any(list(map(len, c)) != n for c in cols):
        return None
    bounds = np.zeros(len(n) + 1, dtype=np.int64)
    np.cumsum(n, out=bounds[1:])
    ra, dec, cat, sig, mag = (np.concatenate(c) for c in cols)
    sig = sig.astype(float, copy=False)
    ok, uv_o, u_i, s_o, c_o, m_o, counts = jit.star_inputs_many(
        np.concatenate(uv), ra.astype(float, copy=False), dec.astype(float, copy=False), cat,
        sig, mag.astype(float, copy=False), bounds, float(width), float(height),
        float(default_sigma))
    return InputColumns(ok, uv_o, u_i, s_o, c_o, m_o, counts, bounds, cat, sig)


# ---------------------------------------------------------------------------- star images
_SAID: set[tuple[str, str, str]] = set()  # (bag, star topic, image topic) already told


def star_input(available: Mapping[str, TopicInfo], names: Mapping[str, str],
               where: str = "") -> str | None:
    """Which role carries a bag's star frames: ``stars`` (centroids) or ``image``.

    The centroids when the star topic holds messages, else the images when the image topic
    does; a bag with both is read through its centroids, which is said once (an INFO line
    per bag and process).  A topic present but empty counts as present (the readers then
    say it is empty); None: neither topic is in the bag.
    """
    stars, image = names.get("stars", TOPIC_STARS), names.get("image", TOPIC_IMAGE)

    def count(topic: str) -> int:
        info = available.get(topic)
        return -1 if info is None else int(info.message_count)

    n_stars, n_image = count(stars), count(image)
    if n_stars > 0 and n_image > 0:
        key = (str(where), stars, image)
        if key not in _SAID:
            _SAID.add(key)
            log.info("%s holds star centroids on %s and images on %s: the centroids are "
                     "used, the images are not read", where or "the bag", stars, image)
        return "stars"
    if n_stars > 0 or (n_stars == 0 and n_image <= 0):
        return "stars"
    return "image" if n_image >= 0 else None


def missing_stars_text(where: str, names: Mapping[str, str], available) -> str:
    """The one-line error of a bag with neither star centroids nor star images."""
    return (f"{where}: required topic {names.get('stars', TOPIC_STARS)} (or star images on "
            f"{names.get('image', TOPIC_IMAGE)}) is missing (topics: "
            f"{', '.join(sorted(available)) or 'none'})")


class ImageFrames:
    """Star images to frames of unidentified centroids, one image at a time, counted.

    The step the ``star_extractor`` node makes too: :func:`~stellar_cal_ros.io.image_msgs.
    image_pixels` (the content check) then :func:`~stellar_cal_ros.sky.extract.
    centroid_frame` (detection, PSF-fit centroids, σ from the signal-to-noise).  An image
    that fails the check (encoding other than mono8/mono16, data size not height × step,
    a size other than the camera's when ``size`` is given) is skipped and counted in
    :attr:`bad`, the first one with a warning.

    Parameters
    ----------
    config : ExtractConfig, optional
        Extraction settings.
    size : (width, height), optional
        The camera's image size (the prior's): images of another size are skipped.  None:
        the first usable image's (one camera makes a bag's images).
    where : str
        The bag, for messages.
    """

    def __init__(self, config: ExtractConfig | None = None,
                 size: tuple[int, int] | None = None, where: str = "") -> None:
        self._config = config  # default made on first use: see config
        self.size = None if size is None else (int(size[0]), int(size[1]))
        self.where = where
        self.received = 0  #: images seen
        self.bad = 0  #: images skipped (unusable content)
        self.stars = 0  #: centroids extracted
        self.cpu_s = 0.0  #: CPU time of the extraction
        self._info_warned = False

    @property
    def config(self) -> ExtractConfig:
        """The extraction's settings (default: ``sky.extract.ExtractConfig()``).

        Made on first use: sky.extract loads scipy.special and the image code, which a bag
        of centroids never needs, and every driver holds an ImageFrames.
        """
        if self._config is None:
            from stellar_cal_ros.sky.extract import ExtractConfig

            self._config = ExtractConfig()
        return self._config

    def camera_info(self, info: Any) -> None:
        """Check a ``CameraInfo`` beside the images against ``size`` (the prior's camera).

        One of another size is warned about once; the camera used stays the prior's, and
        images of another size are skipped.
        """
        got = (int(info.width), int(info.height))
        if self.size is not None and got != self.size and got != (0, 0) and \
                not self._info_warned:
            self._info_warned = True
            log.warning("%s: camera_info describes %d x %d images, the prior's camera is "
                        "%d x %d: images of another size are skipped (images_bad)",
                        self.where or "bag", *got, *self.size)

    def __call__(self, image: ImageMessage) -> StarFrame | None:
        """The frame of one image message (None: skipped and counted)."""
        self.received += 1
        try:
            pixels = image_pixels(image)
            got = (pixels.shape[1], pixels.shape[0])
            self.size = self.size or got
            if got != self.size:
                raise ValueError(f"image of {got[0]} x {got[1]} pixels, the camera's is "
                                 f"{self.size[0]} x {self.size[1]}")
        except ValueError as exc:
            self.bad += 1
            if self.bad == 1:
                log.warning("%simage stamped %.3f skipped: %s (further ones are counted as "
                            "images_bad)", f"{self.where}: " if self.where else "",
                            image.stamp_ns * 1e-9, exc)
            return None
        from stellar_cal_ros.sky.extract import centroid_frame

        c0 = time.process_time()
        frame = centroid_frame(pixels, image.stamp_ns, image.frame_id, 0.0, self.config)
        self.cpu_s += time.process_time() - c0
        self.stars += len(frame)
        frame.log_time_ns = image.log_time_ns
        return frame


#: the reader's kind of each series role (the environment's: ``scalar``)
_SERIES_KIND = {"imu": "imu", "fix": "fix"}


def read_inputs(reader: BagReader, names: Mapping[str, str], roles: list[str],
                where: str = "", available: Mapping[str, TopicInfo] | None = None
                ) -> tuple[dict[str, Any], list[StarFrame], ImageFrames | None]:
    """A bag's star frames and the whole series of ``roles`` (those the bag has).

    The frames are its centroid messages, or its images made into frames one at a time
    (:class:`ImageFrames`; memory holds a chunk of images, never the bag's).  Every
    topic is read in one pass (:meth:`BagReader.read_whole`): a chunk holds messages of
    every topic, which topic by topic would be decompressed and checked once per topic
    (six passes over a contract bag of centroids).

    Returns
    -------
    series : dict
        Role -> :class:`ImuSeries` / :class:`NavSatSeries` / :class:`ScalarSeries`, for
        the ``roles`` (keys of ``names``) whose topic is in the bag.
    frames : list of StarFrame
    images : ImageFrames or None
        The image converter (None for centroids): its counts say what was skipped.
    """
    available = reader.topics() if available is None else available
    where = where or str(reader.path)
    star_role = star_input(available, names, where)
    if star_role is None:
        raise BagError(missing_stars_text(where, names, available))
    want = [k for k in roles if names.get(k) in available]
    images = ImageFrames(where=where) if star_role == "image" else None
    # one pass over the bag for every topic (each chunk decompressed and checked once);
    # the star topic first, as its errors were said first
    topics = {star_role: (names[star_role], star_role)}
    topics.update({k: (names[k], _SERIES_KIND.get(k, "scalar")) for k in want})
    series = reader.read_whole(topics, convert=None if images is None else {"image": images})
    frames = series.pop(star_role)
    if images is not None and images.bad:
        log.warning("%s: %d of %d images skipped (unusable content)", where, images.bad,
                    images.received)
    return series, frames, images


def reads_star_images(path: str | Path, imu_for: str = "", command: str = "diagnose") -> bool:
    """True when a bag's star frames come from its images (no star centroids in it).

    Read from the bag's summary (its topics), before any message.  ``imu_for``: the
    method that needs the IMU (the commands that run it: ``replay``, ``diagnose``,
    ``discover``); a bag without star frames, or without IMU then, raises :class:`BagError`
    at once, naming the methods that run without the IMU (measured: the diagnosis of a bag
    without IMU refused after 7-17 s of noise and candidate runs), as ``command`` runs them:
    ``diagnose`` one from its batch result, ``replay`` the batch command itself.
    """
    with warnings.catch_warnings(), BagReader(path, on_error="skip") as reader:
        warnings.simplefilter("ignore")  # damage is the reading command's to report
        available = reader.topics()
        role = star_input(available, TOPICS, str(path))
    if imu_for and role is None:
        raise BagError(missing_stars_text(str(path), TOPICS, available))
    info = available.get(TOPICS["imu"])
    if imu_for and (info is None or not info.message_count):
        from stellar_cal_ros.methods import registry

        other = [s.name for s in registry.catalog(diagnosable=command != "replay")
                 if not needs_imu(s) and s.kind == "batch"]
        instead = "" if not other else (
            f"; without it `stellar-cal batch --method {other[0]}` calibrates on the star "
            "frames alone" if command == "replay" else
            f"; without it `--method {other[0]}` runs on the star frames alone "
            f"(from `stellar-cal batch --method {other[0]}`'s result)")
        raise BagError(f"{path}: {imu_for} needs IMU samples on {TOPICS['imu']}, which the "
                       f"bag {'does not have' if info is None else 'holds none of'}{instead}")
    return role == "image"


def method_reads_images(path: str | Path, method: str, command: str = "diagnose") -> bool:
    """:func:`reads_star_images`, refusing a bag without the IMU ``method`` needs.

    A path that does not exist is refused by the reader with what a bag is
    (:func:`~stellar_cal_ros.errors.no_such_bag`, every command's line).  The commands that
    run a method on a bag ask: ``replay``, ``diagnose``, ``discover``, their runner;
    ``command`` names the one that asks.
    """
    from stellar_cal_ros.methods import registry

    return reads_star_images(path, imu_for=method if needs_imu(registry.peek(method)) else "",
                             command=command)


def needs_imu(spec) -> bool:
    """Whether a method (its registered spec, or its declaration) reads the IMU.

    A filter does, and a fit with the gyro.
    """
    from stellar_cal_ros.effects.base import Stage

    return spec is not None and (spec.kind == "filter" or Stage.GYRO in spec.stages)


def star_images_text(reader: BagReader, available: Mapping[str, TopicInfo],
                     where: str = "") -> tuple[str, bool]:
    """What ``stellar-cal info`` says of a bag's star images, and whether they are used.

    Their count, the first image's encoding and size (or why it is unusable), the first
    CameraInfo's camera, and whether the commands read them (no star centroids) or not;
    ``("", False)`` for a bag without images on the contract topic.
    """
    info = available.get(TOPIC_IMAGE)
    if info is None or not info.message_count:
        return "", False
    first = next(iter(reader.iter_images(TOPIC_IMAGE)), None)
    desc = "none decodable"
    if first is not None:
        try:
            px = image_pixels(first)
            desc = f"{first.encoding}, {px.shape[1]} x {px.shape[0]}"
        except ValueError as exc:
            desc = f"the first is unusable: {exc}"
    cam = ""
    if available.get(TOPIC_CAMERA_INFO) is not None:
        ci = next(iter(reader.iter_camera_info(TOPIC_CAMERA_INFO)), None)
        if ci is not None and len(ci.k) == 9:
            cam = (f"; camera_info {ci.width} x {ci.height}, fx {ci.k[0]:.2f} cx {ci.k[2]:.2f}"
                   f" cy {ci.k[5]:.2f} px, {ci.distortion_model or 'no distortion model'}")
    used = star_input(available, TOPICS, where) == "image"
    use = ("replay, batch, diagnose and discover extract and identify their stars (the "
           "prior's camera is used)") if used else \
        f"not read: the star centroids on {TOPIC_STARS} are used"
    return f"star images: {info.message_count} on {TOPIC_IMAGE} ({desc}){cam}; {use}", used


class EnvSeries:
    """A scalar time series kept sorted by stamp (temperatures, pressure)."""

    def __init__(self) -> None:
        self.stamp_ns: list[int] = []
        self.value: list[float] = []
        self.ref_ns: int | None = None  # earliest finite sample ever: interpolation origin
        self.version = 0  # bumped on every change (add, trim, restore): the caches' key
        self._cache: tuple[Any, np.ndarray, np.ndarray] | None = None  # interp abscissae

    @classmethod
    def from_series(cls, series: ScalarSeries | None) -> EnvSeries:
        """The whole series of a bag topic (None: empty)."""
        out = cls()
        if series is not None and len(series.stamp_ns):
            order = np.argsort(series.stamp_ns, kind="stable")
            s = np.asarray(series.stamp_ns, dtype=np.int64)[order]
            v = np.asarray(series.value, dtype=float)[order]
            fin = np.isfinite(v)
            out.restore(s.tolist(), v.tolist(), int(s[fin][0]) if fin.any() else None)
        return out

    def add(self, stamp_ns: int, value: float) -> None:
        """Insert one sample (in stamp order)."""
        self.version += 1
        if np.isfinite(value) and (self.ref_ns is None or stamp_ns < self.ref_ns):
            self.ref_ns = stamp_ns
        if not self.stamp_ns or stamp_ns >= self.stamp_ns[-1]:
            self.stamp_ns.append(stamp_ns)
            self.value.append(value)
            return
        i = int(np.searchsorted(np.asarray(self.stamp_ns), stamp_ns, side="right"))
        self.stamp_ns.insert(i, stamp_ns)
        self.value.insert(i, value)

    def extend(self, stamp_ns: np.ndarray, value: np.ndarray) -> None:
        """Insert samples in their order: what :meth:`add` of each does.

        In bulk when they come in stamp order after the held ones (the usual case).
        """
        s = np.asarray(stamp_ns, dtype=np.int64)
        if not len(s):
            return
        if (self.stamp_ns and int(s[0]) < self.stamp_ns[-1]) or bool(np.any(s[1:] < s[:-1])):
            for t, v in zip(s.tolist(), np.asarray(value).tolist(), strict=True):
                self.add(t, v)
            return
        v = np.asarray(value, dtype=float)
        fin = np.isfinite(v)
        if fin.any():
            first = int(s[fin].min())
            if self.ref_ns is None or first < self.ref_ns:
                self.ref_ns = first
        self.version += len(s)
        self.stamp_ns.extend(s.tolist())
        self.value.extend(v.tolist())

    def restore(self, stamp_ns: list[int], value: list[float], ref_ns: int | None) -> None:
        """Replace the samples (checkpoint load)."""
        self.version += 1
        self.stamp_ns, self.value, self.ref_ns = stamp_ns, value, ref_ns

    def interp(self, t_ns: int | np.ndarray) -> float | np.ndarray:
        """``np.interp`` over the finite samples, in s from the earliest one; NaN if none."""
        scalar = np.ndim(t_ns) == 0
        if not self.stamp_ns or self.ref_ns is None:
            return float("nan") if scalar else np.full(np.shape(t_ns), np.nan)
        ref = self.ref_ns
        key = self.version
        if self._cache is None or self._cache[0] != key:
            s = np.asarray(self.stamp_ns, dtype=np.int64)
            v = np.asarray(self.value, dtype=float)
            fin = np.isfinite(v)
            self._cache = (key, (s[fin] - ref) * 1e-9, v[fin])
        _, x, y = self._cache
        if not len(x):
            return float("nan") if scalar else np.full(np.shape(t_ns), np.nan)
        out = np.interp((np.asarray(t_ns, dtype=np.int64) - ref) * 1e-9, x, y)
        return float(out) if scalar else out

    def covers(self, t_ns: int) -> bool:
        """True when a sample at or after ``t_ns`` is held."""
        return bool(self.stamp_ns) and self.stamp_ns[-1] >= t_ns

    def trim(self, before_ns: int) -> None:
        """Drop samples older than ``before_ns`` but keep the one just before it."""
        if len(self.stamp_ns) < 3 or self.stamp_ns[1] >= before_ns:
            return
        i = int(np.searchsorted(np.asarray(self.stamp_ns), before_ns, side="left")) - 1
        if i > 0:
            self.version += 1
            del self.stamp_ns[:i]
            del self.value[:i]


class SiteEstimator:
    """The site: median of the valid fixes (finite, status ≥ 0), over the last ``max_fixes``.

    A running median: each coordinate of the window is also held sorted (insertion and
    eviction by bisection), so the site after each new fix costs O(log n) comparisons and
    one memmove instead of a median over the window — the same value as ``np.median``.
    """

    def __init__(self, max_fixes: int = 100_000) -> None:
        self.max_fixes = int(max_fixes)
        self.stamp_ns: list[int] = []
        self.values = np.zeros((0, 3))
        self.count = 0  # fixes ever added: the cache key
        self._cache: tuple[int, Site] | None = None
        self._sorted: tuple[list[float], list[float], list[float]] = ([], [], [])

    def add(self, stamp_ns: int, lat: float, lon: float, alt: float, status: int = 0) -> bool:
        """Add a fix; False (not used) when invalid."""
        vals = (float(lat), float(lon), float(alt))
        if not (math.isfinite(vals[0]) and math.isfinite(vals[1]) and math.isfinite(vals[2])) \
                or status < 0 or abs(vals[0]) > 90:
            return False
        n = len(self.stamp_ns)
        if n == len(self.values):
            grown = np.zeros((max(2 * n, 64), 3))
            grown[:n] = self.values[:n]
            self.values = grown
        self.values[n] = vals
        self.stamp_ns.append(int(stamp_ns))
        self.count += 1
        for lst, v in zip(self._sorted, vals, strict=True):
            bisect.insort(lst, v)
        k = len(self.stamp_ns) - self.max_fixes
        if k > 0:
            for row in self.values[:k].tolist():
                for lst, v in zip(self._sorted, row, strict=True):
                    del lst[bisect.bisect_left(lst, v)]
            del self.stamp_ns[:k]
            self.values[:n + 1 - k] = self.values[k:n + 1].copy()
        return True

    def add_many(self, stamp_ns, lat, lon, alt, status) -> int:
        """Add fixes (arrays); returns the number of invalid ones."""
        bad = 0
        for row in zip(np.asarray(stamp_ns).tolist(), np.asarray(lat).tolist(),
                       np.asarray(lon).tolist(), np.asarray(alt).tolist(),
                       np.asarray(status).tolist(), strict=True):
            bad += not self.add(*row)
        return bad

    @property
    def site(self) -> Site | None:
        """Median of the valid fixes, None before the first."""
        if not self.stamp_ns:
            return None
        if self._cache is None or self._cache[0] != self.count:
            n = len(self.stamp_ns)
            m = n // 2
            med = [lst[m] if n % 2 else (lst[m - 1] + lst[m]) / 2 for lst in self._sorted]
            self._cache = (self.count, Site(*med))
        return self._cache[1]


def frame_context(stamp_ns: int, inputs: FrameInputs, site: Site | None,
                  env: dict[str, EnvSeries], keys=ENV_KEYS) -> FrameContext:
    """The context effects may use for one frame (environment ``keys`` only, others NaN).

    The motion fields (rate, attitudes, gravity; set by whoever knows them, by assignment)
    start as shared read-only zeros / identities instead of new arrays per frame.
    :func:`frame_contexts` of the one frame (the live path's call: scalar interpolation,
    no arrays).
    """
    nan = float("nan")
    return _context(stamp_ns, inputs, site,
                    env["head"].interp(stamp_ns) if "head" in keys else nan,
                    env["air"].interp(stamp_ns) if "air" in keys else nan,
                    env["pressure"].interp(stamp_ns) if "pressure" in keys else nan)


def frame_contexts(stamps_ns: list[int], inputs: list[FrameInputs], site: Site | None,
                   env: dict[str, EnvSeries], keys=ENV_KEYS) -> list[FrameContext]:
    """:func:`frame_context` of several frames (the environment interpolated in one call)."""
    nan = [float("nan")] * len(stamps_ns)
    t = np.asarray(stamps_ns, dtype=np.int64)
    head, air, pressure = (env[k].interp(t).tolist() if k in keys else nan
                           for k in ("head", "air", "pressure"))
    return [_context(stamp, inp, site, h, a, p)
            for stamp, inp, h, a, p in zip(stamps_ns, inputs, head, air, pressure, strict=True)]


def _context(stamp_ns: int, inp: FrameInputs, site: Site | None, head: float, air: float,
             pressure: float) -> FrameContext:
    """One frame's :class:`FrameContext` (:func:`frame_context`, :func:`frame_contexts`)."""
    return FrameContext(
        stamp=stamp_ns * 1e-9, catalog_id=inp.catalog_id, magnitude=inp.magnitude, site=site,
        head_temperature_c=head, air_temperature_c=air, pressure_pa=pressure,
        omega_b=_ZERO3, R_i_b=_EYE3, R_i_st=_EYE3, gravity_st=_ZERO3)


def _read_only(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


_ZERO3 = _read_only(np.zeros(3))
_EYE3 = _read_only(np.eye(3))


# ---------------------------------------------------------------------------- whole bag
@dataclass
class BagData:
    """The parts of a contract bag the calibrations use (times relative to ``t0_ns``)."""

    t0_ns: int
    imu_t: np.ndarray
    imu_w: np.ndarray
    imu_f: np.ndarray
    frames: list[StarFrame]
    site: Site | None
    head_temperature: ScalarSeries | None
    air_temperature: ScalarSeries | None
    pressure: ScalarSeries | None
    read_seconds: float = 0.0
    imu_dropped: int = 0  #: duplicated-stamp or non-finite IMU messages not used
    nominal_dt: float = 0.0
    source: str = ""  #: path of the bag (empty for data made in memory)
    images_bad: int = 0  #: star images skipped as unusable (a bag of images; ImageFrames)
    #: what a read with ``on_error="skip"`` passed over (:meth:`BagReader.losses`; empty:
    #: nothing, or data not read from a bag)
    losses: dict = field(default_factory=dict)
    #: what runs over this data compute from it alone and share (the direction effects'
    #: tables, :meth:`~stellar_cal_ros.methods.star_model.StarModel.prepare_frames`), under
    #: a key of the fields it was made from (:meth:`prepared_for`); not a constructor
    #: argument: ``dataclasses.replace`` starts an empty one
    prepared: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def prepared_for(self, key: tuple) -> dict:
        """:attr:`prepared`, emptied first when it was made under another ``key``."""
        if self.prepared.get("key") != key:
            self.prepared.clear()
            self.prepared["key"] = key
        return self.prepared

    def __getstate__(self) -> dict:
        """Pickled (a Dask scatter, a copy) without :attr:`prepared`: made again there."""
        return {**self.__dict__, "prepared": {}}

    def losses_record(self) -> dict[str, Any]:
        """:attr:`losses` with what was read (a diagnosis's ``bag_losses``; empty: none).

        The result file's ``data_quality`` keys (doc/interfaces.md §3): ``seconds_read``
        (the IMU's span, the star frames' without IMU) and ``messages_read`` per kind.
        """
        return losses_record(self.losses, self.imu_stamp_ns, len(self.imu_t) + self.imu_dropped,
                             self.frames)

    @property
    def t0(self) -> float:
        """POSIX seconds of relative time zero."""
        return self.t0_ns * 1e-9

    @property
    def imu_stamp_ns(self) -> np.ndarray:
        """IMU stamps, POSIX ns."""
        return self.t0_ns + np.round(self.imu_t * 1e9).astype(np.int64)

    def env(self) -> dict[str, EnvSeries]:
        """The environment series (see :class:`EnvSeries`)."""
        return {"head": EnvSeries.from_series(self.head_temperature),
                "air": EnvSeries.from_series(self.air_temperature),
                "pressure": EnvSeries.from_series(self.pressure)}


def clean_imu(stamp_ns: np.ndarray, w: np.ndarray, f: np.ndarray, where: str = ""
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """IMU in stamp order, duplicated stamps and non-finite samples removed (counted).

    The intervals of removed samples are bridged by the filters
    (:class:`~stellar_cal_ros.core.imu.ImuBuffer`).
    """
    order = np.argsort(stamp_ns, kind="stable")
    stamps = np.asarray(stamp_ns, dtype=np.int64)[order]
    keep = np.concatenate([[True], np.diff(stamps) > 0]) if len(stamps) else np.zeros(0, bool)
    dropped = int(len(stamps) - keep.sum())
    if dropped:
        log.warning("%s: %d IMU messages with duplicated stamps dropped", where, dropped)
    if not np.array_equal(order, np.arange(len(order))):
        log.warning("%s: IMU messages out of stamp order were sorted", where)
    w = np.asarray(w, dtype=float)[order][keep]
    f = np.asarray(f, dtype=float)[order][keep]
    stamps = stamps[keep]
    finite = np.all(np.isfinite(w), axis=1) & np.all(np.isfinite(f), axis=1)
    if not np.all(finite):
        n_bad = int((~finite).sum())
        dropped += n_bad
        log.warning("%s: %d IMU messages with NaN/inf dropped (their intervals are bridged)",
                    where, n_bad)
        w, f, stamps = w[finite], f[finite], stamps[finite]
    return stamps, w, f, dropped


def read_bag_data(path: str | Path, topics: dict[str, str] | None = None,
                  on_error: str = "raise", require_imu: bool = True) -> BagData:
    """Read everything a calibration needs from a contract bag (whole-bag form).

    The batch methods and the diagnosis use it; the Kalman filters stream the bag
    (:func:`stellar_cal_ros.methods.replay.replay`) with the same rules.  With
    ``require_imu=False`` a bag of star frames only (``stellar-cal solve``'s) reads too:
    the IMU arrays are then empty and times are relative to the first star frame.
    """
    names = dict(TOPICS)
    names.update(topics or {})
    t_start = time.perf_counter()
    # on_error="skip": a truncated recording (power loss at sea) is calibrated on what it
    # holds; bad messages are dropped and counted (BagReader.skipped) with a warning.
    with BagReader(path, on_error=on_error) as reader:
        available = reader.topics()
        if star_input(available, names, str(path)) is None:
            raise BagError(missing_stars_text(str(path), names, available))
        use_imu = require_imu or names["imu"] in available
        if use_imu and names["imu"] not in available:
            raise BagError(f"{path}: required topic {names['imu']} is missing "
                           f"(topics: {', '.join(sorted(available)) or 'none'})")
        roles = ["imu", "fix", *ENV_KEYS] if use_imu else ["fix", *ENV_KEYS]
        whole, frames, images = read_inputs(reader, names, roles, str(path), available)
        imu = whole.get("imu")
        site = None
        if "fix" in whole:
            fix = whole["fix"]
            est = SiteEstimator(max_fixes=len(fix.stamp_ns) + 1)
            est.add_many(fix.stamp_ns, fix.latitude_deg, fix.longitude_deg, fix.altitude_m,
                         fix.status)
            site = est.site
        # a topic the bag declares but that holds no message (a node advertised it and
        # never published) is absent: an effect needing it is not applicable, not "not
        # testable with this motion" (MDB inf; unseen case focal_drift)
        scalars = {key: (s if (s := whole.get(key)) is not None and len(s) else None)
                   for key in ENV_KEYS}
        losses = reader.losses(reader.start_ns)
    if imu is None:
        if not frames:
            raise BagError(f"{path}: {names['stars']} holds no star frames")
        stamps, w, f, dropped = np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), 0
        t0_ns, nominal_dt = min(fr.stamp_ns for fr in frames), 0.0
    else:
        stamps, w, f, dropped = clean_imu(imu.stamp_ns, imu.angular_velocity,
                                          imu.linear_acceleration, str(path))
        if len(stamps) < 2:
            raise BagError(f"{path}: {names['imu']} has {len(stamps)} usable messages")
        t0_ns, nominal_dt = time_origin(stamps)
    return BagData(
        t0_ns=t0_ns, imu_t=(stamps - t0_ns) * 1e-9, imu_w=w, imu_f=f, frames=frames,
        site=site, head_temperature=scalars["head"], air_temperature=scalars["air"],
        pressure=scalars["pressure"], read_seconds=time.perf_counter() - t_start,
        imu_dropped=dropped, nominal_dt=nominal_dt, source=str(path),
        images_bad=images.bad if images is not None else 0, losses=losses)


def losses_record(losses: dict, imu_stamp_ns, imu_read: int, frames) -> dict[str, Any]:
    """``losses`` (:meth:`BagReader.losses`) with what was read; {} when nothing was lost.

    A whole-bag read's record (the batch fits', the diagnosis's): the result file's
    ``data_quality`` keys (doc/interfaces.md §3), ``seconds_read`` (the IMU's span, the
    star frames' without IMU) and ``messages_read`` per kind.
    """
    if not losses:
        return {}
    stamps = np.asarray(imu_stamp_ns) if len(imu_stamp_ns) else \
        np.array([f.stamp_ns for f in frames], dtype=np.int64)
    span = float(stamps.max() - stamps.min()) * 1e-9 if len(stamps) else 0.0
    read = {"imu": imu_read, "frames": len(frames)}
    return {**losses, "seconds_read": span,
            "messages_read": {k: int(v) for k, v in read.items() if v}}


def bag_data_from_simulation(result: Any) -> BagData:
    """The :class:`BagData` a bag written from a simulation result would read as.

    For Monte-Carlo benchmarks and tests that do not need to exercise the MCAP layer
    (:func:`read_bag_data` of the written bag gives the same arrays).
    """
    imu = result.imu
    stamps = np.asarray(imu.stamp_ns, dtype=np.int64)
    t0_ns, nominal_dt = time_origin(stamps)
    nav = result.navsat
    est = SiteEstimator(max_fixes=len(nav.stamp_ns) + 1)
    if len(nav.stamp_ns):
        status = getattr(nav, "status", None)
        est.add_many(nav.stamp_ns, nav.latitude_deg, nav.longitude_deg, nav.altitude_m,
                     np.zeros(len(nav.stamp_ns), int) if status is None else status)
    return BagData(
        t0_ns=t0_ns, imu_t=(stamps - t0_ns) * 1e-9,
        imu_w=np.asarray(imu.angular_velocity, dtype=float),
        imu_f=np.asarray(imu.linear_acceleration, dtype=float),
        frames=list(result.star_frames), site=est.site,
        head_temperature=result.head_temperature, air_temperature=result.air_temperature,
        pressure=result.pressure, nominal_dt=nominal_dt)
