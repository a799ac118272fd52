"""Tracing for shapes alone (``tracing_shapes``): what a start needs before any value exists, or
before a check still running has answered, traced without the work only values need."""
from __future__ import annotations

import contextlib
import contextvars
from typing import Iterator

_shapes_only = contextvars.ContextVar("stablebptt_shapes_only", default=False)


@contextlib.contextmanager
def tracing_shapes() -> Iterator[None]:
    """Within the block the caller traces for shapes alone, and ``shapes_only()`` is true: a task whose
    parameters' values wait for a check still running (``Task.settle``: an environment's reward
    diagnosis) gives their shapes without waiting, and a carried population's resets give theirs from
    one reset's, without tracing the batched reset (``episodes.first_population``). Trace a function
    made for the trace (``jax.eval_shape(lambda ...: ...)``): JAX keeps a function's trace,
    ``eval_shape``'s too, for a later jit of the same function, which would then compute these
    stand-ins for values."""
    token = _shapes_only.set(True)
    try:
        yield
    finally:
        _shapes_only.reset(token)


def shapes_only() -> bool:
    """Whether the caller traces for shapes alone (``tracing_shapes``)."""
    return _shapes_only.get()
