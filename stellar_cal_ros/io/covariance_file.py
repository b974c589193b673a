"""The covariance sidecar of a result (``RESULT.covariance.yaml``, doc/interfaces.md §3).

:class:`Covariance` holds the covariance of the estimated parameters with their names and
units and writes the sidecar document (``format: stellar_cal_covariance/1``);
:func:`~stellar_cal_ros.io.calibration.save_calibration` writes it beside the result and
:func:`~stellar_cal_ros.io.calibration.load_covariance` reads it back.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from numpy.typing import NDArray

from stellar_cal_ros.errors import CalibrationFileError
from stellar_cal_ros.io.yaml_style import Dumper, plain

__all__ = ["COVARIANCE_FORMAT", "Covariance", "covariance_path", "parameter_unit"]

COVARIANCE_FORMAT = "stellar_cal_covariance/1"
"""Value of the ``format`` key of a covariance sidecar file."""


def covariance_path(result_path: str | os.PathLike[str]) -> Path:
    """``RESULT.covariance.yaml`` beside ``RESULT.yaml``."""
    p = Path(result_path)
    return p.with_name(p.stem + ".covariance.yaml")


def parameter_unit(name: str) -> str:
    """Unit of an ``effect.parameter`` from the effect registry ('' if unknown)."""
    try:
        from stellar_cal_ros.effects import registry

        eff_id, par = name.split(".", 1)
        eff = registry.create(eff_id)
        return str(eff.units[list(eff.parameter_names).index(par)])
    except Exception:  # noqa: BLE001 - a plugin effect not loaded, an odd name
        return ""


@dataclass
class Covariance:
    """Covariance of the estimated parameters of a result (the sidecar file).

    Attributes
    ----------
    names : list of str
        ``effect.parameter`` (e.g. ``installation.rx``, ``principal_point.cx``).
    units : list of str
        Unit of each parameter (``rad``, ``px``, ``rad/s``, ``s``, ...).
    matrix : ndarray of float64, shape (n, n)
        Covariance, units[i]·units[j].
    """

    names: list[str]
    units: list[str]
    matrix: NDArray[np.float64]

    def __post_init__(self) -> None:
        self.names = [str(n) for n in self.names]
        self.matrix = np.asarray(self.matrix, dtype=np.float64)
        n = len(self.names)
        if self.matrix.shape != (n, n):
            raise CalibrationFileError(
                f"covariance matrix has shape {self.matrix.shape}; expected ({n}, {n}) for "
                f"{n} parameter names")
        if not self.units:
            self.units = [parameter_unit(nm) for nm in self.names]
        if len(self.units) != n:
            raise CalibrationFileError(f"covariance: {len(self.units)} units for {n} names")

    @classmethod
    def from_tuple(cls, t: tuple) -> Covariance:
        """From ``(names, matrix)`` or ``(names, matrix, units)``."""
        names, matrix, *rest = t
        return cls(list(names), list(rest[0]) if rest else [], matrix)

    @property
    def sigma(self) -> NDArray[np.float64]:
        """1-σ of each parameter, shape (n,)."""
        return np.sqrt(np.clip(np.diag(self.matrix), 0.0, None))

    def correlation(self) -> NDArray[np.float64]:
        """Correlation matrix, shape (n, n) (0 where a σ is 0)."""
        s = self.sigma
        with np.errstate(invalid="ignore", divide="ignore"):
            c = self.matrix / np.outer(s, s)
        return np.where(np.isfinite(c), c, 0.0)

    def dump_yaml(self, calibration_name: str = "") -> str:
        """The sidecar document (``format: stellar_cal_covariance/1``)."""
        doc = {
            "format": COVARIANCE_FORMAT,
            "calibration": calibration_name,
            "parameters": list(self.names),
            "units": list(self.units),
            "matrix": [plain(row) for row in self.matrix],
        }
        return yaml.dump(doc, Dumper=Dumper, sort_keys=False, width=120, allow_unicode=True)
