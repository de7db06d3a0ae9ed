"""Calibration from data: find and fit what the model of a recording gets wrong.

The forward model predicts a recording's blurry motion frames from a static reference frame, the raw
gyro and a candidate `Calibration` (Eq. 16 homographies, the Eq. 10/11 thermal IIR at sub-pixel time
steps, rolling readout, an extra Eq. 19 PSF). The discrepancy workflow behind `thermod discrepancy`
compares prediction and measurement, names the missing effect (time offset, readout, gyro bias, scale,
misalignment, τ, optical blur) or says it cannot, fits it and writes a report and a `[calibration]`
table. `live` estimates the gyro bias and time offset from a stream's consecutive frames (the
daemon's calibration monitor runs it). Offline and deterministic: it builds on `thermod.physics` and
`thermod.io` and must never import `thermod.drivers`, `thermod.sim`, zmq or GStreamer, nor anything of
`thermod.runtime` beyond the configuration reader.
"""
