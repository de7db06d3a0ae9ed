"""Frame scheduler → deconvolution workers (kernel render, solve) → in-order output.

For every frame k read at t_k (camera clock) the scheduler waits, at most until ``max(t_k, arrival)
+ wait_timeout_s``, for the gyro ring to hold a sample at or after t_k (asking a FIFO driver for a
read meanwhile), copies the samples of its window (t_k − m·τ − readout, t_k] (Eq. 18) and applies
the policy `thermod deblur` follows too (`thermod.restore.policy`): the rules before the kernel and
the grid the governor chooses (`thermod.runtime.governor`) give the frame's `KernelOrder`, or a
pass-through with its reason (`thermod.io.wire.REASONS`; the camera's flat-field corrections are
tracked here, `Pipeline._ffc_hold`). A job goes to a bounded queue served by worker threads, each
solving in a child process of its own (`thermod.runtime.solvers`), so N workers use N cores; the
worker renders the kernel or kernel grid (Eq. 16–19) and applies the coverage rule there.

Temporal rungs take the newest restored frame before k as the prior (`PRIOR_FRAMES` are kept); a
worker whose predecessor is still being solved temporally waits for it after its own solve, at most
half the budget, else takes k − 2. A temporal job carries a gyro window reaching `MAX_AGE_S` +
readout back for the warp; a frame solved without a prior is published as ``wiener``.

Nothing received is lost silently: a job that waited longer than the budget is solved by its
cheapest rung (``catch_up``); a full queue drops its oldest job (``overload``); a worker that raises
passes its frame through (``worker_error``) and is replaced; frames overwritten in the ring unread
are counted (``frames_overrun``). Outputs leave in frame order (one more than ``reorder_timeout_s``
late is released out of order). Every wait has a timeout, every drop a counter (`Pipeline.stats`).
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import pickle
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from thermod.errors import ConfigError, StopRequested
from thermod.physics.calibration import Calibration
from thermod.physics.deconv.recursive import MAX_AGE_S
from thermod.physics.gyro_effects import CLIP_TOL
from thermod.physics.kernels.grids import coarser_grids
from thermod.restore.plan import grids_within, kernel_window, make_deconvolver, render
from thermod.restore.policy import KernelOrder, PassThrough, gyro_span, order_kernel, refused_early
from thermod.restore.settings import DeblurConfig
from thermod.runtime.config import PipelineConfig
from thermod.runtime.cpu import StageTimes, usable_cpus
from thermod.runtime.governor import Choice, Governor
from thermod.runtime.rings import FrameRing, FrameSlot, GyroRing
from thermod.runtime.settling import Settling
from thermod.runtime.solvers import (
    InChild,
    InThread,
    Layout,
    SharedFrames,
    SolverError,
    close_all,
    limit_threads,
    rung_costs,
    slots_needed,
    start_children,
    warm_gyro,
)

log = logging.getLogger(__name__)

GIL_SWITCH_INTERVAL_S = 0.001   # while the pipeline runs (see `warmup`)
SHORT_OF_CPU_S = 10.0   # the pipeline is short of CPU while this long holds SHORT_OF_CPU_DROPS overload drops
SHORT_OF_CPU_DROPS = 3  # (one drop is a stall, not a shortage: the monitor goes on through it)
MIN_FRAME_PX = 16      # the smallest frame side the live rungs take (`thermod deblur` takes less)
PRIOR_FRAMES = 4       # restored frames kept as priors (a prior k − 1 … k − 4 frames back may be used)
STARVED_WAIT_S = 0.1   # beyond wait_timeout_s, how long a frame waits for a gyro reader that has delivered
                       # nothing since the frame came (starved of a core or the GIL, not short of samples)


@dataclass
class FrameOut:
    """One frame ready to publish: deblurred, or the raw counts passed through with a reason."""

    index: int                      # consecutive scheduler index (frame ring index)
    image: np.ndarray               # float32 [H, W], counts; owned by the receiver
    t: float                        # frame time (s, host monotonic, last row read)
    frame_id: int
    arrival: float
    deblurred: bool
    reason: str | None = None
    kernel_size: tuple[int, int] | None = None
    kernel_extent_px: float | None = None
    coverage: float | None = None
    n_samples: int = 0
    camera_gap_before: int = 0
    overrun_before: int = 0         # frames the frame ring overwrote unread just before this one, with
                                    # the camera's losses before them (no longer told apart)
    t_done: float = 0.0             # host monotonic when released
    kernel: tuple | None = None     # the kernel a deblurred frame was deconvolved with, packed for the
                                    # wire (`thermod.io.wire.pack_kernel`; when the pipeline keeps kernels)
    method: str | None = None       # how it was deblurred (`thermod.io.wire.METHODS`)
    prior_frames: int = 0           # temporal: frames between its prior and it (0: solved alone)
    grid: tuple[int, int] | None = None   # the kernel grid it was solved with ((1, 1): one kernel)

    @property
    def latency_s(self) -> float:
        return self.t_done - self.t


@dataclass
class _Job:
    slot: FrameSlot
    order: KernelOrder              # its kernel, rendered by the worker that solves it
    generation: int
    choice: Choice | None = None
    warp_gyro: tuple | None = None  # (t, rate) raw gyro from before the prior to the frame: the warp's
    t_queued: float = field(default_factory=time.monotonic)
    arrival_s: float = 0.0          # from the frame's read time to the scheduler taking it up
    gyro_wait_s: float = 0.0        # the scheduler's wait for the gyro to cover the frame
    render_s: float = 0.0           # the scheduler's grid choice (the worker adds the kernel's render)
    keep_out: tuple | None = None   # a static overlay's (mask, grown mask): kept out of the solve


@dataclass(frozen=True)
class _Settings:
    calib: Calibration
    deblur: DeblurConfig
    generation: int


def rung_for(gov: Governor, choice: Choice | None, waited_s: float) -> tuple:
    """``(rung, caught_up)``: the rung a worker solves a job with, chosen as `choice`, that waited
    `waited_s` in the queue. The governor's current rung when it stepped down since (the cheaper way
    now); its cheapest rung when the job waited longer than a solve may take (``caught_up``): the
    queue backed up (a burst of frames, a stall) and drains that way before it overflows. A temporal
    rung is its own catch-up (its cost is within the budget by choice, so the queue drains at its
    pace): a caught-up temporal job only stops waiting for its predecessor's result."""
    if choice is None:
        return gov.rungs[0], False
    rung = choice.rung
    if rung in gov.rungs and gov.index > choice.index:
        rung = gov.rungs[gov.index]
    if gov.enabled and rung is not gov.rungs[-1] and waited_s > gov.budget_s:
        return (rung if rung.temporal else gov.rungs[-1]), True
    return rung, False


