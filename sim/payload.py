"""The simulated payload behind ``config/sim.toml``: a thermal camera and a gyro that see the SAME motion.

- Camera: `SimCamera` plays a loop of ``loop_s`` seconds pre-rendered once by the simulator
  (`thermod.sim.playback`, Eq. 10/11) in real time: frame k is read at ``T0 + k/fps`` (host
  monotonic), shows loop frame ``k mod N`` plus fresh temporal noise (``[sim] netd_k``) and is
  delivered when that time has come.
- Gyro: the REAL ICM-42688-P driver (`thermod.drivers.icm42688.ICM42688`) over the SPI bus seam on
  the register-level emulator (`thermod.sim.emu_registers.ICM42688Emu`), whose FIFO fills at 1 kHz
  in real time with the loop motion's raw rate.

The rule it keeps: the loop motion returns to its start orientation after ``loop_s``, so the blur
of every frame, also across the loop's seam, matches the gyro, and the deblurred stream can be
checked against the truth (`truth_for`, `frame_for`, `ffc_truth`, `true_calibration`). Flat-field
corrections (``[sim] ffc_interval_s``), drift (``payload.drift``, ``[sim] tau_s``) and fault
injection (`SimCamera.stall`, `SimCamera.disconnect`, ``payload.chip``): docs/design.md §5,
"The simulated payload".
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from thermod.drivers.camera_base import CameraSource, Frame
from thermod.errors import DeviceError, StopRequested
from thermod.physics.calibration import Calibration
from thermod.sim import playback
from thermod.sim.scenes import COUNTS_PER_K

log = logging.getLogger(__name__)
# Temporal-noise frames, cycled against the loop: with a loop of N frames a frame meets the same noise
# again only after lcm(N, 17) frames (1700 for the default 2 s at 50 fps)
NOISE_FRAMES = 17


class CpuBook:
    """Thread CPU seconds spent emulating devices, booked from any thread: ``book(thread_time_at_start)``."""

    def __init__(self) -> None:
        self.cpu_s = 0.0
        self._lock = threading.Lock()

    def __call__(self, c0: float) -> None:
        with self._lock:
            self.cpu_s += time.thread_time() - c0


class SimPayload:
    """Simulated camera + gyro on a common time base. `prepare` (pre-render or load the cache),
    `start` (set T0), then hand `camera_source()` / `gyro_source()` to the daemon."""

    def __init__(self, sim_cfg, calib: Calibration):
        self.cfg, self.calib = sim_cfg, calib
        # The payload's gyro and camera sample one clock, so its world has no gyro → camera offset: the
        # offset the daemon sees is the camera's transport latency (`true_calibration`), which the
        # configured time_offset_s corrects, not something the configuration puts into the world.
        self.world = calib.replace(frame_rate_hz=sim_cfg.frame_rate_hz, time_offset_s=0.0)
        # a true τ other than the configuration's (``[sim] tau_s``) is a hidden effect of the loop
        hidden = (("time_constant", float(sim_cfg.tau_s)),) if sim_cfg.tau_s else ()
        self.spec = playback.PlaybackSpec(scene=sim_cfg.scene, motion=sim_cfg.motion, seconds=sim_cfg.loop_s,
                                          seed=sim_cfg.seed, calib=self.world, effects=hidden)
        self._cache_dir = Path(sim_cfg.cache_dir) if sim_cfg.cache_dir else None
        self.cache_path = playback.cache_path(self.spec, self._cache_dir)
        self.loop: playback.Playback | None = None
        self.frames: np.ndarray | None = None     # uint16 [N, H, W] (the loop)
        self.truth: np.ndarray | None = None      # float32 [N, H, W] sharp views
        self.noise: np.ndarray | None = None      # int16 [NOISE_FRAMES, H, W] temporal noise (counts)
        self.t0: float | None = None              # host time of loop frame 0's read, first pass
        self.chip = None
        self._camera: SimCamera | None = None
        self._gyro = None
        self.drift = None                         # a `thermod.sim.gyro_model.GyroDrift` on top of the truth
        self.book = CpuBook()                     # thread CPU spent emulating (frames, gyro FIFO): a real
                                                  # payload does not pay it (`thermod.runtime.cpu`)

    # ------------------------------------------------------------------ the loop
    def cached(self) -> bool:
        return self.cache_path.exists()

    def prepare(self, abort=None) -> None:
        """Load the pre-rendered loop from the cache, rendering (once, slowly) if it is missing. Once
        `abort` (a threading.Event) is set, the rendering ends at its next frame with StopRequested
        and nothing is cached."""
        if self.loop is not None:
            return
        t0 = time.monotonic()

        def stop_if_asked(_frames: int) -> None:
            StopRequested.check(abort, "while pre-rendering the simulated payload")

        self.loop = playback.load(self.spec, self._cache_dir, progress=stop_if_asked if abort else False)
        self.frames = np.ascontiguousarray(self.loop.frames)
        self.truth = np.asarray(self.loop.truth, np.float32)
        self.noise = self._noise_bank()
        log.info("simulated payload: %d-frame loop ready in %.1f s (%s)", len(self.frames),
                 time.monotonic() - t0, self.cache_path)

    @property
    def n_frames(self) -> int:
        return 0 if self.frames is None else len(self.frames)

    def truth_for(self, frame_id: int) -> np.ndarray:
        """The sharp view (float32 counts) of delivered frame `frame_id` (ids start at 1), with the NUC
        offset the camera had then (see `ffc_schedule`)."""
        view = self.truth[(int(frame_id) - 1) % self.n_frames]
        sched = self.ffc_schedule()
        off = 0.0 if sched is None else sched.offset(self.read_time(frame_id))
        return view if off == 0 else view + np.float32(off)

    def read_time(self, frame_id: int) -> float:
        """Host time at which delivered frame `frame_id` was read (T0 + (id − 1)/fps)."""
        return self.t0 + (int(frame_id) - 1) / self.cfg.frame_rate_hz

    def ffc_schedule(self):
        """The camera's flat-field correction schedule (on host time, from T0), or None when it runs none."""
        c = self.cfg
        if not c.ffc_interval_s or self.t0 is None:
            return None
        from thermod.sim.emu_camera import FFCSchedule

        return FFCSchedule(c.ffc_interval_s, c.ffc_duration_s, c.ffc_step_counts, origin=self.t0)

    def ffc_truth(self, frame_id: int) -> bool:
        """Whether delivered frame `frame_id` was read during a flat-field correction (frozen, flagged)."""
        sched = self.ffc_schedule()
        return sched is not None and sched.active(self.read_time(frame_id))

    def frame_for(self, frame_id: int) -> np.ndarray:
        """The blurry raw frame (uint16) delivered as `frame_id`: its loop frame plus its temporal noise."""
        c0 = time.thread_time()
        k = int(frame_id) - 1
        img = self.frames[k % self.n_frames]
        if self.noise is not None:
            img = np.clip(img.astype(np.int32) + self.noise[k % len(self.noise)], 0, 65535).astype(np.uint16)
        self.book(c0)
        return img

    @property
    def cpu_s(self) -> float:
        return self.book.cpu_s

    def frame_at(self, k: int) -> np.ndarray:
        """The emulated camera's frame index k (0-based): `frame_for(k + 1)`."""
        return self.frame_for(k + 1)

    def _noise_bank(self) -> np.ndarray | None:
        """[NOISE_FRAMES, H, W] int16 temporal noise (``[sim] netd_k`` in counts), cycled against the loop
        rather than rendered into it, so that a frame's noise differs from one pass of the loop to the
        next, as a camera's does."""
        netd = float(self.cfg.netd_k)
        if not netd:
            return None
        rng = np.random.default_rng(self.cfg.seed + 1)
        shape = (NOISE_FRAMES, *self.frames.shape[1:])
        noise = rng.standard_normal(shape, np.float32) * np.float32(netd * COUNTS_PER_K)
        return np.rint(noise).astype(np.int16)

    # ------------------------------------------------------------------ live
    def start(self, t0: float | None = None) -> None:
        """Fix the common time base: loop frame 0 is read at host time T0 (default: now + 50 ms)."""
        self.t0 = time.monotonic() + 0.05 if t0 is None else float(t0)
        if self._camera is not None:
            self._camera.t0 = self.t0

    def stop(self) -> None:
        pass

    def true_calibration(self, t: float) -> Calibration:
        """The gyro ↔ camera calibration that is true at host time t: the loop's (no time offset), plus the
        drift, plus the camera's transport latency. Its frames carry device timestamps of the last row's
        read, but the clock mapping (`thermod.io.clock.ClockMapper`, as with a real camera) sees only
        their arrivals, so the least transport delay stamps every frame that much late: a time offset of
        +latency_s, which ``config/sim.toml`` sets."""
        c = self.loop.true_calib if self.loop is not None else self.world
        latency = self._camera.latency_s if self._camera is not None else 0.0
        tt = t - (self.t0 or 0.0)
        b = np.asarray(c.bias_rad_s) + (self.drift.bias(tt) if self.drift is not None else 0.0)
        o = latency + (float(self.drift.offset(tt)) if self.drift is not None else 0.0)
        return c.replace(bias_rad_s=tuple(np.asarray(b, float).tolist()), time_offset_s=c.time_offset_s + o)

    def gyro_builder(self) -> EmulatedGyro:
        """What builds the payload's gyro in the gyro process (picklable; after `prepare` and `start`:
        the emulator's clock starts at T0)."""
        if self.loop is None or self.t0 is None:
            raise RuntimeError("SimPayload.gyro_builder: prepare() and start() first")
        return EmulatedGyro(self.loop.gyro_motion, self.t0, self.drift, self.cfg.gyro_noise_rad_s,
                            self.cfg.seed, self.cfg.gyro_rate_hz)

    def _rate_fn(self, t: np.ndarray) -> np.ndarray:
        # read at each FIFO fill: the loop, T0 and the drift may be set after the driver is built
        return drifted_rate(self.loop.gyro_motion, self.t0 if self.t0 is not None else 0.0, self.drift, t)

    def gyro_source(self):
        """The payload's gyro in this process (`emulated_icm42688`), its emulation CPU booked as the
        payload's; `chip` is its emulator (faults)."""
        if self._gyro is None:
            self._gyro = emulated_icm42688(self._rate_fn, self.cfg.gyro_noise_rad_s, self.cfg.seed,
                                           self.cfg.gyro_rate_hz, self.book)
            self.chip = self._gyro.emulator
        return self._gyro

    def camera_source(self) -> SimCamera:
        if self._camera is None:
            self._camera = SimCamera(self)
        return self._camera


