"""The calibration as a Foxglove view: ``replay --viz VIZ.mcap``, the live node, one layout.

The same three channels carry the view everywhere: the ``calibrator`` node publishes them as
ROS topics (seen through ``foxglove_bridge``, or served by the node itself with the Foxglove
SDK's WebSocket server, parameter ``foxglove_port``), and :func:`write_viz` writes a filter
run's history and residuals onto them in an MCAP file (Foxglove SDK, ``foxglove-sdk``), every
message stamped with the data time.  All are ROS 2 messages in CDR with ``ros2msg`` schemas
(so ``ros2 bag play VIZ.mcap`` replays them into ROS too), encoded by :class:`ViewMessages`:

``/calibrator/view`` (``stellar_cal_msgs/CalibrationView``)
    every estimate with its ±1σ band (``parameters[i]``: ``name``, ``unit``, ``value``,
    ``sigma``, ``lo``, ``hi``) in display units (px, arcsec, deg/h, µg, ppm, ms), and the
    NIS: ``nis_frame`` (the update's NIS/dof, joint over its stars), ``nis_moving`` (the
    last :data:`MOVING` updates) with its 95 % χ² band ``nis_band_lo`` / ``nis_band_hi``,
    ``nis_window`` (the replay's statistic: second half of the data so far) and ``verdict``;
    built by :func:`view_fields`;
``/diagnostics`` (``diagnostic_msgs/DiagnosticArray``, 1 Hz of data time)
    the node's own; in the MCAP what it would have published at that time: WARN "model
    mismatch" with the same statistics (:class:`~stellar_cal_ros.methods.results.
    HalfWindowStats`, the texts of :data:`~stellar_cal_ros.methods.results.VERDICT_MESSAGES`);
``/calibrator/residual_field`` (``sensor_msgs/CompressedImage``, PNG, every ``field_period_s``
of data)
    :func:`residual_field`: the detector with the mean residual vector of the accepted stars
    of the last ``field_period_s`` in each cell of a grid, magnified, coloured by its size in
    σ of the mean (green < 2, orange < 4, red beyond): where on the detector, and when, the
    model fails.

:func:`layout` builds the Foxglove layout of these topics with the SDK's layout API; the file
``config/foxglove_layout.json`` is its output (``test_viz.py`` keeps them equal).  Rerun was
measured as the alternative (doc/visualization.md): its SDK wheel is 9x larger and writes
its own ``.rrd`` format, not MCAP.
"""

from __future__ import annotations

import io
import math
from collections.abc import Sequence
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

#: updates in the moving NIS mean
MOVING = 20
#: grid of the residual field (cells per image side)
GRID = 8
#: size of the residual-field image, px (a 40-px title band above a square detector)
IMAGE_PX = 640
TITLE_PX = 40
#: the view's topics (the node's names with its default name ``calibrator``)
TOPICS = {"view": "/calibrator/view", "diagnostics": "/diagnostics",
          "field": "/calibrator/residual_field"}
TYPES = {"view": "stellar_cal_msgs/msg/CalibrationView",
         "diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
         "field": "sensor_msgs/msg/CompressedImage"}
#: the parameters the layout plots, by panel: (title, [(parameter name, label)])
PLOTS = (("principal point, px", [("principal_point.cx", "cx"), ("principal_point.cy", "cy")]),
         ("focal length, px", [("focal_length.f", "f")]),
         ("installation, arcsec", [("installation.rx", "rx"), ("installation.ry", "ry"),
                                   ("installation.rz", "rz")]),
         ("gyro bias, deg/h", [("gyro_bias.bx", "bx"), ("gyro_bias.by", "by"),
                               ("gyro_bias.bz", "bz")]))
