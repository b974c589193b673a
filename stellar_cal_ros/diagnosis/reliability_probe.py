"""The printed bias of a hidden effect, measured where the first order does not hold.

:func:`~stellar_cal_ros.diagnosis.reliability.external_reliability` states the shift an
undetected effect at its MDB leaves in each estimated parameter from the sensitivity
recursion (``−M b``) or the augmented run's joint posterior: first order, with the
filter's gain held fixed.  Beside a large shift of the same injection that misses the
filter's *gain response* — the change of its gain and linearization point with the state,
times the clean run's own corrections — which is first order in ``b`` where those
corrections are large (``psce_rotations``: the first updates of the slew after the 53 s
hold correct the attitude by 0.3-2.4 mrad; an image-plane tilt's printed gyro-bias shift
was 4-7x what the filter does, doc/benchmarks.md).  Those rows are flagged
(``remainders``: below :data:`~stellar_cal_ros.diagnosis.reliability.FIRST_ORDER_SHARE` of
the injection's largest shift in σ).

For each flagged (effect, parameter) the current model is re-run **twice** on the user's
own bag, with the effect injected at +MDB and at −MDB (:func:`with_effect`: the effect classes
render it at the trajectory, camera and sensors the run estimated — the twin's renderer,
:mod:`~stellar_cal_ros.diagnosis.twin`, without noise — and the increment is added to the
user's centroids and IMU samples), where the bag is (``Runs.on_bag``, as the flexure probe
of :mod:`~stellar_cal_ros.diagnosis.flexure`).  The paired difference of the two runs is
the filter's full response at that size, noise and gain response included (both signs:
the response is not odd in the effect); every row of that parameter keeps its first-order
value where the probe agrees within :data:`AGREE` at both signs, else the report prints the
measured shifts (:func:`apply`).  The runs also score the effect: where one sign's score
responds below the λ₀ the MDB is stated for (the tilt's second order), the MDB is restated
for both signs (:func:`both_signs`, :func:`secant`: one run more).  Cost: two runs per
flagged (effect, parameter), three where the MDB is restated; none on a bag where no row is
flagged.

Where the model does not fit the bag (:data:`FITS`) the bag's score responses are not its
twins' (the misfit's residuals move with the state), and ``--verify`` checks the test's MDB
on twins that fit: there the test MDB of a flagged row, and of a row whose MDB the excess
gate set (``mdb_test``), is checked at both signs on the bag's noise-free twin
(:func:`scores_on_twin`, :func:`twin_signs`, :func:`restate_test`), for the effects whose
increment is not odd in the size (:func:`even_energy`, from renders: no run for the others).
"""

from __future__ import annotations

import copy
import dataclasses
import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from stellar_cal_ros.core.noise import NoiseScales
from stellar_cal_ros.diagnosis import injection, reliability
from stellar_cal_ros.diagnosis.discover import excess_energy

log = logging.getLogger(__name__)

#: a first-order row is kept when the probe's shift is within this share of it; else the
#: measured shift is printed (the probe and a simulator injection of the same size differ
#: by up to ~16 % on rows near 1 σ, doc/benchmarks.md: 10 % keeps the issue's ±30 % bar)
AGREE = 0.1
#: the key of a probe run's values that holds the effect's score (not an estimate)
SCORE = "_score"
#: the key of a probe run's values that holds its window's excess variance per star (px²)
EXCESS = "_excess"
#: a round's screening run fits where its mean NIS / dof (the score test's dispersion,
#: :func:`~.screening.dispersion`) is at most this: there an effect's score responds on the
#: bag as on its twins and the probe's runs on the bag restate the MDB at both signs; above
#: it (``dt_step`` s23: 8.3) the per-sign responses are measured on the bag's noise-free
#: twin (:func:`scores_on_twin`)
FITS = 1.2
#: an effect whose increment's even part (:func:`even_energy`) holds at most this share of
#: √λ₀ at the size probed responds alike at both signs (within ~10 % in λ): its test MDB is
#: not run at both signs
LINEAR = 0.05
#: the twin's renderer draws no noise: the increment is the effect alone
_NOISELESS = NoiseScales(star=1e-12, gyro=1e-12, accel=1e-12)


def rendered(data, calibration, method: str, effects: dict[str, Any] | None = None,
             scene=None, imu: bool = True):
    """The noise-free twin of the bag under ``calibration`` with ``effects`` (simulate units).

    ``scene``: :func:`~stellar_cal_ros.diagnosis.twin.twin_scene` of the same bag,
    calibration and method, shared by the renders of one probe (the same twin).
    ``imu=False``: the IMU is not rendered (the same stars; see ``make_twin``).
    """
    from stellar_cal_ros.diagnosis.twin import make_twin

    return make_twin(data, calibration, effects or {}, 0, method, _NOISELESS, scene,
                     imu=imu).data


def rendered_stars(data, calibration, method: str, effects: dict[str, Any] | None = None,
                   scene=None, imu: bool = True):
    """:func:`rendered` without its frames: the stars in arrays and the IMU samples.

    (:func:`~stellar_cal_ros.diagnosis.twin.render`: the same numbers, what
    :func:`injection_of` needs; a 2-h bag's twin as 14 400 messages ≈ 10 MB a render.)
    """
    from stellar_cal_ros.diagnosis.twin import render

    return render(data, calibration, effects or {}, 0, method, _NOISELESS, scene, imu=imu)


def moves_imu(calibration, method: str, effect_id: str, delta: np.ndarray) -> bool:
    """Whether ``effect_id`` at ``delta`` changes the twin's IMU sensor model.

    Where it does not (a camera or direction effect), the twins with and without it render
    the same IMU samples, bit for bit: their difference is zero and the probe need not
    render them (:func:`injection_of`).
    """
    from stellar_cal_ros.diagnosis.twin import twin_model
    from stellar_cal_ros.effects.base import Stage

    m0, th0 = twin_model(calibration, method, {})
    m1, th1 = twin_model(calibration, method,
                         {effect_id: injection.simulation_value(effect_id, delta)})
    for stage in (Stage.GYRO, Stage.ACCEL):
        a, b = m0.sensor_model(th0, stage)[:2], m1.sensor_model(th1, stage)[:2]
        if any(not np.array_equal(x, y) for x, y in zip(a, b, strict=True)):
            return True
    return False


def _moves_imu(calibration, method: str, effect_id: str, delta) -> bool:
    """:func:`moves_imu`; ``True`` where it cannot tell (the render then says why)."""
    try:
        return moves_imu(calibration, method, effect_id, np.asarray(delta))
    except Exception:  # the probe's render reports it
        return True


