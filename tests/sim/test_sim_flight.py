"""thermod.sim.flight_video: a simulated flight written as an AGC'd H.264 video and real-format gyro logs,
whose hidden offset and mount are checked against the pictures themselves."""

import json

import cv2
import numpy as np
import pytest

from thermod.errors import ThermodError
from thermod.io.flightlog import axis_aligned_rotations, read_flight_log
from thermod.io.video import read_video
from thermod.sim.flight_video import LOG_FORMATS, simulate_flight


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    out = tmp_path_factory.mktemp("flight")
    return simulate_flight(out, seconds=2.0, log_seconds=8.0, formats=tuple(LOG_FORMATS), seed=5, crf=0)


def test_files_and_truth_are_written(flight):
    truth = json.loads(flight.truth_path.read_text())
    assert truth["log_offset_s"] == pytest.approx(flight.log_offset_s)
    assert truth["time_offset_s"] == pytest.approx(-flight.log_offset_s)
    assert np.array_equal(truth["camera_from_body"], flight.camera_from_body)
    assert np.array_equal(axis_aligned_rotations()[truth["mount_index"]], flight.camera_from_body)
    assert 1.0 <= flight.video_start_s <= 8.0 - 2.0 - 1.0
    assert set(truth["logs"]) == set(LOG_FORMATS)


def test_video_is_agc_8bit_h264_with_a_gain_per_frame(flight):
    v = read_video(flight.video_path)
    assert v.info.codec == "h264" and v.frames.dtype == np.uint8 and len(v.t) == 60
    np.testing.assert_allclose(v.t, flight.frame_t_video)
    np.testing.assert_allclose(np.diff(v.t), 1 / 30, atol=2e-5)
    counts = flight.recording.frames.astype(np.float64)
    expected = np.clip((counts - flight.agc_offset[:, None, None]) * flight.agc_gain[:, None, None], 0, 255)
    assert np.abs(v.frames - expected).max() <= 1.0                  # crf 0: the stretch, exactly
    rel = np.ptp(flight.agc_gain) / np.mean(flight.agc_gain)
    assert rel > 0.02                                                # the gain really changes …
    assert np.abs(np.diff(flight.agc_gain)).max() < 0.25 * np.ptp(flight.agc_gain)   # … smoothly


@pytest.mark.parametrize("fmt", sorted(LOG_FORMATS))
def test_each_log_format_reads_back_the_body_rates(flight, fmt):
    log = read_flight_log(flight.log_paths[fmt])
    assert log.source_format == fmt and len(log) == 8000
    assert log.t[0] == pytest.approx(flight.log_start_s) and log.rate_hz == pytest.approx(1000)
    np.testing.assert_allclose(log.t, flight.body_t_log, atol=1e-6)
    err = log.rate - flight.body_rate
    quantum = np.radians(0.5) if fmt == "betaflight-csv" else 0.0    # Betaflight logs whole °/s
    assert np.abs(err).max() < quantum + 6 * np.radians(0.1)         # 0.1 °/s white noise
    assert np.std(flight.body_rate) > 20 * np.std(err)


def _image_shifts(frames):
    """Global image motion between consecutive frames (phase correlation), px."""
    win = cv2.createHanningWindow(frames.shape[:0:-1], cv2.CV_64F)
    return np.array([cv2.phaseCorrelate(a.astype(np.float64), b.astype(np.float64), win)[0]
                     for a, b in zip(frames[:-1], frames[1:], strict=True)])


def test_hidden_offset_and_mount_explain_the_pictures(flight):
    """The image shift between frames follows the camera rate predicted from the LOG through the hidden
    mount and offset (a pan right moves the scene left: dx = −f ω_y Δt; a tilt up moves it down:
    dy = f ω_x Δt); a wrong offset or mount explains it worse."""
    v = read_video(flight.video_path)
    shifts = _image_shifts(v.frames)
    log = read_flight_log(flight.log_paths["gcsv"])
    f = flight.recording.calibration.fx

    def predicted(offset, mount):
        mid = 0.5 * (v.t[:-1] + v.t[1:]) + offset
        w_body = np.stack([np.interp(mid, log.t, log.rate[:, i]) for i in range(3)], axis=1)
        w_cam = w_body @ mount.T
        dt = np.diff(v.t)
        return np.stack([-f * w_cam[:, 1] * dt, f * w_cam[:, 0] * dt], axis=1)

    def misfit(offset, mount):
        return float(np.median(np.abs(shifts - predicted(offset, mount))))

    best = misfit(flight.log_offset_s, flight.camera_from_body)
    assert best < 0.3                                                # px per frame
    assert np.std(shifts) > 1.0                                      # the camera really moves
    assert misfit(flight.log_offset_s + 0.25, flight.camera_from_body) > 2 * best
    others = [m for m in axis_aligned_rotations() if not np.array_equal(m, flight.camera_from_body)]
    assert min(misfit(flight.log_offset_s, m) for m in others) > 1.5 * best


def test_seed_hides_a_different_offset_and_mount(tmp_path):
    a = simulate_flight(tmp_path, seconds=0.5, log_seconds=4.0, seed=1, formats=("gcsv",))
    truth_a = (a.log_offset_s, a.mount_index)
    b = simulate_flight(tmp_path, seconds=0.5, log_seconds=4.0, seed=2, formats=("gcsv",), mount=7,
                        video_start_s=1.5)
    assert (b.log_offset_s, b.mount_index) != truth_a
    assert b.mount_index == 7 and b.video_start_s == 1.5
    assert b.log_offset_s == pytest.approx(b.log_start_s + 1.5 - b.frame_t_video[0])


def test_camera_effects_and_a_log_bias_are_kept_in_the_truth(tmp_path):
    sim = simulate_flight(tmp_path, seconds=0.5, log_seconds=3.0, seed=4, formats=("gcsv",),
                          effects={"rolling_readout": 0.02, "time_constant": 0.012},
                          gyro_bias_rad_s=(0.01, -0.02, 0.005))
    truth = json.loads(sim.truth_path.read_text())
    assert truth["effects"] == {"rolling_readout": 0.02, "time_constant": 0.012}
    assert truth["gyro_bias_rad_s"] == [0.01, -0.02, 0.005]
    assert sim.recording.extra_attrs["truth"]["readout_s"] == pytest.approx(0.02)
    log = read_flight_log(sim.log_paths["gcsv"])
    np.testing.assert_allclose(np.mean(log.rate - sim.body_rate, axis=0), [0.01, -0.02, 0.005], atol=2e-4)
    with pytest.raises(ThermodError, match="gyro_bias_rad_s"):
        simulate_flight(tmp_path, seconds=0.5, log_seconds=3.0, effects={"gyro_bias": 0.01})


def test_bad_requests_are_refused(tmp_path):
    with pytest.raises(ThermodError, match="formats"):
        simulate_flight(tmp_path, formats=("px4",))
    with pytest.raises(ThermodError, match="2 s longer"):
        simulate_flight(tmp_path, seconds=3.0, log_seconds=4.0)
    with pytest.raises(ThermodError, match="mount index 24"):
        simulate_flight(tmp_path, mount=24)
    with pytest.raises(ThermodError, match="proper rotation"):
        simulate_flight(tmp_path, mount=-np.eye(3))
    with pytest.raises(ThermodError, match="inside"):
        simulate_flight(tmp_path, seconds=1.0, log_seconds=4.0, video_start_s=3.5)
    with pytest.raises(ThermodError, match="does not exist"):
        simulate_flight(tmp_path / "absent")
