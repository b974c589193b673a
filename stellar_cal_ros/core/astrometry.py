"""Apparent star directions as a star tracker at a site sees them, in GCRS (inertial) axes.

Chain (:func:`apparent_directions`)::

    ICRS mean place at J2000.0 (the tracker message, :meth:`StarCatalog.message_radec`)
      -> proper motion to the date                     (:func:`proper_motion`, erfa.pmsafe)
      -> [annual parallax, optional, default off]      (:func:`parallax`)
      -> [light deflection by the Sun, optional, off]  (:func:`light_deflection`, erfa.ldsun)
      -> aberration, annual + diurnal                  (:func:`aberration`, erfa.ab)
      -> refraction, optional                          (:func:`refraction`, erfa.refco)

Every step takes a ``scale`` (1 = physical, 0 = off, other values scale the effect linearly;
the effects library uses this). Directions are unit vectors, shape (..., 3); a single POSIX
time ``t`` (float) is the usual case (one exposure), arrays of ``t`` broadcasting against
``u[..., 0]`` are accepted.

"GCRS direction" here means the *proper* direction of the incoming light for an observer at
the site moving with the site's barycentric velocity, expressed in GCRS (= ICRS) axes, i.e.
the vector that ERFA's ``atciq`` produces before the bias-precession-nutation rotation to
CIRS. Rotated by :func:`stellar_cal_ros.core.earth.R_itrs_gcrs` into the local ENU frame it
equals ``erfa.atco13``'s observed place (see ``test/test_earth_astrometry.py``: < 0.1 mas
with all steps on).

Neglected by default (both are available as optional steps):

* Light deflection by the Sun: 1.75" at the limb but ``4 mas * cot(theta/2)`` at elongation
  theta, i.e. < 4 mas for theta > 90 deg (a night sky above 20 deg elevation is mostly there)
  and < 10 mas for theta > 45 deg.
* Annual parallax: < 2 mas for half of the Hp < 6 stars, but NOT negligible for the nearby
  bright ones: 2104 of the 4559 stars have parallax > 10 mas, 45 > 100 mas (Sirius 379 mas,
  61 Cyg 287 mas, Procyon 285 mas), displacement up to ``parallax * sin(angle to the Sun)``.
  The reference bags (``psce_sky``) do not include it, so it stays off by default.
* Radial velocity (perspective acceleration), see :meth:`StarCatalog.propagate`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import erfa
import numpy as np
from numpy.typing import ArrayLike, NDArray

from .catalog import J2000_JYEAR, StarCatalog, posix_to_jyear, radec_to_unit
from .earth import (
    SPEED_OF_LIGHT,
    R_itrs_enu,
    R_itrs_gcrs,
    Site,
    posix_to_erfa,
    site_position_gcrs,
    site_velocity_gcrs,
)

__all__ = [
    "AU",
    "aberration",
    "annual_aberration",
    "apparent_directions",
    "azimuth_deg",
    "diurnal_aberration",
    "earth_barycentric",
    "elevation_deg",
    "enu_to_gcrs",
    "gcrs_to_enu",
    "light_deflection",
    "parallax",
    "proper_motion",
    "refraction",
    "refraction_constants",
]

#: Astronomical unit, m.
AU: float = 149597870700.0
_SELMIN = 0.05  # minimum sin(elevation) used by the refraction model (as erfa.atioq)
_CELMIN = 1e-6  # minimum cos(elevation)


def _normalise(u: NDArray[np.float64]) -> NDArray[np.float64]:
    return u / np.linalg.norm(u, axis=-1, keepdims=True)


def earth_barycentric(
    t: ArrayLike,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Return the Earth's barycentric position, velocity and heliocentric position.

    Parameters
    ----------
    t : array_like, shape (...)
        POSIX time, s.

    Returns
    -------
    pb : ndarray, shape (..., 3)
        Barycentric position of the geocentre, au, BCRS (ICRS axes).
    vb : ndarray, shape (..., 3)
        Barycentric velocity of the geocentre, m/s.
    ph : ndarray, shape (..., 3)
        Heliocentric position of the geocentre, au.

    Notes
    -----
    ``erfa.epv00`` at TT (TDB - TT < 2 ms neglected); accuracy about 5 km and 5 mm/s
    (0.003 mas of aberration).
    """
    t = np.asarray(t, dtype=np.float64)
    tu, inv = np.unique(t.ravel(), return_inverse=True)  # frames share one stamp
    _, (tt1, tt2) = posix_to_erfa(tu)
    pvh, pvb = erfa.epv00(tt1, tt2)
    shape = t.shape + (3,)
    return (
        np.asarray(pvb["p"])[inv].reshape(shape),
        (np.asarray(pvb["v"]) * (AU / 86400.0))[inv].reshape(shape),
        np.asarray(pvh["p"])[inv].reshape(shape),
    )