#: residual-field palette (the image is drawn in palette mode: 1 byte a pixel to encode)
_PALETTE = {"background": (18, 18, 24), "border": (120, 120, 130), "grid": (45, 45, 55),
            "green": (80, 200, 90), "orange": (240, 170, 40), "red": (235, 60, 60),
            "centre": (200, 200, 210), "star": (90, 90, 110), "title": (235, 235, 240),
            "subtitle": (180, 180, 190)}
_INK = {k: i for i, k in enumerate(_PALETTE)}


# ------------------------------------------------------------------------- message content
def parameter_estimates(names: Sequence[str], values, sigmas) -> list[dict[str, Any]]:
    """Each estimated scalar in its display unit with its ±1σ band (``ParameterEstimate``)."""
    from stellar_cal_ros.diagnosis.reliability import display_unit

    out = []
    for name, x, s in zip(names, values, sigmas, strict=True):
        unit, factor = display_unit(name)
        v, sd = float(x) * factor, float(s) * factor
        out.append({"name": name, "unit": unit, "value": v, "sigma": sd, "lo": v - sd,
                    "hi": v + sd})
    return out


def view_fields(names: Sequence[str], values, sigmas, updates: int,
                recent: Sequence[tuple[float, int]], cons: dict[str, Any]) -> dict[str, Any]:
    """The content of one ``CalibrationView`` (less its header).

    ``recent``: (NIS, dof) of the last updates, oldest first (the last :data:`MOVING` are
    used; the last one is ``nis_frame``); ``cons``: the run's consistency block so far
    (:func:`~stellar_cal_ros.methods.results.consistency`).
    """
    from stellar_cal_ros.methods.results import nis_band

    last = list(recent)[-MOVING:]
    s_nis = sum(n for n, _ in last)
    s_dof = sum(d for _, d in last)
    nan = math.nan
    lo, hi = nis_band(s_dof) if s_dof else (nan, nan)
    return {"parameters": parameter_estimates(names, values, sigmas), "updates": int(updates),
            "nis_frame": last[-1][0] / max(last[-1][1], 1) if last else nan,
            "nis_moving": s_nis / s_dof if s_dof else nan,
            "nis_band_lo": lo, "nis_band_hi": hi,
            "nis_window": float(cons.get("nis_per_dof", nan)),
            "verdict": str(cons.get("verdict", "no data"))}


class ViewMessages:
    """CDR bytes of the view's messages and their ``ros2msg`` schemas (rosbags' typestore).

    The node publishes these very bytes on ROS and on its Foxglove server; the replay
    writes them to the MCAP.  No rclpy needed.
    """

    def __init__(self) -> None:
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        from stellar_cal_ros.io.schemas import CALIBRATION_VIEW, CALIBRATION_VIEW_SCHEMA

        self.store = get_typestore(Stores.ROS2_JAZZY)
        self.store.register(get_types_from_msg(CALIBRATION_VIEW_SCHEMA, CALIBRATION_VIEW))
        self.schemas = {k: CALIBRATION_VIEW_SCHEMA if k == "view" else
                        self.store.generate_msgdef(t, ros_version=2)[0]
                        for k, t in TYPES.items()}
        self.T = self.store.types

    def _header(self, stamp_ns: int, frame_id: str):
        sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
        return self.T["std_msgs/msg/Header"](
            stamp=self.T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec),
            frame_id=frame_id)

    def _cdr(self, key: str, msg) -> bytes:
        return bytes(self.store.serialize_cdr(msg, TYPES[key]))

    def view(self, stamp_ns: int, frame_id: str, fields: dict[str, Any]) -> bytes:
        """A ``CalibrationView`` from :func:`view_fields`."""
        P = self.T["stellar_cal_msgs/msg/ParameterEstimate"]
        f = dict(fields, parameters=[P(**p) for p in fields["parameters"]])
        return self._cdr("view", self.T[TYPES["view"]](
            header=self._header(stamp_ns, frame_id), **f))

    def image(self, stamp_ns: int, frame_id: str, png: bytes) -> bytes:
        """A ``sensor_msgs/CompressedImage`` holding ``png``."""
        return self._cdr("field", self.T[TYPES["field"]](
            header=self._header(stamp_ns, frame_id), format="png",
            data=np.frombuffer(png, dtype=np.uint8)))

    def diagnostics(self, stamp_ns: int, level: int, name: str, message: str, hw: str,
                    values: dict[str, str]) -> bytes:
        """A ``DiagnosticArray`` of one status."""
        T = self.T
        status = T["diagnostic_msgs/msg/DiagnosticStatus"](
            level=level, name=name, message=message, hardware_id=hw,
            values=[T["diagnostic_msgs/msg/KeyValue"](key=k, value=str(v))
                    for k, v in values.items()])
        return self._cdr("diagnostics", T[TYPES["diagnostics"]](
            header=self._header(stamp_ns, ""), status=[status]))

    def channels(self, context, topics: dict[str, str] | None = None) -> dict[str, Any]:
        """The view's Foxglove channels in ``context`` (an MCAP file or a server).

        ``topics``: their names (default :data:`TOPICS`; the node passes its resolved ones).
        """
        import foxglove

        return {k: foxglove.Channel(topic, message_encoding="cdr", context=context,
                                    schema=foxglove.Schema(name=TYPES[k], encoding="ros2msg",
                                                           data=self.schemas[k].encode()))
                for k, topic in (topics or TOPICS).items()}


