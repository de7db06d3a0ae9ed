"""The live view as an H.264 RTSP stream (``[rtsp]``, ``thermod run --rtsp URL``).

GStreamer's RTSP server (PyGObject, ``GstRtspServer``) serves one shared media built from::

    appsrc (live, time format, leaky: drops old buffers) ! videoconvert ! x264enc (zerolatency,
    ultrafast, short GOP) ! rtph264pay

Frames reach it through a one-slot mailbox: the daemon's emit path (a pipeline thread) only swaps a
reference into the slot — it never converts, encodes or waits — and a feeder thread takes the newest
frame, maps it to 8 bits (`Agc`, optional OpenCV colour map) and pushes it to ``appsrc``. A frame
still in the slot when the next one arrives is replaced and counted (``dropped``), so a slow encoder
or client adds at most one frame of latency and never blocks the daemon. While no client is
connected nothing is converted. A GLib main loop on its own thread runs the server.

Nothing here is imported by the core; GStreamer is imported when an `RtspServer` is built, and its
absence is a `RtspError` naming the Debian packages to install.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from typing import TYPE_CHECKING

import numpy as np

from thermod.errors import ThermodError
from thermod.io.display import Agc, side_by_side
from thermod.io.endpoints import is_loopback_host, split_rtsp_url

if TYPE_CHECKING:
    from thermod.runtime.config import RtspConfig

log = logging.getLogger("thermod.runtime.rtsp")

DEBIAN_PACKAGES = ("gir1.2-gstreamer-1.0", "gir1.2-gst-plugins-base-1.0", "gir1.2-gst-rtsp-server-1.0",
                   "gstreamer1.0-plugins-base", "gstreamer1.0-plugins-good", "gstreamer1.0-plugins-ugly")
# element → the Debian package that ships it
_ELEMENTS = {"appsrc": "gstreamer1.0-plugins-base", "videoconvert": "gstreamer1.0-plugins-base",
             "x264enc": "gstreamer1.0-plugins-ugly", "rtph264pay": "gstreamer1.0-plugins-good"}
RAW_KEEP = 64          # raw frames kept for side by side: covers the pipeline's reorder wait at 50+ fps


class RtspError(ThermodError):
    """The RTSP stream cannot be served: GStreamer missing, bad URL, port taken."""


def parse_url(url: str) -> tuple[str, int, str]:
    """``rtsp://HOST:PORT/PATH`` → (host, port, mount path); anything else is an RtspError."""
    try:
        return split_rtsp_url(url)
    except ValueError as e:
        raise RtspError(f"expected {e}, got {url!r}") from None


def compose(view: str, agc: Agc, frame: np.ndarray | None, raw: np.ndarray | None,
            colormap: int | None) -> np.ndarray:
    """The 8-bit picture of `view`: GRAY8 [H, W], or BGR [H, W, 3] with a colour map. Side by side is
    raw | deblurred, both through the raw's range (same counts → same grey, so the two compare);
    a missing raw (not kept) shows the frame on both sides. Odd sizes are padded to even (H.264 4:2:0)."""
    if view == "raw":
        img = agc(raw)
    elif view == "deblurred":
        img = agc(frame)
    else:
        img = side_by_side(frame if raw is None or raw.shape != frame.shape else raw, frame, agc)
    h, w = img.shape
    if h % 2 or w % 2:
        img = np.pad(img, ((0, h % 2), (0, w % 2)), mode="edge")
    if colormap is not None:
        import cv2
        img = cv2.applyColorMap(img, colormap)
    return np.ascontiguousarray(img)


def output_size(view: str, width: int, height: int) -> tuple[int, int]:
    """(width, height) of the encoded picture."""
    w = 2 * width if view == "side_by_side" else width
    return w + w % 2, height + height % 2


