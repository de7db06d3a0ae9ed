"""The supervisor behind `thermod run`. Builds the sources from the configuration, runs one driver thread
per device (``source.poll(timeout)`` in a loop → ring buffer), the pipeline (scheduler + deconvolution
workers), the publisher, and a 1 Hz health report; handles signals, sd_notify and device faults.

Threads and what they own:

- ``thermod-gyro`` / ``thermod-camera``: the only threads with real-time priority (SCHED_FIFO, when
  ``realtime_priority`` > 0 and permitted). They never block on anything but their device.
- pipeline threads (`thermod.runtime.pipeline`), the publisher's socket thread (`thermod.runtime.publish`).
- the main thread: signals, health, watchdog, SIGHUP reload.

Faults: a gyro I/O error (NACK, unplug) is retried with exponential back-off; meanwhile the
pipeline is told the gyro is offline and frames pass through flagged ``gyro_offline``. A camera
error or stall (no frame for ``max(1 s, 10 frame periods)``) restarts the camera source with
back-off. Every state change is logged once and visible in the health message.

Signals: SIGTERM/SIGINT → clean shutdown (< 2 s), exit 0. SIGHUP → re-read the configuration file
and apply its calibration and deblur settings to the running pipeline (no frame dropped);
source/publish changes need a restart and are reported as such.
"""

from __future__ import annotations

import collections
import dataclasses
import ipaddress
import logging
import math
import os
import threading
import time
from dataclasses import dataclass, field

from thermod.errors import ConfigError, DeviceError
from thermod.runtime import config as configmod
from thermod.runtime.pipeline import FrameOut, Pipeline
from thermod.runtime.rings import FrameRing, GyroRing

log = logging.getLogger("thermod.runtime.daemon")

STALL_MIN_S = 1.0


# ------------------------------------------------------------------------------------ sources
def build_gyro(cfg: configmod.Config, payload=None):
    """The configured gyro source (driver modules are imported only here)."""
    try:
        return _build_gyro(cfg, payload)
    except ImportError as e:
        raise ConfigError(f"{cfg.path}: sources.gyro.kind: the {cfg.gyro.kind!r} driver is not available "
                          f"({e})") from None


def build_camera(cfg: configmod.Config, payload=None):
    """The configured camera source."""
    try:
        return _build_camera(cfg, payload)
    except ImportError as e:
        raise ConfigError(f"{cfg.path}: sources.camera.kind: the {cfg.camera.kind!r} driver is not available "
                          f"({e})") from None


def _build_gyro(cfg: configmod.Config, payload=None):
    g = cfg.gyro
    o = dict(g.options)
    rate = float(cfg.calibration.rate_hz)
    if g.kind == "sim":
        return payload.gyro_source()
    if g.kind == "replay":
        from thermod.drivers import replay
        return replay.ReplayGyro(g.device, loop=o["loop"], speed=o["speed"])
    if g.kind in ("icm42688_spi", "icm42688_i2c", "mpu6000", "bmi088"):
        from thermod.drivers.bus import I2CBus, SPIBus
        if g.kind in ("icm42688_spi", "mpu6000") or (g.kind == "bmi088" and o["bus"] == "spi"):
            bus = SPIBus(_spi_numbers(g.device), max_speed_hz=o["speed_hz"])
        else:
            bus = I2CBus(_i2c_number(g.device), o["address"])
        kw = dict(full_scale_dps=float(o["full_scale_dps"]), rate_hz=float(o["odr_hz"]))
        if g.kind.startswith("icm42688"):
            from thermod.drivers.icm42688 import ICM42688
            return ICM42688(bus, **kw)
        if g.kind == "mpu6000":
            from thermod.drivers.mpu6000 import MPU6000
            return MPU6000(bus, **kw)
        from thermod.drivers.bmi088 import BMI088Gyro
        return BMI088Gyro(bus, **kw)
    if g.kind == "iio":
        from thermod.drivers.iio import IIOGyro
        return IIOGyro(g.device, rate_hz=o["rate_hz"] or rate, buffer_length=o["buffer_length"])
    if g.kind == "serial":
        from thermod.drivers.serial_imu import SerialIMU
        return SerialIMU(g.device, baud=o["baud"], rate_hz=rate, low_latency=o["low_latency"])
    raise ConfigError(f"{cfg.path}: sources.gyro.kind: no driver for {g.kind!r}")


