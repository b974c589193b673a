"""What a diagnosis round holds per frame stays small (issue 24.2: the 2-h round's memory).

A 2-h bag has 14 400 frames: a Python object per frame and per effect held through a round
costs ~0.5 kB each (a dataclass, its dict, three array views), 27 MB for the three
direction effects' tables alone; a table joined while its chunks are still held doubles
it at the moment of the join.  And the compiled kernels' cache must survive two processes
compiling into it at once (a diagnosis's Dask workers, a suite beside a benchmark).
"""

from __future__ import annotations

import dataclasses
import gc
import os
import subprocess
import sys
import tracemalloc

import numpy as np
import pytest

from stellar_cal_ros.effects.base import Stage
from stellar_cal_ros.methods.frames import bag_data_from_simulation
from stellar_cal_ros.methods.replay import build_model
from stellar_cal_ros.methods.results import TableSink
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate

DIRECTION = ["aberration", "refraction", "proper_motion"]


@pytest.fixture(scope="module")
def sim():
    sc = get_scenario("psce_rotations")
    return simulate(sc, duration=120.0, seed=5)


def _traced(fn):
    """``fn()`` and the bytes it leaves allocated (tracemalloc), its result kept alive."""
    gc.collect()
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        out = fn()
        gc.collect()
        return out, tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()


def test_a_bags_direction_tables_hold_arrays_not_an_object_per_frame(sim):
    """The three direction effects' tables of a bag (``StarModel.prepare_frames``, held by
    the bag through a round) cost their stars' numbers and a lookup entry per frame:
    the stars stacked once (id and direction, 32 B per star) and shared by the three
    tables, each adding its Δ (24 B per star), and ≤ 300 B per frame for the one lookup
    (117 B measured; 109 B a star in all, 226 before).  One object per frame and effect
    cost 2.2 kB a frame; each table's own copy of the stars and lookup beside the frames'
    inputs 561 B per frame beyond 200 B per star (the code before: ≈ 50 MB on a 2-h bag,
    ≈ 24 MB now)."""
    data = bag_data_from_simulation(sim)
    first = build_model(sim.prior, DIRECTION)
    first.prepare_frames(data)  # the catalogue, pyerfa: once
    other = dataclasses.replace(data)  # a new bag object: its tables made again
    model = build_model(sim.prior, DIRECTION)
    _, held = _traced(lambda: model.prepare_frames(other))
    frames = len(other.frames)
    stars = sum(len(f.catalog_id) for f in other.frames)
    assert frames > 200 and stars > 10 * frames
    per_frame = (held - (32 + 3 * 24) * stars) / frames
    print(f"{held / stars:.1f} B a star, {per_frame:.0f} B a frame beyond the stars' numbers")
    assert per_frame < 300, f"{per_frame:.0f} B a frame beyond the stars numbers"
    # every frame's lookup: the numbers of the first bag's tables (test_effects: pyerfa's)
    def tables(m):
        return {type(e).__name__: e.prepared_table()[1] for e, _, _ in m._chain[Stage.DIRECTION]}

    made, shared = tables(model), tables(first)
    for name, table in made.items():
        assert len(table) == len(shared[name]) > 200, name
        for stamp, row in table.items():
            assert row.delta.shape == row.u.shape == (len(row.ids), 3)
            np.testing.assert_array_equal(row.ids, shared[name][stamp].ids)
            np.testing.assert_array_equal(row.delta, shared[name][stamp].delta)


