"""OpenCV-compatible camera model of the star tracker, with analytic Jacobians.

Frames and pixels follow ``doc/interfaces.md`` §1: the camera frame is the ROS optical
frame (+z along the boresight, +x towards increasing column ``u``, +y towards increasing row
``v``) and pixel ``(0, 0)`` is the centre of the top-left pixel.

The projection is exactly the one of ``cv2.projectPoints`` with a zero pose and the 14
distortion coefficients in OpenCV order ``k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4 tau_x tau_y``.
For a direction ``d = (X, Y, Z)`` in the camera frame::

    x, y   = X / Z, Y / Z                                  normalised pinhole point
    r2     = x**2 + y**2
    g      = (1 + k1 r2 + k2 r2**2 + k3 r2**3) / (1 + k4 r2 + k5 r2**2 + k6 r2**3)
    x''    = x g + 2 p1 x y + p2 (r2 + 2 x**2) + s1 r2 + s2 r2**2
    y''    = y g + p1 (r2 + 2 y**2) + 2 p2 x y + s3 r2 + s4 r2**2
    w      = M(tau_x, tau_y) @ (x'', y'', 1)                tilted image plane
    u, v   = fx w0 / w2 + cx,  fy w1 / w2 + cy

with ``M`` OpenCV's ``computeTiltProjectionMatrix``: ``R = Ry(tau_y) @ Rx(tau_x)`` with
``Rx(a) = [[1, 0, 0], [0, cos a, sin a], [0, -sin a, cos a]]``,
``Ry(b) = [[cos b, 0, -sin b], [0, 1, 0], [sin b, 0, cos b]]`` and
``M = [[R22, 0, -R02], [0, R22, -R12], [0, 0, 1]] @ R``.

The camera block of the calibration YAML (``doc/interfaces.md`` §3) is the
``camera_calibration_parsers`` layout; :meth:`CameraModel.from_yaml_dict` and
:meth:`CameraModel.to_yaml_dict` read and write it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal, overload

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stellar_cal_ros.core.camera_yaml import (
    DISTORTION_MODEL_SIZES,
    camera_block,
    camera_kwargs,
    is_number,
)
from stellar_cal_ros.errors import ModelError

__all__ = [
    "DISTORTION_MODEL_SIZES",
    "OPENCV_DISTORTION_NAMES",
    "CameraModel",
    "tilt_matrix",
]

FloatArray = NDArray[np.float64]

OPENCV_DISTORTION_NAMES: tuple[str, ...] = (
    "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6",
    "s1", "s2", "s3", "s4", "tau_x", "tau_y",
)  # fmt: skip

# Coefficient counts OpenCV accepts for ``distCoeffs``; shorter vectors are zero-padded to 14.
_ACCEPTED_DISTORTION_SIZES = (4, 5, 8, 12, 14)

# Unproject: Gauss-Newton stops once every residual is below _UNPROJECT_TOL px; a point whose
# residual is still above _UNPROJECT_FAIL px after _UNPROJECT_MAX_ITER iterations is NaN.
_UNPROJECT_TOL = 1e-10
_UNPROJECT_FAIL = 1e-6
_UNPROJECT_MAX_ITER = 30

# Columns of k1 k2 k3 k4 k5 k6 in the parameter vector.
_RADIAL_COLS = [4, 5, 8, 9, 10, 11]

# Number of points projected per block (keeps the temporaries in cache).
_BLOCK = 4096


def tilt_matrix(tau_x: float, tau_y: float) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Return OpenCV's tilted-sensor matrix and its derivatives.

    Same as OpenCV's ``computeTiltProjectionMatrix`` (see the module docstring).

    Parameters
    ----------
    tau_x, tau_y : float
        Sensor tilt angles, rad.

    Returns
    -------
    M : numpy.ndarray, shape (3, 3)
        The matrix applied to the homogeneous distorted normalised point ``(x'', y'', 1)``.
    dM_dtau_x, dM_dtau_y : numpy.ndarray, shape (3, 3)
        Its element-wise derivatives, 1/rad.
    """
    cx_, sx_ = math.cos(tau_x), math.sin(tau_x)
    cy_, sy_ = math.cos(tau_y), math.sin(tau_y)
    rot_x = np.array([[1.0, 0.0, 0.0], [0.0, cx_, sx_], [0.0, -sx_, cx_]])
    d_rot_x = np.array([[0.0, 0.0, 0.0], [0.0, -sx_, cx_], [0.0, -cx_, -sx_]])
    rot_y = np.array([[cy_, 0.0, -sy_], [0.0, 1.0, 0.0], [sy_, 0.0, cy_]])
    d_rot_y = np.array([[-sy_, 0.0, -cy_], [0.0, 0.0, 0.0], [cy_, 0.0, -sy_]])
    rot_xy = rot_y @ rot_x

    def proj_z(r: FloatArray, homogeneous: float) -> FloatArray:
        return np.array(
            [[r[2, 2], 0.0, -r[0, 2]], [0.0, r[2, 2], -r[1, 2]], [0.0, 0.0, homogeneous]]
        )

    matrix = proj_z(rot_xy, 1.0) @ rot_xy
    derivs = []
    for d_rot_xy in (rot_y @ d_rot_x, d_rot_y @ rot_x):
        derivs.append(proj_z(d_rot_xy, 0.0) @ rot_xy + proj_z(rot_xy, 1.0) @ d_rot_xy)
    return matrix, derivs[0], derivs[1]


