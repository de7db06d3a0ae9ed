"""Replay of a format-v1 recording as camera + gyro sources: right frames and samples, relative timing
preserved on the re-based host timeline, paced (real time, ×speed) and as-fast-as-possible lockstep."""

import math
import threading
import time

import h5py
import numpy as np
import pytest

from thermod.drivers.gyro_base import GyroBatch
from thermod.drivers.replay import ReplayCamera, ReplayGyro, ReplaySession
from thermod.errors import DeviceError, RecordingError
from thermod.io import recording
from thermod.physics.calibration import Calibration

FPS, RATE = 50.0, 1000.0
N = 15                                   # 0.3 s of frames


def _recording(gap=True) -> recording.Recording:
    calib = Calibration(width=24, height=16, cx=11.5, cy=7.5, frame_rate_hz=FPS, rate_hz=RATE,
                        time_offset_s=0.0015)
    frames = np.stack([np.full((16, 24), 1000 + 17 * i, np.uint16) for i in range(N)])
    frames[:, 3, 5] = np.arange(N, dtype=np.uint16)                   # every frame distinct
    t = 100.0 + np.arange(N) / FPS
    gyro_t = 100.0 - 0.045 + np.arange(int(0.36 * RATE)) / RATE       # 5τ before the first frame
    if gap:
        gyro_t = np.delete(gyro_t, np.arange(200, 205))              # 5 samples lost in the log
    rate = np.stack([np.sin(gyro_t), np.cos(gyro_t), gyro_t - 100], axis=1).astype(np.float32)
    return recording.Recording(frames, t, gyro_t, rate, calib)


@pytest.fixture
def rec_path(tmp_path):
    rec = _recording()
    p = tmp_path / "rec.h5"
    recording.write(p, rec)
    return p, rec


def _drain(cam, gyro, poll_timeout=30.0):
    """Poll both sources to their end from two threads, as the daemon's driver threads do; each item
    with the host time its poll returned."""
    frames, batches = [], []

    def run(src, out):
        while not src.finished:
            item = src.poll(poll_timeout)
            if item is not None:
                out.append((item, time.monotonic()))

    threads = [threading.Thread(target=run, args=a) for a in ((cam, frames), (gyro, batches))]
    cam.start()
    gyro.start()
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    cam.stop()
    gyro.stop()
    return frames, batches


def test_real_time_replay_preserves_frames_samples_and_timing(rec_path):
    path, rec = rec_path
    cam, gyro = ReplayCamera(path), ReplayGyro(path)
    assert cam.session is gyro.session                         # one timeline for both
    t0 = time.monotonic()
    frames, batches = _drain(cam, gyro, poll_timeout=30.0)
    # every poll returned when its item fell due, none waited out its 30 s timeout (the bound only
    # catches that; the recording lasts 0.36 s)
    assert time.monotonic() - t0 < 30.0
    frames, f_arrival = [f for f, _ in frames], np.array([a for _, a in frames])
    batches, b_arrival = [b for b, _ in batches], np.array([a for _, a in batches])
    assert len(frames) == N
    for i, f in enumerate(frames):
        np.testing.assert_array_equal(f.image, rec.frames[i])
        assert f.frame_id == i and f.gap_before == 0 and f.image.dtype == np.uint16
    assert all(isinstance(b, GyroBatch) for b in batches)
    gt = np.concatenate([b.t for b in batches])
    gr = np.concatenate([b.rate for b in batches])
    assert gr.dtype == np.float32 and gt.dtype == np.float64
    np.testing.assert_array_equal(gr, rec.gyro_rate)
    origin = cam.session.origin
    # re-based: one offset for camera and gyro, so the relative timing (and time_offset_s) survives
    np.testing.assert_allclose([f.t for f in frames], rec.t - rec.gyro_t[0] + origin, atol=1e-9)
    np.testing.assert_allclose(gt, rec.gyro_t - rec.gyro_t[0] + origin, atol=1e-9)
    # the log's 5-sample hole arrives flagged, with its size
    flagged = [b for b in batches if b.gap_before]
    assert len(flagged) == 1 and flagged[0].n_lost == 5 and flagged[0].seq == 200
    assert [b.seq for b in batches] == list(np.cumsum([0] + [len(b) for b in batches[:-1]]))
    assert gyro.stats()["gaps"] == 1 and gyro.stats()["lost"] == 5
    # paced by the recording's clock: nothing is handed out before its time (how late depends on the
    # host's load; that no poll waits past an item's time is shown by the 30 s timeouts above)
    lag = np.array([f.arrival - f.t for f in frames])
    assert np.all(lag >= 0) and np.all(f_arrival >= np.array([f.t for f in frames]))
    # a batch holds only samples already due when it was handed out: FIFO-like, not one early lump
    assert np.all(np.array([b.t[-1] for b in batches]) <= b_arrival)
    assert cam.finished and gyro.finished


