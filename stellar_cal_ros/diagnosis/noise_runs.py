"""Noise as a hypothesis, measured over re-runs (:mod:`~stellar_cal_ros.diagnosis.noise`).

:func:`measure` runs the maximum-likelihood searches of the IMU noise scales over the
runner's re-runs (the stars' scale needs none); :mod:`~stellar_cal_ros.diagnosis.noise`
holds the estimators and the verdict, below the runner (its runs measure the stars).
"""

from __future__ import annotations

import math

from stellar_cal_ros.core.noise import NoiseScales
from stellar_cal_ros.diagnosis.noise import (
    ALPHA,
    MATERIAL,
    NoiseVerdict,
    default_sigma,
    far_off,
    judge_stars,
    p_two_sided,
    structured,
)
from stellar_cal_ros.diagnosis.noise_imu import first_points, imu_sample_scale, search_scale
from stellar_cal_ros.diagnosis.parallel import Task


def measure(runs, prior, effects: tuple[str, ...], base, tell=None,
            components: tuple[str, ...] = ("gyro",)) -> NoiseVerdict:
    """Measure the noise scales on ``runs``' bag for the model ``effects`` from ``prior``.

    ``base`` is a run of that model with the scales ``runs.noise`` and its stars' noise
    measured (``Task(star_noise=True)``).  First the IMU's own samples (no run: their
    sample-to-sample noise, :func:`~.noise_imu.imu_sample_scale`, which no missing effect
    moves); then the stars (no further run); then each IMU component in ``components`` by
    ML over re-runs with the stars' scale applied.  Where the samples look white they
    measure the sensor's noise and the ML is their check: attitude (velocity) motion the
    stars see beyond the samples' noise is a motion of the tracker against the IMU (or a
    wandering bias), not sensor noise, and is said as such, not applied.  Returns the
    verdict; ``verdict.applied`` is what the diagnosis should run with.
    """
    stated = runs.noise or NoiseScales()
    v = NoiseVerdict(stated, stated, method=runs.spec.name)
    n_tests = 1 + len(components)
    cam = prior.camera
    sn = base.star_noise
    applied = _from_samples(v, runs, components, n_tests)
    v.skipped = far_off(base, sn)
    if v.skipped:
        if tell:
            tell(f"noise: {v.skipped}")
        v.applied = applied
        return v
    if sn is not None:
        applied = judge_stars(v, sn, default_sigma(runs.spec.name), (cam.width, cam.height),
                              n_tests, applied)
        v.imu_skipped = structured(sn) if components else ""
        if v.imu_skipped:
            components = ()  # said once, in the verdict's lines
    for comp in components:
        cur = getattr(applied, comp)

        def loglik(xs: list[float], comp=comp, at=applied) -> list:
            tasks = [scale_task(comp, x, prior, effects, at) for x in xs]
            out = runs.run_all(tasks, None)
            return [(out[t.key].window["log_likelihood"], out[t.key].frame_loglik)
                    if out[t.key].ok else -math.inf for t in tasks]

        known = {0.0: base.window["log_likelihood"]} if applied == stated and base.ok else {}
        found = search_scale(comp, loglik, known=known)
        v.imu[comp] = found
        if tell:
            tell(f"noise: {comp} scale {found.value:.3g} +- {found.sigma:.2g} "
                 f"({len(found.points)} runs)" if found.measurable else
                 f"noise: {comp} scale at {'most' if found.bound == 'upper' else 'least'} "
                 f"{found.value:.3g} ({len(found.points)} runs)" if found.bound else
                 f"noise: {comp} scale not measurable on this bag")
        significant = (found.measurable or found.bound) and found.p_value < ALPHA / n_tests \
            and abs(found.value - 1.0) > MATERIAL
        if comp in v.samples and v.samples[comp]["white"]:
            # the samples measured the sensor; the stars asking for more is motion, not noise
            if significant and found.measurable and found.value > 1.0 + BEYOND:
                v.beyond.append(comp)
            continue
        if significant:
            v.rejected.append(comp)
            applied = applied.replace(**{comp: cur * found.value})
    v.applied = applied
    return v


#: the stars' ML scale over the samples' above which the excess is motion, not noise
BEYOND = 0.5
#: the search's runs go before runs queued ahead of need (a round's candidates beside its
#: base run, :func:`~stellar_cal_ros.diagnosis.discover.measure_round_noise`): the search
#: waits for them, and the candidates' runs wait for the verdict
SEARCH_COST = 10.0


def scale_task(comp: str, x: float, prior, effects: tuple[str, ...], at: NoiseScales) -> Task:
    """The run of the ML search of ``comp`` at ln scale ``x`` around the scales ``at``.

    Without the gyro-against-stars check: the search reads the run's log-likelihood alone
    (the check changes no estimate), and :func:`measure` runs only after the current
    model's run on the bag, which judged the gyro, succeeded (≈ 1 CPU-s a run on a 2-h bag).
    With the log-likelihood frame by frame (the search's sandwich σ).
    """
    return Task(f"noise {comp} x{math.exp(x):.3g}", prior, tuple(effects),
                noise=at.replace(**{comp: getattr(at, comp) * math.exp(x)}),
                cost=SEARCH_COST, gyro_check=False, frame_loglik=True)


def first_runs(runs, prior, effects: tuple[str, ...],
               components: tuple[str, ...] = ("gyro",)) -> list[Task]:
    """The runs :func:`measure` starts its first ML search with, if the stars keep the scales.

    Known before the base run (the usual case): run beside it on an idle worker
    (:meth:`~stellar_cal_ros.diagnosis.parallel.Runs.run_ahead`); any other case simply
    does not use them.
    """
    if not components:
        return []
    stated = runs.noise or NoiseScales()
    v = NoiseVerdict(stated, stated, method=runs.spec.name)
    at = _from_samples(v, runs, components, 1 + len(components))
    # ln s = 0 is the base run itself when the samples keep the stated scales
    return [scale_task(components[0], x, prior, effects, at) for x in first_points()
            if x != 0.0 or at != stated]


def start_samples(runs, components: tuple[str, ...] = ("gyro",)) -> None:
    """Start the IMU samples' scales (:func:`_from_samples`) on a free worker, if any.

    So that :func:`first_runs` and :func:`measure` find them computed beside the base run
    instead of waiting for them (:meth:`~stellar_cal_ros.diagnosis.parallel.Runs.on_bag_soon`).
    """
    stated = runs.noise or NoiseScales()
    for comp in components:
        runs.on_bag_soon(imu_sample_scale, runs.spec.name, comp, stated)


def _from_samples(v: NoiseVerdict, runs, components: tuple[str, ...], n_tests: int
                  ) -> NoiseScales:
    """The IMU components' scales from their own samples (where they look white)."""
    applied = v.stated
    for comp in components:  # computed where the bag is: the parent does not read it
        s, e, white, axes = runs.on_bag(imu_sample_scale, runs.spec.name, comp, v.stated)
        if not math.isfinite(s):
            continue
        v.samples[comp] = {"scale": float(s), "sigma": float(e), "white": bool(white)}
        if axes:  # one axis unlike the others: said per axis, the scale is their RMS
            v.samples[comp]["axes"] = [float(a) for a in axes]
        if white and p_two_sided(s, e) < ALPHA / n_tests and abs(s - 1.0) > MATERIAL:
            v.rejected.append(comp)
            applied = applied.replace(**{comp: getattr(v.stated, comp) * s})
    return applied