def _build_camera(cfg: configmod.Config, payload=None):
    c = cfg.camera
    o = dict(c.options)
    if c.kind == "sim":
        return payload.camera_source()
    if c.kind == "replay":
        from thermod.drivers import replay
        return replay.ReplayCamera(c.device, loop=o["loop"], speed=o["speed"])
    if c.kind == "aravis":
        from thermod.drivers.aravis_camera import AravisCamera
        try:
            ipaddress.ip_address(c.device)
            where = {"address": c.device}
        except ValueError:
            where = {"device_id": c.device}
        return AravisCamera(**where, width=cfg.calibration.width, height=cfg.calibration.height,
                            frame_rate_hz=o["frame_rate_hz"] or None, pixel_formats=(o["pixel_format"],),
                            packet_size=o["packet_size"] or None, stall_timeout_s=o["stream_timeout_s"])
    if c.kind == "v4l2":
        from thermod.drivers.v4l2_camera import V4L2Camera
        return V4L2Camera(c.device, width=o["width"], height=o["height"], fourcc=o["fourcc"],
                          frame_rate_hz=o["frame_rate_hz"] or None,
                          telemetry_rows=(o["telemetry_top"], o["telemetry_bottom"]),
                          timestamp_clock=o["timestamp_clock"], timestamp_offset_s=o["timestamp_offset_s"])
    raise ConfigError(f"{cfg.path}: sources.camera.kind: no driver for {c.kind!r}")


def _spi_numbers(dev: str) -> tuple[int, int]:
    base = os.path.basename(dev)          # /dev/spidevB.C
    try:
        b, c = base.removeprefix("spidev").split(".")
        return int(b), int(c)
    except ValueError:
        raise ConfigError(f"sources.gyro.device: expected /dev/spidevB.C, got {dev!r}") from None


def _i2c_number(dev: str) -> int:
    try:
        return int(os.path.basename(dev).removeprefix("i2c-"))
    except ValueError:
        raise ConfigError(f"sources.gyro.device: expected /dev/i2c-N, got {dev!r}") from None


# ------------------------------------------------------------------------------------ driver threads
@dataclass
class DeviceState:
    """What the health message says about one device."""

    name: str
    state: str = "starting"           # starting | running | error | stalled | stopped
    last_error: str = ""
    errors: int = 0
    restarts: int = 0
    last_data: float = math.nan       # host monotonic of the newest item
    items: int = 0
    heartbeat: float = field(default_factory=time.monotonic)
    realtime: bool = False

    def as_dict(self, now: float) -> dict:
        return {"state": self.state, "last_error": self.last_error, "errors": self.errors,
                "restarts": self.restarts, "items": self.items, "realtime": self.realtime,
                "age_s": None if math.isnan(self.last_data) else round(now - self.last_data, 4)}


def _set_realtime(prio: int, what: str) -> bool:
    if prio <= 0:
        return False
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))   # 0 = this thread (Linux)
        log.info("%s thread: SCHED_FIFO priority %d", what, prio)
        return True
    except (PermissionError, OSError, AttributeError) as e:
        log.info("%s thread: real-time priority %d not permitted (%s); running SCHED_OTHER "
                 "(grant LimitRTPRIO in the unit)", what, prio, getattr(e, "strerror", None) or e)
        return False