def test_the_twins_scene_holds_arrays_not_an_object_per_frame(sim):
    """The reliability probe's twin scene (``twin_scene``, held through its renders)
    costs its trajectory's and stars' numbers and ≤ 400 B a frame: the usable stars'
    directions, ids, magnitudes and stated σ (49 B a star: the σ kept for the renders,
    which stacked every message's again), the rates and attitude quaternions per
    IMU sample (56 B), per frame its stamp, counts, environment, gravity and an empty
    context cache (168 B measured).  A ``(FrameInputs, FrameContext)`` pair per frame
    cost 2.3 kB a frame traced (≈ 100 MB of RSS on the 2-h bag) on the code before.
    The probe's renders make no messages: their stars are columns, the centroids (16 B a
    star) and a kept flag (15 B a star beyond 100 B a frame measured)."""
    from stellar_cal_ros.diagnosis import reliability_probe as rp
    from stellar_cal_ros.diagnosis.twin import twin_scene

    data = bag_data_from_simulation(sim)
    twin_scene(data, sim.truth, "psce", imu=False)  # imports, caches: once
    scene, held = _traced(lambda: twin_scene(data, sim.truth, "psce", imu=False))
    frames, samples = len(data.frames), len(data.imu_t)
    stars = sum(len(f.catalog_id) for f in data.frames)
    assert frames > 200 and stars > 10 * frames
    per_frame = (held - 49 * stars - 56 * samples) / frames
    assert per_frame < 400, f"{per_frame:.0f} B a frame beyond the numbers"
    rp.rendered_stars(data, sim.truth, "psce", scene=scene, imu=False)
    plain, made = _traced(lambda: rp.rendered_stars(data, sim.truth, "psce", scene=scene,
                                                    imu=False))
    per_star = (made - 100 * frames) / stars
    assert per_star < 24, f"{per_star:.0f} B a star"
    # the columns are the twin's messages
    twin = rp.rendered(data, sim.truth, "psce", scene=scene, imu=False)
    stamps, counts, ids, uv = plain.stars.kept()
    assert len(stamps) == len(twin.frames)
    np.testing.assert_array_equal(stamps, [f.stamp_ns for f in twin.frames])
    np.testing.assert_array_equal(counts, [len(f.catalog_id) for f in twin.frames])
    np.testing.assert_array_equal(ids, np.concatenate([f.catalog_id for f in twin.frames]))
    np.testing.assert_array_equal(uv, np.concatenate([f.uv for f in twin.frames]))


def test_a_tables_join_does_not_hold_its_chunks_beside_it():
    """``TableSink.table`` joins column by column, dropping each column's chunks: at no
    time are a column's chunks and the whole table held together (peak above the chunks:
    one column), and the sink then holds the table once; the same arrays as one
    ``np.concatenate`` per column, again on a second call."""
    rng = np.random.default_rng(0)
    cols = ("t", "u", "v", "du", "dv", "nis")
    parts = [{k: rng.normal(size=300) for k in cols} for _ in range(200)]
    column = 300 * 200 * 8
    gc.collect()
    tracemalloc.start()  # before the chunks: their release is counted
    try:
        sink = TableSink(chunk_rows=512)
        for p in parts:
            sink.append({k: v.copy() for k, v in p.items()})
        gc.collect()
        before = tracemalloc.get_traced_memory()[0]
        tracemalloc.reset_peak()
        table = sink.table()
        gc.collect()
        after, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak - before < 1.5 * column, (peak - before) / column
    assert after - before < 0.5 * column, (after - before) / column
    for k in cols:
        np.testing.assert_array_equal(table[k], np.concatenate([p[k] for p in parts]))
    again = sink.table()
    assert all(np.array_equal(again[k], table[k]) for k in cols)


def test_a_tables_join_leaves_the_callers_chunks_whole():
    """``TableSink.table`` empties its chunks' dicts as it joins them; a chunk handed to
    ``append`` (one chunk is kept as it came) is the caller's dict, which must keep its
    columns (the join emptied it: ``{}`` after ``table()``)."""
    for rows in (3, 2000):  # below and above a chunk's rows
        chunk = {"a": np.arange(float(rows)), "b": np.ones(rows)}
        sink = TableSink()
        sink.append(chunk)
        table = sink.table()
        assert sorted(chunk) == ["a", "b"] and len(chunk["a"]) == rows
        np.testing.assert_array_equal(table["a"], chunk["a"])
        np.testing.assert_array_equal(sink.table()["b"], chunk["b"])


_STAR_BLOCKS = """
import sys
import numpy as np
from stellar_cal_ros.core.jit import star_blocks
rng = np.random.default_rng(7)
n, N = 6, 9
H = rng.normal(size=(n, 2, N))
A = rng.normal(size=(N, N))
P = A @ A.T + N * np.eye(N)
r = rng.uniform(0.5, 2.0, n)
nu = rng.normal(size=(n, 2))
S, nis = star_blocks(H, P, r, nu)
S0 = np.einsum("iak,kl,ibl->iab", H, P, H) + r[:, None, None] * np.eye(2)
nis0 = np.einsum("ia,iab,ib->i", nu, np.linalg.inv(S0), nu)
assert np.allclose(S, S0, rtol=1e-12, atol=0) and np.allclose(nis, nis0, rtol=1e-10, atol=0)
print(repr(float(nis.sum())))
"""