@dataclasses.dataclass
class Injection:
    """What an effect adds to the user's bag (:func:`injection_of`), without the bag.

    ``stars``: :func:`star_steps` (the frames the twins hold, the user's star rows they
    move and by how much); ``imu_w``, ``imu_f``: the samples' steps, ``None`` where zero.
    Small beside the twins it comes from (a 2-h bag: ~2 MB for a camera effect), so a
    probe renders every injection first and replays them after its twins are dropped.
    """

    stars: tuple[np.ndarray, np.ndarray, np.ndarray]
    imu_w: np.ndarray | None
    imu_f: np.ndarray | None

    def on(self, data):
        """``data`` with the injection added (:func:`with_effect`'s bag)."""
        return dataclasses.replace(
            data, frames=moved_frames(data.frames, *self.stars),
            imu_w=data.imu_w if self.imu_w is None else np.asarray(data.imu_w) + self.imu_w,
            imu_f=data.imu_f if self.imu_f is None else np.asarray(data.imu_f) + self.imu_f)


def injection_of(data, calibration, method: str, effect_id: str, delta: np.ndarray,
                 plain=None, scene=None, imu: bool = True, onto=None,
                 user=None) -> Injection:
    """The increment of ``effect_id`` at ``delta`` (its units) on the user's bag.

    The difference of two noise-free twins (:func:`rendered`) of the bag under
    ``calibration`` (the run's estimate), without (``plain``, if already made) and with the
    effect: per star of each frame (by stamp and catalogue id; a star the twin leaves off
    the detector keeps its centroid) and per IMU sample.  ``scene``: see :func:`rendered`;
    ``imu=False`` where the effect leaves the IMU alone (:func:`moves_imu`; ``plain`` may
    then hold the user's samples).  ``onto``: the bag whose star rows the increments are
    laid on (default ``data``; the probe's noise-free twin, which may hold fewer stars than
    the bag its scene was made from: the renders stay on ``data``).  ``user``: that bag's
    star columns (:func:`star_columns` of its frames) if already made (one call's
    injections lay theirs on the same frames).
    """
    plain = plain if plain is not None else rendered_stars(data, calibration, method,
                                                           scene=scene, imu=imu)
    moved = rendered_stars(data, calibration, method,
                           {effect_id: injection.simulation_value(effect_id, delta)}, scene,
                           imu=imu)
    stars = star_steps(user if user is not None else (data if onto is None else onto).frames,
                       _twin_stars(plain), _twin_stars(moved))
    if not imu:
        return Injection(stars, None, None)
    return Injection(stars, _step(moved.imu_w, plain.imu_w), _step(moved.imu_f, plain.imu_f))


def with_effect(data, calibration, method: str, effect_id: str, delta: np.ndarray,
                plain=None, scene=None):
    """The user's bag with ``effect_id`` at ``delta`` (its units) added, rendered.

    :func:`injection_of` on ``data``.
    """
    return injection_of(data, calibration, method, effect_id, delta, plain, scene).on(data)


def _twin_stars(twin):
    """A twin's stars for :func:`star_steps`: its frames, or :func:`rendered_stars`' columns."""
    return twin.stars.kept() if hasattr(twin, "stars") else twin.frames


def _step(moved: np.ndarray, plain: np.ndarray) -> np.ndarray | None:
    """``moved − plain``; ``None`` where it is zero.

    A camera or direction effect renders no IMU increment: the sum would be a copy of the
    samples (2 x 17 MB on a 2-h bag, held while the probe's run replays them).
    """
    step = moved - plain
    return step if step.any() else None


def add_steps(user: list, plain: list, moved: list) -> list:
    """``user``'s frames with each star moved by its step from ``plain`` to ``moved``.

    Per star of each frame, by stamp and catalogue id (the last row of an id or a stamp
    that repeats); a star or frame the twins do not both hold keeps its centroid.
    (:func:`star_steps`, then :func:`moved_frames`.)
    """
    return moved_frames(user, *star_steps(user, plain, moved))


def star_steps(user: list, plain, moved) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The step of each star of ``user`` from ``plain`` to ``moved`` (see :func:`add_steps`).

    ``(pair, hit, step)``: per user frame the twins' frame of its stamp (−1: none), per
    star row of the user's frames whether the twins both hold it, and the steps of those
    rows in order.  In arrays over the whole bag: the per-frame dictionaries it replaces
    cost ~1 CPU-s per probe run on a 2-h bag; the same sums (test_reliability_injection
    holds it to them).  ``user``, ``plain``, ``moved``: frames, or their stars as columns
    ``(stamps, counts, ids, uv)`` (:func:`star_columns`,
    :meth:`~stellar_cal_ros.diagnosis.twin.TwinStars.kept`).
    """
    u_stamp, u_n, u_ids, _ = _columns(user)
    a_stamp, a_n, a_ids, a_uv = _columns(plain)
    _, b_n, b_ids, b_uv = _columns(moved)
    k_of = {s: k for k, s in enumerate(a_stamp.tolist())}
    pair = np.array([k_of.get(s, -1) for s in u_stamp.tolist()], dtype=np.int64)
    codes = np.unique(np.concatenate([a_ids, b_ids, u_ids]))
    a_key = _keys(a_n, np.arange(len(a_n)), a_ids, codes)
    b_key = _keys(b_n, np.arange(len(b_n)), b_ids, codes)
    u_key = _keys(u_n, pair, u_ids, codes)
    # per (frame, star) of both twins the last row (as the dict over them kept), sorted
    a_last, b_last = _last(a_key), _last(b_key)
    # both key lists are sorted and distinct (np.unique's order): the plain twin's stars the
    # moved one holds, by one binary search (np.isin sorted both again)
    a_sorted, b_sorted = a_key[a_last], b_key[b_last]
    in_b = np.minimum(np.searchsorted(b_sorted, a_sorted), max(len(b_sorted) - 1, 0))
    both = (b_sorted[in_b] == a_sorted) if len(b_sorted) else np.zeros(len(a_sorted), bool)
    s_key = a_sorted[both]
    step = b_uv[b_last[in_b[both]]] - a_uv[a_last[both]]
    at = np.minimum(np.searchsorted(s_key, u_key), max(len(s_key) - 1, 0))
    hit = (np.repeat(pair, u_n) >= 0) & (len(s_key) > 0)
    hit[hit] = s_key[at[hit]] == u_key[hit]
    return pair, hit, step[at[hit]]


def moved_frames(user: list, pair: np.ndarray, hit: np.ndarray, step: np.ndarray) -> list:
    """``user``'s frames with the steps of :func:`star_steps` added to their centroids.

    Every centroid moved in one array (the same sums as frame by frame); a frame the twins
    hold gets a copy of its message whose ``uv`` is its rows of that array.
    """
    counts = np.fromiter((len(f.catalog_id) for f in user), dtype=np.intp, count=len(user))
    ends = np.cumsum(counts).tolist()
    uv = np.concatenate([np.zeros((0, 2))] + [np.asarray(f.uv, dtype=float).reshape(-1, 2)
                                              for f in user])
    uv[hit] += step
    frames, start = [], 0
    for f, end, j in zip(user, ends, (pair >= 0).tolist(), strict=True):
        if j:
            g = _shallow(f)
            # (a frame without stars keeps its own empty array's shape)
            g.uv = uv[start:end] if end > start else np.array(f.uv, dtype=float, copy=True)
            f = g
        frames.append(f)
        start = end
    return frames


def _shallow(frame):
    """``copy.copy(frame)`` without its reduce protocol (~10 µs a frame on a 2-h bag)."""
    if not hasattr(frame, "__dict__"):
        return copy.copy(frame)
    g = object.__new__(type(frame))
    g.__dict__.update(frame.__dict__)
    return g


def _columns(frames) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(stamps, counts, ids, uv)`` of ``frames``' stars (already columns: as given)."""
    if isinstance(frames, tuple):
        return frames
    return star_columns(frames)


