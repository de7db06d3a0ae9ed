"""The vocabulary of calibration effects: every effect a recording can carry, in one table.

An effect is a way the world departs from the nominal model. The simulator renders it (`sim.synth`:
`--effect NAME=VALUE`), a flight video applies the gyro-side ones to the log (`sim.flight_video`), the
discrepancy workflow names and fits the ones it has a candidate for (`calib.discrepancy`), and
`Calibration` holds the fitted value in `fields` (none: the effect is not a calibration value, e.g.
noise). `side` says where it acts: "gyro" (on the log: timing, bias, scale, mount, the chip's filter
and range), "camera" (the optics and the readout and detector timing), "detector" (after the
detector's thermal response: noise, non-uniformity, response, flat-field corrections) or "scene"
(outside the rotation-only model). `conditions_gyro` marks the effects `Calibration.condition_gyro`
applies to the raw samples.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class EffectSpec:
    """One effect: its name, where it acts, its unit, the `Calibration` fields that hold it, how many
    values the simulator takes, and a field name accepted for it as an alias."""

    name: str
    side: str
    unit: str
    fields: tuple[str, ...] = ()
    sizes: tuple[int, ...] = (1,)
    alias: str | None = None
    conditions_gyro: bool = False


EFFECTS: dict[str, EffectSpec] = {e.name: e for e in (
    EffectSpec("time_offset", "gyro", "s", ("time_offset_s",)),
    EffectSpec("rolling_readout", "camera", "s", ("readout_s",)),
    EffectSpec("gyro_bias", "gyro", "rad/s", ("bias_rad_s",), (1, 3)),
    EffectSpec("gyro_scale", "gyro", "—", ("scale",), (1, 3)),
    EffectSpec("misalignment", "gyro", "rad", ("R_cam_gyro",), (3,)),
    EffectSpec("time_constant", "camera", "s", ("tau_s",)),
    EffectSpec("optical_psf", "camera", "px", ("psf_beta",)),
    EffectSpec("netd", "detector", "K"),
    EffectSpec("fpn", "detector", "K"),
    EffectSpec("gain_nonuniformity", "detector", "—"),
    EffectSpec("quantisation_bits", "detector", "bits"),
    EffectSpec("detector_nonlinearity", "detector", "—"),
    EffectSpec("gyro_noise", "gyro", "rad/s"),
    EffectSpec("clock_drift", "gyro", "ppm", ("clock_drift_ppm", "clock_epoch_s"), alias="clock_drift_ppm",
               conditions_gyro=True),
    EffectSpec("gyro_lowpass", "gyro", "Hz", ("gyro_lowpass_hz",), alias="gyro_lowpass_hz",
               conditions_gyro=True),
    EffectSpec("gyro_saturation", "gyro", "rad/s", ("gyro_range_rad_s", "gyro_clip_gain"),
               conditions_gyro=True),
    EffectSpec("ffc_event", "detector", "s,s[,counts]", (), (2, 3)),
    EffectSpec("parallax", "scene", "m,m/s", (), (2,)),
)}

#: Field names accepted for an effect's name (a `Calibration` field that holds it alone).
ALIASES: dict[str, str] = {e.alias: e.name for e in EFFECTS.values() if e.alias}

#: The gyro-side effects: they act on the log, so a flight video applies them to the log it writes.
GYRO_SIDE: frozenset[str] = frozenset(n for n, e in EFFECTS.items() if e.side == "gyro")

#: The scalar `Calibration` fields `Calibration.condition_gyro` reads (0 = off; the clip gain's neutral is 1).
GYRO_CONDITIONING_FIELDS: tuple[str, ...] = tuple(f for e in EFFECTS.values() if e.conditions_gyro
                                                  for f in e.fields)


def canonical(name: str) -> str:
    """An effect's name, with an alias (`clock_drift_ppm`) mapped to the effect (`clock_drift`)."""
    return ALIASES.get(name, name)
