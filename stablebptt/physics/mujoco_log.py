"""MuJoCo's warnings, routed through Python.

By default MuJoCo prints a warning and appends it to ``MUJOCO_LOG.TXT`` in the
working directory. Importing this module (``stablebptt.physics.scene`` does, so every task
built from a model file) installs a handler instead: a warning goes to stderr prefixed ``mujoco:``, or, inside
``collected()``, into a list the caller reports in its own words (e.g. with the
model's file name). No log file is ever written.
"""
from __future__ import annotations

import contextlib
import sys
import threading
from typing import Iterator

import mujoco

_local = threading.local()


def _on_warning(message: str) -> None:
    collectors = getattr(_local, "collectors", None)
    if collectors:
        collectors[-1].append(message)
    else:
        print(f"mujoco: {message}", file=sys.stderr)


@contextlib.contextmanager
def collected() -> Iterator[list[str]]:
    """Collect the MuJoCo warnings this thread raises inside the block."""
    lines: list[str] = []
    _local.collectors = getattr(_local, "collectors", [])
    _local.collectors.append(lines)
    try:
        yield lines
    finally:
        _local.collectors.remove(lines)


mujoco.set_mju_user_warning(_on_warning)
