"""Seeded faulty variants of a simulated run, and how to judge what a command did with them.

A *variant* is a damaged copy of a clean simulated run (its bag and its prior): damaged bytes
(truncation, zeroed ranges, bad chunk CRCs, not an MCAP file), damaged messages (NaN/inf in
IMU or star fields, out-of-image centroids, σ ≤ 0 or NaN, misidentified stars, empty star
arrays, duplicated or late messages), damaged time (IMU gaps, clock jumps), missing topics,
wrong units (gyro in deg/s, swapped axes, a dead gyro) and broken priors.  Every variant
declares, per command, the outcome class it must get:

``error``
    a clear one-line error naming the cause (the variant's ``cause`` pattern), a non-zero
    exit status and no traceback;
``skip``
    the damage is counted (a warning or a counter in the printout) and the key number — the
    equivalent principal point error against the truth — stays within
    :data:`KEY_TOLERANCE` × the clean run's (the clean run over the data the variant keeps:
    :attr:`Built.reference`);
``flagged``
    a result whose YAML (``data_quality.degraded: true``, or a ``consistency.verdict`` other
    than ``consistent``) or printout (a line with "degraded") says the result is degraded;
``ok``
    nothing to notice (the fault is not one for this command).

An expectation may allow several classes (e.g. ``info`` on a damaged bag may fail or flag).
The outcome actually seen is judged by :func:`stellar_cal_ros.sim.fault_campaign.classify`:
a traceback or a signal is a *crash*, a timeout a *hang*, and an exit-0 result whose key
number exceeds the tolerance without a flag is *silently wrong*.
``benchmarks/fault_campaign.py`` runs the commands in subprocesses and prints the table;
``test/test_faults.py`` runs a reduced set.

Everything is seeded: the same base run and variant name give byte-identical files.  Bags
are written three ways: decoded data through the project's :class:`~stellar_cal_ros.io.bag.
BagWriter` (message-level faults), raw records through the independent ``mcap`` writer
(stream-level faults: log times that disagree with header stamps, duplicates), and raw bytes
(container damage).
"""

from __future__ import annotations

import copy
import math
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from stellar_cal_ros.io.bag import BagWriter, ImuSeries, NavSatSeries, ScalarSeries, StarFrame
from stellar_cal_ros.sim.bag_damage import (
    RawMessage,
    bad_chunk_crc,
    chunk_spans,
    flip_bytes,
    header_stamp_ns,
    read_raw,
    truncate,
    with_header_stamp,
    write_raw,
    zero_range,
)

KEY_TOLERANCE = 1.2
"""A counted skip must keep the key number within this factor of the clean run's."""

OUTCOMES = ("error", "skip", "flagged", "ok")
TOPIC_IMU = "/imu/data"
TOPIC_STARS = "/star_tracker/stars"
TOPIC_FIX = "/gnss/fix"
_SCALAR_TOPICS = {"head": ("/star_tracker/temperature", "temperature"),
                  "air": ("/environment/temperature", "temperature"),
                  "pressure": ("/environment/pressure", "pressure")}


# ============================================================================ recordings
@dataclass
class Recording:
    """The decoded topics of one run (None: topic absent)."""

    imu: ImuSeries | None
    stars: list[StarFrame] | None
    navsat: NavSatSeries | None = None
    scalars: dict[str, ScalarSeries] = field(default_factory=dict)

    @classmethod
    def from_simulation(cls, sim: Any) -> Recording:
        """The topics of a :class:`~stellar_cal_ros.sim.world.SimulationResult`."""
        return cls(imu=sim.imu, stars=list(sim.star_frames), navsat=sim.navsat,
                   scalars={"head": sim.head_temperature, "air": sim.air_temperature,
                            "pressure": sim.pressure})

    def copy(self) -> Recording:
        """A deep copy (faults modify it in place)."""
        return copy.deepcopy(self)

    def write(self, path: str | Path, chunk_size: int = 768 * 1024) -> Path:
        """Write the bag with the project's writer (log time = header stamp)."""
        path = Path(path)
        with BagWriter(path, chunk_size=chunk_size) as w:
            if self.imu is not None:
                w.write_imu(self.imu, TOPIC_IMU)
            if self.stars is not None:
                w.write_star_frames(self.stars, TOPIC_STARS)
            if self.navsat is not None:
                w.write_navsat(self.navsat, TOPIC_FIX)
            for key, series in self.scalars.items():
                topic, kind = _SCALAR_TOPICS[key]
                w.write_scalar(series, topic, kind=kind)
        return path

    def keep_time(self, keep: Callable[[np.ndarray], np.ndarray]) -> Recording:
        """A copy holding only the messages whose stamp (ns) ``keep`` accepts."""
        out = self.copy()
        if out.imu is not None:
            m = keep(np.asarray(out.imu.stamp_ns))
            out.imu = _imu_subset(out.imu, m)
        if out.stars is not None:
            out.stars = [f for f in out.stars if keep(np.array([f.stamp_ns]))[0]]
        if out.navsat is not None:
            m = keep(np.asarray(out.navsat.stamp_ns))
            out.navsat = _series_subset(out.navsat, m)
        out.scalars = {k: _series_subset(s, keep(np.asarray(s.stamp_ns)))
                       for k, s in out.scalars.items()}
        return out


