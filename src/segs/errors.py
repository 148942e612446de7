"""Errors caused by the user's input (data, configuration), reported as one line.

Entry points (`segs.train`, `segs.track`, `segs.report`) catch :class:`UserInputError`, print
``error: <message>`` on stderr and exit with status 2, without a traceback. Everything else is a
bug and keeps its traceback.
"""


class UserInputError(ValueError):
    """Bad input named by file or config key; the message is a single line."""


class DataError(UserInputError):
    """A dataset file or folder is missing, unreadable or inconsistent."""


class TrackingFailed(DataError):
    """The frontend tracked no frame that could be mapped: a result of the method on this input
    (recorded in metrics.json with status "tracking_failed"), not a crash.
    frames: frames in the sequence; lost: frames that could not be tracked."""

    def __init__(self, message: str, frames: int = 0, lost: int = 0):
        super().__init__(message)
        self.frames, self.lost = frames, lost


class ConfigError(UserInputError):
    """A configuration value is unknown or out of range."""


class LimitError(UserInputError):
    """A configured resource limit (memory) would be exceeded; the run stopped cleanly."""
