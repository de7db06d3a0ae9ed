import os
import subprocess
import sys

import pytest

from thermod import cli


def test_usage_lists_every_command(capsys):
    assert cli.main([]) == 2
    out = capsys.readouterr().out
    for name in cli.COMMANDS:
        assert name in out


def test_unknown_command(capsys):
    assert cli.main(["frobnicate"]) == 2
    assert "unknown command 'frobnicate'" in capsys.readouterr().err


def test_every_command_module_has_the_command_interface():
    import importlib
    for name, (module, _) in cli.COMMANDS.items():
        m = importlib.import_module(module)
        assert callable(m.add_arguments) and callable(m.run), name


def test_console_script_help_runs():
    r = subprocess.run([sys.executable, "-m", "thermod.cli", "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and "deblur" in r.stdout


def test_unexpected_error_is_one_line_and_v_shows_the_traceback(monkeypatch, capsys):
    """A bug in a command: exit 1 with one line naming the command; -v adds the traceback."""
    from thermod.cli import sim

    def broken(args):
        return {}["missing"]
    monkeypatch.setattr(sim, "run", broken)
    assert cli.main(["sim", "-o", "x.h5"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("thermod sim: internal error: KeyError: 'missing'") and "-v" in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert cli.main(["sim", "-v", "-o", "x.h5"]) == 1
    err = capsys.readouterr().err
    assert "Traceback" in err and "broken" in err


def test_thermod_error_exits_2_without_traceback(monkeypatch, capsys):
    from thermod.cli import sim
    from thermod.errors import ThermodError

    def refuses(args):
        raise ThermodError("x.h5: camera/t: expected floats")
    monkeypatch.setattr(sim, "run", refuses)
    assert cli.main(["sim", "-o", "x.h5"]) == 2
    assert capsys.readouterr().err == "thermod sim: error: x.h5: camera/t: expected floats\n"


def test_bench_finds_the_benchmarks_of_the_checkout(tmp_path):
    """`thermod bench` in a checkout reaches benchmarks/ (which lists its suites for an unknown name),
    whether started at the checkout's root or in a subdirectory; elsewhere it says where it looked."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    for cwd in (root, root / "docs"):
        r = subprocess.run([sys.executable, "-m", "thermod.cli", "bench", "no_such_suite"], cwd=cwd,
                           capture_output=True, text=True, timeout=60)
        assert r.returncode == 2 and "available:" in r.stderr, r.stderr
    # outside a checkout the package's own checkout is used (an editable install)
    r = subprocess.run([sys.executable, "-m", "thermod.cli", "bench", "no_such_suite"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "available:" in r.stderr, r.stderr


def test_a_failed_deblur_prints_no_per_frame_time(tmp_path, capsys):
    """A run whose only input fails has no frames to time: it names the failure, not "0 frames …
    53.0 ms/frame" (the wall time of the failure divided by one)."""
    bad = tmp_path / "bad.h5"
    bad.write_text("not HDF5")
    rc = cli.main(["deblur", str(bad), "-o", str(tmp_path / "out.h5"), "--jobs", "1"])
    out, err = capsys.readouterr()
    assert rc == 2
    assert "ms/frame" not in out and "0 frames" not in out, out
    assert f"1 of 1 file(s) failed: {bad}" in err and "not a readable HDF5 file" in err, err


@pytest.mark.parametrize("argv, name", [
    (["watch", "--endpoint", "tcp://127.0.0.1:9", "--seconds", "0"], "--seconds"),
    (["watch", "--endpoint", "tcp://127.0.0.1:9", "--seconds", "nan"], "--seconds"),
    (["watch", "--endpoint", "tcp://127.0.0.1:9", "--timeout", "-1"], "--timeout"),
    (["watch", "--endpoint", "tcp://127.0.0.1:9", "--interval", "inf"], "--interval"),
    (["record", "-o", "OUT/r.h5", "--endpoint", "tcp://127.0.0.1:9", "--seconds", "nan"], "--seconds"),
])
def test_time_options_are_checked_before_anything_runs(tmp_path, capsys, argv, name):
    """Found by a sweep of bad inputs: these exited 1 (an internal error by the exit-status rule)
    after waiting for a publisher; a bad number is exit 2 naming the option, at once."""
    argv = [a.replace("OUT", str(tmp_path)) for a in argv]
    assert cli.main(argv) == 2
    assert name in capsys.readouterr().err


def test_a_tiny_simulated_frame_and_a_fifo_in_the_report_directory(tmp_path):
    """`thermod sim` of an 8×8 frame (its texture's objects no larger than 6 px), then `thermod
    discrepancy` refusing, before its analysis, a report file that is a FIFO (the write would block)."""
    rec = tmp_path / "s8.h5"
    assert cli.main(["sim", "-o", str(rec), "--width", "8", "--height", "8", "--seconds", "0.3",
                     "--no-progress"]) == 0
    out = tmp_path / "rep"
    out.mkdir()
    os.mkfifo(out / "report.md")
    r = subprocess.run([sys.executable, "-m", "thermod.cli", "discrepancy", str(rec), "--out", str(out)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "report.md" in r.stderr and "regular file" in r.stderr, r.stderr


def test_run_takes_its_signals_before_the_daemon_is_imported():
    """`thermod run` installs its SIGTERM, SIGINT and SIGHUP handlers before it imports the daemon,
    numba or SciPy (0.8–2.6 s on a loaded 2-core payload): a stop or a reload sent during that time
    is taken, not fatal (SIGHUP's default action ends a process)."""
    probe = (
        "import signal, sys\n"
        "real = signal.signal\n"
        "def spy(sig, handler):\n"
        "    real(sig, handler)\n"
        "    if sig == signal.SIGHUP:\n"
        "        heavy = ('numba', 'scipy', 'thermod.runtime.daemon', 'thermod.runtime.config')\n"
        "        print(' '.join(m for m in heavy if m in sys.modules) or '-', flush=True)\n"
        "        import os; os._exit(0)\n"
        "signal.signal = spy\n"
        "from thermod.cli import main\n"
        "main(['run', '--seconds', '1'])\n")
    got = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert got.returncode == 0, got.stderr[-2000:]
    assert got.stdout.split() == ["-"], got.stdout


def test_a_signal_taken_while_the_main_thread_holds_the_events_lock_does_not_deadlock():
    """A signal handler runs in the main thread between any two bytecodes, so a SIGTERM can land while
    that thread holds the stop event's lock inside ``stop.wait`` (`Daemon.serve` waits 20 times a
    second), and a SIGHUP while it holds the reload event's inside ``clear``. Setting the event there
    from the handler deadlocked the daemon (systemd then kills it at TimeoutStopSec). In a process
    with a deadline, since a deadlock cannot be interrupted."""
    probe = (
        "import signal, threading\n"
        "from thermod.cli.run import signal_handlers\n"
        "stop, reload_req = threading.Event(), threading.Event()\n"
        "on_term, on_hup = signal_handlers(stop, reload_req)\n"
        "with stop._cond:\n"
        "    on_term(signal.SIGTERM, None)\n"
        "with reload_req._cond:\n"
        "    on_hup(signal.SIGHUP, None)\n"
        "assert stop.wait(30) and reload_req.wait(30)\n"
        "print('set', flush=True)\n")
    try:
        got = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60)
    except subprocess.TimeoutExpired:
        pytest.fail("the handler deadlocked on the event's lock")
    assert got.returncode == 0 and got.stdout.split() == ["set"], got.stderr[-2000:]


def test_ctrl_c_while_a_command_imports_exits_130_without_a_traceback(monkeypatch, capsys):
    """A Ctrl-C during the seconds a numerical command takes to import is the same exit as one during
    the command itself: 130, no KeyboardInterrupt traceback."""
    def interrupted(name):
        raise KeyboardInterrupt
    monkeypatch.setattr(cli.importlib, "import_module", interrupted)
    assert cli.main(["deblur", "x.h5"]) == 130
    assert "Traceback" not in capsys.readouterr().err
