"""The compiled star step (numba) against the numpy reference path (issue 17, item 2).

* the compiled projection equals :meth:`CameraModel.project` (pixels and both Jacobians) to
  rounding, on a camera with every distortion term, the rational denominator and a tilt;
* one prediction of a frame equals :meth:`StarModel.predict` to rounding;
* a 300 s PSCE replay gives the same estimates through both paths.  Not bit for bit: the
  start-up is ill-conditioned and amplifies any last-bit difference — one ulp changed in
  one centroid of the first frame moves the final estimate by ~2e-4 σ through the numpy
  path alone (measured; :mod:`stellar_cal_ros.methods.star_chain`).  The bound,
  ``SIGMA_TOL`` = 2e-3 σ, is a few times that and ~1000× below anything a wrong Jacobian
  term or a wrong time shift would give;
* a model with an effect that has no compiled form (a user's ``--effect-module``) predicts
  through the effects' methods by itself and gives the same estimates.
"""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest

from stellar_cal_ros.core.camera import CameraModel
from stellar_cal_ros.core.rotation import so3_log
from stellar_cal_ros.effects import registry
from stellar_cal_ros.effects.base import FrameContext
from stellar_cal_ros.effects.time_offset import TimeOffset
from stellar_cal_ros.methods.frames import bag_data_from_simulation
from stellar_cal_ros.methods.kernel import StarFilter
from stellar_cal_ros.methods.replay import replay
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate

jit = pytest.importorskip("stellar_cal_ros.core.jit")
if not jit.HAVE_NUMBA:  # pragma: no cover
    pytest.skip("numba is not installed: only the numpy path exists", allow_module_level=True)

SIGMA_TOL = 2e-3  # |Δθ| / σ after the replay (see the module docstring)
CALL_RTOL = 1e-12  # one call, relative to the largest entry


@pytest.fixture(scope="module")
def sim_data():
    """A 300 s psce_rotations simulation (seed 3) and its bag data."""
    sim = simulate(get_scenario("psce_rotations"), duration=300.0, seed=3)
    return sim, bag_data_from_simulation(sim)


def _replay(sim_data, compiled: bool, monkeypatch):
    sim, data = sim_data
    monkeypatch.setattr(StarFilter, "compiled_step", compiled)
    return replay(data, sim.prior, "psce").filter


def _close(a: np.ndarray, b: np.ndarray) -> None:
    scale = max(float(np.max(np.abs(b))), 1e-300)
    assert float(np.max(np.abs(a - b))) <= CALL_RTOL * scale


def test_projection_kernel_equals_camera_model() -> None:
    rng = np.random.default_rng(4)
    dist = [-0.1, 0.02, 1e-3, -2e-3, 0.01, 0.05, -0.01, 2e-3, 1e-3, -1e-3, 2e-4, 3e-4,
            0.01, -0.02]
    cam = CameraModel(width=1024, height=1024, fx=3970.0, fy=3975.0, cx=515.0, cy=520.0,
                      distortion=dist)
    d = np.column_stack([rng.uniform(-0.12, 0.12, (200, 2)), np.ones(200)])
    d /= np.linalg.norm(d, axis=1)[:, None]
    uv, J_d, J_p = cam.project(d, jacobians=True)
    p = cam.parameters()
    out = np.empty((200, 2)), np.empty((200, 2, 3)), np.empty((200, 2, 18))
    jit.project_points(d, p, jit.tilt_kernel(p[16], p[17]), 1, *out)
    for a, b in zip(out, (uv, J_d, J_p), strict=True):
        _close(a, b)


def test_one_prediction_equals_the_numpy_chain(sim_data) -> None:
    sim, data = sim_data
    res = replay(data, sim.prior, "psce", effects=["time_offset"], keep_tables=False)
    f = res.filter
    assert f.model.compiled_chain() is not None and f.model.has_time_effect
    rng = np.random.default_rng(5)
    fr = data.frames[-1]
    u = rng.normal(size=(15, 3)) * 0.05 + f.R_i_b @ f.model._R_imu_st_prior @ [0, 0, 1.0]
    u /= np.linalg.norm(u, axis=1)[:, None]
    ctx_a, ctx_b = (_ctx(fr) for _ in range(2))
    theta = f.theta + rng.normal(size=f.theta.size) * 1e-3 * np.abs(f.theta)
    omega, phi = np.array([0.01, -0.02, 0.05]), np.array([1e-4, -2e-4, 3e-4])
    for ph in (None, phi):
        a = f.model.predict_state(theta, u, ctx_a, f.R_i_b, omega, 0.013, ph, compiled=True)
        b = f.model.predict_state(theta, u, ctx_b, f.R_i_b, omega, 0.013, ph, compiled=False)
        for name in ("uv", "H_attitude", "H_parameters", "directions_st", "R_i_st"):
            _close(getattr(a, name), getattr(b, name))
        assert a.t_exposure == pytest.approx(b.t_exposure, abs=1e-12)
        _close(ctx_a.R_i_st, ctx_b.R_i_st)


@pytest.mark.parametrize("estimated, fixed", [
    (["aberration", "refraction", "pixel_aspect", "thermal_focal_length"],
     {"proper_motion": {"scale": 0.7}}),
    (["aberration", "pixel_aspect"],
     {"thermal_focal_length": {"coefficient_per_c": 3e-5, "reference_temperature_c": 10.0}})])
