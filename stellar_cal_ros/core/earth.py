"""Earth orientation, site kinematics and normal gravity (numpy + pyerfa).

Frames
------
``gcrs``
    Geocentric Celestial Reference System: geocentric, axes parallel to ICRS, kinematically
    non-rotating. This is the project's inertial frame ``i`` (``doc/interfaces.md``).
``itrs``
    International Terrestrial Reference System (Earth fixed, WGS84 realisation).
``enu``
    Local geodetic East-North-Up frame at a :class:`Site` (axes along the WGS84 ellipsoid
    normal, not the astronomical vertical).

Conventions: ``R_a_b`` maps b-frame vectors to the a-frame, ``v_a = R_a_b @ v_b``; stacked
matrices have shape ``(..., 3, 3)``. Time ``t`` is POSIX seconds (UTC, as ROS time),
float64 or arrays of float64.

Time scales
-----------
POSIX time counts 86400 s per UTC day and has no representation of a leap second; it is
mapped to a UTC calendar date/time and converted with ``erfa.dtf2d`` (UTC) then
``erfa.utctai`` and ``erfa.taitt``. TDB is taken equal to TT (difference < 2 ms, i.e.
< 0.06 mas of aberration and negligible for Earth orientation).
"""

from __future__ import annotations

from dataclasses import dataclass

import erfa
import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "EARTH_ROTATION_RATE",
    "ERA_RATE",
    "POSIX_EPOCH_JD",
    "SPEED_OF_LIGHT",
    "WGS84_A",
    "WGS84_B",
    "WGS84_E2",
    "WGS84_F",
    "WGS84_GAMMA_E",
    "WGS84_GM",
    "WGS84_K",
    "Site",
    "R_itrs_enu",
    "R_itrs_gcrs",
    "earth_rotation_itrs",
    "gravitation_gcrs",
    "gravitation_itrs",
    "gravity_itrs",
    "normal_gravity",
    "posix_to_erfa",
    "site_acceleration_gcrs",
    "site_itrs",
    "site_position_gcrs",
    "site_velocity_gcrs",
    "up_itrs",
]

# --- constants -----------------------------------------------------------------------------
#: WGS84 nominal mean angular velocity of the Earth, rad/s (used by the normal-gravity model).
EARTH_ROTATION_RATE: float = 7.292115e-5
#: Rate of the Earth Rotation Angle (IAU 2000), rad per UT1 second:
#: ``2 pi * 1.00273781191135448 / 86400`` (the derivative of ``erfa.era00``).
ERA_RATE: float = 2.0 * np.pi * 1.00273781191135448 / 86400.0
#: WGS84 semi-major axis, m.
WGS84_A: float = 6378137.0
#: WGS84 flattening.
WGS84_F: float = 1.0 / 298.257223563
#: WGS84 semi-minor axis, m.
WGS84_B: float = WGS84_A * (1.0 - WGS84_F)
#: WGS84 first eccentricity squared.
WGS84_E2: float = WGS84_F * (2.0 - WGS84_F)
#: WGS84 geocentric gravitational constant (with atmosphere), m^3/s^2.
WGS84_GM: float = 3.986004418e14
#: WGS84 normal gravity at the equator, m/s^2.
WGS84_GAMMA_E: float = 9.7803253359
#: WGS84 Somigliana constant ``k = (b gamma_p) / (a gamma_e) - 1``.
WGS84_K: float = 0.00193185265241
#: Speed of light, m/s.
SPEED_OF_LIGHT: float = 299792458.0
#: Julian date (UTC) of the POSIX epoch 1970-01-01T00:00:00.
POSIX_EPOCH_JD: float = 2440587.5

_DAY = 86400.0


@dataclass(frozen=True)
class Site:
    """A point on the Earth given by WGS84 geodetic coordinates.

    Attributes
    ----------
    latitude_deg : float
        Geodetic latitude, degrees, north positive.
    longitude_deg : float
        Longitude, degrees, east positive.
    height_m : float
        Height above the WGS84 ellipsoid, m.
    """

    latitude_deg: float
    longitude_deg: float
    height_m: float

    @property
    def latitude_rad(self) -> float:
        """Geodetic latitude, rad."""
        return float(np.radians(self.latitude_deg))

    @property
    def longitude_rad(self) -> float:
        """Longitude (east positive), rad."""
        return float(np.radians(self.longitude_deg))


# --- time -----------------------------------------------------------------------------------
_JD = tuple[NDArray[np.float64], NDArray[np.float64]]