# --- geometry helpers -----------------------------------------------------------------------
def gcrs_to_enu(u: ArrayLike, t: ArrayLike, site: Site, dut1: float = 0.0) -> NDArray[np.float64]:
    """Rotate GCRS vectors into the local ENU frame: ``R_itrs_enu^T R_itrs_gcrs(t) u``.

    Parameters
    ----------
    u : array_like, shape (..., 3)
        Vectors, GCRS axes.
    t : array_like, shape broadcastable to ``u[..., 0]``
        POSIX time, s.
    site : Site
        Observer / IMU site (WGS84).
    dut1 : float, optional
        UT1 - UTC, s.

    Returns
    -------
    ndarray, shape (..., 3)
    """
    R = np.swapaxes(R_itrs_enu(site), -1, -2) @ R_itrs_gcrs(t, dut1)
    return np.einsum("...ij,...j->...i", R, np.asarray(u, dtype=np.float64))


def enu_to_gcrs(u: ArrayLike, t: ArrayLike, site: Site, dut1: float = 0.0) -> NDArray[np.float64]:
    """Inverse of :func:`gcrs_to_enu`; shapes as there."""
    R = np.swapaxes(R_itrs_gcrs(t, dut1), -1, -2) @ R_itrs_enu(site)
    return np.einsum("...ij,...j->...i", R, np.asarray(u, dtype=np.float64))


def elevation_deg(u: ArrayLike, t: ArrayLike, site: Site, dut1: float = 0.0) -> NDArray[np.float64]:
    """Return the elevation above the geodetic horizon of GCRS directions, degrees, (...)."""
    e = gcrs_to_enu(u, t, site, dut1)
    return np.degrees(np.arctan2(e[..., 2], np.hypot(e[..., 0], e[..., 1])))


def azimuth_deg(u: ArrayLike, t: ArrayLike, site: Site, dut1: float = 0.0) -> NDArray[np.float64]:
    """Return the azimuth (N = 0, E = 90) of GCRS directions, degrees in [0, 360), (...)."""
    e = gcrs_to_enu(u, t, site, dut1)
    return np.mod(np.degrees(np.arctan2(e[..., 0], e[..., 1])), 360.0)


# --- steps ----------------------------------------------------------------------------------
def proper_motion(
    stars: StarCatalog | tuple[ArrayLike, ...], t: ArrayLike, scale: float = 1.0
) -> NDArray[np.float64]:
    """Return ICRS directions with proper motion applied from J2000.0 to the date.

    Parameters
    ----------
    stars : StarCatalog or tuple
        A catalogue, or ``(ra, dec, pm_ra_cosdec, pm_dec[, parallax])`` at epoch J2000.0
        (rad, rad/yr, rad; arrays of shape (n,)). ``(ra, dec)`` alone carries no motion: the
        J2000.0 place is returned.
    t : float
        POSIX time of the observation, s.
    scale : float, optional
        The epoch used is ``2000 + scale * (epoch_of_date - 2000)``; 0 returns the J2000.0
        place (what the tracker message carries), 1 the physical place of date.

    Returns
    -------
    ndarray, shape (n, 3)
        Unit vectors, ICRS. Rigorous space motion (``erfa.pmsafe``, rv = 0).
    """
    epoch = J2000_JYEAR + float(scale) * (float(posix_to_jyear(t)) - J2000_JYEAR)
    if isinstance(stars, StarCatalog):
        return stars.directions(epoch)
    ra, dec = np.asarray(stars[0], dtype=np.float64), np.asarray(stars[1], dtype=np.float64)
    if len(stars) < 4 or scale == 0.0:
        return radec_to_unit(ra, dec)
    plx = np.asarray(stars[4], dtype=np.float64) if len(stars) > 4 else np.zeros_like(ra)
    cat = StarCatalog(
        hip=np.zeros(ra.shape, dtype=np.int64),
        ra=ra,
        dec=dec,
        pm_ra_cosdec=np.asarray(stars[2], dtype=np.float64) * np.ones_like(ra),
        pm_dec=np.asarray(stars[3], dtype=np.float64) * np.ones_like(ra),
        parallax=plx * np.ones_like(ra),
        magnitude=np.zeros_like(ra),
        epoch_jyear=J2000_JYEAR,
    )
    return cat.directions(epoch)