def test_two_processes_compile_into_one_fresh_numba_cache(tmp_path):
    """Two processes that start at once on an empty cache (``NUMBA_CACHE_DIR``) both
    compile ``star_blocks``, write it, and compute what numpy does; a third one then runs
    it from the cache.  (An acceptance run once failed in a worktree whose cache four
    processes rewrote at once: ``SystemError: CPUDispatcher(star_blocks) returned a result
    with an exception set``.)"""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"), OMP_NUM_THREADS="1",
               OPENBLAS_NUM_THREADS="1")
    env.pop("NUMBA_DISABLE_JIT", None)

    def start():
        return subprocess.Popen([sys.executable, "-c", _STAR_BLOCKS], env=env,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    procs = [start(), start()]
    outs = [p.communicate(timeout=600) for p in procs]
    for p, (_, err) in zip(procs, outs, strict=True):
        assert p.returncode == 0, err[-2000:]
    assert any((tmp_path / "numba").rglob("*star_blocks*.nbi")), "nothing was cached"
    third = start()
    out3, err3 = third.communicate(timeout=600)
    assert third.returncode == 0, err3[-2000:]
    assert outs[0][0] == outs[1][0] == out3 and out3.strip()


def _block_sample_noise(samples):
    """The IMU samples' white noise as one block of every axis (the formula before the
    axis-by-axis loop of ``noise_imu.sample_noise``): the reference it must equal."""
    import math

    from stellar_cal_ros.diagnosis.noise_imu import AXES_DIFFER, WHITE_TOLERANCE

    x = np.asarray(samples, dtype=float)
    x = x[np.all(np.isfinite(x), axis=1)]
    d = np.diff(x, n=2, axis=0)
    mad = np.median(np.abs(d - np.median(d, axis=0)), axis=0) * 1.4826 / math.sqrt(6.0)
    sigma = float(np.median(mad))
    if np.min(mad) > 0 and np.max(mad) > AXES_DIFFER * np.min(mad):
        sigma = float(np.sqrt(np.mean(mad**2)))
    err = sigma * 1.17 / math.sqrt(2.0 * len(d) / 2.4 * 3)
    dc = np.clip(d - np.median(d, axis=0), -4 * mad * math.sqrt(6), 4 * mad * math.sqrt(6))
    rho = float(np.median([np.corrcoef(dc[1:, k], dc[:-1, k])[0, 1] for k in range(3)]))
    return sigma, err, abs(rho + 2.0 / 3.0) < WHITE_TOLERANCE, mad


@pytest.mark.parametrize("case", ["white", "axes differ, gaps", "filtered"])
def test_the_samples_noise_is_computed_axis_by_axis_with_the_blocks_numbers(case):
    """``sample_noise`` (the IMU samples' white noise, read on a 2-h bag's 720 000 × 3
    samples, 17 MB) works one axis at a time: its temporaries are a column's, not the
    block's (traced peak ≤ 1.6 × the samples' bytes, 1.38 measured; the block formula's
    12.5 ×), and every
    number is the block formula's, bit for bit — with NaN rows dropped, axes of unequal
    noise (their RMS), and low-pass-filtered samples (not white)."""
    import tracemalloc

    from stellar_cal_ros.diagnosis.noise_imu import sample_noise

    rng = np.random.default_rng(11)
    n = 120_000
    t = np.arange(n) * 0.01
    x = np.stack([np.sin(0.3 * t), np.cos(0.2 * t), 0.1 * t], 1) + rng.normal(size=(n, 3))
    if case == "axes differ, gaps":
        x[:, 2] *= 2.0
        x[rng.random(n) < 1e-3, rng.integers(0, 3)] = np.nan
    if case == "filtered":
        x = np.stack([np.convolve(c, np.ones(4) / 4, "same") for c in x.T], 1)
    want = _block_sample_noise(x)
    tracemalloc.start()
    try:
        got = sample_noise(x, axes=True)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert got[0] == want[0] and got[1] == want[1] and got[2] == want[2]
    np.testing.assert_array_equal(got[3], want[3])
    assert (case == "filtered") != got[2]  # (the cases do read white / not white)
    assert peak <= 1.6 * x.nbytes, f"{peak / x.nbytes:.2f} x the samples"


def test_the_rolling_columns_read_only_the_columns_named_for_them():
    """The stars' noise copies only ``stats.ROLLING_KEYS`` of the residual table's rows
    for ``rolling_columns`` (the whole table's rows were ≈ 30 MB on a 2-h bag): the
    columns from those keys alone equal those from the whole table."""
    from stellar_cal_ros.diagnosis.stats import ROLLING_KEYS, rolling_columns

    rng = np.random.default_rng(3)
    n = 500
    res = {k: rng.normal(size=n) for k in ("du", "dv", "u", "u_pred", "s_uu", "frame",
                                           "omega_x", "omega_y", "omega_z", "x_st",
                                           "y_st", "v", "v_pred", "t")}
    res["z_st"] = 1.0 + rng.random(n)
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    full = rolling_columns(res, (4000.0, 4010.0), (512.0, 500.0), R)
    few = rolling_columns({k: res[k] for k in ROLLING_KEYS if k in res},
                          (4000.0, 4010.0), (512.0, 500.0), R)
    assert full is not None and np.isfinite(full).all()
    np.testing.assert_array_equal(few, full)
    del res["v_pred"]  # the measured row where no predicted one
    np.testing.assert_array_equal(
        rolling_columns({k: res[k] for k in ROLLING_KEYS if k in res}, (4000.0, 4010.0),
                        (512.0, 500.0), R),
        rolling_columns(res, (4000.0, 4010.0), (512.0, 500.0), R))


_TRIM = """
from stellar_cal_ros.core import memory
before = memory.trim_freed()
import numpy as np
print(before, memory.return_freed_arrays(), memory.trim_freed())
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc_trim")
def test_the_heaps_free_pages_are_trimmed_only_where_the_threshold_was_fixed():
    """``trim_freed`` (between a round's runs, ``parallel._run``; after a bag's read) does
    nothing in a process where ``return_freed_arrays`` did not fix glibc's threshold (a
    library user's, a test's), and trims where it did (a diagnosis, its workers); a user's
    ``MALLOC_MMAP_THRESHOLD_`` leaves both alone."""
    env = {k: v for k, v in os.environ.items() if k != "MALLOC_MMAP_THRESHOLD_"}
    out = subprocess.run([sys.executable, "-c", _TRIM], env=env, capture_output=True,
                         text=True, timeout=120, check=True).stdout.split()
    assert out == ["False", "True", "True"]
    out = subprocess.run([sys.executable, "-c", _TRIM], capture_output=True, text=True,
                         timeout=120, check=True,
                         env=dict(env, MALLOC_MMAP_THRESHOLD_="1048576")).stdout.split()
    assert out == ["False", "False", "False"]


_FAULTS = """
import resource
import numpy as np
from stellar_cal_ros.core import memory
print(memory.return_freed_arrays())
held = []
for size in (457_000, 2 * 457_000):  # a 2-h table's column, its u and v stacked
    a = np.ones(size)
    held.append(np.ones(size))  # an array made after it and kept: a is not the heap's top
    del a
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(20):
        a = np.ones(size)
        a += 1.0
        del a
    print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_a_tables_temporary_columns_reuse_the_heaps_pages():
    """A diagnosis process's temporaries of a 2-h table's size (457 000 rows, 3.7 MB; u and
    v stacked, 7.3 MB) come from the heap, where the next one takes the pages the last
    left: no page faults (``memory.MMAP_THRESHOLD`` 8 MB).  Mapped (at 1 MB), each was
    faulted in afresh: 17 861 and 15 280 faults for the 20 of each size (the 2-h round: 1.7 M
    faults, ≈ 5 of its CPU-s in the kernel)."""
    env = {k: v for k, v in os.environ.items() if k != "MALLOC_MMAP_THRESHOLD_"}
    out = subprocess.run([sys.executable, "-c", _FAULTS], env=env, capture_output=True,
                         text=True, timeout=120, check=True).stdout.split()
    assert out[0] == "True"
    column, stacked = map(int, out[1:])
    assert column < 500 and stacked < 500  # (a page or two; 1 MB threshold: ~15 000 each)


