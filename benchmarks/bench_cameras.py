"""Camera path benchmark: what a frame costs between the device and the ring buffer.

1. GigE Vision through Aravis against the real fake camera on loopback (640×512 Mono16): delivered
   rate vs configured, losses, timestamp lag (arrival − mapped device time) and the driver's CPU time
   per frame (buffer → uint16 array → mapped timestamp), at several frame rates.
2. Byte-buffer → uint16 reshaping (the V4L2 flat-bytes path) for a Boson frame.
3. Replay of a recording from disk as fast as possible (lazy one-chunk-per-frame HDF5 reads).

    .venv/bin/python benchmarks/bench_cameras.py [--quick]
"""

from __future__ import annotations

import argparse
import math
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from thermod.drivers.camera_base import as_uint16_image
from thermod.io import recording
from thermod.physics.calibration import Calibration


def bench_aravis(rates, seconds):
    from thermod.drivers.aravis_camera import AravisCamera, gvcp_probe

    fake = shutil.which("arv-fake-gv-camera-0.8")
    if fake is None:
        print("(arv-fake-gv-camera-0.8 not installed: GigE part skipped)")
        return
    if gvcp_probe("127.0.0.1", 0.1) is not None:
        print("(another GigE camera answers on 127.0.0.1: GigE part skipped)")
        return
    proc = subprocess.Popen([fake, "-i", "127.0.0.1", "-s", "BENCH"], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        for _ in range(50):
            if gvcp_probe("127.0.0.1", 0.05):
                break
            time.sleep(0.05)
        print("device Hz: median period of the device timestamps; delivered Hz: frames/s received (the fake "
              "camera is software on this loaded host and stalls now and then). lag = arrival − mapped "
              "device time: the jitter above the fastest arrival (a delay-only clock fit cannot see the "
              "fixed transport delay).")
        print(f"{'fps':>6} {'device Hz':>10} {'delivered Hz':>13} {'lost':>5} {'bad':>4} "
              f"{'lag median ms':>14} {'lag p99 ms':>11} {'driver µs/frame (median)':>25}")
        for fps in rates:
            cam = AravisCamera("127.0.0.1", width=640, height=512, frame_rate_hz=fps, packet_size=8000)
            frames, cost = [], []
            with cam:
                cam.poll(1.0)
                end = time.monotonic() + seconds
                while time.monotonic() < end:
                    f = cam.poll(0.2)
                    if f is not None:
                        frames.append(f)
                        # CPU cost of the conversion is measured from arrival to the return of poll()
                        cost.append(time.monotonic() - f.arrival)
                st = cam.stats()
            arr = np.array([f.arrival for f in frames])
            rate = (len(arr) - 1) / (arr[-1] - arr[0]) if len(arr) > 1 else 0.0
            lag = np.array([f.arrival - f.t for f in frames]) * 1e3
            ts = np.array([f.device_ts for f in frames], np.int64)
            ids = np.array([f.frame_id for f in frames])
            dev_rate = 1e9 / np.median(np.diff(ts) / np.diff(ids)) if len(ts) > 1 else 0.0
            print(f"{fps:6.0f} {dev_rate:10.2f} {rate:13.2f} {st['frames_lost']:5d} {st['bad_buffers']:4d} "
                  f"{np.median(lag):14.2f} {np.percentile(lag, 99):11.2f} {np.median(cost) * 1e6:25.0f}")
    finally:
        proc.kill()
        proc.wait()


def bench_reshape(repeats):
    rng = np.random.default_rng(0)
    img = rng.integers(0, 65535, size=(514, 640), dtype=np.uint16)
    flat = img.view(np.uint8).reshape(1, -1).copy()
    rows = img.view(np.uint8).reshape(514, -1).copy()
    print(f"\n{'layout (640×514 Y16)':>26} {'median µs':>10}")
    for name, data in (("uint16 [H, W]", img), ("uint8 [1, 2HW] (flat)", flat), ("uint8 [H, 2W]", rows),
                       ("bytes", flat.tobytes())):
        ts = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            out = as_uint16_image(data, 514, 640, "bench")
            out = np.ascontiguousarray(out[2:])            # + telemetry strip, as the V4L2 driver does
            ts.append(time.perf_counter() - t0)
        assert np.array_equal(out, img[2:])
        print(f"{name:>26} {np.median(ts) * 1e6:10.1f}")


def bench_replay(n_frames):
    from thermod.drivers.replay import ReplaySession

    calib = Calibration(width=640, height=512, cx=319.5, cy=255.5)
    rng = np.random.default_rng(1)
    frames = rng.integers(0, 65535, size=(n_frames, 512, 640), dtype=np.uint16)
    t = 100.0 + np.arange(n_frames) / calib.frame_rate_hz
    gt = 100.0 - 0.04 + np.arange(int((n_frames / calib.frame_rate_hz + 0.05) * 1000)) / 1000.0
    rec = recording.Recording(frames, t, gt, np.zeros((len(gt), 3), np.float32), calib)
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "bench.h5"
        recording.write(path, rec)
        s = ReplaySession(path, speed=math.inf)
        cam, gyro = s.camera(), s.gyro()
        cam.start()
        gyro.start()
        per = []
        n = 0
        while not cam.finished:
            gyro.poll(0.0)
            t0 = time.perf_counter()
            f = cam.poll(0.0)
            if f is not None:
                per.append(time.perf_counter() - t0)
                n += 1
        s.close()
    print(f"\nreplay from disk, as fast as possible (640×512, {n} frames, lockstep with the gyro): "
          f"median {np.median(per) * 1e3:.2f} ms/frame → {1 / np.median(per):.0f} frames/s")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    rates = (30, 60) if args.quick else (30, 60, 100, 200)
    bench_aravis(rates, 1.5 if args.quick else 3.0)
    bench_reshape(50 if args.quick else 300)
    bench_replay(60 if args.quick else 200)


if __name__ == "__main__":
    main()
