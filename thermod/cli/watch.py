"""`thermod watch`: subscribe to a running daemon and report what arrives.

Prints, every ``--interval`` seconds and at the end: frame rate (from the frames' own times),
latency percentiles ``published − t`` (daemon-side: waiting for gyro coverage + deblurring) and
``received − t`` (end to end; meaningful on the daemon's host only, because ``t`` is that host's
CLOCK_MONOTONIC), messages lost (seq gaps), the deblurred share, which method deblurred them (the
governor's choice in each frame's header: ``temporal``, ``kf``, ``kf_fast``, ``wiener``,
``wiener_half``, with the kernel grid) and why the other frames were not deblurred. With
``--png DIR`` it writes raw|deblurred side-by-side previews (one percentile stretch for both
halves, so brightness compares) at most every ``--png-interval`` seconds. With
``--http HOST:PORT`` it also serves a live page there (`thermod.client.web`): raw | deblurred,
the current blur kernel and health plots.
"""

from __future__ import annotations

import collections
import logging
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from thermod.client.subscriber import SILENCE_S, Silence, Subscriber, gone_message
from thermod.errors import ThermodError
from thermod.io.display import Agc, side_by_side, to_u8  # noqa: F401 - the previews' mapping
from thermod.io.endpoints import DEFAULT_ENDPOINT
from thermod.io.wire import MAX_PAYLOAD_BYTES

log = logging.getLogger(__name__)


def add_arguments(p) -> None:
    p.add_argument("--endpoint", default=DEFAULT_ENDPOINT, help="publisher address (default %(default)s)")
    p.add_argument("--seconds", type=float, default=None, help="stop after N seconds (default: Ctrl-C)")
    p.add_argument("--interval", type=float, default=1.0, help="seconds between status lines")
    p.add_argument("--timeout", type=float, default=SILENCE_S, help=Silence.OPTION_HELP)
    p.add_argument("--png", metavar="DIR", default=None, help="write raw|deblurred preview PNGs to DIR")
    p.add_argument("--png-interval", type=float, default=1.0, help="seconds between previews")
    p.add_argument("--http", metavar="HOST:PORT", default=None,
                   help="serve a live page there, e.g. 127.0.0.1:8080 (port 0: any free port)")
    p.add_argument("--no-raw", action="store_true", help="do not subscribe to raw frames")
    p.add_argument("--curve-server-key", default=None, help="publisher's public certificate → CURVE")
    p.add_argument("--curve-client-key", default=None, help="this client's *.key_secret certificate")
    p.add_argument("--max-frame-mb", type=float, default=MAX_PAYLOAD_BYTES / 2**20,
                   help="largest frame accepted, MiB; a publisher sending more is disconnected "
                        "(default: a 4096×4096 float32 image)")


