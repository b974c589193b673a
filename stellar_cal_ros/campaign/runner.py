"""Run a campaign on Dask distributed: resumable, with progress, into one Parquet table.

Layout of ``OUT_DIR``::

    runs/KEY.json        the row of each finished run (written as it finishes)
    runs/KEY/...         its files (result.yaml, result.covariance.yaml, diagnosis.json)
    results.parquet      every row of the campaign, one per run
    bags/                simulated bags, for runs with ``write_bag``

A run whose ``runs/KEY.json`` says ``ok`` is done and skipped on the next invocation (the key
hashes the run's inputs); failed runs are tried again.  By default a ``LocalCluster`` with one
single-threaded worker process per core is started (OMP/MKL/OpenBLAS threads set to 1 in the
workers); ``scheduler`` connects to an existing cluster instead, whose workers need the
package installed and, for ``write_bag`` or fleet bags, the same paths.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from stellar_cal_ros.campaign.runs import execute_run

__all__ = ["CampaignResult", "load_rows", "run_campaign", "write_parquet"]

log = logging.getLogger(__name__)

_THREAD_ENV = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}


@dataclass
class CampaignResult:
    """What :func:`run_campaign` did."""

    rows: list[dict[str, Any]]  #: one per run of the spec, in its order
    ran: int  #: runs executed now
    skipped: int  #: runs already done (resumed)
    failed: int  #: runs whose row has status "error"
    seconds: float  #: wall-clock time of this invocation
    parquet: Path | None


def _atomic_write(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def _row_path(out_dir: Path, key: str) -> Path:
    return out_dir / "runs" / f"{key}.json"


def _done(out_dir: Path, key: str) -> bool:
    path = _row_path(out_dir, key)
    if not path.exists():
        return False
    try:
        return json.loads(path.read_text()).get("status") == "ok"
    except (OSError, ValueError):
        return False


def _save_row(out_dir: Path, row: dict[str, Any]) -> None:
    files = row.pop("_files", {}) or {}
    key = row["key"]
    if files:
        folder = out_dir / "runs" / key
        folder.mkdir(parents=True, exist_ok=True)
        for name, text in files.items():
            _atomic_write(folder / name, text)
    _atomic_write(_row_path(out_dir, key), json.dumps(row, default=_json_default))


def _json_default(x: Any) -> Any:
    try:
        return float(x)
    except (TypeError, ValueError):
        return str(x)


def load_rows(out_dir: str | Path, keys: list[str] | None = None) -> list[dict[str, Any]]:
    """The saved rows of ``keys`` (default: every row in ``OUT_DIR/runs``)."""
    out_dir = Path(out_dir)
    if keys is None:
        paths = sorted((out_dir / "runs").glob("*.json"))
    else:
        paths = [_row_path(out_dir, k) for k in keys]
    return [json.loads(p.read_text()) for p in paths if p.exists()]


class _Progress:
    """tqdm on a terminal, else a plain line every 5 % (or 30 s) with the ETA."""

    def __init__(self, total: int, enabled: bool) -> None:
        self.total, self.done, self.failed = total, 0, 0
        self.start = self.last = time.perf_counter()
        self.bar = None
        self.enabled = enabled and total > 0
        if self.enabled and sys.stderr.isatty():
            from tqdm import tqdm

            self.bar = tqdm(total=total, unit="run", desc="campaign", file=sys.stderr)

    def update(self, ok: bool) -> None:
        self.done += 1
        self.failed += 0 if ok else 1
        if not self.enabled:
            return
        if self.bar is not None:
            self.bar.update(1)
            if self.failed:
                self.bar.set_postfix(failed=self.failed)
            return
        now = time.perf_counter()
        step = max(1, self.total // 20)
        if self.done % step and now - self.last < 30.0 and self.done != self.total:
            return
        self.last = now
        el = now - self.start
        eta = el / self.done * (self.total - self.done)
        print(f"campaign: {self.done}/{self.total} runs ({self.failed} failed), "
              f"{el:.0f} s elapsed, ETA {eta:.0f} s", file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


@contextlib.contextmanager
def dask_client(scheduler: str | None = None, workers: int | None = None) -> Iterator[Any]:
    """A Dask client: to ``scheduler``, or to a new LocalCluster of single-threaded processes.

    The local cluster is the diagnosis' (:func:`~stellar_cal_ros.diagnosis.parallel.
    local_cluster`: its start method, its timers), with work stealing (the runs are mapped
    at once).
    """
    import dask
    from dask.distributed import Client

    from stellar_cal_ros.diagnosis.parallel import local_cluster

    quiet = logging.getLogger("distributed")
    if quiet.getEffectiveLevel() < logging.WARNING and not log.isEnabledFor(logging.DEBUG):
        quiet.setLevel(logging.WARNING)  # the CLI logs INFO; Dask's INFO lines are noise here
    if scheduler:
        with Client(scheduler) as client:
            yield client
        return
    n = workers or os.cpu_count() or 1
    environ = dict(dask.config.get("distributed.nanny.pre-spawn-environ", {}) or {})
    environ.update(_THREAD_ENV)
    with dask.config.set({"distributed.nanny.pre-spawn-environ": environ}), \
            local_cluster(n, steal=True) as cluster, Client(cluster) as client:
        yield client


def _error_row(run: dict[str, Any], exc: BaseException) -> dict[str, Any]:
    row = {k: (json.dumps(v, sort_keys=True) if isinstance(v, (dict, list)) else v)
           for k, v in run.items()}
    row.update(status="error", error=f"{type(exc).__name__}: {exc}")
    return row


def run_campaign(runs: list[dict[str, Any]], out_dir: str | Path, scheduler: str | None = None,
                 workers: int | None = None, progress: bool = True,
                 client: Any = None) -> CampaignResult:
    """Execute the runs not done yet and write ``OUT_DIR/results.parquet``.

    Parameters
    ----------
    runs : list of dict
        From :func:`stellar_cal_ros.campaign.spec.runs_from_spec` (each with its ``key``).
    out_dir : path
        Where rows, files and the table go (see the module docstring).
    scheduler : str, optional
        Address of an existing Dask scheduler.
    workers : int, optional
        Workers of the local cluster (default: one per core).
    progress : bool
        Progress bar (tqdm on a terminal, plain lines otherwise).
    client : dask.distributed.Client, optional
        Use this client (e.g. a test's cluster) instead of starting one.

    Returns
    -------
    CampaignResult
    """
    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    (out_dir / "runs").mkdir(parents=True, exist_ok=True)
    todo = [r for r in runs if not _done(out_dir, r["key"])]
    failed = 0
    if todo:
        from dask.distributed import as_completed

        bar = _Progress(len(todo), progress)
        ctx = contextlib.nullcontext(client) if client is not None else \
            dask_client(scheduler, workers)
        try:
            with ctx as cl:
                futures = cl.map(execute_run, todo, key=[f"run-{r['key']}" for r in todo],
                                 pure=False)
                by_key = {f.key: r for f, r in zip(futures, todo, strict=True)}
                for fut in as_completed(futures):
                    try:
                        row = fut.result()
                    except Exception as exc:  # noqa: BLE001 - e.g. a killed worker
                        row = _error_row(by_key[fut.key], exc)
                    failed += row.get("status") != "ok"
                    _save_row(out_dir, row)
                    bar.update(row.get("status") == "ok")
        finally:
            bar.close()
    rows = load_rows(out_dir, [r["key"] for r in runs])
    parquet = write_parquet(rows, out_dir / "results.parquet") if rows else None
    return CampaignResult(rows=rows, ran=len(todo), skipped=len(runs) - len(todo),
                          failed=sum(r.get("status") != "ok" for r in rows),
                          seconds=time.perf_counter() - t0, parquet=parquet)


def _column(values: list[Any]):
    import pyarrow as pa

    present = [v for v in values if v is not None]
    if present and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in present) \
            and any(isinstance(v, float) for v in present):
        values = [None if v is None else float(v) for v in values]  # ints and floats mixed
    try:
        return pa.array(values)
    except (pa.ArrowInvalid, pa.ArrowTypeError):
        return pa.array([None if v is None else json.dumps(v, default=str) for v in values])


def write_parquet(rows: list[dict[str, Any]], path: str | Path) -> Path:
    """Write rows (dicts, possibly with different keys) as one Parquet table."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    columns: dict[str, None] = {}
    for row in rows:
        for k in row:
            if k != "_files":
                columns.setdefault(k, None)
    table = pa.table({c: _column([row.get(c) for row in rows]) for c in columns})
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    pq.write_table(table, tmp)
    os.replace(tmp, path)
    return path
