"""The parent's queue of runs (diagnosis/parallel.py ``_Hand``): the next run to a free worker.

Dask places a task on a worker when it is submitted; a round's runs handed out together
could wait behind a long one on one worker while the other idles (issue 24 item 2).  The
queue keeps at most one run per worker thread out, the highest priority first.
"""

from __future__ import annotations

import contextlib
import threading
import time
from concurrent.futures import CancelledError

import pytest

from stellar_cal_ros.diagnosis import parallel
from stellar_cal_ros.diagnosis.discover import method_spec
from stellar_cal_ros.methods.replay import BagData


class _Future:
    def __init__(self, value):
        self.value, self.callbacks, self.released = value, [], False

    def add_done_callback(self, fn):
        self.callbacks.append(fn)

    def finish(self):
        for fn in self.callbacks:
            fn(self)

    def result(self):
        return self.value

    def release(self):
        self.released = True


def test_at_most_slots_out_highest_priority_first_and_a_cancelled_one_never_out():
    """A fake client: which pieces go out when, and what a cancel and a close do."""
    out = []

    def submit(name, priority=0):
        out.append(_Future(name))
        return out[-1]

    hand = parallel._Hand(submit, 2)
    pieces = {name: hand(name, priority=p)
              for name, p in [("a", 100), ("b", 150), ("c", 100), ("d", 300), ("e", -5)]}
    assert [f.value for f in out] == ["a", "b"]  # two slots: the first two out at once
    pieces["c"].cancel()
    seen = []
    pieces["b"].when_done(seen.append)
    out[1].finish()  # b done: the highest queued (d) goes out, c never will
    assert seen == [pieces["b"]] and [f.value for f in out] == ["a", "b", "d"]
    out[0].finish()
    assert [f.value for f in out] == ["a", "b", "d", "e"]
    assert pieces["d"].result() == "d" and hand.out == 2
    with pytest.raises(CancelledError):
        pieces["c"].result()
    pieces["b"].cancel()  # out already: runs to its end, nothing changes
    out[2].finish()
    out[3].finish()
    assert hand.out == 0 and len(out) == 4
    late = []
    pieces["e"].when_done(late.append)  # finished already: called at once
    assert late == [pieces["e"]]
    # closing: what is queued is cancelled, never handed out
    hand = parallel._Hand(submit, 1)
    first, queued = hand("f"), hand("g")
    hand.close()
    out[4].finish()
    assert [f.value for f in out][4:] == ["f"] and first.result() == "f"
    with pytest.raises(CancelledError):
        queued.result()


#: piece -> the worker thread that ran it (module level: the pieces reach the in-process
#: workers pickled, a closure's dict would be a copy)
_WHERE: dict[str, int] = {}


def _piece(bag, name: str, seconds: float) -> str:
    _WHERE[name] = threading.get_ident()
    time.sleep(seconds)
    return name


@contextlib.contextmanager
def _two_workers(monkeypatch):
    """A runner on two in-process Dask workers of one thread each; its bag is never read
    (every piece is a sleep)."""
    from distributed import LocalCluster

    monkeypatch.setattr(parallel.DaskRuns, "_place_bag", lambda self: self.bag)
    bag = object.__new__(BagData)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                      dashboard_address=None) as cluster, \
            parallel.open_runner(bag, method_spec("psce"), 0.5, 2,
                                 scheduler=cluster.scheduler_address) as runs:
        yield runs


def test_a_free_worker_takes_the_next_piece_not_the_busy_one(monkeypatch):
    """A long and a mid-length piece out, then five short ones handed out while both
    workers are busy (the tail's probes and re-run beside the after-runs): every short one
    goes to the worker that frees first.  Dask alone placed each at submission, on the less
    occupied worker by its estimates (a statistic of the bag: milliseconds, so never stolen
    back), some behind the long piece."""
    _WHERE.clear()
    with _two_workers(monkeypatch) as runs:
        # statistics of the bag first: Dask's estimate of such a piece is milliseconds
        runs.on_bag_each(_piece, [(f"stat {i}", 0.001) for i in range(4)])
        pieces = [runs.later(_piece, "long", 2.0), runs.later(_piece, "mid", 0.3)]
        time.sleep(0.1)
        pieces += [runs.later(_piece, f"short {i}", 0.2) for i in range(5)]
        assert [p() for p in pieces] == ["long", "mid"] + [f"short {i}" for i in range(5)]
    assert _WHERE["long"] != _WHERE["mid"]
    assert {_WHERE[f"short {i}"] for i in range(5)} == {_WHERE["mid"]}


