"""A deconvolution worker's solvers: in the worker's own thread, or in a child process of its own.

Why a child process: a solve is mostly GIL-free (FFTW, numba, OpenCV) but takes the GIL back dozens
of times between those calls, and beside the daemon's other threads each return waits for the
holder's switch interval; in a child the solve has a GIL of its own (docs/design.md §6, "Workers";
the measurement: `benchmarks/bench_gil.py`, benchmarks/results/daemon.md).

Data path (process mode): the pipeline owns one `SharedFrames` block (a memfd mapped by the parent
and every child): one input frame per worker and a pool of output slots, each an image and the
spectrum of a temporal `Estimate`. A job sends only its `KernelOrder` (the gyro window and the grid
chosen) through the pipe: the child renders the kernel (beside the other worker's solve, not in the
scheduler; a grid's cells are not pickled) and writes its result into the slot the parent gave it,
returning the kernel packed for the wire (`thermod.io.wire.pack_kernel`) when it is published. A
slot that holds an estimate stays reserved while the pipeline keeps it as a prior or a job on
another worker uses it (`SharedFrames.retain` / `release`). A temporal solve asks the parent for its
prior once its own x₀ is done (the ``prior`` round trip): the parent waits there for frame k − 1,
as a thread would.

`solve_job` and `warm_solvers` are the one implementation of a job and of the warm-up. `InThread`
runs them in the worker's thread and `InChild` in the child (`_child_main`). The pipeline sees
either through the same calls: ``warm``, ``solve``, ``reset`` and ``close``; `rung_costs` times
any of them through ``solve``, as the stream's jobs are timed.
"""

from __future__ import annotations

import dataclasses
import math
import mmap
import multiprocessing
import os
import signal
import threading
import time
import traceback
from dataclasses import dataclass, field
from multiprocessing.reduction import recv_handle, send_handle

import numpy as np

from thermod.errors import StopRequested
from thermod.io.wire import pack_kernel
from thermod.physics.deconv.half import HalfResolution
from thermod.physics.deconv.recursive import Estimate, RecursiveDeconvolver
from thermod.physics.deconv.tiles import central_cell
from thermod.restore import overlay
from thermod.restore.plan import render, solved_grid
from thermod.restore.policy import KernelOrder, PassThrough, render_order
from thermod.runtime.governor import Governor

CHILD_START_S = 60.0      # a child that has not answered its first message by then is given up
SOLVE_TIMEOUT_S = 10.0    # a child silent this long in a job is hung: killed (the worker replaces it)
POLL_S = 0.25             # how often a worker waiting on its child checks that the child lives


class SolverError(RuntimeError):
    """A child process failed a job (its traceback is the message) or went away."""


@dataclass
class Solved:
    """One job's result: the frame deblurred, or (`passthrough`) why its kernel refused it."""

    image: np.ndarray | None   # float32 counts, owned by the caller (None: passed through)
    estimate: object           # the next frame's prior (`Estimate` or `SharedEstimate`), or None
    prior_frames: int          # frames between the prior used and this frame (0: solved alone)
    seconds: float             # the solve's wall time (its render included), the wait for the prior left out
    grid: tuple[int, int]      # the kernel grid it was solved with ((1, 1): one kernel)
    compute_s: float = math.nan   # of `seconds`, the solve itself (a child's own clock; the rest is the
                                  # round trip: frame copies, pipe, the parent's GIL)
    render_s: float = 0.0      # of `compute_s`, the kernel's render
    info: dict = field(default_factory=dict)   # the render's (kernel_size, extent, coverage, n_samples)
    kernel: tuple | None = None   # the kernel solved with, packed for the wire (`pack_kernel`), if asked
    start_partial: bool = False   # deblurred under the stream's start rule (`START_COVERAGE`)
    passthrough: PassThrough | None = None   # the kernel's rules refused the frame (not solved)

    @property
    def overhead_s(self) -> float:
        """The round trip's share of `seconds` (0 in the worker's own thread)."""
        return max(0.0, self.seconds - self.compute_s) if math.isfinite(self.compute_s) else 0.0


