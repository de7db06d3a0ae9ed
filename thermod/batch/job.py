"""The per-file job of `thermod deblur`: one recording in, one deblurred recording out.

A `Job` is plain data (paths, the `DeblurConfig`, the calibration file, the radiometric model), so
the same `run_job` runs in this process (`thermod.batch.local`) or on a Dask worker
(`thermod.batch.cluster`) and writes the same bytes: every frame's kernel comes from
`thermod.restore.plan.render` (the dispatch the daemon uses too) and is removed by `thermod.physics.deconv`:
jointly with its `DeblurConfig.temporal_views` − 1 predecessors (one `TemporalDeconvolver` per file, fed
every frame in read order), or alone when that is 1.

`run_job` never raises for a bad file: it returns an `Outcome` whose `error` is one line naming the
file (a `ThermodError`'s message, or "unexpected …" for a bug), so one file's failure costs no other.
The output is written into ``DST.part`` and renamed to ``DST`` only when complete (`recording.Writer`).
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from thermod.errors import RecordingError, ThermodError
from thermod.io import recording
from thermod.restore.overlay import grown
from thermod.restore.settings import DeblurConfig

log = logging.getLogger(__name__)


class OutputError(ThermodError):
    """The output of one file cannot be written (disk full, permissions, a directory in the way)."""

    def __init__(self, dst: Path, why):
        super().__init__(f"{dst}: cannot write the output ({why})")


@dataclass(frozen=True)
class Job:
    """One recording to deblur. `src`/`dst` are the paths as the user gave them (messages, the
    output's `source` attribute); `src_path`/`dst_path` are where to read and write (absolute on a
    cluster, whose workers do not share this process's working directory)."""

    src: Path
    dst: Path
    cfg: DeblurConfig
    config: Path | None = None        # --config: calibration table overriding the recording's
    celsius: bool = False
    model: object | None = None       # radiometric model for --celsius (None: the recording's own)
    src_path: Path | None = None
    dst_path: Path | None = None

    @property
    def read_path(self) -> Path:
        return self.src_path or self.src

    @property
    def write_path(self) -> Path:
        return self.dst_path or self.dst


@dataclass
class FileReport:
    """What one finished file did: frames, which were passed through and why, time per frame, λ."""

    src: Path
    dst: Path
    n: int
    passed: list[tuple[int, str]]
    times: list[float]                # seconds per frame (render + deconvolve)
    lams: np.ndarray                  # λ per frame (NaN where passed through)
    seconds: float = 0.0              # the whole file, reading and writing included
    motion_source: str = "gyro"       # where the recording's gyro came from ("video": estimated, /motion)


@dataclass
class Outcome:
    """A job's result: `report` when it succeeded, else `error` (one line naming the file)."""

    job: Job
    report: FileReport | None = None
    error: str | None = None
    worker: str = "local"             # where it ran (a Dask worker's address on a cluster)

    @property
    def ok(self) -> bool:
        return self.error is None


class _NoBar:
    """Stands in for a tqdm bar where nobody watches frames (a cluster worker)."""

    total = 0

    def refresh(self) -> None:
        pass

    def update(self, n: int = 1) -> None:
        pass


_per_thread = threading.local()


def deconvolver(cfg: DeblurConfig):
    """This thread's `Deconvolver` for `cfg`'s method, α and λ: FFT plans and LUTs are built once
    per thread and reused by every file it deblurs (one instance is not thread-safe)."""
    from thermod.restore.plan import make_deconvolver  # numba start-up only when deblurring

    key = (cfg.method, float(cfg.alpha), cfg.lam, cfg.kf_iterations if cfg.method == "kf" else None)
    cache = getattr(_per_thread, "decs", None)
    if cache is None:
        cache = _per_thread.decs = {}
    dec = cache.get(key)
    if dec is None:
        dec = cache[key] = make_deconvolver(cfg, live=False)
    return dec


def run_job(job: Job, bar=None, worker: str = "local") -> Outcome:
    """Deblur one file; failures come back as `Outcome.error`, never as an exception."""
    t0 = time.perf_counter()
    try:
        report = deblur_file(job, bar or _NoBar())
        report.seconds = time.perf_counter() - t0
        return Outcome(job, report=report, worker=worker)
    except ThermodError as e:
        why = str(e)
    except Exception as e:       # noqa: BLE001 - a bug must not cost the rest of the batch
        log.debug("%s failed", job.src, exc_info=True)
        why = f"{job.src}: unexpected {type(e).__name__}: {e} (-v for the traceback)"
    if str(job.src) not in why and str(job.dst) not in why and str(job.read_path) not in why \
            and str(job.write_path) not in why:
        why = f"{job.src}: {why}"     # every failure line names its file
    return Outcome(job, error=why, worker=worker)


def recording_radiometry(r: recording.Reader, src: Path):
    """The recording's own model, from its /radiometry attributes; a RecordingError naming the file
    when it has none."""
    from thermod.physics import radiometry

    attrs = r.group_attrs().get(radiometry.RECORDING_GROUP)
    if not attrs:
        raise RecordingError(src, "/radiometry", "no attributes, and --celsius needs a radiometric model: "
                             "give --radiometry FILE (a [radiometry] table) or --config with one")
    try:
        model = radiometry.from_mapping(attrs)
    except radiometry.RadiometryError as e:
        raise RecordingError(src, f"radiometry.attrs['{e.field}']", e.problem) from None
    if model is None:
        raise RecordingError(src, "radiometry.attrs['model']", "is 'none': no model to convert with")
    return model


def deblur_file(job: Job, bar) -> FileReport:
    """Deblur one recording into `job.write_path`; with `job.celsius`, convert with `job.model`
    (None: the recording's own)."""
    src, dst = job.read_path, job.write_path
    if dst.is_dir():
        raise OutputError(dst, "a directory is in the way")
    model = job.model
    with recording.Reader(src) as r:
        calib = r.calibration
        if job.config is not None:
            from thermod.io.calibration_file import load_calibration

            calib = load_calibration(job.config, base=r.calibration)
            if (calib.height, calib.width) != r.frame_shape:
                raise ThermodError(f"{job.config}: calibration is {calib.width}×{calib.height} but {src} has "
                                   f"{r.frame_shape[1]}×{r.frame_shape[0]} frames")
        if job.celsius and model is None:       # before any output is written
            model = recording_radiometry(r, src)
        dec = deconvolver(job.cfg)
        try:
            writer = recording.Writer(dst)
        except RecordingError as e:
            raise OutputError(dst, e.problem) from None
        try:
            with writer:
                report = _deblur_stream(r, calib, job, writer, dec, bar, model)
        except OSError as e:   # output side: full disk, permissions, a directory in the way …
            raise OutputError(dst, e) from None
        except RecordingError as e:
            if Path(e.path) != src:      # the writer's checks are about the output
                raise OutputError(dst, f"{e.field}: {e.problem}") from None
            raise
    return report


def temporal_deconvolver(cfg: DeblurConfig, calib, dec):
    """A `TemporalDeconvolver` over `dec` for one file (its history is that file's), or None when
    `cfg.temporal_views` is 1 (single-frame solves)."""
    if cfg.temporal_views <= 1:
        return None
    from thermod.physics.deconv.temporal import TemporalDeconvolver  # OpenCV only when temporal

    return TemporalDeconvolver(calib, views=cfg.temporal_views, single=dec, min_coverage=cfg.min_coverage)


def _deblur_frame(frame: np.ndarray, reader: recording.Reader, calib, t: float, cfg: DeblurConfig, dec,
                  tdec=None, overlay=None):
    """(deblurred frame, "") or (None, why it is passed through), by the daemon's per-frame policy
    (`thermod.restore.policy.plan_frame`; a recording's gyro stream is whole, so ``gyro_incomplete``
    and ``gyro_gap`` are the only gyro reasons). With `tdec` every frame whose kernel renders enters
    its history, a passed-through one too (its low coverage keeps it out of the joint solves, while the
    history stays in read order). `overlay`: (mask, grown mask) of a static overlay, kept out of the
    solve (`thermod.restore.overlay`)."""
    from thermod.restore import overlay as ov
    from thermod.restore.policy import PassThrough, plan_frame

    plan = plan_frame(t, reader.gyro_t, reader.gyro_rate, calib, cfg)
    image = frame if overlay is None else ov.fill(frame, overlay[1])
    if isinstance(plan, PassThrough):
        if tdec is not None and plan.kernel is not None:
            tdec.push(image, plan.kernel, t)
        return None, str(plan)
    try:
        if tdec is not None:
            out = tdec.run(image, plan.kernel, t, reader.gyro_t, reader.gyro_rate)
        elif hasattr(plan.kernel, "kernels"):
            out = dec.run_varying(image, plan.kernel)
        else:
            out = dec.run(image, plan.kernel)
    except ThermodError as e:   # a kernel that cannot be inverted: keep the frame
        return None, f"kernel_error: {e}"
    return (out if overlay is None else ov.keep(out, frame, overlay[0])), ""


def _deblur_stream(r: recording.Reader, calib, job: Job, w: recording.Writer, dec, bar, model=None) \
        -> FileReport:
    cfg, src = job.cfg, job.read_path
    n, (h, w_px) = r.n_frames, r.frame_shape
    bar.total = (bar.total or 0) + n
    bar.refresh()
    w.reserve("camera/frames", n, (h, w_px), np.uint16)
    w.reserve("camera/t", n, (), np.float64)
    w.reserve("deblurred/frames", n, (h, w_px), np.float32)
    if model is not None:
        w.reserve("deblurred/celsius", n, (h, w_px), np.float32)
        w.set_attrs("deblurred/celsius", {"units": "degC", **model.as_dict()})
    w.put("gyro/t", r.gyro_t)
    w.put("gyro/rate", r.gyro_rate)
    r.copy_extras_into(w.file)
    # Held open until `commit` closes the file, so their chunks reach the disk only when the chunk cache
    # evicts them or at close: the layout (and so the bytes) does not depend on when each short-lived
    # dataset handle dies — a Dask worker's profiler thread that briefly holds a frame of `append`
    # delays that, and moved a chunk in a measured run.
    open_datasets = [w.file[name] for name in w.rows]     # noqa: F841 - kept alive on purpose
    passed: list[tuple[int, str]] = []
    times = []
    lams = np.full(n, np.nan)
    ok = np.zeros(n, dtype=bool)
    tdec = temporal_deconvolver(cfg, calib, dec)
    views = np.zeros(n, dtype=np.int8)     # frames each solve used (0: passed through)
    mask = r.overlay()
    overlay = None if mask is None else (mask, grown(mask))
    for i in range(n):
        frame = r.frame(i)
        w.append_frame(frame, r.t[i])
        t0 = time.perf_counter()
        out, why = _deblur_frame(frame, r, calib, float(r.t[i]), cfg, dec, tdec, overlay)
        times.append(time.perf_counter() - t0)
        if out is None:
            passed.append((i, why))
            log.info("%s: frame %d passed through: %s", src, i, why)
            out = frame.astype(np.float32)
        else:
            ok[i] = True
            lams[i] = dec.last_lam
            views[i] = tdec.last_views if tdec is not None else 1
        w.append("deblurred/frames", out, np.float32)
        if model is not None:     # °C after deblurring: counts, not temperatures, are linear in flux
            w.append("deblurred/celsius", model.to_celsius(out), np.float32)
        bar.update(1)
    w.put("deblurred/t", r.t)
    w.put("deblurred/deblurred", ok)
    w.put("deblurred/lambda", lams)      # per frame (noise-adaptive unless --lambda)
    w.put("deblurred/views", views)
    # a gyro estimated from the pictures (thermod.ingest.video_only) is said so in the output too
    motion = str(r.group_attrs().get("motion", {}).get("source", "gyro"))
    w.set_attrs("deblurred", {"motion_source": motion, "overlay_kept": mask is not None,
                              "kernel": cfg.kernel, "method": dec.method,
                              "mode": cfg.mode,
                              "solver": "temporal" if tdec is not None else "single-frame",
                              "temporal_views": int(cfg.temporal_views),
                              "lambda_mode": "adaptive" if dec.lam is None else "fixed",
                              "alpha": dec.alpha, "m": cfg.m,
                              "grid": np.asarray((1, 1) if cfg.mode == "uniform" else cfg.grid),
                              "psf": cfg.psf, "min_coverage": cfg.min_coverage, "source": str(job.src)})
    w.commit(calib)
    return FileReport(job.src, job.dst, n, passed, times, lams, motion_source=motion)
