"""Summary of a campaign (HTML + PNG).

RMS error against the filter's σ, NEES and NIS with their χ² intervals, the budget against
the actual attitude error, histograms of the normalised errors.

Runs are grouped by the inputs that vary across the campaign, except the seed.
"""

from __future__ import annotations

import html
import json
import math
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from stellar_cal_ros.campaign.spec import RUN_KEYS  # noqa: E402
from stellar_cal_ros.core.distributions import chi2  # noqa: E402

__all__ = ["format_summary", "summarize", "write_summary"]

_GROUP_KEYS = [k for k in RUN_KEYS if k != "seed"]


def _groups(rows: list[dict[str, Any]]) -> list[tuple[str, list[dict[str, Any]]]]:
    varying = [k for k in _GROUP_KEYS if len({json.dumps(r.get(k), sort_keys=True)
                                              for r in rows}) > 1]
    out: dict[str, list] = {}
    for r in rows:
        label = r.get("label") if "label" in varying else None
        label = label or ", ".join(f"{k}={r.get(k)}" for k in varying if k != "label")
        out.setdefault(label or "all runs", []).append(r)
    return list(out.items())


def _interval(dof: float, n: float) -> list[float]:
    return [float(x) for x in chi2.ppf([0.025, 0.975], dof) / n]


