"""Run the CLI on the fault variants of :mod:`stellar_cal_ros.sim.faults` and judge each run.

Every command runs in a subprocess (``python -m stellar_cal_ros ...``) with a timeout, so a
crash, a hang or a signal of one run cannot take the campaign down.  :func:`classify` puts
the run into its outcome class — ``error`` (non-zero exit, one line), ``skip`` (exit 0, the
damage counted), ``flagged`` (the result says it is degraded), ``ok`` (nothing counted) —
or ``crash`` (a traceback, a signal) or ``hang`` (timeout), and gives the verdict against
the variant's expectation:

``pass``       the outcome is one the variant allows (and an error names the cause);
``CRASH``      a traceback or a signal;
``HANG``       no exit within the timeout;
``SILENT``     exit 0, no flag, and the key number beyond :func:`key_limit` (``diagnose``:
               another recommendation than the clean run's; ``info``: a damaged bag
               reported as healthy);
``LOST``       a counted skip that used fewer star frames than the clean run on the data
               the variant keeps (e.g. good chunks after a damaged one dropped);
``UNCLEAR``    an error that is not the CLI's one line or does not name the cause;
``UNCOUNTED``  exit 0 with a good result but the damage not counted anywhere;
``DIFFERS``    a safe outcome, but not the one expected (e.g. an error where a counted skip
               was wanted).

The key number is the equivalent principal point error against the truth (px; see
:func:`key_numbers`); the clean run it is compared with is the same command on the variant's
reference bag (the clean data the variant keeps), with the same prior.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from stellar_cal_ros.sim.faults import KEY_TOLERANCE, BaseRun, Expect, Variant

COMMANDS: dict[str, list[str]] = {
    "replay": ["replay", "{bag}", "--method", "psce", "--prior", "{prior}", "-o", "{out}",
               "-q"],
    "replay_skip": ["replay", "{bag}", "--method", "psce", "--prior", "{prior}", "-o",
                    "{out}", "-q", "--on-error", "skip"],
    "batch": ["batch", "{bag}", "--method", "acf", "--prior", "{prior}", "-o", "{out}"],
    # in this process: a fault bag's round is a few short runs (a local cluster would add
    # ~15 CPU-s per command), and a campaign judging an older checkout runs it alike
    "diagnose": ["diagnose", "{bag}", "--method", "psce", "--calibration", "{prior}", "-o",
                 "{out_dir}", "--no-plots", "--workers", "0"],
    "info": ["info", "{bag}"],
}
"""``python -m stellar_cal_ros`` arguments of each command (``{...}`` filled per run)."""

_PACKAGE_ROOT = Path(__file__).resolve().parents[2]


def command_args(command: str, bag: Path, prior: Path, out: Path) -> list[str]:
    """The CLI arguments of ``command`` on these files (``out``: result YAML path)."""
    fill = {"bag": str(bag), "prior": str(prior), "out": str(out),
            "out_dir": str(out.with_suffix(""))}
    return [a.format(**fill) for a in COMMANDS[command]]


# ============================================================================ measuring
def key_numbers(result: str | Path, truth: str | Path, prior: str | Path) -> dict[str, float]:
    """Errors of a result YAML against the truth.

    Returns
    -------
    dict
        ``eqpp_px``: norm of the equivalent principal point error (boresight of the prior's
        nominal mounting), px; ``installation_arcsec``: norm of the installation rotation
        error, arcsec.
    """
    from stellar_cal_ros.core.rotation import so3_log
    from stellar_cal_ros.io.calibration import load_calibration
    from stellar_cal_ros.methods.results import boresight_pixel

    est, tru, pri = load_calibration(result), load_calibration(truth), load_calibration(prior)
    b = pri.R_imu_st[:, 2]
    e = boresight_pixel(est.camera, est.R_imu_st, b) - boresight_pixel(tru.camera,
                                                                       tru.R_imu_st, b)
    inst = so3_log(tru.R_imu_st.T @ est.R_imu_st) * (180.0 / np.pi * 3600.0)
    return {"eqpp_px": float(np.linalg.norm(e)),
            "installation_arcsec": float(np.linalg.norm(inst))}


def result_flag(result: str | Path | None, text: str) -> str:
    """Why a result says it is degraded ('' if it does not).

    Looked for: ``data_quality.degraded: true`` (with its ``reasons``) or a
    ``consistency.verdict`` other than ``consistent`` in the YAML; a printed line with
    "degraded" or "data quality first".
    """
    if result is not None and Path(result).is_file():
        try:
            d = yaml.safe_load(Path(result).read_text()) or {}
        except yaml.YAMLError:
            d = {}
        dq = d.get("data_quality") if isinstance(d, dict) else None
        if isinstance(dq, dict) and dq.get("degraded"):
            return "data_quality: " + "; ".join(map(str, dq.get("reasons") or ["degraded"]))
        cons = d.get("consistency") if isinstance(d, dict) else None
        if isinstance(cons, dict) and cons.get("verdict") not in (None, "consistent", "ok"):
            return f"consistency: {cons.get('verdict')}"
    for line in text.splitlines():
        if re.search(r"degraded|data quality first", line, re.IGNORECASE):
            return line.strip()
    return ""


_TRACEBACK = re.compile(r"^Traceback \(most recent call last\)", re.MULTILINE)
_COUNTS = re.compile(r"^counts: (.*)$", re.MULTILINE)
_GATED = re.compile(r"\((\d+) gated\)|(\d+) outliers?", re.IGNORECASE)


# a logging warning, a raw Python warning, or the CLI's one-line "stellar-cal CMD: warning: ..."
_WARNING = re.compile(r"^WARNING [\w.]+: (.*)$|UserWarning: (.*)$"
                      r"|^(?:stellar-cal [\w-]+: )?warning: (.*)$", re.MULTILINE | re.IGNORECASE)
_EQPP_SIGMA = re.compile(r"equivalent principal point: .*\+-? ?\(([-+\d.eE]+), ([-+\d.eE]+)\)")
_USED = re.compile(r"updates=(\d+)|^acf: (\d+) frames", re.MULTILINE)


def _normalized(text: str) -> str:
    text = re.sub(r"(/[^\s:;,()]+)+", "PATH", text)
    return re.sub(r"[-+]?\d+(\.\d+)?(e[-+]?\d+)?", "#", text).strip()


def counted_marks(stdout: str, stderr: str) -> set[str]:
    """What a printout counts: warning texts, nonzero ``counts:`` keys, gated/outlier counts."""
    marks = {"warning:" + _normalized(next(g for g in m.groups() if g))
             for m in _WARNING.finditer(stderr)}
    for m in _COUNTS.finditer(stdout):
        for item in m.group(1).split(","):
            k, _, val = item.strip().partition("=")
            if k and val.strip() not in ("", "0"):
                marks.add("count:" + k)
    for m in _GATED.finditer(stdout):
        n = int(m.group(1) or m.group(2) or 0)
        if n:
            marks.add(f"gated:{n}")
    return marks


def expected_error(stdout: str) -> float | None:
    """RMS error a run expects of its key number (None if it prints no σ).

    ``hypot(σ_u, σ_v)`` of its printed equivalent principal point.
    """
    m = _EQPP_SIGMA.search(stdout)
    return float(np.hypot(float(m.group(1)), float(m.group(2)))) if m else None


def frames_used(stdout: str) -> int | None:
    """Star frames a run used: ``updates=`` of ``replay``, ``acf: N frames`` of ``batch``."""
    m = _USED.search(stdout)
    return int(m.group(1) or m.group(2)) if m else None


# ============================================================================ judging
@dataclass
class Observation:
    """What one command did with one variant (:func:`classify`)."""

    outcome: str  # error | skip | flagged | ok | crash | hang
    verdict: str  # pass | CRASH | HANG | SILENT | UNCLEAR | UNCOUNTED | DIFFERS
    message: str  # the error line, the flag, or what was counted
    key: float | None = None  # key number of the run
    limit: float | None = None  # the largest a counted skip may give (key_limit)


def error_line(stderr: str) -> str:
    """The CLI's one-line error (``stellar-cal CMD: error: ...``), or the last line."""
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    for ln in lines:
        if ": error:" in ln:
            return ln.strip()
    return lines[-1].strip() if lines else ""


