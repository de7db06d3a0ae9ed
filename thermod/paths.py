"""Where thermod keeps what it can rebuild, and the rule every file it writes keeps.

An output file is written as ``<path>.part`` and renamed over `path`, so `output_problem` refuses a
`path` that exists and is not a regular file (a directory, or a device such as ``/dev/null``: the
rename would replace the device node) or whose directory does not exist. `input_problem` takes only a
regular file as an input (a FIFO blocks its reader; /dev/zero never ends).

`cache_dir()` is ``$THERMOD_CACHE_DIR``, else ``$THERMOD_CACHE`` (the simulator's older name), else
``$XDG_CACHE_HOME/thermod`` (the systemd unit points it at the service's cache directory), else
``~/.cache/thermod``. FFTW's wisdom (`thermod.physics.deconv.plans`) and the simulator's
pre-rendered loops (`thermod.sim.playback`) live there.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path


def input_problem(path: str | os.PathLike) -> str | None:
    """Why `path` cannot be read as an input file; None if it can. A FIFO would block its reader and a
    device such as /dev/zero never end, so only a regular file is taken."""
    try:
        mode = Path(path).stat().st_mode
    except FileNotFoundError:
        return "does not exist"
    except OSError as e:
        return f"cannot inspect it ({e.strerror or e})"
    except ValueError:                   # a NUL character: no file has such a name
        return "is not a path (it holds a NUL character)"
    if stat.S_ISDIR(mode):
        return "is a directory, expected a file"
    if not stat.S_ISREG(mode):
        return "is a device or special file (a FIFO, a socket), expected a regular file"
    return None


def directory_problem(path: str | os.PathLike) -> str | None:
    """Why `path` cannot be (made) a directory to write files into; None once it is one."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        return "it is a file: expected a directory (or a new one)"
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        return f"cannot create it ({e.strerror or e})"
    return None


def output_problem(path: str | os.PathLike) -> str | None:
    """Why `path` cannot take an output file written beside it and renamed over it; None if it can."""
    p = Path(path)
    try:
        mode = p.stat().st_mode
    except FileNotFoundError:
        mode = None
    except OSError as e:
        return f"cannot inspect it ({e.strerror or e})"
    if mode is not None and not stat.S_ISREG(mode):
        kind = "a directory" if stat.S_ISDIR(mode) else "a device or special file"
        return f"it is {kind}: expected a regular file to write (or a new one)"
    if not p.parent.is_dir():
        return f"directory {p.parent} does not exist"
    return None


def cache_dir() -> Path:
    for name in ("THERMOD_CACHE_DIR", "THERMOD_CACHE"):
        if os.environ.get(name):
            return Path(os.environ[name])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "thermod"
