"""The filters' compiled (numba) kernels: star projection and small rotations.

The per-frame star step of the filters
(:func:`stellar_cal_ros.methods.star_chain.predict_chain`) predicts every star of a frame
in one compiled call built from these pieces.  They compute what the numpy code computes —
:meth:`stellar_cal_ros.core.camera.CameraModel.project` for the projection,
:mod:`stellar_cal_ros.core.rotation` for ``Exp`` and the right Jacobian (the same Python
functions, compiled as they are) — with the same formulas, in scalar loops instead of array
operations.  The distortion kernel therefore repeats the formulas of
``CameraModel._distort_block`` (scalar instead of vectorized): the numpy one stays the
reference (it serves every caller and runs without numba), this one serves the filters'
per-frame step; a change to one is a change to both, and ``test/test_compiled_step.py``
fails until both agree.  Results agree to rounding, not bit for bit (the order of a few
additions and fused multiply-adds differs).

numba is optional: :data:`HAVE_NUMBA` is False when it cannot be imported, and the filters
then predict through the effects' Python methods (same estimates).

All kernels are compiled once per machine and kernel version (``cache=True`` through this
module's :func:`njit`): numba's cache is kept in one directory of the user's cache
(:func:`kernel_cache_dir`), named by a hash of every source file that holds compiled code
(:data:`KERNEL_SOURCES`), not in each checkout's ``__pycache__``.  A fresh clone, a new
worktree or another branch with the same kernel sources loads what any of them compiled
(numba's own cache is per directory: every clone compiled the kernels again, ≈ 65 CPU-s),
and a change to any of those files — a helper's as well as a caller's — is a new version,
compiled once.  ``STELLAR_CAL_KERNEL_CACHE`` names another directory (``tree``: numba's
``__pycache__``); a ``NUMBA_CACHE_DIR`` or ``NUMBA_CACHE_LOCATOR_CLASSES`` of the user's is
obeyed as numba obeys it.

Old versions are pruned (:func:`kernel_cache_used`): a process that uses the kernel cache
stamps its version's directory (:data:`KERNEL_CACHE_STAMP`) and removes the directories of
other versions beside it not used for :data:`KERNEL_CACHE_KEEP_DAYS` days; the current
version's never.
"""

from __future__ import annotations

import functools
import hashlib
import math
import os
import re
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from stellar_cal_ros.core.rotation import _jacobian_single, _so3_exp_single

#: the package's files that hold compiled code: the kernels' modules and the Python functions
#: they compile (``rotation``'s, ``imu_prefix``'s, ``covariance``'s); their contents name the
#: kernel cache
KERNEL_SOURCES = ("core/jit.py", "core/rotation.py", "core/imu_prefix.py", "core/float_text.py",
                  "methods/star_chain.py", "methods/frame_step.py", "core/covariance.py")
#: environment: the kernel cache's directory (``tree``: numba's per-checkout ``__pycache__``)
KERNEL_CACHE_ENV = "STELLAR_CAL_KERNEL_CACHE"
_PACKAGE = Path(__file__).resolve().parents[1]
#: another kernel version's cache not used for this many days is removed (never the current)
KERNEL_CACHE_KEEP_DAYS = 30.0
#: a file in each version's directory; its modification time: when a process last used it
KERNEL_CACHE_STAMP = "last-used"
_VERSION_DIR = re.compile(r"kernels-[0-9a-f]{16}")


@functools.cache
def kernel_version() -> str:
    """Hash of the contents of :data:`KERNEL_SOURCES` (the kernels' version, 16 hex digits)."""
    h = hashlib.sha256()
    for rel in KERNEL_SOURCES:
        h.update(rel.encode() + b"\0" + (_PACKAGE / rel).read_bytes() + b"\0")
    return h.hexdigest()[:16]


def kernel_cache_dir() -> Path | None:
    """The directory that holds this kernel version's compiled code; None: numba's own place.

    ``$STELLAR_CAL_KERNEL_CACHE`` or the user's cache directory (``~/.cache/stellar_cal_ros``
    on Linux), then ``kernels-<version>``; None when the variable says ``tree`` or the user
    set numba's own ``NUMBA_CACHE_DIR``.
    """
    root = os.environ.get(KERNEL_CACHE_ENV, "").strip()
    if root == "tree" or os.environ.get("NUMBA_CACHE_DIR"):
        return None
    if not root:
        from numba.misc.appdirs import AppDirs

        root = AppDirs(appname="stellar_cal_ros", appauthor=False).user_cache_dir
    return Path(root) / f"kernels-{kernel_version()}"


def prune_kernel_caches(current: Path, keep_days: float = KERNEL_CACHE_KEEP_DAYS,
                        now: float | None = None) -> list[Path]:
    """Stamp ``current`` used now; remove the other versions' directories beside it unused.

    A directory ``kernels-<16 hex digits>`` beside ``current`` (not ``current``, nothing of
    another name) whose :data:`KERNEL_CACHE_STAMP` -- or, before stamps, the directory
    itself -- was last modified more than ``keep_days`` days before ``now`` is removed.
    Returns the directories removed; a file-system error leaves that directory as it is.
    """
    now = time.time() if now is None else now
    try:
        (current / KERNEL_CACHE_STAMP).touch()
        others = [p for p in current.parent.iterdir()
                  if p.name != current.name and _VERSION_DIR.fullmatch(p.name) and p.is_dir()]
    except OSError:
        return []
    removed = []
    for old in others:
        stamp = old / KERNEL_CACHE_STAMP
        try:
            used = (stamp if stamp.exists() else old).stat().st_mtime
            if now - used <= keep_days * 86400.0:
                continue
            gone = old.with_name(f".{old.name}.pruned-{os.getpid()}")
            old.rename(gone)  # (a process that starts using it now finds it absent)
        except OSError:
            continue
        shutil.rmtree(gone, ignore_errors=True)
        removed.append(old)
    return removed


