"""Scheduler logic on synthetic inputs through the real renderer and deconvolver: coverage waits,
pass-through reasons, drop-oldest under overload, worker crash → replaced, in-order output, and
deblurred frames closer to the truth than the blurry input."""

import threading
import time

import numpy as np
import pytest

from thermod.physics import kernels
from thermod.physics.calibration import Calibration
from thermod.physics.deconv import Deconvolver
from thermod.runtime.config import DeblurConfig, PipelineConfig
from thermod.runtime.pipeline import Pipeline, kernel_window
from thermod.runtime.rings import FrameRing, GyroRing
from thermod.sim.scenes import load_scene

H, W = 120, 160
CAL = Calibration(width=W, height=H, fx=366.0, fy=366.0, cx=79.5, cy=59.5)
RATE = 1000.0


def omega(t):
    """Yaw pan plus a wobble in pitch: ~9 px of blur over 5τ at fx = 366."""
    t = np.asarray(t, np.float64)
    return np.stack([0.2 * np.sin(2 * np.pi * 3 * t), 0.6 + 0.1 * np.cos(2 * np.pi * 2 * t), 0.02 + 0 * t], 1)


class Collector:
    def __init__(self):
        self.out, self.lock, self.event = [], threading.Lock(), threading.Event()

    def __call__(self, o):
        with self.lock:
            self.out.append(o)
        self.event.set()

    def wait(self, n, timeout=20.0):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self.lock:
                if len(self.out) >= n:
                    return list(self.out)
            time.sleep(0.005)
        with self.lock:
            return list(self.out)


@pytest.fixture(scope="module")
def sharp():
    return load_scene("texture", (H, W), seed=3).astype(np.float32)


def gyro_until(ring, t_start, t_end, seq0=0, gap=False):
    n = int(round((t_end - t_start) * RATE)) + 1
    t = t_start + np.arange(n) / RATE
    ring.write(t, omega(t).astype(np.float32), seq0, gap_before=gap)
    return seq0 + n


def blurry_frame(sharp, t_frame, rng):
    tg = t_frame - 0.1 + np.arange(150) / RATE
    k = kernels.render_thermal_kernel(tg, omega(tg), CAL, t_frame)
    b = kernels.blur(sharp, k) + rng.normal(0, 2.0, sharp.shape)
    return np.clip(np.round(b), 0, 65535).astype(np.uint16), k


def make(emit, *, workers=1, job_queue=4, wait=0.05, factory=None, deblur=None):
    gr, fr = GyroRing(5000), FrameRing(32, (H, W))
    cfg = PipelineConfig(workers=workers, job_queue=job_queue, wait_timeout_s=wait, reorder_timeout_s=2.0)
    p = Pipeline(gr, fr, CAL, deblur or DeblurConfig(), cfg, emit, deconvolver_factory=factory)
    p.warmup()
    return gr, fr, p


def test_kernel_window_is_5tau_plus_readout():
    a, b = kernel_window(CAL.replace(readout_s=0.01), DeblurConfig(), 10.0)
    assert b == 10.0 and a == pytest.approx(10.0 - 5 * 0.008 - 0.01)
    a, _ = kernel_window(CAL, DeblurConfig(kernel="photon"), 10.0)
    assert a == pytest.approx(10.0 - 0.02)      # one frame period at 50 Hz


def test_deblurs_in_order_and_beats_blurry_input(sharp):
    rng = np.random.default_rng(0)
    col = Collector()
    gr, fr, p = make(col, workers=2, job_queue=8)
    p.start()
    try:
        t0 = time.monotonic()
        gyro_until(gr, t0 - 0.2, t0 + 0.5)
        truth_k = []
        for i in range(6):
            tf = t0 + 0.05 + 0.02 * i
            img, k = blurry_frame(sharp, tf, rng)
            truth_k.append(k)
            fr.write(img, tf, frame_id=100 + i, arrival=time.monotonic())
            time.sleep(0.02)
        outs = col.wait(6)
    finally:
        p.stop()
    assert [o.frame_id for o in outs] == list(range(100, 106))
    assert all(o.deblurred and o.reason is None for o in outs)
    for o, k in zip(outs, truth_k, strict=True):
        assert o.image.dtype == np.float32 and o.image.shape == (H, W)
        assert o.coverage == pytest.approx(1.0, abs=1e-3) and o.n_samples >= 40
        assert o.kernel_size == k.weights.shape
        assert o.kernel_extent_px == pytest.approx(k.extent_px, rel=0.05)
    m = (slice(12, -12), slice(12, -12))
    blurry_err = np.sqrt(np.mean((fr.get(fr.head - 1, 0).image.astype(np.float32)[m] - sharp[m]) ** 2))
    deblur_err = np.sqrt(np.mean((outs[-1].image[m] - sharp[m]) ** 2))
    assert deblur_err < 0.7 * blurry_err, (deblur_err, blurry_err)
    st = p.stats()
    assert st["counters"]["deblurred"] == 6 and st["counters"]["frames_out"] == 6
    assert st["latency_p50_s"] is not None


