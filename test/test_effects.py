"""Every registered effect on its own: analytic Jacobians, prior/result round trips, metadata.

Inputs are realistic: the simulator's psce_rotations prior (camera block, installation,
datasheet sigmas), real Hipparcos stars around the tracker boresight 100 s into that
scenario, the Qingdao site at night with weather, and a parameter value a few sigma away
from the initial one.
"""

from __future__ import annotations

import copy
import inspect
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stellar_cal_ros.core import astrometry
from stellar_cal_ros.core.camera import CameraModel
from stellar_cal_ros.core.catalog import load_catalog, posix_to_jyear
from stellar_cal_ros.core.earth import Site
from stellar_cal_ros.core.units import ARCSEC
from stellar_cal_ros.effects import registry
from stellar_cal_ros.effects.base import CAMERA_INDEX, Effect, ExportRole, FrameContext, Stage
from stellar_cal_ros.errors import ModelError
from stellar_cal_ros.io.calibration import load_calibration, save_calibration
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import default_prior_sigma, simulate

T0 = 1795348800.0
SITE = Site(36.07, 120.38, 10.0)
#: INTERFACES.md §4
CONTRACT_IDS = (
    "installation", "principal_point", "focal_length", "pixel_aspect", "radial_k1k2",
    "radial_k3", "tangential", "image_plane_tilt", "thermal_focal_length", "gyro_bias",
    "gyro_scale_factor", "gyro_misalignment", "accel_bias", "accel_scale_factor",
    "time_offset", "aberration", "refraction", "proper_motion",
)
ALL_IDS = registry.available()
#: a fixed, non-trivial pattern of "a few sigma" offsets
OFFSETS = np.array([2.0, -3.0, 2.5, -1.5, 3.0, -2.0, 1.7, -2.6, 2.2])


# ------------------------------------------------------------------ fixtures and helpers
@pytest.fixture(scope="module")
def sim():
    sc = get_scenario("psce_rotations")
    sc.centroid_noise_px = sc.gyro_arw_deg_sqrth = sc.accel_vrw_mps_sqrth = 0.0
    return simulate(sc, duration=110.0, seed=3)


@pytest.fixture(scope="module")
def stars(sim):
    """HIP ids and J2000 directions of the stars the tracker sees 100 s into the run."""
    frame = min(sim.star_frames, key=lambda f: abs(f.stamp_ns * 1e-9 - T0 - 100.0))
    ids = frame.catalog_id.astype(np.int64)
    cat = load_catalog(mag_limit=None)
    sub = cat.subset(cat.index_of(ids))
    assert len(ids) >= 10
    return ids, sub.directions(2000.0), frame.magnitude


def make_ctx(stars) -> FrameContext:
    ids, _, mag = stars
    return FrameContext(
        stamp=T0 + 100.0, catalog_id=ids.copy(), magnitude=mag.copy(), site=SITE,
        head_temperature_c=25.0, air_temperature_c=5.0, pressure_pa=101200.0,
        omega_b=np.array([0.02, -0.05, 0.08]),
    )


def rich_prior(sim):
    """A prior with every block populated: distortion incl. k3 and tilt, sensor errors, …"""
    cal = copy.deepcopy(sim.truth)
    p = cal.camera.parameters()
    p[CAMERA_INDEX["fy"]] *= 1.0 + 3e-4
    p[CAMERA_INDEX["k3"]] = 0.7
    p[CAMERA_INDEX["tau_x"]], p[CAMERA_INDEX["tau_y"]] = 1.5e-3, -2e-3
    cal.camera = cal.camera.with_parameters(p)
    rng = np.random.default_rng(7)
    cal.gyro_error_matrix = 1e-4 * rng.standard_normal((3, 3))
    cal.accel_bias = 1e-3 * rng.standard_normal(3)
    cal.accel_error_matrix = 1e-4 * rng.standard_normal((3, 3))
    cal.time_offset = 0.013
    cal.effects = {
        "thermal_focal_length": {"coefficient_per_c": 1.2e-5, "reference_temperature_c": 18.0},
        "aberration": {"scale": 1.0},
        "refraction": {"scale": 0.5},
        "proper_motion": {"scale": 1.0},
    }
    cal.sigma = default_prior_sigma()
    cal.sigma["effects"] = {"aberration": {"scale": 0.25}}
    return cal


