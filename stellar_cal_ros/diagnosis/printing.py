"""What ``stellar-cal diagnose`` (and ``--auto``) print: the key lines of a summary."""

from __future__ import annotations

from typing import Any

from stellar_cal_ros.diagnosis import reliability
from stellar_cal_ros.diagnosis.auto import describe


def print_notes(summary: dict[str, Any]) -> None:
    """The effects the prior calls uncertain that the model lacks."""
    for p in summary.get("prior_uncertain", []):
        print(f"  note: {p['note']}")


def print_unexplained(summary: dict[str, Any], n: int = 5) -> None:
    """Residual structure no candidate explains, strongest first."""
    for u in summary["unexplained"][:n]:
        print(f"  unexplained: {u['component']} residual vs {u['regressor']} "
              f"(t={u['statistic']:.1f}, p={u['p_value']:.2g})")


def print_data_quality(summary: dict[str, Any]) -> None:
    """The input counters, and the data faults a diagnosis must not explain away."""
    counts = summary.get("counts", {})
    print("counts: " + ", ".join(f"{k}={v}" for k, v in counts.items()))
    faults = summary.get("data_quality", [])
    if faults:
        print("data quality first: " + "; ".join(faults) + ". Residual structure from "
              "damaged input looks like a missing effect: repair the data (or judge the "
              "candidates below with this in mind).")


def print_diagnosis(summary: dict, calibration=None) -> None:
    """Print the key lines of a diagnosis summary.

    ``calibration``: the calibration diagnosed; when it is a run's result, the RMS that run
    reported is printed beside the re-run's, with why they may differ.
    """
    rms, exp = summary["residual_rms_px"], summary["expected_rms_px"]
    print(f"innovation RMS u={rms[0]:.4f} v={rms[1]:.4f} px; the model expects "
          f"u={exp[0]:.4f} v={exp[1]:.4f} px")
    own = (calibration.extra.get("consistency") or {}).get("rms_px") if calibration else None
    if own is not None and len(own) == 2 and \
            max(abs(a - b) for a, b in zip(own, rms, strict=True)) > 1e-4 * max(1e-12, *own):
        print(f"  (the run that wrote this calibration reported u={own[0]:.4f} "
              f"v={own[1]:.4f} px: the diagnosis re-runs the model from the calibration's "
              "values with datasheet σ on every estimated effect, as each candidate's run "
              "does; the two agree when the model fits, and differ when it does not, as "
              "a wrong model ends where it starts)")
    print_data_quality(summary)
    print_notes(summary)
    print("candidates (best first):")
    for c in summary["candidates"][:6]:
        flag = "SIGNIFICANT" if c["significant"] else "           "
        after = c.get("after")
        note = (f"  (not needed once {after['effect']} is added: p={after['p_value']:.2g})"
                if after and not c["significant"] else
                f"  (after {after['effect']}: p={after['p_value']:.2g})" if after else "")
        print(f"  {flag} {c['effect']:22s} score {c['score']:10.1f}  p={c['p_value']:.2g}  "
              f"RMS after u={c['rms_after_px'][0]:.4f} v={c['rms_after_px'][1]:.4f} px{note}")
    also = [c["effect"] for c in sorted(summary["candidates"][1:],
                                        key=lambda c: -(c.get("after") or {}).get("score", 0))
            if c["significant"] and c.get("after")]
    if also:
        top = next(c["after"]["effect"] for c in summary["candidates"] if c.get("after"))
        print(f"  still significant after adding {top}: "
              f"{', '.join(also)} (add them one at a time)")
    implausible = summary.get("implausible", [])
    for u in implausible:
        est, sig = next(iter(u["estimate"].values())), next(iter(u["sigma"].values()))
        after = u.get("after")
        note = (f"; not needed once {after['effect']} is added" if after and not after["needed"]
                else "")
        print(f"  implausible: {u['effect']} (fits {est:.3g} +- {sig:.2g} x its physical "
              f"size{note})")
    if any(not (u.get("after") and not u["after"]["needed"]) for u in implausible):
        print("    (a physical effect at the wrong size: the structure has another cause, or "
              "several effects are missing; add the top candidate and diagnose again)")
    for u in summary["unobservable"]:
        print(f"  unobservable: {u['effect']} ({u['reason']})")
    for u in summary.get("screened_out", []):
        print(f"  screened out: {u['effect']} ({u['reason']})")
    print_unexplained(summary)
    rec = summary.get("recommendation")
    if not rec:
        print_reliability(summary.get("reliability", []))
    print(f"recommendation: add --effects {rec}" if rec else
          "recommendation: no library effect explains the residuals better")


