"""`thermod watch --http`: the live page (thermod.client.web) and the wire's `kernel` topic.

Real parts throughout: a ZeroMQ Publisher/Subscriber pair, the stdlib HTTP server read by urllib, and
at the end headless Chromium (Debian `chromium`) rendering the page served by `thermod watch --http`
against `thermod run --raw` on the simulated payload; its screenshots are checked by pixel content.
"""

import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.support.endpoints import private_endpoint
from thermod.client.subscriber import Subscriber
from thermod.client.web import LAYOUT, LiveView, WebError, WebServer, kernel_image, parse_bind
from thermod.io.wire import MessageError, decode, pack_kernel
from thermod.physics.kernels import Kernel, KernelGrid
from thermod.runtime.publish import Publisher

REPO = Path(__file__).resolve().parents[2]
THERMOD = Path(sys.executable).with_name("thermod")
H, W = 48, 64


def connect(pub, topics):
    """A subscriber that provably receives (PUB drops messages until the subscription has arrived)."""
    sub = Subscriber(pub.endpoint, tuple(set(topics) | {"health"}))
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        pub.publish_health()
        m = sub.recv(0.1)
        if m is not None:
            while sub.recv(0.05) is not None:  # the remaining probes
                pass
            return sub
    raise AssertionError("subscriber never connected")


@pytest.fixture
def pub():
    p = Publisher("tcp://127.0.0.1:*", queue_size=512, hwm=512).start()
    yield p
    p.stop()