#: the pieces in the order they started (module level, as :data:`_WHERE`)
_STARTED: list[str] = []


def _logged(bag, name: str, seconds: float) -> str:
    _STARTED.append(name)
    time.sleep(seconds)
    return name


def _both_busy(runs, long_s: float, mid_s: float) -> list:
    """Two statistics of the bag, then a ``long`` and a ``mid`` piece out on the two workers
    (:data:`_STARTED` cleared after the statistics)."""
    runs.on_bag_each(_logged, [(f"stat {i}", 0.001) for i in range(2)])
    _STARTED.clear()
    busy = [runs.later(_logged, "long", long_s), runs.later(_logged, "mid", mid_s)]
    time.sleep(0.1)
    return busy


def test_a_spare_piece_goes_out_after_every_queued_one_and_is_dropped_while_queued(
        monkeypatch):
    """``Runs.spare`` (the current model's flexure probe beside the candidates' runs, H273):
    it waits while any other piece is queued, even one queued after it, so that it only
    fills a worker that would idle at a batch's end; ``cancel()`` drops it while queued
    (True) and leaves one that is out to run (False).  In this process nothing runs before
    it is asked for: ``cancel()`` is False and the value is still there."""
    with _two_workers(monkeypatch) as runs:
        busy = _both_busy(runs, 1.5, 0.4)
        spare = runs.spare(_logged, "spare", 0.2)
        dropped = runs.spare(_logged, "dropped", 0.2)
        after = [runs.later(_logged, f"queued {i}", 0.2) for i in range(2)]
        assert dropped.cancel() is True
        assert [p() for p in busy + after] == ["long", "mid", "queued 0", "queued 1"]
        assert spare() == "spare"
        assert spare.cancel() is False  # out already (finished): nothing dropped
    assert _STARTED[:2] in (["long", "mid"], ["mid", "long"])
    assert _STARTED[2:] == ["queued 0", "queued 1", "spare"]
    here = parallel.Runs(object.__new__(BagData), method_spec("psce"), 0.5)
    monkeypatch.setattr(here, "_compute_on_bag", lambda fn, *args: fn(None, *args))
    _STARTED.clear()
    lazy = here.spare(_logged, "lazy", 0.0)
    assert _STARTED == [] and lazy.cancel() is False and lazy() == "lazy"


def test_the_current_models_probe_goes_spare_beside_the_candidates_when_the_top_may_stand_in():
    """``run._Tail.beside``: on several workers the current model's flexure probe starts as
    a spare piece once the base run is in, when the screening's most significant candidate
    may stand in for a flexure (not a camera effect) and is significant by its score; the
    tail takes it while it runs, starts it again at a statistic's priority while it is
    still queued, and drops it when no top asks for it."""
    from types import SimpleNamespace

    from stellar_cal_ros.diagnosis.run import _Tail

    started = []

    class FakeRuns:
        workers, spec, fraction, classes, noise = 2, None, 0.5, (), object()

        def spare(self, fn, *args):
            started.append(("spare", args[1]))
            return parallel.Spare(lambda: "early", lambda: self.queued)

        def later(self, fn, *args):
            started.append(("later", args[1]))
            return lambda: "now"

    runs = FakeRuns()
    base = SimpleNamespace(ok=True, prior=object(), residuals=object(), effects=("installation",))

    def cand(effect, p, status="ranked"):
        return SimpleNamespace(effect=effect, status=status, screen=SimpleNamespace(p_value=p))

    tail = _Tail(runs)
    tail.beside(base, [cand("pixel_aspect", 1e-12), cand("time_offset", 1e-9)])
    assert started == [] and tail.early is None  # a camera effect's: no flexure to hide
    tail.beside(base, [cand("pixel_aspect", 0.2), cand("time_offset", 0.004)])
    assert started == []  # not significant over 2 x 2 tests
    tail.beside(base, [cand("pixel_aspect", 0.2), cand("time_offset", 1e-9)])
    assert started == [("spare", base.prior)]
    runs.queued = False  # out already: the tail takes it
    assert tail._current(base)() == "early" and tail.early is None
    tail.beside(base, [cand("time_offset", 1e-9)])
    runs.queued = True  # still queued: dropped, started again now
    assert tail._current(base)() == "now" and started[-1] == ("later", base.prior)
    tail.beside(base, [cand("time_offset", 1e-9)])
    tail.forget()
    assert tail.early is None
    runs.workers = 1  # in this process: nothing started ahead
    n = len(started)
    tail.beside(base, [cand("time_offset", 1e-9)])
    assert len(started) == n and tail.early is None