# ------------------------------------------------------------------------- residual field
def residual_field(res: dict[str, np.ndarray], t_end: float, period_s: float, t_first: float,
                   width: int, height: int) -> bytes | None:
    """PNG of the residual field of the accepted stars with ``t`` in (t_end − period, t_end].

    ``res``: residual-table columns (``t``, ``u``, ``v``, ``du``, ``dv``, ``s_uu``, ``s_vv``,
    ``nis``, ``gated``, :data:`~stellar_cal_ros.methods.results.RESIDUAL_COLUMNS`);
    ``t_first``: the run's first update (the title counts seconds from it).  None when the
    window holds no accepted star.  The one picture the node and the replay draw.
    """
    t = np.asarray(res["t"], float)
    m = ~np.asarray(res["gated"]).astype(bool) & (t > t_end - period_s) & (t <= t_end)
    n = int(m.sum())
    if not n:
        return None
    du, dv = np.asarray(res["du"], float)[m], np.asarray(res["dv"], float)[m]
    rms = math.sqrt(float(np.mean(du * du) + np.mean(dv * dv)))
    nis = float(np.sum(np.asarray(res["nis"], float)[m])) / (2 * n)
    a, b = t_end - t_first - period_s, t_end - t_first
    title = (f"residuals {a:.0f}-{b:.0f} s: {n} stars, RMS |duv| {rms:.3f} px, "
             f"NIS/dof {nis:.2f}")
    return residual_field_png(res, m, width, height, title)


