"""Shared by the tests that need a whole `thermod run` in its own process (tests/io/test_mcap.py,
tests/cli/test_watch_record.py)."""

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.support.endpoints import private_endpoint
from thermod.client.subscriber import Subscriber


@contextlib.contextmanager
def running_daemon(*extra_args: str, ready_timeout_s: float = 240.0):
    """`thermod run --raw` on the simulated payload on an ``ipc://`` socket of its own; yields its endpoint
    once its health says ready (frames and samples flowing: the first start renders the loop), SIGTERM
    after (`tests.support.endpoints.private_endpoint`)."""
    ep = private_endpoint()
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
