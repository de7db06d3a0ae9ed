"""Property-based fuzzing of the device decoders (Hypothesis, bounded for CI): serial IMU frames and
IIO scan types and scan data. Whatever the bytes, only the driver's documented errors escape, every
good sample before (and after) a bad one is kept, and nothing absurd comes out: times finite,
increasing and not in the future, rates finite, lost counts bounded by host time."""

import math
import os
import struct
import time
import tty

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from thermod.drivers.iio import IIOError, IIOGyro, parse_type
from thermod.drivers.serial_imu import (
    MAX_FRAME,
    MAX_RATE_RAD_S,
    SYNC,
    FrameParser,
    SerialIMU,
    SerialIMUError,
    crc16_ccitt,
)
from thermod.sim.emu_iio import IIOEmulator

FUZZ = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
RATE = st.floats(-30.0, 30.0, allow_nan=False, width=32)


def frame(seq, t_us, rate, scale=None):
    """A frame with any field values and a valid CRC (type 2 when ``scale`` is given)."""
    if scale is None:
        body = struct.pack("<BBII3f", 20, 1, seq & 0xFFFFFFFF, t_us & 0xFFFFFFFF, *rate)
    else:
        q = np.clip(np.nan_to_num(np.asarray(rate, np.float64) * 1000), -32768, 32767).astype(int)
        body = struct.pack("<BBII3hf", 18, 2, seq & 0xFFFFFFFF, t_us & 0xFFFFFFFF, *q.tolist(), scale)
    return SYNC + body + struct.pack("<H", crc16_ccitt(body))


def feed_in_chunks(parser, data, cuts):
    out, prev = [], 0
    for c in sorted({min(c, len(data)) for c in cuts}) + [len(data)]:
        out += parser.feed(data[prev:c])
        prev = c
    return out


def check_rates(frames):
    for _, _, r in frames:
        assert all(math.isfinite(x) and abs(x) <= MAX_RATE_RAD_S for x in r)


# -- serial parser ---------------------------------------------------------------------------------
@FUZZ
@given(st.binary(max_size=600), st.lists(st.integers(0, 600), max_size=8))
def test_serial_parser_random_bytes(data, cuts):
    p = FrameParser()
    got = feed_in_chunks(p, data, cuts)
    check_rates(got)
    # every byte is garbage, part of a frame (24 or 26 bytes), a rejected sync, or still buffered
    assert len(p.buf) < MAX_FRAME and len(got) == p.frames
    assert p.garbage_bytes + p.crc_errors + len(p.buf) + 24 * (p.frames + p.invalid_rates) <= len(data)


@FUZZ
@given(st.lists(st.tuples(RATE, RATE, RATE, st.booleans()), min_size=1, max_size=12),
       st.lists(st.tuples(st.integers(0, 400), st.integers(0, 255)), max_size=6),
       st.lists(st.integers(0, 400), max_size=8), st.binary(max_size=20))
def test_serial_parser_mutated_frames_split_across_reads(rates, flips, cuts, junk):
    frames = [frame(i, 1000 * i, r[:3], scale=1e-3 if r[3] else None) for i, r in enumerate(rates)]
    original = junk + b"".join(frames)
    stream = bytearray(original)
    for pos, val in flips:
        if pos < len(stream):
            stream[pos] = val
    p = FrameParser()
    got = feed_in_chunks(p, bytes(stream), cuts)
    check_rates(got)
    # a frame is intact when no flip touched it: every intact frame before the first damaged one is
    # received, in order (later ones may be swallowed by a damaged length only up to the next sync)
    first_damage = min((i for i in range(len(stream)) if stream[i] != original[i]), default=len(stream))
    intact = []
    start = len(junk)
    for i, f in enumerate(frames):
        if start + len(f) > first_damage:
            break
        intact.append(i)
        start += len(f)
    assert [g[0] for g in got[:len(intact)]] == intact
    # the same bytes in one read give the same frames
    assert [g[:2] for g in FrameParser().feed(bytes(stream))] == [g[:2] for g in got]


BAD_RATE = st.sampled_from([math.nan, math.inf, -math.inf, 1e4, 0.5])
BAD_SCALE = st.sampled_from([None, math.nan, math.inf, 0.0, -1e-3, 1e-3])


def plausible(x, scale):
    if scale is None:
        return math.isfinite(x) and abs(x) <= MAX_RATE_RAD_S
    return math.isfinite(scale) and scale > 0          # int16 × 1e-3 stays within ±33 rad/s


