"""Where the daemon's time goes: CPU per stage (threads and solver children) and latency per stage.

`CpuMeter` reads every thread's and each solver child's utime + stime (``/proc/self/task/TID/stat``,
``/proc/PID/stat``), and reports each stage's share of one core over the interval
since its last reading. A thread belongs to the stage its name starts with (`THREAD_STAGES`); the
simulated payload's own work (emulating the IMU's FIFO, adding the camera's noise) runs inside the
driver threads, so the payload counts it (`thermod.sim.payload.SimPayload.cpu_s`) and the meter moves
it from the drivers to ``sim_payload``: a real payload does not pay it.

`StageTimes` keeps the last frames' wall time per pipeline stage (gyro wait, render, queue, solve,
prior wait, reorder, publish) and reports p50 / p99 in ms.
"""

from __future__ import annotations

import collections
import math
import os
import threading
import time
from pathlib import Path

import numpy as np

# thread-name prefix → stage, first match wins
THREAD_STAGES = (
    ("thermod-gyro", "gyro_driver"),
    ("thermod-camera", "camera_driver"),
    ("thermod-scheduler", "scheduler"),
    ("thermod-deconv", "worker_threads"),
    ("thermod-publish", "publish"),
    ("thermod-monitor", "monitor"),
    ("thermod-rtsp", "rtsp"),
    ("MainThread", "main"),
)
PIPELINE_STAGES = ("arrival", "gyro_wait", "render", "queue", "solve", "prior_wait", "reorder", "publish")
_TICK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def stage_of(thread_name: str) -> str:
    return next((s for prefix, s in THREAD_STAGES if thread_name.startswith(prefix)), "other")


def _thread_cpu_s(th: threading.Thread) -> float | None:
    """A thread's CPU time from /proc (never its pthread CPU clock: asking that of a thread that has
    just ended, still listed by `threading.enumerate`, is undefined behaviour and crashed a process)."""
    tid = th.native_id
    if tid is None or not th.is_alive():
        return None
    return _stat_cpu_s(f"/proc/self/task/{tid}/stat")


def process_cpu_s(pid: int) -> float | None:
    """utime + stime of process `pid` (s), None when it is gone."""
    return _stat_cpu_s(f"/proc/{pid}/stat")


