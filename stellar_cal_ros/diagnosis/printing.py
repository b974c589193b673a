"""What ``stellar-cal diagnose`` (and ``--auto``) print: the key lines of a summary.

Each ``*_lines`` function returns the lines; the ``print_*`` functions print them, and the
report (``report.html``) carries the very same lines (issue 21 item 5: what the terminal
shows is what the report holds).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from stellar_cal_ros.diagnosis import leads, reliability, rolling, stats
from stellar_cal_ros.diagnosis.clock import COMPONENT, GYRO_COMPONENT
from stellar_cal_ros.diagnosis.installation_step import COMPONENT as STEP
from stellar_cal_ros.diagnosis.shape_drift import SHAPES
from stellar_cal_ros.diagnosis.slew_steps import COMPONENT as SLEWS


def describe(step: dict[str, Any]) -> str:
    """One path step in words: what the round changed."""
    a = step["action"]
    if a == "add":
        add = step["added"]
        alias = " -- could be a mount flexure, see below" if step.get("could_be_flexure") else ""
        if add.get("at_physical_size") is not None:  # diagnosis.auto._at_size
            alias += (f" -- at {add['at_physical_size']:.3g}x its physical size, beside the "
                      "clock's remainder that makes most of the excess")
        if add.get("with"):  # diagnosis.auto.ADDED_WITH
            alias += (f" with {add['with']} beside it (the offset at its reference stamp, "
                      "not assumed 0)")
        return (f"add {add['effect']} (score {add['score']:.1f}, p = {add['p_value']:.2g})"
                f"{alias}")
    if a == "drop":
        return f"drop {step['removed']} (no longer needed)"
    if a == "noise":
        if step.get("imu_again"):  # (an IMU scale the stars measured on another model)
            return (f"the {' and '.join(step['imu_again'])} noise was measured by the stars "
                    "on another model: measure it again")
        return "the stars' noise differs with this model: measure it again"
    if a == "exchange":
        return f"exchange {step['removed']} for {step['exchanged_for']}"
    if a == "step":  # diagnosis.auto._step_before
        b = step["step_before_window"]
        # (the time it is fitted from: the test's or a frame earlier, ``step_time``)
        t = (b.get("step_time") or [None, b["installation_step"]["t"]])[1]
        return (f"an attitude step before the evaluation window (t~{t:.1f} s): fitted "
                "beside the model from now on "
                f"(score {b['statistic']:.1f}, p = {b['p_value']:.2g}), not a library effect")
    return "nothing significant"


def notes_lines(summary: dict[str, Any]) -> list[str]:
    """The effects the prior calls uncertain that the model lacks."""
    out: list[str] = []
    for p in summary.get("prior_uncertain", []):
        out.append(f"  note: {p['note']}")
    return out


def unexplained_phrase(u: dict[str, Any]) -> tuple[str, str]:
    """What an 'unexplained' line is a structure of, and its size ('' if none).

    E.g. ``("u residual", "0.043 px across its 5-95 % range")``: the one phrasing of the
    terminal (:func:`unexplained_lines`) and the report (``report_html``).  ``what`` is
    ``""`` where the regressor says it all (the clock's line, :mod:`~.clock`; an installation
    step's, :mod:`~.installation_step`).
    """
    size = u.get("change_px")
    what = f"{u['component']} residual"
    span = "across its 5-95 % range"
    if u["regressor"] == "catalogue star":
        what, span = "residual repeating", "rms per axis at least, left by the cells"
    elif " (fixed pattern" in u["regressor"]:  # noise.pattern_findings
        # (noise_structure.band_offset_size: the band slid to the pattern's phase, its
        # offset fitted through the frames' attitude fit, noise_stars._pattern_size)
        span = "for the most offset band against the bands beside it"
    elif " (periodic" in u["regressor"]:  # in time, or a ripple over the detector
        span = "amplitude"
    elif u["component"] == "along motion":  # stats.motion_spread: a noise in the stamps
        what, span = "residual spread along each star's motion", "rms at that image speed"
    elif u["component"] == stats.CURVE_COMPONENT:  # stats.speed_curve: beyond a time offset
        span = ("at most, up to the 95th percentile of image speed, beyond the time offset's "
                "share")
    elif u["component"] in (COMPONENT, GYRO_COMPONENT):  # diagnosis.clock: the offset
        # changes over the run, or the remainder along the motion grows along a slew
        # (the regressor says what changes: no 'residual vs')
        what, span = "", "along each star's motion at the 95th percentile of image speed"
    elif u["component"] in (STEP, SLEWS):  # installation_step, slew_steps: the regressor
        # says it all
        what, span = "", "at the detector's centre"
    elif u["component"] == "size":
        what = "residual spread (size)"
    elif "radius_px" in (u.get("detail") or {}):  # the lens zone's step, fitted (leads)
        d = u["detail"]
        span = (f"across its 5-95 % range; fitted: a step of {abs(d['step_px']):.2g} px at "
                f"{d['radius_px']:.0f} px, the image scale {d['scale_ppm']:.3g} ppm "
                f"{'larger' if d['scale_ppm'] > 0 else 'smaller'} beyond it")
    elif (u.get("detail") or {}).get("cause") in DRIFTS:
        span = "at the detector's corner over the run"
    elif u.get("detail"):
        # (a field's remainder, not the structure's size: the part a library effect's shape
        # takes went into that effect's estimate; unseen case ``quadrant``, a 0.05 px step
        # on a quarter of the detector: 0.029-0.036 px printed at seeds 21, 22, 24, 0.033
        # with noise-free centroids, the step's quarter 0.021 px per axis off the rest in
        # the innovations)
        what, span = "residual", "at most over 99 % of the stars, what the fit left of it"
    return what, (f"{abs(size):.3g} px {span}" if size is not None else "")


def follows_phrase(u: dict[str, Any]) -> str:
    """Why an 'unexplained' line is ranked after its cause's (its ``follows``).

    The one phrasing of the terminal and the report; ``""`` when the line follows nothing.
    """
    if not u.get("follows"):
        return ""
    what = CAUSES.get(u["follows"], ("its fit", ""))[0]
    # (a shutter's re-run may leave a line at a small share of its size: rolling.shrunk)
    gone = f"gone (or at most {100 * rolling.SHRUNK:.0f} % of it left)" \
        if u["follows"] == "rolling shutter" else "gone"
    return f"follows the {u['follows']}: {gone} once {what} is taken out of the centroids"


#: each cause a line may follow: what its re-run took out of the centroids
#: (:func:`follows_phrase`) and the cause's line in a word (:func:`unexplained_lines`)
CAUSES = {"rolling shutter": ("its fitted readout", "shutter"),
          **{s.cause: ("the drift", "drift") for s in SHAPES},
          **{leads.CAUSES[k]: ("the field's fit", f"{k} field") for k in leads.FIELDS},
          leads.CAUSES["temperature"]: ("the turn's fit", "head-temperature"),
          leads.CAUSES["zone"]: ("the step's fit", "radial step"),
          leads.CAUSES["rows"]: ("its smooth fit over the rows", "row structure"),
          leads.CAUSES["columns"]: ("its smooth fit over the columns", "column structure")}
#: the causes of :mod:`~stellar_cal_ros.diagnosis.shape_drift` (a drifting camera shape)
DRIFTS = frozenset(s.cause for s in SHAPES)


def unexplained_lines(summary: dict[str, Any], n: int = 5) -> list[str]:
    """Residual structure no candidate explains, strongest first, with its size in px."""
    out: list[str] = []
    for u in summary["unexplained"][:n]:
        what, size = unexplained_phrase(u)
        out.append(f"  unexplained: {f'{what} vs ' if what else ''}{u['regressor']} "
              f"(t={u['statistic']:.1f}, p={u['p_value']:.2g}"
              + (f"; {size}" if size else "") + (f"; {follows_phrase(u)}" if u.get("follows")
                                                 else "") + ")")
    if summary["unexplained"]:
        # not "the regressor it follows": 'follows' marks a line a cause's re-run explains
        shown = summary["unexplained"][:n]
        causes = sorted({u["follows"] for u in shown if u.get("follows")})
        out.append("    (structure no library effect explains: an effect outside the library, "
              "e.g. a centroid bias with magnitude, a mount bending with gravity, a per-star "
              "catalogue error; each line names after 'vs' the regressor the residual varies "
              "with, the most significant line first; its size is of what the fit left: the "
              "part of a structure a library effect's shape takes is in that effect's "
              "estimate"
              + "".join(f"; a line that follows the {c} comes after the "
                        f"{CAUSES.get(c, ('', c))[1]}'s" for c in causes) + ")")
    if any(u["component"] == "size" for u in summary["unexplained"][:n]):
        out.append("    (a spread that varies with a regressor is noise that depends on it, or a "
                   "bias whose direction changes along it: state the stars' sigma per "
                   "magnitude / region if it is the noise)")
    return out


def noise_lines(summary: dict[str, Any]) -> list[str]:
    """The noise verdict (tested before any physical effect), and whether it is the cause."""
    out: list[str] = []
    noise = summary.get("noise") or {}
    for line in noise.get("verdict", []):
        out.append(f"noise: {line}")
    if noise.get("rescaled") and not summary.get("recommendation") and \
            not summary.get("unexplained") and not any(
                c.get("significant") for c in summary.get("candidates", [])):
        added = list(summary.get("added") or [])
        if added:  # (discover: "no effect is missing" read as "none was", unseen bundle_s06)
            out.append(f"noise is the cause of the rest: with the measured noise and the effects "
                       f"added ({', '.join(added)}) the model fits and no further effect is "
                       "missing (the σ of a run with the stated noise are wrong by these "
                       "factors)")
        else:
            out.append("noise is the cause: with the measured noise the model fits and no "
                       "effect is missing (the σ of a run with the stated noise are wrong by "
                       "these factors)")
    return out


def data_quality_lines(summary: dict[str, Any]) -> list[str]:
    """The input counters, and the data faults a diagnosis must not explain away."""
    from stellar_cal_ros.methods.results import counts_line, quality_line

    out = [counts_line(summary.get("counts", {}))]
    lock = lost_lock_line(summary.get("lost_lock"))
    if lock:  # (first: the run's residuals near it are the re-acquisition's)
        out.insert(0, lock)
    faults = quality_line(summary.get("data_quality", []),
                          "or judge the candidates below with this in mind")
    return out + ([faults] if faults else [])


def lost_lock_line(lock: dict[str, Any] | None) -> str:
    """The filter's lost lock in one line: when, how often, what to do ('' when it kept it).

    ``lock``: ``summary["lost_lock"]`` (:meth:`~stellar_cal_ros.diagnosis.runstats.
    RunSummary.lock_losses`).  Before, a clause of the noise line and two counts.
    """
    if not lock:
        return ""
    n = lock["reinitializations"]
    eps = lock.get("episodes") or []
    spans = [(f"{a:.2f} s" if b - a < 0.005 else f"{a:.2f}-{b:.2f} s")
             + f" ({k} frame{'s' if k != 1 else ''})" for a, b, k in eps]
    when = ("; rejected in a row at t=" + ", ".join(spans[:5])
            + (f" and {len(spans) - 5} more spans" if len(spans) > 5 else "")
            + ", t from the first frame kept") if spans else ""
    return (f"lost lock: the filter lost the attitude and re-acquired it {n} "
            f"time{'s' if n != 1 else ''} ({lock['frames_lost_lock']} frames counted lost"
            f"{when}): the model's predictions were far off the stars there (a large missing "
            "effect, a wrong prior installation or time offset, an IMU gap in a slew, "
            "misidentified stars or a jump of the stamps); the residuals about those times "
            "are the re-acquisition's and a line there (a step, a repeat) may be its echo: "
            "check the bag and the prior at those times before the lines below")


def diagnosis_lines(summary: dict, calibration=None) -> list[str]:
    """The key lines of a diagnosis summary (:func:`print_diagnosis` prints them).

    ``calibration``: the calibration diagnosed; when it is a run's result, the RMS that run
    reported is printed beside the re-run's, with why they may differ.
    """
    out: list[str] = []
    rms, exp = summary["residual_rms_px"], summary["expected_rms_px"]
    out.append(f"innovation RMS u={rms[0]:.4f} v={rms[1]:.4f} px; the model expects "
          f"u={exp[0]:.4f} v={exp[1]:.4f} px")
    own = (calibration.extra.get("consistency") or {}).get("rms_px") if calibration else None
    if own is not None and len(own) == 2 and \
            max(abs(a - b) for a, b in zip(own, rms, strict=True)) > 1e-4 * max(1e-12, *own):
        out.append(f"  (the run that wrote this calibration reported u={own[0]:.4f} "
              f"v={own[1]:.4f} px: the diagnosis re-runs the model from the calibration's "
              "values with datasheet σ on every estimated effect, as each candidate's run "
              "does; the two agree when the model fits, and differ when it does not, as "
              "a wrong model ends where it starts)")
    out += data_quality_lines(summary)
    out += noise_lines(summary)
    out += notes_lines(summary)
    out.append("candidates (best first):")
    for c in summary["candidates"][:6]:
        flag = "SIGNIFICANT" if c["significant"] else "           "
        after = c.get("after")
        note = (f"  (not needed once {after['effect']} is added: p={after['p_value']:.2g})"
                if after and not c["significant"] else
                f"  (after {after['effect']}: p={after['p_value']:.2g})" if after else "")
        out.append(f"  {flag} {c['effect']:22s} score {c['score']:10.1f}  p={c['p_value']:.2g}  "
              f"RMS after u={c['rms_after_px'][0]:.4f} v={c['rms_after_px'][1]:.4f} px{note}")
    also = [c["effect"] for c in sorted(summary["candidates"][1:],
                                        key=lambda c: -(c.get("after") or {}).get("score", 0))
            if c["significant"] and c.get("after")]
    if also:
        top = next(c["after"]["effect"] for c in summary["candidates"] if c.get("after"))
        out.append(f"  still significant after adding {top}: "
              f"{', '.join(also)} (add them one at a time)")
    implausible = summary.get("implausible", [])
    for u in implausible:
        est, sig = next(iter(u["estimate"].values())), next(iter(u["sigma"].values()))
        after = u.get("after")
        note = (f"; not needed once {after['effect']} is added" if after and not after["needed"]
                else "")
        rec = summary.get("recommendation")
        if not note and rec and rec != u["effect"]:
            note = f"; this round cannot tell while {rec} is missing"
        out.append(f"  implausible: {u['effect']} (fits {est:.3g} +- {sig:.2g} x its physical "
                   f"size{note})")
    if any(not (u.get("after") and not u["after"]["needed"]) for u in implausible):
        out.append("    (a physical effect at the wrong size: the structure has another cause, "
                   "or several effects are missing; add the top candidate and diagnose again)")
    for u in summary["unobservable"]:
        out.append(f"  unobservable: {u['effect']} ({u['reason']})")
    for u in summary.get("screened_out", []):
        out.append(f"  screened out: {u['effect']} ({u['reason']})")
    out += unexplained_lines(summary)
    rec = summary.get("recommendation")
    if not rec:
        out += reliability_lines(summary.get("reliability", []))
    rem = summary.get("remainder")
    if rec and rem:
        out.append(f"recommendation: add --effects {rec}, but the structure is {rem['text']}")
    else:
        out.append(f"recommendation: add --effects {rec}" if rec else
                   "recommendation: no library effect explains the residuals better")
    out += axis_lines(summary)
    out += flexure_hiding_lines(summary)
    out += scope_lines(summary, single_round=True)
    return out


def axis_lines(summary: dict[str, Any]) -> list[str]:
    """An added camera shape that may stand in for a one-axis distortion (one line)."""
    a = summary.get("axis_remainder")
    return [f"  {a['text']}"] if a else []


def flexure_hiding_lines(summary: dict[str, Any]) -> list[str]:
    """The mount flexure's MDB when its gravity-shaped test found nothing (one line)."""
    if not summary.get("flexure_hiding"):
        return []
    from stellar_cal_ros.diagnosis.flexure import hiding_text

    return [f"  {hiding_text(summary['flexure_hiding'])}"]


def flexure_hiding_row(summary: dict[str, Any], pm: str = "±"
                       ) -> tuple[str, str, str] | None:
    """The flexure's row of the report's hiding table: ``(name, MDB, the test)``.

    The phrasing of :func:`flexure_hiding_lines`; ``None`` when no bound was made.
    """
    h = summary.get("flexure_hiding")
    if not h:
        return None
    from stellar_cal_ros.diagnosis.flexure import HIDING_NAME, hiding_phrases

    mdb, test = hiding_phrases(h, pm)
    return HIDING_NAME, f"{mdb} (power {h['power']:.0%})", test


def scope_lines(summary: dict[str, Any], single_round: bool) -> list[str]:
    """What this diagnosis can and cannot tell (issue 21 item 5)."""
    out = []
    rec = summary.get("recommendation")
    if single_round and rec:
        what = (f"{rec} is missing" if not summary.get("remainder") else
                f"{rec} explains most of what is missing, not all of it (the gravity-shaped "
                "remainder above)")
        out.append(f"what one round can tell: {what}. Every other candidate was "
                   f"tested alone beside the missing {rec}, which its estimate partly absorbs: "
                   "a size far from the physical one or a weak score says little until "
                   f"{rec} is in the model (`--effects {rec}` and diagnose again, or "
                   "`stellar-cal discover` does the rounds)")
    elif single_round:
        out.append("what one round can tell: no library effect is missing above its minimal "
                   "detectable size (below); smaller effects, the blind directions and "
                   "effects outside the library beyond the structure listed cannot be told")
    else:
        out.append("what this discovery cannot tell: effects below their minimal detectable "
                   "size and the blind directions (above), and effects outside the library "
                   "beyond the 'unexplained' structure listed; `discover --verify` checks the "
                   "sizes printed on twins of this bag")
    return out


def verify_lines(summary: dict[str, Any]) -> list[str]:
    """The ``--verify`` results: each printed MDB and bias checked on twins of the bag."""
    from stellar_cal_ros.diagnosis.verify import describe as verify_text
    from stellar_cal_ros.diagnosis.verify import noise_check_line

    rows = summary.get("verify")
    if not rows:
        return []
    holds = sum(r["holds"] for r in rows)
    safe = sum(r.get("verdict") == "conservative" for r in rows)
    # twins of an effect discover's clock rule refuses at that sign on this bag: their
    # detection is no claim (verify.clock_rule), their biases are
    refused = sum(bool(r.get("refused_by_clock")) for r in rows)
    seeds = sorted({s for r in rows for s in (r.get("seeds") or (
        [r["seed"]] if "seed" in r else []))})
    # the detection judged on the noise-free twin pair's exact λ (verify.noise_free_record)
    free = sum(r.get("detection_on") == "noise-free twin" for r in rows)
    weak = sum(r.get("detection_on") == "noise-free twin" and not r.get("refused_by_clock")
               and not r["paired_power"] >= 0.65 for r in rows)
    # --verify-twins auto: a row the first twins left undecided has more (verify.undecided)
    first = rows[0].get("twins_first", 1)
    more = sum(r.get("twins", 1) > first for r in rows) if "twins_first" in rows[0] else 0
    held = {r.get("twins", 1) for r in rows if r.get("verdict") == "cannot be judged"}
    signs = {"+-": "±", "+": "", "-": "−"}["".join(sorted(
        {"+" if r.get("sign", 1) > 0 else "-" for r in rows}))]
    unjudged = sum(r.get("verdict") == "cannot be judged" for r in rows)
    # the biases judged on the noise-free twin pair (verify.noise_free_record)
    exact = any(r.get("biases_on") == "noise-free twin" for r in rows)
    misses = sum(len(r.get("first_order_misses") or []) for r in rows)
    noisy = (f", seed{'s' if len(seeds) > 1 else ''} {', '.join(map(str, seeds))}"
             if seeds else ", no noisy twin")
    out = [f"verify (twins of this bag, the effect injected at {signs}its "
           f"printed MDB{noisy}"
           + (f"; {more} of them on more than {first} twins: the first {first} left them "
              "undecided" if more else "")
           + f"): {holds} of {len(rows)} claims hold"
           + (f" ({safe} conservatively: on the safe side)" if safe else "")
           + (f", {unjudged} cannot be judged with "
              f"{max(held) if len(held) == 1 else f'up to {max(held)}'} twins (the shift's "
              "twin-to-twin spread is too large for ± 30 % of the claim)" if unjudged else "")
           + (f"; {refused} of them refused by the clock rule on this bag at that sign "
              "(not a miss: the detection not counted, the biases judged)" if refused else "")
           + (f"; the biases measured on the noise-free twin (exact at the twin's size), "
              f"{misses} of them beyond ± 30 % of the printed first-order bias (the line "
              "gives the measured shift)" if exact else "")
           + (f"; the detection from the noise-free twin's score response (its power at "
              f"the test's level: 80 % claimed, 65 % holds), {weak} of {free} below"
              if free else "")]
    check = noise_check_line(rows[0].get("noise_check"))
    out += [f"  {check}"] if check else []
    out += [f"  {verify_text(r)}" for r in rows]
    return out


def discovery_lines(summary: dict[str, Any]) -> list[str]:
    """Print the path, the final estimates, the rejections and what could still hide."""
    out: list[str] = []
    out += data_quality_lines(summary)
    out += noise_lines(summary)
    out.append("path:")
    for s in summary["path"]:
        rms, exp = s["rms_px"], s["expected_rms_px"]
        out.append(f"  round {s['round']}: RMS u={rms[0]:.4f} v={rms[1]:.4f} px (expects "
              f"{exp[0]:.4f} {exp[1]:.4f}), loglik {s['log_likelihood']:.1f}, "
              f"{s['reruns']} runs in {s['seconds']:.1f} s -> {describe(s)}")
    for eff, params in summary["final_estimates"].items():
        text = ", ".join(estimate_phrase(eff, n, v, s) for n, (v, s) in params.items())
        out.append(f"  added {eff}: {text}{added_caveat(summary, eff)}")
    rem = summary.get("remainder")
    if rem:
        alias = rem.get("could_be_flexure") or {}
        later = [e for e in rem.get("later") or [] if e not in alias]
        out.append(f"  the residuals after {'+'.join(rem['like'])} were {rem['text']}"
                   + (f"; {', '.join(later)}, added after it, may absorb that remainder in "
                      "turn (the rounds' 'remainder' in diagnosis.json)" if later else "")
                   + "".join(f"; {b['text']}" for b in alias.values()))
    out += axis_lines(summary)
    if summary["stopped"] != "nothing more is significant":
        out.append(f"  {summary['stopped']}")
    for rj in summary["rejected"]:
        if rj["status"] != "not_applicable":
            out.append(f"  not added: {rj['effect']}: {rj['reason']}")
    out += notes_lines(summary)
    out += unexplained_lines(summary)
    out += reliability_lines(summary.get("reliability", []))
    out += flexure_hiding_lines(summary)
    out += verify_lines(summary)
    out += scope_lines(summary, single_round=False)
    out.append(f"final model: {', '.join(summary['model']['effects'])}; "
          f"{summary['executor']}, {summary['seconds']:.1f} s in all")
    return out


def added_caveat(summary: dict[str, Any], effect: str) -> str:
    """What follows an added effect's estimates when a mount flexure explains it as well.

    ``" -- could be a mount flexure (outside the library): this motion cannot separate
    them"`` (:data:`~stellar_cal_ros.diagnosis.flexure.ALIAS_TEXT`); for time_offset beside
    the clock's line (:mod:`~stellar_cal_ros.diagnosis.clock`), that the constant is a mean
    over a changing offset; else ``""``: the terminal's and the report's one phrasing.
    """
    from stellar_cal_ros.diagnosis.flexure import ALIAS_TEXT

    alias = (summary.get("remainder") or {}).get("could_be_flexure") or {}
    if effect == "time_offset" and any(u["component"] == COMPONENT
                                       for u in summary.get("unexplained") or []):
        # diagnosis.clock: the offset changes over the run, the constant is its mean
        return (" -- a mean over an offset that changes over the run (see the time "
                "offset's 'unexplained' line): its +- is that of a constant, not the offset "
                "at any time")
    tie = (summary.get("ties") or {}).get(effect)
    if tie is not None:  # diagnosis.auto._tie
        return (f" -- or {tie['with']}: this motion can't tell them apart (either beside "
                f"the other is not significant, p = {tie['p_value']:.2g})")
    return f" -- {ALIAS_TEXT}" if effect in alias else ""


def reliability_lines(entries: list[dict[str, Any]], per_effect: int = 4) -> list[str]:
    """What could still be hiding: each effect's MDB and the σ its bias would dominate.

    Each bias is that of one parameter of the effect alone at its printed MDB (named in
    brackets): the shift an injection of that size reproduces.  Directions the data cannot
    see are a separate clause, with what an effect of plausible size there could shift.
    """
    out: list[str] = []
    if not entries:
        return out
    note = dispersion_note(entries)
    out.append("what could still be hiding (minimal detectable size on this bag, power "
               f"{reliability.POWER:.0%}; each bias is that parameter alone at its MDB"
               + (f"; MDBs {note}" if note else "") + "):")
    for e in entries:
        mdb = mdb_phrase(e)
        flag = "" if e["testable"] else " (not testable: above its plausible size)"
        if e["testable"] and e.get("physical_value") is not None:
            flag = (f" (physics fixes it at {e['physical_value']:g}x: a structure with its "
                    "pattern is flagged from this size on, as 'implausible' below "
                    f"{e['implausible_below']:g}x)")
        if e.get("refused_beside_clock"):  # diagnosis.clock.refuses: the MDB is not what adds it
            flag += f" ({e['refused_beside_clock']['text']})"
        line = f"  {e['effect']:22s} MDB {mdb}{flag}"
        dom = sorted(e["dominates"], key=lambda n: -e["biases"][n] / e["sigma"][n])
        if dom:
            line += "; would bias " + _listed([bias_phrase(e, n) for n in dom], per_effect)
        line += "".join("; " + c for c in first_order_phrases(e, per_effect))
        blind = e.get("blind") or {}
        bdom = sorted(blind.get("dominates", []),
                      key=lambda n: -blind["biases"][n] / e["sigma"][n])
        if bdom:
            line += (f"; blind to {len(blind['directions'])} direction(s) "
                     f"({'; '.join(blind['directions'])}): up to its plausible size there it "
                     "would move " + ", ".join(f"{n} by {blind['biases_shown'][n]}"
                                               for n in bdom[:per_effect])
                     + " with no trace in the residuals")
        out.append(line)
    return out


def estimate_phrase(effect: str, name: str, value: float, sigma: float, pm: str = "+-"
                    ) -> str:
    """``name = value +- sigma`` of parameter ``name`` of ``effect``, in its display unit.

    ``pm``: the plus-minus sign (``"±"`` in the HTML report).
    """
    key = f"{effect}.{name}"
    return f"{name} = {reliability.shown(key, value)} {pm} {reliability.shown(key, sigma)}"


def mdb_phrase(entry: dict[str, Any]) -> str:
    """An effect's minimal detectable size per parameter, e.g. ``tau_x 3.1e-05 rad``.

    :func:`detection_phrase`, then where alternatives share its shape the size from which
    it is named as itself (:func:`identified_phrase`).
    """
    return detection_phrase(entry) + identified_phrase(entry)


def identified_phrase(entry: dict[str, Any]) -> str:
    """From which size an effect whose shape others share is named as itself, or ''.

    ``"; image_plane_tilt, principal_point share 89-90% of its shape on this motion: named
    as itself (not as one of them, nor with 'or' one) from p1 0.000172, p2 0.000169"``
    (``mdb_identified``, :func:`reliability.identification`): the parameters whose size
    exceeds their MDB; one beyond its plausible size is "not below its plausible size".
    """
    ident = entry.get("mdb_identified")
    if not ident:
        return ""
    shares = [max(r.values()) for r in entry["shares_shape_with"].values()]
    lo, hi = f"{min(shares):.0%}", f"{max(shares):.0%}"
    plausible = entry.get("plausible_size", {})
    more = {n: v for n, v in ident.items() if v > entry["mdb"][n]}
    if not more:
        return ""
    within = {n: v for n, v in more.items() if not v > plausible.get(n, np.inf)}
    sizes = ", ".join(f"{n} {reliability.shown(entry['effect'] + '.' + n, v)}"
                      for n, v in within.items())
    beyond = [n for n in more if n not in within]
    if within:
        said = [f"named as itself (not as one of them, nor with 'or' one) from {sizes}"] + (
            [f"along {', '.join(beyond)} not below its plausible size"] if beyond else [])
    else:
        said = [f"not named as itself below its plausible size ({', '.join(beyond)})"]
    return (f"; {', '.join(entry['shares_shape_with'])} "
            f"share{'s' if len(shares) == 1 else ''} "
            f"{lo if lo == hi else lo[:-1] + '-' + hi} of its shape on this motion: "
            + "; ".join(said))


def detection_phrase(entry: dict[str, Any]) -> str:
    """An effect's minimal detectable size per parameter, e.g. ``tau_x 3.1e-05 rad``.

    Where the decision's excess gate sets it (``mdb_set_by`` "explained_gate",
    :func:`reliability.detectability`), it says so, gives the sign the misfit leans to
    (found from a smaller size) and the test's MDB alone; where runs on the bag restated
    it (``gate_probe``, :func:`~.reliability_probe.gate_secant`), the first-order size
    too.  Where probe runs restated it at both signs (``mdb_set_by`` "probe"), the
    first-order size follows, at which the biases are stated: ``tau_x 7.13 mrad (either
    sign, by probe runs; first order 4.54 mrad, the size of the biases)``; "by probe runs
    on the bag's noise-free twin" where they ran there (``twin_probe``, a model that does
    not fit the bag), and so for the test's MDB beside a gate's (``mdb_first_order``).
    """
    from stellar_cal_ros.diagnosis.discover import MIN_EXPLAINED

    def sizes(mdb: dict[str, float], sign: str = "") -> str:
        return ", ".join(f"{n} {'-' if v < 0 else sign}"
                         f"{reliability.shown(entry['effect'] + '.' + n, abs(v))}"
                         for n, v in mdb.items())

    by = entry.get("mdb_set_by")

    def where(n: str) -> str:
        on_twin = "step" in entry.get("twin_probe", {}).get(n, {})
        return "by probe runs" + (" on the bag's noise-free twin" if on_twin else "")

    if by == "explained_gate":
        ran = {n: p["size"] for n, p in entry.get("gate_probe", {}).items()
               if entry["mdb"].get(n) != p["size"]}
        restated = entry.get("mdb_first_order", {})
        test = ", ".join(
            sizes({n: v}) + (f" (either sign, {where(n)}; first order "
                             f"{sizes({n: restated[n]})})" if n in restated else "")
            for n, v in entry["mdb_test"].items())
        return (f"{sizes(entry['mdb'])} (the size at which an effect of either sign removes "
                f"{MIN_EXPLAINED:.0%} of the excess variance, as an add needs"
                + (f", by runs on this bag (first order {sizes(ran)})" if ran else "")
                + "; of the sign "
                f"the misfit leans to from {sizes(entry.get('mdb_leaning', {}), '+')}; the "
                f"test alone: {test})")
    first = entry.get("mdb_test", {}) if by == "probe" else {}

    def one(n: str, v: float) -> str:
        text = reliability.shown(entry["effect"] + "." + n, v)
        if n in first and first[n] != v:
            text += (f" (either sign, {where(n)}; first order "
                     f"{reliability.shown(entry['effect'] + '.' + n, first[n])}, the size "
                     "of the biases)")
        return text

    return ", ".join(f"{n} {one(n, v)}" for n, v in entry["mdb"].items())


def dispersion_note(entries: list[dict[str, Any]]) -> str:
    """What MDBs stated for residuals that scatter beyond the stated noise assume, or ''.

    Such a round divides its statistics (the ratio's, and a screened round's score) by the
    residuals' dispersion (``dispersion``, :func:`reliability.detectability`) and its MDBs
    are stated for it; where the round has an excess to explain (``excess_gate``; absent:
    taken to have one) a candidate must also remove
    :data:`~stellar_cal_ros.diagnosis.discover.MIN_EXPLAINED` of it (on ``dt_step`` that
    gate, not the test, kept gyro_scale_factor at 5x the MDB of residuals as stated from
    being added: doc/benchmarks.md): where it asks more, the MDB is the gate's
    (``mdb_set_by``, :func:`mdb_phrase`); else the note says a lower bound.  A round
    within a few % of its stated noise has no such excess: the note says the dispersion
    alone.
    """
    from stellar_cal_ros.diagnosis.discover import MIN_EXPLAINED

    disp = max((e.get("dispersion", 1.0) for e in entries), default=1.0)
    if disp == 1.0:
        return ""
    gate = any(e.get("mdb_set_by") == "explained_gate" for e in entries)
    excess = any(e.get("excess_gate", True) for e in entries if "dispersion" in e)
    return (f"stated for residuals at {disp:.3g}x the stated noise's variance, as this model "
            f"leaves them, {np.sqrt(disp):.2f}x the MDB of residuals as stated"
            + (f"; here an effect must also remove {MIN_EXPLAINED:.0%} of the excess variance "
               "to be added: where that asks more, the MDB is the size that does, said so "
               "in its row" if gate else
               f"; a lower bound: here an effect must also remove {MIN_EXPLAINED:.0%} of the "
               "excess variance to be added" if excess else ""))


def bias_phrase(entry: dict[str, Any], quantity: str, sigma: str = "sigma") -> str:
    """The bias an effect at its MDB puts into ``quantity``, as the terminal and report say it.

    ``quantity by <bias> [<the effect's parameter>] (measured: <at +MDB>, <at -MDB>)
    (sigma <its σ>)``: the bracket when the effect has several parameters, the measured
    clause when probe runs replaced the first order.  ``sigma``: its symbol.
    """
    src = entry.get("bias_parameter", {})
    minus = entry.get("biases_minus", {})
    shown = reliability.shown
    return (f"{quantity} by {entry['biases_shown'][quantity]}"
            + (f" [{src[quantity]}]" if len(entry["mdb"]) > 1 and src.get(quantity) else "")
            + (f" (measured: {shown(quantity, entry['biases_signed'][quantity])} at +MDB, "
               f"{shown(quantity, minus[quantity])} at -MDB)" if quantity in minus else "")
            + f" ({sigma} {entry['sigma_shown'][quantity]})")


def first_order_phrases(entry: dict[str, Any], limit: int | None = None,
                        sigma: str = "sigma") -> list[str]:
    """The clauses on the rows an effect's first-order biases do not hold, as said everywhere.

    The rows a probe run measured below their σ (with their first-order value), then the
    remainders set apart beside the injection's largest shift; ``limit`` names at most
    that many of each.
    """
    out = []
    below = [n for p in entry.get("probe", {}).values() for n in p["unlisted"]]
    if below:
        out.append(f"first order off, measured by a probe run at +-MDB below its {sigma}: "
                   + _listed([f"{n} (first order {reliability.shown(n, _first(entry, n))})"
                              for n in below], limit))
    rem = entry.get("remainders", [])
    if rem:
        out.append(f"beside its {max(entry['largest_shift_sigma'].values()):.0f} {sigma} "
                   "shift, first-order remainders an injection need not reproduce: "
                   + _listed([f"{n} by {entry['biases_shown'][n]}" for n in rem], limit))
    return out


def _listed(items: list[str], limit: int | None) -> str:
    """``a, b and 3 more`` (all of them without a limit)."""
    if limit is None or len(items) <= limit:
        return ", ".join(items)
    return ", ".join(items[:limit]) + f" and {len(items) - limit} more"


def _first(entry: dict[str, Any], quantity: str) -> float:
    """The first-order bias of a row a probe run replaced."""
    return next(p["first_order"][quantity] for p in entry["probe"].values()
                if quantity in p["first_order"])


def print_diagnosis(summary: dict, calibration=None) -> None:
    """Print :func:`diagnosis_lines`."""
    print("\n".join(diagnosis_lines(summary, calibration)))


def print_discovery(summary: dict[str, Any]) -> None:
    """Print :func:`discovery_lines`."""
    print("\n".join(discovery_lines(summary)))


def print_reliability(entries: list[dict[str, Any]], per_effect: int = 4) -> None:
    """Print :func:`reliability_lines`."""
    for line in reliability_lines(entries, per_effect):
        print(line)
