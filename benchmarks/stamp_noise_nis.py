"""The stars' NIS/dof of a replay whose frames' stamps jitter, with and without ``stamp=``.

Each bag: ``--scenario`` (psce_rotations through :func:`simulate`, swaying_base through
:func:`~stellar_cal_ros.diagnosis.injection.clean_simulation`: the model's own effects),
frames stamped N(0, ``--jitter-ms``) off their exposures
(:func:`~stellar_cal_ros.sim.tracker_errors.stamp_jitter`), replayed with the stated noise
and with ``NoiseScales(stamp_ms=--jitter-ms)`` (the stamps' noise in each frame's R).  One
line a seed: the two NIS/dof; then their mean and sd (issue 21, H277).

Run::

    .venv/bin/python benchmarks/stamp_noise_nis.py --scenario psce_rotations --duration 120 \
        --seeds 21,22,23,24,25,26
    .venv/bin/python benchmarks/stamp_noise_nis.py --scenario swaying_base --duration 60 \
        --seeds 21,22,23,24
"""

from __future__ import annotations

import argparse

import numpy as np

from stellar_cal_ros.core.noise import NoiseScales
from stellar_cal_ros.diagnosis.injection import clean_simulation
from stellar_cal_ros.methods.frames import bag_data_from_simulation
from stellar_cal_ros.methods.replay import replay
from stellar_cal_ros.sim import tracker_errors
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate


def nis_dof(res) -> float:
    """The stars' NIS per degree of freedom over the whole replay."""
    s = res.stats.current() if hasattr(res.stats, "current") else res.stats
    return s.sum_nis / (2.0 * s.stars)


def main() -> None:
    """The command line (see the module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenario", default="psce_rotations",
                    choices=("psce_rotations", "swaying_base"))
    ap.add_argument("--duration", type=float, default=120.0)
    ap.add_argument("--seeds", default="21,22,23,24,25,26")
    ap.add_argument("--jitter-ms", type=float, default=1.0)
    a = ap.parse_args()
    method = "psce" if a.scenario == "psce_rotations" else "swaying_base"
    got = []
    for seed in (int(s) for s in a.seeds.split(",")):
        if method == "psce":
            sim = simulate(get_scenario(a.scenario), duration=a.duration, seed=seed)
        else:
            sim, _ = clean_simulation("swaying_base", False, seed, a.duration)
        tracker_errors.stamp_jitter(sim, a.jitter_ms * 1e-3, seed)
        data = bag_data_from_simulation(sim)
        row = [nis_dof(replay(data, sim.prior, method, noise=NoiseScales(stamp_ms=st),
                              keep_tables=False)) for st in (0.0, a.jitter_ms)]
        got.append(row)
        print(f"seed {seed}: NIS/dof {row[0]:.4f} without, {row[1]:.4f} with stamp="
              f"{a.jitter_ms:g}", flush=True)
    x = np.array(got)[:, 1]
    print(f"with stamp={a.jitter_ms:g}: mean {x.mean():.4f} sd {x.std(ddof=1):.4f}")


if __name__ == "__main__":
    main()