def test_waits_for_gyro_then_deblurs(sharp):
    rng = np.random.default_rng(1)
    col = Collector()
    gr, fr, p = make(col, wait=0.5)
    p.start()
    try:
        now = time.monotonic()
        tf = now + 0.01
        seq = gyro_until(gr, now - 0.2, now - 0.01)        # gyro still short of the frame time
        img, _ = blurry_frame(sharp, tf, rng)
        fr.write(img, tf, frame_id=1, arrival=now)
        time.sleep(0.1)
        assert col.out == []                                 # still waiting (bounded) for coverage
        gyro_until(gr, now - 0.009, tf + 0.005, seq)
        outs = col.wait(1)
    finally:
        p.stop()
    assert len(outs) == 1 and outs[0].deblurred
    assert 0.09 < outs[0].t_done - now < 0.45


def test_missing_gyro_times_out_and_passes_through(sharp):
    col = Collector()
    gr, fr, p = make(col, wait=0.05)
    p.start()
    try:
        now = time.monotonic()
        gyro_until(gr, now - 0.2, now - 0.02)                # the newest 20 ms (most of the weight) missing
        fr.write(sharp.astype(np.uint16), now, frame_id=7, arrival=now)
        outs = col.wait(1)
        p.gyro_online = False                                # the daemon knows the gyro is down: no wait
        t1 = time.monotonic()
        fr.write(sharp.astype(np.uint16), t1, frame_id=8, arrival=t1)
        outs = col.wait(2)
    finally:
        p.stop()
    a, b = outs
    assert not a.deblurred and a.reason == "gyro_incomplete"
    # Eq. 18 weight of (t−40 ms, t−20 ms] with τ = 8 ms: (e^−2.5 − e^−5) / (1 − e^−5)
    assert a.coverage == pytest.approx((np.exp(-2.5) - np.exp(-5)) / (1 - np.exp(-5)), abs=0.01)
    assert a.latency_s == pytest.approx(0.05, abs=0.04)     # waited wait_timeout_s, not longer
    np.testing.assert_array_equal(a.image, sharp.astype(np.uint16).astype(np.float32))   # raw counts, f32
    assert b.reason == "gyro_offline" and b.latency_s < 0.03
    c = p.stats()["counters"]
    assert c["passthrough_gyro_incomplete"] == 1 and c["passthrough_gyro_offline"] == 1


def test_gap_inside_window_passes_through(sharp):
    col = Collector()
    gr, fr, p = make(col)
    p.start()
    try:
        now = time.monotonic()
        seq = gyro_until(gr, now - 0.2, now - 0.03)
        gyro_until(gr, now - 0.02, now + 0.2, seq + 10, gap=True)   # FIFO overflow: 10 samples lost
        fr.write(sharp.astype(np.uint16), now, frame_id=1, arrival=now)        # gap 20–30 ms before: in 5τ
        fr.write(sharp.astype(np.uint16), now + 0.1, frame_id=2, arrival=now)  # window after the gap
        outs = col.wait(2)
    finally:
        p.stop()
    assert [(o.frame_id, o.deblurred, o.reason) for o in outs] == [(1, False, "gyro_gap"), (2, True, None)]


def test_disabled_passes_everything_through(sharp):
    col = Collector()
    gr, fr, p = make(col, deblur=DeblurConfig(enabled=False))
    p.start()
    try:
        for i in range(3):
            fr.write(sharp.astype(np.uint16), time.monotonic(), frame_id=i, arrival=time.monotonic())
        outs = col.wait(3)
    finally:
        p.stop()
    assert [o.reason for o in outs] == ["disabled"] * 3


class SlowDeconvolver(Deconvolver):
    """The real deconvolver on a slow machine (fault injection for overload)."""

    def run(self, image, kernel, **kw):
        time.sleep(0.15)
        return super().run(image, kernel, **kw)


