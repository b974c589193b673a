"""Numbers as the text Python's ``repr`` / ``str`` gives them, for whole tables at once (compiled).

A history CSV holds ~35 full-precision floats per row; ``repr`` of a Python float (David
Gay's shortest round trip, ``_Py_dg_dtoa`` mode 0) costs ≈ 0.55 µs each, 0.25-0.3 CPU-s
of a 2-h replay.  :func:`table_text` writes the same bytes from arrays in one compiled pass:
each float's shortest round-trip digits by Ryu (Ulf Adams, PLDI 2018: the shortest digits
that read back to the same double, the closest of them to it, a tie to the even digit —
what mode 0 returns), laid out as ``float.__repr__`` lays them (fixed notation for a
decimal exponent ``-4 < decpt <= 16``, else ``d.ddde±XX`` with at least two exponent
digits; ``.0`` on an integral fixed value; ``nan``, ``inf``, ``-inf``, ``-0.0``), integers
as ``str``, booleans as ``True``/``False``.  ``test/test_float_text.py`` checks it against
``repr`` byte for byte on special values, every power of two and ten, the layout's
boundaries and 10⁶ random doubles of every exponent.

numba is optional: :data:`HAVE_NUMBA` is False when it cannot be imported, and the callers
then use ``repr``.
"""

from __future__ import annotations

import numpy as np

# numba is optional (jit's stand-in decorator leaves the Python functions without it)
from stellar_cal_ros.core.jit import HAVE_NUMBA, njit

_POW5_INV_BITCOUNT = 125
_POW5_BITCOUNT = 125