def test_a_bags_direction_tables_forgotten_are_made_again_the_same(sim):
    """``runstats.forget_prepared`` (a round's ``finish`` before its lines, the probe
    before its renders) drops the bag's direction tables; a later run's model makes them
    again with the same numbers."""
    from stellar_cal_ros.diagnosis.runstats import forget_prepared

    data = bag_data_from_simulation(sim)
    first = build_model(sim.prior, DIRECTION)
    first.prepare_frames(data)
    held = {k: v for k, v in data.prepared.items() if isinstance(k, type)}
    assert len(held) == 3 and "inputs" in data.prepared
    forget_prepared(data)
    assert not data.prepared
    again = build_model(sim.prior, DIRECTION)
    again.prepare_frames(data)
    for cls, (_, table) in held.items():
        made = data.prepared[cls][1]
        assert made is not table and len(made) == len(table) > 200
        for a in ("start", "ids", "u", "delta", "weather"):
            np.testing.assert_array_equal(getattr(made, a), getattr(table, a))


_RELEASE = """
import numpy as np
from numba import njit
from stellar_cal_ros.core import jit
from stellar_cal_ros.methods.frame_step import release_linking_ir
x = np.array([0.1, -0.2, 0.3])
e0 = jit.skew3(x)
lib = next(iter(jit.skew3.overloads.values())).library
loaded = bool(sum(jit.skew3._cache_hits.values()))
if not loaded:
    lib._get_module_for_linking()  # numba's copy for linking (made when cached)
assert lib._shared_module is not None
n = release_linking_ir(("stellar_cal_ros.core.jit",))
assert n >= 1 and lib._shared_module is None, n
assert release_linking_ir(("stellar_cal_ros.core.jit",)) == 0
assert np.array_equal(jit.skew3(x), e0)


@njit
def caller(v):
    return jit.skew3(v) * 2.0


assert np.array_equal(caller(x), 2.0 * e0)  # links the kernel's module, made again
assert lib._shared_module is not None
print(loaded, repr(float(np.abs(e0).sum())))
"""


