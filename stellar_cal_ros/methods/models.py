"""Which model a method estimates: its baseline, the user's effects, candidates — one rule.

Every filter method estimates its **baseline** (the paper's state) plus the effects the user
adds (``--effects``; ``-id`` removes an added one, the baseline cannot be removed).  An
effect the prior calls uncertain (a positive σ for one of its quantities,
:func:`prior_uncertain_effects`) but that is not in the model is *not* added silently: the
replay names it ("the prior says ... is uncertain; not in the model") and the diagnosis
tests it first among the candidates.  The same rule for every method; a method's baseline
and the stages it models are its :class:`~stellar_cal_ros.methods.registry.MethodSpec`'s.

*Consider* effects are appended after the estimated ones: they are predicted through but
kept at their prior value, and the filter tracks the state's sensitivity to them (the
diagnosis' one-pass score tests, see :class:`~stellar_cal_ros.core.covariance.Sensitivity`).
"""

from __future__ import annotations

import logging

import numpy as np

from stellar_cal_ros.effects import registry
from stellar_cal_ros.errors import ModelError
from stellar_cal_ros.io.calibration import Calibration
from stellar_cal_ros.methods import registry as methods
from stellar_cal_ros.methods.star_model import StarModel

log = logging.getLogger(__name__)


def resolve_effects(method: str, requested: list[str] | None,
                    baseline: tuple[str, ...] | None = None) -> list[str]:
    """Effects added to the baseline: ``requested`` in order, ``-id`` removes one.

    Unknown ids raise :class:`ModelError` (with the known ones); effects acting in a stage
    the method does not model (accelerometer effects for PSCE) too.
    """
    spec = methods.get(method)
    base = spec.baseline if baseline is None else tuple(baseline)
    out: list[str] = []
    for item in requested or []:
        item = item.strip()
        if not item:
            continue
        if item.startswith("-"):
            eid = item[1:]
            if eid in base:
                raise ModelError(f"{eid} is in the {method} baseline and cannot be removed")
            out = [e for e in out if e != eid]
            continue
        stage = registry.effect_class(item).stage
        if stage not in spec.stages:
            raise ModelError(f"effect {item} acts on the {stage.value} stage, which the "
                             f"{method} method does not model")
        if item not in out and item not in base:
            out.append(item)
    return out


def build_model(prior: Calibration, method: str, effects: list[str] | None = None,
                consider: list[str] | None = None,
                baseline: tuple[str, ...] | None = None) -> StarModel:
    """StarModel of the method's baseline + ``effects``, then the ``consider`` effects."""
    base = methods.get(method).baseline if baseline is None else tuple(baseline)
    ids = list(base) + [e for e in (effects or []) if e not in base]
    extra = [e for e in (consider or []) if e not in ids]
    # estimated effects in application order, then the consider ones (trailing θ entries)
    return StarModel(registry.create_many(ids) + registry.create_many(extra), prior)


def _positive(values, index=None) -> bool:
    if values is None:
        return False
    if isinstance(values, dict):  # camera_calibration_parsers matrix layout
        values = values.get("data")
    try:
        a = np.asarray(values, dtype=float).ravel()
    except (TypeError, ValueError):
        return False
    if index is not None:
        a = a[[i for i in index if i < a.size]]
    return bool(np.any(np.isfinite(a) & (a > 0)))


def prior_uncertain_effects(prior: Calibration) -> list[str]:
    """Library effects the prior's ``sigma`` block calls uncertain (registry order).

    Mapping (calibration YAML keys → effect ids)::

        camera.camera_matrix fx, fy          → focal_length
        camera.camera_matrix cx, cy          → principal_point
        camera.distortion_coefficients k1 k2 → radial_k1k2;  p1 p2 → tangential;  k3 → radial_k3
        gyro.bias                            → gyro_bias
        gyro.error_matrix diagonal           → gyro_scale_factor;  off-diagonal → gyro_misalignment
        accelerometer.bias                   → accel_bias
        accelerometer.error_matrix diagonal  → accel_scale_factor
        installation.rotation_vector         → installation
        time_offset                          → time_offset
        effects.<id> (any positive entry)    → <id> (a registered effect)

    The accelerometer's off-diagonal entries have no library effect; a positive σ there is
    logged.
    """
    sig = prior.sigma or {}
    out: set[str] = set()
    cam = sig.get("camera", {}) or {}
    K = cam.get("camera_matrix")
    if _positive(K, (0, 4)):
        out.add("focal_length")
    if _positive(K, (2, 5)):
        out.add("principal_point")
    dist = cam.get("distortion_coefficients")
    if _positive(dist, (0, 1)):
        out.add("radial_k1k2")
    if _positive(dist, (2, 3)):
        out.add("tangential")
    if _positive(dist, (4,)):
        out.add("radial_k3")
    if _positive((sig.get("installation", {}) or {}).get("rotation_vector")):
        out.add("installation")
    gyro = sig.get("gyro", {}) or {}
    if _positive(gyro.get("bias")):
        out.add("gyro_bias")
    if _positive(gyro.get("error_matrix"), (0, 4, 8)):
        out.add("gyro_scale_factor")
    if _positive(gyro.get("error_matrix"), (1, 2, 3, 5, 6, 7)):
        out.add("gyro_misalignment")
    acc = sig.get("accelerometer", {}) or {}
    if _positive(acc.get("bias")):
        out.add("accel_bias")
    if _positive(acc.get("error_matrix"), (0, 4, 8)):
        out.add("accel_scale_factor")
    if _positive(acc.get("error_matrix"), (1, 2, 3, 5, 6, 7)):
        log.info("prior: accelerometer misalignment sigma given, but no library effect "
                 "models it; kept at the prior value")
    if _positive(sig.get("time_offset")):
        out.add("time_offset")
    for eid, block in (sig.get("effects", {}) or {}).items():
        vals = list(block.values()) if isinstance(block, dict) else block
        if eid in registry.EFFECTS and any(_positive(v) for v in np.atleast_1d(
                np.asarray(vals, dtype=object)).ravel()):
            out.add(eid)
    order = {k: n for n, k in enumerate(registry.EFFECTS)}
    return sorted(out, key=lambda e: order.get(e, len(order)))


def uncertain_not_in_model(prior: Calibration, method: str, model_effects: list[str]
                           ) -> list[str]:
    """Effects the prior calls uncertain that the model leaves fixed (and the method models)."""
    have, stages = set(model_effects), methods.get(method).stages
    return [e for e in prior_uncertain_effects(prior)
            if e not in have and registry.EFFECTS[e].stage in stages]
