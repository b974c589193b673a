"""Shared form of the astrometric effects: where the tracker sees a star versus its J2000.0 place.

Not an effect module (the registry skips ``_`` modules): ``aberration.py``,
``refraction.py`` and ``proper_motion.py`` each subclass :class:`ScaledDirection`.  Each is a
DIRECTION-stage effect with one parameter, a *scale* of the physical effect
(0 = absent, 1 = as physics predicts): ``u' = u + s · Δ(u)`` where ``Δ`` is the full
correction computed by :mod:`stellar_cal_ros.core.astrometry` (pyerfa).  Estimating the
scale tells the user whether the effect is present, and how strongly, without fitting any
free-form correction.

``Δ`` is a function of each star alone (its direction, catalogue number, the frame's time,
site and weather), written once per effect (:meth:`ScaledDirection.delta_stars`, arrays
with one entry per star).  A frame's ``Δ`` is that function of the frame's stars; a whole
bag's (:meth:`ScaledDirection.prepare`, before a replay of data in memory) is the same
function of all its stars at once — pyerfa's per-call overhead, not its arithmetic, was
the cost (1.2 ms per frame for the aberration) — and the frames then look their rows up.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stellar_cal_ros.core.earth import Site
from stellar_cal_ros.effects.base import Effect, ExportRole, FrameContext, Plausible, Stage

#: a frame of this many stars or fewer is computed, not looked up: pyerfa's
#: precession-nutation is then evaluated exactly, for more it is interpolated on a grid
#: (:func:`stellar_cal_ros.core.earth._c2i`, 9e-13 rad) — as in the whole bag's call
_EXACT_BELOW = 4
#: a looked-up star must be this close to the prepared one (unit vector; the same
#: right ascension and declination turned into a vector by another routine differ by ulps)
_SAME_STAR = 1e-12


@dataclass
class _Prepared:
    """One frame's stars in the table of :meth:`ScaledDirection.prepare` (views of it)."""

    ids: np.ndarray  #: catalogue numbers (unique, nonzero)
    u: np.ndarray  #: (n, 3) their directions
    delta: np.ndarray  #: (n, 3) their Δ
    weather: tuple[float, float]  #: pressure (Pa), air temperature (°C) it was made with


class Stacked:
    """The identified stars of a bag's frames in a few arrays, looked up by stamp.

    Every kept frame's stars are rows ``start[j]:start[j + 1]`` of ``ids`` and ``u``; a
    frame is found by its stamp (POSIX s; of frames with the same stamp, the last).  A
    frame whose numbers are not unique and nonzero is left out.  Made once per bag
    (:meth:`~stellar_cal_ros.methods.star_model.StarModel.prepare_frames`) and shared by the
    direction effects' tables (:class:`_Table`), which add their Δ only: on a 2-h bag each
    effect's own copy of the stars and the stamps' lookup was ≈ 9 MB, held through the
    round's screening runs.
    """

    def __init__(self, stamps: np.ndarray, catalog_ids: list[np.ndarray] | np.ndarray,
                 u: list[np.ndarray] | np.ndarray, pressure_pa: np.ndarray,
                 air_temperature_c: np.ndarray, counts: np.ndarray | None = None) -> None:
        """The stars of frames at ``stamps`` (POSIX s).

        ``catalog_ids``, ``u``: per frame its numbers and directions, or with ``counts``
        (F,) every frame's stacked (``counts[j]`` rows each: one array, no list of them).
        """
        if counts is None:
            counts = np.array([len(ids) for ids in catalog_ids], dtype=np.int64)
            catalog_ids = np.concatenate([np.zeros(0, np.int64)] + [
                np.asarray(ids, dtype=np.int64).reshape(-1) for ids in catalog_ids])
            u = np.concatenate([np.zeros((0, 3))] + [np.asarray(x, dtype=float).reshape(-1, 3)
                                                      for x in u])
        counts = np.asarray(counts, dtype=np.int64)
        ids = np.asarray(catalog_ids, dtype=np.int64).reshape(-1)
        # a frame is kept when its numbers are nonzero and unique: the rows sorted by frame
        # and number, a number repeated in a frame is one equal to its neighbour
        frame = np.repeat(np.arange(len(counts)), counts)
        bad = np.zeros(len(counts), dtype=bool)
        bad[frame[ids <= 0]] = True
        order = np.lexsort((ids, frame))
        f_sorted, i_sorted = frame[order], ids[order]
        bad[f_sorted[1:][(f_sorted[1:] == f_sorted[:-1]) & (i_sorted[1:] == i_sorted[:-1])]] = True
        keep = (counts > 0) & ~bad
        rows = np.repeat(keep, counts)
        self.count = counts[keep]
        kk = np.flatnonzero(keep)
        self.stamps = np.asarray(stamps, dtype=float)[kk]
        self.weather = np.stack([np.asarray(pressure_pa, dtype=float)[kk],
                                 np.asarray(air_temperature_c, dtype=float)[kk]], axis=1)
        self.ids = ids[rows]
        self.u = np.asarray(u, dtype=float).reshape(-1, 3)[rows]
        self.start = np.concatenate([[0], np.cumsum(self.count)])
        self._row = {t: j for j, t in enumerate(self.stamps.tolist())}  # a stamp's last frame
        self._order: dict[int, np.ndarray] = {}  # argsort of a frame's ids, made when needed

    def __len__(self) -> int:
        return len(self._row)

    def per_star(self, values: np.ndarray) -> np.ndarray:
        """``values`` (one per kept frame) repeated for each of its stars."""
        return np.repeat(values, self.count)