def test_as_fast_as_possible_is_lockstep(rec_path):
    path, rec = rec_path
    s = ReplaySession(path, speed=math.inf, lead_s=0.05)
    cam, gyro = s.camera(), s.gyro()
    cam.start()
    gyro.start()
    t0 = time.monotonic()
    assert cam.poll(0.0) is None              # the gyro has not covered frame 0 yet
    events, idle_rounds = [], 0
    while not (cam.finished and gyro.finished):
        b = gyro.poll(0.0)
        if b is not None:
            events.append(("g", b.t[-1], cam.session.camera_next))
        f = cam.poll(0.0)
        if f is not None:
            events.append(("f", f.t, None))
        idle_rounds += b is None and f is None
        assert time.monotonic() - t0 < 30       # only catches a hang
    gyro_out = -math.inf
    n_frames = 0
    for kind, t, cam_next in events:
        if kind == "g":
            assert t <= cam_next + 0.05 + 1e-9   # never more than lead_s ahead of the next frame
            gyro_out = t
        else:
            n_frames += 1
            assert gyro_out >= t - 1e-9 or gyro.finished   # the gyro covers every frame handed out
    assert n_frames == N
    # not paced by the clock: in lockstep one of the two sources always has an item ready, so no
    # round of non-blocking polls comes back empty (a paced replay would idle until items fall due)
    assert idle_rounds == 0


def test_speed_factor_paces_but_keeps_the_time_scale(rec_path):
    path, rec = rec_path
    cam = ReplayCamera(path, speed=4.0)
    cam.start()
    s = cam.session
    frames = []
    while len(frames) < N:
        f = cam.poll(30.0)                    # returns when the frame falls due; 30 s only catches a hang
        assert f is not None
        frames.append(f)
    # paced at 4×: no frame before its due time, origin + (re-based time − origin) / 4 ...
    assert all(f.arrival >= s.due(f.t) for f in frames)
    assert frames[-1].arrival - s.origin >= (rec.t[-1] - rec.gyro_t[0]) / 4
    # ... and not at 1×, which would take the recording's own 0.325 s (a bound ~4× the 4× pace)
    assert frames[-1].arrival - s.origin < rec.t[-1] - rec.gyro_t[0]
    np.testing.assert_allclose(np.diff([f.t for f in frames]), 1 / FPS, atol=1e-9)   # physical time


def test_loop_continues_ids_and_time(tmp_path):
    rec = _recording(gap=False)
    s = ReplaySession(rec, speed=math.inf, loop=True)
    cam = s.camera()
    cam.start()
    frames = [cam.poll(0.1) for _ in range(2 * N + 3)]
    ids = [f.frame_id for f in frames]
    assert ids == list(range(2 * N + 3))
    np.testing.assert_array_equal(frames[N + 2].image, rec.frames[2])
    period = s.loop_period
    assert period == pytest.approx(rec.gyro_t[-1] + 1 / RATE - rec.gyro_t[0])
    assert frames[N + 2].t - frames[2].t == pytest.approx(period)
    assert all(f.gap_before == 0 for f in frames)               # the seam is not a loss
    assert np.all(np.diff([f.t for f in frames]) > 0)


def test_only_camera_started_does_not_wait_for_gyro(rec_path):
    path, _ = rec_path
    cam = ReplaySession(path, speed=math.inf).camera()
    cam.start()
    assert [cam.poll(0.0).frame_id for _ in range(N)] == list(range(N))
    assert cam.poll(0.01) is None and cam.stats()["state"] == "finished"