class _DriverThread(threading.Thread):
    """Calls ``source.poll`` in a loop, hands results to ``sink``, retries failures with back-off."""

    def __init__(self, kind: str, source, sink, state: DeviceState, stop: threading.Event, *,
                 poll_timeout: float, priority: int, retry_max_s: float, stall_s: float | None = None,
                 on_down=None, on_up=None):
        super().__init__(name=f"thermod-{kind}", daemon=True)
        self.kind, self.source, self.sink, self.st, self.stop_ev = kind, source, sink, state, stop
        self.poll_timeout, self.priority = poll_timeout, priority
        self.retry_max_s, self.stall_s = retry_max_s, stall_s
        self.on_down, self.on_up = on_down, on_up
        self.started_source = False
        self._sink_errors: set[str] = set()
        self.sink_drops = 0

    def _down(self, why: str, state: str = "error") -> None:
        self.st.errors += 1
        self.st.last_error = why
        if self.st.state not in ("error", "stalled"):
            log.warning("%s %s: %s", self.kind, state, why)
            if self.on_down:
                self.on_down()
        self.st.state = state

    def _up(self) -> None:
        if self.st.state != "running":
            if self.st.state in ("error", "stalled"):
                log.warning("%s %s recovered", self.kind, self.st.name)
            self.st.state = "running"
            if self.on_up:
                self.on_up()

    def _sleep(self, s: float) -> None:
        end = time.monotonic() + s
        while not self.stop_ev.is_set() and time.monotonic() < end:
            self.st.heartbeat = time.monotonic()
            self.stop_ev.wait(min(0.1, end - time.monotonic()))

    def _restart_source(self) -> None:
        self.st.restarts += 1
        try:
            self.source.stop()
        except Exception as e:   # noqa: BLE001 - a dead device may fail to stop; we reopen anyway
            log.debug("%s stop during restart failed: %s", self.kind, e)
        self.source.start()

    def run(self) -> None:
        self.st.realtime = _set_realtime(self.priority, self.kind)
        backoff = 0.05
        consecutive = 0
        while not self.stop_ev.is_set():
            self.st.heartbeat = time.monotonic()
            try:
                if not self.started_source:
                    self.source.start()
                    self.started_source = True
                elif consecutive >= 3:
                    self._restart_source()
                item = self.source.poll(self.poll_timeout)
            except (DeviceError, OSError) as e:
                consecutive += 1
                self._down(str(e))
                self._sleep(backoff)
                backoff = min(self.retry_max_s, backoff * 2)
                continue
            except Exception as e:          # a driver bug: log with traceback, keep supervising
                consecutive += 1
                log.exception("%s source raised unexpectedly", self.kind)
                self._down(f"{type(e).__name__}: {e}")
                self._sleep(backoff)
                backoff = min(self.retry_max_s, backoff * 2)
                continue
            now = time.monotonic()
            if item is None:
                if self.stall_s and self.st.state == "running" and now - self.st.last_data > self.stall_s:
                    self._down(f"no data for {now - self.st.last_data:.2f} s", "stalled")
                    consecutive = 3          # reconnect on the next turn
                elif self.stall_s and self.st.state == "stalled":
                    self._sleep(backoff)
                    backoff = min(self.retry_max_s, backoff * 2)
                continue
            consecutive, backoff = 0, 0.05
            self.st.last_data = now
            self._up()
            try:
                self.sink(item)
            except Exception as e:      # e.g. a frame of the wrong size: counted, logged once per kind
                self.st.errors += 1
                self.st.last_error = msg = f"{type(e).__name__}: {e}"
                if msg not in self._sink_errors:
                    self._sink_errors.add(msg)
                    log.error("%s: item dropped: %s", self.kind, msg)
                self.sink_drops += 1
        if self.started_source:
            try:
                self.source.stop()
            except Exception as e:  # noqa: BLE001
                log.debug("%s stop failed: %s", self.kind, e)
        self.st.state = "stopped"


