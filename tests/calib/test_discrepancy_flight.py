"""The discrepancy workflow's motion-only path on flight recordings (no static lead-in).

Recordings come from the simulator's fine-time renderer (`sim/flight_recordings.py`: 160×120
analysed at full resolution, 0.4 s, the real Betaflight log's attitude when ../shared/data is there,
else the synthetic `sim.motion.flight`; NETD 50 mK, the seeded texture). What holds on them today:
a clean flight names nothing (with or without rotor vibration, at high contrast too), effects
outside the vocabulary are reported `unexplained` and never misnamed, and (on the real log) a gyro
low-pass under the flight's slow attitude motion is reported as the time offset it acts as.

The hidden calibration effects themselves need a larger flight than this one (a 6 ms offset moves
the image 0.33 px RMS here): they are tested at the simulator's default size and length in
test_discrepancy_flight_effects.py; their static-lead-in versions are in test_discrepancy.py,
test_discrepancy_gyro.py and test_discrepancy_detector.py.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from thermod.calib.discrepancy import identify
from thermod.calib.discrepancy.report import _markdown
from thermod.physics import gyro_effects as G
from thermod.sim.flight_recordings import (
    REAL_LOG,
    SIZE,
    analysed,
    high_contrast_scene,
    nominal_calibration,
    vignetting_drift,
)

pytestmark = pytest.mark.heavy(6)      # CPU minutes on one core (measured 5.9)


@pytest.mark.slow
def test_clean_flight_recording_adds_nothing():
    fr, ana = analysed("clean", {})
    assert ana.reference == "motion"
    assert ana.steps == []
    assert not ana.unexplained
    assert ana.model.calib == fr.nominal
    assert ana.gap_final == pytest.approx(ana.gap_initial)
    # The nominal model and the estimated scene explain the motion to within a few % of its signal:
    # measured 0.079 over a floor of 0.076 on the real log.
    assert ana.gap_initial < 0.1
    assert ana.noise_floor < ana.gap_initial < 1.2 * ana.noise_floor + 0.05
    # Nothing named, so the report says what the flight resolves: each timing parameter's smallest
    # change the naming rule could name. A 6 ms offset moves this flight's image 0.33 px RMS (module
    # docstring): measured ±5.1 ms for the offset, ±4.8 ms for τ, 0.08–0.64 °/s for the bias axes.
    res = {k: v["resolution"] for k, v in ana.resolution["parameters"].items()}
    assert set(res) == {p[1] for p in identify.PARAMS}
    assert 2e-3 < res["time_offset_s"] < 1e-2 and 2e-3 < res["tau_s"] < 1e-2
    assert all(0.01 < math.degrees(res[f"bias_{a}_rad_s"]) < 2.0 for a in "xyz")
    assert all(0 < v["sigma"] < v["resolution"] for v in ana.resolution["parameters"].values())
    # the curvature in units of min_gain: a change of one parameter alone (the others held) rises at
    # least as fast as one the others may absorb
    rise = np.array(ana.resolution["rise"])
    assert np.allclose(rise, rise.T, rtol=1e-6, atol=0)
    assert np.all(np.linalg.eigvalsh(rise) > -1e-9 * rise.max())
    assert all(rise[i, i] * r ** 2 >= 1 - 1e-6 for i, r in enumerate(res[p[1]] for p in identify.PARAMS))
    assert ana.report()["resolution"] == ana.resolution
    md = _markdown(ana, ["clean.h5"], [])
    offset_ms = 1e3 * res["time_offset_s"]
    assert f"- resolution of this flight: a timing effect smaller than time_offset ±{offset_ms:.2g} ms" in md


@pytest.mark.costly
@pytest.mark.slow
def test_high_contrast_clean_flight_is_not_unexplained():
    fr, ana = analysed("contrast-clean", {}, scene=high_contrast_scene(nominal_calibration(SIZE)))
    assert not ana.unexplained
    assert ana.steps == []


@pytest.mark.costly
@pytest.mark.slow
def test_clean_flight_with_vibration_names_no_gyro_effect():
    # a 10 Hz rotor vibration (15 °/s RMS, harmonics to 40 Hz) on top of the flight attitude
    fr, ana = analysed("clean-vibration", {}, vibration_deg_s=15.0)
    assert ana.named == [] and not ana.unexplained


@pytest.mark.costly
@pytest.mark.slow
def test_lowpass_under_slow_flight_motion_is_reported_as_the_simpler_time_offset(require):
    # The flight attitude alone (below ~6 Hz) through a 40 Hz DLPF: the filter acts as its 5.6 ms
    # group delay plus < 1 % attenuation, which a time offset explains as well with one parameter;
    # the report names that. Holds on the real log's roll-dominated flight; on the synthetic flight
    # (a bare clone) nothing was named (measured), so the claim is made for the real log only.
    require(REAL_LOG, "../shared/data/gyro (the real Betaflight log)")
    fr, ana = analysed("lowpass-narrow", {"gyro_lowpass": 40.0})
    assert ana.reference == "motion"
    assert ana.named[:1] == ["time_offset"], ana.named
    assert "gyro_lowpass" not in ana.named
    assert ana.model.calib.time_offset_s == pytest.approx(-G.group_delay_s(40.0), abs=1e-3)
    assert not ana.unexplained


OUTSIDE = {
    # a vignetting change over the flight: 1 % of the signal lost in the corners by the end
    "vignetting": ({}, lambda rec: vignetting_drift(rec, 0.01, t_from=float(rec.t[0]))),
    # parallax: flat ground 3 m below, the camera swaying at 0.3 m/s RMS (≈ 2 px of shift in the
    # bottom rows by the end; the sky half has none)
    "parallax": ({"parallax": (3.0, 0.3)}, None),
}


@pytest.mark.costly
@pytest.mark.slow
@pytest.mark.parametrize("case", list(OUTSIDE))
def test_effect_outside_the_vocabulary_is_unexplained_not_misnamed(case):
    fx, edit = OUTSIDE[case]
    fr, ana = analysed(case, fx, edit=edit)
    assert ana.unexplained, (ana.gap_initial, ana.gap_final, ana.noise_floor)
    assert ana.named == [], ana.named
