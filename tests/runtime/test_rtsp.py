"""The RTSP live view (`thermod.runtime.rtsp`): the 8-bit mapping, the [rtsp] configuration, the error
without GStreamer, and `thermod run --rtsp` played by a real client (ffmpeg) thermod did not write."""

import os
import shutil
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from tests.support.endpoints import free_port, private_endpoint
from thermod.errors import ConfigError
from thermod.runtime import config
from thermod.runtime.config import RtspConfig
from thermod.runtime.rtsp import Agc, RtspError, RtspServer, compose, output_size, parse_url

REPO = Path(__file__).resolve().parents[2]
THERMOD = Path(sys.executable).with_name("thermod")



def env() -> dict:
    return {**os.environ, "NUMBA_CACHE_DIR": os.environ.get("NUMBA_CACHE_DIR", str(REPO / ".numba_cache"))}


# ------------------------------------------------------------------------------------ AGC
def test_agc_maps_percentiles_to_black_and_white():
    img = np.arange(100 * 100, dtype=np.float32).reshape(100, 100)       # uniform 0‥9999
    agc = Agc(1.0, 99.0)
    lo, hi = agc.update(img)
    assert lo == pytest.approx(99.99, abs=0.01) and hi == pytest.approx(9899.01, abs=0.01)
    out = agc.apply(img, lo, hi)
    assert out.dtype == np.uint8 and out.shape == img.shape
    assert np.all(out.ravel()[:100] == 0) and np.all(out.ravel()[-100:] == 255)   # saturates outside
    mid = img.ravel()[5000]
    assert out.ravel()[5000] == round((mid - lo) / (hi - lo) * 255)
    assert np.all(np.diff(out.ravel().astype(int)) >= 0)                        # monotonic


def test_agc_ignores_a_few_hot_pixels_and_nan():
    rng = np.random.default_rng(1)
    img = rng.normal(3000.0, 20.0, (240, 320)).astype(np.float32)
    ref = Agc(1.0, 99.0).update(img)
    img[::40, ::40] = 60000.0                  # 0.06 % dead-hot pixels
    img[5, 5] = np.nan
    lo, hi = Agc(1.0, 99.0).update(img)
    assert lo == pytest.approx(ref[0], abs=2.0) and hi == pytest.approx(ref[1], abs=2.0)
    out = Agc.apply(img, lo, hi)
    assert out[5, 5] == 0 and out[0, 0] == 255
    # the scene spans most of the grey scale: 2nd–98th percentile of the output ≥ 200 grey levels apart
    p2, p98 = np.percentile(out, [2, 98])
    assert p98 - p2 > 200


def test_agc_flat_frame_is_black_and_smoothing_follows_a_step():
    assert np.all(Agc.apply(np.full((8, 8), 7.0), 7.0, 7.0) == 0)
    agc = Agc(0.0, 100.0, smoothing=0.8)
    agc.update(np.linspace(0, 100, 64).reshape(8, 8))
    for k in range(1, 4):
        lo, hi = agc.update(np.linspace(1000, 1100, 64).reshape(8, 8))
        # exponential filter of (lo, hi): the old range's weight is 0.8^k
        assert lo == pytest.approx(0.8**k * 0 + (1 - 0.8**k) * 1000)
        assert hi == pytest.approx(0.8**k * 100 + (1 - 0.8**k) * 1100)