class WatchStats:
    """Accumulates what a subscriber saw; `summary()` gives the numbers, `format()` a table.
    Latency percentiles cover the last `window` frames (memory stays bounded when left running)."""

    def __init__(self, window: int = 30000):
        self.frames = 0
        self.deblurred = 0
        self.reasons: collections.Counter = collections.Counter()
        self.methods: collections.Counter = collections.Counter()   # "kf 3×4", "wiener", … (deblurred)
        self.frame_t = [np.inf, -np.inf]
        self.lat_publish: collections.deque = collections.deque(maxlen=window)
        self.lat_receive: collections.deque = collections.deque(maxlen=window)
        self.raw = 0
        self.gyro_samples = 0
        self.gyro_t = [np.inf, -np.inf]
        self.gyro_indices = 0                  # device sample indices the batches span, skipped ones included
        self._gyro_seq_end: int | None = None  # one past the newest batch's last index
        self.gyro_gap_batches = 0
        self.gyro_lost = 0
        self.health: dict | None = None
        self.messages = 0
        self.silent_s: float | None = None     # set when watching stopped: nothing arrived, nobody there
        self.listening: bool | None = None     # after a silence: whether something listened at the endpoint

    def add(self, topic: str, header: dict, array) -> None:
        self.messages += 1
        if topic == "frame":
            self.frames += 1
            self.frame_t = [min(self.frame_t[0], header["t"]), max(self.frame_t[1], header["t"])]
            self.lat_publish.append(header["published"] - header["t"])
            if "received" in header:
                self.lat_receive.append(header["received"] - header["t"])
            if header["deblurred"]:
                self.deblurred += 1
                self.methods[method_label(header)] += 1
            else:
                self.reasons[str(header.get("reason") or "unspecified")] += 1
        elif topic == "raw":
            self.raw += 1
        elif topic == "gyro":
            n = len(array)
            self.gyro_samples += n
            if n:
                self.gyro_t = [min(self.gyro_t[0], float(array["t"][0])), max(self.gyro_t[1], header["t"])]
                if "sample_seq" in header:
                    first, last = int(header["sample_seq"]), self._gyro_seq_end
                    # indices skipped since the last batch were samples lost; indices going back mean a
                    # restarted device (a reload): a new run of indices starts there
                    self.gyro_indices += n if last is None or first < last else first + n - last
                    self._gyro_seq_end = first + n
            self.gyro_gap_batches += bool(header.get("gap_before"))
            self.gyro_lost += int(header.get("n_lost") or 0)
        elif topic == "health":
            self.health = header

    def summary(self, gaps: dict | None = None) -> dict:
        t0, t1 = self.frame_t
        fps = (self.frames - 1) / (t1 - t0) if self.frames > 1 and t1 > t0 else float("nan")
        span = self.gyro_t[1] - self.gyro_t[0]
        # the device's sample rate on the host clock: its sample indices count the samples lost at
        # the device or on the way, so this is the clock mapping's rate, whatever was lost
        k = self.gyro_indices
        device_hz = (k - 1) / span if k > 1 and span > 0 else float("nan")
        return {
            "frames": self.frames,
            "fps": fps,
            "deblurred_share": self.deblurred / self.frames if self.frames else float("nan"),
            "reasons": dict(self.reasons.most_common()),
            "methods": dict(self.methods.most_common()),
            "latency_publish_ms": _percentiles(self.lat_publish),
            "latency_receive_ms": _percentiles(self.lat_receive),
            "raw": self.raw,
            "gyro_hz": (self.gyro_samples - 1) / span if self.gyro_samples > 1 and span > 0 else float("nan"),
            "gyro_device_hz": device_hz,
            "gyro_gap_batches": self.gyro_gap_batches,
            "gyro_samples_lost": self.gyro_lost,
            "lost_messages": dict(gaps or {}),
        }

    def format(self, gaps: dict | None = None) -> str:
        s = self.summary(gaps)
        lp, lr = s["latency_publish_ms"], s["latency_receive_ms"]
        lines = [
            f"frames       {s['frames']:>8d}   {s['fps']:8.2f} fps   "
            f"deblurred {100 * s['deblurred_share']:5.1f} %",
            "latency ms        p50      p95      p99      max",
            "  published−t " + "".join(f"{lp[k]:9.2f}" for k in ("p50", "p95", "p99", "max")),
            "  received−t  " + "".join(f"{lr[k]:9.2f}" for k in ("p50", "p95", "p99", "max")),
            f"raw frames   {s['raw']:>8d}",
            f"gyro         {self.gyro_samples:>8d} samples {s['gyro_hz']:9.1f} Hz (device "
            f"{s['gyro_device_hz']:.1f} Hz)   gap batches {s['gyro_gap_batches']}   samples lost "
            f"{s['gyro_samples_lost']}",
            "lost msgs    " + (", ".join(f"{k} {v}" for k, v in sorted(s["lost_messages"].items()) if v)
                               or "none"),
        ]
        if s["methods"]:
            lines.append("deblurred by: " + ", ".join(f"{k} ×{v}" for k, v in s["methods"].items()))
        if s["reasons"]:
            lines.append("not deblurred: " + ", ".join(f"{k} ×{v}" for k, v in s["reasons"].items()))
        if self.health:
            h = self.health
            g = h.get("governor") or {}
            if g.get("method"):
                nan = float("nan")
                lines.append(f"governor     {g['method']} (ladder {' > '.join(g.get('ladder', []))}), budget "
                             f"{g.get('budget_ms', nan):.1f} ms (×{g.get('latency_scale', 1.0):.2f} "
                             f"for a p99 of {g.get('latency_goal_ms', nan):.0f} ms)")
                lines.append(f"             load ×{g.get('load', nan):.2f}, down {g.get('degrades', 0)} up "
                             f"{g.get('climbs', 0)}, {g.get('late', 0)} late frames solved cheaper")
            lines += cpu_lines(h)
            lines += motion_lines(h)
            lines.append(f"daemon rates {_compact(h.get('rates'))}")
            lines.append(f"daemon drops {_compact({k: v for k, v in (h.get('drops') or {}).items() if v})}")
            lines.append(f"devices      {_devices(h.get('devices'))}")
            lines += calibration_lines(h.get("calibration"))
        return "\n".join(lines)

    def status_line(self, gaps: dict | None = None) -> str:
        if self.frames == 0:
            if self.messages:
                return f"no frames yet ({self.messages} other messages)"
            return "nothing received yet" + (" (the endpoint is bound: daemon starting?)" if self.listening
                                              else "")
        s = self.summary(gaps)
        lp = s["latency_publish_ms"]["p50"]
        lr = s["latency_receive_ms"]["p50"]
        lost = sum(s["lost_messages"].values())
        top = max(self.methods, key=self.methods.get) if self.methods else "-"
        return (f"{s['frames']} frames {s['fps']:.1f} fps | deblurred {100 * s['deblurred_share']:.0f} % "
                f"({top}) | "
                f"latency p50 {lp:.1f}/{lr:.1f} ms | lost {lost} | gyro {s['gyro_hz']:.0f} Hz")


