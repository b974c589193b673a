"""HTML pages of the reports: one run, two runs, a diagnosis.

``stellar-cal report`` (:func:`write_run_report`), ``compare`` (:func:`write_compare_report`)
and ``diagnose`` (:func:`write_html`).  The figures come from
:mod:`stellar_cal_ros.diagnosis.report`.

Each page is one self-contained ``report.html`` beside its PNGs: a summary first, then the
calibrated values ± σ, the residuals against the noise the model expects, over the
detector, over time and against each possible cause, every parameter over time, the NIS,
and the provenance (bag, prior, command line, version, date).
"""

from __future__ import annotations

import html
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from stellar_cal_ros import __version__
from stellar_cal_ros.diagnosis import printing, report, stats
from stellar_cal_ros.effects import registry

Table = dict[str, np.ndarray]

_STYLE = """body{font-family:sans-serif;max-width:1400px;margin:auto;padding:0 1em;color:#222}
table{border-collapse:collapse;margin:.5em 0}
td,th{border:1px solid #ccc;padding:3px 6px;vertical-align:top;text-align:left}
td.num{text-align:right;font-family:monospace} tr.sig{background:#e6ffe6}
tr.bad{background:#ffe6e6} td.expl{font-size:85%;max-width:520px}
img{max-width:100%;border:1px solid #eee} p.cap{color:#555;font-size:90%;margin-top:0}
nav a{margin-right:1em} .warn{color:#a00} h2{border-bottom:1px solid #ddd;margin-top:1.6em}"""


def _e(x: Any) -> str:
    return html.escape(str(x))


def _page(title: str, body: str, nav: list[tuple[str, str]] | None = None) -> str:
    links = "".join(f"<a href='#{a}'>{_e(t)}</a>" for a, t in nav or [])
    return (f"<!doctype html><html><head><meta charset='utf-8'><title>{_e(title)}</title>"
            f"<style>{_STYLE}</style></head><body><h1>{_e(title)}</h1>"
            + (f"<nav>{links}</nav>" if links else "") + body + "</body></html>")


def _figure(anchor: str, title: str, image: Path | str | None, caption: str) -> str:
    if image is None:
        return ""
    return (f"<h2 id='{anchor}'>{_e(title)}</h2><img src='{_e(Path(image).name)}' "
            f"alt='{_e(title)}'><p class=cap>{caption}</p>")


# ------------------------------------------------------------------------------ tables
def _fmt(x: float, digits: int = 6) -> str:
    return "–" if x is None or not np.isfinite(x) else f"{x:.{digits}g}"


def calibration_table(history: Table | None, calibration: Any,
                      truth: dict[str, float] | None = None,
                      extra_columns: bool = True) -> str:
    """The calibrated values ± σ: one row per estimated parameter (display units).

    From the history's last row where there is one (every estimated parameter with its σ),
    else from the calibration file's camera / installation / sensor blocks.
    """
    rows = []
    if history is not None and report.parameter_names(history):
        head = ("<tr><th>parameter</th><th>value</th><th>± σ</th><th>unit</th>"
                + ("<th>truth</th><th>(value − truth) / σ</th>" if truth else "") + "</tr>")
        for name in report.parameter_names(history):
            scale, unit = report.display_unit(name, report.parameter_unit(name))
            v = float(history[name][-1]) * scale
            s = float(history[f"sigma.{name}"][-1]) * scale
            cells = (f"<td>{_e(name)}</td><td class=num>{_fmt(v, 8)}</td>"
                     f"<td class=num>{_fmt(s, 3)}</td><td>{_e(unit)}</td>")
            cls = ""
            if truth:
                tv = truth.get(name)
                z = (v - tv * scale) / s if tv is not None and s > 0 else float("nan")
                cls = " class=bad" if np.isfinite(z) and abs(z) > 3 else ""
                cells += (f"<td class=num>{_fmt(None if tv is None else tv * scale, 8)}</td>"
                          f"<td class=num>{_fmt(z, 3)}</td>")
            rows.append(f"<tr{cls}>{cells}</tr>")
        note = ("<p class=cap>Installation: the small rotation δ of the tracker about its own "
                "axes from the prior's mounting (R_imu_st = R_prior · Exp(δ)); gyro bias in "
                "deg/h; scale factors in ppm. Red rows: more than 3σ from the truth.</p>")
        return f"<table>{head}{''.join(rows)}</table>{note}"
    cov_table = _covariance_table(calibration)
    if cov_table:
        return cov_table
    cam = calibration.camera
    sig = calibration.sigma or {}
    K = ((sig.get("camera") or {}).get("camera_matrix") or {}).get("data") or [0.0] * 9
    for label, v, s, unit in (("fx", cam.fx, K[0], "px"), ("fy", cam.fy, K[4], "px"),
                              ("cx", cam.cx, K[2], "px"), ("cy", cam.cy, K[5], "px"),
                              ("time_offset", calibration.time_offset * 1e3,
                               float(sig.get("time_offset") or 0) * 1e3, "ms")):
        rows.append(f"<tr><td>{label}</td><td class=num>{_fmt(v, 8)}</td>"
                    f"<td class=num>{_fmt(s, 3) if s else '–'}</td><td>{unit}</td></tr>")
    q = np.round(calibration.installation.as_quat(), 10).tolist()
    rows.append(f"<tr><td>installation quaternion_xyzw</td><td colspan=3>{q}</td></tr>")
    return ("<table><tr><th>quantity</th><th>value</th><th>± σ</th><th>unit</th></tr>"
            f"{''.join(rows)}</table><p class=cap>No history file: the values of the "
            "calibration file.</p>")


