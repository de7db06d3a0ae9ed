"""thermod.io.flightlog on real logs (Betaflight blackbox, PX4 ULog: tests/data/flightlogs) and on files
written in Gyroflow's gcsv and Betaflight's CSV, read back through telemetry-parser; errors; fuzzing."""

import functools
import os
import stat
import tempfile
from pathlib import Path

import numpy as np
import pytest
import telemetry_parser
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from thermod.io.flightlog import (
    DEG,
    FORWARD_CAMERA_FROM_FRD,
    GCSV_ORIENTATION_OPENCV_CAMERA,
    FlightLog,
    FlightLogError,
    axis_aligned_rotations,
    read_flight_log,
    write_ardupilot_bin,
    write_betaflight_csv,
    write_gcsv,
)

DATA = Path(__file__).parents[1] / "data" / "flightlogs"
BBL = DATA / "betaflight_btfl_001.bbl"
ULG = DATA / "px4_sample_appended_multiple.ulg"


@pytest.fixture(scope="module")
def bbl_log() -> FlightLog:
    return read_flight_log(BBL)          # telemetry-parser takes ~1.5 s over this 50 s log: read it once


def _check(log: FlightLog):
    assert log.t.dtype == np.float64 and log.rate.dtype == np.float64
    assert log.rate.shape == (len(log.t), 3) and np.all(np.diff(log.t) > 0)
    assert np.all(np.isfinite(log.rate))


# ------------------------------------------------------------------------------------------ real logs
def test_real_betaflight_blackbox_gives_the_longest_log_in_frd_rad_s(bbl_log):
    log = bbl_log
    _check(log)
    assert log.source_format == "betaflight" and log.frame == "FRD"
    assert log.n_logs == 2 and log.log_index == 1                     # the 50 s flight, not the 0.2 s one
    assert log.rate_hz == pytest.approx(500, rel=1e-3)
    assert log.duration_s == pytest.approx(49.98, abs=0.01)
    assert log.t[0] == pytest.approx(191.882474)                       # the FC's clock, untouched
    assert "Betaflight 4.2.11" in log.model
    # gyroADC (°/s, x fwd / y left / z up) → FRD rad/s: (roll, −pitch, −yaw)
    # the same samples as telemetry-parser's raw view of the second log, axes and clock undone
    raw = telemetry_parser.Parser(str(BBL)).telemetry()[1]["Gyroscope"]["Data"]
    np.testing.assert_allclose(log.t, [d["t"] for d in raw], atol=1e-9)
    gyro_adc = np.array([(d["x"], d["y"], d["z"]) for d in raw]) * DEG
    np.testing.assert_allclose(log.rate, gyro_adc * [1, -1, -1], atol=1e-12)
    assert 0.5 < np.abs(log.rate).max() < 40                            # a flight: up to a few 100 °/s
    short = read_flight_log(BBL, log_index=0)
    assert len(short) == 98 and short.log_index == 0
    with pytest.raises(FlightLogError, match=r"log 5: the file holds 2 log\(s\)"):
        read_flight_log(BBL, log_index=5)


def test_real_px4_ulog_sensor_combined():
    log = read_flight_log(ULG)
    _check(log)
    assert log.source_format == "px4-ulog" and log.frame == "FRD" and "sensor_combined" in log.model
    assert log.rate_hz == pytest.approx(250, rel=1e-3) and len(log) == 2373
    assert log.duration_s == pytest.approx(9.6176, abs=1e-4)
    from pyulog import ULog
    d = ULog(str(ULG), ["sensor_combined"]).get_dataset("sensor_combined")
    np.testing.assert_allclose(log.rate[:, 2], d.data["gyro_rad[2]"])
    np.testing.assert_allclose(log.t, d.data["timestamp"] * 1e-6)


def test_real_betaflight_log_survives_gcsv_and_csv_round_trips(tmp_path, bbl_log):
    real = bbl_log
    g = read_flight_log(write_gcsv(tmp_path / "real.gcsv", real.t, real.rate))
    assert g.source_format == "gcsv" and g.frame == "imu" and g.orientation == "XYZ"
    np.testing.assert_allclose(g.t, real.t, atol=1e-6)
    np.testing.assert_allclose(g.rate, real.rate, atol=1e-6)
    c = read_flight_log(write_betaflight_csv(tmp_path / "real.csv", real.t, real.rate))
    assert c.source_format == "betaflight-csv" and c.frame == "FRD"
    np.testing.assert_allclose(c.t, real.t, atol=1e-6)
    np.testing.assert_allclose(c.rate, real.rate, atol=1e-9)           # the real log is whole °/s already


def test_shared_betaflight_export_is_a_reduced_csv_no_parser_reads(shared_data, require):
    """shared/data/gyro/betaflight_smooth_2khz.csv is a reduced export (time_us, gyro_*_degps, acc_*_raw),
    not Blackbox Explorer's CSV: refused by name, not misread."""
    path = shared_data / "gyro" / "betaflight_smooth_2khz.csv"
    require(path.exists(), "../shared/data/gyro/betaflight_smooth_2khz.csv (the real Betaflight log)")
    assert path.read_text()[:40].startswith("time_us,gyro_roll_degps")
    with pytest.raises(FlightLogError, match=r"betaflight_smooth_2khz\.csv: not a log format"):
        read_flight_log(path)


