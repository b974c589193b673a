"""Cramér–Rao bound of the bundle method (free attitude per frame, one camera).

The Fisher information of θ is the camera block of the bundle's normal equations with the
frames' attitudes marginalised (the Schur complement of :class:`~stellar_cal_ros.methods.
bundle.Bundle`), with the frames' stated σ and the prior's information; evaluated at the
truth, its inverse is the bound ``benchmarks/bundle_bound.py`` and ``test/test_bundle.py``
hold the estimator to.
"""

from __future__ import annotations

import numpy as np

from stellar_cal_ros.methods.acf_covariance import _equilibrated_inverse
from stellar_cal_ros.methods.bundle import Bundle, BundleFrame
from stellar_cal_ros.methods.star_model import StarModel


def information_at(model: StarModel, frames: list[BundleFrame], theta: np.ndarray,
                   attitudes: list[np.ndarray], sigma_prior: np.ndarray) -> np.ndarray:
    """Fisher information of θ (attitudes marginalised, prior included) at given values.

    With the stated σ of the frames (no variance factor): at the truth, its inverse is the
    Cramér–Rao bound of the bundle.
    """
    b = Bundle(model, frames, theta, sigma_prior)
    ne = b.normal(theta, attitudes)
    S, _, _ = Bundle.schur(ne, 0.0, stars_only=True)
    return S + np.diag(1.0 / sigma_prior ** 2)


def crlb_bundle(frames: list[BundleFrame], model: StarModel, theta_true: np.ndarray,
                attitudes_true: list[np.ndarray], sigma_prior: np.ndarray) -> np.ndarray:
    """Cramér–Rao bound of θ: the inverse of :func:`information_at` at the truth."""
    cov = _equilibrated_inverse(information_at(model, frames, theta_true, attitudes_true,
                                               sigma_prior))
    return 0.5 * (cov + cov.T)
