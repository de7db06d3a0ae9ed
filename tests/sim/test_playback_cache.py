"""The simulated payload's loop cache is keyed by what the scene is drawn from, and the fallback from
``real`` to the procedural texture is one plain log line."""

import logging
import os

import cv2
import numpy as np

from thermod.sim import playback, scenes


def _with_frames(tmp_path, value: int):
    d = tmp_path / "data"
    (d / "thermal").mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(d / "thermal" / "a.png"), np.full((16, 16), value, np.uint16))
    return d


def test_cache_key_follows_the_scene_source(tmp_path, monkeypatch):
    spec = playback.PlaybackSpec(scene="real:0")
    monkeypatch.setenv("THERMOD_SHARED_DATA", str(tmp_path / "absent"))
    without = spec.key()
    assert scenes.scene_source("real:0") == "texture (no real frames)"
    monkeypatch.setenv("THERMOD_SHARED_DATA", str(_with_frames(tmp_path, 18000)))
    with_real = spec.key()
    assert with_real != without                      # the data appeared: render the real scene
    assert spec.key() == with_real                   # and reuse it after
    png = _with_frames(tmp_path, 19000) / "thermal" / "a.png"      # the image changed
    os.utime(png, ns=(0, os.stat(png).st_mtime_ns + 10**9))
    assert spec.key() != with_real
    # procedural scenes do not depend on shared data
    assert playback.PlaybackSpec(scene="bars").key() == playback.PlaybackSpec(scene="bars").key()


def test_fallback_is_one_log_line_without_source_code(tmp_path, monkeypatch, caplog):
    monkeypatch.setenv("THERMOD_SHARED_DATA", str(tmp_path / "absent"))
    with caplog.at_level(logging.WARNING, logger="thermod.sim.scenes"):
        img = scenes.load_scene("real:1", (120, 160))
    assert img.shape == (120, 160)
    assert [r.getMessage() for r in caplog.records] == [
        "scene 'real:1': no real frames (shared/data not found; set THERMOD_SHARED_DATA), using the "
        "procedural 'texture' scene instead"]