def perturbed(eff: Effect, prior) -> tuple[np.ndarray, np.ndarray]:
    v0, s0 = eff.initial(prior)
    return v0 + OFFSETS[: eff.size] * s0, s0


def central_fd(f, x: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """Central differences of f at x: array of shape f(x).shape + (len(x),)."""
    cols = []
    for k, h in enumerate(steps):
        e = np.zeros_like(x)
        e[k] = h
        cols.append((np.asarray(f(x + e)) - np.asarray(f(x - e))) / (2.0 * h))
    return np.stack(cols, axis=-1)


def assert_jacobian(J, J_fd, rtol=1e-6, atol=1e-12, what=""):
    J, J_fd = np.asarray(J, dtype=float), np.asarray(J_fd, dtype=float)
    assert J.shape == J_fd.shape, f"{what}: shape {J.shape} != {J_fd.shape}"
    scale = np.max(np.abs(J_fd)) if J_fd.size else 0.0
    err = np.max(np.abs(J - J_fd)) if J.size else 0.0
    assert err <= rtol * scale + atol, f"{what}: max error {err:.3e} (scale {scale:.3e})"


def camera_p() -> np.ndarray:
    """A realistic, fully populated 18-vector of OpenCV camera parameters."""
    cam = CameraModel(1024, 1024, 3968.99, 3970.2, 516.5, 521.5,
                      [0.13, -0.43, 5e-4, -3e-4, 0.7, 0.01, -0.02, 0.03,
                       1e-4, -2e-4, 3e-4, 1e-4, 1.5e-3, -2e-3])
    return cam.parameters()


# ------------------------------------------------------------------ metadata
def test_every_contract_effect_is_implemented():
    """Every contract id exists; an effect file added to the package needs no list here
    (the parametrized checks below run on every registered effect)."""
    missing = [i for i in CONTRACT_IDS if i not in ALL_IDS]
    assert missing == [], f"contract effect ids not implemented: {missing}"


@pytest.mark.parametrize("eid", ALL_IDS)
def test_effect_metadata(eid):
    eff = registry.create(eid)
    assert eff.id == eid
    assert isinstance(eff.stage, Stage)
    assert eff.size >= 1 and len(set(eff.parameter_names)) == eff.size
    assert len(eff.units) == eff.size and all(eff.units)
    sig = np.asarray(eff.default_sigma, dtype=float)
    assert sig.shape == (eff.size,) and np.all(np.isfinite(sig)) and np.all(sig > 0)
    assert eff.process_noise_density().shape == (eff.size,)
    assert len(eff.explanation.strip()) > 80, "explanation: cause, size, residual signature"
    assert eff.id in repr(eff)


#: the application order, which is also the layout of θ (the golden replay holds it)
APPLICATION_ORDER = (
    "installation", "focal_length", "pixel_aspect", "principal_point", "radial_k1k2",
    "radial_k3", "tangential", "image_plane_tilt", "thermal_focal_length", "gyro_bias",
    "gyro_scale_factor", "gyro_misalignment", "accel_bias", "accel_scale_factor",
    "time_offset", "proper_motion", "aberration", "refraction",
)


def test_one_file_per_effect_in_the_order_its_classes_declare():
    classes = [registry.EFFECTS[i] for i in CONTRACT_IDS]
    assert sorted(Path(inspect.getfile(c)).name for c in classes) == sorted(
        f"{i}.py" for i in CONTRACT_IDS)
    assert all(registry.is_library(c) for c in classes)
    assert tuple(i for i in registry.available() if i in CONTRACT_IDS) == APPLICATION_ORDER
    keys = [(c.stage, c.order) for c in map(registry.effect_class, ALL_IDS)]
    assert len(set(keys)) == len(keys), "two effects of one stage share an order"
    ids = [e.id for e in registry.create_many(list(reversed(CONTRACT_IDS)))]
    assert tuple(ids) == APPLICATION_ORDER


@pytest.mark.parametrize("eid", ALL_IDS)
def test_declarations_on_the_class(eid, sim):
    """Plausible size (converted for this camera), display unit, export and budget role."""
    eff = registry.create(eid)
    assert eff.plausible is not None, "state the plausible size where the effect acts"
    size = eff.plausible_parameters(sim.prior)
    assert size.shape == (eff.size,) and np.all(np.isfinite(size)) and np.all(size > 0)
    # the conversion is invertible: the plausible size, where it acts, is the statement
    stated = np.broadcast_to(np.asarray(eff.plausible.size, dtype=float), (eff.size,))
    np.testing.assert_allclose(eff.where_it_acts(size, sim.prior), stated, rtol=1e-12)
    for name in eff.parameter_names:
        unit, factor = eff.display(name)
        assert isinstance(unit, str) and factor > 0
    assert isinstance(eff.export(), ExportRole)
    if eff.budget_source is not None:
        assert eff.stage in (Stage.CAMERA, Stage.TRACKER)
    assert eff.physical_value is None or eff.stage is Stage.DIRECTION


# ------------------------------------------------------------------ own-stage Jacobians
@pytest.mark.parametrize("eid", ALL_IDS)
def test_own_stage_jacobian(eid, sim, stars):
    prior = sim.prior
    eff = registry.create(eid)
    value, sigma = perturbed(eff, prior)
    h = 1e-3 * sigma
    ctx = make_ctx(stars)
    u_i = stars[1]
    st = eff.stage
    if st in (Stage.GYRO, Stage.ACCEL):
        assert_jacobian(eff.sensor_bias_jacobian(value),
                        central_fd(eff.sensor_bias, value, h), what="db/dv")
        assert_jacobian(eff.sensor_matrix_jacobian(value),
                        central_fd(eff.sensor_matrix, value, h), what="dE/dv")
        assert np.any(eff.sensor_bias_jacobian(value)) or np.any(
            eff.sensor_matrix_jacobian(value))
    elif st is Stage.DIRECTION:
        J = eff.directions_jacobian(value, u_i, ctx)
        J_fd = central_fd(lambda v: eff.directions(v, u_i, ctx), value, h)
        # erfa computes the apparent places to ~1e-12: compare in rad, absolutely
        assert_jacobian(J, J_fd, rtol=0.0, atol=1e-12, what="du'/dv")
        assert np.max(np.abs(J)) > 1e-7, "a physical correction of at least 0.02 arcsec"
    elif st is Stage.TIME:
        assert_jacobian(eff.time_shift_jacobian(value, ctx),
                        central_fd(lambda v: eff.time_shift(v, ctx), value, h), what="dt/dv")
    elif st is Stage.TRACKER:
        assert_jacobian(eff.tracker_rotation_jacobian(value, ctx),
                        central_fd(lambda v: eff.tracker_rotation(v, ctx), value, h),
                        what="ddelta/dv")
    elif st is Stage.CAMERA:
        p = camera_p()
        J, D = eff.camera_jacobian(value, p, ctx)
        assert_jacobian(J, central_fd(lambda v: eff.camera_parameters(v, p, ctx), value, h),
                        what="dp'/dv")
        hp = 1e-6 * np.maximum(np.abs(p), 1e-3)
        assert_jacobian(D, central_fd(lambda q: eff.camera_parameters(value, q, ctx), p, hp),
                        what="dp'/dp")
        assert np.any(J)
    else:  # pragma: no cover
        pytest.fail(f"unknown stage {st}")


@pytest.mark.parametrize("eid", ALL_IDS)
def test_other_stages_are_neutral(eid, sim, stars):
    """An effect acts at its own stage only; every other stage passes values through."""
    eff = registry.create(eid)
    value, _ = perturbed(eff, sim.prior)
    ctx, u_i, p = make_ctx(stars), stars[1], camera_p()
    if eff.stage not in (Stage.GYRO, Stage.ACCEL):
        assert not np.any(eff.sensor_bias(value)) and not np.any(eff.sensor_matrix(value))
        assert not np.any(eff.sensor_bias_jacobian(value))
    if eff.stage is not Stage.DIRECTION:
        assert np.array_equal(eff.directions(value, u_i, ctx), u_i)
        assert not np.any(eff.directions_jacobian(value, u_i, ctx))
    if eff.stage is not Stage.TIME:
        assert eff.time_shift(value, ctx) == 0.0
    if eff.stage is not Stage.TRACKER:
        assert not np.any(eff.tracker_rotation(value, ctx))
    if eff.stage is not Stage.CAMERA:
        J, D = eff.camera_jacobian(value, p, ctx)
        assert np.array_equal(eff.camera_parameters(value, p, ctx), p)
        assert not np.any(J) and np.array_equal(D, np.eye(18))


@pytest.mark.parametrize("eid", ["pixel_aspect", "thermal_focal_length"])
def test_bilinear_camera_form_is_the_effect(eid, sim, stars):
    """``BilinearCamera`` (the compiled chain's form) gives the effect's own camera
    parameters and both Jacobians, at any value, camera and frame."""
    from stellar_cal_ros.effects.base import BilinearCamera

    eff = registry.create(eid)
    form = eff.affine_form()
    assert isinstance(form, BilinearCamera)
    ctx, p = make_ctx(stars), camera_p()
    s = eff.camera_scale(ctx)
    for value in (np.array([0.0]), np.array([3e-3]), np.array([-2e-5])):
        M = form.D0 + np.einsum("j,jab->ab", value * s, form.Dv)
        np.testing.assert_allclose(M @ p + form.J0 @ value,
                                   eff.camera_parameters(value, p, ctx), rtol=1e-15)
        J, D = eff.camera_jacobian(value, p, ctx)
        np.testing.assert_allclose(M, D, rtol=0, atol=1e-15)
        Jf = np.einsum("j,jab,b->aj", s, form.Dv, p) + form.J0
        np.testing.assert_allclose(Jf, J, rtol=1e-15)


# ------------------------------------------------------------------ physics of the directions
def test_direction_effects_at_scale_one_are_the_astrometry(stars):
    ids, u_i, _ = stars
    ctx = make_ctx(stars)
    t = np.full(len(u_i), ctx.stamp)
    one = np.ones(1)
    ab = registry.create("aberration").directions(one, u_i, ctx)
    np.testing.assert_allclose(ab, astrometry.aberration(u_i, t, SITE), rtol=0, atol=1e-15)
    shift = np.arccos(np.clip(np.sum(ab * u_i, axis=1), -1, 1)) / ARCSEC
    assert np.all((shift > 1.0) & (shift < 21.0))
    rf = registry.create("refraction").directions(one, u_i, ctx)
    ref = astrometry.refraction(u_i, t, SITE, pressure_hpa=1012.0, temperature_c=5.0)
    np.testing.assert_allclose(rf, ref, rtol=0, atol=1e-15)
    pm = registry.create("proper_motion").directions(one, u_i, ctx)
    cat = load_catalog(mag_limit=None)
    sub = cat.subset(cat.index_of(ids))
    np.testing.assert_allclose(pm, sub.directions(float(posix_to_jyear(ctx.stamp))),
                               rtol=0, atol=1e-15)


def test_direction_cache_follows_content_not_identity(stars):
    """Regression: the correction cache was keyed on id(u_i) and went stale."""
    ctx, u_i = make_ctx(stars), stars[1]
    for eid in ("aberration", "refraction"):
        eff = registry.create(eid)
        u = u_i.copy()
        eff.directions(np.ones(1), u, ctx)
        u[:] = u_i[::-1]  # same array object, other stars
        got = eff.directions(np.ones(1), u, ctx)
        fresh = eff.directions(np.ones(1), u_i[::-1].copy(), make_ctx(stars))
        np.testing.assert_allclose(got, fresh, rtol=0, atol=1e-15)
        sub = eff.directions_jacobian(np.ones(1), u_i[:4], ctx)  # a subset, same context
        assert sub.shape == (4, 3, 1)


def test_direction_table_of_a_bag_equals_each_frame(stars):
    """``prepare`` (every star of a bag in one pyerfa call) gives each frame the Δ its own
    call gives, for every star or a subset in another order; a frame whose context differs
    from what was prepared (weather, site, a star not there) is computed, not looked up."""
    ids, u_i, _ = stars
    stamps = T0 + np.array([40.0, 100.0, 160.0])
    u_frames = [u_i[:-1], u_i, u_i[1:]]
    id_frames = [ids[:-1], ids, ids[1:]]
    for eid in ("aberration", "refraction", "proper_motion"):
        eff, ref = registry.create(eid), registry.create(eid)
        eff.prepare(stamps, id_frames, u_frames, SITE, np.full(3, 101200.0), np.full(3, 5.0))
        for sub in (slice(None), [4, 1, 0, 7, 2, 8]):
            ctx = make_ctx(stars)
            ctx.catalog_id = ids[sub]
            got = eff._prepared(u_i[sub], ctx)
            assert got is not None
            np.testing.assert_array_equal(got, ref.delta(u_i[sub], make_ctx(stars) if
                                                         sub == slice(None) else ctx))
        ctx = make_ctx(stars)
        ctx.site = None
        assert eff._prepared(u_i, ctx) is None
        ctx = make_ctx(stars)
        ctx.catalog_id = ids + 1  # other stars
        assert eff._prepared(u_i, ctx) is None
        ctx = make_ctx(stars)
        ctx.pressure_pa = 90000.0
        assert (eff._prepared(u_i, ctx) is None) == (eid == "refraction")
        ctx = make_ctx(stars)
        ctx.catalog_id = ids[:4]  # few stars: pyerfa exact, not the bag's interpolation
        assert eff._prepared(u_i[:4], ctx) is None


def test_direction_columns_of_a_batch_equal_each_frames(stars):
    """``delta_frames`` (a batch's frames in one gather: ``FusedStep.stack``) gives each
    frame, bit for bit, what its own ``_cached_delta`` gives: frames that are their table
    row are taken at once; the others (stars in another order or a subset, another site
    or weather, few stars, a star moved, a NaN direction, a stamp not prepared) go frame
    by frame, computed or looked up as before."""
    ids, u_i, _ = stars
    stamps = T0 + np.array([40.0, 100.0, 160.0])
    u_frames = [u_i[:-1], u_i, u_i[1:]]
    id_frames = [ids[:-1], ids, ids[1:]]
    moved = u_frames[1].copy()
    moved[3] = (moved[3] + 1e-9) / np.linalg.norm(moved[3] + 1e-9)
    nan = u_frames[2].copy()
    nan[1] = np.nan
    sub = [4, 1, 0, 7, 2, 8]
    #: (directions, frame, catalogue rows, context changes, whether the table row is taken)
    table = [(u_frames[0], 0, slice(None), {}, True), (u_frames[1], 1, slice(None), {}, True),
             (u_frames[2], 2, slice(None), {}, True), (u_frames[1][sub], 1, sub, {}, False),
             (u_frames[1], 1, slice(None), {"site": Site(36.0, 120.0, 0.0)}, False),
             (u_frames[1], 1, slice(None), {"pressure_pa": 90000.0}, None),
             (u_frames[0][:4], 0, slice(0, 4), {}, False), (moved, 1, slice(None), {}, False),
             (nan, 2, slice(None), {}, False),
             (u_frames[1], 1, slice(None), {"stamp": T0 + 7.0}, False),
             (u_frames[2], 2, slice(None), {}, True)]

    def contexts() -> list[FrameContext]:
        out = []
        for _, k, rows, changes, _ in table:
            c = make_ctx(stars)
            c.stamp, c.catalog_id = float(stamps[k]), id_frames[k][rows]
            for key, v in changes.items():
                setattr(c, key, v)
            out.append(c)
        return out

    us = [row[0] for row in table]
    offs = np.concatenate([[0], np.cumsum([len(u) for u in us])])
    for eid in ("aberration", "refraction", "proper_motion"):
        eff, ref = registry.create(eid), registry.create(eid)
        eff.prepare(stamps, id_frames, u_frames, SITE, np.full(3, 101200.0), np.full(3, 5.0))
        ref.use_prepared(eff.prepared_table())
        ctxs = contexts()
        got = eff.directions_jacobian_frames(np.ones(1), us, np.concatenate(us), offs, ctxs)
        want = np.concatenate([ref._cached_delta(u, c) for u, c in zip(us, contexts(),
                                                                        strict=True)])
        assert got.shape == (len(want), 3, 1)
        np.testing.assert_array_equal(got[:, :, 0], want)
        for c, row in zip(ctxs, table, strict=True):  # which went frame by frame
            taken = (not eff.uses_weather) if row[4] is None else row[4]
            assert ("_direction_cache" in c.extra) is not taken


def test_a_bags_direction_tables_are_made_once(sim):
    """Models replayed over the same bag in memory share each direction effect's table
    (``StarModel.prepare_frames``, ``BagData.prepared``): the same numbers as a table made
    for the bag afresh; another bag (``dataclasses.replace``), other frames or a pickled
    copy make their own."""
    import dataclasses
    import pickle

    from stellar_cal_ros.methods.frames import bag_data_from_simulation
    from stellar_cal_ros.methods.replay import build_model

    def tables(model) -> dict:
        return {type(e).__name__: e.prepared_table()[1]
                for e, _, _ in model._chain[Stage.DIRECTION]}

    data = bag_data_from_simulation(sim)
    first = build_model(sim.prior, ["aberration", "refraction", "proper_motion"])
    first.prepare_frames(data)
    again = build_model(sim.prior, ["aberration"])
    again.prepare_frames(data)
    assert tables(again)["Aberration"] is tables(first)["Aberration"]  # made once
    other = dataclasses.replace(data)
    assert not other.prepared  # a new bag object starts empty
    fresh = build_model(sim.prior, ["aberration"])
    fresh.prepare_frames(other)
    shared, made = tables(again)["Aberration"], tables(fresh)["Aberration"]
    assert made is not shared and len(made) == len(shared) > 100
    for stamp, row in made.items():
        np.testing.assert_array_equal(row.delta, shared[stamp].delta)
        np.testing.assert_array_equal(row.ids, shared[stamp].ids)
    data.frames = data.frames[:-1]  # other frames: made again
    fewer = build_model(sim.prior, ["aberration"])
    fewer.prepare_frames(data)
    assert tables(fewer)["Aberration"] is not shared
    assert len(tables(fewer)["Aberration"]) == len(shared) - 1
    assert not pickle.loads(pickle.dumps(data)).prepared  # not sent to a worker


def test_proper_motion_without_identifications(stars):
    eff = registry.create("proper_motion")
    ctx = make_ctx(stars)
    ctx.catalog_id = np.zeros(0, dtype=np.int64)
    u_i = stars[1]
    assert np.array_equal(eff.directions(np.ones(1), u_i, ctx), u_i)
    ctx.catalog_id = np.zeros(len(u_i), dtype=np.int64)  # 0: not identified
    assert not np.any(eff.directions_jacobian(np.ones(1), u_i, ctx))
    ctx.catalog_id = stars[0][:3]
    with pytest.raises(ModelError):
        eff.directions(np.ones(1), u_i, ctx)


def test_refraction_needs_a_site(stars):
    ctx = make_ctx(stars)
    ctx.site = None
    with pytest.raises(ModelError, match="site"):
        registry.create("refraction").directions(np.ones(1), stars[1], ctx)


# ------------------------------------------------------------------ prior → result round trip
def _sigma_at(sigma: dict, path: str):
    node = sigma
    for key in path.split("."):
        assert isinstance(node, dict) and key in node, f"sigma.{path} missing"
        node = node[key]
    return node


def _expected_sigma_paths(eff: Effect) -> list[str]:
    if eff.id == "installation":
        return ["installation.rotation_vector"]
    if eff.id == "time_offset":
        return ["time_offset"]
    if eff.stage in (Stage.GYRO, Stage.ACCEL):
        block = "gyro" if eff.stage is Stage.GYRO else "accelerometer"
        return [f"{block}.bias" if eff.id.endswith("_bias") else f"{block}.error_matrix"]
    if eff.id in ("focal_length", "principal_point"):
        return ["camera.camera_matrix"]
    if eff.stage is Stage.CAMERA and eff.id not in ("pixel_aspect", "thermal_focal_length"):
        return ["camera.distortion_coefficients"]
    return [f"effects.{eff.id}.{n}" for n in eff.parameter_names]


def _assert_same_numbers(a, b):
    np.testing.assert_allclose(a.camera.parameters(), b.camera.parameters(), rtol=1e-14, atol=0)
    assert a.camera.width == b.camera.width and a.camera.height == b.camera.height
    assert (a.installation.inv() * b.installation).magnitude() < 1e-15
    for key in ("gyro_bias", "gyro_error_matrix", "accel_bias", "accel_error_matrix"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key), err_msg=key)
    assert a.time_offset == b.time_offset