def star_columns(frames: list) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(stamps, counts, ids, uv)`` of ``frames``' stars, for :func:`star_steps`."""
    stamps = np.array([int(f.stamp_ns) for f in frames], dtype=np.int64)
    counts = np.array([len(f.catalog_id) for f in frames], dtype=np.intp)
    ids = np.concatenate([np.zeros(0, dtype=np.int64)]
                         + [np.asarray(f.catalog_id, dtype=np.int64).reshape(-1)
                            for f in frames])
    uv = np.concatenate([np.zeros((0, 2))] + [np.asarray(f.uv, dtype=float).reshape(-1, 2)
                                              for f in frames])
    return stamps, counts, ids, uv


def _keys(counts: np.ndarray, index: np.ndarray, ids: np.ndarray, codes: np.ndarray
          ) -> np.ndarray:
    """One key per star: its frame's ``index`` and its id's place in ``codes``."""
    return np.repeat(np.asarray(index, dtype=np.int64), counts) * len(codes) \
        + np.searchsorted(codes, ids)


def _last(key: np.ndarray) -> np.ndarray:
    """The row of the last occurrence of each distinct key."""
    rev = key[::-1]
    _, first = np.unique(rev, return_index=True)
    return len(key) - 1 - first


def own_shift(calibration, method: str, effect_id: str, delta: np.ndarray) -> dict[str, float]:
    """What the effect at ``delta`` itself does to the equivalent principal point (px).

    An effect can move the true value too; the printed bias of the equivalent principal
    point is the estimate's shift minus this
    (:func:`~stellar_cal_ros.diagnosis.reliability.bias_rows`), and so is every measured
    one (the probe here, ``discover --verify``, the injection tests).  The point is the
    image of the nominal boresight, which the installation puts at the principal point:
    an effect acting about the principal point (focal length, aspect, distortion, an
    image-plane tilt) leaves it where it is (0 px), a principal-point offset moves it one
    to one.
    """
    from stellar_cal_ros.diagnosis.runstats import EPP_NAMES
    from stellar_cal_ros.diagnosis.twin import twin_model
    from stellar_cal_ros.methods.results import epp_jacobian

    value = {effect_id: injection.simulation_value(effect_id, delta)}
    m0, th0 = twin_model(calibration, method, {})
    m1, th1 = twin_model(calibration, method, value)
    step = epp_jacobian(m1, th1, 0)[0] - epp_jacobian(m0, th0, 0)[0]
    return dict(zip(EPP_NAMES, map(float, step), strict=True))


def measure_on_bag(data, spec, prior, effects: tuple[str, ...], fraction: float, noise,
                   classes: tuple[type, ...], calibration,
                   probes: tuple[tuple[str, tuple[float, ...]], ...]
                   ) -> list[dict[str, float] | None]:
    """The current model's estimates on the bag with each probe injected, where the bag is.

    For :meth:`~stellar_cal_ros.diagnosis.parallel.Runs.on_bag`: per ``(effect, delta)`` of
    ``probes``, the same call as the diagnosis's run of ``effects`` from ``prior`` with
    ``noise`` (the two differ by the injection only).  ``{name: value}`` of every parameter
    and of the equivalent principal point less the effect's own change of it
    (:func:`own_shift`); ``None`` for a run that fails (the probe is an addition: it never
    stops a diagnosis).
    """
    def values(run, effect_id: str, delta: np.ndarray) -> dict[str, float]:
        out = injection.run_values(run)
        out[EXCESS] = float(run.stats.window(fraction)["excess_variance"])
        # the effect's score in this run (a consider parameter: the estimates are the
        # run's without it): against the round's, the score's response at this size
        scored = spec.screen(run, [effect_id]) if spec.screen is not None else {}
        if effect_id in scored and len(scored[effect_id]) > 5:
            out[SCORE] = np.asarray(scored[effect_id][5], dtype=float)
        for q, v in own_shift(calibration, spec.name, effect_id, delta).items():
            if q in out:
                out[q] -= v
        return out

    return _runs_on_bag(data, spec, prior, effects, fraction, noise, classes, calibration,
                        probes, values)


def clock_on_bag(data, spec, prior, effects: tuple[str, ...], fraction: float, noise,
                 classes: tuple[type, ...], calibration,
                 probes: tuple[tuple[str, tuple[float, ...]], ...]) -> list[Any]:
    """The clock test of the current model's run on the bag with each probe injected.

    As :func:`measure_on_bag` (the same injections and run), but the run keeps its residual
    table and returns its clock test (:func:`~stellar_cal_ros.diagnosis.clock.clock_test`
    with the run's own calibration, as :func:`~stellar_cal_ros.diagnosis.auto._top` asks
    it of a round's run), ``None`` where none could be made or the run failed: whether the
    clock rule (:func:`~stellar_cal_ros.diagnosis.clock.refuses`) still refuses a rate
    effect at that size (:func:`~stellar_cal_ros.diagnosis.auto._refused_rows`).
    """
    from stellar_cal_ros.diagnosis import clock

    def ticks(run, effect_id: str, delta: np.ndarray):
        if run.residuals is None:
            return None
        return clock.clock_test(run.residuals, run.calibration or prior, fraction)

    return _runs_on_bag(data, spec, prior, effects, fraction, noise, classes, calibration,
                        probes, ticks, tables=True)


def clock_runs(runs, prior, effects: tuple[str, ...], calibration, probes: tuple) -> list[Any]:
    """:func:`clock_on_bag` on ``runs``' bag, in one call where the bag is (one render).

    The model ``effects`` from ``prior``, the injections rendered under ``calibration``.
    """
    return runs.later(clock_on_bag, runs.spec, prior, tuple(effects), runs.fraction,
                      runs.noise, runs.classes, calibration, probes)()