def video_bytes(img: np.ndarray) -> bytes:
    """The picture as GStreamer lays out raw video: each row padded to a multiple of 4 bytes."""
    rows = img.reshape(img.shape[0], -1)
    pad = -rows.shape[1] % 4
    return (np.pad(rows, ((0, 0), (0, pad))) if pad else rows).tobytes()


def colormap_code(name: str) -> int | None:
    if not name:
        return None
    import cv2
    return int(getattr(cv2, "COLORMAP_" + name.upper()))


# ------------------------------------------------------------------------------------ GStreamer
def _import_gst():
    """(Gst, GstRtspServer, GLib, GstVideo), initialised; RtspError naming the Debian packages if missing."""
    hint = "install the Debian packages " + " ".join(DEBIAN_PACKAGES) + " (make debian-deps) and PyGObject " \
           "(pip install 'thermod[aravis]')"
    try:
        import gi
    except ImportError:
        raise RtspError(f"rtsp: PyGObject (gi) is not installed; {hint}") from None
    try:
        gi.require_version("Gst", "1.0")
        gi.require_version("GstRtspServer", "1.0")
        gi.require_version("GstVideo", "1.0")
        from gi.repository import GLib, Gst, GstRtspServer, GstVideo
    except (ImportError, ValueError) as e:
        raise RtspError(f"rtsp: GStreamer's RTSP server is not available ({e}); {hint}") from None
    Gst.init(None)
    missing = {el: pkg for el, pkg in _ELEMENTS.items() if Gst.ElementFactory.find(el) is None}
    if missing:
        raise RtspError(f"rtsp: GStreamer elements {', '.join(missing)} missing; install the Debian packages "
                        + " ".join(sorted(set(missing.values()))))
    return Gst, GstRtspServer, GLib, GstVideo


