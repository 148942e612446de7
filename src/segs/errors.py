"""Errors caused by the user's input (data, configuration), reported as one line.

Entry points (`segs.train`, `segs.track`, `segs.report`) catch :class:`UserInputError`, print
``error: <message>`` on stderr and exit with status 2, without a traceback. Everything else is a
bug and keeps its traceback.
"""


class UserInputError(ValueError):
    """Bad input named by file or config key; the message is a single line."""


class DataError(UserInputError):
    """A dataset file or folder is missing, unreadable or inconsistent."""


class ConfigError(UserInputError):
    """A configuration value is unknown or out of range."""


class LimitError(UserInputError):
    """A configured resource limit (memory) would be exceeded; the run stopped cleanly."""
