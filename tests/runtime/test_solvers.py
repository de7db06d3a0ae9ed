"""The workers' solvers in child processes (`thermod.runtime.solvers`): the same results as in the
worker's thread, temporal priors passed through shared memory, slots given back, a failed or killed
child said and replaced, and threads when a child cannot be used."""

import os
import signal
import time

import numpy as np
import pytest

from tests.support.collecting import Collector
from tests.support.solver_faults import POISON, crashing_factory, hanging_factory
from thermod.physics import kernels
from thermod.physics.calibration import Calibration
from thermod.restore.plan import make_deconvolver, render
from thermod.restore.settings import DeblurConfig
from thermod.runtime import solvers
from thermod.runtime.config import PipelineConfig
from thermod.runtime.governor import ladder
from thermod.runtime.pipeline import PRIOR_FRAMES, Pipeline
from thermod.runtime.rings import FrameRing, GyroRing
from thermod.runtime.solvers import (
    InChild,
    InThread,
    Layout,
    SharedEstimate,
    SharedFrames,
    SolverError,
    slots_needed,
)
from thermod.sim.scenes import load_scene

H, W = 120, 160
CAL = Calibration(width=W, height=H, fx=366.0, fy=366.0, cx=79.5, cy=59.5, frame_rate_hz=50.0)
RATE = 1000.0
TEMPORAL = DeblurConfig(method="wiener", mode="uniform", temporal_views=2)


def omega(t):
    t = np.asarray(t, np.float64)
    return np.stack([0.2 * np.sin(2 * np.pi * 3 * t), 0.6 + 0.1 * np.cos(2 * np.pi * 2 * t), 0.02 + 0 * t], 1)


class _Settings:
    def __init__(self, deblur, calib=CAL):
        self.deblur, self.calib = deblur, calib


@pytest.fixture(scope="module")
def stream():
    """Five blurry noisy frames of a pan, with their kernels and the gyro."""
    sharp = load_scene("texture", (H, W), seed=3).astype(np.float32)
    rng = np.random.default_rng(1)
    tg = np.arange(-0.3, 0.2, 1 / RATE)
    rate = omega(tg).astype(np.float32)
    out = []
    for i in range(5):
        t = 0.02 * i
        k, _ = render(tg, rate, CAL, t, TEMPORAL)
        out.append(((kernels.blur(sharp, k) + rng.normal(0, 2.0, sharp.shape)).astype(np.float32), k, t))
    return out, (tg, rate)


@pytest.fixture()
def frames():
    f = SharedFrames(Layout((H, W), 1, slots_needed(1, PRIOR_FRAMES), 4 * H * W))
    yield f
    f.close()


def _run(solver, stream, gyro, keep_out=None):
    rung = ladder(TEMPORAL)[0]
    assert rung.temporal
    prev, outs = None, []
    for img, k, t in stream:
        got = solver.solve(_Settings(TEMPORAL), rung, img, k, t, gyro, lambda p=prev: p, keep_out=keep_out)
        outs.append(got)
        if isinstance(prev, SharedEstimate):
            prev.release()
        prev = got.estimate
    if isinstance(prev, SharedEstimate):
        prev.release()
    return outs


def test_a_child_solves_as_the_thread_does_and_gives_its_slots_back(stream, frames):
    data, gyro = stream
    here = _run(InThread(make_deconvolver), data, gyro)
    child = InChild(make_deconvolver, frames, 0)
    try:
        there = _run(child, data, gyro)
    finally:
        child.close()
    assert [g.prior_frames for g in here] == [g.prior_frames for g in there] == [0, 1, 1, 1, 1]
    for a, b in zip(here, there, strict=True):
        np.testing.assert_allclose(b.image, a.image, rtol=0, atol=1e-3 * float(np.ptp(a.image)))
        assert b.grid == a.grid and b.seconds > 0
    # the prior changed the result: the comparison above is not of two single-frame solves
    assert float(np.abs(there[-1].image - InThread(make_deconvolver).solve(
        _Settings(TEMPORAL), ladder(TEMPORAL)[-1], data[-1][0], data[-1][1], data[-1][2], gyro,
        lambda: None).image).max()) > 1.0
    assert all(isinstance(g.estimate, SharedEstimate) for g in there)
    assert frames.in_use() == 0


