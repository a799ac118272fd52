"""Imports that leave out a dependency's optional backends which no stablebptt command runs."""
from __future__ import annotations

import contextlib
import sys
from typing import Iterable, Iterator


@contextlib.contextmanager
def imported_without(names: Iterable[str]) -> Iterator[None]:
    """Within, ``import NAME`` raises ImportError for each of ``names`` not imported yet, so a library
    that tries it takes NAME for not installed; afterwards each imports as usual."""
    blocked = [name for name in names if name not in sys.modules]
    for name in blocked:
        sys.modules[name] = None
    try:
        yield
    finally:
        for name in blocked:
            if name in sys.modules and sys.modules[name] is None:
                del sys.modules[name]