# ------------------------------------------------------------------------------------------- writers
def test_gcsv_round_trip_through_telemetry_parser(tmp_path):
    rng = np.random.default_rng(0)
    t = 1234.5 + np.cumsum(rng.uniform(0.9e-3, 1.1e-3, 3000))
    w = rng.normal(0, 2.0, (3000, 3))
    path = write_gcsv(tmp_path / "flight.gcsv", t, w, orientation="yxz", note="sim, test",
                      extra={"frame_readout_time": 12.5})
    text = path.read_text().splitlines()
    assert text[0] == "GYROFLOW IMU LOG" and "t,gx,gy,gz" in text and "orientation,yxz" in text
    tp = telemetry_parser.Parser(str(path))                               # Gyroflow's own parser
    assert tp.camera == "thermod"
    log = read_flight_log(path)
    assert log.orientation == "yxz" and log.frame == "imu"
    np.testing.assert_allclose(log.t, t, atol=0.6e-6)
    np.testing.assert_allclose(log.rate, w, atol=0.6e-6)
    assert log.rate_hz == pytest.approx(1000, rel=0.02)


def test_betaflight_csv_is_read_as_blackbox_in_frd(tmp_path):
    t = 10.0 + np.arange(1000) / 2000.0
    w = np.zeros((1000, 3))
    w[:, 0], w[:, 1], w[:, 2] = 1.0, -0.5, 0.25                           # roll right, pitch down, yaw right
    path = write_betaflight_csv(tmp_path / "bf.csv", t, w, integer_deg_s=False)
    lines = path.read_text().splitlines()
    assert lines[2].startswith('"loopIteration","time","gyroADC[0]"')
    first = [float(v) for v in lines[3].split(",")]
    assert first[1] == 10_000_000                                         # µs since boot
    np.testing.assert_allclose(first[2:], np.array([1.0, 0.5, -0.25]) / DEG, atol=1e-3)   # FLU in the file
    log = read_flight_log(path)
    assert log.source_format == "betaflight-csv" and log.rate_hz == pytest.approx(2000)
    np.testing.assert_allclose(log.rate, w, atol=1e-5)


def _decode_csv(t: np.ndarray, w_frd: np.ndarray, *, time_unit: str = "us", rotation: str = "raw") -> str:
    """A CSV as blackbox_decode writes it: ", " between cells, units in brackets after the names
    (--unit-frame-time us|s, --unit-rotation raw|deg/s|rad/s), flags as text, more columns around."""
    flu = w_frd * [1, -1, -1]
    gyro = {"raw": np.round(flu / DEG), "deg/s": flu / DEG, "rad/s": flu}[rotation]
    unit = "" if rotation == "raw" else f" ({rotation})"
    names = ["loopIteration", f"time ({time_unit})", "axisP[0]", "axisP[1]", "vbatLatest (V)",
             *[f"gyroADC[{k}]{unit}" for k in range(3)], "motor[0]", "flightModeFlags (flags)"]
    rows = [", ".join(names)]
    for i, (ti, g) in enumerate(zip(t, gyro, strict=True)):
        tt = str(round(ti * 1e6)) if time_unit == "us" else f"{ti:.6f}"
        gg = [f"{v:g}" if rotation == "raw" else f"{v:.6f}" for v in g]
        rows.append(", ".join([str(4 * i), tt, "3", "-2", "16.1", *gg, "1200", "ANGLE_MODE|HORIZON_MODE"]))
    return "\n".join(rows) + "\n"


@pytest.mark.parametrize("time_unit,rotation", [("us", "raw"), ("s", "deg/s"), ("us", "rad/s")])
@pytest.mark.parametrize("eol,bom", [("\n", False), ("\r\n", True)])
def test_blackbox_decode_csv_is_read_in_its_stated_units(tmp_path, time_unit, rotation, eol, bom):
    """blackbox_decode's CSV (``loopIteration, time (us), …``), which telemetry-parser does not
    recognise, gives the same FRD rad/s on the FC's clock whatever units it was exported in, with
    Windows line ends or a byte order mark."""
    t = 452.2 + np.arange(2000) / 1000.0
    w = np.zeros((2000, 3))
    w[:, 0], w[:, 1], w[:, 2] = 0.5, -1.0, 2.0                                # whole °/s are not exact
    w = np.round(w / DEG) * DEG
    path = tmp_path / "LOG00001.01.csv"
    text = _decode_csv(t, w, time_unit=time_unit, rotation=rotation).replace("\n", eol)
    path.write_bytes((b"\xef\xbb\xbf" if bom else b"") + text.encode())
    log = read_flight_log(path)
    _check(log)
    assert log.source_format == "betaflight-csv" and log.frame == "FRD" and len(log) == 2000
    assert log.rate_hz == pytest.approx(1000, rel=1e-3)
    np.testing.assert_allclose(log.t, t, atol=1e-6)
    np.testing.assert_allclose(log.rate, w, atol=1e-5)


