"""What a sync refuses, each naming what was wrong (a video with too little motion is refused by
`thermod.motion.picture.TooLittleMotion`)."""

from thermod.errors import ThermodError


class SyncError(ThermodError):
    """The video and the gyro log could not be synced; the message says what was wrong."""


class SyncInputError(SyncError):
    """An input array has the wrong shape, type or values."""


class TooLittleMotion(SyncError):
    """The video's rotation does not rise above the noise of its own measurement."""


class DurationMismatch(SyncError):
    """The video is longer than the log that should contain it."""


class LogMismatch(SyncError):
    """No place in the log (or more than one) correlates with the video's rotation."""
