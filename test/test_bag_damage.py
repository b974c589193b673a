"""Damaged bags: ``info`` names every damaged part; skip mode resynchronises on the next chunk."""

from __future__ import annotations

import dataclasses
import json
import re
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from bag_checks import (
    IMU_FIELDS,
    SCALARS,
    assert_same,
    join_stream,
    read_all,
    simulated_bag,
)

from stellar_cal_ros.cli import main
from stellar_cal_ros.errors import BagError
from stellar_cal_ros.io.bag import BagReader, BagWriter

ROOT = Path(__file__).resolve().parents[1]
ZEROED = (0.40, 0.55)  # fraction of the file zeroed


@pytest.fixture(scope="module")
def healthy(tmp_path_factory) -> Path:
    return simulated_bag(tmp_path_factory.mktemp("damage") / "sim.mcap", duration=120.0,
                         chunk_size=128 * 1024)


def _zeroed(src: Path, dst: Path, keep_summary: bool = True) -> tuple[Path, int, int]:
    data = bytearray(src.read_bytes())
    a, b = int(len(data) * ZEROED[0]), int(len(data) * ZEROED[1])
    data[a:b] = bytes(b - a)
    if not keep_summary:  # cut before the summary: a recording whose footer was never written
        # footer: opcode, length, summary start, summary offset start, crc, then the magic
        summary_start = struct.unpack_from("<Q", data, len(data) - 8 - 4 - 8 - 8)[0]
        assert 0 < summary_start < len(data)
        del data[summary_start:]
    dst.write_bytes(bytes(data))
    return dst, a, b


def _lost_chunks(healthy: Path, a: int, b: int) -> list:
    """Chunk index entries of the healthy file that overlap the zeroed bytes [a, b)."""
    with BagReader(healthy) as r:
        chunks = r._src.summary.chunk_indexes
    return [c for c in chunks if c.offset < b and c.offset + c.length > a]


def _gone(log_time_ns: np.ndarray, lost: list) -> np.ndarray:
    """Which messages (by log time) the lost chunks held."""
    gone = np.zeros(len(log_time_ns), bool)
    for c in lost:
        gone |= (log_time_ns >= c.start) & (log_time_ns <= c.end)
    return gone


def _info(bag: Path, capsys) -> tuple[int, list[str]]:
    rc = main(["info", str(bag)])
    return rc, capsys.readouterr().out.splitlines()


def test_info_healthy_bag(healthy: Path, capsys) -> None:
    rc, out = _info(healthy, capsys)
    assert rc == 0 and out[-1].startswith("integrity: every chunk")
    assert "120.000 s, 6 topics (mcap)" in out[0]


def test_info_names_each_damaged_chunk(healthy: Path, tmp_path: Path, capsys) -> None:
    bag, a, b = _zeroed(healthy, tmp_path / "zeroed.mcap")
    lost = _lost_chunks(healthy, a, b)
    rc, out = _info(bag, capsys)
    damaged = [line for line in out if line.startswith("DAMAGED") and "no message lost" not in line]
    elsewhere = [line for line in out if line.startswith("DAMAGED") and line not in damaged]
    assert rc == 1 and len(lost) >= 2
    assert len(damaged) == len(lost), "\n".join(out)
    assert all("outside the chunks" in line for line in elsewhere)  # e.g. a message index
    t0 = BagReader(healthy).start_ns
    for line, c in zip(damaged, sorted(lost, key=lambda c: c.offset), strict=True):
        n = len(BagReader(healthy)._src.summary.chunk_indexes)
        assert f"chunk {c.number}/{n} at byte {c.offset}:" in line
        assert f"lost log time {(c.start - t0) * 1e-9:.3f}-{(c.end - t0) * 1e-9:.3f} s" in line
        assert "/imu/data" in line and "/star_tracker/stars" in line