def drifted_rate(motion: playback.LoopMotion, t0: float, drift, t) -> np.ndarray:
    """The raw rate the payload's gyro shows at host times t: the loop motion from T0 on; with a
    `thermod.sim.gyro_model.GyroDrift`, a sample stamped t shows the motion at t + offset(t), plus bias(t)."""
    tt = np.asarray(t, np.float64) - t0
    if drift is None:
        return motion.rate_gyro(tt)
    return motion.rate_gyro(tt + drift.offset(tt)) + drift.bias(tt)


def emulated_icm42688(rate_fn, noise_rad_s: float, seed: int, rate_hz: float, book: CpuBook):
    """The real ICM-42688-P driver over the SPI bus seam on the register-level emulator
    (`thermod.sim.emu_registers.ICM42688Emu`), whose FIFO fills at the output data rate in real time
    with ``rate_fn(t)``. Each transfer's CPU is booked in `book` (a real payload's SPI transfer is an
    ioctl). The driver carries ``emulator`` (the chip: faults) and ``emulation_cpu`` (`book`)."""
    from thermod.drivers.bus import SPIBus
    from thermod.drivers.icm42688 import ICM42688
    from thermod.sim.emu_registers import EmuSPI, ICM42688Emu

    class BookedSPI(EmuSPI):
        def xfer2(self, data):
            c0 = time.thread_time()
            try:
                return super().xfer2(data)
            finally:
                book(c0)

    chip = ICM42688Emu(rate_fn=rate_fn, noise_rad_s=noise_rad_s, seed=seed)
    driver = ICM42688(SPIBus(BookedSPI(chip)), full_scale_dps=2000.0, rate_hz=rate_hz,
                      name="ICM-42688-P (sim)")
    driver.emulator, driver.emulation_cpu = chip, book
    return driver


