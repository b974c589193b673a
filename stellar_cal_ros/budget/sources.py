"""Error sources of a budget: from a result file (covariance or σ) or from a spec of σ's.

An :class:`ErrorModel` holds parameters ξ (k,) with covariance ``C`` (k, k) and the linear map
``D`` (21, k) to the parameter error ``δx`` of :mod:`.propagation` (18 OpenCV camera
parameters + installation ψ), grouped into named sources, plus the centroid noise σ.

Parameter names are the estimators' (``principal_point.cx``, ``focal_length.f``,
``radial_k1k2.k1``, ``image_plane_tilt.tau_x``, ``installation.rx`` …) or the camera's own
(``fx`` … ``tau_y``); :func:`parameter_direction` maps each to its column of ``D``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from stellar_cal_ros.budget.propagation import N_PARAMETERS
from stellar_cal_ros.core.camera import CameraModel
from stellar_cal_ros.core.units import ARCSEC
from stellar_cal_ros.effects import registry
from stellar_cal_ros.effects.base import CAMERA_INDEX, FrameContext, Stage, _camera_sigma
from stellar_cal_ros.errors import ModelError, yaml_error_text
from stellar_cal_ros.io.calibration import Calibration

__all__ = [
    "CENTROID",
    "ErrorModel",
    "error_model_from_result",
    "error_model_from_spec",
    "find_covariance",
    "load_covariance",
    "parameter_direction",
]

CENTROID = "centroid"
#: Order of the sources in a budget.
SOURCE_ORDER = ("centroid", "principal_point", "focal_length", "pixel_aspect", "distortion",
                "image_plane_tilt", "installation")

# a camera parameter named by itself (a spec, a sigma block) -> its source
_GROUP_OF_CAMERA = {"fx": "focal_length", "fy": "focal_length", "cx": "principal_point",
                    "cy": "principal_point", "tau_x": "image_plane_tilt",
                    "tau_y": "image_plane_tilt"}


@dataclass
class ErrorModel:
    """Error sources of a budget (see the module docstring).

    Attributes
    ----------
    camera : CameraModel
        The camera the errors are linearised about (the true one, or the estimate).
    names : list of str
        Parameter names, k.
    directions : numpy.ndarray, shape (21, k)
        ``∂δx/∂ξ``.
    covariance : numpy.ndarray, shape (k, k)
        Covariance of ξ (units of each parameter).
    groups : dict of str to list of int
        Source name → columns of ξ.
    centroid_sigma_px : float
        Centroid noise per axis, px (0: no centroid source).
    origin : str
        Where the covariance came from (printed with the budget).
    notes : list of str
        Assumptions and parameters left out, for the report.
    """

    camera: CameraModel
    names: list[str]
    directions: np.ndarray
    covariance: np.ndarray
    groups: dict[str, list[int]]
    centroid_sigma_px: float = 0.0
    origin: str = ""
    notes: list[str] = field(default_factory=list)

    def sources(self) -> list[str]:
        """Source names, centroid noise first when present."""
        return ([CENTROID] if self.centroid_sigma_px > 0 else []) + list(self.groups)

    def parameter_covariance(self, source: str | None = None) -> np.ndarray:
        """Covariance (21, 21) of ``δx`` from one source (its marginal block) or all."""
        if source == CENTROID:
            return np.zeros((N_PARAMETERS, N_PARAMETERS))
        cols = list(range(len(self.names))) if source is None else self.groups[source]
        D = self.directions[:, cols]
        return D @ self.covariance[np.ix_(cols, cols)] @ D.T

    def sampler(self, source: str | None = None):
        """Return ``draw(rng) -> (δx (21,), uses_centroid)`` for one source or all."""
        cols = list(range(len(self.names))) if source is None else (
            [] if source == CENTROID else self.groups[source])
        D = self.directions[:, cols]
        L = _cholesky_psd(self.covariance[np.ix_(cols, cols)]) if cols else np.zeros((0, 0))
        centroid = (source in (None, CENTROID)) and self.centroid_sigma_px > 0

        def draw(rng: np.random.Generator) -> tuple[np.ndarray, bool]:
            if not cols:
                return np.zeros(N_PARAMETERS), centroid
            return D @ (L @ rng.standard_normal(len(cols))), centroid

        return draw

    def block(self, source: str) -> tuple[np.ndarray, np.ndarray]:
        """``(D_s (21, k_s), C_s (k_s, k_s))`` of one source (not the centroid)."""
        cols = self.groups[source]
        return self.directions[:, cols], self.covariance[np.ix_(cols, cols)]


def _cholesky_psd(C: np.ndarray) -> np.ndarray:
    """A square root ``L`` with ``L Lᵀ = C`` for a positive semi-definite ``C``."""
    w, V = np.linalg.eigh(0.5 * (C + C.T))
    return V * np.sqrt(np.clip(w, 0.0, None))


# ---------------------------------------------------------------------------- names


def parameter_direction(name: str, camera: CameraModel) -> tuple[str, np.ndarray] | None:
    """Source and column of ``D`` (21,) of a parameter name, or None if not in a budget.

    Parameters
    ----------
    name : str
        ``effect.parameter`` as the estimators name it, or a camera parameter
        (:attr:`CameraModel.PARAMETER_NAMES`), or ``installation.rx|ry|rz``.
    camera : CameraModel
        The linearisation point (e.g. ``focal_length.f`` moves ``fy`` by ``fy/fx``,
        ``pixel_aspect.aspect`` by ``fx``: :func:`effect_directions`).

    Returns
    -------
    (str, numpy.ndarray) or None
    """
    col = np.zeros(N_PARAMETERS)
    effect, _, par = name.rpartition(".")
    if not effect and name in CAMERA_INDEX:
        col[CAMERA_INDEX[name]] = 1.0
        return _GROUP_OF_CAMERA.get(name, "distortion"), col
    columns = effect_directions(effect, camera)
    if columns is None or par not in columns[1]:
        return None
    return columns[0], columns[1][par]


def effect_directions(effect_id: str, camera: CameraModel
                      ) -> tuple[str, dict[str, np.ndarray]] | None:
    """The budget source of an effect and the column of ``D`` (21,) of each parameter.

    Both come from the effect's class: its ``budget_source`` (None: not part of a budget)
    and its stage's Jacobian at ``camera`` — ``∂p/∂value`` (18 OpenCV parameters) for a
    CAMERA effect, ``∂δ/∂value`` (installation rotation) for a TRACKER effect.
    """
    if effect_id not in registry.EFFECTS:
        return None
    eff = registry.create(effect_id)
    if eff.budget_source is None or eff.stage not in (Stage.CAMERA, Stage.TRACKER):
        return None
    cal = Calibration(camera=camera, installation=Rotation.identity())
    value, _ = eff.initial(cal)
    ctx = FrameContext(stamp=0.0)
    D = np.zeros((N_PARAMETERS, eff.size))
    if eff.stage is Stage.CAMERA:
        D[:18] = eff.camera_jacobian(value, camera.parameters(), ctx)[0]
    else:
        D[18:] = eff.tracker_rotation_jacobian(value, ctx)
    return eff.budget_source, {n: D[:, i] for i, n in enumerate(eff.parameter_names)}


def _assemble(camera: CameraModel, names: list[str], covariance: np.ndarray,
              centroid_sigma_px: float, origin: str, notes: list[str]) -> ErrorModel:
    keep, cols, groups, dropped = [], [], {}, []
    for i, name in enumerate(names):
        mapped = parameter_direction(name, camera)
        if mapped is None:
            dropped.append(name)
            continue
        group, col = mapped
        groups.setdefault(group, []).append(len(keep))
        keep.append(i)
        cols.append(col)
    if dropped:
        notes.append("not part of a tracker budget (left out): " + ", ".join(dropped))
    order = {g: i for i, g in enumerate(SOURCE_ORDER)}
    groups = dict(sorted(groups.items(), key=lambda kv: order.get(kv[0], len(order))))
    if not keep and centroid_sigma_px <= 0:
        raise ModelError("the budget has no error source (no camera or installation "
                         "parameter with a sigma, and no centroid noise)")
    return ErrorModel(
        camera=camera,
        names=[names[i] for i in keep],
        directions=np.array(cols).T.reshape(N_PARAMETERS, len(keep)),
        covariance=np.asarray(covariance, dtype=float)[np.ix_(keep, keep)],
        groups=groups,
        centroid_sigma_px=float(centroid_sigma_px),
        origin=origin,
        notes=notes,
    )


# ---------------------------------------------------------------------------- result file


def load_covariance(path: str | Path) -> tuple[list[str], np.ndarray]:
    """Read a covariance sidecar: ``names`` (k) and ``matrix`` (k × k, or k² row-major).

    YAML, JSON or ``.npz``; ``parameters`` is accepted for ``names`` and ``covariance`` or
    ``data`` for ``matrix``.

    Raises
    ------
    stellar_cal_ros.errors.ModelError
        Unreadable file, missing key, wrong size, asymmetric or non-finite matrix.
    """
    path = Path(path)
    try:
        if path.suffix == ".npz":
            with np.load(path, allow_pickle=False) as z:
                raw: Mapping[str, Any] = {k: z[k] for k in z.files}
        else:
            raw = yaml.safe_load(path.read_text())  # JSON is YAML
    except (OSError, ValueError, yaml.YAMLError) as exc:
        raise ModelError(f"{path}: cannot read the covariance: {yaml_error_text(exc)}") from None
    if not isinstance(raw, Mapping):
        raise ModelError(f"{path}: a covariance file must be a mapping with 'names' and "
                         "'matrix'")
    names = next((raw[k] for k in ("names", "parameters") if k in raw), None)
    matrix = next((raw[k] for k in ("matrix", "covariance", "data") if k in raw), None)
    if names is None or matrix is None:
        raise ModelError(f"{path}: needs 'names' and 'matrix' (got keys {sorted(raw)})")
    names = [str(n) for n in np.asarray(names).reshape(-1)]
    try:
        M = np.asarray(matrix, dtype=float)
    except (TypeError, ValueError):
        raise ModelError(f"{path}: 'matrix' must hold numbers") from None
    k = len(names)
    if M.size != k * k:
        raise ModelError(f"{path}: 'matrix' must hold {k}x{k} numbers for {k} names, "
                         f"got {M.size}")
    M = M.reshape(k, k)
    if not np.all(np.isfinite(M)) or not np.allclose(M, M.T, rtol=1e-6, atol=0.0):
        raise ModelError(f"{path}: 'matrix' must be finite and symmetric")
    if np.any(np.diag(M) < 0):
        raise ModelError(f"{path}: negative variance on the diagonal")
    return names, M


def find_covariance(result_path: str | Path) -> Path | None:
    """The covariance sidecar next to a result (``RESULT.covariance.yaml|json|npz``)."""
    stem = Path(result_path).with_suffix("")
    for ext in ("yaml", "json", "npz"):
        p = Path(f"{stem}.covariance.{ext}")
        if p.exists():
            return p
    return None


def _diagonal_from_sigma(cal: Any) -> tuple[list[str], np.ndarray]:
    """Parameter names and variances from a result's ``sigma`` block (contract §3)."""
    names, var = [], []
    entries = ("fx", "cx", "cy") + tuple(n for n in CameraModel.PARAMETER_NAMES[4:])
    sig = _camera_sigma(cal, entries, (0.0,) * len(entries))
    by_name = dict(zip(entries, sig, strict=True))
    if by_name.pop("fx") > 0:  # fx and fy are one focal length f (fy = f · fy/fx)
        names.append("focal_length.f")
        var.append(_camera_sigma(cal, ("fx",), (0.0,))[0] ** 2)
    aspect = (((cal.sigma or {}).get("effects") or {}).get("pixel_aspect") or {}).get("aspect")
    if aspect:
        names.append("pixel_aspect.aspect")
        var.append(float(aspect) ** 2)
    for name, s in by_name.items():
        if s > 0:
            names.append(name)
            var.append(s * s)
    rot = ((cal.sigma or {}).get("installation") or {}).get("rotation_vector")
    if rot:
        for axis, s in zip(("rx", "ry", "rz"), rot, strict=False):
            if float(s) > 0:
                names.append(f"installation.{axis}")
                var.append(float(s) ** 2)
    return names, np.diag(var) if var else np.zeros((0, 0))


