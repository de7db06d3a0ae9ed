"""Sync of a video to a gyro log from the pictures (`thermod.sync`), on simulated flights with a
hidden truth: an AGC'd 8-bit 160×120 video of 3 s at 50 Hz starting somewhere in a longer log, the
camera on the flight controller in a random one of the 24 axis-aligned mounts plus a small
misalignment, and a gyro bias (sim/sync_flights.py)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from thermod import sync as S
from thermod.errors import ThermodError
from thermod.motion import picture as P
from thermod.physics.geometry import Intrinsics, so3_log
from thermod.sim import sync_flights as sf


def _sync(fl, frames=None, gyro_t=None, gyro_rate=None):
    return S.synchronise(fl.frames if frames is None else frames, fl.frame_t,
                         fl.gyro_t if gyro_t is None else gyro_t,
                         fl.gyro_rate if gyro_rate is None else gyro_rate, fl.intrinsics, tau_s=fl.tau_s)


@pytest.fixture(scope="module")
def procedural():
    fl = sf.make_flight(3, motion="procedural", mount_index=11)
    return fl, _sync(fl)


def test_the_24_mounts_are_the_distinct_axis_aligned_rotations():
    Ms = np.stack(S.MOUNTS)
    assert Ms.shape == (24, 3, 3)
    assert np.allclose(np.linalg.det(Ms), 1.0)
    assert np.allclose(np.einsum("nji,njk->nik", Ms, Ms), np.eye(3))
    assert len({M.astype(int).tobytes() for M in Ms}) == 24
    assert np.array_equal(S.MOUNTS[0], np.eye(3))


def test_normalising_a_frame_removes_a_gain_and_offset():
    rng = np.random.default_rng(1)
    f = rng.normal(1000, 50, (40, 60))
    assert np.allclose(P.normalise_frame(f), P.normalise_frame(3.7 * f - 200), atol=1e-5)


def _check_recovered(fl, res):
    period = 1.0 / sf.FPS
    err = res.time_offset_s - fl.true_offset_s
    # measured on seed 3 (procedural): −0.2 ms; real log seeds 0–2: −1.2, −1.0, −1.0 ms
    assert abs(err) < period
    assert abs(err) <= res.fine.lag_bound_s + 4 * res.fine.time_offset_sigma_s + 1e-4
    assert res.mount_index == fl.mount_index
    assert res.mount_cost_ratio > 3
    angle = np.linalg.norm(so3_log(fl.true_R.T @ res.R_cam_gyro))
    assert angle < math.radians(1.0), math.degrees(angle)
    assert np.all(np.abs(res.fine.bias_rad_s - fl.bias_rad_s) < 0.003)


def test_procedural_flight_is_synced_and_its_mount_found(procedural):
    fl, res = procedural
    _check_recovered(fl, res)
    assert res.coarse.ncc > 0.95
    assert res.motion["snr"] > P.MIN_MOTION_SNR


def test_real_log_flight_is_synced_and_its_mount_found(require):
    require(sf.real_log() is not None, "../shared/data/gyro (the real Betaflight log)")
    fl = sf.make_flight(1, motion="real")
    _check_recovered(fl, _sync(fl))


def test_the_rolling_readout_is_fitted_from_the_bands():
    # hidden 12 ms readout (the user's nominal: 0); measured 12.2 ± 0.2 ms, offset error −0.3 ms
    fl = sf.make_flight(4, motion="procedural", effects={"rolling_readout": 0.012})
    res = _sync(fl)
    assert res.fine.readout_s == pytest.approx(0.012, abs=0.0015)
    assert 0 < res.fine.readout_sigma_s < 0.0015
    assert abs(res.time_offset_s - fl.true_offset_s) < 0.004
    assert res.mount_index == fl.mount_index
    assert res.calibration_changes()["readout_s"] == pytest.approx(res.fine.readout_s)


def test_a_clock_drift_between_video_and_log_is_fitted():
    # the log's clock 1000 ppm fast (a video stamped at a nominal rate): measured 1003 ± 49 ppm
    fl = sf.make_flight(7, 6.0, motion="procedural", drift_ppm=1000.0)
    res = _sync(fl)
    assert res.fine.clock_drift_ppm == pytest.approx(1000.0, abs=200.0)
    assert 0 < res.fine.clock_drift_sigma_ppm < 150
    assert abs(res.time_offset_s - fl.true_offset_s) < 0.002
    changes = res.calibration_changes()
    assert changes["clock_drift_ppm"] == res.fine.clock_drift_ppm
    assert changes["clock_epoch_s"] == pytest.approx(0.5 * (fl.frame_t[0] + fl.frame_t[-1]))


class _LazyReader:
    """A video reader that hands out one frame at a time and counts the reads."""

    def __init__(self, frames):
        self.frames, self.reads = frames, 0

    def __len__(self):
        return len(self.frames)

    def __getitem__(self, k):
        self.reads += 1
        return self.frames[k]


def test_a_lazy_reader_gives_the_same_sync_reading_each_frame_once(procedural):
    fl, res = procedural
    reader = _LazyReader(fl.frames)
    lazy = _sync(fl, frames=reader)
    assert reader.reads == len(fl.frames) + 1            # the shape check reads frame 0 once more
    assert lazy.time_offset_s == res.time_offset_s and lazy.mount_index == res.mount_index


def test_report_and_figure(procedural, tmp_path):
    fl, res = procedural
    d = json.loads(json.dumps(res.to_dict()))
    assert d["mount"] == S.MOUNTS[fl.mount_index].astype(int).tolist()
    assert d["time_offset_s"]["sigma"] > 0 and d["time_offset_s"]["lag_bound"] == pytest.approx(fl.tau_s / 2)
    assert len(d["gyro_bias_rad_s"]["sigma"]) == 3
    changes = res.calibration_changes()
    assert set(changes) == {"time_offset_s", "R_cam_gyro", "bias_rad_s", "readout_s", "clock_drift_ppm",
                            "clock_epoch_s"}
    assert changes["time_offset_s"] == 0
    assert res.camera_clock(fl.gyro_t)[0] == pytest.approx(fl.gyro_t[0] + res.time_offset_s)
    png = tmp_path / "sync.png"
    S.plot_sync(res, fl.gyro_t, fl.gyro_rate, png)
    assert png.stat().st_size > 20_000


def test_a_static_video_is_refused():
    fl = sf.make_flight(5, motion="procedural", static=True)
    with pytest.raises(S.TooLittleMotion, match="too little rotation"):
        _sync(fl)


def test_a_log_of_another_flight_is_refused(procedural):
    fl, _ = procedural
    other = sf.procedural_motion(77).omega(fl.gyro_t)
    with pytest.raises(S.LogMismatch, match="gyro log"):
        _sync(fl, gyro_rate=other)


# The refusals below reuse the flight's measured picture motion (the correlation is what judges the log).
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_shuffled_log_is_refused(procedural, seed):
    fl, res = procedural
    blocks = np.array_split(fl.gyro_rate, 80)             # 0.5 s blocks, the spectrum kept
    order = np.random.default_rng(seed).permutation(len(blocks))
    with pytest.raises(S.LogMismatch, match="gyro log"):
        S.coarse_sync(res.picture, fl.gyro_t, np.concatenate([blocks[i] for i in order]), tau_s=fl.tau_s)


def test_a_log_shorter_than_the_video_is_refused(procedural):
    fl, res = procedural
    i0 = np.searchsorted(fl.gyro_t, fl.frame_t[0] - fl.true_offset_s)
    n = int(2.0 * sf.LOG_RATE_HZ)
    with pytest.raises(S.DurationMismatch, match="the video lasts 2.98 s but the gyro log only 2.00 s"):
        S.coarse_sync(res.picture, fl.gyro_t[i0:i0 + n], fl.gyro_rate[i0:i0 + n])


def test_a_log_without_rotation_is_refused(procedural):
    fl, res = procedural
    with pytest.raises(S.LogMismatch, match="never change"):
        S.coarse_sync(res.picture, fl.gyro_t, np.zeros_like(fl.gyro_rate))


@pytest.mark.parametrize("change, message", [
    ({"frame_t": np.zeros(150)}, "frame_t: times must increase"),
    ({"frame_t": np.arange(10.0)}, "expected one time per frame"),
    ({"gyro_rate": np.zeros((5, 3))}, "gyro_rate: expected shape"),
    ({"gyro_t": np.full(40000, np.nan)}, "gyro_t: contains NaN"),
    ({"frames": np.zeros((150, 60, 80), np.uint8)}, "80×60 px but the intrinsics describe 160×120"),
])
def test_bad_inputs_are_named(procedural, change, message):
    fl, _ = procedural
    kw = {"frames": fl.frames, "frame_t": fl.frame_t, "gyro_t": fl.gyro_t, "gyro_rate": fl.gyro_rate}
    kw.update(change)
    with pytest.raises(S.SyncInputError, match=message) as e:
        S.synchronise(kw["frames"], kw["frame_t"], kw["gyro_t"], kw["gyro_rate"], fl.intrinsics)
    assert isinstance(e.value, ThermodError)


def _per_frame_gain(images, raw) -> np.ndarray:
    """Least-squares gain of each frame of `images` against the detector counts `raw`."""
    out = []
    for y, x in zip(images, raw, strict=True):
        A = np.c_[x.ravel().astype(np.float64), np.ones(x.size)]
        out.append(np.linalg.lstsq(A, y.ravel().astype(np.float64), rcond=None)[0][0])
    return np.array(out)


def test_the_agc_is_undone_from_the_picture_rotations(procedural):
    from thermod.motion.agc import fit_agc

    fl, res = procedural
    fit = fit_agc(fl.frames, res.picture, fl.intrinsics)
    agc_gain = _per_frame_gain(fl.frames, fl.raw)
    kept_gain = _per_frame_gain(fit.counts(fl.frames), fl.raw)
    spread = lambda g: float(np.std(g / np.median(g)))  # noqa: E731
    # measured: the AGC's per-frame gain spreads 14.9 %, what is left after the fit 0.67 % (max 1.5 %)
    assert spread(agc_gain) > 0.1
    assert spread(kept_gain) < 0.015
    assert np.max(np.abs(kept_gain / np.median(kept_gain) - 1)) < 0.04


def test_the_discrepancy_recording_is_a_synced_format_v1_stretch(procedural):
    from thermod.calib.discrepancy import prepare
    from thermod.sync.discrepancy import discrepancy_recording, stretches

    fl, res = procedural
    (a0, a1), (b0, b1) = stretches(res, 1.0, 2)
    assert a1 <= b0 and a1 - a0 == b1 - b0 == 50
    rec = discrepancy_recording(fl.frames, fl.frame_t, fl.gyro_t, fl.gyro_rate, res, fl.intrinsics,
                                frames_range=(a0, a1))
    assert rec.frames.dtype == np.uint16 and rec.frames.shape == (50, 120, 160)
    assert rec.calibration.time_offset_s == 0.0
    # the log's samples now sit on the video clock: their stamps cover the stretch
    assert rec.gyro_t[0] < rec.t[0] - 0.25 and rec.gyro_t[-1] > rec.t[-1]
    assert np.allclose(rec.calibration.R_cam_gyro_matrix, res.R_cam_gyro)
    d = prepare(rec, rec.calibration, name="stretch")
    assert d.reference == "motion" and len(d.frame_t) > 40


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(n=st.integers(0, 40), h=st.integers(8, 24), w=st.integers(8, 24), m=st.integers(0, 300),
       seed=st.integers(0, 2**16), dtype=st.sampled_from([np.uint8, np.uint16, np.float32]),
       rate_hz=st.sampled_from([0.0, 1e-3, 50.0, 1e6]), log_rate=st.sampled_from([1e-3, 100.0, 8000.0]))
def test_arbitrary_inputs_end_in_a_result_or_a_sync_error(n, h, w, m, seed, dtype, rate_hz, log_rate):
    rng = np.random.default_rng(seed)
    frames = (rng.random((n, h, w)) * 200).astype(dtype)
    frame_t = np.cumsum(rng.exponential(1.0 / rate_hz, n)) if rate_hz > 0 else np.zeros(n)
    gyro_t = np.cumsum(rng.exponential(1.0 / log_rate, m))
    gyro_rate = rng.normal(0, 1, (m, 3))
    intr = Intrinsics(w, h, 20.0, 20.0, (w - 1) / 2, (h - 1) / 2)
    try:
        S.synchronise(frames, frame_t, gyro_t, gyro_rate, intr)
    except (S.SyncError, S.TooLittleMotion):
        pass