def test_a_queued_piece_asked_for_goes_out_next():
    """``_Hand.promote`` (a spare piece asked for while still queued, ``DaskRuns.spare``):
    it goes out at the next free slot, before the pieces queued above its old priority; one
    out already, or queued at least as high, is left where it is (False).  On coord a
    spare asked for waited behind every queued piece."""
    out = []

    def submit(name, priority=0):
        out.append(_Future(name))
        return out[-1]

    hand = parallel._Hand(submit, 1)
    pieces = {name: hand(name, priority=p) for name, p in
              [("busy", 0), ("spare", parallel.SPARE_PRIORITY), ("a", 100), ("b", 100)]}
    assert hand.promote(pieces["busy"], parallel.ON_BAG_PRIORITY) is False  # out already
    assert hand.promote(pieces["a"], 50) is False  # queued higher already
    assert hand.promote(pieces["spare"], parallel.ON_BAG_PRIORITY) is True
    out[0].finish()
    assert [f.value for f in out] == ["busy", "spare"]
    out[1].finish()
    out[2].finish()
    assert [f.value for f in out] == ["busy", "spare", "a", "b"]


def test_the_rolling_shutters_rerun_goes_spare_and_is_dropped_where_no_line_asks_for_it(
        monkeypatch):
    """``rolling.start_lines_without`` (the tail's re-run beside the line tests) starts as a
    spare piece: on the several round (H281) its fit's p was under START_P with no rolling
    line to explain, and at a statistic's priority it went before the refined model's
    flexure probe, which ended the round alone.  ``first_if_cause`` drops it where no
    line of its direction asks for it, and takes its value where one does."""
    from types import SimpleNamespace

    from stellar_cal_ros.diagnosis import rolling, stats

    made, dropped = [], []

    class FakeRuns:
        fraction, spec, noise, classes = 0.5, None, None, ()

        def spare(self, fn, *args):
            made.append(fn.__name__)
            return parallel.Spare(lambda: (("gone",), None), lambda: dropped.append(1) or True)

        def later(self, fn, *args):  # pragma: no cover - the re-run must not go out so
            raise AssertionError("started at a statistic's priority")

    fit = {"p_value": 0.01, "axis": "v", "coefficient": 1e-5}
    monkeypatch.setattr(rolling, "of_run", lambda run, fraction, axis=None: fit)
    run = SimpleNamespace(ok=True, prior=object(), effects=(), calibration=None)
    started = rolling.start_lines_without(run, FakeRuns(), None)
    assert made == ["lines_without_on_bag"] and started[0] is fit
    line = SimpleNamespace(regressor="u residual vs u (column)")
    assert not stats.rolling_axis(line.regressor)
    found, follows = rolling.first_if_cause([line], run, FakeRuns(), None, started=started)
    assert found == [line] and follows == set() and dropped == [1]
    rolling.drop_unasked([line], started)  # (output.causes_first: before the drifts' runs)
    assert dropped == [1, 1]
    shutter_line = SimpleNamespace(regressor=stats.ROLLING + " ...)")
    rolling.drop_unasked([line, shutter_line], started)
    assert dropped == [1, 1]  # a line of its own asks for it: kept


def test_a_spare_piece_asked_for_while_queued_goes_before_the_queued_runs(monkeypatch):
    """``DaskRuns.spare`` asked for while still queued (the shutter's re-run a rolling line
    asks for, H281): it goes out at the next free worker, before the pieces queued above
    its spare priority, not after all of them."""
    with _two_workers(monkeypatch) as runs:
        busy = _both_busy(runs, 1.0, 0.6)
        spare = runs.spare(_logged, "spare", 0.1)
        after = [runs.later(_logged, f"queued {i}", 0.1) for i in range(2)]
        assert spare() == "spare"
        assert [p() for p in busy + after] == ["long", "mid", "queued 0", "queued 1"]
    assert _STARTED[2:] == ["spare", "queued 0", "queued 1"]
