"""`make run` asks only for what the daemon uses, and neither it nor `make test` stops on a machine
without apt: they say which Debian packages are missing and go on (except under THERMOD_STRICT=1, CI)."""

import os
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
MAKE = shutil.which("make")


@pytest.fixture(autouse=True)
def _make_installed(require):
    require(MAKE is not None, "GNU make")


def make(*args, env=None):
    e = {k: v for k, v in os.environ.items() if k != "THERMOD_STRICT"}
    return subprocess.run([MAKE, "-C", str(ROOT), "--no-print-directory", *args], capture_output=True,
                          text=True, env={**e, **(env or {})}, timeout=60)


def test_run_installs_the_daemons_packages_and_test_adds_the_clients():
    run, test = make("-n", "run").stdout, make("-n", "test").stdout
    for pkg in ("gir1.2-aravis-0.8", "gir1.2-gst-rtsp-server-1.0", "gstreamer1.0-plugins-ugly"):
        assert pkg in run and pkg in test, pkg
    for pkg in ("chromium", "ffmpeg", "aravis-tools"):
        assert pkg not in run and pkg in test, pkg


def test_without_apt_make_says_what_is_missing_and_goes_on(tmp_path):
    """A PATH with neither dpkg nor apt-get nor sudo: every package counts as missing, none can be
    installed; the targets name them and succeed, and fail only under THERMOD_STRICT=1."""
    r = make("debian-test-deps", env={"PATH": str(tmp_path)})
    assert r.returncode == 0, r.stderr
    notes = [ln for ln in r.stderr.splitlines() if ln.startswith("note: could not install")]
    assert len(notes) == 2, r.stderr
    assert "gir1.2-gst-rtsp-server-1.0" in notes[0] and "--rtsp" in notes[0]
    assert "chromium" in notes[1] and "ffmpeg" in notes[1] and "skip" in notes[1]
    strict = make("debian-deps", env={"PATH": str(tmp_path), "THERMOD_STRICT": "1"})
    assert strict.returncode != 0 and "could not install" in strict.stderr
