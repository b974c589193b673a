"""The distribution functions the package uses, from :mod:`scipy.special`, without ``scipy.stats``.

Importing ``scipy.stats`` costs ≈ 20 MiB of a 2-h ``diagnose`` round's RSS (issue 24.2) for
a dozen functions that ``scipy.stats`` itself computes with :mod:`scipy.special`'s ufuncs.
Each name here (:data:`chi2`, :data:`ncx2`, :data:`norm`, :data:`t`, :data:`f`,
:data:`nct`, :data:`binom`) offers the methods of its ``scipy.stats`` namesake that the
package calls, with the same shape arguments (no ``loc``/``scale``, but for ``norm.pdf``)
and the same values: the ufunc ``scipy.stats`` calls (scipy 1.17) on the arguments inside
the support, and the values its generic wrappers give elsewhere — 1 or 0 at and beyond the
support's ends, nan for a shape out of range or a nan argument, a scalar for scalar
arguments.  :func:`rankdata` ranks as ``scipy.stats.rankdata`` does (ties share their mean
rank, a nan makes every rank nan).  ``test/test_distributions.py`` holds every function to
``scipy.stats`` over a grid that includes the edges.

Where scipy lacks one of the private boost ufuncs (``_ncx2_sf``, ``_nct_sf``, ``_binom_sf``:
an older scipy), that function asks ``scipy.stats`` itself.
"""

from __future__ import annotations

from collections.abc import Callable
from types import SimpleNamespace

import numpy as np
from scipy import special
from scipy.special import _ufuncs

_NORM_PDF_C = np.sqrt(2 * np.pi)  # scipy.stats' _norm_pdf_C


def _scalar_or_array(out: np.ndarray):
    """A 0-d result as its scalar, as ``scipy.stats`` returns it."""
    return out[()] if out.ndim == 0 else out


def _positive(*shapes: np.ndarray) -> np.ndarray:
    """``rv_continuous``'s default shape check: every shape > 0."""
    ok = np.asarray(True)
    for s in shapes:
        ok = ok & (s > 0)
    return ok


def _of_x(fn: Callable, x, shapes: tuple, check: Callable, support: tuple[float, float],
          edge: str):
    """``rv_continuous.sf`` (``edge`` 'sf') or ``.cdf`` ('cdf') of ``fn`` (loc 0, scale 1).

    0 outside the support, 1 at and below its lower end ('sf') or at and above its upper
    end ('cdf'), nan where a shape fails ``check`` or ``x`` is nan, ``fn`` strictly inside.
    """
    x = np.asarray(x)
    x = np.asarray(x, dtype=np.promote_types(x.dtype, np.float64))
    x, *shapes = np.broadcast_arrays(x, *(np.asarray(s) for s in shapes))
    ok = np.broadcast_to(check(*shapes), x.shape)
    lo, hi = support
    out = np.zeros(x.shape, dtype=x.dtype)
    out[~ok | np.isnan(x)] = np.nan
    out[ok & ((x <= lo) if edge == "sf" else (x >= hi))] = 1.0
    inside = ok & (lo < x) & (x < hi)
    if inside.any():
        out[inside] = fn(x[inside], *(s[inside] for s in shapes))
    return _scalar_or_array(out)


def _of_q(fn: Callable, q, shapes: tuple, check: Callable, at_0: float, at_1: float):
    """``rv_continuous.ppf``/``.isf`` of ``fn``: ``at_0``/``at_1`` at q = 0/1, nan outside [0, 1].

    Strictly inside, ``fn(q) * 1 + 0`` as scipy's ``* scale + loc`` (a −0 becomes 0).
    """
    q, *shapes = np.broadcast_arrays(np.asarray(q), *(np.asarray(s) for s in shapes))
    ok = np.broadcast_to(check(*shapes), q.shape)
    out = np.full(q.shape, np.nan)
    out[ok & (q == 0)] = at_0
    out[ok & (q == 1)] = at_1
    inside = ok & (0 < q) & (q < 1)
    if inside.any():
        out[inside] = fn(q[inside], *(s[inside] for s in shapes)) * 1.0 + 0.0
    return _scalar_or_array(out)


