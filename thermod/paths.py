"""Where thermod keeps what it can rebuild: one cache directory for every part.

`cache_dir()` is ``$THERMOD_CACHE_DIR``, else ``$THERMOD_CACHE`` (the simulator's older name), else
``$XDG_CACHE_HOME/thermod`` (the systemd unit points it at the service's cache directory), else
``~/.cache/thermod``. FFTW's wisdom (`thermod.physics.deconv.plans`) and the simulator's
pre-rendered loops (`thermod.sim.playback`) live there.
"""

from __future__ import annotations

import os
from pathlib import Path


def cache_dir() -> Path:
    for name in ("THERMOD_CACHE_DIR", "THERMOD_CACHE"):
        if os.environ.get(name):
            return Path(os.environ[name])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "thermod"