def test_overload_drops_oldest_job_and_publishes_it_passed_through(sharp):
    rng = np.random.default_rng(2)
    col = Collector()
    gr, fr, p = make(col, workers=1, job_queue=1, factory=lambda d: SlowDeconvolver(d.method, d.alpha, d.lam))
    p.start()
    try:
        t0 = time.monotonic()
        gyro_until(gr, t0 - 0.2, t0 + 1.0)
        n = 8
        for i in range(n):
            img, _ = blurry_frame(sharp, t0 + 0.02 * i, rng)
            fr.write(img, t0 + 0.02 * i, frame_id=i, arrival=time.monotonic())
            time.sleep(0.02)
        outs = col.wait(n, timeout=10)
    finally:
        p.stop()
    assert [o.frame_id for o in outs] == list(range(n))        # every frame exactly once, in order
    reasons = [o.reason for o in outs]
    c = p.stats()["counters"]
    assert c["jobs_dropped"] == reasons.count("overload") >= 3
    assert c["deblurred"] == sum(o.deblurred for o in outs) >= 2
    assert c["deblurred"] + c["jobs_dropped"] == n
    dropped = [o for o in outs if o.reason == "overload"]
    assert all(o.kernel_size is not None and o.coverage > 0.99 for o in dropped)   # kernel info kept


class CrashingDeconvolver(Deconvolver):
    """Raises on frames whose kernel was rendered for the poisoned frame time."""

    poisoned_t: float = -1.0

    def run(self, image, kernel, **kw):
        if abs(float(image.mean()) - 1234.0) < 1e-3:
            raise FloatingPointError("injected worker fault")
        return super().run(image, kernel, **kw)


def test_worker_exception_passes_frame_through_and_worker_is_replaced(sharp):
    rng = np.random.default_rng(3)
    col = Collector()
    gr, fr, p = make(col, workers=1, factory=lambda d: CrashingDeconvolver(d.method, d.alpha, d.lam))
    p.start()
    try:
        t0 = time.monotonic()
        gyro_until(gr, t0 - 0.2, t0 + 0.5)
        first = p.alive()["worker0"], p._workers[0]
        for i in range(4):
            img = np.full((H, W), 1234, np.uint16) if i == 1 else blurry_frame(sharp, t0 + 0.02 * i, rng)[0]
            fr.write(img, t0 + 0.02 * i, frame_id=i, arrival=time.monotonic())
            time.sleep(0.05)
        outs = col.wait(4)
        time.sleep(0.15)
        alive = p.alive()
    finally:
        p.stop()
    assert [(o.frame_id, o.deblurred, o.reason) for o in outs] == [
        (0, True, None), (1, False, "worker_error"), (2, True, None), (3, True, None)]
    c = p.stats()["counters"]
    assert c["worker_errors"] == 1 and c["workers_replaced"] == 1
    assert first[0] and alive["worker0"] and p._workers[0] is not first[1]


def test_update_swaps_settings_live(sharp):
    col = Collector()
    gr, fr, p = make(col)
    p.start()
    try:
        t0 = time.monotonic()
        gyro_until(gr, t0 - 0.2, t0 + 0.5)
        fr.write(sharp.astype(np.uint16), t0, frame_id=0, arrival=t0)
        col.wait(1)
        p.update(deblur=DeblurConfig(enabled=False))
        fr.write(sharp.astype(np.uint16), t0 + 0.02, frame_id=1, arrival=t0)
        col.wait(2)
        p.update(deblur=DeblurConfig(method="wiener"), calib=CAL.replace(tau_s=0.004))
        fr.write(sharp.astype(np.uint16), t0 + 0.04, frame_id=2, arrival=t0)
        outs = col.wait(3)
    finally:
        p.stop()
    assert [(o.deblurred, o.reason) for o in outs] == [(True, None), (False, "disabled"), (True, None)]
    assert p.calib.tau_s == 0.004 and p.deblur.method == "wiener" and p.counters["reloads"] == 2


def test_grid_mode_renders_a_kernel_grid(sharp):
    rng = np.random.default_rng(4)
    col = Collector()
    gr, fr, p = make(col, deblur=DeblurConfig(mode="grid", grid=(2, 2)))
    p.start()
    try:
        t0 = time.monotonic()
        gyro_until(gr, t0 - 0.2, t0 + 0.5)
        img, k = blurry_frame(sharp, t0, rng)
        fr.write(img, t0, frame_id=0, arrival=t0)
        outs = col.wait(1)
    finally:
        p.stop()
    assert outs[0].deblurred and outs[0].coverage > 0.99
    assert outs[0].kernel_extent_px == pytest.approx(k.extent_px, rel=0.25)