def _imu_subset(imu: ImuSeries, m: np.ndarray) -> ImuSeries:
    return replace(imu, stamp_ns=np.asarray(imu.stamp_ns)[m],
                   angular_velocity=np.asarray(imu.angular_velocity)[m],
                   linear_acceleration=np.asarray(imu.linear_acceleration)[m], log_time_ns=None)


def _series_subset(s: Any, m: np.ndarray) -> Any:
    kw = {}
    for name in s.__dataclass_fields__:
        v = getattr(s, name)
        if isinstance(v, np.ndarray) and v.ndim >= 1 and len(v) == len(m):
            kw[name] = v[m]
    kw["log_time_ns"] = None
    return replace(s, **kw)


# ============================================================================ variants
@dataclass(frozen=True)
class Expect:
    """What one command must do with a variant.

    Attributes
    ----------
    command : str
        A key of :data:`COMMANDS`.
    outcomes : tuple of str
        Acceptable outcome classes (:data:`OUTCOMES`).
    cause : str
        Regular expression (case-insensitive) the one-line error must match.
    """

    command: str
    outcomes: tuple[str, ...]
    cause: str = ""


def expect(command: str, outcomes: str, cause: str = "") -> Expect:
    """``expect("replay", "error|flagged", "truncat")`` → :class:`Expect`."""
    out = tuple(outcomes.split("|"))
    bad = set(out) - set(OUTCOMES)
    if bad:
        raise ValueError(f"unknown outcome class {bad}")
    return Expect(command, out, cause)


@dataclass
class BaseRun:
    """The clean run every variant is made from (written by :func:`make_base`)."""

    directory: Path
    bag: Path
    prior: Path
    truth: Path
    recording: Recording
    seed: int

    def prior_dict(self) -> dict[str, Any]:
        """The prior YAML as a dict."""
        return yaml.safe_load(self.prior.read_text())


@dataclass
class Built:
    """The files of one variant.

    Attributes
    ----------
    bag, prior : Path
        What the commands are run on.
    reference : Path or None
        A clean bag holding the data the variant keeps: the key number of a ``skip`` is
        compared with the clean run on it (None: the base bag).
    """

    bag: Path
    prior: Path
    reference: Path | None = None


@dataclass
class Variant:
    """One fault: how to build it and what each command must do with it."""

    name: str
    category: str
    description: str
    build: Callable[[BaseRun, Path, np.random.Generator], Built]
    expect: tuple[Expect, ...]
    reduced: bool = False  # part of the default-suite set (test/test_faults.py)

    def make(self, base: BaseRun, directory: str | Path) -> Built:
        """Build the variant's files in ``directory`` (seeded by the base seed and the name)."""
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        rng = np.random.default_rng([base.seed, zlib.crc32(self.name.encode())])
        return self.build(base, d, rng)


def make_base(directory: str | Path, scenario: str = "psce_rotations", duration: float = 300.0,
              seed: int = 1) -> BaseRun:
    """Simulate and write the clean run (``clean.mcap`` + prior + truth) into ``directory``."""
    from stellar_cal_ros.sim.scenarios import get_scenario
    from stellar_cal_ros.sim.world import simulate, write_simulation

    d = Path(directory)
    sim = simulate(get_scenario(scenario), duration=duration, seed=seed)
    paths = write_simulation(sim, d / "clean.mcap")
    return BaseRun(d, paths["bag"], paths["prior"], paths["truth"],
                   Recording.from_simulation(sim), seed)


