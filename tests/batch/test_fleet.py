"""`thermod deblur --scheduler`: a fleet of recordings on a real Dask `LocalCluster` (2 worker
processes) writes the same bytes as the local run, a corrupt file fails alone, and a scheduler that
does not answer or workers that do not share the output directory are one-line errors."""

import os
import shutil
import socket
import subprocess
import sys

import numpy as np
import pytest

from thermod.batch import cluster
from thermod.cli import main
from thermod.io import recording
from thermod.physics.calibration import Calibration
from thermod.sim import synth

MOTIONS = ("roll:60", "pan:40", "tilt:30")


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """Three 160×120 recordings of 10 frames (rolling, panning, tilting) and a truncated copy of one."""
    d = tmp_path_factory.mktemp("fleet")
    calib = Calibration(width=160, height=120, cx=79.5, cy=59.5)
    paths = []
    for i, motion in enumerate(MOTIONS):
        rec = synth.simulate("texture", motion, seconds=0.2, calib=calib, seed=i, truth=False,
                             effects={"netd": 0.03})
        assert rec.n_frames == 10
        paths.append(d / f"rec{i}.h5")
        recording.write(paths[-1], rec)
    corrupt = d / "corrupt.h5"
    data = paths[0].read_bytes()
    corrupt.write_bytes(data[: len(data) // 2])      # a copy cut short mid-transfer
    return paths, corrupt


@pytest.fixture(scope="module")
def wisdom(tmp_path_factory):
    """A private FFTW wisdom file for the module, inherited by the cluster's workers: the default
    ~/.cache/thermod is rewritten by any thermod process on the machine, and a plan measured anew can
    round differently (same values to ~1e-6 of the range, other bits)."""
    old = os.environ.get("THERMOD_CACHE_DIR")
    os.environ["THERMOD_CACHE_DIR"] = str(tmp_path_factory.mktemp("wisdom"))
    yield os.environ["THERMOD_CACHE_DIR"]
    if old is None:
        del os.environ["THERMOD_CACHE_DIR"]
    else:
        os.environ["THERMOD_CACHE_DIR"] = old


@pytest.fixture(scope="module")
def local_cluster(wisdom):
    import distributed  # in the test extra: a missing engine fails, never skips
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                                  silence_logs=40) as c:
        yield c


def deblur(capsys, *argv):
    rc = main(["deblur", *map(str, argv)])
    out, err = capsys.readouterr()
    return rc, out, err


def summary_counts(text):
    """Per-file "A → B: n deblurred, m passed through" parts (timings differ between runs)."""
    return sorted(line.split(", ")[0] + line.split(", ")[1] for line in text.splitlines() if " → " in line)


@pytest.mark.slow
def test_cluster_writes_the_local_runs_bytes_and_a_corrupt_file_fails_alone(fleet, local_cluster, tmp_path,
                                                                            capsys):
    paths, corrupt = fleet
    inputs = [paths[0], corrupt, paths[1], paths[2]]
    # the local run first, in a fresh process: it plans the FFTs and leaves the wisdom the workers load
    local = subprocess.run([sys.executable, "-m", "thermod.cli", "deblur", *map(str, inputs), "-o",
                            str(tmp_path / "local")], capture_output=True, text=True, timeout=600)
    rc_local, out_local, err_local = local.returncode, local.stdout, local.stderr
    address = local_cluster.scheduler_address
    rc, out, err = deblur(capsys, *inputs, "-o", tmp_path / "fleet", "--scheduler", address)

    assert rc == rc_local == 2
    lines = err.strip().splitlines()
    summary = f"thermod deblur: 1 of 4 file(s) failed: {corrupt}"
    assert lines[-1] == err_local.strip().splitlines()[-1] == summary
    failures = [ln for ln in lines if ln.startswith("thermod deblur: error:")]
    assert len(failures) == 1 and f"{corrupt}: file: not a readable HDF5 file" in failures[0]
    assert "Traceback" not in err
    workers = set(local_cluster.scheduler_info["workers"])
    for p in paths:                       # per file: started on a worker, then done with its frames
        started = [ln for ln in lines if ln.startswith(f"thermod deblur: {p}: started on ")]
        done = [ln for ln in lines if ln.startswith(f"thermod deblur: {p}: done, 10 frames in ")]
        assert len(started) == len(done) == 1, err
        assert started[0].rsplit(" ", 1)[1] in workers and done[0].rsplit(" ", 1)[1] in workers
        assert lines.index(started[0]) < lines.index(done[0])
    assert summary_counts(out) == [s.replace(str(tmp_path / "local"), str(tmp_path / "fleet"))
                                   for s in summary_counts(out_local)]
    assert "3 file(s) in" in out and f"on {address}" in out

    names = sorted(p.name for p in paths)
    assert sorted(p.name for p in (tmp_path / "fleet").iterdir()) == names      # no .part left, no corrupt.h5
    assert sorted(p.name for p in (tmp_path / "local").iterdir()) == names
    for name in names:
        fleet_bytes = (tmp_path / "fleet" / name).read_bytes()
        assert fleet_bytes == (tmp_path / "local" / name).read_bytes(), name
    res = recording.read(tmp_path / "fleet" / paths[0].name)
    assert res.deblurred.shape == (10, 120, 160) and not np.array_equal(res.deblurred, res.frames)


@pytest.mark.slow
def test_workers_that_do_not_share_the_output_directory_stop_the_run(fleet, local_cluster, tmp_path, require):
    """The client in its own mount namespace with a tmpfs over the output directory: it writes there,
    the workers (outside) see the real, empty directory — the run a missing shared filesystem makes."""
    ok = shutil.which("unshare") is not None and subprocess.run(
        ["unshare", "-m", "true"], capture_output=True).returncode == 0
    require(ok, "unshare -m (a mount namespace, to give the client a filesystem the workers lack)")
    out = tmp_path / "out"
    out.mkdir()
    cli = [sys.executable, "-m", "thermod.cli", "deblur", str(fleet[0][0]), "-o", f"{out}/",
           "--scheduler", local_cluster.scheduler_address]
    script = f"mount -t tmpfs none {out} && exec \"$@\""
    p = subprocess.run(["unshare", "-m", "sh", "-c", script, "sh", *cli], capture_output=True, text=True,
                       timeout=300)
    assert p.returncode == 2, p.stderr
    assert p.stderr.count("\n") == 1 and "Traceback" not in p.stderr, p.stderr
    assert p.stderr.startswith("thermod deblur: error: --scheduler: worker tcp://"), p.stderr
    assert f"does not see {out} as this machine does" in p.stderr and "shared filesystem" in p.stderr
    assert list(out.iterdir()) == []      # nothing was submitted


@pytest.mark.slow
def test_a_worker_killed_mid_file_costs_a_retry_not_the_file(tmp_path, local_cluster, capsys, monkeypatch):
    """SIGKILL the worker the moment it announces a file (a crash, an OOM kill): the scheduler hands
    the task to another worker, the file is written whole there, with the local run's bytes, and no
    ``.part`` of the dead worker's attempt is left."""
    import signal

    import distributed

    calib = Calibration(width=160, height=120, cx=79.5, cy=59.5)
    src = tmp_path / "long.h5"        # long enough (60 frames) that the kill lands while it is deblurred
    recording.write(src, synth.simulate("texture", "roll:60", seconds=1.2, calib=calib, seed=7, truth=False,
                                        effects={"netd": 0.03}))
    local = subprocess.run([sys.executable, "-m", "thermod.cli", "deblur", str(src), "-o",
                            str(tmp_path / "local.h5")], capture_output=True, text=True, timeout=600)
    assert local.returncode == 0, local.stderr
    with distributed.Client(local_cluster.scheduler_address, set_as_default=False) as c:
        pids = c.run(os.getpid)
    killed = []

    class KillOnStart(cluster.Lines):
        def started(self, job, worker):
            super().started(job, worker)
            if not killed and worker in pids:
                os.kill(pids[worker], signal.SIGKILL)
                killed.append(worker)

    monkeypatch.setattr(cluster, "Lines", KillOnStart)
    address = local_cluster.scheduler_address
    rc, _, err = deblur(capsys, src, "-o", tmp_path / "fleet.h5", "--scheduler", address)
    assert killed, err
    assert rc == 0, err
    done = [ln for ln in err.splitlines() if ln.startswith(f"thermod deblur: {src}: done, 60 frames in ")]
    assert len(done) == 1 and not done[0].endswith(killed[0]), err     # finished elsewhere
    assert (tmp_path / "fleet.h5").read_bytes() == (tmp_path / "local.h5").read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith("fleet")) == ["fleet.h5"]
    with distributed.Client(local_cluster.scheduler_address, set_as_default=False) as c:
        c.wait_for_workers(2, timeout=120)     # the nanny restarted it: the module's cluster stays whole


