"""The exceptions that mean: say so in one line, no traceback."""


class InputError(ValueError):
    """Bad user input. Scripts print its message as one line and exit with code 2."""


class StorageError(OSError):
    """A file could not be written (full disk, permissions). Scripts print one line and exit with code 1."""
