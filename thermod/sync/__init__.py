"""Sync a thermal video to a flight-controller gyro log from the pictures alone.

Nothing tells where in a long log the video sits, nor how the camera is mounted on the flight
controller. `synchronise` (`result`) finds both, on arrays (the readers of video containers and log
formats are in `thermod.io`), in three stages: the picture motion (`thermod.motion.picture`), the
coarse whole-log correlation (`coarse`) and the fine robust fit (`fine`). The motion-only discrepancy
workflow on a stretch of the synced video (`discrepancy`) is the stage that sees τ apart from the
offset; `plots` draws the sync. What it recovers at a given size is in benchmarks/results/sync.md.
Refused, never guessed: `thermod.motion.picture.TooLittleMotion` and the `SyncError` subclasses.
"""

from thermod.motion.picture import PictureMotion, TooLittleMotion, check_motion, picture_motion
from thermod.sync.coarse import MOUNTS, CoarseSync, coarse_sync, covered_part
from thermod.sync.errors import DurationMismatch, LogMismatch, SyncError, SyncInputError
from thermod.sync.fine import FineSync, refine
from thermod.sync.gyro import cumulative_rotation
from thermod.sync.plots import plot_sync
from thermod.sync.result import SyncResult, synchronise

__all__ = ["MOUNTS", "CoarseSync", "DurationMismatch", "FineSync", "LogMismatch", "PictureMotion",
           "SyncError", "SyncInputError", "SyncResult", "TooLittleMotion", "check_motion", "coarse_sync",
           "covered_part", "cumulative_rotation", "picture_motion", "plot_sync", "refine", "synchronise"]
