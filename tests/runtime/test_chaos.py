"""A 40-second chaos soak (`thermod.chaos`): the daemon on the simulated payload under a random
schedule of gyro, camera, clock, reload and subscriber faults. Every camera frame is published or
counted under a reason, no thread dies, bad reloads are refused and good ones applied, the watchdog
keeps being fed within the unit's WatchdogSec, and memory does not grow without bound. No rates are
asserted (the machine is shared); `benchmarks/bench_chaos.py` is the long version."""

from pathlib import Path

import pytest

from thermod import chaos
from thermod.io.wire import REASONS

pytestmark = pytest.mark.slow

UNIT = Path(__file__).resolve().parents[2] / "systemd" / "thermod.service"
SOAK_S = 40.0            # every fault kind is scheduled by 30 s (seeds 1-3 and 9); bench_chaos soaks longer
RSS_GROWTH_MB = 200      # generous: stalled subscribers pin at most publish.max_queue_mb (128 MB) together


@pytest.fixture(scope="module")
def soak(tmp_path_factory):
    r = chaos.run(SOAK_S, seed=9, method="wiener", workdir=tmp_path_factory.mktemp("chaos"),
                  watchdog_s=chaos.unit_watchdog_s(UNIT))
    print(chaos.table(r))
    return r


def test_the_schedule_covers_every_fault_kind():
    kinds = {f.kind for f in chaos.schedule(SOAK_S, seed=9)}
    assert kinds == set(chaos.KINDS)
    # and is reproducible from its seed, different for another
    assert chaos.schedule(SOAK_S, seed=9) == chaos.schedule(SOAK_S, seed=9) != chaos.schedule(SOAK_S, seed=10)


def test_every_frame_published_or_counted(soak):
    f = soak["frames"]
    assert f["drained"], chaos.table(soak)
    assert f["delivered"] > 500 and f["published"] > 500
    assert f["unaccounted"] == 0, chaos.table(soak)
    assert f["in_flight"] == 0 and f["duplicates"] == 0
    # nothing vanishes silently: every frame the accounting subscriber did not get is a seq gap it saw,
    # either a drop the publisher counted or one ZeroMQ made at the SNDHWM when the subscriber's thread
    # was starved (possible on a loaded machine: subscribers are told of it by the gap, as documented)
    assert f["seq_gaps"] == f["dropped"]["publisher_dropped"] + f["wire_lost"], chaos.table(soak)
    assert f["wire_lost"] <= 0.02 * f["published"], chaos.table(soak)
    assert f["ids_unexplained"] <= 0, chaos.table(soak)
    # every frame published without deblurring carries a reason, counted by the pipeline
    seen = {k: v for k, v in soak["published_by_reason"].items() if k != "deblurred"}
    assert set(seen) <= set(REASONS) and all(v <= soak["passthrough"][k] for k, v in seen.items()), seen


def test_no_thread_died_and_still_publishing(soak):
    assert soak["threads"]["deaths"] == 0, soak["threads"]
    e = soak["end"]
    assert e["alive"] and e["recovered"] and e["published_last_1.5s"] > 0, e    # deblurring again


def test_reloads_bad_refused_good_applied(soak):
    r = soak["reloads"]
    assert soak["faults"].get("reload_good", 0) >= 1 and soak["faults"].get("reload_bad", 0) >= 1
    assert r["problems"] == []
    assert r["applied"] == r["good"] == soak["faults"]["reload_good"]
    assert r["refused_total"] == r["kept_settings"] == r["bad_total"] == soak["faults"]["reload_bad"]


def test_watchdog_fed_within_watchdog_sec(soak):
    wd = soak["watchdog"]
    assert wd["pings"] >= SOAK_S / 2       # the daemon pings every second
    assert wd["longest_gap_s"] < chaos.unit_watchdog_s(UNIT), wd


def test_rss_growth_bounded(soak):
    assert soak["rss_mb"]["growth"] < RSS_GROWTH_MB, soak["rss_mb"]


def test_every_fault_kind_was_injected(soak):
    assert set(soak["faults"]) == set(chaos.KINDS), soak["faults"]