def summarize(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Statistics per group of runs (see the module docstring)."""
    out = []
    for label, group in _groups(rows):
        ok = [r for r in group if r.get("status") == "ok"]
        g: dict[str, Any] = {"group": label, "runs": len(group), "failed": len(group) - len(ok),
                             "parameters": {}}
        params = sorted({k[4:] for r in ok for k in r if k.startswith("err.")})
        for p in params:
            e = np.array([r[f"err.{p}"] for r in ok if f"err.{p}" in r], dtype=float)
            s = np.array([r[f"sigma.{p}"] for r in ok if f"err.{p}" in r], dtype=float)
            n = len(e)
            rms, sig = float(np.sqrt(np.mean(e**2))), float(np.sqrt(np.mean(s**2)))
            g["parameters"][p] = {"n": n, "rms_error": rms, "mean_sigma": sig,
                                  "ratio": rms / sig if sig > 0 else math.nan,
                                  "ratio_interval": [math.sqrt(x) for x in _interval(n, n)],
                                  "normalized": (e / np.where(s > 0, s, np.nan)).tolist()}
        nees = [r["nees"] for r in ok if isinstance(r.get("nees"), (int, float))
                and math.isfinite(r["nees"])]
        if nees:
            dof = ok[0].get("nees_dof", 0)
            g["nees"] = {"mean": float(np.mean(nees)), "dof": dof,
                         "interval": _interval(dof * len(nees), len(nees))}
        nis_dof = sum(int(r.get("nis_dof") or 0) for r in ok)
        if nis_dof:
            g["nis_per_dof"] = {"value": sum(r.get("nis_sum", 0.0) for r in ok) / nis_dof,
                                "interval": _interval(nis_dof, nis_dof)}
        for conv in ("axis", "system"):
            b = [r.get(f"budget.{conv}.total_arcsec") for r in ok]
            a = [r.get(f"actual.{conv}.total_arcsec") for r in ok]
            if all(x is not None for x in b + a) and ok:
                pred = float(np.sqrt(np.mean(np.square(b))))
                act = float(np.sqrt(np.mean(np.square(a))))
                g[f"budget_{conv}"] = {"predicted_arcsec": pred, "actual_rms_arcsec": act,
                                       "ratio": act / pred if pred > 0 else math.nan}
        t = [r.get("t.total") for r in ok if r.get("t.total") is not None]
        g["mean_run_seconds"] = float(np.mean(t)) if t else math.nan
        out.append(g)
    return out


def _display(parameter: str) -> tuple[float, str]:
    """Factor and unit a parameter's error is shown in (the reports' display units)."""
    from stellar_cal_ros.diagnosis.report import display_unit, parameter_unit

    if parameter.startswith("eqpp."):
        return 1.0, "px"
    return display_unit(parameter, parameter_unit(parameter))


def format_summary(stats: list[dict[str, Any]]) -> str:
    """Text tables of :func:`summarize`."""
    lines = []
    for g in stats:
        lines.append(f"== {g['group']}: {g['runs']} runs ({g['failed']} failed), "
                     f"{g['mean_run_seconds']:.1f} s per run")
        if g["parameters"]:
            lo, hi = next(iter(g["parameters"].values()))["ratio_interval"]
            lines.append(f"  {'parameter':28s} {'RMS error':>11s} {'mean sigma':>11s} "
                         f"{'unit':8s} {'RMS/sigma':>9s}   (95 % if consistent: {lo:.2f} .. "
                         f"{hi:.2f})")
            for p, s in g["parameters"].items():
                scale, unit = _display(p)
                lines.append(f"  {p:28s} {s['rms_error'] * scale:11.4g} "
                             f"{s['mean_sigma'] * scale:11.4g} {unit or '-':8s} "
                             f"{s['ratio']:9.2f}")
        if "nees" in g:
            n = g["nees"]
            lines.append(f"  NEES mean {n['mean']:.2f} ({n['dof']} dof; 95 % "
                         f"{n['interval'][0]:.2f} .. {n['interval'][1]:.2f})")
        if "nis_per_dof" in g:
            n = g["nis_per_dof"]
            lines.append(f"  NIS/dof {n['value']:.4f} (95 % {n['interval'][0]:.4f} .. "
                         f"{n['interval'][1]:.4f})")
        for conv, title in (("axis", "tracker (optical axis)"), ("system", "IMU system")):
            b = g.get(f"budget_{conv}")
            if b:
                lines.append(f"  attitude error from the calibration, {title}: budget "
                             f"{b['predicted_arcsec']:.3f}\", actual RMS "
                             f"{b['actual_rms_arcsec']:.3f}\" (ratio {b['ratio']:.2f})")
    return "\n".join(lines)


def histogram_groups(stats: list[dict[str, Any]], parameter: str
                     ) -> tuple[list[tuple[str, np.ndarray]], int]:
    """Return the normalised errors of ``parameter`` per group and the histogram's range.

    Variants are not pooled; the half range is at least 4 and holds every value.
    """
    zs = [(g["group"], np.asarray(g["parameters"][parameter]["normalized"], float))
          for g in stats if parameter in g["parameters"]]
    zs = [(label, z[np.isfinite(z)]) for label, z in zs]
    zmax = max([4.0] + [float(np.max(np.abs(z))) for _, z in zs if len(z)])
    return zs, math.ceil(zmax)


def _plots(stats: list[dict[str, Any]], out_dir: Path) -> list[str]:
    names = sorted({p for g in stats for p in g["parameters"]})
    if not names:
        return []
    ncol = 4
    nrow = -(-len(names) // ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(4 * ncol, 2.8 * nrow), squeeze=False)
    for ax, p in zip(axes.flat, names, strict=False):
        zs, lim = histogram_groups(stats, p)
        bins = np.linspace(-lim, lim, 4 * lim + 1)
        for label, z in zs:
            ax.hist(z, bins=bins, density=True, alpha=0.5 if len(zs) > 1 else 0.7,
                    histtype="stepfilled", label=f"{label} (n={len(z)})")
        x = np.linspace(-lim, lim, 400)
        ax.plot(x, np.exp(-0.5 * x**2) / math.sqrt(2 * math.pi), "k-", lw=1)
        ax.set_title(f"{p}\n(error / sigma; N(0,1) if consistent)", fontsize=8)
        if len(zs) > 1:
            ax.legend(fontsize=6)
    for ax in list(axes.flat)[len(names):]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(out_dir / "normalized_errors.png", dpi=80)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6, 5))
    for g in stats:
        r = [g["parameters"][p]["ratio"] for p in names if p in g["parameters"]]
        ax.plot(range(len(r)), r, "o", label=g["group"][:40])
    lo, hi = next(iter(stats[0]["parameters"].values()))["ratio_interval"]
    ax.axhspan(lo, hi, color="0.85", label="95 % if consistent")
    ax.axhline(1.0, color="k", lw=0.8)
    ax.set_xticks(range(len(names)), names, rotation=60, ha="right", fontsize=7)
    ax.set_ylabel("RMS error / mean sigma")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out_dir / "rms_vs_sigma.png", dpi=80)
    plt.close(fig)
    return ["normalized_errors.png", "rms_vs_sigma.png"]


def write_summary(rows: list[dict[str, Any]], out_dir: str | Path) -> Path:
    """Write ``summary.json``, ``summary.html`` and the PNGs; return the HTML path."""
    out_dir = Path(out_dir)
    stats = summarize(rows)
    (out_dir / "summary.json").write_text(json.dumps(stats, indent=1, default=float))
    images = _plots(stats, out_dir)
    failed = [r for r in rows if r.get("status") != "ok"]
    body = "".join(f"<img src='{i}'>" for i in images)
    errors = "".join(f"<li>{html.escape(str(r.get('key')))}: {html.escape(str(r.get('error')))}"
                     "</li>" for r in failed) or "<li>none</li>"
    page = (f"<!doctype html><html><head><meta charset='utf-8'><title>campaign summary</title>"
            "<style>body{font-family:sans-serif;max-width:1300px;margin:auto} img{max-width:"
            "100%}</style></head><body><h1>Campaign summary</h1>"
            f"<pre>{html.escape(format_summary(stats))}</pre><h2>Failed runs</h2>"
            f"<ul>{errors}</ul>{body}</body></html>")
    path = out_dir / "summary.html"
    path.write_text(page)
    return path
