"""Exception types shared across thermod. Each names the file, field or device at fault."""


class ThermodError(Exception):
    """Base class for every error thermod raises on purpose."""


class RecordingError(ThermodError):
    """A recording file is malformed: names the file and the field, and what was expected."""

    def __init__(self, path, field: str, problem: str):
        self.path, self.field, self.problem = str(path), field, problem
        super().__init__(f"{path}: {field}: {problem}")


class ConfigError(ThermodError):
    """A configuration value is unknown, of the wrong type or out of range."""


class DeviceError(ThermodError):
    """A device could not be opened, identified or read. The message says what to check."""


class FileError(ThermodError):
    """A file cannot be read or written as asked: names the file and the problem."""

    def __init__(self, path, problem: str):
        self.path, self.problem = str(path), problem
        super().__init__(f"{path}: {problem}")


class StopRequested(ThermodError):
    """A stop (SIGTERM, SIGINT) came while waiting for something: that wait is abandoned."""

    @staticmethod
    def requested(abort) -> bool:
        """Whether `abort` (a `threading.Event`, or None: no stop to hear) is set."""
        return abort is not None and abort.is_set()

    @classmethod
    def check(cls, abort, when: str) -> None:
        """Raise when `abort` is set; `when` completes "stop requested …" (e.g. "during the warm-up")."""
        if cls.requested(abort):
            raise cls(f"stop requested {when}")
