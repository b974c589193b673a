"""One campaign run: simulate or read a bag, replay, diagnose, budget — and the row it gives.

Every call into the estimators and the simulator is in this module (the functions
:func:`simulate_run`, :func:`replay_bag`, :func:`diagnose_bag`), so a change of their API is
one edit here.  A run is a small JSON-able dict (see ``doc/budget.md``, "Campaigns"); the
worker simulates or reads its own bag, nothing big travels.

Row columns (one row per run, flat): the inputs (``key``, ``label``, ``scenario``,
``duration``, ``seed``, ``method``, ``bag`` …, dict-valued inputs as JSON text), ``status``
and ``error``, ``est.<p>``, ``sigma.<p>`` and (with a truth) ``err.<p>`` per estimated
parameter ``<p>``, ``nees``/``nees_dof``, ``nis_sum``/``nis_dof`` (updates after
``nis_after_s``), the equivalent principal point (``eqpp.*``), ``budget.*`` and
``actual.*`` attitude errors (arcsec), ``diag.*``, timings ``t.*`` (s) and the worker.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import os
import socket
import tempfile
import time
import traceback
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["STEPS", "bag_for_replay", "execute_run", "replay_bag", "run_key", "simulate_run"]

#: What a run can do, in this order.
STEPS = ("simulate", "replay", "diagnose", "budget")


def run_key(run: dict[str, Any]) -> str:
    """Hash (16 hex digits) of a run's inputs; a fleet bag's size and mtime are included."""
    material = dict(run)
    for name in ("bag", "prior", "truth"):
        path = run.get(name)
        if path:
            try:
                st = os.stat(path)
                material[f"_{name}_stat"] = [st.st_size, int(st.st_mtime)]
            except OSError:
                material[f"_{name}_stat"] = None
    text = json.dumps(material, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


# ---------------------------------------------------------------------------- the adapter


def simulate_run(run: dict[str, Any]):
    """Simulate the run's scenario; return the ``SimulationResult``."""
    from stellar_cal_ros.errors import ScenarioError
    from stellar_cal_ros.sim.scenarios import get_scenario
    from stellar_cal_ros.sim.world import simulate

    scenario = get_scenario(run["scenario"])
    for name, value in (run.get("scenario_overrides") or {}).items():
        if not hasattr(scenario, name) or name in ("name", "motion_factory"):
            raise ScenarioError(f"scenario_overrides: {name!r} is not a scenario setting")
        setattr(scenario, name, copy.deepcopy(value))
    return simulate(scenario, duration=run.get("duration"), seed=int(run.get("seed", 0)),
                    effects=run.get("truth_effects") or {})


def replay_bag(bag, prior, method: str, effects: list[str] | None = None,
               config: dict[str, Any] | None = None):
    """Calibrate a bag (path or in-memory ``BagData``) with a filter method; the ReplayResult.

    ``config`` holds fields of the method's configuration (its registered ``config_cls``:
    ``PsceConfig``, ``SwayingConfig`` ...).
    """
    from stellar_cal_ros.errors import ModelError
    from stellar_cal_ros.methods import registry
    from stellar_cal_ros.methods.replay import replay

    spec = registry.get(method)
    if spec.kind != "filter":
        raise ModelError(f"campaign: method {method!r} is not a filter method (one of "
                         f"{', '.join(registry.names('filter'))})")
    return replay(bag, prior, method, list(effects or []), _config(spec.config_cls, config))


def diagnose_bag(bag, calibration, method: str, effects: list[str], out_dir: Path,
                 candidates: list[str] | None = None) -> dict[str, Any]:
    """Run the diagnosis (no plots) and return its summary."""
    from stellar_cal_ros.diagnosis.run import diagnose

    return diagnose(bag, calibration, method, effects, out_dir, candidates=candidates,
                    plots=False, verbose=False)


def _config(cls, values: dict[str, Any] | None):
    from stellar_cal_ros.errors import ModelError

    cfg = cls()
    for name, value in (values or {}).items():
        if not hasattr(cfg, name):
            raise ModelError(f"campaign: {cls.__name__} has no setting {name!r}")
        setattr(cfg, name, value)
    return cfg


def _truth_parameters(model, truth):
    from stellar_cal_ros.methods.replay import truth_parameters

    return truth_parameters(model, truth)


