"""The bundle on real night-sky frames (``../shared/realsky``), against tetra3rs.

Skipped, with the reason shown, when the folder is absent (a clone has no ../shared).
The numbers behind these checks: ``benchmarks/realsky_bundle.py`` (doc/benchmarks.md).
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
import refdata

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "realsky_bundle.py"
IMAGES = refdata.REALSKY
#: the three frames of one camera in one optical state (test2_g100_e50ms is another: its own
#: fit has k1 = -0.46 against ~0 for these)
FRAMES = ["jan1_g90_e100ms", "jan1_g90_e50ms", "test_5mp_g100_e50ms"]

pytestmark = refdata.needs(folder=IMAGES)


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("realsky_bundle", BENCH)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # its dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def images(bench):
    return [bench.load_grey(bench.image_path(IMAGES, n)) for n in FRAMES]


def _data(bench, frames):
    return bench.BagData(t0_ns=frames[0].stamp_ns, imu_t=np.zeros(0), imu_w=np.zeros((0, 3)),
                         imu_f=np.zeros((0, 3)), frames=frames, site=None,
                         head_temperature=None, air_temperature=None, pressure=None)


def test_held_out_rms_against_tetra3rs(bench):
    """After discover --method bundle, on the project's PSF-fit centroids: held-out RMS at
    most 0.9x tetra3rs calibrate_camera's (the issue's acceptance; measured 0.62x), by the
    same rule and against its own re-solve RMSE; on tetra3rs's moment centroids the two
    fits are equal within 10 % (the centroids are the difference), every frame identified."""
    out = bench.compare(FRAMES, IMAGES, discover=True, t3_models=(("radial", 4),))
    rows = {r.name.split(",")[0]: r for r in out["rows"]}
    psf, moments = rows["ours: psf centroids"], rows["ours: tetra3rs centroids"]
    t3 = rows["tetra3rs radial"]
    assert all(n >= 25 for n in out["ours"]["psf"]["identified"])
    assert np.mean(psf.held_out) <= 0.9 * np.mean(t3.held_out), (psf.held_out, t3.held_out)
    assert np.mean(psf.held_out) <= 0.9 * np.mean(t3.own)
    assert np.mean(moments.held_out) <= 1.1 * np.mean(t3.held_out)
    assert sum(psf.rejected) <= 3


def test_a_frame_of_another_camera_state_is_named(bench, images):
    """test2_g100_e50ms (another focus/zoom) is named as not sharing the others' camera."""
    from stellar_cal_ros.methods.bundle_runs import run_bundle

    odd = bench.load_grey(bench.image_path(IMAGES, "test2_g100_e50ms"))
    frames, fovs, _, _ = bench.identified_frames(images + [odd], "tetra3rs")
    prior = bench.pinhole_prior(1280, 960, float(np.nanmedian(fovs)))
    res = run_bundle(_data(bench, frames), prior, [])
    assert len(res.degraded) == 1 and res.degraded[0].startswith("frame 3 does not share")