# ------------------------------------------------------------------------------------ the daemon
class Daemon:
    """All parts wired together. `start`, then `serve` (blocks) or `tick` from your own loop, `stop`.

    ``gyro``/``camera``/``publisher`` may be passed in (tests inject sources with faults); by default
    they are built from the configuration.
    """

    def __init__(self, cfg: configmod.Config, *, gyro=None, camera=None, publisher=None, notifier=None,
                 overrides: dict | None = None):
        self.cfg = cfg
        self.overrides = dict(overrides or {})
        self.payload = None
        if cfg.uses_sim and (gyro is None or camera is None):
            from thermod.sim.payload import SimPayload
            self.payload = SimPayload(cfg.sim, cfg.calibration)
        self.gyro = gyro if gyro is not None else build_gyro(cfg, self.payload)
        self.camera = camera if camera is not None else build_camera(cfg, self.payload)
        if publisher is None:
            from thermod.runtime.publish import Publisher
            p = cfg.publish
            publisher = Publisher(p.endpoint, hwm=p.hwm, curve_secret_key_file=p.curve_secret_key,
                                  authorized_keys_dir=p.curve_authorized_keys,
                                  allow_insecure_remote=p.allow_insecure_remote,
                                  max_queue_bytes=int(p.max_queue_mb * 2**20),
                                  max_message_bytes=cfg.calibration.width * cfg.calibration.height * 4)
        self.publisher = publisher
        if notifier is None:
            from thermod.runtime.sdnotify import Notifier
            notifier = Notifier()
        self.notifier = notifier
        c = cfg.calibration
        # a step of more than 4 sample periods without a device-counter gap is a hole in time too
        self.gyro_ring = GyroRing(int(cfg.pipeline.gyro_ring_s * c.rate_hz * 1.1) + 64,
                                  max_step_s=4.0 / c.rate_hz)
        self.frame_ring = FrameRing(cfg.pipeline.frame_ring, (c.height, c.width))
        self.pipeline = Pipeline(self.gyro_ring, self.frame_ring, c, cfg.deblur, cfg.pipeline, self._emit)
        self._stop = threading.Event()
        self.gyro_state = DeviceState(getattr(self.gyro, "name", "gyro"))
        self.camera_state = DeviceState(getattr(self.camera, "name", "camera"))
        self._threads: list[_DriverThread] = []
        self.counters = collections.Counter()
        self._ready = False
        self._last_health = 0.0
        self._last_ping = 0.0
        self._ping_every = min(1.0, self.notifier.watchdog_interval() or 1.0)
        self._prev: dict = {}
        self._rates: dict = {"gyro_hz": 0.0, "frames_in_hz": 0.0, "frames_out_hz": 0.0, "deblurred_hz": 0.0}
        self._health_seq = 0
        self.last_health: dict = {}

    # ---------------------------------------------------------------- sinks (driver threads)
    def _on_gyro(self, b) -> None:
        self.gyro_ring.write(b.t, b.rate, b.seq, gap_before=b.gap_before)
        self.gyro_state.items += len(b.t)
        if b.gap_before:
            self.counters["gyro_gaps"] += 1
            self.counters["gyro_lost"] += int(b.n_lost)
        if self.cfg.publish.gyro:
            self.publisher.publish_gyro(b.t, b.rate, seq=b.seq, gap_before=b.gap_before, n_lost=b.n_lost)

    def _on_frame(self, f) -> None:
        try:
            self.frame_ring.write(f.image, f.t, f.frame_id, f.arrival, f.gap_before)
        except ValueError as e:
            self.counters["frames_wrong_shape"] += 1
            raise DeviceError(f"{self.camera_state.name}: {e} (calibration.width/height)") from None
        self.camera_state.items += 1
        if f.gap_before:
            self.counters["camera_frames_lost"] += int(f.gap_before)
        if self.cfg.publish.raw:
            self.publisher.publish_raw(f.image, f.t, frame_id=f.frame_id, gap_before=int(f.gap_before))

    def _emit(self, o: FrameOut) -> None:
        self.publisher.publish_frame(o.image, o.t, frame_id=o.frame_id, deblurred=o.deblurred,
                                     kernel_size=o.kernel_size, kernel_extent_px=o.kernel_extent_px,
                                     coverage=o.coverage, reason=o.reason, copy=False, n_samples=o.n_samples,
                                     latency_s=o.latency_s, camera_gap_before=o.camera_gap_before)

    # ---------------------------------------------------------------- lifecycle
    def start(self) -> None:
        cfg = self.cfg
        self.publisher.start()  # first: a taken endpoint fails here, before seconds of payload preparation
        log.info("publishing on %s", getattr(self.publisher, "endpoint", cfg.publish.endpoint))
        if self.payload is not None:
            if not self.payload.cached():
                log.warning("simulated payload: first start, pre-rendering %.0f s of frames (cached in %s); "
                            "this takes a while once", cfg.sim.loop_s, self.payload.cache_path)
            self.payload.prepare()
        dt = self.pipeline.warmup()
        log.info("renderer and %d deconvolution workers ready (%.2f s)", self.pipeline.n_workers, dt)
        if self.payload is not None:
            self.payload.start()
        self.pipeline.start(self.frame_ring.head)
        frame_period = 1.0 / cfg.calibration.frame_rate_hz
        self._threads = [
            _DriverThread("gyro", self.gyro, self._on_gyro, self.gyro_state, self._stop,
                          poll_timeout=cfg.gyro.poll_timeout_s, priority=cfg.gyro.realtime_priority,
                          retry_max_s=cfg.gyro.retry_max_s, stall_s=0.5,
                          on_down=self._gyro_down, on_up=self._gyro_up),
            _DriverThread("camera", self.camera, self._on_frame, self.camera_state, self._stop,
                          poll_timeout=cfg.camera.poll_timeout_s, priority=cfg.camera.realtime_priority,
                          retry_max_s=cfg.camera.retry_max_s, stall_s=max(STALL_MIN_S, 10 * frame_period)),
        ]
        for th in self._threads:
            th.start()

    def _gyro_down(self) -> None:
        self.pipeline.gyro_online = False
        self.counters["gyro_outages"] += 1

    def _gyro_up(self) -> None:
        self.pipeline.gyro_online = True

    def stop(self) -> None:
        self._stop.set()
        t0 = time.monotonic()
        for th in self._threads:
            th.join(max(0.05, 0.8 - (time.monotonic() - t0)))
        self.pipeline.stop(timeout=0.6)
        if self.payload is not None:
            self.payload.stop()
        self.notifier.stopping("stopping")
        try:
            self.publisher.stop()
        finally:
            self.notifier.close()
        log.info("stopped after %.2f s", time.monotonic() - t0)

    def reload(self) -> None:
        """SIGHUP: re-read the configuration; apply calibration and deblur settings live."""
        self.notifier.reloading()
        try:
            new = configmod.load(None if self.cfg.path.startswith("<") else self.cfg.path, self.overrides)
        except ConfigError as e:
            log.error("reload failed, keeping the running configuration: %s", e)
            self.counters["reload_errors"] += 1
            return
        restart_needed = [k for k in ("gyro", "camera", "publish", "pipeline", "sim") if
                          getattr(new, k) != getattr(self.cfg, k)]
        if restart_needed:
            log.warning("reload: changes to %s need a restart; applied calibration and deblur only",
                        ", ".join(restart_needed))
        self.pipeline.update(calib=new.calibration, deblur=new.deblur)
        self.cfg = dataclasses.replace(self.cfg, calibration=new.calibration, deblur=new.deblur)
        self.counters["reloads"] += 1
        log.info("reloaded calibration and deblur settings from %s", new.path)
        self.notifier.ready(self._status_line())

    def serve(self, stop: threading.Event, reload_req: threading.Event | None = None, *,
              seconds: float | None = None) -> None:
        """Main loop: health, watchdog, reloads, until `stop` is set (or `seconds` pass)."""
        end = math.inf if seconds is None else time.monotonic() + seconds
        while not stop.is_set() and time.monotonic() < end:
            stop.wait(0.05)
            if reload_req is not None and reload_req.is_set():
                reload_req.clear()
                self.reload()
            self.tick()

    # ---------------------------------------------------------------- health / watchdog
    def critical_alive(self) -> dict[str, bool]:
        now = time.monotonic()
        w = self.cfg.pipeline.watchdog_s
        out = {th.kind: th.is_alive() and now - th.st.heartbeat < w for th in self._threads}
        alive = self.pipeline.alive()
        for name, ok in alive.items():
            hb = self.pipeline.heartbeat.get(name, 0.0)
            out[name] = ok and now - hb < w
        out["publisher"] = bool(getattr(self.publisher, "running", True))
        return out

    def tick(self) -> None:
        now = time.monotonic()
        self.pipeline.supervise()
        if not self._ready and self.gyro_state.items > 0 and self.camera_state.items > 0:
            self._ready = True
            log.info("ready: frames and gyro samples flowing")
            self.notifier.ready(self._status_line())
        # WATCHDOG=1 at half systemd's timeout (≤ 1 s), and only while every critical thread checks in
        if self._ready and now - self._last_ping >= self._ping_every and all(self.critical_alive().values()):
            self._last_ping = now
            self.notifier.watchdog()
        if now - self._last_health >= self.cfg.publish.health_period_s:
            self.publish_health(now)

    def _status_line(self) -> str:
        h = self.last_health.get("rates", {})
        return (f"gyro {h.get('gyro_hz', 0):.0f} Hz, frames {h.get('frames_in_hz', 0):.1f} fps, "
                f"deblurred {h.get('deblurred_hz', 0):.1f} fps, gyro {self.gyro_state.state}, "
                f"camera {self.camera_state.state}")

    def health(self, now: float | None = None, *, update_rates: bool = False) -> dict:
        now = time.monotonic() if now is None else now
        ps = self.pipeline.stats()
        pc = ps["counters"]
        totals = {"gyro_samples": self.gyro_state.items, "frames_in": self.camera_state.items,
                  "frames_out": pc.get("frames_out", 0), "deblurred": pc.get("deblurred", 0)}
        if update_rates:    # rates are per health period; other callers see the last period's
            dt = now - self._prev["_t"] if self._prev else None
            self._rates = {name: round((totals[k] - self._prev.get(k, 0)) / dt, 3) if dt else 0.0
                           for k, name in (("gyro_samples", "gyro_hz"), ("frames_in", "frames_in_hz"),
                                           ("frames_out", "frames_out_hz"), ("deblurred", "deblurred_hz"))}
            self._prev = {**totals, "_t": now}
        rates = dict(self._rates)
        drop_keys = ("passthrough_", "jobs_dropped", "frames_overrun", "worker_errors", "camera_frames_lost")
        drops = {k: v for k, v in pc.items() if k.startswith(drop_keys)}
        for th in self._threads:
            drops[f"{th.kind}_items_rejected"] = th.sink_drops
        drops.update(gyro_gaps=self.counters["gyro_gaps"], gyro_lost=self.counters["gyro_lost"],
                     gyro_ring_clock_jumps=self.gyro_ring.clock_jumps,
                     gyro_ring_time_holes=self.gyro_ring.time_holes,
                     camera_frames_lost=self.counters["camera_frames_lost"])
        pub = self.publisher.stats() if hasattr(self.publisher, "stats") else {}
        drops["publish_queue_dropped"] = pub.get("queue_dropped", 0)
        drops["publish_budget_dropped"] = pub.get("budget_dropped_total", 0)
        devices = {"gyro": {**self.gyro_state.as_dict(now), "stats": _safe_stats(self.gyro)},
                   "camera": {**self.camera_state.as_dict(now), "stats": _safe_stats(self.camera)}}
        clocks = {}
        for k, src in (("gyro", self.gyro), ("camera", self.camera)):
            clk = getattr(src, "clock", None)
            if clk is not None:
                clocks[k] = {"residual_std_s": _f(getattr(clk, "residual_std_s", None)),
                             "drift_ppm": _f(getattr(clk, "drift_ppm", None)),
                             "resets": getattr(clk, "resets", None)}
        return {
            "rates": rates, "drops": drops, "devices": devices, "totals": totals, "clocks": clocks,
            "pipeline": {k: v for k, v in ps.items() if k != "counters"} | {"counters": pc},
            "threads": self.critical_alive(), "ready": self._ready, "gyro_online": self.pipeline.gyro_online,
            "publisher": {k: pub[k] for k in ("queue_depth", "queue_dropped", "send_errors", "hwm",
                                              "held_bytes", "held_peak_bytes", "budget_dropped", "warnings")
                          if k in pub},
            "daemon": dict(self.counters),
        }

    def publish_health(self, now: float | None = None) -> dict:
        now = time.monotonic() if now is None else now
        self._last_health = now
        h = self.health(now, update_rates=True)
        self.last_health = h
        self.publisher.publish_health(rates=h["rates"], drops=h["drops"], devices=h["devices"],
                                      calibration=self.pipeline.calib.as_dict(), t=now,
                                      **{k: v for k, v in h.items() if k not in ("rates", "drops",
                                                                                  "devices")})
        if self._ready:
            self.notifier.status(self._status_line())
        return h


def _safe_stats(src) -> dict:
    try:
        return {k: v for k, v in src.stats().items() if isinstance(v, (int, float, str, bool)) or v is None}
    except Exception as e:  # noqa: BLE001 - health must not die with a driver's stats()
        return {"stats_error": str(e)}


def _f(v):
    return None if v is None or (isinstance(v, float) and not math.isfinite(v)) else float(v)