def order_for(rung, order: KernelOrder, caught_up: bool) -> KernelOrder:
    """The kernel order a worker renders: the scheduler's, or one kernel for a caught-up job on the
    half-resolution rung (the queue drains at that rung's cheapest cost, not over the grid chosen
    for the rung the job was scheduled to)."""
    if caught_up and rung.half and order.deblur.mode != "uniform":
        return dataclasses.replace(order, deblur=dataclasses.replace(order.deblur, mode="uniform"))
    return order


def default_workers() -> int:
    """One worker per usable core: the affinity, capped by a CPU quota (a cgroup's, systemd's
    ``CPUQuota=``; `thermod.runtime.cpu.usable_cpus`)."""
    return usable_cpus()


def _picklable(obj) -> bool:
    try:
        pickle.dumps(obj)
    except Exception:
        return False
    return True


def single_method(rung) -> str:
    """The name a rung's frame solved without a prior is published under (its own solve's method)."""
    return rung.method if rung.temporal else rung.name


# ------------------------------------------------------------------------------- pipeline
class Pipeline:
    """Scheduler thread + deconvolution workers between the rings and an output callback.

    Parameters
    ----------
    gyro_ring, frame_ring : the rings the driver threads write.
    calib, deblur, cfg : calibration, deblur and pipeline settings (`update` swaps the first two live).
    emit : called once per frame with a `FrameOut`, in frame order, from a pipeline thread. Must not
        block (e.g. `Publisher.publish_frame(..., copy=False)`).
    deconvolver_factory : DeblurConfig → object with ``run(image, kernel)`` / ``run_varying(image,
        grid)`` (default `thermod.physics.deconv.Deconvolver`), one per worker thread.
    renderer : same signature as `render` (default), the seam for the kernel renderer (run by the
        workers, in their child processes: it must pickle there).
    kernels : keep each deblurred frame's kernel, packed for the wire, in `FrameOut.kernel`; a callable
        is asked at each job (the daemon's: while a subscriber subscribes to the kernel topic).
    """

    def __init__(self, gyro_ring: GyroRing, frame_ring: FrameRing, calib: Calibration, deblur: DeblurConfig,
                 cfg: PipelineConfig, emit: Callable[[FrameOut], None], *,
                 deconvolver_factory: Callable | None = None, renderer: Callable | None = None,
                 kernels: bool | Callable[[], bool] = True):
        self.gyro_ring, self.frame_ring, self.cfg, self.emit = gyro_ring, frame_ring, cfg, emit
        if min(calib.width, calib.height) < MIN_FRAME_PX:
            raise ConfigError(f"calibration.width/height: the live rungs need frames of at least "
                              f"{MIN_FRAME_PX}×{MIN_FRAME_PX} px (a half-resolution solve, a temporal "
                              f"warp's support), got {calib.width}×{calib.height}; `thermod deblur` "
                              "takes smaller ones")
        self._settings = _Settings(calib, deblur.within_frame(calib.width, calib.height), 0)
        self._process_settings = None   # (BLAS thread limits, GIL switch interval) to restore at stop
        self._factory = deconvolver_factory or make_deconvolver
        self._render = renderer or render
        self._kernels = kernels if callable(kernels) else (lambda keep=bool(kernels): keep)
        self.n_workers = cfg.workers or default_workers()
        self.gyro_online = True           # the daemon clears this while the gyro device is down
        # when the gyro reader last delivered samples (host monotonic), set by the daemon: read by
        # `_wait_for_gyro` to tell a reader that has not run from samples that are missing
        self.gyro_delivered: Callable[[], float] | None = None
        # a static overlay burnt into the frames, as (mask, grown mask) or None, set by the daemon when
        # its gyro source finds one (the video source): kept out of the solve (`thermod.restore.overlay`)
        self.overlay: Callable[[], tuple | None] | None = None
        self._stop = threading.Event()
        self._jobs: collections.deque[_Job] = collections.deque()
        self._jobs_cond = threading.Condition()
        self._out_lock = threading.Lock()
        self._pending: dict[int, tuple[FrameOut, float]] = {}
        self._overrun_at: dict[int, int] = {}    # ring index → frames overwritten just before it
        self._next_out = 0
        self._scheduler: threading.Thread | None = None
        self._workers: list[threading.Thread | None] = []
        self._worker_busy_since: list[float | None] = []
        self._next_index = 0
        self.heartbeat: dict[str, float] = {}
        self._latencies = collections.deque(maxlen=2048)
        self._lat_lock = threading.Lock()
        self.counters = collections.Counter()
        self._count_lock = threading.Lock()
        self.stage_times = StageTimes()   # wall time per stage, for health (`thermod.runtime.cpu`)
        self.settling = Settling(time.monotonic())   # replaced at `start`: health's ``warming_up``
        self._solvers: list = []        # per worker: InThread or InChild (`thermod.runtime.solvers`)
        self._frames: SharedFrames | None = None   # process mode: the frames shared with the children
        self._est_cond = threading.Condition()
        self._estimates: collections.OrderedDict = collections.OrderedDict()   # index → Estimate
        self._solving: set[int] = set()           # indices a worker is solving temporally now
        self._overload_drops: collections.deque = collections.deque(maxlen=SHORT_OF_CPU_DROPS)  # when
        self._in_ffc = False              # scheduler thread only: the last frame was flagged ffc
        self._ffc_last_t: float | None = None   # read time of the last frame flagged ffc
        self.governor = self._new_governor(calib, deblur)

    def _new_governor(self, calib: Calibration, deblur: DeblurConfig) -> Governor:
        return Governor(deblur, calib.frame_rate_hz, self.n_workers, calib.width / calib.height)

    # ------------------------------------------------------------------ lifecycle
    def warmup(self, max_kernel_px: int = 64, budget_s: float = 30.0,
               abort: threading.Event | None = None) -> float:
        """Start the workers' solvers (`cfg.processes`: a child process each) and build them, one per
        rung of the governor's ladder, before the first frame: the numba renderer compiled, LUTs, the
        FFT plans of every padded shape a kernel up to `max_kernel_px` can need (plans are per padded
        shape; building one mid-stream costs a frame or ten), and the governor's reference cost of
        each rung, uniform and over every grid the adaptive mode can render (the finest and its
        coarser ones: their tiles' plans are built too), timed on the first worker once every worker's
        plans are built, through the call the stream's jobs use (a child's round trip included: what
        the governor is given in the stream). A temporal rung is timed with a prior (the frame before,
        restored, warped across one frame period of roll): its cost is the one it has in the stream.
        The children warm up together. Returns seconds spent.

        A set `abort` (the daemon's stop) ends the warm-up within `solvers.POLL_S`: the children are
        killed (mid-warm-up they cannot hear "stop") and `StopRequested` is raised. Solving in
        threads, the solver being built finishes first."""
        t0 = time.monotonic()
        try:
            self._warmup(max_kernel_px, budget_s, abort)
        except StopRequested:
            self._close_solvers(timeout=0.0)
            raise
        finally:
            for solver in self._solvers:     # the stream's stop lets a child finish its frame
                if isinstance(solver, InChild):
                    solver.abort = None
        return time.monotonic() - t0

    def _warmup(self, max_kernel_px: int, budget_s: float, abort: threading.Event | None) -> None:
        def check() -> None:
            StopRequested.check(abort, "during the warm-up")

        t0 = time.monotonic()
        self._set_process_limits()
        s = self._settings
        gov = self.governor
        tg, rate = warm_gyro(s.calib)
        # a frame like a camera's (structure and noise): the solvers' costs depend on the content (a flat
        # frame's robust range and spectra come cheap), and the governor lives on their ratios
        h, w_px = self.frame_ring.shape
        yy, xx = np.mgrid[:h, :w_px]
        img = (8000.0 + 200.0 * np.sin(xx / 7.0) * np.cos(yy / 11.0)
               + np.random.default_rng(0).normal(0.0, 10.0, (h, w_px))).astype(np.float32)
        # the scheduler's grid choice runs here, in this process: its compiled code loaded now
        grids_within(tg, rate, s.calib, 0.0, s.deblur, (s.deblur.grid_tol_px, s.deblur.temporal_tol_px))
        check()
        orders = [KernelOrder(0.0, tg, rate, dataclasses.replace(s.deblur, mode="uniform"))]
        if any(r.varying for r in gov.rungs) and s.deblur.mode != "uniform":
            for g in coarser_grids(tuple(s.deblur.grid), s.calib.width / s.calib.height)[:-1]:
                orders.append(KernelOrder(0.0, tg, rate, dataclasses.replace(s.deblur, mode="grid", grid=g)))
        self._start_solvers(abort)
        left = max(0.0, budget_s - (time.monotonic() - t0))

        def warm(solver):
            solver.warm(s, gov.rungs, img, orders[0], orders[1:], max_kernel_px=max_kernel_px, budget_s=left)

        if isinstance(self._solvers[0], InChild):     # each child on its own core: together
            with ThreadPoolExecutor(len(self._solvers), thread_name_prefix="thermod-warm") as pool:
                list(pool.map(warm, self._solvers))
        else:
            for solver in self._solvers:
                check()
                warm(solver)
        check()
        # timed as the stream's jobs are (the render, the solve, and a child's round trip), on the first
        # worker, alone
        for fam, cells, compute_s, overhead_s in rung_costs(self._solvers[0], s, gov.rungs, img, orders[0],
                                                            orders[1:]):
            gov.seed(fam, cells, compute_s, overhead_s)

    def _set_process_limits(self) -> None:
        """One thread per solve (the workers are the parallelism), and a short GIL switch interval:
        a worker returning from a GIL-free section (FFTW, numba, OpenCV: most of a solve) waits for
        the GIL until the thread holding it reaches the switch interval (CPython's: 5 ms)."""
        if self._process_settings is None:
            self._process_settings = (limit_threads(), sys.getswitchinterval())
            sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)

    def _start_solvers(self, abort: threading.Event | None = None) -> None:
        """Each worker's solvers: a child process each when `cfg.processes` (threads when the children
        cannot start, e.g. no memfd under a seccomp filter: said in the log), else in-thread. `abort`:
        see `warmup`."""
        if self._solvers:
            return
        n = self.n_workers
        if self.cfg.processes and not (_picklable(self._factory) and _picklable(self._render)):
            log.info("the deconvolver factory %r or the renderer %r cannot go to a child process; solving in "
                     "the worker threads", self._factory, self._render)
        elif self.cfg.processes:
            try:
                probe = self._factory(self._settings.deblur)
                shape = tuple(self.frame_ring.shape)
                info = probe.padded_shape(shape, shape) if hasattr(probe, "padded_shape") else shape
                layout = Layout(shape, n, slots_needed(n, PRIOR_FRAMES), info[0] * (info[1] // 2 + 1))
                self._frames = SharedFrames(layout)
                self._solvers = start_children(self._factory, self._frames, n, self._render, abort=abort)
                return
            except (OSError, SolverError) as e:
                if self._frames is not None:
                    self._frames.close()
                    self._frames = None
                # a child killed by the stop's signal
                StopRequested.check(abort, "while the solver children started")
                log.warning("solver processes unavailable (%s); solving in the worker threads", e)
        self._solvers = [InThread(self._factory, self._render) for _ in range(n)]

    def _solver_at(self, i: int):
        """Worker i's solvers; a child that died is replaced (a fresh interpreter: ~1 s)."""
        solver = self._solvers[i]
        if isinstance(solver, InChild) and not solver.alive:
            self._count("solver_children_replaced", 1)
            log.warning("solver child %d died (exit code %s); starting a new one", i, solver.proc.exitcode)
            solver.close()
            solver = self._solvers[i] = InChild(self._factory, self._frames, i)
        return solver

    def start(self, start_index: int | None = None) -> Pipeline:
        self._set_process_limits()
        self._start_solvers()
        self._stop.clear()
        self._next_index = self._next_out = self.frame_ring.head if start_index is None else start_index
        self._workers = [None] * self.n_workers
        self._worker_busy_since = [None] * self.n_workers
        for i in range(self.n_workers):
            self._spawn_worker(i)
        self.settling = Settling(time.monotonic())
        self._scheduler = threading.Thread(target=self._schedule_loop, name="thermod-scheduler", daemon=True)
        self._scheduler.start()
        return self

    def stop(self, timeout: float = 1.0) -> None:
        """Stop accepting frames, let workers finish their current job, release what is left."""
        self._stop.set()
        with self._jobs_cond:
            self._jobs_cond.notify_all()
        deadline = time.monotonic() + timeout
        for th in [self._scheduler, *self._workers]:
            if th is not None:
                th.join(max(0.0, deadline - time.monotonic()))
        # jobs still queued were received: publish them passed through rather than lose them
        with self._jobs_cond:
            left = list(self._jobs)
            self._jobs.clear()
        for job in left:
            self._count("shutdown_passthrough", 1)
            self._passthrough(job.slot, "overload", job.order.info)
        self._flush_pending(force=True)
        self._close_solvers()
        if self._process_settings is not None:     # the process may go on (tests, an embedding app)
            blas_limits, switch_interval = self._process_settings
            blas_limits.restore_original_limits()
            sys.setswitchinterval(switch_interval)
            self._process_settings = None

    def _close_solvers(self, timeout: float = 0.5) -> None:
        if any(th is not None and th.is_alive() for th in self._workers):
            return        # a worker still solving past stop's timeout: its daemon thread ends with us
        with self._est_cond:
            self._estimates.clear()
        close_all(self._solvers, timeout=timeout)
        self._solvers = []
        if self._frames is not None:
            self._frames.close()
            self._frames = None

    def update(self, calib: Calibration | None = None, deblur: DeblurConfig | None = None) -> None:
        """Swap calibration / deblur settings (SIGHUP). Frames in flight finish with the old ones;
        workers rebuild their deconvolver when the deblur settings change."""
        s = self._settings
        calib = calib or s.calib
        deblur = (deblur or s.deblur).within_frame(calib.width, calib.height)
        self._settings = new = _Settings(calib, deblur, s.generation + 1)
        if new.deblur != s.deblur or new.calib.frame_rate_hz != s.calib.frame_rate_hz:
            gov = self._new_governor(new.calib, new.deblur)
            gov.inherit(self.governor)
            self.governor = gov
        self._count("reloads", 1)

    @property
    def calib(self) -> Calibration:
        return self._settings.calib

    @property
    def deblur(self) -> DeblurConfig:
        return self._settings.deblur

    def alive(self) -> dict[str, bool]:
        """Which pipeline threads are running (for the watchdog)."""
        out = {"scheduler": self._scheduler is not None and self._scheduler.is_alive()}
        for i, th in enumerate(self._workers):
            out[f"worker{i}"] = th is not None and th.is_alive()
        return out

    def supervise(self) -> int:
        """Replace dead worker threads; returns how many were restarted."""
        n = 0
        if self._stop.is_set():
            return 0
        for i, th in enumerate(self._workers):
            if th is None or not th.is_alive():
                self._count("workers_replaced", 1)
                log.warning("deconvolution worker %d died; starting a new one", i)
                self._spawn_worker(i)
                n += 1
        return n

    # ------------------------------------------------------------------ scheduler
    def _schedule_loop(self) -> None:
        i = self._next_index
        last_id = None            # the frame id of the last frame read
        while not self._stop.is_set():
            self.heartbeat["scheduler"] = time.monotonic()
            self.supervise()
            self._flush_pending()
            got = self.frame_ring.get(i, timeout=0.1)
            if got is None:
                continue
            if isinstance(got, int):   # overwritten before we read them: never seen, count them
                lost = got - i
                self._count("frames_overrun", lost)
                self._overrun_at[got] = self._overrun_at.get(got, 0) + lost   # said in its header
                log.warning("scheduler fell behind: %d frames overwritten in the frame ring", lost)
                self._skip_outputs(i, got)
                i = got
                continue
            if got.index in self._overrun_at and last_id is not None:
                # an overwritten frame's own camera losses (its gap_before) went with it: the frame ids
                # say how many frames in all are missing before this one
                unseen = got.frame_id - last_id - 1 - got.gap_before - self._overrun_at[got.index]
                if unseen > 0:
                    self._count("frames_overrun", unseen)
                    self._overrun_at[got.index] += unseen
            last_id = got.frame_id
            try:
                self._schedule(got)
            except Exception:            # never let one frame kill the scheduler
                log.exception("scheduler failed on frame %d; passing it through", got.frame_id)
                self._passthrough(got, "kernel_error", {})
            i += 1
            self._next_index = i

    def _schedule(self, slot: FrameSlot) -> None:
        s = self._settings
        self._count("frames_in", 1)
        if slot.gap_before:
            self._count("camera_frames_lost", slot.gap_before)
        early = refused_early(s.deblur, self._ffc_hold(slot, s))
        if early is not None:
            self._passthrough(slot, early.reason, {})
            return
        g0, g1, margin = gyro_span(s.calib, s.deblur, slot.t)
        t_wait = time.monotonic()
        if self.gyro_online:
            self._wait_for_gyro(g1, slot)
        t_render = time.monotonic()
        w = self.gyro_ring.window(g0 - margin, g1 + margin, pad=2)
        if s.calib.gyro_range_rad_s > 0 and len(w) and np.any(np.abs(w.rate) >= s.calib.gyro_range_rad_s
                                                              * (1 - CLIP_TOL)):
            self._count("frames_gyro_clipped", 1)   # continued by the calibration: flagged, not dropped
        chosen = []

        def choose(needed, floor):
            now = time.monotonic()
            # since its arrival, on the host clock: a replay's frame times keep its recording's pace
            chosen.append(self.governor.choose(needed, now, floor, age_s=now - slot.arrival))
            return chosen[-1].grid

        order = order_kernel(slot.t, w.t, w.rate, s.calib, s.deblur, gap=w.gap, online=self.gyro_online,
                             first_gyro_t=w.oldest_t, choose=choose)
        if isinstance(order, PassThrough):
            self._refused(slot, order)
            return
        choice = chosen[-1]
        warp_gyro = None
        if any(r.temporal for r in self.governor.rungs):
            # the warp from a prior up to MAX_AGE_S old: rows read from t − MAX_AGE_S − readout on
            gw0 = float(s.calib.camera_time_to_gyro(np.array([slot.t - MAX_AGE_S - s.calib.readout_s]))[0])
            ww = self.gyro_ring.window(min(gw0, g0) - margin, g1 + margin, pad=2)
            if not ww.gap and len(ww) >= 2:
                warp_gyro = (ww.t, ww.rate)
            else:
                self._count("temporal_gyro_gap", 1)
        keep_out = self.overlay() if self.overlay is not None else None
        if keep_out is not None:
            self._count("overlay_kept", 1)
        now = time.monotonic()
        self._enqueue(_Job(slot, order, s.generation, choice, warp_gyro, t_queued=now,
                           arrival_s=t_wait - slot.t, gyro_wait_s=t_render - t_wait, render_s=now - t_render,
                           keep_out=keep_out))

    def _wait_for_gyro(self, g1: float, slot: FrameSlot) -> None:
        """Wait until the gyro ring covers gyro time `g1`, at most until ``max(t, arrival) +
        wait_timeout_s``; then, while the reader has delivered nothing since the frame came, up to
        `STARVED_WAIT_S` more: its silence says the reader has not run, not that samples are missing
        (a loaded payload starves a thread for tens of ms: the frame waits, and is deblurred)."""
        deadline = max(slot.t, slot.arrival) + self.cfg.wait_timeout_s
        if self.gyro_ring.wait_until(g1, deadline - time.monotonic()) or self.gyro_delivered is None:
            return
        cap = deadline + STARVED_WAIT_S
        covered = False
        while not covered and self.gyro_delivered() < slot.arrival and (left := cap - time.monotonic()) > 0:
            covered = self.gyro_ring.wait_until(g1, min(left, 0.005))
        # a delivery is stamped before its samples reach the ring: give the writer that moment
        if covered or self.gyro_ring.wait_until(g1, 0.005):
            self._count("gyro_late_waits", 1)

    def _refused(self, slot: FrameSlot, refusal: PassThrough) -> None:
        """A frame the policy passes through (before its kernel, or on it)."""
        if refusal.reason == "kernel_error":
            self._count("kernel_errors", 1)
            log.error("kernel rendering failed for frame %d: %s", slot.frame_id, refusal.detail)
        self._passthrough(slot, refusal.reason, refusal.info)

    def _ffc_hold(self, slot: FrameSlot, s: _Settings) -> bool:
        """Whether a frame must pass through because of a flat-field correction (FFC).

        During an FFC the camera repeats a frozen frame (or shows its shutter) and then steps to a new
        NUC: the detector state is not the IIR model's (Eq. 10) over that stretch, so no kernel may
        span it. A frame is held when the camera flags it, when its kernel window
        (t − m·τ − readout, t] reaches back to the last flagged frame, or when it was read less than
        ``ffc_settle_s`` (default m·τ) after that frame. Frames arrive in order (one scheduler thread).
        """
        if slot.ffc:
            if not self._in_ffc:
                self._in_ffc = True
                self._count("ffc_events", 1)
            self._ffc_last_t = slot.t
            return True
        self._in_ffc = False
        if self._ffc_last_t is None:
            return False
        settle = s.deblur.ffc_settle_s if s.deblur.ffc_settle_s is not None else s.deblur.m * s.calib.tau_s
        window_start, _ = kernel_window(s.calib, s.deblur, slot.t)
        return window_start <= self._ffc_last_t or slot.t - self._ffc_last_t < settle

    def _enqueue(self, job: _Job) -> None:
        dropped = None
        with self._jobs_cond:
            if len(self._jobs) >= self.cfg.job_queue:
                dropped = self._jobs.popleft()
            self._jobs.append(job)
            self._jobs_cond.notify()
        if dropped is not None:
            self._overload_drops.append(time.monotonic())
            self._count("jobs_dropped", 1)
            self.governor.overloaded(time.monotonic())
            self._passthrough(dropped.slot, "overload", dropped.order.info)

    # ------------------------------------------------------------------ workers
    def _spawn_worker(self, i: int) -> None:
        th = threading.Thread(target=self._work_loop, args=(i,), name=f"thermod-deconv{i}", daemon=True)
        self._workers[i] = th
        th.start()

    def _prior_for(self, index: int, wait_s: float):
        """The newest restored frame before `index` (within `PRIOR_FRAMES`), waiting up to `wait_s`
        for index − 1 while a worker is solving it temporally; None when there is none."""
        deadline = time.monotonic() + wait_s
        with self._est_cond:
            while index - 1 in self._solving and index - 1 not in self._estimates:
                left = deadline - time.monotonic()
                if left <= 0:
                    self._count("temporal_prior_wait_timeouts", 1)
                    break
                self._est_cond.wait(left)
            for j in range(index - 1, index - 1 - PRIOR_FRAMES, -1):
                est = self._estimates.get(j)
                if est is not None:
                    return est
        return None

    def _keep_estimate(self, index: int, est) -> None:
        """Keep a restored frame as a prior (the newest `PRIOR_FRAMES`); one dropped gives its shared
        slot back (process mode)."""
        dropped = []
        with self._est_cond:
            if est is not None:
                self._estimates[index] = est
                while len(self._estimates) > PRIOR_FRAMES:
                    dropped.append(self._estimates.popitem(last=False)[1])
            self._solving.discard(index)
            self._est_cond.notify_all()
        for e in dropped:
            if hasattr(e, "release"):
                e.release()

    def _work_loop(self, i: int) -> None:
        name = f"worker{i}"
        try:
            solver = self._solver_at(i)
        except (OSError, SolverError):
            self._count("worker_errors", 1)
            log.exception("worker %d: its solver process would not start", i)
            time.sleep(1.0)       # supervise() tries again: not in a tight loop
            return
        while not self._stop.is_set():
            self.heartbeat[name] = time.monotonic()
            with self._jobs_cond:
                if not self._jobs:
                    self._jobs_cond.wait(0.1)
                if not self._jobs:
                    continue
                job = self._jobs.popleft()
            t_start = time.monotonic()
            index = job.slot.index
            self._worker_busy_since[i] = time.monotonic()
            est = None
            try:
                s = self._settings
                gov = self.governor
                rung, caught_up = rung_for(gov, job.choice, time.monotonic() - job.t_queued)
                if rung.temporal:         # only a temporal solve leaves a prior worth waiting for
                    with self._est_cond:
                        self._solving.add(index)
                if caught_up:
                    self._count("catch_up", 1)
                wait_s = 0.0 if caught_up else 0.5 * gov.budget_s
                order = order_for(rung, job.order, caught_up)
                got = solver.solve(s, rung, job.slot.image, order, job.slot.t, job.warp_gyro,
                                   lambda index=index, wait_s=wait_s: self._prior_for(index, wait_s),
                                   pack=self._kernels(), keep_out=job.keep_out)
                if got.passthrough is not None:        # the kernel's coverage rule, or no kernel
                    self._job_done(i, index, None)
                    self.stage_times.add(arrival=job.arrival_s, gyro_wait=job.gyro_wait_s,
                                         render=job.render_s + got.render_s, queue=t_start - job.t_queued)
                    self._refused(job.slot, got.passthrough)
                    continue
                est = got.estimate
                if got.start_partial:
                    self._count("start_partial_kernels", 1)
                method, prior_frames, grid = rung.name, got.prior_frames, got.grid
                if rung.temporal:
                    if prior_frames == 0:
                        method = single_method(rung)
                        self._count("temporal_alone", 1)
                    else:
                        self._count(f"temporal_prior_{prior_frames}", 1)
                t_end = time.monotonic()
                gov.observe(gov.family(rung), grid[0] * grid[1], got.compute_s, t_end, got.overhead_s)
                self.stage_times.add(arrival=job.arrival_s, gyro_wait=job.gyro_wait_s,
                                     render=job.render_s + got.render_s,
                                     queue=t_start - job.t_queued, solve=got.seconds - got.render_s,
                                     prior_wait=t_end - t_start - got.seconds)
                out = got.image
                if out.shape != job.slot.image.shape:
                    raise ValueError(f"deconvolver returned shape {out.shape} for a "
                                     f"{job.slot.image.shape} frame")
            except Exception:
                if est is not None and hasattr(est, "release"):
                    est.release()
                self._keep_estimate(index, None)       # the next frame solves alone, now
                self._count("worker_errors", 1)
                log.exception("deconvolution failed on frame %d; passing it through and replacing the worker",
                              job.slot.frame_id)
                solver.reset()
                self._worker_busy_since[i] = None      # busy until its solver is replaced
                self._passthrough(job.slot, "worker_error", job.order.info)
                return            # this thread ends; supervise() starts a fresh one (fresh state)
            self._job_done(i, index, est)
            self._count("deblurred", 1)
            self._count(f"method_{method}", 1)
            o = self._out(job.slot, out, True, None, {**job.order.info, **got.info}, got.kernel)
            o.method = method
            o.prior_frames = prior_frames
            o.grid = grid
            self._complete(o)

    def _job_done(self, worker: int, index: int, estimate) -> None:
        """Worker `worker` is free again; frame `index` leaves `estimate` (None: no prior) to the next."""
        self._keep_estimate(index, estimate)
        self._worker_busy_since[worker] = None

    # ------------------------------------------------------------------ output (in order)
    def _out(self, slot: FrameSlot, image, deblurred: bool, reason: str | None, info: dict,
             kernel=None) -> FrameOut:
        return FrameOut(index=slot.index, image=image, t=slot.t, frame_id=slot.frame_id, arrival=slot.arrival,
                        deblurred=deblurred, reason=reason, kernel_size=info.get("kernel_size"),
                        kernel_extent_px=info.get("kernel_extent_px"), coverage=info.get("coverage"),
                        n_samples=int(info.get("n_samples", 0)), camera_gap_before=slot.gap_before,
                        overrun_before=self._overrun_at.pop(slot.index, 0), kernel=kernel)

    def _passthrough(self, slot: FrameSlot, reason: str, info: dict) -> None:
        self._count(f"passthrough_{reason}", 1)
        self._complete(self._out(slot, slot.image.astype(np.float32), False, reason, info))

    def _skip_outputs(self, a: int, b: int) -> None:
        with self._out_lock:
            if self._next_out == a:
                self._next_out = b
        self._flush_pending()

    def _complete(self, out: FrameOut) -> None:
        with self._out_lock:
            self._pending[out.index] = (out, time.monotonic())
        self._flush_pending()

    def _flush_pending(self, force: bool = False) -> None:
        ready: list[tuple[FrameOut, float]] = []    # (frame, when it was complete)
        with self._out_lock:
            now = time.monotonic()
            while self._pending:
                if self._next_out in self._pending:
                    ready.append(self._pending.pop(self._next_out))
                    self._next_out += 1
                    continue
                oldest = min(self._pending)
                if oldest < self._next_out:     # a late frame already skipped: release it now
                    ready.append(self._pending.pop(oldest))
                    self._count("released_out_of_order", 1)
                    continue
                waited = now - self._pending[oldest][1]
                if force or waited > self.cfg.reorder_timeout_s:
                    self._count("reorder_skips", 1)
                    self._next_out = oldest
                    continue
                break
            for o, t_complete in ready:
                o.t_done = time.monotonic()
                try:
                    self.emit(o)
                except Exception:
                    self._count("emit_errors", 1)
                    log.exception("output callback failed for frame %d", o.frame_id)
                self.stage_times.add(reorder=o.t_done - t_complete, publish=time.monotonic() - o.t_done)
                self._count("frames_out", 1)
                with self._lat_lock:
                    self._latencies.append(o.latency_s)
                if o.method is not None and not self.settling.state(o.t_done)["warming_up"]:
                    self.governor.released(o.latency_s, o.t_done)   # the tail after the start-up
                self.settling.add(o.t_done, o.latency_s)

    # ------------------------------------------------------------------ health
    def _count(self, key: str, n: int = 1) -> None:
        # workers, scheduler and the daemon's thread bump the same counters: += alone can lose counts
        with self._count_lock:
            self.counters[key] += n

    def stats(self) -> dict:
        with self._lat_lock:
            lat = np.array(self._latencies, dtype=np.float64)
        with self._count_lock:
            counters = dict(self.counters)
        with self._jobs_cond:
            depth = len(self._jobs)
        now = time.monotonic()
        busy = [now - b for b in self._worker_busy_since if b is not None]
        return {
            "counters": counters,
            "job_queue_depth": depth,
            "pending_reorder": len(self._pending),
            "frames_behind": self.frame_ring.head - self._next_index,
            "workers": self.n_workers,
            "workers_alive": sum(1 for th in self._workers if th is not None and th.is_alive()),
            "latency_p50_s": float(np.percentile(lat, 50)) if len(lat) else None,
            "latency_p99_s": float(np.percentile(lat, 99)) if len(lat) else None,
            "worker_busy_max_s": max(busy) if busy else 0.0,
            "governor": self.governor.state(),
            "stage_ms": self.stage_times.summary(),
            **self.settling.state(now),
        }

    def short_of_cpu(self, hold_s: float = SHORT_OF_CPU_S) -> bool:
        """Whether `SHORT_OF_CPU_DROPS` jobs were dropped for overload within `hold_s`: work that can
        wait (the calibration monitor) gives way meanwhile."""
        drops = self._overload_drops
        return len(drops) == drops.maxlen and time.monotonic() - drops[0] < hold_s

    def solver_pids(self) -> list[int]:
        """The solver children's process ids (empty when solving in threads)."""
        return [s.proc.pid for s in self._solvers if isinstance(s, InChild) and s.proc.pid]