@pytest.mark.parametrize("which", ["sim_prior", "rich_prior"])
@pytest.mark.parametrize("eid", ALL_IDS)
def test_initial_store_round_trip(eid, which, sim, tmp_path):
    prior = sim.prior if which == "sim_prior" else rich_prior(sim)
    eff = registry.create(eid)
    value, sigma = eff.initial(prior)
    assert value.shape == sigma.shape == (eff.size,)
    assert np.all(np.isfinite(value)) and np.all(np.isfinite(sigma)) and np.all(sigma > 0)
    cal = copy.deepcopy(prior)
    eff.store(value, sigma, cal)
    _assert_same_numbers(cal, prior)
    for key, block in prior.effects.items():  # the effects block keeps its values
        for name, v in block.items():
            assert cal.effects[key][name] == pytest.approx(v, rel=1e-15), f"{key}.{name}"
    # the stored calibration is a prior giving the same start again (value and sigma)
    v2, s2 = registry.create(eid).initial(cal)
    np.testing.assert_allclose(v2, value, rtol=1e-14, atol=1e-300)
    np.testing.assert_allclose(s2, sigma, rtol=1e-14, atol=0)
    # the YAML file is loadable, keeps the numbers, and the sigma is in the contract layout
    path = tmp_path / "result.yaml"
    save_calibration(cal, path)
    back = load_calibration(path)
    _assert_same_numbers(back, cal)
    assert back.sigma == cal.sigma and back.effects == cal.effects
    for spec in _expected_sigma_paths(eff):
        node = _sigma_at(back.sigma, spec)
        if spec == "installation.rotation_vector":
            np.testing.assert_allclose(node, sigma, rtol=1e-15)
        elif spec == "time_offset":
            assert node == pytest.approx(sigma[0], rel=1e-15)
        elif spec.endswith(".bias"):
            np.testing.assert_allclose(node, sigma, rtol=1e-15)
        elif spec.endswith("error_matrix") and not spec.startswith("camera"):
            flat = [3 * i + j for i, j in eff.entries]
            assert len(node) == 9
            np.testing.assert_allclose(np.asarray(node)[flat], sigma, rtol=1e-15)
        elif spec.startswith("camera."):
            data = node["data"]
            assert node["rows"] * node["cols"] == len(data)
            if spec.endswith("camera_matrix"):
                assert len(data) == 9
            else:
                n_cam = len(back.camera.to_yaml_dict()["distortion_coefficients"]["data"])
                assert len(data) >= n_cam
            names = getattr(eff, "camera_entries", ("fx",))
            for name, s in zip(names, sigma, strict=False):
                k = {"fx": 0, "fy": 4, "cx": 2, "cy": 5}.get(name)
                got = data[k] if k is not None else data[CameraModel.PARAMETER_NAMES.index(
                    name) - 4]
                assert got == pytest.approx(s, rel=1e-15), name
        else:
            assert node == pytest.approx(sigma[list(eff.parameter_names).index(
                spec.rsplit(".", 1)[1])], rel=1e-15)


