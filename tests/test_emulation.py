"""The benchmarks' emulated slower machine: a recording on a clock s times slower renders the same
kernels, so a daemon fed it does the same work per frame at 1/s the frame rate."""

import numpy as np
import pytest

from benchmarks.emulation import daemon_sets, stretched
from thermod.io.recording import Recording
from thermod.physics.calibration import Calibration
from thermod.restore.plan import render
from thermod.restore.settings import DeblurConfig


def _recording(seed=3) -> Recording:
    rng = np.random.default_rng(seed)
    cal = Calibration(width=96, height=72, fx=180.0, fy=180.0, cx=47.5, cy=35.5, tau_s=0.008,
                      frame_rate_hz=50.0, rate_hz=1000.0, time_offset_s=0.002, bias_rad_s=(0.01, 0.0, -0.02))
    gyro_t = np.arange(600) / 1000.0
    rate = np.stack([0.6 * np.sin(9 * gyro_t), 0.4 * np.cos(5 * gyro_t), 0.3 * np.sin(3 * gyro_t + 1)], 1)
    rate = (rate + 0.01 * rng.standard_normal(rate.shape)).astype(np.float32)
    t = 0.1 + np.arange(20) / 50.0
    frames = rng.integers(1000, 3000, (20, 72, 96)).astype(np.uint16)
    return Recording(frames=frames, t=t, gyro_t=gyro_t, gyro_rate=rate, calibration=cal)


@pytest.mark.parametrize("scale", [0.5, 2.6])
@pytest.mark.parametrize("mode", ["uniform", "grid"])
def test_stretched_recording_renders_the_same_kernels(scale, mode):
    rec = _recording()
    slow = stretched(rec, scale)
    slow.validate()
    assert slow.calibration.frame_rate_hz == pytest.approx(50.0 / scale)
    assert slow.calibration.tau_s == pytest.approx(0.008 * scale)
    deblur = DeblurConfig(mode=mode, grid=(2, 3))
    for i in (5, 12, 19):
        k0, info0 = render(rec.gyro_t, rec.gyro_rate, rec.calibration, float(rec.t[i]), deblur)
        k1, info1 = render(slow.gyro_t, slow.gyro_rate, slow.calibration, float(slow.t[i]), deblur)
        assert abs(info1["n_samples"] - info0["n_samples"]) <= 1     # a sample on the window's edge
        a = k0.kernels if mode == "grid" else [[k0]]
        b = k1.kernels if mode == "grid" else [[k1]]
        for ra, rb in zip(a, b, strict=True):
            for ka, kb in zip(ra, rb, strict=True):
                assert kb.origin == ka.origin and kb.coverage == pytest.approx(ka.coverage)
                np.testing.assert_allclose(kb.weights, ka.weights, atol=2e-5 * float(ka.weights.max()))


def test_daemon_sets_scale_the_latency_caps_and_the_windows_not_the_shares():
    from thermod.runtime import config

    cfg = config.load()
    sets = dict(s.split("=") for s in daemon_sets(2.0, cfg))
    assert float(sets["deblur.max_solve_s"]) == pytest.approx(2 * cfg.deblur.max_solve_s, abs=1e-4)
    assert float(sets["deblur.latency_p99_s"]) == pytest.approx(2 * cfg.deblur.latency_p99_s, abs=1e-4)
    assert float(sets["monitor.window_s"]) == pytest.approx(2 * cfg.monitor.window_s)
    assert float(sets["pipeline.gyro_ring_s"]) == pytest.approx(2 * cfg.pipeline.gyro_ring_s)
    assert float(sets["monitor.max_window_s"]) == pytest.approx(2 * cfg.monitor.max_window_s)
    assert not any(k.endswith("cpu_share") for k in sets)
