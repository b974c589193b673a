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
adding an effect to a filter needs no change to the filter: write a subclass with an ``id``
in a file of its own in this package (the registry finds it), or load it as a plugin (see
:mod:`stellar_cal_ros.effects.registry`).

Parameters are plain vectors.  Everything the rest of the package needs to know about an
effect is declared on its class, so a new effect is one file:

==================  ======================================================================
attribute           read by
==================  ======================================================================
``stage``,          the filters (which stage the effect acts in), the application order
``order``           within that stage (lower first; it also fixes the state layout)
``parameter_names``  every table, result file and report
``units``,
``default_sigma``,
``process_noise``
``plausible``       the diagnosis: the largest size seen in practice, stated where the
                    effect acts (px at the detector corner, arcsec, ms, ppm ...) and
                    converted to the parameters for the run's camera
                    (:meth:`Effect.plausible_parameters`)
``physical_value``  the diagnosis: the value physics fixes (astrometric scales: 1)
``physical_limit``  the diagnosis: the size (norm of the parameters, their units) no
                    working instrument reaches; an estimate clearly beyond it is a stand-in
``display_units``   every printed number (arcsec, ppm, mrad, ms ...)
``export_role``     ``stellar-cal export``: where the value goes (:class:`ExportRole`)
``budget_source``   ``stellar-cal budget``: the error source it belongs to (None: not part
                    of a tracker budget); the budget's direction is the stage's Jacobian
``simulation_*``    ``stellar-cal simulate --effect ID=V``
``requires``,       the diagnosis (applicability) and ``stellar-cal effects``
``explanation``
==================  ======================================================================

``initial`` reads the starting value from a prior
:class:`~stellar_cal_ros.io.calibration.Calibration` and ``store`` writes an estimate back
into one.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from stellar_cal_ros.core.earth import Site
from stellar_cal_ros.core.units import ARCSEC, DEG, DEG_PER_HOUR, MICRO_G, MS, PPM
from stellar_cal_ros.errors import ModelError


class Stage(enum.Enum):
    """Where in the model chain an effect acts."""

    GYRO = "gyro"
    ACCEL = "accel"
    DIRECTION = "direction"
    TIME = "time"
    TRACKER = "tracker"
    CAMERA = "camera"


#: order of the stages in the estimated parameter vector θ (the layout, not the physics:
#: effects of different stages never act on each other's output)
STAGE_ORDER = (Stage.TRACKER, Stage.CAMERA, Stage.GYRO, Stage.ACCEL, Stage.TIME,
               Stage.DIRECTION)


class ExportRole(enum.Enum):
    """What ``stellar-cal export`` does with an effect's stored value."""

    CAMERA = "camera"  #: it lives in the camera block: exported as far as OpenCV's model can
    EXTRINSIC = "extrinsic"  #: the camera–IMU transform / time shift of the target file
    IMU = "imu"  #: an inertial-sensor error: the camera formats hold none (listed)
    STAR_DIRECTIONS = "star_directions"  #: a correction of the star directions (listed)
    NOT_EXPORTABLE = "not_exportable"  #: a sensor effect no target format can express


#: the unit a parameter of each unit is shown in (others: as they are; "1": no unit)
UNIT_DISPLAY: dict[str, str] = {"rad": "arcsec", "s": "ms", "rad/s": "deg/h", "m/s^2": "ug",
                                "1/degC": "ppm/degC", "1": ""}


#: unit → (dimension, value in the dimension's base unit): what :func:`unit_factor` converts
_UNITS: dict[str, tuple[str, float]] = {
    "rad": ("angle", 1.0), "mrad": ("angle", 1e-3), "deg": ("angle", DEG),
    "arcsec": ("angle", ARCSEC), "s": ("time", 1.0), "ms": ("time", MS),
    "rad/s": ("rate", 1.0), "deg/h": ("rate", DEG_PER_HOUR), "m/s^2": ("accel", 1.0),
    "ug": ("accel", MICRO_G), "mg": ("accel", 1e3 * MICRO_G), "1": ("ratio", 1.0),
    "ppm": ("ratio", PPM), "%": ("ratio", 1e-2), "px": ("px", 1.0),
    "1/degC": ("per_degC", 1.0), "ppm/degC": ("per_degC", PPM),
    "x physical": ("ratio", 1.0),
}


