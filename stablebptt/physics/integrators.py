"""Explicit one-step integrators of ``x' = derivative(x, u)`` on pytrees, the control held over the step."""
from __future__ import annotations

from typing import Any, Callable

import jax

PyTree = Any
Derivative = Callable[[PyTree, PyTree], PyTree]


def euler(derivative: Derivative, dt: float) -> Callable[[PyTree, PyTree], PyTree]:
    """Explicit Euler: every component advances with the rates at the start of the step."""
    def step(x, u):
        return jax.tree.map(lambda a, r: a + dt * r, x, derivative(x, u))

    return step


def rk4(derivative: Derivative, dt: float) -> Callable[[PyTree, PyTree], PyTree]:
    """The classic fourth-order Runge-Kutta step."""
    def step(x, u):
        shifted = lambda k, h: jax.tree.map(lambda a, r: a + h * r, x, k)
        k1 = derivative(x, u)
        k2 = derivative(shifted(k1, dt / 2), u)
        k3 = derivative(shifted(k2, dt / 2), u)
        k4 = derivative(shifted(k3, dt), u)
        return jax.tree.map(lambda a, b, c, d, e: a + dt / 6 * (b + 2 * c + 2 * d + e), x, k1, k2, k3, k4)

    return step


INTEGRATORS = {"euler": euler, "rk4": rk4}