def residual_field_png(res: dict[str, np.ndarray], mask: np.ndarray, width: int, height: int,
                       title: str) -> bytes:
    """PNG of the grid-mean residual vectors of the stars in ``mask`` (see the module)."""
    from PIL import Image, ImageDraw

    side, top, cell = IMAGE_PX, TITLE_PX, IMAGE_PX / GRID
    img = Image.new("P", (side, side + top), _INK["background"])
    img.putpalette([c for rgb in _PALETTE.values() for c in rgb])
    draw = ImageDraw.Draw(img)
    draw.rectangle([0, top, side - 1, side + top - 1], outline=_INK["border"])
    for k in range(1, GRID):
        draw.line([k * cell, top, k * cell, side + top - 1], fill=_INK["grid"])
        draw.line([0, top + k * cell, side, top + k * cell], fill=_INK["grid"])
    u, v = np.asarray(res["u"], float)[mask], np.asarray(res["v"], float)[mask]
    du, dv = np.asarray(res["du"], float)[mask], np.asarray(res["dv"], float)[mask]
    s = np.sqrt(0.5 * (np.asarray(res["s_uu"], float)[mask]
                       + np.asarray(res["s_vv"], float)[mask]))
    iu = np.clip((u * GRID / width).astype(int), 0, GRID - 1)
    iv = np.clip((v * GRID / height).astype(int), 0, GRID - 1)
    k = iu * GRID + iv  # cells in column-major order
    count = np.bincount(k, minlength=GRID * GRID)
    used = np.flatnonzero(count >= 3)
    c = count[used]
    mean = np.column_stack([np.bincount(k, du, GRID * GRID)[used] / c,
                            np.bincount(k, dv, GRID * GRID)[used] / c])
    length = np.hypot(mean[:, 0], mean[:, 1])
    z = length / (np.bincount(k, s, GRID * GRID)[used] / c / np.sqrt(c))
    typical = float(np.percentile(length, 80)) if len(used) else 1e-12
    gain = 0.4 * cell / max(typical, 1e-12)  # most arrows within 40 % of a cell
    cells = np.column_stack(np.divmod(used, GRID)).tolist()
    for (a, b), d, zz in zip(cells, (gain * mean).tolist(), z.tolist(), strict=True):
        x0, y0 = (a + 0.5) * cell, top + (b + 0.5) * cell
        shrink = min(1.0, 0.9 * cell / max(math.hypot(*d), 1e-12))  # outliers: clipped
        x1, y1 = x0 + d[0] * shrink, y0 + d[1] * shrink
        ink = _INK["green"] if zz < 2 else _INK["orange"] if zz < 4 else _INK["red"]
        draw.line([x0, y0, x1, y1], fill=ink, width=3)
        ang, arrow = math.atan2(y1 - y0, x1 - x0), math.hypot(x1 - x0, y1 - y0)
        head = min(10.0, 0.4 * arrow)
        for side_angle in (0.45, -0.45):  # the head's two strokes point back along the arrow
            draw.line([x1, y1, x1 - head * math.cos(ang + side_angle),
                       y1 - head * math.sin(ang + side_angle)], fill=ink, width=3)
        draw.ellipse([x0 - 2, y0 - 2, x0 + 2, y0 + 2], fill=_INK["centre"])
    draw.point(list(zip((u * side / width).tolist(), (top + v * side / height).tolist(),
                        strict=True)), fill=_INK["star"])
    draw.text((6, 4), title, fill=_INK["title"])
    draw.text((6, 20), f"arrow of 40 % of a cell = {typical:.3f} px (longer ones clipped at "
              "90 %); green < 2 sigma of the mean, orange < 4, red beyond",
              fill=_INK["subtitle"])
    buf = io.BytesIO()
    img.save(buf, format="PNG", compress_level=1)  # 1: ~4x faster to write than 6, ~1.3x larger
    return buf.getvalue()


# ------------------------------------------------------------------------- replay --viz
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


