"""FFT plans for the deconvolver: pyFFTW float32 r2c/c2r pairs (FFTW_MEASURE, wisdom kept on disk)
or scipy.fft, one `Plan` per padded shape with the solver's scratch buffers.

FFTW's float32 r2c/c2r pair makes the whole K&F solve faster than scipy.fft with identical
results (benchmarks/results/deconv.md, "FFT back end"), so FFTW is the default. Padded sizes come
from a coarse ladder (16 × 5-smooth), so plans are reused across frames whose kernels differ by a
few pixels; the first frame of a new size pays FFTW's planning (~1.5 s at 640×480) once per
machine: the wisdom is kept in `wisdom_path()`.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import threading
import time
from pathlib import Path

import numpy as np
import scipy.fft

from thermod.paths import cache_dir

try:  # optional (the "test" extra): faster float32 plans
    import pyfftw
except ImportError:  # pragma: no cover - depends on the installation
    pyfftw = None

log = logging.getLogger(__name__)

# FFTW_MEASURE takes ~0.7 s per plan at 640×480; cut short, its plans ran 45 % slower (measured),
# so plan fully once and keep the wisdom on disk (`thermod.paths.cache_dir`).
# Only the daemon's warm-up is capped (a slow payload must still start); offline runs plan without a
# limit: a plan cut short on a loaded machine is not the full MEASURE wisdom another process finds,
# so that process measures its own, and a fleet's outputs would differ in the last bits.
PLANNING_TIMELIMIT_S = 3.0
MAX_PLANS = 8                 # padded shapes kept (LRU), each with its buffers

_WISDOM_LOCK = threading.Lock()
_wisdom_loaded = False


def wisdom_path() -> Path:
    return cache_dir() / "fftw_wisdom_float32"


def _load_wisdom() -> None:
    global _wisdom_loaded
    with _WISDOM_LOCK:
        if _wisdom_loaded:
            return
        _wisdom_loaded = True
        try:
            pyfftw.import_wisdom((b"", wisdom_path().read_bytes(), b""))
        except (OSError, ValueError, TypeError) as e:  # absent or stale: plan from scratch
            log.debug("no FFTW wisdom loaded (%s)", e)


@contextlib.contextmanager
def _planning_turn():
    """One planner at a time among the processes sharing the wisdom file (a batch's local processes,
    a Dask fleet's workers), holding it from reading the file to saving the new plan: the first
    process to need a size measures it, the others take its plan. Two processes measuring the same
    size can pick different FFTW algorithms, whose results differ in the last bits, so outputs
    would depend on which process deblurred them."""
    path = wisdom_path()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path.with_name(path.name + ".lock"), os.O_RDWR | os.O_CREAT, 0o644)
    except OSError:                   # read-only cache: no sharing to coordinate
        yield
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        with contextlib.suppress(OSError, ValueError, TypeError):    # absent or stale: plan anew
            pyfftw.import_wisdom((b"", path.read_bytes(), b""))
        yield
    finally:
        os.close(fd)                  # releases the lock


def save_wisdom() -> None:
    """This process's wisdom merged into the file (under the planners' lock: the file's newer plans
    are read in first, so a process never writes back the older wisdom it started with)."""
    with _planning_turn():
        _write_wisdom()


def _write_wisdom() -> None:
    """Write this process's wisdom (the caller holds `_planning_turn`, which read the file in)."""
    path = wisdom_path()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.name}.{os.getpid()}.{threading.get_ident()}")
        tmp.write_bytes(pyfftw.export_wisdom()[1])
        os.replace(tmp, path)
    except OSError as e:  # read-only home, sandboxed service: plans still work, just not cached
        log.debug("FFTW wisdom not saved to %s (%s)", path, e)


