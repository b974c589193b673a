"""The calibration as a Foxglove view: ``replay --viz VIZ.mcap`` and the shipped layout.

:func:`write_viz` turns a filter run (its history and residual tables) into an MCAP file
written with the Foxglove SDK (``foxglove-sdk``), on these channels, all stamped with the
data time so Foxglove's timeline is the bag's:

``/stellar_cal/estimate`` (JSON, one per update)
    ``value.<effect>.<parameter>``, ``sigma...``, ``lo...`` / ``hi...`` (value ∓ σ) in
    display units (px, arcsec, deg/h, µg, ppm, ms), so a Plot panel draws each estimate in
    its ±1σ band;
``/stellar_cal/nis`` (JSON, one per update)
    ``frame`` (the update's NIS/dof, joint over its stars), ``moving`` (mean of the last
    :data:`MOVING` updates) and its χ² band ``band_lo`` / ``band_hi``, and ``window``, the
    run's NIS/dof so far (the replay's statistic: per star, second half of the data so far);
``/diagnostics`` (diagnostic_msgs/DiagnosticArray, CDR, 1 Hz of data time)
    what the live ``calibrator`` node would have published at that time: WARN "model
    mismatch" with the same statistics (:class:`~stellar_cal_ros.methods.results.
    HalfWindowStats`, the texts of :data:`~stellar_cal_ros.methods.results.VERDICT_MESSAGES`);
``/stellar_cal/residual_field`` (foxglove.CompressedImage, PNG, every ``field_period_s``)
    the detector with the mean residual vector of the accepted stars of the last
    ``field_period_s`` in each cell of a grid, magnified, coloured by its size in σ of the
    mean (green < 2, orange < 4, red beyond): where on the detector, and when, the model
    fails.

:func:`layout` builds the matching Foxglove layout with the SDK's layout API; the file
``config/foxglove_layout.json`` is its output (``test_viz.py`` keeps them equal).  Rerun was
measured as the alternative (doc/visualization.md): its SDK wheel is 9x larger and writes
its own ``.rrd`` format, not MCAP.
"""

from __future__ import annotations

import io
import math
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

#: updates in the moving NIS mean
MOVING = 20
#: grid of the residual field (cells per image side)
GRID = 8
#: size of the residual-field image, px
IMAGE_PX = 640
TOPICS = {"estimate": "/stellar_cal/estimate", "nis": "/stellar_cal/nis",
          "diagnostics": "/diagnostics", "field": "/stellar_cal/residual_field"}
#: the parameters the layout plots, by panel: (title, [(path under value., label)])
PLOTS = (("principal point, px", [("principal_point.cx", "cx"), ("principal_point.cy", "cy")]),
         ("focal length, px", [("focal_length.f", "f")]),
         ("installation, arcsec", [("installation.rx", "rx"), ("installation.ry", "ry"),
                                   ("installation.rz", "rz")]),
         ("gyro bias, deg/h", [("gyro_bias.bx", "bx"), ("gyro_bias.by", "by"),
                               ("gyro_bias.bz", "bz")]))


def _display(name: str) -> tuple[float, str]:
    from stellar_cal_ros.diagnosis.report import display_unit, parameter_unit

    return display_unit(name, parameter_unit(name))


def _nested(flat: dict[str, float]) -> dict[str, dict[str, float]]:
    out: dict[str, dict[str, float]] = {}
    for name, v in flat.items():
        eff, _, par = name.partition(".")
        out.setdefault(eff, {})[par] = v
    return out


def _num(x: float) -> float | None:
    """A number for JSON (None where not finite: JSON has no NaN)."""
    return float(x) if math.isfinite(x) else None


def _ns(t: float) -> int:
    return int(round(t * 1e9))


def _frame_updates(res: dict[str, np.ndarray]):
    """The residual table's frames as the update objects RunStats reads (per-star NIS)."""
    if not len(res.get("t", ())):
        return
    frame = np.asarray(res["frame"])
    cut = np.flatnonzero(np.diff(frame)) + 1
    for idx in np.split(np.arange(len(frame)), cut):
        acc = ~np.asarray(res["gated"][idx]).astype(bool)
        S = np.empty((len(idx), 2, 2))
        S[:, 0, 0], S[:, 1, 1] = res["s_uu"][idx], res["s_vv"][idx]
        S[:, 0, 1] = S[:, 1, 0] = res["s_uv"][idx]
        nis = np.asarray(res["nis"][idx], float)
        yield SimpleNamespace(
            stamp=float(res["t"][idx[0]]), accepted=acc, S=S,
            uv=np.column_stack([res["u"][idx], res["v"][idx]]),
            uv_pred=np.column_stack([res["u_pred"][idx], res["v_pred"][idx]]),
            nis_stars=nis, nis=float(nis[acc].sum()), dof=int(2 * acc.sum()))


