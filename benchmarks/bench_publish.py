"""Transport speed: cost of a `publish_*` call in the daemon's threads, of decoding a message,
loopback latency and throughput to one subscriber, for 640×512 frames (float32 deblurred, uint16 raw)
and gyro batches; and the publisher's memory with subscribers that connect and never read.

    .venv/bin/python benchmarks/bench_publish.py [--quick]
"""

import argparse
import subprocess
import sys
import time

import numpy as np

from thermod.chaos import FROZEN_SUBSCRIBER, rss_mb
from thermod.client.subscriber import Subscriber
from thermod.io.wire import decode, encode_header
from thermod.runtime.publish import DEFAULT_MAX_QUEUE_BYTES, Publisher

H, W = 512, 640


def connect(pub, topics):
    sub = Subscriber(pub.endpoint, topics=(*topics, "health"), rcvhwm=1000)
    while True:
        pub.publish_health()
        if sub.recv(0.05) is not None:
            while sub.recv(0.05) is not None:
                pass
            return sub


def call_cost(n):
    """Median µs per call; the publisher is not started, so only the caller's work is timed."""
    img = np.random.default_rng(0).normal(1e4, 100, (H, W)).astype(np.float32)
    raw = img.astype(np.uint16)
    gt, gr = np.arange(20) * 1e-3, np.zeros((20, 3), np.float32)
    rows = []
    for name, fn in [
        ("publish_frame f32 (copy)", lambda p, i: p.publish_frame(img, i, frame_id=i, deblurred=True,
                                                                kernel_size=(15, 15), coverage=1.0)),
        ("publish_frame f32 (handover)", lambda p, i: p.publish_frame(img, i, frame_id=i, deblurred=True,
                                                                    copy=False)),
        ("publish_raw u16 (copy)", lambda p, i: p.publish_raw(raw, i, frame_id=i)),
        ("publish_gyro 20 samples", lambda p, i: p.publish_gyro(gt, gr, seq=20 * i)),
        ("publish_health", lambda p, i: p.publish_health(rates={"frame_hz": 50.0})),
    ]:
        p = Publisher("tcp://127.0.0.1:*", queue_size=8)
        dt = []
        for i in range(n):
            t0 = time.perf_counter()
            fn(p, i)
            dt.append(time.perf_counter() - t0)
        rows.append((name, 1e6 * np.median(dt), 1e6 * np.percentile(dt, 99)))
    return rows


def decode_cost(n):
    """Median µs to validate and decode one frame message (a view, no copy)."""
    img = np.ones((H, W), np.float32)
    head = {"v": 1, "seq": 0, "t": 1.0, "published": 1.0, "deblurred": True, "shape": [H, W], "dtype": "<f4",
            "frame_id": 0, "kernel_size": [15, 15], "coverage": 1.0}
    frames = [b"frame", encode_header(head), img.tobytes()]
    dt = []
    for _ in range(n):
        t0 = time.perf_counter()
        decode(frames)
        dt.append(time.perf_counter() - t0)
    return 1e6 * np.median(dt), 1e6 * np.percentile(dt, 99)


def stalled_memory(n_stalled, seconds, **pub_kw):
    """Publisher RSS (MB) before and after `seconds` of 50 fps frames with `n_stalled` subscribers
    (separate processes, connecting 0.5 s apart) that never read, and the publisher's counters."""
    img = np.ones((480, 640), np.float32)
    with Publisher("tcp://127.0.0.1:*", max_message_bytes=img.nbytes, **pub_kw) as pub:
        procs = []
        rss0 = rss_mb()
        try:
            t_next = time.monotonic()
            for i in range(int(seconds * 50)):
                if i % 25 == 0 and len(procs) < n_stalled:
                    procs.append(subprocess.Popen([sys.executable, "-c", FROZEN_SUBSCRIBER, pub.endpoint]))
                pub.publish_frame(img, float(i), frame_id=i, deblurred=True)
                t_next += 0.02
                time.sleep(max(0.0, t_next - time.monotonic()))
            rss1 = rss_mb()
            st = pub.stats()
        finally:
            for p in procs:
                p.kill()
                p.wait()
    return rss0, rss1, st


