"""The human report: one HTML page with matplotlib PNGs (headless, Agg backend)."""

from __future__ import annotations

import html
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from stellar_cal_ros.diagnosis import stats  # noqa: E402
from stellar_cal_ros.effects import registry  # noqa: E402

Table = dict[str, np.ndarray]


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


def plot_vector_fields(panels: list[tuple[str, Table]], width: int, height: int,
                       fraction: float, path: Path) -> None:
    """Regional mean residual vectors over the detector (mrcal-style), side by side."""
    fig, axes = plt.subplots(1, len(panels), figsize=(5.2 * len(panels), 5), squeeze=False)
    fields = [_binned_field(r, stats.evaluation_mask(r, fraction), width, height)
              for _, r in panels]
    scale = max(max(np.max(np.hypot(f[2], f[3])) for f in fields), 1e-6)
    for ax, (title, _), (X, Y, mu, mv, cnt) in zip(axes[0], panels, fields, strict=True):
        ok = cnt > 0
        q = ax.quiver(X[ok], Y[ok], mu[ok], mv[ok], np.hypot(mu[ok], mv[ok]), angles="xy",
                      scale_units="xy", scale=scale / (0.9 * width / 8), cmap="viridis")
        ax.set_xlim(0, width)
        ax.set_ylim(height, 0)
        ax.set_aspect("equal")
        ax.set_title(f"{title}\nmax regional mean {np.max(np.hypot(mu, mv)):.3f} px")
        ax.set_xlabel("u (column) px")
        ax.set_ylabel("v (row) px")
        fig.colorbar(q, ax=ax, shrink=0.7, label="px")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _bins(x: np.ndarray, n: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Bin edges by quantiles, or equal widths where quantiles collapse (piled-up values)."""
    edges = np.unique(np.percentile(x, np.linspace(0, 100, n + 1)))
    if len(edges) < n // 2 + 1:
        edges = np.linspace(x.min(), x.max(), n + 1)
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2)
    return idx, 0.5 * (edges[1:] + edges[:-1])


def plot_regressors(panels: list[tuple[str, Table]], centre: tuple[float, float],
                    fraction: float, path: Path) -> None:
    """Binned innovation RMS (u, v) against each regressor, current vs best candidate.

    The radius panel shows the mean *radial* component instead (sign matters there).
    """
    regs = list(stats.regressors(panels[0][1], centre))
    n = len(regs)
    fig, axes = plt.subplots(2, (n + 1) // 2, figsize=(4.0 * ((n + 1) // 2), 6.5),
                             squeeze=False)
    for ax, name in zip(axes.ravel(), regs, strict=False):
        for (title, res), style in zip(panels, ("-", "--"), strict=False):
            m = stats.evaluation_mask(res, fraction) & stats.accepted(res)
            x = np.asarray(stats.regressors(res, centre)[name], dtype=float)[m]
            ok = np.isfinite(x)
            if ok.sum() < 10 or np.ptp(x[ok]) == 0:
                continue
            idx, mid = _bins(x[ok])
            has = np.array([np.any(idx == i) for i in range(len(mid))])
            if name == "radius":
                du_, dv_ = res["u"][m][ok] - centre[0], res["v"][m][ok] - centre[1]
                rr = np.maximum(np.hypot(du_, dv_), 1e-9)
                y = (res["du"][m][ok] * du_ + res["dv"][m][ok] * dv_) / rr
                val = np.array([y[idx == i].mean() if h else np.nan
                                for i, h in enumerate(has)])
                ax.plot(mid, val, style, color="C2", marker="o", ms=3, label=f"radial {title}")
                ax.set_ylabel("mean radial innovation, px")
                continue
            for comp, color in (("du", "C0"), ("dv", "C1")):
                y = res[comp][m][ok]
                val = np.array([np.sqrt(np.mean(y[idx == i] ** 2)) if h else np.nan
                                for i, h in enumerate(has)])
                ax.plot(mid, val, style, color=color, marker="o", ms=3,
                        label=f"{comp} {title}")
            ax.set_ylabel("innovation RMS, px")
        ax.axhline(0, color="k", lw=0.5)
        ax.set_title(name)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    axes.ravel()[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def plot_time(panels: list[tuple[str, Table]], path: Path) -> None:
    """Frame-mean innovations against time."""
    fig, ax = plt.subplots(figsize=(10, 3.2))
    for (title, res), style in zip(panels, ("-", "--"), strict=False):
        m = stats.accepted(res)
        if not np.any(m):
            continue
        frames = res["frame"][m]
        uniq, inv = np.unique(frames, return_inverse=True)
        cnt = np.bincount(inv)
        t = np.bincount(inv, res["t"][m]) / cnt
        for comp, color in (("du", "C0"), ("dv", "C1")):
            ax.plot(t - t.min(), np.bincount(inv, res[comp][m]) / cnt, style, color=color,
                    lw=0.6, label=f"{comp} {title}")
    ax.set_xlabel("time, s")
    ax.set_ylabel("frame-mean innovation, px")
    ax.legend(fontsize=7, ncol=4)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def _after_note(c: dict[str, Any]) -> str:
    """The candidate's test after the top one, for the table."""
    a = c.get("after")
    if not a:
        return ""
    verdict = "significant" if c["significant"] else "not needed then"
    return (f"<br><small>after {html.escape(a['effect'])}: p = {a['p_value']:.2g} "
            f"({verdict})</small>")


def write_html(out_dir: Path, summary: dict[str, Any], images: list[tuple[str, str]],
               title: str) -> Path:
    """Write ``report.html`` (one page) and return its path."""
    rows = []
    for c in summary["candidates"]:
        eff = registry.create(c["effect"])
        est = ", ".join(f"{k}={v:.4g}±{c['sigma'][k]:.2g}" for k, v in c["estimate"].items())
        rows.append(
            f"<tr class={'sig' if c['significant'] else 'ns'}><td><b>{c['effect']}</b></td>"
            f"<td>{c['score']:.1f}</td><td>{c['p_value']:.2g}{_after_note(c)}</td>"
            f"<td>{c['rms_after_px'][0]:.4f} / {c['rms_after_px'][1]:.4f}</td>"
            f"<td>{html.escape(est)}</td><td class=expl>{html.escape(eff.explanation)}</td></tr>")
    unexplained = "".join(
        f"<li>{html.escape(u['component'])} residual vs <b>{html.escape(u['regressor'])}</b>: "
        f"t = {u['statistic']:.1f}, p = {u['p_value']:.2g}, change {u['change_px']:.3f} px "
        "across its 5–95 % range</li>" for u in summary["unexplained"]) or "<li>none</li>"
    unobs = "".join(f"<li><b>{u['effect']}</b>: {html.escape(u['reason'])}</li>"
                    for u in summary.get("implausible", []) + summary["unobservable"]
                    + summary["not_applicable"]) or "<li>none</li>"
    rms, exp = summary["residual_rms_px"], summary["expected_rms_px"]
    nis = summary["nis"]
    imgs = "".join(f"<h2>{html.escape(t)}</h2><img src='{f}'>" for t, f in images)
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>body{{font-family:sans-serif;max-width:1400px;margin:auto}} table{{border-collapse:collapse}}
td,th{{border:1px solid #ccc;padding:4px;vertical-align:top}} tr.sig{{background:#e6ffe6}}
td.expl{{font-size:85%;max-width:520px}} img{{max-width:100%}}</style></head><body>
<h1>{html.escape(title)}</h1>
<p>Model: <b>{summary['model']['method']}</b> with {', '.join(summary['model']['effects'])}.
Evaluation: {summary['evaluation']}.</p>
<p>Innovation RMS <b>{rms[0]:.4f} / {rms[1]:.4f} px</b> (u / v) against the
{exp[0]:.4f} / {exp[1]:.4f} px the model expects; mean NIS per star {nis['mean']:.3f}
(consistent: {nis['lower']:.3f} … {nis['upper']:.3f}).</p>
<h2>Candidate effects</h2><p>Best first; green = significant after correction, and still
significant once the top one is added.</p>
<table><tr><th>effect</th><th>score 2Δℓ</th><th>p (Bonferroni)</th>
<th>RMS after, px</th><th>estimate ± σ</th><th>what it is</th></tr>{''.join(rows)}</table>
<h2>Unexplained structure</h2><ul>{unexplained}</ul>
<h2>Not ranked</h2><ul>{unobs}</ul>
{imgs}
</body></html>"""
    path = out_dir / "report.html"
    path.write_text(page)
    return path