def test_a_static_overlay_is_kept_out_of_the_solve_in_the_thread_and_in_the_child(stream, frames):
    """A logo burnt into every frame: solved as scene it rings into the scene beside it; kept out,
    its pixels are the input's and the ring is gone, in both solvers, the prior included."""
    from thermod.restore.overlay import grown

    data, gyro = stream
    mask = np.zeros((H, W), bool)
    mask[6:24, 8:12] = mask[6:24, 30:34] = mask[6:10, 8:34] = True       # printed strokes, top-left
    near = np.zeros((H, W), bool)
    near[0:40, 0:50] = True
    near &= ~mask
    hi = np.float32(np.percentile(data[0][0], 99.9) + 300)
    logo = [(np.where(mask, hi, img).astype(np.float32), k, t) for img, k, t in data]
    keep_out = (mask, grown(mask))

    def run(solver, keep):
        return [got.image for got in _run(solver, logo, gyro, keep_out if keep else None)]

    truth = np.where(mask, hi, load_scene("texture", (H, W), seed=3))[near]     # the stream's sharp scene
    plain = run(InThread(make_deconvolver), False)
    here = run(InThread(make_deconvolver), True)
    child = InChild(make_deconvolver, frames, 0)
    try:
        there = run(child, True)
        assert child._overlay_sent is keep_out[1]                    # sent once, not with every job
    finally:
        child.close()
    for a, b in zip(here, there, strict=True):
        assert np.all(a[mask] == hi) and np.all(b[mask] == hi)
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-3 * float(np.ptp(a)))
    # the solved logo rings into the scene beside it; kept out, it does not (measured: 141 → 29 counts
    # mean error within ~25 px of it)
    err_plain = np.median([np.abs(p[near] - truth).mean() for p in plain])
    err_kept = np.median([np.abs(k[near] - truth).mean() for k in here])
    assert err_kept < 0.5 * err_plain, (err_plain, err_kept)
    assert frames.in_use() == 0


def test_a_failed_job_is_said_with_the_childs_traceback_and_the_child_goes_on(stream, frames):
    data, gyro = stream
    rung = ladder(DeblurConfig(method="wiener", mode="uniform"))[-1]
    s = _Settings(DeblurConfig(method="wiener", mode="uniform"))
    child = InChild(crashing_factory, frames, 0)
    try:
        with pytest.raises(SolverError, match="injected worker fault"):
            child.solve(s, rung, np.full((H, W), POISON, np.float32), data[0][1], 0.0, None, lambda: None)
        got = child.solve(s, rung, data[0][0], data[0][1], 0.0, None, lambda: None)
        assert np.isfinite(got.image).all() and got.estimate is None
    finally:
        child.close()
    assert frames.in_use() == 0


def test_a_child_outlives_sigterm_and_sigint_sent_to_the_process_group(stream, frames):
    """systemd's stop and Ctrl-C signal every process of the group: the parent stops its children
    itself, after the frames in flight."""
    data, _ = stream
    child = InChild(make_deconvolver, frames, 0)
    try:
        os.kill(child.proc.pid, signal.SIGTERM)
        os.kill(child.proc.pid, signal.SIGINT)
        rung = ladder(DeblurConfig(method="wiener", mode="uniform"))[-1]
        got = child.solve(_Settings(DeblurConfig(method="wiener")), rung, data[0][0], data[0][1], 0.0, None,
                          lambda: None)
        assert child.alive and np.isfinite(got.image).all()
    finally:
        child.close()
    assert not child.alive


def test_a_hung_child_is_killed_after_the_solve_timeout(stream, frames, monkeypatch):
    data, _ = stream
    monkeypatch.setattr(solvers, "SOLVE_TIMEOUT_S", 1.0)
    rung = ladder(DeblurConfig(method="wiener", mode="uniform"))[-1]
    s = _Settings(DeblurConfig(method="wiener", mode="uniform"))
    child = InChild(hanging_factory, frames, 0)
    try:
        t0 = time.monotonic()
        with pytest.raises(SolverError, match="no answer within 1 s; killed"):
            child.solve(s, rung, np.full((H, W), POISON, np.float32), data[0][1], 0.0, None, lambda: None)
        assert time.monotonic() - t0 < 10.0
        assert not child.alive
    finally:
        child.close()
    assert frames.in_use() == 0