def posix_to_erfa(t: ArrayLike) -> tuple[_JD, _JD]:
    """Convert POSIX seconds to two-part Julian dates in UTC and TT.

    Parameters
    ----------
    t : array_like, shape (...)
        POSIX time, s (UTC without leap seconds, as ROS ``header.stamp``).

    Returns
    -------
    utc : tuple of ndarray, each shape (...)
        ``(utc1, utc2)``: ERFA quasi-JD UTC (``utc1`` = JD of the preceding 0h, ``utc2`` =
        fraction of day), from ``erfa.dtf2d("UTC", ...)``.
    tt : tuple of ndarray, each shape (...)
        ``(tt1, tt2)``: TT two-part JD via ``erfa.utctai`` then ``erfa.taitt``.

    Notes
    -----
    ``days = floor(t / 86400)``, the calendar date of ``2440587.5 + days`` comes from
    ``erfa.jd2cal`` and the time of day ``t - 86400 days`` is split into h, m, s for
    ``erfa.dtf2d`` (which handles the 86401-s length of a leap-second day; the leap second
    itself has no POSIX representation). Precision is that of float64 POSIX seconds
    (about 0.24 us in 2026).
    """
    t = np.asarray(t, dtype=np.float64)
    days = np.floor(t / _DAY)
    sod = t - days * _DAY
    iy, im, iday, _ = erfa.jd2cal(POSIX_EPOCH_JD, days)
    hour = np.floor(sod / 3600.0)
    minute = np.floor((sod - 3600.0 * hour) / 60.0)
    sec = sod - 3600.0 * hour - 60.0 * minute
    utc1, utc2 = erfa.dtf2d("UTC", iy, im, iday, hour.astype(int), minute.astype(int), sec)
    tai1, tai2 = erfa.utctai(utc1, utc2)
    tt1, tt2 = erfa.taitt(tai1, tai2)
    return (np.asarray(utc1), np.asarray(utc2)), (np.asarray(tt1), np.asarray(tt2))


def _ut1(utc1: NDArray[np.float64], utc2: NDArray[np.float64], dut1: float):
    """Return UT1 two-part JD from UTC (``erfa.utcut1``)."""
    return erfa.utcut1(utc1, utc2, dut1)


def _rot3(theta: NDArray[np.float64]) -> NDArray[np.float64]:
    """Return SOFA ``R3(theta)`` (frame rotation about z), shape ``theta.shape + (3, 3)``."""
    c, s = np.cos(theta), np.sin(theta)
    out = np.zeros(np.shape(theta) + (3, 3))
    out[..., 0, 0] = c
    out[..., 0, 1] = s
    out[..., 1, 0] = -s
    out[..., 1, 1] = c
    out[..., 2, 2] = 1.0
    return out


def _orthonormalise(R: NDArray[np.float64]) -> NDArray[np.float64]:
    """One Newton step of the polar decomposition, ``1.5 R - 0.5 R R^T R``."""
    return 1.5 * R - 0.5 * R @ np.swapaxes(R, -1, -2) @ R


def _c2i(tt1: NDArray[np.float64], tt2: NDArray[np.float64], pn_step_s: float | None):
    """Return the GCRS->CIRS matrix (``erfa.c2i06a``), optionally interpolated on a grid.

    ``pn_step_s``: if given and the grid is coarser than the request, ``c2i06a`` is evaluated
    every ``pn_step_s`` seconds of TT and interpolated linearly element-wise, then
    re-orthonormalised. The curvature error of linear interpolation (dominated by the 0.2"
    fortnightly nutation) is 9e-13 rad for 600 s nodes and 2.5e-11 rad for 3600 s nodes.
    """
    tt1 = np.asarray(tt1, dtype=np.float64)
    tt2 = np.asarray(tt2, dtype=np.float64)
    if pn_step_s is None or tt1.size <= 4:
        return np.asarray(erfa.c2i06a(tt1, tt2))
    ref = float(np.ravel(tt1)[0])
    x = ((tt1 - ref) + tt2).ravel() * _DAY  # s of TT since ref JD
    lo = np.floor(x.min() / pn_step_s)
    hi = np.ceil(x.max() / pn_step_s)
    nodes = np.arange(lo, hi + 1.0) * pn_step_s
    if nodes.size >= x.size:
        return np.asarray(erfa.c2i06a(tt1, tt2))
    nodes_jd2 = nodes / _DAY
    Rn = np.asarray(erfa.c2i06a(np.full(nodes.size, ref), nodes_jd2)).reshape(-1, 9)
    Ri = np.empty((x.size, 9))
    for j in range(9):
        Ri[:, j] = np.interp(x, nodes, Rn[:, j])
    return _orthonormalise(Ri.reshape(tt1.shape + (3, 3)))