def residual_field_png(res: dict[str, np.ndarray], mask: np.ndarray, width: int, height: int,
                       title: str) -> bytes:
    """PNG of the grid-mean residual vectors of the stars in ``mask`` (see the module)."""
    from PIL import Image, ImageDraw

    side = IMAGE_PX
    img = Image.new("RGB", (side, side + 40), (18, 18, 24))
    draw = ImageDraw.Draw(img)
    sx, sy = side / width, side / height
    cell = side / GRID
    draw.rectangle([0, 40, side - 1, side + 39], outline=(120, 120, 130))
    for k in range(1, GRID):
        draw.line([k * cell, 40, k * cell, side + 39], fill=(45, 45, 55))
        draw.line([0, 40 + k * cell, side, 40 + k * cell], fill=(45, 45, 55))
    u, v = np.asarray(res["u"], float)[mask], np.asarray(res["v"], float)[mask]
    du, dv = np.asarray(res["du"], float)[mask], np.asarray(res["dv"], float)[mask]
    s = np.sqrt(0.5 * (np.asarray(res["s_uu"], float) + np.asarray(res["s_vv"], float)))[mask]
    iu = np.clip((u * GRID / width).astype(int), 0, GRID - 1)
    iv = np.clip((v * GRID / height).astype(int), 0, GRID - 1)
    cells = []
    for a in range(GRID):
        for b in range(GRID):
            m = (iu == a) & (iv == b)
            if m.sum() >= 3:
                n = int(m.sum())
                mean = np.array([du[m].mean(), dv[m].mean()])
                z = float(np.hypot(*mean) / (np.mean(s[m]) / math.sqrt(n)))
                cells.append((a, b, mean, z, n))
    lengths = [float(np.hypot(*c[2])) for c in cells]
    typical = float(np.percentile(lengths, 80)) if lengths else 1e-12
    gain = 0.4 * cell / max(typical, 1e-12)  # most arrows within 40 % of a cell
    for a, b, mean, z, _n in cells:
        x0, y0 = (a + 0.5) * cell, 40 + (b + 0.5) * cell
        d = gain * mean
        d *= min(1.0, 0.9 * cell / max(float(np.hypot(*d)), 1e-12))  # outliers: clipped
        x1, y1 = x0 + d[0], y0 + d[1]
        color = (80, 200, 90) if z < 2 else (240, 170, 40) if z < 4 else (235, 60, 60)
        draw.line([x0, y0, x1, y1], fill=color, width=3)
        ang, length = math.atan2(y1 - y0, x1 - x0), math.hypot(x1 - x0, y1 - y0)
        head = min(10.0, 0.4 * length)
        for d in (0.45, -0.45):  # the head's two strokes point back along the arrow
            draw.line([x1, y1, x1 - head * math.cos(ang + d), y1 - head * math.sin(ang + d)],
                      fill=color, width=3)
        draw.ellipse([x0 - 2, y0 - 2, x0 + 2, y0 + 2], fill=(200, 200, 210))
    draw.point(list(zip((u * sx).tolist(), (40 + v * sy).tolist(), strict=True)),
               fill=(90, 90, 110))
    draw.text((6, 4), title, fill=(235, 235, 240))
    draw.text((6, 20), f"arrow of 40 % of a cell = {typical:.3f} px (longer ones clipped at "
              "90 %); green < 2 sigma of the mean, orange < 4, red beyond",
              fill=(180, 180, 190))
    buf = io.BytesIO()
    img.save(buf, format="PNG")
    return buf.getvalue()


class _Diagnostics:
    """``diagnostic_msgs/DiagnosticArray`` CDR messages (rosbags' Jazzy definitions)."""

    def __init__(self) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.store = get_typestore(Stores.ROS2_JAZZY)
        self.text = self.store.generate_msgdef("diagnostic_msgs/msg/DiagnosticArray",
                                               ros_version=2)[0]

    def encode(self, t_ns: int, level: int, name: str, message: str, hw: str,
               values: dict[str, str]) -> bytes:
        T = self.store.types
        sec, nsec = divmod(int(t_ns), 1_000_000_000)
        status = T["diagnostic_msgs/msg/DiagnosticStatus"](
            level=level, name=name, message=message, hardware_id=hw,
            values=[T["diagnostic_msgs/msg/KeyValue"](key=k, value=str(v))
                    for k, v in values.items()])
        header = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
            sec=sec, nanosec=nsec), frame_id="")
        msg = T["diagnostic_msgs/msg/DiagnosticArray"](header=header, status=[status])
        return bytes(self.store.serialize_cdr(msg, "diagnostic_msgs/msg/DiagnosticArray"))