def test_a_killed_child_is_said_and_the_pool_runs_out_loudly(stream, frames):
    data, gyro = stream
    child = InChild(make_deconvolver, frames, 0)
    os.kill(child.proc.pid, signal.SIGKILL)
    child.proc.join(5)
    rung = ladder(DeblurConfig(method="wiener", mode="uniform"))[-1]
    with pytest.raises(SolverError, match="solver child 0"):
        child.solve(_Settings(DeblurConfig(method="wiener")), rung, data[0][0], data[0][1], 0.0, None,
                    lambda: None)
    child.close()
    assert frames.in_use() == 0
    held = [frames.acquire() for _ in range(frames.layout.slots)]
    with pytest.raises(SolverError, match="no free output slot"):
        frames.acquire()
    for s in held:
        frames.release(s)


def _pipeline(col, factory=None, deblur=TEMPORAL):
    gr, fr = GyroRing(5000), FrameRing(32, (H, W))
    cfg = PipelineConfig(workers=2, job_queue=8, wait_timeout_s=0.2, reorder_timeout_s=5.0, processes=True)
    p = Pipeline(gr, fr, CAL, deblur, cfg, col, deconvolver_factory=factory)
    p.warmup(budget_s=5.0)
    return gr, fr, p


def test_the_pipeline_replaces_a_killed_child_and_publishes_every_frame(stream):
    data, _ = stream
    col = Collector()
    gr, fr, p = _pipeline(col)
    assert all(isinstance(s, InChild) for s in p._solvers)
    p.start()
    try:
        t0 = time.monotonic()
        tg = np.arange(t0 - 0.3, t0 + 1.5, 1 / RATE)
        gr.write(tg, omega(tg - t0).astype(np.float32), 0)
        n = 40
        for i in range(n):
            if i == 15:
                os.kill(p._solvers[0].proc.pid, signal.SIGKILL)
            fr.write(np.clip(data[i % 5][0], 0, 65535).astype(np.uint16), t0 + 0.02 * i, frame_id=i,
                     arrival=time.monotonic())
            time.sleep(0.02)
        outs = col.wait(n, timeout=90)
    finally:
        # a worker still on a job (a loaded machine) keeps the solvers open past stop's timeout:
        # this one only catches a worker that never returns
        p.stop(timeout=60.0)
    c = p.stats()["counters"]
    assert [o.frame_id for o in outs] == list(range(n))
    assert {o.reason for o in outs} <= {None, "worker_error", "overload"}
    assert c.get("solver_children_replaced", 0) == 1, c
    assert all(o.deblurred for o in outs[-10:])
    assert sum(o.method == "temporal" for o in outs[-10:]) >= 8, [o.method for o in outs]
    assert p._frames is None and p._solvers == []          # stop closed them


def test_a_factory_a_child_cannot_import_keeps_the_solves_in_the_threads():
    col = Collector()
    _, _, p = _pipeline(col, factory=lambda d: make_deconvolver(d))
    try:
        assert p._solvers and all(isinstance(s, InThread) for s in p._solvers)
        assert p._frames is None
    finally:
        p.stop()


def test_no_shared_memory_keeps_the_solves_in_the_threads_and_says_so(monkeypatch, caplog):
    """A seccomp filter or a full /dev/shm: memfd_create fails, the daemon runs on in threads."""
    def refuse(*a, **k):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "memfd_create", refuse)
    col = Collector()
    with caplog.at_level("WARNING", logger="thermod.runtime.pipeline"):
        _, _, p = _pipeline(col)
    try:
        assert p._solvers and all(isinstance(s, InThread) for s in p._solvers)
        assert "solver processes unavailable" in caplog.text and "Operation not permitted" in caplog.text
    finally:
        p.stop()