def R_itrs_gcrs(
    t: ArrayLike,
    dut1: float = 0.0,
    xp: float = 0.0,
    yp: float = 0.0,
    *,
    pn_step_s: float | None = 600.0,
) -> NDArray[np.float64]:
    """Return the GCRS -> ITRS rotation, ``v_itrs = R @ v_gcrs`` (IAU 2006/2000A, CIO based).

    Parameters
    ----------
    t : array_like, shape (...)
        POSIX time, s.
    dut1 : float, optional
        UT1 - UTC, s. Default 0: |UT1 - UTC| < 0.9 s by definition, i.e. up to 13.5" of
        rotation about the CIP (about 0.42 km at the equator); it is a *pure rotation about
        the pole* and for a stationary system equivalent to a small azimuth error.
    xp, yp : float, optional
        Polar motion coordinates of the CIP, rad. Default 0: |xp|, |yp| < 0.6" (a tilt of the
        terrestrial frame, < 20 m on the ground).
    pn_step_s : float or None, keyword-only
        Evaluate the precession-nutation matrix ``erfa.c2i06a`` (about 25 us per call) every
        ``pn_step_s`` seconds and interpolate (interpolation error < 1e-12 rad for 600 s,
        2.5e-11 rad for 3600 s; 90 000 samples in 0.06 s). ``None``: every sample exactly.

    Returns
    -------
    ndarray, shape (..., 3, 3)
        ``R_itrs_gcrs = W(xp, yp, s') @ R3(ERA(UT1)) @ Q^T(TT)``, i.e. ``erfa.c2tcio`` of
        ``erfa.c2i06a``, ``erfa.era00`` and ``erfa.pom00(xp, yp, erfa.sp00)``; identical to
        ``erfa.c2t06a`` (check in the tests).
    """
    (utc1, utc2), (tt1, tt2) = posix_to_erfa(t)
    ut11, ut12 = _ut1(utc1, utc2, dut1)
    rc2i = _c2i(tt1, tt2, pn_step_s)
    era = np.asarray(erfa.era00(ut11, ut12))
    rpom = np.asarray(erfa.pom00(xp, yp, erfa.sp00(tt1, tt2)))
    return rpom @ _rot3(era) @ rc2i


def earth_rotation_itrs() -> NDArray[np.float64]:
    """Return the Earth's angular velocity w.r.t. the GCRS, expressed in ITRS, rad/s.

    Returns
    -------
    ndarray, shape (3,)
        ``ERA_RATE * e_z``. Neglected: polar motion (< 3e-6 rad of axis tilt), the rotation of
        the CIP by precession-nutation (|dQ/dt| < 1e-11 rad/s) and length-of-day variations
        (~1e-8 relative).
    """
    return np.array([0.0, 0.0, ERA_RATE])


# --- site geometry ------------------------------------------------------------------------
def site_itrs(site: Site) -> NDArray[np.float64]:
    """Return the ITRS (WGS84) Cartesian position of a site.

    Parameters
    ----------
    site : Site
        Observer / IMU site (WGS84).

    Returns
    -------
    ndarray, shape (3,)
        m, from ``erfa.gd2gc(erfa.WGS84, lon, lat, h)``.
    """
    return np.asarray(
        erfa.gd2gc(1, site.longitude_rad, site.latitude_rad, site.height_m), dtype=np.float64
    )


def R_itrs_enu(site: Site) -> NDArray[np.float64]:
    """Return the rotation from the local geodetic ENU frame to ITRS.

    Parameters
    ----------
    site : Site
        Observer / IMU site (WGS84).

    Returns
    -------
    ndarray, shape (3, 3)
        Columns are the East, North and Up unit vectors in ITRS (Up = WGS84 ellipsoid
        normal): ``e = (-sin l, cos l, 0)``, ``n = (-sin p cos l, -sin p sin l, cos p)``,
        ``u = (cos p cos l, cos p sin l, sin p)`` with p the geodetic latitude, l the longitude.
    """
    p, lam = site.latitude_rad, site.longitude_rad
    sp, cp, sl, cl = np.sin(p), np.cos(p), np.sin(lam), np.cos(lam)
    return np.array(
        [
            [-sl, -sp * cl, cp * cl],
            [cl, -sp * sl, cp * sl],
            [0.0, cp, sp],
        ]
    )


def up_itrs(site: Site) -> NDArray[np.float64]:
    """Return the ellipsoid-normal up unit vector in ITRS, shape (3,)."""
    return R_itrs_enu(site)[:, 2]