def write_viz(path: str | Path, history: dict[str, np.ndarray],
              residuals: dict[str, np.ndarray], calibration: Any, method: str,
              field_period_s: float = 30.0) -> dict[str, int]:
    """Write the view of one run to ``path`` (MCAP); returns the messages per topic."""
    import foxglove
    from foxglove.channels import CompressedImageChannel
    from foxglove.messages import CompressedImage, Timestamp

    from stellar_cal_ros.methods.results import VERDICT_MESSAGES, HalfWindowStats, consistency

    ctx = foxglove.Context()
    counts = dict.fromkeys(TOPICS, 0)
    diag = _Diagnostics()
    with foxglove.open_mcap(str(path), allow_overwrite=True, context=ctx):
        est_ch = foxglove.Channel(TOPICS["estimate"], message_encoding="json", context=ctx)
        nis_ch = foxglove.Channel(TOPICS["nis"], message_encoding="json", context=ctx)
        diag_ch = foxglove.Channel(TOPICS["diagnostics"], message_encoding="cdr", context=ctx,
                                   schema=foxglove.Schema(
                                       name="diagnostic_msgs/msg/DiagnosticArray",
                                       encoding="ros2msg", data=diag.text.encode()))
        field_ch = CompressedImageChannel(TOPICS["field"], context=ctx)
        names = [k for k in history if not k.startswith("sigma.") and "." in k]
        scale = {n: _display(n)[0] for n in names}
        t_h = np.asarray(history.get("t", ()), float)
        nis = np.asarray(history.get("nis", ()), float)
        dof = np.maximum(np.asarray(history.get("dof", ()), float), 1)
        stats = HalfWindowStats()
        frames = list(_frame_updates(residuals))
        k_frame = 0
        next_diag = t_h[0] if len(t_h) else 0.0
        cam = calibration.camera
        t_res = np.asarray(residuals.get("t", ()), float)
        acc = ~np.asarray(residuals.get("gated", np.zeros(0, bool))).astype(bool)
        next_field = (t_h[0] + field_period_s) if len(t_h) else 0.0
        for i, t in enumerate(t_h):
            value = {n: float(history[n][i]) * scale[n] for n in names}
            sigma = {n: float(history["sigma." + n][i]) * scale[n] for n in names
                     if "sigma." + n in history}
            est_ch.log({"value": _nested({n: _num(x) for n, x in value.items()}),
                        "sigma": _nested({n: _num(x) for n, x in sigma.items()}),
                        "lo": _nested({n: _num(value[n] - s) for n, s in sigma.items()}),
                        "hi": _nested({n: _num(value[n] + s) for n, s in sigma.items()})},
                       log_time=_ns(t))
            counts["estimate"] += 1
            while k_frame < len(frames) and frames[k_frame].stamp <= t + 1e-9:
                stats.add(frames[k_frame])
                k_frame += 1
            cons = consistency(stats.current())
            lo_w = max(0, i + 1 - MOVING)
            s_dof = float(dof[lo_w:i + 1].sum())
            half = 1.959964 * math.sqrt(2.0 / s_dof)
            nis_ch.log({"frame": _num(nis[i] / dof[i]),
                        "moving": _num(nis[lo_w:i + 1].sum() / s_dof),
                        "band_lo": max(0.0, 1 - half), "band_hi": 1 + half,
                        "window": _num(cons["nis_per_dof"]), "verdict": cons["verdict"]},
                       log_time=_ns(t))
            counts["nis"] += 1
            if t >= next_diag:
                mismatch = cons["verdict"] == "model mismatch"
                msg = VERDICT_MESSAGES["model mismatch"] if mismatch else \
                    "consistent with the noise model so far"
                values = {"consistency.verdict": cons["verdict"],
                          "consistency.nis_per_dof": f"{cons['nis_per_dof']:.3f}",
                          "consistency.whiteness_p": f"{cons['whiteness_p']:.3g}",
                          "consistency.rms_px": "{:.4f} {:.4f}".format(*cons["rms_px"]),
                          "consistency.expected_rms_px": "{:.4f} {:.4f}".format(
                              *cons["expected_rms_px"])}
                diag_ch.log(diag.encode(_ns(t), 1 if mismatch else 0,
                                        f"calibrator: {method} calibration", msg,
                                        "imu_link+star_tracker_optical_frame", values),
                            log_time=_ns(t))
                counts["diagnostics"] += 1
                next_diag = t + 1.0
            if len(t_res) and (t >= next_field or i == len(t_h) - 1):
                m = acc & (t_res > t - field_period_s) & (t_res <= t)
                if m.sum():
                    rms = np.sqrt(np.mean(np.square(residuals["du"][m]))
                                  + np.mean(np.square(residuals["dv"][m])))
                    title = (f"residuals {t - t_h[0] - field_period_s:.0f}-"
                             f"{t - t_h[0]:.0f} s: {int(m.sum())} stars, RMS |duv| "
                             f"{rms:.3f} px, NIS/dof so far {cons['nis_per_dof']:.2f}")
                    png = residual_field_png(residuals, m, cam.width, cam.height, title)
                    sec, nsec = divmod(_ns(t), 1_000_000_000)
                    field_ch.log(CompressedImage(timestamp=Timestamp(sec, nsec),
                                                 frame_id="star_tracker_optical_frame",
                                                 data=png, format="png"), log_time=_ns(t))
                    counts["field"] += 1
                next_field = t + field_period_s
    return counts


