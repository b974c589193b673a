"""What one call of the compiled frame step costs, and where (issue 24.1).

Usage::

    python benchmarks/frame_step_profile.py [--bag BAG.mcap] [--frames 40] [--repeat 2000]

Replays ``BAG`` (default: the 600-s ``psce_rotations`` bag of ``psce_speed.py``, simulated
once) with the PSCE filter and keeps the arguments of ``--frames`` ordinary calls of
:func:`stellar_cal_ros.methods.frame_step.frame_step` (copies, spread over the bag), then
times, hot (the same frame ``--repeat`` times, CPU time per call):

* ``frame_step`` itself;
* the same step ``--repeat`` times inside one compiled call (the state reset from copies
  each time): the per-frame cost of a batched call over a pump's frames, which pays no
  marshalling, no boxing and no Python between two steps;
* :func:`~stellar_cal_ros.methods.frame_step.frame_steps`, the replay's batched call: the
  frame 50 times in a row in one call (each frame's state kept, as a replay's run up to its
  next covariance check), its marshalling included, per frame;
* the call alone: a compiled function taking the same arguments and returning at once
  (argument marshalling), and one that also builds and returns a result tuple of the same
  shape (the boxing of the returned arrays);
* its parts on the same frame, each a compiled call of its own (so each carries ~1-2 µs of
  call overhead): the attitude interval, the covariance propagation, the prediction with
  Jacobians, the per-star innovation blocks, one Kalman gain, the Joseph step, the gate.

Prints the stars and state size of the timed frame and the iterations the kept frames took.
The replay's own figure (``replay_profile.py``: ``frame_step`` exclusive time over a whole
replay) is higher: there the driver's Python runs between two calls and the step starts with
cold caches.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from stellar_cal_ros.core.jit import joseph, kalman_gain, njit, star_blocks
from stellar_cal_ros.io.calibration import load_calibration
from stellar_cal_ros.methods import frame_step as fsm
from stellar_cal_ros.methods.kernel import StarFilter
from stellar_cal_ros.methods.replay import replay
from stellar_cal_ros.methods.star_chain import predict_chain

sys.path.insert(0, str(Path(__file__).parent))


@njit
def _loop_steps(K, P0, theta0, R0, *rest):
    """``K`` steps of the same frame in one compiled call (state reset from copies each time)."""
    nis = 0.0
    for _ in range(K):
        out = fsm.frame_step(P0.copy(), theta0.copy(), R0.copy(), *rest)
        nis += out[2][0]
    return nis


@njit
def _noop(*args):
    return 0


@njit
def _noop_tuple(*args):
    n = args[24].shape[0]
    return (0, np.zeros(6, dtype=np.int64), np.zeros(13), np.zeros(n, dtype=np.bool_),
            np.zeros((n, 2)), np.zeros((n, 2, 2)), np.zeros(n), np.zeros((n, 3)), np.zeros(3),
            np.eye(3))


def capture(bag: Path, frames: int) -> list[tuple]:
    """Copies of the arguments of ``frames`` frame_step calls spread over a replay of ``bag``."""
    prior = load_calibration(str(bag).removesuffix(".mcap") + ".prior.yaml")
    calls: list[tuple] = []
    original = fsm.frame_step
    count = [0]

    def keep(*a):
        count[0] += 1
        if count[0] % 25 == 0 and len(calls) < frames:
            calls.append(tuple(x.copy() if isinstance(x, np.ndarray) else x for x in a))
        return original(*a)

    fsm.frame_step = keep
    StarFilter.batched_step = False  # one Python call a frame (the batched call is timed below)
    try:
        replay(bag, prior, "psce", keep_tables=False)
    finally:
        fsm.frame_step = original
        StarFilter.batched_step = True
    return calls


def batched_args(a: tuple, K: int) -> tuple:
    """:func:`~stellar_cal_ros.methods.frame_step.frame_steps` arguments of ``K`` frames.

    ``K`` times the frame of the ``frame_step`` arguments ``a`` (the same interval and stars,
    one after another).
    """
    (P, theta, R_a, M, score, info, acc, tp, C, w_hat, phi, slope, j, mj, ta, tb, Gamma,
     theta_ref, q_diag, b0, E0, Jb, JE, th0, w_raw, uv, u, sigma, base, *chain) = a
    *consts, du, bscale, Pe, cfg = chain
    n = len(uv)
    rep = lambda x: np.ascontiguousarray(np.concatenate([x] * K))  # noqa: E731
    return (P.copy(), theta.copy(), R_a.copy(), M.copy(), score.copy(), info.copy(),
            np.full(K, bool(acc)), tp, C, w_hat, phi, slope, np.full(K, j, dtype=np.int64),
            np.full(K, mj, dtype=np.int64), np.full(K, ta), np.full(K, tb), Gamma, theta_ref,
            q_diag, b0, E0, Jb, JE, th0, np.tile(w_raw, (K, 1)), np.arange(K, dtype=np.int64),
            rep(uv), rep(u), rep(sigma), np.arange(K + 1, dtype=np.int64) * n, np.full(K, base),
            *consts, rep(du), np.tile(bscale, (K, 1)).reshape(K, len(bscale)), Pe, cfg,
            np.full(K, tb + base), np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0),
            np.zeros(1, dtype=np.int64), np.array([0.0, 0, 0, 0, 0, 0, 0, np.inf, 0.0]))


def per_call(f, make_args, repeat: int) -> float:
    """CPU µs per call of ``f(*args)`` (fresh argument copies, made outside the timing)."""
    sets = [make_args() for _ in range(repeat)]
    f(*sets[0])
    t = time.process_time()
    for a in sets:
        f(*a)
    return (time.process_time() - t) / repeat * 1e6


def main(argv=None) -> int:
    """Command line entry."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--bag", type=Path)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--repeat", type=int, default=2000)
    args = ap.parse_args(argv)
    if args.bag is None:
        import psce_speed

        args.bag = psce_speed.ensure_bag(600.0)
    calls = capture(args.bag, args.frames)
    if not calls:
        print("no frame took the compiled step")
        return 1
    a = calls[-1]

    def fresh():
        return tuple(x.copy() if isinstance(x, np.ndarray) else x for x in a)

    (P, theta, R_a, M, _score, _info, _acc, tp, C, w_hat, phi, slope, j, mj, ta, tb, Gamma,
     theta_ref,
     q_diag, _b0, _E0, _Jb, _JE, _th0, w_raw, uv, u, sigma, base, s0, g, timed, R_prior, T,
     tracked, c, B, need, dcol, dfix, dgrp, cam, du, bscale, Pe, cfg) = a
    n, N, P_all = len(uv), P.shape[0], len(theta)
    iterations = [int(fsm.frame_step(*tuple(x.copy() if isinstance(x, np.ndarray) else x
                                             for x in c_))[1][1]) for c_ in calls]
    ok, R_b, F = fsm.attitude_interval(tp, C, w_hat, phi, slope, j, mj, ta, tb, R_a, Gamma,
                                       theta - theta_ref, cfg[10])
    uv_p, dirs = np.empty((n, 2)), np.empty((n, 3))
    H_att, H_par, R_out = np.empty((n, 2, 3)), np.empty((n, 2, P_all)), np.empty((2, 3, 3))
    zero3 = np.zeros(3)

    def predict():
        return (theta, u, R_b, zero3, False, w_raw, base, s0, g, timed, R_prior, T, tracked, c,
                B, need, dcol, dfix, dgrp, cam, du, bscale, 1, uv_p, dirs, H_att, H_par, R_out)

    predict_chain(*predict())
    H0 = np.zeros((n, 2, N))
    H0[:, :, :3] = H_att
    H0[:, :, 3:3 + Pe] = H_par[:, :, :Pe]
    nu0 = uv - uv_p
    H, rr, nu = H0.reshape(-1, N).copy(), np.repeat(sigma ** 2, 2), nu0.reshape(-1).copy()
    K = kalman_gain(P, H, rr, nu)[1]
    nis = star_blocks(H0, P, sigma ** 2, nu0)[1]
    accepted = np.zeros(n, dtype=bool)
    rows = [
        ("frame_step (whole call)", fsm.frame_step, fresh),
        ("  call alone (marshalling)", _noop, fresh),
        ("  call + result tuple", _noop_tuple, fresh),
        ("  attitude interval", fsm.attitude_interval,
         lambda: (tp, C, w_hat, phi, slope, j, mj, ta, tb, R_a, Gamma, theta - theta_ref,
                  cfg[10])),
        ("  covariance propagation", fsm.propagate_coupled,
         lambda: (P.copy(), M, Pe, F, q_diag * (tb - ta))),
        ("  prediction + Jacobians", predict_chain, predict),
        ("  per-star blocks (gate input)", star_blocks, lambda: (H0, P, sigma ** 2, nu0)),
        ("  gate", fsm.gate, lambda: (nis, dirs, cfg, accepted)),
        ("  Kalman gain (one iteration)", kalman_gain, lambda: (P, H, rr, nu)),
        ("  Joseph step", joseph, lambda: (P, K, H, rr)),
    ]
    its = {int(k): int(v) for k, v in zip(*np.unique(iterations, return_counts=True),
                                           strict=True)}
    print(f"bag {args.bag.name}: timed frame with {n} stars, state N = {N} (θ {P_all}); "
          f"iterations of the {len(calls)} kept frames: {its}")
    print(f"{'':34s} {'µs/call':>8s}")
    for label, f, make in rows:
        print(f"{label:34s} {per_call(f, make, args.repeat):8.1f}")
    # the same step K times inside one compiled call: what a batched call over a pump's
    # frames would pay per frame (no marshalling, no boxing, no Python between two steps)
    _loop_steps(1, *fresh())
    t = time.process_time()
    _loop_steps(args.repeat, *fresh())
    print(f"{'frame_step in one compiled loop':34s} "
          f"{(time.process_time() - t) / args.repeat * 1e6:8.1f}  (per frame, 3 state copies)")
    # the replay's batched call (frame_steps: a run of up to 50 frames, to the next
    # covariance check), the marshalling of its arguments and results included
    K = 50
    calls_b = max(args.repeat // K, 1)
    sets = [batched_args(a, K) for _ in range(calls_b + 1)]
    fsm.frame_steps(*sets[0])
    t = time.process_time()
    for s_ in sets[1:]:
        fsm.frame_steps(*s_)
    print(f"{'frame_steps (the batched call)':34s} "
          f"{(time.process_time() - t) / (calls_b * K) * 1e6:8.1f}  (per frame, runs of {K}, "
          "each frame's state kept)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