def _c2i_and_rate(
    tt1: NDArray[np.float64], tt2: NDArray[np.float64], pn_step_s: float | None, h_s: float = 600.0
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Return ``erfa.c2i06a`` and its time derivative (1/s, 600-s central difference).

    With ``pn_step_s`` both are evaluated on a grid of nodes and interpolated linearly (see
    :func:`_c2i`); the derivative is then accurate to ~1e-14 rad/s (1e-7 m/s at the surface).
    """
    tt1 = np.asarray(tt1, dtype=np.float64)
    tt2 = np.asarray(tt2, dtype=np.float64)
    h = h_s / _DAY

    def exact(a, b):
        Q = np.asarray(erfa.c2i06a(a, b))
        dQ = (np.asarray(erfa.c2i06a(a, b + h)) - np.asarray(erfa.c2i06a(a, b - h))) / (2 * h_s)
        return Q, dQ

    if pn_step_s is None or tt1.size <= 4:
        return exact(tt1, tt2)
    ref = float(np.ravel(tt1)[0])
    x = ((tt1 - ref) + tt2).ravel() * _DAY
    nodes = np.arange(np.floor(x.min() / pn_step_s), np.ceil(x.max() / pn_step_s) + 1.0)
    nodes *= pn_step_s
    if nodes.size >= x.size:
        return exact(tt1, tt2)
    Qn, dQn = exact(np.full(nodes.size, ref), nodes / _DAY)
    Qn, dQn = Qn.reshape(-1, 9), dQn.reshape(-1, 9)
    Qi = np.empty((x.size, 9))
    dQi = np.empty((x.size, 9))
    for j in range(9):
        Qi[:, j] = np.interp(x, nodes, Qn[:, j])
        dQi[:, j] = np.interp(x, nodes, dQn[:, j])
    shape = tt1.shape + (3, 3)
    return _orthonormalise(Qi.reshape(shape)), dQi.reshape(shape)


def site_position_gcrs(
    site: Site, t: ArrayLike, dut1: float = 0.0, *, pn_step_s: float | None = 600.0
) -> NDArray[np.float64]:
    """Return the site position in the GCRS, ``r_gcrs = R_itrs_gcrs(t)^T r_itrs``.

    Parameters
    ----------
    site : Site
        Observer / IMU site (WGS84).
    t : array_like, shape (...)
        POSIX time, s.
    dut1 : float, optional
        UT1 - UTC, s.
    pn_step_s : float or None, keyword-only
        See :func:`R_itrs_gcrs`.

    Returns
    -------
    ndarray, shape (..., 3)
        m.
    """
    R = R_itrs_gcrs(t, dut1, pn_step_s=pn_step_s)
    return np.einsum("...ji,j->...i", R, site_itrs(site))


def site_velocity_gcrs(
    site: Site, t: ArrayLike, dut1: float = 0.0, *, pn_step_s: float | None = 600.0
) -> NDArray[np.float64]:
    """Return the site velocity w.r.t. the GCRS, expressed in GCRS axes.

    Parameters
    ----------
    site : Site
        Observer / IMU site (WGS84).
    t : array_like, shape (...)
        POSIX time, s.
    dut1 : float, optional
        UT1 - UTC, s.
    pn_step_s : float or None, keyword-only
        Interpolation step of the precession-nutation matrix and its rate, see
        :func:`R_itrs_gcrs`.

    Returns
    -------
    ndarray, shape (..., 3)
        m/s. With ``R_gcrs_itrs = Q(TT) R3(-ERA)``:
        ``v = Q (omega e_z x (R3(-ERA) r)) + (dQ/dt) R3(-ERA) r`` where
        ``omega = ERA_RATE`` (exact derivative of ``erfa.era00``) and ``dQ/dt`` is a 600-s
        central difference of ``erfa.c2i06a`` (contributes ~5e-5 m/s). Accurate to < 1e-6 m/s
        apart from the neglected length-of-day excess (UT1 vs SI seconds, ~1e-8 relative, i.e.
        ~4e-6 m/s) and polar motion.
    """
    (utc1, utc2), (tt1, tt2) = posix_to_erfa(t)
    ut11, ut12 = _ut1(utc1, utc2, dut1)
    c2i, dc2i = _c2i_and_rate(tt1, tt2, pn_step_s)
    Q = np.swapaxes(c2i, -1, -2)  # CIRS -> GCRS
    dQ = np.swapaxes(dc2i, -1, -2)
    era = np.asarray(erfa.era00(ut11, ut12))
    r_cirs = np.einsum("...ij,j->...i", np.swapaxes(_rot3(era), -1, -2), site_itrs(site))
    v_cirs = np.cross(earth_rotation_itrs(), r_cirs)
    return np.einsum("...ij,...j->...i", Q, v_cirs) + np.einsum("...ij,...j->...i", dQ, r_cirs)


def site_acceleration_gcrs(site: Site, t: ArrayLike, dut1: float = 0.0) -> NDArray[np.float64]:
    """Return the site's inertial (centripetal) acceleration in the GCRS, m/s^2, shape (..., 3).

    ``a = omega x (omega x r)`` with ``omega = ERA_RATE e_z`` (precession-nutation terms
    < 1e-9 m/s^2 neglected).
    """
    R = R_itrs_gcrs(t, dut1)
    r = site_itrs(site)
    w = earth_rotation_itrs()
    a_itrs = np.cross(w, np.cross(w, r))
    return np.einsum("...ji,j->...i", R, a_itrs)


# --- gravity --------------------------------------------------------------------------------
def normal_gravity(site: Site) -> float:
    """Return the WGS84 normal gravity magnitude at a site, m/s^2.

    Parameters
    ----------
    site : Site
        Observer / IMU site (WGS84).

    Returns
    -------
    float
        Somigliana's closed formula on the ellipsoid
        ``g0 = g_e (1 + k sin^2 p) / sqrt(1 - e^2 sin^2 p)`` and the WGS84 (NIMA TR8350.2
        eq. 4-3) second-order free-air reduction
        ``g = g0 [1 - 2/a (1 + f + m - 2 f sin^2 p) h + 3 h^2 / a^2]``,
        ``m = omega^2 a^2 b / GM``. Gives 9.7982198789 m/s^2 at 36.07 N, 10 m.
    """
    s2 = np.sin(site.latitude_rad) ** 2
    g0 = WGS84_GAMMA_E * (1.0 + WGS84_K * s2) / np.sqrt(1.0 - WGS84_E2 * s2)
    m = EARTH_ROTATION_RATE**2 * WGS84_A**2 * WGS84_B / WGS84_GM
    h = site.height_m
    free_air = 2.0 / WGS84_A * (1.0 + WGS84_F + m - 2.0 * WGS84_F * s2) * h
    return float(g0 * (1.0 - free_air + 3.0 * h * h / WGS84_A**2))


def gravity_itrs(site: Site) -> NDArray[np.float64]:
    """Return the normal gravity vector (gravitation + centrifugal) in ITRS, m/s^2.

    Parameters
    ----------
    site : Site
        Observer / IMU site (WGS84).

    Returns
    -------
    ndarray, shape (3,)
        ``-normal_gravity(site) * up`` along the ellipsoid normal, pointing down (the tiny
        curvature of the normal plumb line with height, < 1e-4" at 10 km, and the deflection of
        the vertical of the real geoid, typically 1-30", are neglected).
    """
    return -normal_gravity(site) * up_itrs(site)


def gravitation_itrs(site: Site) -> NDArray[np.float64]:
    """Return the gravitation (mass attraction only) in ITRS, m/s^2.

    Parameters
    ----------
    site : Site
        Observer / IMU site (WGS84).

    Returns
    -------
    ndarray, shape (3,)
        ``G = g - a_cf`` with the centrifugal acceleration
        ``a_cf = -omega x (omega x r) = omega^2 (x, y, 0)``, ``omega = EARTH_ROTATION_RATE``.
        This is what an inertial-frame INS integrates: ``dv_i/dt = R_i_b f_b + G_i``
        (Zhang et al. eq. 9 with ``g^i`` the mass attraction).
    """
    r = site_itrs(site)
    w = np.array([0.0, 0.0, EARTH_ROTATION_RATE])
    a_cf = -np.cross(w, np.cross(w, r))
    return gravity_itrs(site) - a_cf


def gravitation_gcrs(
    site: Site, t: ArrayLike, dut1: float = 0.0, *, pn_step_s: float | None = 600.0
) -> NDArray[np.float64]:
    """Return the gravitation at a site in the GCRS (inertial) frame, m/s^2.

    Parameters
    ----------
    site : Site
        Observer / IMU site (WGS84).
    t : array_like, shape (N,) or scalar
        POSIX time, s.
    dut1 : float, optional
        UT1 - UTC, s.
    pn_step_s : float or None, keyword-only
        See :func:`R_itrs_gcrs`.

    Returns
    -------
    ndarray, shape (N, 3) (or (3,) for scalar t)
        ``R_itrs_gcrs(t)^T @ gravitation_itrs(site)``. Lunisolar tides (< 2e-6 m/s^2) are
        neglected.
    """
    R = R_itrs_gcrs(t, dut1, pn_step_s=pn_step_s)
    return np.einsum("...ji,j->...i", R, gravitation_itrs(site))