@functools.cache
def kernel_cache_used(current: Path) -> list[Path]:
    """:func:`prune_kernel_caches` once per process and directory (numba's first cached kernel)."""
    return prune_kernel_caches(current)


def _import_numba():
    """The ``njit`` of numba and ``numba.core.caching``, imported without reading ``coverage``.

    numba's import reads the ``coverage`` package when it is installed, to report compiled
    lines to a coverage run (``numba.misc.coverage_support``): ≈ 0.1 CPU-s of every
    process that compiles or loads a kernel (a replay's 2.5 %, 2026-11-29).  With no
    coverage run in this process (``coverage`` not imported before numba), numba's import
    finds it absent; it stays importable after (a coverage run started later in the
    process does not see compiled lines, as without ``coverage`` installed).
    """
    blocked = "coverage" not in sys.modules
    if blocked:
        sys.modules["coverage"] = None  # type: ignore[assignment]  # (import: ImportError)
    try:
        from numba import njit as numba_njit
        from numba.core import caching
    finally:
        if blocked and "coverage" in sys.modules and sys.modules["coverage"] is None:
            del sys.modules["coverage"]
    return numba_njit, caching


try:  # optional: without it the filters use the numpy path
    _numba_njit, _caching = _import_numba()
except ImportError:  # pragma: no cover - exercised only without numba
    HAVE_NUMBA = False

    def njit(*args, **kwargs):  # noqa: D103 - stand-in decorator: the Python function
        if args and callable(args[0]):
            return args[0]
        return lambda f: f
else:
    HAVE_NUMBA = True

    class _KernelLocator(_caching._SourceFileBackedLocatorMixin, _caching._CacheLocator):
        """numba's cache of a package kernel in :func:`kernel_cache_dir`, stamped by its version."""

        def __init__(self, py_func, py_file):
            self._py_file = py_file
            self._lineno = py_func.__code__.co_firstlineno
            self._cache_path = str(kernel_cache_dir())

        def get_cache_path(self):  # noqa: D102 - numba's locator interface
            return self._cache_path

        def ensure_cache_path(self):  # noqa: D102 - numba's; then stamped, others pruned
            super().ensure_cache_path()
            kernel_cache_used(Path(self._cache_path))

        def get_source_stamp(self):  # noqa: D102 - every kernel source, not the one file
            return kernel_version()

        @classmethod
        def from_function(cls, py_func, py_file):  # noqa: D102 - None: numba's locators
            try:
                ours = Path(py_file).resolve().is_relative_to(_PACKAGE)
            except OSError:
                return None
            if not ours or kernel_cache_dir() is None:
                return None
            return super().from_function(py_func, py_file)  # None when it cannot be written

    class _KernelCacheImpl(_caching.CompileResultCacheImpl):
        _locator_classes = [_KernelLocator, *_caching.CompileResultCacheImpl._locator_classes]

    class _KernelCache(_caching.FunctionCache):
        _impl_class = _KernelCacheImpl

        def load_overload(self, sig, target_context):  # noqa: D102 - numba's; a miss said
            cres = super().load_overload(sig, target_context)
            if cres is None:  # numba compiles it now (progress.first_compile: said once)
                from stellar_cal_ros.progress import first_compile

                first_compile()
            return cres

    def njit(*args, **kwargs):
        """The ``njit`` of numba; ``cache=True``: the code kept in the kernel cache (module doc)."""
        if not kwargs.pop("cache", False):
            return _numba_njit(*args, **kwargs)

        def cached(dispatcher):
            if hasattr(dispatcher, "enable_caching"):  # (NUMBA_DISABLE_JIT: the function)
                dispatcher._cache = _KernelCache(dispatcher.py_func)
            return dispatcher

        if args and callable(args[0]):
            return cached(_numba_njit(*args, **kwargs))
        decorator = _numba_njit(*args, **kwargs)
        return lambda f: cached(decorator(f))

FloatArray = np.ndarray

#: ``Exp(φ)`` (3, 3) of one rotation vector (compiled; :func:`.rotation.so3_exp`)
so3_exp1 = njit(cache=True)(_so3_exp_single)
#: ``I + sign·b [φ]× + c [φ]×²`` (compiled; ``sign`` −1: the right Jacobian)
jacobian1 = njit(cache=True)(_jacobian_single)


@njit(cache=True)
def mat3_mul(a: FloatArray, b: FloatArray) -> FloatArray:
    """``a @ b`` of two (3, 3) matrices."""
    out = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            out[i, j] = a[i, 0] * b[0, j] + a[i, 1] * b[1, j] + a[i, 2] * b[2, j]
    return out


@njit(cache=True)
def skew3(v: FloatArray) -> FloatArray:
    """``[v]×`` (3, 3) of a 3-vector."""
    S = np.zeros((3, 3))
    S[0, 1], S[0, 2] = -v[2], v[1]
    S[1, 0], S[1, 2] = v[2], -v[0]
    S[2, 0], S[2, 1] = -v[1], v[0]
    return S


@njit(cache=True)
def _proj_z(r: FloatArray, homogeneous: float) -> FloatArray:
    return np.array([[r[2, 2], 0.0, -r[0, 2]], [0.0, r[2, 2], -r[1, 2]],
                     [0.0, 0.0, homogeneous]])


