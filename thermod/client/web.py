"""The browser view of `thermod watch --http HOST:PORT`: a live page served with the standard library.

The subscriber thread hands every message to `LiveView.add` (which only keeps references under a
short lock) and calls `LiveView.sample` once a second; `WebServer` threads encode images on demand
(once per frame, shared by every browser), so a slow or stalled browser never holds up the subscriber.

Endpoints (all GET, nothing is ever written):

- ``/``              the page: raw | deblurred, the current kernel, health plots (plain JS on <canvas>)
- ``/frame.jpg``     newest frame as 8-bit JPEG: raw | deblurred side by side with one 1st–99th
                     percentile stretch (AGC) for both, or the deblurred alone when no raw frames arrive
                     (``X-Has-Raw: 0``); 503 until the first frame
- ``/kernel.png``    the newest deblurred frame's blur kernel (topic ``kernel``), scaled to its peak;
                     a grid is shown cell by cell; 404 while none has arrived
- ``/health.json``   status and the last `HISTORY_S` seconds of fps, latency percentiles, drops,
                     gyro rate and clock-fit residuals, one point a second

The page loads nothing from elsewhere (no CDN): the machine may be offline.
"""

from __future__ import annotations

import collections
import json
import logging
import math
import socket
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np

from thermod.errors import ThermodError
from thermod.io.display import side_by_side, to_u8
from thermod.io.endpoints import is_loopback_host
from thermod.io.json_safe import jsonable

log = logging.getLogger(__name__)

HISTORY_S = 300            # seconds of health history kept and plotted
# raw frames kept to pair with their deblurred frame (by frame_id): the deblurred output may lag the
# raw by a second or more on a loaded machine (≈ 100 VGA frames at 50 fps in 64 MiB)
RAW_KEEP_BYTES = 64 << 20
RAW_STALE_S = 2.0          # no raw frame for this long: show the deblurred frame alone
JPEG_QUALITY = 85
KERNEL_VIEW_PX = 192       # the kernel image is scaled (nearest) to at most this many pixels a side
# Page layout (CSS px); tests read these to find the regions in a screenshot.
LAYOUT = {"frame": (8, 56, 900, 338), "kernel": (924, 56, 192, 192),
          "plots": (8, 430, 1264, 440), "plot_size": (410, 205)}


class WebError(ThermodError):
    """The --http address is malformed or cannot be bound."""