def key_limit(reference: float | None, reference_rms: float | None) -> float | None:
    """Largest key number a counted skip may give.

    :data:`~stellar_cal_ros.sim.faults.KEY_TOLERANCE` × the clean run's error, or × the RMS
    error the clean run expects of itself (its σ) if that is larger: one run's error below
    its own σ is luck, and a fault cannot be judged against luck.
    """
    if reference is None:
        return None
    return KEY_TOLERANCE * max(reference, reference_rms or 0.0)


def classify(exp: Expect, returncode: int | None, stdout: str, stderr: str, *,
             flag: str = "", key: float | None = None, limit: float | None = None,
             clean_marks: set[str] | None = None, used: int | None = None,
             reference_used: int | None = None, recommendation: str | None = None,
             clean_recommendation: str | None = None) -> Observation:
    """Judge one run against its expectation.

    Parameters
    ----------
    exp : Expect
        What the command must do.
    returncode : int or None
        Exit status; None: the run timed out (hang).
    stdout : str
        Its standard output.
    stderr : str
        Its standard error.
    flag : str
        :func:`result_flag` of the run.
    key, limit : float, optional
        Key number of this run and the largest one a counted skip may give
        (:func:`key_limit`).
    clean_marks : set of str
        :func:`counted_marks` of the clean run (what it counts anyway).
    used, reference_used : int, optional
        :func:`frames_used` of this run and of the clean run on the reference data: a run
        that uses fewer than 95 % of them has lost data the damage did not take (``LOST``).
    recommendation, clean_recommendation : str, optional
        ``diagnose``: the recommended effect of this run and of the clean run.
    """
    if returncode is None:
        return Observation("hang", "HANG", "timed out", key, limit)
    if returncode < 0 or _TRACEBACK.search(stderr) or _TRACEBACK.search(stdout):
        tb = [ln for ln in stderr.splitlines() if ln.strip()]
        return Observation("crash", "CRASH", tb[-1].strip() if tb else f"signal {-returncode}",
                           key, limit)
    if returncode != 0:
        line = error_line(stderr)
        body = line.split(": error:", 1)[-1]
        if "error" not in exp.outcomes:
            return Observation("error", "DIFFERS", line, key, limit)
        ok = ": error:" in line and (not exp.cause or re.search(exp.cause, body, re.IGNORECASE))
        return Observation("error", "pass" if ok else "UNCLEAR", line, key, limit)
    if flag:
        return Observation("flagged", "pass" if "flagged" in exp.outcomes else "DIFFERS", flag,
                           key, limit)
    marks = counted_marks(stdout, stderr) - (clean_marks or set())
    outcome = "skip" if marks else "ok"
    wrong = key is not None and limit is not None and key > limit
    note = ", ".join(sorted(marks)) or "nothing counted"
    if exp.command == "diagnose":
        wrong = wrong or recommendation != clean_recommendation
        note = f"recommends {recommendation or 'nothing'}; " + note
    if exp.command == "info" and not set(exp.outcomes) & {"ok", "skip"}:
        wrong = True  # a damaged bag reported as healthy
    if wrong:
        return Observation(outcome, "SILENT", note, key, limit)
    if used is not None and reference_used and used < 0.95 * reference_used:
        return Observation(outcome, "LOST", f"{used} of {reference_used} frames used; " + note,
                           key, limit)
    if outcome in exp.outcomes:
        return Observation(outcome, "pass", note, key, limit)
    if outcome == "ok" and "skip" in exp.outcomes:
        return Observation(outcome, "UNCOUNTED", note, key, limit)
    return Observation(outcome, "DIFFERS", note, key, limit)