@njit(cache=True)
def tilt_kernel(tau_x: float, tau_y: float) -> FloatArray:
    """``(M, dM/dtau_x, dM/dtau_y)`` stacked (3, 3, 3), as :func:`.camera.tilt_matrix`."""
    cx_, sx_ = math.cos(tau_x), math.sin(tau_x)
    cy_, sy_ = math.cos(tau_y), math.sin(tau_y)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cx_, sx_], [0.0, -sx_, cx_]])
    drx = np.array([[0.0, 0.0, 0.0], [0.0, -sx_, cx_], [0.0, -cx_, -sx_]])
    ry = np.array([[cy_, 0.0, -sy_], [0.0, 1.0, 0.0], [sy_, 0.0, cy_]])
    dry = np.array([[-sy_, 0.0, -cy_], [0.0, 0.0, 0.0], [cy_, 0.0, -sy_]])
    rxy = mat3_mul(ry, rx)
    out = np.empty((3, 3, 3))
    out[0] = mat3_mul(_proj_z(rxy, 1.0), rxy)
    for k in range(2):
        d = mat3_mul(ry, drx) if k == 0 else mat3_mul(dry, rx)
        out[k + 1] = mat3_mul(_proj_z(d, 0.0), rxy) + mat3_mul(_proj_z(rxy, 1.0), d)
    return out


@njit(cache=True, error_model="numpy")
def distort_points(x: FloatArray, y: FloatArray, p: FloatArray, tilt: FloatArray, jac: int,
                   uv: FloatArray, J_xy: FloatArray, J_p: FloatArray) -> None:
    """Distortion, tilt and camera matrix of normalised points, with Jacobians.

    Parameters
    ----------
    x, y : numpy.ndarray, shape (N,)
        Normalised coordinates ``X/Z``, ``Y/Z``.
    p : numpy.ndarray, shape (18,)
        Camera parameters (:attr:`CameraModel.PARAMETER_NAMES`).
    tilt : numpy.ndarray, shape (3, 3, 3)
        :func:`tilt_kernel` of ``p[16], p[17]``.
    jac : int
        0: pixels only; 1: also ``J_xy``; 2: also ``J_p``.
    uv, J_xy, J_p : numpy.ndarray, shapes (N, 2), (N, 2, 2), (N, 2, 18)
        Outputs (``J_xy``, ``J_p`` unused below their ``jac`` level; every entry of
        ``J_p`` is written).

    The rational denominator, the prism terms and the tilt stage are skipped when their
    coefficients are zero (their Jacobian columns are still computed).
    """
    fx, fy, cx, cy = p[0], p[1], p[2], p[3]
    k1, k2, p1, p2, k3, k4, k5, k6 = p[4], p[5], p[6], p[7], p[8], p[9], p[10], p[11]
    s1, s2, s3, s4 = p[12], p[13], p[14], p[15]
    rational = k4 != 0.0 or k5 != 0.0 or k6 != 0.0
    prism = s1 != 0.0 or s2 != 0.0 or s3 != 0.0 or s4 != 0.0
    tilted = p[16] != 0.0 or p[17] != 0.0
    M = tilt[0]
    for i in range(x.shape[0]):
        xi, yi = x[i], y[i]
        xx = xi * xi
        yy = yi * yi
        xy2 = 2.0 * xi * yi
        r2 = xx + yy
        r4 = r2 * r2
        # radial factor g = num / den
        num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        iden = 1.0
        g = num
        if rational:
            iden = 1.0 / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6)))
            g = num * iden
        # tangential and thin prism
        ex = r2 + 2.0 * xx  # d x''/d p2
        ey = r2 + 2.0 * yy  # d y''/d p1
        xd0 = xi * g + p1 * xy2 + p2 * ex
        yd0 = yi * g + p1 * ey + p2 * xy2
        if prism:
            xd0 = xd0 + r2 * (s1 + s2 * r2)
            yd0 = yd0 + r2 * (s3 + s4 * r2)
        # tilted image plane, then camera matrix
        iw = 1.0
        xd, yd = xd0, yd0
        if tilted:
            iw = 1.0 / (M[2, 0] * xd0 + M[2, 1] * yd0 + M[2, 2])
            xd = (M[0, 0] * xd0 + M[0, 1] * yd0 + M[0, 2]) * iw
            yd = (M[1, 0] * xd0 + M[1, 1] * yd0 + M[1, 2]) * iw
        uv[i, 0] = fx * xd + cx
        uv[i, 1] = fy * yd + cy
        if jac == 0:
            continue
        # T = d(u, v) / d(x'', y''), from the tilt stage and the focal lengths
        fiw, giw = fx * iw, fy * iw
        T00, T01, T10, T11 = fx, 0.0, 0.0, fy
        if tilted:
            T00 = fiw * (M[0, 0] - xd * M[2, 0])
            T01 = fiw * (M[0, 1] - xd * M[2, 1])
            T10 = giw * (M[1, 0] - yd * M[2, 0])
            T11 = giw * (M[1, 1] - yd * M[2, 1])
        # D = d(x'', y'') / d(x, y)
        dg = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
        if rational:
            dg = (dg - g * (k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2))) * iden
        ax = xi * dg
        ay = yi * dg
        if prism:
            ax = ax + (s1 + 2.0 * s2 * r2)
            ay = ay + (s3 + 2.0 * s4 * r2)
        ax = ax + ax
        ay = ay + ay
        cross = p1 * xi + p2 * yi
        cross = cross + cross
        D00 = g + xi * ax + 2.0 * p1 * yi + 6.0 * p2 * xi
        D01 = yi * ax + cross
        D10 = xi * ay + cross
        D11 = g + yi * ay + 6.0 * p1 * yi + 2.0 * p2 * xi
        if tilted:
            J_xy[i, 0, 0] = T00 * D00 + T01 * D10
            J_xy[i, 0, 1] = T00 * D01 + T01 * D11
            J_xy[i, 1, 0] = T10 * D00 + T11 * D10
            J_xy[i, 1, 1] = T10 * D01 + T11 * D11
        else:
            J_xy[i, 0, 0] = fx * D00
            J_xy[i, 0, 1] = fx * D01
            J_xy[i, 1, 0] = fy * D10
            J_xy[i, 1, 1] = fy * D11
        if jac == 1:
            continue
        J = J_p[i]
        J[:, :] = 0.0
        J[0, 0] = xd
        J[1, 1] = yd
        J[0, 2] = 1.0
        J[1, 3] = 1.0
        # radial k1 k2 k3 (columns 4 5 8) and k4 k5 k6 (9 10 11) move (x'', y'') along
        # (x, y) by h = d g / d k
        r6 = r4 * r2
        ru = T00 * xi + T01 * yi if tilted else fx * xi
        rv = T10 * xi + T11 * yi if tilted else fy * yi
        mg = -g * iden if rational else -g
        for col, pw in ((4, r2), (5, r4), (8, r6)):
            h = pw * iden if rational else pw
            J[0, col] = ru * h
            J[1, col] = rv * h
        for col, pw in ((9, r2), (10, r4), (11, r6)):
            J[0, col] = ru * (pw * mg)
            J[1, col] = rv * (pw * mg)
        # tangential p1, p2: d(x'', y'')/dp1 = (2xy, ey), d(x'', y'')/dp2 = (ex, 2xy)
        if tilted:
            J[0, 6] = T00 * xy2 + T01 * ey
            J[1, 6] = T10 * xy2 + T11 * ey
            J[0, 7] = T00 * ex + T01 * xy2
            J[1, 7] = T10 * ex + T11 * xy2
        else:
            J[0, 6] = fx * xy2
            J[1, 6] = fy * ey
            J[0, 7] = fx * ex
            J[1, 7] = fy * xy2
        # thin prism s1 s2 (x'' only) and s3 s4 (y'' only): (r2, r4)
        J[0, 12], J[0, 13] = T00 * r2, T00 * r4
        J[1, 12], J[1, 13] = T10 * r2, T10 * r4
        J[0, 14], J[0, 15] = T01 * r2, T01 * r4
        J[1, 14], J[1, 15] = T11 * r2, T11 * r4
        # tilt angles act after the distortion: d(w0/w2, w1/w2)/dtau, w = M (x'', y'', 1)
        for k in range(2):
            dM = tilt[k + 1]
            dw2 = dM[2, 0] * xd0 + dM[2, 1] * yd0 + dM[2, 2]
            J[0, 16 + k] = fiw * (dM[0, 0] * xd0 + dM[0, 1] * yd0 + dM[0, 2] - xd * dw2)
            J[1, 16 + k] = giw * (dM[1, 0] * xd0 + dM[1, 1] * yd0 + dM[1, 2] - yd * dw2)


