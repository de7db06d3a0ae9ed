"""Register-chip gyro drivers against their register-level emulators, through the real bus seam
(smbus2 i2c_msg transactions / spidev-style xfer2), in real time (each test ≤ ~1 s)."""

import errno
import math
import time

import numpy as np
import pytest

from thermod.drivers.bmi088 import BMI088Error, BMI088Gyro
from thermod.drivers.bus import I2CBus, SPIBus
from thermod.drivers.gyro_base import GyroDeviceError
from thermod.drivers.icm42688 import ICM42688, ICM42688Error
from thermod.drivers.mpu6000 import MPU6000, MPU6000Error
from thermod.errors import DeviceError
from thermod.sim.emu_registers import BMI088GyroEmu, EmuI2C, EmuSPI, ICM42688Emu, MPU6000Emu

CHIPS = {"icm42688": (ICM42688, ICM42688Emu, ICM42688Error), "mpu6000": (MPU6000, MPU6000Emu, MPU6000Error),
         "bmi088": (BMI088Gyro, BMI088GyroEmu, BMI088Error)}
ID_REG = {"icm42688": "WHO_AM_I 0x75", "mpu6000": "WHO_AM_I 0x75", "bmi088": "GYRO_CHIP_ID 0x00"}


@pytest.fixture(autouse=True)
def fast_resets(monkeypatch):
    # the emulators reset instantly; the datasheet waits (100 ms MPU, 30 ms BMI) stay in the drivers
    monkeypatch.setattr(MPU6000, "reset_wait_s", 0.002)
    monkeypatch.setattr(BMI088Gyro, "reset_wait_s", 0.002)


def make_bus(kind, chip, address=0x68, **kw):
    return I2CBus(EmuI2C({0x68: chip}), address, **kw) if kind == "i2c" else SPIBus(EmuSPI(chip), **kw)


def collect_timed(gyro, n, timeout=0.01, hang_s=60.0):
    """Batches holding at least `n` samples, and for each the host time its poll returned (never
    earlier than its FIFO read). A loaded machine just takes longer; `hang_s` only catches a hang."""
    out, returned, t_end = [], [], time.monotonic() + hang_s
    while sum(len(b) for b in out) < n:
        assert time.monotonic() < t_end, f"{sum(len(b) for b in out)} of {n} samples: {gyro.stats()}"
        b = gyro.poll(timeout)
        if b is not None:
            out.append(b)
            returned.append(time.monotonic())
    return out, np.array(returned)


def collect(gyro, n, timeout=0.01):
    return collect_timed(gyro, n, timeout)[0]


def read_lateness(batches, returned, decode):
    """How long after its true time the newest sample of each batch was in hand: the read-time
    jitter of this run, which the clock fit's lower envelope must not follow."""
    newest = np.array([decode(b.rate[-1:, 0], b.t[-1:])[0] for b in batches])
    return returned - newest


LSB_S_2000DPS = math.radians(2000) / 32768 / 20.0    # sawtooth_clock: one LSB of the x rate in seconds


def cat(batches):
    return np.concatenate([b.t for b in batches]), np.concatenate([b.rate for b in batches])


def constant(w):
    w = np.asarray(w, np.float64)
    return lambda t: np.tile(w, (len(t), 1))


def sawtooth_clock(t_ref, period=1.0, slope=20.0):
    """A rate that encodes its own sample time: x = slope·((t − t_ref) mod period) − slope/2."""
    def fn(t):
        ph = np.mod(np.asarray(t) - t_ref, period)
        return np.stack([slope * ph - slope / 2, np.zeros_like(ph), np.full_like(ph, 0.5)], axis=1)

    def decode(rate_x, t_approx):
        ph = (rate_x.astype(np.float64) + slope / 2) / slope
        k = np.round((t_approx - t_ref - ph) / period)
        return t_ref + k * period + ph
    return fn, decode