def cpu_lines(h: dict) -> list[str]:
    """Where the daemon's time goes, from a health message: CPU per stage (% of one core; the solver
    children, the rest, and the simulated payload apart) and each pipeline stage's p50 / p99 (ms)."""
    cpu = h.get("cpu") or {}
    st = cpu.get("stages") or {}
    out = []
    if st:
        rest = sorted(((k, v) for k, v in st.items() if k not in ("solves", "sim_payload")),
                      key=lambda kv: -kv[1])
        out.append(f"cpu % core   solves {st.get('solves', 0.0):.1f}, the rest "
                   f"{cpu.get('overhead_without_sim', cpu.get('parent_without_sim', 0.0)):.1f} ("
                   + ", ".join(f"{k} {v:.1f}" for k, v in rest) + ")"
                   + (f", simulated payload {st['sim_payload']:.1f}" if "sim_payload" in st else ""))
    stages = (h.get("pipeline") or {}).get("stage_ms") or {}
    if stages:
        warm = " — warming up: cold-start numbers" if h.get("warming_up") else ""
        out.append("stage ms     " + ", ".join(f"{k} {v[0]:.1f}/{v[1]:.1f}" for k, v in stages.items())
                   + " (p50/p99)" + warm)
    return out


def motion_lines(h: dict) -> list[str]:
    """Where the kernels' motion comes from, when it is not a gyro: the video source's registrations."""
    if h.get("motion_source") != "video":
        return []
    st = ((h.get("devices") or {}).get("gyro") or {}).get("stats") or {}
    sigma = st.get("sigma_rad_s")
    return [f"motion       from the video (no gyro): {st.get('measured', 0)} of {st.get('frames', 0)} frame "
            f"pairs registered ({st.get('dense', 0)} by every pixel), {st.get('bridged', 0)} bridged, "
            f"{st.get('untracked', 0)} untracked, {st.get('cut', 0)} cuts, {st.get('duplicate', 0)} repeats, "
            f"{st.get('gap', 0)} time gaps"
            + (f", a static overlay on {100 * st['overlay_fraction']:.1f} % left out"
               if isinstance(st.get("overlay_fraction"), (int, float)) and st["overlay_fraction"] > 0 else "")
            + (f", last σ {math.degrees(sigma):.2f} °/s" if isinstance(sigma, (int, float))
               and math.isfinite(sigma) else "")]


def calibration_lines(cal) -> list[str]:
    """The calibration in force and the live monitor's estimate (± 1 σ) from a health message's
    ``calibration``; nothing from a daemon that reports neither. A value the daemon could not give
    (null: not estimated, an unbounded σ) reads "?"."""
    if not isinstance(cal, dict) or not isinstance(cal.get("applied"), dict):
        return []
    a = cal["applied"]
    out = [f"calibration  in force ({cal.get('source', '?')}): gyro bias "
           f"{_vec(a.get('bias_rad_s'))} mrad/s, time offset {_ms(a.get('time_offset_s'))} ms, "
           f"tau {_ms(a.get('tau_s'))} ms"]
    e = cal.get("estimate")
    mon = cal.get("monitor") or {}
    if e:
        tau = ("not estimated" if e.get("tau_s") is None
               else f"{_ms(e['tau_s'])} ± {_ms(e.get('tau_s_sigma'))} ms")
        out.append(f"  estimate   gyro bias {_vec(e.get('gyro_bias_rad_s'))} ± "
                   f"{_vec(e.get('gyro_bias_rad_s_sigma'))} mrad/s, time offset "
                   f"{_ms(e.get('time_offset_s'))} ± {_ms(e.get('time_offset_s_sigma'))} ms, tau {tau}")
        if e.get("ambiguous"):
            out.append("  AMBIGUOUS  bias and offset confounded in this window (correlation "
                       f"{e.get('bias_offset_correlation')}): reported, never applied")
        out.append(f"  monitor    {e.get('n_pairs', 0)} frame pairs, residual "
                   f"{_num(e.get('residual_px'), 1, 3)} px (in force "
                   f"{_num(e.get('residual_applied_px'), 1, 3)}), CPU "
                   f"{_num(mon.get('cpu_share'), 100, 1)} % of a core"
                   f"{' (settled: watching for drift)' if mon.get('settled') else ''}, "
                   f"{'applies' if mon.get('apply') else 'reports only'}, "
                   f"{mon.get('changes_applied', 0)} changes applied")
    elif mon.get("enabled"):
        out.append("  estimate   none yet (the monitor needs a few seconds of motion)")
    return out


