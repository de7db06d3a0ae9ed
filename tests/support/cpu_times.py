"""CPU time per test, a plugin of tests/conftest.py (`pytest_plugins`).

With THERMOD_CPU_TIMES set (to a number N, or to a file path), the run ends with the N slowest tests
by CPU (default 10) and the total; benchmarks/test_time.py compares two runs."""

import os

import pytest

# CPU time per test: with THERMOD_CPU_TIMES set (to a number N, or to a file path), the run ends with
# the N slowest tests by CPU (default 10) and the total; a path gets a "seconds<TAB>test" line as each
# test ends (so a run cut short still has its numbers). CPU, not wall time, because the machine is
# shared. Each phase (setup, call, teardown) counts this process's time.process_time() plus the CPU of
# the child processes it reaped (getrusage(RUSAGE_CHILDREN): daemons, ffmpeg). A module fixture's
# cost falls on the test that first needs it. Under xdist the numbers ride on the reports.
CPU_TIMES = os.environ.get("THERMOD_CPU_TIMES")


def _cpu_now() -> float:
    import resource
    import time
    ch = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + ch.ru_utime + ch.ru_stime


if CPU_TIMES:
    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_setup(item):
        t0 = _cpu_now()
        yield
        item.__dict__.setdefault("_cpu_s", {})["setup"] = _cpu_now() - t0

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_call(item):
        t0 = _cpu_now()
        yield
        item.__dict__.setdefault("_cpu_s", {})["call"] = _cpu_now() - t0

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_teardown(item):
        t0 = _cpu_now()
        yield
        item.__dict__.setdefault("_cpu_s", {})["teardown"] = _cpu_now() - t0

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_makereport(item, call):
        outcome = yield
        outcome.get_result().cpu_s = item.__dict__.get("_cpu_s", {}).get(call.when, 0.0)

    _CPU_BY_TEST: dict[str, float] = {}
    _WORKER = [False]       # an xdist worker: its controller logs the reports it forwards

    def pytest_configure(config):
        _WORKER[0] = hasattr(config, "workerinput")

    def pytest_runtest_logreport(report):
        cpu = float(getattr(report, "cpu_s", 0.0))
        _CPU_BY_TEST[report.nodeid] = _CPU_BY_TEST.get(report.nodeid, 0.0) + cpu
        if report.when == "teardown" and not CPU_TIMES.isdigit() and not _WORKER[0]:
            with open(CPU_TIMES, "a", encoding="utf-8") as f:
                f.write(f"{_CPU_BY_TEST[report.nodeid]:.2f}\t{report.nodeid}\n")

    def pytest_terminal_summary(terminalreporter):
        ranked = sorted(_CPU_BY_TEST.items(), key=lambda kv: -kv[1])
        n = int(CPU_TIMES) if CPU_TIMES.isdigit() else 10
        tr = terminalreporter
        tr.section(f"CPU time per test (process + reaped children), {n} slowest")
        for nodeid, s in ranked[:n]:
            tr.write_line(f"{s:8.1f} s  {nodeid}")
        tr.write_line(f"{sum(_CPU_BY_TEST.values()) / 60:8.2f} CPU-min in {len(ranked)} tests")