@dataclass
class _Timed:
    """The prior callable with its wait measured (the wait is not solve cost)."""

    fetch: object
    waited: float = 0.0

    def __call__(self):
        t0 = time.perf_counter()
        try:
            return self.fetch()
        finally:
            self.waited += time.perf_counter() - t0


def _kept(got: Solved, image, keep_out) -> Solved:
    """`got` with a static overlay's pixels (`keep_out[0]`) taken back from the input `image`."""
    if keep_out is None or got.image is None:
        return got
    return dataclasses.replace(got, image=overlay.keep(got.image, image, keep_out[0]))


def make_solver(factory, rung, deblur, calib):
    """A worker's solver for `rung`: the factory's deconvolver, wrapped in a `RecursiveDeconvolver`
    for a temporal rung."""
    d = factory(rung.deblur(deblur))
    if rung.temporal:
        return RecursiveDeconvolver(calib, d, min_coverage=deblur.min_coverage)
    if getattr(rung, "half", False):
        return HalfResolution(d)
    return d


def solve_job(decs: dict, factory, rung, deblur, calib, img, kernel, t_frame, warp_gyro, prior, *,
              renderer=render, pack: bool = False, fill_mask: np.ndarray | None = None) -> Solved:
    """Solve one frame by `rung` with the solvers in `decs` (one per family, built on first use).
    `fill_mask` (uint8, `thermod.restore.overlay.grown`): a static overlay, inpainted before the solve
    (the caller takes its pixels back from the input: the restored frame stays the next one's prior).
    `kernel`: a `KernelOrder`, rendered here by `renderer` under the policy's coverage rule
    (`render_order`; a refused frame comes back as `Solved.passthrough`), or a rendered kernel.
    `prior` (temporal rungs): a callable returning the newest restored frame before this one, or
    None; it is called after the frame's own solve and may wait. `pack`: return the kernel solved
    with, packed for the wire."""
    t0 = time.perf_counter()
    info, start_partial = {}, False
    if isinstance(kernel, KernelOrder):
        plan = render_order(kernel, calib, renderer)
        if isinstance(plan, PassThrough):
            seconds = time.perf_counter() - t0
            return Solved(None, None, 0, seconds, (1, 1), compute_s=seconds, render_s=seconds,
                          info=dict(plan.info), passthrough=PassThrough(plan.reason, plan.info, plan.detail))
        kernel, info, start_partial = plan.kernel, dict(plan.info), plan.start_partial
    render_s = time.perf_counter() - t0
    if fill_mask is not None:
        img = overlay.fill(img, fill_mask)
    fam = Governor.family(rung)
    deconv = decs.get(fam)
    if deconv is None:
        deconv = decs[fam] = make_solver(factory, rung, deblur, calib)
    timed = _Timed(prior)
    if rung.temporal:
        gt, gr = warp_gyro if warp_gyro is not None else (None, None)
        out, est = deconv.solve(img, kernel, t_frame, gt, gr, timed if gt is not None else None)
        prior_frames, solver = deconv.last_prior_frames, deconv.single
    else:
        out = deconv.run_varying(img, kernel) if hasattr(kernel, "kernels") else deconv.run(img, kernel)
        est, prior_frames, solver = None, 0, deconv
    seconds = time.perf_counter() - t0 - timed.waited
    out = np.asarray(out, np.float32)
    grid = solved_grid(solver, kernel)
    if hasattr(kernel, "kernels") and grid == (1, 1):
        # the deconvolver's uniform shortcut solved with the central cell: say so, kernel included
        r, c = central_cell(kernel.centers, out.shape)
        kernel = kernel.kernels[r][c]
        if info:
            info.update(kernel_size=tuple(int(s) for s in kernel.weights.shape),
                        kernel_extent_px=float(kernel.extent_px))
    return Solved(out, est, prior_frames, seconds, grid, compute_s=seconds, render_s=render_s, info=info,
                  kernel=pack_kernel(kernel) if pack else None, start_partial=start_partial)


@dataclass
class _WarmKernel:
    """A box kernel (duck-typed `thermod.physics.kernels.Kernel`) used only to build FFT plans."""

    weights: np.ndarray
    origin: tuple[int, int]