def test_info_without_summary_and_bad_crc(healthy: Path, tmp_path: Path, capsys) -> None:
    bag, a, _ = _zeroed(healthy, tmp_path / "nosummary.mcap", keep_summary=False)
    rc, out = _info(bag, capsys)
    damaged = [line for line in out if line.startswith("DAMAGED")]
    assert rc == 1 and damaged
    assert any("invalid record opcode 0x00" in line and "lost log time" in line
               for line in damaged), "\n".join(out)
    # one flipped byte in an uncompressed chunk: decompression cannot notice, the CRC does
    content = read_all(BagReader(healthy))
    plain = tmp_path / "plain.mcap"
    with BagWriter(plain, compression="none", chunk_size=128 * 1024) as w:
        w.write_imu(content["imu"])
    data = bytearray(plain.read_bytes())
    data[len(data) // 2] ^= 0x01
    plain.write_bytes(bytes(data))
    rc, out = _info(plain, capsys)
    assert rc == 1 and sum("chunk CRC mismatch" in line for line in out) == 1


@pytest.mark.parametrize("keep_summary", [True, False], ids=["summary", "no_summary"])
def test_skip_resynchronises_after_the_damage(healthy: Path, tmp_path: Path,
                                              keep_summary: bool) -> None:
    bag, a, b = _zeroed(healthy, tmp_path / "z.mcap", keep_summary)
    lost = _lost_chunks(healthy, a, b)
    full = read_all(BagReader(healthy))["imu"]
    gone = _gone(full.log_time_ns, lost)
    assert 0.1 < gone.mean() < 0.3
    with BagReader(bag) as r, pytest.raises(BagError, match="truncated or corrupt"):
        r.read_imu()
    with BagReader(bag, on_error="skip") as r:
        with pytest.warns(UserWarning, match="reading goes on with the next valid chunk"):
            imu = r.read_imu()
        assert r.truncated and r.problems
        blocks = list(r.stream())
    kept = type(full)(full.stamp_ns[~gone], full.angular_velocity[~gone],
                      full.linear_acceleration[~gone], full.frame_id, full.log_time_ns[~gone],
                      full.angular_velocity_covariance, full.linear_acceleration_covariance)
    assert_same(imu, kept, IMU_FIELDS, "imu")
    assert_same(join_stream(blocks)["imu"], kept, IMU_FIELDS, "stream imu")


def test_replay_on_error_skip_keeps_the_chunks_after_the_damage(healthy: Path,
                                                                tmp_path: Path) -> None:
    bag, a, b = _zeroed(healthy, tmp_path / "z.mcap")
    prior = healthy.parent / "sim.prior.yaml"
    cmd = [sys.executable, "-m", "stellar_cal_ros", "replay", str(bag), "--method", "psce",
           "--prior", str(prior), "-o", str(tmp_path / "r.yaml"), "-q", "--on-error", "skip"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    # the reader's warnings counted in the one data quality line (H252: they were printed)
    assert "reading goes on with the next valid chunk" not in proc.stderr, proc.stderr
    said = [ln for ln in proc.stdout.splitlines() if "damaged or truncated parts" in ln]
    assert len(said) == 1 and "the reader's" in said[0], proc.stdout
    frames = int(re.search(r"frames=(\d+)", proc.stdout).group(1))
    assert frames > 0.7 * 240  # 2 Hz over 120 s, about a sixth lost (was 40 % kept)
    # the result file records what was lost (coord: nothing): each lost chunk's log time,
    # and exactly the IMU messages of the chunks kept
    dq = yaml.safe_load((tmp_path / "r.yaml").read_text())["data_quality"]
    lost = _lost_chunks(healthy, a, b)
    gone = _gone(read_all(BagReader(healthy))["imu"].log_time_ns, lost)
    assert dq["messages_read"]["imu"] == int((~gone).sum()), dq
    received = int(re.search(r"frames_received=(\d+)", proc.stdout).group(1))
    assert dq["messages_read"]["frames"] == received and dq["messages_skipped"] == 0
    assert dq["bag_parts_lost"] == len(dq["parts_lost"]) >= len(lost), dq
    t0 = BagReader(healthy).start_ns
    for c in lost:
        assert sum(f"lost log time {(c.start - t0) * 1e-9:.3f}-{(c.end - t0) * 1e-9:.3f} s"
                   in line for line in dq["parts_lost"]) == 1, (c, dq["parts_lost"])
    assert dq["seconds_read"] == pytest.approx(120.0, abs=0.1)


def test_info_checks_the_data_section_crc(healthy: Path, tmp_path: Path, capsys) -> None:
    """A file written by the mcap library with a data CRC, damaged outside every chunk."""
    from mcap.writer import CompressionType, Writer

    from stellar_cal_ros.io import cdr
    from stellar_cal_ros.io.bag import IMU_SCHEMA

    imu = read_all(BagReader(healthy))["imu"]
    _, size, encode = cdr.imu_encoder(imu)
    raw = encode(np.arange(len(imu))).tobytes()
    path = tmp_path / "crc.mcap"
    with open(path, "wb") as fh:
        w = Writer(fh, chunk_size=64 * 1024, compression=CompressionType.ZSTD,
                   enable_data_crcs=True)
        w.start(profile="ros2", library="test")
        cid = w.register_channel("/imu/data", "cdr",
                                 w.register_schema("sensor_msgs/msg/Imu", "ros2msg",
                                                   IMU_SCHEMA.encode()))
        for k, t in enumerate(imu.stamp_ns.tolist()):
            w.add_message(cid, log_time=t, data=raw[k * size:(k + 1) * size], publish_time=t)
        w.finish()
    # the data CRC is computed as the mcap library does (exit 1 only for the missing stars)
    assert _info(path, capsys)[1][-1].startswith("integrity: every chunk")
    with BagReader(path) as r:
        ci = sorted(r._src.summary.chunk_indexes, key=lambda c: c.offset)[0]
    data = bytearray(path.read_bytes())
    data[ci.offset + ci.length + 20] ^= 0xFF  # inside the first chunk's message index
    path.write_bytes(bytes(data))
    rc, out = _info(path, capsys)
    damaged = [line for line in out if line.startswith("DAMAGED")]
    assert rc == 1 and len(damaged) == 1 and "data section CRC mismatch" in damaged[0]
    with BagReader(path) as r:  # the damaged index is not trusted, the records are walked
        np.testing.assert_array_equal(r.read_imu().stamp_ns, imu.stamp_ns)


# ------------------------------------------------ diagnose / discover / batch / twin, skip
QUICK = ["--workers", "0", "--no-plots", "--noise", "stated", "--candidates",
         "time_offset,radial_k3"]
#: what a diagnosis decides (its terminal lines aside): the same from the same data
DECISIONS = ("recommendation", "candidates", "unexplained", "clock_change",
             "installation_step", "remainder")


def _cli(*argv: str, check: bool = True) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, "-m", "stellar_cal_ros", *argv], capture_output=True,
                          text=True, timeout=900, cwd=ROOT)
    assert proc.returncode == 0 or not check, proc.stderr[-3000:]
    return proc


