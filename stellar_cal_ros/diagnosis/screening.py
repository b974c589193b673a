"""Screening: one run of the current model that scores every candidate at once.

A round of the diagnosis is

1. **screening** — a score (Lagrange-multiplier) test of every candidate from one run of
   the *current* model: with the sensitivity of the filter's state to the candidates'
   parameters (Willsky–Jones recursion), the score ``s`` and Fisher information ``I`` of
   each candidate over the evaluation window give ``LM = sᵀ I⁻¹ s ~ χ²_k`` under "not
   missing";
2. **full augmented re-runs**, in parallel, of the candidates whose screening p-value is
   below :data:`SCREEN_P` (a loose threshold: the decision is the augmented run's);
3. the decision rules of :mod:`~stellar_cal_ros.diagnosis.discover`.

The screening function is pluggable, in one place: :func:`screen_function` returns the
kernel's screening for a method, or ``None`` — then every candidate passes and step 2
re-runs them all (the behaviour before screening existed).  Its signature::

    screen(bag, calibration, method, effects, candidates, window)
        -> {effect_id: (LM, dof, I)}            or (LM, dof, I, M)

``bag`` is a :class:`~stellar_cal_ros.methods.replay.BagData`, ``calibration`` the start
values of the round (the same prior as the re-runs, :func:`~stellar_cal_ros.diagnosis.
discover.rerun_prior`), ``effects`` the model's effects beyond the method's baseline,
``window`` the evaluation fraction (the last ``window`` of the frames).  ``I`` is (k, k)
in the effect's units⁻² over the window; the optional ``M`` (n_θ, k) is the sensitivity of
the current model's final θ to the candidate (consider analysis), which gives the
reliability report for candidates that are not re-run.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import stats as sps

from stellar_cal_ros.diagnosis.runstats import BagRef, load_bag

#: a candidate is re-run when its score test's unadjusted p-value is below this
SCREEN_P = 0.05

ScreenFn = Callable[..., dict[str, tuple]]


@dataclass
class ScreenResult:
    """The score test of one candidate."""

    lm: float
    dof: int
    information: np.ndarray  #: (k, k) over the evaluation window
    sensitivity: np.ndarray | None = None  #: (n_θ, k): ∂θ̂/∂β of the current model

    @property
    def p_value(self) -> float:
        """P(χ²_dof > LM)."""
        return float(sps.chi2.sf(max(self.lm, 0.0), max(self.dof, 1)))

    @property
    def passes(self) -> bool:
        """Worth a full augmented re-run."""
        return self.p_value < SCREEN_P


#: the score test is local: when the current model is this far off (NIS/dof), or lost lock
#: and re-acquired, its linearization no longer predicts what an added effect would do, and
#: every candidate is re-run
SCREEN_MAX_DISPERSION = 2.0


def screen_function(method: str) -> ScreenFn | None:
    """The screening pass of ``method``: the kernel's one-pass score test."""
    return _kernel_screen


def _kernel_screen(bag, calibration, method: str, effects: list[str], candidates: list[str],
                   window: float, baseline: tuple[str, ...] | None = None) -> dict[str, tuple]:
    """One run of the current model with the candidates as consider parameters.

    Returns ``{id: (LM, dof, I, M)}``; when the run is too far from consistent for a local
    test (see :data:`SCREEN_MAX_DISPERSION`) every candidate gets LM = ∞ (re-run them all).
    """
    from stellar_cal_ros.methods.replay import replay
    from stellar_cal_ros.methods.screening import score_tests

    r = replay(bag, calibration, method, effects, consider=list(candidates),
               baseline=baseline, keep_tables=False, eval_fraction=window)
    scores = score_tests(r, list(candidates))
    nis = r.stats.nis_per_dof()[0]
    local = np.isfinite(nis) and nis <= SCREEN_MAX_DISPERSION and not (
        r.counters.get("reinitializations", 0) or r.counters.get("frames_lost_lock", 0))
    return {eid: (c.lm if local else np.inf, c.dof, c.info, c.bias_per_unit)
            for eid, c in scores.items()}


def _screen_where_the_bag_is(bag: BagRef, fn: ScreenFn, calibration, method: str,
                             effects: list[str], candidates: list[str], window: float,
                             baseline: tuple[str, ...] | None) -> dict[str, tuple]:
    return fn(load_bag(bag), calibration, method, effects, candidates, window, baseline)


def run_screen(runs, fn: ScreenFn | None, calibration, method: str, effects: list[str],
               candidates: list[str], window: float,
               baseline: tuple[str, ...] | None = None) -> dict[str, ScreenResult] | None:
    """Screen ``candidates`` where the runs execute; ``None`` without a screening pass."""
    if fn is None or not candidates:
        return None
    raw: dict[str, Any] = runs.call(_screen_where_the_bag_is, fn, calibration, method,
                                    list(effects), list(candidates), window,
                                    None if baseline is None else tuple(baseline))
    out = {}
    for eid, item in raw.items():
        lm, dof, info = item[:3]
        sens = item[3] if len(item) > 3 else None
        out[eid] = ScreenResult(float(lm), int(dof), np.atleast_2d(np.asarray(info, float)),
                                None if sens is None else np.asarray(sens, dtype=float))
    return out