def _covariance_table(calibration: Any) -> str:
    """Values ± σ from the result's covariance sidecar (a batch result has no history)."""
    import copy

    from stellar_cal_ros.errors import StellarCalError
    from stellar_cal_ros.io.calibration import load_covariance

    side = calibration.extra.get("covariance_file")
    folder = calibration.extra.get("_folder")
    if not side or folder is None:
        return ""
    try:
        cov = load_covariance(Path(folder) / side)
    except StellarCalError:
        return ""
    values: dict[str, float] = {}
    for eff_id in dict.fromkeys(n.split(".", 1)[0] for n in cov.names):
        if eff_id == "installation":
            continue  # δ from the run's prior mounting: the quaternion is in the file
        try:
            eff = copy.deepcopy(registry.create(eff_id))
            v, _ = eff.initial(calibration)
        except Exception:  # noqa: BLE001 - a plugin effect not loaded here
            continue
        values.update({f"{eff_id}.{p}": float(x) for p, x in zip(eff.parameter_names, v,
                                                                   strict=True)})
    rows = []
    for name, sd in zip(cov.names, cov.sigma, strict=True):
        scale, unit = report.display_unit(name, report.parameter_unit(name))
        v = values.get(name)
        rows.append(f"<tr><td>{_e(name)}</td><td class=num>"
                    f"{_fmt(None if v is None else v * scale, 8)}</td>"
                    f"<td class=num>{_fmt(sd * scale, 3)}</td><td>{_e(unit)}</td></tr>")
    q = np.round(calibration.installation.as_quat(), 10).tolist()
    return ("<table><tr><th>parameter</th><th>value</th><th>± σ</th><th>unit</th></tr>"
            f"{''.join(rows)}</table><p class=cap>From {_e(side)} (σ) and the result file "
            f"(values); installation quaternion_xyzw {q}, its σ as a rotation about the "
            "tracker axes.</p>")


def provenance_table(calibration: Any, result_path: Path | None, bag: Path | None,
                     residual_source: str = "", history: Table | None = None) -> str:
    """Bag, prior, command line, package version and date of the run and of the report."""
    prov = dict(calibration.extra.get("provenance") or {})
    init = calibration.extra.get("init_from") or {}
    effects = ", ".join(estimated_effects(calibration, history)) or "(not recorded)"
    if not calibration.estimated and history is not None:
        effects += " (from the history file)"
    when = datetime.fromtimestamp(calibration.stamp, UTC).isoformat(timespec="seconds")
    rows = [("result file", result_path), ("method", calibration.method),
            ("estimated effects", effects),
            ("estimate time", f"{when} (POSIX {calibration.stamp:.3f} s)"),
            ("bag", bag or prov.get("bag")), ("prior", prov.get("prior")),
            ("command line", prov.get("command")), ("stellar_cal version (run)",
                                                      prov.get("version")),
            ("run date (UTC)", prov.get("date")),
            ("started from", init.get("file")),
            ("covariance file", calibration.extra.get("covariance_file")),
            ("residuals", residual_source),
            ("report written", f"{datetime.now(UTC).isoformat(timespec='seconds')} "
                               f"by stellar_cal {__version__}")]
    body = "".join(f"<tr><th>{_e(k)}</th><td>{_e(v)}</td></tr>" for k, v in rows
                   if v not in (None, ""))
    if not prov:
        body += ("<tr><th>note</th><td>this result carries no provenance block (written "
                 "by an older version or by a library call)</td></tr>")
    return f"<table>{body}</table>"