def scores_on_twin(data, spec, prior, effects: tuple[str, ...], fraction: float, noise,
                   classes: tuple[type, ...], calibration,
                   probes: tuple[tuple[str, tuple[float, ...]], ...],
                   limits: tuple[float, ...] | None = None,
                   noise_variance: float = float("nan")) -> list[Any]:
    """Each probe's score response on the bag's noise-free twin: ``(Δs, I)`` per probe.

    As :func:`measure_on_bag`, on the twin of the bag under ``calibration``
    (:func:`rendered`: the bag's motion, stamps and stars, no noise, no misfit) instead of
    the bag: the current model's run on the twin with each probe injected scores its
    effect, paired against the run on the twin alone (``Δs``; ``I``: that run's
    information, which a twin that fits divides by nothing), as ``discover --verify``'s
    twins respond (:mod:`~.verify`).  On a bag the model does not fit the bag's own
    response is not that: the tilt's score on ``dt_step`` s23 (screen dispersion 8.3)
    moved 756 / 214 (in λ) at ± its MDB where its noise-free twin moves 29.6 / 7.1 (and
    ``--verify``'s twin of seed 1 31 / 9.6: the misfit's residuals times the score's own
    change with the state).  ``None`` for a probe whose
    run (or its effect's run without it) fails.

    ``limits``: ``probes`` are pairs (``+size``, ``−size``), one limit each; a pair whose
    increments' even part (:func:`even_energy`, whitened by ``noise_variance`` per star and
    the twin's IMU noise) is at most its limit is not run (the response is then odd in the
    size: either sign responds alike) and gives ``{"even": E}``; the others
    ``{"even": E, "plus": (Δs, I), "minus": ...}``.
    """
    from stellar_cal_ros.diagnosis.noise import stated_scales
    from stellar_cal_ros.diagnosis.runstats import register_effect_classes
    from stellar_cal_ros.diagnosis.twin import twin_scene

    register_effect_classes(classes)
    scene = twin_scene(data, calibration, spec.name, imu=True)
    twin = rendered(data, calibration, spec.name, scene=scene)
    # the increments rendered from the bag's scene, laid on the twin's stars (by stamp and
    # catalogue id: a star the twin left off the detector is not hit)
    injections = _rendered_injections(data, spec, calibration, probes, scene, onto=twin)
    for failed in injections:
        if isinstance(failed, Exception):
            raise failed
    even: list[float] = []
    run = list(range(len(probes)))
    if limits is not None:
        rates = noise or stated_scales(calibration)
        dt = data.nominal_dt or float(np.median(np.diff(scene.t)))
        sig = (scene.arw * rates.gyro / np.sqrt(dt), scene.vrw * rates.accel / np.sqrt(dt))
        even = [even_energy(injections[2 * k], injections[2 * k + 1], noise_variance, sig)
                for k in range(len(limits))]
        run = [i for i in run if not even[i // 2] <= limits[i // 2]]
    del scene

    def scored(run, effect_id: str, delta: np.ndarray):
        item = spec.screen(run, [effect_id]).get(effect_id)
        if item is None or len(item) <= 5:
            return None
        return np.asarray(item[5], dtype=float), np.atleast_2d(np.asarray(item[2], float))

    asked = [probes[i] for i in run]
    alone = tuple(dict.fromkeys((e, tuple(0.0 for _ in d)) for e, d in asked))
    nothing = Injection((np.full(len(twin.frames), -1), np.zeros(0, bool), np.zeros((0, 2))),
                        None, None)
    rows = _runs_on_bag(twin, spec, prior, effects, fraction, noise, classes, calibration,
                        alone, scored, injections=[nothing] * len(alone)) if alone else []
    zero = dict(zip((e for e, _ in alone), rows, strict=True))
    moved = _runs_on_bag(twin, spec, prior, effects, fraction, noise, classes, calibration,
                         tuple(asked), scored, injections=[injections[i] for i in run])
    got: list[Any] = [None] * len(probes)
    for i, (effect_id, _), row in zip(run, asked, moved, strict=True):
        z = zero[effect_id]
        got[i] = None if row is None or z is None else (row[0] - z[0], z[1])
    if limits is None:
        return got
    return [{"even": even[k], **({"plus": got[2 * k], "minus": got[2 * k + 1]}
                                 if 2 * k in run else {})} for k in range(len(limits))]


def even_energy(plus: Injection, minus: Injection, noise_variance: float,
                imu_sigma: tuple[float, float]) -> float:
    """The whitened energy of the part of an effect's increment that is even in its size.

    ``plus``, ``minus``: the increments at ± a size (:func:`injection_of`); per star hit by
    both ``(Δ₊ + Δ₋) / 2`` over the per-axis variance ``noise_variance / 2`` (the window's
    variance per star, both axes), and per IMU sample over ``imu_sigma`` (gyro, accel).  A
    score's response ``λ± = |P(o ± e)|²`` (``o``, ``e`` the odd and even parts, ``P`` the
    score's projection of the whitened innovations, which never hold more than the
    increment's energy) then differs between the signs by at most ``|√λ± − |Po|| ≤ √E``:
    E is 0 for an effect linear in its parameters (a k3, an aspect, a scale factor:
    ≤ 2e-12 rendered on ``dt_step`` s23), the image-plane tilt's second order not (37-41
    there, λ₀ 19.4).
    """
    def rows(inj: Injection) -> np.ndarray:
        _, hit, step = inj.stars
        out = np.full((len(hit), 2), np.nan)
        out[hit] = step
        return out

    e = 0.5 * (rows(plus) + rows(minus))
    energy = float(np.nansum(e * e) / (0.5 * noise_variance))
    for a, b, sig in ((plus.imu_w, minus.imu_w, imu_sigma[0]),
                      (plus.imu_f, minus.imu_f, imu_sigma[1])):
        if a is None and b is None:
            continue
        half = 0.5 * ((0.0 if a is None else a) + (0.0 if b is None else b))
        energy += float(np.sum(np.square(half)) / sig ** 2)
    return energy


def _runs_on_bag(data, spec, prior, effects: tuple[str, ...], fraction: float, noise,
                 classes: tuple[type, ...], calibration,
                 probes: tuple[tuple[str, tuple[float, ...]], ...], measure,
                 tables: bool = False, injections: list | None = None) -> list[Any]:
    """Per probe, ``measure(run, effect, delta)`` of the model's run with it injected.

    The runs of :func:`measure_on_bag` and :func:`clock_on_bag`: every injection rendered
    first, then one run each (its effect scored where the method screens, unless
    ``tables``: the run keeps its residual table instead); ``None`` for one that fails.
    ``injections``: the probes' increments already rendered (:func:`scores_on_twin`).
    """
    from stellar_cal_ros.diagnosis.runstats import (
        forget_prepared,
        quiet,
        register_effect_classes,
    )

    register_effect_classes(classes)
    # the gyro-against-stars check is off: it changes no estimate, the current model's run
    # on this bag (``calibration``'s, which the probe needs finished) has judged the gyro,
    # and an injection at a detectable size is far below the gross faults it looks for
    # (deg/s, a dead gyro, swapped axes); ≈ 1 CPU-s a run on a 2-h bag
    kw: dict[str, Any] = {"gyro_fault": "off"}
    if noise is not None:
        kw["noise"] = noise
    # every injection first (one scene and plain twin for all), then the runs: the twins
    # (on a 2-h bag the scene ~100 MB, each render ~20-60 MB) are not held while the filter
    # replays, nor a previous probe's moved bag while the next is rendered
    # the probe's runs replay other data: the direction effects' tables the round's runs
    # shared on this bag (≈ 20 MB an effect on a 2-h bag) are not held through its renders
    forget_prepared(data)
    if injections is None:
        injections = _rendered_injections(data, spec, calibration, probes)
    out: list[Any] = []
    for (effect_id, delta), inj in zip(probes, injections, strict=True):
        score = {"consider": [effect_id]} if spec.screen is not None and not tables else {}
        try:
            if isinstance(inj, Exception):
                raise inj
            moved = inj.on(data)
            with quiet():
                run = spec.runner(moved, prior, list(effects), keep_tables=tables,
                                  eval_fraction=fraction, **kw, **score)
            del moved
            out.append(measure(run, effect_id, np.asarray(delta)))
            del run
        except Exception as exc:
            log.warning("the probe of %s did not run: %s: %s", effect_id,
                        type(exc).__name__, exc)
            out.append(None)
    return out


def _rendered_injections(data, spec, calibration, probes: tuple, scene=None,
                         onto=None) -> list:
    """Each probe's :class:`Injection` on ``data`` (one scene and plain twin for all).

    An exception in place of one that could not be rendered (its run reports it).
    ``scene``: the bag's twin scene if already made; ``onto``: see :func:`injection_of`.
    """
    injections: list[Injection | Exception] = []
    plain = user = None
    imu = [_moves_imu(calibration, spec.name, e, d) for e, d in probes]
    for (effect_id, delta), moves in zip(probes, imu, strict=True):
        try:
            if scene is None:
                from stellar_cal_ros.diagnosis.twin import twin_scene

                scene = twin_scene(data, calibration, spec.name, imu=any(imu))
            # the plain twin renders the IMU if any probe of this call moves it
            plain = plain if plain is not None else rendered_stars(
                data, calibration, spec.name, scene=scene, imu=any(imu))
            # (the frames every increment is laid on: their star columns made once)
            user = user if user is not None else star_columns(
                (data if onto is None else onto).frames)
            injections.append(injection_of(data, calibration, spec.name, effect_id,
                                           np.asarray(delta), plain, scene, imu=moves,
                                           onto=onto, user=user))
        except Exception as exc:
            injections.append(exc)
    return injections


def score_step(score: np.ndarray | None, screen) -> np.ndarray | None:
    """``Δs``: the change of the effect's score a probe's injection makes on the bag.

    ``score``: the effect's score in the probe's run; ``screen``: the round's score test of
    the effect on the bag (its score ``s₀``).  Paired (the bag's noise is in both): the
    score's response at that size.  ``None`` where either is missing.
    """
    if score is None or screen is None or screen.score is None:
        return None
    return np.asarray(score, dtype=float) - np.asarray(screen.score, dtype=float)


def both_signs(entry: dict[str, Any], parameter: str, d_plus: np.ndarray | None,
               d_minus: np.ndarray | None, screen) -> tuple[float, float] | None:
    """The MDB of ``parameter`` that holds at both signs, from the probe's score responses.

    The printed MDB (``sqrt(λ₀ / I_jj)``) is first order: the score's non-centrality
    ``λ = Δsᵀ I⁻¹ Δs / φ`` (the round's dispersion φ, as the MDB's; on the test's
    directions, :meth:`~.screening.ScreenResult.response`) at ±MDB is λ₀ only where the
    score is linear in the effect.  An image-plane tilt's second-order
    response makes one sign weaker (psce, twins of a clean bag: 0.55 λ₀ at +τx, found 8
    of 20; 2.4 λ₀ at −τx).  Where the probe ran at the MDB itself and the weaker sign's
    response ``λ_w`` is below λ₀, the MDB becomes ``mdb · c₁``, ``c₁ = sqrt(λ₀ / λ_w)``
    (one step with the response taken as quadratic in the size), ``mdb_set_by`` "probe",
    ``mdb_test`` the first-order MDBs; ``(sign, c₁)`` is returned for :func:`secant`.  An
    MDB the excess gate set (``mdb_set_by`` "explained_gate") is left as it is.
    ``probe[parameter]`` keeps ``lam_plus``/``lam_minus`` (the responses at ±size).  The
    biases stay those measured at the probed size (``hidden_size``).
    """
    if d_plus is None or d_minus is None:
        return None
    lam = {"lam_plus": screen.response(d_plus), "lam_minus": screen.response(d_minus)}
    entry["probe"][parameter].update(lam)
    mdb, lam0, worse = entry["mdb"][parameter], float(entry["lam0"]), min(lam.values())
    # an MDB the excess gate set (:func:`~.reliability.detectability`) is not the score
    # test's: the score's response does not restate it
    if entry.get("mdb_set_by") == "explained_gate":
        return None
    if not (0.0 < worse < lam0 and entry["hidden_size"][parameter] == mdb):
        return None
    step = float(np.sqrt(lam0 / worse))
    entry.setdefault("mdb_test", dict(entry["mdb"]))
    entry["mdb_set_by"] = "probe"
    restate(entry, parameter, mdb * step)
    return (1.0 if lam["lam_plus"] <= lam["lam_minus"] else -1.0), step


def restate(entry: dict[str, Any], parameter: str, value: float) -> None:
    """``entry``'s printed MDB of ``parameter`` restated by runs on the bag: ``value``.

    ``mdb_identified`` (:func:`~.reliability.identification`) is at least the MDB: it
    follows a raised one.
    """
    entry["mdb"][parameter] = float(value)
    ident = entry.get("mdb_identified") or {}
    if parameter in ident:
        ident[parameter] = max(float(ident[parameter]), entry["mdb"][parameter])


def twin_response(row: tuple[np.ndarray, np.ndarray], screen=None) -> float:
    """The round's test's response to a twin run's ``(Δs, I)`` (:func:`scores_on_twin`).

    The test's directions (``screen``'s, :meth:`~.screening.ScreenResult.response`: its
    blind ones left out, as the MDB's) weighed by the twin's information, which a twin
    that fits divides by nothing; every direction without ``screen``.
    """
    if screen is None:
        return reliability.score_response(*row)
    return screen.response(row[0], row[1], 1.0)


def secant(entry: dict[str, Any], parameter: str, step: float, lam_step: float) -> None:
    """The weaker sign's MDB from its responses at 1x and ``step`` x the first-order MDB.

    The tilt's response grows faster than quadratic (clean psce s23: 0.35, 0.54, 0.84,
    1.32, 2.06 λ₀ at 1, 1.25, 1.5, 1.75, 2x), so :func:`both_signs`'s step errs large
    (1.69x, seen with ~1.2 λ₀).  A secant in log λ against log size through the two
    responses gives the size where λ₀ is reached: ``c = step · (λ₀ / λ_step)^(1/p)``,
    ``p = ln(λ_step / λ_w) / ln(step)``.  Kept at ``step`` where the response did not grow
    (``p ≤ 0``).  ``probe[parameter]``: ``step`` and ``lam_step``.
    """
    probe = entry["probe"][parameter]
    probe.update(step=step, lam_step=lam_step)
    beyond = secant_beyond(probe, float(entry["lam0"]), step, lam_step)
    if beyond is not None:
        restate(entry, parameter, entry["mdb_test"][parameter] * step * beyond)


def secant_beyond(probe: dict[str, float], lam0: float, step: float, lam_step: float
                  ) -> float | None:
    """Where the weaker sign reaches ``lam0``, in units of ``step`` x the probed size.

    (:func:`secant`.)  ``probe``: ``lam_plus``, ``lam_minus`` (the responses at ± the
    probed size); ``lam_step`` the weaker sign's at ``step`` x it.  ``None`` where the
    response did not grow (the step is then kept).
    """
    worse = min(probe["lam_plus"], probe["lam_minus"])
    if not (lam_step > worse > 0.0 and step > 1.0):
        return None
    power = np.log(lam_step / worse) / np.log(step)
    return float((lam0 / lam_step) ** (1.0 / power))


def fits(screen) -> bool:
    """Whether the round's score test of an effect ran on a model that fits (:data:`FITS`)."""
    return screen is None or float(screen.dispersion) <= FITS


def stated_size(entry: dict[str, Any], parameter: str) -> float:
    """The size of ``parameter`` the printed test MDB is for residuals as stated.

    ``mdb_test`` (the test's, where the excess gate set the printed MDB) or ``mdb``, over
    √``dispersion`` (a round that does not fit states its MDB for its dispersion), at most
    the plausible size: where ``discover --verify`` injects its twins (:func:`~.verify.
    twin_scale`) and where :func:`scores_on_twin` probes the test's MDB at both signs.
    """
    d = float(entry.get("dispersion", 1.0))
    return min(float(entry.get("mdb_test", entry["mdb"])[parameter]) / np.sqrt(d),
               float(entry["plausible_size"].get(parameter, np.inf)))


def twin_signs(entry: dict[str, Any], parameter: str, plus, minus, size: float,
               screen=None) -> tuple[float, float] | None:
    """The test MDB's responses at ± ``size`` on the noise-free twin (:func:`scores_on_twin`).

    ``plus``, ``minus``: ``(Δs, I)`` of the two runs, ``screen`` the round's test of the
    effect (:func:`twin_response`).  ``twin_probe[parameter]`` keeps
    ``size``, ``lam_plus``, ``lam_minus``; where the weaker sign
    responds below λ₀, ``(sign, c₁)`` (:func:`both_signs`' step) for one run more
    (:func:`restate_test`).
    """
    if plus is None or minus is None:
        return None
    lam = {"lam_plus": twin_response(plus, screen), "lam_minus": twin_response(minus, screen)}
    entry.setdefault("twin_probe", {}).setdefault(parameter, {}).update(size=float(size), **lam)
    lam0, worse = float(entry["lam0"]), min(lam.values())
    if not 0.0 < worse < lam0:
        return None
    return (1.0 if lam["lam_plus"] <= lam["lam_minus"] else -1.0), float(np.sqrt(lam0 / worse))


def restate_test(entry: dict[str, Any], parameter: str, step: float, lam_step: float) -> None:
    """The test MDB of ``parameter`` at its weaker sign, from the twin's runs (:func:`secant`).

    The printed test MDB grows by the secant's factor (``step`` where the response did not
    grow); the first order's is kept (``mdb_first_order``).  Where the excess gate set the
    printed MDB (``mdb_set_by`` "explained_gate") that is ``mdb_test`` and the printed MDB
    is at least it; else the printed MDB, ``mdb_set_by`` "probe" and ``mdb_test`` the
    first order, as :func:`both_signs` states it.
    """
    probe = entry["twin_probe"][parameter]
    probe.update(step=step, lam_step=lam_step)
    beyond = secant_beyond(probe, float(entry["lam0"]), step, lam_step)
    key = "mdb_test" if entry.get("mdb_set_by") == "explained_gate" else "mdb"
    first = float(entry[key][parameter])
    entry.setdefault("mdb_first_order", {})[parameter] = first
    if key == "mdb":
        entry.setdefault("mdb_test", dict(entry["mdb"]))
        entry["mdb_set_by"] = "probe"
    entry[key][parameter] = first * step * (1.0 if beyond is None else beyond)
    restate(entry, parameter, max(float(entry["mdb"][parameter]), entry[key][parameter]))


def _started(runs, args: tuple, probes: tuple, per: int, fn: Callable | None = None
             ) -> list[Callable[[], list]]:
    """``probes`` (in groups of ``per``) of ``fn`` (default :func:`measure_on_bag`) started.

    By ``runs.later``, one part a worker.
    """
    # one call renders the bag's twin once for all its probes; on several workers the
    # groups are split over them, each part rendering the twin itself (the same
    # noise-free numbers), so the probe's runs are not one worker's serial tail
    groups = len(probes) // per
    parts = max(1, min(runs.workers, groups))
    bounds = [per * (groups * i // parts) for i in range(parts + 1)]
    return [runs.later(fn or measure_on_bag, *args, probes[a:b])
            for a, b in zip(bounds[:-1], bounds[1:], strict=True)]


def flagged(entry: dict[str, Any]) -> list[str]:
    """The effect's parameters whose printed rows the first order does not hold."""
    return list(dict.fromkeys(entry["bias_parameter"][q] for q in entry.get("remainders", [])))


def gated(entry: dict[str, Any]) -> list[str]:
    """The parameters of a testable entry whose printed MDB is the excess gate's.

    ``mdb_set_by`` "explained_gate" (:func:`~.reliability.detectability`): the size at which
    the sign the misfit works against passes the decision's excess gate, from the effect's
    whitened energy taken as quadratic in the size (:func:`gate_secant` measures it).
    """
    if entry.get("mdb_set_by") != "explained_gate" or not entry.get("testable"):
        return []
    test, lean = entry.get("mdb_test", {}), entry.get("mdb_leaning", {})
    return [p for p, v in entry["mdb"].items()
            if np.isfinite(v) and v > test.get(p, np.inf) and np.isfinite(lean.get(p, np.nan))]


def gate_secant(entry: dict[str, Any], parameter: str, energy: float) -> float | None:
    """The gate MDB of ``parameter`` restated from the energy a run at its size measured.

    The printed size ``h`` (the sign the misfit works against) and the leaning sign's ``l``
    solve ``I b² ∓ 2 s b = q`` (:func:`~.reliability.detectability`; ``q`` =
    ``lam_gate`` x ``dispersion``): in units of ``I``, ``b² − (h − l) b = h l``.  At the
    hard sign the energy is the small difference of the two terms, so a few % of curvature
    the first order misses (the reference gates its worst stars as ``b`` grows: 0.93x the
    information's at ±2.86e-3 on ``dt_step`` s23) move it by tens of %: there the
    candidate removed 7.7 % (5.5-9.1 % on seeds 101-110) where the gate needs 10 %.
    ``energy``: the whitened energy the effect at ``−sign(l)`` x the size added to the
    current model's residuals on the user's bag (a probe run: ``(E₁ − E₀) · 2 · stars /
    noise``).  First call (the run at ``h``): the curvature is taken from it with the
    linear term kept (``κ b² − (h − l) b``, the misfit's overlap is first order),
    ``κ = (ρ l + h − l) / h`` with ``ρ = energy / q``, and the size where that reaches
    ``q`` is returned for one run more (``None``: ``h`` kept where ``ρ ≥ 1``, the gate
    passing there with at least the test's power, or where no curvature is positive).
    Second call (the run at that size): the MDB is the secant through the two measured
    energies at ``q`` (the curvature still falls between them: one step landed at 9.6 %
    on seed 101).  At least the test's ``mdb_test``.  ``gate_probe[parameter]``: ``size``,
    ``energy_ratio`` (``ρ``) and ``step``, ``step_energy_ratio``.
    """
    q = float(entry.get("lam_gate", 0.0)) * float(entry.get("dispersion", 1.0))
    if not q > 0.0:
        return None
    rho = float(energy) / q
    probe = entry.setdefault("gate_probe", {})
    if parameter in probe:  # the second run: the secant through the two
        first = probe[parameter]
        h, b1, rho1 = first["size"], abs(entry["mdb"][parameter]), first["energy_ratio"]
        first.update(step=b1, step_energy_ratio=rho)
        if rho > rho1 and b1 != h:
            root = b1 + (1.0 - rho) * (b1 - h) / (rho - rho1)
            restate(entry, parameter, max(root, entry["mdb_test"][parameter]))
        return None
    h = float(entry["mdb"][parameter])
    lean = abs(float(entry["mdb_leaning"][parameter]))
    probe[parameter] = {"size": h, "energy_ratio": rho}
    kappa = (rho * lean + h - lean) / h
    # at least the stated energy at h: the gate passes there with the test's power (the
    # printed size holds, perhaps conservative: not lowered, no run more)
    if not (kappa > 0.0 and rho < 1.0):
        return None
    root = ((h - lean) + np.sqrt((h - lean) ** 2 + 4.0 * kappa * h * lean)) / (2.0 * kappa)
    restate(entry, parameter, max(root, entry["mdb_test"][parameter]))
    return entry["mdb"][parameter] if entry["mdb"][parameter] != h else None


def _at_hard_sign(entry: dict[str, Any], parameter: str) -> tuple[str, tuple[float, ...]]:
    """A probe of ``parameter`` at its MDB, at the sign the misfit works against."""
    size = -np.sign(entry["mdb_leaning"][parameter]) * entry["mdb"][parameter]
    return entry["effect"], tuple(injection.parameter_delta(entry["effect"], parameter,
                                                            size).tolist())


def _agrees(first: float, measured: float) -> bool:
    return abs(measured - first) <= AGREE * abs(first)


def apply(entry: dict[str, Any], parameter: str, plus: dict[str, float],
          minus: dict[str, float], sigma: dict[str, float]) -> None:
    """Put a probe's measured shifts at ``+size`` and ``−size`` into ``entry``.

    Each row whose printed bias comes from ``parameter`` keeps its first-order value where
    the probe agrees within :data:`AGREE` at both signs; else it takes the measured shifts:
    ``biases_signed[q]`` the shift at +size, ``biases_minus[q]`` the one at −size (the
    effect's second order can make them differ: the tilt moves radial_k1k2.k2 by 0.56 σ at
    +MDB and 1.47 σ at −MDB), ``biases[q]`` the larger magnitude.  The rows are listed
    again against σ (``sigma``: every quantity's σ in the current model) and none of
    ``parameter``'s is a remainder any more.  ``entry["probe"][parameter]``: the size, per
    replaced row its first-order value (``first_order``), and the rows the first order
    listed that the measurement does not (``unlisted``: below their σ at both signs).
    """
    first = {}
    was = set(entry.get("dominates", [])) | set(entry.get("remainders", []))
    minus_rows = entry.setdefault("biases_minus", {})
    for q, src in entry["bias_parameter"].items():
        if src != parameter or q not in plus or q not in minus:
            continue
        f, mp, mm = entry["biases_signed"][q], float(plus[q]), float(minus[q])
        if _agrees(f, mp) and _agrees(-f, mm):
            continue
        first[q] = f
        entry["biases_signed"][q], minus_rows[q] = mp, mm
        entry["biases"][q] = max(abs(mp), abs(mm))
        entry["biases_shown"][q] = reliability.shown(q, entry["biases"][q])
    entry["remainders"] = [q for q in entry.get("remainders", [])
                           if entry["bias_parameter"][q] != parameter]
    listed = [q for q, b in entry["biases"].items()
              if sigma.get(q, 0.0) > 0 and b > reliability.DOMINATES_SIGMA * sigma[q]]
    entry["dominates"] = [q for q in listed if q not in entry["remainders"]]
    entry.setdefault("probe", {})[parameter] = {
        "size": entry["hidden_size"][parameter], "first_order": first,
        "unlisted": [q for q in first if q in was and q not in listed]}
    for q in listed:
        entry["sigma"][q] = sigma[q]
        entry["sigma_shown"][q] = reliability.shown(q, sigma[q])


def probe_entries(entries: list[dict[str, Any]], base, runs, screens=None) -> int:
    """Measure the flagged rows of ``entries`` by probe runs; the number of runs made.

    ``base``: the current model's run on ``runs``' bag (with its noise and window), whose
    start (``base.prior``) and effects the probe runs repeat; its calibration renders the
    injections.  Two runs per flagged (effect, parameter), the effect at +size and −size,
    all in one call where the bag is.  ``screens``: the round's score tests
    (``{effect: ScreenResult}``); with them each probe run also scores its effect and the
    MDB is restated where one sign responds below λ₀ (:func:`both_signs`).
    """
    return start_probes(entries, base, runs, screens)()


def start_probes(entries: list[dict[str, Any]], base, runs, screens=None
                 ) -> Callable[[], int]:
    """:func:`probe_entries` as a function to call for it (``entries`` are then filled in).

    On a cluster the probe's runs start now (:meth:`~stellar_cal_ros.diagnosis.parallel.
    Runs.later`), beside what the parent does before it calls (the line tests: the probe
    needs the candidates only, not the lines); in this process they run when called.
    """
    if base is None or not base.ok or base.calibration is None or base.prior is None:
        return lambda: 0
    todo = [(entry, parameter) for entry in entries for parameter in flagged(entry)]
    gates = [(entry, parameter) for entry in entries for parameter in gated(entry)]
    if not todo and not gates:
        return lambda: 0
    screens = screens or {}
    # the test's MDB at both signs on the noise-free twin: a gate-set row's (the twin has no
    # gate: discover --verify checks the test's), and a flagged row's where the model does
    # not fit the bag (its response on the bag is not the twins')
    on_twin = list({(id(entry), parameter): (entry, parameter)
                    for entry, parameter in gates + [
                        (e, q) for e, q in todo if not fits(screens.get(e["effect"]))]
                    if screens.get(entry["effect"]) is not None
                    and runs.spec.screen is not None}.values())
    sizes = [stated_size(entry, parameter) for entry, parameter in on_twin]
    twin_probes = tuple((entry["effect"], tuple(injection.parameter_delta(
        entry["effect"], parameter, sign * size).tolist()))
        for (entry, parameter), size in zip(on_twin, sizes, strict=True)
        for sign in (1.0, -1.0))
    probes = tuple((entry["effect"], tuple(injection.parameter_delta(
        entry["effect"], parameter, sign * entry["hidden_size"][parameter]).tolist()))
        for entry, parameter in todo for sign in (1.0, -1.0))
    # one run per gate-set MDB: the effect at it, at the sign the misfit works against
    hard = tuple(_at_hard_sign(entry, parameter) for entry, parameter in gates)
    args = (runs.spec, base.prior, tuple(base.effects), runs.fraction, runs.noise,
            runs.classes, base.calibration)
    pending = _started(runs, args, probes, 2) if probes else []
    pending_gates = _started(runs, args, hard, 1) if hard else []
    limits = tuple(LINEAR ** 2 * float(entry["lam0"]) for entry, _ in on_twin)
    pending_twin = runs.later(scores_on_twin, *args, twin_probes, limits,
                              float(base.window["noise_variance"])) if on_twin else None

    def done() -> int:
        w = base.window

        def energy(row) -> float | None:  # the whitened energy the probe's effect added
            if row is None or not w["noise_variance"] > 0:
                return None
            return excess_energy(row[EXCESS] - w["excess_variance"], w["noise_variance"],
                                 w["n_window"])

        # the gate-set MDBs: one step from the run at the printed size, then a secant
        regate = []
        for (entry, parameter), row in zip(gates, [row for part in pending_gates
                                                   for row in part()], strict=True):
            e = energy(row)
            if e is not None and gate_secant(entry, parameter, e) is not None:
                regate.append((entry, parameter))
        got = [row for part in pending for row in part()]
        before, sigma = injection.summary_values(base), base.sigma_by_name()
        steps = []
        for k, (entry, parameter) in enumerate(todo):
            plus, minus = got[2 * k], got[2 * k + 1]
            if plus is not None and minus is not None:
                s_plus, s_minus = plus.pop(SCORE, None), minus.pop(SCORE, None)
                apply(entry, parameter, injection.paired_shift(before, plus),
                      injection.paired_shift(before, minus), sigma)
                screen = screens.get(entry["effect"])
                if not fits(screen):  # measured on the twin (below)
                    continue
                step = both_signs(entry, parameter, score_step(s_plus, screen),
                                  score_step(s_minus, screen), screen)
                if step is not None:
                    steps.append((entry, parameter, screen, *step))
        got_twin = pending_twin() if pending_twin is not None else []
        twin_steps = []
        made = len(probes) + len(hard)
        for (entry, parameter), size, got in zip(on_twin, sizes, got_twin, strict=True):
            entry.setdefault("twin_probe", {})[parameter] = {"size": float(size),
                                                             "even_energy": got["even"]}
            if "plus" not in got:  # odd in the size: either sign responds alike
                continue
            made += 2
            step = twin_signs(entry, parameter, got["plus"], got["minus"], size,
                              screens.get(entry["effect"]))
            if step is not None:
                twin_steps.append((entry, parameter, size, *step))
        if twin_steps:  # one run more each on the twin: the weaker sign at the one step
            again_twin = tuple((entry["effect"], tuple(injection.parameter_delta(
                entry["effect"], parameter, sign * factor * size).tolist()))
                for entry, parameter, size, sign, factor in twin_steps)
            rows = [row for part in _started(runs, args, again_twin, 1, scores_on_twin)
                    for row in part()]
            for (entry, parameter, _, _, factor), row in zip(twin_steps, rows, strict=True):
                restate_test(entry, parameter, factor,
                             twin_response(row, screens.get(entry["effect"]))
                             if row is not None else 0.0)
            made += len(again_twin)
        if not steps and not regate:
            return made
        # one run more per restated MDB: the weaker sign at the one step's size (a secant)
        again = tuple((entry["effect"], tuple(injection.parameter_delta(
            entry["effect"], parameter, sign * factor * entry["mdb_test"][parameter]).tolist()))
            for entry, parameter, _, sign, factor in steps) + tuple(
            _at_hard_sign(entry, parameter) for entry, parameter in regate)
        rows = [row for part in _started(runs, args, again, 1) for row in part()]
        for (entry, parameter, screen, _, factor), row in zip(steps, rows[:len(steps)],
                                                             strict=True):
            d = score_step(None if row is None else row.get(SCORE), screen)
            if d is not None:
                secant(entry, parameter, factor, screen.response(d))
        for (entry, parameter), row in zip(regate, rows[len(steps):], strict=True):
            e = energy(row)
            if e is not None:
                gate_secant(entry, parameter, e)
        return made + len(again)

    return done