def test_compose_views_sizes_and_shared_range():
    raw = np.tile(np.linspace(0, 1000, 31, dtype=np.float32), (21, 1))   # odd size 31×21
    frame = raw * 0.5 + 250
    for view in ("deblurred", "raw"):
        img = compose(view, Agc(), frame, raw, None)
        assert img.shape == (22, 32) and img.dtype == np.uint8
        assert output_size(view, 31, 21) == (32, 22)
    sbs = compose("side_by_side", Agc(0.0, 100.0), frame, raw, None)
    assert sbs.shape == (22, 62) and output_size("side_by_side", 31, 21) == (62, 22)
    # both halves through the raw's range: the frame's column of value v has the raw's grey for v
    assert sbs[0, 0] == 0 and sbs[0, 30] == 255
    assert sbs[0, 31 + 15] == sbs[0, 15]          # frame[15] = 500 = raw[15]
    assert sbs[0, 31] == round(250 / 1000 * 255)
    # no raw kept: the frame on both sides
    alone = compose("side_by_side", Agc(), frame, None, None)
    assert np.array_equal(alone[:, :31], alone[:, 31:62])
    import cv2
    bgr = compose("deblurred", Agc(), frame, None, cv2.COLORMAP_INFERNO)
    assert bgr.shape == (22, 32, 3) and len({tuple(p) for p in bgr[0]}) > 10


# ------------------------------------------------------------------------------------ configuration
def test_rtsp_config_defaults_and_errors():
    cfg = config.load()
    assert cfg.rtsp == RtspConfig() and not cfg.rtsp.enabled
    cfg = config.load(None, {"rtsp.enabled": True, "rtsp.url": "rtsp://0.0.0.0:9000/live/a",
                             "rtsp.view": "side_by_side", "rtsp.colormap": "inferno"})
    assert cfg.rtsp.enabled and parse_url(cfg.rtsp.url) == ("0.0.0.0", 9000, "/live/a")
    for key, value, words in (("rtsp.url", "http://127.0.0.1:8554/thermal", "rtsp.url"),
                              ("rtsp.url", "rtsp://127.0.0.1/thermal", "port"),
                              ("rtsp.url", "rtsp://127.0.0.1:8554", "path"),
                              ("rtsp.view", "both", "rtsp.view"),
                              ("rtsp.colormap", "rainbowish", "rtsp.colormap"),
                              ("rtsp.agc_low_pct", 60.0, "rtsp.agc_low_pct"),
                              ("rtsp.bitrate", 10,
                               r"^--set rtsp.bitrate=10: unknown key \(did you mean rtsp.bitrate_kbps\?\)$")):
        with pytest.raises(ConfigError, match=words):
            config.load(None, {key: value})
    with pytest.raises(ConfigError, match=r"^--set rtsp.agc_high_pct=50.0: expected a value above agc_low"):
        config.load(None, {"rtsp.agc_low_pct": 50.0, "rtsp.agc_high_pct": 50.0})


def test_without_pygobject_the_error_names_the_debian_packages(monkeypatch):
    monkeypatch.setitem(sys.modules, "gi", None)          # `import gi` raises ImportError
    with pytest.raises(RtspError) as e:
        RtspServer(RtspConfig(enabled=True), 64, 48, 50.0)
    for pkg in ("gir1.2-gst-rtsp-server-1.0", "gstreamer1.0-plugins-ugly", "gir1.2-gstreamer-1.0"):
        assert pkg in str(e.value)


def test_thermod_run_rtsp_without_gstreamer_exits_with_the_packages(monkeypatch, capsys):
    from thermod.cli import main
    monkeypatch.setitem(sys.modules, "gi", None)
    rc = main(["run", "--rtsp", f"rtsp://127.0.0.1:{free_port()}/thermal", "--endpoint",
               private_endpoint(), "--seconds", "1"])
    err = capsys.readouterr().err
    assert rc == 2 and "thermod run: error: rtsp:" in err and "gir1.2-gst-rtsp-server-1.0" in err


# ------------------------------------------------------------------------------------ a real client
def test_thermod_run_rtsp_port_taken_is_one_line_exit_2(capsys, require):
    require(_gstreamer_ok(), "GStreamer RTSP server (Debian gir1.2-gst-rtsp-server-1.0)")
    from thermod.cli import main
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        rc = main(["run", "--rtsp", f"rtsp://127.0.0.1:{port}/thermal", "--endpoint",
                   private_endpoint(), "--seconds", "1"])
    err = capsys.readouterr().err
    assert rc == 2 and f"rtsp.url: cannot listen on 127.0.0.1:{port}" in err and "in use" in err, err