@njit(cache=True, error_model="numpy")
def project_points(d: FloatArray, p: FloatArray, tilt: FloatArray, jac: int, uv: FloatArray,
                   J_d: FloatArray, J_p: FloatArray) -> None:
    """Project camera-frame directions ``d`` (N, 3) into ``uv`` (N, 2), with Jacobians.

    ``J_d`` (N, 2, 3) ``d(u, v)/d(d)`` and ``J_p`` (N, 2, 18) as :func:`distort_points`
    (``jac`` 0: none; otherwise both).  Rows with ``z <= 0`` give NaN.
    """
    n = d.shape[0]
    x = np.empty(n)
    y = np.empty(n)
    iz = np.empty(n)
    for i in range(n):
        z = d[i, 2]
        iz[i] = 1.0 / z if z > 0.0 else np.nan
        x[i] = d[i, 0] * iz[i]
        y[i] = d[i, 1] * iz[i]
    J_xy = np.empty((n if jac else 0, 2, 2))
    distort_points(x, y, p, tilt, 2 if jac else 0, uv, J_xy, J_p)
    if not jac:
        return
    # d(x, y) / d(X, Y, Z) = [[1/Z, 0, -x/Z], [0, 1/Z, -y/Z]]
    for i in range(n):
        for r in range(2):
            a = J_xy[i, r, 0] * iz[i]
            b = J_xy[i, r, 1] * iz[i]
            J_d[i, r, 0] = a
            J_d[i, r, 1] = b
            J_d[i, r, 2] = -(a * x[i] + b * y[i])


# ---------------------------------------------------------------------------- IMU prefix
@njit(cache=True)
def quat_block_scan(dq: FloatArray, levels: FloatArray) -> FloatArray:
    """:func:`~stellar_cal_ros.core.imu_prefix._block_scan` compiled: the same floats.

    ``dq`` (nb, B, 4) → (4, nb, B): the inclusive Hamilton products within each block (at
    step ``s``, position ``k ≥ s`` becomes ``Q[k − s] ⊗ Q[k]``, the products of
    ``strapdown._quat_multiply_soa`` in their order), normalized as there.  ``levels``
    ``(log2 B + 1, 4, B)`` receives the last block's values before the first and after each
    step (unnormalized); a first dimension of 0: not wanted.  Each entry takes the very
    operations of the numpy scan (no reassociation, no fused multiply-add), so the prefix's
    rows are the same bit for bit (``test/test_imu_prefix.py``).
    """
    nb, B = dq.shape[0], dq.shape[1]
    Q = np.empty((4, nb, B))
    for i in range(nb):
        for k in range(B):
            for c in range(4):
                Q[c, i, k] = dq[i, k, c]
    want = levels.shape[0] > 0
    if want:
        for c in range(4):
            for k in range(B):
                levels[0, c, k] = Q[c, nb - 1, k]
    s, lvl = 1, 0
    while s < B:
        for i in range(nb):
            for k in range(B - 1, s - 1, -1):  # downwards: Q[k − s] still the level before
                ax, ay, az, aw = Q[0, i, k - s], Q[1, i, k - s], Q[2, i, k - s], Q[3, i, k - s]
                bx, by, bz, bw = Q[0, i, k], Q[1, i, k], Q[2, i, k], Q[3, i, k]
                Q[0, i, k] = aw * bx + ax * bw + ay * bz - az * by
                Q[1, i, k] = aw * by - ax * bz + ay * bw + az * bx
                Q[2, i, k] = aw * bz + ax * by - ay * bx + az * bw
                Q[3, i, k] = aw * bw - ax * bx - ay * by - az * bz
        s *= 2
        lvl += 1
        if want:
            for c in range(4):
                for k in range(B):
                    levels[lvl, c, k] = Q[c, nb - 1, k]
    for i in range(nb):
        for k in range(B):
            x, y, z, w = Q[0, i, k], Q[1, i, k], Q[2, i, k], Q[3, i, k]
            n = math.sqrt(x * x + y * y + z * z + w * w)
            Q[0, i, k] = x / n
            Q[1, i, k] = y / n
            Q[2, i, k] = z / n
            Q[3, i, k] = w / n
    return Q


