"""The supervisor behind `thermod run`. Builds the sources from the configuration, runs one driver thread
per device (``source.poll(timeout)`` in a loop → ring buffer), the pipeline (scheduler + deconvolution
workers), the publisher, and a 1 Hz health report; handles signals, sd_notify and device faults.

Threads: ``thermod-gyro`` / ``thermod-camera``, the only ones with real-time priority (SCHED_FIFO when
``realtime_priority`` > 0 and permitted), which never block on anything but their device; the
pipeline's (`thermod.runtime.pipeline`) and the publisher's (`thermod.runtime.publish`);
``thermod-monitor`` (`thermod.runtime.monitor`), whose proposals are applied here with
`Pipeline.update`; and the main thread: signals, health, watchdog, SIGHUP reload.

Faults: a gyro I/O error is retried with back-off while frames pass through flagged ``gyro_offline``;
a camera error or stall (no frame for ``max(1 s, 10 frame periods)``) restarts the camera source
with back-off. Every state change is logged once and visible in the health message.
Signals: SIGTERM/SIGINT → clean shutdown (< 2 s), exit 0, also during the start (`start`). SIGHUP →
re-read the configuration and apply its calibration, deblur and radiometry settings to the running
pipeline (no frame dropped); source/publish changes need a restart and are reported as such; a
reload that fails keeps the running configuration and says why (log, ``health["reload"]``). Data
flow: docs/design.md §6.

Parts: `thermod.runtime.sources` (driver registry), `thermod.runtime.driver_thread` (one thread per
device), `thermod.runtime.health` (the health message), this module; `thermod.cli.run` is the command.
"""

from __future__ import annotations

import collections
import dataclasses
import itertools
import logging
import math
import threading
import time

from thermod.errors import ConfigError, DeviceError, StopRequested, ThermodError
from thermod.io.wire import frame_method_fields
from thermod.restore.policy import MAX_STEP_PERIODS
from thermod.runtime import config as configmod
from thermod.runtime import sources
from thermod.runtime.cpu import CpuMeter
from thermod.runtime.driver_thread import DeviceState, DriverThread
from thermod.runtime.gyro_process import GyroProcess, GyroPump
from thermod.runtime.health import Health, Snapshot, status_line
from thermod.runtime.pipeline import FrameOut, Pipeline
from thermod.runtime.rings import FrameRing, GyroRing
from thermod.runtime.sources import Source

_UNREAD = object()         # the camera's radiometric constants have not been asked for yet

log = logging.getLogger("thermod.runtime.daemon")

STALL_MIN_S = 1.0
GYRO_STALL_S = 0.5          # a gyro silent this long is stalled (it delivers every few ms)
GYRO_START_WAIT_S = 5.0     # the camera waits this long at most for a gyro process's first samples
# sections a running daemon cannot change: a reload that changes them is applied in part
_RESTART_SECTIONS = ("gyro", "camera", "publish", "pipeline", "sim", "rtsp", "monitor")