def _gstreamer_ok() -> bool:
    try:
        from thermod.runtime.rtsp import _import_gst
        _import_gst()
        return True
    except RtspError:
        return False


def _play(url: str, n: int, width: int, height: int, deadline: float, pix_fmt: str = "gray",
          server: subprocess.Popen | None = None) -> np.ndarray:
    """`n` frames of `url` decoded by ffmpeg as [n, height, width] (gray) or [n, height, width, 3]
    (bgr24); retries while the server starts (a `server` process that exits meanwhile fails at once,
    with what it said)."""
    channels = 3 if pix_fmt == "bgr24" else 1
    last = ""
    while time.monotonic() < deadline:
        if server is not None and server.poll() is not None:
            raise AssertionError(f"the server exited ({server.returncode}) before {url} played: "
                                 f"{server.stderr.read()[-2000:]}")
        try:
            p = subprocess.run(["ffmpeg", "-nostdin", "-loglevel", "error", "-rtsp_transport", "tcp",
                                "-i", url, "-frames:v", str(n), "-fps_mode", "passthrough", "-f", "rawvideo",
                                "-pix_fmt", pix_fmt, "-"],
                               capture_output=True, timeout=max(1.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            break
        if p.returncode == 0 and len(p.stdout) == n * width * height * channels:
            shape = (n, height, width, channels) if channels > 1 else (n, height, width)
            return np.frombuffer(p.stdout, np.uint8).reshape(shape)
        last = p.stderr.decode(errors="replace")[-500:] + f" ({len(p.stdout)} bytes)"
        time.sleep(0.5)
    raise AssertionError(f"ffmpeg decoded no {width}x{height} stream from {url}: {last}")


def test_video_bytes_pads_rows_to_4_bytes():
    from thermod.runtime.rtsp import video_bytes
    img = np.arange(6 * 3, dtype=np.uint8).reshape(3, 6)
    b = np.frombuffer(video_bytes(img), np.uint8).reshape(3, 8)
    assert np.array_equal(b[:, :6], img) and not b[:, 6:].any()
    bgr = np.ones((2, 3, 3), np.uint8)
    assert len(video_bytes(bgr)) == 2 * 12 and len(video_bytes(np.ones((2, 4), np.uint8))) == 8


def test_server_odd_size_colour_map_played_by_ffmpeg(require):
    """The server alone (no daemon): a 63×47 picture (padded to 64×48, rows not a multiple of 4 bytes
    in BGR) in the inferno colour map decodes to the colours `compose` made (not swapped, not sheared)."""
    require(shutil.which("ffmpeg") is not None, "ffmpeg (Debian package ffmpeg)")
    require(_gstreamer_ok(), "GStreamer RTSP server, x264enc (Debian gir1.2-gst-rtsp-server-1.0 "
            "gstreamer1.0-plugins-ugly)")
    import cv2
    yy, xx = np.mgrid[0:47, 0:63]
    scene = (300.0 + 2.0 * xx + 1.0 * yy).astype(np.float32)       # a ramp: every colour of the map
    cfg = RtspConfig(enabled=True, url=f"rtsp://127.0.0.1:{free_port()}/t", colormap="inferno",
                     agc_smoothing=0.0, bitrate_kbps=4000)
    server = RtspServer(cfg, 63, 47, 25.0)
    server.start()
    stop = threading.Event()

    def camera():
        i = 0
        while not stop.is_set():
            server.offer(scene, time.monotonic(), i)
            i += 1
            time.sleep(0.04)

    th = threading.Thread(target=camera, daemon=True)
    th.start()
    try:
        frames = _play(cfg.url, 5, 64, 48, time.monotonic() + 60, pix_fmt="bgr24")
        stats = server.stats()
    finally:
        stop.set()
        th.join()
        server.stop()
    expected = compose("deblurred", Agc(cfg.agc_low_pct, cfg.agc_high_pct), scene, None,
                       cv2.COLORMAP_INFERNO).astype(float)
    err = np.abs(frames[-1].astype(float) - expected)[:47, :63].mean(axis=(0, 1))
    swapped = np.abs(frames[-1].astype(float) - expected[..., ::-1])[:47, :63].mean()
    # measured: 1.8–2.8 levels per channel (4:2:0 chroma, H.264); with B and R swapped: 74
    assert err.max() < 12, err
    assert swapped > 3 * err.max()
    assert stats["frames_pushed"] >= 5 and stats["url"] == cfg.url
    assert 5 <= stats["encoded"] <= stats["frames_pushed"] + 1     # + the one being counted


@pytest.mark.slow
@pytest.mark.parametrize("view", ["deblurred", "raw", "side_by_side"])
def test_thermod_run_rtsp_played_by_ffmpeg(view, require):
    require(shutil.which("ffmpeg") is not None, "ffmpeg (Debian package ffmpeg)")
    require(_gstreamer_ok(), "GStreamer RTSP server, x264enc (Debian gir1.2-gst-rtsp-server-1.0 "
            "gstreamer1.0-plugins-ugly)")
    from thermod.client.subscriber import Subscriber
    cal = config.load().calibration
    url = f"rtsp://127.0.0.1:{free_port()}/thermal"
    ep = private_endpoint()
    # the hand-held shake these picture statistics were measured on: the default multirotor motion
    # swings the scene's few dark objects in and out of view, and the smoothed AGC range lags behind
    # (agc_smoothing 0.8), so some decoded frames' 1st percentile sits at 72–168 (AGC as designed)
    proc = subprocess.Popen([str(THERMOD), "run", "--rtsp", url, "--endpoint", ep, "--seconds", "150",
                             "--set", "deblur.method=wiener", "--set", f"rtsp.view={view}",
                             "--set", "sim.motion=shake:3", "-v"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env(), text=True)
    try:
        width = 2 * cal.width if view == "side_by_side" else cal.width
        with Subscriber(ep, topics=("health",)) as sub:
            frames = _play(url, 10, width, cal.height, time.monotonic() + 120, server=proc)
            health = None
            for _ in range(40):       # older health messages may still be queued: the one counting ffmpeg's
                m = sub.recv(timeout=0.5)
                if m is not None and (m[1].get("rtsp") or {}).get("frames_pushed", 0) >= 10:
                    health = m[1]["rtsp"]
                    break
        assert proc.poll() is None, proc.stderr.read()
    finally:
        proc.terminate()
        out = proc.communicate(timeout=20)[1]
    assert proc.returncode == 0, out[-2000:]
    assert "rtsp: serving" in out
    # the scene moves (hand-held shake): consecutive decoded pictures differ
    diffs = [np.abs(frames[i + 1].astype(int) - frames[i]).mean() for i in range(len(frames) - 1)]
    assert sum(d > 0.5 for d in diffs) >= 5, diffs
    # not blank: AGC spreads the scene over the grey scale (its 1st–99th percentile → 0‥255);
    # measured over 40 decoded frames: 1st percentile 0–14, 99th 252–255, std 31–97
    for f in frames:
        p1, p99 = np.percentile(f, [1, 99])
        assert p1 < 64 and p99 > 192 and f.std() > 10, (p1, p99, f.std())
    if view == "side_by_side":
        # raw left, deblurred right, same range: similar brightness, and the deblurred half is sharper
        left, right = frames[:, :, :cal.width].astype(float), frames[:, :, cal.width:].astype(float)
        assert abs(left.mean() - right.mean()) < 20
        sharp = [np.abs(np.diff(h, axis=1)).mean() for h in (left, right)]
        assert sharp[1] > sharp[0], sharp
    assert health is not None and health["url"] == url, "no health message counted the 10 frames played"
    assert health["dropped"] >= 0 and health["view"] == view