def test_all_effects_stored_together(sim, tmp_path):
    """Storing every effect's initial value (in registry order) changes no number."""
    prior = rich_prior(sim)
    cal = copy.deepcopy(prior)
    for eff in registry.create_many(ALL_IDS):
        value, sigma = eff.initial(prior)
        eff.store(value, sigma, cal)
    _assert_same_numbers(cal, prior)
    save_calibration(cal, tmp_path / "all.yaml")
    back = load_calibration(tmp_path / "all.yaml")
    _assert_same_numbers(back, prior)
    assert back.effects == cal.effects
    assert "pixel_aspect" not in back.effects  # fy lives in the camera block only
    for path in ("installation.rotation_vector", "camera.camera_matrix",
                 "camera.distortion_coefficients", "gyro.bias", "gyro.error_matrix",
                 "accelerometer.bias", "accelerometer.error_matrix", "time_offset"):
        _sigma_at(back.sigma, path)


def test_store_writes_the_estimate(sim):
    """A value away from the prior lands where the contract puts it."""
    prior = sim.prior
    cal = copy.deepcopy(prior)
    delta = np.array([1e-3, -2e-3, 3e-3])
    inst = registry.create("installation")
    inst.initial(prior)
    inst.store(delta, np.full(3, 1e-4), cal)
    want = prior.installation * Rotation.from_rotvec(delta)
    assert (cal.installation.inv() * want).magnitude() < 1e-15
    pp = registry.create("principal_point")
    pp.store(np.array([500.0, 530.0]), np.array([1.0, 2.0]), cal)
    assert (cal.camera.cx, cal.camera.cy) == (500.0, 530.0)
    assert _sigma_at(cal.sigma, "camera.camera_matrix")["data"][2] == 1.0
    to = registry.create("time_offset")
    to.store(np.array([0.021]), np.array([0.002]), cal)
    assert cal.time_offset == 0.021 and cal.sigma["time_offset"] == 0.002


