"""ClockMapper: lower-envelope fit of device counters to host time, drift, jumps."""

import numpy as np
import pytest

from thermod.errors import DeviceError
from thermod.io.clock import ClockMapper


def fifo_reads(seconds, *, drift_ppm=250.0, p_late=0.01, t0=500.0, seed=0, latency=60e-6):
    """Simulated 1 kHz FIFO read every 5–5.5 ms: (newest seq, arrival) per read, true period."""
    rng = np.random.default_rng(seed)
    period = 1e-3 * (1 + drift_ppm * 1e-6)
    out, t = [], t0 + 0.001
    while t < t0 + seconds:
        t += 0.005 + rng.uniform(0, 0.0005)
        a = t + latency + rng.uniform(0, 20e-6)
        if rng.random() < p_late:
            a += rng.uniform(0.002, 0.020)
        out.append((int(np.floor((t - t0) / period)), a))
    return out, t0, period


def mapped_errors(reads, t0, period, mapper):
    errs, naive, prev = [], [], -1
    for s, a in reads:
        if s <= prev:
            continue
        idx = np.arange(prev + 1, s + 1)
        mapper.observe(s, a)
        errs.append(mapper.to_host(idx) - (t0 + idx * period))
        naive.append(a - (t0 + idx * period))
        prev = s
    return np.concatenate(errs), np.concatenate(naive)


def test_lower_envelope_beats_read_time_stamping():
    reads, t0, period = fifo_reads(20.0, seed=1)
    m = ClockMapper(1e-3, window_s=10.0)
    err, naive = mapped_errors(reads, t0, period, m)
    # the bias is the bus latency (60–80 µs), which no host-side fit can see; the spread is tiny
    assert np.std(err) < 0.05e-3
    assert np.max(np.abs(err)) < 0.5e-3
    assert 40e-6 < np.median(err) < 120e-6
    assert np.std(naive) > 1e-3 and np.max(naive) > 10e-3       # what stamping by read time gives
    assert m.drift_ppm == pytest.approx(250.0, abs=15.0)
    assert 0 < m.residual_std_s < 200e-6
    assert m.resets == 0


@pytest.mark.parametrize("drift_ppm", [-150.0, 0.0, 80.0])
def test_drift_tracked(drift_ppm):
    reads, t0, period = fifo_reads(8.0, drift_ppm=drift_ppm, seed=2)
    m = ClockMapper(1e-3, window_s=5.0)
    err, _ = mapped_errors(reads, t0, period, m)
    assert m.drift_ppm == pytest.approx(drift_ppm, abs=15.0)
    assert np.std(err[len(err) // 2:]) < 20e-6


def test_drift_change_followed_by_sliding_window():
    # the oscillator warms up: 0 ppm for 10 s, then +300 ppm; a 4 s window follows it
    m = ClockMapper(1e-3, window_s=4.0)
    seq, tt = 0, 100.0
    errs = []
    for i in range(4000):                     # 5 ms reads, 20 s
        ppm = 0.0 if i < 2000 else 300.0
        tt += 0.005 * (1 + ppm * 1e-6)        # true time of the newest sample advances
        seq += 5
        m.observe(seq, tt + 50e-6 + (i * 37 % 11) * 10e-6)
        if i > 3500:
            errs.append(m.to_host(seq) - tt)
    assert m.drift_ppm == pytest.approx(300.0, abs=10.0)
    assert np.max(np.abs(np.array(errs) - 50e-6)) < 30e-6


def test_counter_reset_and_host_steps_recover():
    m = ClockMapper(1e-3, window_s=5.0)
    t = 10.0
    for k in range(400):                      # 2 s at +100 ppm
        m.observe(5 * k, t + 5 * k * 1.0001e-3)
    assert m.drift_ppm == pytest.approx(100.0, abs=1.0)
    # device reboots: counter restarts at 0 two seconds later
    base = t + 2.0 + 0.5
    assert m.observe(0, base) is True
    assert m.resets == 1
    assert m.to_host(0) == pytest.approx(base)
    assert m.drift_ppm == pytest.approx(100.0, abs=1.0)   # the oscillator is the same
    for k in range(1, 200):
        m.observe(5 * k, base + 5 * k * 1.0001e-3)
    assert m.to_host(1000) == pytest.approx(base + 1.0001, abs=5e-6)
    # host clock steps back 10 ms: an arrival earlier than possible restarts at once
    step_back = base - 0.010
    assert m.observe(1000, step_back + 1.0001) is True
    assert m.resets == 2
    # host clock steps forward 50 ms: confirmed after 0.5 s of late arrivals, then remapped
    later = step_back + 0.050
    jumped = [m.observe(1000 + 5 * k, later + (1000 + 5 * k) * 1.0001e-3) for k in range(1, 140)]
    assert sum(jumped) == 1 and m.resets == 3
    assert m.to_host(2000) == pytest.approx(later + 2.0002, abs=5e-6)


def test_single_late_reads_never_pull_the_fit():
    m = ClockMapper(1e-3, window_s=5.0)
    for k in range(1000):
        late = 0.015 if k % 50 == 7 else 0.0
        m.observe(5 * k, 3.0 + 5e-3 * k + late)
    assert m.resets == 0
    assert m.to_host(5000) == pytest.approx(3.0 + 5.0, abs=1e-9)
    assert m.drift_ppm == pytest.approx(0.0, abs=1e-3)


def test_nanosecond_counters_beyond_float_precision():
    # a GigE camera timestamp in ns, ~1.8e18 (exceeds 2**53): mapping must keep sub-µs precision
    m = ClockMapper(1e-9, window_s=10.0, name="gige")
    base = 1_800_000_000_123_456_789
    for k in range(300):
        m.observe(base + k * 20_000_000 + 7, 50.0 + k * 0.02)
    t = m.to_host(np.array([base + 7, base + 299 * 20_000_000 + 7], dtype=np.int64))
    assert t.dtype == np.float64
    assert t == pytest.approx([50.0, 50.0 + 299 * 0.02], abs=1e-7)
    assert m.to_host(base + 7 + 10_000_000) == pytest.approx(50.01, abs=1e-7)


def test_errors_name_the_device():
    with pytest.raises(DeviceError, match="imu0.*no clock observations"):
        ClockMapper(1e-3, name="imu0").to_host(5)
    with pytest.raises(DeviceError, match="nominal_period_s"):
        ClockMapper(0.0)
    with pytest.raises(DeviceError, match="finite"):
        ClockMapper(1e-3).observe(1, float("nan"))


def test_growing_backlog_cannot_fake_an_impossible_drift():
    # An overloaded reader falling 30 ms further behind every second tilts the lower envelope by
    # 30 000 ppm; no oscillator drifts that much, so the slope stays within max_drift_ppm and the
    # line stays at or below every arrival (never stamps a sample later than it was received).
    reads, t0, period = fifo_reads(6.0, drift_ppm=0.0, p_late=0.0, seed=4)
    m = ClockMapper(1e-3, window_s=5.0, max_drift_ppm=2000.0)
    for s, a in reads:
        a_late = a + 0.030 * (a - t0)
        m.observe(s, a_late)
        assert m.to_host(s) <= a_late + 1e-9
    assert abs(m.drift_ppm) <= 2000.0 + 1e-6