def test_a_betaflight_csv_behind_a_bom_or_with_crlf_reads_like_the_plain_one(tmp_path):
    t = 10.0 + np.arange(1000) / 2000.0
    w = np.tile([0.2, -0.1, 0.05], (1000, 1))
    plain = write_betaflight_csv(tmp_path / "bf.csv", t, w, integer_deg_s=False)
    text = plain.read_bytes()
    (tmp_path / "bom.csv").write_bytes(b"\xef\xbb\xbf" + text.replace(b"\n", b"\r\n"))
    a, b = read_flight_log(plain), read_flight_log(tmp_path / "bom.csv")
    assert b.source_format == "betaflight-csv" and "Betaflight 4.4.0" in b.model
    np.testing.assert_array_equal(a.t, b.t)
    np.testing.assert_array_equal(a.rate, b.rate)


def test_a_csv_cut_mid_row_loses_that_row_but_a_damaged_one_is_refused(tmp_path, caplog):
    t = 1.0 + np.arange(3000) / 1000.0
    text = _decode_csv(t, np.zeros((3000, 3)))
    cut = tmp_path / "cut.csv"
    cut.write_text(text[: text.index("\n3000, ") + 4])                      # a crash mid-row
    with caplog.at_level("WARNING", logger="thermod.io.flightlog"):
        log = read_flight_log(cut)
    assert len(log) == 750 and "skipped 1 unreadable data row" in caplog.text
    bad = tmp_path / "bad.csv"
    lines = text.splitlines()
    for i in range(1, len(lines), 3):                                        # blackbox_decode's unknown time
        cells = lines[i].split(", ")
        lines[i] = ", ".join([cells[0], "X", *cells[2:]])
    bad.write_text("\n".join(lines) + "\n")
    with pytest.raises(FlightLogError, match=r"bad\.csv: \d+ of 3000 data rows without a number"):
        read_flight_log(bad)


@pytest.mark.parametrize("names,problem", [
    ("loopIteration, time (us), axisP[0], rcCommand[0]",
     r"no gyroADC\[0\], gyroADC\[1\], gyroADC\[2\] column"),
    ("loopIteration, time (ms), gyroADC[0], gyroADC[1], gyroADC[2]",
     r"time column in 'ms': expected us or s"),
    ("loopIteration, time (us), gyroADC[0] (rad/s), gyroADC[1], gyroADC[2]",
     r"gyroADC columns in '' and 'rad/s'"),
    ('"loopIteration","iteration","gyroADC[0]","gyroADC[1]","gyroADC[2]"', r"no time column"),
])
def test_a_betaflight_csv_without_usable_columns_names_what_it_lacks(tmp_path, names, problem):
    path = tmp_path / "cols.csv"
    path.write_text(names + "\n" + "".join(f"{i}, {1000 * i}, 1, 2, 3\n" for i in range(100)))
    with pytest.raises(FlightLogError, match=r"cols\.csv: " + problem):
        read_flight_log(path)


def test_real_betaflight_log_as_blackbox_decode_exports_it(tmp_path, shared_data, require):
    """The real 1 kHz KakuteF7 log of shared/data, its gyroADC written as blackbox_decode's CSV:
    the same samples as the binary log gives."""
    bfl = shared_data / "logs" / "betaflight_4.2_LOG00037.BFL"
    require(bfl.exists(), "shared/data/logs/betaflight_4.2_LOG00037.BFL (the real Betaflight log)")
    real = read_flight_log(bfl)
    path = tmp_path / "LOG00037.01.csv"
    path.write_text(_decode_csv(real.t, real.rate))
    log = read_flight_log(path)
    assert log.source_format == "betaflight-csv" and log.rate_hz == pytest.approx(1000, rel=1e-3)
    np.testing.assert_allclose(log.t, real.t, atol=1e-9)
    np.testing.assert_allclose(log.rate, real.rate, atol=1e-9)


def test_a_gcsv_behind_a_byte_order_mark_is_read_and_named(tmp_path):
    t = 5.0 + np.arange(1000) / 1000.0
    w = np.tile([0.1, 0.2, 0.3], (1000, 1))
    text = write_gcsv(tmp_path / "plain.gcsv", t, w, orientation="YxZ").read_bytes()
    path = tmp_path / "bom.gcsv"
    path.write_bytes(b"\xef\xbb\xbf" + text)
    log = read_flight_log(path)
    assert log.path == str(path) and log.source_format == "gcsv" and log.orientation == "YxZ"
    np.testing.assert_allclose(log.rate, w, atol=1e-6)
    path.write_bytes(b"\xef\xbb\xbf" + text.replace(b"orientation,YxZ", b"orientation,YYZ"))
    with pytest.raises(FlightLogError, match=r"bom\.gcsv: orientation 'YYZ'"):
        read_flight_log(path)


@pytest.mark.parametrize("n_imus,stagger_s", [(1, 0.0), (2, 0.0), (2, 5e-6), (3, 20e-6)])
def test_ardupilot_bin_is_read_in_frd_keeping_the_first_imu(tmp_path, n_imus, stagger_s):
    rng = np.random.default_rng(n_imus)
    t = 7.0 + np.arange(2000) / 400.0 + rng.normal(0, 20e-6, 2000)        # loop jitter
    w = rng.normal(0, 1.0, (2000, 3))
    path = write_ardupilot_bin(tmp_path / "flight.bin", t, w, n_imus=n_imus, stagger_s=stagger_s)
    assert path.read_bytes()[:4] == bytes([0xA3, 0x95, 0x80, 0x80])      # DataFlash FMT of FMT
    assert telemetry_parser.Parser(str(path)).camera == "ArduPilot"
    log = read_flight_log(path)
    assert log.source_format == "ardupilot" and log.frame == "FRD" and len(log) == 2000
    np.testing.assert_allclose(log.t, t, atol=0.6e-6)                      # µs in the file
    np.testing.assert_allclose(log.rate, w, atol=1e-6)                     # instance 0, float32 in the file