@dataclass(frozen=True)
class EmulatedGyro:
    """The payload's gyro as a picklable constructor, for the gyro process: the loop's motion (not its
    frames), T0 and the drift, fixed when the daemon starts its drivers."""

    motion: playback.LoopMotion
    t0: float
    drift: object | None
    noise_rad_s: float
    seed: int
    rate_hz: float

    def rate(self, t) -> np.ndarray:
        return drifted_rate(self.motion, self.t0, self.drift, t)

    def __call__(self):
        return emulated_icm42688(self.rate, self.noise_rad_s, self.seed, self.rate_hz, CpuBook())


class SimCamera(CameraSource):
    """The payload's camera: the simulator's GigE-style emulated camera (`thermod.sim.emu_camera.EmuCamera`:
    device clock with drift, 16-bit block ids, transport latency, a buffer pool) playing the loop,
    plus the faults the daemon must survive: `stall` (frames stop arriving) and `disconnect`.

    Frame index k is read at ``T0 + k/fps`` and shows loop frame ``k mod N``; its id is k + 1.
    """

    name = "sim camera"
    # What the simulated camera reports as its Planck constants (as a FLIR camera does over GenICam):
    # chosen so that the simulated scenes' counts (≈ 17 000–19 000) read as ≈ 20–30 °C.
    PLANCK = {"R": 3.4e5, "B": 1428.0, "F": 1.0, "O": 15000.0}

    def __init__(self, payload: SimPayload, *, latency_s: float = 0.002, drift_ppm: float = 20.0):
        self.p = payload
        self.latency_s, self.drift_ppm = latency_s, drift_ppm
        self.emu = None
        self._stall_until = -math.inf
        self._down_until = -math.inf
        self._undelivered = 0
        self.counters = {"stalls": 0, "disconnects": 0, "starts": 0, "discarded_in_stall": 0}

    def start(self) -> None:
        if time.monotonic() < self._down_until:
            raise DeviceError(f"{self.name}: not responding (simulated disconnect) — check the cable")
        self.p.prepare()
        if self.p.t0 is None:
            self.p.start()
        if self.emu is None:
            from thermod.sim.emu_camera import EmuCamera

            fps = self.p.cfg.frame_rate_hz
            # EmuCamera's frame k completes at origin + (k+1)/fps; ours at T0 + k/fps
            self.emu = EmuCamera(self.p, fps, origin=self.p.t0 - 1.0 / fps, latency_s=self.latency_s,
                                 drift_ppm=self.drift_ppm, seed=self.p.cfg.seed, name=self.name,
                                 ffc=self.p.ffc_schedule())
        self.emu.start()
        self.counters["starts"] += 1

    def stop(self) -> None:
        if self.emu is not None:
            self.emu.stop()

    def stall(self, seconds: float) -> None:
        """Deliver nothing for `seconds` (the frames are read by the sensor and lost: id gaps)."""
        self._stall_until = time.monotonic() + seconds
        self.counters["stalls"] += 1

    def disconnect(self, seconds: float) -> None:
        """Every poll/start raises DeviceError for `seconds`."""
        self._down_until = time.monotonic() + seconds
        self.counters["disconnects"] += 1

    def poll(self, timeout: float) -> Frame | None:
        now = time.monotonic()
        if now < self._down_until:
            if self.emu is not None:
                self.emu.stop()
            time.sleep(min(timeout, self._down_until - now))
            raise DeviceError(f"{self.name}: connection lost (simulated) — check the cable")
        if self.emu is None:
            raise DeviceError(f"{self.name}: poll() before start()")
        f = self.emu.poll(timeout)
        if f is None:
            return None
        if time.monotonic() < self._stall_until:
            self.counters["discarded_in_stall"] += 1
            self._undelivered += 1 + f.gap_before
            return None
        if self._undelivered:                 # frames the sensor read but never sent: an id gap
            f.gap_before += self._undelivered
            self._undelivered = 0
        return f

    @property
    def clock(self):
        """The emulated camera's device-clock → host mapping (its fit residuals go into health)."""
        return None if self.emu is None else self.emu.clock

    def radiometry(self):
        from thermod.physics.radiometry import Planck

        return Planck(**self.PLANCK)

    def stats(self) -> dict:
        return {**(self.emu.stats() if self.emu is not None else {}), **self.counters}
