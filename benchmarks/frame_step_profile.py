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
* :func:`~stellar_cal_ros.methods.frame_step.frame_steps`, the replay's batched call, on the
  longest run of frames a batched replay of the bag handed it (its own arguments, kept from
  a second replay with ``StarFilter.batched_step`` True: consecutive frames, each from the
  state the one before left), its marshalling included, per frame; beside it the same
  frames as one :func:`~stellar_cal_ros.methods.frame_step.frame_step` call each (the state
  carried from frame to frame, as the per-frame replay calls them; the final state is
  checked equal to the batched call's, bit for bit);
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
    n = args[25].shape[0]  # (uv: the frame's stars)
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


def capture_run(bag: Path) -> tuple | None:
    """Copies of the arguments of the last longest :func:`frame_steps` call of a batched replay.

    Only a call that stepped every frame it was given (``done`` = K) is kept: its frames are
    then each a :func:`frame_step` call of the per-frame replay, from the state the frame
    before left.  None: no batch.
    """
    prior = load_calibration(str(bag).removesuffix(".mcap") + ".prior.yaml")
    best: list = [None, 0]
    original = fsm.frame_steps

    def keep(*a):
        kept = tuple(x.copy() if isinstance(x, np.ndarray) else x for x in a)
        out = original(*a)
        if int(out[0]) == len(a[12]) >= best[1]:  # (the last longest: a settled run)
            best[:] = [kept, len(a[12])]
        return out

    fsm.frame_steps = keep
    try:
        replay(bag, prior, "psce", keep_tables=False)
    finally:
        fsm.frame_steps = original
    return best[0]


def split_run(b: tuple) -> tuple[tuple, list]:
    """The state and each frame's other :func:`frame_step` arguments of a run ``b``.

    ``b``: :func:`frame_steps` arguments (fixed exposure times: the rows and times as given).
    Returns ``(state, frames)``: ``state`` = ``(P, theta, R_a, M, score, info)``, ``frames[i]``
    the arguments after the state, for frame ``i``.
    """
    (P, theta, R_a, M, score, info, acc, tp, C, w_hat, phi, slope, js, mjs, tas, tbs, Gamma,
     theta_ref, q_diag, b0, E0, Jb, JE, th0, imu_w, ms, uv, u, sigma, offs, base, *rest) = b
    *consts, du, bscale, Pe, cfg = rest[:-6]
    frames = []
    for i in range(len(js)):
        a, e = int(offs[i]), int(offs[i + 1])
        frames.append((bool(acc[i]), tp, C, w_hat, phi, slope, int(js[i]), int(mjs[i]),
                       float(tas[i]), float(tbs[i]), Gamma, theta_ref, q_diag, b0, E0, Jb, JE,
                       th0, imu_w[ms[i]].copy(), uv[a:e].copy(), u[a:e].copy(),
                       sigma[a:e].copy(), float(base[i]), *consts, du[a:e].copy(),
                       bscale[i].copy(), Pe, cfg))
    return (P, theta, R_a, M, score, info), frames


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
    # the replay's batched call (frame_steps) on a run of consecutive frames it was handed,
    # against the same frames one frame_step call each (the state carried, as a replay
    # without batches calls them)
    b = capture_run(args.bag)
    if b is None:
        print("no batched call stepped a whole run")
        return 0
    state, frames = split_run(b)
    K = len(frames)
    reps = max(args.repeat // K, 1)
    fsm.frame_steps(*b)
    t = time.process_time()
    for _ in range(reps):
        out = fsm.frame_steps(*b)
    t_batch = (time.process_time() - t) / (reps * K) * 1e6
    states = [tuple(x.copy() for x in state) for _ in range(reps + 1)]
    for f in frames:
        fsm.frame_step(*states[0], *f)
    t = time.process_time()
    for st in states[1:]:
        for f in frames:
            fsm.frame_step(*st, *f)
    t_single = (time.process_time() - t) / (reps * K) * 1e6
    same = all(np.array_equal(x, y[K - 1]) for x, y in zip(
        states[-1], out[11:], strict=True))
    its = {int(k): int(v) for k, v in zip(*np.unique(out[2][:, 1], return_counts=True),
                                           strict=True)}
    print(f"a replay's run of {K} consecutive frames (iterations {its}), per frame:")
    print(f"{'frame_steps (the batched call)':34s} {t_batch:8.1f}")
    print(f"{'frame_step, one call a frame':34s} {t_single:8.1f}  (the same frames; final state "
          f"equal to the batch's: {same})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
