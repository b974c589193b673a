"""Figures of a calibration run, at mrcal's and Kalibr's level (matplotlib, Agg backend).

Every function takes data — a residual table (:data:`~stellar_cal_ros.methods.replay.
RESIDUAL_COLUMNS`, ``t`` in POSIX s), a history table (one row per update: ``t``, ``nis``,
``dof`` and every parameter ``effect.parameter`` with ``sigma.effect.parameter``), a
calibration, a diagnosis summary — and writes one PNG.  ``panels`` are ``[(title, table),
...]``: one panel per run (e.g. the current model and the model with an added effect), drawn
side by side with **one** colour scale and one reference arrow.

The HTML pages that put them together are in :mod:`stellar_cal_ros.diagnosis.report_html`
(:func:`write_run_report`, :func:`write_compare_report`, :func:`write_html`), which imports
this module (not the other way round).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib import colors  # noqa: E402

from stellar_cal_ros.core import distributions as dist  # noqa: E402
from stellar_cal_ros.diagnosis import reliability, stats  # noqa: E402
from stellar_cal_ros.effects import registry  # noqa: E402
from stellar_cal_ros.effects.base import UNIT_DISPLAY, unit_factor  # noqa: E402

Table = dict[str, np.ndarray]
Panels = Sequence[tuple[str, Table]]

RAD_TO_DEG = 180.0 / np.pi
ARCSEC_PER_RAD = RAD_TO_DEG * 3600.0

#: axis label of each regressor of :func:`stats.regressors` (the values are converted by
#: :data:`REGRESSOR_SCALE` first)
REGRESSOR_LABELS = {
    "time": "time since the first frame, s",
    "magnitude": "star magnitude, mag",
    "u (column)": "u (column), px",
    "v (row)": "v (row), px",
    "radius": "distance from the principal point, px",
    "angular rate": "angular rate, deg/s",
    "head temperature": "optical head temperature, °C",
    "elevation": "star elevation, deg",
    "gravity_x_st": "gravity direction, x in the tracker frame (unit vector)",
    "gravity_y_st": "gravity direction, y in the tracker frame (unit vector)",
    "rotation_angle": "rotation angle, deg",
}
REGRESSOR_SCALE = {"angular rate": RAD_TO_DEG}

#: axis label of each residual component of the regressor tests
COMPONENT_LABELS = {"u": "u innovation, px", "v": "v innovation, px",
                    "radial": "radial innovation (outwards), px",
                    "size": "innovation length |Δuv|, px"}


def _save(fig: Any, path: Path, dpi: int = 90) -> Path:
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return Path(path)


def _nis(res: Table) -> np.ndarray:
    """Per-star NIS (2 dof): the table's, else from the whitened innovations."""
    if "nis" in res:
        return np.asarray(res["nis"], dtype=float)
    w = stats.whitened(res)
    return np.sum(w**2, axis=1)


#: columns :func:`stats.regressors` reads that a batch (ACF) residual table lacks
_REGRESSOR_COLUMNS = ("magnitude", "omega_x", "omega_y", "omega_z", "head_temperature")


def _complete(res: Table) -> Table:
    """The table with NaN columns for the regressors it lacks (they are then not drawn)."""
    missing = [k for k in _REGRESSOR_COLUMNS if k not in res]
    if not missing:
        return res
    n = len(res["t"])
    return {**res, **{k: np.full(n, np.nan) for k in missing}}


def _eval(res: Table, fraction: float) -> np.ndarray:
    """Accepted stars of the evaluation window."""
    return stats.evaluation_mask(res, fraction) & stats.accepted(res)


def display_unit(name: str, unit: str) -> tuple[float, str]:
    """Factor and unit to show a parameter in, as its effect's class declares it.

    Arcsec, deg/h, ug, ppm, mrad, ms where apt; a name of no known effect by ``unit``.
    """
    effect_id = name.split(".", 1)[0]
    if effect_id in registry.EFFECTS or effect_id == "equivalent_principal_point":
        shown, factor = reliability.display_unit(name)
        return factor, shown
    shown = UNIT_DISPLAY.get(unit, unit)
    return (unit_factor(unit, shown) if shown and unit else 1.0), shown


def parameter_unit(name: str) -> str:
    """The effect's unit of ``effect.parameter`` ('' if the effect is unknown)."""
    from stellar_cal_ros.io.covariance_file import parameter_unit as unit_of

    return unit_of(name)