def unit_factor(unit: str, to: str) -> float:
    """How many ``to`` one ``unit`` is (``unit_factor('rad', 'arcsec')`` = 206264.8).

    Raises :class:`~stellar_cal_ros.errors.ModelError` for units of different kinds or a unit
    it does not know (unless both are the same string).
    """
    if unit == to:
        return 1.0
    a, b = _UNITS.get(unit), _UNITS.get(to)
    if a is None or b is None or a[0] != b[0]:
        raise ModelError(f"cannot convert {unit!r} to {to!r}")
    return a[1] / b[1]


@dataclass(frozen=True)
class Plausible:
    """The largest size of an effect seen in practice, stated where it acts.

    ``size`` (one number for every parameter, or one per parameter) is in ``unit``:

    * ``at=""`` (the default): the parameters themselves, in the effect's display unit
      (``720 arcsec``, ``1000 ppm``, ``50 ms``) or its parameter unit;
    * ``at="corner"``: pixels of image displacement at the detector's corner (the largest
      over the detector) — for coefficients whose meaning depends on the lens (distortion:
      a k3 of 2 is 0.05 px at the corner of a 15° field and 60 px at that of a 60° field).

    An effect converts it to its parameters for the run's camera with
    :meth:`Effect.plausible_parameters`; a class may override :meth:`Effect.plausible_gain`
    for another statement (the focal length: a fraction of f).
    """

    size: float | tuple[float, ...]
    unit: str
    at: str = ""

    def text(self, index: int = 0) -> str:
        """The statement, e.g. ``'5 px at the detector corner'``."""
        sizes = np.atleast_1d(np.asarray(self.size, dtype=float))
        size = sizes[min(index, sizes.size - 1)]
        unit = "" if self.unit == "1" else f" {self.unit}"
        where = {"corner": " at the detector corner"}.get(self.at, "")
        return f"{size:g}{unit}{where}"


