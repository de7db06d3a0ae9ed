"""The real Aravis fake GigE camera (`arv-fake-gv-camera-0.8 -i 127.0.0.1`) as a fixture, shared by the
driver's tests (tests/drivers/test_aravis.py) and the flat-field tests (tests/runtime/test_ffc.py)."""

import ctypes
import fcntl
import os
import shutil
import signal
import subprocess
import time

import pytest

from thermod.drivers.aravis_camera import gvcp_probe

FAKE = shutil.which("arv-fake-gv-camera-0.8")
LOCK = "/tmp/thermod-arv-fake-camera.lock"   # the fake camera can only listen on 127.0.0.1:3956


def _gi_ok() -> bool:
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis  # noqa: F401
    except (ImportError, ValueError):
        return False
    return True


GI_OK = _gi_ok()


def _die_with_parent() -> None:
    """In the child: SIGKILL when the test process dies (a killed test run must not leave the camera)."""
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(1, signal.SIGKILL)          # PR_SET_PDEATHSIG


class FakeCamera:
    """The fake GigE camera as a subprocess that tests can kill and restart."""

    def __init__(self, serial: str):
        self.serial = serial
        self.proc = None

    def start(self, *extra: str) -> None:
        self.kill()
        self.proc = subprocess.Popen([FAKE, "-i", "127.0.0.1", "-s", self.serial, *extra],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                     preexec_fn=_die_with_parent)
        deadline = time.monotonic() + 30      # a hang bound
        while time.monotonic() < deadline:
            info = gvcp_probe("127.0.0.1", 0.05)
            if info and info["serial"] == self.serial:
                return
            if self.proc.poll() is not None:
                break
            time.sleep(0.05)
        self.kill()
        pytest.fail("arv-fake-gv-camera-0.8 did not come up on 127.0.0.1:3956 (port taken?)")

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(5)


@pytest.fixture
def fake_camera(require):
    require(FAKE is not None and GI_OK, "Aravis fake GigE camera (aravis-tools, gir1.2-aravis-0.8)")
    # Serialise across test processes: one fake camera per machine (fixed GVCP port 3956).
    with open(LOCK, "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        deadline = time.monotonic() + 15
        while (other := gvcp_probe("127.0.0.1", 0.05)) is not None:     # someone else's camera still up
            if time.monotonic() > deadline:
                pytest.fail(f"a GigE camera {other} already answers on 127.0.0.1:3956 and does not go away; "
                            "stop that arv-fake-gv-camera-0.8")
            time.sleep(0.2)
        cam = FakeCamera(f"TH{os.getpid() % 10000:04d}")
        cam.start()
        try:
            yield cam
        finally:
            cam.kill()


def _collect(cam, n, timeout=60.0):
    """The next `n` frames. The timeout only catches a camera that stopped (the fake camera sends 20–40
    fps; a loaded CI machine may take several times the nominal 25–50 ms per frame, never a minute)."""
    frames, end = [], time.monotonic() + timeout
    while len(frames) < n:
        assert time.monotonic() < end, f"only {len(frames)} of {n} frames in {timeout} s: {cam.stats()}"
        f = cam.poll(0.2)
        if f is not None:
            frames.append(f)
    return frames