def _stat_cpu_s(path: str) -> float | None:
    try:
        with open(path, "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / _TICK
    except (OSError, IndexError, ValueError):
        return None


class CpuMeter:
    """Per-stage CPU shares (% of one core) between two calls of `sample`."""

    def __init__(self) -> None:
        self._last: dict[object, float] = {}
        self._t: float | None = None
        self._proc: float | None = None

    def sample(self, child_pids=(), sim_cpu_s: float | None = None, now: float | None = None,
               gyro_pids=(), gyro_sim_cpu_s: float | None = None) -> dict:
        """``{"stages": {stage: %}, "parent": %, "parent_without_sim": %, "overhead_without_sim": %,
        "interval_s": s}`` since the last call (empty stages on the first). `child_pids` are the solver
        children (stage ``solves``), `gyro_pids` the gyro process (``gyro_process``); `sim_cpu_s` and
        `gyro_sim_cpu_s` the payload's emulation CPU so far in this process and in the gyro process.
        The overhead is everything but the solves and the emulation: the parent and the gyro process."""
        now = time.monotonic() if now is None else now
        used: dict[str, float] = collections.defaultdict(float)
        seen: dict[object, float] = {}
        for th in threading.enumerate():
            c = _thread_cpu_s(th)
            if c is None:
                continue
            key = ("t", th.native_id)
            seen[key] = c
            if key in self._last:
                used[stage_of(th.name)] += max(0.0, c - self._last[key])
        for stage, pids in (("solves", child_pids), ("gyro_process", gyro_pids)):
            for pid in pids:
                c = process_cpu_s(pid)
                if c is None:
                    continue
                key = ("p", pid)
                seen[key] = c
                if key in self._last:
                    used[stage] += max(0.0, c - self._last[key])
        for key, total in (("sim", sim_cpu_s), ("gyro_sim", gyro_sim_cpu_s)):
            if total is not None:
                seen[key] = total
        proc = time.process_time()
        dt = None if self._t is None else now - self._t
        out: dict = {"interval_s": dt, "stages": {}}
        if dt and dt > 0:
            # the payload's work ran in the drivers: moved from them to sim_payload
            parent_sim = self._move_sim(used, seen, "sim", ("gyro_driver", "camera_driver"))
            self._move_sim(used, seen, "gyro_sim", ("gyro_process",))
            out["stages"] = {k: round(100.0 * v / dt, 1) for k, v in sorted(used.items())}
            out["parent"] = round(100.0 * (proc - self._proc) / dt, 1)
            out["parent_without_sim"] = round(out["parent"] - 100.0 * parent_sim / dt, 1)
            gyro = out["stages"].get("gyro_process", 0.0)
            out["overhead_without_sim"] = round(out["parent_without_sim"] + gyro, 1)
        self._last, self._t, self._proc = seen, now, proc
        return out

    def _move_sim(self, used: dict, seen: dict, key: str, stages: tuple[str, ...]) -> float:
        """Move the emulation CPU `key` spent since the last call from `stages` to ``sim_payload``."""
        if key not in seen or key not in self._last:
            return 0.0
        sim = left = max(0.0, seen[key] - self._last[key])
        for s in stages:
            take = min(left, used.get(s, 0.0))
            used[s] = used.get(s, 0.0) - take
            left -= take
        used["sim_payload"] = used.get("sim_payload", 0.0) + sim
        return sim


class StageTimes:
    """Wall time per pipeline stage over the last `keep` frames (thread-safe)."""

    def __init__(self, keep: int = 512) -> None:
        self._d = {s: collections.deque(maxlen=keep) for s in PIPELINE_STAGES}
        self._lock = threading.Lock()

    def add(self, **seconds: float) -> None:
        with self._lock:
            for k, v in seconds.items():
                if v is not None and v >= 0:
                    self._d[k].append(v)

    def summary(self) -> dict:
        """``{stage: [p50 ms, p99 ms]}`` for the stages with samples."""
        with self._lock:
            arrays = {k: np.fromiter(d, float) for k, d in self._d.items() if d}
        return {k: [round(1e3 * float(np.percentile(a, 50)), 2), round(1e3 * float(np.percentile(a, 99)), 2)]
                for k, a in arrays.items()}


def cgroup_cpu_quota(proc_cgroup: str = "/proc/self/cgroup", root: str = "/sys/fs/cgroup") -> float | None:
    """The CPU quota of this process's cgroup in cores (cgroup v2 ``cpu.max``, v1 CFS quota; the
    tightest of its ancestors), or None when there is none. systemd's ``CPUQuota=`` sets it."""
    try:
        lines = Path(proc_cgroup).read_text().splitlines()
    except OSError:
        return None
    found = []
    for line in lines:
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        _, controllers, path = parts
        if controllers == "":
            base, files = Path(root), ("cpu.max",)
        elif "cpu" in controllers.split(","):
            base = Path(root) / controllers if (Path(root) / controllers).is_dir() else Path(root) / "cpu"
            files = ("cpu.cfs_quota_us",)
        else:
            continue
        d = base / path.lstrip("/")
        while True:
            q = _quota_at(d, files[0])
            if q is not None:
                found.append(q)
            if d == base or d.parent == d:
                break
            d = d.parent
    return min(found) if found else None


def _quota_at(d: Path, name: str) -> float | None:
    try:
        if name == "cpu.max":
            quota, period = (d / name).read_text().split()[:2]
            return None if quota == "max" else int(quota) / int(period)
        quota = int((d / name).read_text())
        return None if quota < 0 else quota / int((d / "cpu.cfs_period_us").read_text())
    except (OSError, ValueError):
        return None


def usable_cpus() -> int:
    """The cores this process's solves may use: its CPU affinity, capped by its cgroup's CPU quota
    rounded down (1.2 cores of quota: one, at least one). The daemon's own threads need a share of
    the quota too, and two solves on a quota short of two cores are stalled together by its
    throttling (measured at 1.2 cores: benchmarks/results/payload.md)."""
    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:   # pragma: no cover - non-Linux
        n = os.cpu_count() or 1
    q = cgroup_cpu_quota()
    if q is not None and q > 0:
        n = min(n, math.floor(q + 1e-6))
    return max(1, n)