def window_mask(res: Table, fraction: float, calibration: Any = None) -> np.ndarray:
    """Stars of the run's evaluation window.

    From the result's ``consistency.window_start`` (the window the run's own verdict
    used), else the last ``fraction`` of the table's frames.
    """
    cons = (calibration.extra.get("consistency") or {}) if calibration is not None else {}
    start = cons.get("window_start")
    if isinstance(start, (int, float)) and len(res["t"]):
        return np.asarray(res["t"], float) >= start
    return stats.evaluation_mask(res, fraction)


def nis_per_dof(res: Table, mask: np.ndarray) -> dict[str, float]:
    """NIS per degree of freedom of the window's accepted stars and its 95 % band.

    Each star has 2 dof; this is the one NIS figure every command and report prints.
    """
    nis = stats.nis_consistency({**res, "nis": report._nis(res)}, mask)
    return {k: v / 2.0 if k != "n" else v for k, v in nis.items()}


def judged_nis(res: Table, mask: np.ndarray, calibration: Any = None
               ) -> tuple[dict[str, float], str]:
    """:func:`nis_per_dof` as the run judged it, and a note of why (empty when as white).

    A run that declared its stars' noise correlated (``--noise-scale star=K,rho=R``) holds
    in their σ the factor a white-noise filter needs, so its NIS/dof reads ~1/k²: it is
    judged as the run judged it (:func:`~stellar_cal_ros.methods.results.consistency`:
    times its k², in its widened band; the calibration's ``consistency.correlated``), not
    as white noise ("smaller than the noise model expects").
    """
    nis = nis_per_dof(res, mask)
    cons = (calibration.extra.get("consistency") or {}) if calibration is not None else {}
    corr = cons.get("correlated")
    if not corr or len(cons.get("interval") or ()) != 2:
        return nis, ""
    raw = nis["mean"]
    nis = dict(nis, mean=raw * corr["inflation"], lower=cons["interval"][0],
               upper=cons["interval"][1])
    return nis, (f" (x{corr['inflation']:.3g} for the stars' noise declared correlated from "
                 f"frame to frame, rho {corr['star_rho']:.2f}; {raw:.3f} as white)")


def _summary_line(res: Table, fraction: float, calibration: Any = None) -> str:
    mask = window_mask(res, fraction, calibration)
    rms, exp = stats.rms(res, mask), stats.expected_rms(res, mask)
    nis, declared = judged_nis(res, mask, calibration)
    ok = nis["lower"] <= nis["mean"] <= nis["upper"]
    verdict = ("consistent with the noise model" if ok else
               "<span class=warn>larger than the noise model allows: an effect is missing "
               "or a noise level is wrong</span>" if nis["mean"] > nis["upper"] else
               "<span class=warn>smaller than the noise model expects (noise set too "
               "high?)</span>")
    m = mask & stats.accepted(res)
    gated = int(np.sum(mask & ~stats.accepted(res)))
    return (f"Innovation RMS <b>{rms[0]:.4f} / {rms[1]:.4f} px</b> (u / v) against the "
            f"{exp[0]:.4f} / {exp[1]:.4f} px the model expects; NIS/dof "
            f"<b>{nis['mean']:.3f}</b>{declared} (95 % band {nis['lower']:.3f} … "
            f"{nis['upper']:.3f}): "
            f"{verdict}. {int(m.sum())} stars accepted, {gated} gated, in the evaluation "
            "window (the second half of the run).")


# ------------------------------------------------------------------------------ pages
_CAPTIONS = {
    "hist": ("Left: innovations whitened by their predicted covariance — a correct model "
             "gives N(0, 1) (black); heavier tails or a wider core mean unmodelled error. "
             "Right: the same in pixels against the RMS the model expects (dashed)."),
    "stars": ("Each accepted star's innovation (measured − predicted centroid) at its position, "
              "magnified as the reference arrow says; colour is the length in px, on one "
              "scale for all panels. Random noise looks random; a pattern is a missing "
              "effect."),
    "field": ("Mean innovation of each region of the detector (mrcal-style): systematic "
              "error survives the averaging, noise does not. One colour scale and one "
              "reference arrow for all panels."),
    "params": ("Every estimated parameter against time: line = estimate, dark band ±1σ, "
               "light band ±3σ, dashed red = truth (simulated bags). The σ must shrink and "
               "the estimate settle inside its band."),
    "nis": ("Normalized innovation squared per degree of freedom. Its moving mean must stay "
            "in the green band (95 % if the model and its noise are right)."),
    "regressors": ("Innovation RMS in bins of each possible cause (dotted: the RMS the model "
                   "expects); the radius panel shows the mean radial component (distortion "
                   "signature). A slope or a step is a missing effect."),
    "time": "Frame-mean innovations against time.",
    "unexplained": ("The residual structure no candidate explains: each panel is one line of "
                    "the diagnosis, the residual component against its regressor (grey: "
                    "stars; black: binned mean ± standard error)."),
}


