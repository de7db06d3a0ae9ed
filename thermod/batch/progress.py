"""Per-file progress of a batch: started, done (frames, seconds, where) or failed (one line naming the
file). The local run keeps its frame bar and prints only failures (its per-file lines are logged:
`-v` shows them); a cluster run, where frames are counted on the workers, prints a line per event."""

from __future__ import annotations

import logging
import sys

from thermod.batch.job import Job, Outcome

log = logging.getLogger("thermod.batch")

PREFIX = "thermod deblur"


class Progress:
    """Events of a batch; the default reports to the log only, failures to stderr."""

    def __init__(self, stream=None):
        self.stream = stream or sys.stderr

    def started(self, job: Job, worker: str) -> None:
        log.info("%s: started (%s)", job.src, worker)

    def finished(self, outcome: Outcome) -> None:
        if outcome.ok:
            r = outcome.report
            log.info("%s: done, %d frames in %.1f s (%s)", r.src, r.n, r.seconds, outcome.worker)
        else:
            print(f"{PREFIX}: error: {outcome.error}", file=self.stream, flush=True)


class Lines(Progress):
    """One line per event on stderr (a cluster run): which file, where, how many frames, how long."""

    def started(self, job: Job, worker: str) -> None:
        print(f"{PREFIX}: {job.src}: started on {worker}", file=self.stream, flush=True)

    def finished(self, outcome: Outcome) -> None:
        if outcome.ok:
            r = outcome.report
            print(f"{PREFIX}: {r.src}: done, {r.n} frames in {r.seconds:.1f} s on {outcome.worker}",
                  file=self.stream, flush=True)
        else:
            super().finished(outcome)