def test_a_loaded_kernel_keeps_its_code_not_its_llvm_module(tmp_path):
    """``frame_step.release_linking_ir`` (each diagnosis run, after the filter ran) drops
    the LLVM module numba keeps of a kernel for later links (≈ 23 MB of a 2-h round's four
    kernels): the kernel computes the same, and a kernel compiled afterwards that calls it
    still links it (its module is made again: from the kept bitcode when it was loaded
    from the cache, from numba's own module when it was compiled here).  A first process
    compiles into a fresh cache, a second loads from it."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"), OMP_NUM_THREADS="1",
               OPENBLAS_NUM_THREADS="1")
    env.pop("NUMBA_DISABLE_JIT", None)
    outs = [subprocess.run([sys.executable, "-c", _RELEASE], env=env, capture_output=True,
                           text=True, timeout=600) for _ in range(2)]
    for p in outs:
        assert p.returncode == 0, p.stderr[-2000:]
    first, second = (p.stdout.split() for p in outs)
    assert first[0] == "False" and second[0] == "True"  # compiled, then loaded
    assert first[1] == second[1]


def test_a_runner_keeps_the_objects_alive_at_its_start_out_of_the_collectors_passes(tmp_path):
    """open_runner freezes the objects alive at its start (gc.freeze: a 2-h round's full
    collections walked ~100 000 objects of its imports, 8 x ~60 ms) and unfreezes them at
    its end, also where the block raises; objects made inside are collected as before.
    Objects someone else froze (a calibrator node's) stay frozen."""
    from stellar_cal_ros.core.memory import frozen_objects
    from stellar_cal_ros.diagnosis.discover import method_spec
    from stellar_cal_ros.diagnosis.parallel import open_runner

    initial = gc.get_freeze_count()  # (a node test's freeze, frozen again at the end)
    try:
        gc.unfreeze()
        gc.freeze()
        held = gc.get_freeze_count()
        with frozen_objects():
            assert gc.get_freeze_count() == held
        assert gc.get_freeze_count() == held  # not thawed
        gc.unfreeze()
        before = gc.get_freeze_count()
        assert before == 0
        with frozen_objects():
            assert gc.get_freeze_count() > before
            cycle: list = []
            cycle.append(cycle)
            del cycle
            assert gc.collect() >= 1  # a cycle made inside is garbage as before
        assert gc.get_freeze_count() == before
        sc = get_scenario("psce_rotations")
        bag = tmp_path / "b.mcap"
        from stellar_cal_ros.sim.world import write_simulation

        write_simulation(simulate(sc, duration=20.0, seed=3), bag)
        with pytest.raises(RuntimeError):
            with open_runner(bag, method_spec("psce"), 0.5, 0):
                assert gc.get_freeze_count() > before
                raise RuntimeError("inside")
        assert gc.get_freeze_count() == before
    finally:
        if initial:
            gc.freeze()
