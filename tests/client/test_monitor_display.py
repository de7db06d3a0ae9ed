"""The calibration monitor's estimate where people read it: `thermod watch`'s text and the browser page
(health.json, and the page's DOM as headless Chromium renders it from a real Publisher's health)."""

import json
import shutil
import subprocess
import tempfile
import time
import urllib.request

import pytest

from thermod.cli.watch import WatchStats, calibration_lines
from thermod.client.subscriber import Subscriber
from thermod.client.web import LiveView, WebServer
from thermod.physics.calibration import Calibration
from thermod.runtime.publish import Publisher

APPLIED = Calibration(width=64, height=48, fx=200.0, fy=200.0, time_offset_s=0.0017,
                      bias_rad_s=(0.001, -0.002, 0.0)).as_dict()
ESTIMATE = {"gyro_bias_rad_s": [0.0123, -0.0045, 0.002], "gyro_bias_rad_s_sigma": [0.0011, 0.0009, 0.006],
            "time_offset_s": 0.00654, "time_offset_s_sigma": 0.00041, "tau_s": None, "tau_s_sigma": None,
            "t": 12.0, "n_pairs": 150, "residual_px": 0.131, "residual_applied_px": 0.162, "notes": []}
CAL = {**APPLIED, "applied": APPLIED, "source": "monitor", "estimate": ESTIMATE,
       "monitor": {"enabled": True, "apply": True, "cpu_share": 0.072, "changes_applied": 2}}


def test_watch_text_shows_applied_and_estimate():
    text = "\n".join(calibration_lines(CAL))
    assert "in force (monitor)" in text and "time offset 1.70 ms" in text
    assert "[12.30, -4.50, 2.00] ± [1.10, 0.90, 6.00] mrad/s" in text
    assert "time offset 6.54 ± 0.41 ms" in text and "tau not estimated" in text
    assert "CPU 7.2 % of a core, applies" in text and "2 changes applied" in text
    settled = calibration_lines({**CAL, "monitor": {**CAL["monitor"], "cpu_share": 0.009, "settled": True}})
    assert "CPU 0.9 % of a core (settled: watching for drift), applies" in "\n".join(settled)
    s = WatchStats()
    s.add("health", {"calibration": CAL, "rates": {}, "drops": {}, "devices": {}}, None)
    assert "6.54 ± 0.41 ms" in s.format()
    # what the daemon could not give (null in JSON) reads "?", never a crash
    unbounded = {**ESTIMATE, "gyro_bias_rad_s_sigma": [None, 0.001, None], "time_offset_s_sigma": None}
    text = "\n".join(calibration_lines({**CAL, "estimate": unbounded, "monitor": {"enabled": True}}))
    assert "± [?, 1.00, ?] mrad/s" in text and "6.54 ± ? ms" in text and "CPU ? %" in text
    # a daemon without a monitor (or an older one) shows what it has, nothing made up
    assert calibration_lines({**APPLIED}) == []
    off = calibration_lines({**CAL, "estimate": None, "monitor": {"enabled": False}})
    assert len(off) == 1 and "in force" in off[0]
    assert "AMBIGUOUS" not in text
    amb = {**ESTIMATE, "ambiguous": True, "bias_offset_correlation": [0.1, -0.99, 0.0]}
    text = "\n".join(calibration_lines({**CAL, "estimate": amb}))
    assert "AMBIGUOUS  bias and offset confounded in this window (correlation [0.1, -0.99, 0.0])" in text


def test_watch_text_shows_a_tau_estimate():
    est = {**ESTIMATE, "tau_s": 0.0098, "tau_s_sigma": 0.0005, "n_tau_patches": 40}
    text = "\n".join(calibration_lines({**CAL, "estimate": est}))
    assert "tau 9.80 ± 0.50 ms" in text and "not estimated" not in text


@pytest.fixture
def pub():
    p = Publisher("tcp://127.0.0.1:*", queue_size=64, hwm=64).start()
    yield p
    p.stop()


def _served_health(pub, view):
    with Subscriber(pub.endpoint, ("health",)) as sub:
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            pub.publish_health(calibration=CAL)
            m = sub.recv(0.1)
            if m is not None:
                view.add(*m)
                return
    raise AssertionError("no health message arrived")


def test_page_shows_the_estimate(pub, require, tmp_path):
    view = LiveView(pub.endpoint)
    _served_health(pub, view)
    with WebServer(view, "127.0.0.1:0") as server:
        with urllib.request.urlopen(server.url + "health.json", timeout=10) as r:
            s = json.loads(r.read())
        assert s["health"]["calibration"]["estimate"]["time_offset_s"] == pytest.approx(0.00654)
        chromium = shutil.which("chromium")
        require(chromium is not None, "chromium (Debian package chromium)")
        with tempfile.TemporaryDirectory() as profile:
            dom = subprocess.run([chromium, "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
                                  "--disable-background-networking", "--disable-component-update",
                                  f"--user-data-dir={profile}", "--virtual-time-budget=3000", "--dump-dom",
                                  server.url], check=True, capture_output=True, text=True, timeout=120).stdout
    cal = dom[dom.index('id="cal"'):]
    cal = cal[:cal.index("</div>")]
    assert "calibration (monitor)" in cal and "offset 6.54 ± 0.41 ms" in cal, cal
    assert "[12.30, -4.50, 2.00] ± [1.10, 0.90, 6.00] mrad/s" in cal and "not estimated" in cal
    assert "monitor CPU 7.2 %, applies" in cal, cal          # not settled: said only when it is
