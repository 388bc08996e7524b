"""Errors the CLI turns into one-line messages (no traceback, exit code != 0)."""


class DeepMappingError(Exception):
    """Base class of every error a user can fix (bad input, bad options)."""

    exit_code = 2


class InputError(DeepMappingError):
    """Missing, unreadable, corrupt or inconsistent input data.

    The message names the file and the problem, e.g. ``scans/003.pcd: contains NaN``.
    """


class ConfigError(DeepMappingError):
    """Invalid settings or option combination."""