def latency(n, fps):
    """Frames paced at `fps`: received − published and received − call, ms."""
    img = np.ones((H, W), np.float32)
    with Publisher("tcp://127.0.0.1:*", hwm=1000, queue_size=1000) as pub:
        sub = connect(pub, ("frame",))
        lat_send, lat_all = [], []
        for i in range(n):
            t = time.monotonic()
            pub.publish_frame(img, t, frame_id=i, deblurred=True)
            m = sub.recv(1.0)
            lat_send.append(m[1]["received"] - m[1]["published"])
            lat_all.append(m[1]["received"] - t)
            time.sleep(max(0.0, 1 / fps - (time.monotonic() - t)))
        sub.close()
    return [np.median(lat_send) * 1e3, np.percentile(lat_send, 99) * 1e3, np.median(lat_all) * 1e3,
            np.percentile(lat_all, 99) * 1e3]


def throughput(n, dtype):
    img = np.ones((H, W), dtype)
    # Everything is queued at once, so lift the byte bounds for this run.
    with Publisher("tcp://127.0.0.1:*", hwm=10000, queue_size=10000, queue_bytes=1 << 32,
                   max_queue_bytes=1 << 32) as pub:
        sub = connect(pub, ("frame", "raw"))
        got = 0
        t0 = time.monotonic()
        for i in range(n):
            if dtype == np.float32:
                pub.publish_frame(img, i, frame_id=i, deblurred=True, copy=False)
            else:
                pub.publish_raw(img, i, frame_id=i, copy=False)
        while got < n and sub.recv(2.0) is not None:
            got += 1
        dt = time.monotonic() - t0
        lost = n - got
        sub.close()
    return got / dt, got * img.nbytes / dt / 2**20, lost


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    q = ap.parse_args().quick
    print(f"frames {W}×{H}\n")
    print(f"{'call (caller thread)':<32}{'median µs':>12}{'p99 µs':>12}")
    for name, med, p99 in call_cost(50 if q else 300):
        print(f"{name:<32}{med:12.1f}{p99:12.1f}")
    med, p99 = decode_cost(200 if q else 2000)
    print(f"{'decode frame f32 (subscriber)':<32}{med:12.1f}{p99:12.1f}")
    print(f"\n{'loopback latency at 50 fps, f32':<32}{'median ms':>12}{'p99 ms':>12}")
    ls = latency(50 if q else 250, 50.0)
    print(f"{'published → received':<32}{ls[0]:12.3f}{ls[1]:12.3f}")
    print(f"{'publish call → received':<32}{ls[2]:12.3f}{ls[3]:12.3f}")
    print(f"\n{'throughput, one subscriber':<32}{'frames/s':>12}{'MiB/s':>12}{'lost':>8}")
    for name, dt in (("frame f32", np.float32), ("raw u16", np.uint16)):
        fps, mib, lost = throughput(100 if q else 500, dt)
        print(f"{name:<32}{fps:12.0f}{mib:12.0f}{lost:8d}")
    secs = 4.0 if q else 10.0
    print(f"\n4 stalled subscribers, 640×480 f32 at 50 fps, {secs:.0f} s")
    print(f"{'publisher':<32}{'RSS MB before':>14}{'after':>8}{'held MB':>9}{'dropped':>9}")
    for name, kw in (("unbounded (hwm 100, old)", dict(hwm=100, max_queue_bytes=1 << 40)),
                     (f"max_queue_mb = {DEFAULT_MAX_QUEUE_BYTES >> 20} (default)", dict(hwm=100))):
        r0, r1, st = stalled_memory(4, secs, **kw)
        print(f"{name:<32}{r0:14.0f}{r1:8.0f}{st['held_peak_bytes'] / 2**20:9.0f}"
              f"{st['budget_dropped_total']:9d}")


if __name__ == "__main__":
    main()