@pytest.mark.parametrize("bus_kind", ["i2c", "spi"])
@pytest.mark.parametrize("fs", [2000.0, 1000.0, 500.0, 250.0, 125.0, 62.5, 31.25, 15.625])
def test_icm42688_rates_and_units_at_every_full_scale(bus_kind, fs):
    w = np.radians(fs) * np.array([0.61, -0.33, 0.97])          # within ±full scale on every axis
    chip = ICM42688Emu(rate_fn=constant(w), noise_rad_s=0.0)
    gyro = ICM42688(make_bus(bus_kind, chip), full_scale_dps=fs)
    gyro.start()
    t, r = cat(collect(gyro, 400))
    gyro.stop()
    lsb = math.radians(fs) / 32768
    assert r.dtype == np.float32 and t.dtype == np.float64 and r.shape == (len(t), 3)
    assert len(t) >= 35
    assert np.max(np.abs(r - w)) <= 0.5 * lsb * 1.0001          # exact up to quantisation
    # full-scale and ODR codes landed in GYRO_CONFIG0 (the driver read them back too)
    assert chip.regs[0x4F] == (ICM42688Emu.FS_DPS.index(fs) << 5) | 0x06
    assert chip.odr_hz() == 1000.0
    # the sample period on the device clock, once the clock fit has settled: until a fast read
    # corrects a late first one (a loaded machine), times stay monotonic but may run closer
    assert np.all(np.diff(t) > 0) and np.median(np.diff(t[len(t) // 2:])) == pytest.approx(1e-3, abs=1e-6)


@pytest.mark.parametrize("bus_kind", ["i2c", "spi"])
@pytest.mark.parametrize("fs", [250.0, 500.0, 1000.0, 2000.0])
def test_mpu6000_rates_and_units_at_every_full_scale(bus_kind, fs):
    w = np.radians(fs) * np.array([-0.8, 0.45, 0.12])
    chip = MPU6000Emu(rate_fn=constant(w), noise_rad_s=0.0)
    gyro = MPU6000(make_bus(bus_kind, chip), full_scale_dps=fs)
    gyro.start()
    t, r = cat(collect(gyro, 40))
    lsb = math.radians(fs) / 32768
    assert len(t) >= 35
    assert np.max(np.abs(r - w)) <= 0.5 * lsb * 1.0001
    assert (chip.regs[0x1B] >> 3) & 3 == MPU6000Emu.FS_DPS.index(fs)
    assert chip.odr_hz() == 1000.0 and chip.regs[0x23] == 0x70
    # SPI disables the I²C interface, as the datasheet requires for the MPU-6000
    assert bool(chip.regs[0x6A] & 0x10) == (bus_kind == "spi")


def test_mpu6000_sample_rate_divider():
    chip = MPU6000Emu(noise_rad_s=0.0)
    gyro = MPU6000(make_bus("i2c", chip), rate_hz=250.0)
    gyro.start()
    t, _ = cat(collect(gyro, 100, timeout=0.02))        # 0.4 s at 250 Hz
    assert chip.regs[0x19] == 3 and chip.regs[0x1A] & 7 == 1
    assert np.median(np.diff(t[len(t) // 2:])) == pytest.approx(0.004, rel=1e-3)   # once the fit settled
    with pytest.raises(MPU6000Error, match="rate_hz=300"):
        MPU6000(make_bus("i2c", chip), rate_hz=300.0)


@pytest.mark.parametrize("bus_kind", ["i2c", "spi"])
def test_icm42688_timestamps_follow_the_device_clock_not_the_read_time(bus_kind):
    fn, decode = sawtooth_clock(time.monotonic())
    chip = ICM42688Emu(rate_fn=fn, noise_rad_s=0.0, drift_ppm=300.0)
    gyro = ICM42688(make_bus(bus_kind, chip), full_scale_dps=2000.0, read_interval_s=0.003)
    gyro.start()
    batches, returned = collect_timed(gyro, 1200)
    t, r = cat(batches)
    truth = decode(r[:, 0], t)
    skip = len(t) // 4                        # after the first 0.3 s the drift has been fitted
    err = (t - truth)[skip:]
    # what stamping each sample with its read time would err by, in this run on this machine
    by_read = np.repeat(returned, [len(b) for b in batches])[skip:] - truth[skip:]
    lateness = read_lateness(batches, returned, decode)
    # sample times, not read times: the spread of the error is quantisation (20 rad/s per s at
    # 1.07 mrad/s per LSB → 53 µs) and drift tracking, a small part of the read-time spread (which
    # a 3 ms read interval alone makes ~0.9 ms); the offset is the lower envelope of the reads,
    # never later than the typical read
    q = LSB_S_2000DPS
    assert np.std(err) < 0.2 * np.std(by_read)
    assert -2 * q <= np.median(err) <= np.percentile(lateness, 10) + 2 * q
    assert np.all(np.diff(t) > 0)
    seqs = [b.seq for b in batches]
    assert seqs == list(np.cumsum([0] + [len(b) for b in batches[:-1]]))
    assert len(t) == chip.counters["popped"] // 8            # every sample the chip clocked out
    # the device oscillator runs 300 ppm fast: its ticks are shorter in host seconds. The fit follows
    # the lower envelope of the reads, so over this run's span it can be off by about the envelope's
    # own lateness (the fastest tenth of the reads) per span: 150 ppm on a quiet machine, more when
    # this run's reads were all late (test_clock checks the fit itself against known jitter)
    span = float(t[-1] - t[0])
    tol_ppm = max(150.0, 2e6 * float(np.percentile(lateness, 10)) / span)
    assert gyro.clock.drift_ppm == pytest.approx(-300.0, abs=tol_ppm)


def test_icm42688_16_byte_packets_with_accel():
    w = np.array([0.1, 0.2, -0.3])
    chip = ICM42688Emu(rate_fn=constant(w), noise_rad_s=0.0)
    gyro = ICM42688(make_bus("spi", chip), full_scale_dps=500.0, fifo_accel=True)
    gyro.start()
    assert chip.record_size() == 16 and chip.regs[0x5F] & 0x03 == 0x03
    t, r = cat(collect(gyro, 30))
    assert len(t) >= 30
    assert np.max(np.abs(r - w)) <= 0.5 * math.radians(500) / 32768 * 1.0001


@pytest.mark.parametrize("bus_kind", ["i2c", "spi"])
@pytest.mark.parametrize("fs", [2000.0, 1000.0, 500.0, 250.0, 125.0])
def test_bmi088_rates_and_units_at_every_full_scale(bus_kind, fs):
    w = np.radians(fs) * np.array([0.5, -0.99, 0.07])
    chip = BMI088GyroEmu(rate_fn=constant(w), noise_rad_s=0.0)
    gyro = BMI088Gyro(make_bus(bus_kind, chip), full_scale_dps=fs)
    gyro.start()
    t, r = cat(collect(gyro, 400))
    assert len(t) >= 35
    assert np.max(np.abs(r - w)) <= 0.5 * math.radians(fs) / 32768 * 1.0001
    assert chip.regs[0x0F] == BMI088GyroEmu.FS_DPS.index(fs)
    assert chip.regs[0x10] == 0x82 and chip.odr_hz() == 1000.0      # bit 7 reads 1
    assert chip.regs[0x3E] == 0x80                                   # stream mode, X/Y/Z
    assert np.median(np.diff(t[len(t) // 2:])) == pytest.approx(1e-3, abs=1e-6)   # once the fit settled


@pytest.mark.parametrize("name", ["icm42688", "mpu6000", "bmi088"])
def test_fifo_overflow_detected_flushed_counted(name):
    Driver, Emu, _ = CHIPS[name]
    fn, decode = sawtooth_clock(time.monotonic())
    chip = Emu(rate_fn=fn, noise_rad_s=0.0)
    gyro = Driver(make_bus("i2c", chip), full_scale_dps=2000.0)
    gyro.start()
    before = collect(gyro, 150)
    time.sleep(0.45)                     # FIFO: 256 (ICM), 170 (MPU) or 100 (BMI) samples
    after, returned = collect_timed(gyro, 250)
    st = gyro.stats()
    assert chip.counters["overflows"] >= 1 and chip.counters["flushes"] >= 2
    # the stall is one overflow; a reader preempted for longer than the FIFO lasts (a loaded
    # machine, BMI088: 100 ms) makes more, each of which must be accounted just as well
    batches = before + after
    gaps = [i for i, b in enumerate(batches) if b.gap_before]
    assert after[0].gap_before and st["gaps"] == len(gaps) and st["overflows"] >= len(gaps)
    assert st["lost"] == sum(batches[i].n_lost for i in gaps)
    for prev, b in zip(batches[:-1], batches[1:], strict=True):
        assert b.seq == prev.seq + len(prev) + b.n_lost
    # the lost count is estimated from host time; the truth is in the rates. The estimate is off by
    # what the reader's own preemption adds: ±2 samples when reads are timely, more when this run's
    # reads were late (a loaded machine), and at most the half-bracket around the flush that the
    # driver reports (`lost_uncertainty`: a reader preempted inside the flush's call)
    late = read_lateness(after, returned, decode)
    tol = 2 + int(math.ceil(1000.0 * max(float(np.percentile(late, 90)), 0.0))) + st["lost_uncertainty"]
    for i in gaps:
        t_last_true = decode(batches[i - 1].rate[-1:, 0], batches[i - 1].t[-1:])[0]
        t_next_true = decode(batches[i].rate[:1, 0], batches[i].t[:1])[0]
        true_lost = round((t_next_true - t_last_true) * 1000) - 1
        assert abs(batches[i].n_lost - true_lost) <= tol, (batches[i].n_lost, true_lost, tol)
        if batches[i] is after[0]:
            assert true_lost > 400                   # the 0.45 s stall
    # samples after a gap are intact and correctly timed (the clock fit restarted): never before
    # their true time, never later than the reads of this run delivered them
    t, r = cat(after)
    err = t - decode(r[:, 0], t)
    q = LSB_S_2000DPS
    assert -q <= err.min() and err.max() <= read_lateness(after, returned, decode).max() + q
    assert np.all(np.abs(r[:, 2] - 0.5) < 1e-3)


@pytest.mark.parametrize("name", ["icm42688", "mpu6000", "bmi088"])
def test_samples_after_an_overflow_keep_their_time_when_the_next_reads_are_late(name):
    """A reader starved long enough to overflow the FIFO often reads late again just after: the
    clock fit restarts at the flush, not at that late read, so the samples after the gap keep their
    true times (a fit started on a read 30 ms late stamped them 30 ms late)."""
    Driver, Emu, _ = CHIPS[name]
    fn, decode = sawtooth_clock(time.monotonic())
    chip = Emu(rate_fn=fn, noise_rad_s=0.0)
    gyro = Driver(make_bus("i2c", chip), full_scale_dps=2000.0)
    status, late_reads = gyro._fifo_status, [0]

    def preempted_after_the_status_read():
        out = status()
        if late_reads[0] > 0:            # the count is read, then the thread loses the CPU for 30 ms
            late_reads[0] -= 1
            time.sleep(0.030)
        return out

    gyro._fifo_status = preempted_after_the_status_read
    gyro.start()
    collect(gyro, 150)
    time.sleep(0.45)                     # overflow
    late_reads[0] = 3                    # the flush's read and the two after it are late
    after = collect(gyro, 200)
    gyro.stop()
    assert after[0].gap_before
    t, r = cat(after)
    err = t - decode(r[:, 0], t)
    # the anchor's own error: the flush's half-bracket (a reader preempted inside it) and a sample
    # period; a late read adds nothing
    tol = 1.5e-3 + gyro.stats()["lost_uncertainty"] * 1e-3 + LSB_S_2000DPS
    assert np.abs(err).max() <= tol, (np.abs(err).max(), tol)


@pytest.mark.parametrize("name", ["icm42688", "mpu6000", "bmi088"])
@pytest.mark.parametrize("bus_kind", ["i2c", "spi"])
def test_wrong_chip_id_refused_with_actionable_message(name, bus_kind):
    Driver, Emu, Error = CHIPS[name]
    gyro = Driver(make_bus(bus_kind, Emu(chip_id=0x12)))
    with pytest.raises(Error) as e:
        gyro.start()
    msg = str(e.value)
    assert f"{ID_REG[name]} read 0x12, expected 0x" in msg
    assert "check wiring / I²C address / bus number / SPI mode" in msg
    assert isinstance(e.value, GyroDeviceError) and isinstance(e.value, DeviceError)


def test_nothing_at_the_address_names_the_bus_and_address():
    gyro = ICM42688(make_bus("i2c", ICM42688Emu(), address=0x69))
    with pytest.raises(ICM42688Error, match=r"address 0x69\): identification failed: .*Remote I/O error.*"
                       "check wiring / I²C address"):
        gyro.start()
    assert gyro.stats()["io_errors"] == 1


def test_config_not_accepted_is_reported():
    class Stubborn(ICM42688Emu):                   # a chip whose GYRO_CONFIG0 keeps its reset value
        def _on_write(self, reg, value):
            super()._on_write(reg, value)
            if reg == 0x4F:
                self.regs[0x4F] = 0x06
    gyro = ICM42688(make_bus("spi", Stubborn()), full_scale_dps=250.0)
    with pytest.raises(ICM42688Error, match="GYRO_CONFIG0 0x4F read back 0x06, expected 0x66"):
        gyro.start()


@pytest.mark.parametrize("name", ["icm42688", "mpu6000", "bmi088"])
def test_io_errors_surface_as_driver_exception_and_recover_after_replug(name):
    Driver, Emu, Error = CHIPS[name]
    w = np.array([0.2, 0.0, -0.1])
    chip = Emu(rate_fn=constant(w), noise_rad_s=0.0)
    gyro = Driver(make_bus("i2c", chip), full_scale_dps=500.0)
    gyro.start()
    first = collect(gyro, 50)
    chip.unplug(0.1)                               # comes back power-cycled: configuration lost
    with pytest.raises(Error, match="FIFO status read failed: .*Remote I/O error.*check wiring"):
        gyro.poll(0.1)
    errors = 1
    t_end = time.monotonic() + 60                  # only catches a driver that never recovers
    after = []
    while len(after) < 20:
        assert time.monotonic() < t_end, gyro.stats()
        try:
            b = gyro.poll(0.1)
        except Error:
            errors += 1
            time.sleep(0.01)
            continue
        if b is not None:
            after.append(b)
    st = gyro.stats()
    assert st["io_errors"] == errors >= 2 and st["recoveries"] == 1
    assert after and after[0].gap_before and after[0].n_lost >= 80
    _, r = cat(after)
    assert np.max(np.abs(r - w)) < math.radians(500) / 32768    # re-configured at the right scale
    assert first and first[-1].seq + len(first[-1]) + after[0].n_lost == after[0].seq
    # a single NACK glitch is one error, then reading continues
    chip.nack(1)
    with pytest.raises(Error):
        gyro.poll(0.1)
    assert collect(gyro, 1)


def test_invalid_samples_are_dropped_but_keep_their_ticks():
    fn, decode = sawtooth_clock(time.monotonic())
    chip = ICM42688Emu(rate_fn=fn, noise_rad_s=0.0)
    gyro = ICM42688(make_bus("spi", chip))
    gyro.start()
    chip.invalid_samples = 7                       # the first samples after the gyro powers on
    batches, returned = collect_timed(gyro, 300)
    # a valid sample or two may come first: on a loaded machine the chip samples between the start's
    # flush and the line above (seen once in a full make test: one, seq 0)
    gaps = [i for i, b in enumerate(batches) if b.gap_before]
    assert len(gaps) == 1 and gyro.stats()["invalid"] == 7, (gaps, gyro.stats())
    g = batches[gaps[0]]
    before = sum(len(b) for b in batches[:gaps[0]])
    assert before <= 3 and g.seq == before + 7                  # the invalid ones kept their ticks
    assert g.n_lost == 7 == gyro.stats()["lost"]
    t, r = cat(batches)
    assert len(t) == sum(len(b) for b in batches) and np.all(r != -np.radians(2000))
    assert np.all(np.diff(t) > 0)
    err = np.median((t - decode(r[:, 0], t))[-100:])
    # with the drift unresolved over 0.3 s the fit is the earliest read (lower envelope): a batch's
    # error is the smallest read lateness up to its own read (it is mapped then; a less late read
    # after it cannot move it); 7 ticks miscounted would put it 7 ms off
    q = LSB_S_2000DPS
    so_far = np.minimum.accumulate(read_lateness(batches, returned, decode))
    envelope = np.repeat(so_far, [len(b) for b in batches])[-100:]
    assert -q <= err <= np.median(envelope) + q


def test_stop_start_cycle_continues_the_sequence_with_a_gap():
    # the daemon restarts a failing source with stop() + start(): counting and timing must carry on
    fn, decode = sawtooth_clock(time.monotonic())
    chip = ICM42688Emu(rate_fn=fn, noise_rad_s=0.0)
    gyro = ICM42688(make_bus("spi", chip))
    gyro.start()
    first = collect(gyro, 100)
    gyro.stop()
    time.sleep(0.2)
    gyro.start()
    second, returned = collect_timed(gyro, 100)
    true_lost = round((decode(second[0].rate[:1, 0], second[0].t[:1])[0]
                       - decode(first[-1].rate[-1:, 0], first[-1].t[-1:])[0]) * 1000) - 1
    # host-time estimate: ±2 samples, plus what this run's late reads add (a loaded machine)
    late = read_lateness(second, returned, decode)
    tol = 2 + int(math.ceil(1000.0 * max(float(np.percentile(late, 90)), 0.0)))
    assert second[0].gap_before and true_lost >= 200 and abs(second[0].n_lost - true_lost) <= tol
    assert second[0].seq == first[-1].seq + len(first[-1]) + second[0].n_lost
    t, r = cat(second)
    assert t[0] > first[-1].t[-1]
    err = t - decode(r[:, 0], t)
    q = LSB_S_2000DPS
    assert -q <= err.min() and err.max() <= read_lateness(second, returned, decode).max() + q


def test_bursts_are_split_at_the_bus_limits():
    w = np.array([0.05, 0.1, 0.15])
    chip = ICM42688Emu(rate_fn=constant(w), noise_rad_s=0.0)
    i2c = EmuI2C({0x68: chip})
    gyro = ICM42688(I2CBus(i2c, 0x68, max_read=64), read_interval_s=0.05)
    gyro.start()
    n0 = i2c.transactions
    b = gyro.poll(0.2)
    assert len(b) >= 40                            # ≥ 320 bytes → ≥ 5 chunked reads of ≤ 64 bytes
    assert i2c.transactions - n0 >= 1 + len(b) * 8 // 64
    assert np.max(np.abs(b.rate - w)) <= 0.5 * math.radians(2000) / 32768 * 1.0001
    spi = EmuSPI(chip)
    with pytest.raises(OSError) as e:
        spi.xfer2([0xB0] + [0] * 4096)             # spidev refuses more than its 4096-byte buffer
    assert e.value.errno == errno.EMSGSIZE


def test_bad_parameters_rejected():
    chip = ICM42688Emu()
    with pytest.raises(ICM42688Error, match="full_scale_dps=300"):
        ICM42688(make_bus("spi", chip), full_scale_dps=300)
    with pytest.raises(ICM42688Error, match="rate_hz=1234"):
        ICM42688(make_bus("spi", chip), rate_hz=1234)
    with pytest.raises(ICM42688Error, match="before start"):
        ICM42688(make_bus("spi", chip)).poll(0.0)


def test_emulator_overflow_semantics():
    clock = [0.0]
    icm = ICM42688Emu(clock=lambda: clock[0], noise_rad_s=0.0)
    for reg, v in ((0x4E, 0x0C), (0x5F, 0x02), (0x16, 0x40)):
        icm.write(reg, bytes([v]))
    clock[0] = 0.1005                                 # 100 ticks at 1 kHz
    assert int.from_bytes(icm.read(0x2E, 2), "big") == 800
    clock[0] = 1.0                                     # 1000 ticks: the 2 KB FIFO keeps the newest 256
    st, hi, lo = icm.read(0x2D, 3)
    assert st & 0x02 and (hi << 8 | lo) == 2048
    assert icm.read(0x2D, 1)[0] == 0                   # INT_STATUS cleared on read
    mpu = MPU6000Emu(clock=lambda: clock[0], noise_rad_s=0.0, rate_fn=constant([0.01, 0.02, 0.03]))
    for reg, v in ((0x6B, 0x01), (0x1A, 0x01), (0x23, 0x70), (0x6A, 0x40)):
        mpu.write(reg, bytes([v]))
    clock[0] = 2.0                                      # way past 1024 bytes
    assert mpu.read(0x3A, 1)[0] & 0x10
    assert int.from_bytes(mpu.read(0x72, 2), "big") == 1024
    # byte-wise overwrite: 1024 % 6 = 4, so the FIFO now starts in the middle of a record
    first = np.frombuffer(mpu.read(0x74, 6), ">i2")
    scale = 32768 / math.radians(250)
    assert not np.array_equal(first, np.rint(np.array([0.01, 0.02, 0.03]) * scale))


def test_missing_bus_device_files_are_named():
    with pytest.raises(DeviceError, match=r"/dev/i2c-97: cannot open .*i2c-dev"):
        I2CBus(97, 0x68)
    with pytest.raises(DeviceError, match=r"/dev/spidev9\.7: cannot open .*dtparam=spi=on"):
        SPIBus((9, 7))
    with pytest.raises(DeviceError, match=r"/dev/i2c-96: cannot open"):
        I2CBus("/dev/i2c-96")
    with pytest.raises(DeviceError, match=r"/dev/spidev9\.6: cannot open"):
        SPIBus("/dev/spidev9.6")
    with pytest.raises(DeviceError, match="expected /dev/spidevB.C"):
        SPIBus("/dev/ttyUSB0")
    with pytest.raises(DeviceError, match="expected /dev/i2c-N"):
        I2CBus("i2c1")


@pytest.mark.parametrize("name", ["icm42688", "mpu6000", "bmi088"])
@pytest.mark.parametrize("bus_kind", ["i2c", "spi"])
def test_bus_glitches_reading_all_ones_are_counted_not_raised(name, bus_kind):
    # an undriven data line reads 0xFF: an overflow flag, a FIFO count no FIFO holds, ICM headers
    # that say "empty". None is an I/O error; each is counted and the stream carries on.
    Driver, Emu, _ = CHIPS[name]
    w = np.array([0.2, -0.1, 0.05])
    chip = Emu(rate_fn=constant(w), noise_rad_s=0.0)
    gyro = Driver(make_bus(bus_kind, chip), full_scale_dps=500.0)
    gyro.start()
    batches = []
    for k in range(12):
        batches += collect(gyro, 20)
        chip.glitch(1 + k % 3, reg=chip.fifo_reg if k % 2 else None)
    batches += collect(gyro, 50)
    st = gyro.stats()
    assert st["io_errors"] == 0 and st["overflows"] + st["bad_counts"] + st["invalid"] >= 1
    assert st["gaps"] >= 1 and st["lost"] >= st["invalid"]       # invalid samples are missing ones
    for prev, b in zip(batches[:-1], batches[1:], strict=True):
        assert b.seq == prev.seq + len(prev) + b.n_lost
    t, r = cat(batches)
    assert np.all(np.diff(t) > 0)
    if name == "icm42688":                     # its packet headers tell garbage from data
        assert st["invalid"] >= 1 and np.max(np.abs(r - w)) <= 0.5 * math.radians(500) / 32768 * 1.0001


def test_short_transfers_are_io_errors():
    class Short(EmuSPI):                       # a SpiDev-like device that returns fewer bytes
        def xfer2(self, data):
            rx = super().xfer2(data)
            return rx[:-1] if data[0] & 0x80 else rx
    gyro = ICM42688(SPIBus(Short(ICM42688Emu())))
    with pytest.raises(ICM42688Error, match="short read at register 0x75: 0 of 1"):
        gyro.start()


def test_a_waiting_reader_gets_the_fifo_read_at_once():
    """`request_read`: a FIFO driver on a slow interval (its CPU) reads at once when a frame waits for
    its newest samples, and a `GyroRing` waiter asks for it while it waits."""
    import threading

    from thermod.runtime.rings import GyroRing

    chip = ICM42688Emu(noise_rad_s=0.0)
    gyro = ICM42688(make_bus("spi", chip), full_scale_dps=2000.0, read_interval_s=0.5)
    gyro.start()
    gyro.poll(1.0)                                     # the first read: the interval starts now
    assert gyro.poll(0.05) is None                     # nothing before the interval, unasked
    ring = GyroRing(4096)
    ring.request = gyro.request_read

    done = threading.Event()

    def driver():                                      # what the gyro's driver thread does
        while not done.is_set():
            b = gyro.poll(0.05)
            if b is not None:
                ring.write(b.t, b.rate, b.seq)

    th = threading.Thread(target=driver)
    t0 = time.monotonic()
    th.start()
    # a read within a sample period of t0 may not cover it yet: the waiter asks again, and gets it
    covered = ring.wait_until(t0, 0.4)                 # what the scheduler does for each frame
    waited = time.monotonic() - t0
    done.set()
    th.join(1.0)
    assert covered and waited < 0.25, waited           # not the 0.5 s interval


@pytest.mark.parametrize("name, rate_hz, fill_ms, interval_ms", [
    ("icm42688", 1000, 256.0, 25.0), ("icm42688", 8000, 32.0, 4.0),
    ("mpu6000", 1000, 1024 / 6, 1024 / 6 / 8), ("mpu6000", 8000, 1024 / 48, 1024 / 48 / 8),
    ("bmi088", 2000, 50.0, 6.25)])
def test_the_fifo_is_read_eight_times_per_fill_at_most_every_25_ms(name, rate_hz, fill_ms, interval_ms):
    Driver, Emu, _ = CHIPS[name]
    gyro = Driver(make_bus("spi", Emu(rate_fn=constant([0, 0, 0]))), full_scale_dps=2000.0, rate_hz=rate_hz)
    assert gyro.fifo_seconds * 1e3 == pytest.approx(fill_ms)
    assert gyro.read_interval_s * 1e3 == pytest.approx(interval_ms)
    gyro.read_interval_s = 0.003                     # a reader may set its own
    assert gyro.read_interval_s == 0.003
