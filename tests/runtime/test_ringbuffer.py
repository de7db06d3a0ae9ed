"""Ring buffers: windows by time, gaps, clock jumps, and a writer and readers hammering concurrently
(every copy a reader gets must be internally consistent: never a half-written batch or frame)."""

import threading
import time

import numpy as np
import pytest

from thermod.runtime.rings import FrameRing, GyroRing


def _rates(seq):
    seq = np.asarray(seq, np.float64)
    return np.stack([np.sin(seq * 1e-3), seq * 1e-4, -seq * 1e-5], 1).astype(np.float32)


def test_window_by_time_with_padding():
    r = GyroRing(100)
    seq = np.arange(50)
    r.write(seq * 1e-3, _rates(seq), 0)
    w = r.window(0.0105, 0.0205, pad=0)
    np.testing.assert_array_equal(w.seq, np.arange(11, 21))
    w = r.window(0.0105, 0.0205, pad=1)
    np.testing.assert_array_equal(w.seq, np.arange(10, 22))
    np.testing.assert_allclose(w.t, w.seq * 1e-3)
    np.testing.assert_array_equal(w.rate, _rates(w.seq))
    assert w.rate.dtype == np.float32 and w.t.dtype == np.float64
    assert not w.gap and w.newest_t == pytest.approx(0.049) and w.oldest_t == 0.0
    # window edges: (t0, t1] – a sample exactly at t1 is inside, exactly at t0 is not
    w = r.window(0.010, 0.020, pad=0)
    assert w.seq[0] == 11 and w.seq[-1] == 20


def test_wraparound_keeps_newest_capacity():
    r = GyroRing(64)
    for k in range(10):
        s = np.arange(k * 20, k * 20 + 20)
        r.write(s * 1e-3, _rates(s), int(s[0]))
    assert r.count == 200 and r.samples_written == 200
    w = r.window(-1, 1, pad=0)
    np.testing.assert_array_equal(w.seq, np.arange(136, 200))
    assert w.oldest_t == pytest.approx(0.136)
    # a batch larger than the ring keeps its newest samples and marks the lost head as a gap
    s = np.arange(200, 300)
    r.write(s * 1e-3, _rates(s), 200)
    w = r.window(-1, 1, pad=0)
    np.testing.assert_array_equal(w.seq, np.arange(236, 300))


def test_gap_flags_inside_window():
    r = GyroRing(200)
    s1 = np.arange(0, 40)
    r.write(s1 * 1e-3, _rates(s1), 0)
    s2 = np.arange(60, 100)          # 20 samples lost (FIFO overflow) before seq 60
    r.write(s2 * 1e-3, _rates(s2), 60, gap_before=True)
    assert r.gaps_marked == 1
    assert r.window(0.070, 0.090).gap is False          # window entirely after the gap
    assert r.window(0.010, 0.030).gap is False          # entirely before (the gap is 10 samples later)
    assert r.window(0.030, 0.070).gap is True           # spans it
    assert r.window(0.020, 0.0395, pad=0).gap is True   # the next sample is the first after the gap
    assert r.window(0.020, 0.030, pad=0).gap is False


def test_hole_in_time_is_a_gap():
    r = GyroRing(200, max_step_s=0.004)
    s = np.arange(0, 30)
    r.write(s * 1e-3 - 0.5, _rates(s), 0)                 # a batch stamped 0.5 s early …
    s2 = np.arange(30, 80)
    r.write(s2 * 1e-3, _rates(s2), 30)                    # … then correct times: seq has no gap, time has
    assert r.time_holes == 1 and r.gaps_marked == 0
    assert r.window(0.035, 0.045).gap is False
    w = r.window(0.0, 0.01)
    assert w.gap is True and w.seq[0] == 29                 # the early sample is padding
    r.write(np.array([0.080, 0.0805, 0.090]), _rates([80, 81, 82]), 80)   # a hole inside a batch
    assert r.time_holes == 2 and r.window(0.085, 0.095, pad=0).gap is True


def test_clock_jump_starts_new_epoch():
    r = GyroRing(100)
    s = np.arange(30)
    r.write(5.0 + s * 1e-3, _rates(s), 0)
    r.write(1.0 + s * 1e-3, _rates(s + 30), 30)          # host time went backwards
    assert r.clock_jumps == 1
    w = r.window(-10, 10, pad=0)
    np.testing.assert_array_equal(w.seq, np.arange(30, 60))   # old epoch unreadable
    assert w.t[0] == pytest.approx(1.0)
    # a batch whose own times step back keeps only its part after the last backward step
    r.write(np.array([2.0, 2.001, 1.5, 1.501]), _rates(np.arange(60, 64)), 60)
    assert r.clock_jumps == 2
    np.testing.assert_array_equal(r.window(-10, 10, pad=0).seq, [62, 63])
    with pytest.raises(ValueError, match="gyro batch"):
        r.write(np.array([np.nan]), np.zeros((1, 3)), 64)


