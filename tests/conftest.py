"""Shared test set-up: the repository root on sys.path, and a float64 switch for single tests."""
import contextlib
import sys
from pathlib import Path

import jax
import pytest

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import stablebptt  # noqa: E402,F401  (its XLA:CPU set-up must precede JAX's CPU client)


@contextlib.contextmanager
def float64():
    """Run a block in float64 without flipping the whole session (other tests are float32)."""
    previous = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)
    try:
        yield
    finally:
        jax.config.update("jax_enable_x64", previous)


@pytest.fixture
def x64():
    with float64():
        yield
