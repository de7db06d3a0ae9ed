"""One vocabulary of calibration effects (`thermod.physics.effects.EFFECTS`): the simulator, the flight
video, the discrepancy workflow and `Calibration` all read it."""

import dataclasses
import re
from pathlib import Path

import pytest

from thermod.calib import discrepancy as D
from thermod.errors import ThermodError
from thermod.physics.calibration import GYRO_EFFECT_KEYS, Calibration
from thermod.physics.effects import ALIASES, EFFECTS, GYRO_SIDE, canonical
from thermod.sim import flight_video, synth


def test_every_candidate_and_field_is_in_the_vocabulary():
    assert set(D.EFFECTS) <= set(EFFECTS)
    fields = {f.name for f in dataclasses.fields(Calibration)}
    for spec in EFFECTS.values():
        assert set(spec.fields) <= fields, spec.name
        assert spec.side in ("gyro", "camera", "detector", "scene"), spec.name
    assert set(GYRO_EFFECT_KEYS) == {f for e in EFFECTS.values() if e.conditions_gyro for f in e.fields}


def test_the_simulator_takes_every_effect_and_documents_it():
    assert set(re.findall(r"``([a-z_]+)``", synth.__doc__)) == set(EFFECTS)
    design = (Path(__file__).resolve().parents[2] / "docs" / "design.md").read_text()
    table = design.split("### The simulator's effects", 1)[1].split("\n#", 1)[0]
    assert set(re.findall(r"^    ([a-z_]+) {2,}", table, flags=re.M)) == set(EFFECTS)
    for alias, name in ALIASES.items():
        assert canonical(alias) == name
    with pytest.raises(ThermodError, match="unknown effect; known: time_offset"):
        synth.check_effects({"gyro_drift": 0.1})
    with pytest.raises(ThermodError, match="misalignment: expected 3 value"):
        synth.check_effects({"misalignment": 0.1})
    assert synth.check_effects({"clock_drift_ppm": 20.0}) == {"clock_drift": 20.0}


def test_a_flight_video_applies_exactly_the_gyro_side_effects_to_the_log():
    assert GYRO_SIDE == {"time_offset", "gyro_bias", "gyro_scale", "misalignment", "gyro_noise",
                         "clock_drift", "gyro_lowpass", "gyro_saturation"}
    assert flight_video.GYRO_SIDE_EFFECTS == GYRO_SIDE | set(ALIASES)
