"""`thermod run` with replay sources runs with the recording's own calibration unless the configuration
asks for its ``[calibration]`` (``[sources.camera] calibration = "config"``); a SIGHUP reload keeps
that choice."""


import numpy as np
import pytest

from tests.support.endpoints import private_endpoint
from thermod.errors import ConfigError
from thermod.io import recording
from thermod.physics.calibration import Calibration
from thermod.runtime import config
from thermod.runtime.daemon import Daemon

FPS, RATE, N = 50.0, 1000.0, 10



@pytest.fixture
def rec_path(tmp_path):
    # a calibration unlike the config defaults in every field the deblurring depends on
    calib = Calibration(width=32, height=24, fx=400.0, fy=400.0, cx=15.5, cy=11.5, tau_s=0.011,
                        frame_rate_hz=FPS, rate_hz=RATE, time_offset_s=0.0037,
                        bias_rad_s=(0.01, -0.02, 0.003), readout_s=0.004)
    frames = np.stack([np.full((24, 32), 1000 + 17 * i, np.uint16) for i in range(N)])
    t = 10.0 + np.arange(N) / FPS
    gyro_t = 10.0 - 0.06 + np.arange(int(0.3 * RATE)) / RATE
    rate = np.stack([np.sin(gyro_t), np.cos(gyro_t), 0 * gyro_t], axis=1).astype(np.float32)
    p = tmp_path / "rec.h5"
    recording.write(p, recording.Recording(frames, t, gyro_t, rate, calib))
    return p, calib


def _config(tmp_path, rec, choice: str | None, tau: float = 0.008):
    line = "" if choice is None else f'calibration = "{choice}"'
    path = tmp_path / "replay.toml"
    path.write_text(f"""
[sources.gyro]
kind = "replay"
path = "{rec}"
[sources.camera]
kind = "replay"
path = "{rec}"
{line}
[calibration]
width = 32
height = 24
fx = 380.0
fy = 380.0
tau_s = {tau}
[deblur]
method = "wiener"
[publish]
endpoint = "{private_endpoint()}"
[monitor]
enabled = false
""")
    return path


def _daemon(cfg):
    return Daemon(cfg)


@pytest.mark.parametrize("choice", [None, "recording"])
def test_replay_runs_with_the_recordings_calibration_by_default(tmp_path, rec_path, choice):
    rec, calib = rec_path
    cfg = config.load(_config(tmp_path, rec, choice))
    assert cfg.camera.options["calibration"] == "recording"
    d = _daemon(cfg)
    assert d.pipeline.calib == calib
    assert d.cfg.calibration == calib
    assert d.calibration_source == f"recording {rec}"
    h = d.health()
    assert h["calibration"]["source"] == f"recording {rec}"
    assert Calibration.from_dict(h["calibration"]["applied"]) == calib


def test_config_calibration_overrides_only_when_asked(tmp_path, rec_path):
    rec, calib = rec_path
    cfg = config.load(_config(tmp_path, rec, "config"))
    d = _daemon(cfg)
    assert d.pipeline.calib == cfg.calibration != calib
    assert d.pipeline.calib.tau_s == 0.008 and d.pipeline.calib.time_offset_s == 0.0
    assert d.calibration_source == "config"


def test_reload_keeps_the_recordings_calibration(tmp_path, rec_path):
    rec, calib = rec_path
    path = _config(tmp_path, rec, None)
    d = _daemon(config.load(path))
    _config(tmp_path, rec, None, tau=0.02)          # the file's [calibration] changes: not in force
    assert d.reload()
    assert d.pipeline.calib == calib
    _config(tmp_path, rec, "config", tau=0.02)      # asked for: the file's [calibration] applies
    assert d.reload()
    assert d.pipeline.calib.tau_s == 0.02 and d.pipeline.calib.width == 32


def test_unknown_choice_is_a_config_error(tmp_path, rec_path):
    rec, _ = rec_path
    with pytest.raises(ConfigError, match=r"sources\.camera\.calibration"):
        config.load(_config(tmp_path, rec, "camera"))

