"""Level of the periodic frame-mean test (``stats.periodic_findings``) on red frame means.

Each of 20 stars a frame carries an AR(1) over frames (rho = e^(-1/5), marginal 0.05 px,
frames 0.5 s apart, as in the unseen case ``ar1``): the frame means are red.  Prints the
share of tests (u and v, REPS tables) below 1 % and 5 %; a test that holds its level reads
~0.01 and ~0.05.  ``--rho 0`` is the white reference.  Each line twice: the flat reference
(the neighbours' mean, white noise's) and the red one (``red=True``, their log-linear level,
what the diagnosis uses once the stars' noise reads correlated along their tracks).

Run::

    .venv/bin/python benchmarks/periodic_red_level.py --reps 300
"""

from __future__ import annotations

import argparse

import numpy as np

from stellar_cal_ros.diagnosis import stats


def table(rng: np.random.Generator, rho: float, frames: int, stars: int = 20):
    """A residual table of AR(1) star tracks (every star in every frame) and its mask."""
    f = np.repeat(np.arange(frames), stars)
    out = {}
    for key in ("du", "dv"):
        e = rng.standard_normal((frames, stars))
        x = np.empty_like(e)
        x[0] = e[0]
        for i in range(1, frames):
            x[i] = rho * x[i - 1] + np.sqrt(1.0 - rho * rho) * e[i]
        out[key] = 0.05 * x.ravel()
    res = {"frame": f, "t": 0.5 * f, "gated": np.zeros(len(f), bool), **out}
    return res, np.ones(len(f), bool)


def main() -> None:
    """Print the share of periodic tests below 1 % and 5 % at 150 and 300 frames."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=300)
    ap.add_argument("--rho", type=float, default=float(np.exp(-0.2)))
    ap.add_argument("--seed", type=int, default=3)
    a = ap.parse_args()
    rng = np.random.default_rng(a.seed)
    for frames in (150, 300):
        tables = [table(rng, a.rho, frames) for _ in range(a.reps)]
        for red in (False, True):
            p = np.array([f.p_value for t in tables for f in stats.periodic_findings(*t, red)])
            print(f"AR(1) rho {a.rho:.3f} per star, {frames} frames, "
                  f"{'red ' if red else 'flat'} reference: {len(p)} tests, "
                  f"p<1% {np.mean(p < 0.01):.4f}  p<5% {np.mean(p < 0.05):.4f}")


if __name__ == "__main__":
    main()
