"""The simulated payload's time offset: its camera's frames are stamped by the clock mapping of their
arrivals, so they come out the transport latency late (docs/design.md §2), and the shipped
``config/sim.toml`` corrects exactly that; the configured offset is the daemon's belief, never put
into the simulated world."""

import numpy as np

from thermod.runtime import config
from thermod.sim.payload import SimPayload

# the small payload tests/runtime/test_monitor.py runs: its loop is rendered once and cached
SMALL = {"calibration.width": 160, "calibration.height": 120,
         "calibration.fx": 366.0, "calibration.fy": 366.0}


def _stamping_delays(payload: SimPayload, n: int) -> np.ndarray:
    """Frame time as delivered − the time its last row was read, for `n` frames after the first 10."""
    cam = payload.camera_source()
    cam.start()
    out = []
    try:
        while len(out) < n + 10:
            f = cam.poll(0.2)
            if f is not None:
                out.append(f.t - payload.read_time(f.frame_id))
    finally:
        cam.stop()
    return np.asarray(out[10:])


def test_frames_are_stamped_the_latency_late_and_sim_toml_corrects_it():
    cfg = config.load(None, SMALL)
    payload = SimPayload(cfg.sim, cfg.calibration)
    delays = _stamping_delays(payload, 40)
    latency = payload.camera_source().latency_s
    assert latency > 0
    assert abs(np.median(delays) - latency) < 0.0005, (np.median(delays), latency)
    truth = payload.true_calibration(payload.read_time(30))
    assert truth.time_offset_s == cfg.calibration.time_offset_s == latency


def test_the_configured_offset_is_not_put_into_the_world():
    cfg = config.load(None, {**SMALL, "calibration.time_offset_s": 0.007})
    payload = SimPayload(cfg.sim, cfg.calibration)
    payload.camera_source()
    assert payload.spec.calib.time_offset_s == 0.0
    assert payload.true_calibration(0.0).time_offset_s == payload.camera_source().latency_s
