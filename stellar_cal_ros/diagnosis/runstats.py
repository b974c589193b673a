"""One calibration run of the diagnosis, reduced to the statistics its decisions need.

A candidate's augmented run produces a filter, a residual table and a state history: on a
2-h bag about 100 MB.  The diagnosis needs only a few numbers from it (the innovation
log-likelihood over the evaluation window, the NIS dispersion, the excess variance, the
RMS, the final θ and its covariance, the counters), so every run is reduced to a
:class:`RunSummary` where it ran — in a worker process — and only that travels back.  The
residual table is kept only when asked for (the reference run whose structure is tested
and plotted).

:func:`evaluate` is the function the workers execute.  It takes the bag as a path (read
once per worker and cached), as the bag's bytes (when the workers do not share the
parent's filesystem) or as an in-memory :class:`~stellar_cal_ros.methods.replay.BagData`,
and calls the estimator only through :attr:`~stellar_cal_ros.diagnosis.discover.
DiagnosisSpec.runner`.  :func:`run_statistics` is
the single place that reads a :class:`~stellar_cal_ros.methods.replay.ReplayResult`.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from stellar_cal_ros.core.memory import trim_freed
from stellar_cal_ros.io.calibration import Calibration
from stellar_cal_ros.methods.replay import BagData, ReplayResult, read_bag_data
from stellar_cal_ros.methods.results import epp_jacobian, keeping_frames

Table = dict[str, np.ndarray]

#: names of the derived quantities whose bias the reliability report shows: the equivalent
#: principal point (u, v), px
EPP_NAMES = ("equivalent_principal_point.u", "equivalent_principal_point.v")


@dataclass
class BagBytes:
    """A bag's file content, for workers that cannot read the parent's path."""

    name: str
    data: bytes
    digest: str

    @classmethod
    def of(cls, path: str | Path) -> BagBytes:
        """Read ``path`` into memory."""
        raw = Path(path).read_bytes()
        return cls(Path(path).name, raw, hashlib.sha1(raw).hexdigest())


BagRef = str | Path | BagBytes | BagData


@dataclass
class RunSummary:
    """What the diagnosis keeps of one run (no filter, no history).

    Its ``window`` is the run's own streaming statistics
    (:class:`~stellar_cal_ros.methods.results.RunStats`, the one class of running
    innovation statistics) summarized over the evaluation window.
    """

    effects: tuple[str, ...]  #: effects beyond the method's baseline
    names: list[str] = field(default_factory=list)  #: θ parameter names
    slices: dict[str, tuple[int, int]] = field(default_factory=dict)
    theta: np.ndarray = field(default_factory=lambda: np.zeros(0))
    P: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))  #: θ covariance
    prior_sigma: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: the evaluation window's statistics (:meth:`stellar_cal_ros.methods.results.RunStats.window`)
    window: dict[str, Any] = field(default_factory=dict)
    calibration: Calibration | None = None
    #: the calibration the run started from (a re-run with a probe starts there too)
    prior: Calibration | None = None
    counters: dict[str, int] = field(default_factory=dict)
    derived: dict[str, Any] = field(default_factory=dict)
    #: gradient of the equivalent principal point (u, v) with respect to θ, (2, n)
    epp_jacobian: np.ndarray | None = None
    seconds: float = 0.0  #: wall time of the run
    residuals: Table | None = None
    #: a screening run's raw score tests, ``{effect: (LM, dof, I, M)}``
    #: (:mod:`~stellar_cal_ros.diagnosis.screening`)
    scores: dict[str, tuple] | None = None
    #: the stars' noise measured on this run (:class:`~stellar_cal_ros.diagnosis.noise.
    #: StarNoise`), when asked for
    star_noise: Any = None
    #: the window's log-likelihood frame by frame, ``(2, frames)`` (frame indices, terms:
    #: :meth:`~stellar_cal_ros.methods.results.RunStats.frame_log_likelihood`), when asked for
    frame_loglik: np.ndarray | None = None
    #: stamps of the frames its consider parameters (a screening run's candidates) were
    #: scored on with a stale input only they need (:attr:`~stellar_cal_ros.methods.driver.
    #: Calibrator.consider_stale_ns`)
    consider_stale_ns: tuple[int, ...] = ()
    error: str = ""

    @property
    def ok(self) -> bool:
        """The run finished."""
        return not self.error

    @property
    def lost_lock(self) -> bool:
        """The filter lost lock in the run (re-initialized, or frames counted lost)."""
        return bool(self.counters.get("reinitializations", 0)
                    or self.counters.get("frames_lost_lock", 0))

    def lock_losses(self) -> dict[str, Any] | None:
        """When and how often the filter lost lock in the run (``None``: it never did).

        ``{"reinitializations", "frames_lost_lock", "episodes"}``: the kernel's counts, and
        the spans ``[first, last, frames]`` (s from the residual table's first row, as the other
        lines' times) of the frames in a row with fewer than ``min_stars`` stars accepted
        (:class:`~stellar_cal_ros.methods.kernel.KernelConfig`: the frames the filter
        skipped; three in a row re-acquire); ``episodes`` is ``None`` without a residual
        table.  (Before, a lost lock was a clause of the noise line and two counts.)
        """
        if not self.lost_lock:
            return None
        from stellar_cal_ros.methods.kernel import KernelConfig

        out: dict[str, Any] = {
            "reinitializations": int(self.counters.get("reinitializations", 0)),
            "frames_lost_lock": int(self.counters.get("frames_lost_lock", 0)),
            "episodes": None}
        res = self.residuals
        if res is None or not len(res.get("t", ())):
            return out
        frame = np.asarray(res["frame"])
        ids, k = np.unique(frame, return_inverse=True)
        k = k.reshape(-1)
        accepted = np.bincount(k, ~np.asarray(res["gated"], dtype=bool), len(ids))
        t = np.bincount(k, np.asarray(res["t"], dtype=float), len(ids)) / np.bincount(
            k, minlength=len(ids))
        t = t - float(np.min(res["t"]))
        # (rejected frames: some star gated, too few accepted; not a frame of few stars)
        lost = np.flatnonzero((accepted < KernelConfig.min_stars) & (
            np.bincount(k, minlength=len(ids)) > accepted))
        # (an episode: lost frames in a row among the frames with rows; a re-acquiring
        # frame writes none)
        eps = []
        for g in np.split(lost, np.flatnonzero(np.diff(lost) > 1) + 1) if len(lost) else []:
            eps.append([float(t[g[0]]), float(t[g[-1]]), len(g)])
        out["episodes"] = eps
        return out

    @property
    def sigma(self) -> np.ndarray:
        """Posterior σ of θ."""
        return np.sqrt(np.clip(np.diag(self.P), 0.0, None))

    def block(self, effect_id: str) -> slice:
        """θ slice of ``effect_id``."""
        a, b = self.slices[effect_id]
        return slice(a, b)

    def sigma_by_name(self) -> dict[str, float]:
        """σ of every θ parameter and of the derived quantities, by name."""
        out = dict(zip(self.names, self.sigma.tolist(), strict=True))
        s = self.derived.get("equivalent_principal_point_sigma_px")
        if s is not None:
            out.update(zip(EPP_NAMES, map(float, s), strict=True))
        return out

    def value_by_name(self) -> dict[str, float]:
        """Estimate of every θ parameter, by name."""
        return dict(zip(self.names, self.theta.tolist(), strict=True))


def run_statistics(result: ReplayResult, fraction: float,
                   keep_residuals: bool = False) -> RunSummary:
    """Reduce a run to its :class:`RunSummary` (the one place that reads a ReplayResult)."""
    flt = result.filter
    model = flt.model
    n = flt.P_est  # the estimated θ (a screening run's consider entries follow it)
    theta = np.array(flt.theta, dtype=float)
    P = np.array(flt.P[flt.it, flt.it], dtype=float)
    derived = {k: v for k, v in (result.derived or {}).items()
               if isinstance(v, (int, float, list, tuple)) and not isinstance(v, bool)}
    try:
        J = epp_jacobian(model, theta, n)[1]
    except Exception:  # a model without a camera chain: no derived bias
        J = None
    return RunSummary(
        effects=(),
        names=model.parameter_names()[:n],
        slices={k: (s.start, s.stop) for k, s in model.slices.items() if s.stop <= n},
        theta=theta[:n],
        P=0.5 * (P + P.T),
        prior_sigma=np.array(model.initial_sigma[:n], dtype=float),
        # the run's own streaming statistics over its evaluation window (every run alike,
        # whether or not it kept its residual table)
        window=result.stats.window(fraction),
        calibration=result.calibration,
        counters=dict(result.counters),
        consider_stale_ns=tuple(getattr(result, "consider_stale_ns", ())),
        derived=derived,
        epp_jacobian=J,
        residuals=result.residuals if keep_residuals else None,
    )


# ----------------------------------------------------------------------------- worker side
_BAG_CACHE: dict[tuple, BagData] = {}


def load_bag(ref: BagRef) -> BagData:
    """The bag's data: in memory already, or read (once per process) from a path or bytes."""
    if isinstance(ref, BagData):
        return ref
    if isinstance(ref, BagBytes):
        key: tuple = ("bytes", ref.digest)
    else:
        st = os.stat(ref)
        key = ("path", str(ref), st.st_size, st.st_mtime_ns)
    if key not in _BAG_CACHE:
        _BAG_CACHE.clear()  # one bag per worker at a time
        if isinstance(ref, BagBytes):
            with tempfile.TemporaryDirectory() as tmp:
                path = Path(tmp) / ref.name
                path.write_bytes(ref.data)
                _BAG_CACHE[key] = read_bag_data(path, require_imu=False)
        else:
            _BAG_CACHE[key] = read_bag_data(ref, require_imu=False)
        trim_freed()  # the reader's freed blocks (≈ 45 MB of a 2-h bag's heap)
    return _BAG_CACHE[key]


def forget_held_prepared() -> None:
    """:func:`forget_prepared` on every bag this process holds (none is read), then a trim."""
    for data in _BAG_CACHE.values():
        forget_prepared(data)
    trim_freed()


def forget_prepared(data: BagData) -> None:
    """Drop the direction effects' tables the runs on ``data`` shared.

    (:attr:`~stellar_cal_ros.methods.frames.BagData.prepared`, ≈ 13 MB an effect on a 2-h
    bag.)  A later run that needs them makes them again: the same numbers.
    """
    if hasattr(data, "prepared"):
        data.prepared.clear()


def forget_bags() -> None:
    """Drop the bags :func:`load_bag` holds (this process hands its runs to workers now)."""
    _BAG_CACHE.clear()


def register_effect_classes(classes: tuple[type, ...]) -> None:
    """Register user effect classes a fresh worker process does not know yet."""
    from stellar_cal_ros.effects import registry

    for cls in classes:
        if cls.id not in registry.EFFECTS:
            registry.register(cls)


@contextlib.contextmanager
def quiet(name: str = "stellar_cal_ros.methods", level: int = logging.ERROR):
    """Raise a logger's level for a while.

    A candidate run's filter warnings (missing effect, frames rejected) are expected, and
    the diagnosis reports what matters.
    """
    logger = logging.getLogger(name)
    old = logger.level
    logger.setLevel(max(level, old))
    try:
        yield
    finally:
        logger.setLevel(old)


def evaluate(bag: BagRef, spec, prior: Calibration, effects: tuple[str, ...],
             fraction: float, keep_residuals: bool = False,
             effect_classes: tuple[type, ...] = (),
             screen: tuple[str, ...] = (), candidate: bool = False, noise=None,
             star_noise: bool = False, gyro_check: bool = True,
             frame_loglik: bool = False) -> RunSummary:
    """Run ``spec.runner`` on the bag and return the run's statistics (worker entry point).

    A failing run returns a :class:`RunSummary` with ``error`` set (the diagnosis reports it
    and goes on); with ``keep_residuals`` the residual table is returned too, with the
    gravity direction in the tracker frame added (:mod:`~stellar_cal_ros.diagnosis.context`).
    ``screen``: candidates scored by this run (a screening run: they are *consider*
    parameters, which leave the filter's estimate unchanged; ``spec.screen`` turns the
    run into their raw score tests, kept in :attr:`RunSummary.scores`).  ``candidate``: an
    augmented run, whose data faults the runner flags instead of raising.  ``noise``: the
    noise scales the run uses; ``star_noise``: measure the stars' noise on its residuals
    here, where the bag is (:func:`~stellar_cal_ros.diagnosis.noise.measure_stars`).
    ``gyro_check=False``: the gyro-against-stars check does not run (``gyro_fault="off"``:
    it changes no estimate, only the counters and flags; for re-runs of a bag whose gyro
    the diagnosis's current-model run has judged, whose counters nobody reads).
    ``frame_loglik``: keep the window's log-likelihood frame by frame
    (:attr:`RunSummary.frame_loglik`, :func:`~stellar_cal_ros.methods.results.keeping_frames`).
    """
    t0 = time.perf_counter()
    try:
        register_effect_classes(effect_classes)
        data = load_bag(bag)
        kw: dict = {"consider": list(screen)} if screen else {}
        if noise is not None:
            kw["noise"] = noise
        if candidate:
            # the gyro-against-stars check judges the data: the current model's run raises
            # on a fault; a candidate's run only flags it, since the compensated gyro it
            # checks carries that candidate's gyro-error estimates, which diverge when the
            # candidate is wrong
            kw["gyro_fault"] = "flag"
        if not gyro_check:
            kw["gyro_fault"] = "off"
        with quiet(), keeping_frames() if frame_loglik else contextlib.nullcontext():
            result = spec.runner(data, prior, list(effects),
                                 keep_tables=keep_residuals or star_noise,
                                 eval_fraction=fraction, **kw)
        # the kernels it loaded keep their code, not their LLVM modules (only where the run
        # loaded them: importing frame_step here would load numba for a batch method too)
        fs = sys.modules.get("stellar_cal_ros.methods.frame_step")
        if fs is not None:
            fs.release_linking_ir()
        out = run_statistics(result, fraction, keep_residuals)
        if star_noise:
            from stellar_cal_ros.diagnosis.noise import measure_stars

            out.star_noise = measure_stars(result, data, spec.name, fraction, noise, out)
        if frame_loglik:
            out.frame_loglik = result.stats.frame_log_likelihood()
        if screen:
            out.scores = spec.screen(result, list(screen))
        if keep_residuals:
            from stellar_cal_ros.diagnosis.context import add_gravity_regressors

            out.residuals = add_gravity_regressors(result.residuals, data, result.calibration)
    except Exception as exc:  # a candidate failing must not stop the diagnosis
        out = RunSummary(effects=tuple(effects), error=f"{type(exc).__name__}: {exc}")
    out.effects = tuple(effects)
    out.prior = prior
    out.seconds = time.perf_counter() - t0
    return out


def bag_facts(bag: BagRef) -> dict[str, Any]:
    """What the parent needs to know about a bag without holding it (applicability)."""
    data = load_bag(bag)
    return {"site": data.site is not None,
            "head_temperature": data.head_temperature is not None,
            "frames": len(data.frames),
            "duration": float(data.imu_t[-1] - data.imu_t[0]) if len(data.imu_t) else 0.0}
