"""The built-in demonstration behind ``stellar-cal demo`` (the README's first command).

The model-discovery loop on a bag with a hidden physical effect:

1. simulate ``psce_rotations`` with an effect the baseline PSCE model does not have;
2. calibrate with the baseline model (``replay --method psce``);
3. diagnose: the residuals exceed the noise floor and the ranking names the effect;
4. calibrate again with the effect added (``--effects ID``);
5. the residual RMS falls to the noise floor and the new parameter matches the truth.

Each step prints what the equivalent ``stellar-cal`` command line is.  An application beside
the command line (:mod:`stellar_cal_ros.cli`), built on the same layers.
"""

from __future__ import annotations

from pathlib import Path

from stellar_cal_ros.diagnosis import stats
from stellar_cal_ros.diagnosis.printing import print_diagnosis
from stellar_cal_ros.diagnosis.run import diagnose
from stellar_cal_ros.io.calibration import load_calibration, save_calibration
from stellar_cal_ros.io.residuals import write_residuals
from stellar_cal_ros.methods.replay import read_bag_data, replay_psce
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate, write_simulation

HIDDEN_EFFECT = ("time_offset", 0.02)  # the tracker stamps its frames 20 ms early


def _rms(result) -> tuple[float, float]:
    res = result.residuals
    return stats.rms(res, stats.evaluation_mask(res))


def run_demo(output: Path, duration: float = 600.0, seed: int = 7) -> int:
    """Run the demonstration; return a process exit status (0: the loop worked)."""
    output = Path(output)
    effect_id, value = HIDDEN_EFFECT
    bag = output / "demo.mcap"
    print(f"== 1. simulate psce_rotations ({duration:.0f} s) with a hidden effect ==")
    print(f"   $ stellar-cal simulate --scenario psce_rotations --duration {duration:.0f} "
          f"--seed {seed} --effect {effect_id}={value} -o {bag}")
    scenario = get_scenario("psce_rotations")
    sim = simulate(scenario, duration=duration, seed=seed, effects={effect_id: value})
    paths = write_simulation(sim, bag)
    noise = scenario.centroid_noise_px
    print(f"   {len(sim.star_frames)} star frames, {sim.imu.stamp_ns.size} IMU samples; "
          f"centroid noise {noise} px (the floor to reach)")

    data = read_bag_data(bag)
    prior = load_calibration(paths["prior"])
    truth = load_calibration(paths["truth"])

    print("== 2. calibrate with the baseline PSCE model ==")
    base_yaml = output / "baseline.yaml"
    print(f"   $ stellar-cal replay {bag} --method psce --prior {paths['prior']} -o {base_yaml}")
    base = replay_psce(data, prior)
    save_calibration(base.calibration, base_yaml)
    write_residuals(output / "baseline_residuals.csv", base.residuals)
    rms0 = _rms(base)
    print(f"   innovation RMS u={rms0[0]:.4f} v={rms0[1]:.4f} px "
          f"= {max(rms0) / noise:.1f}x the noise floor: the model misses something")

    print("== 3. diagnose ==")
    report_dir = output / "diagnosis"
    print(f"   $ stellar-cal diagnose {bag} --calibration {base_yaml} --method psce "
          f"-o {report_dir}")
    summary = diagnose(data, base.calibration, "psce", [], report_dir, verbose=False)
    print_diagnosis(summary, base.calibration)
    found = summary.get("recommendation")
    print(f"   report: {report_dir / 'report.html'}")
    if found is None:
        print("   the diagnosis found no effect: demo failed")
        return 1

    print(f"== 4. add {found} and calibrate again ==")
    new_yaml = output / f"with_{found}.yaml"
    print(f"   $ stellar-cal replay {bag} --method psce --prior {paths['prior']} "
          f"--effects {found} -o {new_yaml}")
    again = replay_psce(data, prior, [found])
    save_calibration(again.calibration, new_yaml)
    rms1 = _rms(again)
    print(f"   innovation RMS u={rms1[0]:.4f} v={rms1[1]:.4f} px "
          f"({max(rms1) / noise:.3f}x the noise floor)")

    print("== 5. result ==")
    if found == effect_id == "time_offset":
        sig = again.calibration.sigma.get("time_offset", float("nan"))
        print(f"   time_offset estimated {again.calibration.time_offset * 1e3:.3f} "
              f"+- {sig * 1e3:.3f} ms (truth {truth.time_offset * 1e3:.3f} ms)")
    ok = found == effect_id and max(rms1) <= 1.05 * noise
    print(f"   the hidden effect was {effect_id}; the diagnosis named {found}; "
          f"RMS {max(rms0):.4f} -> {max(rms1):.4f} px: "
          + ("the loop worked." if ok else "NOT as expected."))
    return 0 if ok else 1