class RtspServer:
    """Serves frames offered by the daemon (`offer`, `offer_raw`) as ``cfg.url``; `start`, `stop`.

    `stats()` → ``{url, clients, frames_pushed, dropped, ...}`` for the health message: ``dropped``
    counts frames replaced in the mailbox, ``frames_pushed − encoded`` those the leaky ``appsrc``
    dropped because the encoder was busy.
    """

    def __init__(self, cfg: RtspConfig, width: int, height: int, frame_rate_hz: float):
        self.cfg = cfg
        self.host, self.port, self.mount = parse_url(cfg.url)
        self.Gst, self._GstRtspServer, self._GLib, self._GstVideo = _import_gst()
        self.width, self.height = width, height
        self.out_w, self.out_h = output_size(cfg.view, width, height)
        self.frame_rate_hz = frame_rate_hz
        self._agc = Agc(cfg.agc_low_pct, cfg.agc_high_pct, cfg.agc_smoothing)
        self._cmap = colormap_code(cfg.colormap)
        self._lock = threading.Condition()
        self._slot: tuple | None = None        # (frame, raw, t) waiting for the feeder
        self._raws: collections.OrderedDict[int, np.ndarray] = collections.OrderedDict()
        self._appsrc = self._encoder = None
        self._last_pts = -1
        self._stop = threading.Event()
        self.clients = 0
        self.counters = collections.Counter()
        self._loop = self._ctx = self._source = self._server = None
        self._threads: list[threading.Thread] = []

    @property
    def url(self) -> str:
        return f"rtsp://{self.host}:{self.port}{self.mount}"

    # ---------------------------------------------------------------- the daemon's side (never blocks)
    def offer(self, image: np.ndarray, t: float, frame_id: int) -> None:
        """An output frame (deblurred or passed through) from the daemon's emit path."""
        if self.cfg.view == "raw":
            return
        raw = None
        if self.cfg.view == "side_by_side":
            with self._lock:
                raw = self._raws.get(frame_id)
        self._post(image, raw, t)

    def offer_raw(self, image: np.ndarray, t: float, frame_id: int) -> None:
        """A raw frame from the camera thread: the stream itself (view = raw) or kept for side by side."""
        if self.cfg.view == "raw":
            self._post(None, image, t)
        elif self.cfg.view == "side_by_side" and self.clients:
            copy = np.array(image, copy=True)   # the driver may reuse its buffer
            with self._lock:
                self._raws[frame_id] = copy
                while len(self._raws) > RAW_KEEP:
                    self._raws.popitem(last=False)

    def _post(self, frame, raw, t) -> None:
        with self._lock:
            if not self.clients:
                self.counters["no_client"] += 1
                return
            if self._slot is not None:
                self.counters["dropped"] += 1
            self._slot = (frame, raw, t)
            self._lock.notify()

    # ---------------------------------------------------------------- feeder thread
    def _feed(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                if self._slot is None:
                    self._lock.wait(0.1)
                item, self._slot = self._slot, None
                src = self._appsrc
            if item is None:
                continue
            if src is None:
                with self._lock:
                    self.counters["no_client"] += 1
                continue
            try:
                self._push(src, *item)
            except Exception as e:  # noqa: BLE001 - a bad frame must not end the stream
                with self._lock:
                    self.counters["push_errors"] += 1
                log.warning("rtsp: frame not pushed: %s: %s", type(e).__name__, e)

    def _push(self, src, frame, raw, t) -> None:
        Gst = self.Gst
        pts = self._pts(src, t)
        if pts is None:               # the media is not running yet (a client is connecting)
            with self._lock:
                self.counters["not_playing"] += 1
            return
        img = compose(self.cfg.view, self._agc, frame, raw, self._cmap)
        buf = Gst.Buffer.new_wrapped(video_bytes(img))
        buf.pts = pts
        buf.duration = int(1e9 / self.frame_rate_hz)
        ret = src.emit("push-buffer", buf)
        with self._lock:
            self.counters["frames_pushed" if ret == Gst.FlowReturn.OK else "push_refused"] += 1

    def _pts(self, src, t: float) -> int | None:
        """The frame's host time `t` (CLOCK_MONOTONIC) as the pipeline's running time, so the stream
        keeps the frames' capture spacing (not the feeder's jitter); None before the pipeline runs."""
        clock = src.get_clock()
        if clock is None:
            return None
        now_running = clock.get_time() - src.get_base_time()
        pts = now_running - int(round((time.monotonic() - t) * 1e9))
        pts = max(pts, self._last_pts + 1, 0)     # frames arrive in order; never step back
        self._last_pts = pts
        return pts

    # ---------------------------------------------------------------- RTSP server
    def _launch(self) -> str:
        # x264 in one thread: one slice per frame and no frame-thread delay (tune=zerolatency alone
        # turns on sliced threads; ffmpeg then decoded only the first of the two slices of each frame)
        fmt = "GRAY8" if self._cmap is None else "BGR"
        rate = max(1, int(round(self.frame_rate_hz)))
        return (f"( appsrc name=thermod_src is-live=true format=time do-timestamp=false block=false "
                f"max-buffers=1 leaky-type=downstream "
                f"caps=video/x-raw,format={fmt},width={self.out_w},height={self.out_h},framerate={rate}/1 "
                f"! videoconvert ! video/x-raw,format=I420 "
                f"! x264enc name=thermod_enc tune=zerolatency threads=1 speed-preset=ultrafast "
                f"key-int-max={self.cfg.key_int} bitrate={self.cfg.bitrate_kbps} "
                f"! rtph264pay name=pay0 pt=96 config-interval=-1 )")

    def _media_configure(self, factory, media) -> None:
        bin_ = media.get_element()
        media.connect("unprepared", self._media_unprepared)
        with self._lock:
            self._appsrc = bin_.get_child_by_name("thermod_src")
            self._encoder = bin_.get_child_by_name("thermod_enc")
            self._last_pts = -1
        self._encoder.get_static_pad("src").add_probe(self.Gst.PadProbeType.BUFFER, self._encoded)
        log.info("rtsp: stream started (%dx%d)", self.out_w, self.out_h)

    def _encoded(self, pad, info):
        with self._lock:
            self.counters["encoded"] += 1
        return self.Gst.PadProbeReturn.OK

    def _media_unprepared(self, media) -> None:
        with self._lock:
            self._appsrc = self._encoder = None

    def _client_connected(self, server, client) -> None:
        with self._lock:
            self.clients += 1
            self.counters["connections"] += 1
        client.connect("closed", self._client_closed)
        client.connect("play-request", self._client_play)

    def _client_play(self, client, ctx) -> None:
        """A client starts playing: the encoder's next frame is a key frame (with SPS/PPS), so the
        picture starts at once instead of after up to ``key_int`` undecodable frames."""
        with self._lock:
            enc = self._encoder
        if enc is not None:
            ev = self._GstVideo.video_event_new_upstream_force_key_unit(self.Gst.CLOCK_TIME_NONE, True, 0)
            enc.get_static_pad("src").send_event(ev)

    def _client_closed(self, client) -> None:
        with self._lock:
            self.clients = max(0, self.clients - 1)
            if not self.clients:
                self._raws.clear()

    def start(self) -> None:
        """Listen on the URL's port (RtspError if it cannot) and start the main-loop and feeder threads."""
        RS, GLib = self._GstRtspServer, self._GLib
        self._server = server = RS.RTSPServer()
        server.set_address(self.host)
        server.set_service(str(self.port))
        factory = RS.RTSPMediaFactory()
        factory.set_launch(self._launch())
        factory.set_shared(True)
        factory.connect("media-configure", self._media_configure)
        server.get_mount_points().add_factory(self.mount, factory)
        server.connect("client-connected", self._client_connected)
        self._ctx = GLib.MainContext.new()
        try:
            self._source = server.create_source(None)
        except GLib.Error as e:
            raise RtspError(f"rtsp.url: cannot listen on {self.host}:{self.port}: {e.message}") from None
        self._source.attach(self._ctx)
        self._loop = GLib.MainLoop.new(self._ctx, False)
        self._stop.clear()
        self._threads = [threading.Thread(target=self._run_loop, name="thermod-rtsp", daemon=True),
                         threading.Thread(target=self._feed, name="thermod-rtsp-feed", daemon=True)]
        for th in self._threads:
            th.start()
        log.info("rtsp: serving %s (%s)", self.url, self.cfg.view)
        if not is_loopback_host(self.host):
            log.warning("rtsp: %s is reachable from the network and RTSP has no authentication here: "
                        "anyone who can reach it can watch", self.url)

    def _run_loop(self) -> None:
        self._ctx.push_thread_default()
        try:
            self._loop.run()
        finally:
            self._ctx.pop_thread_default()

    def stop(self, timeout: float = 1.0) -> None:
        """Close clients, stop the threads; idempotent."""
        if self._loop is None:
            return
        RS = self._GstRtspServer
        self._stop.set()
        with self._lock:
            self._lock.notify_all()
        done = threading.Event()

        def close_all(*_):
            # on the loop's thread: the server's objects are not thread safe
            self._server.client_filter(lambda server, client, *a: RS.RTSPFilterResult.REMOVE)
            self._source.destroy()
            self._loop.quit()
            done.set()
            return False

        src = self._GLib.idle_source_new()
        src.set_callback(close_all)
        src.attach(self._ctx)
        t0 = time.monotonic()
        done.wait(timeout)
        for th in self._threads:
            th.join(max(0.05, timeout - (time.monotonic() - t0)))
        self._loop = None

    def stats(self) -> dict:
        with self._lock:
            c = dict(self.counters)
            clients = self.clients
        return {"url": self.url, "view": self.cfg.view, "clients": clients,
                "frames_pushed": c.get("frames_pushed", 0), "dropped": c.get("dropped", 0),
                "encoded": c.get("encoded", 0),
                "push_refused": c.get("push_refused", 0), "push_errors": c.get("push_errors", 0),
                "connections": c.get("connections", 0)}