# ============================================================================ running
@dataclass
class Run:
    """One finished (or timed-out) subprocess run of a command."""

    command: str
    argv: list[str]
    returncode: int | None
    stdout: str
    stderr: str
    seconds: float
    out: Path
    key: float | None = None
    installation: float | None = None
    flag: str = ""
    recommendation: str | None = None


def run_command(command: str, bag: Path, prior: Path, out: Path, truth: Path | None,
                timeout: float, code: Path | None = None) -> Run:
    """Run one CLI command in a subprocess and measure its result.

    The package is imported from ``code`` (a checkout's root; default: the tree this module
    belongs to) through ``cwd`` and ``PYTHONPATH``, so a worktree runs its own code and a
    campaign can judge another version.
    """
    root = Path(code) if code is not None else _PACKAGE_ROOT
    out.parent.mkdir(parents=True, exist_ok=True)
    out.unlink(missing_ok=True)
    argv = command_args(command, bag, prior, out)
    env = dict(os.environ, PYTHONPATH=str(root), PYTHONUNBUFFERED="1")
    t0 = time.perf_counter()
    try:
        p = subprocess.run([sys.executable, "-m", "stellar_cal_ros", *argv], cwd=root,
                           env=env, capture_output=True, text=True, timeout=timeout,
                           errors="replace")
        rc, so, se = p.returncode, p.stdout, p.stderr
    except subprocess.TimeoutExpired as exc:
        rc = None
        so = exc.stdout.decode(errors="replace") if isinstance(exc.stdout, bytes) else \
            (exc.stdout or "")
        se = exc.stderr.decode(errors="replace") if isinstance(exc.stderr, bytes) else \
            (exc.stderr or "")
    run = Run(command, argv, rc, so, se, time.perf_counter() - t0, out)
    if rc == 0 and out.is_file() and truth is not None:
        try:
            k = key_numbers(out, truth, prior)
            run.key, run.installation = k["eqpp_px"], k["installation_arcsec"]
        except Exception as exc:  # noqa: BLE001 - an unreadable result is reported, not fatal
            run.flag = ""
            run.stderr += f"\n(campaign: result not readable: {exc})"
    run.flag = result_flag(out if rc == 0 else None, so + "\n" + se)
    diag = out.with_suffix("") / "diagnosis.json"
    if command == "diagnose" and rc == 0 and diag.is_file():
        run.recommendation = json.loads(diag.read_text()).get("recommendation")
    return run


