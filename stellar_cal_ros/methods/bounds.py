"""Posterior Cramér–Rao bounds of the filters' models over a bag.

For a model with additive Gaussian noise that is linear in the error state, the posterior
CRLB recursion of Tichavský, Muravchik & Nehorai (IEEE TSP 1998) is the Kalman covariance
recursion with every Jacobian evaluated on the *true* trajectory and parameters (the Fisher
information of the data plus the prior's ``P0⁻¹``).  :func:`crlb` runs the method's own filter
with: θ at the truth (``truth`` with the prior's σ block, so the prior information is the
filter's), the attitude acquired under the true camera and installation and propagated with
the truth-corrected IMU, nothing injected (:func:`bound_filter_class`), every star used (no
gate, no field-of-view test) and no relinearization.  The returned ``filter.P`` (and the
calibration's σ) is the bound of *this model*: e.g. the swaying filter treats the sway
displacement as white noise of σ_d, as the filter does.
"""

from __future__ import annotations

import copy
import dataclasses
import math

from stellar_cal_ros.io.calibration import Calibration
from stellar_cal_ros.methods import registry


def bound_filter_class(filter_cls):
    """``filter_cls`` whose nominal state is never corrected (see :func:`crlb`)."""

    class BoundFilter(filter_cls):
        method = f"{filter_cls.method}_crlb"

        def inject(self, dx):
            """No injection: θ stays at the truth, the attitude on the truth-driven strapdown."""

    BoundFilter.__name__ = BoundFilter.__qualname__ = f"{filter_cls.__name__}Bound"
    return BoundFilter


def crlb(bag, prior: Calibration, truth: Calibration, method: str = "psce",
         effects: list[str] | None = None, config=None, filter_cls=None):
    """Posterior Cramér–Rao bound of ``method`` with ``effects`` over ``bag`` (a ReplayResult)."""
    from stellar_cal_ros.methods.replay import replay

    spec = registry.get(method)
    ref = copy.deepcopy(truth)
    ref.sigma = copy.deepcopy(prior.sigma)
    cfg = dataclasses.replace(config or spec.config_cls(), gate_probability=1.0, max_iterations=1,
                              scale_gate_by_frame=False, fov_margin=math.inf, unit_check=False)
    return replay(bag, ref, method, effects, cfg,
                  filter_cls=bound_filter_class(filter_cls or spec.filter_cls))