def _run_figures(out: Path, panels: list[tuple[str, Table]], width: int, height: int,
                 centre: tuple[float, float], fraction: float, prefix: str = "") -> list:
    """The residual figures shared by the one-run and two-run pages."""
    figs = [("hist", "Residuals against the expected noise",
             report.plot_histograms(panels, fraction, out / f"{prefix}histogram.png")),
            ("stars", "Residuals of every star over the detector",
             report.plot_star_vectors(panels, width, height, fraction,
                                      out / f"{prefix}star_vectors.png")),
            ("field", "Regional mean residual over the detector",
             report.plot_vector_fields(panels, width, height, fraction,
                                       out / f"{prefix}vector_field.png")),
            ("regressors", "Residuals against possible causes",
             report.plot_regressors(panels, centre, fraction, out / f"{prefix}regressors.png")),
            ("time", "Innovations against time",
             report.plot_time(panels, out / f"{prefix}time.png"))]
    return figs


def _candidates_html(summary: dict[str, Any]) -> str:
    rows = []
    for c in summary.get("candidates", []):
        try:
            expl = registry.create(c["effect"]).explanation
        except Exception:  # noqa: BLE001 - a plugin effect not loaded here
            expl = ""
        eff = c["effect"]
        est = ", ".join(printing.estimate_phrase(eff, k, v, c["sigma"][k], "±")
                        for k, v in c["estimate"].items())
        rows.append(
            f"<tr class={'sig' if c['significant'] else 'ns'}><td><b>{_e(c['effect'])}</b></td>"
            f"<td class=num>{c['score']:.1f}</td><td class=num>{c['p_value']:.2g}"
            f"{_after_note(c)}</td><td class=num>{c['rms_after_px'][0]:.4f} / "
            f"{c['rms_after_px'][1]:.4f}</td><td>{_e(est)}</td><td class=expl>{_e(expl)}</td>"
            "</tr>")
    return ("<table><tr><th>effect</th><th>score 2Δℓ</th><th>p (Bonferroni)</th>"
            "<th>RMS after, px (u / v)</th><th>estimate ± σ</th><th>what it is</th></tr>"
            f"{''.join(rows)}</table>")


def _after_note(c: dict[str, Any]) -> str:
    """The candidate's test after the top one, for the table."""
    a = c.get("after")
    if not a:
        return ""
    verdict = "significant" if c["significant"] else "not needed then"
    return (f"<br><small>after {_e(a['effect'])}: p = {a['p_value']:.2g} "
            f"({verdict})</small>")


def _unexplained_html(summary: dict[str, Any], image: Path | str | None = None) -> str:
    items = "".join(
        f"<li>{_e(what) + ' vs ' if what else ''}<b>{_e(u['regressor'])}</b>: "
        f"t = {u['statistic']:.1f}, "
        f"p = {u['p_value']:.2g}" + (f", {_e(size)}" if size else "")
        + (f"; {_e(printing.follows_phrase(u))}" if u.get("follows") else "")
        + (f" (<a href='#unexplained-plot'>plot {k + 1}</a>)" if image else "") + "</li>"
        for k, u in enumerate(summary.get("unexplained", []))
        for what, size in [printing.unexplained_phrase(u)]) or "<li>none</li>"
    fig = (f"<img id='unexplained-plot' src='{_e(Path(image).name)}' alt='unexplained'>"
           f"<p class=cap>{_CAPTIONS['unexplained']}</p>" if image else "")
    return f"<ul>{items}</ul>{fig}"


def _pre(lines: list[str]) -> str:
    return "<pre>" + _e("\n".join(lines)) + "</pre>"