def _equivalent_pp(model, theta, P):
    from stellar_cal_ros.methods.results import equivalent_principal_point

    return equivalent_principal_point(model, theta, P)


def bag_for_replay(bag, run: dict[str, Any]):
    """The ``BagData`` a run replays: from a simulation result, a path, or as is.

    ``use_config_centroid_sigma`` zeroes the stars' own σ so the configuration's is used
    (an ideal, noise-free tracker modelled as a very good one).
    """
    from stellar_cal_ros.methods.replay import BagData, bag_data_from_simulation, read_bag_data

    if isinstance(bag, (str, Path)):
        data = read_bag_data(bag)
    elif isinstance(bag, BagData):
        data = bag
    else:
        data = bag_data_from_simulation(bag)
    if run.get("use_config_centroid_sigma"):
        for f in data.frames:
            f.sigma = np.zeros_like(f.sigma)
    return data


# ---------------------------------------------------------------------------- the run


def _parameter_covariance(result) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Names, estimate θ and covariance of the calibration parameters of a replay."""
    flt = result.filter
    idx = getattr(flt, "it", slice(3, None))  # swaying: its own layout; PSCE: after φ
    P = flt.P[idx, idx]
    return flt.model.parameter_names(), np.asarray(flt.theta, dtype=float), np.array(P)


def _replay_columns(row: dict, run: dict, result, truth) -> tuple[list[str], np.ndarray]:
    names, theta, P = _parameter_covariance(result)
    sig = np.sqrt(np.clip(np.diag(P), 0.0, None))
    for n, v, s in zip(names, theta, sig, strict=True):
        row[f"est.{n}"] = float(v)
        row[f"sigma.{n}"] = float(s)
    row["parameter_names"] = list(names)
    row["covariance"] = [float(x) for x in P.reshape(-1)]
    hist = result.history
    after = run.get("nis_after_s")
    if after is None:
        after = min(300.0, 0.3 * result.duration)
    late = (hist["t"] - hist["t"][0] > after) if len(hist["t"]) else np.zeros(0, bool)
    row["nis_sum"] = float(np.sum(hist["nis"][late]))
    row["nis_dof"] = int(np.sum(hist["dof"][late]))
    row["frames_used"] = int(len(hist["t"]))
    row["stars_gated"] = int(np.sum(hist["gated"])) if len(hist["gated"]) else 0
    res = result.residuals
    ok = ~res["gated"].astype(bool) if len(res["gated"]) else np.zeros(0, bool)
    half = len(ok) // 2
    for c in ("u", "v"):
        x = res["d" + c][half:][ok[half:]]
        row[f"innovation_rms_{c}_px"] = float(np.sqrt(np.mean(x**2))) if x.size else math.nan
    derived = result.derived or {}
    if "equivalent_principal_point_px" in derived:
        for i, c in enumerate("uv"):
            row[f"eqpp.{c}_px"] = float(derived["equivalent_principal_point_px"][i])
            row[f"eqpp.sigma_{c}_px"] = float(derived["equivalent_principal_point_sigma_px"][i])
    if truth is not None:
        model = result.filter.model
        true_theta = _truth_parameters(model, truth)
        err = theta - true_theta
        for n, e in zip(names, err, strict=True):
            row[f"err.{n}"] = float(e)
        try:
            row["nees"] = float(err @ np.linalg.solve(P, err))
        except np.linalg.LinAlgError:
            row["nees"] = math.nan
        row["nees_dof"] = len(err)
        if "equivalent_principal_point_px" in derived:
            eq_true = _equivalent_pp(model, true_theta, P)["equivalent_principal_point_px"]
            for i, c in enumerate("uv"):
                row[f"eqpp.err_{c}_px"] = float(derived["equivalent_principal_point_px"][i]
                                                - eq_true[i])
    return names, P


def _budget_columns(row: dict, run: dict, result, names, P, prior, truth) -> None:
    from stellar_cal_ros.budget.analysis import BudgetOptions, run_budget
    from stellar_cal_ros.budget.sources import error_model_from_result
    from stellar_cal_ros.budget.truth import actual_attitude_errors

    opts = dict(run.get("budget") or {})
    centroid = float(opts.pop("centroid_sigma_px", 0.0))
    unestimated = opts.pop("unestimated", "exclude")
    bo = BudgetOptions(draws=0, frames=100)
    for k, v in opts.items():
        if not hasattr(bo, k):
            from stellar_cal_ros.errors import ModelError

            raise ModelError(f"campaign: budget has no setting {k!r}")
        setattr(bo, k, v)
    model = error_model_from_result(result.calibration, (names, P), "replay", prior, None,
                                    centroid, unestimated)
    b = run_budget(model, bo)
    for conv in ("axis", "system"):
        for k, v in b["frame"][conv]["linear"]["total"].items():
            row[f"budget.{conv}.{k}_arcsec"] = v
    if truth is not None:
        act = actual_attitude_errors(truth, result.calibration, bo.frames, bo.stars_per_frame,
                                     bo.seed)
        for conv in ("axis", "system"):
            for k, v in act[conv].items():
                row[f"actual.{conv}.{k}_arcsec"] = v


def execute_run(run: dict[str, Any]) -> dict[str, Any]:
    """Do one run and return its row; never raises (a failure is a row with its error).

    Files a run produces travel back in ``row["_files"]`` ({name: text}) for the client
    to write (workers need not share a disk with it).
    """
    from stellar_cal_ros.io.calibration import dump_calibration_yaml, load_calibration

    t_all = time.perf_counter()
    row: dict[str, Any] = {"key": run.get("key") or run_key(run), "status": "ok", "error": ""}
    for k, v in run.items():
        if k != "key":
            row[k] = json.dumps(v, sort_keys=True) if isinstance(v, (dict, list)) else v
    row["worker"] = f"{socket.gethostname()}:{os.getpid()}"
    row["omp_num_threads"] = os.environ.get("OMP_NUM_THREADS", "")
    files: dict[str, str] = {}
    steps = list(run.get("steps") or ["replay"])
    try:
        truth = None
        if run.get("bag"):
            bag = run["bag"]
            prior = load_calibration(run["prior"])
            truth = load_calibration(run["truth"]) if run.get("truth") else None
        else:
            t = time.perf_counter()
            sim = simulate_run(run)
            row["t.simulate"] = time.perf_counter() - t
            prior, truth = sim.prior, sim.truth
            files["prior.yaml"] = dump_calibration_yaml(prior)
            if run.get("write_bag"):
                from stellar_cal_ros.sim.world import write_simulation

                bag = Path(run["write_bag"]) / f"{row['key']}.mcap"
                write_simulation(sim, bag)
            else:
                bag = sim
            row["stars_per_frame_mean"] = float(sim.meta["stars_per_frame"]["mean"])
        t = time.perf_counter()
        bag = bag_for_replay(bag, run)
        row["t.read"] = time.perf_counter() - t
        result = None
        if "replay" in steps or "budget" in steps or "diagnose" in steps:
            t = time.perf_counter()
            result = replay_bag(bag, prior, run.get("method", "psce"),
                                run.get("estimate_effects"), run.get("config"))
            row["t.replay"] = time.perf_counter() - t
            names, P = _replay_columns(row, run, result, truth)
            files["result.yaml"] = dump_calibration_yaml(result.calibration)
            files["result.covariance.yaml"] = json.dumps(
                {"names": names, "matrix": P.tolist()})
        if "diagnose" in steps:
            t = time.perf_counter()
            with tempfile.TemporaryDirectory() as tmp:
                opts = run.get("diagnose") or {}
                summary = diagnose_bag(bag, result.calibration, run.get("method", "psce"),
                                       list(run.get("estimate_effects") or []), Path(tmp),
                                       opts.get("candidates"))
                files["diagnosis.json"] = (Path(tmp) / "diagnosis.json").read_text()
            row["diag.recommendation"] = summary.get("recommendation") or ""
            top = (summary.get("candidates") or [{}])[0]
            row["diag.top_effect"] = top.get("effect", "")
            row["diag.top_p_value"] = float(top.get("p_value", math.nan))
            row["t.diagnose"] = time.perf_counter() - t
        if "budget" in steps:
            t = time.perf_counter()
            _budget_columns(row, run, result, names, P, prior, truth)
            row["t.budget"] = time.perf_counter() - t
    except Exception as exc:  # noqa: BLE001 - a failed run is a row, reported by the runner
        row["status"] = "error"
        row["error"] = f"{type(exc).__name__}: {exc}"
        row["traceback"] = traceback.format_exc(limit=6)
    row["t.total"] = time.perf_counter() - t_all
    row["_files"] = files
    return row
