"""Print and plot a budget (the dictionary of :func:`.analysis.run_budget`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

__all__ = ["format_budget", "plot_budget", "write_budget"]

_TITLES = {"axis": "star tracker (optical-axis reference)",
           "mounting": "star tracker (mounting reference)",
           "system": "IMU-referenced system (installation added)"}


def _cell(x: float | None, width: int = 7) -> str:
    return f"{'-':>{width}s}" if x is None else f"{x:{width}.3f}"


def format_budget(b: dict[str, Any]) -> str:
    """The budget as text tables (arcsec, 1σ unless stated)."""
    cam, opt = b["camera"], b["options"]
    fov = b["camera"]["field_of_view_deg"]
    lines = [
        f"camera {cam['width']}x{cam['height']} px, fx={cam['fx']:.2f} fy={cam['fy']:.2f} px, "
        f"principal point ({cam['cx']:.2f}, {cam['cy']:.2f}), field {fov[0]:.2f} x "
        f"{fov[1]:.2f} deg",
        f"covariance: {b['origin']}",
    ]
    lines += [f"note: {n}" for n in b["notes"]]
    n_mc = opt["frames"] if opt["mc_frames"] is None else opt["mc_frames"]
    mc = (f"Monte Carlo {opt['draws']} draws per source ({n_mc} frames each)"
          if opt["draws"] > 0 else "no Monte Carlo")
    lines.append(f"{opt['frames']} frames of {opt['stars_per_frame']} stars uniform over the "
                 f"detector; {mc}; maximum error at {opt['max_error_k']:g} sigma")
    st = b["star"]
    lines.append("")
    lines.append(f"one star: incident-angle error at {st['reference_angle_deg']:.2f} deg, "
                 "arcsec (optical-axis reference; Sun et al.'s metric)")
    lines.append(f"  {'source':17s} {'linear':>8s} {'MC':>8s} {'+-SE':>6s} {'MC mean':>8s} "
                 f"{'max err':>8s} {'mounting':>9s}")
    for s in b["sources"]:
        mc = st["mc"].get(s)
        lines.append(
            f"  {s:17s} {st['linear'][s]:8.3f} "
            + (f"{mc['sigma']:8.3f} {mc['standard_error']:6.3f} {mc['mean']:8.3f} "
               if mc else f"{'-':>8s} {'':6s} {'-':>8s} ")
            + f"{_cell(st['max_error'].get(s), 8)} {st['linear_mounting'][s]:9.3f}")
    for conv in ("axis", "system", "mounting"):
        fr = b["frame"][conv]
        lines.append("")
        lines.append(f"frame attitude, {_TITLES[conv]}, arcsec: cross-boresight per axis "
                     "(x, y), roll, total")
        lines.append(f"  {'source':17s} {'x':>7s} {'y':>7s} {'roll':>7s} {'total':>7s} "
                     f"{'MC x':>7s} {'MC y':>7s} {'MC roll':>7s} {'MC tot':>7s} "
                     f"{'max err':>8s}")
        for s in b["sources"]:
            li, mc = fr["linear"][s], fr["mc"].get(s)
            mcs = " ".join(_cell(None if mc is None else mc[k]) for k in
                           ("x", "y", "roll", "total"))
            lines.append(f"  {s:17s} {li['x']:7.3f} {li['y']:7.3f} {li['roll']:7.3f} "
                         f"{li['total']:7.3f} {mcs} {fr['max_error'][s]['mean']:8.3f}")
    for conv in ("axis", "system"):
        lines += _shares(b, conv)
    return "\n".join(lines)


def _shares(b: dict[str, Any], conv: str) -> list[str]:
    """Each source's share of the summed variances, and what correlations change."""
    lin = b["frame"][conv]["linear"]
    parts = {s: lin[s]["total"] ** 2 for s in b["sources"] if s != "total"}
    summed = sum(parts.values())
    if summed <= 0:
        return []
    out = ["", f"shares of the {_TITLES[conv]} variance (linear, total angle):",
           "  " + ", ".join(f"{s} {100 * v / summed:.1f} %" for s, v in
                            sorted(parts.items(), key=lambda kv: -kv[1]) if v > 0)]
    total = lin["total"]["total"]
    if abs(total**2 - summed) > 1e-3 * summed:
        out.append(f"  the correlations between sources take the total from "
                   f"{summed ** 0.5:.3f}\" (independent) to {total:.3f}\"")
    return out