def parallax(
    u: ArrayLike,
    t: ArrayLike,
    parallax_rad: ArrayLike,
    site: Site | None = None,
    scale: float = 1.0,
    dut1: float = 0.0,
) -> NDArray[np.float64]:
    """Apply annual (and, with a site, geocentric) parallax.

    Parameters
    ----------
    u : array_like, shape (..., 3)
        Barycentric unit directions.
    t : array_like
        POSIX time, s.
    parallax_rad : array_like, shape (...)
        rad (negative values are clipped to 0).
    site : Site or None, optional
        Observer at the site (adds the < 2e-5 mas diurnal parallax); None: geocentre.
    scale : float, optional
        Multiplies the parallax.
    dut1 : float, optional
        UT1 - UTC, s.

    Returns
    -------
    ndarray, shape (..., 3)
        ``normalise(u - scale * parallax * p_obs[au])`` (as ``erfa.pmpx``).
    """
    pb, _, _ = earth_barycentric(t)
    if site is not None:
        pb = pb + site_position_gcrs(site, t, dut1) / AU
    w = scale * np.clip(np.asarray(parallax_rad, dtype=np.float64), 0.0, None)[..., None]
    return _normalise(np.asarray(u, dtype=np.float64) - w * pb)


def light_deflection(u: ArrayLike, t: ArrayLike, scale: float = 1.0) -> NDArray[np.float64]:
    """Apply the gravitational deflection of light by the Sun (``erfa.ldsun``).

    Parameters
    ----------
    u : array_like, shape (..., 3)
        Directions (unit vectors, BCRS).
    t : array_like
        POSIX time, s.
    scale : float, optional
        Multiplies the deflection.

    Returns
    -------
    ndarray, shape (..., 3)
        ``normalise(u + scale * (ldsun(u, e, |E|) - u))`` with ``e`` the unit heliocentric
        position of the geocentre. Size ``4 mas * cot(theta/2)``, theta = elongation.
    """
    u = np.asarray(u, dtype=np.float64)
    _, _, ph = earth_barycentric(t)
    em = np.linalg.norm(ph, axis=-1)
    e = ph / em[..., None]
    p1 = np.asarray(erfa.ldsun(u, e, em))
    return _normalise(u + scale * (p1 - u))