def test_wait_until_times_out_and_wakes():
    r = GyroRing(100)
    t0 = time.monotonic()
    assert r.wait_until(1.0, timeout=0.05) is False
    # never before its timeout (a guarantee); the upper bound, 100×, only catches a wait that hangs
    assert 0.05 <= time.monotonic() - t0 < 5.0

    def later():
        time.sleep(0.05)
        r.write(np.array([0.5, 1.0]), np.zeros((2, 3)), 0)

    th = threading.Thread(target=later)
    th.start()
    t0 = time.monotonic()
    assert r.wait_until(1.0, timeout=60.0) is True
    # woken by the write, not by its 60 s timeout (a bound no loaded machine comes near)
    assert time.monotonic() - t0 < 30.0
    th.join()


def test_gyro_ring_writer_and_readers_hammering():
    """A small ring lapped constantly: every window a reader gets is consecutive and matches its seq."""
    r = GyroRing(257)
    stop = threading.Event()
    errors, reads = [], [0, 0]
    total = 30_000

    def writer():
        s = 0
        rng = np.random.default_rng(1)
        while s < total:
            n = min(int(rng.integers(1, 40)), total - s)
            seq = np.arange(s, s + n)
            r.write(seq * 1e-3, _rates(seq), s)
            s += n
            if s % 7 == 0:
                time.sleep(0)
        stop.set()

    def reader(k):
        rng = np.random.default_rng(10 + k)
        while not stop.is_set():
            newest = r.newest_t
            if not np.isfinite(newest):
                continue
            t1 = newest - rng.uniform(0, 0.2)
            w = r.window(t1 - 0.045, t1)
            reads[k] += 1
            if len(w) == 0:
                continue
            if not (np.all(np.diff(w.seq) == 1) and np.allclose(w.t, w.seq * 1e-3)
                    and np.array_equal(w.rate, _rates(w.seq))):
                errors.append((w.seq[:3], w.t[:3]))

    threads = [threading.Thread(target=writer)]
    threads += [threading.Thread(target=reader, args=(k,)) for k in range(2)]
    for th in threads:
        th.start()
    for th in threads:
        th.join(60)
    assert not errors, errors[:3]
    assert r.samples_written == total
    assert min(reads) > 100


def test_frame_ring_in_order_reads_and_overrun():
    fr = FrameRing(4, (6, 8))
    for k in range(3):
        fr.write(np.full((6, 8), k, np.uint16), t=k * 0.02, frame_id=k + 1, arrival=k * 0.02 + 0.001)
    s = fr.get(1, timeout=0)
    assert s.index == 1 and s.frame_id == 2 and s.t == pytest.approx(0.02) and np.all(s.image == 1)
    assert fr.get(3, timeout=0.01) is None
    assert fr.stamp(1) == pytest.approx((0.02, 0.021)) and fr.stamp(3) is None
    for k in range(3, 9):
        fr.write(np.full((6, 8), k, np.uint16), t=k * 0.02, frame_id=k + 1, arrival=0.0)
    assert fr.get(2, timeout=0) == 5          # overwritten: oldest available is 5
    assert fr.stamp(4) is None and fr.stamp(5) == pytest.approx((0.1, 0.0)) and fr.stamp(9) is None
    with pytest.raises(ValueError, match=r"frame shape \(5, 8\) does not match the ring's \(6, 8\)"):
        fr.write(np.zeros((5, 8), np.uint16), 0.0, 0, 0.0)


def test_frame_ring_writer_and_reader_hammering():
    fr = FrameRing(3, (48, 64))
    n = 3000
    got, lost, bad = [], [0], []

    def writer():
        for k in range(n):
            fr.write(np.full((48, 64), k % 65536, np.uint16), t=float(k), frame_id=k, arrival=float(k))
            if k % 3 == 0:
                time.sleep(0)

    th = threading.Thread(target=writer)
    th.start()
    i = 0
    while i < n:
        s = fr.get(i, timeout=2.0)
        if s is None:
            break
        if isinstance(s, int):
            lost[0] += s - i
            i = s
            continue
        if not (np.all(s.image == s.frame_id) and s.frame_id == i and s.t == float(i)):
            bad.append(i)
        got.append(i)
        i += 1
    th.join()
    assert not bad
    assert len(got) + lost[0] == n      # every frame either read intact or counted as lost
    assert len(got) > 0
