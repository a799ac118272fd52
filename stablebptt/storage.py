"""Files written atomically: readers see the old file or the new one, never half of one.

Every file the library writes (run folders, sweep records, reports, pictures)
goes through ``atomic_write``: a temporary file beside the target, flushed to
disk, then renamed over it. A full disk or a signal at any moment leaves the
old file and no temporary one.
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

from stablebptt.errors import InputError, StorageError, plain_scalar


def _temporary(path: Path) -> Path:
    return path.with_name(f".{path.name}.{os.getpid()}.tmp")


def write_temporary(path: Path, data: bytes) -> Path:
    """``data`` in a temporary file beside ``path``, on disk; removed again if anything fails."""
    temporary = _temporary(path)
    try:
        with open(temporary, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
    except BaseException as error:  # a full disk, or a signal mid-write: no temporary is left either way
        temporary.unlink(missing_ok=True)
        if isinstance(error, OSError):
            raise StorageError(error.errno, f"cannot write {path}: {error.strerror or error}") from None
        raise
    return temporary


def atomic_write(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that readers see the old or the new file, never half of one.

    Raises:
      StorageError: the file could not be written (e.g. a full disk); no temporary file is left.
    """
    temporary = write_temporary(path, data)
    try:
        os.replace(temporary, path)
    except OSError as error:
        temporary.unlink(missing_ok=True)
        raise StorageError(error.errno, f"cannot write {path}: {error.strerror or error}") from None


def json_bytes(payload: Any) -> bytes:
    return (json.dumps(payload, indent=2, sort_keys=True, default=plain_scalar) + "\n").encode()


def write_json(path: Path, payload: Any) -> None:
    atomic_write(path, json_bytes(payload))


def read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"{path} does not exist: is this a run directory?") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise InputError(f"{path} is not valid JSON ({error})") from None


def file_sha256(path: Path | str) -> str:
    """The SHA-256 of a file's bytes, as runs and grids record a model file's contents."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()
