"""Simulated camera source: real-time delivery at fps, 16-bit block ids wrapping 65535 → 1 (0 invalid),
device clock offset and drift, transport losses and buffer overruns, injectable frame providers."""

import time

import numpy as np
import pytest

from tests.support.camera_polling import poll_frames
from thermod.drivers.camera_base import CameraSource
from thermod.errors import DeviceError
from thermod.sim.emu_camera import EmuCamera, make_provider


def _k(cam, f):
    """Emulator frame index of a delivered frame (the unwrapped id counts from the first raw id)."""
    return f.frame_id - cam.first_frame_id


@pytest.fixture
def stack():
    return np.stack([np.full((6, 8), 1000 * (i + 1), np.uint16) for i in range(4)])


def test_id_wrap_skips_zero_and_timestamps_in_ns(stack):
    cam = EmuCamera(stack, fps=100.0, first_frame_id=65533, drift_ppm=0.0)
    assert isinstance(cam, CameraSource)
    with cam:
        frames = poll_frames(cam, 8)
        st = cam.stats()
    raw = [cam.raw_frame_id(_k(cam, f)) for f in frames]
    assert raw == [65533, 65534, 65535, 1, 2, 3, 4, 5]
    assert [f.frame_id for f in frames] == list(range(65533, 65541))
    assert all(f.gap_before == 0 for f in frames)
    assert st["id_wraps"] == 1 and st["frames_lost"] == 0
    np.testing.assert_array_equal(np.diff([f.device_ts for f in frames]), 10_000_000)   # 10 ms in ns
    for f in frames:
        np.testing.assert_array_equal(f.image, stack[_k(cam, f) % 4])


def test_real_time_delivery_at_fps(stack):
    cam = EmuCamera(stack, fps=50.0, latency_s=0.002, jitter_s=0.0002)
    with cam:
        frames = poll_frames(cam, 25)
    k = np.array([_k(cam, f) for f in frames])
    t_true = np.array([cam.true_time(i) for i in k])
    np.testing.assert_allclose(np.diff(t_true), 0.02 * np.diff(k), atol=1e-9)   # the device's 50 fps
    np.testing.assert_array_equal(np.diff([f.device_ts for f in frames]), 20_000_000 * np.diff(k))
    # paced by the device, not the reader: no frame before its readout + transport (− the 0.2 ms
    # jitter); how much later is the host's load
    arr = np.array([f.arrival for f in frames])
    assert np.all(arr >= t_true + 0.002 - 1e-4)


def test_drift_is_tracked_by_the_clock_mapper(stack):
    drift = 800.0          # ppm, a cheap oscillator; device runs fast
    cam = EmuCamera(stack, fps=50.0, drift_ppm=drift, device_offset_ns=123_456_789_000, latency_s=0.002,
                    n_buffers=128)
    with cam:
        frames = poll_frames(cam, 90)                                  # 1.8 s
        st = cam.stats()
    dts = np.diff([f.device_ts for f in frames]) / np.diff([f.frame_id for f in frames])
    np.testing.assert_allclose(dts, 0.02 * (1 + drift * 1e-6) * 1e9, atol=1)
    assert st["clock_drift_ppm"] == pytest.approx(-drift, abs=250)  # host s per device s, minus one
    err = np.array([f.t - cam.true_time(_k(cam, f)) for f in frames[40:]])
    # mapped times sit at the lower envelope of arrivals: the true readout time + the fixed 2 ms transport
    assert np.all(np.abs(err - 0.002) < 0.0015), err
    naive = (np.array([f.device_ts for f in frames]) - frames[0].device_ts) * 1e-9 + frames[0].t
    true = np.array([cam.true_time(_k(cam, f)) for f in frames])
    assert abs((naive - true)[-1] - (naive - true)[0]) > 0.0012    # ignoring the drift would cost > 1 ms


def test_transport_loss_and_invalid_ids(stack):
    cam = EmuCamera(stack, fps=100.0, drop=[3, 4], invalid_ids=[7])
    with cam:
        frames = poll_frames(cam, 8)
        st = cam.stats()
    assert st["lost_transport"] == 2 and st["invalid_ids"] == 1
    assert st["frames_lost"] == 2 + st["lost_overrun"] == sum(f.gap_before for f in frames)
    if st["lost_overrun"] == 0:            # (a reader stalled > 80 ms by a loaded machine loses more)
        assert [f.frame_id for f in frames] == [1, 2, 3, 6, 7, 8, 9, 10]
        assert [f.gap_before for f in frames] == [0, 0, 0, 2, 0, 0, 0, 0]


def test_slow_consumer_overruns_the_buffer_pool(stack):
    cam = EmuCamera(stack, fps=100.0, n_buffers=4)
    with cam:
        pre = poll_frames(cam, 2)
        time.sleep(0.2)                                            # ~20 frames while only 4 buffers
        frames = poll_frames(cam, 10)
        st = cam.stats()
    assert st["lost_overrun"] >= 10
    seen = pre + frames
    assert sum(f.gap_before for f in seen) == st["frames_lost"]
    # every gap is exactly the frames the device dropped between the two delivered ones
    for a, b in zip(seen, seen[1:], strict=False):
        assert b.gap_before == cam.timeline.lost_between(_k(cam, a), _k(cam, b))
    assert [f.gap_before > 0 for f in frames[:5]] == [False, False, False, False, True]  # 4 old, then gap


def test_callable_provider_gets_true_time_and_float_counts_are_digitised():
    seen = []

    def render(t):
        seen.append(t)
        return np.full((4, 5), 70000.0 if len(seen) == 2 else 1234.6, np.float32)

    cam = EmuCamera(render, fps=100.0)
    with cam:
        frames = poll_frames(cam, 3)
    assert seen == pytest.approx([cam.true_time(_k(cam, f)) for f in frames])
    assert frames[0].image.dtype == np.uint16 and frames[0].image[0, 0] == 1235
    assert frames[1].image.max() == 65535                          # saturates like the ADC


def test_shared_origin_aligns_with_other_emulators(stack):
    origin = time.monotonic() - 10.0                               # a timeline started 10 s ago
    cam = EmuCamera(stack, fps=50.0, origin=origin)
    with cam:
        f = poll_frames(cam, 1)[0]
    k = _k(cam, f)
    assert k >= 500 and cam.true_time(k) == pytest.approx(origin + (k + 1) / 50.0)


def test_bad_inputs_raise_device_errors():
    with pytest.raises(DeviceError, match="frames must be"):
        EmuCamera("not frames")
    with pytest.raises(DeviceError, match="first_frame_id must be a valid 16-bit block id"):
        EmuCamera(np.zeros((2, 2), np.uint16), first_frame_id=0)
    with pytest.raises(DeviceError, match="poll\\(\\) before start"):
        EmuCamera(np.zeros((2, 2), np.uint16)).poll(0.01)
    p = make_provider(lambda t: np.zeros((2, 2, 3)))
    with pytest.raises(DeviceError, match="expected \\[H, W\\]"):
        p(0, 0.0)
