"""The Dask executor: `thermod deblur --scheduler tcp://HOST:8786` runs each file as one task on a
Dask distributed cluster (`distributed.Client`), the same `run_job` as the local executor.

Assumption — a shared filesystem: every worker opens the inputs and writes the outputs (``DST.part``,
renamed when complete) at the same absolute paths as this machine, and so reads `--config`. Before
any task is submitted, `check_shared_output` has every worker read a marker this process wrote into
each output directory and create and remove a file there: a worker that cannot (no such mount,
another machine's local directory, no permission) stops the run with one line naming the worker and
the directory. A finished file that this machine cannot see is reported as failed.

Progress: each task logs a "started" event (`Worker.log_event`) that the client prints; a finished
task prints its frames, seconds and worker; a failed file one line naming it. A task the cluster
loses (its worker died) fails that file only. Bit-identical outputs need the same thermod, numpy and
FFT plans on the workers as here (one environment, FFTW wisdom in a shared `THERMOD_CACHE_DIR`).
"""

from __future__ import annotations

import logging
import os
import queue
import re
import threading
import time
import uuid
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

from thermod.batch.job import Job, Outcome, run_job
from thermod.batch.progress import Lines, Progress
from thermod.errors import ThermodError

log = logging.getLogger(__name__)

TOPIC = "thermod-deblur"
CONNECT_TIMEOUT_S = 10.0
POLL_S = 0.2
_ADDRESS = re.compile(r"^(tcp|tls|ws|wss|ucx)://[^\s/:]+(:\d+)?/?$|^(tcp|tls)://\[[0-9a-fA-F:.]+\](:\d+)?/?$")


class SchedulerError(ThermodError):
    """The Dask scheduler cannot be reached or used (names the address and what went wrong)."""


def _import_distributed():
    try:
        import distributed
    except ImportError as e:   # the optional extra: the payload's install leaves it out
        raise SchedulerError(f"--scheduler needs the 'distributed' package: pip install 'thermod[fleet]' "
                             f"({e})") from None
    return distributed


def connect(address: str, timeout_s: float = CONNECT_TIMEOUT_S):
    """A `distributed.Client` of the scheduler at `address`, with at least one worker, or a
    SchedulerError naming the address within about `timeout_s` (twice at worst: connect, workers)."""
    if not _ADDRESS.match(address):
        raise SchedulerError(f"--scheduler {address}: expected a Dask scheduler address like tcp://HOST:8786")
    if not timeout_s > 0:
        raise SchedulerError(f"--connect-timeout {timeout_s}: expected a positive number of seconds")
    distributed = _import_distributed()
    quiet = [logging.getLogger(n)
             for n in ("distributed.client", "distributed.comm.core", "distributed.core")]
    levels = [q.level for q in quiet]
    for q in quiet:                       # the failure is reported once, below, as one line
        q.setLevel(logging.CRITICAL)
    result: dict = {}

    def attempt():
        try:
            result["client"] = distributed.Client(address, timeout=timeout_s, set_as_default=False)
        except BaseException as e:        # noqa: BLE001 - OSError, TimeoutError, comm errors …
            result["error"] = e

    # Client's own timeout does not cover a peer that accepts the connection and never speaks (measured:
    # still waiting after 120 s with timeout=1), so the attempt runs in a daemon thread we stop waiting for.
    thread = threading.Thread(target=attempt, name="thermod-dask-connect", daemon=True)
    thread.start()
    thread.join(timeout_s + 1.0)
    for q, level in zip(quiet, levels, strict=True):
        q.setLevel(level)
    if "client" not in result:
        e = result.get("error")
        why = "no answer" if e is None else (str(e).strip().splitlines() or [type(e).__name__])[0]
        raise SchedulerError(f"--scheduler {address}: no Dask scheduler answered within {timeout_s:g} s "
                             f"({why})")
    client = result["client"]
    try:
        client.wait_for_workers(1, timeout=timeout_s)
    except Exception:                     # noqa: BLE001 - a timeout, or the scheduler went away
        client.close()
        raise SchedulerError(f"--scheduler {address}: the scheduler has no workers (waited {timeout_s:g} s); "
                             f"start some with `dask worker {address}`") from None
    return client


def _probe(checks: list[tuple[str, str]]) -> list[str]:
    """On a worker: for each (directory, token), the problems with writing outputs there."""
    problems = []
    for d, token in checks:
        marker = Path(d) / f".thermod-fleet-{token}"
        try:
            seen = marker.read_text()
        except OSError as e:
            seen = f"({e.strerror or e})"
        if seen != token:
            problems.append(f"does not see {d} as this machine does ({marker.name}: {seen or 'empty'}); "
                            "the workers need the output directory on a shared filesystem")
            continue
        mine = Path(d) / f".thermod-fleet-{token}-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        try:
            mine.write_bytes(b"")
            mine.unlink()
        except OSError as e:
            problems.append(f"cannot write the output directory {d} ({e.strerror or e})")
    return problems