@dataclass(frozen=True, eq=False)
class CameraModel:
    """Pinhole camera with OpenCV's full distortion model (``cv2.projectPoints`` compatible).

    Instances are immutable; :meth:`with_parameters` and :func:`dataclasses.replace` make
    modified copies.

    Parameters
    ----------
    width, height : int
        Image size, px.
    fx, fy : float
        Focal lengths, px (> 0).
    cx, cy : float
        Principal point, px, in the convention where ``(0, 0)`` is the centre of the top-left
        pixel.
    distortion : array_like, shape (14,)
        Distortion coefficients in OpenCV order (:data:`OPENCV_DISTORTION_NAMES`),
        dimensionless except ``tau_x``, ``tau_y`` (rad). 4, 5, 8 or 12 coefficients are
        accepted and zero-padded, as OpenCV does. Stored as a read-only float64 array.
    name : str
        Camera name (``camera_name`` of the YAML block).

    Attributes
    ----------
    PARAMETER_NAMES : tuple of str
        Names of the 18 entries of :meth:`parameters`, and of the columns of the parameter
        Jacobian of :meth:`project`: ``fx fy cx cy`` then :data:`OPENCV_DISTORTION_NAMES`.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: FloatArray = field(default_factory=lambda: np.zeros(14))
    name: str = "star_tracker"

    PARAMETER_NAMES: ClassVar[tuple[str, ...]] = ("fx", "fy", "cx", "cy") + OPENCV_DISTORTION_NAMES

    def __post_init__(self) -> None:
        for key in ("width", "height"):
            value = getattr(self, key)
            if not is_number(value) or value != int(value) or int(value) <= 0:
                raise ModelError(f"camera {key} must be a positive integer, got {value!r}")
            object.__setattr__(self, key, int(value))
        for key in ("fx", "fy", "cx", "cy"):
            value = getattr(self, key)
            if not is_number(value) or not math.isfinite(float(value)):
                raise ModelError(f"camera {key} must be a finite number, got {value!r}")
            object.__setattr__(self, key, float(value))
        if self.fx <= 0.0 or self.fy <= 0.0:
            raise ModelError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        dist = np.asarray(self.distortion, dtype=np.float64).reshape(-1)
        if dist.size not in _ACCEPTED_DISTORTION_SIZES:
            raise ModelError(
                f"distortion must have one of {_ACCEPTED_DISTORTION_SIZES} coefficients "
                f"(OpenCV order {' '.join(OPENCV_DISTORTION_NAMES)}), got {dist.size}"
            )
        if not np.all(np.isfinite(dist)):
            raise ModelError(f"distortion coefficients must be finite, got {dist.tolist()}")
        full = np.zeros(14)
        full[: dist.size] = dist
        full.setflags(write=False)
        object.__setattr__(self, "distortion", full)
        object.__setattr__(self, "name", str(self.name))
        # Cached tilt matrix and its derivatives (not dataclass fields).
        object.__setattr__(self, "_tilt", tilt_matrix(full[12], full[13]))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, CameraModel):
            return NotImplemented
        keys = ("width", "height", "fx", "fy", "cx", "cy", "name")
        return all(getattr(self, k) == getattr(other, k) for k in keys) and bool(
            np.array_equal(self.distortion, other.distortion)
        )

    __hash__ = None  # type: ignore[assignment]

    # ------------------------------------------------------------------ construction

    @classmethod
    def pinhole(
        cls,
        width: int,
        height: int,
        focal_length_px: float,
        cx: float | None = None,
        cy: float | None = None,
    ) -> CameraModel:
        """Return a distortion-free camera with square pixels.

        Parameters
        ----------
        width, height : int
            Image size, px.
        focal_length_px : float
            ``fx = fy``, px.
        cx, cy : float, optional
            Principal point, px; default the image centre ``(width - 1) / 2``,
            ``(height - 1) / 2``.

        Returns
        -------
        CameraModel
        """
        return cls(
            width=width,
            height=height,
            fx=focal_length_px,
            fy=focal_length_px,
            cx=(width - 1) / 2.0 if cx is None else cx,
            cy=(height - 1) / 2.0 if cy is None else cy,
            distortion=np.zeros(14),
        )

    def parameters(self) -> FloatArray:
        """Return the parameter vector ``fx fy cx cy k1 ... tau_y``.

        Returns
        -------
        numpy.ndarray, shape (18,)
            In the order of :attr:`PARAMETER_NAMES`; px for the first four.
        """
        return np.concatenate([[self.fx, self.fy, self.cx, self.cy], self.distortion])

    def with_parameters(self, p: ArrayLike) -> CameraModel:
        """Return a copy with another parameter vector (same size and name).

        Parameters
        ----------
        p : array_like, shape (18,)
            In the order of :attr:`PARAMETER_NAMES`.

        Returns
        -------
        CameraModel
        """
        p = np.asarray(p, dtype=np.float64)
        if p.shape != (18,):
            raise ModelError(f"camera parameter vector must have shape (18,), got {p.shape}")
        if type(self) is CameraModel and p[0] > 0.0 and p[1] > 0.0 and bool(
            np.all(np.isfinite(p))
        ):
            # Hot path of the filters (a camera per star frame): the values are already
            # validated by the checks above, so skip __post_init__ and reuse the cached tilt
            # matrix when tau_x, tau_y are unchanged.
            new = object.__new__(CameraModel)
            dist = p[4:].copy()
            dist.setflags(write=False)
            for key, value in (("width", self.width), ("height", self.height),
                               ("fx", float(p[0])), ("fy", float(p[1])), ("cx", float(p[2])),
                               ("cy", float(p[3])), ("distortion", dist), ("name", self.name)):
                object.__setattr__(new, key, value)
            same_tilt = dist[12] == self.distortion[12] and dist[13] == self.distortion[13]
            tilt = self._tilt if same_tilt else tilt_matrix(dist[12], dist[13])  # type: ignore[attr-defined]
            object.__setattr__(new, "_tilt", tilt)
            return new
        return CameraModel(
            width=self.width,
            height=self.height,
            fx=float(p[0]),
            fy=float(p[1]),
            cx=float(p[2]),
            cy=float(p[3]),
            distortion=p[4:].copy(),
            name=self.name,
        )

    def distortion_model(self) -> str:
        """Return the smallest ``camera_calibration_parsers`` model holding every coefficient.

        Returns
        -------
        str
            ``"plumb_bob"`` (k1 k2 p1 p2 k3), ``"rational_polynomial"`` (+ k4 k5 k6) or
            ``"opencv_full"`` (+ s1..s4, tau_x, tau_y).
        """
        nonzero = np.flatnonzero(self.distortion)
        last = int(nonzero[-1]) + 1 if nonzero.size else 0
        for model, size in DISTORTION_MODEL_SIZES.items():
            if last <= size:
                return model
        raise AssertionError("unreachable: 14 coefficients at most")  # pragma: no cover

    # ------------------------------------------------------------------ YAML

    @classmethod
    def from_yaml_dict(cls, camera_block: Mapping[str, Any]) -> CameraModel:
        """Build a camera from the ``camera`` block of a calibration YAML.

        The layout is ``camera_calibration_parsers``' (``doc/interfaces.md`` §3). Keys
        not listed there (``rectification_matrix``, ``projection_matrix``, ...) are ignored.

        Parameters
        ----------
        camera_block : mapping
            The parsed block (``image_width``, ``image_height``, ``camera_name`` (optional),
            ``camera_matrix``, ``distortion_model``, ``distortion_coefficients``).

        Returns
        -------
        CameraModel

        Raises
        ------
        stellar_cal_ros.errors.ModelError
            On a missing key, a matrix of the wrong size, non-numeric or non-finite values,
            a camera matrix that is not ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` (e.g. a
            nonzero skew), an unknown distortion model, or a coefficient count that does not
            match the model.
        """
        return cls(**camera_kwargs(camera_block))

    def to_yaml_dict(self) -> dict[str, Any]:
        """Return the ``camera`` block of a calibration YAML (plain Python types).

        The distortion model is :meth:`distortion_model` and the coefficient count is that
        model's. ``rectification_matrix`` (identity) and ``projection_matrix`` (``[K | 0]``)
        are included so the block is a complete ``camera_calibration_parsers`` file.

        Returns
        -------
        dict
            ``image_width``, ``image_height``, ``camera_name``, ``camera_matrix``,
            ``distortion_model``, ``distortion_coefficients``, ``rectification_matrix``,
            ``projection_matrix``.
        """
        return camera_block(self)

    # ------------------------------------------------------------------ projection core

    def _distort(
        self, x: FloatArray, y: FloatArray, jac: int, want: NDArray[np.bool_] | None = None
    ) -> tuple[FloatArray, FloatArray | None, FloatArray | None]:
        """Map normalised pinhole points to pixels, in cache-sized blocks.

        Parameters
        ----------
        x, y : numpy.ndarray, shape (N,)
            Normalised coordinates ``X/Z``, ``Y/Z``.
        jac : int
            0: no Jacobian; 1: Jacobian w.r.t. ``(x, y)``; 2: also w.r.t. the parameters.
        want : numpy.ndarray of bool, shape (18,), optional
            Parameter Jacobian columns to compute (the others stay zero); default all.

        Returns
        -------
        uv : numpy.ndarray, shape (N, 2)
            Pixels, px.
        J_xy : numpy.ndarray, shape (N, 2, 2) or None
            ``d(u, v)/d(x, y)``, a transposed view of a (2, 2, N) buffer.
        J_p : numpy.ndarray, shape (N, 2, 18) or None
            ``d(u, v)/d(parameters)``, a transposed view of a (2, 18, N) buffer.
        """
        n = x.shape[0]
        uv = np.empty((n, 2))
        # Component-major buffers: every write is contiguous. Zero-initialised because the
        # block kernel writes only the entries that can be nonzero.
        Jt_xy = np.empty((2, 2, n)) if jac >= 1 else None
        Jt = np.zeros((2, 18, n)) if jac >= 2 else None
        # Blocks keep the ~50 temporaries in cache; 4096 points was fastest on x86-64.
        for a in range(0, max(n, 1), _BLOCK):
            b = min(a + _BLOCK, n)
            self._distort_block(
                x[a:b],
                y[a:b],
                uv[a:b],
                None if Jt_xy is None else Jt_xy[:, :, a:b],
                None if Jt is None else Jt[:, :, a:b],
                want,
            )
        return (
            uv,
            None if Jt_xy is None else Jt_xy.transpose(2, 0, 1),
            None if Jt is None else Jt.transpose(2, 0, 1),
        )

    def _distort_block(
        self,
        x: FloatArray,
        y: FloatArray,
        uv: FloatArray,
        Jt_xy: FloatArray | None,
        Jt: FloatArray | None,
        want: NDArray[np.bool_] | None = None,
    ) -> None:
        """Kernel of :meth:`_distort` on one block of points, writing into the given views.

        The rational denominator, the prism terms and the tilt stage are skipped when their
        coefficients are zero (their parameter Jacobian columns are still computed).

        Parameters
        ----------
        x, y : numpy.ndarray, shape (n,)
            Normalised coordinates.
        uv : numpy.ndarray, shape (n, 2)
            Output pixels.
        Jt_xy : numpy.ndarray, shape (2, 2, n), or None
            Output ``d(u, v)/d(x, y)``, component-major; None to skip.
        Jt : numpy.ndarray, shape (2, 18, n), or None
            Output ``d(u, v)/d(parameters)``, component-major, zero on entry; None to skip.
        want : numpy.ndarray of bool, shape (18,), or None
            Columns of ``Jt`` to compute (thin prism, k3-k6 and tilt are skipped when not
            wanted; the others are cheap and always filled); None: all.
        """
        k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4, tau_x, tau_y = self.distortion.tolist()
        rational = k4 != 0.0 or k5 != 0.0 or k6 != 0.0
        prism = s1 != 0.0 or s2 != 0.0 or s3 != 0.0 or s4 != 0.0
        tilted = tau_x != 0.0 or tau_y != 0.0
        fx, fy = self.fx, self.fy
        n = x.shape[0]
        xx = x * x
        yy = y * y
        xy2 = 2.0 * x * y
        r2 = xx + yy
        # Stage 1: radial factor g = num / den.
        num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        if rational:
            iden = 1.0 / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)))
            g = num * iden
        else:
            iden = 1.0
            g = num
        # Stage 2: tangential and thin prism.
        ex = r2 + 2.0 * xx  # d x''/d p2
        ey = r2 + 2.0 * yy  # d y''/d p1
        xd0 = x * g + p1 * xy2 + p2 * ex
        yd0 = y * g + p1 * ey + p2 * xy2
        if prism:
            r4 = r2 * r2
            xd0 = xd0 + r2 * (s1 + s2 * r2)
            yd0 = yd0 + r2 * (s3 + s4 * r2)
        # Stage 3: tilted image plane, then camera matrix.
        M, dM_dtx, dM_dty = self._tilt  # type: ignore[attr-defined]
        if tilted:
            iw = 1.0 / (M[2, 0] * xd0 + M[2, 1] * yd0 + M[2, 2])
            xd = (M[0, 0] * xd0 + M[0, 1] * yd0 + M[0, 2]) * iw
            yd = (M[1, 0] * xd0 + M[1, 1] * yd0 + M[1, 2]) * iw
        else:
            iw = 1.0
            xd = xd0
            yd = yd0
        uv[:, 0] = fx * xd + self.cx
        uv[:, 1] = fy * yd + self.cy
        if Jt_xy is None:
            return

        # T = d(u, v) / d(x'', y''), from the tilt stage and the focal lengths.
        if tilted:
            fiw = fx * iw
            giw = fy * iw
            T00 = fiw * (M[0, 0] - xd * M[2, 0])
            T01 = fiw * (M[0, 1] - xd * M[2, 1])
            T10 = giw * (M[1, 0] - yd * M[2, 0])
            T11 = giw * (M[1, 1] - yd * M[2, 1])
        else:
            fiw, giw = fx, fy
        # D = d(x'', y'') / d(x, y).
        dnum = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
        if rational:
            dg = (dnum - g * (k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2))) * iden
        else:
            dg = dnum
        ax = x * dg
        ay = y * dg
        if prism:
            ax = ax + (s1 + 2.0 * s2 * r2)
            ay = ay + (s3 + 2.0 * s4 * r2)
        ax = ax + ax
        ay = ay + ay
        cross = p1 * x + p2 * y
        cross = cross + cross
        D00 = g + x * ax + 2.0 * p1 * y + 6.0 * p2 * x
        D01 = y * ax + cross
        D10 = x * ay + cross
        D11 = g + y * ay + 6.0 * p1 * y + 2.0 * p2 * x
        if tilted:
            Jt_xy[0, 0] = T00 * D00 + T01 * D10
            Jt_xy[0, 1] = T00 * D01 + T01 * D11
            Jt_xy[1, 0] = T10 * D00 + T11 * D10
            Jt_xy[1, 1] = T10 * D01 + T11 * D11
        else:
            np.multiply(fx, D00, out=Jt_xy[0, 0])
            np.multiply(fx, D01, out=Jt_xy[0, 1])
            np.multiply(fy, D10, out=Jt_xy[1, 0])
            np.multiply(fy, D11, out=Jt_xy[1, 1])
        if Jt is None:
            return

        Jt[0, 0] = xd
        Jt[1, 1] = yd
        Jt[0, 2] = 1.0
        Jt[1, 3] = 1.0
        if not prism:
            r4 = r2 * r2
        # only k1 k2 of the radial terms wanted: the first two rows of powers
        short = want is not None and not want[8:12].any()
        powers = np.empty((2 if short else 6, n))
        powers[0] = r2
        powers[1] = r4
        if not short:
            np.multiply(r4, r2, out=powers[2])
        if want is None or want[12:16].any():
            # thin prism s1 s2 (x'' only) and s3 s4 (y'' only): (r2, r4)
            if tilted:
                np.multiply(T00, powers[:2], out=Jt[0, 12:14])
                np.multiply(T10, powers[:2], out=Jt[1, 12:14])
                np.multiply(T01, powers[:2], out=Jt[0, 14:16])
                np.multiply(T11, powers[:2], out=Jt[1, 14:16])
            else:
                np.multiply(fx, powers[:2], out=Jt[0, 12:14])
                np.multiply(fy, powers[:2], out=Jt[1, 14:16])
        # Radial k1 k2 k3 k4 k5 k6 move (x'', y'') along (x, y) h, h = d g / d k.
        if short:
            if rational:
                powers *= iden
        elif rational:
            powers[3:] = powers[:3] * (-g * iden)
            powers[:3] *= iden
        else:
            powers[3:] = powers[:3] * -g
        radial_cols: Any = slice(4, 6) if short else _RADIAL_COLS  # k1 k2 are columns 4, 5
        # Tangential p1, p2: d(x'', y'')/dp1 = (2xy, ey), d(x'', y'')/dp2 = (ex, 2xy).
        if tilted:
            Jt[0, radial_cols] = (T00 * x + T01 * y) * powers
            Jt[1, radial_cols] = (T10 * x + T11 * y) * powers
            Jt[0, 6] = T00 * xy2 + T01 * ey
            Jt[1, 6] = T10 * xy2 + T11 * ey
            Jt[0, 7] = T00 * ex + T01 * xy2
            Jt[1, 7] = T10 * ex + T11 * xy2
        else:
            Jt[0, radial_cols] = (fx * x) * powers
            Jt[1, radial_cols] = (fy * y) * powers
            np.multiply(fx, xy2, out=Jt[0, 6])
            np.multiply(fy, ey, out=Jt[1, 6])
            np.multiply(fx, ex, out=Jt[0, 7])
            np.multiply(fy, xy2, out=Jt[1, 7])
        # Tilt angles act after the distortion: d(w0/w2, w1/w2)/dtau with w = M (x'', y'', 1).
        for col, dM in ((16, dM_dtx), (17, dM_dty)):
            if want is not None and not want[col]:
                continue
            dw2 = dM[2, 0] * xd0 + dM[2, 1] * yd0 + dM[2, 2]
            Jt[0, col] = fiw * (dM[0, 0] * xd0 + dM[0, 1] * yd0 + dM[0, 2] - xd * dw2)
            Jt[1, col] = giw * (dM[1, 0] * xd0 + dM[1, 1] * yd0 + dM[1, 2] - yd * dw2)

    # ------------------------------------------------------------------ public projection

    @overload
    def normalized_to_pixel(
        self, xy: ArrayLike, *, jacobians: Literal[False] = ...
    ) -> FloatArray: ...

    @overload
    def normalized_to_pixel(
        self, xy: ArrayLike, *, jacobians: Literal[True]
    ) -> tuple[FloatArray, FloatArray, FloatArray]: ...

    def normalized_to_pixel(
        self, xy: ArrayLike, *, jacobians: bool = False
    ) -> FloatArray | tuple[FloatArray, FloatArray, FloatArray]:
        """Apply distortion, tilt and camera matrix to normalised pinhole points.

        Parameters
        ----------
        xy : array_like, shape (N, 2)
            Normalised points ``(X/Z, Y/Z)`` (dimensionless).
        jacobians : bool
            Also return the Jacobians.

        Returns
        -------
        uv : numpy.ndarray, shape (N, 2)
            Pixel coordinates, px.
        J_xy : numpy.ndarray, shape (N, 2, 2)
            ``d(u, v) / d(x, y)``, px. Only with ``jacobians=True``.
        J_parameters : numpy.ndarray, shape (N, 2, 18)
            ``d(u, v) / d(parameters)``, columns as :attr:`PARAMETER_NAMES`. Only with
            ``jacobians=True``.
        """
        xy_arr = np.asarray(xy, dtype=np.float64)
        if xy_arr.ndim != 2 or xy_arr.shape[1] != 2:
            raise ValueError(f"xy must have shape (N, 2), got {xy_arr.shape}")
        uv, J_xy, J_p = self._distort(xy_arr[:, 0], xy_arr[:, 1], 2 if jacobians else 0)
        if jacobians:
            assert J_xy is not None and J_p is not None
            return uv, J_xy, J_p
        return uv

    @overload
    def project(self, directions: ArrayLike, *, jacobians: Literal[False] = ...,
                parameters: NDArray[np.bool_] | None = ...) -> FloatArray: ...

    @overload
    def project(
        self, directions: ArrayLike, *, jacobians: Literal[True],
        parameters: NDArray[np.bool_] | None = ...,
    ) -> tuple[FloatArray, FloatArray, FloatArray]: ...

    def project(
        self, directions: ArrayLike, *, jacobians: bool = False,
        parameters: NDArray[np.bool_] | None = None,
    ) -> FloatArray | tuple[FloatArray, FloatArray, FloatArray]:
        """Project camera-frame directions to pixels, as ``cv2.projectPoints`` does.

        Parameters
        ----------
        directions : array_like, shape (N, 3)
            Directions (or points) in the camera optical frame; need not be unit vectors.
            Rows with ``z <= 0`` (behind the camera) give NaN.
        jacobians : bool
            Also return the analytic Jacobians.
        parameters : numpy.ndarray of bool, shape (18,), optional
            The columns of ``J_parameters`` needed (e.g. those an estimator uses); columns
            not needed may be left zero, which saves time.  Default: all.

        Returns
        -------
        uv : numpy.ndarray, shape (N, 2)
            Pixel coordinates ``(u, v)``, px.
        J_direction : numpy.ndarray, shape (N, 2, 3)
            ``d(u, v) / d(directions)``, px per unit of the input. Only with
            ``jacobians=True``.
        J_parameters : numpy.ndarray, shape (N, 2, 18)
            ``d(u, v) / d(parameters)``, columns as :attr:`PARAMETER_NAMES` (px/px for
            ``fx fy cx cy``, px per unit coefficient, px/rad for ``tau_x tau_y``). Only with
            ``jacobians=True``.

        Notes
        -----
        The Jacobians are returned as transposed views of component-major buffers (the fastest
        layout to fill); use :func:`numpy.ascontiguousarray` if a C-contiguous array is needed.
        """
        uv, J_d, J_p = self._project(directions, 2 if jacobians else 0, parameters)
        if not jacobians:
            return uv
        assert J_d is not None and J_p is not None
        return uv, J_d, J_p

    def project_direction(self, directions: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """:meth:`project` with ``d(u, v) / d(directions)`` only, no parameter Jacobian.

        The same floats as ``project(directions, jacobians=True)[:2]`` (the parameter
        Jacobian is computed after, and apart from, the pixels and the direction Jacobian),
        without the cost of its 18 columns: for fits of the attitude alone (a frame's
        Gauss-Newton refits, :func:`~stellar_cal_ros.core.attitude.refine_frame_rotation`).

        Returns
        -------
        uv : numpy.ndarray, shape (N, 2)
            Pixel coordinates, px.
        J_direction : numpy.ndarray, shape (N, 2, 3)
            ``d(u, v) / d(directions)``, as :meth:`project`'s.
        """
        uv, J_d, _ = self._project(directions, 1, None)
        assert J_d is not None
        return uv, J_d

    def _project(
        self, directions: ArrayLike, jac: int, parameters: NDArray[np.bool_] | None
    ) -> tuple[FloatArray, FloatArray | None, FloatArray | None]:
        """:meth:`project`'s work: ``jac`` 0 pixels, 1 also ``J_direction``, 2 also ``J_p``."""
        d = np.asarray(directions, dtype=np.float64)
        if d.ndim != 2 or d.shape[1] != 3:
            raise ValueError(f"directions must have shape (N, 3), got {d.shape}")
        z = d[:, 2]
        if not (z > 0.0).all():
            z = np.where(z > 0.0, z, np.nan)
        iz = 1.0 / z
        x = d[:, 0] * iz
        y = d[:, 1] * iz
        uv, J_xy, J_p = self._distort(x, y, jac, parameters)
        if not jac:
            return uv, None, None
        assert J_xy is not None
        # d(x, y) / d(X, Y, Z) = [[1/Z, 0, -x/Z], [0, 1/Z, -y/Z]]; built component-major.
        Jt_xy = J_xy.transpose(1, 2, 0)  # (2, 2, N), the contiguous buffer
        Jt_d = np.empty((2, 3, d.shape[0]))
        np.multiply(Jt_xy[:, 0], iz, out=Jt_d[:, 0])
        np.multiply(Jt_xy[:, 1], iz, out=Jt_d[:, 1])
        Jt_d[:, 2] = -(Jt_d[:, 0] * x + Jt_d[:, 1] * y)
        return uv, Jt_d.transpose(2, 0, 1), J_p

    def pixel_to_normalized(self, uv: ArrayLike) -> FloatArray:
        """Invert :meth:`normalized_to_pixel` by Gauss-Newton with the analytic Jacobian.

        Starts from the distortion-free inverse and iterates until every residual is below
        1e-10 px (typically 3-4 iterations for a star tracker).

        Parameters
        ----------
        uv : array_like, shape (N, 2)
            Pixel coordinates, px.

        Returns
        -------
        numpy.ndarray, shape (N, 2)
            Normalised points ``(x, y)``. Rows that do not converge to 1e-6 px within 30
            iterations (far outside the domain where the distortion is invertible), or with
            non-finite input, are NaN.
        """
        uv_arr = np.asarray(uv, dtype=np.float64)
        if uv_arr.ndim != 2 or uv_arr.shape[1] != 2:
            raise ValueError(f"uv must have shape (N, 2), got {uv_arr.shape}")
        x = (uv_arr[:, 0] - self.cx) / self.fx
        y = (uv_arr[:, 1] - self.cy) / self.fy
        for _ in range(_UNPROJECT_MAX_ITER):
            pred, J, _ = self._distort(x, y, 1)
            assert J is not None
            r = uv_arr - pred
            if not np.any(np.abs(r) > _UNPROJECT_TOL):  # NaN rows count as done
                break
            det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
            x = x + (J[:, 1, 1] * r[:, 0] - J[:, 0, 1] * r[:, 1]) / det
            y = y + (J[:, 0, 0] * r[:, 1] - J[:, 1, 0] * r[:, 0]) / det
        else:
            r = uv_arr - self._distort(x, y, 0)[0]
        failed = ~(np.max(np.abs(r), axis=1) <= _UNPROJECT_FAIL)
        xy = np.stack([x, y], axis=1)
        xy[failed] = np.nan
        return xy

    def unproject(self, uv: ArrayLike) -> FloatArray:
        """Return the unit camera-frame directions that project to the given pixels.

        Parameters
        ----------
        uv : array_like, shape (N, 2)
            Pixel coordinates, px.

        Returns
        -------
        numpy.ndarray, shape (N, 3)
            Unit vectors with ``z > 0`` such that ``project(unproject(uv)) == uv`` (to below
            1e-9 px). NaN rows where :meth:`pixel_to_normalized` does not converge.
        """
        xy = self.pixel_to_normalized(uv)
        d = np.empty((xy.shape[0], 3))
        d[:, :2] = xy
        d[:, 2] = 1.0
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return d

    def in_image(self, uv: ArrayLike, margin: float = 0.0) -> NDArray[np.bool_]:
        """Return which pixel coordinates fall on the sensor.

        With ``(0, 0)`` the centre of the top-left pixel, the sensor covers
        ``-0.5 <= u < width - 0.5`` and ``-0.5 <= v < height - 0.5``.

        Parameters
        ----------
        uv : array_like, shape (N, 2)
            Pixel coordinates, px.
        margin : float
            Border, px, excluded on every side (negative values enlarge the area).

        Returns
        -------
        numpy.ndarray of bool, shape (N,)
            True inside; False outside or for NaN.
        """
        uv_arr = np.asarray(uv, dtype=np.float64)
        if uv_arr.ndim != 2 or uv_arr.shape[1] != 2:
            raise ValueError(f"uv must have shape (N, 2), got {uv_arr.shape}")
        u = uv_arr[:, 0]
        v = uv_arr[:, 1]
        lo = -0.5 + margin
        return (
            (u >= lo)
            & (u < self.width - 0.5 - margin)
            & (v >= lo)
            & (v < self.height - 0.5 - margin)
        )