def _all_candidates_html(summary: dict[str, Any]) -> str:
    """Every candidate of the last round with its status: ranked, screened out, ..."""
    rows = []
    for c in summary.get("candidates", []):
        rows.append((c["effect"], "significant" if c["significant"] else "ranked",
                     f"{c['p_value']:.2g}", f"{c['score']:.1f}", "re-run with it"))
    for key, status in (("implausible", "implausible"), ("screened_out", "screened out"),
                        ("unobservable", "not testable"), ("not_applicable", "not applicable")):
        for c in summary.get(key, []):
            p = c.get("p_value")
            rows.append((c["effect"], status, "" if p is None else f"{p:.2g}",
                         "" if c.get("score") is None else f"{c['score']:.1f}",
                         c.get("reason", "")))
    if not rows:
        return "<p>none</p>"
    return ("<table><tr><th>effect</th><th>status</th><th>p</th><th>score</th><th>why</th>"
            "</tr>" + "".join(f"<tr><td><b>{_e(a)}</b></td><td>{_e(b)}</td><td class=num>"
                              f"{_e(c)}</td><td class=num>{_e(d)}</td><td>{_e(w)}</td></tr>"
                              for a, b, c, d, w in rows) + "</table>")


def _reliability_html(summary: dict[str, Any]) -> str:
    rows = []
    for e in summary.get("reliability", []):
        mdb = printing.mdb_phrase(e)
        bias = "; ".join(
            ([", ".join(printing.bias_phrase(e, n, "σ") for n in e["dominates"])]
             if e["dominates"] else []) + printing.first_order_phrases(e, sigma="σ"))
        blind = e.get("blind") or {}
        btxt = ("; ".join(blind.get("directions", [])) + ": " + ", ".join(
            f"{n} by {blind['biases_shown'][n]}" for n in blind.get("dominates", []))
            if blind.get("dominates") else "")
        # diagnosis.clock.refuses: the MDB is not what adds it
        clk = (e.get("refused_beside_clock") or {}).get("text")
        rows.append(f"<tr><td><b>{_e(e['effect'])}</b></td><td>{_e(mdb)}"
                    f"{'' if e['testable'] else ' (not testable)'}"
                    f"{f' ({_e(clk)})' if clk else ''}</td><td>{_e(bias)}</td>"
                    f"<td>{_e(btxt)}</td></tr>")
    flex = printing.flexure_hiding_row(summary)
    if flex:
        # outside the library: its MDB from the gravity-shaped test that found nothing
        rows.append(f"<tr><td><b>{_e(flex[0])}</b></td><td>{_e(flex[1])}</td>"
                    f"<td>{_e(flex[2])}</td><td></td></tr>")
    if not rows:
        return ""
    note = printing.dispersion_note(summary.get("reliability", []))
    return ("<h2>What could still be hiding</h2><p>Minimal detectable size (power 80 %) on "
            "this bag, and the bias each parameter alone at that size leaves (the shift an "
            "injection reproduces); blind directions: what an effect of plausible size there "
            "would move with no trace." + (f" MDBs {_e(note)}." if note else "")
            + "</p><table><tr><th>effect</th><th>MDB</th><th>would "
            "bias (above its σ)</th><th>blind directions</th></tr>" + "".join(rows)
            + "</table>")


def _discovery_html(summary: dict[str, Any]) -> str:
    """The sections the terminal shows: noise, path, added, candidates, hiding, verify."""
    out = []
    noise = summary.get("noise") or {}
    if noise.get("verdict"):
        out.append("<h2>Noise (tested before any effect)</h2>" + _pre(noise["verdict"]))
    if summary.get("path"):
        rows = "".join(
            f"<tr><td>{s['round']}</td><td>{_e(', '.join(s['model']))}</td><td class=num>"
            f"{s['rms_px'][0]:.4f} / {s['rms_px'][1]:.4f}</td><td class=num>"
            f"{s['expected_rms_px'][0]:.4f} / {s['expected_rms_px'][1]:.4f}</td>"
            f"<td>{_e(s['action'])}</td></tr>" for s in summary["path"])
        out.append("<h2>Path</h2><table><tr><th>round</th><th>model</th><th>RMS, px</th>"
                   f"<th>expected, px</th><th>then</th></tr>{rows}</table>")
    if summary.get("final_estimates"):
        items = "".join(
            f"<li><b>{_e(eff)}</b>: " + _e(", ".join(
                printing.estimate_phrase(eff, n, v, sg, "±")
                for n, (v, sg) in params.items()) + printing.added_caveat(summary, eff))
            + "</li>"
            for eff, params in summary["final_estimates"].items())
        out.append(f"<h2>Added effects</h2><ul>{items}</ul>")
    out.append("<h2>Every candidate of the last round</h2>" + _all_candidates_html(summary))
    out.append(_reliability_html(summary))
    if summary.get("verify"):
        from stellar_cal_ros.diagnosis.verify import describe, noise_check_line

        check = noise_check_line(summary["verify"][0].get("noise_check"))
        out.append("<h2>Verified on twins of this bag</h2><ul>" + "".join(
            f"<li>{_e(line)}</li>" for line in ([check] if check else [])
            + [describe(r) for r in summary["verify"]]) + "</ul>")
    if summary.get("terminal"):
        out.append("<h2>What the terminal showed</h2>" + _pre(summary["terminal"]))
    return "".join(out)


