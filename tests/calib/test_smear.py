"""Which kernel explains the smear (`thermod.calib.smear`): on simulated flights whose detector is
known, the comparison names the detector that made the frames, and no blur explains neither."""

from __future__ import annotations

import numpy as np
import pytest

from thermod.calib import smear
from thermod.errors import RecordingError
from thermod.sim.flight_recordings import flight_motion, nominal_calibration
from thermod.sim.synth import simulate

SIZE = (320, 240)


def _compare(kind: str) -> smear.SmearComparison:
    cal = nominal_calibration(SIZE)           # τ 8 ms
    rec = simulate("texture", flight_motion(0, False, 0.0, None, None), 1.0, cal, {"netd": 0.05}, seed=0,
                   kind=kind)
    return smear.compare(rec.frames, rec.t, rec.gyro_t, rec.gyro_rate, rec.calibration)


@pytest.mark.slow
@pytest.mark.parametrize("kind, best", [("thermal", "exponential"), ("photon", "box")])
def test_the_detector_that_made_the_frames_explains_their_smear(kind, best, tmp_path):
    r = _compare(kind)
    assert len(r.frames) >= 10 and all(e >= smear.MIN_EXTENT_PX for e in r.extent_px)
    assert r.best == best and r.p_value < smear.SIGNIFICANCE, r.summary()
    assert r.total["none"] > max(r.total["box"], r.total["exponential"])   # the frames do smear
    assert len(r.gaps[best]) == len(r.frames) and np.all(np.isfinite(r.gaps[best]))
    if kind == "thermal":
        # τ on a scan of 0.5–2× the calibration's 8 ms in steps of 19 %
        assert 0.8 * 0.008 <= r.tau_s <= 1.25 * 0.008, r.tau_s
    smear.plot(r, tmp_path / "smear.png")
    assert (tmp_path / "smear.png").stat().st_size > 0
    assert best in r.summary()


def test_a_recording_with_no_smear_is_undecided_and_says_why():
    cal = nominal_calibration((160, 120))
    rec = simulate("texture", "pan:0", 0.2, cal, {"netd": 0.05}, seed=0)
    r = smear.compare(rec.frames, rec.t, rec.gyro_t, rec.gyro_rate, rec.calibration)
    assert r.best is None and r.leader is None and r.frames == [] and "no frame smears" in r.summary()
    with pytest.raises(RecordingError, match="frames"):
        smear.compare(rec.frames[0], rec.t, rec.gyro_t, rec.gyro_rate, rec.calibration)