def _tables() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Ryu's 128-bit tables (low, high words): ⌊2^j / 5^q⌋ + 1 and 5^i's top 125 bits."""
    inv_lo, inv_hi, pow_lo, pow_hi = [], [], [], []
    mask = (1 << 64) - 1
    for q in range(342):
        p = 5 ** q
        v = (1 << (p.bit_length() - 1 + _POW5_INV_BITCOUNT)) // p + 1
        inv_lo.append(v & mask)
        inv_hi.append(v >> 64)
    for i in range(326):
        p = 5 ** i
        n = p.bit_length()
        v = p >> (n - _POW5_BITCOUNT) if n >= _POW5_BITCOUNT else p << (_POW5_BITCOUNT - n)
        pow_lo.append(v & mask)
        pow_hi.append(v >> 64)
    return tuple(np.array(a, dtype=np.uint64) for a in (inv_lo, inv_hi, pow_lo, pow_hi))


_INV_LO, _INV_HI, _POW_LO, _POW_HI = _tables()

_U32 = np.uint64(0xFFFFFFFF)


@njit(cache=True, inline="always")
def _umul128(a, b):
    """(high, low) 64-bit words of the 128-bit product of two uint64."""
    s32 = np.uint64(32)
    a_lo = a & _U32
    a_hi = a >> s32
    b_lo = b & _U32
    b_hi = b >> s32
    b00 = a_lo * b_lo
    b01 = a_lo * b_hi
    b10 = a_hi * b_lo
    b11 = a_hi * b_hi
    mid1 = b10 + (b00 >> s32)
    mid2 = b01 + (mid1 & _U32)
    hi = b11 + (mid1 >> s32) + (mid2 >> s32)
    lo = (mid2 << s32) | (b00 & _U32)
    return hi, lo


@njit(cache=True, inline="always")
def _mul_shift(m, mul_lo, mul_hi, j):
    """⌊m · mul / 2^j⌋ for 64 < j < 128 (mul 128-bit)."""
    high1, low1 = _umul128(m, mul_hi)
    high0, low0 = _umul128(m, mul_lo)
    s = high0 + low1
    if s < high0:
        high1 += np.uint64(1)
    dist = np.uint64(j - 64)
    return (high1 << (np.uint64(64) - dist)) | (s >> dist)


@njit(cache=True, inline="always")
def _pow5_factor(v):
    n = 0
    five = np.uint64(5)
    zero = np.uint64(0)
    while v % five == zero:
        v //= five
        n += 1
    return n


@njit(cache=True, inline="always")
def _pow5bits(e):
    return ((e * 1217359) >> 19) + 1


@njit(cache=True, inline="always")
def _shortest(bits, inv_lo, inv_hi, pow_lo, pow_hi):
    """Ryu's ``d2d``: (digits, decimal exponent) of a finite nonzero double's bit pattern."""
    mant = bits & np.uint64((1 << 52) - 1)
    ex = np.int64((bits >> np.uint64(52)) & np.uint64(0x7FF))
    one = np.uint64(1)
    zero = np.uint64(0)
    ten = np.uint64(10)
    if ex == 0:
        e2 = 1 - 1023 - 52 - 2
        m2 = mant
    else:
        e2 = ex - 1023 - 52 - 2
        m2 = (one << np.uint64(52)) | mant
    even = (m2 & one) == zero
    accept = even
    mv = np.uint64(4) * m2
    mm_shift = np.uint64(1) if (mant != zero or ex <= 1) else np.uint64(0)
    vm_tz = False
    vr_tz = False
    if e2 >= 0:
        q = ((e2 * 78913) >> 18) - (1 if e2 > 3 else 0)
        e10 = q
        k = _POW5_INV_BITCOUNT + _pow5bits(q) - 1
        i = -e2 + q + k
        vr = _mul_shift(mv, inv_lo[q], inv_hi[q], i)
        vp = _mul_shift(mv + np.uint64(2), inv_lo[q], inv_hi[q], i)
        vm = _mul_shift(mv - one - mm_shift, inv_lo[q], inv_hi[q], i)
        if q <= 21:
            if mv % np.uint64(5) == zero:
                vr_tz = _pow5_factor(mv) >= q
            elif accept:
                vm_tz = _pow5_factor(mv - one - mm_shift) >= q
            else:
                vp -= np.uint64(1 if _pow5_factor(mv + np.uint64(2)) >= q else 0)
    else:
        q = (((-e2) * 732923) >> 20) - (1 if -e2 > 1 else 0)
        e10 = q + e2
        i = -e2 - q
        k = _pow5bits(i) - _POW5_BITCOUNT
        j = q - k
        vr = _mul_shift(mv, pow_lo[i], pow_hi[i], j)
        vp = _mul_shift(mv + np.uint64(2), pow_lo[i], pow_hi[i], j)
        vm = _mul_shift(mv - one - mm_shift, pow_lo[i], pow_hi[i], j)
        if q <= 1:
            vr_tz = True
            if accept:
                vm_tz = mm_shift == one
            else:
                vp -= one
        elif q < 63:
            vr_tz = (mv & ((one << np.uint64(q)) - one)) == zero
    removed = 0
    last = zero
    if vm_tz or vr_tz:
        while vp // ten > vm // ten:
            vm_tz = vm_tz and vm % ten == zero
            vr_tz = vr_tz and last == zero
            last = vr % ten
            vr //= ten
            vp //= ten
            vm //= ten
            removed += 1
        if vm_tz:
            while vm % ten == zero:
                vr_tz = vr_tz and last == zero
                last = vr % ten
                vr //= ten
                vp //= ten
                vm //= ten
                removed += 1
        if vr_tz and last == np.uint64(5) and vr % np.uint64(2) == zero:
            last = np.uint64(4)  # exactly half way: to the even digit
        up = (vr == vm and (not accept or not vm_tz)) or last >= np.uint64(5)
        out = vr + (one if up else zero)
    else:
        up = False
        hundred = np.uint64(100)
        while vp // hundred > vm // hundred:
            up = vr % hundred >= np.uint64(50)
            vr //= hundred
            vp //= hundred
            vm //= hundred
            removed += 2
        while vp // ten > vm // ten:
            up = vr % ten >= np.uint64(5)
            vr //= ten
            vp //= ten
            vm //= ten
            removed += 1
        out = vr + (one if (vr == vm or up) else zero)
    return out, e10 + removed


@njit(cache=True, inline="always")
def _put_float(buf, pos, x, bits, inv_lo, inv_hi, pow_lo, pow_hi, digits):
    """Write ``repr(x)`` at ``buf[pos:]`` (``bits``: x's bit pattern); the new position."""
    if x != x:
        buf[pos] = 110  # n
        buf[pos + 1] = 97  # a
        buf[pos + 2] = 110
        return pos + 3
    if bits >> np.uint64(63):
        buf[pos] = 45  # -
        pos += 1
        x = -x
        bits &= np.uint64(0x7FFFFFFFFFFFFFFF)
    if x == np.inf:
        buf[pos] = 105  # i
        buf[pos + 1] = 110  # n
        buf[pos + 2] = 102  # f
        return pos + 3
    if x == 0:
        buf[pos] = 48
        buf[pos + 1] = 46
        buf[pos + 2] = 48
        return pos + 3
    out, e10 = _shortest(bits, inv_lo, inv_hi, pow_lo, pow_hi)
    n = 0
    ten = np.uint64(10)
    while out > np.uint64(0):  # digits, last first
        digits[n] = np.uint8(48 + np.int64(out % ten))
        out //= ten
        n += 1
    decpt = e10 + n  # the value is 0.d1d2...dn x 10^decpt
    if -4 < decpt <= 16:
        if decpt <= 0:
            buf[pos] = 48
            buf[pos + 1] = 46
            pos += 2
            for _ in range(-decpt):
                buf[pos] = 48
                pos += 1
            for i in range(n - 1, -1, -1):
                buf[pos] = digits[i]
                pos += 1
        elif decpt >= n:
            for i in range(n - 1, -1, -1):
                buf[pos] = digits[i]
                pos += 1
            for _ in range(decpt - n):
                buf[pos] = 48
                pos += 1
            buf[pos] = 46
            buf[pos + 1] = 48
            pos += 2
        else:
            for i in range(n - 1, -1, -1):
                buf[pos] = digits[i]
                pos += 1
                if n - 1 - i == decpt - 1:
                    buf[pos] = 46
                    pos += 1
        return pos
    buf[pos] = digits[n - 1]
    pos += 1
    if n > 1:
        buf[pos] = 46
        pos += 1
        for i in range(n - 2, -1, -1):
            buf[pos] = digits[i]
            pos += 1
    e = decpt - 1
    buf[pos] = 101  # e
    buf[pos + 1] = 45 if e < 0 else 43
    pos += 2
    if e < 0:
        e = -e
    if e >= 100:
        buf[pos] = 48 + e // 100
        pos += 1
    buf[pos] = 48 + (e // 10) % 10
    buf[pos + 1] = 48 + e % 10
    return pos + 2


@njit(cache=True, inline="always")
def _put_int(buf, pos, v, digits):
    if v == 0:
        buf[pos] = 48
        return pos + 1
    if v < 0:
        buf[pos] = 45
        pos += 1
        u = np.uint64(-(v + 1)) + np.uint64(1)  # |v|, also for -2^63
    else:
        u = np.uint64(v)
    n = 0
    ten = np.uint64(10)
    while u != np.uint64(0):
        digits[n] = np.uint8(48 + np.int64(u % ten))
        u //= ten
        n += 1
    for i in range(n - 1, -1, -1):
        buf[pos] = digits[i]
        pos += 1
    return pos


@njit(cache=True)
def _table_text(n, F, N, kind, idx, inv_lo, inv_hi, pow_lo, pow_hi):
    """The CSV text (uint8) of ``n`` rows.

    Column ``c`` is ``F[:, idx[c]]`` (``kind[c]`` 0: repr of a float) or ``N[:, idx[c]]``
    (1: an integer, 2: a boolean).
    """
    B = F.view(np.uint64)
    ncol = kind.shape[0]
    buf = np.empty(n * (25 * ncol + 2), dtype=np.uint8)
    digits = np.empty(24, dtype=np.uint8)
    pos = 0
    for r in range(n):
        for c in range(ncol):
            if c:
                buf[pos] = 44  # ,
                pos += 1
            k = kind[c]
            if k == 0:
                pos = _put_float(buf, pos, F[r, idx[c]], B[r, idx[c]], inv_lo, inv_hi, pow_lo,
                                 pow_hi, digits)
            elif k == 1:
                pos = _put_int(buf, pos, N[r, idx[c]], digits)
            elif N[r, idx[c]]:
                buf[pos] = 84  # True
                buf[pos + 1] = 114
                buf[pos + 2] = 117
                buf[pos + 3] = 101
                pos += 4
            else:
                buf[pos] = 70  # False
                buf[pos + 1] = 97
                buf[pos + 2] = 108
                buf[pos + 3] = 115
                buf[pos + 4] = 101
                pos += 5
        buf[pos] = 13
        buf[pos + 1] = 10
        pos += 2
    return buf[:pos]


def table_text(cols: list[np.ndarray]) -> str | None:
    r"""CSV rows of 1-D numeric columns as ``repr``/``str`` of each cell writes them.

    Cells joined with ``,``, rows ended by ``\r\n`` (the ``excel`` dialect's bytes for
    cells that need no quoting).  Floats (any width) as ``repr`` of the Python float,
    integers as ``str``, booleans as ``True``/``False``.  None without numba, or for a
    column of another kind or unsigned integers beyond int64.
    """
    if not HAVE_NUMBA or not cols:
        return None
    kinds = np.empty(len(cols), dtype=np.int8)
    idx = np.empty(len(cols), dtype=np.int64)
    fl, it = [], []
    for c, col in enumerate(cols):
        k = col.dtype.kind
        if k == "f":
            kinds[c], idx[c] = 0, len(fl)
            fl.append(col)
        elif k in "iub":
            if k == "u" and col.dtype.itemsize == 8 and len(col) and col.max() > 2 ** 63 - 1:
                return None
            kinds[c], idx[c] = (2 if k == "b" else 1), len(it)
            it.append(col)
        else:
            return None
    n = len(cols[0])
    F = np.empty((n, len(fl)), dtype=np.float64)
    for j, col in enumerate(fl):
        F[:, j] = col
    N = np.empty((n, len(it)), dtype=np.int64)
    for j, col in enumerate(it):
        N[:, j] = col
    buf = _table_text(n, F, N, kinds, idx, _INV_LO, _INV_HI, _POW_LO, _POW_HI)
    return buf.tobytes().decode("ascii")