def _indices(name: str, camera: CameraModel) -> set[int]:
    """Entries of ``δx`` a parameter moves (empty if it is not in a budget)."""
    mapped = parameter_direction(name, camera)
    return set() if mapped is None else set(np.flatnonzero(mapped[1]).tolist())


def error_model_from_result(cal: Any, covariance: tuple[list[str], np.ndarray] | None = None,
                            covariance_source: str = "", prior: Any = None,
                            exclude: list[str] | None = None,
                            centroid_sigma_px: float = 0.0,
                            unestimated: str = "exclude") -> ErrorModel:
    """Error sources of a calibration result.

    Parameters
    ----------
    cal : Calibration
        The result; its camera is the linearisation point.
    covariance : (names, matrix), optional
        Full covariance of the estimated parameters (:func:`load_covariance`).  Without it
        the diagonal of ``cal.sigma`` is used, and the budget says so: correlations (e.g.
        principal point with installation, large for a PSCE result) are then lost.
    covariance_source : str
        Where the covariance came from, for the report.
    prior : Calibration, optional
        The run's prior: tells which geometric parameters the run did not estimate (absent
        from the covariance; with the diagonal, σ equal to the prior's, which the result
        file repeats).  They are held at the prior's value, so their error is the prior's σ.
    exclude : list of str, optional
        Parameter names to leave out (either naming).
    centroid_sigma_px : float
        Centroid noise per axis, px, for the centroid source (0: none).
    unestimated : str
        With a prior: ``"exclude"`` leaves the unestimated parameters out (listed in the
        notes; the diagnosis is what bounds an effect a model assumes absent),
        ``"include"`` adds them with the prior's σ.

    Returns
    -------
    ErrorModel
    """
    if unestimated not in ("exclude", "include"):
        raise ModelError(f"unestimated must be 'exclude' or 'include', got {unestimated!r}")
    notes: list[str] = []
    drop = set(exclude or [])
    if covariance is not None:
        names, C = list(covariance[0]), np.asarray(covariance[1], dtype=float)
        origin = f"full covariance ({covariance_source or 'given'})"
    else:
        names, C = _diagonal_from_sigma(cal)
        origin = ("diagonal of the result's sigma block (no covariance file: correlations "
                  "between parameters are ignored)")
    if prior is not None:
        p_names, p_C = _diagonal_from_sigma(prior)
        p_var = dict(zip(p_names, np.diag(p_C), strict=True))
        if covariance is not None:
            covered = set().union(*(_indices(n, cal.camera) for n in names))
            held = [n for n in p_names if _indices(n, cal.camera)
                    and not _indices(n, cal.camera) & covered]
        else:
            held = [n for n, v in zip(names, np.diag(C), strict=True)
                    if n in p_var and np.isclose(v, p_var[n], rtol=1e-9, atol=0.0)]
        if held:
            what = ", ".join(f"{n} (σ {math.sqrt(p_var[n]):.3g})" for n in held)
            if unestimated == "include":
                notes.append(f"not estimated, held at the prior, in the budget with the "
                             f"prior's sigma: {what}")
                new = [n for n in held if n not in names]
                k = len(names)
                C2 = np.zeros((k + len(new), k + len(new)))
                C2[:k, :k] = C
                C2[k:, k:] = np.diag([p_var[n] for n in new])
                names, C = names + new, C2
            else:
                notes.append(f"not estimated, held at the prior (left out; --unestimated "
                             f"include adds the prior's sigma): {what}")
                drop |= set(held)
    if drop:
        keep = [i for i, n in enumerate(names) if n not in drop and n.split(".")[-1] not in drop]
        ex = set(exclude or [])
        asked = [n for i, n in enumerate(names)
                 if i not in keep and (n in ex or n.split(".")[-1] in ex)]
        if asked:
            notes.append("excluded on request: " + ", ".join(asked))
        names, C = [names[i] for i in keep], C[np.ix_(keep, keep)]
    return _assemble(cal.camera, list(names), C, centroid_sigma_px, origin, notes)


