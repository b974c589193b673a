"""Proper motion of the stars from J2000.0 to the date (Hipparcos 2)."""

from __future__ import annotations

import numpy as np

from stellar_cal_ros.effects._direction import ScaledDirection
from stellar_cal_ros.errors import ModelError


class ProperMotion(ScaledDirection):
    """Proper motion of the stars from J2000.0 to the date (Hipparcos 2)."""

    id = "proper_motion"
    order = 10
    explanation = (
        "Stars move on the sky, up to several arcsec per year for nearby ones; messages carry "
        "J2000.0 places, so after 27 years a few stars sit up to 100 arcsec from where the "
        "model expects them. Residual: large errors on a few particular stars (by catalog id), "
        "always the same direction for the same star, whatever the attitude."
    )

    def fraction_reading(self, fraction: float, posix_s: float) -> str:
        """A fraction ``f`` of the motion since J2000.0: places at epoch date − f (date − 2000).

        Catalogues are published at other epochs (Gaia DR3 at J2016.0, Hipparcos at
        J1991.25): messages carrying such places see ``f`` = (date − epoch) / (date − 2000)
        of the motion the model applies (unseen case ``sky_epoch2016``: 0.407 ± 0.0068 for a
        catalogue at J2016.0 on a 2026.9 bag, was said "has another cause" alone).
        """
        from stellar_cal_ros.core.catalog import posix_to_jyear

        date = float(posix_to_jyear(float(posix_s)))
        epoch = date - fraction * (date - 2000.0)
        if not (date > 2000.0 and 1900.0 <= epoch < date - 0.5):
            return ""
        return (f"or the messages' catalogue places are at epoch J{epoch:.1f}, not J2000.0 "
                "(the stars then move by that fraction of the motion since J2000.0: the "
                "places' epoch, not the model, is then to be fixed)")

    def delta_stars(self, u, t, catalog_id, site, pressure_pa, air_temperature_c):  # noqa: D102
        from stellar_cal_ros.core.catalog import load_catalog, posix_to_jyear

        ids = np.asarray(catalog_id, dtype=np.int64).reshape(-1)
        out = np.zeros_like(u)
        if ids.size == 0:  # no identifications in the context: no star is known
            return out
        if ids.size != len(u):
            raise ModelError(f"proper_motion: {ids.size} catalog ids for {len(u)} directions")
        cat = _full_catalog(load_catalog)
        idx = cat.index_of(ids)
        known = idx >= 0
        if np.any(known):
            sub = cat.subset(idx[known])
            jyear = np.asarray(posix_to_jyear(np.asarray(t, dtype=float)[known]))
            out[known] = sub.directions(jyear) - sub.directions(2000.0)
        return out


_CATALOG = None


def _full_catalog(loader):
    global _CATALOG
    if _CATALOG is None:
        _CATALOG = loader(mag_limit=None)
    return _CATALOG
