r"""The printed first-order biases against the model's response on the bag's noise-free twin.

``discover --verify`` checks each printed bias on noisy twins; on a bag the model does not
fit (``dt_step``) or at an effect's second order (a gyro misalignment's ``e02`` on a clean
psce bag) the twins' mean moves 1.18-1.29x the printed row (doc/benchmarks.md, H255).  The
issue's fix: the row from a run on the noise-free twin (the bag's motion, stamps and stars,
no noise, no misfit: :func:`~stellar_cal_ros.diagnosis.reliability_probe.rendered`) instead
of the first-order sensitivity on the bag.  This measures what that would print and cost:
per effect and sign, :func:`~stellar_cal_ros.diagnosis.verify.check_claims` on the twin of
``discover --auto``'s result with no noise drawn (the runs keep the measured noise scales),
each listed quantity's shift against the printed row (its ratio: what a noise-free twin
says the row should be), and the CPU of one current-model run on that twin (what each row
would cost a diagnosis).  Run::

    python benchmarks/first_order_on_twin.py BAG.mcap RESULT.d psce --effects radial_k3
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from stellar_cal_ros.diagnosis.discover import method_spec
from stellar_cal_ros.diagnosis.noise import stated_scales
from stellar_cal_ros.diagnosis.reliability_probe import rendered
from stellar_cal_ros.diagnosis.twin import twin_scene
from stellar_cal_ros.diagnosis.verify import check_claims
from stellar_cal_ros.io.calibration import load_calibration
from stellar_cal_ros.methods.frames import read_bag_data


def main() -> int:
    """Print, per effect and sign, each listed row's noise-free-twin shift / printed."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("bag")
    ap.add_argument("result", type=Path)
    ap.add_argument("method", nargs="?", default="psce")
    ap.add_argument("--effects", default="radial_k3")
    ap.add_argument("--signs", default="1,-1")
    a = ap.parse_args()
    data = read_bag_data(a.bag)
    calibration = load_calibration(a.result / "calibration.yaml")
    summary = json.loads((a.result / "diagnosis.json").read_text())
    effects = list(method_spec(a.method).baseline) + list(summary.get("added", []))
    noise = stated_scales(calibration)
    scene = twin_scene(data, calibration, a.method)
    renders = []

    def make(injected):
        t0 = time.process_time()
        twin = rendered(data, calibration, a.method, injected, scene)
        renders.append(time.process_time() - t0)
        return twin, {}

    t0 = time.process_time()
    twin = rendered(data, calibration, a.method, {}, scene)
    spec = method_spec(a.method)
    t1 = time.process_time()
    spec.runner(twin, calibration, effects, eval_fraction=0.5, noise=noise,
                gyro_fault="off")
    run_cpu = time.process_time() - t1
    print(f"one render {t1 - t0:.2f} CPU-s, one current-model run on the noise-free twin "
          f"{run_cpu:.2f} CPU-s", flush=True)
    signs = tuple(int(s) for s in a.signs.split(","))
    t0 = time.process_time()
    recs = check_claims(make, calibration, a.method, effects, summary["reliability"], noise,
                        0, only=a.effects.split(","), signs=signs)
    print(f"check_claims {time.process_time() - t0:.1f} CPU-s (full rounds)")
    for rec in recs:
        for c in rec["biases"]:
            print(f"{rec['effect']} {rec['parameter']} {rec['sign']:+d} x{rec['size_scale']:.3g}"
                  f" {c['quantity']}: printed {c['printed']:.4g}, noise-free twin "
                  f"{c['measured']:.4g}, ratio {c['ratio']:.3f} ({c['sigma']:.3g} sigma)",
                  flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
