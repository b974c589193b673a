"""The live view (issue 25): ``replay --viz`` writes the run as Foxglove shows it, and the
shipped layout reads exactly those topics.

The MCAP is read back with the ``mcap`` library (and ``mcap-ros2-support`` for
/diagnostics), independently of the Foxglove SDK that wrote it.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest
from sim_bags import simulated_bag

from stellar_cal_ros.cli import main
from stellar_cal_ros.io.calibration import load_calibration
from stellar_cal_ros.io.residuals import read_residuals

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def viz(tmp_path_factory):
    """A 120-s bag whose frames are stamped 3 ms early, calibrated without time_offset."""
    d = tmp_path_factory.mktemp("viz")
    bag, prior, _ = simulated_bag("psce_rotations", 120.0, 7, {"time_offset": 0.003})
    assert main(["replay", str(bag), "--method", "psce", "--prior", str(prior), "-o",
                 str(d / "r.yaml"), "--viz", str(d / "v.mcap"), "-q"]) == 0
    return d


def _messages(path: Path):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    out: dict[str, list] = {}
    with open(path, "rb") as fh:
        for _schema, channel, message, decoded in make_reader(
                fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
                    topics=["/diagnostics"]):
            out.setdefault(channel.topic, []).append((message.log_time, decoded))
    with open(path, "rb") as fh:
        for _schema, channel, message in make_reader(fh).iter_messages():
            if channel.topic != "/diagnostics":
                out.setdefault(channel.topic, []).append((message.log_time, message.data))
    return out


def test_replay_viz_holds_the_run_over_time(viz):
    msgs = _messages(viz / "v.mcap")
    hist = read_residuals(viz / "r.history.csv")
    cal = load_calibration(viz / "r.yaml")
    # one estimate and one NIS message per update, at the update's time, in display units
    est = msgs["/stellar_cal/estimate"]
    assert len(est) == len(hist["t"]) == len(msgs["/stellar_cal/nis"])
    assert [t for t, _ in est] == [int(round(t * 1e9)) for t in hist["t"]]
    last = json.loads(est[-1][1])
    assert last["value"]["principal_point"]["cx"] == pytest.approx(hist["principal_point.cx"][-1])
    arcsec = np.degrees(1.0) * 3600.0
    assert last["value"]["installation"]["ry"] == pytest.approx(
        hist["installation.ry"][-1] * arcsec)
    assert last["hi"]["installation"]["ry"] - last["lo"]["installation"]["ry"] == pytest.approx(
        2 * hist["sigma.installation.ry"][-1] * arcsec)
    # /diagnostics: what the node would say; at the end the run's own verdict
    diag = msgs["/diagnostics"]
    assert len(diag) >= 100  # 1 Hz of data time
    final = diag[-1][1].status[0]
    values = {kv.key: kv.value for kv in final.values}
    assert cal.extra["consistency"]["verdict"] == "model mismatch"
    assert values["consistency.verdict"] == "model mismatch" and final.level == 1
    assert float(values["consistency.nis_per_dof"]) == pytest.approx(
        cal.extra["consistency"]["nis_per_dof"], rel=0.03)
    nis = json.loads(msgs["/stellar_cal/nis"][-1][1])
    assert nis["window"] == pytest.approx(float(values["consistency.nis_per_dof"]), rel=1e-3)
    # the residual field: PNG images of the detector through the run
    from PIL import Image

    field = msgs["/stellar_cal/residual_field"]
    assert len(field) >= 4
    raw = field[-1][1]
    img = Image.open(io.BytesIO(raw[raw.find(b"\x89PNG"):]))
    assert img.size == (640, 680)
    pixels = np.asarray(img.convert("RGB")).reshape(-1, 3)
    red = np.sum((pixels[:, 0] > 200) & (pixels[:, 1] < 90))
    assert red > 50  # significant mean residuals drawn (the model misses the offset)


def test_the_shipped_layout_is_the_viz_layout_and_reads_its_topics(viz):
    from stellar_cal_ros.viz import TOPICS, layout_json

    text = (ROOT / "config" / "foxglove_layout.json").read_text()
    assert text == layout_json(), "regenerate config/foxglove_layout.json (viz.layout_json)"
    assert (viz / "v.layout.json").read_text() == text
    doc = json.loads(text)
    flat = json.dumps(doc)
    for topic in TOPICS.values():
        assert topic in flat, topic
    msgs = _messages(viz / "v.mcap")
    est = json.loads(msgs["/stellar_cal/estimate"][-1][1])
    # every estimate path the plots name exists in the messages
    import re

    for path in set(re.findall(r'"/stellar_cal/estimate\.([^"]+)"', flat)):
        node = est
        for key in path.split("."):
            node = node[key]
        assert isinstance(node, float), path