def _observer_velocity(
    t: ArrayLike, site: Site | None, annual: float, diurnal: float, dut1: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Return (observer BCRS velocity in m/s scaled, Sun-observer distance au)."""
    _, vb, ph = earth_barycentric(t)
    v = annual * vb
    if site is not None and diurnal != 0.0:
        v = v + diurnal * site_velocity_gcrs(site, t, dut1)
    return v, np.linalg.norm(ph, axis=-1)


def _ab(u: ArrayLike, v_mps: NDArray[np.float64], s_au: NDArray[np.float64]):
    """Relativistic aberration ``erfa.ab`` with velocity v (m/s)."""
    u = np.asarray(u, dtype=np.float64)
    vc = v_mps / SPEED_OF_LIGHT
    bm1 = np.sqrt(1.0 - np.sum(vc * vc, axis=-1))
    return np.asarray(erfa.ab(u, vc, s_au, bm1))


def aberration(
    u: ArrayLike,
    t: ArrayLike,
    site: Site | None = None,
    scale: float = 1.0,
    *,
    annual: bool = True,
    diurnal: bool = True,
    dut1: float = 0.0,
) -> NDArray[np.float64]:
    """Apply stellar aberration for the observer's total barycentric velocity.

    Parameters
    ----------
    u : array_like, shape (..., 3)
        Natural (catalogue/astrometric) unit directions, ICRS axes.
    t : array_like
        POSIX time, s.
    site : Site or None, optional
        Observer site; None (or ``diurnal=False``): geocentric observer.
    scale : float, optional
        Multiplies the velocity (0 = off, 1 = physical).
    annual, diurnal : bool, keyword-only
        Include the Earth's barycentric velocity (``erfa.epv00``, <= 30.3 km/s, <= 20.9")
        and the site's rotation velocity (:func:`site_velocity_gcrs`, 465 cos(lat) m/s,
        <= 0.32").
    dut1 : float, keyword-only
        UT1 - UTC, s.

    Returns
    -------
    ndarray, shape (..., 3)
        Proper direction in GCRS axes. Relativistic formula ``erfa.ab`` (Expl. Suppl. 2013
        eq. 7.40, with ``v = v_earth + v_site`` (Galilean sum, error ~(v/c)^2 * v_site/c,
        negligible): ``p = (bm1 u + (1 + u.v/(1+bm1)) v) / (1 + u.v)``, normalised.
    """
    if scale == 0.0 or not (annual or diurnal):
        return np.array(u, dtype=np.float64, copy=True)
    v, s = _observer_velocity(t, site, float(annual), float(diurnal), dut1)
    return _ab(u, scale * v, s)


def annual_aberration(u: ArrayLike, t: ArrayLike, scale: float = 1.0) -> NDArray[np.float64]:
    """Aberration by the Earth's barycentric velocity only; see :func:`aberration`."""
    return aberration(u, t, None, scale, annual=True, diurnal=False)


def diurnal_aberration(
    u: ArrayLike, t: ArrayLike, site: Site, scale: float = 1.0, dut1: float = 0.0
) -> NDArray[np.float64]:
    """Aberration by the site's rotation velocity only (<= 0.32"); see :func:`aberration`."""
    return aberration(u, t, site, scale, annual=False, diurnal=True, dut1=dut1)


def refraction_constants(
    pressure_hpa: ArrayLike,
    temperature_c: ArrayLike,
    humidity: ArrayLike = 0.5,
    wavelength_um: ArrayLike = 0.55,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Return ``(A, B)`` of ``dZ = A tan z + B tan^3 z``, rad (``erfa.refco``).

    Parameters
    ----------
    pressure_hpa : array_like
        Air pressure at the observer, hPa.
    temperature_c : array_like
        Air temperature, deg C.
    humidity : array_like, optional
        Relative humidity, 0-1.
    wavelength_um : array_like, optional
        Effective wavelength, um (> 100 um selects the radio formula in ERFA).

    Returns
    -------
    A, B : ndarray
        rad, broadcast shape of the inputs (0-d for scalars).
    """
    a, b = erfa.refco(pressure_hpa, temperature_c, humidity, wavelength_um)
    return np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)


def refraction(
    u_gcrs: ArrayLike,
    t: ArrayLike,
    site: Site,
    pressure_hpa: ArrayLike,
    temperature_c: ArrayLike,
    humidity: ArrayLike = 0.5,
    wavelength_um: ArrayLike = 0.55,
    scale: float = 1.0,
    dut1: float = 0.0,
) -> NDArray[np.float64]:
    """Apply atmospheric refraction, raising directions toward the zenith.

    Parameters
    ----------
    u_gcrs : array_like, shape (..., 3)
        Topocentric unrefracted unit directions, GCRS axes.
    t : array_like
        POSIX time, s.
    site : Site
        Observer / IMU site (WGS84).
    pressure_hpa, temperature_c, humidity, wavelength_um : array_like
        See :func:`refraction_constants`; scalars or arrays broadcasting against ``u[..., 0]``
        (e.g. the air temperature at each star's exposure time).
    scale : float, optional
        Multiplies the refraction angle.
    dut1 : float, optional
        UT1 - UTC, s.

    Returns
    -------
    ndarray, shape (..., 3)
        Observed (refracted) unit directions, GCRS axes.

    Notes
    -----
    In ENU (``R_itrs_enu^T R_itrs_gcrs(t)``), with ``r = cos(el)``, ``z = sin(el)`` of the
    unrefracted direction (clamped at ``z >= 0.05``, ``r >= 1e-6``, as ``erfa.atioq``) and
    ``tz = r/z``, the refraction ``del = (A + B tz^2) tz / (1 + (A + 3 B tz^2) / z^2)`` (one
    Newton step inverting ``dZ = A tan z_obs + B tan^3 z_obs``) rotates the vector up in its
    vertical plane: ``(e, n) *= cos(del) - del z / r``, ``u_up = cos(del) z + del r``.
    About 59" at 45 deg elevation for 1012 hPa, 5 deg C. Valid above ~15 deg elevation.
    """
    a, b = refraction_constants(pressure_hpa, temperature_c, humidity, wavelength_um)
    R_enu_gcrs = np.swapaxes(R_itrs_enu(site), -1, -2) @ R_itrs_gcrs(t, dut1)
    e = np.einsum("...ij,...j->...i", R_enu_gcrs, np.asarray(u_gcrs, dtype=np.float64))
    r = np.maximum(np.hypot(e[..., 0], e[..., 1]), _CELMIN)
    z = np.maximum(e[..., 2], _SELMIN)
    tz = r / z
    w = b * tz * tz
    dl = scale * (a + w) * tz / (1.0 + (a + 3.0 * w) / (z * z))
    cosdel = 1.0 - 0.5 * dl * dl
    f = cosdel - dl * z / r
    eo = np.stack([e[..., 0] * f, e[..., 1] * f, cosdel * e[..., 2] + dl * r], axis=-1)
    return _normalise(np.einsum("...ji,...j->...i", R_enu_gcrs, eo))


# aliases: apparent_directions' keyword arguments shadow the step functions' names
_pm_step = proper_motion
_px_step = parallax
_ld_step = light_deflection
_ab_step = aberration
_refr_step = refraction


def _scale_of(x: bool | float | None) -> float:
    if x is None or x is False:
        return 0.0
    if x is True:
        return 1.0
    return float(x)


def apparent_directions(
    catalog_or_radec_pm: StarCatalog | tuple[ArrayLike, ...],
    t: float,
    site: Site,
    *,
    proper_motion: bool | float = True,
    aberration: bool | float = True,
    refraction: Mapping[str, Any] | None = None,
    parallax: bool | float = False,
    light_deflection: bool | float = False,
    dut1: float = 0.0,
) -> NDArray[np.float64]:
    """Return the star directions a tracker at ``site`` sees at POSIX time ``t``, GCRS axes.

    Parameters
    ----------
    catalog_or_radec_pm : StarCatalog or tuple
        Catalogue, or ``(ra, dec[, pm_ra_cosdec, pm_dec[, parallax]])`` at J2000.0 (message
        convention: rad, rad/yr, rad), arrays of shape (n,).
    t : float
        POSIX time (true mid-exposure), s.
    site : Site
        Observer / IMU site (WGS84).
    proper_motion, aberration, parallax, light_deflection : bool or float, keyword-only
        Scale of each step (True = 1, False = 0). Parallax needs a catalogue or a 5-tuple.
    refraction : mapping or None, keyword-only
        None: no refraction. Else keys ``pressure_hpa``, ``temperature_c`` and optional
        ``humidity`` (0.5), ``wavelength_um`` (0.55), ``scale`` (1.0).
    dut1 : float, keyword-only
        UT1 - UTC, s.

    Returns
    -------
    ndarray, shape (n, 3)
        Unit vectors, GCRS axes.

    Notes
    -----
    Sequence: J2000.0 place -> :func:`proper_motion` -> :func:`parallax` ->
    :func:`light_deflection` -> :func:`aberration` (annual + diurnal, ``erfa.ab``) ->
    :func:`refraction`. With every step at scale 1 this reproduces ``erfa.atco13``.
    """
    stars = catalog_or_radec_pm
    u = _pm_step(stars, t, _scale_of(proper_motion))
    s_px = _scale_of(parallax)
    if s_px != 0.0:
        if isinstance(stars, StarCatalog):
            plx = stars.parallax
        elif len(stars) > 4:
            plx = np.asarray(stars[4], dtype=np.float64)
        else:
            plx = np.zeros(u.shape[:-1])
        u = _px_step(u, t, plx, site, s_px, dut1)
    s_ld = _scale_of(light_deflection)
    if s_ld != 0.0:
        u = _ld_step(u, t, s_ld)
    s_ab = _scale_of(aberration)
    if s_ab != 0.0:
        u = _ab_step(u, t, site, s_ab, dut1=dut1)
    if refraction is not None:
        cfg = dict(refraction)
        u = _refr_step(
            u,
            t,
            site,
            cfg["pressure_hpa"],
            cfg["temperature_c"],
            cfg.get("humidity", 0.5),
            cfg.get("wavelength_um", 0.55),
            float(cfg.get("scale", 1.0)),
            dut1,
        )
    return u
