"""One cache directory for every part (`thermod.paths.cache_dir`): the environment's names in order,
XDG_CACHE_HOME (which the systemd unit sets) honoured by FFTW's wisdom and the simulator's loops alike."""

from pathlib import Path

from thermod.paths import cache_dir
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
