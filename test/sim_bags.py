"""Simulated bags shared by the tests, made once per test session (no reference data needed).

``psce_bag(duration)`` and ``swaying_bag(duration)`` return ``(bag, prior, truth)`` paths of
a bag written by the simulator (``stellar-cal simulate``), cached in a session directory.
"""

from __future__ import annotations

import atexit
import shutil
import tempfile
from pathlib import Path

from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate, write_simulation

_DIR: Path | None = None
_CACHE: dict[tuple, tuple[Path, Path, Path]] = {}


def _dir() -> Path:
    global _DIR
    if _DIR is None:
        _DIR = Path(tempfile.mkdtemp(prefix="stellar_cal_test_bags_"))
        atexit.register(shutil.rmtree, _DIR, True)
    return _DIR


def simulated_bag(scenario: str, duration: float, seed: int = 7,
                  effects: dict | None = None) -> tuple[Path, Path, Path]:
    """``(bag, prior, truth)`` of a simulated scenario (cached per arguments)."""
    key = (scenario, float(duration), seed, tuple(sorted((effects or {}).items())))
    if key not in _CACHE:
        path = _dir() / f"{scenario}_{int(duration)}s_{seed}_{len(_CACHE)}.mcap"
        res = simulate(get_scenario(scenario), duration=duration, seed=seed, effects=effects)
        paths = write_simulation(res, path)
        _CACHE[key] = (paths["bag"], paths["prior"], paths["truth"])
    return _CACHE[key]


def psce_bag(duration: float = 120.0, seed: int = 7) -> tuple[Path, Path, Path]:
    """A Tan et al. rotation-sequence bag."""
    return simulated_bag("psce_rotations", duration, seed)


def swaying_bag(duration: float = 150.0, seed: int = 7) -> tuple[Path, Path, Path]:
    """A Zhang et al. swaying-base bag."""
    return simulated_bag("swaying", duration, seed)