def test_an_estimate_beyond_what_an_instrument_reaches_is_implausible():
    """:func:`~stellar_cal_ros.diagnosis.discover.beyond_limit`: a detector tilt of 122 mrad
    (unseen case ``rolling`` seed 23: a rolling shutter fitted as tau (-110, -54) mrad, σ
    0.1 mrad) is beyond the tilt's physical limit (50 mrad) and said so; the acceptance
    cases' (10, -8) mrad, a tilt at the limit within 5σ, and an effect with no limit are not."""
    from stellar_cal_ros.diagnosis.discover import beyond_limit

    tilt = registry.create("image_plane_tilt")
    why = beyond_limit(tilt, [-0.1095, -0.0536], [6.6e-5, 7.8e-5])
    assert why.startswith("the data fit image_plane_tilt of 122 mrad, beyond what a working "
                          "instrument reaches (50 mrad)"), why
    assert beyond_limit(tilt, [0.01, -0.008], [1e-4, 1e-4]) == ""
    assert beyond_limit(tilt, [0.054, 0.0], [1e-3, 1e-3]) == ""  # 4 mrad over: 4σ
    assert beyond_limit(tilt, [0.056, 0.0], [1e-3, 1e-3]) != ""  # 6σ over
    assert beyond_limit(registry.create("time_offset"), [0.5], [1e-5]) == ""


