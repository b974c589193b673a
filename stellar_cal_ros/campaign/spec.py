"""The campaign spec (YAML) and the list of runs it expands to.

::

    run:                    # defaults of every run
      scenario: psce_rotations
      duration: 120
      method: psce
      steps: [simulate, replay, budget]
    matrix:                 # Cartesian product over these run keys
      estimate_effects: [[], [time_offset]]
    variants:               # each merged over every matrix point (settings that go together)
      - {label: "0.05 px", scenario_overrides: {centroid_noise_px: 0.05},
         config: {centroid_sigma_px: 0.05}}
    seeds: 20               # 0..19; or [3, 5, 8]; or {start: 1000, count: 20}
    bags:                   # instead of simulating: a fleet of recorded bags
      - {bag: a.mcap, prior: a.prior.yaml, truth: a.truth.yaml}

Run keys: ``label``, ``scenario``, ``duration``, ``seed``, ``truth_effects`` (the
``simulate --effect`` values), ``scenario_overrides`` (Scenario attributes, e.g.
``centroid_noise_px``, ``prior_sigma``), ``write_bag`` (write the simulated bag under
``OUT_DIR/bags`` and replay it from disk), ``bag``, ``prior``, ``truth``, ``method``,
``estimate_effects`` (``replay --effects``), ``config`` (``PsceConfig``/``SwayingConfig``
fields), ``steps`` (of ``simulate, replay, diagnose, budget``), ``diagnose``
(``{candidates}``), ``budget`` (``BudgetOptions`` fields, ``centroid_sigma_px``, ``unestimated``),
``nis_after_s``, ``use_config_centroid_sigma`` (ignore the stars' own σ).
"""

from __future__ import annotations

import copy
import itertools
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from stellar_cal_ros.budget.sources import read_spec
from stellar_cal_ros.campaign.runs import STEPS, run_key
from stellar_cal_ros.errors import ModelError

__all__ = ["RUN_KEYS", "read_campaign_spec", "runs_from_spec"]

RUN_KEYS = ("label", "scenario", "duration", "seed", "truth_effects", "scenario_overrides",
            "write_bag", "bag", "prior", "truth", "method", "estimate_effects", "config",
            "steps", "diagnose", "budget", "nis_after_s", "use_config_centroid_sigma")
_TOP_KEYS = ("name", "run", "matrix", "variants", "seeds", "bags")


def read_campaign_spec(path: str | Path) -> dict[str, Any]:
    """Load a campaign spec (a mapping) with a clear error."""
    return read_spec(path, "campaign spec")


def _check_run(run: Mapping[str, Any], where: str) -> None:
    unknown = sorted(set(run) - set(RUN_KEYS))
    if unknown:
        raise ModelError(f"{where}: unknown run key(s) {', '.join(unknown)}; known: "
                         + ", ".join(RUN_KEYS))
    steps = run.get("steps") or ["replay"]
    bad = [s for s in steps if s not in STEPS]
    if bad:
        raise ModelError(f"{where}: unknown step(s) {', '.join(bad)}; known: "
                         + ", ".join(STEPS))
    if not run.get("bag") and not run.get("scenario"):
        raise ModelError(f"{where}: a run needs a scenario to simulate or a bag to read")
    if run.get("bag") and not run.get("prior"):
        raise ModelError(f"{where}: bag {run['bag']} needs its prior")


def _seeds(value: Any) -> list[int | None]:
    if value is None:
        return [None]
    if isinstance(value, bool):
        raise ModelError("campaign spec: seeds must be a count, a list or {start, count}")
    if isinstance(value, int):
        return list(range(value))
    if isinstance(value, list) and all(isinstance(v, int) for v in value):
        return list(value)
    if isinstance(value, Mapping) and isinstance(value.get("count"), int):
        start = int(value.get("start", 0))
        return list(range(start, start + value["count"]))
    raise ModelError("campaign spec: seeds must be a count, a list of integers or "
                     "{start, count}")


def runs_from_spec(spec: Mapping[str, Any], base_dir: str | Path,
                   out_dir: str | Path) -> list[dict[str, Any]]:
    """Expand a spec into runs (each with its ``key``), in a stable order.

    Relative ``bag``/``prior``/``truth`` paths are resolved against ``base_dir`` (the spec's
    folder); ``write_bag: true`` becomes ``OUT_DIR/bags``.
    """
    unknown = sorted(set(spec) - set(_TOP_KEYS))
    if unknown:
        raise ModelError(f"campaign spec: unknown key(s) {', '.join(unknown)}; known: "
                         + ", ".join(_TOP_KEYS))
    if not isinstance(spec.get("run") or {}, Mapping):
        raise ModelError("campaign spec: run must be a mapping of run keys (defaults of "
                         "every run)")
    base = dict(spec.get("run") or {})
    matrix = spec.get("matrix") or {}
    if not isinstance(matrix, Mapping) or not all(isinstance(v, list) and v
                                                  for v in matrix.values()):
        raise ModelError("campaign spec: matrix must map run keys to non-empty lists")
    variants = spec.get("variants") or [{}]
    bags = spec.get("bags") or [{}]
    if not isinstance(variants, list) or not all(isinstance(v, Mapping) for v in variants):
        raise ModelError("campaign spec: variants must be a list of mappings")
    if not isinstance(bags, list) or not all(isinstance(v, Mapping) for v in bags):
        raise ModelError("campaign spec: bags must be a list of {bag, prior[, truth]}")
    seeds = _seeds(spec.get("seeds"))
    keys = list(matrix)
    runs, seen = [], set()
    for bag in bags:
        for point in itertools.product(*(matrix[k] for k in keys)):
            for variant in variants:
                for seed in seeds:
                    run = copy.deepcopy(base)
                    run.update(zip(keys, copy.deepcopy(point), strict=True))
                    run.update(copy.deepcopy(dict(variant)))
                    run.update(copy.deepcopy(dict(bag)))
                    if seed is not None and not run.get("bag"):
                        run["seed"] = seed
                    _check_run(run, f"campaign run {len(runs) + 1}")
                    for name in ("bag", "prior", "truth"):
                        if run.get(name):
                            p = Path(run[name])
                            run[name] = str(p if p.is_absolute() else Path(base_dir) / p)
                    if run.get("write_bag") is True:
                        run["write_bag"] = str(Path(out_dir).resolve() / "bags")
                    key = run_key(run)
                    if key in seen:
                        continue  # a fleet bag repeated over seeds is one run
                    seen.add(key)
                    run["key"] = key
                    runs.append(run)
    return runs