# ---------------------------------------------------------------------------- builders
def _bag_from(fn: Callable[[Recording, np.random.Generator],
                            Recording | tuple[Recording, Recording]]):
    """A builder that modifies the decoded recording and writes it with the project writer.

    ``fn`` returns the damaged recording, or (damaged, reference) when the damage takes
    data away (the reference holds the same clean data the damaged one keeps).
    """

    def build(base: BaseRun, d: Path, rng: np.random.Generator) -> Built:
        out = fn(base.recording.copy(), rng)
        rec, ref = out if isinstance(out, tuple) else (out, None)
        return Built(rec.write(d / "variant.mcap"), base.prior,
                     ref.write(d / "reference.mcap") if ref is not None else None)

    return build


def _raw_from(fn: Callable[[list[RawMessage], np.random.Generator], list[RawMessage]]):
    """A builder that rewrites the clean bag's raw messages with the ``mcap`` writer."""

    def build(base: BaseRun, d: Path, rng: np.random.Generator) -> Built:
        msgs = fn(read_raw(base.bag), rng)
        return Built(write_raw(d / "variant.mcap", msgs), base.prior)

    return build


def _bytes_from(fn: Callable[[bytes, BaseRun, np.random.Generator], bytes],
                reference: Callable[[BaseRun, Path], Path | None] | None = None):
    """A builder that damages the clean bag's bytes."""

    def build(base: BaseRun, d: Path, rng: np.random.Generator) -> Built:
        bag = d / "variant.mcap"
        bag.write_bytes(fn(base.bag.read_bytes(), base, rng))
        ref = reference(base, d) if reference is not None else None
        return Built(bag, base.prior, ref)

    return build


def _prior_from(fn: Callable[[dict[str, Any]], Any]):
    """A builder that breaks the prior (YAML dict → dict, or raw text / bytes)."""

    def build(base: BaseRun, d: Path, rng: np.random.Generator) -> Built:
        out = fn(base.prior_dict())
        prior = d / "prior.yaml"
        if isinstance(out, bytes):
            prior.write_bytes(out)
        elif isinstance(out, str):
            prior.write_text(out)
        else:
            prior.write_text(yaml.safe_dump(out, sort_keys=False))
        return Built(base.bag, prior)

    return build


def _reference_without_chunks(select: Callable[[list[tuple[int, int, int, int]], int],
                                               list[tuple[int, int, int, int]]]):
    """Reference bag: the clean recording without the messages of the damaged chunks."""

    def ref(base: BaseRun, d: Path) -> Path:
        spans = select(chunk_spans(base.bag), base.bag.stat().st_size)
        ranges = [(s, e) for _, _, s, e in spans]

        def keep(t: np.ndarray) -> np.ndarray:
            m = np.ones(len(t), dtype=bool)
            for s, e in ranges:
                m &= ~((t >= s) & (t <= e))
            return m

        return base.recording.keep_time(keep).write(d / "reference.mcap")

    return ref


def _chunks_after(cut: int):
    return lambda spans, size: [c for c in spans if c[0] + c[1] > cut]


