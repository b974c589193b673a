"""Star image files: 8-bit JPEG/PNG, 16-bit PNG/TIFF (Pillow) and FITS (fitsio).

A colour image becomes grey (ITU-R 601 luma for 8-bit; 16-bit colour is refused with a
one-line error).  The image's own time is read when the file has one: FITS ``DATE-OBS``
(UTC, ISO 8601; mid-exposure = start + ``EXPTIME``/2), EXIF ``DateTimeOriginal`` with its
``OffsetTimeOriginal`` (an EXIF time without an offset is local time of unknown zone and is
not used).  The exposure time comes from FITS ``EXPTIME`` / ``EXPOSURE`` or EXIF
``ExposureTime``.
"""

from __future__ import annotations

import datetime as dt
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stellar_cal_ros.errors import StellarCalError

__all__ = ["StarImage", "parse_utc", "read_image"]

FITS_SUFFIXES = (".fits", ".fit", ".fts", ".fits.gz", ".fit.gz")


@dataclass
class StarImage:
    """A grey star image and what its file says about it."""

    pixels: np.ndarray  #: (height, width) uint8 / uint16 / float
    path: str
    time_posix: float | None = None  #: mid-exposure, POSIX s (None: the file has no time)
    exposure_s: float = 0.0  #: 0 if unknown

    @property
    def width(self) -> int:
        """Columns."""
        return int(self.pixels.shape[1])

    @property
    def height(self) -> int:
        """Rows."""
        return int(self.pixels.shape[0])


def parse_utc(text: str) -> float:
    """POSIX seconds of an ISO 8601 time (UTC unless it carries an offset)."""
    s = str(text).strip().replace(" ", "T")
    if s.endswith("Z"):
        s = s[:-1] + "+00:00"
    try:
        t = dt.datetime.fromisoformat(s)
    except ValueError:
        raise StellarCalError(f"not an ISO 8601 time: {text!r}") from None
    if t.tzinfo is None:
        t = t.replace(tzinfo=dt.UTC)
    return t.timestamp()


def read_image(path: str | Path) -> StarImage:
    """Read a star image (see the module docstring); one-line errors for what cannot be read."""
    p = Path(path)
    if not p.is_file():
        raise StellarCalError(f"{p}: no such image file")
    if p.name.lower().endswith(FITS_SUFFIXES):
        return _read_fits(p)
    try:
        from PIL import Image, UnidentifiedImageError
    except ImportError as exc:  # pragma: no cover - Pillow comes with matplotlib
        raise StellarCalError(f"reading {p} needs Pillow: {exc}") from exc
    try:
        im = Image.open(p)
        im.load()
    except (UnidentifiedImageError, OSError) as exc:
        raise StellarCalError(f"{p}: cannot read the image ({exc})") from None
    mode = im.mode
    if mode in ("L", "P", "RGB", "RGBA", "LA", "CMYK", "YCbCr", "1"):
        pixels = np.asarray(im.convert("L"))
    elif mode in ("I;16", "I;16B", "I;16L", "I;16N"):
        pixels = np.asarray(im).astype(np.uint16)
    elif mode in ("I", "F"):
        arr = np.asarray(im)
        pixels = arr.astype(np.uint16) if mode == "I" and arr.min() >= 0 and \
            arr.max() <= 65535 else arr.astype(np.float32)
    else:
        raise StellarCalError(f"{p}: image mode {mode} is not supported (use a grey 8- or "
                              "16-bit image)")
    time_posix, exposure = _exif_time(im)
    return StarImage(pixels, str(p), time_posix, exposure)


def _exif_time(im) -> tuple[float | None, float]:
    try:
        exif = im.getexif()
        sub = exif.get_ifd(0x8769)  # Exif IFD
    except Exception:  # noqa: BLE001 - images without (valid) EXIF
        return None, 0.0
    exposure = 0.0
    if 0x829A in sub:  # ExposureTime
        try:
            exposure = float(sub[0x829A])
        except (TypeError, ValueError, ZeroDivisionError):
            exposure = 0.0
    original, offset = sub.get(0x9003), sub.get(0x9011)  # DateTimeOriginal, OffsetTimeOriginal
    if not original or not offset:
        return None, exposure
    try:
        t = dt.datetime.strptime(str(original).strip(), "%Y:%m:%d %H:%M:%S")
        t = dt.datetime.fromisoformat(t.isoformat() + str(offset).strip())
    except ValueError:
        return None, exposure
    return t.timestamp() + exposure / 2.0, exposure


def _read_fits(p: Path) -> StarImage:
    try:
        import fitsio
    except ImportError as exc:  # pragma: no cover - pinned in requirements.txt
        raise StellarCalError(f"reading FITS needs fitsio (pip install fitsio==1.4.2): "
                              f"{exc}") from exc
    try:
        data, header = fitsio.read(str(p), header=True)
    except (OSError, ValueError) as exc:
        raise StellarCalError(f"{p}: cannot read FITS ({exc})") from None
    data = np.asarray(data)
    if data.ndim == 3 and 1 in data.shape:
        data = data.reshape([d for d in data.shape if d != 1])
    if data.ndim != 2:
        raise StellarCalError(f"{p}: FITS image of shape {data.shape} is not one grey frame")
    if data.dtype.kind in "iu" and data.min() >= 0 and data.max() <= 65535:
        pixels = data.astype(np.uint16)
    else:
        pixels = data.astype(np.float32)
    exposure = 0.0
    for key in ("EXPTIME", "EXPOSURE"):
        if key in header:
            try:
                exposure = float(header[key])
            except (TypeError, ValueError):
                pass
            break
    t = None
    if "DATE-OBS" in header:
        t = parse_utc(str(header["DATE-OBS"])) + exposure / 2.0
    if t is not None and not math.isfinite(t):
        t = None
    return StarImage(pixels, str(p), t, exposure)