def _mark_correlation(ax, lin: dict[str, Any], names: list[str]) -> None:
    """Mark beside the total what the sources would give if independent.

    A note says when their correlations make the total differ from it (even smaller than
    a component).
    """
    if "total" not in names:
        return
    k = names.index("total")
    srcs = [s for s in names if s != "total"]
    indep = {c: float(np.sqrt(sum(lin[s][c] ** 2 for s in srcs))) for c in ("cross", "roll")}
    ax.plot([k - 0.4, k], [indep["cross"]] * 2, "k--", lw=1.2)
    ax.plot([k, k + 0.4], [indep["roll"]] * 2, "k--", lw=1.2,
            label="total if the sources were independent")
    tot = {c: lin["total"][c] for c in ("cross", "roll")}
    top = max([indep["cross"], indep["roll"]] + [lin[s][c] for s in names
                                                  for c in ("cross", "roll")])
    ax.set_ylim(0, 1.45 * top)  # room for the legend above the bars
    if any(abs(tot[c] - indep[c]) > 0.01 * max(indep[c], 1e-12) for c in tot):
        ax.set_ylim(0, 2.0 * top)  # and for the note
        ax.text(0.02, 0.76, "the total is not the root-sum-square of the bars: the sources'\n"
                "errors are correlated (estimated together, they compensate each other):\n"
                f"cross {tot['cross']:.3g}\" (independent: {indep['cross']:.3g}\"), roll "
                f"{tot['roll']:.3g}\" (independent: {indep['roll']:.3g}\")",
                transform=ax.transAxes, va="top", fontsize=7,
                bbox={"facecolor": "white", "alpha": 0.85, "edgecolor": "0.6"})


def plot_budget(b: dict[str, Any], out_dir: Path) -> list[Path]:
    """Write ``incident_angle.png``, ``attitude.png`` and ``fov_map.png``; return the paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    cur = b["curves"]
    ang = np.asarray(cur["angles_deg"])
    srcs = [s for s in b["sources"] if s != "total"]
    srcs = [s for s in srcs if max(cur["linear"]["axis"][s]) > 0]
    ncol = 3
    nrow = -(-(len(srcs) + 1) // ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.6 * ncol, 3.6 * nrow), squeeze=False)
    k = b["options"]["max_error_k"]
    for ax, s in zip(axes.flat, srcs, strict=False):
        ax.plot(ang, cur["linear"]["axis"][s], "-", label="linear 1σ")
        if s in cur["mc"]:
            ax.plot(ang, cur["mc"][s], "o", ms=3, label="Monte Carlo 1σ")
        if s in cur["max_error"]:
            ax.plot(ang, np.asarray(cur["max_error"][s]) / k, "--",
                    label=f"max error / {k:g}")
        ax.axvline(b["star"]["reference_angle_deg"], color="0.7", lw=0.8)
        ax.set_title(s)
        ax.set_xlabel("incident angle (deg)")
        ax.set_ylabel("angle error (arcsec)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    ax = axes.flat[len(srcs)]
    for s in srcs + ["total"]:
        ax.plot(ang, cur["linear"]["axis"][s], "-" if s != "total" else "k-", label=s)
    ax.set_title("all sources (linear 1σ)")
    ax.set_xlabel("incident angle (deg)")
    ax.set_ylabel("angle error (arcsec)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    for extra in list(axes.flat)[len(srcs) + 1:]:
        extra.axis("off")
    fig.suptitle("Incident-angle error of one star (optical-axis reference)")
    fig.tight_layout()
    paths = [out_dir / "incident_angle.png"]
    fig.savefig(paths[-1], dpi=90)
    plt.close(fig)

    fig, axes = plt.subplots(1, 2, figsize=(12, 4), sharey=False)
    for ax, conv in zip(axes, ("axis", "system"), strict=True):
        lin = b["frame"][conv]["linear"]
        names = [s for s in b["sources"]]
        x = np.arange(len(names))
        ax.bar(x - 0.2, [lin[s]["cross"] for s in names], 0.4, label="cross-boresight (per axis)")
        ax.bar(x + 0.2, [lin[s]["roll"] for s in names], 0.4, label="roll")
        ax.set_xticks(x, names, rotation=30, ha="right")
        ax.set_ylabel("arcsec (1σ, linear)")
        ax.set_title(_TITLES[conv])
        _mark_correlation(ax, lin, names)
        ax.legend(fontsize=8, loc="upper left")
        ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    paths.append(out_dir / "attitude.png")
    fig.savefig(paths[-1], dpi=90)
    plt.close(fig)

    fm = b["fov_map"]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.6))
    for ax, conv in zip(axes, ("axis", "system"), strict=True):
        img = ax.imshow(np.asarray(fm[conv]), origin="upper", cmap="viridis",
                        extent=[fm["u"][0], fm["u"][-1], fm["v"][-1], fm["v"][0]])
        fig.colorbar(img, ax=ax, label="arcsec (1σ)")
        ax.set_title(f"one star's direction error from the calibration\n{_TITLES[conv]}",
                     fontsize=9)
        ax.set_xlabel("u (column) px")
        ax.set_ylabel("v (row) px")
    fig.tight_layout()
    paths.append(out_dir / "fov_map.png")
    fig.savefig(paths[-1], dpi=90)
    plt.close(fig)
    return paths


def write_budget(b: dict[str, Any], out_dir: Path, plots: bool = True) -> list[Path]:
    """Write ``budget.json`` (and the plots); return the paths written."""
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "budget.json"
    path.write_text(json.dumps(b, indent=1))
    return [path] + (plot_budget(b, out_dir) if plots else [])