def test_direction_and_bilinear_effects_predict_equal_the_numpy_chain(sim_data, estimated,
                                                                      fixed) -> None:
    """The astrometric DIRECTION effects (``u' = u + s Δ``, Δ per frame) and the bilinear
    camera effects (pixel aspect, thermal focal length: ``BilinearCamera``) in the compiled
    chain: centroids and every Jacobian column equal :meth:`StarModel.predict`'s, with the
    effects estimated and fixed at a prior value (a prior's effects block)."""
    from stellar_cal_ros.methods.star_model import StarModel

    sim, data = sim_data
    fr = data.frames[len(data.frames) // 2]
    prior = copy.deepcopy(sim.prior)
    prior.effects = fixed
    model = StarModel(registry.create_many(["installation", "focal_length", "radial_k1k2",
                                            *estimated]), prior)
    assert model.compiled_chain() is not None and model.fixed_effects
    theta = model.initial_value.copy()
    for eid, v in (("aberration", 0.8), ("refraction", 1.3), ("pixel_aspect", 2e-3),
                   ("thermal_focal_length", 4e-5)):
        if eid in model.slices:
            theta[model.slices[eid]] = v
    ok = np.isfinite(fr.right_ascension)
    u = np.column_stack([np.cos(fr.declination) * np.cos(fr.right_ascension),
                         np.cos(fr.declination) * np.sin(fr.right_ascension),
                         np.sin(fr.declination)])[ok]
    z = u.mean(axis=0) / np.linalg.norm(u.mean(axis=0))  # boresight on the frame's stars
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    R = np.column_stack([x, np.cross(z, x), z]) @ model._R_imu_st_prior.T  # R_i_b

    def ctx():
        return FrameContext(stamp=fr.stamp_ns * 1e-9, catalog_id=fr.catalog_id[ok].astype(int),
                            site=data.site, pressure_pa=95000.0, air_temperature_c=5.0,
                            head_temperature_c=27.0)

    for ph in (None, np.array([1e-4, -2e-4, 3e-4])):
        a = model.predict_state(theta, u, ctx(), R, np.zeros(3), 0.0, ph, compiled=True)
        b = model.predict_state(theta, u, ctx(), R, np.zeros(3), 0.0, ph, compiled=False)
        for name in ("uv", "H_attitude", "H_parameters", "directions_st"):
            _close(getattr(a, name), getattr(b, name))
        for eid in estimated:  # their columns are there
            assert np.max(np.abs(a.H_parameters[:, :, model.slices[eid]])) > 0


def _ctx(frame) -> FrameContext:
    """A bare frame context at the frame's stamp."""
    return FrameContext(stamp=frame.stamp_ns * 1e-9)


def _sigma_units(a, b) -> float:
    sig = np.sqrt(np.diag(b.P))[:b.theta.size]
    return float(np.max(np.abs(a.theta - b.theta) / sig))


def test_compiled_callers_pass_predict_chain_no_literal_flags() -> None:
    """A constant passed to a compiled function from compiled code makes numba compile it
    again for that literal (``Literal[bool](False)``): predict_chain and its projection
    were compiled three times in a fresh checkout.  Its compiled callers pass typed values."""
    import ast
    import inspect

    from stellar_cal_ros.methods import frame_step, star_chain

    calls = 0
    for module in (frame_step, star_chain):
        for node in ast.walk(ast.parse(inspect.getsource(module))):
            if isinstance(node, ast.Call) and getattr(node.func, "id", "") == "predict_chain":
                calls += 1
                assert not any(isinstance(a, ast.Constant) for a in node.args), node.lineno
    assert calls >= 2


def test_replay_same_estimates_both_paths(sim_data, monkeypatch) -> None:
    fast = _replay(sim_data, True, monkeypatch)
    ref = _replay(sim_data, False, monkeypatch)
    assert fast.model.compiled_chain() is not None
    assert fast.counters.updates == ref.counters.updates
    assert _sigma_units(fast, ref) <= SIGMA_TOL
    np.testing.assert_allclose(np.sqrt(np.diag(fast.P)), np.sqrt(np.diag(ref.P)), rtol=1e-6)


def test_fused_frame_step_taken_and_equal_to_numpy(sim_data, monkeypatch) -> None:
    """One compiled call per frame (issue 24.1): taken for (nearly) every update, and the
    consider sensitivity, its score and information, and the running statistics equal the
    numpy path's (the same start-up amplification as above bounds θ; the sums are far
    less sensitive)."""
    from stellar_cal_ros.methods import frame_step

    sim, data = sim_data
    calls = _count_calls(monkeypatch, frame_step.FusedStep, "call")
    monkeypatch.setattr(StarFilter, "batched_step", False)  # one call a frame (counted)
    runs = []
    for compiled in (True, False):
        monkeypatch.setattr(StarFilter, "compiled_step", compiled)
        # an astrometric DIRECTION effect too: its Δ comes with each frame
        runs.append(replay(data, sim.prior, "psce", consider=["radial_k3", "proper_motion"],
                           keep_tables=False))
        if compiled:
            n_fused = len(calls)
    fast, ref = runs
    assert len(calls) == n_fused  # the numpy path never calls it
    assert fast.counters["updates"] == ref.counters["updates"]
    assert n_fused >= 0.95 * fast.counters["updates"]
    assert _sigma_units(fast.filter, ref.filter) <= SIGMA_TOL
    a, b = fast.filter.sensitivity, ref.filter.sensitivity
    assert a.frames == b.frames > 0
    np.testing.assert_allclose(a.info, b.info, rtol=1e-4)
    # the score is a sum of innovations: compared in units of its standard deviation
    assert np.all(np.abs(a.score - b.score) <= 1e-2 * np.sqrt(np.diag(b.info)))
    sa, sb = fast.stats, ref.stats
    sa, sb = (s.current() if hasattr(s, "current") else s for s in (sa, sb))
    assert (sa.frames, sa.stars, sa.gated) == (sb.frames, sb.stars, sb.gated)
    for name in ("sum_logdet", "sum_nis", "sum_du2", "sum_dv2", "sum_suu", "sum_svv"):
        assert getattr(sa, name) == pytest.approx(getattr(sb, name), rel=1e-5), name


def _count_calls(monkeypatch, owner, name: str) -> list:
    """``owner.name`` wrapped for the test: each call appends to the returned list."""
    calls = []
    original = getattr(owner, name)

    def counted(*a, **k):
        calls.append(1)
        return original(*a, **k)

    monkeypatch.setattr(owner, name, counted)
    return calls


def _damaged(data, gaps=((60.0, 60.025), (150.0, 153.0)), dropped=lambda i: i % 37 == 5,
             outliers=lambda i: i % 23 == 7, few=lambda i: 400 <= i < 404 or i % 97 == 50,
             bad: int = 300, twice: int = 200, seed: int = 11):
    """The bag with IMU gaps (``gaps``: one bridged, one long), dropped frames, frames with
    outliers (gated stars), frames with too few stars (skipped; a run of them re-acquires),
    a frame with a non-finite centroid (``bad``) and a frame sent twice (``twice``); the
    defaults: a 300 s bag's."""
    import dataclasses

    t = data.imu_t
    keep = np.ones(len(t), dtype=bool)
    for a, b in gaps:
        keep &= ~((t > a) & (t < b))
    rng = np.random.default_rng(seed)
    frames = []
    for i, fr in enumerate(data.frames):
        if dropped(i):
            continue
        fr = copy.deepcopy(fr)
        if outliers(i):  # gated
            fr.uv[:3] += rng.choice([-1.0, 1.0], size=(3, 2)) * 40.0
        if few(i):
            fr = dataclasses.replace(fr, catalog_id=fr.catalog_id[:2],
                                     right_ascension=fr.right_ascension[:2],
                                     declination=fr.declination[:2], uv=fr.uv[:2],
                                     magnitude=fr.magnitude[:2], sigma=fr.sigma[:2])
        if i == bad:
            fr.uv[1, 0] = np.nan
        frames.append(fr)
        if i == twice:
            frames.append(copy.deepcopy(fr))
    return dataclasses.replace(data, imu_t=t[keep], imu_w=data.imu_w[keep],
                               imu_f=data.imu_f[keep], frames=frames)


def _count_batches(monkeypatch) -> tuple[list, list]:
    """Lists that record each frame taken from a batch and each batch committed at once."""
    from stellar_cal_ros.methods import frame_step

    taken, committed = [], []
    original = frame_step.FrameBatch.take
    commit = StarFilter.commit_batch

    def counted(self, *a, **k):
        out = original(self, *a, **k)
        taken.append(out is not None)
        return out

    def counted_commit(self, *a, **k):
        out = commit(self, *a, **k)
        committed.append(0 if out is None else out.count)
        return out

    monkeypatch.setattr(frame_step.FrameBatch, "take", counted)
    monkeypatch.setattr(StarFilter, "commit_batch", counted_commit)
    return taken, committed


def test_batched_frame_steps_equal_one_call_a_frame(sim_data, monkeypatch) -> None:
    """A replay's runs of frames stepped in one compiled call (``StarFilter.batched_step``)
    and committed a batch at once (``StarFilter.commit_batch``: counters, gate counts, gyro
    watch; the driver's statistics and history rows per batch) give what one call a frame
    gives, bit for bit: the state, the consider sensitivity and its score and information
    (the evaluation window starts mid-run), the history and residual tables, the statistics,
    the gyro watch's records, chain and verdicts and every counter — on a bag with IMU gaps,
    dropped, gated, skipped, re-acquiring, invalid and repeated frames; and without tables
    (no ``FrameUpdate`` made on the batch path) the same statistics."""
    sim, data = sim_data
    data = _damaged(data)
    taken, committed = _count_batches(monkeypatch)
    runs = {}
    for batched in (False, True):
        monkeypatch.setattr(StarFilter, "batched_step", batched)
        runs[batched] = replay(data, sim.prior, "psce", consider=["radial_k3"])
        runs[batched, "no tables"] = replay(data, sim.prior, "psce", consider=["radial_k3"],
                                            keep_tables=False)
    one, batch = runs[False], runs[True]
    c = batch.counters
    assert c["skipped_few_stars"] >= 5 and c["reinitializations"] >= 1 and c["imu_gaps"] >= 1
    assert c["stars_gated"] >= 30 and c["frames_duplicate"] == 1 and c["stars_invalid"] >= 1
    # most frames came out of a batch, most of them committed a batch at once
    assert sum(taken) + sum(committed) >= 0.9 * c["updates"]
    assert sum(committed) >= 0.5 * c["updates"] and sum(taken) >= 10
    assert one.counters == c
    assert vars(runs[False, "no tables"].stats) == vars(runs[True, "no tables"].stats) == \
        vars(one.stats)
    assert runs[False, "no tables"].counters == runs[True, "no tables"].counters == c
    wa, wb = one.filter.gyro_watch, batch.filter.gyro_watch
    assert (wa is None) == (wb is None) and one.filter.data_faults == batch.filter.data_faults
    if wa is not None:
        assert sorted(wa) == sorted(wb) and len(wa["t"]) >= 10
        for key in wa:
            np.testing.assert_array_equal(np.asarray(wa[key], dtype=object),
                                          np.asarray(wb[key], dtype=object), err_msg=key)
    _same_run(one, batch, 1)


def _same_run(one, batch, rows: int) -> None:
    """Two replays' state, consider sensitivity, tables (``rows`` or more) and statistics
    are the same floats."""
    fa, fb = one.filter, batch.filter
    for name in ("theta", "P", "R_i_b"):
        np.testing.assert_array_equal(getattr(fa, name), getattr(fb, name), err_msg=name)
    sa, sb = fa.sensitivity, fb.sensitivity
    assert sa.frames == sb.frames > 0
    for name in ("M", "score", "info"):
        np.testing.assert_array_equal(getattr(sa, name), getattr(sb, name), err_msg=name)
    for table in ("history", "residuals"):
        ta, tb = getattr(one, table), getattr(batch, table)
        assert list(ta) == list(tb) and len(ta["t"]) >= rows
        for k in ta:
            np.testing.assert_array_equal(ta[k], tb[k], err_msg=f"{table}.{k}")
    assert vars(one.stats) == vars(batch.stats)


@pytest.mark.parametrize("gyro_fault", ["raise", "off"])
def test_batched_steps_with_a_time_offset_equal_one_call_a_frame(monkeypatch,
                                                                  gyro_fault) -> None:
    """A time offset held as a consider parameter (the screening's candidate) keeps every
    frame's exposure shift at its value: the replay's frames are stepped in batches, and the
    state, the consider sensitivity (with its ``∂uv/∂Δt`` column: the offset's information
    is positive), its score and information, the tables, statistics and counters are those
    of one call a frame, bit for bit.  An estimated time offset moves the shift at each
    update: the batch finds each frame's exposure time from the state before it, the same
    floats (the readiness boundary and damaged frames: the test after this).  A 19 s bag whose
    prior offset (4 ms) is not the truth's (0): the shift is in every exposure time; with the
    gyro watch (its first frames: each frame taken from the batch) and without it (batches
    committed at once)."""
    sim = simulate(get_scenario("psce_rotations"), duration=19.0, seed=4)
    data = bag_data_from_simulation(sim)
    prior = copy.deepcopy(sim.prior)
    prior.time_offset = 0.004
    taken, committed = _count_batches(monkeypatch)
    for kw in ({"consider": ["time_offset", "radial_k3"]},
               {"effects": ["time_offset"], "consider": ["radial_k3"]}):
        runs = {}
        for batched in (False, True):
            monkeypatch.setattr(StarFilter, "batched_step", batched)
            taken.clear()
            committed.clear()
            runs[batched] = replay(data, prior, "psce", gyro_fault=gyro_fault, **kw)
        one, batch = runs[False], runs[True]
        f = batch.filter
        n_up = batch.counters["updates"]
        assert n_up >= 30 and f.model.has_time_effect
        i_dt = f.model.slices["time_offset"].start
        assert f.model.fixed_exposure_shift(f.theta, f.P_est) == \
            (None if "effects" in kw else prior.time_offset)
        if "effects" in kw:  # estimated: the shift moves, the call follows it
            assert i_dt < f.P_est and sum(taken) + sum(committed) >= 0.9 * n_up
            assert f.theta[i_dt] != prior.time_offset
        else:
            assert i_dt >= f.P_est and f.theta[i_dt] == prior.time_offset
            assert sum(taken) + sum(committed) >= 0.9 * n_up
            if gyro_fault == "off":
                assert sum(committed) >= 0.5 * n_up
            k = i_dt - f.P_est
            assert f.sensitivity.info[k, k] > 0 and np.any(f.sensitivity.M[:, k] != 0)
        assert one.counters == batch.counters
        _same_run(one, batch, 30)


def _damaged_short(data):
    """:func:`_damaged` for a 19 s bag (frames at 2 Hz; four in a row with too few stars)."""
    return _damaged(data, ((6.0, 6.025), (14.0, 14.4)), lambda i: False, lambda i: i % 7 == 3,
                    lambda i: 20 <= i < 24 or i == 9, 12, 15, 12)


#: look-aheads that put a frame at the readiness boundary of the 19 s bags' pumps (IMU
#: blocks of 0.5 s, frames at 2 Hz: the newest IMU stamp is 0.2463 s after the first frame
#: not handed on): 2 ms inside the first update's shift change (4 ms -> ~0: not ready by the
#: prior's offset, ready by the run's estimate), and 15 µs inside the estimate's wander
#: later (ready by the state before a run, not by the one its turn finds)
_BOUNDARY_LOOKAHEADS = (0.2443, 0.246315)


@pytest.mark.parametrize("method", ["psce", "swaying_base"])
def test_batched_steps_with_an_estimated_time_offset_equal_one_call_a_frame(monkeypatch,
                                                                           method) -> None:
    """An estimated time offset: the replay's frames are stepped in batches whose compiled
    call finds each frame's exposure time, IMU rows and readiness from the state after the
    frame before, and the state, sensitivity (score, information), tables, statistics and
    counters are those of one call a frame, bit for bit — on a short bag (19 s) with gated,
    skipped, re-acquired, invalid and repeated frames and IMU gaps, and on the same bag
    clean with the driver's pumps every 0.5 s of IMU and a look-ahead that puts frames on
    the readiness boundary: a frame not
    ready by the state before a run but ready by the state its turn finds (handed on in the
    same pump) and one ready before but not at its turn (left pending: the batch stops
    before it).  The swaying-base filter (velocity driven by the accelerometer) takes no
    compiled step: one call a frame in both, the same floats."""
    from stellar_cal_ros.methods import driver as driver_mod
    from stellar_cal_ros.methods import replay as replay_mod
    from stellar_cal_ros.methods.driver_config import DriverConfig

    scenario = "psce_rotations" if method == "psce" else "swaying"
    sim = simulate(get_scenario(scenario), duration=19.0, seed=4)
    clean = bag_data_from_simulation(sim)
    prior = copy.deepcopy(sim.prior)
    prior.time_offset = 0.004
    taken, committed = _count_batches(monkeypatch)
    events = {"left": 0, "runs": []}
    run_out = driver_mod.Calibrator._run_out

    def counted(self, run, *a):
        events["runs"][-1] += 1
        done = run_out(self, run, *a)
        events["left"] += not done
        return done

    pump = driver_mod.Calibrator._pump

    def pumped(self, *a, **k):
        events["runs"].append(0)
        return pump(self, *a, **k)

    monkeypatch.setattr(driver_mod.Calibrator, "_run_out", counted)
    monkeypatch.setattr(driver_mod.Calibrator, "_pump", pumped)
    monkeypatch.setattr(replay_mod, "IMU_BLOCK", 50)
    both = 0
    cases = [(clean, look) for look in _BOUNDARY_LOOKAHEADS] + [(_damaged_short(clean), 0.29)]
    for data, look in cases:
        monkeypatch.setattr(replay_mod, "REPLAY_LOOKAHEAD_S", look)
        for gyro_fault in ("raise", "off"):
            runs = {}
            for batched in (False, True):
                monkeypatch.setattr(StarFilter, "batched_step", batched)
                taken.clear()
                committed.clear()
                events["left"] = 0
                events["runs"].clear()
                drv = DriverConfig(reorder_window_s=replay_mod.REPLAY_REORDER_S,
                                   max_pending_frames=1_000_000, batch_frames=True,
                                   strict_clock=True, frame_updates=False, imu_batch=64)
                runs[batched] = replay(data, prior, method, effects=["time_offset"],
                                       consider=["radial_k3"], gyro_fault=gyro_fault,
                                       driver=drv)
            one, batch = runs[False], runs[True]
            f = batch.filter
            c = batch.counters
            assert c["updates"] >= 20
            if data is not clean:
                assert c["skipped_few_stars"] >= 5 and c["reinitializations"] >= 1
                assert c["imu_gaps"] >= 1 and c["stars_gated"] >= 5
                assert c["frames_duplicate"] == 1 and c["stars_invalid"] >= 1
            i_dt = f.model.slices["time_offset"].start
            assert i_dt < f.P_est and f.theta[i_dt] != prior.time_offset
            assert one.counters == c
            _same_run(one, batch, 20)
            if method == "psce":
                assert sum(taken) + sum(committed) >= 0.5 * c["updates"]
                if gyro_fault == "off":
                    assert sum(committed) >= 0.3 * c["updates"]
                if data is clean:  # the boundary: runs left pending, frames a later run took
                    both |= bool(events["left"]) | 2 * any(n >= 2 for n in events["runs"])
            else:
                assert sum(taken) == sum(committed) == 0
    assert method != "psce" or both == 3


#: the swaying-base filter's compiled star update against its numpy update: |Δ| / σ of θ̂, the
#: velocity, position and attitude after the replay (measured: 1.3e-7 σ on 60 s, seed 4;
#: the coordinator's bound for rounding-level changes: 0.01 σ), and the relative difference
#: of the covariance's diagonal (measured 2.5e-9), the sensitivity's and the statistics'
SWAYING_SIGMA_TOL = 1e-4
SWAYING_RTOL = 1e-6


def test_swaying_batches_refuse_a_gyro_fault_over_the_first_frames(monkeypatch) -> None:
    """The swaying filter commits its batches within the gyro watch's first frames
    (``commit_early_frames``): a gyro in deg/s is refused there as one call a frame refuses
    it (the same DataError), and flagged instead (``gyro_fault="flag"``) the run's counters,
    faults and estimates are those of one call a frame, bit for bit (the batches' equality
    over the first frames of a sound gyro: the test below, with the watch)."""
    from stellar_cal_ros.errors import DataError
    from stellar_cal_ros.methods.swaying import SwayingFilter

    sim = simulate(get_scenario("swaying"), duration=30.0, seed=4)
    data = bag_data_from_simulation(sim)
    data.imu_w = np.degrees(data.imu_w)
    said, runs = {}, {}
    for batched in (True, False):
        monkeypatch.setattr(SwayingFilter, "batched_step", batched)
        with pytest.raises(DataError, match=r"deg/s") as err:
            replay(data, sim.prior, "swaying_base", keep_tables=False)
        said[batched] = str(err.value)
        runs[batched] = replay(data, sim.prior, "swaying_base", keep_tables=False,
                               gyro_fault="flag")
    assert said[True] == said[False]
    fast, ref = runs[True], runs[False]
    assert fast.counters == ref.counters and fast.counters["gyro_star_mismatch"] == 1
    assert fast.filter.data_faults == ref.filter.data_faults
    for name in ("theta", "velocity", "position", "R_i_b", "P"):
        np.testing.assert_array_equal(getattr(fast.filter, name), getattr(ref.filter, name),
                                      err_msg=name)


def _swaying_bag(damaged: bool):
    """The swaying tests' 60 s bag (seed 4), damaged as :func:`_damaged` when asked."""
    sim = simulate(get_scenario("swaying"), duration=60.0, seed=4)
    data = bag_data_from_simulation(sim)
    if damaged:
        data = _damaged(data, ((20.0, 20.025), (40.0, 40.4)), lambda i: i % 37 == 5,
                        lambda i: i % 7 == 3, lambda i: 60 <= i < 64 or i == 29, 52, 45, 12)
    return sim, data


def _swaying_runs_equal(monkeypatch, switch, calls, data, prior, method, damaged,
                        min_calls: int = 0) -> None:
    """Replays with ``SwayingFilter.<switch>`` True then False (the numpy reference): the
    compiled call (counted in ``calls``) taken for every frame (at least ``min_calls``
    times when given) and never by the reference;
    counters equal, θ̂, velocity, position and attitude within ``SWAYING_SIGMA_TOL`` σ, the
    covariance's diagonal, M, the information, the score (in its σ) and the running
    statistics within ``SWAYING_RTOL``."""
    from stellar_cal_ros.methods.swaying import SwayingFilter

    if switch != "compiled_frame":  # (the three calls apart: not one frame's call)
        monkeypatch.setattr(SwayingFilter, "compiled_frame", False)
    runs = {}
    for compiled in (True, False):
        monkeypatch.setattr(SwayingFilter, switch, compiled)
        calls.clear()
        runs[compiled] = replay(data, prior, method, consider=["radial_k3"],
                                keep_tables=False)
        if compiled:
            n_calls = len(calls)
    assert not calls  # the reference never calls it
    fast, ref = runs[True], runs[False]
    a, b = fast.filter, ref.filter
    assert fast.counters == ref.counters
    n_up = ref.counters["updates"]
    assert n_up >= 100 and n_calls >= (min_calls or n_up)
    if damaged:
        c = ref.counters
        assert c["skipped_few_stars"] >= 5 and c["reinitializations"] >= 1
        assert c["stars_gated"] >= 5 and c["position_updates"] >= 40 and c["imu_gaps"] >= 1
    sig = np.sqrt(np.diag(b.P))
    est = slice(3, b.N)  # θ̂, velocity, position
    x_a = np.concatenate([a.theta[:a.P_est], a.velocity, a.position])
    x_b = np.concatenate([b.theta[:b.P_est], b.velocity, b.position])
    assert np.max(np.abs(x_a - x_b) / sig[est]) <= SWAYING_SIGMA_TOL
    d_att = np.linalg.norm(so3_log(a.R_i_b @ b.R_i_b.T))
    assert d_att <= SWAYING_SIGMA_TOL * np.min(sig[:3])
    np.testing.assert_allclose(np.diag(a.P), np.diag(b.P), rtol=SWAYING_RTOL)
    sa, sb = a.sensitivity, b.sensitivity
    assert sa.frames == sb.frames > 0
    np.testing.assert_allclose(sa.M, sb.M, rtol=0,
                               atol=SWAYING_RTOL * float(np.max(np.abs(sb.M))))
    np.testing.assert_allclose(sa.info, sb.info, rtol=SWAYING_RTOL)
    assert np.all(np.abs(sa.score - sb.score) <= SWAYING_RTOL * np.sqrt(np.diag(sb.info)))
    ta, tb = fast.stats, ref.stats
    ta, tb = (s.current() if hasattr(s, "current") else s for s in (ta, tb))
    assert (ta.frames, ta.stars, ta.gated) == (tb.frames, tb.stars, tb.gated)
    for name in ("sum_logdet", "sum_nis", "sum_du2", "sum_dv2", "sum_suu", "sum_svv"):
        assert getattr(ta, name) == pytest.approx(getattr(tb, name), rel=SWAYING_RTOL), name


@pytest.mark.parametrize(("method", "damaged"), [("swaying_base", False),
                                               ("swaying_base", True),
                                               ("traditional", False)])
def test_swaying_compiled_star_update_equals_the_numpy_update(monkeypatch, method,
                                                              damaged) -> None:
    """The swaying-base filter propagates and applies its position reference in numpy and
    takes the star update in one compiled call (``frame_step.star_update``, the fused step's
    update; ``SwayingFilter.compiled_star_update``).  Against the numpy update (the
    reference, ``compiled_star_update = False``): the call is taken for every update and
    never by the reference; the counters are equal (gated, skipped, re-acquired frames on the
    damaged bag), θ̂, the velocity, position and attitude within ``SWAYING_SIGMA_TOL`` σ, the
    covariance's diagonal, the consider sensitivity (M, information), the score (in its σ)
    and the running statistics within ``SWAYING_RTOL`` relative.  ``traditional`` (a
    ``SwayingFilter``) inherits the compiled update and is held to the same bounds."""
    from stellar_cal_ros.methods import frame_step

    sim, data = _swaying_bag(damaged)
    calls = _count_calls(monkeypatch, frame_step.FusedStep, "update")
    _swaying_runs_equal(monkeypatch, "compiled_star_update", calls, data, sim.prior, method,
                        damaged)


#: a compiled swaying interval against the numpy one from the same state, in the state's σ
#: (P's entries in σ_i σ_j; the same sums in another order: measured ≤ 1e-12)
INTERVAL_TOL = 1e-10


@pytest.mark.parametrize(("method", "damaged"), [("swaying_base", False),
                                               ("swaying_base", True),
                                               ("traditional", False)])
def test_swaying_compiled_propagation_equals_the_numpy_propagation(monkeypatch, method,
                                                                   damaged) -> None:
    """The swaying-base filter's propagation between frames (the strapdown sums over the IMU
    samples, Φ, ``P ← Φ P Φᵀ + Q_d``, the sensitivity, velocity and position) in one
    compiled call (``frame_step.swaying_propagate``, ``SwayingFilter.compiled_propagation``)
    against the numpy reference (``ImuPropagation._interval`` and ``_transition``).

    Interval by interval from the same state (the numpy one computed, the state restored,
    then the compiled one kept): attitude (rad), P (in σ_i σ_j), M, velocity and position
    (in σ) within ``INTERVAL_TOL``, on every interval of a run whose first-order bound
    (1e-7 rad) rebuilds references under θ̂.  Then the whole run against the numpy run, as
    the compiled star update's test: counters equal, θ̂, velocity, position and attitude within
    ``SWAYING_SIGMA_TOL`` σ, P's diagonal, M, the information, the score and the statistics
    within ``SWAYING_RTOL``.  ``traditional`` inherits it; a damaged bag (IMU gaps, gated
    stars, frames with too few stars, a re-acquisition) too."""
    from stellar_cal_ros.methods import frame_step
    from stellar_cal_ros.methods.registry import get as registry_get
    from stellar_cal_ros.methods.swaying import SwayingFilter

    sim, data = _swaying_bag(damaged)
    monkeypatch.setattr(SwayingFilter, "compiled_frame", False)  # (its hook, apart)
    calls = _count_calls(monkeypatch, frame_step, "swaying_propagate")
    worst = np.zeros(5)
    n_checked = [0, 0]  # intervals, of which after a rebuild
    interval = SwayingFilter._propagate_interval

    def checked(self, k, m, t_target):
        state = self.state
        before = state.snapshot(sensitivity=True)
        R0, rebuilds = self.R_i_b, self.propagation.rebuilds
        SwayingFilter.compiled_propagation = False
        try:
            interval(self, k, m, t_target)
        finally:
            SwayingFilter.compiled_propagation = True
        ref = (self.R_i_b, state.P.copy(), state.sensitivity.M.copy(), self.velocity.copy(),
               self.position.copy())
        state.restore(before)
        self.R_i_b = R0
        interval(self, k, m, t_target)
        got = (self.R_i_b, state.P, state.sensitivity.M, self.velocity, self.position)
        sig = np.sqrt(np.diag(ref[1]))
        scale = (1.0, np.outer(sig, sig), sig[:, None], sig[self.iv], sig[self.ir])
        for i, (x, y, s_) in enumerate(zip(got, ref, scale, strict=True)):
            worst[i] = max(worst[i], np.max(np.abs(x - y) / s_))
        n_checked[0] += 1
        n_checked[1] += self.propagation.rebuilds > rebuilds

    monkeypatch.setattr(SwayingFilter, "_propagate_interval", checked)
    # (a smaller first-order bound: references rebuilt under θ̂ during the run)
    config = dataclasses.replace(registry_get(method).config_cls(),
                                 fast_propagation_max_rad=1e-7)
    replay(data, sim.prior, method, None, config, consider=["radial_k3"], keep_tables=False)
    assert n_checked[0] >= 100 and len(calls) >= n_checked[0] and n_checked[1] >= 3
    assert np.all(worst <= INTERVAL_TOL), worst
    monkeypatch.setattr(SwayingFilter, "_propagate_interval", interval)
    _swaying_runs_equal(monkeypatch, "compiled_propagation", calls, data, sim.prior, method,
                        damaged)


@pytest.mark.parametrize(("method", "damaged"), [("swaying_base", False),
                                               ("swaying_base", True),
                                               ("traditional", False)])
def test_swaying_compiled_reference_equals_the_numpy_reference(monkeypatch, method,
                                                               damaged) -> None:
    """The swaying filter's inertial reference (Z1: the position, or ``traditional``'s
    zero velocity in the navigation frame) updated and injected in one compiled call
    (``frame_step.reference_update``, ``SwayingFilter.compiled_reference``) against the
    numpy update and injection: the call taken for every reference update and never by
    the reference path; the whole runs held to the compiled star update's bounds
    (:func:`_swaying_runs_equal`)."""
    from stellar_cal_ros.methods import frame_step

    sim, data = _swaying_bag(damaged)
    calls = _count_calls(monkeypatch, frame_step, "reference_update")
    _swaying_runs_equal(monkeypatch, "compiled_reference", calls, data, sim.prior, method,
                        damaged, min_calls=50)


@pytest.mark.parametrize("damaged", [False, True])
def test_swaying_compiled_frame_equals_the_three_calls(monkeypatch, damaged) -> None:
    """A swaying-base frame's propagation, position reference (when due), rate and star
    update in one compiled call (``frame_step.swaying_frame``,
    ``SwayingFilter.compiled_frame``) against the three calls (compiled propagation,
    reference and star update, each the numpy path's tested equal above): the call taken
    for all but the frames that rebuild the reference (or follow a gap) and never by the
    reference path; the whole runs within :func:`_swaying_runs_equal`'s bounds (counters
    equal, θ̂, velocity, position, attitude in σ, P, M, information, score, statistics).
    ``traditional``'s velocity reference keeps the three calls."""
    from stellar_cal_ros.methods import frame_step
    from stellar_cal_ros.methods.swaying import SwayingFilter

    sim, data = _swaying_bag(damaged)
    calls = _count_calls(monkeypatch, frame_step, "swaying_frame")
    # one call a frame (its batch, equal to it bit for bit, is tested apart: these bags'
    # frames would all be batched, the gyro watch's first frames too)
    monkeypatch.setattr(SwayingFilter, "batched_step", False)
    _swaying_runs_equal(monkeypatch, "compiled_frame", calls, data, sim.prior,
                        "swaying_base", damaged, min_calls=100 if damaged else 0)
    monkeypatch.setattr(SwayingFilter, "compiled_frame", True)
    replay(data, sim.prior, "traditional", keep_tables=False)
    assert not calls


def test_a_moving_shift_builds_each_frame_context_once_a_look(monkeypatch) -> None:
    """An estimated time offset: the driver's pump reads a frame's exposure shift (is the
    IMU there yet?) from the context it then hands the frame on with, not from a second
    one built for the shift (every frame's context was built twice: 92 contexts for the
    38 frames of this replay, 56 now).  Counted per look at a frame: a pump, and the runs
    it has put out before (a run's updates move the shift, and the frame is looked at
    again).  The same run bit for bit: the estimated-offset test above."""
    from stellar_cal_ros.methods import driver as driver_mod
    from stellar_cal_ros.methods import replay as replay_mod
    from stellar_cal_ros.methods.driver_config import DriverConfig

    sim = simulate(get_scenario("psce_rotations"), duration=19.0, seed=4)
    prior = copy.deepcopy(sim.prior)
    prior.time_offset = 0.004
    looks: dict[tuple, int] = {}
    where = [0, 0]  # pumps, runs put out
    context, pump, run_out = (driver_mod.frame_context, driver_mod.Calibrator._pump,
                              driver_mod.Calibrator._run_out)

    def counted(stamp_ns, *a, **k):
        key = (*where, stamp_ns)
        looks[key] = looks.get(key, 0) + 1
        return context(stamp_ns, *a, **k)

    def pumped(self, *a, **k):
        where[0] += 1
        return pump(self, *a, **k)

    def ran(self, *a, **k):
        where[1] += 1
        return run_out(self, *a, **k)

    monkeypatch.setattr(driver_mod, "frame_context", counted)
    monkeypatch.setattr(driver_mod.Calibrator, "_pump", pumped)
    monkeypatch.setattr(driver_mod.Calibrator, "_run_out", ran)
    monkeypatch.setattr(replay_mod, "IMU_BLOCK", 50)
    monkeypatch.setattr(replay_mod, "REPLAY_LOOKAHEAD_S", 0.29)
    drv = DriverConfig(reorder_window_s=replay_mod.REPLAY_REORDER_S,
                       max_pending_frames=1_000_000, batch_frames=True, strict_clock=True,
                       frame_updates=False, imu_batch=64)
    res = replay(bag_data_from_simulation(sim), prior, "psce", effects=["time_offset"],
                 keep_tables=False, driver=drv)
    assert res.counters["updates"] >= 20 and len(looks) >= res.counters["frames"]
    assert max(looks.values()) == 1, sorted(k for k, v in looks.items() if v > 1)[:5]


def _odd_frame():
    """A star message of 100 × 80 px with every case of the star and σ rules: identified
    with catalog_id 0, unidentified, off-detector, non-finite and every bad σ (0, negative,
    inf, NaN)."""
    from stellar_cal_ros.core.types import StarFrame

    nan, inf = float("nan"), float("inf")
    return StarFrame(
        stamp_ns=1, frame_id="st", exposure_time=0.1,
        catalog_id=np.array([5, 0, 0, 7, 8, 9, 10, 11, 12], dtype=np.uint32),
        right_ascension=np.array([0.1, 0.2, nan, 0.3, 0.4, inf, 0.5, 0.6, 0.7]),
        declination=np.array([0.2, -0.1, nan, 0.3, 0.0, 0.1, 0.2, 0.3, -0.4]),
        uv=np.array([[10.0, 20.0], [30.0, 40.0], [50.0, 60.0], [-0.6, 5.0], [99.4, 5.0],
                     [1.0, 1.0], [2.0, nan], [3.0, 3.0], [4.0, 4.0]]),
        magnitude=np.arange(9.0), sigma=np.array([0.1, 0.0, 0.2, 0.3, -1.0, 0.1, 0.1, inf, nan]))


def test_compiled_frame_inputs_equal_numpy() -> None:
    """``frame_inputs(compiled=True)`` (one compiled loop) applies the star rule and the σ
    rule exactly as the numpy functions: identified with catalog_id 0, unidentified,
    off-detector, non-finite and every bad σ (0, negative, inf, NaN)."""
    from stellar_cal_ros.methods.frames import frame_inputs

    frame = _odd_frame()
    a = frame_inputs(frame, 100, 80, 0.05, compiled=True)
    b = frame_inputs(frame, 100, 80, 0.05, compiled=False)
    for name in ("ok", "uv", "u_i", "sigma", "catalog_id", "magnitude"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert (a.bad_sigma, a.unidentified) == (b.bad_sigma, b.unidentified) == (3, 1)
    # the usable star with σ 0 (counted in the compiled loop); an unusable one is not
    assert a.unknown_sigma == b.unknown_sigma == 1
    assert a.ok.sum() == 5
    # arrays of unequal lengths: the numpy path's error, whichever is asked for
    short = dataclasses.replace(frame, magnitude=np.arange(8.0))
    for compiled in (True, False):
        with pytest.raises(IndexError):
            frame_inputs(short, 100, 80, 0.05, compiled=compiled)


def test_frame_inputs_of_many_messages_are_each_ones_own() -> None:
    """``frame_inputs_many`` (a replay's release of star messages in one compiled call) gives
    each message the inputs ``frame_inputs(compiled=True)`` gives it, bit for bit and dtype
    for dtype: the bad σ, unidentified, off-detector and non-finite stars of ``_odd_frame``,
    an empty message, and messages beside each other; None (each message then computes its
    own) when one message's arrays differ in length, the stars' σ is scaled or the
    compiled path is not asked for."""
    from stellar_cal_ros.core.noise import NoiseScales
    from stellar_cal_ros.core.types import StarFrame
    from stellar_cal_ros.methods.frames import frame_inputs, frame_inputs_many

    odd = _odd_frame()
    rng = np.random.default_rng(3)

    def clean(k: int, stamp: int) -> StarFrame:
        return StarFrame(
            stamp_ns=stamp, frame_id="st", exposure_time=0.1,
            catalog_id=rng.integers(1, 9000, k).astype(np.uint32),
            right_ascension=rng.uniform(0, 2 * np.pi, k), declination=rng.uniform(-1, 1, k),
            uv=rng.uniform(0, 79, (k, 2)), magnitude=rng.uniform(2, 7, k),
            sigma=rng.uniform(0.02, 0.1, k))

    frames = [clean(12, 2), odd, clean(0, 3), clean(1, 4), odd, clean(25, 5)]
    many = frame_inputs_many(frames, 100, 80, 0.05, compiled=True)
    assert many is not None and len(many) == len(frames)
    for fr, got in zip(frames, many, strict=True):
        want = frame_inputs(fr, 100, 80, 0.05, compiled=True)
        for name in ("ok", "uv", "u_i", "sigma", "catalog_id", "magnitude"):
            a, b = getattr(got, name), getattr(want, name)
            assert a.dtype == b.dtype and a.shape == b.shape, name
            assert a.tobytes() == b.tobytes(), name
        assert (got.bad_sigma, got.unidentified, got.unknown_sigma, got.valid) == \
            (want.bad_sigma, want.unidentified, want.unknown_sigma, want.valid)
    assert (many[1].bad_sigma, many[1].unidentified, many[1].unknown_sigma) == (3, 1, 1)
    assert len(many[2].uv) == 0 and many[2].valid
    short = dataclasses.replace(odd, magnitude=np.arange(8.0))
    assert frame_inputs_many([frames[0], short], 100, 80, 0.05, compiled=True) is None
    assert frame_inputs_many(frames, 100, 80, 0.05, NoiseScales(star=1.2), compiled=True) \
        is None
    assert frame_inputs_many(frames, 100, 80, 0.05, NoiseScales(gyro=3.0), compiled=True) \
        is not None
    assert frame_inputs_many(frames, 100, 80, 0.05) is None
    assert frame_inputs_many([], 100, 80, 0.05, compiled=True) is None


def test_input_columns_are_the_messages_inputs_stacked() -> None:
    """``frame_inputs_columns`` (the twin's scene: one compiled call, its columns kept) holds
    ``frame_inputs_many``'s inputs stacked, bit for bit, the messages' bounds, ids and stated
    σ; the twin's per-frame fallback makes the same columns (the scene's usable stars, ids,
    magnitudes, counts, and each message's ids and σ as stated)."""
    from stellar_cal_ros.core.types import StarFrame
    from stellar_cal_ros.diagnosis.twin import _columns_one_by_one
    from stellar_cal_ros.methods.frames import frame_inputs_columns, frame_inputs_many

    odd = _odd_frame()
    rng = np.random.default_rng(4)

    def clean(k: int, stamp: int) -> StarFrame:
        return StarFrame(
            stamp_ns=stamp, frame_id="st", exposure_time=0.1,
            catalog_id=rng.integers(0, 3, k).astype(np.uint32) * rng.integers(1, 9000, k),
            right_ascension=rng.uniform(0, 2 * np.pi, k), declination=rng.uniform(-1, 1, k),
            uv=rng.uniform(0, 79, (k, 2)), magnitude=rng.uniform(2, 7, k),
            sigma=rng.uniform(0.02, 0.1, k).astype(np.float32))

    frames = [clean(12, 2), odd, clean(0, 3), clean(1, 4), odd, clean(25, 5)]
    cols = frame_inputs_columns(frames, 100, 80, 0.05, compiled=True)
    many = frame_inputs_many(frames, 100, 80, 0.05, compiled=True)
    for name in ("ok", "uv", "u_i", "sigma", "catalog_id", "magnitude"):
        stacked = np.concatenate([getattr(inp, name) for inp in many])
        assert getattr(cols, name).tobytes() == stacked.tobytes(), name
    n = [len(fr.uv) for fr in frames]
    assert cols.bounds.tolist() == np.cumsum([0, *n]).tolist()
    assert cols.counts[:, 0].tolist() == [len(inp.uv) for inp in many]
    assert np.array_equal(cols.message_ids, np.concatenate([fr.catalog_id for fr in frames]))
    stated = np.concatenate([np.asarray(fr.sigma, dtype=float) for fr in frames])
    assert cols.message_sigma.dtype == float and cols.message_sigma.tobytes() == stated.tobytes()
    assert np.count_nonzero(cols.message_ids == 0) > 3  # ids 0 for the scene's count

    class Camera:
        width, height = 100, 80

    slow = _columns_one_by_one(frames, Camera(), 0.05)
    for name in ("ok", "catalog_id", "magnitude", "counts", "bounds", "message_ids"):
        assert np.array_equal(getattr(slow, name)[..., :1] if name == "counts"
                              else getattr(slow, name),
                              getattr(cols, name)[..., :1] if name == "counts"
                              else getattr(cols, name)), name
    assert slow.message_sigma.tobytes() == stated.tobytes()
    np.testing.assert_allclose(slow.u_i, cols.u_i, rtol=0, atol=1e-15)


def test_imu_noise_scales_keep_the_compiled_frame_inputs() -> None:
    """A noise that rescales only the IMU (the IMU noise search's runs) or holds a gyro bias
    walk leaves the stars' σ as stated: its frame inputs are the compiled ones (``valid``,
    so the replay commits its frames in batches), equal to the stated noise's bit for bit;
    a star scale, a measured σ of unknown stars or σ groups take the numpy path."""
    from stellar_cal_ros.core.noise import NoiseScales
    from stellar_cal_ros.core.types import StarFrame
    from stellar_cal_ros.methods.frames import frame_inputs

    frame = StarFrame(
        stamp_ns=1, frame_id="st", exposure_time=0.1,
        catalog_id=np.array([5, 6, 7], dtype=np.uint32),
        right_ascension=np.array([0.1, 0.2, 0.3]), declination=np.array([0.2, -0.1, 0.3]),
        uv=np.array([[10.0, 20.0], [30.0, 40.0], [50.0, 60.0]]),
        magnitude=np.arange(3.0), sigma=np.array([0.1, 0.0, 0.2]))
    stated = frame_inputs(frame, 100, 80, 0.05, compiled=True)
    assert stated.valid
    for noise in (NoiseScales(gyro=3.0), NoiseScales(gyro=1 / 3, accel=2.0),
                  NoiseScales(gyro_bias_rw=5.0), NoiseScales(star_rho=0.3)):
        assert noise.stars_as_stated
        got = frame_inputs(frame, 100, 80, 0.05, noise=noise, compiled=True)
        assert got.valid, noise
        for name in ("ok", "uv", "u_i", "sigma", "catalog_id", "magnitude"):
            np.testing.assert_array_equal(getattr(got, name), getattr(stated, name),
                                          err_msg=name)
        numpy_path = frame_inputs(frame, 100, 80, 0.05, noise=noise, compiled=False)
        np.testing.assert_array_equal(numpy_path.sigma, got.sigma)
    for noise in (NoiseScales(star=1.2), NoiseScales(unknown_sigma_px=0.3)):
        assert not noise.stars_as_stated
        got = frame_inputs(frame, 100, 80, 0.05, noise=noise, compiled=True)
        assert not got.valid
        assert not np.array_equal(got.sigma, stated.sigma)


def test_compiled_imu_screen_equals_numpy(sim_data) -> None:
    """``jit.imu_block_screen`` decides what the driver's numpy screen decides (strictly
    increasing; every stamp positive, every sample finite), on clean and damaged blocks —
    NaN, inf, a sum that overflows, zero and negative stamps, repeated and reversed stamps,
    empty, one sample, strided and read-only arrays; and the driver counts and keeps the
    same samples through either."""
    from stellar_cal_ros.core import jit
    from stellar_cal_ros.methods.driver import Calibrator

    if not jit.HAVE_NUMBA:
        pytest.skip("numba not importable: the driver takes the numpy screen")
    rng = np.random.default_rng(5)
    t0 = np.arange(1, 9, dtype=np.int64) * 10_000_000
    w0, f0 = rng.normal(size=(8, 3)), rng.normal(size=(8, 3))
    blocks = [(t0, w0, f0), (t0[:0], w0[:0], f0[:0]), (t0[:1], w0[:1], f0[:1])]
    for what in ("nan", "inf", "big", "zero", "negative", "repeat", "reverse"):
        t, w, f = t0.copy(), w0.copy(), f0.copy()
        if what in ("nan", "inf"):
            w[3, 1] = float(what)
        elif what == "big":
            f[:] = 1e308  # finite samples whose sum overflows
        elif what in ("zero", "negative"):
            t[0] = 0 if what == "zero" else -5
        elif what == "repeat":
            t[4] = t[3]
        else:
            t = t[::-1]
        blocks.append((t, w, f))
    ro = (t0.copy(), w0.copy(), f0.copy())
    for a in ro:
        a.flags.writeable = False
    blocks += [ro, (t0[::2], np.asfortranarray(w0)[::2], f0[::2])]
    for t, w, f in blocks:
        inc = len(t) < 2 or bool((t[1:] > t[:-1]).all())
        clean = bool((t > 0).all() and np.isfinite(w).all() and np.isfinite(f).all())
        assert jit.imu_block_screen(t, w, f) == (inc, clean)
    sim, _ = sim_data
    counts = []
    for screen in (None, False):  # compiled (on first use), numpy
        cal = Calibrator(sim.prior, "psce")
        cal._imu_screen = screen
        base = 0
        for t, w, f in blocks:
            with np.errstate(over="ignore"):  # the numpy screen's sum of the 1e308 block
                cal.push_imu_block(np.where(t > 0, t + base, t), w, f)
            base += 1_000_000_000
        counts.append((vars(cal.counters), cal._imu.t.tolist(), cal._last_imu_ns))
        assert (cal._imu_screen is not False) == (screen is None)
    assert counts[0] == counts[1]
    assert counts[0][0]["imu_invalid"] == 4  # NaN, inf, zero and negative stamps


class PlainTimeOffset(TimeOffset):
    """The library's time offset as a user would write it: no compiled form."""

    def affine_form(self):  # noqa: D102
        return None


def test_effect_without_compiled_form_falls_back(sim_data, monkeypatch) -> None:
    sim, data = sim_data
    fast = replay(data, sim.prior, "psce", effects=["time_offset"], keep_tables=False).filter
    monkeypatch.setitem(registry.EFFECTS, "time_offset", PlainTimeOffset)
    plain = replay(data, sim.prior, "psce", effects=["time_offset"], keep_tables=False).filter
    assert fast.model.compiled_chain() is not None
    assert plain.model.compiled_chain() is None  # the effects' Python methods
    assert plain.counters.updates == fast.counters.updates
    assert _sigma_units(fast, plain) <= SIGMA_TOL


def test_gain_joseph_and_star_blocks_equal_numpy() -> None:
    from stellar_cal_ros.core.covariance import _gain
    from stellar_cal_ros.core.gating import block_nis

    rng = np.random.default_rng(6)
    n, N = 20, 22
    A = rng.normal(size=(N, N))
    P = A @ A.T / N + np.eye(N) * 1e-3
    H3 = rng.normal(size=(n, 2, N))
    H = H3.reshape(-1, N)
    r = rng.uniform(0.01, 0.1, n)
    r2 = np.repeat(r, 2)
    nu = rng.normal(size=2 * n)
    K_ref, nis_ref = _gain(P, H, r2, nu, 0.0, 1)
    ok, K, nis = jit.kalman_gain(P, H, r2, nu)
    assert ok == 1
    np.testing.assert_allclose(K, K_ref, rtol=0, atol=1e-10 * np.max(np.abs(K_ref)))
    assert nis == pytest.approx(nis_ref, rel=1e-10)
    Ak = np.eye(N) - K_ref @ H
    _close(jit.joseph(P, K_ref, H, r2), Ak @ P @ Ak.T + (K_ref * r2) @ K_ref.T)
    S_ref = (H3 @ P) @ H3.transpose(0, 2, 1)
    S_ref[:, 0, 0] += r
    S_ref[:, 1, 1] += r
    S, nis_s = jit.star_blocks(H3, P, r, nu.reshape(n, 2))
    _close(S, S_ref)
    _close(nis_s, block_nis(nu.reshape(n, 2), S_ref))
    assert jit.kalman_gain(-P, H, -r2, nu)[0] == 0  # not positive definite: refused
    # the factor the sensitivity solves with: S = L Lᵀ, and S⁻¹ X as numpy's solve
    ok, K_f, nis_f, L = jit.kalman_gain_factor(P, H, r2, nu)
    assert ok == 1 and np.array_equal(K_f, K) and nis_f == nis
    S_full = H @ P @ H.T + np.diag(r2)
    _close(L @ L.T, S_full)
    X = rng.normal(size=(2 * n, 5))
    _close(jit.cholesky_solve(L, X.copy()), np.linalg.solve(S_full, X))


def test_without_numba_the_numpy_path_runs() -> None:
    """numba not importable: no compiled chain, no compiled update, the replay still runs."""
    import subprocess
    import sys

    code = (
        "import sys; sys.modules['numba'] = None\n"
        "from stellar_cal_ros.core import covariance, jit\n"
        "from stellar_cal_ros.methods.frames import bag_data_from_simulation\n"
        "from stellar_cal_ros.methods.replay import replay\n"
        "from stellar_cal_ros.sim.scenarios import get_scenario\n"
        "from stellar_cal_ros.sim.world import simulate\n"
        "assert not jit.HAVE_NUMBA and covariance.compiled_kernels() is None\n"
        "sim = simulate(get_scenario('psce_rotations'), duration=20.0, seed=3)\n"
        "f = replay(bag_data_from_simulation(sim), sim.prior, 'psce').filter\n"
        "assert f.model.compiled_chain() is None and f.counters.updates > 30\n"
        "print('ok')\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300, check=False)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]


@pytest.mark.parametrize(("duration", "damaged", "watch"), [(60.0, False, False),
                                                            (60.0, True, False),
                                                            (150.0, False, True)])
def test_swaying_frame_batch_equals_one_call_a_frame(monkeypatch, duration, damaged,
                                                     watch) -> None:
    """A replay's swaying-base frames stepped a run at a time (``frame_step.swaying_frames``,
    ``SwayingFilter.prepare_frames``: each frame's ``swaying_frame`` in one compiled loop)
    and committed at once (``StarFilter.commit_batch`` with the swaying part
    ``_commit_more``: velocity, position, the position references' counts, sensitivity
    frames and history rows in order; the driver's statistics take the references' rows)
    against one call a frame (``batched_step = False``, the reference): the same floats —
    counters, θ̂, velocity, position, attitude, P, M, information, score, the statistics'
    sums and the references' NIS — bit for bit, with most frames committed in batches.
    The 60 s bags (seed 4, clean and damaged as :func:`_damaged`) without the gyro watch
    (the swaying filter commits a batch within the watch's first frames too:
    ``commit_early_frames``); 150 s with it."""
    from stellar_cal_ros.methods.registry import get as registry_get
    from stellar_cal_ros.methods.swaying import SwayingFilter

    if duration == 60.0:
        sim, data = _swaying_bag(damaged)
    else:
        sim = simulate(get_scenario("swaying"), duration=duration, seed=4)
        data = bag_data_from_simulation(sim)
    config = dataclasses.replace(registry_get("swaying_base").config_cls(), unit_check=watch)
    committed = []
    commit = SwayingFilter.commit_batch

    def counted(self, limit):
        b = commit(self, limit)
        committed.append(0 if b is None else b.count)
        return b

    monkeypatch.setattr(SwayingFilter, "commit_batch", counted)
    runs = {}
    for batched in (True, False):
        monkeypatch.setattr(SwayingFilter, "batched_step", batched)
        committed.clear()
        runs[batched] = replay(data, sim.prior, "swaying_base", None, config,
                               consider=["radial_k3"], keep_tables=False)
        if batched:
            n_batched = sum(committed)
    assert not committed  # (the reference commits none)
    fast, ref = runs[True], runs[False]
    assert fast.counters == ref.counters
    c = ref.counters
    assert n_batched >= 0.8 * c["updates"] and c["position_updates"] >= 50
    if damaged:
        assert c["skipped_few_stars"] >= 5 and c["reinitializations"] >= 1
        assert c["stars_gated"] >= 5 and c["imu_gaps"] >= 1
    a, b = fast.filter, ref.filter
    for name in ("theta", "velocity", "position", "R_i_b", "P"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    sa, sb = a.sensitivity, b.sensitivity
    assert sa.frames == sb.frames > 0
    for name in ("M", "info", "score"):
        np.testing.assert_array_equal(getattr(sa, name), getattr(sb, name), err_msg=name)
    ta, tb = (s.current() if hasattr(s, "current") else s for s in (fast.stats, ref.stats))
    assert vars(ta).keys() == vars(tb).keys()
    for name, value in vars(tb).items():
        if isinstance(value, float | int):
            assert getattr(ta, name) == value, name


def test_swaying_batch_rebuilds_the_reference_where_its_window_ends(monkeypatch) -> None:
    """A frame whose reference strapdown is to be rebuilt because its window ends
    (``reference_window_s``: 15 s on the 60 s bag, three rebuilds) is batched too:
    ``SwayingFilter.prepare_frames`` rebuilds it (from the frame's first sample under θ̂, as
    ``ImuPropagation.step`` would in the frame's own propagation) and steps the frame in the
    batch.  The same floats as one call a frame (which takes the three calls there) — θ̂,
    velocity, position, attitude, P, the sensitivity — and with batches no frame of the
    clean bag takes its own propagation (``_propagate_interval``); before, each rebuild
    frame did (and loaded three kernels for it on the 2-h bag)."""
    from stellar_cal_ros.methods.registry import get as registry_get
    from stellar_cal_ros.methods.swaying import SwayingFilter

    sim, data = _swaying_bag(False)
    config = dataclasses.replace(registry_get("swaying_base").config_cls(), unit_check=False,
                                 reference_window_s=15.0)
    own = []
    interval = SwayingFilter._propagate_interval

    def counted(self, k, m, t_target):
        own.append(t_target)
        return interval(self, k, m, t_target)

    monkeypatch.setattr(SwayingFilter, "_propagate_interval", counted)
    runs, props = {}, {}
    for batched in (True, False):
        monkeypatch.setattr(SwayingFilter, "batched_step", batched)
        own.clear()
        runs[batched] = replay(data, sim.prior, "swaying_base", None, config,
                               consider=["radial_k3"], keep_tables=False)
        props[batched] = len(own)
    fast, ref = runs[True], runs[False]
    assert fast.counters == ref.counters and ref.counters["updates"] > 100
    assert props[False] >= 3 and props[True] == 0, props
    a, b = fast.filter, ref.filter
    assert a.propagation.ref_start == b.propagation.ref_start > 0
    for name in ("theta", "velocity", "position", "R_i_b", "P"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    for name in ("M", "info", "score"):
        np.testing.assert_array_equal(getattr(a.sensitivity, name), getattr(b.sensitivity, name),
                                      err_msg=name)