def _num(x, scale: float, digits: int) -> str:
    return f"{scale * x:.{digits}f}" if isinstance(x, (int, float)) and not isinstance(x, bool) else "?"


def _ms(x) -> str:
    return _num(x, 1e3, 2)


def _vec(v) -> str:
    """A rad/s vector in mrad/s."""
    if not isinstance(v, (list, tuple)):
        return "?"
    return "[" + ", ".join(_num(x, 1e3, 2) for x in v) + "]"


def method_label(header: dict) -> str:
    """How a deblurred frame was deblurred, from its header: "kf", "kf 3×4", "wiener", …; "?" from a
    daemon older than the governor (no ``method`` key)."""
    m = header.get("method") or "?"
    g = header.get("grid")
    return f"{m} {g[0]}×{g[1]}" if isinstance(g, list) and len(g) == 2 and g != [1, 1] else m


def _percentiles(values) -> dict:
    if not values:
        return dict.fromkeys(("p50", "p95", "p99", "max"), float("nan"))
    ms = 1e3 * np.asarray(values, dtype=np.float64)
    p50, p95, p99 = np.percentile(ms, [50, 95, 99])
    return {"p50": float(p50), "p95": float(p95), "p99": float(p99), "max": float(ms.max())}


def _devices(d) -> str:
    """``gyro running, camera reconnecting (3 errors, 1 restart: timeout)``: each device's state, and
    its trouble only when it had some."""
    if not isinstance(d, dict) or not d:
        return "-"
    out = []
    for name, st in d.items():
        if not isinstance(st, dict):
            out.append(f"{name} {st}")
            continue
        trouble = [f"{n} {k}{'s' if n != 1 else ''}" for k, n in (("error", st.get("errors") or 0),
                                                                 ("restart", st.get("restarts") or 0)) if n]
        why = f": {st['last_error']}" if st.get("last_error") else ""
        detail = f" ({', '.join(trouble)}{why})" if trouble or why else ""
        out.append(f"{name} {st.get('state', '?')}{detail}")
    return ", ".join(out)


def _compact(d) -> str:
    if not isinstance(d, dict) or not d:
        return "-"
    return ",".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in d.items())


# ------------------------------------------------------------------------------------ previews
class PreviewWriter:
    """Pairs frames with their raw counterpart by frame_id and writes a PNG every `interval` s."""

    def __init__(self, directory, interval: float = 1.0, keep: int = 64):
        import cv2  # only needed with --png

        self._cv2 = cv2
        self.dir = Path(directory)
        try:
            self.dir.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise ThermodError(f"--png {directory}: cannot create directory ({e})") from None
        self.interval, self.keep = interval, keep
        self._raw: collections.OrderedDict = collections.OrderedDict()
        self._pending: collections.OrderedDict = collections.OrderedDict()
        self._last_write = -np.inf
        self._last_raw_seen = -np.inf
        self.written: list[Path] = []

    def add(self, topic: str, header: dict, array: np.ndarray) -> None:
        now = time.monotonic()
        fid = header.get("frame_id")
        if topic == "raw":
            self._raw[fid] = array
            self._last_raw_seen = now
            _trim(self._raw, self.keep)
            if fid in self._pending:  # the frame came first: pair it now
                self._write(self._pending.pop(fid), array, fid)
        elif topic == "frame" and now - self._last_write >= self.interval:
            raw = self._raw.get(fid)
            if raw is None and now - self._last_raw_seen < 2.0:
                self._pending[fid] = array  # raw is flowing but this one is not here (yet)
                _trim(self._pending, 4)
                return
            self._write(array, raw, fid)

    def _write(self, frame, raw, fid) -> None:
        self._last_write = time.monotonic()
        self._pending.clear()
        img = side_by_side(raw, frame, gap=4)
        path = self.dir / f"watch_{int(fid):08d}.png"
        tmp = self.dir / ".latest.png.part.png"
        if not self._cv2.imwrite(str(path), img) or not self._cv2.imwrite(str(tmp), img):
            raise ThermodError(f"--png {self.dir}: could not write {path.name}")
        os.replace(tmp, self.dir / "latest.png")
        self.written.append(path)


