"""Unit conversions used across the package (one definition each).

Every constant is named ``<UNIT>`` = that unit expressed in SI / radians, so a value in the
unit is multiplied by the constant to get SI, and an SI value is divided by it::

    angle_rad = 3.0 * ARCSEC          # 3 arcsec in radians
    angle_arcsec = angle_rad / ARCSEC

(Before this module ``ARCSEC`` meant rad/arcsec in some modules and arcsec/rad in others.)
"""

from __future__ import annotations

import math

#: one arc second, in radians
ARCSEC = math.pi / (180.0 * 3600.0)
#: one degree, in radians
DEG = math.pi / 180.0
#: one degree per hour, in rad/s
DEG_PER_HOUR = math.pi / 180.0 / 3600.0
#: one degree per √hour (angle random walk), in rad/√s
DEG_PER_SQRT_HOUR = math.pi / 180.0 / 60.0
#: standard gravity, m/s²
G0 = 9.80665
#: one micro-g, in m/s²
MICRO_G = 1e-6 * G0
#: one part per million (scale factors)
PPM = 1e-6
#: one millisecond, in s
MS = 1e-3
