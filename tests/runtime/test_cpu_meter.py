"""Where the daemon's time goes: `thermod.runtime.cpu` books each thread's CPU under its stage, the solver
children's under ``solves``, moves the simulated payload's work out of the driver threads, and keeps
each pipeline stage's latency percentiles; `thermod watch` prints both."""

import subprocess
import sys
import threading
import time

import pytest

from thermod.cli.watch import cpu_lines
from thermod.runtime.cpu import CpuMeter, StageTimes, process_cpu_s, stage_of


def spin(seconds: float) -> None:
    end = time.thread_time() + seconds
    while time.thread_time() < end:
        pass


def test_threads_are_booked_under_their_stage_by_name():
    assert stage_of("thermod-scheduler") == "scheduler"
    assert stage_of("thermod-deconv1") == "worker_threads"
    assert stage_of("thermod-gyro") == "gyro_driver"
    assert stage_of("MainThread") == "main"
    assert stage_of("Thread-7") == "other"


def test_a_busy_child_shows_under_solves():
    meter = CpuMeter()
    assert meter.sample()["stages"] == {}                     # the first reading opens the period
    child = subprocess.Popen([sys.executable, "-c", "import sys, time\nsys.stdin.read()\n"
                              "t = time.process_time() + 0.3\nwhile time.process_time() < t: pass\n"
                              "time.sleep(30)"], stdin=subprocess.PIPE)
    try:
        time.sleep(0.5)                                      # its start-up, before the period
        meter.sample(child_pids=[child.pid])
        c0 = process_cpu_s(child.pid)
        child.stdin.close()
        deadline = time.monotonic() + 20
        while process_cpu_s(child.pid) - c0 < 0.29 and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.1)
        out = meter.sample(child_pids=[child.pid])
        time.sleep(0.2)
        tail = meter.sample(child_pids=[child.pid])
    finally:
        child.kill()
        child.wait()
    booked = out["stages"]["solves"] * out["interval_s"] / 100
    assert booked == pytest.approx(0.3, abs=0.05)
    assert tail["stages"].get("solves", 0) < 5                # asleep now: nothing more is booked


def test_a_thread_is_booked_its_cpu_between_two_readings():
    meter = CpuMeter()
    go, spun, stop = threading.Event(), threading.Event(), threading.Event()

    def work():
        go.wait()
        spin(0.25)
        spun.set()
        stop.wait()

    th = threading.Thread(target=work, name="thermod-publish")
    th.start()
    try:
        meter.sample()
        go.set()
        assert spun.wait(20)
        out = meter.sample()
    finally:
        stop.set()
        th.join()
    assert out["stages"]["publish"] * out["interval_s"] / 100 == pytest.approx(0.25, abs=0.03)


def test_the_simulated_payload_is_moved_out_of_the_driver_threads():
    meter = CpuMeter()
    go, spun, stop = threading.Event(), threading.Event(), threading.Event()
    th = threading.Thread(target=lambda: (go.wait(), spin(0.2), spun.set(), stop.wait()), name="thermod-gyro")
    th.start()
    try:
        meter.sample(sim_cpu_s=1.0)
        go.set()
        assert spun.wait(20)
        out = meter.sample(sim_cpu_s=1.15)        # 0.15 s of the gyro thread's 0.2 s emulated the chip
    finally:
        stop.set()
        th.join()
    dt = out["interval_s"]
    assert out["stages"]["sim_payload"] * dt / 100 == pytest.approx(0.15, abs=0.01)
    assert out["stages"]["gyro_driver"] * dt / 100 == pytest.approx(0.05, abs=0.03)
    assert out["parent_without_sim"] == pytest.approx(out["parent"] - out["stages"]["sim_payload"], abs=0.11)


def test_stage_times_give_p50_and_p99_in_ms_and_ignore_missing_values():
    st = StageTimes(keep=100)
    for i in range(100):
        st.add(solve=(i + 1) / 1e3, queue=None, render=-1.0)
    s = st.summary()
    assert set(s) == {"solve"}
    assert s["solve"][0] == pytest.approx(50.5, abs=0.01) and s["solve"][1] == pytest.approx(99.01, abs=0.01)


