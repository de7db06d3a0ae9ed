"""The daemon's temporal rungs end to end (daemon in-process on the simulated payload, 160×120 frames):
with the default deblur configuration every frame is published and deblurred, none raw (the first
either), ≥ 99 % by the temporal rung unless the governor stepped down (the first frame has no prior),
health and the frames' metadata name the method, and the governor's ladder starts with the temporal
rung, whose cost warm-up measured."""

import time

import pytest

from tests.support.endpoints import private_endpoint
from thermod.runtime import config
from thermod.runtime.daemon import Daemon

pytestmark = pytest.mark.slow



def test_the_default_daemon_deblurs_temporally():
    opts = {"publish.endpoint": private_endpoint(), "calibration.width": 160,
            "calibration.height": 120, "calibration.fx": 366.0, "calibration.fy": 366.0,
            "pipeline.workers": 2, "monitor.enabled": False,
            # a deeper job queue than the default: the shared test machine stalls the process for
            # 0.1–0.2 s at times, and what a stall does to the default queue is not the point here
            "pipeline.job_queue": 16}
    d = Daemon(config.load(None, opts))
    seen = []
    emit = d.pipeline.emit

    def keep(o):
        seen.append((o.frame_id, o.deblurred, o.method, o.prior_frames, o.reason))
        emit(o)

    d.pipeline.emit = keep
    gov = d.pipeline.governor
    assert [r.name for r in gov.rungs] == ["temporal", "wiener", "wiener_half"]
    d.start()
    try:
        # warm-up measured every rung's cost, the temporal ones with a prior
        refs = gov.state()["cost_ms"]
        assert any(k.startswith("temporal×") for k in refs) and any(k.startswith("wiener×") for k in refs)
        assert "wiener_half×1" in refs                 # the last resort, timed too
        t0 = time.monotonic()
        while time.monotonic() - t0 < 5.0:
            d.tick()
            time.sleep(0.05)
        h = d.health()
        running = list(seen)        # before the stop: its last frames wait for a gyro that has stopped
    finally:
        d.stop()
    c = d.pipeline.stats()["counters"]
    n = c["frames_in"]
    assert n >= 150 and len(running) >= n - 10
    assert c["frames_out"] == n == len(seen)                               # every frame published
    ids = [f for f, *_ in seen]
    assert ids == sorted(ids)
    temporal = [s for s in running if s[2] == "temporal"]
    deblurred = [s for s in running if s[1]]
    g = {k: h["governor"].get(k, 0) for k in ("cost_ms", "load", "frames", "degrades", "climbs",
                                              "overload_steps", "stalls")}
    # Every frame the temporal rung made had a prior (the first frame, catch-ups and the first frame
    # back after a step down aside: its last prior may be past MAX_AGE_S), and the rung held the stream
    # unless the governor stepped down, which it does only when measured costs or overloads say the
    # machine is loaded (a shared test host can be): then the method degrades, never the share of
    # frames deblurred. (A bare clone's suite at 748d785 saw 3 frames alone: the first and one step
    # down and back, beside the other test worker.)
    alone_allowed = 1 + c.get("catch_up", 0) + g["climbs"]
    on_temporal = len(temporal) + c.get("temporal_alone", 0)
    assert len(temporal) >= 0.99 * (on_temporal - alone_allowed), (g, c)
    if g["degrades"] == 0:
        assert len(temporal) >= 0.99 * len(deblurred), (g, c)
    else:
        assert len(temporal) >= 0.2 * len(deblurred), (g, c)      # it started, and stayed a while, there
    assert all(s[3] >= 1 for s in temporal)
    assert not [s for s in running if not s[1]], c                         # none went out raw
    assert c.get("temporal_alone", 0) <= alone_allowed, (g, c)
    by = h["governor"]["deblurred_by"]
    assert by.get("temporal", 0) >= len(temporal) - 2                      # health counts them too


def test_a_9_fps_camera_is_deblurred_without_the_temporal_rung():
    """An export-limited 9 Hz core: no prior is ever within the temporal rung's age limit. The daemon
    starts (its workers' warm-up used to refuse the rung: exit with an internal error) and deblurs by
    Wiener."""
    opts = {"publish.endpoint": private_endpoint(), "calibration.width": 160,
            "calibration.height": 120, "calibration.fx": 366.0, "calibration.fy": 366.0,
            "calibration.frame_rate_hz": 9.0, "sim.frame_rate_hz": 9.0,
            "pipeline.workers": 2, "monitor.enabled": False}
    d = Daemon(config.load(None, opts))
    seen = []
    d.pipeline.emit = lambda o, emit=d.pipeline.emit: seen.append((o.deblurred, o.method)) or emit(o)
    assert [r.name for r in d.pipeline.governor.rungs] == ["wiener", "wiener_half"]
    d.start()
    try:
        t0 = time.monotonic()
        while time.monotonic() - t0 < 3.0:
            d.tick()
            time.sleep(0.05)
        running = list(seen)
    finally:
        d.stop()
    assert len(running) >= 15
    assert all(ok and method.startswith("wiener") for ok, method in running), running