# ---------------------------------------------------------------------------- spec file


def _number(block: Mapping[str, Any], key: str, where: str) -> float:
    v = block[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
        raise ModelError(f"{where}.{key} must be a non-negative number, got {v!r}")
    return float(v)


def _one_of(block: Any, units: dict[str, float], where: str) -> float:
    """The σ of a block given in one of several units, converted (``units``: key → factor)."""
    if not isinstance(block, Mapping):
        raise ModelError(f"{where} must be a mapping like {{{next(iter(units))}: 0.1}}")
    found = [k for k in units if k in block]
    if len(found) != 1:
        raise ModelError(f"{where} needs exactly one of {', '.join(units)}, got {sorted(block)}")
    return _number(block, found[0], where) * units[found[0]]


def spec_camera(spec: Mapping[str, Any], base: Path | None = None) -> CameraModel:
    """The camera of a spec, principal point at the centre.

    ``calibration: FILE`` (its camera block), or ``focal_length_mm`` + ``pixel_size_mm`` (or
    ``focal_length_px``), ``width``, ``height``.
    """
    from stellar_cal_ros.io.calibration import load_calibration

    cam = spec.get("camera")
    if not isinstance(cam, Mapping):
        raise ModelError("spec.camera must be a mapping (focal_length_mm, pixel_size_mm, "
                         "width, height; or calibration: FILE)")
    if "calibration" in cam:
        path = Path(cam["calibration"])
        return load_calibration(path if path.is_absolute() or base is None else base / path
                                ).camera
    for key in ("width", "height"):
        if not isinstance(cam.get(key), int) or cam[key] <= 0:
            raise ModelError(f"spec.camera.{key} must be a positive integer")
    if "focal_length_px" in cam:
        f = _number(cam, "focal_length_px", "spec.camera")
    else:
        for key in ("focal_length_mm", "pixel_size_mm"):
            if key not in cam:
                raise ModelError(f"spec.camera.{key} is missing (or give focal_length_px)")
        f = _number(cam, "focal_length_mm", "spec.camera") / _number(
            cam, "pixel_size_mm", "spec.camera")
    if f <= 0:
        raise ModelError("spec.camera: the focal length must be positive")
    return CameraModel.pinhole(cam["width"], cam["height"], f)


def error_model_from_spec(spec: Mapping[str, Any], camera: CameraModel,
                          reference_angle_deg: float) -> ErrorModel:
    """Error sources from a spec's ``sources`` block (1σ each; see ``doc/budget.md``).

    ``centroid: {sigma_px}``, ``principal_point: {sigma_px}`` (each axis),
    ``focal_length: {sigma_px | sigma_mm}`` (needs ``camera.pixel_size_mm`` for mm),
    ``image_plane_tilt: {sigma_deg | sigma_rad}`` (each axis), ``distortion: {sigma_px}``
    (a radial k1 error moving a star at the reference angle by σ px; or coefficient σ's
    ``{k1, k2, p1, p2, k3}``), ``installation: {sigma_arcsec}`` (a number or three).
    """
    src = spec.get("sources")
    if not isinstance(src, Mapping) or not src:
        raise ModelError("spec.sources must be a non-empty mapping of source: {sigma...}")
    known = ("centroid", "principal_point", "focal_length", "image_plane_tilt", "distortion",
             "installation")
    unknown = sorted(set(src) - set(known))
    if unknown:
        raise ModelError(f"spec.sources: unknown source(s) {', '.join(unknown)}; known: "
                         + ", ".join(known))
    pitch = (spec.get("camera") or {}).get("pixel_size_mm")
    names: list[str] = []
    var: list[float] = []
    notes: list[str] = []
    centroid = 0.0
    for name in known:
        if name not in src:
            continue
        where = f"spec.sources.{name}"
        block = src[name]
        if name == "centroid":
            centroid = _one_of(block, {"sigma_px": 1.0}, where)
        elif name == "principal_point":
            s = _one_of(block, {"sigma_px": 1.0}, where)
            names += ["cx", "cy"]
            var += [s * s] * 2
        elif name == "focal_length":
            units = {"sigma_px": 1.0}
            if pitch:
                units["sigma_mm"] = 1.0 / float(pitch)
            s = _one_of(block, units, where)
            names.append("focal_length.f")
            var.append(s * s)
        elif name == "image_plane_tilt":
            s = _one_of(block, {"sigma_rad": 1.0, "sigma_deg": math.pi / 180.0}, where)
            names += ["tau_x", "tau_y"]
            var += [s * s] * 2
        elif name == "distortion":
            if isinstance(block, Mapping) and "sigma_px" in block:
                rho = math.tan(math.radians(reference_angle_deg))
                s = _number(block, "sigma_px", where) / (camera.fx * rho**3)
                names.append("k1")
                var.append(s * s)
                notes.append(f"distortion: a radial k1 error of σ {s:.3g} moves a star at "
                             f"{reference_angle_deg:.2f}° by {block['sigma_px']} px (1σ)")
            elif isinstance(block, Mapping) and block:
                for k in block:
                    if k not in ("k1", "k2", "p1", "p2", "k3"):
                        raise ModelError(f"{where}: unknown coefficient {k!r} (k1 k2 p1 p2 "
                                         "k3, or sigma_px)")
                    names.append(k)
                    var.append(_number(block, k, where) ** 2)
            else:
                raise ModelError(f"{where} must be {{sigma_px: ...}} or coefficient sigmas")
        elif name == "installation":
            if not isinstance(block, Mapping) or "sigma_arcsec" not in block:
                raise ModelError(f"{where} must be {{sigma_arcsec: number or [x, y, z]}}")
            s = np.broadcast_to(np.asarray(block["sigma_arcsec"], dtype=float), (3,))
            names += ["installation.rx", "installation.ry", "installation.rz"]
            var += list((s * ARCSEC) ** 2)
    return _assemble(camera, names, np.diag(var) if var else np.zeros((0, 0)), centroid,
                     "spec (independent sources, 1σ each)", notes)


def read_spec(path: str | Path, what: str = "budget spec") -> dict[str, Any]:
    """Load a spec YAML (a mapping of plain types) with a clear one-line error."""
    path = Path(path)
    try:
        spec = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ModelError(f"{path}: cannot read the {what}: {yaml_error_text(exc)}") from None
    if not isinstance(spec, dict):
        raise ModelError(f"{path}: a {what} must be a mapping")
    return json.loads(json.dumps(spec, default=str))  # plain types only
