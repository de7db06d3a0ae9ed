"""The default executor: the files one after another in this process, behind one frame bar.

One thread's `Deconvolver` serves every file (its FFT plans are built once), which is also why a
single process is the default: a second process would pay numba start-up and FFT planning again
and compete for the same cores that one solve's FFTs already use.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

from thermod.batch.job import Job, Outcome, run_job
from thermod.batch.progress import Progress


def run(jobs: Sequence[Job], progress: Progress | None = None) -> list[Outcome]:
    """Deblur `jobs` in order; one Outcome per job, in the same order."""
    from tqdm import tqdm

    progress = progress or Progress()
    outcomes = []
    with tqdm(total=0, unit="frame", desc="thermod deblur", disable=None, file=sys.stderr) as bar:
        for job in jobs:
            progress.started(job, "local")
            outcome = run_job(job, bar)
            progress.finished(outcome)
            outcomes.append(outcome)
    return outcomes