def write_html(out_dir: Path, summary: dict[str, Any], images: list[tuple[str, str]],
               title: str, unexplained_image: str | Path | None = None) -> Path:
    """Write the diagnosis page ``report.html`` and return its path.

    ``images`` are ``(title, file name)`` pairs shown after the tables;
    ``unexplained_image`` (from :func:`report.plot_unexplained`) is linked from every
    "unexplained" line.
    """
    out_dir = Path(out_dir)
    unobs = "".join(f"<li><b>{_e(u['effect'])}</b>: {_e(u['reason'])}</li>"
                    for u in summary.get("implausible", []) + summary.get("unobservable", [])
                    + summary.get("not_applicable", [])) or "<li>none</li>"
    rms, exp = summary["residual_rms_px"], summary["expected_rms_px"]
    nis = summary["nis"]
    imgs = "".join(f"<h2>{_e(t)}</h2><img src='{_e(f)}'>" for t, f in images)
    body = (_discovery_html(summary) + f"<p>Model: <b>{_e(summary['model']['method'])}</b> with "
            f"{_e(', '.join(summary['model']['effects']))}. Evaluation: "
            f"{_e(summary['evaluation'])}.</p><p>Innovation RMS <b>{rms[0]:.4f} / "
            f"{rms[1]:.4f} px</b> (u / v) against the {exp[0]:.4f} / {exp[1]:.4f} px the model "
            f"expects; NIS/dof {nis['mean'] / 2:.3f} (consistent: {nis['lower'] / 2:.3f} … "
            f"{nis['upper'] / 2:.3f}).</p><h2>Candidate effects</h2><p>Best first; green = "
            "significant after correction, and still significant once the top one is "
            f"added.</p>{_candidates_html(summary)}<h2>Unexplained structure</h2>"
            f"{_unexplained_html(summary, unexplained_image)}<h2>Not ranked</h2><ul>{unobs}</ul>"
            f"{imgs}")
    path = out_dir / "report.html"
    path.write_text(_page(title, body))
    return path