def spawned_workers(pid):
    """PIDs of `pid`'s multiprocessing worker processes (spawned: `spawn_main` in their command line)."""
    out = []
    for task in os.listdir(f"/proc/{pid}/task"):
        try:
            kids = open(f"/proc/{pid}/task/{task}/children").read().split()
        except OSError:
            continue
        for k in kids:
            try:
                cmd = open(f"/proc/{k}/cmdline", "rb").read()
            except OSError:
                continue
            if b"spawn_main" in cmd:
                out.append(int(k))
    return out


@pytest.mark.slow
def test_local_processes_write_the_in_process_bytes_and_survive_a_killed_worker(fleet, wisdom, tmp_path):
    """`--jobs 2` (the default on 2 cores): the files in two local processes. One of them is SIGKILLed
    while it writes its file: that file starts again in a new pool, every output is whole and has the
    in-process (`--jobs 1`) run's bytes, and the corrupt file still fails alone."""
    import signal
    import time

    paths, corrupt = fleet
    calib = Calibration(width=160, height=120, cx=79.5, cy=59.5)
    longer = []
    for i in range(2):          # 60 frames each, so a worker is caught mid-file
        longer.append(tmp_path / f"long{i}.h5")
        rec = synth.simulate("texture", "roll:60", seconds=1.2, calib=calib, seed=10 + i, truth=False,
                             effects={"netd": 0.03})
        recording.write(longer[-1], rec)
    inputs = [*longer, corrupt, *paths]
    cli = [sys.executable, "-m", "thermod.cli", "deblur", *map(str, inputs), "-o"]
    here = subprocess.run([*cli, str(tmp_path / "here"), "--jobs", "1"], capture_output=True, text=True,
                          timeout=600)
    assert here.returncode == 2, here.stderr
    out = tmp_path / "pool"
    p = subprocess.Popen([*cli, str(out), "--jobs", "2"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True)
    killed = None
    deadline = time.monotonic() + 300
    while killed is None and p.poll() is None and time.monotonic() < deadline:
        workers = spawned_workers(p.pid)
        if out.is_dir() and any(f.name.endswith(".part") for f in out.iterdir()) and workers:
            killed = workers[0]
            os.kill(killed, signal.SIGKILL)
        time.sleep(0.05)
    stdout, stderr = p.communicate(timeout=600)
    assert killed is not None, stderr
    assert p.returncode == 2, stderr
    assert stderr.strip().splitlines()[-1] == f"thermod deblur: 1 of 6 file(s) failed: {corrupt}"
    assert "Traceback" not in stderr
    assert sorted(summary_counts(stdout)) == sorted(
        s.replace(str(tmp_path / "here"), str(out)) for s in summary_counts(here.stdout))
    names = sorted(q.name for q in [*longer, *paths])
    assert sorted(q.name for q in out.iterdir()) == names           # no .part left
    for name in names:
        assert (out / name).read_bytes() == (tmp_path / "here" / name).read_bytes(), name


def test_a_negative_jobs_count_is_one_line(fleet, tmp_path, capsys):
    rc, _, err = deblur(capsys, fleet[0][0], "-o", tmp_path / "o.h5", "--jobs", "-1")
    assert rc == 2 and "--jobs -1: expected 0 (one process per usable core) or a positive number" in err


def test_a_scheduler_that_does_not_answer_is_one_line_within_the_connect_timeout(fleet, tmp_path):
    """A port that accepts connections but never speaks Dask's protocol (a hung or wrong service)."""
    with socket.socket() as silent:
        silent.bind(("127.0.0.1", 0))
        silent.listen(8)                  # the kernel completes the handshakes; nobody ever replies
        address = f"tcp://127.0.0.1:{silent.getsockname()[1]}"
        cmd = [sys.executable, "-m", "thermod.cli", "deblur", str(fleet[0][0]), "-o", str(tmp_path / "o.h5"),
               "--scheduler", address, "--connect-timeout", "1"]
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=120,
                           env={**os.environ, "PYTHONWARNINGS": "ignore"})
    assert p.returncode == 2
    assert p.stderr.startswith(f"thermod deblur: error: --scheduler {address}: no Dask scheduler answered "
                               "within 1 s"), p.stderr
    assert p.stderr.count("\n") == 1 and "Traceback" not in p.stderr, p.stderr
    assert not (tmp_path / "o.h5").exists() and not (tmp_path / "o.h5.part").exists()