def scene():
    yy, xx = np.mgrid[0:H, 0:W]
    raw = (3000 + 400 * np.sin(xx / 5.0) * np.cos(yy / 7.0) + 8 * xx).astype(np.uint16)
    frame = raw.astype(np.float32) + 150 * ((xx // 8 + yy // 8) % 2)  # visibly different from raw
    return raw, frame


def get(url):
    with urllib.request.urlopen(url, timeout=10) as r:
        return r.status, dict(r.headers), r.read()


def pump(sub, view, until, timeout=10.0):
    """Receive into `view` until `until()` holds."""
    deadline = time.monotonic() + timeout
    while not until():
        assert time.monotonic() < deadline, "messages did not arrive"
        m = sub.recv(0.1)
        if m is not None:
            view.add(*m)


# ------------------------------------------------------------------------------------- kernel topic
def test_kernel_topic_round_trip(pub):
    w = np.zeros((5, 7), np.float32)
    w[2, 1:6] = [0.1, 0.2, 0.4, 0.2, 0.1]
    k = Kernel(w, origin=(2, 3), coverage=0.995)
    sub = connect(pub, ("kernel",))
    pub.publish_kernel(k, 12.5, frame_id=41)
    m = sub.recv(5.0)
    assert m is not None
    topic, h, a = m
    assert topic == "kernel" and h["frame_id"] == 41 and h["t"] == 12.5
    assert h["origin"] == [2, 3] and h["extent_px"] == pytest.approx(2.0)
    assert h["coverage"] == pytest.approx(0.995)
    assert a.dtype == np.float32 and np.array_equal(a, w)
    sub.close()


def test_kernel_grid_cells_share_one_origin():
    rng = np.random.default_rng(1)
    shapes = [[(3, 3), (5, 4)], [(1, 1), (4, 6)]]
    origins = [[(1, 1), (4, 0)], [(0, 0), (1, 5)]]
    unit = [[(lambda x: x / x.sum())(rng.random(s).astype(np.float32)) for s in row] for row in shapes]
    cells = [[Kernel(w, o) for w, o in zip(ws, og, strict=True)]
             for ws, og in zip(unit, origins, strict=True)]
    g = KernelGrid(cells, centers=np.zeros((2, 2, 2)), bounds=np.zeros((2, 2, 4)), times=np.zeros(2),
                   image_shape=(100, 100))
    fields, out = pack_kernel(g)
    oy, ox = fields["origin"]
    assert (oy, ox) == (4, 5) and out.shape == (2, 2, 4 + 3, 5 + 4)   # max origin + max reach past it
    for r in range(2):
        for c in range(2):
            k = cells[r][c]
            y0, x0 = oy - k.origin[0], ox - k.origin[1]
            sub = out[r, c, y0:y0 + k.weights.shape[0], x0:x0 + k.weights.shape[1]]
            assert np.array_equal(sub, k.weights)
            assert out[r, c].sum() == pytest.approx(1.0, abs=1e-6)   # nothing but zeros around it
    assert fields["extent_px"] == pytest.approx(g.max_extent_px)


def test_kernel_topic_rejects_other_ranks():
    frames = [b"kernel", json.dumps({"v": 1, "seq": 0, "t": 1.0, "published": 1.0, "deblurred": False,
                                     "shape": [2, 2, 2], "dtype": "<f4"}).encode(), bytes(32)]
    with pytest.raises(MessageError) as e:
        decode(frames)
    assert e.value.kind == "shape"


def test_kernel_image_scales_to_peak_and_tiles_cells():
    w = np.zeros((3, 5), np.float32)
    w[1, 4], w[0, 0] = 0.5, 0.25
    img = kernel_image(w, size=100)
    assert img.shape == (60, 100)                       # ×20, nearest neighbour
    assert img[20:40, 80:100].min() == 255 and img[0:20, 0:20].max() == 128   # 127.5 rounds up
    grid = np.stack([np.stack([w, w])] * 3)             # 3 rows × 2 cols of 3 × 5
    assert kernel_image(grid, size=100, gap=2).shape == (7 * (3 * (3 + 2) - 2), 7 * (2 * (5 + 2) - 2))
    # a grid larger than the box is shrunk here, block maxima kept: every cell's peak stays white
    big = np.zeros((6, 8, 95, 22), np.float32)
    big[:, :, 50, 3:20] = 1.0 / 17                       # one-pixel-high streaks
    img = kernel_image(big, size=192)
    assert max(img.shape) <= 192 and img.max() == 255
    assert np.sum(img == 255) >= 6 * 8 * 4                 # no streak averaged away


# ------------------------------------------------------------------------------------------ the page
def publish_scene(pub, raw, frame, i, t0, *, with_raw=True, kernel=None):
    t = t0 + 0.02 * i
    if with_raw:
        pub.publish_raw(raw, t, frame_id=i)
    pub.publish_frame(frame, t, frame_id=i, deblurred=True, kernel_size=(5, 7), kernel_extent_px=2.0,
                      coverage=1.0)
    if kernel is not None:
        pub.publish_kernel(kernel, t, frame_id=i)


def test_page_serves_pairs_kernel_and_health(pub):
    raw, frame = scene()
    w = np.zeros((5, 7), np.float32)
    w[2, 1:6] = 0.2
    k = Kernel(w, origin=(2, 3))
    sub = connect(pub, ("frame", "raw", "kernel", "health"))
    view = LiveView(pub.endpoint)
    with WebServer(view, "127.0.0.1:0") as server:
        with pytest.raises(urllib.error.HTTPError) as e:
            get(server.url + "frame.jpg")
        assert e.value.code == 503                       # nothing yet
        t0 = time.monotonic() - 1.0                     # frames read a second ago: latency > 0.6 s
        pub.publish_health(rates={"gyro_hz": 1000.0}, drops={"passthrough_overload": 3, "gyro_lost": 1},
                           clocks={"gyro": {"residual_std_s": 2.0e-5}})
        for i in range(1, 11):
            publish_scene(pub, raw, frame, i, t0, kernel=k)
        pump(sub, view, lambda: view._counts["kernel"] == 10)
        view.sample({"frame": 0}, now=time.monotonic())
        pub.publish_health(rates={"gyro_hz": 998.0}, drops={"passthrough_overload": 9, "gyro_lost": 1},
                           clocks={"gyro": {"residual_std_s": 3.0e-5}})
        for i in range(11, 21):
            publish_scene(pub, raw, frame, i, t0, kernel=k)
        pump(sub, view, lambda: view._counts["health"] == 2 and view._counts["kernel"] == 20)
        t_prev = view.series[-1]["t"]
        p = view.sample({"frame": 4}, now=time.monotonic() + 1.0)   # one second later, 4 lost on the wire
        dt = p["t"] - t_prev

        status, hdr, body = get(server.url + "frame.jpg")
        img = cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_GRAYSCALE)
        assert hdr["Content-Type"] == "image/jpeg" and hdr["X-Has-Raw"] == "1" and hdr["X-Frame-Id"] == "20"
        assert img.shape == (H, 2 * W + 4)
        lo, hi = np.percentile(raw.astype(np.float32), [1, 99])          # one AGC for both halves
        want_l = np.clip((raw - lo) * 255 / (hi - lo), 0, 255)
        want_r = np.clip((frame - lo) * 255 / (hi - lo), 0, 255)
        assert np.abs(img[:, :W] - want_l).mean() < 3 and np.abs(img[:, W + 4:] - want_r).mean() < 3
        assert np.abs(img[:, W + 4:] - want_l).mean() > 10   # not the raw (17.5 on this scene)

        status, hdr, body = get(server.url + "kernel.png")
        kimg = cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_GRAYSCALE)
        assert hdr["X-Frame-Id"] == "20" and np.array_equal(kimg, kernel_image(w))
        assert hdr["X-Shape"] == "5x7" and float(hdr["X-Extent-Px"]) == pytest.approx(2.0)

        status, hdr, body = get(server.url + "health.json")
        s = json.loads(body)
        assert s["raw"] is True and s["counts"]["frame"] == 20 and s["counts"]["deblurred"] == 20
        assert s["frame"]["frame_id"] == 20 and s["frame"]["kernel_size"] == [5, 7]
        assert s["kernel"]["shape"] == [5, 7] and s["kernel"]["origin"] == [2, 3]
        ser = s["series"]
        assert len(ser["t"]) == 2
        assert ser["fps"][-1] == pytest.approx(50.0, rel=1e-6)          # frame times 20 ms apart
        assert ser["drops_per_s"][-1] == pytest.approx(6 / dt)          # daemon drops 4 → 10
        assert ser["lost_per_s"][-1] == pytest.approx(4 / dt)
        assert ser["gyro_hz"] == [1000.0, 998.0] and ser["gyro_residual_us"] == pytest.approx([20.0, 30.0])
        assert ser["camera_residual_us"] == [None, None]
        assert 600 < ser["lat_p50_ms"][-1] <= ser["lat_p95_ms"][-1] <= ser["lat_p99_ms"][-1] < 60e3

        status, hdr, page = get(server.url)
        assert b"<canvas id=\"p_fps\"" in page and b"http" not in page.replace(b"http-equiv", b"")  # no CDN
        with pytest.raises(urllib.error.HTTPError) as e:
            get(server.url + "nothing")
        assert e.value.code == 404
    sub.close()