@dataclass(frozen=True)
class BilinearCamera:
    """A CAMERA map bilinear in the value and the camera vector (compiled form).

    ``p' = (D0 + Σ_j v_j s_j Dv_j) p + J0 v`` with ``s = Effect.camera_scale(ctx)`` (k,)
    per frame: the pixel aspect (``fy = fx (1 + a)``) and the thermal focal length
    (``f (1 + c ΔT)``) — constant matrices ``D0`` (18, 18), ``Dv`` (k, 18, 18), ``J0``
    (18, k).  Its Jacobians: ``∂p'/∂p = D0 + Σ v_j s_j Dv_j``, ``∂p'/∂v_j = s_j Dv_j p +
    J0[:, j]``.
    """

    D0: np.ndarray
    Dv: np.ndarray
    J0: np.ndarray


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
    #: frames' stamps (POSIX s, ascending) from which the parameters take a free step each
    #: (a nuisance's, e.g. :class:`~stellar_cal_ros.diagnosis.slew_steps.SlewSteps`): the
    #: filter adds the default σ² to their variance there (:meth:`stepped` first)
    steps_at: tuple[float, ...] = ()
    #: the second half of the parameters holds the first half's value before its last step
    #: (set by the filter at each step, never in the measurement: a fixed-lag estimate)
    keeps_before_step: ClassVar[bool] = False
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
    #: position in its stage: effects of one stage apply in increasing order (the library's
    #: use 10-90; the default puts a new effect after every library effect of its stage)
    order: ClassVar[int] = 100
    #: largest size seen in practice, where the effect acts (None: the default σ, in the
    #: parameter units); see :class:`Plausible` and :meth:`plausible_parameters`
    plausible: ClassVar[Plausible | None] = None
    #: the value physics fixes, for an effect whose parameter scales a known correction
    #: (astrometric: 1); an estimate far from it means another cause with a similar pattern
    physical_value: ClassVar[float | None] = None
    #: the size (Euclidean norm of the parameters, in their units) no working instrument
    #: reaches (None: no such bound); a significant estimate clearly beyond it is the
    #: effect's pattern standing in for another cause, not the effect (discover: implausible)
    physical_limit: ClassVar[float | None] = None
    #: (unit, factor from the parameter unit) every parameter is shown in; None: from
    #: :data:`UNIT_DISPLAY` by each parameter's unit
    display_units: ClassVar[tuple[str, float] | None] = None
    #: what ``stellar-cal export`` does with the stored value (None: by stage, see
    #: :meth:`export`)
    export_role: ClassVar[ExportRole | None] = None
    #: error source of a tracker budget (``stellar-cal budget``) the parameters belong to,
    #: e.g. ``"distortion"``; None: not part of a budget
    budget_source: ClassVar[str | None] = None
    #: the test of the current model that must ask for the effect before it is a candidate
    #: of ``discover`` or ``diagnose`` (``"clock drift"``: the clock test's drift,
    #: :meth:`~stellar_cal_ros.diagnosis.clock.ClockChange.asks_drift`); ``""``: a candidate
    #: in every round (an effect a wrong candidate can stand in for, e.g. a clock's rate
    #: for a clock's step, is offered only on its own evidence)
    offered_on: ClassVar[str] = ""

    @property
    def size(self) -> int:
        """Number of parameters."""
        return len(self.parameter_names)

    # ------------------------------------------------------------------ declarations
    @classmethod
    def display(cls, name: str | None = None) -> tuple[str, float]:
        """(unit, factor) a user reads parameter ``name`` in (``'arcsec'``, 206264.8).

        ``display_units`` if declared, else the parameter's unit through
        :data:`UNIT_DISPLAY` (an unknown unit is shown as it is).
        """
        if cls.display_units is not None:
            return cls.display_units
        names = list(cls.parameter_names)
        unit = cls.units[names.index(name)] if name in names and cls.units else (
            cls.units[0] if cls.units else "1")
        shown = UNIT_DISPLAY.get(unit, unit)
        return shown, (unit_factor(unit, shown) if shown else 1.0)

    @classmethod
    def export(cls) -> ExportRole:
        """The export role: declared, else by stage (camera, extrinsic, IMU, directions)."""
        if cls.export_role is not None:
            return cls.export_role
        return {Stage.CAMERA: ExportRole.NOT_EXPORTABLE, Stage.TRACKER: ExportRole.EXTRINSIC,
                Stage.TIME: ExportRole.EXTRINSIC, Stage.GYRO: ExportRole.IMU,
                Stage.ACCEL: ExportRole.IMU,
                Stage.DIRECTION: ExportRole.STAR_DIRECTIONS}[cls.stage]

    def plausible_gain(self, calibration: Any) -> np.ndarray:
        """Size where the effect acts (in ``plausible.unit``) per unit of each parameter (k,).

        ``at="corner"``: the largest image displacement over the detector of
        ``calibration``'s camera per unit parameter (:func:`corner_gain`); otherwise the
        conversion from the parameter's unit to ``plausible.unit`` (:func:`unit_factor`).
        """
        pl = self.plausible
        if pl is not None and pl.at == "corner":
            return corner_gain(self, calibration)
        units = self.units or ("1",) * self.size
        return np.array([unit_factor(u, pl.unit if pl is not None else u) for u in units])

    def plausible_parameters(self, calibration: Any = None) -> np.ndarray:
        """The plausible size in the parameters' units (k,), for ``calibration``'s camera.

        ``plausible.size / plausible_gain``; without a ``plausible`` statement, a
        ``plausible_size`` tuple on the class (parameter units, the older form), else the
        default σ.  A size that cannot be converted (no camera given for a camera-dependent
        statement, a parameter that does not move the image) falls back to the default σ.
        """
        default = np.asarray(self.default_sigma, dtype=float)
        pl = self.plausible
        if pl is None:
            legacy = getattr(type(self), "plausible_size", None)
            size = default if legacy is None or callable(legacy) else legacy
            out = np.broadcast_to(np.asarray(size, dtype=float), (self.size,)).copy()
            return np.where(out > 0, out, default)
        with np.errstate(divide="ignore", invalid="ignore"):
            out = np.broadcast_to(np.asarray(pl.size, dtype=float), (self.size,)) / \
                np.asarray(self.plausible_gain(calibration), dtype=float)
        return np.where(np.isfinite(out) & (out > 0), out, default)

    def plausible_depends_on_camera(self) -> bool:
        """The plausible statement needs the camera (px at the corner, a share of f)."""
        pl = self.plausible
        return pl is not None and (pl.at == "corner"
                                   or type(self).plausible_gain is not Effect.plausible_gain)

    def fraction_reading(self, fraction: float, posix_s: float) -> str:
        """What a fit at ``fraction`` of :attr:`physical_value` may mean on data of ``posix_s``.

        "" (default): nothing but another cause with a similar pattern.  An effect whose
        fraction has a reading of its own (proper motion: the catalogue's epoch) says it.
        """
        return ""

    def where_it_acts(self, value: np.ndarray, calibration: Any = None) -> np.ndarray:
        """``|value|`` per parameter in the unit of the plausible statement (k,).

        E.g. a k3 as px at the detector corner of ``calibration``'s camera (NaN without a
        camera); the parameter units when the class states no ``plausible``.
        """
        v = np.abs(np.asarray(value, dtype=float))
        pl = self.plausible
        if pl is None:
            return v
        return v * np.asarray(self.plausible_gain(calibration), dtype=float)

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

    def stepped(self, k: int, value: np.ndarray, sigma: np.ndarray) -> None:
        """The filter's estimate and σ just before step ``k`` of :attr:`steps_at` (none kept)."""

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

    def camera_scale(self, ctx: FrameContext) -> np.ndarray:
        """The frame's scales ``s`` (k,) of a :class:`BilinearCamera` form (ones)."""
        return np.ones(self.size)

    # ------------------------------------------------------------------ compiled form
    def affine_form(self) -> Any:
        """The stage map as a constant affine map of the value, for the compiled star step.

        CAMERA: ``(J (18, k), D (18, 18))`` with ``p' = D p + J v``; TRACKER: ``J`` (3, k)
        with ``δ = J v``; TIME: ``g`` (k,) with ``Δt = g · v`` — for every value, input and
        context, and equal to the Jacobians the methods above return.  DIRECTION: True when
        ``directions(v, u, ctx) = u + Σ_j v_j C_j`` with ``C = directions_jacobian(·, u,
        ctx)`` the same for every value (it may depend on the frame: it comes in with it).
        CAMERA may also be a :class:`BilinearCamera` (with :meth:`camera_scale` per frame).
        The filters then predict every star of a frame in one compiled kernel
        (:class:`~stellar_cal_ros.methods.star_chain.CompiledChain`).  None (the default, and
        any map that depends on the context or is not affine): the model predicts through
        the Python methods, with the same numbers to rounding.
        """
        return None

    def __repr__(self) -> str:
        return f"<effect {self.id}: {', '.join(self.parameter_names)}>"