def print_discovery(summary: dict[str, Any]) -> None:
    """Print the path, the final estimates, the rejections and what could still hide."""
    print_data_quality(summary)
    print("path:")
    for s in summary["path"]:
        rms, exp = s["rms_px"], s["expected_rms_px"]
        print(f"  round {s['round']}: RMS u={rms[0]:.4f} v={rms[1]:.4f} px (expects "
              f"{exp[0]:.4f} {exp[1]:.4f}), loglik {s['log_likelihood']:.1f}, "
              f"{s['reruns']} runs in {s['seconds']:.1f} s -> {describe(s)}")
    for eff, params in summary["final_estimates"].items():
        text = ", ".join(f"{n} = {reliability.shown(f'{eff}.{n}', v)} +- "
                         f"{reliability.shown(f'{eff}.{n}', s)}" for n, (v, s) in params.items())
        print(f"  added {eff}: {text}")
    if summary["stopped"] != "nothing more is significant":
        print(f"  {summary['stopped']}")
    for rj in summary["rejected"]:
        if rj["status"] != "not_applicable":
            print(f"  not added: {rj['effect']}: {rj['reason']}")
    print_notes(summary)
    print_unexplained(summary)
    print_reliability(summary.get("reliability", []))
    print(f"final model: {', '.join(summary['model']['effects'])}; "
          f"{summary['executor']}, {summary['seconds']:.1f} s in all")


def print_reliability(entries: list[dict[str, Any]], per_effect: int = 4) -> None:
    """What could still be hiding: each effect's MDB and the σ its bias would dominate.

    Each bias is that of one parameter of the effect alone at its printed MDB (named in
    brackets): the shift an injection of that size reproduces.  Directions the data cannot
    see are a separate clause, with what an effect of plausible size there could shift.
    """
    if not entries:
        return
    print("what could still be hiding (minimal detectable size on this bag, power "
          f"{reliability.POWER:.0%}; each bias is that parameter alone at its MDB):")
    for e in entries:
        mdb = ", ".join(f"{n} {reliability.shown(e['effect'] + '.' + n, v)}"
                        for n, v in e["mdb"].items())
        flag = "" if e["testable"] else " (not testable: above its plausible size)"
        line = f"  {e['effect']:22s} MDB {mdb}{flag}"
        dom = sorted(e["dominates"], key=lambda n: -e["biases"][n] / e["sigma"][n])
        src = e.get("bias_parameter", {})
        if dom:
            line += "; would bias " + ", ".join(
                f"{n} by {e['biases_shown'][n]}"
                + (f" [{src[n]}]" if len(e["mdb"]) > 1 and src.get(n) else "")
                + f" (sigma {e['sigma_shown'][n]})"
                for n in dom[:per_effect]) + (f" and {len(dom) - per_effect} more"
                                              if len(dom) > per_effect else "")
        blind = e.get("blind") or {}
        bdom = sorted(blind.get("dominates", []),
                      key=lambda n: -blind["biases"][n] / e["sigma"][n])
        if bdom:
            line += (f"; blind to {len(blind['directions'])} direction(s) "
                     f"({'; '.join(blind['directions'])}): up to its plausible size there it "
                     "would move " + ", ".join(f"{n} by {blind['biases_shown'][n]}"
                                               for n in bdom[:per_effect])
                     + " with no trace in the residuals")
        print(line)
