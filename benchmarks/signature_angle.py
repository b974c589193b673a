"""How far one effect's signature lies from another's on a bag: angles through the information.

Both effects are scored by one screening run of the prior's model (consider parameters,
:func:`stellar_cal_ros.methods.screening.score_tests`), whose joint information over the
evaluation window ``I`` is the inner product of their signatures.  Per parameter of the
first effect this prints the squared canonical correlation with the second effect's span,
``I_xm I_mm⁻¹ I_mx / I_xx`` (1: the second explains it entirely), its angle, and the plain
correlation with each parameter of the second; then the canonical correlations of the two
spans.  A parameter at a few degrees cannot be told from the other effect on this motion:
its distinguishing part has ``1 − ρ²`` of its information (the MDB of that part is the
parameter's MDB over ``sqrt(1 − ρ²)``).  Run::

    python benchmarks/signature_angle.py BAG.mcap CALIBRATION.yaml psce \
        gyro_scale_factor gyro_misalignment
"""

from __future__ import annotations

import argparse

import numpy as np

import stellar_cal_ros.methods.screening as kernel_screening
from stellar_cal_ros.diagnosis import runstats
from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
from stellar_cal_ros.io.calibration import load_calibration


def _pinv(m: np.ndarray) -> np.ndarray:
    w, v = np.linalg.eigh(m)
    good = w > 1e-12 * w.max()
    return (v[:, good] / w[good]) @ v[:, good].T


def main() -> int:
    """Print the angles for the bag, calibration, method and two effects of the command line."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("bag")
    ap.add_argument("calibration")
    ap.add_argument("method")
    ap.add_argument("first")
    ap.add_argument("second")
    a = ap.parse_args()
    got = {}
    score_tests = kernel_screening.score_tests

    def keep(result, candidates, *args, **kw):
        flt = result.filter
        got.update(info=np.array(flt.sensitivity.info), n=flt.P_est,
                   effects={e.id: (flt.model.slices[e.id], e.parameter_names)
                            for e in flt.model.effects})
        return score_tests(result, candidates, *args, **kw)

    kernel_screening.score_tests = keep  # the joint information, before it is split by effect
    prior = rerun_prior(load_calibration(a.calibration))
    runstats.evaluate(a.bag, method_spec(a.method), prior, (), 0.5, screen=(a.first, a.second))
    info = got["info"]
    info = 0.5 * (info + info.T)

    def columns(eid):
        sl, names = got["effects"][eid]
        return np.arange(sl.start - got["n"], sl.stop - got["n"]), names

    (x, xn), (m, mn) = columns(a.first), columns(a.second)
    imm = info[np.ix_(m, m)]
    inv = _pinv(imm)
    for j, name in zip(x, xn, strict=True):
        v = info[j, m]
        rho2 = float(v @ inv @ v / info[j, j])
        corr = info[j, m] / np.sqrt(info[j, j] * np.diag(imm))
        print(f"{a.first}.{name}: rho^2 with {a.second} {rho2:.4f} (angle "
              f"{np.degrees(np.arccos(np.sqrt(min(rho2, 1.0)))):.1f} deg); "
              + " ".join(f"{n} {c:+.3f}" for n, c in zip(mn, corr, strict=True)))
    ixx = info[np.ix_(x, x)]
    w, v = np.linalg.eigh(imm)
    good = w > 1e-12 * w.max()
    cross = np.linalg.solve(np.linalg.cholesky(ixx), info[np.ix_(x, m)]) @ (
        v[:, good] / np.sqrt(w[good]))
    print("canonical correlations of the two spans:",
          " ".join(f"{c:.4f}" for c in np.linalg.svd(cross, compute_uv=False)))
    print(f"{a.second} information eigenvalues:", " ".join(f"{e:.3g}" for e in w))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