@dataclass
class Row:
    """One line of the campaign table."""

    variant: str
    category: str
    command: str
    expected: str
    outcome: str
    verdict: str
    key: float | None
    reference: float | None
    limit: float | None
    seconds: float
    message: str


@dataclass
class Campaign:
    """Runs variants against a base run; clean runs are cached per (command, reference bag).

    Parameters
    ----------
    base : BaseRun
        The clean run (:func:`~stellar_cal_ros.sim.faults.make_base`).
    workdir : Path
        Where variants and outputs are written.
    timeout : float
        Seconds per command before it counts as a hang.
    code : Path, optional
        Root of the checkout whose CLI is judged (default: this one).
    """

    base: BaseRun
    workdir: Path
    timeout: float = 300.0
    code: Path | None = None
    _clean: dict[tuple[str, str], Run] = field(default_factory=dict)

    def clean(self, command: str, bag: Path | None = None) -> Run:
        """The command on a clean bag (default: the base bag), cached.

        A reference bag the command refuses (e.g. the ACF on data with a chunk's time span
        cut out: an IMU gap) falls back to the base bag.
        """
        k = (command, str(bag or self.base.bag))
        if k not in self._clean:
            out = self.workdir / "clean" / f"{command}_{len(self._clean)}.yaml"
            run = run_command(command, bag or self.base.bag, self.base.prior, out,
                              self.base.truth, self.timeout, self.code)
            if run.returncode != 0:
                if bag is not None:
                    self._clean[k] = self.clean(command)
                    return self._clean[k]
                raise RuntimeError(f"the clean {command} run failed: {run.stderr[-2000:]}")
            self._clean[k] = run
        return self._clean[k]

    def run(self, variant: Variant, commands: set[str] | None = None) -> list[Row]:
        """Build the variant and run each expected command on it."""
        d = self.workdir / variant.name
        built = variant.make(self.base, d)
        rows = []
        for exp in variant.expect:
            if commands is not None and exp.command not in commands:
                continue
            run = run_command(exp.command, built.bag, built.prior, d / f"{exp.command}.yaml",
                              self.base.truth, self.timeout, self.code)
            ref = self.clean(exp.command, built.reference) \
                if exp.command != "info" and run.returncode == 0 else None
            base_clean = self.clean(exp.command) if exp.command != "info" else None
            obs = classify(
                exp, run.returncode, run.stdout, run.stderr, flag=run.flag, key=run.key,
                limit=key_limit(ref.key, expected_error(ref.stdout)) if ref else None,
                clean_marks=counted_marks(base_clean.stdout, base_clean.stderr)
                if base_clean else set(),
                used=frames_used(run.stdout) if run.returncode == 0 else None,
                reference_used=frames_used(ref.stdout) if ref else None,
                recommendation=run.recommendation,
                clean_recommendation=ref.recommendation if ref else None)
            rows.append(Row(variant.name, variant.category, exp.command,
                            "|".join(exp.outcomes), obs.outcome, obs.verdict, obs.key,
                            ref.key if ref else None, obs.limit, run.seconds,
                            obs.message.replace(str(self.workdir), "<work>")))
        return rows


TABLE_HEADER = (f"{'variant':26s} {'command':11s} {'expected':18s} {'outcome':8s} "
                f"{'key px':>8s} {'clean':>7s} {'limit':>7s} {'s':>5s}  verdict    what")


def format_rows(rows: list[Row]) -> list[str]:
    """One table line per run."""
    lines = []
    def f(x: float | None, w: int, show: bool) -> str:
        return f"{x:{w}.4f}" if show and x is not None else " " * w

    for r in rows:
        num = r.key is not None
        msg = r.message if len(r.message) <= 110 else r.message[:107] + "..."
        lines.append(f"{r.variant:26s} {r.command:11s} {r.expected:18s} {r.outcome:8s} "
                     f"{f(r.key, 8, num)} {f(r.reference, 7, num)} {f(r.limit, 7, num)} "
                     f"{r.seconds:5.1f}  "
                     f"{r.verdict:10s} {msg}")
    return lines


def format_table(rows: list[Row]) -> str:
    """The campaign table (one line per run) and the verdict counts."""
    lines = [TABLE_HEADER, *format_rows(rows)]
    counts: dict[str, int] = {}
    for r in rows:
        counts[r.verdict] = counts.get(r.verdict, 0) + 1
    lines.append("verdicts: " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items())))
    return "\n".join(lines)