# ------------------------------------------------------------------------------------- 8-bit images
def kernel_image(weights: np.ndarray, size: int = KERNEL_VIEW_PX, gap: int = 2) -> np.ndarray:
    """A kernel [kh, kw] (or grid [rows, cols, kh, kw]) as 8-bit: weight / peak, cells separated by
    `gap` pixels, scaled up (nearest neighbour, an integer factor) to at most `size` a side, or, when
    larger, down by an integer factor taking each block's maximum: a 6 × 8 grid of 95 × 22 kernels left
    for the browser to shrink into the 192 px box was averaged, its peak drawn at 186 of 255 and its
    one-pixel comet tails faded."""
    w = np.asarray(weights, np.float32)
    if w.ndim == 2:
        w = w[None, None]
    rows, cols, kh, kw = w.shape
    peak = float(w.max())
    cells = to_u8(w, 0.0, peak if peak > 0 else 1.0)
    mosaic = np.full((rows * (kh + gap) - gap, cols * (kw + gap) - gap), 40, np.uint8)
    for r in range(rows):
        for c in range(cols):
            mosaic[r * (kh + gap): r * (kh + gap) + kh, c * (kw + gap): c * (kw + gap) + kw] = cells[r, c]
    if max(mosaic.shape) > size:
        f = -(-max(mosaic.shape) // size)           # ceil: the result fits the box
        H, W = -(-mosaic.shape[0] // f) * f, -(-mosaic.shape[1] // f) * f
        padded = np.zeros((H, W), np.uint8)
        padded[: mosaic.shape[0], : mosaic.shape[1]] = mosaic
        return padded.reshape(H // f, f, W // f, f).max(axis=(1, 3))
    k = max(1, size // max(mosaic.shape))
    return np.repeat(np.repeat(mosaic, k, axis=0), k, axis=1)


# --------------------------------------------------------------------------------------- the state
class LiveView:
    """What the page shows. `add` and `sample` run in the subscriber's thread, the rest in HTTP threads."""

    def __init__(self, endpoint: str = "", history_s: int = HISTORY_S):
        import cv2  # only `watch --http` needs the encoder

        self._cv2 = cv2
        self.endpoint = endpoint
        self._lock = threading.Lock()
        self._frames: collections.deque = collections.deque(maxlen=4)   # (header, array), newest last
        self._raws: collections.OrderedDict = collections.OrderedDict()  # frame_id → array
        self._raw_bytes = 0
        self._last_raw_at = -math.inf
        self._kernel: tuple[dict, np.ndarray] | None = None
        self._health: dict | None = None
        self._counts: collections.Counter = collections.Counter()
        self._interval = self._new_interval()
        self._prev_drops: float | None = None
        self._prev_lost = 0
        self._t0 = time.monotonic()
        self.series: collections.deque = collections.deque(maxlen=int(history_s))
        self._encode_lock = threading.Lock()
        self._jpeg: tuple[tuple, bytes, bool] | None = None
        self._png: tuple[int, bytes] | None = None

    @staticmethod
    def _new_interval() -> dict:
        return {"n": 0, "t0": math.inf, "t1": -math.inf, "lat": []}

    # ------------------------------------------------------------ subscriber side (never blocks)
    def add(self, topic: str, header: dict, array) -> None:
        with self._lock:
            self._counts[topic] += 1
            if topic == "frame":
                self._frames.append((header, array))
                iv = self._interval
                iv["n"] += 1
                iv["t0"], iv["t1"] = min(iv["t0"], header["t"]), max(iv["t1"], header["t"])
                iv["lat"].append(header.get("received", header["published"]) - header["t"])
                if header["deblurred"]:
                    self._counts["deblurred"] += 1
            elif topic == "raw":
                old = self._raws.pop(header["frame_id"], None)
                self._raw_bytes += array.nbytes - (0 if old is None else old.nbytes)
                self._raws[header["frame_id"]] = array
                self._last_raw_at = time.monotonic()
                while self._raw_bytes > RAW_KEEP_BYTES and len(self._raws) > 1:
                    self._raw_bytes -= self._raws.popitem(last=False)[1].nbytes
            elif topic == "kernel":
                self._kernel = (header, array)
            elif topic == "health":
                self._health = header

    def sample(self, gaps: dict | None = None, now: float | None = None) -> dict:
        """Close one plot interval (call about once a second): fps and latency percentiles of the frames
        received in it, drops (the daemon's counters and messages lost on the wire) per second, and
        the daemon's gyro rate and clock-fit residuals from its newest health message."""
        now = time.monotonic() if now is None else now
        with self._lock:
            iv, self._interval = self._interval, self._new_interval()
            health = self._health
        prev_t = self.series[-1]["t"] if self.series else None
        t = now - self._t0
        dt = t - prev_t if prev_t is not None and t > prev_t else None
        fps = (iv["n"] - 1) / (iv["t1"] - iv["t0"]) if iv["n"] > 1 and iv["t1"] > iv["t0"] else None
        lat = np.percentile(1e3 * np.asarray(iv["lat"]), [50, 95, 99]) if iv["lat"] else [None] * 3
        lost = sum((gaps or {}).values())
        point = {"t": t, "fps": fps, "lat_p50_ms": lat[0], "lat_p95_ms": lat[1], "lat_p99_ms": lat[2],
                 "lost_per_s": (lost - self._prev_lost) / dt if dt else None,
                 "drops_per_s": None, "gyro_hz": None, "gyro_residual_us": None,
                 "camera_residual_us": None}
        self._prev_lost = lost
        if health is not None:
            drops = sum(v for v in (health.get("drops") or {}).values()
                        if isinstance(v, (int, float)) and not isinstance(v, bool))
            if self._prev_drops is not None and dt:
                point["drops_per_s"] = max(0.0, drops - self._prev_drops) / dt
            self._prev_drops = drops
            point["gyro_hz"] = (health.get("rates") or {}).get("gyro_hz")
            for role in ("gyro", "camera"):
                res = ((health.get("clocks") or {}).get(role) or {}).get("residual_std_s")
                point[f"{role}_residual_us"] = None if res is None else 1e6 * res
        point = jsonable(point)
        self.series.append(point)
        return point

    # ------------------------------------------------------------------ HTTP side
    def _newest_pair(self):
        """The newest frame and its raw counterpart; while raw frames flow, a frame whose raw has not
        arrived is skipped for an older one that has it. → (header, frame, raw or None, raw flowing)
        or None."""
        with self._lock:
            if not self._frames:
                return None
            raw_flowing = time.monotonic() - self._last_raw_at < RAW_STALE_S
            if raw_flowing:
                for h, a in reversed(self._frames):
                    raw = self._raws.get(h.get("frame_id"))
                    if raw is not None:
                        return h, a, raw, True
            h, a = self._frames[-1]
            return h, a, None, raw_flowing

    def frame_jpeg(self) -> tuple[bytes, dict] | None:
        """(JPEG bytes, header of the frame shown) of the newest frame (pair), encoded once."""
        got = self._newest_pair()
        if got is None:
            return None
        h, frame, raw, flowing = got
        key = (h.get("frame_id"), h.get("seq"), raw is not None)
        with self._encode_lock:
            if self._jpeg is None or self._jpeg[0] != key:
                img = side_by_side(raw, frame, gap=4)
                ok, buf = self._cv2.imencode(".jpg", img, [self._cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
                if not ok:
                    raise WebError("OpenCV could not encode a JPEG")
                self._jpeg = (key, buf.tobytes(), raw is not None)
            return self._jpeg[1], {**h, "has_raw": self._jpeg[2], "raw_flowing": flowing}

    def kernel_png(self) -> tuple[bytes, dict] | None:
        with self._lock:
            k = self._kernel
        if k is None:
            return None
        h, w = k
        with self._encode_lock:
            if self._png is None or self._png[0] != h.get("seq"):
                ok, buf = self._cv2.imencode(".png", kernel_image(w))
                if not ok:
                    raise WebError("OpenCV could not encode a PNG")
                self._png = (h.get("seq"), buf.tobytes())
            return self._png[1], h

    def status(self) -> dict:
        """What /health.json returns: counts, the newest frame's and kernel's headers, the series."""
        with self._lock:
            counts = dict(self._counts)
            frame = dict(self._frames[-1][0]) if self._frames else None
            kernel = dict(self._kernel[0]) if self._kernel else None
            health = self._health
            raw_flowing = time.monotonic() - self._last_raw_at < RAW_STALE_S
        series = list(self.series)
        keep = ("frame_id", "t", "deblurred", "reason", "kernel_size", "kernel_extent_px", "coverage")
        return jsonable({
            "endpoint": self.endpoint, "counts": counts, "raw": raw_flowing,
            "frame": None if frame is None else {k: frame.get(k) for k in keep},
            "kernel": None if kernel is None else {k: kernel.get(k) for k in
                                                   ("frame_id", "shape", "origin", "extent_px", "coverage")},
            "health": None if health is None else {
                **{k: health.get(k) for k in ("rates", "drops", "ready", "gyro_online", "clocks",
                                              "calibration", "cpu", "warming_up")},
                "stage_ms": (health.get("pipeline") or {}).get("stage_ms")},
            "series": {k: [p.get(k) for p in series] for k in (series[0] if series else {})},
        })


# ------------------------------------------------------------------------------------- the server
def parse_bind(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[IPv6]:PORT``; port 0 = any free port) → (host, port), or `WebError`."""
    host, sep, port = str(text).rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise WebError(f"--http {text!r}: expected HOST:PORT, e.g. 127.0.0.1:8080 ([::1]:8080 for IPv6)")
    return host, int(port)


class WebServer:
    """ThreadingHTTPServer bound exactly where asked, serving `view` from a background thread."""

    def __init__(self, view: LiveView, bind: str):
        self.view = view
        host, port = parse_bind(bind)
        try:
            family = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0][0]
        except socket.gaierror as e:
            raise WebError(f"--http {bind}: cannot resolve {host!r} ({e})") from None
        server_cls = type("_Server", (ThreadingHTTPServer,), {"address_family": family,
                                                                 "daemon_threads": True})
        try:
            self.httpd = server_cls((host, port), _handler(view))
        except OSError as e:
            raise WebError(f"--http {bind}: cannot listen there ({e.strerror or e})") from None
        if not is_loopback_host(host):
            log.warning("--http %s: reachable from the network, without authentication", bind)
        h, p = self.httpd.server_address[:2]
        self.url = f"http://{f'[{h}]' if ':' in h else h}:{p}/"
        self._thread: threading.Thread | None = None

    def start(self) -> WebServer:
        self._thread = threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.2},
                                        name="thermod-web", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        if self._thread is not None:
            self.httpd.shutdown()
            self._thread.join()
            self._thread = None
        self.httpd.server_close()

    def __enter__(self) -> WebServer:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def _handler(view: LiveView):
    class Handler(BaseHTTPRequestHandler):
        timeout = 10.0                      # a client that stops talking frees its thread
        server_version = "thermod-watch"

        def do_GET(self):  # noqa: N802 - http.server's name
            path = self.path.split("?", 1)[0]
            if path in ("/", "/index.html"):
                self._send(200, "text/html; charset=utf-8", PAGE.encode())
            elif path == "/health.json":
                self._send(200, "application/json", json.dumps(view.status(), allow_nan=False).encode())
            elif path == "/frame.jpg":
                got = view.frame_jpeg()
                if got is None:
                    self._send(503, "text/plain", b"no frame received yet\n")
                else:
                    data, h = got
                    self._send(200, "image/jpeg", data, {"X-Frame-Id": str(h.get("frame_id")),
                                                         "X-Has-Raw": "1" if h["has_raw"] else "0",
                                                         "X-Raw-Flowing": "1" if h["raw_flowing"] else "0"})
            elif path == "/kernel.png":
                got = view.kernel_png()
                if got is None:
                    self._send(404, "text/plain", b"no kernel received yet\n")
                else:
                    h = got[1]
                    self._send(200, "image/png", got[0], {
                        "X-Frame-Id": str(h.get("frame_id")), "X-Shape": "x".join(map(str, h["shape"])),
                        "X-Extent-Px": str(h.get("extent_px")), "X-Coverage": str(h.get("coverage"))})
            else:
                self._send(404, "text/plain", b"not found\n")

        def _send(self, code: int, ctype: str, body: bytes, extra: dict | None = None) -> None:
            self.send_response(code)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            for k, v in (extra or {}).items():
                self.send_header(k, v)
            self.end_headers()
            try:
                self.wfile.write(body)
            except (BrokenPipeError, ConnectionResetError):
                pass

        def log_message(self, fmt, *args):
            log.debug("%s %s", self.address_string(), fmt % args)

    return Handler


# ----------------------------------------------------------------------------------------- the page
def _box(name: str) -> str:
    x, y, w, h = LAYOUT[name]
    return f"left:{x}px;top:{y}px;width:{w}px;height:{h}px"


_PW, _PH = LAYOUT["plot_size"]
PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>thermod watch</title>
<style>
body{margin:0;background:#16181c;color:#d8dde4;font:13px/1.35 system-ui,sans-serif}
.abs{position:absolute}
#bar{left:8px;top:6px;right:8px;height:22px;font-size:14px;white-space:nowrap;overflow:hidden}
.lbl{position:absolute;top:34px;color:#9aa4b1}
#frame{object-fit:contain;background:#000}
#kernel{image-rendering:pixelated;object-fit:contain;background:#000}
#kinfo{left:924px;top:256px;width:340px;color:#9aa4b1}
#cal{left:924px;top:334px;width:350px;color:#9aa4b1;font-size:12px}
#plots{display:flex;flex-wrap:wrap;gap:12px}
canvas{background:#0e1013;border:1px solid #2a2f36}
.warn{color:#f0b44c}
</style></head><body>
<div id="bar" class="abs">thermod watch &mdash; waiting for the daemon&hellip;</div>
<div class="lbl" id="lraw" style="left:8px">raw</div>
<div class="lbl" id="ldeb" style="left:462px">deblurred</div>
<div class="lbl" style="left:924px">kernel (weight / peak)</div>
<img id="frame" class="abs" style="FRAME_BOX" alt="">
<img id="kernel" class="abs" style="KERNEL_BOX" alt="">
<div id="kinfo" class="abs"></div>
<div id="cal" class="abs"></div>
<div id="plots" class="abs" style="PLOTS_BOX">
<canvas id="p_fps" width="@PW@" height="@PH@"></canvas>
<canvas id="p_lat" width="@PW@" height="@PH@"></canvas>
<canvas id="p_drops" width="@PW@" height="@PH@"></canvas>
<canvas id="p_gyro" width="@PW@" height="@PH@"></canvas>
<canvas id="p_clock" width="@PW@" height="@PH@"></canvas>
</div>
<script>
"use strict";
const $ = id => document.getElementById(id);
function fmt(v, d) { return v === null || v === undefined ? "–" : Number(v).toFixed(d); }

// GET past the browser's cache (a new URL each time)
const fresh = path => fetch(path + "?" + Date.now(), {cache: "no-store"});

// Show the image at path in <img id>, releasing the blob URL it showed before; the response, for its headers.
async function showImage(path, id) {
  const r = await fresh(path);
  if (r.ok) {
    const img = $(id), old = img.src;
    img.src = URL.createObjectURL(await r.blob());
    if (old.startsWith("blob:")) URL.revokeObjectURL(old);
  }
  return r;
}

async function pollFrame() {
  try {
    const r = await showImage("/frame.jpg", "frame");
    if (r.ok) {
      const raw = r.headers.get("X-Has-Raw") === "1", flowing = r.headers.get("X-Raw-Flowing") === "1";
      $("lraw").textContent = raw ? "raw" : "";
      $("ldeb").style.left = raw ? "462px" : "8px";
      $("ldeb").innerHTML = raw ? "deblurred" : "deblurred <span class=warn>(" + (flowing
        ? "raw frames arrive, but the deblurred output lags too far behind to pair them"
        : "no raw frames arrive: start the daemon with <b>thermod run --raw</b> to see them side by side") +
        ")</span>";
    }
  } catch (e) {}
  setTimeout(pollFrame, 100);
}

async function pollKernel() {
  try {
    const r = await showImage("/kernel.png", "kernel");
    if (r.ok) {
      const shape = r.headers.get("X-Shape").split("x"), num = k => Number(r.headers.get(k));
      $("kinfo").innerHTML = "frame " + r.headers.get("X-Frame-Id") + "<br>size " +
        shape.slice(-2).join(" × ") + " px" +
        (shape.length === 4 ? " (grid " + shape[0] + " × " + shape[1] + ")" : "") +
        "<br>extent " + fmt(num("X-Extent-Px"), 2) + " px<br>gyro coverage " +
        fmt(100 * num("X-Coverage"), 1) + " %";
    } else if (r.status === 404) {
      $("kinfo").textContent =
        "no kernel yet (none deblurred, or the daemon runs with publish.kernel = false)";
    }
  } catch (e) {}
  setTimeout(pollKernel, 250);
}

function plot(id, title, unit, t, lines) {
  const c = $(id), g = c.getContext("2d"), W = c.width, H = c.height;
  const L = 48, R = 8, T = 22, B = 20;
  g.clearRect(0, 0, W, H);
  g.font = "12px system-ui, sans-serif";
  g.fillStyle = "#d8dde4"; g.fillText(title + " (" + unit + ")", L, 15);
  let lo = Infinity, hi = -Infinity, n = 0;
  for (const l of lines)
    for (const v of l.v) if (v !== null) { lo = Math.min(lo, v); hi = Math.max(hi, v); n++; }
  if (!n || t.length < 2) { g.fillStyle = "#6c7683"; g.fillText("no data", W / 2 - 20, H / 2); return; }
  lo = Math.min(0, lo); hi = hi > lo ? hi * 1.1 : lo + 1;
  const t0 = t[0], t1 = Math.max(t[t.length - 1], t0 + 1);
  const X = v => L + (v - t0) / (t1 - t0) * (W - L - R), Y = v => H - B - (v - lo) / (hi - lo) * (H - T - B);
  g.strokeStyle = "#2a2f36"; g.fillStyle = "#8a94a1"; g.lineWidth = 1;
  for (let i = 0; i <= 4; i++) {
    const v = lo + (hi - lo) * i / 4, y = Y(v);
    g.beginPath(); g.moveTo(L, y); g.lineTo(W - R, y); g.stroke();
    g.fillText(Math.abs(v) >= 100 ? v.toFixed(0) : v.toPrecision(3), 2, y + 4);
  }
  g.fillText("-" + (t1 - t0).toFixed(0) + " s", L, H - 5); g.fillText("now", W - R - 24, H - 5);
  let lx = L + g.measureText(title + " (" + unit + ")").width + 14;
  for (const l of lines) {
    g.strokeStyle = l.c; g.lineWidth = 2; g.beginPath();
    let pen = false;
    t.forEach((tt, i) => { const v = l.v[i]; if (v === null) { pen = false; return; }
      if (pen) g.lineTo(X(tt), Y(v)); else g.moveTo(X(tt), Y(v)); pen = true; });
    g.stroke();
    g.fillStyle = l.c; g.fillText(l.n, lx, 15); lx += g.measureText(l.n).width + 12;
  }
}

// The calibration in force and the live monitor's estimate ± 1 σ (health.calibration).
function calText(cal) {
  if (!cal || !cal.applied) return "";
  const a = cal.applied, e = cal.estimate, m = cal.monitor || {};
  const ms = v => fmt(1e3 * v, 2), vec = v => "[" + v.map(x => fmt(1e3 * x, 2)).join(", ") + "]";
  let h = "calibration (" + cal.source + "): bias " + vec(a.bias_rad_s) + " mrad/s, offset " +
    ms(a.time_offset_s) + " ms, τ " + ms(a.tau_s) + " ms";
  if (e) {
    h += "<br>estimate: bias " + vec(e.gyro_bias_rad_s) + " ± " + vec(e.gyro_bias_rad_s_sigma) +
      " mrad/s<br>offset " + ms(e.time_offset_s) + " ± " + ms(e.time_offset_s_sigma) + " ms, τ " +
      (e.tau_s === null ? "not estimated" : ms(e.tau_s) + " ± " + ms(e.tau_s_sigma) + " ms") +
      "<br>monitor CPU " + fmt(100 * m.cpu_share, 1) + " %" + (m.settled ? " (settled)" : "") + ", " +
      (m.apply ? "applies" : "reports only") + ", " + (m.changes_applied || 0) + " changes";
  } else if (m.enabled) {
    h += "<br>estimate: none yet";
  }
  return h;
}

// Where the daemon's time goes (health.cpu: % of one core per stage; stage_ms: p50 / p99 per stage).
function cpuText(h) {
  if (!h || !h.cpu || !h.cpu.stages) return "";
  const st = h.cpu.stages, sim = st.sim_payload;
  const parts = Object.keys(st).filter(k => k !== "solves" && k !== "sim_payload")
    .sort((a, b) => st[b] - st[a]).map(k => k + " " + fmt(st[k], 1));
  let out = "<br>CPU (% of one core): solves " + fmt(st.solves, 1) + ", the rest " +
    fmt(h.cpu.overhead_without_sim ?? h.cpu.parent_without_sim, 1) + " (" + parts.join(", ") + ")" +
    (sim === undefined ? "" : ", simulated payload " + fmt(sim, 1));
  const sm = h.stage_ms || {};
  const lat = Object.keys(sm).map(k => k + " " + fmt(sm[k][0], 1) + "/" + fmt(sm[k][1], 1));
  if (lat.length) out += "<br>stage ms p50/p99: " + lat.join(", ") +
    (h.warming_up ? " (warming up: cold-start numbers)" : "");
  return out;
}

async function pollHealth() {
  try {
    const r = await fresh("/health.json");
    const s = await r.json(), S = s.series, t = S.t || [];
    const last = k => (S[k] && S[k].length ? S[k][S[k].length - 1] : null);
    const c = s.counts, deb = c.frame ? 100 * (c.deblurred || 0) / c.frame : null;
    $("bar").innerHTML = "thermod watch &mdash; " + s.endpoint + " &nbsp; frames " + (c.frame || 0) +
      " &nbsp; " + fmt(last("fps"), 1) + " fps &nbsp; deblurred " + fmt(deb, 0) + " % &nbsp; latency p50 " +
      fmt(last("lat_p50_ms"), 1) + " ms &nbsp; raw " + (s.raw ? "yes" : "<span class=warn>none</span>") +
      (s.frame && s.frame.reason ? " &nbsp; <span class=warn>passing through: " + s.frame.reason + "</span>"
                                 : "");
    $("cal").innerHTML = calText(s.health && s.health.calibration) + cpuText(s.health);
    plot("p_fps", "frame rate", "fps", t, [{n: "fps", c: "#e6553a", v: S.fps || []}]);
    plot("p_lat", "latency received − t", "ms", t, [{n: "p50", c: "#4cc38a", v: S.lat_p50_ms || []},
      {n: "p95", c: "#f0b44c", v: S.lat_p95_ms || []}, {n: "p99", c: "#e6553a", v: S.lat_p99_ms || []}]);
    plot("p_drops", "drops", "1/s", t, [{n: "daemon", c: "#e6553a", v: S.drops_per_s || []},
      {n: "lost on wire", c: "#5aa9e6", v: S.lost_per_s || []}]);
    plot("p_gyro", "gyro rate (daemon)", "Hz", t, [{n: "gyro", c: "#5aa9e6", v: S.gyro_hz || []}]);
    plot("p_clock", "clock-fit residual", "µs", t, [{n: "gyro", c: "#5aa9e6", v: S.gyro_residual_us || []},
      {n: "camera", c: "#c678dd", v: S.camera_residual_us || []}]);
  } catch (e) {
    $("bar").innerHTML = "thermod watch &mdash; <span class=warn>lost contact with thermod watch</span>";
  }
  setTimeout(pollHealth, 1000);
}
pollFrame(); pollKernel(); pollHealth();
</script></body></html>
""".replace("FRAME_BOX", _box("frame")).replace("KERNEL_BOX", _box("kernel")) \
   .replace("PLOTS_BOX", _box("plots")).replace("@PW@", str(_PW)).replace("@PH@", str(_PH))
