"""One cache directory for every part (`thermod.paths.cache_dir`): the environment's names in order,
XDG_CACHE_HOME (which the systemd unit sets) honoured by FFTW's wisdom and the simulator's loops alike.
Every command that writes a file refuses a target that is not a regular file (`output_problem`)."""

import io
import os
import stat
import subprocess
import sys
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import numpy as np
import pytest

from thermod.cli import main
from thermod.io import recording
from thermod.paths import cache_dir, directory_problem, input_problem, output_problem
from thermod.physics.calibration import Calibration
from thermod.physics.deconv.plans import wisdom_path
from thermod.sim.playback import PlaybackSpec, cache_path


def test_cache_dir_precedence(monkeypatch, tmp_path):
    for name in ("THERMOD_CACHE_DIR", "THERMOD_CACHE", "XDG_CACHE_HOME"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert cache_dir() == tmp_path / "home" / ".cache" / "thermod"
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_dir() == tmp_path / "xdg" / "thermod"
    monkeypatch.setenv("THERMOD_CACHE", str(tmp_path / "old"))
    assert cache_dir() == tmp_path / "old"
    monkeypatch.setenv("THERMOD_CACHE_DIR", str(tmp_path / "new"))
    assert cache_dir() == tmp_path / "new"


def test_wisdom_and_simulator_loops_share_the_directory(monkeypatch, tmp_path):
    for name in ("THERMOD_CACHE_DIR", "THERMOD_CACHE"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))      # as the unit sets it
    assert wisdom_path().parent == tmp_path / "thermod"
    assert Path(cache_path(PlaybackSpec())).parent == tmp_path / "thermod"


def _recording(path: Path) -> Path:
    calib = Calibration(width=16, height=12, cx=7.5, cy=5.5)
    gyro_t = np.arange(0.0, 0.2, 0.001)
    rec = recording.Recording(np.full((3, 12, 16), 1000, np.uint16), 0.1 + 0.02 * np.arange(3), gyro_t,
                              np.zeros((len(gyro_t), 3), np.float32), calib)
    recording.write(path, rec)
    return path


@pytest.mark.parametrize("target", ["fifo", "directory", "missing_dir"])
@pytest.mark.parametrize("command", ["deblur", "export", "sim"])
def test_writers_refuse_a_target_that_is_not_a_regular_file(tmp_path, command, target):
    """Output goes to ``<path>.part``, renamed over the target: a device such as /dev/null (a FIFO
    stands in for one here) would be replaced by a regular file, so it is refused, as are a
    directory given where `deblur` cannot take one and a missing directory, with exit 2."""
    rec = _recording(tmp_path / "in.h5")
    out = {"fifo": tmp_path / "special", "directory": tmp_path / "adir",
           "missing_dir": tmp_path / "nowhere" / "out"}[target]
    if target == "fifo":
        os.mkfifo(out)
    elif target == "directory":
        out.mkdir()
    argv = {"deblur": ["deblur", str(rec), "-o", str(out), "--uniform", "--method", "wiener"],
            "export": ["export", str(rec), "--gcsv", str(out)],
            "sim": ["sim", "-o", str(out), "--width", "32", "--height", "24", "--seconds", "0.1",
                    "--no-progress"]}[command]
    err = io.StringIO()
    with redirect_stdout(io.StringIO()), redirect_stderr(err):
        rc = main(argv)
    if command == "deblur" and target == "directory":     # -o DIR writes DIR/in.h5 (documented)
        assert rc == 0 and (out / "in.h5").is_file()
        return
    assert rc == 2, err.getvalue()
    assert str(out) in err.getvalue() and "Traceback" not in err.getvalue()
    if target == "fifo":
        assert stat.S_ISFIFO(out.stat().st_mode)                    # untouched
    assert not list(tmp_path.glob("**/*.part"))


def test_a_path_with_a_nul_character_is_a_problem_not_a_value_error(tmp_path):
    assert input_problem(f"{tmp_path}/a\0b") == "is not a path (it holds a NUL character)"
    assert "does not exist" in input_problem(tmp_path / "nope") and input_problem(__file__) is None


def test_output_and_directory_problems(tmp_path):
    assert output_problem(tmp_path / "new.h5") is None
    (tmp_path / "file").write_text("x")
    assert output_problem(tmp_path / "file") is None
    assert "directory" in output_problem(tmp_path)
    assert "does not exist" in output_problem(tmp_path / "no" / "x.h5")
    assert directory_problem(tmp_path / "a" / "b") is None and (tmp_path / "a" / "b").is_dir()
    assert "expected a directory" in directory_problem(tmp_path / "file")


@pytest.mark.parametrize("command", ["deblur", "export", "run_config", "calibration_file"])
def test_readers_refuse_a_fifo_instead_of_blocking_on_it(tmp_path, command):
    """A FIFO would block its reader for ever (and /dev/zero never end): every file input takes only a
    regular file, and says so with exit 2. Run as a process with a deadline, so a regression fails
    instead of hanging the suite."""
    fifo = tmp_path / "in.h5"
    os.mkfifo(fifo)
    rec = _recording(tmp_path / "ok.h5")
    argv = {"deblur": ["deblur", str(fifo), "-o", str(tmp_path / "out.h5")],
            "export": ["export", str(fifo), "--gcsv", str(tmp_path / "out.gcsv")],
            "run_config": ["run", "--config", str(fifo), "--seconds", "1"],
            "calibration_file": ["deblur", str(rec), "-o", str(tmp_path / "out.h5"), "--config", str(fifo)],
            }[command]
    r = subprocess.run([sys.executable, "-m", "thermod.cli", *argv], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 2, r.stderr
    assert str(fifo) in r.stderr and "regular file" in r.stderr and "Traceback" not in r.stderr