def test_a_sibling_gcsv_is_not_read_in_place_of_the_named_file(tmp_path):
    t = np.arange(100) / 1000.0 + 1
    write_gcsv(tmp_path / "x.gcsv", t, np.ones((100, 3)))
    log = read_flight_log(write_betaflight_csv(tmp_path / "x.csv", t, np.zeros((100, 3))))
    assert log.source_format == "betaflight-csv" and np.all(log.rate == 0)


def test_the_24_axis_aligned_mounts():
    r = axis_aligned_rotations()
    assert r.shape == (24, 3, 3) and len({m.tobytes() for m in r}) == 24
    assert np.allclose(np.einsum("kij,kil->kjl", r, r), np.eye(3)) and np.allclose(np.linalg.det(r), 1)
    assert np.array_equal(r[-1], np.eye(3)) and np.array_equal(r, axis_aligned_rotations())
    assert any(np.array_equal(m, FORWARD_CAMERA_FROM_FRD) for m in r)


def test_gcsv_camera_orientation_gives_gyroflow_the_axes_it_gives_an_fc_log(tmp_path):
    """Camera-frame rates written with GCSV_ORIENTATION_OPENCV_CAMERA reach Gyroflow's axes
    (telemetry-parser's normalized_imu) as the same motion logged by a flight controller with a
    forward camera does."""
    t = 2.0 + np.arange(400) / 400.0
    w_frd = np.random.default_rng(3).normal(0, 1.0, (400, 3))
    fc = write_ardupilot_bin(tmp_path / "fc.bin", t, w_frd)
    cam = write_gcsv(tmp_path / "cam.gcsv", t, w_frd @ FORWARD_CAMERA_FROM_FRD.T,
                     orientation=GCSV_ORIENTATION_OPENCV_CAMERA)
    g_fc = np.array([r["gyro"] for r in telemetry_parser.Parser(str(fc)).normalized_imu()])
    g_cam = np.array([r["gyro"] for r in telemetry_parser.Parser(str(cam)).normalized_imu()])
    np.testing.assert_allclose(g_cam, g_fc, atol=1e-4)               # °/s; float32 and µrad/s rounding


def test_forward_camera_mount_is_a_proper_rotation():
    m = FORWARD_CAMERA_FROM_FRD
    assert np.allclose(m @ m.T, np.eye(3)) and np.linalg.det(m) == pytest.approx(1.0)
    assert np.allclose(m @ [0, 0, 1], [0, 1, 0])       # body yaw (z down) is the camera's y (down): a pan


def test_writers_refuse_bad_series(tmp_path):
    with pytest.raises(FlightLogError, match="increase strictly"):
        write_gcsv(tmp_path / "a.gcsv", [0, 1, 1], np.zeros((3, 3)))
    with pytest.raises(FlightLogError, match=r"rates \[N, 3\]"):
        write_gcsv(tmp_path / "a.gcsv", [0, 1], np.zeros((2, 2)))
    with pytest.raises(FlightLogError, match="permutation"):
        write_gcsv(tmp_path / "a.gcsv", [0, 1], np.zeros((2, 3)), orientation="XXZ")
    with pytest.raises(FlightLogError, match="≥ 0"):
        write_betaflight_csv(tmp_path / "a.csv", [-1, 0], np.zeros((2, 3)))