class _Table:
    """One effect's Δ of the stars of :class:`Stacked`, looked up by stamp.

    One object per frame (a dataclass and three views, ≈ 0.6 kB a frame and effect: 27 MB
    for the three direction effects of a 2-h bag, held through a diagnosis round) is made
    only when a frame is looked up (:meth:`get`), and dropped with it.
    """

    def __init__(self, stacked: Stacked, delta: np.ndarray) -> None:
        self.stacked, self.delta = stacked, delta

    def __len__(self) -> int:
        return len(self.stacked)

    @property
    def start(self) -> np.ndarray:
        """The frames' first rows (and the last's end), :class:`Stacked`'s."""
        return self.stacked.start

    @property
    def ids(self) -> np.ndarray:
        """The stars' catalogue numbers, :class:`Stacked`'s."""
        return self.stacked.ids

    @property
    def u(self) -> np.ndarray:
        """The stars' directions (n, 3), :class:`Stacked`'s."""
        return self.stacked.u

    @property
    def weather(self) -> np.ndarray:
        """Each frame's pressure (Pa) and air temperature (°C), :class:`Stacked`'s."""
        return self.stacked.weather

    def get(self, stamp: float) -> _Prepared | None:
        """The frame of ``stamp`` (None: not prepared)."""
        st = self.stacked
        j = st._row.get(stamp)
        if j is None:
            return None
        sl = slice(int(st.start[j]), int(st.start[j + 1]))
        return _Prepared(st.ids[sl], st.u[sl], self.delta[sl],
                         (float(st.weather[j, 0]), float(st.weather[j, 1])))

    def __getitem__(self, stamp: float) -> _Prepared:
        got = self.get(stamp)
        if got is None:
            raise KeyError(stamp)
        return got

    def items(self):
        """``(stamp, frame)`` of every prepared frame."""
        return ((t, self.get(t)) for t in self.stacked._row)

    def order(self, stamp: float) -> np.ndarray:
        """The argsort of the ids of the frame of ``stamp`` (made once, shared)."""
        st = self.stacked
        j = st._row[stamp]
        if j not in st._order:
            st._order[j] = np.argsort(self[stamp].ids, kind="stable")
        return st._order[j]


def _same_floats(a: tuple[float, ...], b: tuple[float, ...]) -> bool:
    """Equal, NaN equal to NaN."""
    return all(x == y or (x != x and y != y) for x, y in zip(a, b, strict=True))


