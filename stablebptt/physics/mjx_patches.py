"""MJX's private functions replaced while this library traces, and what each tracing thread asks of them.

A patch is the process's while any context of its kind is open (``applied``): MJX's modules are
shared. What a trace asks of a patch is a flag of the tracing thread (``choosing``, read from
``tracing`` as the patch is traced), so that programs traced at once in several threads each take
their own choices, and code traced in a thread that asked for nothing gets MJX's own.
"""
from __future__ import annotations

import collections
import contextlib
import threading

from stablebptt.physics import mjx_internals

_lock = threading.RLock()
_depth: collections.Counter = collections.Counter()  # open contexts of each kind
_originals: dict[str, list] = {}


@contextlib.contextmanager
def applied(kind: str, patches):
    """``patches``, (owner, attribute, replacement) triples or a function that makes them (called only
    where the first of its kind is entered), applied while any context of ``kind`` is open. The last to
    close restores what the first found: a patch another library makes meanwhile is undone with it."""
    with _lock:
        if _depth[kind] == 0:
            mjx_internals.check_version()
            patches = patches() if callable(patches) else patches
            _originals[kind] = [(owner, name, owner.__dict__[name]) for owner, name, _ in patches]
            for owner, name, replacement in patches:
                setattr(owner, name, replacement)
        _depth[kind] += 1
    try:
        yield
    finally:
        with _lock:
            _depth[kind] -= 1
            if _depth[kind] == 0:
                for owner, name, original in _originals.pop(kind):
                    setattr(owner, name, original)


class TraceChoices(threading.local):
    """What this thread's trace asks of MJX, read by the shared patches as they are traced."""
    implicit_solver = False
    geometry_held = False
    physics_steps_recomputed = False
    camera_poses_held = False
    c_sensors = False  # sensors as C computes them (c_sensors.py)
    steps_recomputed = 0  # the mjx.step calls this thread's traces have recomputed, counted as they are traced
    physics_steps_carrying_state = False  # MuJoCo Playground's loop of physics steps as state_carried.steps
    loops_carrying_state = 0  # that loop's calls this thread's traces took so, counted as they are traced


tracing = TraceChoices()


@contextlib.contextmanager
def choosing(choice: str):
    """This thread's trace takes ``choice`` (an attribute of ``TraceChoices``) until the context ends."""
    if not hasattr(TraceChoices, choice):
        raise AttributeError(f"no trace choice {choice!r}")
    before = getattr(tracing, choice)
    setattr(tracing, choice, True)
    try:
        yield
    finally:
        setattr(tracing, choice, before)