def check_shared_output(client, directories: Sequence[Path]) -> None:
    """Every worker sees each output directory as this process does and can write into it."""
    token = uuid.uuid4().hex
    markers = []
    try:
        for d in directories:
            marker = d / f".thermod-fleet-{token}"
            try:
                marker.write_text(token)
            except OSError as e:
                raise SchedulerError(f"-o {d}: cannot write the output directory ({e.strerror or e})") \
                    from None
            markers.append(marker)
        answers = client.run(_probe, [(str(d), token) for d in directories], on_error="return")
    finally:
        for m in markers:
            m.unlink(missing_ok=True)
    for worker, problems in sorted(answers.items()):
        if isinstance(problems, BaseException):
            raise SchedulerError(f"--scheduler: worker {worker} could not check the output directory "
                                 f"({type(problems).__name__}: {problems})")
        if problems:
            raise SchedulerError(f"--scheduler: worker {worker} {problems[0]}")


def _remote_job(job: Job) -> Outcome:
    """The task: announce the start to the client, then the same job as a local run."""
    from distributed import get_worker

    worker = get_worker()
    worker.log_event(TOPIC, {"src": str(job.src), "worker": worker.address})
    return run_job(job, worker=worker.address)


def _absolute(p: Path | None) -> Path | None:
    return None if p is None else Path(os.path.abspath(p))


def run(jobs: Sequence[Job], address: str, progress: Progress | None = None,
        connect_timeout_s: float = CONNECT_TIMEOUT_S) -> list[Outcome]:
    """Deblur `jobs` on the cluster at `address`; one Outcome per job, in the jobs' order."""
    progress = progress or Lines()
    # the workers do not share our working directory: absolute paths to open, the given ones to report
    jobs = [replace(j, src_path=_absolute(j.src), dst_path=_absolute(j.dst), config=_absolute(j.config))
            for j in jobs]
    client = connect(address, connect_timeout_s)
    try:
        check_shared_output(client, sorted({j.write_path.parent for j in jobs}))
        return _run_tasks(client, jobs, progress)
    finally:
        client.close()


def _run_tasks(client, jobs: list[Job], progress: Progress) -> list[Outcome]:
    started: queue.SimpleQueue = queue.SimpleQueue()
    client.subscribe_topic(TOPIC, lambda event: started.put(event[1]))
    token = uuid.uuid4().hex[:8]
    futures = [client.submit(_remote_job, job, key=f"thermod-deblur-{token}-{i}", pure=False)
               for i, job in enumerate(jobs)]
    by_src = {str(j.src): j for j in jobs}
    announced: set[str] = set()
    outcomes: list[Outcome | None] = [None] * len(jobs)
    pending = set(range(len(jobs)))

    def announce():
        while True:
            try:
                msg = started.get_nowait()
            except queue.Empty:
                return
            if msg["src"] in by_src and msg["src"] not in announced:
                announced.add(msg["src"])
                progress.started(by_src[msg["src"]], msg["worker"])

    try:
        while pending:
            done = [i for i in pending if futures[i].done()]
            if not done:
                announce()
                time.sleep(POLL_S)
                continue
            announce()
            for i in sorted(done):
                pending.discard(i)
                outcome = _collect(futures[i], jobs[i])
                if str(jobs[i].src) not in announced:   # its start event is still on its way
                    announced.add(str(jobs[i].src))
                    progress.started(jobs[i], outcome.worker)
                progress.finished(outcome)
                outcomes[i] = outcome
    except BaseException:                 # Ctrl-C: do not leave the cluster busy with our files
        client.cancel(futures)
        raise
    finally:
        client.unsubscribe_topic(TOPIC)
    return outcomes


def _collect(future, job: Job) -> Outcome:
    try:
        outcome = future.result()
    except Exception as e:                # noqa: BLE001 - the worker died or the task was lost
        why = (str(e).strip().splitlines() or [""])[0]
        return Outcome(job, error=f"{job.src}: not deblurred: the cluster lost its task "
                                  f"({type(e).__name__}: {why})", worker="?")
    if outcome.ok and not job.write_path.exists():
        return Outcome(job, error=f"{job.dst}: written by {outcome.worker} but not visible here: the "
                                  "workers and this machine must share the output filesystem",
                       worker=outcome.worker)
    return outcome
