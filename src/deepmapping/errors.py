"""Errors the CLI turns into one-line messages (no traceback, exit code != 0)."""


class Interrupted(Exception):
    """Ctrl-C during training: a checkpoint was written to `path` (not an error: --resume continues).

    Here, not in solver.trainer, so that the CLI catches it without importing torch."""

    def __init__(self, path):
        super().__init__(f"interrupted; checkpoint saved to {path}")
        self.path = path


class DeepMappingError(Exception):
    """Base class of every error a user can fix (bad input, bad options)."""

    exit_code = 2


class InputError(DeepMappingError):
    """Missing, unreadable, corrupt or inconsistent input data.

    The message names the file and the problem, e.g. ``scans/003.pcd: contains NaN``.
    """


class ConfigError(DeepMappingError):
    """Invalid settings or option combination."""


class OutputError(DeepMappingError, OSError):
    """A result cannot be written (disk full, read-only folder, no permission).

    The message names the file: ``runs/x/poses.npy: cannot write (No space left on device)``.
    Also an ``OSError``, so code that catches OSError around a write still catches it.
    """


class FolderBusy(DeepMappingError):
    """Another deepmapping process holds the lock of the output folder (see ``io.lock``)."""


class TrainingError(DeepMappingError):
    """Training cannot go on: the loss stayed NaN/inf after every allowed rollback."""