class ScaledDirection(Effect):
    """``u' = u + s · Δ(u)``: one parameter, the scale of a correction physics fixes (1)."""

    stage = Stage.DIRECTION
    parameter_names = ("scale",)
    units = ("1",)
    default_sigma = (1.0,)
    physical_value = 1.0
    display_units = ("x physical", 1.0)
    plausible = Plausible(1.0, "x physical")
    export_role = ExportRole.STAR_DIRECTIONS
    #: Δ depends on the pressure and air temperature of the frame context
    uses_weather = False

    def delta_stars(self, u: np.ndarray, t: np.ndarray, catalog_id: np.ndarray,
                    site: Site | None, pressure_pa: np.ndarray,
                    air_temperature_c: np.ndarray) -> np.ndarray:
        """Full (scale 1) correction (n, 3) of stars ``u`` (n, 3) at POSIX times ``t`` (n,).

        ``catalog_id`` (n,) or empty (no identifications); ``pressure_pa`` and
        ``air_temperature_c`` (n,), NaN where unknown.
        """
        raise NotImplementedError

    def delta(self, u_i: np.ndarray, ctx: FrameContext) -> np.ndarray:
        """Full (scale 1) correction of one frame's directions (n, 3)."""
        n = len(u_i)
        return self.delta_stars(u_i, np.full(n, ctx.stamp), np.asarray(ctx.catalog_id),
                                ctx.site, np.full(n, ctx.pressure_pa),
                                np.full(n, ctx.air_temperature_c))

    # ------------------------------------------------------------------ a whole bag
    def prepare(self, stamps: np.ndarray, catalog_ids: list[np.ndarray], u: list[np.ndarray],
                site: Site | None, pressure_pa: np.ndarray,
                air_temperature_c: np.ndarray) -> None:
        """Compute Δ of every star of every frame in one call (frames then look it up).

        ``stamps`` (F,) POSIX s; per frame its catalogue numbers and directions (identified
        stars); ``pressure_pa``, ``air_temperature_c`` (F,).  A frame whose numbers are not
        unique and nonzero is left out (computed when it comes).  A frame whose context
        differs from what was prepared (another site or weather, a star not in the table,
        :data:`_EXACT_BELOW` stars or fewer) is computed as before: the table changes no
        number (one call for many stars computes each star as its frame's call does).
        """
        self.prepare_stacked(Stacked(stamps, catalog_ids, u, pressure_pa, air_temperature_c),
                             site)

    def prepare_stacked(self, stacked: Stacked, site: Site | None) -> None:
        """:meth:`prepare` of stars already stacked (shared with the other effects' tables)."""
        self._site, self._table = site, None
        if not len(stacked):
            return
        d = self.delta_stars(stacked.u, stacked.per_star(stacked.stamps), stacked.ids, site,
                             stacked.per_star(stacked.weather[:, 0]),
                             stacked.per_star(stacked.weather[:, 1]))
        self._table = _Table(stacked, d)

    def prepared_table(self) -> tuple[Site | None, _Table | None]:
        """What :meth:`prepare` made (the site and the table).

        Another instance of this class takes it (:meth:`use_prepared`) for the same bag
        instead of calling pyerfa again.
        """
        return self._site, self._table

    def use_prepared(self, made: tuple[Site | None, _Table | None]) -> None:
        """Take :meth:`prepared_table` of another instance of this class on the same bag.

        Δ is a function of the stars, times, site and weather alone (not of the scale):
        the table is the same numbers :meth:`prepare` would compute; it is only read.
        """
        self._site, self._table = made

    def _prepared(self, u: np.ndarray, ctx: FrameContext) -> np.ndarray | None:
        """The frame's Δ from the table of :meth:`prepare`, or None."""
        # (:meth:`_Table.get`'s rows, read in place: this runs for each frame and effect)
        table = getattr(self, "_table", None)
        st = table.stacked if table else None
        j = st._row.get(float(ctx.stamp)) if st is not None else None
        if j is None or ctx.site != self._site:
            return None
        if self.uses_weather and not _same_floats(
                (float(st.weather[j, 0]), float(st.weather[j, 1])),
                (ctx.pressure_pa, ctx.air_temperature_c)):
            return None
        ids = np.asarray(ctx.catalog_id).reshape(-1)
        if len(ids) != len(u) or len(u) <= _EXACT_BELOW:
            return None
        a, b = st.start[j:j + 2].tolist()
        hit_ids = st.ids[a:b]
        if len(ids) == b - a and bool((ids == hit_ids).all()):
            rows = st.u[a:b], table.delta[a:b]  # every star of the frame (the usual case)
        else:
            order = table.order(float(ctx.stamp))
            k = np.searchsorted(hit_ids, ids, sorter=order)
            pos = order[np.minimum(k, len(hit_ids) - 1)]
            if np.any(hit_ids[pos] != ids):
                return None
            rows = st.u[a:b][pos], table.delta[a:b][pos]
        if float(np.abs(rows[0] - u).max()) > _SAME_STAR:
            return None
        return rows[1]

    def _cached_delta(self, u_i: np.ndarray, ctx: FrameContext) -> np.ndarray:
        # One entry per effect, keyed by the *content* of everything delta() reads: a key
        # on id(u_i) returned stale (even wrongly shaped) corrections when a caller passed
        # a subset u_i[mask] with the same context and Python reused a freed array's id.
        u = np.ascontiguousarray(u_i, dtype=float)
        key = (
            u.shape, u.tobytes(),
            np.ascontiguousarray(ctx.catalog_id, dtype=np.int64).tobytes(),
            float(ctx.stamp), ctx.site,
            *(float(x) if np.isfinite(x) else None
              for x in (ctx.pressure_pa, ctx.air_temperature_c)),
        )
        cache = ctx.extra.setdefault("_direction_cache", {})
        hit = cache.get(self.id)
        if hit is None or hit[0] != key:
            d = self._prepared(u, ctx)
            hit = (key, self.delta(u, ctx) if d is None else d)
            cache[self.id] = hit
        return hit[1]

    def delta_frames(self, us: list, u: np.ndarray, offs: np.ndarray, ctxs: list
                     ) -> np.ndarray:
        """The Δ of several frames (:meth:`_cached_delta` of each), stacked (N, 3).

        ``us``: each frame's directions (its rows ``offs[i]:offs[i + 1]`` of ``u``, (N, 3),
        the frames stacked); ``ctxs`` their contexts.  A frame whose stars are all those of
        its row of the table, in order, with the table's site and weather (the usual case,
        :meth:`_prepared`'s first branch) takes its rows of the table in one gather for all
        such frames — the same floats, without a key and a lookup a frame and effect (a
        2-h bag's batched replay: 14 400 frames an effect); any other frame goes through
        :meth:`_cached_delta` as before.
        """
        K = len(ctxs)
        out = np.empty((len(u), 3))
        table = getattr(self, "_table", None)
        fast = np.zeros(K, dtype=bool)
        if table is not None and K:
            st, site = table.stacked, self._site
            row = st._row
            n = np.diff(offs)
            js = np.array([row.get(float(c.stamp), -1) if c.site is site or c.site == site
                           else -1 for c in ctxs], dtype=np.int64)
            ids = [np.asarray(c.catalog_id).reshape(-1) for c in ctxs]
            fast = (js >= 0) & (n > _EXACT_BELOW) & \
                (np.fromiter(map(len, ids), dtype=np.int64, count=K) == n)
            fast &= st.count[np.where(fast, js, 0)] == n
            if self.uses_weather and fast.any():
                w = st.weather[np.where(fast, js, 0)]
                p = np.array([c.pressure_pa for c in ctxs], dtype=float)
                a = np.array([c.air_temperature_c for c in ctxs], dtype=float)
                fast &= ((w[:, 0] == p) | (np.isnan(w[:, 0]) & np.isnan(p))) & \
                    ((w[:, 1] == a) | (np.isnan(w[:, 1]) & np.isnan(a)))
            if fast.any():
                which = np.flatnonzero(fast)
                take = np.repeat(fast, n)  # the stacked rows of those frames
                rows = np.repeat(st.start[js[which]] - offs[which], n[which]) + \
                    np.flatnonzero(take)
                cat = np.concatenate([ids[i] for i in which.tolist()])
                same = st.ids[rows] == cat
                # (conservative: a NaN direction, which _prepared passes, goes frame by frame)
                near = np.abs(st.u[rows] - u[take]) <= _SAME_STAR
                if not (same.all() and near.all()):  # some frame is not its table row
                    bad = ~(same & near[:, 0] & near[:, 1] & near[:, 2])
                    fast[which[np.flatnonzero(np.bincount(
                        np.repeat(np.arange(len(which)), n[which]), weights=bad,
                        minlength=len(which)))]] = False
                    keep = fast[np.repeat(which, n[which])]
                    take[take] = keep
                    rows = rows[keep]
                out[take] = table.delta[rows]
        for i in np.flatnonzero(~fast).tolist():
            out[offs[i]:offs[i + 1]] = self._cached_delta(us[i], ctxs[i])
        return out

    def directions_jacobian_frames(self, value, us: list, u: np.ndarray, offs: np.ndarray,
                                   ctxs: list) -> np.ndarray:
        """:meth:`directions_jacobian` of several frames, stacked (N, 3, 1) (:meth:`delta_frames`).

        None when a subclass computes its Jacobian otherwise (the caller then asks frame by
        frame).
        """
        if type(self).directions_jacobian is not ScaledDirection.directions_jacobian or \
                type(self)._cached_delta is not ScaledDirection._cached_delta:
            return None
        return self.delta_frames(us, u, offs, ctxs)[:, :, None]

    def directions(self, value, u_i, ctx):  # noqa: D102
        return u_i + value[0] * self._cached_delta(u_i, ctx)

    def directions_jacobian(self, value, u_i, ctx):  # noqa: D102
        return self._cached_delta(u_i, ctx)[:, :, None]

    def affine_form(self):  # noqa: D102 - u' = u + s Δ(u, ctx): Δ comes with the frame
        return True
