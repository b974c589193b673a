"""The round's timeline (diagnosis/timeline.py) and its replay on idle cores
(benchmarks/round_timeline.py): what doc/benchmarks.md's 1 -> 2 worker figures rest on."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import pytest

from stellar_cal_ros.diagnosis import parallel, timeline
from stellar_cal_ros.diagnosis.discover import method_spec
from stellar_cal_ros.diagnosis.runstats import RunSummary
from stellar_cal_ros.methods.replay import BagData

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from round_timeline import replay  # noqa: E402


def _busy(seconds: float) -> None:
    end = time.process_time() + seconds
    while time.process_time() < end:
        pass


def test_runs_in_this_process_are_on_the_timeline(tmp_path, monkeypatch):
    """Each run is a task of its batch with its CPU; the parent's work between batches is
    serial; the replay's path is the parent's CPU (every run here is in the parent)."""
    path = tmp_path / "t.jsonl"
    monkeypatch.setenv(timeline.ENV, str(path))

    def fake_evaluate(bag, spec, prior, effects, *rest):
        _busy(0.05 * len(effects))
        return RunSummary(effects=tuple(effects))

    monkeypatch.setattr(parallel, "evaluate", fake_evaluate)
    bag = object.__new__(BagData)  # never read: every run is faked
    with parallel.open_runner(bag, method_spec("psce"), 0.5, 0) as runs:
        runs.run_all([parallel.Task("a", None, ("x",)), parallel.Task("b", None, ("x", "y"))])
        _busy(0.1)  # the parent's own work between two batches
        runs.run_all([parallel.Task("c", None, ("x",))])
    events = [json.loads(line) for line in path.read_text().splitlines()]
    tasks = {e["key"]: e for e in events if e["kind"] == "task"}
    assert set(tasks) == {"a", "b", "c"}
    assert tasks["b"]["cpu"] == pytest.approx(0.1, abs=0.03)
    assert [tasks[k]["batch"] for k in "abc"] == [1, 1, 2]
    batches = [e for e in events if e["kind"] == "batch"]
    assert [b["wait"] for b in batches] == [["a", "b"], ["c"]]
    r = replay(events)
    assert r["serial"] >= 0.1
    end = next(e for e in events if e["kind"] == "end")
    assert r["idle"] == pytest.approx(end["cpu"], abs=0.02)  # all of it on one core
    monkeypatch.delenv(timeline.ENV)
    timeline.write({"kind": "never"})  # off: nothing written
    assert len(path.read_text().splitlines()) == len(events)


def _batch_with_a_run_ahead(cpu1: float) -> list[dict]:
    """The parent (pid 1) and two workers (2, 3, started after 0.5 and 2 CPU-s); batch 1
    handed out at the parent's 1.5 CPU-s (done at ``cpu1``): a on 2 (4 CPU-s, waited for),
    b on 3 (5 CPU-s, made ahead)."""
    p, w1, w2 = 1, 2, 3
    return [
        {"kind": "cluster", "pid": p, "time": 0.0, "cpu": 1.0},
        {"kind": "process", "pid": w1, "created": 0.0, "start": 1.0, "cpu": 0.5},
        {"kind": "process", "pid": w2, "created": 0.0, "start": 1.0, "cpu": 2.0},
        {"kind": "batch", "pid": p, "batch": 1, "submit": 10.0, "done": 20.0,
         "cpu0": 1.5, "cpu1": cpu1, "wait": ["a"]},
        {"kind": "task", "pid": w1, "key": "a", "batch": 1, "start": 11.0, "end": 19.0,
         "cpu": 4.0, "read": 0.0},
        {"kind": "task", "pid": w2, "key": "b", "batch": 1, "start": 11.0, "end": 25.0,
         "cpu": 5.0, "read": 0.0},
    ]


def test_the_replay_runs_each_worker_s_tasks_in_order_after_its_start():
    """Two workers: the path is the parent's serial CPU plus, per batch, the busiest
    worker's runs -- a worker starts when the cluster was asked for plus its own start; a
    run made ahead holds its worker up, the parent waits only for its batch's runs."""
    p, w1, w2 = 1, 2, 3
    ev = _batch_with_a_run_ahead(1.7) + [
        # the parent works 1 CPU-s, then batch 2: c on w1, d on w2 (after b)
        {"kind": "batch", "pid": p, "batch": 2, "submit": 21.0, "done": 40.0,
         "cpu0": 2.7, "cpu1": 2.9, "wait": ["c", "d"]},
        {"kind": "task", "pid": w1, "key": "c", "batch": 2, "start": 21.5, "end": 30.0,
         "cpu": 3.0, "read": 0.0},
        {"kind": "task", "pid": w2, "key": "d", "batch": 2, "start": 25.5, "end": 39.0,
         "cpu": 1.0, "read": 0.0},
        {"kind": "end", "pid": p, "time": 41.0, "cpu": 3.4},
    ]
    # a run started and never asked for (its batch never closed) holds its worker up too
    never = {"kind": "task", "pid": w2, "key": "e", "batch": 9, "start": 22.0, "end": 23.0,
             "cpu": 0.5, "read": 0.0}
    assert replay(ev + [never])["idle"] == pytest.approx(10.0)  # d after it: 8.5..9.5
    never["cpu"] = 1.5
    assert replay(ev + [never])["idle"] == pytest.approx(11.0)  # d 9.5..10.5, + 0.5
    r = replay(ev)
    # a: w1 free at 1 + 0.5, batch at 1.5 -> 1.5..5.5; b: w2 free at 3 -> 3..8
    # the parent: 5.5 + 1 = 6.5; c 6.5..9.5; d after b: 8..9 -> 9.5; + 0.5 at the end
    assert r["idle"] == pytest.approx(10.0)
    assert r["serial"] == pytest.approx(1.5 + 1.0 + 0.5)
    assert r["beside"] == pytest.approx(0.2 + 0.2)


def test_the_replay_waits_for_a_run_made_ahead_where_the_parent_takes_it():
    """A run made ahead in one batch (a round's candidate beside the noise's base run) and
    taken, still running, by a later batch is waited for there: the parent goes on only
    once it is done (before, the replay waited for the taking batch's own runs only)."""
    p, w1 = 1, 2
    ev = _batch_with_a_run_ahead(1.5) + [
        # the parent works 1 CPU-s, takes b (batch 2 runs nothing new), then hands out c
        {"kind": "batch", "pid": p, "batch": 2, "submit": 21.0, "done": 26.0,
         "cpu0": 2.5, "cpu1": 2.5, "wait": ["b"]},
        {"kind": "batch", "pid": p, "batch": 3, "submit": 27.0, "done": 40.0,
         "cpu0": 2.5, "cpu1": 2.5, "wait": ["c"]},
        {"kind": "task", "pid": w1, "key": "c", "batch": 3, "start": 27.5, "end": 39.0,
         "cpu": 3.0, "read": 0.0},
        {"kind": "end", "pid": p, "time": 41.0, "cpu": 3.0},
    ]
    # a 1.5..5.5, b 3..8; the parent 5.5 + 1 = 6.5, waits for b to 8; c 8..11; + 0.5
    assert replay(ev)["idle"] == pytest.approx(11.5)
