"""What the device emulators that run on a thread share: start/stop of the writer thread, use as a
context manager, and the temporary folder holding their device nodes (removed on stop)."""

from __future__ import annotations

import tempfile
import threading
from typing import Self


class ThreadedEmulator:
    """Base of an emulator whose device runs in ``_run`` on one daemon thread until ``_stop`` is set.

    Subclasses open their device in ``_open`` (before the thread starts) and close it in ``_close``
    (after it has ended).
    """

    thread_name = "emu"

    def __init__(self, given_dir, tmp_prefix: str):
        self._tmp = None if given_dir else tempfile.TemporaryDirectory(prefix=tmp_prefix)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def _dir(self) -> str:
        """The temporary folder made when no folder was given."""
        return self._tmp.name

    def _open(self) -> None: ...

    def _close(self) -> None: ...

    def _run(self) -> None:
        raise NotImplementedError

    def start(self) -> Self:
        self._open()
        self._thread = threading.Thread(target=self._run, name=self.thread_name, daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
        self._close()
        if self._tmp is not None:
            self._tmp.cleanup()

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