def write_run_report(out_dir: str | Path, calibration: Any, residuals: Table,
                     history: Table | None = None, summary: dict[str, Any] | None = None,
                     truth: Any = None, *, result_path: Path | None = None,
                     bag: Path | None = None, residual_source: str = "",
                     fraction: float = 0.5, title: str | None = None) -> Path:
    """The report of one run: PNGs and ``report.html`` in ``out_dir``; returns the page.

    Parameters
    ----------
    out_dir : path
        Folder to write (created).
    calibration : Calibration
        The run's result.
    residuals : dict of arrays
        The run's residual table (``t`` POSIX s).
    history : dict of arrays, optional
        The run's history table (``RESULT.history.csv``): parameters over time, NIS.
    summary : dict, optional
        ``diagnosis.json`` of a diagnosis of this result: candidates, and a plot behind
        every unexplained line.
    truth : Calibration, optional
        The true calibration (``BAG.truth.yaml`` of a simulated bag).
    result_path, bag : path, optional
        For the provenance table.
    residual_source : str
        Where the residuals come from (provenance).
    fraction : float
        Last fraction of the frames the statistics use (after convergence).
    title : str, optional
        Page title (default from the result's name).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if result_path is not None:  # where a covariance sidecar would be
        import copy

        calibration = copy.copy(calibration)
        calibration.extra = {**calibration.extra, "_folder": str(Path(result_path).parent)}
    cam = calibration.camera
    centre = (cam.cx, cam.cy)
    name = result_path.stem if result_path else calibration.method
    panels = [(name, residuals)]
    tv = (report.truth_values(history, calibration, truth)
          if truth is not None and history is not None else None)
    figs = _run_figures(out, panels, cam.width, cam.height, centre, fraction)
    if history is not None:
        figs.insert(3, ("params", "Parameters over time",
                        report.plot_parameter_history(history, out / "parameters.png", tv)))
        figs.insert(4, ("nis", "Consistency: NIS over time",
                        report.plot_nis(history, out / "nis.png")))
    body = [f"<p>{_summary_line(residuals, fraction, calibration)}</p>",
            "<h2 id='values'>Calibrated values ± σ</h2>",
            calibration_table(history, calibration, tv)]
    body += [_figure(a, t, img, _CAPTIONS[a]) for a, t, img in figs]
    nav = [("values", "values")] + [(a, t.split(":")[0]) for a, t, img in figs if img]
    if summary is not None:
        img = report.plot_unexplained(residuals, summary.get("unexplained", []), centre,
                                      fraction, out / "unexplained.png")
        body += ["<h2 id='diagnosis'>Diagnosis</h2>", _candidates_html(summary),
                 "<h3>Unexplained structure</h3>", _unexplained_html(summary, img)]
        nav.append(("diagnosis", "diagnosis"))
    body += ["<h2 id='provenance'>Provenance</h2>",
             provenance_table(calibration, result_path, bag, residual_source, history)]
    nav.append(("provenance", "provenance"))
    path = out / "report.html"
    path.write_text(_page(title or f"stellar_cal report: {name}", "".join(body), nav))
    return path


@dataclass
class RunData:
    """One run for :func:`write_compare_report`."""

    name: str
    calibration: Any
    residuals: Table
    history: Table | None = None
    path: Path | None = None
    residual_source: str = ""


def model_change(method_a: str, ea: list[str], method_b: str, eb: list[str]) -> str:
    """One sentence on how B's model differs from A's.

    A change of method is not an added effect.
    """
    added = [e for e in eb if e not in ea]
    removed = [e for e in ea if e not in eb]
    if method_a != method_b:
        return (f"A and B are different methods ({method_a} and {method_b}), not one model "
                f"with an effect added: B estimates {', '.join(added) or 'nothing'} that A "
                f"does not, A estimates {', '.join(removed) or 'nothing'} that B does not.")
    return (f"B adds {', '.join(added) or 'nothing'}" +
            (f" and drops {', '.join(removed)}" if removed else "") + " to A's model.")


def estimated_effects(calibration: Any, history: Table | None = None) -> list[str]:
    """The effects a run estimated: its ``estimated`` list, else its history's columns."""
    if calibration.estimated:
        return list(calibration.estimated)
    if history is None:
        return []
    return list(dict.fromkeys(n.split(".", 1)[0] for n in report.parameter_names(history)))


def _final(history: Table | None) -> dict[str, tuple[float, float]]:
    if history is None:
        return {}
    return {n: (float(history[n][-1]), float(history[f"sigma.{n}"][-1]))
            for n in report.parameter_names(history)}


def _installation_in(frame_of: RunData, run: RunData) -> dict[str, tuple[float, float]]:
    """``run``'s installation as δ from ``frame_of``'s prior mounting (rad, with run's σ).

    Each history holds δ from its own run's prior; a run started from another's result
    (``--init-from``) has another reference, so B is re-expressed in A's.
    """
    from scipy.spatial.transform import Rotation

    h = frame_of.history
    names = [f"installation.{p}" for p in ("rx", "ry", "rz")]
    if h is None or run.history is None or not all(n in h for n in names) or not all(
            n in run.history for n in names):
        return {}
    delta_a = np.array([h[n][-1] for n in names])
    nominal = frame_of.calibration.installation * Rotation.from_rotvec(-delta_a)
    delta = (nominal.inv() * run.calibration.installation).as_rotvec()
    return {n: (float(d), float(run.history[f"sigma.{n}"][-1]))
            for n, d in zip(names, delta, strict=True)}


def comparison_table(a: RunData, b: RunData, truth: dict[str, float] | None = None) -> str:
    """Parameters of two runs: values ± σ, the difference in σ of B, truth.

    The installation of both is δ from A's prior mounting.
    """
    fa, fb = _final(a.history), _final(b.history)
    fb.update(_installation_in(a, b))
    names = list(dict.fromkeys(list(fa) + list(fb)))
    rows = []
    for n in names:
        scale, unit = report.display_unit(n, report.parameter_unit(n))
        va, sa = fa.get(n, (np.nan, np.nan))
        vb, sb = fb.get(n, (np.nan, np.nan))
        d = (vb - va) * scale
        z = (vb - va) / sb if sb > 0 else np.nan
        cls = " class=bad" if np.isfinite(z) and abs(z) > 3 else ""
        t = "" if not truth else f"<td class=num>{_fmt((truth.get(n, np.nan)) * scale, 8)}</td>"
        only = "" if n in fa and n in fb else (" (only in B)" if n in fb else " (only in A)")
        rows.append(f"<tr{cls}><td>{_e(n)}{only}</td><td>{_e(unit)}</td>"
                    f"<td class=num>{_fmt(va * scale, 8)} ± {_fmt(sa * scale, 2)}</td>"
                    f"<td class=num>{_fmt(vb * scale, 8)} ± {_fmt(sb * scale, 2)}</td>"
                    f"<td class=num>{_fmt(d, 3)}</td><td class=num>{_fmt(z, 3)}</td>{t}</tr>")
    head = ("<tr><th>parameter</th><th>unit</th><th>A</th><th>B</th><th>B − A</th>"
            "<th>(B − A) / σ_B</th>" + ("<th>truth</th>" if truth else "") + "</tr>")
    return (f"<table>{head}{''.join(rows)}</table><p class=cap>Red: the parameter moved by "
            "more than 3σ of the later run — the added effect changed what it means.</p>")


