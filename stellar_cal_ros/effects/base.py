"""The effect interface: how one physical effect enters the measurement and process models.

An effect owns a few parameters (``parameter_names``) and acts at exactly one *stage* of the
chain that turns a catalogue star into a predicted centroid, or a gyro reading into a body
rate::

    GYRO       ω = (I + E)⁻¹ (ω_meas − b)        effects add to b and E
    DIRECTION  u_i → u_i'                       apparent place (aberration, refraction, …)
    TIME       t_exposure = stamp + Δt           effects add to Δt
    TRACKER    R_imu_st = R_prior · Exp(Σ δ)     effects add small rotations δ (tracker axes)
    CAMERA     p (18 OpenCV parameters) → p'     effects set or scale camera parameters

For each stage the effect implements a value function and its Jacobian (analytic; the test
suite checks every one against finite differences).  The estimators compose the stages, so
adding an effect to a filter needs no change to the filter: write a subclass, give it an
``id``, and register it (see :mod:`stellar_cal_ros.effects.registry`).

Parameters are plain vectors.  Their meaning, units, prior sigma and the process noise of
a random-walk model are declared on the class; ``initial`` reads the starting value from a
prior :class:`~stellar_cal_ros.io.calibration.Calibration` and ``store`` writes an estimate
back into one.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from stellar_cal_ros.core.earth import Site


class Stage(enum.Enum):
    """Where in the model chain an effect acts."""

    GYRO = "gyro"
    ACCEL = "accel"
    DIRECTION = "direction"
    TIME = "time"
    TRACKER = "tracker"
    CAMERA = "camera"


@dataclass
class FrameContext:
    """What an effect may use to model one star frame (all optional but ``stamp``)."""

    stamp: float  # POSIX s, the reported mid-exposure time
    catalog_id: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    magnitude: np.ndarray = field(default_factory=lambda: np.zeros(0))
    site: Site | None = None
    head_temperature_c: float = float("nan")
    air_temperature_c: float = float("nan")
    pressure_pa: float = float("nan")
    omega_b: np.ndarray = field(default_factory=lambda: np.zeros(3))  # rad/s at exposure
    R_i_b: np.ndarray = field(default_factory=lambda: np.eye(3))
    R_i_st: np.ndarray = field(default_factory=lambda: np.eye(3))
    gravity_st: np.ndarray = field(default_factory=lambda: np.zeros(3))  # unit, tracker frame
    extra: dict[str, Any] = field(default_factory=dict)


class Effect:
    """Base class of a physical effect (see the module docstring)."""

    id: ClassVar[str] = ""
    stage: ClassVar[Stage]
    parameter_names: ClassVar[tuple[str, ...]] = ()
    units: ClassVar[tuple[str, ...]] = ()
    default_sigma: ClassVar[tuple[float, ...]] = ()
    #: random-walk density of each parameter, unit/√s (0: a constant)
    process_noise: ClassVar[tuple[float, ...]] = ()
    #: context the effect needs ("site", "head_temperature", "weather", "rate", "gravity")
    requires: ClassVar[tuple[str, ...]] = ()
    #: one paragraph for the user: cause, typical size, residual signature
    explanation: ClassVar[str] = ""
    #: ``stellar-cal simulate --effect ID=V[,V...]``: units of the values (default: the
    #: parameter units), the factor of each to the parameter units, and whether the values
    #: are offsets from the nominal (prior) value rather than the value itself
    simulation_units: ClassVar[tuple[str, ...] | None] = None
    simulation_scale: ClassVar[tuple[float, ...] | None] = None
    simulation_relative: ClassVar[bool] = False

    @property
    def size(self) -> int:
        """Number of parameters."""
        return len(self.parameter_names)

    # ------------------------------------------------------------------ prior and result
    def initial(self, prior: Any) -> tuple[np.ndarray, np.ndarray]:
        """Starting value and 1-sigma from a prior calibration.

        Default: the inverse of the default :meth:`store`, i.e. ``prior.effects[id]`` and
        ``prior.sigma["effects"][id]`` where the prior has them, else zero and the default σ.
        """
        block = _mapping_or_empty((getattr(prior, "effects", None) or {}).get(self.id))
        sig = _mapping_or_empty(
            _mapping_or_empty((getattr(prior, "sigma", None) or {}).get("effects")).get(self.id))
        value = np.array([_number_or(block.get(n), 0.0) for n in self.parameter_names])
        sigma = np.array([
            s if (s := _number_or(sig.get(n), 0.0)) > 0 else float(d)
            for n, d in zip(self.parameter_names, self.default_sigma, strict=True)
        ])
        return value, sigma

    def store(self, value: np.ndarray, sigma: np.ndarray, cal: Any) -> None:
        """Write an estimate into a calibration (default: under ``effects[id]``)."""
        cal.effects[self.id] = {n: float(v) for n, v in zip(self.parameter_names, value,
                                                             strict=True)}
        cal.sigma.setdefault("effects", {})[self.id] = {
            n: float(s) for n, s in zip(self.parameter_names, sigma, strict=True)
        }

    def from_simulation(self, values: np.ndarray, nominal: Any) -> np.ndarray:
        """Parameter value of a ``simulate --effect`` value (see ``simulation_*``).

        The simulator renders the truth through the effect classes themselves, so a new
        effect file is simulated, estimated and diagnosed with no other file edited.
        """
        v = np.asarray(values, dtype=float).reshape(-1)
        if self.simulation_scale is not None:
            v = v * np.asarray(self.simulation_scale, dtype=float)
        if self.simulation_relative:
            v = v + self.initial(nominal)[0]
        return v

    def process_noise_density(self) -> np.ndarray:
        """Random-walk density per parameter (unit/√s)."""
        if not self.process_noise:
            return np.zeros(self.size)
        return np.asarray(self.process_noise, dtype=float)

    # ------------------------------------------------------------------ GYRO / ACCEL stage
    def sensor_bias(self, value: np.ndarray) -> np.ndarray:
        """Contribution to the sensor bias b (3,)."""
        return np.zeros(3)

    def sensor_bias_jacobian(self, value: np.ndarray) -> np.ndarray:
        """∂b/∂value (3, k)."""
        return np.zeros((3, self.size))

    def sensor_matrix(self, value: np.ndarray) -> np.ndarray:
        """Contribution to the sensor error matrix E (3, 3)."""
        return np.zeros((3, 3))

    def sensor_matrix_jacobian(self, value: np.ndarray) -> np.ndarray:
        """∂E/∂value (3, 3, k)."""
        return np.zeros((3, 3, self.size))

    # ------------------------------------------------------------------ DIRECTION stage
    def directions(self, value: np.ndarray, u_i: np.ndarray, ctx: FrameContext) -> np.ndarray:
        """Apply the effect to inertial unit directions (n, 3)."""
        return u_i

    def directions_jacobian(
        self, value: np.ndarray, u_i: np.ndarray, ctx: FrameContext
    ) -> np.ndarray:
        """∂u_i'/∂value (n, 3, k)."""
        return np.zeros((len(u_i), 3, self.size))

    # ------------------------------------------------------------------ TIME stage
    def time_shift(self, value: np.ndarray, ctx: FrameContext) -> float:
        """Seconds added to the reported exposure stamp."""
        return 0.0

    def time_shift_jacobian(self, value: np.ndarray, ctx: FrameContext) -> np.ndarray:
        """∂Δt/∂value (k,)."""
        return np.zeros(self.size)

    # ------------------------------------------------------------------ TRACKER stage
    def tracker_rotation(self, value: np.ndarray, ctx: FrameContext) -> np.ndarray:
        """Small rotation (3,) about the tracker axes added to the installation."""
        return np.zeros(3)

    def tracker_rotation_jacobian(self, value: np.ndarray, ctx: FrameContext) -> np.ndarray:
        """∂δ/∂value (3, k)."""
        return np.zeros((3, self.size))

    # ------------------------------------------------------------------ CAMERA stage
    def camera_parameters(
        self, value: np.ndarray, p: np.ndarray, ctx: FrameContext
    ) -> np.ndarray:
        """Map the running 18-vector of OpenCV camera parameters to a new one."""
        return p

    def camera_jacobian(
        self, value: np.ndarray, p: np.ndarray, ctx: FrameContext
    ) -> tuple[np.ndarray, np.ndarray]:
        """Return (∂p'/∂value (18, k), ∂p'/∂p (18, 18))."""
        return np.zeros((18, self.size)), np.eye(18)

    # ------------------------------------------------------------------ compiled form
    def affine_form(self) -> Any:
        """The stage map as a constant affine map of the value, for the compiled star step.

        CAMERA: ``(J (18, k), D (18, 18))`` with ``p' = D p + J v``; TRACKER: ``J`` (3, k)
        with ``δ = J v``; TIME: ``g`` (k,) with ``Δt = g · v`` — for every value, input and
        context, and equal to the Jacobians the methods above return.  The filters then
        predict every star of a frame in one compiled kernel
        (:class:`~stellar_cal_ros.methods.star_chain.CompiledChain`).  None (the default, and
        any map that depends on the context or is not affine): the model predicts through
        the Python methods, with the same numbers to rounding.
        """
        return None

    def __repr__(self) -> str:
        return f"<effect {self.id}: {', '.join(self.parameter_names)}>"


