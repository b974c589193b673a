"""Inject an effect of a given size and measure what it does: the check of every printed number.

The diagnosis prints, for every library effect not in the model, its minimal detectable
size (MDB) on the user's bag and the shift an undetected effect of that size leaves in the
estimated parameters (:mod:`~stellar_cal_ros.diagnosis.reliability`).  This module turns
such a claim into an injection: the same data (same seed, or the user's own trajectory
re-rendered by ``stellar-cal twin``) with the effect added at the printed size, run through
the same model, and the shift measured as the paired difference (the noise cancels).

:func:`simulation_value` converts a parameter value (the effect's units) into the value
``simulate --effect`` / ``twin --effect`` take; :func:`paired_shift` measures the shift of
every estimated quantity between two runs.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from stellar_cal_ros.effects import registry

#: the astrometric (sky) effects at their physical size
SKY = {"aberration": 1.0, "refraction": 1.0, "proper_motion": 1.0}
#: the swaying scenario's sensor and camera errors, zeroed: its baseline model is then right
SWAY_CLEAN = {k: 0.0 for k in ("principal_point", "radial_k1k2", "tangential",
                               "gyro_scale_factor", "gyro_misalignment",
                               "accel_scale_factor")}
#: the simulated scenario of each method
SCENARIO = {"psce": "psce_rotations", "swaying_base": "swaying"}


def clean_simulation(method: str, sky: bool, seed: int, duration: float,
                     effects: dict[str, Any] | None = None):
    """A simulation whose effects the method's model (plus the sky, if ``sky``) all holds.

    ``effects``: further effects injected (they are then what the model lacks); the bag is
    then paired with the clean one (``simulate(paired_with=)``: every star both hold gets
    the same noise).  Returns ``(simulation, model effects)``.
    """
    from stellar_cal_ros.sim.scenarios import get_scenario
    from stellar_cal_ros.sim.world import simulate

    eff = dict(SWAY_CLEAN) if method == "swaying_base" else {}
    if sky:
        eff.update(SKY)
    clean = dict(eff) if effects else None
    eff.update(effects or {})
    sim = simulate(get_scenario(SCENARIO[method]), duration=duration, seed=seed, effects=eff,
                   paired_with=clean)
    return sim, (list(SKY) if sky else [])


def clean_case(method: str, sky: bool, seed: int, duration: float):
    """``(bag data, prior, model effects)`` of a clean bag (:func:`clean_simulation`)."""
    from stellar_cal_ros.methods.replay import bag_data_from_simulation

    sim, model = clean_simulation(method, sky, seed, duration)
    return bag_data_from_simulation(sim), sim.prior, model


def simulation_value(effect_id: str, delta: np.ndarray) -> np.ndarray:
    """The ``--effect`` value of a parameter change ``delta`` (the effect's units).

    The inverse of :meth:`~stellar_cal_ros.effects.base.Effect.from_simulation` for an
    effect whose simulated value is zero otherwise (``simulation_relative`` effects are
    offsets from the nominal value, so the same inverse holds).
    """
    eff = registry.create(effect_id)
    v = np.asarray(delta, dtype=float).reshape(-1)
    if eff.simulation_scale is not None:
        v = v / np.asarray(eff.simulation_scale, dtype=float)
    return v


def parameter_delta(effect_id: str, parameter: str, size: float) -> np.ndarray:
    """The effect's parameter vector with ``parameter`` alone at ``size``."""
    eff = registry.create(effect_id)
    out = np.zeros(eff.size)
    out[list(eff.parameter_names).index(parameter)] = size
    return out


def run_values(result) -> dict[str, float]:
    """Estimated parameters and the equivalent principal point of a replay, by name."""
    flt = result.filter
    n = flt.P_est
    out = dict(zip(flt.model.parameter_names()[:n], map(float, flt.theta[:n]), strict=True))
    return _with_epp(out, result.derived)


def summary_values(run) -> dict[str, float]:
    """:func:`run_values` of a diagnosis run (a ``RunSummary``)."""
    return _with_epp(run.value_by_name(), run.derived)


def _with_epp(values: dict[str, float], derived: dict | None) -> dict[str, float]:
    """``values`` and the equivalent principal point of ``derived`` (if there), by name."""
    from stellar_cal_ros.diagnosis.runstats import EPP_NAMES

    epp = (derived or {}).get("equivalent_principal_point_px")
    if epp is not None:
        values.update(zip(EPP_NAMES, map(float, epp), strict=True))
    return values


def paired_shift(clean: dict[str, float], injected: dict[str, float],
                 true_shift: dict[str, float] | None = None) -> dict[str, float]:
    """Shift of every quantity from the clean run to the injected one.

    ``true_shift``: what the effect itself does to a derived quantity (the equivalent
    principal point of a camera effect); the bias is the estimate's shift minus it.
    """
    true_shift = true_shift or {}
    return {k: injected[k] - v - true_shift.get(k, 0.0) for k, v in clean.items()
            if k in injected}


def printed_shift(entry: dict[str, Any], quantity: str, sign: float = 1.0) -> float:
    """The shift the report prints for ``quantity`` with the effect at ``sign`` × its size.

    Linear in the sign (``sign · biases_signed``) unless a probe measured the row at both
    signs (``biases_minus``, :mod:`~stellar_cal_ros.diagnosis.reliability_probe`).
    """
    if sign < 0 and quantity in entry.get("biases_minus", {}):
        return float(entry["biases_minus"][quantity])
    return float(np.sign(sign)) * float(entry["biases_signed"][quantity])


def claimed_shift(entry: dict[str, Any], quantity: str, sign: float = 1.0,
                  share: float = 1.0) -> tuple[float, float]:
    """The shift the report claims for ``quantity`` at ``share`` x ``sign`` x its size.

    ``(a, b)``: every value between them is claimed.  At the printed size (``share`` 1)
    both are the printed shift (:func:`printed_shift`); so is ``share`` x that for a row
    the first order holds, and any ``share`` above 1 (a probe-restated MDB, the biases
    printed at the first-order size scaled alike).  A row a probe replaced
    (:func:`~.reliability_probe.apply`: the first order ``f`` off by more than 10 % at the
    printed size on the bag, ``P`` measured there) claims, below the printed size, its
    first order plus the probe's departure ``P − f`` as at least of second order in the
    size: ``s·f + sⁿ·(P − f)`` for any ``n ≥ 2``, i.e. from ``s·f`` to ``s·f + s²(P − f)``.
    Scaling the measured ``P`` linearly (``s·P``) claims at a small share a departure that
    the size, the excess gate's 10-30x the test's MDB, and the bag's misfit made: on
    ``dt_step`` s23 the twins at 3-9 % of the gate's MDB moved radial_k3's rows by −2.7 to
    −7.2x, pixel_aspect's, proper_motion's and refraction's by 0.26-1.9x that, and by
    0.88-1.21x the first order (doc/benchmarks.md, H229); the image-plane tilt, whose first
    order is off at its own size, at 0.42 of it 1.50x the first order, 0.83-1.14x the
    first order with the departure of second order.
    """
    printed = printed_shift(entry, quantity, sign)
    source = (entry.get("probe") or {}).get(entry["bias_parameter"].get(quantity), {})
    first = source.get("first_order", {}).get(quantity)
    if first is None or share >= 1.0:
        return share * printed, share * printed
    first = float(np.sign(sign)) * float(first)
    return share * first + share * share * (printed - first), share * first


def injected_parameter(entry: dict[str, Any]) -> tuple[str, list[str]]:
    """The parameter to inject for an entry, and the quantities whose bias it carries.

    The one ``discover --verify`` injects (:mod:`~stellar_cal_ros.diagnosis.verify`) and
    the clock rule's per-sign check is made at (:func:`~stellar_cal_ros.diagnosis.auto.
    _refused_rows`): of the printed bias claims (:func:`claims`) the parameter whose
    largest bias is the most σ, else the one whose hidden size is the smallest share of
    its plausible size.
    """
    groups = claims(entry)
    if groups:
        best = max(groups, key=lambda p: max(
            entry["biases"][q] / max(entry["sigma"].get(q, 1e-300), 1e-300) for q in groups[p]))
        return best, groups[best]
    plaus = entry["plausible_size"]
    return min(entry["hidden_size"], key=lambda p: entry["hidden_size"][p]
               / max(float(plaus.get(p, 1.0)), 1e-300)), []


def claims(entry: dict[str, Any], sign: float = 1.0, share: float = 1.0
           ) -> dict[str, list[str]]:
    """The printed bias claims of one reliability entry, grouped by the injected parameter.

    ``{parameter: [quantities whose printed bias comes from that parameter alone]}``, over
    the quantities the report lists (``dominates``) whose printed shift at ``sign`` × size
    exceeds their σ (a row a probe measured large at one sign only is claimed there).  At
    ``share`` x the size: where the claim (:func:`claimed_shift`), per share, exceeds σ
    at both its ends (as the report lists a row at its size).
    """
    from stellar_cal_ros.diagnosis.reliability import DOMINATES_SIGMA

    out: dict[str, list[str]] = {}
    for q in entry.get("dominates", []):
        least = min(abs(v) for v in claimed_shift(entry, q, sign, share)) / share
        if least > DOMINATES_SIGMA * entry["sigma"][q]:
            out.setdefault(entry["bias_parameter"][q], []).append(q)
    return out