def write_viz(path: str | Path, history: dict[str, np.ndarray],
              residuals: dict[str, np.ndarray], calibration: Any, method: str,
              field_period_s: float = 30.0, noise: Any = None) -> dict[str, int]:
    """Write the view of one run to ``path`` (MCAP); returns the messages per topic.

    ``noise``: the run's :class:`~stellar_cal_ros.core.noise.NoiseScales`, so the view's
    verdict is the replay's (a ``--noise-scale star=K,rho=R`` run is judged under its ρ).
    """
    import foxglove

    from stellar_cal_ros.methods.results import VERDICT_MESSAGES, HalfWindowStats, consistency

    ctx = foxglove.Context()
    counts = dict.fromkeys(TOPICS, 0)
    enc = ViewMessages()
    imu_frame, st_frame = calibration.frames["imu"], calibration.frames["star_tracker"]
    with foxglove.open_mcap(str(path), allow_overwrite=True, context=ctx):
        ch = enc.channels(ctx)
        names = [k for k in history if not k.startswith("sigma.") and "." in k]
        t_h = np.asarray(history.get("t", ()), float)
        nis = np.asarray(history.get("nis", ()), float)
        dof = np.asarray(history.get("dof", ()), float).astype(int)
        stats = HalfWindowStats()
        frames = list(_frame_updates(residuals))
        k_frame = 0
        next_diag = t_h[0] if len(t_h) else 0.0
        cam = calibration.camera
        next_field = (t_h[0] + field_period_s) if len(t_h) else 0.0
        for i, t in enumerate(t_h):
            while k_frame < len(frames) and frames[k_frame].stamp <= t + 1e-9:
                stats.add(frames[k_frame])
                k_frame += 1
            cons = consistency(stats.current(), noise)
            fields = view_fields(names, [history[n][i] for n in names],
                                 [history["sigma." + n][i] for n in names], i + 1,
                                 list(zip(nis[max(0, i + 1 - MOVING):i + 1].tolist(),
                                          dof[max(0, i + 1 - MOVING):i + 1].tolist(),
                                          strict=True)), cons)
            ch["view"].log(enc.view(_ns(t), imu_frame, fields), log_time=_ns(t))
            counts["view"] += 1
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
                ch["diagnostics"].log(enc.diagnostics(
                    _ns(t), 1 if mismatch else 0, f"calibrator: {method} calibration", msg,
                    f"{imu_frame}+{st_frame}", values), log_time=_ns(t))
                counts["diagnostics"] += 1
                next_diag = t + 1.0
            if t >= next_field or i == len(t_h) - 1:
                png = residual_field(residuals, t, field_period_s, t_h[0], cam.width,
                                     cam.height) if len(residuals.get("t", ())) else None
                if png is not None:
                    ch["field"].log(enc.image(_ns(t), st_frame, png), log_time=_ns(t))
                    counts["field"] += 1
                next_field = t + field_period_s
    return counts


# ------------------------------------------------------------------------- layout
def layout():
    """The Foxglove layout of the view (``config/foxglove_layout.json``)."""
    import foxglove.layouts as fl

    view = TOPICS["view"]

    def plot(title: str, series: list) -> Any:
        return fl.PlotPanel(title=title, config=fl.PlotConfig(
            paths=series, show_legend=True, legend_display="floating", is_synced=True,
            x_axis_val="timestamp"))

    def band(name: str, label: str, color: str) -> list:
        p = f'{view}.parameters[:]{{name=="{name}"}}'
        return [fl.PlotSeries(value=f"{p}.value", label=label, color=color),
                fl.PlotSeries(value=f"{p}.lo", label=f"{label} -1σ", color=color,
                              line_style="dashed", line_size=0.6),
                fl.PlotSeries(value=f"{p}.hi", label=f"{label} +1σ", color=color,
                              line_style="dashed", line_size=0.6)]

    colors = ("#4e98e2", "#f5774d", "#61cbb4")
    estimates = [fl.SplitItem(content=plot(title, [s for k, (p, lab) in enumerate(items)
                                                   for s in band(p, lab, colors[k])]))
                 for title, items in PLOTS]
    nis = plot("NIS/dof (1 = the noise model; above the band: the model misses something)", [
        fl.PlotSeries(value=f"{view}.nis_frame", label="each update", color="#9a9a9a",
                      show_line=False),
        fl.PlotSeries(value=f"{view}.nis_moving", label=f"mean of {MOVING}", color="#4e98e2"),
        fl.PlotSeries(value=f"{view}.nis_band_lo", label="95 % band", color="#61cbb4",
                      line_style="dashed"),
        fl.PlotSeries(value=f"{view}.nis_band_hi", label="95 % band", color="#61cbb4",
                      line_style="dashed"),
        fl.PlotSeries(value=f"{view}.nis_window", label="run so far (replay's)",
                      color="#f5774d")])
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