@FUZZ
@given(st.lists(st.tuples(BAD_RATE, BAD_SCALE), min_size=1, max_size=8))
def test_serial_parser_drops_non_finite_rates_and_keeps_the_rest(bad):
    stream, expect = b"", []
    for i, (x, scale) in enumerate(bad):
        stream += frame(2 * i, 0, (0.1, 0.2, 0.3))
        expect.append(2 * i)
        stream += frame(2 * i + 1, 0, (x, 0.0, 0.0), scale=scale)
        if plausible(x, scale):
            expect.append(2 * i + 1)
    p = FrameParser()
    got = p.feed(stream)
    check_rates(got)
    assert [g[0] for g in got] == expect and p.invalid_rates == 2 * len(bad) - len(expect)


# -- serial driver: device counters that jump ------------------------------------------------------
SEQ_STEP = st.sampled_from(["next", "next", "next", "skip", "back", "same", "jump"])
TIME_STEP = st.sampled_from(["next", "next", "next", "zero", "back", "same", "jump", "wrap"])


@pytest.fixture(scope="module")
def pty_pair():
    master, slave = os.openpty()
    tty.setraw(slave)
    os.set_blocking(master, False)
    yield master, os.ttyname(slave)
    os.close(master)
    os.close(slave)


@FUZZ
@given(st.lists(st.tuples(SEQ_STEP, TIME_STEP, RATE), min_size=1, max_size=60), st.integers(1, 4))
def test_serial_driver_survives_any_device_counters(pty_pair, steps, n_writes):
    master, path = pty_pair
    seq, t_us, frames = 1000, 5_000_000, []
    for s_kind, t_kind, r in steps:
        seq = {"next": seq + 1, "skip": seq + 3, "back": seq - 50, "same": seq, "jump": seq + 2**30}[s_kind]
        t_us = {"next": t_us + 1000, "zero": 0, "back": t_us - 70_000, "same": t_us, "jump": t_us + 2**31 - 7,
                "wrap": 2**32 - 300}[t_kind]
        frames.append(frame(seq, t_us, (r, -r, 0.5)))
    gyro = SerialIMU(path, low_latency=False)
    t_start = time.monotonic()
    gyro.start()
    try:
        chunk = -(-len(frames) // n_writes)
        batches = []
        for k in range(0, len(frames), chunk):
            os.write(master, b"".join(frames[k:k + chunk]))
            deadline = time.monotonic() + 30.0         # returns once read; 30 s only catches a hang
            while gyro.stats()["frames"] < min(len(frames), k + chunk) and time.monotonic() < deadline:
                b = gyro.poll(0.01)
                if b is not None:
                    batches.append(b)
        while (b := gyro.poll(0.0)) is not None:
            batches.append(b)
    except SerialIMUError:
        return                                          # a documented error is an acceptable answer
    finally:
        gyro.stop()
    t_now = time.monotonic()
    assert sum(len(b) for b in batches) == len(frames)  # every frame with a good CRC and rate is kept
    t = np.concatenate([b.t for b in batches])
    r = np.concatenate([b.rate for b in batches])
    assert np.all(np.isfinite(t)) and np.all(np.diff(t) > 0) and np.all(np.isfinite(r))
    # not in the future beyond the spacing forced on samples whose device times stand still
    assert t[-1] <= t_now + 0.5e-3 * len(frames) + 0.01
    # lost counts: seq gaps the device's own clock confirms, or host-time estimates across epochs
    assert sum(b.n_lost for b in batches) <= (t_now - t_start) * gyro.rate_hz + 2 * len(frames) + 10
    for prev, b in zip(batches[:-1], batches[1:], strict=True):
        assert b.seq >= prev.seq + len(prev)


# -- IIO scan types ----------------------------------------------------------------------------------
TYPE_TEXT = st.one_of(
    st.builds(lambda e, s, b, sb, rep, sh: f"{e}:{s}{b}/{sb}{rep}>>{sh}",
              st.sampled_from(["le", "be", "xe"]), st.sampled_from("su"), st.integers(0, 70),
              st.sampled_from([0, 8, 12, 16, 24, 32, 64, 128]),
              st.one_of(st.just(""), st.integers(0, 70).map(lambda r: f"X{r}")), st.integers(0, 70)),
    st.text(max_size=30),
    st.from_regex(r"\A(le|be):[su]\d{1,5}/\d{1,5}(X\d{1,3})?>>\d{1,5}\Z"),
)


@FUZZ
@given(TYPE_TEXT)
def test_iio_scan_type_parses_or_says_why(text):
    try:
        t = parse_type(text, "in_anglvel_x_type")
    except IIOError as e:
        assert "in_anglvel_x_type" in str(e)
        return
    assert t.storage_bits in (8, 16, 32, 64) and 0 < t.bits <= t.storage_bits - t.shift and t.repeat >= 1


def run_iio(emu, data, rate_hz=1000.0):
    """Start the driver on the emulated tree, write ``data`` (bytes, or a function of the started
    driver returning them) into its FIFO ourselves, and read it all."""
    gyro = IIOGyro("icm42688", sysfs_root=emu.sysfs_root, dev_path=emu.dev_path, rate_hz=rate_hz)
    gyro.start()
    batches = []
    try:
        if callable(data):
            data = data(gyro)
        w = os.open(emu.dev_path, os.O_WRONLY | os.O_NONBLOCK)
        try:
            for k in range(0, len(data), 4096):
                os.write(w, data[k:k + 4096])
                while (b := gyro.poll(0.0)) is not None:
                    batches.append(b)
        finally:
            os.close(w)
        while (b := gyro.poll(0.0)) is not None:
            batches.append(b)
    finally:
        gyro.stop()
    return gyro, batches, len(data)


def check_batches(gyro, batches, n_records, t_start):
    t_now = time.monotonic()
    assert sum(len(b) for b in batches) == n_records
    if not batches:
        return
    t = np.concatenate([b.t for b in batches])
    r = np.concatenate([b.rate for b in batches])
    assert np.all(np.isfinite(t)) and np.all(np.diff(t) > 0) and np.all(np.isfinite(r))
    assert t[-1] <= t_now + 0.5 / gyro.rate_hz * n_records + 0.01
    assert sum(b.n_lost for b in batches) <= (t_now - t_start) * gyro.rate_hz + n_records + 10
    for prev, b in zip(batches[:-1], batches[1:], strict=True):
        assert b.seq == prev.seq + len(prev) + b.n_lost


@pytest.fixture(scope="module")
def iio_tree():
    """The emulated sysfs tree and FIFO, without its writer: the tests write the records."""
    emu = IIOEmulator()
    yield emu
    emu.stop()


ELEMENTS = ["in_anglvel_x", "in_anglvel_y", "in_anglvel_z", "in_timestamp"]


@FUZZ
@given(st.lists(TYPE_TEXT, min_size=4, max_size=4), st.binary(max_size=3000))
def test_iio_random_scan_types_and_random_data(iio_tree, types, data):
    emu = iio_tree
    saved = {el: (emu.dir / f"scan_elements/{el}_type").read_text() for el in ELEMENTS}
    try:
        for el, text in zip(ELEMENTS, types, strict=True):
            (emu.dir / f"scan_elements/{el}_type").write_text(text + "\n")
        t_start = time.monotonic()
        try:
            gyro, batches, _ = run_iio(emu, data)
        except IIOError as e:
            assert "iio:device0" in str(e)               # refused, naming the device and the file
            return
        check_batches(gyro, batches, len(data) // gyro.record_size, t_start)
    finally:
        for el, text in saved.items():
            (emu.dir / f"scan_elements/{el}_type").write_text(text)


STAMP = st.sampled_from(["ok", "ok", "ok", "ok", "zero", "negative", "huge", "back", "ahead", "hole",
                         "before-start"])


@FUZZ
@given(st.lists(STAMP, min_size=1, max_size=80), st.integers(-32768, 32767))
def test_iio_any_time_stamps(iio_tree, kinds, raw):
    # 100 kHz, so that 80 good stamps 10 µs apart fit between the buffer enable and the read
    def records(gyro):
        time.sleep(0.002)
        now_ns = time.monotonic_ns()
        holes = np.cumsum([50_000 * (k == "hole") for k in kinds])          # a hole delays every later stamp
        base = now_ns - (len(kinds) + 10) * 10_000 - int(holes[-1])
        bad = {"zero": 0, "negative": -12345, "huge": 2**62, "back": base - 10**10, "ahead": now_ns + 10**9,
               "before-start": int(t_start * 1e9) - 10**8}
        stamps = [bad[k] if k in bad else base + i * 10_000 + int(holes[i]) for i, k in enumerate(kinds)]
        y = -raw if raw > -32768 else 0
        return b"".join(struct.pack("<3h2xq", raw, y, 7, s) for s in stamps)

    t_start = time.monotonic()
    gyro, batches, size = run_iio(iio_tree, records, rate_hz=100_000.0)
    assert gyro.record_size == 16 and size == 16 * len(kinds)
    check_batches(gyro, batches, len(kinds), t_start)
    assert all(np.all(b.rate[:, 2] == np.float32(7 * gyro.scale[2])) for b in batches)
    if set(kinds) <= {"ok", "hole"}:
        assert gyro.stats()["resets"] == 0               # good stamps and holes are no new epoch
        assert sum(b.n_lost for b in batches) == 5 * kinds.count("hole") - (kinds[0] == "hole") * 5
