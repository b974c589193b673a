"""Checkpoints of a streaming calibration: save, kill, restart, continue — nothing lost.

:func:`save_checkpoint` writes one file (atomically, checksummed:
:mod:`~stellar_cal_ros.io.checkpoint`); :func:`load_checkpoint` into a new
:class:`~stellar_cal_ros.methods.driver.Calibrator` built with the same prior, method,
effects and configuration continues exactly where the saved one stopped: feeding both the
same remaining messages gives bit-identical results.

Schema (``schema: stellar_cal_checkpoint``, ``version``: :data:`VERSION`)
-------------------------------------------------------------------------
The file's metadata is named by this schema, not by attribute names of the code:

* ``identity`` — method, baseline, effects, consider effects, parameter names: a checkpoint
  of another model is refused;
* ``config`` — the filter's configuration (a difference is warned about; the new one is used);
* ``driver`` — the streaming driver's state: ``counters`` (input counts), ``clock``
  (``t0_ns``, ``nominal_dt``, ``imu_max_ns``, ``last_imu_ns``, ``last_frame_ns``,
  ``first_frame_ns``, ``imu_leap``), ``frame_index``, ``faults``, the buffers (``imu_queue``,
  ``staged``, pending ``frames`` with their inputs and whether they await identification),
  ``env`` (temperature and pressure series), ``fixes``, ``convergence`` and ``stats``
  (:func:`~stellar_cal_ros.methods.results.stats_state`: a live node's blocks as one array);
* ``filter`` (absent before the filter starts) — ``blocks`` (name, size, kind, navigation of
  each block of the error state, checked against the restored filter's), ``covariance``,
  ``nominal`` (the values the blocks correct: attitude, θ, a method's navigation values),
  ``sensitivity`` (consider parameters), ``counters``, ``imu`` (the IMU buffer: the samples
  the filter still reads, from the one before its current sample; a save drops the older),
  ``propagation``, and ``fields``: the filter's other state by the names its class declares
  (:attr:`~stellar_cal_ros.methods.kernel.StarFilter.checkpoint_fields`; a method adds its
  own, e.g. the swaying filter's reference-measurement clock).

A file of another version (older ones included) is refused with one line
(:class:`~stellar_cal_ros.errors.CheckpointError`); the ``calibrator`` node then starts from
the prior.  Arrays go into the file's named arrays, everything else into JSON.
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
from stellar_cal_ros.methods.driver import Calibrator, InputCounters
from stellar_cal_ros.methods.frames import FrameInputs
from stellar_cal_ros.methods.imu_queue import ImuQueue
from stellar_cal_ros.methods.kernel import FilterCounters
from stellar_cal_ros.methods.results import stats_from_dict, stats_state

log = logging.getLogger(__name__)

SCHEMA = "stellar_cal_checkpoint"
#: the schema version this code writes and reads (5: explicit filter schema; 6: the IMU
#: reference's in-sample slope rows, core.imu_prefix; 7: the live statistics' blocks as one
#: array, results.stats_state)
VERSION = 7


class _Encoder:
    """Nested values → JSON structure + named arrays."""

    def __init__(self) -> None:
        self.arrays: dict[str, np.ndarray] = {}

    def enc(self, v: Any, key: str) -> Any:
        if isinstance(v, np.ndarray):
            self.arrays[key] = v.copy()  # the state goes on changing while it is written
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


def _blocks(flt) -> list[list]:
    return [[b.name, b.size, b.kind, bool(b.navigation)] for b in flt.layout.blocks.values()]


def _filter_section(flt, enc: _Encoder) -> dict[str, Any]:
    """The ``filter`` section of the schema (module docstring)."""
    st = flt.state
    sens = st.sensitivity
    return {
        "blocks": _blocks(flt),
        "covariance": enc.enc(st.P, "filter.covariance"),
        "nominal": enc.enc(dict(st.nominal), "filter.nominal"),
        "sensitivity": None if sens is None else enc.enc(
            {"M": sens.M, "score": sens.score, "info": sens.info, "frames": sens.frames,
             "accumulate": sens.accumulate}, "filter.sensitivity"),
        "counters": enc.enc(dataclasses.asdict(flt.counters), "filter.counters"),
        "imu": enc.enc(flt.imu.state(), "filter.imu"),
        "propagation": enc.enc(flt.propagation.state(), "filter.propagation"),
        "fields": {name: enc.enc(getattr(flt, attr), f"filter.{name}")
                   for name, attr in type(flt).checkpoint_fields.items()},
    }


def _restore_filter(flt, sec: dict[str, Any], arrays: dict[str, np.ndarray], path) -> None:
    if sec["blocks"] != _blocks(flt):
        raise CheckpointError(f"{path}: the checkpoint's state blocks {sec['blocks']} are not "
                              f"this filter's {_blocks(flt)}")
    fields = type(flt).checkpoint_fields
    missing = set(fields) - set(sec["fields"])
    if missing:
        raise CheckpointError(f"{path}: the checkpoint lacks the filter's {sorted(missing)}")
    st = flt.state
    st.P = _dec(sec["covariance"], arrays)
    st.nominal.update(_dec(sec["nominal"], arrays))
    if sec["sensitivity"] is not None:
        for name, value in _dec(sec["sensitivity"], arrays).items():
            setattr(st.sensitivity, name, value)
    flt.counters = FilterCounters(**_dec(sec["counters"], arrays))
    flt.imu.load_state(_dec(sec["imu"], arrays))
    flt.propagation.load_state(_dec(sec["propagation"], arrays))
    for name, attr in fields.items():
        setattr(flt, attr, _dec(sec["fields"][name], arrays))


def _identity(cal: Calibrator) -> dict[str, Any]:
    return {"method": cal.method, "baseline": list(cal.baseline), "effects": cal.effects,
            "consider": cal.consider, "parameters": cal.model.parameter_names()}


def _driver_section(cal: Calibrator, enc: _Encoder) -> dict[str, Any]:
    """The ``driver`` section of the schema (module docstring)."""
    cal._settle_imu()  # the IMU releases a replay's driver deferred: saved as done
    cal._trim(least=0)  # only the IMU samples the filter still reads (not up to 4096 more)
    q = cal._imu
    return {
        "counters": dataclasses.asdict(cal.counters),
        "clock": {"t0_ns": cal.t0_ns, "nominal_dt": cal.nominal_dt,
                  "imu_max_ns": cal.imu_max_ns, "last_imu_ns": cal._last_imu_ns,
                  "last_frame_ns": cal._last_frame_ns, "first_frame_ns": cal._first_frame_ns,
                  "imu_leap": None if cal._imu_leap is None else list(cal._imu_leap)},
        "frame_index": cal._frame_index, "faults": list(cal.faults),
        "imu_queue": enc.enc({"t": q.t[:q.n], "w": q.w[:q.n], "f": q.f[:q.n],
                              "sorted": q.sorted}, "driver.imu_queue"),
        "staged": enc.enc(list(cal._staged), "driver.staged"),
        "frames": [{"stamp_ns": int(f.stamp_ns), "frame_id": f.frame_id,
                    "exposure_time": float(f.exposure_time),
                    "identify": int(f.stamp_ns) in cal._to_identify,
                    "arrays": enc.enc({k: getattr(f, k) for k in (
                        "catalog_id", "right_ascension", "declination", "uv", "magnitude",
                        "sigma")}, f"driver.frame{i}"),
                    "inputs": enc.enc(dataclasses.asdict(cal._inputs[int(f.stamp_ns)]),
                                      f"driver.inputs{i}")}
                   for i, f in enumerate(cal._frames_pending)],
        "env": {k: {"stamp_ns": s.stamp_ns, "value": s.value, "ref_ns": s.ref_ns}
                for k, s in cal.env.items()},
        "fixes": enc.enc({"stamp_ns": np.asarray(cal.sites.stamp_ns, dtype=np.int64),
                          "values": cal.sites.values[:len(cal.sites.stamp_ns)].copy(),
                          "count": cal.sites.count}, "driver.fixes"),
        "convergence": enc.enc(list(cal._conv), "driver.convergence"),
        "stats": enc.enc(stats_state(cal.stats), "driver.stats"),
    }


def _restore_driver(cal: Calibrator, d: dict[str, Any], a: dict[str, np.ndarray]) -> None:
    cal.counters = InputCounters(**d["counters"])
    c = d["clock"]
    cal.t0_ns, cal.nominal_dt, cal.imu_max_ns = c["t0_ns"], c["nominal_dt"], c["imu_max_ns"]
    cal._last_imu_ns, cal._last_frame_ns = c["last_imu_ns"], c["last_frame_ns"]
    cal._first_frame_ns = c["first_frame_ns"]
    cal._imu_leap = None if c["imu_leap"] is None else tuple(c["imu_leap"])
    cal._frame_index, cal.faults = d["frame_index"], list(d["faults"])
    qd = _dec(d["imu_queue"], a)
    cal._imu = ImuQueue()
    cal._imu.push(qd["t"], qd["w"], qd["f"])
    cal._imu.sorted = qd["sorted"]
    cal._staged = [tuple(x) for x in _dec(d["staged"], a)]
    cal._staged_n = int(sum(len(x[0]) for x in cal._staged))
    for f in d["frames"]:
        fr = StarFrame(stamp_ns=f["stamp_ns"], frame_id=f["frame_id"],
                       exposure_time=f["exposure_time"], **_dec(f["arrays"], a))
        cal._frames_pending.append(fr)
        cal._inputs[int(f["stamp_ns"])] = FrameInputs(**_dec(f["inputs"], a))
        if f["identify"]:
            cal._to_identify.add(int(f["stamp_ns"]))
    for k, s in cal.env.items():
        e = d["env"][k]
        s.restore(list(e["stamp_ns"]), list(e["value"]), e["ref_ns"])
    fx = _dec(d["fixes"], a)
    for t, row in zip(fx["stamp_ns"].tolist(), fx["values"].tolist(), strict=True):
        cal.sites.add(t, *row)
    cal.sites.count = fx["count"] + 1  # the cache key changes with the restored fixes
    for item in _dec(d["convergence"], a):
        cal._conv.append(tuple(item))
    cal.stats = stats_from_dict(_dec(d["stats"], a))


def checkpoint_contents(cal: Calibrator) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Everything needed to continue: named arrays and metadata (module docstring).

    The arrays are copies: ``cal`` may go on while they are written.
    """
    enc = _Encoder()
    meta: dict[str, Any] = {
        "schema": SCHEMA, "version": VERSION, "identity": _identity(cal),
        "config": enc.enc(dataclasses.asdict(cal.config), "config"),
        "driver": _driver_section(cal, enc),
        "filter": None if cal.filter is None else _filter_section(cal.filter, enc),
    }
    return enc.arrays, meta