@njit(cache=True)
def _corrected_row(x: FloatArray, i: int, b: FloatArray, A: FloatArray,
                   has_A: bool) -> tuple[float, float, float]:
    """``A (x[i] − b)`` with explicit sums (``imu_prefix._corrected``'s floats; no ``A``)."""
    dx, dy, dz = x[i, 0] - b[0], x[i, 1] - b[1], x[i, 2] - b[2]
    if has_A:
        return (dx * A[0, 0] + dy * A[0, 1] + dz * A[0, 2],
                dx * A[1, 0] + dy * A[1, 1] + dz * A[1, 2],
                dx * A[2, 0] + dy * A[2, 1] + dz * A[2, 2])
    return dx, dy, dz


@njit(cache=True, error_model="numpy")
def prefix_sample_rows(imu_t: FloatArray, imu_w: FloatArray, imu_f: FloatArray,
                       t_prev: float, b: FloatArray, A: FloatArray, has_A: bool,
                       b_a: FloatArray, A_a: FloatArray, has_A_a: bool,
                       dth_last: FloatArray, w_last: FloatArray, dt_last: float,
                       dv_last: FloatArray, accel: bool, dt: FloatArray, dth: FloatArray,
                       w_hat: FloatArray, phi: FloatArray, slope: FloatArray,
                       f_hat: FloatArray, du: FloatArray, dv: FloatArray) -> int:
    """The per-sample rows of :meth:`~stellar_cal_ros.core.imu_prefix.ImuPrefix.extend`.

    One pass over the ``m`` samples, the same floats as its numpy operations (each entry
    the very products, sums and quotients in their order; no fused multiply-add): the
    sample lengths ``dt`` (from ``t_prev``), the corrected rates ``w_hat``
    (``imu_prefix._corrected``: ``A (w − b)`` with explicit sums; ``has_A`` False: no
    ``A``), the increments ``dth`` and their coning-corrected ``phi`` (from ``dth_last``),
    the ``slope`` rows (:func:`~stellar_cal_ros.core.imu_prefix.sample_slopes`, from
    ``w_last``, ``dt_last``), and with ``accel`` the corrected specific force ``f_hat``,
    its increments ``dv`` and the sculled ``du``
    (:func:`~stellar_cal_ros.core.imu_prefix.sculled_increments`, from ``dv_last``) —
    whose Taylor coefficients are taken here only where the increment's angle is below
    1e-2 rad: returns how many samples are not (their ``du`` rows left for numpy).
    """
    m = imu_t.shape[0]
    big = 0
    tp = t_prev
    px, py, pz = dth_last[0], dth_last[1], dth_last[2]  # the previous increment
    wx0, wy0, wz0 = w_last[0], w_last[1], w_last[2]  # the previous corrected rate
    dtp = dt_last
    vx0, vy0, vz0 = dv_last[0], dv_last[1], dv_last[2]
    for i in range(m):
        t = imu_t[i]
        h = t - tp
        tp = t
        dt[i] = h
        dx, dy, dz = _corrected_row(imu_w, i, b, A, has_A)
        w_hat[i, 0], w_hat[i, 1], w_hat[i, 2] = dx, dy, dz
        hx, hy, hz = dx * h, dy * h, dz * h
        dth[i, 0], dth[i, 1], dth[i, 2] = hx, hy, hz
        phi[i, 0] = hx + (py * hz - pz * hy) / 12.0
        phi[i, 1] = hy + (pz * hx - px * hz) / 12.0
        phi[i, 2] = hz + (px * hy - py * hx) / 12.0
        if dtp > 0.0:
            k = 2.0 * h * h / (h + dtp)
            slope[i, 0] = (dx - wx0) * k
            slope[i, 1] = (dy - wy0) * k
            slope[i, 2] = (dz - wz0) * k
        else:
            slope[i, 0] = 0.0
            slope[i, 1] = 0.0
            slope[i, 2] = 0.0
        if accel:
            fx, fy, fz = _corrected_row(imu_f, i, b_a, A_a, has_A_a)
            f_hat[i, 0], f_hat[i, 1], f_hat[i, 2] = fx, fy, fz
            vx, vy, vz = fx * h, fy * h, fz * h
            dv[i, 0], dv[i, 1], dv[i, 2] = vx, vy, vz
            p = math.sqrt(hx * hx + hy * hy + hz * hz)
            if not p < 1e-2:
                big += 1
            p2 = p * p
            ca = 0.5 - p2 / 24.0 + p2 * p2 / 720.0
            cb = 1.0 / 6.0 - p2 / 120.0 + p2 * p2 / 5040.0
            c1x, c1y, c1z = hy * vz - hz * vy, hz * vx - hx * vz, hx * vy - hy * vx
            c2x, c2y, c2z = hy * c1z - hz * c1y, hz * c1x - hx * c1z, hx * c1y - hy * c1x
            # (cross(dth_prev, dv) + cross(dv_prev, dth)) / 12
            ex = ((py * vz - pz * vy) + (vy0 * hz - vz0 * hy)) / 12.0
            ey = ((pz * vx - px * vz) + (vz0 * hx - vx0 * hz)) / 12.0
            ez = ((px * vy - py * vx) + (vx0 * hy - vy0 * hx)) / 12.0
            du[i, 0] = vx + ca * c1x + cb * c2x + ex
            du[i, 1] = vy + ca * c1y + cb * c2y + ey
            du[i, 2] = vz + ca * c1z + cb * c2z + ez
            vx0, vy0, vz0 = vx, vy, vz
        px, py, pz = hx, hy, hz
        wx0, wy0, wz0 = dx, dy, dz
        dtp = h
    return big