def _middle_chunk(spans, size):
    return [spans[len(spans) // 2]] if spans else []


# ---------------------------------------------------------------------------- IMU faults
def _imu_values(rec: Recording, fraction: float, rng: np.random.Generator, value: float,
                count: int | None = None) -> Recording:
    imu = rec.imu
    n = len(imu)
    k = count if count is not None else max(1, int(round(fraction * n)))
    idx = rng.choice(np.arange(n // 10, n - n // 10), size=k, replace=False)
    w = np.array(imu.angular_velocity, dtype=float)
    w[idx, rng.integers(0, 3, size=k)] = value
    rec.imu = replace(imu, angular_velocity=w)
    return rec


def _imu_drop(rec: Recording, fraction: float, rng: np.random.Generator) -> Recording:
    n = len(rec.imu)
    m = np.ones(n, dtype=bool)
    m[rng.choice(np.arange(n // 10, n - n // 10), size=int(round(fraction * n)),
                 replace=False)] = False
    rec.imu = _imu_subset(rec.imu, m)
    return rec


def _imu_gap(rec: Recording, start_frac: float, seconds: float,
             reference: bool = False) -> Recording | tuple[Recording, Recording]:
    """IMU silent for ``seconds``; the reference: all IMU, no star frames in the gap."""
    t = np.asarray(rec.imu.stamp_ns)
    t0 = t[0] + int(start_frac * (t[-1] - t[0]))
    t1 = t0 + int(seconds * 1e9)
    ref = rec.copy() if reference else None
    rec.imu = _imu_subset(rec.imu, ~((t > t0) & (t <= t1)))
    if ref is None:
        return rec
    ref.stars = [f for f in ref.stars if not t0 < f.stamp_ns <= t1]
    return rec, ref


def _imu_scale(rec: Recording, matrix: np.ndarray) -> Recording:
    w = np.asarray(rec.imu.angular_velocity, dtype=float) @ np.asarray(matrix).T
    rec.imu = replace(rec.imu, angular_velocity=w)
    return rec


# ---------------------------------------------------------------------------- star faults
def _pick_stars(rec: Recording, fraction: float, rng: np.random.Generator,
                min_stars: int = 1) -> list[tuple[int, int]]:
    """``fraction`` of all stars, as (frame, star) pairs, away from the first frames."""
    pairs = [(i, j) for i, f in enumerate(rec.stars) if i >= 5 and len(f) >= min_stars
             for j in range(len(f))]
    k = max(1, int(round(fraction * len(pairs))))
    sel = rng.choice(len(pairs), size=k, replace=False)
    return [pairs[s] for s in sel]


def _set_star_field(rec: Recording, fraction: float, rng: np.random.Generator, name: str,
                    value: Any) -> Recording:
    for i, j in _pick_stars(rec, fraction, rng):
        f = rec.stars[i]
        arr = np.array(getattr(f, name), dtype=float)
        arr[j] = value
        setattr(f, name, arr)
    return rec


def _swap_identities(rec: Recording, fraction: float, rng: np.random.Generator) -> Recording:
    """Label stars as another star of the same frame (the identification mixed two up)."""
    for i, j in _pick_stars(rec, fraction, rng, min_stars=2):
        f = rec.stars[i]
        other = int(rng.choice([k for k in range(len(f)) if k != j]))
        f.catalog_id = np.array(f.catalog_id, copy=True)
        f.right_ascension = np.array(f.right_ascension, dtype=float)
        f.declination = np.array(f.declination, dtype=float)
        f.magnitude = np.array(f.magnitude, dtype=float)
        for name in ("catalog_id", "right_ascension", "declination", "magnitude"):
            getattr(f, name)[j] = getattr(f, name)[other]
    return rec


def _random_identities(rec: Recording, fraction: float, rng: np.random.Generator) -> Recording:
    """Label stars as a random catalogue star anywhere on the sky."""
    for i, j in _pick_stars(rec, fraction, rng):
        f = rec.stars[i]
        z = rng.uniform(-1.0, 1.0)
        f.catalog_id = np.array(f.catalog_id, copy=True)
        f.right_ascension = np.array(f.right_ascension, dtype=float)
        f.declination = np.array(f.declination, dtype=float)
        f.catalog_id[j] = int(rng.integers(1, 118_219))
        f.right_ascension[j] = rng.uniform(0.0, 2.0 * np.pi)
        f.declination[j] = math.asin(z)
    return rec


def _out_of_image(rec: Recording, fraction: float, rng: np.random.Generator) -> Recording:
    for i, j in _pick_stars(rec, fraction, rng):
        f = rec.stars[i]
        f.uv = np.array(f.uv, dtype=float)
        f.uv[j] = rng.choice([[-800.0, 300.0], [5000.0, 5000.0], [1e7, -1e7]])
    return rec


def _empty_frames(rec: Recording, fraction: float,
                  rng: np.random.Generator) -> tuple[Recording, Recording]:
    """Star frames with no stars; the reference: the clean run without those frames."""
    n = len(rec.stars)
    idx = set(rng.choice(np.arange(5, n), size=max(1, int(round(fraction * n))),
                         replace=False).tolist())
    ref = rec.copy()
    ref.stars = [f for i, f in enumerate(ref.stars) if i not in idx]
    for i in idx:
        rec.stars[i] = _frame_subset(rec.stars[i], np.zeros(len(rec.stars[i]), dtype=bool))
    return rec, ref


def _frame_subset(f: StarFrame, m: np.ndarray) -> StarFrame:
    return replace(f, catalog_id=np.asarray(f.catalog_id)[m],
                   right_ascension=np.asarray(f.right_ascension)[m],
                   declination=np.asarray(f.declination)[m], uv=np.asarray(f.uv)[m],
                   magnitude=np.asarray(f.magnitude)[m], sigma=np.asarray(f.sigma)[m],
                   log_time_ns=None)


def _huge_frame(rec: Recording, rng: np.random.Generator) -> Recording:
    """One frame with 20 000 stars of garbage (an absurd message size)."""
    i = len(rec.stars) // 2
    f = rec.stars[i]
    n = 20_000
    rec.stars[i] = replace(f, catalog_id=rng.integers(1, 118_219, n).astype(np.uint32),
                           right_ascension=rng.uniform(0, 2 * np.pi, n),
                           declination=rng.uniform(-1.5, 1.5, n),
                           uv=rng.uniform(-1e4, 1e4, (n, 2)), magnitude=np.full(n, 5.0),
                           sigma=np.full(n, 0.05), log_time_ns=None)
    return rec


# ---------------------------------------------------------------------------- stream faults
def _duplicate(topic: str, fraction: float):
    def fn(msgs: list[RawMessage], rng: np.random.Generator) -> list[RawMessage]:
        idx = [k for k, m in enumerate(msgs) if m.topic == topic]
        dup = set(rng.choice(idx[5:], size=max(1, int(round(fraction * len(idx)))),
                             replace=False).tolist())
        out = []
        for k, m in enumerate(msgs):
            out.append(m)
            if k in dup:
                out.append(replace(m, log_time_ns=m.log_time_ns + 1000))
        return out

    return fn


def _late(topic: str, fraction: float):
    """Messages delivered after their successor (log time after the next one's)."""

    def fn(msgs: list[RawMessage], rng: np.random.Generator) -> list[RawMessage]:
        idx = [k for k, m in enumerate(msgs) if m.topic == topic]
        pos = rng.choice(np.arange(5, len(idx) - 1), size=max(1, int(round(
            fraction * len(idx)))), replace=False)
        msgs = list(msgs)
        for p in sorted(pos.tolist()):
            a, b = idx[p], idx[p + 1]
            msgs[a] = replace(msgs[a], log_time_ns=msgs[b].log_time_ns + 1)
        msgs.sort(key=lambda m: m.log_time_ns)
        return msgs

    return fn


def _clock_jump(topics: tuple[str, ...] | None, seconds: float, from_frac: float):
    """Header stamps of ``topics`` (None: all) jump by ``seconds`` from a point on.

    Log times stay as recorded (the recorder's clock did not jump).
    """

    def fn(msgs: list[RawMessage], rng: np.random.Generator) -> list[RawMessage]:
        t = [m.log_time_ns for m in msgs]
        at = min(t) + int(from_frac * (max(t) - min(t)))
        out = []
        for m in msgs:
            if (topics is None or m.topic in topics) and m.log_time_ns >= at:
                m = replace(m, data=with_header_stamp(
                    m.data, header_stamp_ns(m.data) + int(seconds * 1e9)))
            out.append(m)
        return out

    return fn


def _drop_topic(topic: str):
    def fn(rec: Recording, rng: np.random.Generator) -> Recording:
        if topic == TOPIC_IMU:
            rec.imu = None
        elif topic == TOPIC_STARS:
            rec.stars = None
        elif topic == TOPIC_FIX:
            rec.navsat = None
        return rec

    return fn


# ---------------------------------------------------------------------------- priors
def _without(*keys: str):
    def fn(d: dict[str, Any]) -> dict[str, Any]:
        node = d
        for k in keys[:-1]:
            node = node[k]
        node.pop(keys[-1], None)
        return d

    return fn


def _set(keys: tuple[str, ...], value: Any):
    def fn(d: dict[str, Any]) -> dict[str, Any]:
        node = d
        for k in keys[:-1]:
            node = node[k]
        node[keys[-1]] = value(node[keys[-1]]) if callable(value) else value
        return d

    return fn


def _nan_first(v: list[float]) -> list[float]:
    return [float("nan")] + list(v[1:])


# ---------------------------------------------------------------------------- the catalogue
_BAG_DAMAGE = r"truncat|corrupt|damag|crc|unreadable|not an mcap|incomplete|invalid"
_UNITS = r"deg/s|degree|unit|rad/s"
_CLOCK = r"clock|stamp|time|jump|offset|gap|overlap"
_GYRO = r"gyro|axes|axis|rotation|imu"


def _expects(spec: str, cause: str) -> tuple[Expect, ...]:
    """``"replay=error batch=skip|flagged"`` → one :class:`Expect` per command."""
    out = []
    for item in spec.split():
        command, _, outcomes = item.partition("=")
        out.append(expect(command, outcomes, cause))
    return tuple(out)


def _truncated(fraction: float):
    return _bytes_from(lambda b, base, r: truncate(b, fraction),
                       lambda base, d: _reference_without_chunks(_chunks_after(
                           int(base.bag.stat().st_size * fraction)))(base, d))


def _in_middle_chunk(damage: Callable[[bytes, int], bytes]):
    def fn(b: bytes, base: BaseRun, r: np.random.Generator) -> bytes:
        return damage(b, _middle_chunk(chunk_spans(base.bag), 0)[0][0])

    return _bytes_from(fn, _reference_without_chunks(_middle_chunk))


def _zeroed_middle(b: bytes, base: BaseRun, r: np.random.Generator) -> bytes:
    return zero_range(b, len(b) // 2, 65536)


def _zeroed_chunks(spans: list[tuple[int, int, int, int]], size: int):
    return [c for c in spans if c[0] < size // 2 + 65536 and c[0] + c[1] > size // 2]


def _missing(base: BaseRun, d: Path, rng: np.random.Generator) -> Built:
    return Built(d / "no_such_bag.mcap", base.prior)


def _all_stars_empty(rec: Recording, rng: np.random.Generator) -> Recording:
    rec.stars = [_frame_subset(f, np.zeros(len(f), dtype=bool)) for f in rec.stars]
    return rec


_SWAP_XY = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
_DAMAGED_BAG = "info=error|flagged replay=error replay_skip=skip"
_ALL_ERROR = "replay=error batch=error diagnose=error info=error"
_SKIP_RB = "replay=skip batch=skip"
_PRIORS = [  # name, description, change, cause
    ("prior_no_camera", "camera block missing", _without("camera"), r"camera"),
    ("prior_no_installation", "installation block missing", _without("installation"),
     r"installation"),
    ("prior_k_wrong_shape", "camera_matrix with 8 values",
     _set(("camera", "camera_matrix", "data"), lambda x: x[:8]), r"camera_matrix|9|camera"),
    ("prior_nan_focal", "fx NaN", _set(("camera", "camera_matrix", "data"), _nan_first),
     r"finite|nan|focal|camera"),
    ("prior_zero_quaternion", "installation quaternion all zero",
     _set(("installation", "quaternion_xyzw"), [0.0, 0.0, 0.0, 0.0]), r"quaternion"),
    ("prior_bad_distortion_model", "unknown distortion model",
     _set(("camera", "distortion_model"), "fisheye9"), r"distortion"),
    ("prior_sigma_wrong_shape", "installation sigma with 2 values",
     _set(("sigma", "installation", "rotation_vector"), [0.001, 0.001]),
     r"sigma|rotation_vector"),
    ("prior_sigma_negative", "negative focal-length sigma",
     _set(("sigma", "camera", "camera_matrix", "data"), lambda x: [-abs(x[0])] + x[1:]),
     r"sigma|negative|positive"),
    ("prior_not_yaml", "binary garbage", lambda d: bytes(range(256)) * 4,
     r"yaml|mapping|format|decode|utf"),
    ("prior_empty", "an empty file", lambda d: "", r"empty"),
]


def catalogue() -> list[Variant]:
    """Every variant of the campaign (``reduced=True``: the default-suite set).

    Each row: name, category, description, builder, expected outcome per command
    (``command=class|class``), the pattern an error must match, and whether the variant is
    in the reduced set.
    """
    rows: list[tuple[str, str, str, Any, str, str, bool]] = [
        # -- container / bytes
        ("truncated_half", "bytes", "file cut at 50 % (power loss while recording)",
         _truncated(0.5), _DAMAGED_BAG + " batch=error diagnose=error", _BAG_DAMAGE, True),
        ("truncated_tail", "bytes", "last 1 % of the file missing (summary lost)",
         _truncated(0.99), _DAMAGED_BAG, _BAG_DAMAGE, False),
        ("truncated_header", "bytes", "only the first 20 bytes",
         _bytes_from(lambda b, base, r: b[:20]), _ALL_ERROR, _BAG_DAMAGE, False),
        ("zeroed_middle", "bytes", "64 KiB zeroed in the middle of the file",
         _bytes_from(_zeroed_middle, _reference_without_chunks(_zeroed_chunks)),
         _DAMAGED_BAG + " batch=error", _BAG_DAMAGE, True),
        ("bad_chunk_crc", "bytes", "the middle chunk's stored CRC altered",
         _in_middle_chunk(bad_chunk_crc), _DAMAGED_BAG + " batch=error", _BAG_DAMAGE, False),
        ("flipped_bytes_chunk", "bytes", "16 bytes flipped inside the middle chunk",
         _in_middle_chunk(lambda b, at: flip_bytes(b, range(at + 200, at + 216))),
         _DAMAGED_BAG + " batch=error", _BAG_DAMAGE, False),
        ("not_mcap", "bytes", "a text file named .mcap",
         _bytes_from(lambda b, base, r: b"this is not a bag\n" * 100), _ALL_ERROR,
         r"not an mcap|magic", True),
        ("empty_file", "bytes", "a 0-byte file", _bytes_from(lambda b, base, r: b""),
         _ALL_ERROR, r"not an mcap|empty|magic", False),
        ("missing_file", "bytes", "the bag does not exist", _missing, _ALL_ERROR,
         r"not found|no such|does not exist", False),
        # -- IMU values and timing
        ("imu_nan_one", "imu", "one NaN gyro sample mid-run",
         _bag_from(lambda rec, r: _imu_values(rec, 0, r, np.nan, count=1)),
         "replay=skip|flagged batch=skip|flagged diagnose=skip|flagged", "", True),
        ("imu_inf_one", "imu", "one inf gyro sample mid-run",
         _bag_from(lambda rec, r: _imu_values(rec, 0, r, np.inf, count=1)),
         "replay=skip|flagged batch=skip|flagged", "", False),
        ("imu_nan_1pct", "imu", "1 % of gyro samples NaN",
         _bag_from(lambda rec, r: _imu_values(rec, 0.01, r, np.nan)),
         "replay=skip|flagged batch=skip|flagged diagnose=skip|flagged", "", False),
        ("imu_missing_1pct", "imu", "1 % of IMU messages lost",
         _bag_from(lambda rec, r: _imu_drop(rec, 0.01, r)),
         "replay=skip|flagged batch=skip|flagged diagnose=skip|flagged", "", False),
        ("imu_gap_short", "imu", "IMU silent for 0.3 s mid-run",
         _bag_from(lambda rec, r: _imu_gap(rec, 0.5, 0.3)),
         "replay=skip|flagged batch=skip|flagged|error", r"gap", False),
        ("imu_gap_60s", "imu", "IMU silent for 60 s mid-run (stars go on)",
         _bag_from(lambda rec, r: _imu_gap(rec, 0.5, 60.0, reference=True)),
         "replay=skip|flagged batch=error diagnose=skip|flagged|error", r"gap", True),
        ("imu_deg_s", "units", "gyro recorded in deg/s",
         _bag_from(lambda rec, r: _imu_scale(rec, np.eye(3) * 180.0 / np.pi)),
         "replay=error batch=error diagnose=error", _UNITS, True),
        ("imu_axes_swapped", "units", "gyro x and y axes swapped (a mirror)",
         _bag_from(lambda rec, r: _imu_scale(rec, _SWAP_XY)),
         "replay=error|flagged batch=error|flagged", _GYRO, False),
        ("imu_dead", "units", "gyro reports zeros while the tracker turns",
         _bag_from(lambda rec, r: _imu_scale(rec, np.zeros((3, 3)))),
         "replay=error|flagged batch=error|flagged", _GYRO, False),
        ("imu_dead_axis", "units", "gyro z axis reports zeros (the others are good)",
         _bag_from(lambda rec, r: _imu_scale(rec, np.diag([1.0, 1.0, 0.0]))),
         "replay=error|flagged batch=error|flagged", _GYRO, True),
        ("imu_duplicates", "stream", "1 % of IMU messages recorded twice",
         _raw_from(_duplicate(TOPIC_IMU, 0.01)), _SKIP_RB, "", False),
        ("imu_late", "stream", "1 % of IMU messages logged after their successor",
         _raw_from(_late(TOPIC_IMU, 0.01)), "replay=skip|ok batch=skip|ok", "", False),
        # -- star values
        ("stars_nan_uv", "stars", "1 % of centroids NaN",
         _bag_from(lambda rec, r: _set_star_field(rec, 0.01, r, "uv", np.nan)), _SKIP_RB,
         "", False),
        ("stars_inf_radec", "stars", "1 % of catalogue directions inf",
         _bag_from(lambda rec, r: _set_star_field(rec, 0.01, r, "declination", np.inf)),
         _SKIP_RB, "", False),
        ("stars_out_of_image", "stars", "1 % of centroids far outside the image",
         _bag_from(lambda rec, r: _out_of_image(rec, 0.01, r)), _SKIP_RB, "", True),
        ("stars_sigma_negative", "stars", "1 % of star sigmas -0.05 px",
         _bag_from(lambda rec, r: _set_star_field(rec, 0.01, r, "sigma", -0.05)), _SKIP_RB,
         "", False),
        ("stars_sigma_nan", "stars", "1 % of star sigmas NaN",
         _bag_from(lambda rec, r: _set_star_field(rec, 0.01, r, "sigma", np.nan)), _SKIP_RB,
         "", False),
        *[(f"misid_swap_{p}pct", "stars",
           f"{p} % of stars labelled as another star of the same frame",
           _bag_from(lambda rec, r, p=p: _swap_identities(rec, p / 100.0, r)),
           _SKIP_RB + " diagnose=skip|flagged", "", p == 2) for p in (1, 2, 5)],
        ("misid_swap_15pct", "stars", "15 % of stars labelled as another star of the frame",
         _bag_from(lambda rec, r: _swap_identities(rec, 0.15, r)),
         "replay=skip|flagged batch=flagged", "", True),
        *[(f"misid_random_{p}pct", "stars",
           f"{p} % of stars labelled as a random catalogue star",
           _bag_from(lambda rec, r, p=p: _random_identities(rec, p / 100.0, r)), _SKIP_RB,
           "", False) for p in (1, 5)],
        ("stars_empty_10pct", "stars", "10 % of star frames empty",
         _bag_from(lambda rec, r: _empty_frames(rec, 0.1, r)), "replay=skip|ok batch=skip|ok",
         "", False),
        ("stars_all_empty", "stars", "every star frame empty", _bag_from(_all_stars_empty),
         "replay=error batch=error diagnose=error", r"star", False),
        ("stars_huge_frame", "stars", "one frame of 20 000 garbage stars",
         _bag_from(lambda rec, r: _huge_frame(rec, r)), _SKIP_RB, "", False),
        ("stars_duplicates", "stream", "1 % of star frames recorded twice",
         _raw_from(_duplicate(TOPIC_STARS, 0.01)), _SKIP_RB, "", False),
        ("stars_late", "stream", "2 % of star frames logged after their successor",
         _raw_from(_late(TOPIC_STARS, 0.02)), "replay=skip|ok batch=skip|ok", "", False),
        # -- clocks
        ("clock_stars_+1h", "time", "star tracker clock 1 h ahead of the IMU's",
         _raw_from(_clock_jump((TOPIC_STARS,), 3600.0, 0.0)),
         "replay=error batch=error diagnose=error", _CLOCK, True),
        *[(f"clock_imu_{sign}1h", "time", f"IMU clock {sign}1 h off the star tracker's",
           _raw_from(_clock_jump((TOPIC_IMU,), float(f"{sign}3600"), 0.0)),
           "replay=error batch=error diagnose=error", _CLOCK, False) for sign in "+-"],
        ("clock_imu_jump_-1h", "time", "IMU clock jumps back 1 h mid-run",
         _raw_from(_clock_jump((TOPIC_IMU,), -3600.0, 0.5)), "replay=error batch=error",
         _CLOCK, False),
        ("clock_imu_jump_+1h", "time", "IMU clock jumps 1 h ahead mid-run",
         _raw_from(_clock_jump((TOPIC_IMU,), 3600.0, 0.5)),
         "replay=error|flagged batch=error", _CLOCK, False),
        ("clock_all_jump_+1h", "time", "every clock jumps 1 h ahead mid-run",
         _raw_from(_clock_jump(None, 3600.0, 0.5)), "replay=skip|flagged|error batch=error",
         _CLOCK, False),
        # -- topics
        ("missing_imu_topic", "topics", "no /imu/data", _bag_from(_drop_topic(TOPIC_IMU)),
         "replay=error batch=error diagnose=error", r"/imu/data", True),
        ("missing_star_topic", "topics", "no /star_tracker/stars",
         _bag_from(_drop_topic(TOPIC_STARS)), "replay=error batch=error diagnose=error",
         r"/star_tracker/stars", False),
        ("missing_gnss_topic", "topics", "no /gnss/fix (not needed by the baseline)",
         _bag_from(_drop_topic(TOPIC_FIX)), "replay=ok|skip batch=ok|skip", "", False),
        # -- priors
        # a negative σ is warned about (its magnitude or the default is used), not refused
        *[(name, "prior", text, _prior_from(fn),
           "replay=error|skip batch=error|skip" if name == "prior_sigma_negative"
           else "replay=error batch=error", cause, name in ("prior_no_camera", "prior_nan_focal"))
          for name, text, fn, cause in _PRIORS],
        ("prior_no_sigma", "prior", "no sigma block", _prior_from(_without("sigma")),
         "replay=error|skip|flagged batch=error|skip|flagged", r"sigma", False),
    ]
    out = [Variant(name, cat, text, build, _expects(spec, cause), reduced)
           for name, cat, text, build, spec, cause, reduced in rows]
    names = [x.name for x in out]
    assert len(names) == len(set(names)), "variant names must be unique"
    return out