def test_bad_recordings_and_arguments(tmp_path, rec_path):
    with pytest.raises(RecordingError, match="does not exist"):
        ReplayCamera(tmp_path / "missing.h5")
    path, _ = rec_path
    bad = tmp_path / "bad.h5"
    bad.write_bytes(path.read_bytes())
    with h5py.File(bad, "a") as f:
        f.attrs["version"] = 2
    with pytest.raises(RecordingError, match=r"version.*expected 1, got 2"):
        ReplayGyro(bad)
    with h5py.File(bad, "a") as f:
        f.attrs["version"] = 1
        del f["camera/t"]
        f["camera/t"] = np.arange(N, dtype=np.float64)[::-1]
    with pytest.raises(RecordingError, match="camera/t: time must be strictly increasing"):
        ReplayCamera(bad)
    with pytest.raises(DeviceError, match="speed must be > 0"):
        ReplaySession(path, speed=0)
    with pytest.raises(DeviceError, match="poll\\(\\) before start"):
        ReplayCamera(path, speed=2.0).poll(0.0)


def test_late_start_joins_the_stream_like_a_live_device(tmp_path):
    rec = _recording(gap=False)
    path = tmp_path / "nogap.h5"
    recording.write(path, rec)
    s = ReplaySession(path, loop=True)                   # real time (looped: timing-robust on a busy host)
    cam, gyro = s.camera(), s.gyro()
    cam.start()
    first = cam.poll(30.0)                               # 30 s: only catches a hang
    time.sleep(0.2)
    t_join = time.monotonic()
    gyro.start()                                         # 0.2 s late: the past is not replayed in a burst
    b = gyro.poll(30.0)
    assert b.gap_before and b.n_lost == b.seq > 100
    assert b.t[0] >= t_join - 0.1 - 1e-3                 # at most the 0.1 s catch-up allowance overdue
    i0 = b.seq % len(rec.gyro_t)
    np.testing.assert_array_equal(b.rate, rec.gyro_rate[i0:i0 + len(b)])
    cam.stop()
    time.sleep(0.1)
    cam.start()                                          # frames while stopped are gone, and counted
    f = cam.poll(30.0)
    assert f.frame_id > first.frame_id + 1 and f.gap_before == f.frame_id - first.frame_id - 1
    np.testing.assert_array_equal(f.image, rec.frames[f.frame_id % N])


def test_every_source_offers_name_clock_and_stats():
    # the runtime reads these three from any camera or gyro source, without probing for them
    from thermod.drivers.bus import SPIBus
    from thermod.drivers.icm42688 import ICM42688
    from thermod.drivers.iio import IIOGyro
    from thermod.drivers.serial_imu import SerialIMU
    from thermod.drivers.v4l2_camera import V4L2Camera
    from thermod.io.clock import ClockMapper
    from thermod.sim.emu_camera import EmuCamera
    from thermod.sim.emu_registers import EmuSPI, ICM42688Emu

    rec = _recording()
    session = ReplaySession(rec)
    sources = [ReplayCamera(rec, session=session), ReplayGyro(rec, session=session),
               ICM42688(SPIBus(EmuSPI(ICM42688Emu()))), IIOGyro("icm42688"), SerialIMU("/dev/null"),
               V4L2Camera("/dev/video99"), EmuCamera(rec.frames)]
    for src in sources:
        assert isinstance(src.name, str) and src.name
        assert src.clock is None or isinstance(src.clock, ClockMapper)
        assert isinstance(src.stats(), dict)
    assert sources[0].clock is None and sources[1].clock is None      # replayed times need no mapping
    assert all(isinstance(s.clock, ClockMapper) for s in sources[2:5])


@pytest.mark.parametrize("empty", ["camera", "gyro"])
@pytest.mark.parametrize("loop", [False, True])
def test_a_stream_with_nothing_to_replay_is_refused_at_open(tmp_path, rec_path, empty, loop):
    """A recording whose frames (or gyro samples) are all gone cannot stand in for that device: the
    source says so when it is made, not with an IndexError from its driver thread."""
    path, _ = rec_path
    bad = tmp_path / "empty.h5"
    bad.write_bytes(path.read_bytes())
    with h5py.File(bad, "a") as f:
        names = ("camera/frames", "camera/t") if empty == "camera" else ("gyro/t", "gyro/rate")
        for name in names:
            data = f[name][:0]
            del f[name]
            f[name] = data
    source = ReplayCamera if empty == "camera" else ReplayGyro
    other = ReplayGyro if empty == "camera" else ReplayCamera
    with pytest.raises(DeviceError, match=rf"empty\.h5 {empty}: the recording holds no"):
        source(bad, loop=loop)
    other(bad, loop=loop)                     # the other stream is still there to replay
