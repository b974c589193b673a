"""Typed blocks of an error state (after OpenVINS's ``Type`` / ``StateHelper``).

An error-state Kalman filter estimates a small correction ``δx`` to a *nominal* state that
lives on a manifold (a rotation, vectors, parameters).  A :class:`Block` knows its name,
error-state size, offset in the covariance and how a correction is applied to its nominal
value (box-plus).  A :class:`StateLayout` is the ordered list of blocks; measurement
Jacobians are assembled per block (:meth:`StateLayout.assemble`), so a filter that gains or
loses a block needs no change in its update code.

Conventions
-----------
* ``rotation`` blocks: nominal ``R`` (3, 3), left perturbation in the reference frame,
  ``R = Exp(δφ) R̂`` (Tan et al. eq. 7; the inertial frame for the IMU attitude); box-plus
  ``R ← Exp(δφ) R``; the covariance reset after injecting δφ is ``G = I + ½[δφ]×``
  (:func:`stellar_cal_ros.core.covariance.reset_rotation`).
* ``vector`` blocks: nominal a float vector, box-plus ``x ← x + δx``.
* *navigation* blocks are the ones an acquisition (or re-acquisition after an IMU gap or a
  lost lock) sets from scratch; parameter blocks keep their estimate across it.
* a block corrects a *nominal* value (``nominal``, default its own name), or a part of one
  (``index``): the estimated effects' blocks are slices of one parameter vector θ.
* ``driven_by`` names the white sensor noise ("gyro", "accel") that enters a block directly
  (the attitude, the velocity): a bridged IMU interval inflates those blocks.

:class:`ErrorState` is the one owner of the covariance: it holds the nominal values, ``P``
and the consider sensitivity, and every change of ``P`` (propagation, update, injection and
reset, acquisition, repair, snapshots) is one of its methods, built on the functions of
:mod:`stellar_cal_ros.core.covariance`.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from stellar_cal_ros.core import covariance as cov
from stellar_cal_ros.core.rotation import so3_exp


def nominal_view(key: str, doc: str) -> property:
    """A filter attribute that reads and writes ``self.state.nominal[key]``.

    The :class:`ErrorState` owns every nominal value; a filter names its own (``R_i_b``,
    ``theta``, ``velocity`` ...) with one line each instead of a getter/setter pair.
    """

    def get(self):  # noqa: ANN001, ANN202 - any filter holding an ErrorState as .state
        return self.state.nominal[key]

    def put(self, value) -> None:  # noqa: ANN001
        self.state.nominal[key] = value

    return property(get, put, doc=doc)


@dataclass(frozen=True)
class Block:
    """One block of the error state."""

    name: str
    size: int
    offset: int = 0
    kind: str = "vector"  #: "rotation" (left, Exp) or "vector" (additive)
    navigation: bool = False  #: set by acquisition, not kept across a re-acquisition
    nominal: str = ""  #: the nominal value it corrects ("": its own name)
    index: slice | None = None  #: its part of that nominal value (None: all of it)
    driven_by: str = ""  #: white sensor noise entering it directly ("gyro", "accel")

    @property
    def value_name(self) -> str:
        """Name of the nominal value this block corrects."""
        return self.nominal or self.name

    @property
    def sl(self) -> slice:
        """Slice of the block in the error state."""
        return slice(self.offset, self.offset + self.size)

    def boxplus(self, value: np.ndarray, dx: np.ndarray) -> np.ndarray:
        """Nominal value after applying the correction ``dx`` (size ``self.size``)."""
        if self.kind == "rotation":
            return so3_exp(dx) @ value
        return value + dx


class StateLayout:
    """Ordered blocks of an error state; offsets are assigned in order.

    Parameters
    ----------
    blocks : iterable of (name, size, kind, navigation) or Block
        ``kind`` and ``navigation`` default to ``"vector"`` and ``False``.
    """

    def __init__(self, blocks: Iterable[Block | Sequence]) -> None:
        self.blocks: dict[str, Block] = {}
        offset = 0
        for b in blocks:
            if not isinstance(b, Block):
                name, size, *rest = b
                kind = rest[0] if rest else "vector"
                nav = bool(rest[1]) if len(rest) > 1 else False
                b = Block(name, int(size), 0, kind, nav)
            if b.name in self.blocks:
                raise ValueError(f"duplicate state block {b.name!r}")
            b = replace(b, offset=offset)
            self.blocks[b.name] = b
            offset += b.size
        self.size = offset
        self.navigation_index = np.concatenate(
            [np.arange(b.offset, b.offset + b.size) for b in self.blocks.values()
             if b.navigation] or [np.zeros(0, dtype=int)]).astype(int)

    def __getitem__(self, name: str) -> Block:
        return self.blocks[name]

    def __contains__(self, name: str) -> bool:
        return name in self.blocks

    def sl(self, name: str) -> slice:
        """Slice of block ``name``."""
        return self.blocks[name].sl

    def names(self) -> list[str]:
        """Block names in order."""
        return list(self.blocks)

    def span(self, first: str, last: str) -> slice:
        """Slice from the start of ``first`` to the end of ``last`` (contiguous blocks)."""
        return slice(self.blocks[first].offset, self.blocks[last].sl.stop)

    def assemble(self, parts: dict[str, np.ndarray], rows: int) -> np.ndarray:
        """Jacobian ``(rows, N)`` from per-block columns ``{name: (rows, size)}``.

        Blocks without an entry get zero columns (a measurement that does not see them).
        """
        H = np.zeros((rows, self.size))
        for name, cols in parts.items():
            H[:, self.blocks[name].sl] = cols
        return H

    def __repr__(self) -> str:
        inner = ", ".join(f"{b.name}[{b.offset}:{b.offset + b.size}]" for b in self.blocks.values())
        return f"StateLayout({inner})"


class ErrorState:
    """Nominal values, error covariance and consider sensitivity of a :class:`StateLayout`.

    The one owner of ``P`` (after OpenVINS's ``StateHelper``): the filters change it only
    through these methods.

    Parameters
    ----------
    layout : StateLayout
    nominal : dict
        Initial nominal value of every name the blocks correct (``Block.value_name``);
        e.g. ``{"attitude": None, "theta": θ}``.
    n_consider : int
        Number of consider parameters whose sensitivity is carried
        (:class:`~stellar_cal_ros.core.covariance.Sensitivity`; 0: none).
    """

    def __init__(self, layout: StateLayout, nominal: dict[str, np.ndarray | None],
                 n_consider: int = 0) -> None:
        self.layout = layout
        self.N = layout.size
        self.P = np.zeros((self.N, self.N))
        self.nominal: dict[str, np.ndarray | None] = dict(nominal)
        missing = {b.value_name for b in layout.blocks.values()} - set(self.nominal)
        if missing:
            raise ValueError(f"no nominal value for {sorted(missing)}")
        self.sensitivity = cov.Sensitivity(self.N, n_consider) if n_consider else None
        self._rotations = [b for b in layout.blocks.values() if b.kind == "rotation"]
        # box-plus of additive blocks that follow each other in the error state and in
        # their nominal value: one addition per run (the same arithmetic, fewer calls)
        runs: list[list] = []
        for b in layout.blocks.values():
            if b.kind != "vector":
                continue
            idx = b.index if b.index is not None else slice(0, b.size)
            last = runs[-1] if runs else None
            if last is not None and last[0] == b.value_name and last[1].stop == b.offset \
                    and last[2].stop == idx.start and b.index is not None:
                last[1] = slice(last[1].start, b.sl.stop)
                last[2] = slice(last[2].start, idx.stop)
            else:
                runs.append([b.value_name, b.sl, idx, b.index is None])
        self._runs = [tuple(r) for r in runs]

    # ------------------------------------------------------------------ views
    def sl(self, name: str) -> slice:
        """Slice of block ``name`` in the error state."""
        return self.layout.sl(name)

    def sigma(self) -> np.ndarray:
        """1-σ of the error state."""
        return np.sqrt(np.maximum(self.P.diagonal(), 0.0))  # (a view: 10 -> 4 µs a call)

    # ------------------------------------------------------------------ direct settings
    def _index(self, x) -> slice | np.ndarray:
        return self.layout.sl(x) if isinstance(x, str) else x

    def assign(self, rows, cols, value: np.ndarray) -> None:
        """``P[rows, cols] = value`` and its transpose (rows, cols: block names or slices)."""
        r, c = self._index(rows), self._index(cols)
        self.P[r, c] = value
        if r != c:
            self.P[c, r] = self.P[r, c].T

    def add_diagonal(self, q: np.ndarray) -> None:
        """``P += diag(q)`` (q (N,))."""
        self.P.flat[::self.N + 1] += q

    def add_noise(self, variances: dict[str, float]) -> None:
        """``var · I`` on the blocks ``driven_by`` each sensor (a bridged IMU interval)."""
        for b in self.layout.blocks.values():
            var = variances.get(b.driven_by) if b.driven_by else None
            if var is not None:
                self.P[b.sl, b.sl] += var * np.eye(b.size)

    def forget(self, index: np.ndarray) -> None:
        """Zero the rows and columns ``index`` (states to be set again from scratch)."""
        self.P[index, :] = 0.0
        self.P[:, index] = 0.0

    # ------------------------------------------------------------------ propagation
    def propagate(self, Phi: np.ndarray, q_flat: tuple[np.ndarray, np.ndarray] | None = None,
                  Phi_consider: np.ndarray | None = None) -> None:
        """``P ← Φ P Φᵀ + Q`` symmetrized; ``q_flat = (flat index, values)`` of Q's entries.

        The sensitivity follows (``M ← Φ M + Φ_β``, ``Phi_consider`` (N, m)).
        """
        Pn = Phi @ self.P @ Phi.T
        if q_flat is not None:
            Pn.ravel()[q_flat[0]] += q_flat[1]
        self.P = 0.5 * (Pn + Pn.T)
        if self.sensitivity is not None:
            self.sensitivity.propagate(Phi, Phi_consider)

    def propagate_coupled(self, rows: slice, cols: slice, F: np.ndarray,
                          q_diag: np.ndarray | None = None,
                          F_consider: np.ndarray | None = None) -> None:
        """``Φ = I + F`` with F only in ``[rows, cols]`` (:func:`~.covariance.propagate_coupled`).

        ``F_consider`` (rows, m): the consider columns of the driven rows (sensitivity).
        """
        cov.propagate_coupled(self.P, rows, cols, F, q_diag)
        if self.sensitivity is not None:
            self.sensitivity.propagate_coupled(rows, cols, F, F_consider)

    # ------------------------------------------------------------------ updates
    def iterated_update(self, H: np.ndarray, h: np.ndarray, z: np.ndarray,
                        r_diag: np.ndarray, relinearize, policy: cov.UpdatePolicy,
                        rotation: slice, others: slice | None,
                        H_consider: np.ndarray | None = None,
                        compiled: bool = False,
                        common: np.ndarray | None = None) -> cov.UpdateResult:
        """:func:`~.covariance.iterated_update` of ``P``; on success P (and M) take it.

        The correction ``res.dx`` is not injected (:meth:`inject`).  ``H_consider`` (m, n_c):
        the measurement's consider columns (sensitivity update with the prior's S).
        ``common`` (m,) or (m, k): noises all rows share, ``R = diag(r) + C Cᵀ`` (the frame's
        stamp, a shift of all its stars: :func:`~.covariance.common_columns`).
        """
        res = cov.iterated_update(self.P, H, h, z, r_diag, relinearize, policy, rotation,
                                  others, compiled=compiled, common=common)
        if not res.ok:
            return res
        sens = self.sensitivity
        if sens is not None:
            S = res.H @ self.P @ res.H.T
            S.ravel()[::len(S) + 1] += r_diag
            if common is not None:
                C = common.reshape(len(common), -1)
                S += C @ C.T
            sens.update(res.H, H_consider, res.K, z - h, S)
        self.P = res.P
        return res

    def linear_update(self, H: np.ndarray, nu: np.ndarray, R: np.ndarray
                      ) -> tuple[np.ndarray, float]:
        """One linear update (:func:`~.covariance.linear_update`): returns ``(dx, NIS)``.

        The measurement sees no consider parameter.  ``dx`` is not injected.
        """
        P0 = self.P
        dx, self.P, K, nis = cov.linear_update(P0, H, nu, R)
        if self.sensitivity is not None:
            self.sensitivity.update(H, np.zeros((len(nu), self.sensitivity.size)), K, nu,
                                    H @ P0 @ H.T + R)
        return dx, nis

    def inject(self, dx: np.ndarray) -> None:
        """Box-plus ``dx`` into the nominal values (per block), reset P (and M), symmetrize.

        A rotation block's covariance is reset by ``G = I + ½[δφ]×``
        (:func:`~.covariance.reset_rotation`).
        """
        self.boxplus(dx)
        for b in self._rotations:
            cov.reset_rotation(self.P, b.sl, dx[b.sl])
        self.P = 0.5 * (self.P + self.P.T)
        if self.sensitivity is not None:
            for b in self._rotations:
                self.sensitivity.reset_rotation(b.sl, dx[b.sl])

    def boxplus(self, dx: np.ndarray) -> None:
        """The nominal values' part of :meth:`inject` (P and M left as they are)."""
        nom = self.nominal
        for b in self._rotations:
            nom[b.value_name] = b.boxplus(nom[b.value_name], dx[b.sl])
        for name, sl, idx, whole in self._runs:
            if whole:
                nom[name] = nom[name] + dx[sl]
            else:
                nom[name][idx] += dx[sl]

    # ------------------------------------------------------------------ health
    def check(self, name: str = "covariance") -> None:
        """:func:`~.covariance.check` of P (raises ModelError)."""
        cov.check(self.P, name)

    def repair(self) -> bool:
        """Replace P by its nearest positive definite matrix; False if it is not finite."""
        fixed = cov.repair(self.P)
        if fixed is None:
            return False
        self.P = fixed
        return True

    # ------------------------------------------------------------------ snapshots
    def snapshot(self, sensitivity: bool = False) -> tuple:
        """Copies of P and the nominal values (and the sensitivity M)."""
        nom = {k: None if v is None else v.copy() for k, v in self.nominal.items()}
        M = self.sensitivity.M.copy() if sensitivity and self.sensitivity is not None \
            else None
        return self.P.copy(), nom, M

    def restore(self, snap: tuple) -> None:
        """Back to a :meth:`snapshot` (M only if it was taken with it)."""
        P, nom, M = snap
        self.P = P.copy()
        self.nominal.update({k: None if v is None else v.copy() for k, v in nom.items()})
        if M is not None:
            self.sensitivity.M = M.copy()