def layout():
    """The Foxglove layout of the view (``config/foxglove_layout.json``)."""
    import foxglove.layouts as fl

    def plot(title: str, series: list) -> Any:
        return fl.PlotPanel(title=title, config=fl.PlotConfig(
            paths=series, show_legend=True, legend_display="floating", is_synced=True,
            x_axis_val="timestamp"))

    def band(path: str, label: str, color: str) -> list:
        t = TOPICS["estimate"]
        return [fl.PlotSeries(value=f"{t}.value.{path}", label=label, color=color),
                fl.PlotSeries(value=f"{t}.lo.{path}", label=f"{label} -1σ", color=color,
                              line_style="dashed", line_size=0.6),
                fl.PlotSeries(value=f"{t}.hi.{path}", label=f"{label} +1σ", color=color,
                              line_style="dashed", line_size=0.6)]

    colors = ("#4e98e2", "#f5774d", "#61cbb4")
    estimates = [fl.SplitItem(content=plot(title, [s for k, (p, lab) in enumerate(items)
                                                   for s in band(p, lab, colors[k])]))
                 for title, items in PLOTS]
    n = TOPICS["nis"]
    nis = plot("NIS/dof (1 = the noise model; above the band: the model misses something)", [
        fl.PlotSeries(value=f"{n}.frame", label="each update", color="#9a9a9a",
                      show_line=False),
        fl.PlotSeries(value=f"{n}.moving", label=f"mean of {MOVING}", color="#4e98e2"),
        fl.PlotSeries(value=f"{n}.band_lo", label="95 % band", color="#61cbb4",
                      line_style="dashed"),
        fl.PlotSeries(value=f"{n}.band_hi", label="95 % band", color="#61cbb4",
                      line_style="dashed"),
        fl.PlotSeries(value=f"{n}.window", label="run so far (replay's)", color="#f5774d")])
    image = fl.ImagePanel(title="residual field (mean residual per cell)",
                          config=fl.ImageConfig(image_mode=fl.ImageModeConfig(
                              image_topic=TOPICS["field"])))
    diagnostics = fl.SplitContainer(direction="column", items=[
        fl.SplitItem(content=fl.DiagnosticsSummaryPanel(config=fl.DiagnosticsSummaryConfig(
            topic_to_render=TOPICS["diagnostics"], sort_by_level=True))),
        fl.SplitItem(content=fl.DiagnosticsDetailPanel(config=fl.DiagnosticsDetailConfig(
            topic_to_render=TOPICS["diagnostics"])))])
    return fl.Layout(content=fl.SplitContainer(direction="row", items=[
        fl.SplitItem(proportion=3, content=fl.SplitContainer(
            direction="column", items=[*estimates, fl.SplitItem(content=nis)])),
        fl.SplitItem(proportion=2, content=fl.SplitContainer(direction="column", items=[
            fl.SplitItem(proportion=3, content=image),
            fl.SplitItem(proportion=2, content=diagnostics)]))]))


def layout_json() -> str:
    """:func:`layout` as the JSON Foxglove imports (indented, stable)."""
    import json

    return json.dumps(json.loads(layout().to_json()), indent=1, sort_keys=True) + "\n"