def _stats_row(r: RunData, fraction: float) -> str:
    res = r.residuals
    mask = window_mask(res, fraction, r.calibration)
    rms, exp = stats.rms(res, mask), stats.expected_rms(res, mask)
    nis, _ = judged_nis(res, mask, r.calibration)
    gated = int(np.sum(mask & ~stats.accepted(res)))
    effects = ", ".join(estimated_effects(r.calibration, r.history)) or "(not recorded)"
    return (f"<tr><td>{_e(r.name)}</td><td>{_e(effects)}</td><td class=num>{rms[0]:.4f} / "
            f"{rms[1]:.4f}</td><td class=num>{exp[0]:.4f} / {exp[1]:.4f}</td>"
            f"<td class=num>{nis['mean']:.3f} ({nis['lower']:.3f} … {nis['upper']:.3f})</td>"
            f"<td class=num>{gated}</td></tr>")


def write_compare_report(out_dir: str | Path, a: RunData, b: RunData, truth: Any = None,
                         bag: Path | None = None, fraction: float = 0.5) -> Path:
    """Two runs of the model-discovery loop side by side; returns ``report.html``.

    Parameter differences in σ units, RMS and NIS before / after, and every residual
    figure with A and B as two panels on one scale.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cam = b.calibration.camera
    centre = (cam.cx, cam.cy)
    panels = [(f"A: {a.name}", a.residuals), (f"B: {b.name}", b.residuals)]
    tv = None
    if truth is not None and b.history is not None:
        tv = report.truth_values(b.history, b.calibration, truth)
        if a.history is not None:  # A's where both have it: the installation is in A's frame
            tv = {**tv, **report.truth_values(a.history, a.calibration, truth)}
    ea, eb = estimated_effects(a.calibration, a.history), estimated_effects(b.calibration,
                                                                             b.history)
    change = model_change(a.calibration.method, ea, b.calibration.method, eb)
    figs = _run_figures(out, panels, cam.width, cam.height, centre, fraction)
    for key, r in (("a", a), ("b", b)):
        if r.history is not None:
            figs.append(("params", f"Parameters over time, {key.upper()}: {r.name}",
                         report.plot_parameter_history(r.history, out / f"parameters_{key}.png",
                                                       tv)))
            figs.append(("nis", f"NIS over time, {key.upper()}: {r.name}",
                         report.plot_nis(r.history, out / f"nis_{key}.png")))
    body = [f"<p>{_e(change)}</p>",
            "<h2 id='before-after'>Residuals before / after</h2><table><tr><th>run</th>"
            "<th>estimated effects</th><th>RMS u / v, px</th><th>expected u / v, px</th>"
            "<th>NIS/dof (95 % band)</th><th>gated</th>"
            f"</tr>{_stats_row(a, fraction)}{_stats_row(b, fraction)}</table>",
            "<h2 id='params-diff'>Parameter differences</h2>", comparison_table(a, b, tv)]
    seen = set()
    for anchor, t, img in figs:
        cap = _CAPTIONS[anchor] if anchor not in seen else ""
        seen.add(anchor)
        body.append(_figure(f"{anchor}-{len(body)}", t, img, cap))
    body += ["<h2 id='provenance'>Provenance</h2>", "<h3>A</h3>",
             provenance_table(a.calibration, a.path, bag, a.residual_source, a.history),
             "<h3>B</h3>",
             provenance_table(b.calibration, b.path, bag, b.residual_source, b.history)]
    nav = [("before-after", "before / after"), ("params-diff", "parameters"),
           ("provenance", "provenance")]
    path = out / "report.html"
    path.write_text(_page(f"stellar_cal comparison: {a.name} → {b.name}", "".join(body), nav))
    return path