def test_a_scheduler_without_workers_is_one_line_not_a_wait_forever(fleet, tmp_path, capsys):
    import distributed
    with distributed.LocalCluster(n_workers=0, processes=False, protocol="tcp", dashboard_address=":0",
                                  silence_logs=40) as c:
        rc, _, err = deblur(capsys, fleet[0][0], "-o", tmp_path / "o.h5", "--scheduler", c.scheduler_address,
                            "--connect-timeout", "1")
    assert rc == 2 and err.count("\n") == 1, err
    assert f"--scheduler {c.scheduler_address}: the scheduler has no workers (waited 1 s)" in err
    assert not (tmp_path / "o.h5").exists()


@pytest.mark.parametrize("address", ["localhost:8786", "tcp://", "http://h:8786", "tcp://h:port"])
def test_a_malformed_scheduler_address_is_refused_before_connecting(fleet, tmp_path, capsys, address):
    rc, _, err = deblur(capsys, fleet[0][0], "-o", tmp_path / "o.h5", "--scheduler", address)
    assert rc == 2 and f"--scheduler {address}: expected a Dask scheduler address like tcp://HOST:8786" in err


def test_probe_names_a_directory_the_worker_sees_differently(tmp_path):
    """What a worker on another machine finds: the directory, but not this machine's marker in it."""
    token = "0123abcd"
    assert cluster._probe([(str(tmp_path), token)]) != []
    assert "does not see" in cluster._probe([(str(tmp_path), token)])[0]
    (tmp_path / f".thermod-fleet-{token}").write_text(token)
    assert cluster._probe([(str(tmp_path), token)]) == []
    assert sorted(p.name for p in tmp_path.iterdir()) == [f".thermod-fleet-{token}"]   # its own file removed


def test_local_runs_and_the_core_import_no_dask_distributed():
    """The cluster engine is loaded only with --scheduler; the core never imports it. (dask itself may
    appear: pyfftw's `interfaces` imports dask.array whenever dask is installed.)"""
    mods = ["thermod.physics.deconv", "thermod.io.recording", "thermod.calib.forward", "thermod.batch.job",
            "thermod.batch.local", "thermod.batch.progress", "thermod.cli.deblur"]
    code = ("import importlib, sys\n"
            f"for m in {mods!r}: importlib.import_module(m)\n"
            "print(sorted(m for m in sys.modules\n"
            "             if m.split('.')[0] == 'distributed' or m == 'thermod.batch.cluster'))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]"
