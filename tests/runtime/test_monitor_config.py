"""The ``[monitor]`` section: its defaults, and errors naming the key."""

import pytest

from thermod.errors import ConfigError
from thermod.runtime import config


def test_monitor_section_defaults_and_errors(tmp_path):
    cfg = config.load()
    assert cfg.monitor == config.MonitorConfig() and cfg.monitor.enabled and not cfg.monitor.apply
    assert config.load(None, {"monitor.apply": True, "monitor.cpu_share": 0.05}).monitor.cpu_share == 0.05
    with pytest.raises(ConfigError, match=r"monitor\.cpu_share"):
        config.load(None, {"monitor.cpu_share": 2.0})
    with pytest.raises(ConfigError, match=r"monitor\.apply"):
        config.load(None, {"monitor.apply": "yes"})
    with pytest.raises(ConfigError, match=r"monitor\.sigma"):
        config.load(None, {"monitor.sigma": 3})
