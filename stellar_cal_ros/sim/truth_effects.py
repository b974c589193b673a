"""Truth values of physical effects for the simulator (``--effect ID=VALUE``).

Every *library* effect (and every effect a user registers, e.g. ``--effect-module
my_effect.py``) is simulated through its own class: the values given on the command line are
turned into its parameters by :meth:`~stellar_cal_ros.effects.base.Effect.from_simulation`
(the units the class declares in ``simulation_units``, e.g. arcsec for the installation,
deg/h for the gyro bias, px from the nominal value for the principal point and focal length;
otherwise the parameter units), and the truth is rendered through the very
:class:`~stellar_cal_ros.methods.star_model.StarModel` chain the filters estimate with.
:func:`effect_table` lists every id with its size and units.

Three effects are **not in the library**, on purpose: they test that the diagnosis reports
structure no library effect explains.

==========================  =====  ==========================================================
id                          size   unit / meaning
==========================  =====  ==========================================================
mount_flexure               1      arcsec of tracker rotation per unit lateral gravity
                                   (gravity-dependent bending of the mount)
magnitude_bias              2      px per magnitude (from mag 4), direction deg in the image
                                   (a magnitude-dependent centroid bias)
misidentification           1      fraction of stars given a wrong catalogue identity
==========================  =====  ==========================================================
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from stellar_cal_ros.effects import registry
from stellar_cal_ros.errors import ScenarioError

#: simulator-only effects (not estimable by any library effect): id → (size, unit)
SIM_ONLY: dict[str, tuple[int, str]] = {
    "mount_flexure": (1, "arcsec per unit lateral gravity"),
    "magnitude_bias": (2, "px per magnitude, direction deg"),
    "misidentification": (1, "fraction of stars"),
}


def effect_table() -> dict[str, tuple[int, tuple[str, ...]]]:
    """Every simulatable id: (size, units of its ``--effect`` values), registry order."""
    out: dict[str, tuple[int, tuple[str, ...]]] = {}
    for eid in registry.available():
        cls = registry.EFFECTS[eid]
        units = cls.simulation_units or tuple(cls.units) or ("",) * len(cls.parameter_names)
        out[eid] = (len(cls.parameter_names), tuple(units))
    for eid, (size, unit) in SIM_ONLY.items():
        out[eid] = (size, (unit,) * size)
    return out


def _sizes() -> dict[str, int]:
    return {k: v[0] for k, v in effect_table().items()}


#: library effect ids of the contract (the simulator takes any registered id)
CONTRACT_EFFECTS = tuple(registry.EFFECTS)


def normalize_effect(effect_id: str, value: Any) -> np.ndarray:
    """Validate one effect value and return it as a float array of the effect's size.

    A scalar given for a vector effect is broadcast (``gyro_bias=0.01`` sets all axes).
    """
    sizes = _sizes()
    if effect_id not in sizes:
        raise ScenarioError(
            f"unknown effect id {effect_id!r}; known: {', '.join(sizes)} (an effect of your "
            "own: --effect-module FILE.py)")
    arr = np.atleast_1d(np.asarray(value, dtype=float)).ravel()
    size = sizes[effect_id]
    if arr.size == 1 and size > 1:
        arr = np.full(size, arr[0])
    if arr.size != size:
        raise ScenarioError(
            f"effect {effect_id!r} takes {size} value(s), got {arr.size}: {value!r}"
        )
    if not np.all(np.isfinite(arr)):
        raise ScenarioError(f"effect {effect_id!r} has a non-finite value: {value!r}")
    return arr


def parse_effect_arguments(items: Iterable[str]) -> dict[str, np.ndarray]:
    """Parse command-line ``ID=V[,V...]`` items into normalized effect values."""
    out: dict[str, np.ndarray] = {}
    for item in items:
        if "=" not in item:
            raise ScenarioError(f"--effect expects ID=VALUE[,VALUE...], got {item!r}")
        key, text = item.split("=", 1)
        try:
            values = [float(x) for x in text.replace(";", ",").split(",") if x.strip()]
        except ValueError:
            raise ScenarioError(f"--effect {key}: cannot parse numbers in {text!r}") from None
        out[key.strip()] = normalize_effect(key.strip(), values)
    return out


def merged_effects(
    defaults: Mapping[str, Any], overrides: Mapping[str, Any] | None = None
) -> dict[str, np.ndarray]:
    """Every known effect with its value: scenario defaults, then overrides, else 0."""
    out = {k: np.zeros(n) for k, n in _sizes().items()}
    for source in (defaults, overrides or {}):
        for key, value in source.items():
            out[key] = normalize_effect(key, value)
    return out


def error_matrix(scale_factor: np.ndarray, misalignment: np.ndarray | None = None) -> np.ndarray:
    """Sensor error matrix E of ``w_meas = (I + E) w_true + bias`` (diag = scale factors)."""
    E = np.diag(np.asarray(scale_factor, dtype=float))
    if misalignment is not None:
        m = np.asarray(misalignment, dtype=float)
        E[0, 1], E[0, 2], E[1, 0], E[1, 2], E[2, 0], E[2, 1] = m
    return E