def test_without_raw_the_deblurred_frame_is_shown_alone(pub):
    raw, frame = scene()
    sub = connect(pub, ("frame", "raw"))
    view = LiveView(pub.endpoint)
    with WebServer(view, "127.0.0.1:0") as server:
        for i in range(1, 4):
            publish_scene(pub, raw, frame, i, time.monotonic(), with_raw=False)
        pump(sub, view, lambda: view._counts["frame"] == 3)
        _, hdr, body = get(server.url + "frame.jpg")
        img = cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_GRAYSCALE)
        assert hdr["X-Has-Raw"] == "0" and img.shape == (H, W)
        lo, hi = np.percentile(frame, [1, 99])                           # its own AGC
        assert np.abs(img - np.clip((frame - lo) * 255 / (hi - lo), 0, 255)).mean() < 3
        assert json.loads(get(server.url + "health.json")[2])["raw"] is False
        with pytest.raises(urllib.error.HTTPError) as e:
            get(server.url + "kernel.png")
        assert e.value.code == 404
    sub.close()


def test_stalled_browsers_block_neither_the_subscriber_nor_other_browsers(pub):
    raw, frame = scene()
    sub = connect(pub, ("frame", "raw"))
    view = LiveView(pub.endpoint)
    with WebServer(view, "127.0.0.1:0") as server:
        host, port = parse_bind(server.url[len("http://"):-1])
        stalled = []
        for _ in range(4):   # half a request line, then silence; and a request never read
            s = socket.create_connection((host, port))
            s.sendall(b"GET /frame.jpg HT")
            stalled.append(s)
        for i in range(1, 6):
            publish_scene(pub, raw, frame, i, time.monotonic())
        pump(sub, view, lambda: view._counts["frame"] == 5, timeout=5)
        for _ in range(4):
            s = socket.create_connection((host, port))
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1024)
            s.sendall(b"GET /frame.jpg HTTP/1.0\r\n\r\n" * 50)
            stalled.append(s)
        for i in range(6, 31):
            publish_scene(pub, raw, frame, i, time.monotonic())
        pump(sub, view, lambda: view._counts["frame"] == 30, timeout=5)
        _, hdr, _ = get(server.url + "frame.jpg")
        assert hdr["X-Frame-Id"] == "30"
        for s in stalled:
            s.close()
    sub.close()