def _from_stats(name: str, method: str, *args):
    """``scipy.stats.<name>.<method>(*args)``: where this scipy lacks a private ufunc."""
    from scipy import stats  # only an older scipy gets here

    return getattr(getattr(stats, name), method)(*args)


# ---- χ² ------------------------------------------------------------------------------------

def chi2_sf(x, df):
    """``scipy.stats.chi2.sf(x, df)``: ``chdtrc(df, x)``."""
    return _of_x(lambda x, df: special.chdtrc(df, x), x, (df,), _positive, (0.0, np.inf), "sf")


def chi2_isf(p, df):
    """``scipy.stats.chi2.isf(p, df)``: ``chdtri(df, p)``."""
    return _of_q(lambda p, df: special.chdtri(df, p), p, (df,), _positive, np.inf, 0.0)


def chi2_ppf(p, df):
    """``scipy.stats.chi2.ppf(p, df)``: ``2 gammaincinv(df / 2, p)`` (not ``chdtri(df, 1 − p)``)."""
    return _of_q(lambda p, df: 2 * special.gammaincinv(df / 2, p), p, (df,), _positive,
                 0.0, np.inf)


def _ncx2_check(df, nc):
    return (df > 0) & np.isfinite(df) & (nc >= 0)


def _ncx2_sf_inside(x, df, nc):
    out = np.empty(x.shape)
    central = nc == 0
    out[central] = special.chdtrc(df[central], x[central])
    with np.errstate(over="ignore"):  # as scipy.stats (its gh-17432)
        out[~central] = _ufuncs._ncx2_sf(x[~central], df[~central], nc[~central])
    return out


def ncx2_sf(x, df, nc):
    """``scipy.stats.ncx2.sf(x, df, nc)``: boost's ``_ncx2_sf`` (``chdtrc`` at nc = 0)."""
    if not hasattr(_ufuncs, "_ncx2_sf"):
        return _from_stats("ncx2", "sf", x, df, nc)
    return _of_x(_ncx2_sf_inside, x, (df, nc), _ncx2_check, (0.0, np.inf), "sf")


# ---- normal, t, F, non-central t ---------------------------------------------------------

def _any_shape(*shapes):
    return np.asarray(True)


def norm_sf(x):
    """``scipy.stats.norm.sf(x)``: ``ndtr(−x)``."""
    return _of_x(lambda x: special.ndtr(-x), x, (), _any_shape, (-np.inf, np.inf), "sf")


def norm_ppf(q):
    """``scipy.stats.norm.ppf(q)``: ``ndtri(q)``."""
    return _of_q(special.ndtri, q, (), _any_shape, -np.inf, np.inf)


def norm_isf(q):
    """``scipy.stats.norm.isf(q)``: ``−ndtri(q)``."""
    return _of_q(lambda q: -special.ndtri(q), q, (), _any_shape, np.inf, -np.inf)


def norm_pdf(x, loc=0.0, scale=1.0):
    """``scipy.stats.norm.pdf(x, loc, scale)``: ``exp(−z²/2) / √(2π) / scale``."""
    x = np.asarray(x)
    z = np.asarray((x - loc) / scale, dtype=np.promote_types(x.dtype, np.float64))
    z, scale = np.broadcast_arrays(z, np.asarray(scale))
    ok = scale > 0
    out = np.zeros(z.shape, dtype=z.dtype)
    out[~ok | np.isnan(z)] = np.nan
    good = ok & (-np.inf <= z) & (z <= np.inf)
    if good.any():
        zg = z[good]
        out[good] = np.exp(-zg**2 / 2.0) / _NORM_PDF_C / scale[good]
    return _scalar_or_array(out)


def t_sf(x, df):
    """``scipy.stats.t.sf(x, df)``: ``stdtr(df, −x)``."""
    return _of_x(lambda x, df: special.stdtr(df, -x), x, (df,), _positive,
                 (-np.inf, np.inf), "sf")


def t_cdf(x, df):
    """``scipy.stats.t.cdf(x, df)``: ``stdtr(df, x)``."""
    return _of_x(lambda x, df: special.stdtr(df, x), x, (df,), _positive,
                 (-np.inf, np.inf), "cdf")