def _trim(d: collections.OrderedDict, keep: int) -> None:
    while len(d) > keep:
        d.popitem(last=False)


# ----------------------------------------------------------------------------------------- run
def watch(sub: Subscriber, seconds: float | None, *, interval: float = 1.0,
          previews: PreviewWriter | None = None, view=None, out=None,
          timeout: float = SILENCE_S) -> WatchStats:
    """Receive until `seconds` pass (None: until Ctrl-C), printing a status line every `interval`;
    every message also goes to `view` (a `thermod.client.web.LiveView`), sampled once a second.
    After `timeout` s (0: no limit) with nothing received it checks the endpoint (`Silence`): if
    nothing listens there it stops early, with ``stats.silent_s`` set; a bound but silent publisher
    (a daemon still starting up) is waited for."""
    out = sys.stdout if out is None else out
    stats = WatchStats()
    silence = Silence(sub.endpoint, timeout)
    t_end = None if seconds is None else time.monotonic() + seconds
    next_line = time.monotonic() + interval
    next_sample = time.monotonic() + 1.0 if view is not None else np.inf
    try:
        while t_end is None or time.monotonic() < t_end:
            wait = min(next_line, next_sample, t_end or np.inf, silence.due) - time.monotonic()
            msg = sub.recv(max(0.0, wait))
            gone = msg is None and silence.gone()
            stats.listening, stats.silent_s = silence.listening, silence.silent_s
            if gone:
                break
            if msg is not None:
                silence.heard()
                stats.add(*msg)
                if previews is not None and msg[0] in ("frame", "raw"):
                    previews.add(*msg)
                if view is not None:
                    view.add(*msg)
            now = time.monotonic()
            if now >= next_sample:
                view.sample(sub.gaps, now)
                next_sample = max(next_sample + 1.0, now + 0.5)
            if now >= next_line:
                print(stats.status_line(sub.gaps), file=out, flush=True)
                next_line += interval
    except KeyboardInterrupt:
        pass
    return stats


def _check_times(args) -> None:
    """The options in seconds and MiB: finite, positive (--timeout: 0 or more)."""
    for name, v, zero_ok in (("--seconds", args.seconds, False), ("--interval", args.interval, False),
                             ("--png-interval", args.png_interval, False), ("--timeout", args.timeout, True),
                             ("--max-frame-mb", args.max_frame_mb, False)):
        if v is not None and not (math.isfinite(v) and (v >= 0 if zero_ok else v > 0)):
            raise ThermodError(f"{name} {v}: expected a finite number {'≥ 0' if zero_ok else '> 0'}")


def run(args) -> int:
    _check_times(args)
    topics = ("frame", "gyro", "health") if args.no_raw else ("frame", "raw", "gyro", "health")
    previews = PreviewWriter(args.png, args.png_interval) if args.png else None
    view = server = None
    if args.http:
        from thermod.client.web import LiveView, WebServer

        topics += ("kernel",)
        view = LiveView(args.endpoint)
        server = WebServer(view, args.http).start()
        print(f"live view on {server.url}", flush=True)
    try:
        with Subscriber(args.endpoint, topics, curve_server_key=args.curve_server_key,
                        curve_client_key_file=args.curve_client_key,
                        max_message_bytes=int(args.max_frame_mb * 2**20)) as sub:
            stats = watch(sub, args.seconds, interval=args.interval, previews=previews, view=view,
                          timeout=args.timeout)
            if stats.messages:
                print(stats.format(sub.gaps), flush=True)
            if sub.errors:
                print(f"rejected malformed messages: {dict(sub.errors)}", flush=True)
    finally:
        if server is not None:
            server.stop()
    if previews is not None and previews.written:
        print(f"previews: {len(previews.written)} PNGs in {previews.dir} (latest.png = newest)", flush=True)
    if stats.silent_s is not None:
        print(gone_message("watch", args.endpoint, stats.silent_s, received=bool(stats.messages)),
              file=sys.stderr)
        return 1
    if stats.frames == 0:
        print(f"thermod watch: no frames from {args.endpoint}; is `thermod run` up and publishing there?",
              file=sys.stderr)
        return 1
    return 0