def warm_solvers(decs: dict, factory, rungs, deblur, calib, img, uniform, grids, *, max_kernel_px: int,
                 budget_s: float, renderer=render) -> None:
    """Render `uniform` and `grids` (`KernelOrder`s; the renderer's compiled code loaded here), build
    the solvers of every rung into `decs` and run each once on the uniform kernel and on each grid
    (a temporal rung with a prior: the frame before, restored, warped across one frame period),
    then build the FFT plans of every padded shape a kernel up to `max_kernel_px` can need, within
    `budget_s`. Plans are measured here (FFTW), not estimated mid-stream."""
    t_end = time.monotonic() + budget_s
    uniform, *grids = [renderer(o.gyro_t, o.gyro_rate, calib, o.t_frame, o.deblur)[0]
                       for o in [uniform, *grids]]
    period = 1.0 / calib.frame_rate_hz
    tg, rate = warm_gyro(calib)
    for rung in rungs:
        fam = Governor.family(rung)
        if fam in decs:
            continue
        d = decs[fam] = make_solver(factory, rung, deblur, calib)
        base = getattr(d, "single", d)
        planner = d if isinstance(d, HalfResolution) else base     # the sizes this rung solves at
        live = getattr(base, "realtime", False)
        base.realtime = False  # measure plans now, while no frame is waiting
        for k in [uniform, *(grids if rung.varying else [])]:
            if rung.temporal:
                _, first = d.solve(img, k, -period, tg, rate)
                d.solve(img, k, 0.0, tg, rate, first)
                if d.last_prior_frames != 1:
                    raise RuntimeError(f"warm-up: the {rung.name} rung found no prior")
            else:
                (d.run_varying if hasattr(k, "kernels") else d.run)(img, k)
        if hasattr(planner, "padded_shape"):
            sizes = {}
            for kh in range(1, max_kernel_px + 1, 2):
                for kw in range(1, max_kernel_px + 1, 2):
                    sizes.setdefault(tuple(planner.padded_shape(img.shape, (kh, kw))), (kh, kw))
            for kh, kw in sizes.values():
                if time.monotonic() > t_end:
                    break
                box = np.full((kh, kw), 1.0 / (kh * kw), np.float32)
                planner.run(img, _WarmKernel(box, (kh // 2, kw // 2)))
        base.realtime = live


def rung_costs(solver, settings, rungs, img, uniform, grids, repeats: int = 2) -> list[tuple]:
    """``[(family, cells, compute_s, overhead_s)]``: each rung's cost on `uniform` and on each of
    `grids`, timed through `solver.solve` as the stream's jobs are: the solve itself, and the round
    trip around it (in a child; 0 in a thread), from the fastest of `repeats` (a preempted run would
    make a rung look dearer than it is). A temporal rung
    is timed with a prior: the frame before, restored, warped across one frame period of roll."""
    period = 1.0 / settings.calib.frame_rate_hz
    gyro = warm_gyro(settings.calib)
    out = []
    for rung in rungs:
        fam = Governor.family(rung)
        for k in [uniform, *(grids if rung.varying else [])]:
            first = None
            if rung.temporal:
                first = solver.solve(settings, rung, img, k, -period, gyro, lambda: None).estimate
            try:
                runs = [solver.solve(settings, rung, img, k, 0.0, gyro, lambda first=first: first)
                        for _ in range(repeats)]
            finally:
                if first is not None and hasattr(first, "release"):
                    first.release()
            for r in runs:
                if r.estimate is not None and hasattr(r.estimate, "release"):
                    r.estimate.release()
            if rung.temporal and runs[0].prior_frames != 1:
                raise RuntimeError(f"warm-up: the {rung.name} rung found no prior")
            g = runs[0].grid                      # a coarse grid may be one kernel in disguise
            best = min(runs, key=lambda r: r.seconds)
            out.append((fam, g[0] * g[1], best.compute_s, best.overhead_s))
    return out


def warm_gyro(calib) -> tuple[np.ndarray, np.ndarray]:
    """Raw gyro samples of a roll (a grid of distinct kernels) around t = 0, for the warm-up."""
    tg = np.arange(-0.2, 0.05, 1.0 / calib.rate_hz)
    return tg, np.tile(np.float32([0.01, 0.2, 1.0]), (len(tg), 1))


def limit_threads():
    """One thread per solve, in this process (its BLAS limits returned, to restore). The workers are
    the parallelism: OpenCV's own thread pool (the temporal rung's remap and box
    filters) and BLAS's (small fits, whose spinning threads cost 6-10× the product on a loaded
    2-core host) would only oversubscribe the cores they share."""
    import cv2
    from threadpoolctl import threadpool_limits

    cv2.setNumThreads(1)
    return threadpool_limits(1)


# ------------------------------------------------------------------------------ in the thread
class InThread:
    """A worker's solvers in its own thread (one per worker; the process's GIL is shared)."""

    def __init__(self, factory, renderer=render):
        self.factory, self.renderer = factory, renderer
        self.decs: dict = {}
        self._generation = None

    def warm(self, settings, rungs, img, uniform, grids, *, max_kernel_px, budget_s) -> None:
        self._generation = (settings.deblur, settings.calib)
        warm_solvers(self.decs, self.factory, rungs, settings.deblur, settings.calib, img, uniform, grids,
                     max_kernel_px=max_kernel_px, budget_s=budget_s, renderer=self.renderer)

    def solve(self, settings, rung, image, kernel, t_frame, warp_gyro, prior, *,
              pack: bool = False, keep_out=None) -> Solved:
        if self._generation != (settings.deblur, settings.calib):
            self.decs, self._generation = {}, (settings.deblur, settings.calib)
        img = np.asarray(image, np.float32)
        got = solve_job(self.decs, self.factory, rung, settings.deblur, settings.calib, img, kernel, t_frame,
                        warp_gyro, prior, renderer=self.renderer, pack=pack,
                        fill_mask=None if keep_out is None else keep_out[1])
        return _kept(got, image, keep_out)

    def reset(self) -> None:
        """Forget the solvers (after a failed job: the next one starts from fresh state)."""
        self.decs, self._generation = {}, None

    def close(self) -> None:
        self.decs = {}


# ------------------------------------------------------------------------------ shared memory
@dataclass(frozen=True)
class Layout:
    """Where things are in the shared block (byte offsets; float32 arrays)."""

    shape: tuple[int, int]           # frame H, W
    workers: int
    slots: int
    info_capacity: int               # float32 values a slot's spectrum may hold

    @property
    def frame_bytes(self) -> int:
        return 4 * self.shape[0] * self.shape[1]

    @property
    def slot_bytes(self) -> int:
        return self.frame_bytes + 4 * self.info_capacity

    @property
    def size(self) -> int:
        return self.workers * self.frame_bytes + self.slots * self.slot_bytes

    def views(self, buf) -> tuple[list, list, list]:
        """(inputs, slot images, slot spectra (flat)) as float32 views on `buf`."""
        n = self.shape[0] * self.shape[1]
        inputs = [np.frombuffer(buf, np.float32, n, i * self.frame_bytes).reshape(self.shape)
                  for i in range(self.workers)]
        base = self.workers * self.frame_bytes
        images = [np.frombuffer(buf, np.float32, n, base + s * self.slot_bytes).reshape(self.shape)
                  for s in range(self.slots)]
        infos = [np.frombuffer(buf, np.float32, self.info_capacity,
                               base + s * self.slot_bytes + self.frame_bytes) for s in range(self.slots)]
        return inputs, images, infos


class SharedFrames:
    """The frames shared with the children: one input per worker, `slots` output slots with
    reference counts (a slot is free at zero). Linux memfd: nothing to clean up if the daemon dies."""

    def __init__(self, layout: Layout):
        self.layout = layout
        self.fd = os.memfd_create("thermod-frames", os.MFD_CLOEXEC)
        try:
            os.ftruncate(self.fd, layout.size)
            self._map = mmap.mmap(self.fd, layout.size)
        except OSError:
            os.close(self.fd)
            raise
        self.inputs, self.images, self.infos = layout.views(self._map)
        for v in (*self.inputs, *self.images, *self.infos):
            v.fill(0.0)          # every page touched now, not by a frame in flight (a fault each 4 kB)
        self._refs = [0] * layout.slots
        self._lock = threading.Lock()

    def acquire(self) -> int:
        """A free slot, reserved (count 1). The pool is sized so that one is always free
        (`slots_needed`); running out is a bug, said as such."""
        with self._lock:
            for s, n in enumerate(self._refs):
                if n == 0:
                    self._refs[s] = 1
                    return s
        raise SolverError(f"no free output slot among {self.layout.slots}: a slot was not released")

    def retain(self, slot: int) -> None:
        with self._lock:
            self._refs[slot] += 1

    def release(self, slot: int) -> None:
        with self._lock:
            if self._refs[slot] > 0:
                self._refs[slot] -= 1

    def in_use(self) -> int:
        with self._lock:
            return sum(1 for n in self._refs if n)

    def close(self) -> None:
        self.inputs = self.images = self.infos = []
        try:
            self._map.close()
        except BufferError:      # a view still exported (a frame in flight): the mapping goes with it
            pass
        os.close(self.fd)


def slots_needed(workers: int, kept: int) -> int:
    """Output slots for `workers` and `kept` estimates kept as priors: the kept ones, one being
    written per worker, and one lent per worker (a prior evicted while a job still reads it)."""
    return kept + 2 * workers + 1


@dataclass(eq=False)
class SharedEstimate:
    """A temporal `Estimate` held in a slot of `SharedFrames` (the parent's handle; `release` when it
    is no longer kept)."""

    frames: SharedFrames
    slot: int
    t_frame: float
    info_shape: tuple[int, int]
    shape: tuple[int, int]

    def release(self) -> None:
        self.frames.release(self.slot)

    def ref(self) -> tuple:
        """What the child needs to read it."""
        return (self.slot, self.t_frame, self.info_shape, self.shape)


# ------------------------------------------------------------------------------ in a child process
def _child_main(conn, factory, renderer=render) -> None:
    """A child's loop: map the shared frames, then serve ``warm``, ``solve`` and ``stop``.

    SIGTERM and SIGINT are ignored: systemd's stop and a terminal's Ctrl-C reach the whole process
    group, and the parent, stopping in order, finishes the frames in flight before it closes its
    children (``stop``, then a kill). A parent that dies leaves the pipe at EOF: the child ends."""
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        fd = recv_handle(conn)
        layout: Layout = conn.recv()
    except (EOFError, OSError):
        return                           # the parent went away while this interpreter started
    # mapped in full now (MAP_POPULATE): no page-table faults on a frame in flight
    buf = mmap.mmap(fd, layout.size, flags=mmap.MAP_SHARED | getattr(mmap, "MAP_POPULATE", 0))
    inputs, images, infos = layout.views(buf)
    limit_threads()
    decs: dict = {}
    deblur = calib = fill_mask = None

    def prior():
        conn.send(("prior",))
        ref = conn.recv()
        if ref is None:
            return None
        slot, t_frame, info_shape, shape = ref
        info = infos[slot][:info_shape[0] * info_shape[1]].reshape(info_shape)
        return Estimate(images[slot], t_frame, info, tuple(shape))

    try:
        conn.send(("ready", os.getpid()))
    except OSError:
        return                           # the parent went away
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return                       # the parent went away
        kind = msg[0]
        try:
            if kind == "stop":
                # nothing here to flush (the frames are the parent's); the interpreter's own teardown
                # (numba, FFTW) costs about 0.3 s that systemd's stop would wait for
                os._exit(0)
            if kind == "settings":
                _, deblur, calib = msg
                decs = {}
            elif kind == "overlay":
                fill_mask = None if msg[1] is None else np.unpackbits(msg[1], count=msg[2][0] * msg[2][1]
                                                                      ).reshape(msg[2])
            elif kind == "warm":
                _, rungs, img, uniform, grids, kw = msg
                warm_solvers(decs, factory, rungs, deblur, calib, img, uniform, grids, renderer=renderer,
                             **kw)
                conn.send(("warmed",))
            elif kind == "solve":
                _, rung, worker, slot, kernel, t_frame, warp_gyro, pack = msg
                got = solve_job(decs, factory, rung, deblur, calib, inputs[worker], kernel, t_frame,
                                warp_gyro, prior, renderer=renderer, pack=pack, fill_mask=fill_mask)
                if got.passthrough is not None:
                    p = got.passthrough
                    conn.send(("passed", p.reason, p.info, p.detail, got.seconds))
                    continue
                images[slot][...] = got.image
                est = None
                if got.estimate is not None and got.estimate.info.size <= layout.info_capacity:
                    info = got.estimate.info
                    infos[slot][:info.size] = info.ravel()
                    est = (float(got.estimate.t_frame), tuple(info.shape), tuple(got.estimate.shape))
                conn.send(("done", got.prior_frames, got.seconds, tuple(got.grid), est, got.render_s,
                           got.info, got.kernel, got.start_partial))
        except Exception:
            decs = {}                    # the next job starts from fresh state
            try:
                conn.send(("error", traceback.format_exc()))
            except OSError:
                return


class InChild:
    """A worker's solvers in a child process (spawned: a fresh interpreter, a GIL of its own)."""

    def __init__(self, factory, frames: SharedFrames, worker: int, *, wait: bool = True, renderer=render,
                 abort: threading.Event | None = None):
        self.frames, self.worker = frames, worker
        # the daemon's stop, while it starts: a stop asked for ends every wait for this child
        # (`StopRequested`) instead of waiting out a warm-up of seconds
        self.abort = abort
        self._generation = None
        self._overlay_sent = None
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_child_main, args=(child, factory, renderer),
                                name=f"thermod-solve{worker}",
                                daemon=True)
        self.proc.start()
        child.close()
        try:
            send_handle(self._conn, frames.fd, self.proc.pid)
            self._conn.send(frames.layout)
        except BaseException:
            self._kill()
            raise
        if wait:
            self.wait_ready()

    def wait_ready(self) -> None:
        """Wait for the child's first message (its imports done, the frames mapped)."""
        try:
            msg = self._recv(CHILD_START_S)
        except BaseException:
            self._kill()
            raise
        if msg[0] != "ready":
            self._kill()
            raise SolverError(f"solver child {self.worker}: expected 'ready', got {msg[0]!r}")

    @property
    def alive(self) -> bool:
        return self.proc.is_alive()

    def _recv(self, timeout: float | None):
        """The child's next message; SolverError if it died, failed, or said nothing within `timeout`."""
        t_end = math.inf if timeout is None else time.monotonic() + timeout
        while True:
            StopRequested.check(self.abort, f"while waiting for solver child {self.worker}")
            left = t_end - time.monotonic()
            if left <= 0:
                self._kill()             # hung: whatever it says later would answer the wrong job
                raise SolverError(f"solver child {self.worker}: no answer within {timeout:g} s; killed")
            try:
                if self._conn.poll(min(POLL_S, left)):
                    msg = self._conn.recv()
                    break
            except (EOFError, OSError) as e:
                raise SolverError(f"solver child {self.worker} (pid {self.proc.pid}) went away: "
                                  f"exit code {self.proc.exitcode}") from e
            if not self.proc.is_alive():
                raise SolverError(f"solver child {self.worker} (pid {self.proc.pid}) died: exit code "
                                  f"{self.proc.exitcode}")
        if msg[0] == "error":
            raise SolverError(f"solver child {self.worker} failed:\n{msg[1]}")
        return msg

    def _send(self, msg) -> None:
        try:
            self._conn.send(msg)
        except OSError as e:         # BrokenPipeError: the child is gone
            raise SolverError(f"solver child {self.worker} (pid {self.proc.pid}) went away: exit code "
                              f"{self.proc.exitcode}") from e

    def _settings(self, settings) -> None:
        gen = (settings.deblur, settings.calib)
        if self._generation != gen:
            self._send(("settings", settings.deblur, settings.calib))
            self._generation = gen

    def _overlay(self, keep_out) -> None:
        grown = None if keep_out is None else keep_out[1]
        if grown is not self._overlay_sent:
            self._send(("overlay", None, None) if grown is None else
                       ("overlay", np.packbits(grown.astype(bool)), grown.shape))
            self._overlay_sent = grown

    def warm(self, settings, rungs, img, uniform, grids, *, max_kernel_px, budget_s) -> None:
        self._settings(settings)
        kw = dict(max_kernel_px=max_kernel_px, budget_s=budget_s)
        self._send(("warm", list(rungs), img, uniform, grids, kw))
        self._recv(budget_s + CHILD_START_S)

    def solve(self, settings, rung, image, kernel, t_frame, warp_gyro, prior, *,
              pack: bool = False, keep_out=None) -> Solved:
        """Solve in the child. `prior` is called here, in the worker's thread, when the child asks.
        `keep_out`: a static overlay's (mask, grown mask), sent to the child when it changes."""
        frames = self.frames
        t0 = time.perf_counter()
        np.copyto(frames.inputs[self.worker], image, casting="unsafe")
        slot = frames.acquire()
        lent: list[SharedEstimate] = []
        waited = 0.0
        est = None
        try:
            self._settings(settings)
            self._overlay(keep_out)
            self._send(("solve", rung, self.worker, slot, kernel, float(t_frame), warp_gyro, bool(pack)))
            while True:
                msg = self._recv(SOLVE_TIMEOUT_S)
                if msg[0] != "prior":
                    break
                w0 = time.perf_counter()
                got = prior()
                if isinstance(got, SharedEstimate):
                    frames.retain(got.slot)
                    lent.append(got)
                    self._send(got.ref())
                else:
                    self._send(None)
                waited += time.perf_counter() - w0
            if msg[0] == "passed":
                _, reason, info, detail, compute_s = msg
                seconds = time.perf_counter() - t0 - waited
                return Solved(None, None, 0, seconds, (1, 1), compute_s=min(compute_s, seconds),
                              render_s=compute_s, info=info, passthrough=PassThrough(reason, info, detail))
            _, prior_frames, compute_s, grid, est_meta, render_s, info, packed, start_partial = msg
            image_out = frames.images[slot].copy()
            if est_meta is not None:
                t_est, info_shape, shape = est_meta
                est = SharedEstimate(frames, slot, t_est, tuple(info_shape), tuple(shape))
            seconds = time.perf_counter() - t0 - waited
            got = Solved(image_out, est, prior_frames, seconds, tuple(grid),
                         compute_s=min(compute_s, seconds), render_s=render_s, info=info, kernel=packed,
                         start_partial=start_partial)
            return _kept(got, image, keep_out)
        except BaseException:
            est = None
            raise
        finally:   # the slot is the caller's only when it holds the estimate
            for e in lent:
                e.release()
            if est is None:
                frames.release(slot)

    def reset(self) -> None:
        """After a failed job: the child has dropped its solvers already."""

    def _kill(self) -> None:
        if self.proc.is_alive():
            self.proc.kill()
        self.proc.join(1.0)
        self._conn.close()

    def request_stop(self) -> None:
        try:
            self._conn.send(("stop",))
        except OSError:
            pass

    def close(self, timeout: float = 1.0) -> None:
        self.request_stop()
        self.proc.join(timeout)
        self._kill()


def close_all(solvers: list, timeout: float = 1.0) -> None:
    """Close every worker's solvers within one `timeout`: all children are told first, so their
    exits overlap, and what has not exited by then is killed."""
    deadline = time.monotonic() + timeout
    for solver in solvers:
        if isinstance(solver, InChild):
            solver.request_stop()
    for solver in solvers:
        if isinstance(solver, InChild):
            solver.close(max(0.0, deadline - time.monotonic()))
        else:
            solver.close()


def start_children(factory, frames: SharedFrames, workers: int, renderer=render,
                   abort: threading.Event | None = None) -> list[InChild]:
    """One `InChild` per worker, started together (each child's start-up, about 1 s of imports,
    overlaps the others'). A set `abort` ends the wait for them (`StopRequested`, `InChild.abort`)."""
    out: list[InChild] = []
    try:
        for i in range(workers):
            out.append(InChild(factory, frames, i, wait=False, renderer=renderer, abort=abort))
        for c in out:
            c.wait_ready()
    except BaseException as e:
        # a child still importing cannot hear "stop": after a stop request it is killed at once
        close_all(out, timeout=0.0 if isinstance(e, StopRequested) else 1.0)
        raise
    return out


__all__ = ["InChild", "InThread", "Layout", "SharedEstimate", "SharedFrames", "Solved", "SolverError",
           "close_all", "limit_threads", "rung_costs", "slots_needed", "solve_job", "start_children",
           "warm_solvers"]
