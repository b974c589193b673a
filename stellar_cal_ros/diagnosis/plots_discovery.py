"""Plots of ``diagnose --auto``: the path of the forward selection."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def plot_path(path: list[dict[str, Any]], out: Path) -> None:
    """Innovation RMS (u, v) and the RMS the model expects at each round, effects named."""
    rounds = [s["round"] for s in path]
    fig, ax = plt.subplots(figsize=(max(5.0, 1.6 * len(path)), 3.6))
    for k, (name, color) in enumerate((("u", "C0"), ("v", "C1"))):
        ax.plot(rounds, [s["rms_px"][k] for s in path], "o-", color=color,
                label=f"RMS {name}")
        ax.plot(rounds, [s["expected_rms_px"][k] for s in path], ":", color=color,
                label=f"expected {name}")
    labels = ["+ " + s["added"]["effect"] if s["added"] else "(stop)" for s in path]
    for x, s, text in zip(rounds, path, labels, strict=True):
        ax.annotate(text, (x, max(s["rms_px"])), textcoords="offset points", xytext=(4, 6),
                    fontsize=8)
    ax.set_xticks(rounds)
    ax.set_xlabel("round (the model of the round: the effects added before it)")
    ax.set_ylabel("innovation RMS, px")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=80)
    plt.close(fig)
