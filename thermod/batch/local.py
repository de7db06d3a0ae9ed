"""The default executor: the files on this machine, one after another in this process, or with
``processes > 1`` in a pool of that many worker processes (one file each at a time).

One process's `Deconvolver` serves every file it deblurs (its FFT plans are built once). A solve
is single-threaded, so on N cores N processes deblur about N files at once (measured with 2
processes on 2 cores: `benchmarks/results/fleet.md`). Each process pays
numba's start-up once (about 1–2 s), which is why one file, or ``processes = 1``, stays in this
process. The bytes written do not depend on which process wrote them (the same FFT plans: one
wisdom file, `THERMOD_CACHE_DIR`).

A worker process that dies (killed, out of memory, a crash in native code) breaks the pool: the
files it and the others were deblurring are started again in a new pool, and a file whose
attempts all die is reported failed, alone, like any bad file.
"""

from __future__ import annotations

import multiprocessing
import os
import sys
from collections.abc import Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool

from thermod.batch.job import Job, Outcome, run_job
from thermod.batch.progress import Lines, Progress

MAX_ATTEMPTS = 3          # a file whose worker process died this many times is reported failed


def usable_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def run(jobs: Sequence[Job], progress: Progress | None = None, processes: int = 1) -> list[Outcome]:
    """Deblur `jobs`; one Outcome per job, in the same order."""
    if processes <= 1 or len(jobs) <= 1:
        return _run_here(jobs, progress or Progress())
    return _run_pool(list(jobs), progress or Lines(), min(processes, len(jobs)))


def _run_here(jobs: Sequence[Job], progress: Progress) -> list[Outcome]:
    from tqdm import tqdm

    outcomes = []
    with tqdm(total=0, unit="frame", desc="thermod deblur", disable=None, file=sys.stderr) as bar:
        for job in jobs:
            progress.started(job, "local")
            outcome = run_job(job, bar)
            progress.finished(outcome)
            outcomes.append(outcome)
    return outcomes


def _pool_job(job: Job) -> Outcome:
    return run_job(job, worker=f"local process {os.getpid()}")


def _run_pool(jobs: list[Job], progress: Progress, processes: int) -> list[Outcome]:
    outcomes: list[Outcome | None] = [None] * len(jobs)
    attempts = [0] * len(jobs)
    todo = list(range(len(jobs)))
    # spawn, not fork: the parent may hold threads (tqdm, numba's) whose locks a fork would copy held
    ctx = multiprocessing.get_context("spawn")
    while todo:
        pool = ProcessPoolExecutor(max_workers=processes, mp_context=ctx)
        running: dict = {}
        broken = False
        try:
            while (todo or running) and not broken:
                while todo and len(running) < processes:     # a file starts only when a process is free
                    i = todo.pop(0)
                    attempts[i] += 1
                    progress.started(jobs[i], "a local process")
                    running[pool.submit(_pool_job, jobs[i])] = i
                done, _ = wait(running, return_when=FIRST_COMPLETED)
                for fut in done:
                    i = running.pop(fut)
                    try:
                        outcomes[i] = fut.result()
                    except BrokenProcessPool:
                        broken = True
                        running[fut] = i           # with the others still out, below
                        break
                    progress.finished(outcomes[i])
        except BaseException:
            pool.shutdown(wait=False, cancel_futures=True)
            raise
        if broken:
            # every file that was out is started again in a new pool, ahead of those not yet begun
            again = []
            for fut, i in running.items():
                if fut.done() and fut.exception() is None:
                    outcomes[i] = fut.result()
                    progress.finished(outcomes[i])
                elif attempts[i] >= MAX_ATTEMPTS:
                    outcomes[i] = Outcome(jobs[i], error=f"{jobs[i].src}: not deblurred: the process "
                                                         f"deblurring it died {attempts[i]} times")
                    progress.finished(outcomes[i])
                else:
                    again.append(i)
            todo = sorted(again) + todo
        pool.shutdown(wait=True, cancel_futures=True)
    return outcomes  # type: ignore[return-value]