def _diagnosis(prior: Path, bag: Path, out: Path, *extra: str) -> tuple[dict, str]:
    proc = _cli("diagnose", str(bag), "--calibration", str(prior), "--method", "psce",
                "-o", str(out), *QUICK, *extra)
    return json.loads((out / "diagnosis.json").read_text()), proc.stdout


def _kept(series, keep):
    """The messages of ``series`` whose log time (ns) ``keep`` keeps (a mask of it)."""
    keep = keep(np.asarray(series.log_time_ns))
    arrays = {f.name: v[keep] for f in dataclasses.fields(series)
              if isinstance(v := getattr(series, f.name), np.ndarray) and v.shape[:1] == keep.shape}
    return dataclasses.replace(series, **arrays)


def _written(healthy: Path, keep, path: Path) -> Path:
    """A bag of the healthy bag's messages whose log time ``keep`` keeps (what a read past
    damage should hold: the intact parts alone)."""
    content = read_all(BagReader(healthy))
    with BagWriter(path, chunk_size=128 * 1024) as w:
        w.write_imu(_kept(content["imu"], keep))
        w.write_star_frames([f for f in content["stars"] if keep(np.array([f.log_time_ns]))[0]])
        w.write_navsat(_kept(content["fix"], keep))
        for role, topic in SCALARS.items():
            w.write_scalar(_kept(content[role], keep), topic,
                           kind="pressure" if role == "pressure" else "temperature")
    return path