@njit(cache=True)
def anchored_matrices(anchors: FloatArray, L: FloatArray, old: int, r: int,
                      C: FloatArray) -> None:
    """The prefix's attitude matrices of scan positions ``old .. r − 1``, into ``C``.

    Position ``p`` (block ``p // B``, place ``p % B`` of ``L`` (4, nb, B)): the block's
    anchor ``anchors[:, p // B]`` ⊗ ``L`` (``strapdown._quat_multiply_soa``'s order), as a
    matrix (``imu_prefix._quat_soa_to_matrix``'s formulas) in ``C[p − old]``: the same
    floats as those two numpy calls.
    """
    B = L.shape[2]
    for p in range(old, r):
        i, k = p // B, p % B
        ax, ay, az, aw = anchors[0, i], anchors[1, i], anchors[2, i], anchors[3, i]
        bx, by, bz, bw = L[0, i, k], L[1, i, k], L[2, i, k], L[3, i, k]
        x = aw * bx + ax * bw + ay * bz - az * by
        y = aw * by - ax * bz + ay * bw + az * bx
        z = aw * bz + ax * by - ay * bx + az * bw
        w = aw * bw - ax * bx - ay * by - az * bz
        xx, yy, zz = x * x, y * y, z * z
        xy, xz, yz = x * y, x * z, y * z
        wx, wy, wz = w * x, w * y, w * z
        o = C[p - old]
        o[0, 0] = 1.0 - 2.0 * (yy + zz)
        o[0, 1] = 2.0 * (xy - wz)
        o[0, 2] = 2.0 * (xz + wy)
        o[1, 0] = 2.0 * (xy + wz)
        o[1, 1] = 1.0 - 2.0 * (xx + zz)
        o[1, 2] = 2.0 * (yz - wx)
        o[2, 0] = 2.0 * (xz - wy)
        o[2, 1] = 2.0 * (yz + wx)
        o[2, 2] = 1.0 - 2.0 * (xx + yy)


# ---------------------------------------------------------------------------- Kalman update
@njit(cache=True)
def kalman_gain(P: FloatArray, H: FloatArray, r_diag: FloatArray, nu: FloatArray
                ) -> tuple[int, FloatArray, float]:
    """One pass of :func:`stellar_cal_ros.core.covariance.iterated_update`: the gain.

    ``S = H P Hᵀ + diag(r)``, its Cholesky factor ``L`` (LAPACK), ``K = P Hᵀ S⁻¹`` and the
    NIS ``νᵀ S⁻¹ ν`` (forward and back substitution).  ``P`` (N, N), ``H`` (m, N), ``r_diag``
    and ``nu`` (m,).  Returns ``(ok, K (N, m), nis)``; ``ok`` 0 when ``S`` is not positive
    definite (then ``K`` is zero).  :func:`kalman_gain_factor` also returns ``L``.
    """
    ok, K, nis, _ = kalman_gain_factor(P, H, r_diag, nu)
    return ok, K, nis