# ------------------------------------------------------------------------------------ the daemon
class Daemon:
    """All parts wired together. `start`, then `serve` (blocks) or `tick` from your own loop, `stop`.

    ``gyro``/``camera``/``publisher`` may be passed in (tests inject sources with faults); by default
    they are built from the configuration. ``deconvolver_factory`` is the pipeline's seam for the
    deconvolver (tests inject a slow one to exercise the governor).
    """

    def __init__(self, cfg: configmod.Config, *, gyro=None, camera=None, publisher=None, notifier=None,
                 overrides: dict | None = None, deconvolver_factory=None):
        self.cfg = cfg
        self.overrides = dict(overrides or {})
        self.payload = sources.simulated_payload(cfg) if gyro is None or camera is None else None
        if gyro is None and cfg.gyro.options.get("own_process", False):
            g = cfg.gyro
            self.gyro: Source = GyroProcess(
                f"{g.kind} gyro", poll_timeout=g.poll_timeout_s, priority=g.realtime_priority,
                retry_max_s=g.retry_max_s, stall_s=GYRO_STALL_S,
                preload=("thermod.sim.payload",) if g.kind == "sim" else ())   # a driver's module is light
        else:
            self.gyro = gyro if gyro is not None else sources.build_gyro(cfg, self.payload)
        self.camera: Source = camera if camera is not None else sources.build_camera(cfg, self.payload)
        # a replayed recording runs with its own calibration unless the config asks for its [calibration]
        calib, self.calibration_source = sources.calibration_in_force(cfg, self.camera)
        if calib is not cfg.calibration:
            log.info("calibration: the replayed recording's own (sources.camera.calibration = 'config' "
                     "for the configuration's)")
            cfg = self.cfg = dataclasses.replace(cfg, calibration=calib)
        self._offer_frame = getattr(self.gyro, "offer", None)     # a video source: fed the frames
        if self._offer_frame is not None:
            cfg = self.cfg = self._for_video_motion(cfg)
            self.gyro.bind(cfg.calibration)
            log.info("gyro: none; the motion is measured from the camera's frames (one frame of latency)")
        if publisher is None:
            from thermod.runtime.publish import Publisher
            p = cfg.publish
            publisher = Publisher(p.endpoint, hwm=p.hwm, curve_secret_key_file=p.curve_secret_key,
                                  authorized_keys_dir=p.curve_authorized_keys,
                                  allow_insecure_remote=p.allow_insecure_remote,
                                  max_queue_bytes=int(p.max_queue_mb * 2**20), gyro_batch_s=p.gyro_batch_s,
                                  max_message_bytes=cfg.calibration.width * cfg.calibration.height * 4)
        self.publisher = publisher
        self._camera_radiometry = _UNREAD     # model = "camera": the constants, read at the first frame
        self.rtsp = None     # the H.264 live view ([rtsp]); GStreamer is imported only when enabled
        if cfg.rtsp.enabled:
            from thermod.runtime.rtsp import RtspServer
            self.rtsp = RtspServer(cfg.rtsp, cfg.calibration.width, cfg.calibration.height,
                                   cfg.calibration.frame_rate_hz)
        if notifier is None:
            from thermod.runtime.sdnotify import Notifier
            notifier = Notifier()
        self.notifier = notifier
        c = cfg.calibration
        # a step without a device-counter gap is a hole in time too, by the per-frame policy's rule
        self.gyro_ring = GyroRing(int(cfg.pipeline.gyro_ring_s * c.rate_hz * 1.1) + 64,
                                  max_step_s=MAX_STEP_PERIODS / c.rate_hz)
        self.frame_ring = FrameRing(cfg.pipeline.frame_ring, (c.height, c.width))
        self.pipeline = Pipeline(self.gyro_ring, self.frame_ring, c, cfg.deblur, cfg.pipeline, self._emit,
                                 deconvolver_factory=deconvolver_factory, kernels=self._kernels_wanted)
        self.monitor = None       # the live calibration monitor ([monitor], thermod.runtime.monitor)
        if cfg.monitor.enabled and self._offer_frame is not None:
            log.info("monitor: off (the motion comes from the frames it would check it against)")
        elif cfg.monitor.enabled:
            from thermod.runtime.monitor import Monitor
            self.monitor = Monitor(cfg.monitor, self.gyro_ring, self.frame_ring, lambda: self.pipeline.calib,
                                   short_of_cpu=lambda: self.pipeline.short_of_cpu(),
                                   gyro_history_s=cfg.pipeline.gyro_ring_s)
        self._stop = threading.Event()
        self.gyro_state = DeviceState(self.gyro.name)
        self.pipeline.gyro_delivered = lambda: self.gyro_state.last_data
        self.pipeline.overlay = getattr(self.gyro, "overlay", None)    # a video source finds logos
        self.camera_state = DeviceState(self.camera.name)
        self.driver_threads: list[DriverThread] = []
        self.counters = collections.Counter()
        self.ready = False
        self._last_health = 0.0
        self._last_ping = 0.0
        self._ping_every = min(1.0, self.notifier.watchdog_interval() or 1.0)
        self._health = Health()
        self._cpu = CpuMeter()             # CPU per stage, read once per health period
        self._cpu_report: dict = {}
        self.last_health: dict = {}
        # the last SIGHUP's outcome, in every health message: ok, error (why it was refused), at (host time)
        self.reload_status: dict = {"ok": True, "error": None, "at": None, "restart_needed": []}

    # ---------------------------------------------------------------- sinks (driver threads)
    def _on_gyro(self, b) -> None:
        self.gyro_ring.write(b.t, b.rate, b.seq, gap_before=b.gap_before)
        self.gyro_state.items += len(b.t)
        if b.gap_before:
            self.counters["gyro_gaps"] += 1
            self.counters["gyro_lost"] += int(b.n_lost)
        if self.cfg.publish.gyro and self._wanted("gyro"):
            self.publisher.publish_gyro(b.t, b.rate, seq=b.seq, gap_before=b.gap_before, n_lost=b.n_lost)

    def _wanted(self, topic: str) -> bool:
        """Whether a subscriber now asks for `topic` (an injected publisher that cannot tell: yes)."""
        wants = getattr(self.publisher, "wants", None)
        return True if wants is None else wants(topic)

    def _kernels_wanted(self) -> bool:
        """Pack each frame's kernel for the wire: while it is published and subscribed to."""
        return self.cfg.publish.kernel and self._wanted("kernel")

    def _on_frame(self, f) -> None:
        try:
            self.frame_ring.write(f.image, f.t, f.frame_id, f.arrival, f.gap_before,
                                  ffc=getattr(f, "ffc", False))
        except ValueError as e:
            self.counters["frames_wrong_shape"] += 1
            raise DeviceError(f"{self.camera_state.name}: {e} (calibration.width/height)") from None
        self.camera_state.items += 1
        if self._offer_frame is not None:
            self._offer_frame(f.image, f.t)
        if f.gap_before:
            self.counters["camera_frames_lost"] += int(f.gap_before)
        if self.cfg.publish.raw and self._wanted("raw"):
            self.publisher.publish_raw(f.image, f.t, frame_id=f.frame_id, gap_before=int(f.gap_before))
        if self.rtsp is not None:
            self.rtsp.offer_raw(f.image, f.t, f.frame_id)

    def radiometry(self):
        """The counts → °C model in force: the configuration's, or with model = "camera" the constants
        the camera reports (asked once; a camera without them converts nothing, said in the log and in
        health)."""
        rad = self.cfg.radiometry
        if rad != configmod.CAMERA_RADIOMETRY:
            return rad
        if self._camera_radiometry is _UNREAD:
            try:
                self._camera_radiometry = self.camera.radiometry()
            except Exception as e:  # noqa: BLE001 - a driver's read must not stop the frames
                log.warning("radiometry: reading the camera's constants failed: %s", e)
                self._camera_radiometry = None
            if self._camera_radiometry is None:
                log.warning("radiometry: model = 'camera' but %s reports no Planck constants; no °C",
                            self.camera.name)
        return self._camera_radiometry

    def _emit(self, o: FrameOut) -> None:
        self.publisher.publish_frame(o.image, o.t, frame_id=o.frame_id, deblurred=o.deblurred,
                                     kernel_size=o.kernel_size, kernel_extent_px=o.kernel_extent_px,
                                     coverage=o.coverage, reason=o.reason, copy=False, n_samples=o.n_samples,
                                     latency_s=o.latency_s, camera_gap_before=o.camera_gap_before,
                                     overrun_before=o.overrun_before,
                                     **frame_method_fields(o.method, o.grid))
        if self.cfg.publish.kernel and o.kernel is not None:
            self.publisher.publish_kernel(o.kernel, o.t, frame_id=o.frame_id)
        if (rad := self.radiometry()) is not None and self._wanted("celsius"):
            # after deblurring: counts are linear in flux, °C not
            self.publisher.publish("celsius", {"t": float(o.t), "frame_id": int(o.frame_id),
                                               "deblurred": bool(o.deblurred),
                                               "radiometry": rad.as_dict()},
                                   rad.to_celsius(o.image), copy=False)
        if self.rtsp is not None:
            self.rtsp.offer(o.image, o.t, o.frame_id)

    # ---------------------------------------------------------------- lifecycle
    def start(self, abort: threading.Event | None = None) -> bool:
        """Start every part; `stop` ends them, also after a start that failed or was abandoned.

        `abort` (the stop signal's event, as `serve` gets it): set before the start is done, it ends
        the start between two steps, and the seconds of the workers' warm-up within a fraction of a
        second (`Pipeline.warmup`) and the simulated payload's first pre-rendering at its next frame;
        returns False then, True once started."""
        try:
            self._start(abort)
        except StopRequested as e:
            log.info("start abandoned: %s", e)
            return False
        return True

    def _start(self, abort: threading.Event | None) -> None:
        def check(when: str) -> None:
            StopRequested.check(abort, when)

        cfg = self.cfg
        check("before the start")
        self.publisher.start()  # first: a taken endpoint fails here, before seconds of payload preparation
        log.info("publishing on %s", self.publisher.endpoint)
        if self.rtsp is not None:
            self.rtsp.start()     # a taken port fails here too
        if isinstance(self.gyro, GyroProcess):
            self.gyro.spawn()         # its interpreter starts while the payload and the workers prepare
        if self.payload is not None:
            check("before the simulated payload's preparation")
            if not self.payload.cached():
                log.warning("simulated payload: first start, pre-rendering %.0f s of frames (cached in %s); "
                            "this takes a while once", cfg.sim.loop_s, self.payload.cache_path)
                self.notifier.extend_timeout(600.0)      # beyond TimeoutStartSec, once
            self.payload.prepare(abort)
        check("before the warm-up")
        log.info("warming up %d deconvolution workers", self.pipeline.n_workers)
        dt = self.pipeline.warmup(abort=abort)
        log.info("renderer and %d deconvolution workers ready (%.2f s)", self.pipeline.n_workers, dt)
        check("after the warm-up")
        if self.payload is not None:
            self.payload.start()
        self.pipeline.start(self.frame_ring.head)
        frame_period = 1.0 / cfg.calibration.frame_rate_hz
        # a FIFO gyro reads on a slow interval (its CPU) and at once when a frame waits for it
        self.gyro_ring.request = getattr(self.gyro, "request_read", None)
        if isinstance(self.gyro, GyroProcess):
            self.gyro.start(sources.gyro_builder(cfg, self.payload))
            gyro_thread = GyroPump(self.gyro, self._on_gyro, self.gyro_state, self._stop,
                                   on_down=self._gyro_down, on_up=self._gyro_up)
        else:
            g = cfg.gyro
            gyro_thread = DriverThread("gyro", self.gyro, self._on_gyro, self.gyro_state, self._stop,
                                       poll_timeout=g.poll_timeout_s, priority=g.realtime_priority,
                                       retry_max_s=g.retry_max_s, stall_s=GYRO_STALL_S,
                                       on_down=self._gyro_down, on_up=self._gyro_up)
        self.driver_threads = [
            gyro_thread,
            DriverThread("camera", self.camera, self._on_frame, self.camera_state, self._stop,
                         poll_timeout=cfg.camera.poll_timeout_s, priority=cfg.camera.realtime_priority,
                         retry_max_s=cfg.camera.retry_max_s, stall_s=max(STALL_MIN_S, 10 * frame_period)),
        ]
        gyro_thread.start()
        if isinstance(self.gyro, GyroProcess):
            self._await_gyro(GYRO_START_WAIT_S, abort)
            check("while waiting for the gyro process")
        for th in self.driver_threads[1:]:
            th.start()
        if self.monitor is not None:
            self.monitor.start()

    def _await_gyro(self, timeout: float, abort: threading.Event | None = None) -> None:
        """Wait until the gyro's first samples are in the ring, at most `timeout` s (or until `abort`
        is set): the camera starts then, so the first frames find their motion (a gyro process builds
        its source only now). A gyro that is not up by then is waited for frame by frame, as any
        outage."""
        deadline = time.monotonic() + timeout
        while self.gyro_ring.count == 0 and time.monotonic() < deadline and not self._stop.is_set() \
                and self.gyro_state.state != "error" and not StopRequested.requested(abort):
            time.sleep(0.01)
        if StopRequested.requested(abort):
            return
        if self.gyro_ring.count == 0:
            log.warning("gyro: no sample yet (%s); starting the camera anyway", self.gyro_state.state)

    def _gyro_down(self) -> None:
        self.pipeline.gyro_online = False
        self.counters["gyro_outages"] += 1

    def _gyro_up(self) -> None:
        self.pipeline.gyro_online = True

    def stop(self) -> None:
        self._stop.set()
        t0 = time.monotonic()
        marks = [("signal", t0)]

        def mark(stage: str) -> None:
            marks.append((stage, time.monotonic()))
        for th in self.driver_threads:
            th.join(max(0.05, 0.8 - (time.monotonic() - t0)))
        if isinstance(self.gyro, GyroProcess):
            self.gyro.stop(timeout=0.3)    # spawned even when the start failed before its pump ran
        mark("drivers")
        if self.monitor is not None:
            self.monitor.stop(timeout=0.3)
        mark("monitor")
        self.pipeline.stop(timeout=0.6)
        mark("pipeline")
        if self.payload is not None:
            self.payload.stop()
        mark("payload")
        self.notifier.stopping("stopping")
        if self.rtsp is not None:
            self.rtsp.stop()
        mark("rtsp")
        try:
            self.publisher.stop()
        finally:
            self.notifier.close()
        mark("publisher")
        steps = ", ".join(f"{name} {1e3 * (b - a):.0f} ms" for (_, a), (name, b) in itertools.pairwise(marks))
        log.info("stopped after %.2f s (%s)", time.monotonic() - t0, steps)

    def _for_video_motion(self, cfg: configmod.Config) -> configmod.Config:
        """`cfg` as a video source runs it: its rates are the camera's own, on the frames' clock (the
        calibration's gyro part is the identity), a frame waits for the next one's registration, and
        the p99 latency goal is one frame period longer."""
        if self._offer_frame is None:
            return cfg
        calib = self.gyro.calibration_for(cfg.calibration)
        wait = max(cfg.pipeline.wait_timeout_s, self.gyro.samples_wait_s(calib.frame_rate_hz))
        # the latency loop holds the p99 the source allows: the configured one plus the frame period
        # every frame waits for the next one's registration (a goal it cannot reach pins the loop at
        # its floor, and the stream at the cheapest rung)
        goal = cfg.deblur.latency_p99_s + 1.0 / calib.frame_rate_hz
        return dataclasses.replace(cfg, calibration=calib,
                                   pipeline=dataclasses.replace(cfg.pipeline, wait_timeout_s=wait),
                                   deblur=dataclasses.replace(cfg.deblur, latency_p99_s=goal))

    def reload(self) -> bool:
        """SIGHUP: re-read the configuration and apply its calibration and deblur settings live.

        Whatever goes wrong (unreadable file, invalid TOML or values, a calibration that does not fit
        the camera's frames, a failure while applying), the daemon keeps running on the configuration
        it has, logs why and reports it as ``health["reload"]``. Returns whether the reload was applied.
        """
        self.notifier.reloading()
        now = time.monotonic()
        try:
            new = configmod.load(None if self.cfg.path.startswith("<") else self.cfg.path, self.overrides)
            calib, _ = sources.calibration_in_force(new, self.camera)
            new = self._for_video_motion(dataclasses.replace(new, calibration=calib))
            self._check_reload(new)
            self.pipeline.update(calib=new.calibration, deblur=new.deblur)
            if self._offer_frame is not None and \
                    _camera_part(new.calibration) != _camera_part(self.cfg.calibration):
                self.gyro.bind(new.calibration)     # a new τ, readout or lens: the next pair starts afresh
        except Exception as e:  # noqa: BLE001 - a reload must never take the running daemon down
            why = str(e) if isinstance(e, ThermodError) else f"{type(e).__name__}: {e}"
            log.error("reload refused, keeping the running configuration: %s", why)
            self.counters["reload_errors"] += 1
            self.reload_status = {"ok": False, "error": why, "at": now, "restart_needed": []}
            self.notifier.ready(self._status_line())
            return False
        restart_needed = [k for k in _RESTART_SECTIONS if getattr(new, k) != getattr(self.cfg, k)]
        if restart_needed:
            log.warning("reload: changes to %s need a restart; applied calibration and deblur only",
                        ", ".join(restart_needed))
        self.cfg = dataclasses.replace(self.cfg, calibration=new.calibration, deblur=new.deblur,
                                       radiometry=new.radiometry)
        self.calibration_source = sources.calibration_in_force(new, self.camera)[1]
        self._camera_radiometry = _UNREAD
        self.counters["reloads"] += 1
        self.reload_status = {"ok": True, "error": None, "at": now, "restart_needed": restart_needed}
        log.info("reloaded calibration and deblur settings from %s", new.path)
        self.notifier.ready(self._status_line())
        return True

    def _check_reload(self, new: configmod.Config) -> None:
        """Refuse what the running daemon cannot apply: a calibration for frames of another size."""
        h, w = self.frame_ring.shape
        c = new.calibration
        if (c.width, c.height) != (w, h):
            raise ConfigError(f"{new.path}: calibration.width/height: expected the running camera's frame "
                              f"size {w}×{h}, got {c.width}×{c.height} (a new camera needs a restart)")

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
        out = {th.kind: th.is_alive() and now - th.st.heartbeat < w for th in self.driver_threads}
        alive = self.pipeline.alive()
        for name, ok in alive.items():
            hb = self.pipeline.heartbeat.get(name, 0.0)
            out[name] = ok and now - hb < w
        out["publisher"] = bool(self.publisher.running)
        return out

    def tick(self) -> None:
        now = time.monotonic()
        self.pipeline.supervise()
        if self.monitor is not None and (new := self.monitor.take_proposal()) is not None:
            self.pipeline.update(calib=new)        # the monitor checked it lowers the residual
            self.calibration_source = "monitor"
            self.counters["calibration_changes"] += 1
        if not self.ready and self.gyro_state.items > 0 and self.camera_state.items > 0:
            self.ready = True
            log.info("ready: frames and gyro samples flowing")
            self.notifier.ready(self._status_line())
        # WATCHDOG=1 at half systemd's timeout (≤ 1 s), and only while every critical thread checks in
        if self.ready and now - self._last_ping >= self._ping_every and all(self.critical_alive().values()):
            self._last_ping = now
            self.notifier.watchdog()
        if now - self._last_health >= self.cfg.publish.health_period_s:
            self.publish_health(now)

    def _status_line(self) -> str:
        return status_line(self.last_health, self.gyro_state.state, self.camera_state.state)

    def health(self, now: float | None = None, *, update_rates: bool = False) -> dict:
        """The health message (see `thermod.runtime.health`); `update_rates` also closes the CPU
        meter's period."""
        now = time.monotonic() if now is None else now
        if update_rates:
            sim = None if self.payload is None else self.payload.cpu_s
            if isinstance(self.gyro, GyroProcess):
                gyro_pids, gyro_sim = (() if self.gyro.pid is None else (self.gyro.pid,)), self.gyro.sim_cpu_s
            else:
                gyro_pids, gyro_sim = (), None
            self._cpu_report = self._cpu.sample(self.pipeline.solver_pids(), sim, now, gyro_pids=gyro_pids,
                                                gyro_sim_cpu_s=gyro_sim if sim is not None else None)
        return self._health.message(self._snapshot(now), now, update_rates=update_rates)

    def _snapshot(self, now: float) -> Snapshot:
        return Snapshot(
            pipeline=self.pipeline.stats(), gyro_items=self.gyro_state.items,
            camera_items=self.camera_state.items,
            sources={"gyro": (self.gyro, self.gyro_state.as_dict(now)),
                     "camera": (self.camera, self.camera_state.as_dict(now))},
            sink_drops={f"{th.kind}_items_rejected": th.sink_drops for th in self.driver_threads},
            counters=dict(self.counters), gyro_ring_clock_jumps=self.gyro_ring.clock_jumps,
            gyro_ring_time_holes=self.gyro_ring.time_holes, publisher=self.publisher.stats(),
            threads=self.critical_alive(), ready=self.ready, gyro_online=self.pipeline.gyro_online,
            reload=dict(self.reload_status), rtsp=self.rtsp.stats() if self.rtsp is not None else None,
            radiometry=self._radiometry_report(), calibration=self._calibration_report(),
            cpu=self._cpu_report)

    def _calibration_report(self) -> dict:
        """The calibration in force (flat, as `thermod record` reads it), where it came from, and the
        monitor's live estimate."""
        applied = self.pipeline.calib.as_dict()
        return {**applied, "applied": applied, "source": self.calibration_source,
                "estimate": self.monitor.estimate() if self.monitor is not None else None,
                "monitor": self.monitor.state() if self.monitor is not None else {"enabled": False}}

    def _radiometry_report(self) -> dict:
        """Which counts → °C model the daemon converts with, and where it came from."""
        if self.cfg.radiometry is None:
            return {"source": None, "model": None}
        model = self.radiometry()
        return {"source": "camera" if self.cfg.radiometry == configmod.CAMERA_RADIOMETRY else "config",
                "model": model.as_dict() if model is not None else None}

    def publish_health(self, now: float | None = None) -> dict:
        now = time.monotonic() if now is None else now
        self._last_health = now
        h = self.health(now, update_rates=True)
        self.last_health = h
        self.publisher.publish_health(rates=h["rates"], drops=h["drops"], devices=h["devices"],
                                      calibration=h["calibration"], t=now,
                                      **{k: v for k, v in h.items() if k not in ("rates", "drops",
                                                                                  "devices", "calibration")})
        if self.ready:
            self.notifier.status(self._status_line())
        return h


def _camera_part(c) -> tuple:
    """What a video source measures with: the intrinsics, τ and readout."""
    return (c.intrinsics, c.tau_s, c.readout_s)