def _decisions(d: dict) -> dict:
    return {k: d.get(k) for k in DECISIONS}


def test_diagnose_on_error_skip_reads_past_a_hole_and_says_so(healthy: Path,
                                                              tmp_path: Path) -> None:
    """diagnose stopped at damage (no --on-error).  With skip it diagnoses what the bag holds,
    records the loss in diagnosis.json (bag_losses, first data_quality line) and prints it in
    one line; the hole (about 18 s of IMU and frames, mid-bag) is a gap, not data: no test
    fires on it, the decisions are the healthy bag's (nothing missing, no clock change, no
    attitude step)."""
    bag, a, b = _zeroed(healthy, tmp_path / "sim_hole.mcap")
    prior = healthy.parent / "sim.prior.yaml"
    proc = subprocess.run([sys.executable, "-m", "stellar_cal_ros", "diagnose", str(bag),
                           "--calibration", str(prior), "--method", "psce", "-o",
                           str(tmp_path / "strict"), *QUICK],
                          capture_output=True, text=True, timeout=900, cwd=ROOT)
    assert proc.returncode == 1 and "--on-error skip" in proc.stderr.splitlines()[-1]
    hole, text = _diagnosis(prior, bag, tmp_path / "hole", "--on-error", "skip")
    whole, _ = _diagnosis(prior, healthy, tmp_path / "whole")
    lost = _lost_chunks(healthy, a, b)
    gone = _gone(read_all(BagReader(healthy))["imu"].log_time_ns, lost)
    bl = hole["bag_losses"]
    assert bl["bag_parts_lost"] == len(bl["parts_lost"]) >= len(lost) and \
        bl["messages_skipped"] == 0, bl
    assert bl["messages_read"]["imu"] == int((~gone).sum()), bl
    assert hole["data_quality"][0].startswith(f"{bl['bag_parts_lost']} damaged or truncated")
    said = [ln for ln in text.splitlines() if "damaged or truncated parts" in ln]
    assert len(said) == 1 and said[0].startswith("data quality first: "), text
    assert "bag_losses" not in whole  # a whole bag's diagnosis: no such key
    assert _decisions(hole)["recommendation"] == _decisions(whole)["recommendation"]
    for d in (hole, whole):
        assert not d["unexplained"], d["unexplained"]
        assert not [c for c in d["candidates"] if c["significant"]]
    assert hole["clock_change"] is None or not hole["clock_change"].get("significant"), \
        hole["clock_change"]
    assert hole["installation_step"] is None or not hole["installation_step"].get(
        "significant"), hole["installation_step"]