@njit(cache=True)
def kalman_gain_factor(P: FloatArray, H: FloatArray, r_diag: FloatArray, nu: FloatArray
                       ) -> tuple[int, FloatArray, float, FloatArray]:
    """:func:`kalman_gain` and the Cholesky factor ``L`` (m, m) of its ``S`` (zeros if not ok).

    A caller that solves more with the same ``S`` (the frame step's sensitivity) takes
    :func:`cholesky_solve` of ``L`` instead of factorizing ``S`` again.
    """
    N, m = P.shape[0], H.shape[0]
    PHt = np.ascontiguousarray(P @ np.ascontiguousarray(H.T))  # (N, m)
    S = H @ PHt
    for i in range(m):
        S[i, i] += r_diag[i]
    # Cholesky (lower), column by column; the rows below the diagonal four at a time (four
    # independent sums: each entry's subtractions in the same order)
    L = np.zeros((m, m))
    for j in range(m):
        s = S[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:
            return 0, np.zeros((N, m)), math.nan, L
        d = math.sqrt(s)
        L[j, j] = d
        i = j + 1
        while i + 3 < m:
            s0, s1, s2, s3 = S[i, j], S[i + 1, j], S[i + 2, j], S[i + 3, j]
            for k in range(j):
                ljk = L[j, k]
                s0 -= L[i, k] * ljk
                s1 -= L[i + 1, k] * ljk
                s2 -= L[i + 2, k] * ljk
                s3 -= L[i + 3, k] * ljk
            L[i, j] = s0 / d
            L[i + 1, j] = s1 / d
            L[i + 2, j] = s2 / d
            L[i + 3, j] = s3 / d
            i += 4
        for q in range(i, m):
            s = S[q, j]
            for k in range(j):
                s -= L[q, k] * L[j, k]
            L[q, j] = s / d
    y = np.empty(m)
    for i in range(m):
        s = nu[i]
        for k in range(i):
            s -= L[i, k] * y[k]
        y[i] = s / L[i, i]
    nis = 0.0
    for i in range(m):
        nis += y[i] * y[i]
    # Kᵀ = S⁻¹ (P Hᵀ)ᵀ
    Kt = cholesky_solve(L, np.ascontiguousarray(PHt.T))  # (m, N)
    return 1, np.ascontiguousarray(Kt.T), nis, L


@njit(cache=True)
def cholesky_solve(L: FloatArray, X: FloatArray) -> FloatArray:
    """``S⁻¹ X`` for ``S = L Lᵀ`` (``L`` lower (m, m), ``X`` (m, k) C order), in place; ``X``.

    Solve ``L W = X``, then ``Lᵀ Y = W``, a row at a time (contiguous rows; each entry
    takes its subtractions in ascending order, then its division).
    """
    m, k = X.shape
    acc = np.empty(k)
    for t in range(2 * m):
        down = t < m  # L W = X downwards, then Lᵀ Y = W upwards
        i = t if down else 2 * m - 1 - t
        for c in range(k):
            acc[c] = X[i, c]
        for j in range(0, i) if down else range(i + 1, m):
            coef = L[i, j] if down else L[j, i]
            for c in range(k):
                acc[c] -= coef * X[j, c]
        d = L[i, i]
        for c in range(k):
            X[i, c] = acc[c] / d
    return X


@njit(cache=True)
def joseph(P: FloatArray, K: FloatArray, H: FloatArray, r_diag: FloatArray) -> FloatArray:
    """``(I − K H) P (I − K H)ᵀ + K diag(r) Kᵀ`` (not symmetrized, :func:`kalman_gain`)."""
    N = P.shape[0]
    A = -(K @ H)
    for i in range(N):
        A[i, i] += 1.0
    KR = K * r_diag
    return (A @ P) @ np.ascontiguousarray(A.T) + KR @ np.ascontiguousarray(K.T)


@njit(cache=True)
def star_blocks(H: FloatArray, P: FloatArray, r: FloatArray, nu: FloatArray
                ) -> tuple[FloatArray, FloatArray]:
    """Each star's innovation covariance and NIS (the gate's inputs), compiled.

    ``S_i = H_i P H_iᵀ + r_i I`` (n, 2, 2) and ``ν_iᵀ S_i⁻¹ ν_i`` (n,) for ``H`` (n, 2, N),
    ``P`` (N, N), ``r`` (n,) variances, ``nu`` (n, 2) — as ``(H @ P) @ Hᵀ`` and
    :func:`stellar_cal_ros.core.gating.block_nis`.
    """
    n, N = H.shape[0], P.shape[0]
    S = np.empty((n, 2, 2))
    nis = np.empty(n)
    HP = np.empty((2, N))
    for i in range(n):
        for a in range(2):  # HP[a] = Σ_k H[i, a, k] P[k]: rows of P (each sum in k order)
            for c in range(N):
                HP[a, c] = 0.0
            for k in range(N):
                h = H[i, a, k]
                for c in range(N):
                    HP[a, c] += h * P[k, c]
        for a in range(2):
            for b in range(2):
                acc = 0.0
                for c in range(N):
                    acc += HP[a, c] * H[i, b, c]
                S[i, a, b] = acc
        S[i, 0, 0] += r[i]
        S[i, 1, 1] += r[i]
        s00, s01, s11 = S[i, 0, 0], S[i, 0, 1], S[i, 1, 1]
        x, y = nu[i, 0], nu[i, 1]
        nis[i] = (s11 * x * x - 2 * s01 * x * y + s00 * y * y) / (s00 * s11 - s01 * s01)
    return S, nis


# ---------------------------------------------------------------------------- frame inputs
@njit(cache=True)
def _usable_stars(uv: FloatArray, ra: FloatArray, dec: FloatArray, cat: np.ndarray,
                  a: int, b: int, width: float, height: float, ok: np.ndarray):
    """:func:`star_inputs`' star rule over the stars ``a:b`` (``ok`` written); (usable, unid)."""
    k = 0
    unid = 0
    for i in range(a, b):
        u, v = uv[i, 0], uv[i, 1]
        if cat[i] == 0 and math.isnan(ra[i]) and math.isnan(dec[i]):
            unid += 1
        good = (math.isfinite(ra[i]) and math.isfinite(dec[i])
                and math.isfinite(u) and math.isfinite(v))
        good = good and u >= -0.5 and u < width - 0.5 and v >= -0.5 and v < height - 0.5
        ok[i] = good
        k += good
    return k, unid


@njit(cache=True)
def _star_rows(uv: FloatArray, ra: FloatArray, dec: FloatArray, cat: np.ndarray,
               sigma: FloatArray, mag: FloatArray, a: int, b: int, ok: np.ndarray,
               default_sigma: float, uv_o: FloatArray, u_i: FloatArray, s_o: FloatArray,
               c_o: np.ndarray, m_o: FloatArray, j: int):
    """:func:`star_inputs`' rows of the usable stars of ``a:b``, written from row ``j``.

    Returns ``(bad_sigma, unknown_sigma)`` of those stars.
    """
    bad = 0
    unknown = 0
    for i in range(a, b):
        if not ok[i]:
            continue
        uv_o[j, 0], uv_o[j, 1] = uv[i, 0], uv[i, 1]
        cd = math.cos(dec[i])
        u_i[j, 0] = cd * math.cos(ra[i])
        u_i[j, 1] = cd * math.sin(ra[i])
        u_i[j, 2] = math.sin(dec[i])
        s = sigma[i]
        fine = math.isfinite(s)
        if not (fine and s >= 0):
            bad += 1
        unknown += s == 0
        s_o[j] = s if fine and s > 0 else default_sigma
        c_o[j] = cat[i]
        m_o[j] = mag[i]
        j += 1
    return bad, unknown


@njit(cache=True)
def star_inputs(uv: FloatArray, ra: FloatArray, dec: FloatArray, cat: np.ndarray,
                sigma: FloatArray, mag: FloatArray, width: float, height: float,
                default_sigma: float):
    """:func:`stellar_cal_ros.methods.frames.frame_inputs` of one message, compiled.

    The star rule of :func:`~stellar_cal_ros.methods.frames.star_masks`: a star is usable when
    its RA/Dec and centroid are finite and the centroid lies on the detector (``−0.5 ≤ u <
    width − 0.5``, likewise v); unidentified when ``cat`` is 0 and RA and Dec are NaN.  Its σ
    (:func:`~stellar_cal_ros.methods.frames.star_sigma`) is the message's when finite and
    positive, ``default_sigma`` otherwise (negative, infinite or NaN ones counted).
    Returns ``(ok (n,), uv (k, 2), u_i (k, 3), sigma (k,), catalog_id (k,) int64,
    magnitude (k,), bad_sigma, unidentified, unknown_sigma)`` — the numpy function's values
    (same formulas; ``unknown_sigma``: usable stars whose σ is 0).  Arrays of unequal lengths
    (the loops do not check bounds) give ``bad_sigma`` −1 and nothing else: the caller then
    takes the numpy path.
    """
    n = uv.shape[0]
    if ra.shape[0] != n or dec.shape[0] != n or cat.shape[0] != n or sigma.shape[0] != n \
            or mag.shape[0] != n:
        return (np.zeros(0, dtype=np.bool_), np.empty((0, 2)), np.empty((0, 3)), np.empty(0),
                np.empty(0, dtype=np.int64), np.empty(0), -1, 0, 0)
    ok = np.empty(n, dtype=np.bool_)
    k, unid = _usable_stars(uv, ra, dec, cat, 0, n, width, height, ok)
    uv_o = np.empty((k, 2))
    u_i = np.empty((k, 3))
    s_o = np.empty(k)
    c_o = np.empty(k, dtype=np.int64)
    m_o = np.empty(k)
    bad, unknown = _star_rows(uv, ra, dec, cat, sigma, mag, 0, n, ok, default_sigma, uv_o, u_i,
                              s_o, c_o, m_o, 0)
    return ok, uv_o, u_i, s_o, c_o, m_o, bad, unid, unknown


@njit(cache=True)
def star_inputs_many(uv: FloatArray, ra: FloatArray, dec: FloatArray, cat: np.ndarray,
                     sigma: FloatArray, mag: FloatArray, bounds: np.ndarray, width: float,
                     height: float, default_sigma: float):
    """:func:`star_inputs` of many messages in one call, their stars concatenated.

    Message ``f`` holds the stars ``bounds[f]:bounds[f + 1]`` of the arrays (of equal
    lengths: the caller's check).  Returns ``(ok (n,), uv (k, 2), u_i (k, 3), sigma (k,),
    catalog_id (k,), magnitude (k,), counts (F, 4))``: the messages' usable rows one after
    the other, and per message its usable stars, ``bad_sigma``, ``unidentified`` and
    ``unknown_sigma`` — each message's values those of :func:`star_inputs` (the same
    functions over its stars).
    """
    F = bounds.shape[0] - 1
    ok = np.empty(uv.shape[0], dtype=np.bool_)
    counts = np.zeros((F, 4), dtype=np.int64)
    k = 0
    for f in range(F):
        kf, unid = _usable_stars(uv, ra, dec, cat, bounds[f], bounds[f + 1], width, height, ok)
        counts[f, 0] = kf
        counts[f, 2] = unid
        k += kf
    uv_o = np.empty((k, 2))
    u_i = np.empty((k, 3))
    s_o = np.empty(k)
    c_o = np.empty(k, dtype=np.int64)
    m_o = np.empty(k)
    j = 0
    for f in range(F):
        bad, unknown = _star_rows(uv, ra, dec, cat, sigma, mag, bounds[f], bounds[f + 1], ok,
                                  default_sigma, uv_o, u_i, s_o, c_o, m_o, j)
        counts[f, 1] = bad
        counts[f, 3] = unknown
        j += counts[f, 0]
    return ok, uv_o, u_i, s_o, c_o, m_o, counts


# ---------------------------------------------------------------------------- IMU blocks
@njit(cache=True)
def imu_block_screen(t: np.ndarray, w: np.ndarray, f: np.ndarray) -> tuple[bool, bool]:
    """``(increasing, clean)`` of an IMU block, in one pass (the driver's usual case).

    ``t`` (m,) stamps ns, ``w`` and ``f`` (m, 3).  ``increasing``: stamps strictly
    increasing; ``clean``: every stamp positive and every rate and force finite — what
    ``Calibrator.push_imu_block``'s numpy screen decides, element by element (no sum that
    could overflow).
    """
    m = t.shape[0]
    inc = True
    for i in range(1, m):
        if not t[i] > t[i - 1]:
            inc = False
            break
    for i in range(m):
        if not t[i] > 0:
            return inc, False
        for k in range(3):
            if not (math.isfinite(w[i, k]) and math.isfinite(f[i, k])):
                return inc, False
    return inc, True
