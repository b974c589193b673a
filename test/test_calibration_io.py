"""Calibration YAML: reference files, round trips, malformed files, unknown keys."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import refdata
import yaml

from stellar_cal_ros.errors import CalibrationFileError
from stellar_cal_ros.io.calibration import (
    Calibration,
    calibration_from_dict,
    calibration_to_dict,
    load_calibration,
    save_calibration,
)

DATA = refdata.DATA
REFERENCE = refdata.files("*.prior.yaml") + refdata.files("*.truth.yaml")
needs_data = refdata.needs()


def _doc(path: Path) -> dict:
    return yaml.safe_load(path.read_text())


@needs_data
@pytest.mark.parametrize("path", REFERENCE, ids=lambda p: p.name)
def test_reference_files_load_and_round_trip(path: Path, tmp_path: Path) -> None:
    cal = load_calibration(path)
    doc = _doc(path)
    assert cal.method == doc["method"]
    assert cal.camera.width == doc["camera"]["image_width"]
    np.testing.assert_array_equal(
        cal.installation.as_quat(), doc["installation"]["quaternion_xyzw"]
    )
    np.testing.assert_array_equal(cal.gyro_bias, doc["gyro"]["bias"])
    np.testing.assert_array_equal(cal.gyro_error_matrix.ravel(), doc["gyro"]["error_matrix"])
    out = tmp_path / "out.yaml"
    save_calibration(cal, out)
    again = load_calibration(out)
    assert again == cal
    new = _doc(out)
    for key, value in doc.items():  # every key the reference file has comes back unchanged
        if key == "camera":
            for ck, cv in value.items():
                assert new["camera"][ck] == cv, ck
        else:
            assert new[key] == value, key
    assert calibration_from_dict(calibration_to_dict(cal)) == cal


def test_prior_sigma_layout(reference_data) -> None:
    cal = load_calibration(reference_data / "psce_ideal_900s.prior.yaml")
    assert len(cal.sigma["installation"]["rotation_vector"]) == 3
    assert cal.sigma["camera"]["distortion_coefficients"]["cols"] == 5
    assert cal.sigma["time_offset"] == pytest.approx(0.05)


def test_effects_of_sky_truth(reference_data) -> None:
    cal = load_calibration(reference_data / "psce_sky_900s.truth.yaml")
    assert cal.effects["refraction"]["humidity"] == 0.5
    assert set(cal.effects) == {"aberration", "refraction", "proper_motion"}


def _minimal() -> dict:
    return {
        "format": "stellar_cal/1",
        "camera": {
            "image_width": 1024,
            "image_height": 1024,
            "camera_matrix": {
                "rows": 3,
                "cols": 3,
                "data": [4000.0, 0, 511.5, 0, 4000.0, 511.5, 0, 0, 1],
            },
            "distortion_model": "plumb_bob",
            "distortion_coefficients": {"rows": 1, "cols": 5, "data": [0.1, 0, 0, 0, 0]},
        },
        "installation": {"quaternion_xyzw": [0.0, 0.0, 0.0, 1.0]},
        "gyro": {"bias": [1e-7, 0.0, 0.0]},
    }


def test_optional_blocks_default(tmp_path: Path) -> None:
    cal = calibration_from_dict(_minimal())
    assert cal.time_offset == 0.0 and cal.effects == {} and cal.sigma == {}
    np.testing.assert_array_equal(cal.accel_bias, np.zeros(3))
    np.testing.assert_array_equal(cal.gyro_error_matrix, np.zeros((3, 3)))
    assert cal.frames == {"imu": "imu_link", "star_tracker": "star_tracker_optical_frame"}
    save_calibration(cal, tmp_path / "c.yaml")
    assert load_calibration(tmp_path / "c.yaml") == cal


def test_unknown_keys_preserved(tmp_path: Path) -> None:
    d = _minimal()
    d["future_block"] = {"a": [1.0, 2.0], "b": "text"}
    d["effects"] = {"new_effect_v2": {"scale": 1.5}}
    cal = calibration_from_dict(d)
    assert cal.extra == {"future_block": {"a": [1.0, 2.0], "b": "text"}}
    save_calibration(cal, tmp_path / "c.yaml")
    doc = _doc(tmp_path / "c.yaml")
    assert doc["future_block"] == d["future_block"]
    assert doc["effects"] == {"new_effect_v2": {"scale": 1.5}}
    assert load_calibration(tmp_path / "c.yaml") == cal


def test_error_matrix_as_nested_list() -> None:
    d = _minimal()
    d["gyro"]["error_matrix"] = [[1e-4, 0, 0], [0, 2e-4, 0], [0, 0, 3e-4]]
    cal = calibration_from_dict(d)
    np.testing.assert_array_equal(np.diag(cal.gyro_error_matrix), [1e-4, 2e-4, 3e-4])


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    return p


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(CalibrationFileError, match="not found"):
        load_calibration(tmp_path / "nope.yaml")


def test_yaml_syntax_error(tmp_path: Path) -> None:
    p = _write(tmp_path, "format: stellar_cal/1\ncamera: {image_width: 1024\n  gyro: [\n")
    with pytest.raises(CalibrationFileError, match="YAML syntax error"):
        load_calibration(p)


def test_empty_file(tmp_path: Path) -> None:
    with pytest.raises(CalibrationFileError, match="empty"):
        load_calibration(_write(tmp_path, ""))


@pytest.mark.parametrize(
    ("mutate", "match"),
    [
        (lambda d: d.update(format="stellar_cal/2"), "format"),
        (lambda d: d.pop("format"), "format"),
        (lambda d: d.pop("camera"), "camera"),
        (lambda d: d.pop("installation"), "installation"),
        (lambda d: d.pop("gyro"), "gyro"),
        (lambda d: d["gyro"].update(bias=[1.0, 2.0]), "gyro.bias"),
        (lambda d: d["gyro"].update(error_matrix=[0.0] * 8), "gyro.error_matrix"),
        (lambda d: d["installation"].update(quaternion_xyzw=[0, 0, 1]), "quaternion"),
        (lambda d: d["installation"].update(quaternion_xyzw=[0, 0, 0, 0]), "norm"),
        (lambda d: d.update(time_offset="soon"), "time_offset"),
        (lambda d: d["camera"]["distortion_coefficients"].update(data=[0.0] * 4), "camera"),
        (lambda d: d.update(effects=[1, 2]), "effects"),
        (lambda d: d.update(sigma={"installation": {"rotation_vector": [1.0]}}), "rotation_vector"),
    ],
)
def test_malformed_content(tmp_path: Path, mutate, match: str) -> None:
    d = _minimal()
    mutate(d)
    p = _write(tmp_path, yaml.safe_dump(d))
    with pytest.raises(CalibrationFileError, match=match):
        load_calibration(p)


def test_not_a_mapping(tmp_path: Path) -> None:
    with pytest.raises(CalibrationFileError, match="mapping"):
        load_calibration(_write(tmp_path, "- 1\n- 2\n"))


def test_save_is_atomic_and_keeps_old_file_on_failure(tmp_path: Path, monkeypatch) -> None:
    cal = calibration_from_dict(_minimal())
    target = tmp_path / "result.yaml"
    save_calibration(cal, target)
    before = target.read_text()

    def boom(*_a, **_k):
        raise OSError("disk full")

    monkeypatch.setattr("stellar_cal_ros.io.calibration.os.replace", boom)
    cal2 = Calibration(camera=cal.camera, installation=cal.installation, gyro_bias=[1.0, 2.0, 3.0])
    with pytest.raises(CalibrationFileError, match="disk full"):
        save_calibration(cal2, target)
    assert target.read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["result.yaml"]  # no temp file left


def test_residual_table_parquet_and_csv_round_trip(tmp_path):
    """--residuals RES.parquet or RES.csv (contract §5): both formats keep every column."""
    import numpy as np

    from stellar_cal_ros.io.residuals import read_residuals, write_residuals

    table = {"t": np.array([1795348800.25, 1795348800.75]), "catalog_id": np.array([7, 9]),
             "du": np.array([0.01, -0.02]), "gated": np.array([False, True])}
    for name in ("r.parquet", "r.csv"):
        back = read_residuals(write_residuals(tmp_path / name, table))
        for key, value in table.items():
            np.testing.assert_array_equal(back[key], value)


def test_residual_csv_bytes_are_the_csv_modules(tmp_path):
    """Numeric columns are joined directly (no csv.writer per cell): the same bytes."""
    import csv

    from stellar_cal_ros.io.residuals import TableWriter, write_residuals

    rng = np.random.default_rng(5)
    table = {"t": rng.normal(size=40) * 1e9, "frame": np.arange(40),
             "x": np.r_[np.nan, np.inf, -np.inf, 1e-300, -0.0, rng.normal(size=35)],
             "gated": rng.random(40) > 0.5, "count": np.arange(40, dtype=np.uint16),
             "big": np.r_[1e16, -1e300, 5e-324, 0.1, 123456789.0, rng.normal(size=35) * 1e20],
             "f32": rng.normal(size=40).astype(np.float32), "neg": -np.arange(40)}
    with open(tmp_path / "ref.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(list(table))
        w.writerows(zip(*[[repr(x) if v.dtype.kind == "f" else str(x) for x in v.tolist()]
                          for v in table.values()], strict=True))
    ref = (tmp_path / "ref.csv").read_bytes()
    assert write_residuals(tmp_path / "a.csv", table).read_bytes() == ref
    with TableWriter(tmp_path / "b.csv") as tw:  # streamed in chunks, an empty one first
        tw.append({k: v[:0] for k, v in table.items()})
        tw.append({k: v[:15] for k, v in table.items()})
        tw.append({k: v[15:] for k, v in table.items()})
    assert (tmp_path / "b.csv").read_bytes() == ref
    for one in ("x", "gated"):  # a single column
        with open(tmp_path / "ref1.csv", "w", newline="") as fh:
            csv.writer(fh).writerows([[one]] + [[repr(x) if table[one].dtype.kind == "f"
                                                 else str(x)] for x in table[one].tolist()])
        assert write_residuals(tmp_path / "one.csv", {one: table[one]}).read_bytes() == \
            (tmp_path / "ref1.csv").read_bytes()
    text = dict(table, name=np.array(["a,b"] * 40))  # a string column: quoted by csv
    assert b'"a,b"' in write_residuals(tmp_path / "c.csv", text).read_bytes()


def test_history_rows_gathered_in_blocks_are_the_row_by_row_bytes(tmp_path):
    """TableSink.append_row with arrays: one gather per block, the same file and table."""
    from stellar_cal_ros.methods.results import TableSink

    rng = np.random.default_rng(6)
    keys = ("t", "dof", "a", "b", "c", "d")
    take = np.array([0, 3, 1, 2])
    rows = [([float(rng.normal()), int(k)], (rng.normal(size=2), np.r_[np.nan, rng.normal()]))
            for k in range(25)]
    one, gathered = (TableSink(tmp_path / "one.csv", chunk_rows=7),
                     TableSink(tmp_path / "gathered.csv", chunk_rows=7))
    memory = TableSink(chunk_rows=7)
    expected = [np.concatenate(a)[take[2]] for _, a in rows]
    for head, arrays in rows:
        one.append_row(keys, head + np.concatenate(arrays)[take].tolist())
        gathered.append_row(keys, list(head), arrays, take)
        memory.append_row(keys, list(head), arrays, take)
        arrays[0][:] = 0.0  # the sink keeps copies
    for sink in (one, gathered):
        sink.close()
    assert (tmp_path / "gathered.csv").read_bytes() == (tmp_path / "one.csv").read_bytes()
    table = memory.table()
    assert table["dof"].dtype.kind == "i" and table["t"].dtype.kind == "f"
    np.testing.assert_array_equal(table["c"], expected)


def test_installation_is_the_rotation_of_the_files_quaternion_bit_for_bit(tmp_path: Path) -> None:
    """A file's installation is kept as its unit quaternion and made a ``Rotation`` when
    read (issue 24.1: a replay no longer imports ``scipy.spatial``): the same floats as
    ``Rotation.from_quat`` of the file's numbers, and the installation effect's result is
    ``prior.installation * Rotation.from_rotvec(δ)``, bit for bit."""
    import copy
    import dataclasses

    from scipy.spatial.transform import Rotation

    from stellar_cal_ros.effects.installation import Installation
    from stellar_cal_ros.io.calibration import store_estimate

    rng = np.random.default_rng(5)
    for _ in range(200):
        q = rng.normal(size=4)  # a file's quaternion: unit to its printed digits
        d = _minimal()
        d["installation"]["quaternion_xyzw"] = (q / np.linalg.norm(q)
                                                * (1 + rng.uniform(-1e-9, 1e-9))).tolist()
        cal = calibration_from_dict(d)
        ref = Rotation.from_quat(d["installation"]["quaternion_xyzw"])
        assert isinstance(cal.installation, Rotation)
        assert np.array_equal(cal.installation.as_quat(), ref.as_quat())
        assert np.array_equal(cal.installation_quat, ref.as_quat())
        assert np.array_equal(cal.R_imu_st, ref.as_matrix())
        eff = Installation()
        eff.initial(cal)
        delta = rng.normal(size=3) * rng.choice([1e-5, 1e-3, 0.1])
        out = store_estimate(cal, [eff], {"installation": slice(0, 3)}, delta, np.ones(3),
                             "psce", 0.0)
        want = ref * Rotation.from_rotvec(delta)
        assert np.array_equal(out.installation.as_quat(), want.as_quat())
        assert np.array_equal(out.R_imu_st, want.as_matrix())
        assert np.array_equal(eff.nominal.as_quat(), ref.as_quat())
    # a Rotation assigned, copies and replacements: the same rotation
    cal.installation = want
    assert cal.installation is want and np.array_equal(cal.installation_quat, want.as_quat())
    for other in (copy.deepcopy(cal), dataclasses.replace(cal)):
        assert other == cal and np.array_equal(other.installation.as_quat(), want.as_quat())
    save_calibration(out, tmp_path / "r.yaml")
    back = load_calibration(tmp_path / "r.yaml")
    assert back == out  # (to 1e-15: the file's numbers are the quaternion's repr)