def test_a_clock_drift_without_a_reference_stamp_counts_from_the_first_frame(sim):
    """A prior without a stamp (0, a hand-written prior) must not put clock_drift's rate on
    a lever of 1.7e9 s (the POSIX epoch): the first frame's stamp is the reference, and the
    result stores it."""
    prior = copy.deepcopy(sim.prior)
    prior.stamp = 0.0
    prior.effects = {}
    eff = registry.create("clock_drift")
    value, _ = eff.initial(prior)
    first, later = 1.7e9, 1.7e9 + 100.0
    assert eff.time_shift(np.array([1e-5]), FrameContext(stamp=first)) == 0.0
    assert eff.time_shift_jacobian(value, FrameContext(stamp=later))[0] == pytest.approx(100.0)
    cal = copy.deepcopy(prior)
    eff.store(np.array([1e-5]), np.array([1e-7]), cal)
    assert cal.effects["clock_drift"]["reference_stamp"] == first


def test_a_clock_drift_candidate_counts_from_the_run_s_start_not_a_result_s_stamp(sim):
    """Fails on coord2 3ff819c: discover's second round starts from the first round's
    result, whose stamp is its estimate's time (the run's end); the clock_drift candidate's
    prior (``candidate_prior``) took it as the reference, so at the first frames the rate
    sat on a lever of −300 s (σ 1e-3: 0.3 s of exposure time) and one update moved an
    exposure behind the one before (unseen case ``rolling_cols`` s22: "cannot propagate
    backwards in time").  The reference is the first frame's stamp, as for a prior stamp
    long before the run (an older calibration); the run's start (the simulated prior's
    stamp, 0.254 s before its first frame) and a stored reference stay."""
    from stellar_cal_ros.diagnosis.discover import candidate_prior

    first = sim.star_frames[0].stamp_ns * 1e-9
    assert 0.0 < first - sim.prior.stamp < 1.0  # the simulated bag's start
    for stamp, lever0 in ((first + 299.5, 0.0),  # a result's stamp: the run's last frame
                          (first - 30 * 86400.0, 0.0),  # a calibration 30 days older
                          (sim.prior.stamp, first - sim.prior.stamp)):  # the bag's start
        prior = copy.deepcopy(sim.prior)
        prior.stamp, prior.effects = stamp, {}
        cand = candidate_prior(prior, "clock_drift", sim.prior)
        eff = registry.create("clock_drift")
        value, sigma = eff.initial(cand)
        assert sigma[0] >= 1e-3
        lever = [eff.time_shift_jacobian(value, FrameContext(stamp=first + dt))[0]
                 for dt in (0.0, 100.0)]
        assert lever == pytest.approx([lever0, lever0 + 100.0], abs=1e-6)
        cal = copy.deepcopy(cand)
        eff.store(value, sigma, cal)
        assert cal.effects["clock_drift"]["reference_stamp"] == pytest.approx(first - lever0)
    stored = copy.deepcopy(sim.prior)  # a stored reference is the clock's: kept
    stored.stamp = first + 299.5
    stored.effects = {"clock_drift": {"rate": 2e-5, "reference_stamp": first - 50.0}}
    eff = registry.create("clock_drift")
    value, _ = eff.initial(stored)
    assert eff.time_shift(value, FrameContext(stamp=first)) == pytest.approx(2e-5 * 50.0)
