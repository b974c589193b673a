r"""z of clock_drift's rate over seeds, with and without time_offset beside it (issue 21, H208).

The drift-only psce bag (:func:`~stellar_cal_ros.diagnosis.injection.clean_simulation`,
300 s) with ``sky_clock_drift``'s stamps (late by 0 at the prior's stamp, clock_drift's
reference, growing to 30 ms at the last frame) and every stamp shifted by a constant c
(``--offsets``, s: positive = late, a time_offset of −c), replayed with the final model
``discover`` made before H208 (clock_drift alone) and with time_offset beside it.  One JSON
line per seed, offset and model: the rate and its printed σ (ppm), the truth
``−(D / T) / (1 + D / T)`` and ``z = (rate − truth) / σ``; time_offset's fit (us).

    PYTHONPATH=$PWD python benchmarks/clock_drift_z.py --seeds 21,22,23,24,25,26 \
        --offsets 0,25e-6,-25e-6
"""

from __future__ import annotations

import argparse
import json

from stellar_cal_ros.diagnosis.injection import clean_simulation
from stellar_cal_ros.methods.replay import bag_data_from_simulation, replay

DRIFT_S = 0.03


def main() -> None:  # noqa: D103
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="21,22,23,24")
    ap.add_argument("--offsets", default="0,25e-6,-25e-6")
    args = ap.parse_args()
    for seed in (int(s) for s in args.seeds.split(",")):
        for c in (float(x) for x in args.offsets.split(",")):
            sim, model = clean_simulation("psce", False, seed, 300.0)
            t0, t1 = round(sim.prior.stamp * 1e9), sim.star_frames[-1].stamp_ns
            for f in sim.star_frames:
                f.stamp_ns = int(f.stamp_ns + round(
                    (c + DRIFT_S * (f.stamp_ns - t0) / (t1 - t0)) * 1e9))
            span = (t1 - t0) * 1e-9
            truth = -(DRIFT_S / span) / (1.0 + DRIFT_S / span)
            data = bag_data_from_simulation(sim)
            for eff in (["clock_drift"], ["clock_drift", "time_offset"]):
                cal = replay(data, sim.prior, "psce", list(model) + eff,
                             keep_tables=False).calibration
                rate = cal.effects["clock_drift"]["rate"]
                sig = cal.sigma["effects"]["clock_drift"]["rate"]
                row = {"seed": seed, "offset_us": c * 1e6, "effects": eff,
                       "rate_ppm": rate * 1e6, "sigma_ppm": sig * 1e6,
                       "truth_ppm": truth * 1e6, "z": (rate - truth) / sig}
                if "time_offset" in eff:
                    row["dt_us"] = cal.time_offset * 1e6
                    row["dt_sigma_us"] = cal.sigma["time_offset"] * 1e6
                print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