def save_checkpoint(cal: Calibrator, path: str | os.PathLike[str]) -> None:
    """Write :func:`checkpoint_contents` to ``path``.

    Written by :mod:`stellar_cal_ros.io.checkpoint`: atomic replace, SHA-256 verified on
    reading (the live node writes in a background thread:
    :class:`~stellar_cal_ros.io.checkpoint.CheckpointWriter`).
    """
    write_checkpoint(path, *checkpoint_contents(cal))


def check_version(meta: dict[str, Any], path: str | os.PathLike[str]) -> None:
    """Refuse, in one line, a file that is not a checkpoint of this schema version."""
    version = meta.get("version")
    if meta.get("schema") != SCHEMA or version != VERSION:
        older = meta.get("format")  # the versions before 5 wrote "stellar_cal_checkpoint/N"
        what = f"version {version}" if meta.get("schema") == SCHEMA else \
            (f"format {older!r}" if older else "no schema version")
        raise CheckpointError(f"{path}: checkpoint of {what}; this version reads "
                              f"{SCHEMA} version {VERSION} only")


def load_checkpoint(cal: Calibrator, path: str | os.PathLike[str]) -> None:
    """Restore the state saved by :func:`save_checkpoint` (same prior/method/effects/config).

    Raises
    ------
    CheckpointError
        Missing, truncated, damaged (checksum), another schema version or another model
        (``cal`` is left as it was), or contents that do not fit the schema (``cal`` is
        reset: it starts from the prior).
    """
    a, meta = read_checkpoint(path)
    check_version(meta, path)
    if meta["identity"] != _identity(cal):
        raise CheckpointError(f"{path}: checkpoint of another model {meta['identity']} "
                              f"(this one: {_identity(cal)})")
    if _dec(meta["config"], a) != dataclasses.asdict(cal.config):
        log.warning("%s: filter settings differ from the checkpoint's; using the new ones", path)
    try:
        cal._reset_state()
        _restore_driver(cal, meta["driver"], a)
        if meta["filter"] is not None:
            cal._build_filter()
            _restore_filter(cal.filter, meta["filter"], a, path)
    except (KeyError, TypeError, ValueError) as exc:
        cal._reset_state()
        raise CheckpointError(f"{path}: checkpoint does not match its schema version "
                              f"{VERSION} ({type(exc).__name__}: {exc})") from None
    except CheckpointError:
        cal._reset_state()
        raise
