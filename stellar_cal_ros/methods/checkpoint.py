"""Checkpoints of a streaming calibration: save, kill, restart, continue — nothing lost.

:func:`save_checkpoint` writes one file (atomically, checksummed:
:mod:`~stellar_cal_ros.io.checkpoint`) holding the driver's buffers (reorder queues, pending
frames, environment series, fixes, running statistics) and the filter's state — generic over
the filter's attributes, so a method's own state (the PSCE prefix integrals, the swaying
filter's reference window) is saved without per-method code. :func:`load_checkpoint` into a
new :class:`~stellar_cal_ros.methods.driver.Calibrator` built with the same prior, method,
effects and configuration continues exactly where the saved one stopped: feeding both the
same remaining messages gives bit-identical results.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from collections import deque
from typing import Any

import numpy as np

from stellar_cal_ros.core.types import StarFrame
from stellar_cal_ros.errors import CheckpointError
from stellar_cal_ros.io.checkpoint import read_checkpoint, write_checkpoint
from stellar_cal_ros.methods.driver import Calibrator, InputCounters, _ImuQueue
from stellar_cal_ros.methods.frames import FrameInputs
from stellar_cal_ros.methods.kernel import FilterCounters
from stellar_cal_ros.methods.results import stats_from_dict

log = logging.getLogger(__name__)

CHECKPOINT_FORMAT = "stellar_cal_checkpoint/4"
#: filter attributes rebuilt by the constructor (configuration, caches, workspaces)
_FILTER_SKIP = {"model", "config", "layout", "gate", "update_policy", "grid", "site",
                "_Phi"}


class _Encoder:
    """Nested values → JSON structure + named arrays."""

    def __init__(self) -> None:
        self.arrays: dict[str, np.ndarray] = {}

    def enc(self, v: Any, key: str) -> Any:
        if isinstance(v, np.ndarray):
            self.arrays[key] = v
            return {"__a__": key}
        if isinstance(v, (np.integer,)):
            return int(v)
        if isinstance(v, (np.floating,)):
            return float(v)
        if isinstance(v, np.bool_):
            return bool(v)
        if v is None or isinstance(v, (bool, int, float, str)):
            return v
        if isinstance(v, slice):
            return {"__s__": [v.start, v.stop, v.step]}
        if isinstance(v, tuple):
            return {"__t__": [self.enc(x, f"{key}#{i}") for i, x in enumerate(v)]}
        if isinstance(v, (list, deque)):
            return [self.enc(x, f"{key}#{i}") for i, x in enumerate(v)]
        if isinstance(v, dict):
            return {"__d__": {str(k): self.enc(x, f"{key}.{k}") for k, x in v.items()}}
        raise TypeError(f"cannot checkpoint {key} of type {type(v).__name__}")


def _dec(v: Any, arrays: dict[str, np.ndarray]) -> Any:
    if isinstance(v, dict):
        if "__a__" in v:
            return arrays[v["__a__"]].copy()
        if "__s__" in v:
            return slice(*v["__s__"])
        if "__t__" in v:
            return tuple(_dec(x, arrays) for x in v["__t__"])
        if "__d__" in v:
            return {k: _dec(x, arrays) for k, x in v["__d__"].items()}
    if isinstance(v, list):
        return [_dec(x, arrays) for x in v]
    return v


def _filter_state(flt, enc: _Encoder) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in vars(flt).items():
        if k in _FILTER_SKIP:
            continue
        if k in ("imu", "propagation"):  # objects that say what defines them
            out[k] = {"__obj__": enc.enc(v.state(), f"f.{k}")}
        elif k == "state":  # the ErrorState: covariance, nominal values, sensitivity
            sens = v.sensitivity
            out[k] = {"__state__": enc.enc(
                {"P": v.P, "nominal": v.nominal,
                 "sensitivity": None if sens is None else {
                     "M": sens.M, "score": sens.score, "info": sens.info,
                     "frames": sens.frames, "accumulate": sens.accumulate}}, "f.state")}
        elif k == "counters":
            out[k] = enc.enc(dataclasses.asdict(v), "f.counters")
        else:
            out[k] = enc.enc(v, f"f.{k}")
    return out


def _restore_filter(flt, state: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
    for k, v in state.items():
        if isinstance(v, dict) and "__obj__" in v:
            getattr(flt, k).load_state(_dec(v["__obj__"], arrays))
        elif isinstance(v, dict) and "__state__" in v:
            s = _dec(v["__state__"], arrays)
            flt.state.P = s["P"]
            flt.state.nominal.update(s["nominal"])
            for name, value in (s["sensitivity"] or {}).items():
                setattr(flt.state.sensitivity, name, value)
        elif k == "counters":
            flt.counters = FilterCounters(**_dec(v, arrays))
        else:
            setattr(flt, k, _dec(v, arrays))


def _identity(cal: Calibrator) -> dict[str, Any]:
    return {"method": cal.method, "baseline": list(cal.baseline), "effects": cal.effects,
            "consider": cal.consider, "parameters": cal.model.parameter_names()}


def save_checkpoint(cal: Calibrator, path: str | os.PathLike[str]) -> None:
    """Write everything needed to continue to ``path``.

    Written by :mod:`stellar_cal_ros.io.checkpoint`: atomic replace, SHA-256 verified on
    reading.
    """
    enc = _Encoder()
    q = cal._imu
    frames = cal._frames_pending
    meta: dict[str, Any] = {
        "format": CHECKPOINT_FORMAT, "identity": _identity(cal),
        "config": enc.enc(dataclasses.asdict(cal.config), "config"),
        "counters": dataclasses.asdict(cal.counters),
        "t0_ns": cal.t0_ns, "nominal_dt": cal.nominal_dt, "imu_max_ns": cal.imu_max_ns,
        "last_imu_ns": cal._last_imu_ns, "last_frame_ns": cal._last_frame_ns,
        "frame_index": cal._frame_index, "faults": list(cal.faults),
        "imu_leap": None if cal._imu_leap is None else list(cal._imu_leap),
        "first_frame_ns": cal._first_frame_ns,
        "imu_queue": enc.enc({"t": q.t[:q.n], "w": q.w[:q.n], "f": q.f[:q.n],
                              "sorted": q.sorted}, "q"),
        "staged": enc.enc(list(cal._staged), "staged"),
        "frames": [{"stamp_ns": int(f.stamp_ns), "frame_id": f.frame_id,
                    "exposure_time": float(f.exposure_time),
                    "arrays": enc.enc({k: getattr(f, k) for k in (
                        "catalog_id", "right_ascension", "declination", "uv", "magnitude",
                        "sigma")}, f"frame{i}"),
                    "inputs": enc.enc(dataclasses.asdict(cal._inputs[int(f.stamp_ns)]),
                                      f"inputs{i}")}
                   for i, f in enumerate(frames)],
        "env": {k: {"stamp_ns": s.stamp_ns, "value": s.value, "ref_ns": s.ref_ns}
                for k, s in cal.env.items()},
        "fixes": enc.enc({"stamp_ns": np.asarray(cal.sites.stamp_ns, dtype=np.int64),
                          "values": cal.sites.values[:len(cal.sites.stamp_ns)].copy(),
                          "count": cal.sites.count}, "fixes"),
        "conv": enc.enc(list(cal._conv), "conv"),
        "stats": enc.enc(dataclasses.asdict(cal.stats), "stats"),
        "filter": None if cal.filter is None else _filter_state(cal.filter, enc),
    }
    write_checkpoint(path, enc.arrays, meta)


def load_checkpoint(cal: Calibrator, path: str | os.PathLike[str]) -> None:
    """Restore the state saved by :func:`save_checkpoint` (same prior/method/effects/config).

    Raises
    ------
    CheckpointError
        Missing, truncated, damaged (checksum), another format, or another model.
    """
    a, meta = read_checkpoint(path)
    if meta.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{path}: checkpoint format {meta.get('format')!r}, this version "
                              f"reads {CHECKPOINT_FORMAT!r}")
    if meta["identity"] != _identity(cal):
        raise CheckpointError(f"{path}: checkpoint of another model {meta['identity']} "
                              f"(this one: {_identity(cal)})")
    if _dec(meta["config"], a) != dataclasses.asdict(cal.config):
        log.warning("%s: filter settings differ from the checkpoint's; using the new ones", path)
    cal._reset_state()
    cal.counters = InputCounters(**meta["counters"])
    cal.t0_ns, cal.nominal_dt = meta["t0_ns"], meta["nominal_dt"]
    cal.imu_max_ns, cal._last_imu_ns = meta["imu_max_ns"], meta["last_imu_ns"]
    cal._last_frame_ns, cal._frame_index = meta["last_frame_ns"], meta["frame_index"]
    cal.faults = list(meta.get("faults", []))
    cal._imu_leap = None if meta.get("imu_leap") is None else tuple(meta["imu_leap"])
    cal._first_frame_ns = meta.get("first_frame_ns")
    qd = _dec(meta["imu_queue"], a)
    cal._imu = _ImuQueue()
    cal._imu.push(qd["t"], qd["w"], qd["f"])
    cal._imu.sorted = qd["sorted"]
    cal._staged = [tuple(x) for x in _dec(meta["staged"], a)]
    cal._staged_n = int(sum(len(x[0]) for x in cal._staged))
    for f in meta["frames"]:
        arr = _dec(f["arrays"], a)
        fr = StarFrame(stamp_ns=f["stamp_ns"], frame_id=f["frame_id"],
                       exposure_time=f["exposure_time"], **arr)
        cal._frames_pending.append(fr)
        cal._inputs[int(f["stamp_ns"])] = FrameInputs(**_dec(f["inputs"], a))
    for k, s in cal.env.items():
        e = meta["env"][k]
        s.restore(list(e["stamp_ns"]), list(e["value"]), e["ref_ns"])
    fx = _dec(meta["fixes"], a)
    for t, row in zip(fx["stamp_ns"].tolist(), fx["values"].tolist(), strict=True):
        cal.sites.add(t, *row)
    cal.sites.count = fx["count"] + 1  # the cache key changes with the restored fixes
    for item in _dec(meta["conv"], a):
        cal._conv.append(tuple(item))
    st = _dec(meta["stats"], a)
    cal.stats = stats_from_dict(st)
    if meta["filter"] is not None:
        cal._build_filter()
        _restore_filter(cal.filter, meta["filter"], a)
