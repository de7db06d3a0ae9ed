"""Shared by the tests that need a whole `thermod run` in its own process (tests/io/test_mcap.py,
tests/cli/test_watch_record.py)."""

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from thermod.client.subscriber import Subscriber


@contextlib.contextmanager
def running_daemon(*extra_args: str, ready_timeout_s: float = 240.0):
    """`thermod run --raw` on the simulated payload on an ``ipc://`` socket of its own; yields its endpoint
    once its health says ready (frames and samples flowing: the first start renders the loop), SIGTERM
    after. Not a free TCP port: between finding one and binding it, another test's daemon may take it,
    and this test would then subscribe to that daemon (seen: a recording with another's calibration)."""
    where = tempfile.mkdtemp(prefix="thermod-")
    ep = f"ipc://{where}/pub.sock"
    env = dict(os.environ)
    env.setdefault("NUMBA_CACHE_DIR", str(Path(__file__).resolve().parents[2] / ".numba_cache"))
    proc = subprocess.Popen([str(Path(sys.executable).with_name("thermod")), "run", "--endpoint", ep,
                             "--raw", "--seconds", "300", *extra_args],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env, text=True)
    try:
        with Subscriber(ep, ("health",)) as hs:
            deadline = time.monotonic() + ready_timeout_s
            while time.monotonic() < deadline and proc.poll() is None:
                m = hs.recv(0.5)
                if m is not None and m[1].get("ready"):
                    break
            else:
                err = proc.stderr.read() if proc.poll() is not None else ""
                pytest.fail(f"daemon never became ready: {err}")
        yield ep
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(20)
        shutil.rmtree(where, ignore_errors=True)