# -------------------------------------------------------------------------------------------- errors
def test_unsupported_empty_missing_and_truncated_files(tmp_path):
    (tmp_path / "notes.txt").write_text("hello, world\n1,2,3\n")
    with pytest.raises(FlightLogError, match=r"notes\.txt: not a log format"):
        read_flight_log(tmp_path / "notes.txt")
    (tmp_path / "empty.bbl").write_bytes(b"")
    with pytest.raises(FlightLogError, match=r"empty\.bbl: empty file"):
        read_flight_log(tmp_path / "empty.bbl")
    with pytest.raises(FlightLogError, match=r"absent\.ulg: does not exist"):
        read_flight_log(tmp_path / "absent.ulg")
    (tmp_path / "logs.bbl").mkdir()                                      # a folder, not "no such file"
    with pytest.raises(FlightLogError, match=r"logs\.bbl: is a directory, expected a file"):
        read_flight_log(tmp_path / "logs.bbl")
    os.mkfifo(tmp_path / "pipe.bbl")
    with pytest.raises(FlightLogError, match=r"pipe\.bbl: is a device or special file"):
        read_flight_log(tmp_path / "pipe.bbl")
    data = ULG.read_bytes()
    (tmp_path / "cut.ulg").write_bytes(data[:2000])                       # the header and no data
    with pytest.raises(FlightLogError, match=r"cut\.ulg: (no gyro samples|pyulog cannot read it)"):
        read_flight_log(tmp_path / "cut.ulg")
    bbl = BBL.read_bytes()
    (tmp_path / "cut.bbl").write_bytes(bbl[:3000])                       # headers only, no frames
    with pytest.raises(FlightLogError, match=r"cut\.bbl: .*(no gyro samples|truncated)"):
        read_flight_log(tmp_path / "cut.bbl")
    (tmp_path / "half.bbl").write_bytes(bbl[: len(bbl) // 2])             # power cut mid-flight: usable
    half = read_flight_log(tmp_path / "half.bbl")
    assert 5 < half.duration_s < 40 and half.source_format == "betaflight"


def test_a_log_without_gyro_is_refused(tmp_path):
    path = tmp_path / "nogyro.gcsv"
    path.write_text("GYROFLOW IMU LOG\nversion,1.3\nid,x\ntscale,0.001\ngscale,1\nt\n")
    with pytest.raises(FlightLogError, match=r"nogyro\.gcsv: no gyro samples"):
        read_flight_log(path)
    csv = tmp_path / "nogyro.csv"
    csv.write_text('"loopIteration","time","motor[0]"\n0,100,1000\n1,200,1001\n')
    with pytest.raises(FlightLogError, match=r"nogyro\.csv: no gyroADC\[0\], gyroADC\[1\], gyroADC\[2\] col"):
        read_flight_log(csv)


@pytest.mark.parametrize("tscale", ["nan", "inf"])
def test_a_gcsv_whose_time_scale_is_not_finite_is_refused(tmp_path, tscale):
    rows = "".join(f"{37250000 + 1000 * k},-5055,-21524,85127\n" for k in range(2000))
    path = tmp_path / "tscale.gcsv"
    head = f"GYROFLOW IMU LOG\nversion,1.3\nid,x\ntscale,{tscale}\ngscale,1e-06\nt,gx,gy,gz\n"
    path.write_text(head + rows)
    with pytest.raises(FlightLogError, match=r"tscale\.gcsv: .*(time|tscale)"):
        read_flight_log(path)


@pytest.mark.parametrize("line, field", [("orientation,QQQ", "orientation"), ("orientation,", "orientation"),
                                         ("orientation,XXY", "orientation"), ("gscale,abc", "gscale"),
                                         ("tscale,0", "tscale")])
def test_a_bad_gcsv_header_is_refused_before_the_parser_panics(tmp_path, capfd, line, field):
    """telemetry-parser panics on a bad orientation (a Rust backtrace on stderr with RUST_BACKTRACE):
    the header is checked first, and the error names the field."""
    rows = "".join(f"{k},1,2,3\n" for k in range(2000))
    path = tmp_path / "head.gcsv"
    path.write_text(f"GYROFLOW IMU LOG\nversion,1.3\nid,x\n{line}\ntscale,0.001\ngscale,1\nt,gx,gy,gz\n"
                    .replace("tscale,0.001\n", "" if line.startswith("tscale") else "tscale,0.001\n")
                    .replace("gscale,1\n", "" if line.startswith("gscale") else "gscale,1\n") + rows)
    with pytest.raises(FlightLogError, match=rf"head\.gcsv: {field} "):
        read_flight_log(path)
    assert "panicked" not in capfd.readouterr().err


def test_a_parser_panic_becomes_a_flight_log_error(tmp_path):
    # telemetry-parser unwraps the time column: a Rust panic (a data row before the column names keeps
    # the file from thermod's own Betaflight CSV reader)
    bad = tmp_path / "panic.csv"
    bad.write_text('5,5\nloopIteration,time,gyroADC[0],gyroADC[1],gyroADC[2]\n0,abc,1,2,3\n')
    with pytest.raises(FlightLogError, match=r"panic\.csv: the parser failed: truncated or corrupt"):
        read_flight_log(bad)


def test_rate_zero_and_non_increasing_times_are_refused(tmp_path):
    header = "GYROFLOW IMU LOG\nversion,1.3\nid,x\ntscale,1\ngscale,1\nt,gx,gy,gz\n"
    same = tmp_path / "frozen.gcsv"
    same.write_text(header + "".join(f"{k // 500},0,0,0\n" for k in range(1000)))   # 1 Hz clock ticks
    with pytest.raises(FlightLogError, match=r"frozen\.gcsv: .*(not after|rate)"):
        read_flight_log(same)
    back = tmp_path / "back.gcsv"
    rows = [f"{t},1,2,3\n" for t in list(range(0, 50)) + list(range(10, 60))]
    back.write_text(header.replace("tscale,1", "tscale,0.001") + "".join(rows))
    with pytest.raises(FlightLogError, match=r"back\.gcsv: gyro sample 50 at 0\.010000 s is not after"):
        read_flight_log(back)
    slow = tmp_path / "slow.gcsv"
    slow.write_text(header + "".join(f"{k},1,2,3\n" for k in range(20)))             # 1 Hz
    with pytest.raises(FlightLogError, match=r"slow\.gcsv: gyro sample rate 1 Hz"):
        read_flight_log(slow)


def test_a_rate_no_gyro_reads_is_refused(tmp_path):
    """A row of 1e301 rad/s is finite but no gyro's: it is refused naming the file, not carried into
    the sync (where it overflowed and read as "the rates never change"); so is a log in °/s read as
    rad/s (a .gcsv whose gscale is 1 for a logger writing °/s)."""
    t = np.arange(3000) / 1000.0
    path = write_gcsv(tmp_path / "wild.gcsv", t, np.zeros((3000, 3)))
    lines = path.read_text().splitlines()
    i = lines.index("t,gx,gy,gz") + 1501
    lines[i] = lines[i].split(",")[0] + ",0,1" + "0" * 307 + ",0"       # 1e301 rad/s at gscale 1e-6
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(FlightLogError, match=r"wild\.gcsv: 1 gyro samples over 80 rad/s"):
        read_flight_log(path)
    w = np.zeros((3000, 3))
    w[1000:1200, 2] = 90 * DEG * np.sin(np.linspace(0, np.pi, 200)) ** 2      # a 90 °/s pan
    deg = write_gcsv(tmp_path / "deg.gcsv", t, w / DEG, gscale=1e-3)          # °/s numbers, rad/s gscale
    with pytest.raises(FlightLogError, match=r"deg\.gcsv: \d+ gyro samples over 80 rad/s .*°/s read as rad"):
        read_flight_log(deg)
    np.testing.assert_allclose(read_flight_log(write_gcsv(tmp_path / "rad.gcsv", t, w)).rate, w, atol=1e-6)


def test_a_damaged_ulog_says_so_in_one_log_line_not_on_stdout(tmp_path, capfd, caplog):
    """pyulog prints a line per damaged record; the reader keeps stdout clean and logs one summary."""
    b = bytearray(ULG.read_bytes())
    for i in range(3000, len(b), 997):
        b[i] ^= 0xFF
    path = tmp_path / "flip.ulg"
    path.write_bytes(bytes(b))
    with caplog.at_level("WARNING", logger="thermod.io.flightlog"):
        with pytest.raises(FlightLogError, match=r"flip\.ulg: "):
            read_flight_log(path)
    assert capfd.readouterr().out == ""
    said = [r.getMessage() for r in caplog.records if r.name == "thermod.io.flightlog"]
    assert len(said) == 1 and "pyulog reported" in said[0] and "flip.ulg" in said[0]


def test_isolated_out_of_order_samples_are_dropped_and_counted(tmp_path):
    t = np.arange(5000) / 1000.0
    path = write_gcsv(tmp_path / "glitch.gcsv", t, np.zeros((5000, 3)))
    lines = path.read_text().splitlines()
    i = lines.index("t,gx,gy,gz") + 2000
    lines[i] = "1000,0,0,0"                                                # one stale stamp (1 ms)
    path.write_text("\n".join(lines) + "\n")
    log = read_flight_log(path)
    assert log.n_dropped == 1 and len(log) == 4999



def _betaflight_csv_rows(tmp_path, t, name="log.csv") -> tuple[list[str], list[list[str]]]:
    """The three header rows and the data rows (as cells) of a Betaflight CSV at times `t`."""
    w = np.random.default_rng(1).normal(0, 1, (len(t), 3))
    lines = write_betaflight_csv(tmp_path / name, t, w).read_text().splitlines()
    return lines[:3], [r.split(",") for r in lines[3:]]


def test_a_clock_that_repeats_every_stamp_is_refused_as_such(tmp_path):
    """2 kHz rows on a 1 kHz clock: every stamp twice. Once each lone repeat was dropped nothing was
    left and the error read "1 gyro sample(s)"; it names the repeat."""
    head, rows = _betaflight_csv_rows(tmp_path, 100 + np.arange(4000) / 1000)
    body = [",".join([r[0], rows[i // 2 * 2][1], *r[2:]]) for i, r in enumerate(rows)]
    (tmp_path / "twice.csv").write_text("\n".join(head + body) + "\n")
    with pytest.raises(FlightLogError, match=r"twice\.csv: gyro sample 1 at 100\.000000 s is not after the "
                                             r"one before \(100\.000000 s\).*out of order or repeated"):
        read_flight_log(tmp_path / "twice.csv")


@pytest.mark.parametrize("us", [10**17, 10**300], ids=["3000 years", "1e294 s"])
def test_a_time_no_log_clock_gives_is_refused(tmp_path, us):
    """A time of 3000 years (float64 keeps 15 µs there: a 1 kHz log read at 993 Hz) or 10²⁹⁴ s (its
    300 digits were the message)."""
    head, rows = _betaflight_csv_rows(tmp_path, np.arange(3000) / 1000)
    body = [",".join([r[0], str(us + int(r[1])), *r[2:]]) for r in rows]
    (tmp_path / "far.csv").write_text("\n".join(head + body) + "\n")
    with pytest.raises(FlightLogError, match=r"far\.csv: gyro sample 0 at 1e\+\d+ s: expected a log clock"):
        read_flight_log(tmp_path / "far.csv")


def test_betaflight_csvs_joined_end_to_end_are_read_as_logs_of_their_own(tmp_path):
    """A Blackbox Explorer export, then a blackbox_decode one with other columns and units (``cat``):
    the second's names are taken (its gyro was read from motor[0] and its time in s as µs before),
    the header rows are not counted as damaged rows (a short log was refused for them)."""
    rng = np.random.default_rng(2)
    t1, w1 = 100 + np.arange(400) / 1000, rng.normal(0, 1, (400, 3))
    first = write_betaflight_csv(tmp_path / "a.csv", t1, w1, integer_deg_s=False).read_text()
    t2, w2 = 300 + np.arange(600) / 2000, rng.normal(0, 1, (600, 3))
    deg = w2 @ np.diag([1.0, -1.0, -1.0]) / DEG
    second = "loopIteration, time (s), motor[0], gyroADC[0] (deg/s), gyroADC[1] (deg/s), gyroADC[2] (deg/s)\n"
    second += "".join(f"{i}, {t:.6f}, 1500, {x:.6f}, {y:.6f}, {z:.6f}\n" for i, (t, (x, y, z)) in
                      enumerate(zip(t2, deg, strict=True)))
    path = tmp_path / "joined.csv"
    path.write_text(first + second + first)
    log = read_flight_log(path)
    assert log.n_logs == 3 and log.log_index == 1 and len(log) == 600
    np.testing.assert_allclose(log.t, t2, atol=1e-9)
    np.testing.assert_allclose(log.rate, w2, atol=1e-6)
    third = read_flight_log(path, log_index=2)
    np.testing.assert_allclose(third.t, t1, atol=1e-9)
    np.testing.assert_allclose(third.rate, w1, atol=1e-6)


def test_a_betaflight_csv_whose_32_bit_microsecond_clock_wraps_is_one_log(tmp_path):
    """Betaflight's time is µs since power-up in 32 bits: 71.6 min after it, the counter wraps. An
    exporter that does not carry it on (blackbox_decode does) gave two logs, and the longer half."""
    head, rows = _betaflight_csv_rows(tmp_path, np.arange(4000) / 1000)
    us = (2**32 - 1_500_000 + 1000 * np.arange(4000)) % 2**32
    (tmp_path / "wrap.csv").write_text("\n".join(head + [",".join([r[0], str(u), *r[2:]])
                                                         for r, u in zip(rows, us, strict=True)]) + "\n")
    log = read_flight_log(tmp_path / "wrap.csv")
    assert log.n_logs == 1 and len(log) == 4000
    np.testing.assert_allclose(log.t, (2**32 - 1_500_000) * 1e-6 + np.arange(4000) / 1000, atol=1e-6)


def _ulog_with_wild_stamp(data: bytes, sample: int, bit: int) -> bytes:
    """The ULog `data` with one bit of sensor_combined's `sample`-th timestamp flipped."""
    import struct

    from pyulog import ULog
    d = next(d for d in ULog(str(ULG), ["sensor_combined"]).data_list if d.name == "sensor_combined")
    # a data record: size (u16), 'D', msg_id (u16), then the timestamp (u64)
    key = struct.pack("<BH", ord("D"), d.msg_id) + struct.pack("<Q", int(d.data["timestamp"][sample]))
    i = data.index(key) + 3
    b = bytearray(data)
    b[i + bit // 8] ^= 1 << (bit % 8)
    return bytes(b)


@pytest.mark.parametrize("bit", [30, 62])
def test_a_ulog_with_one_wild_stamp_drops_it_as_the_other_readers_do(tmp_path, bit):
    """One flipped bit of a ULog timestamp (2 ks or 10¹³ s ahead) refused the whole 10 s log as "not
    after the one before"; the blackbox and CSV readers drop such a lone sample, and so does this."""
    path = tmp_path / "wild.ulg"
    path.write_bytes(_ulog_with_wild_stamp(ULG.read_bytes(), 1000, bit))
    log = read_flight_log(path)
    assert log.n_dropped == 1 and len(log) == 2372 and log.duration_s == pytest.approx(9.6176, abs=1e-4)


def test_ulog_files_joined_end_to_end_are_separate_logs(tmp_path):
    """``cat a.ulg b.ulg``: pyulog mixes the two up (either's samples, in no stated order, as one
    log); each is read from its own header, the longest by default."""
    data = ULG.read_bytes()
    half = data[: len(data) // 2]
    (tmp_path / "two.ulg").write_bytes(half + data)
    log = read_flight_log(tmp_path / "two.ulg")
    assert log.n_logs == 2 and log.log_index == 1 and len(log) == 2373
    short = read_flight_log(tmp_path / "two.ulg", log_index=0)
    assert short.log_index == 0 and 100 < len(short) < 2000
    np.testing.assert_array_equal(short.t, log.t[: len(short)])
    with pytest.raises(FlightLogError, match=r"two\.ulg: log 2: the file holds 2 log\(s\)"):
        read_flight_log(tmp_path / "two.ulg", log_index=2)
    (tmp_path / "junk.ulg").write_bytes(data + data[:20])        # a second header cut short: ignored
    assert read_flight_log(tmp_path / "junk.ulg").n_logs == 1


@pytest.mark.parametrize("field, value", [(b"acc_1G", b"abc"), (b"P interval", b"0"), (b"vbatref", b"")])
def test_a_blackbox_header_the_parser_panics_on_says_so_once(tmp_path, capfd, field, value):
    """fc-blackbox unwraps header values: a Rust panic, printed to stderr (with RUST_BACKTRACE a
    backtrace of 30 lines) beside thermod's own error. It is one FlightLogError now."""
    import re
    data = re.sub(rb"H " + re.escape(field) + rb":[^\n]*", b"H " + field + b":" + value, BBL.read_bytes())
    (tmp_path / "head.bbl").write_bytes(data)
    with pytest.raises(FlightLogError, match=r"head\.bbl: the parser failed: truncated or corrupt \(\S"):
        read_flight_log(tmp_path / "head.bbl")
    assert "panicked" not in capfd.readouterr().err


def test_a_blackbox_log_without_gyro_is_refused_before_the_probe(tmp_path, monkeypatch):
    """The probe parses every logged field of the file's first bytes (700 bytes of Python objects a
    byte); for a log without gyroADC it went on to 16 MiB: 3.5 GB and 30 s for a 4 MB log. The log
    is refused first, and the probe never reads more than 1 MiB."""
    from thermod.io import flightlog
    monkeypatch.setattr(flightlog, "_probe_prefix", lambda *a: pytest.fail("probed a log without gyro"))
    (tmp_path / "nogyro.bbl").write_bytes(BBL.read_bytes().replace(b"gyroADC", b"gyroXYZ"))
    with pytest.raises(FlightLogError, match=r"nogyro\.bbl: no gyro samples in this BlackBox"):
        read_flight_log(tmp_path / "nogyro.bbl")
    assert max(flightlog.PROBE_BYTES) <= 2**20

# ----------------------------------------------------------------------------------------- fuzzing
@functools.cache
def _seeds() -> dict[str, bytes]:
    """A small valid file of each family, to mutate."""
    t, w = 1.0 + np.arange(200) / 500.0, np.random.default_rng(0).normal(0, 1, (200, 3))
    with tempfile.TemporaryDirectory() as d:
        return {".bbl": BBL.read_bytes()[:6000], ".ulg": ULG.read_bytes()[:6000],
                ".bin": write_ardupilot_bin(Path(d) / "s.bin", t, w, n_imus=2).read_bytes(),
                ".gcsv": write_gcsv(Path(d) / "s.gcsv", t, w).read_bytes(),
                ".csv": write_betaflight_csv(Path(d) / "s.csv", t, w).read_bytes()}


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_fuzzed_logs_give_a_log_or_a_flight_log_error(tmp_path, capfd, data):
    suffix = data.draw(st.sampled_from([".bbl", ".ulg", ".gcsv", ".csv", ".bin"]))
    kind = data.draw(st.sampled_from(["random", "mutate", "text", "joined"]))
    if kind == "random":
        blob = data.draw(st.binary(max_size=2048))
    elif kind == "text":
        scale = st.sampled_from(["0.001", "1", "nan", "inf", "-1", "0", "1e308", "abc", ""])
        head = data.draw(st.sampled_from([
            f"GYROFLOW IMU LOG\nversion,1.3\ntscale,{data.draw(scale)}\ngscale,{data.draw(scale)}\n"
            "t,gx,gy,gz\n",
            '"loopIteration","time","gyroADC[0]","gyroADC[1]","gyroADC[2]"\n',
            "H Product:Blackbox flight data recorder by Nicholas Sherlock\n"]))
        body = data.draw(st.text(alphabet="0123456789,.-e\nabc\"", max_size=400))
        blob = (head + body).encode()
    else:
        blob = b""
        for _ in range(1 if kind == "mutate" else data.draw(st.integers(2, 3))):    # joined: logs end to end
            b = bytearray(_seeds()[suffix])
            for _ in range(data.draw(st.integers(0 if kind == "joined" else 1, 12))):
                b[data.draw(st.integers(0, len(b) - 1))] = data.draw(st.integers(0, 255))
            blob += bytes(b[: data.draw(st.integers(1, len(b)))])
    path = tmp_path / f"fuzz{suffix}"
    path.write_bytes(blob)
    capfd.readouterr()
    try:
        log = read_flight_log(path)
    except FlightLogError as e:
        assert "fuzz" in str(e)
        return
    finally:
        assert "panicked" not in capfd.readouterr().err          # a Rust panic is the error, not a print
    _check(log)
    assert 10 <= log.rate_hz <= 100_000


def test_fixture_logs_are_small_and_licensed():
    for p in (BBL, ULG):
        assert p.stat().st_size < 1_000_000
    readme = (DATA / "README.md").read_text()
    assert BBL.name in readme and ULG.name in readme and "MIT" in readme and "BSD-3-Clause" in readme
    assert (DATA / "LICENSE-fc-blackbox-MIT").exists() and (DATA / "LICENSE-pyulog-BSD-3-Clause").exists()


@pytest.mark.parametrize("writer", [write_gcsv, write_betaflight_csv, write_ardupilot_bin])
def test_every_log_writer_refuses_a_special_file_as_its_target(tmp_path, writer):
    """The three writers share one write-then-rename: a FIFO (or /dev/null) is refused, not replaced."""
    target = tmp_path / "special"
    os.mkfifo(target)
    t = 1.0 + np.arange(200) / 500.0
    with pytest.raises(FlightLogError, match="special file"):
        writer(target, t, np.zeros((200, 3)))
    assert stat.S_ISFIFO(target.stat().st_mode)