def test_bind_address_errors():
    assert parse_bind("127.0.0.1:8080") == ("127.0.0.1", 8080)
    assert parse_bind("[::1]:0") == ("::1", 0)
    for bad in ("8080", "127.0.0.1", "127.0.0.1:http", ":80", "127.0.0.1:70000"):
        with pytest.raises(WebError, match="HOST:PORT"):
            parse_bind(bad)
    view = LiveView()
    with WebServer(view, "127.0.0.1:0") as first:
        taken = first.url.rstrip("/").rsplit(":", 1)[1]
        with pytest.raises(WebError, match=f"127.0.0.1:{taken}: cannot listen"):
            WebServer(view, f"127.0.0.1:{taken}")


def test_watch_cli_reports_a_bad_http_address(capsys):
    from thermod import cli

    assert cli.main(["watch", "--http", "localhost", "--seconds", "0.1"]) == 2
    assert "--http 'localhost': expected HOST:PORT" in capsys.readouterr().err


# ------------------------------------------------------------------------ a real browser, a real daemon
def screenshot(url, path, profile):
    chromium = shutil.which("chromium")
    flags = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             f"--user-data-dir={profile}", "--window-size=1280,900", "--hide-scrollbars",
             "--virtual-time-budget=3000", f"--screenshot={path}"]
    subprocess.run([chromium, *flags, url], check=True, capture_output=True, timeout=120)
    img = cv2.imread(str(path))
    assert img is not None, f"chromium wrote no screenshot to {path}"
    return img


def region(img, name):
    x, y, w, h = LAYOUT[name]
    return img[y:y + h, x:x + w]


def line_pixels(img, bgr_hex, tol=40):
    """Pixels within `tol` of a plot line colour (#rrggbb)."""
    r, g, b = (int(bgr_hex[i:i + 2], 16) for i in (1, 3, 5))
    return int((np.abs(img.astype(int) - [b, g, r]).max(axis=2) < tol).sum())


