"""Shared test set-up: the package imported first, and a float64 switch for single tests.

The tests import the installed package (``make`` installs it in editable mode), as users do.
"""
import contextlib
from pathlib import Path

import jax
import pytest

import stablebptt  # noqa: F401  (its XLA:CPU set-up must precede JAX's CPU client)

ROOT = Path(__file__).resolve().parent.parent  # the checkout: scripts are run from here


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