# ------------------------------------------------------------------------------ histograms
def plot_histograms(panels: Panels, fraction: float, path: Path) -> Path:
    """Innovations against the noise the model expects.

    Left: whitened innovations ``L⁻¹ν`` (both axes) against N(0, 1); right: raw ``du, dv``
    against N(0, σ) with σ the RMS the model expects.  One row per panel.
    """
    fig, axes = plt.subplots(len(panels), 2, figsize=(11, 3.4 * len(panels)), squeeze=False)
    for row, (title, res) in zip(axes, panels, strict=True):
        m = _eval(res, fraction)
        if not np.any(m):
            row[0].set_title(f"{title}: no accepted stars")
            continue
        w = stats.whitened({k: np.asarray(v)[m] for k, v in res.items()}).ravel()
        lim = max(5.0, float(np.percentile(np.abs(w), 99.5)))
        bins = np.linspace(-lim, lim, 81)
        row[0].hist(w, bins=bins, density=True, color="C0", alpha=0.6, label="measured")
        x = np.linspace(-lim, lim, 400)
        row[0].plot(x, dist.norm.pdf(x), "k-", lw=1.2, label="N(0, 1) expected")
        row[0].set_yscale("log")
        row[0].set_ylim(1e-4, 1.0)
        row[0].set_xlabel("normalized innovation (whitened by its covariance), σ")
        row[0].set_ylabel("density")
        row[0].set_title(f"{title}: normalized, std {np.std(w):.2f} (expected 1)")
        row[0].legend(fontsize=8)
        du, dv = np.asarray(res["du"])[m], np.asarray(res["dv"])[m]
        exp = stats.expected_rms(res, m)
        lim = max(float(np.percentile(np.abs(np.r_[du, dv]), 99.5)), 4 * max(exp))
        bins = np.linspace(-lim, lim, 81)
        x = np.linspace(-lim, lim, 400)
        for comp, y, s, c in (("du", du, exp[0], "C0"), ("dv", dv, exp[1], "C1")):
            row[1].hist(y, bins=bins, density=True, histtype="step", color=c, lw=1.3,
                        label=f"{comp}: RMS {np.sqrt(np.mean(y**2)):.4f} px")
            row[1].plot(x, dist.norm.pdf(x, 0, s), color=c, ls="--", lw=1,
                        label=f"expected N(0, {s:.4f} px)")
        row[1].set_yscale("log")
        row[1].set_ylim(1e-3 / max(exp), 1.0 / min(exp))
        row[1].set_xlabel("innovation (measured − predicted), px")
        row[1].set_ylabel("density")
        row[1].set_title(f"{title}: in pixels")
        row[1].legend(fontsize=8)
    fig.tight_layout()
    return _save(fig, path)


# ------------------------------------------------------------------------------ vector fields
def _binned_field(res: Table, mask: np.ndarray, width: int, height: int, bins: int = 8):
    m = mask & stats.accepted(res)
    u, v, du, dv = res["u"][m], res["v"][m], res["du"][m], res["dv"][m]
    iu = np.clip((u / width * bins).astype(int), 0, bins - 1)
    iv = np.clip((v / height * bins).astype(int), 0, bins - 1)
    k = iv * bins + iu
    cnt = np.bincount(k, minlength=bins * bins)
    mu = np.bincount(k, du, minlength=bins * bins) / np.maximum(cnt, 1)
    mv = np.bincount(k, dv, minlength=bins * bins) / np.maximum(cnt, 1)
    centres = (np.arange(bins) + 0.5) / bins
    X, Y = np.meshgrid(centres * width, centres * height)
    return X.ravel(), Y.ravel(), mu, mv, cnt


def _nice(x: float) -> float:
    """A round number (1, 2, 5 × 10ⁿ) at or below ``x``."""
    if not np.isfinite(x) or x <= 0:
        return 1.0
    e = 10.0 ** np.floor(np.log10(x))
    return float(max(m for m in (1.0, 2.0, 5.0) if m * e <= x) * e)


