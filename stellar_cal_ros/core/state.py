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
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from stellar_cal_ros.core.rotation import so3_exp


@dataclass(frozen=True)
class Block:
    """One block of the error state."""

    name: str
    size: int
    offset: int = 0
    kind: str = "vector"  #: "rotation" (left, Exp) or "vector" (additive)
    navigation: bool = False  #: set by acquisition, not kept across a re-acquisition

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
            b = Block(b.name, b.size, offset, b.kind, b.navigation)
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