@pytest.mark.slow
def test_chromium_renders_the_live_page(require, tmp_path):
    require(shutil.which("chromium") is not None, "chromium (Debian package chromium)")
    env = dict(os.environ)
    env.setdefault("NUMBA_CACHE_DIR", str(REPO / ".numba_cache"))
    ep = private_endpoint()
    daemon = subprocess.Popen([str(THERMOD), "run", "--raw", "--endpoint", ep, "--set",
                               "deblur.method=wiener", "--seconds", "400"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env, text=True)
    watcher = subprocess.Popen([str(THERMOD), "watch", "--endpoint", ep, "--http", "127.0.0.1:0",
                                "--interval", "30", "--seconds", "400"], stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, env=env, text=True)
    try:
        line = watcher.stdout.readline()
        m = re.search(r"live view on (http://127\.0\.0\.1:\d+/)", line)
        assert m, f"thermod watch did not report its URL: {line!r}"
        url = m.group(1)
        threading.Thread(target=lambda: watcher.stdout.read(), daemon=True).start()  # keep the pipe drained
        deadline = time.monotonic() + 300        # first start may render the payload and compile numba
        while True:
            assert daemon.poll() is None, f"daemon exited: {daemon.stderr.read()}"
            s = json.loads(get(url + "health.json")[2])
            fps = [v for v in s["series"].get("fps", []) if v]
            if s["raw"] and s["kernel"] and len(fps) >= 3 and s["series"]["gyro_hz"][-1]:
                break
            assert time.monotonic() < deadline, f"the page never got frames, raw and kernels: {s}"
            time.sleep(1.0)
        kernels, frames = {}, {}
        with Subscriber(ep, ("frame", "kernel")) as sub:   # what the daemon puts on the kernel topic
            # until 10 deblurred frames came with their kernels: how long depends on the machine's
            # load (overload passes frames through), the deadline only catches a daemon that stopped
            t_end = time.monotonic() + 120
            while len(set(kernels) & set(frames)) < 10:
                assert time.monotonic() < t_end, (len(frames), len(kernels), dict(sub.gaps))
                m = sub.recv(0.2)
                if m is not None:
                    (kernels if m[0] == "kernel" else frames)[m[1]["frame_id"]] = (m[1], np.array(m[2]))
        with tempfile.TemporaryDirectory() as profile:
            first = screenshot(url, tmp_path / "first.png", profile)
            time.sleep(3.0)
            second = screenshot(url, tmp_path / "second.png", profile)
    finally:
        for p in (watcher, daemon):
            p.send_signal(signal.SIGTERM)
        for p in (watcher, daemon):
            p.wait(30)
    # kernels come only with deblurred frames (a loaded machine may drop messages on the way, so
    # not every deblurred frame's kernel is asserted to arrive)
    deblurred = {i for i, (h, _) in frames.items() if h["deblurred"]}
    both = set(kernels) & set(frames)
    assert both <= deblurred and len(both) >= 10
    for i in both:
        (kh, k), (fh, _) = kernels[i], frames[i]
        # one kernel [kh, kw], or a grid [rows, cols, kh, kw] when the roll made the blur vary (the
        # governor picks the grid by the load too: wire.md)
        assert list(k.shape[-2:]) == fh["kernel_size"] and kh["t"] == fh["t"]
        assert list(k.shape[:-2]) == ([] if fh["grid"] == [1, 1] else fh["grid"])
        assert kh["extent_px"] == pytest.approx(fh["kernel_extent_px"])
        cells = k.reshape(-1, *k.shape[-2:]).sum(axis=(1, 2))
        assert cells == pytest.approx(np.ones(len(cells)), abs=1e-4)
    assert first.shape[:2] == (900, 1280)
    x, y, w, h = LAYOUT["frame"]
    for shot in (first, second):
        frame = region(shot, "frame").astype(np.float32)
        raw_half, deb_half = frame[:, : w // 2 - 4], frame[:, w // 2 + 4:]
        for half in (raw_half, deb_half):        # a thermal scene, not a blank or black box
            assert half.std() > 15 and 20 < half.mean() < 235
        assert region(shot, "kernel").max() > 200   # the kernel's peak is drawn white
    moved = np.abs(region(first, "frame").astype(np.float32) - region(second, "frame")).mean()
    assert moved > 2.0, "the frames did not change between two screenshots 3 s apart"
    plots = region(second, "plots")
    pw, ph = LAYOUT["plot_size"]
    fps_plot, lat_plot, gyro_plot = plots[:ph, :pw], plots[:ph, pw + 12: 2 * pw + 12], plots[ph + 12:, :pw]
    assert line_pixels(fps_plot, "#e6553a") > 100        # the fps line
    assert line_pixels(lat_plot, "#4cc38a") > 100        # latency p50
    assert line_pixels(gyro_plot, "#5aa9e6") > 100       # the daemon's gyro rate