#: detector points (fractions of width and height) where :func:`corner_gain` looks
_GRID = np.linspace(0.0, 1.0, 5)


def corner_gain(effect: Effect, calibration: Any) -> np.ndarray:
    """Largest image displacement (px) over the detector per unit of each parameter (k,).

    For a CAMERA-stage effect at the calibration's camera and value: the detector's
    corners, edges and centre (a 5 × 5 grid) are unprojected with the camera, and the
    displacement per unit parameter is ``|∂(u, v)/∂p · ∂p/∂value|`` (the camera's analytic
    projection Jacobian times the effect's); the largest over the grid, normally at a
    corner.  Other stages, or no camera: NaN (the caller falls back to the default σ).
    """
    if effect.stage is not Stage.CAMERA or getattr(calibration, "camera", None) is None:
        return np.full(effect.size, np.nan)
    cam = calibration.camera
    value, _ = effect.initial(calibration)
    gu, gv = np.meshgrid(_GRID * (cam.width - 1.0), _GRID * (cam.height - 1.0))
    d = cam.unproject(np.column_stack([gu.ravel(), gv.ravel()]))
    d = d[np.all(np.isfinite(d), axis=1)]
    _, _, J_p = cam.project(d, jacobians=True)  # (n, 2, 18)
    J_e, _ = effect.camera_jacobian(value, cam.parameters(), FrameContext(stamp=0.0))
    disp = np.einsum("nij,jk->nik", J_p, np.asarray(J_e, dtype=float))  # (n, 2, k)
    return np.linalg.norm(disp, axis=1).max(axis=0)


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
FX, FY = CAMERA_INDEX["fx"], CAMERA_INDEX["fy"]


class CameraSetEffect(Effect):
    """A camera effect whose parameters *are* some OpenCV camera parameters.

    Subclasses list the camera entries they own in ``camera_entries``; the value overwrites
    those entries.  The starting value comes from the prior camera and the result is written
    back into the calibration's camera block, so OpenCV reproduces it.
    """

    stage = Stage.CAMERA
    export_role = ExportRole.CAMERA
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