def _mapping_or_empty(x: Any) -> dict:
    return x if isinstance(x, dict) else {}


def _number_or(x: Any, default: float) -> float:
    """``x`` as a finite float, else ``default`` (missing or malformed entries of a file)."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return default
    return v if np.isfinite(v) else default


CAMERA_INDEX = {
    name: i
    for i, name in enumerate(
        ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6",
         "s1", "s2", "s3", "s4", "tau_x", "tau_y")
    )
}


class CameraSetEffect(Effect):
    """A camera effect whose parameters *are* some OpenCV camera parameters.

    Subclasses list the camera entries they own in ``camera_entries``; the value overwrites
    those entries.  The starting value comes from the prior camera and the result is written
    back into the calibration's camera block, so OpenCV reproduces it.
    """

    stage = Stage.CAMERA
    camera_entries: ClassVar[tuple[str, ...]] = ()

    def _index(self) -> list[int]:
        return [CAMERA_INDEX[n] for n in self.camera_entries]

    def initial(self, prior: Any) -> tuple[np.ndarray, np.ndarray]:  # noqa: D102
        p = prior.camera.parameters()
        value = p[self._index()].copy()
        sigma = _camera_sigma(prior, self.camera_entries, self.default_sigma)
        return value, sigma

    def store(self, value: np.ndarray, sigma: np.ndarray, cal: Any) -> None:  # noqa: D102
        p = cal.camera.parameters()
        p[self._index()] = value
        cal.camera = cal.camera.with_parameters(p)
        _store_camera_sigma(cal, self.camera_entries, sigma)

    def camera_parameters(self, value, p, ctx):  # noqa: D102
        out = p.copy()
        out[self._index()] = value
        return out

    def camera_jacobian(self, value, p, ctx):  # noqa: D102
        # constant (the entries are overwritten whatever their value): built once, read-only
        cached = self.__dict__.get("_camera_jacobian")
        if cached is None:
            idx = self._index()
            J = np.zeros((18, self.size))
            J[idx, np.arange(self.size)] = 1.0
            D = np.eye(18)
            D[idx, idx] = 0.0
            J.setflags(write=False)
            D.setflags(write=False)
            cached = self._camera_jacobian = (J, D)
        return cached

    def affine_form(self):  # noqa: D102
        return self.camera_jacobian(None, None, None)


# Contract §3: sigma.camera.camera_matrix (3x3 data) and distortion_coefficients (OpenCV order).
_K_SIGMA_INDEX = {"fx": 0, "fy": 4, "cx": 2, "cy": 5}
_DIST_ORDER = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4",
               "tau_x", "tau_y")


def _camera_sigma(prior: Any, entries: tuple[str, ...], default: tuple[float, ...]) -> np.ndarray:
    cam_sigma = (prior.sigma or {}).get("camera", {})
    K = (cam_sigma.get("camera_matrix") or {}).get("data")
    D = (cam_sigma.get("distortion_coefficients") or {}).get("data")
    out = []
    for name, fallback in zip(entries, default, strict=True):
        value = None
        if name in _K_SIGMA_INDEX and K is not None and len(K) == 9:
            value = K[_K_SIGMA_INDEX[name]]
        elif name in _DIST_ORDER and D is not None and _DIST_ORDER.index(name) < len(D):
            value = D[_DIST_ORDER.index(name)]
        out.append(float(value) if value is not None and float(value) > 0 else float(fallback))
    return np.array(out)


def _store_camera_sigma(cal: Any, entries: tuple[str, ...], sigma: np.ndarray) -> None:
    cam = cal.sigma.setdefault("camera", {})
    K = cam.setdefault("camera_matrix", {"rows": 3, "cols": 3, "data": [0.0] * 9})
    n_dist = max(5, len(cal.camera.to_yaml_dict()["distortion_coefficients"]["data"]))
    D = cam.setdefault("distortion_coefficients", {"rows": 1, "cols": n_dist,
                                                   "data": [0.0] * n_dist})
    if len(D["data"]) < n_dist:
        D["data"] = list(D["data"]) + [0.0] * (n_dist - len(D["data"]))
        D["cols"] = n_dist
    for name, s in zip(entries, sigma, strict=True):
        if name in _K_SIGMA_INDEX:
            K["data"][_K_SIGMA_INDEX[name]] = float(s)
        else:
            i = _DIST_ORDER.index(name)
            if i >= len(D["data"]):
                D["data"] = list(D["data"]) + [0.0] * (i + 1 - len(D["data"]))
                D["cols"] = len(D["data"])
            D["data"][i] = float(s)
