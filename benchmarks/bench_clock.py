"""Clock mapping benchmark: a simulated 1 kHz gyro FIFO read every ~5 ms; and the CPU cost of the
gyro drivers on their emulators in real time.

The device oscillator runs +250 ppm off nominal; each read counts the samples in the FIFO, then
takes the host time. 1 % of reads are preempted between the count and the time stamp (2–20 ms
late). Compares thermod.io.clock.ClockMapper (causal: each batch is mapped with the fit as it stood
right after that batch was observed) with stamping samples by the read time.

Second table: a real-time run of each register driver on its register emulator (and the serial
driver on its pty emulator), polled the way the daemon does, as % of one core (process CPU time
over wall time, driver and emulator together), with the mapped-time error against the emulator's
truth.

    .venv/bin/python benchmarks/bench_clock.py [--seconds 120] [--repeats 5] [--quick]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from thermod.io.clock import ClockMapper


def simulate_reads(seconds: float, *, rate_hz=1000.0, drift_ppm=250.0, read_every_s=0.005,
                   read_jitter_s=0.0005, bus_latency_s=60e-6, p_late=0.01, late_s=(0.002, 0.020),
                   t0=1234.5, seed=0):
    """(seq of the newest sample read, host arrival, true host time of every sample) per read."""
    rng = np.random.default_rng(seed)
    period_true = (1.0 / rate_hz) * (1.0 + drift_ppm * 1e-6)
    reads = []
    t = t0 + 0.001
    while t < t0 + seconds:
        t += read_every_s + rng.uniform(0.0, read_jitter_s)
        # samples taken before the FIFO count was latched are the ones this read returns
        n_avail = int(np.floor((t - t0) / period_true)) + 1
        arrival = t + bus_latency_s + rng.uniform(0.0, 20e-6)
        if rng.random() < p_late:
            arrival += rng.uniform(*late_s)
        reads.append((n_avail - 1, arrival))
    seqs = np.array([r[0] for r in reads], np.int64)
    arrivals = np.array([r[1] for r in reads])
    return seqs, arrivals, t0, period_true


def run_methods(seqs, arrivals, t0, period_true, rate_hz=1000.0, **mapper_kw):
    """Per-sample time errors (s) for the mapper and the two read-time stampings."""
    mapper = ClockMapper(1.0 / rate_hz, **mapper_kw)
    err_map, err_batch, err_fill = [], [], []
    prev = -1
    tic = time.perf_counter()
    for s, a in zip(seqs, arrivals, strict=True):
        if s <= prev:
            continue
        idx = np.arange(prev + 1, s + 1)
        truth = t0 + idx * period_true
        mapper.observe(int(s), float(a))
        err_map.append(mapper.to_host(idx) - truth)
        err_batch.append(a - truth)                              # every sample stamped at read time
        err_fill.append(a - (s - idx) / rate_hz - truth)         # newest at read time, back-filled
        prev = s
    cost = (time.perf_counter() - tic) / len(seqs)
    return (np.concatenate(err_map), np.concatenate(err_batch), np.concatenate(err_fill), mapper, cost)


def cpu_run(kind: str, seconds: float):
    """(% of a core, samples/s, mapped-time error std and max in ms) for one driver on its emulator."""
    from thermod.drivers.bus import I2CBus, SPIBus
    from thermod.drivers.icm42688 import ICM42688
    from thermod.drivers.mpu6000 import MPU6000
    from thermod.drivers.serial_imu import SerialIMU
    from thermod.sim.emu_registers import EmuI2C, EmuSPI, ICM42688Emu, MPU6000Emu
    from thermod.sim.emu_serial import SerialIMUEmulator

    t_ref = time.monotonic()

    def saw(t):      # x encodes the sample time (20 rad/s per s): the truth for the error column
        ph = np.mod(np.asarray(t) - t_ref, 1.0)
        return np.stack([20.0 * ph - 10.0, np.zeros_like(ph), np.full_like(ph, 0.5)], axis=1)

    emu = None
    if kind.startswith("serial"):
        emu = SerialIMUEmulator(rate_fn=lambda t: saw(t).astype(np.float32), drift_ppm=250.0).start()
        gyro = SerialIMU(emu.link)
    else:
        chip = (ICM42688Emu if "ICM" in kind else MPU6000Emu)(rate_fn=saw, drift_ppm=250.0, noise_rad_s=0.0)
        bus = SPIBus(EmuSPI(chip)) if "SPI" in kind else I2CBus(EmuI2C({0x68: chip}), 0x68)
        cls = ICM42688 if "ICM" in kind else MPU6000
        if cls is MPU6000:
            cls.reset_wait_s = 0.002
        gyro = cls(bus, full_scale_dps=2000.0, read_interval_s=0.002)
    gyro.start()
    ts, rs = [], []
    w0, c0 = time.monotonic(), time.process_time()
    while time.monotonic() - w0 < seconds:
        b = gyro.poll(0.002)                      # as the daemon's gyro thread does (sim.toml)
        if b is not None:
            ts.append(b.t)
            rs.append(b.rate[:, 0])
    cpu = (time.process_time() - c0) / (time.monotonic() - w0) * 100
    gyro.stop()
    if emu is not None:
        emu.stop()
    t, x = np.concatenate(ts), np.concatenate(rs).astype(np.float64)
    ph = (x + 10.0) / 20.0
    truth = t_ref + np.round(t - t_ref - ph) + ph
    err = (t - truth)[len(t) // 3:]
    return cpu, len(t) / seconds, np.std(err) * 1e3, np.max(np.abs(err - np.median(err))) * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=120.0)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--drift-ppm", type=float, default=250.0)
    ap.add_argument("--cpu-seconds", type=float, default=5.0)
    ap.add_argument("--quick", action="store_true", help="30 s x 3 runs, 2 s CPU runs")
    args = ap.parse_args()
    if args.quick:
        args.seconds, args.repeats, args.cpu_seconds = 30.0, 3, 2.0
    rows = {"ClockMapper (lower envelope)": [], "read time, back-filled at 1 ms": [],
            "read time for the whole batch": []}
    drift, resid, costs = [], [], []
    for rep in range(args.repeats):
        seqs, arr, t0, pt = simulate_reads(args.seconds, drift_ppm=args.drift_ppm, seed=rep)
        em, eb, ef, m, cost = run_methods(seqs, arr, t0, pt)
        for name, e in zip(rows, (em, ef, eb), strict=True):
            rows[name].append((np.std(e) * 1e3, np.max(np.abs(e)) * 1e3, np.median(e) * 1e3))
        drift.append(m.drift_ppm)
        resid.append(m.residual_std_s * 1e6)
        costs.append(cost * 1e6)
    print(f"1 kHz gyro, {args.drift_ppm:+.0f} ppm, FIFO read every 5-5.5 ms, 1 % of reads 2-20 ms late; "
          f"{args.seconds:.0f} s x {args.repeats} runs (medians over runs)")
    print(f"{'method':<34}{'err std ms':>12}{'err max ms':>12}{'bias ms':>10}")
    for name, vals in rows.items():
        v = np.median(np.array(vals), axis=0)
        print(f"{name:<34}{v[0]:>12.4f}{v[1]:>12.3f}{v[2]:>10.3f}")
    print(f"fitted drift: median {np.median(drift):+.1f} ppm (true {args.drift_ppm:+.1f}); "
          f"residual_std_s median {np.median(resid):.1f} µs; observe+to_host cost median "
          f"{np.median(costs):.1f} µs per read")
    print()
    print(f"driver + emulator in real time, 1 kHz, +250 ppm, polled every 2 ms, {args.cpu_seconds:.0f} s "
          "each (medians of 3 runs; error: mapped time vs the emulator's sample time, after the first third)")
    print(f"{'source':<34}{'% of a core':>12}{'samples/s':>11}{'err std ms':>12}{'err max ms':>12}")
    for kind in ("ICM-42688-P on SPI emulator", "ICM-42688-P on I2C emulator", "MPU-6000 on I2C emulator",
                 "serial IMU on a pty"):
        v = np.median(np.array([cpu_run(kind, args.cpu_seconds) for _ in range(3)]), axis=0)
        print(f"{kind:<34}{v[0]:>12.1f}{v[1]:>11.0f}{v[2]:>12.4f}{v[3]:>12.3f}")


if __name__ == "__main__":
    main()