def t_isf(q, df):
    """``scipy.stats.t.isf(q, df)``: ``−stdtrit(df, q)``."""
    return _of_q(lambda q, df: -special.stdtrit(df, q), q, (df,), _positive, np.inf, -np.inf)


def f_sf(x, dfn, dfd):
    """``scipy.stats.f.sf(x, dfn, dfd)``: ``fdtrc(dfn, dfd, x)``."""
    return _of_x(lambda x, a, b: special.fdtrc(a, b, x), x, (dfn, dfd), _positive,
                 (0.0, np.inf), "sf")


def _nct_sf_inside(x, df, nc):
    with np.errstate(over="ignore", invalid="ignore"):  # as scipy.stats
        return np.clip(_ufuncs._nct_sf(x, df, nc), 0, 1)


def nct_sf(x, df, nc):
    """``scipy.stats.nct.sf(x, df, nc)``: boost's ``_nct_sf`` clipped to [0, 1]."""
    if not hasattr(_ufuncs, "_nct_sf"):
        return _from_stats("nct", "sf", x, df, nc)
    return _of_x(_nct_sf_inside, x, (df, nc), lambda df, nc: (df > 0) & (nc == nc),
                 (-np.inf, np.inf), "sf")


# ---- binomial ----------------------------------------------------------------------------

def binom_sf(k, n, p):
    """``scipy.stats.binom.sf(k, n, p)``: boost's ``_binom_sf(⌊k⌋, n, p)`` clipped to [0, 1].

    1 below 0, 0 from ``n`` on, nan for ``n`` not a whole number ≥ 0, ``p`` outside [0, 1]
    or a nan ``k``.
    """
    if not hasattr(_ufuncs, "_binom_sf"):
        return _from_stats("binom", "sf", k, n, p)
    k, n, p = np.broadcast_arrays(np.asarray(k), np.asarray(n), np.asarray(p))
    ok = (n >= 0) & (n == np.round(n)) & (p >= 0) & (p <= 1)
    out = np.zeros(k.shape, "d")
    out[~ok | np.isnan(k)] = np.nan
    out[((k < 0) | np.isneginf(k)) & ok] = 1.0
    inside = ok & (k >= 0) & (k < n) & np.isfinite(k)
    if inside.any():
        out[inside] = np.clip(_ufuncs._binom_sf(np.floor(k[inside]), n[inside], p[inside]),
                              0, 1)
    return _scalar_or_array(out)


# ---- ranks -------------------------------------------------------------------------------

def rankdata(x) -> np.ndarray:
    """``scipy.stats.rankdata(x)`` (flattened; ties share their mean rank; any nan: all nan)."""
    x = np.ravel(np.asarray(x))
    if x.size and np.isnan(x).any():
        return np.full(x.shape, np.nan)
    j = np.argsort(x, kind="stable")
    y = x[j]
    first = np.r_[True, y[:-1] != y[1:]] if x.size else np.zeros(0, bool)
    starts = np.flatnonzero(first)
    counts = np.diff(starts, append=x.size)
    ranks = np.repeat(starts + 1.0 + (counts - 1.0) / 2, counts)
    out = np.empty(x.shape)
    out[j] = ranks
    return out


#: ``scipy.stats.chi2``'s ``sf``, ``isf``, ``ppf``
chi2 = SimpleNamespace(sf=chi2_sf, isf=chi2_isf, ppf=chi2_ppf)
#: ``scipy.stats.ncx2``'s ``sf``
ncx2 = SimpleNamespace(sf=ncx2_sf)
#: ``scipy.stats.norm``'s ``sf``, ``ppf``, ``isf``, ``pdf``
norm = SimpleNamespace(sf=norm_sf, ppf=norm_ppf, isf=norm_isf, pdf=norm_pdf)
#: ``scipy.stats.t``'s ``sf``, ``cdf``, ``isf``
t = SimpleNamespace(sf=t_sf, cdf=t_cdf, isf=t_isf)
#: ``scipy.stats.f``'s ``sf``
f = SimpleNamespace(sf=f_sf)
#: ``scipy.stats.nct``'s ``sf``
nct = SimpleNamespace(sf=nct_sf)
#: ``scipy.stats.binom``'s ``sf``
binom = SimpleNamespace(sf=binom_sf)