def test_diagnose_of_a_bag_cut_at_half_is_that_of_its_first_half(healthy: Path,
                                                                   tmp_path: Path) -> None:
    """A recording cut at half (power lost: no summary, no footer) read with skip is the
    first half of the bag: its diagnosis decides (and computes) what the diagnosis of a bag
    of that first half alone does."""
    with BagReader(healthy) as r:
        chunks = sorted(r._src.summary.chunk_indexes, key=lambda c: c.offset)
    cut_chunk = chunks[len(chunks) // 2]
    raw = healthy.read_bytes()
    cut = tmp_path / "sim_cut.mcap"
    cut.write_bytes(raw[:cut_chunk.offset])
    content = read_all(BagReader(healthy))
    end = max(c.end for c in chunks[:len(chunks) // 2])
    first = _written(healthy, lambda t: t <= end, tmp_path / "sim_first.mcap")
    prior = healthy.parent / "sim.prior.yaml"
    halved, _ = _diagnosis(prior, cut, tmp_path / "cut", "--on-error", "skip")
    alone, _ = _diagnosis(prior, first, tmp_path / "first")
    assert halved["bag_losses"]["bag_parts_lost"] == 1 and "bag_losses" not in alone
    assert halved["bag_losses"]["seconds_read"] == pytest.approx(
        (content["imu"].stamp_ns[content["imu"].log_time_ns <= end][-1]
         - content["imu"].stamp_ns[0]) * 1e-9)
    assert _decisions(halved) == _decisions(alone)
    assert halved["counts"] == alone["counts"]
    assert halved["residual_rms_px"] == alone["residual_rms_px"]


def test_twin_on_error_skip_renders_what_the_bag_holds_and_says_what_was_lost(
        healthy: Path, tmp_path: Path) -> None:
    """twin stopped at damage (no --on-error); with skip it re-renders the messages read
    (the IMU of the chunks kept, exactly) and says in one line what was lost."""
    bag, a, b = _zeroed(healthy, tmp_path / "z.mcap")
    prior = healthy.parent / "sim.prior.yaml"
    proc = _cli("twin", str(bag), "--calibration", str(prior), "-o", str(tmp_path / "t.mcap"),
                "--on-error", "skip")
    gone = _gone(read_all(BagReader(healthy))["imu"].log_time_ns, _lost_chunks(healthy, a, b))
    assert f", {int((~gone).sum())} IMU samples" in proc.stdout, proc.stdout
    said = [ln for ln in proc.stdout.splitlines() if "damaged or truncated parts" in ln]
    assert len(said) == 1 and said[0].startswith("data quality: "), proc.stdout
    assert len(read_all(BagReader(tmp_path / "t.mcap"))["imu"]) == int((~gone).sum())


#: a batch result's keys of a read past damage (what was read and lost: not the fit's)
LOSS_KEYS = ("bag_parts_lost", "messages_skipped", "parts_lost", "seconds_read",
             "messages_read")


def _fit(result: Path) -> dict:
    """A batch result without what differs between two bags of the same messages."""
    doc = yaml.safe_load(result.read_text())
    for key in ("stamp", "provenance", "covariance_file"):
        doc.pop(key)
    doc["data_quality"] = {k: v for k, v in doc["data_quality"].items() if k not in LOSS_KEYS}
    return doc


@pytest.mark.parametrize("damage", ["hole", "cut"])
@pytest.mark.parametrize("method", ["acf", "bundle"])
def test_batch_on_error_skip_fits_the_intact_parts_and_says_the_loss_once(
        healthy: Path, tmp_path: Path, damage: str, method: str) -> None:
    """``batch --on-error skip`` (H239) on a bag with a hole mid-bag (zeroed bytes) or cut
    at half (inside a chunk, no summary) decides what it decides on a bag of the intact
    chunks' messages alone: the same fit, number for number, or the same refusal (acf across
    the hole: its gyro chain cannot bridge the 20 s gap); what was read is recorded.  The
    loss is said once: in the ``data quality`` line, which counts the reader's warnings
    about it, or in the refusal's one line; nothing else on stderr (main printed the
    reader's 3 warnings before the line: no summary, the damaged part, the part met again;
    5-7 across the hole; H252).  ``stellar-cal -v`` prints them, one line each."""
    with BagReader(healthy) as r:
        chunks = r._src.summary.chunk_indexes
    if damage == "hole":
        bag, a, b = _zeroed(healthy, tmp_path / "hole.mcap")
        lost = _lost_chunks(healthy, a, b)
    else:
        raw = healthy.read_bytes()
        bag = tmp_path / "cut.mcap"
        bag.write_bytes(raw[:len(raw) // 2])
        lost = [c for c in chunks if c.offset + c.length > len(raw) // 2]
    assert 0 < len(lost) < len(chunks)
    intact = _written(healthy, lambda t: ~_gone(t, lost), tmp_path / "intact.mcap")
    prior = healthy.parent / "sim.prior.yaml"
    run = [method, "--prior", str(prior), "-q"]
    proc = _cli("batch", str(bag), "--method", *run, "-o", str(tmp_path / "skip.yaml"),
                "--on-error", "skip", check=False)
    alone = _cli("batch", str(intact), "--method", *run, "-o", str(tmp_path / "intact.yaml"),
                 check=False)
    assert proc.returncode == alone.returncode == (damage == "hole" and method == "acf"), \
        proc.stderr[-2000:] + alone.stderr[-2000:]
    if alone.returncode:  # the same refusal, in one line that says the damage read past
        err = [ln for ln in proc.stderr.splitlines() if ln.strip()]
        assert len(err) == 1 and "gap" in err[0], proc.stderr
        why = alone.stderr.strip().replace(str(intact), str(bag))
        assert err[0].startswith(why + f" (read past damage in {bag}: the reader's "), err[0]
        return
    assert _fit(tmp_path / "skip.yaml") == _fit(tmp_path / "intact.yaml")
    assert proc.stdout.splitlines()[0] == alone.stdout.splitlines()[0]  # frames, stars, RMS
    content = read_all(BagReader(intact))
    dq = yaml.safe_load((tmp_path / "skip.yaml").read_text())["data_quality"]
    assert dq["messages_read"] == {"imu": len(content["imu"]), "frames": len(content["stars"])}
    assert dq["bag_parts_lost"] == len(dq["parts_lost"]) >= 1 and dq["messages_skipped"] == 0
    said = [ln for ln in proc.stdout.splitlines() if "damaged or truncated parts" in ln]
    assert len(said) == 1 and said[0].startswith(f"data quality: {dq['bag_parts_lost']} "), \
        proc.stdout
    held = re.search(r"the reader's (\d+) warnings? about the damage counted here", said[0])
    assert held and int(held.group(1)) >= 1, said[0]
    assert not [ln for ln in proc.stderr.splitlines() if "warning" in ln.lower()], proc.stderr
    if damage == "cut" and method == "acf":  # -v: the reader's warnings as they come
        loud = _cli("-v", "batch", str(bag), "--method", *run, "-o",
                    str(tmp_path / "loud.yaml"), "--on-error", "skip")
        warned = [ln for ln in loud.stderr.splitlines()
                  if ln.startswith("stellar-cal batch: warning: ")]
        assert len(warned) == int(held.group(1)), loud.stderr
        assert "the reader's" not in loud.stdout


def test_a_cut_bag_read_without_skip_is_refused_in_one_line(healthy: Path,
                                                            tmp_path: Path) -> None:
    """A recording cut inside a chunk (no summary) read without ``--on-error skip``: the
    refusal is the one stderr line, naming ``--on-error skip``; the reader's "no summary"
    warning is not printed before it (it was, as a second line, until this change: the scan
    that the warning announced then stopped at the damage)."""
    raw = healthy.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(raw[:len(raw) // 2])
    prior = healthy.parent / "sim.prior.yaml"
    proc = _cli("replay", str(cut), "--method", "psce", "--prior", str(prior), "-q",
                "-o", str(tmp_path / "r.yaml"), check=False)
    err = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode != 0
    assert len(err) == 1, proc.stderr
    assert "--on-error skip" in err[0] and "no summary" not in err[0], err[0]