class Plan:
    """Real FFT pair for one padded shape: write into `.rin`/`.cin`, call `fwd()`/`inv()`.

    A 3-D shape (n, hp, wp) is a stack of n tiles transformed in one call (FFTW's `howmany`): one
    plan and one Python call per step for all tiles of a frame, which also holds their OTFs
    (`.K`, `.K2`). Results live in plan-owned buffers (FFTW) and are overwritten by the next call.
    """

    def __init__(self, shape, backend, workers, measure_unseen=True, timelimit_s=None):
        self.shape = shape
        self.estimated = False  # planned with FFTW_ESTIMATE (no wisdom, real-time caller)
        hp, wp = shape[-2:]
        cshape = (*shape[:-1], wp // 2 + 1)   # half spectrum of each tile
        self.backend = backend
        self.workers = workers
        # FFTW's inverse is unnormalised: the x-step folds 1/N into its output for free
        self.norm = np.float32(1.0 / (hp * wp) if backend == "fftw" else 1.0)
        if backend == "fftw":
            _load_wisdom()
            self.rin = pyfftw.empty_aligned(shape, "float32")
            self.cout = pyfftw.empty_aligned(cshape, "complex64")
            self.cin = pyfftw.empty_aligned(cshape, "complex64")
            self.rout = pyfftw.empty_aligned(shape, "float32")
            # A real-time caller cannot wait ~0.7 s for a measured plan mid-stream (it would hold up
            # the frame queue), nor for another process's planning: it takes the wisdom it loaded if
            # that has this size, else estimates.
            with _planning_turn() if measure_unseen else contextlib.nullcontext():
                t0 = time.perf_counter()
                try:
                    flags = ("FFTW_MEASURE",) if measure_unseen else ("FFTW_MEASURE", "FFTW_WISDOM_ONLY")
                    self._make_fftw(flags, workers, timelimit_s)
                except RuntimeError:
                    self.estimated = True
                    self._make_fftw(("FFTW_ESTIMATE",), workers, None)
                # planned anew (not taken from wisdom): remember it. Only inside the planning turn: a
                # real-time plan taken from the wisdom loaded at start can take > 50 ms on a loaded
                # machine, and writing that older wisdom back dropped plans other processes had saved
                # since (a fleet's workers then measured their own, and their outputs differed in the
                # last bits from the local run's)
                if measure_unseen and not self.estimated and time.perf_counter() - t0 > 0.05:
                    _write_wisdom()
        else:
            self.rin = np.empty(shape, np.float32)
            self.cin = np.empty(cshape, np.complex64)
        self.g2 = gradient_power((hp, wp))
        self.wx = np.empty((3, wp), np.float32)  # row scratch for the fused w-step
        self.wy = np.empty((2, wp), np.float32)
        self.idx = np.empty(wp, np.int32)
        self.div = self.rin  # the w-step writes its divergence straight into the FFT input
        self.spec = np.empty(cshape, np.complex64)
        if len(shape) == 3:   # the tiles' OTFs K and |K|² (a uniform solve caches its own per kernel)
            self.K = np.empty(cshape, np.complex64)
            self.K2 = np.empty(cshape, np.float32)

    def _make_fftw(self, flags, workers, timelimit_s) -> None:
        self._f = pyfftw.FFTW(self.rin, self.cout, axes=(-2, -1), flags=flags, threads=workers,
                              planning_timelimit=timelimit_s)
        self._b = pyfftw.FFTW(self.cin, self.rout, axes=(-2, -1), direction="FFTW_BACKWARD",
                              flags=(*flags, "FFTW_DESTROY_INPUT"), threads=workers,
                              planning_timelimit=timelimit_s)

    def fwd(self) -> np.ndarray:
        if self.backend == "fftw":
            self._f.execute()
            return self.cout
        return scipy.fft.rfft2(self.rin, workers=self.workers)

    def inv(self) -> np.ndarray:
        if self.backend == "fftw":
            self._b.execute()
            return self.rout
        return scipy.fft.irfft2(self.cin, s=self.shape[-2:], workers=self.workers)


def gradient_power(shape) -> np.ndarray:
    """|F∂x|² + |F∂y|² of the circular forward differences (the image prior's response) on the half
    spectrum of an (h, w) grid."""
    ky = np.fft.fftfreq(shape[0]).astype(np.float64)[:, None]
    kx = np.fft.rfftfreq(shape[1]).astype(np.float64)[None, :]
    return ((2 - 2 * np.cos(2 * np.pi * kx)) + (2 - 2 * np.cos(2 * np.pi * ky))).astype(np.float32)


def place_kernel(psf: np.ndarray, w: np.ndarray, origin) -> np.ndarray:
    """`psf` (2-D) set to the kernel `w` with its origin at index (0, 0), wrapped, zero elsewhere: the
    layout whose FFT is the OTF that does not displace the image. Returns `psf`."""
    psf.fill(0.0)
    rows = (np.arange(w.shape[0]) - origin[0]) % psf.shape[0]
    cols = (np.arange(w.shape[1]) - origin[1]) % psf.shape[1]
    psf[np.ix_(rows, cols)] = w
    return psf


def fast_len(n: int) -> int:
    """Smallest m ≥ n with m = 16·k, k = 2^a·3^b·5^c. Measured FFTW r2c+c2r pairs at 640×480
    padding: 512×720 1.07 ms, 500×720 1.16, 540×720 1.45, 576×720 1.30, 512×675 2.32 — powers of
    two pay, odd factors cost, so the coarse ladder loses nothing and lets kernels of slightly
    different sizes share one FFT plan."""
    k = max(1, -(-int(n) // 16))
    while True:
        r = k
        for p in (2, 3, 5):
            while r % p == 0:
                r //= p
        if r == 1:
            return 16 * k
        k += 1
