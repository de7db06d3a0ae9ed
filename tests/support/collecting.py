"""Shared by the pipeline tests (tests/runtime): a sink for the
pipeline's `emit` that keeps every output and lets a test wait for the first `n`."""

import threading
import time


class Collector:
    def __init__(self):
        self.out, self.lock, self.event = [], threading.Lock(), threading.Event()

    def __call__(self, o):
        with self.lock:
            self.out.append(o)
        self.event.set()

    def wait(self, n, timeout=120.0):
        """The first `n` outputs, as soon as they are there; the timeout only catches a hang."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self.lock:
                if len(self.out) >= n:
                    return list(self.out)
            time.sleep(0.005)
        with self.lock:
            return list(self.out)