def test_the_gyro_process_is_its_own_stage_and_its_emulation_is_the_payloads():
    """A child spinning 0.3 s, 0.2 s of which emulated the chip (reported by the child): gyro_process
    0.1 s, sim_payload 0.2 s, and the overhead is the parent's plus the gyro process's."""
    meter = CpuMeter()
    child = subprocess.Popen([sys.executable, "-c", "import sys, time\nsys.stdin.readline()\n"
                              "t = time.process_time()\nwhile time.process_time() - t < 0.3: pass\n"
                              "print(flush=True)\nsys.stdin.readline()"],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        time.sleep(0.3)          # its interpreter's start-up, before the first reading
        meter.sample(gyro_pids=(child.pid,), sim_cpu_s=0.0, gyro_sim_cpu_s=2.0)
        child.stdin.write("go\n")
        child.stdin.flush()
        assert child.stdout.readline() == "\n"
        out = meter.sample(gyro_pids=(child.pid,), sim_cpu_s=0.0, gyro_sim_cpu_s=2.2)
    finally:
        child.stdin.write("end\n")
        child.stdin.flush()
        child.wait(10)
    dt = out["interval_s"]
    assert out["stages"]["gyro_process"] * dt / 100 == pytest.approx(0.1, abs=0.04)
    assert out["stages"]["sim_payload"] * dt / 100 == pytest.approx(0.2, abs=0.01)
    assert out["parent_without_sim"] == pytest.approx(out["parent"], abs=0.11)   # none of it in the parent
    overhead = out["parent"] + out["stages"]["gyro_process"]
    assert out["overhead_without_sim"] == pytest.approx(overhead, abs=0.11)


def test_watch_prints_the_breakdown_from_health():
    h = {"cpu": {"stages": {"solves": 120.0, "scheduler": 15.0, "gyro_driver": 4.0, "sim_payload": 10.0},
                 "parent": 29.0, "parent_without_sim": 19.0},
         "pipeline": {"stage_ms": {"queue": [0.3, 12.5], "solve": [20.1, 41.0]}}}
    lines = cpu_lines(h)
    assert lines[0] == ("cpu % core   solves 120.0, the rest 19.0 (scheduler 15.0, gyro_driver 4.0), "
                        "simulated payload 10.0")
    assert lines[1] == "stage ms     queue 0.3/12.5, solve 20.1/41.0 (p50/p99)"
    assert cpu_lines({}) == []
    # a daemon whose gyro reads in its own process: the rest is the parent's and that process's
    h["cpu"] = {"stages": {"solves": 120.0, "gyro_process": 6.0, "scheduler": 15.0, "sim_payload": 10.0},
                "parent": 29.0, "parent_without_sim": 19.0, "overhead_without_sim": 25.0}
    assert cpu_lines(h)[0] == ("cpu % core   solves 120.0, the rest 25.0 (scheduler 15.0, gyro_process 6.0), "
                               "simulated payload 10.0")


def test_a_cgroup_cpu_quota_caps_the_cores_the_workers_use(tmp_path):
    from thermod.runtime.cpu import cgroup_cpu_quota

    # cgroup v2: the tightest quota among the process's cgroup and its ancestors
    (tmp_path / "self").write_text("0::/system.slice/thermod.service\n")
    root = tmp_path / "fs"
    svc = root / "system.slice" / "thermod.service"
    svc.mkdir(parents=True)
    (root / "system.slice" / "cpu.max").write_text("max 100000\n")
    (svc / "cpu.max").write_text("120000 100000\n")
    assert cgroup_cpu_quota(str(tmp_path / "self"), str(root)) == pytest.approx(1.2)
    (root / "system.slice" / "cpu.max").write_text("50000 100000\n")
    assert cgroup_cpu_quota(str(tmp_path / "self"), str(root)) == pytest.approx(0.5)
    (svc / "cpu.max").write_text("max 100000\n")
    (root / "system.slice" / "cpu.max").write_text("max 100000\n")
    assert cgroup_cpu_quota(str(tmp_path / "self"), str(root)) is None
    # cgroup v1: the CFS quota of the cpu controller's hierarchy (-1: none)
    (tmp_path / "self1").write_text("4:memory:/x\n1:cpu,cpuacct:/bench\n")
    d = tmp_path / "v1" / "cpu,cpuacct" / "bench"
    d.mkdir(parents=True)
    (d / "cpu.cfs_quota_us").write_text("100000\n")
    (d / "cpu.cfs_period_us").write_text("100000\n")
    assert cgroup_cpu_quota(str(tmp_path / "self1"), str(tmp_path / "v1")) == pytest.approx(1.0)
    (d / "cpu.cfs_quota_us").write_text("-1\n")
    assert cgroup_cpu_quota(str(tmp_path / "self1"), str(tmp_path / "v1")) is None
    assert cgroup_cpu_quota(str(tmp_path / "missing")) is None


def test_the_monitor_gives_way_while_the_pipeline_is_short_of_cpu():
    """While frames are dropped for overload the calibration monitor does no work: it only counts the
    time it gave way (`yielded_s`), and starts again when the pipeline is no longer short."""
    from thermod.physics.calibration import Calibration
    from thermod.runtime.config import MonitorConfig
    from thermod.runtime.monitor import Monitor
    from thermod.runtime.rings import FrameRing, GyroRing

    short = threading.Event()
    short.set()
    m = Monitor(MonitorConfig(), GyroRing(1000), FrameRing(4, (120, 160)), lambda: Calibration(),
                short_of_cpu=short.is_set)
    steps = []
    m._step = lambda: steps.append(1) or False
    m.start()
    try:
        time.sleep(0.6)
        assert steps == [] and m.counters["yielded_s"] >= 0.5
        short.clear()
        deadline = time.monotonic() + 10
        while not steps and time.monotonic() < deadline:
            time.sleep(0.02)
        assert steps
    finally:
        m.stop()


def test_one_overload_drop_is_a_stall_three_are_a_shortage():
    import collections

    from thermod.runtime.pipeline import SHORT_OF_CPU_DROPS, Pipeline

    p = Pipeline.__new__(Pipeline)            # the rule alone, without rings and workers
    p._overload_drops = collections.deque(maxlen=SHORT_OF_CPU_DROPS)
    now = time.monotonic()
    p._overload_drops.append(now)
    assert not p.short_of_cpu()
    p._overload_drops.extend([now, now])
    assert p.short_of_cpu() and not p.short_of_cpu(hold_s=0.0)
    p._overload_drops.extend([now - 30, now - 20, now - 11])
    assert not p.short_of_cpu()