def _arrow_figure(fields: list[tuple[str, np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
                  width: int, height: int, arrow_len_px: float, path: Path,
                  what: str, width_in: float = 5.2) -> Path:
    """Arrows (x, y, du, dv) per panel, one colour scale, one reference arrow, one colour bar.

    The longest typical arrow (99th percentile over all panels) is drawn ``arrow_len_px``
    detector pixels long; the reference arrow has a round length in px.
    """
    lengths = np.concatenate([np.hypot(f[3], f[4]) for f in fields]) if fields else np.zeros(0)
    top = float(np.percentile(lengths, 99)) if lengths.size else 0.0
    top = top if top > 0 else 1e-3
    gain = arrow_len_px / top  # detector px drawn per px of residual
    norm = colors.Normalize(vmin=0.0, vmax=top)
    ref = _nice(top)
    fig, axes = plt.subplots(1, len(fields), figsize=(width_in * len(fields) + 1.4, 5.6),
                             squeeze=False, layout="constrained")
    q = None
    for ax, (title, X, Y, du, dv) in zip(axes[0], fields, strict=True):
        mag = np.hypot(du, dv)
        q = ax.quiver(X, Y, du, dv, mag, angles="xy", scale_units="xy", scale=1.0 / gain,
                      cmap="viridis", norm=norm, width=0.004)
        ax.set_xlim(0, width)
        ax.set_ylim(height, 0)
        ax.set_aspect("equal")
        ax.set_title(f"{title}\n{what}; largest {np.max(mag) if mag.size else 0:.3f} px\n",
                     fontsize=10)
        ax.set_xlabel("u (column), px")
        ax.set_ylabel("v (row), px")
        ax.quiverkey(q, 0.02, 1.015, ref, f"reference: {ref:g} px (arrows magnified ×{gain:.0f})",
                     labelpos="E", coordinates="axes", fontproperties={"size": 8})
    fig.colorbar(plt.cm.ScalarMappable(norm=norm, cmap="viridis"), ax=list(axes[0]),
                 shrink=0.85, label="residual length, px")
    return _save(fig, path)


def plot_vector_fields(panels: Panels, width: int, height: int, fraction: float,
                       path: Path, bins: int = 8) -> Path:
    """Regional mean innovation over the detector (``bins``×``bins`` cells), side by side."""
    fields = []
    for title, res in panels:
        X, Y, mu, mv, cnt = _binned_field(res, stats.evaluation_mask(res, fraction), width,
                                          height, bins)
        ok = cnt > 0
        fields.append((title, X[ok], Y[ok], mu[ok], mv[ok]))
    return _arrow_figure(fields, width, height, 0.9 * width / bins, path,
                         f"mean of each of {bins}×{bins} regions")


def plot_star_vectors(panels: Panels, width: int, height: int, fraction: float, path: Path,
                      max_arrows: int = 3000, seed: int = 0) -> Path:
    """Every accepted star's innovation at its position, side by side.

    A random subset when there are more than ``max_arrows`` stars.
    """
    rng = np.random.default_rng(seed)
    fields = []
    for title, res in panels:
        idx = np.flatnonzero(_eval(res, fraction))
        if len(idx) > max_arrows:
            idx = np.sort(rng.choice(idx, max_arrows, replace=False))
        fields.append((title, res["u"][idx], res["v"][idx], res["du"][idx], res["dv"][idx]))
    return _arrow_figure(fields, width, height, 0.06 * width, path,
                         "each star (measured − predicted)")


# ------------------------------------------------------------------------------ regressors
def _bins(x: np.ndarray, n: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Bin edges by quantiles, or equal widths where values pile up.

    Piled up: the quantile edges collapse, or half of the bins together span less than 5 %
    of the range (e.g. an angular rate that is zero most of the time).
    """
    edges = np.unique(np.percentile(x, np.linspace(0, 100, n + 1)))
    span = float(x.max() - x.min())
    narrow = np.sort(np.diff(edges))[: n // 2].sum() < 0.05 * span if len(edges) > 2 else True
    if len(edges) < n // 2 + 1 or narrow:
        edges = np.linspace(x.min(), x.max(), n + 1)
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2)
    return idx, 0.5 * (edges[1:] + edges[:-1])


def _regressor_values(res: Table, centre: tuple[float, float], name: str) -> np.ndarray | None:
    regs = stats.regressors(_complete(res), centre)
    if name not in regs:
        return None
    return np.asarray(regs[name], dtype=float) * REGRESSOR_SCALE.get(name, 1.0)


def _component(res: Table, centre: tuple[float, float], comp: str) -> np.ndarray:
    if comp == "u":
        return np.asarray(res["du"], float)
    if comp == "v":
        return np.asarray(res["dv"], float)
    du_, dv_ = res["u"] - centre[0], res["v"] - centre[1]
    if comp == "radial":
        return (res["du"] * du_ + res["dv"] * dv_) / np.maximum(np.hypot(du_, dv_), 1e-9)
    return np.hypot(res["du"], res["dv"])


def plot_regressors(panels: Panels, centre: tuple[float, float], fraction: float,
                    path: Path) -> Path:
    """Binned innovation RMS (u, v) against each regressor, one line style per panel.

    The radius panel shows the mean *radial* component instead (sign matters there).  The
    dotted line is the RMS the model expects.
    """
    first = stats.regressors(_complete(panels[0][1]), centre)
    regs = [r for r, x in first.items() if np.any(np.isfinite(np.asarray(x, dtype=float)))]
    n = len(regs)
    ncol = (n + 1) // 2
    fig, axes = plt.subplots(2, ncol, figsize=(4.2 * ncol, 7.0), squeeze=False)
    for ax, name in zip(axes.ravel(), regs, strict=False):
        for (title, res), style in zip(panels, ("-", "--", ":"), strict=False):
            m = _eval(res, fraction)
            x = _regressor_values(res, centre, name)[m]
            ok = np.isfinite(x)
            if ok.sum() < 10 or np.ptp(x[ok]) == 0:
                continue
            idx, mid = _bins(x[ok])
            has = np.array([np.any(idx == i) for i in range(len(mid))])
            if name == "radius":
                y = _component(res, centre, "radial")[m][ok]
                val = np.array([y[idx == i].mean() if h else np.nan for i, h in enumerate(has)])
                ax.plot(mid, val, style, color="C2", marker="o", ms=3, label=f"radial, {title}")
                ax.set_ylabel("mean radial innovation, px")
                continue
            for comp, color in (("du", "C0"), ("dv", "C1")):
                y = np.asarray(res[comp])[m][ok]
                val = np.array([np.sqrt(np.mean(y[idx == i] ** 2)) if h else np.nan
                                for i, h in enumerate(has)])
                ax.plot(mid, val, style, color=color, marker="o", ms=3,
                        label=f"{comp}, {title}")
            ax.axhline(float(np.mean(stats.expected_rms(res, m))), color="k", ls=":", lw=0.8)
            ax.set_ylabel("innovation RMS, px")
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel(REGRESSOR_LABELS.get(name, name), fontsize=9)
        ax.set_title(name)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    axes.ravel()[0].legend(fontsize=7)
    fig.tight_layout()
    return _save(fig, path, dpi=80)


def _finding_text(f: dict[str, Any]) -> str:
    """The panel of a finding whose regressor is no column of the residual table.

    A flexure-shaped remainder (:mod:`~stellar_cal_ros.diagnosis.flexure`) is tested
    against the filter's response to a flexure probe, not against a column: the panel says
    its test and size instead of a scatter plot.
    """
    head = (f"{f['regressor']}\n{f['component']}: t = {f['statistic']:.1f}, "
            f"p = {f['p_value']:.2g}")
    d = f.get("detail") or {}
    if "arcsec_per_g" in d:
        return (head + f"\nremainder {abs(f.get('change_px', float('nan'))):.3g} px at most"
                f"\nas a mount bending {d['arcsec_per_g']:.3g} +- "
                f"{d.get('sigma_arcsec_per_g', float('nan')):.2g} arcsec per unit lateral gravity"
                "\n(tested against the filter's response to a flexure probe:"
                "\nno residual-table column to plot it against)")
    return head + "\n(no column of the residual table to plot it against)"


def plot_unexplained(res: Table, findings: Sequence[dict[str, Any]],
                     centre: tuple[float, float], fraction: float, path: Path,
                     max_panels: int = 6, seed: int = 0) -> Path | None:
    """One panel per "unexplained" finding: the residual component against its regressor.

    Grey dots: stars (a subset); black: binned mean ± its standard error; the text gives
    the test's t statistic and p-value.  ``findings`` are the diagnosis summary's
    ``unexplained`` entries (``regressor``, ``component``, ``statistic``, ``p_value``).
    """
    findings = list(findings)[:max_panels]
    if not findings:
        return None
    m = _eval(res, fraction)
    rng = np.random.default_rng(seed)
    ncol = min(3, len(findings))
    nrow = (len(findings) + ncol - 1) // ncol
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.6 * ncol, 3.6 * nrow), squeeze=False)
    for ax, f in zip(axes.ravel(), findings, strict=False):
        x = _regressor_values(res, centre, f["regressor"])
        if x is None:
            ax.text(0.5, 0.5, _finding_text(f), ha="center", va="center", fontsize=8,
                    transform=ax.transAxes, wrap=True)
            ax.axis("off")
            continue
        y = _component(res, centre, f["component"])
        ok = m & np.isfinite(x) & np.isfinite(y)
        xs, ys = x[ok], y[ok]
        pick = rng.choice(len(xs), min(len(xs), 4000), replace=False) if len(xs) else []
        ax.plot(xs[pick], ys[pick], ".", color="0.7", ms=2, rasterized=True)
        if len(xs) >= 10:
            idx, mid = _bins(xs, 12)
            mean = np.array([ys[idx == i].mean() if np.any(idx == i) else np.nan
                             for i in range(len(mid))])
            sem = np.array([ys[idx == i].std() / np.sqrt(max((idx == i).sum(), 1))
                            if np.any(idx == i) else np.nan for i in range(len(mid))])
            ax.errorbar(mid, mean, sem, color="k", marker="o", ms=3, lw=1, capsize=2)
            lo, hi = np.percentile(ys, [1, 99])
            pad = 0.1 * (hi - lo)
            ax.set_ylim(lo - pad, hi + pad)
        ax.axhline(0, color="C3", lw=0.6)
        ax.set_xlabel(REGRESSOR_LABELS.get(f["regressor"], f["regressor"]), fontsize=9)
        ax.set_ylabel(COMPONENT_LABELS.get(f["component"], f["component"]), fontsize=9)
        ax.set_title(f"{f['component']} vs {f['regressor']}: t = {f['statistic']:.1f}, "
                     f"p = {f['p_value']:.2g}", fontsize=9)
    for ax in axes.ravel()[len(findings):]:
        ax.axis("off")
    fig.tight_layout()
    return _save(fig, path, dpi=80)


# ------------------------------------------------------------------------------ time series
def plot_time(panels: Panels, path: Path) -> Path:
    """Frame-mean innovations against time."""
    fig, ax = plt.subplots(figsize=(10, 3.2))
    t0 = min((float(np.min(r["t"])) for _, r in panels if len(r["t"])), default=0.0)
    for (title, res), style in zip(panels, ("-", "--", ":"), strict=False):
        m = stats.accepted(res)
        if not np.any(m):
            continue
        _, inv = np.unique(res["frame"][m], return_inverse=True)
        cnt = np.bincount(inv)
        t = np.bincount(inv, res["t"][m]) / cnt
        for comp, color in (("du", "C0"), ("dv", "C1")):
            ax.plot(t - t0, np.bincount(inv, res[comp][m]) / cnt, style, color=color,
                    lw=0.6, label=f"{comp}, {title}")
    ax.set_xlabel("time since the first frame, s")
    ax.set_ylabel("frame-mean innovation, px")
    ax.legend(fontsize=7, ncol=4)
    fig.tight_layout()
    return _save(fig, path, dpi=80)


def parameter_names(history: Table) -> list[str]:
    """The estimated parameters of a history table (those with a ``sigma.`` column)."""
    return [k for k in history if not k.startswith("sigma.") and f"sigma.{k}" in history]


def plot_parameter_history(history: Table, path: Path,
                           truth: dict[str, float] | None = None,
                           ncol: int = 4) -> Path | None:
    """Every estimated parameter ± σ against time (shaded 1σ and 3σ), with the truth.

    ``truth`` maps ``effect.parameter`` to its true value in the same (effect) units.
    """
    names = parameter_names(history)
    if not names or len(history.get("t", ())) == 0:
        return None
    t = np.asarray(history["t"], float)
    t = t - t[0]
    ncol = min(ncol, len(names))
    nrow = (len(names) + ncol - 1) // ncol
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.1 * ncol, 2.8 * nrow), squeeze=False)
    for ax, name in zip(axes.ravel(), names, strict=False):
        scale, unit = display_unit(name, parameter_unit(name))
        v = np.asarray(history[name], float) * scale
        s = np.asarray(history[f"sigma.{name}"], float) * scale
        ax.fill_between(t, v - 3 * s, v + 3 * s, color="C0", alpha=0.12, lw=0)
        ax.fill_between(t, v - s, v + s, color="C0", alpha=0.3, lw=0)
        ax.plot(t, v, color="C0", lw=0.9)
        tv = None if truth is None else truth.get(name)
        if tv is not None and np.isfinite(tv):
            ax.axhline(tv * scale, color="C3", ls="--", lw=1)
            z = (v[-1] - tv * scale) / s[-1] if s[-1] > 0 else np.nan
            note = f", {z:+.1f}σ from truth"
        else:
            note = ""
        # the y range: the last 80 % of the run's ±3σ band, and the truth
        k0 = len(v) // 5
        lo = np.nanmin(v[k0:] - 3 * s[k0:])
        hi = np.nanmax(v[k0:] + 3 * s[k0:])
        if tv is not None and np.isfinite(tv):
            lo, hi = min(lo, tv * scale), max(hi, tv * scale)
        if np.isfinite(lo) and np.isfinite(hi) and hi > lo:
            pad = 0.08 * (hi - lo)
            ax.set_ylim(lo - pad, hi + pad)
        ax.set_title(f"{name} [{unit or '–'}]\n{v[-1]:.5g} ± {s[-1]:.2g}{note}", fontsize=8.5)
        ax.tick_params(labelsize=7)
        ax.ticklabel_format(axis="y", useOffset=False, style="plain")
        ax.set_xlabel("time since the first update, s", fontsize=7)
    for ax in axes.ravel()[len(names):]:
        ax.axis("off")
    fig.tight_layout()
    return _save(fig, path, dpi=80)


def plot_nis(history: Table, path: Path, window: int | None = None) -> Path | None:
    """NIS per degree of freedom of every update against time, with its χ² band.

    Dots: each update's NIS/dof; line: the mean over a moving window of ``window`` updates
    (default n/40, at least 10); grey band: where that mean lies with 95 % probability if
    the model is right (χ² with the window's summed dof, divided by it).
    """
    if len(history.get("nis", ())) == 0:
        return None
    t = np.asarray(history["t"], float)
    t = t - t[0]
    nis = np.asarray(history["nis"], float)
    dof = np.maximum(np.asarray(history["dof"], float), 1)
    n = len(nis)
    w = window or max(10, n // 40)
    w = min(w, n)
    kern = np.ones(w)
    s_nis = np.convolve(nis, kern, "valid")
    s_dof = np.convolve(dof, kern, "valid")
    tc = np.convolve(t, kern / w, "valid")
    mean = s_nis / s_dof
    lo = dist.chi2.ppf(0.025, s_dof) / s_dof
    hi = dist.chi2.ppf(0.975, s_dof) / s_dof
    fig, ax = plt.subplots(figsize=(10, 3.4))
    ax.plot(t, nis / dof, ".", color="0.6", ms=2, label="one update")
    ax.fill_between(tc, lo, hi, color="C2", alpha=0.25, lw=0,
                    label=f"95 % band of a {w}-update mean")
    ax.plot(tc, mean, color="C0", lw=1.2, label=f"mean of {w} updates")
    ax.axhline(1.0, color="k", lw=0.6)
    ax.set_yscale("log")
    ratio = nis / dof
    ok = ratio > 0
    lo_y = min(0.2, float(np.percentile(ratio[ok], 1)) if np.any(ok) else 0.2)
    hi_y = max(5.0, float(np.percentile(ratio[ok], 99.5)) * 1.5 if np.any(ok) else 5.0)
    ax.set_ylim(lo_y, hi_y)
    ax.set_xlabel("time since the first update, s")
    ax.set_ylabel("NIS / dof (log scale)")
    ax.set_title("normalized innovation squared of each update, joint over its stars (1 = "
                 "consistent); the run's NIS/dof is in the text", fontsize=10)
    ax.legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    return _save(fig, path, dpi=80)


def truth_values(history: Table, calibration: Any, truth: Any) -> dict[str, float]:
    """True value of every history parameter, in the effects' units.

    Each effect reads its value from ``truth`` as from a prior, except the installation,
    whose parameter is the rotation from the run's *prior* mounting: the prior is
    recovered as ``R_result · Exp(−δ_final)``.
    """
    import copy

    from scipy.spatial.transform import Rotation

    from stellar_cal_ros.effects import registry

    out: dict[str, float] = {}
    names = parameter_names(history)
    for eff_id in dict.fromkeys(n.split(".", 1)[0] for n in names):
        try:
            eff = registry.create(eff_id)
        except Exception:  # noqa: BLE001 - a plugin effect not loaded
            continue
        if eff_id == "installation":
            delta = np.array([history[f"installation.{p}"][-1] for p in eff.parameter_names])
            nominal = calibration.installation * Rotation.from_rotvec(-delta)
            value = (nominal.inv() * truth.installation).as_rotvec()
        else:
            value, _ = copy.deepcopy(eff).initial(truth)
        for p, v in zip(eff.parameter_names, value, strict=True):
            out[f"{eff_id}.{p}"] = float(v)
    return out
