"""The memory of the gradient path, estimated from a trace before anything compiles.

A step's memory is estimated from its jaxpr: the peak of the values live at
once when the equations run one by one, each freed after its last use (an inner
loop holds one iteration's values at a time). XLA fuses many of them away, so
the estimate errs on the safe side.

``plan_memory`` turns the bound into the settings that fit the machine: the
forward-mode step Jacobians of all T x batch examples are computed in chunks
small enough to fit, and the reverse-mode rollout recomputes each step in the
backward pass (``jax.checkpoint``) instead of storing its intermediates when
storing them would not fit. Only a scene that cannot fit even one example is
refused, with the estimate and the option that helps.
"""
from __future__ import annotations

import os
from typing import Any, Callable, NamedTuple

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np

from stablebptt.errors import InputError

PyTree = Any
BUDGET_FRACTION = 0.5  # of the memory available when the plan is made: the rest is XLA's, the data's and the OS's


def _value_bytes(variables) -> int:
    return sum(int(np.prod(v.aval.shape)) * v.aval.dtype.itemsize for v in variables
               if isinstance(v, jax.extend.core.Var) and hasattr(v.aval, "shape") and hasattr(v.aval, "dtype"))


def _peak_bytes(jaxpr) -> int:
    """The most bytes live at once when ``jaxpr`` runs equation by equation, each value freed after its last use."""
    last_use = {}
    for index, equation in enumerate(jaxpr.eqns):
        for variable in equation.invars:
            if isinstance(variable, jax.extend.core.Var):
                last_use[variable] = index
    for variable in jaxpr.outvars:
        if isinstance(variable, jax.extend.core.Var):
            last_use[variable] = len(jaxpr.eqns)
    live = _value_bytes(list(jaxpr.invars) + list(jaxpr.constvars))
    peak = live
    for index, equation in enumerate(jaxpr.eqns):
        inner = max((_peak_bytes(j) for j in jax.extend.core.jaxprs_in_params(equation.params)), default=0)
        live += _value_bytes(equation.outvars)
        peak = max(peak, live + inner)
        dead = {v for v in equation.invars if isinstance(v, jax.extend.core.Var) and last_use.get(v) == index}
        dead |= {v for v in equation.outvars if v not in last_use}
        live -= _value_bytes(dead)
    return peak


def traced_bytes(function: Callable, *example_args) -> int:
    """The bytes one call of ``function`` holds at its peak, from its jaxpr (no compilation)."""
    return _peak_bytes(jax.make_jaxpr(function)(*example_args).jaxpr)


def available_bytes() -> int:
    """Memory the gradient path can take: on an accelerator its allocator's limit less what it holds
    already (the host's memory is not where the path lives), else what the OS reports as available
    (MemAvailable), else the physical memory."""
    device = jax.devices()[0]
    stats = (device.memory_stats() or {}) if device.platform != "cpu" else {}
    if "bytes_limit" in stats:
        return int(stats["bytes_limit"]) - int(stats.get("bytes_in_use", 0))
    try:
        with open("/proc/meminfo") as handle:
            for line in handle:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


class MemoryPlan(NamedTuple):
    """Settings of the gradient path that fit the memory budget.

    Attributes:
      jacobian_chunk: examples per chunk of the batched step Jacobians
        (``"forward"``), or None for all at once.
      rematerialize: recompute each step in the backward pass (``"reverse"``).
      estimate: the bound, in bytes, of the gradient path without the plan.
    """

    jacobian_chunk: int | None
    rematerialize: bool
    estimate: int


def gigabytes(count: float) -> str:
    return f"{count / 2**30:.3g} GB"


def budget_bytes() -> int:
    """What a run's gradient path and networks may take of this machine's memory."""
    return int(BUDGET_FRACTION * available_bytes())


def measure_now(name: str, measure: Callable[[], int]) -> int:
    """``plan_memory``'s default ``measured``: every measurement traced now."""
    return measure()


def plan_memory(step: Callable, state: PyTree, control: PyTree, horizon: int, batch: int, step_derivative: str,
                tangents: int, budget: int | None = None,
                measured: Callable[[str, Callable[[], int]], int] = measure_now, copies: int = 1,
                devices: int = 1) -> MemoryPlan:
    """Fit the gradient path of ``batch`` rollouts of ``horizon`` steps into ``budget`` bytes.

    Args:
      step: ``step(state, control) -> state``.
      state, control: one example of each (no batch axis).
      horizon, batch: the rollout's steps and examples per update.
      step_derivative: ``"forward"`` or ``"reverse"`` (``Plan.step_derivative``).
      tangents: forward-mode tangents pushed per example (Jacobian columns computed).
      budget: bytes the path may use; default a fraction of the available memory.
      measured: ``measured(name, measure)`` gives ``measure()``, the bytes of one traced step
        (``"forward"`` or ``"reverse"``), or the answer kept from an identical earlier run.
      copies: gradient paths held at once, each of ``batch`` rollouts (seeds batched in one program:
        each seed's chunk of Jacobians, or its stored steps, is live beside the others').
      devices: devices the rollouts are split over evenly (``TrainConfig.devices``): each holds its
        share of every path, and ``budget`` is one device's. A chunk of Jacobians is then a multiple
        of ``devices``, so that each device computes its share of it.

    Raises:
      InputError: if not even one example fits.
    """
    budget = budget if budget is not None else budget_bytes()
    examples = horizon * batch
    share = lambda whole: -(-whole // devices)  # one device's part of a path split over the devices
    batched = f" x {copies} seeds in one program" if copies > 1 else ""
    if step_derivative == "forward":
        tangent_of = lambda tree: jax.tree.map(jnp.ones_like, tree)
        per_tangent = measured("forward", lambda: traced_bytes(
            lambda s, u: jax.jvp(step, (s, u), (tangent_of(s), tangent_of(u))), state, control))
        per_example = per_tangent * max(tangents, 1)
        if per_example * copies > budget:
            one_by_one = " or train the seeds one after another (--seed-batching map)" if batched else ""
            raise InputError(f"one example's step Jacobian{batched} needs up to {gigabytes(per_example * copies)}, "
                             f"more than the {gigabytes(budget)} this machine can give it: set Plan.step_derivative "
                             f"to 'reverse'{one_by_one}")
        fitting = budget // (per_example * copies) * devices  # examples at once over all the devices
        estimate = per_example * share(examples) * copies
        if fitting >= examples:
            return MemoryPlan(None, False, estimate)
        # A divisor of the example count: equal chunks compile the step's Jacobian once, not twice;
        # split evenly over the devices (a chunk that does not divide stays whole on each of them).
        chunks = [size for size in range(devices, int(fitting) + 1, devices) if examples % size == 0]
        return MemoryPlan(max(chunks or [1]), False, estimate)
    # Reverse mode stores every step's intermediates for the backward pass.
    per_step = measured("reverse", lambda: traced_bytes(lambda s, u: jax.vjp(step, s, u)[1], state, control))
    stored = per_step * share(examples) * copies
    if stored <= budget:
        return MemoryPlan(None, False, stored)
    state_bytes = sum(leaf.size * leaf.dtype.itemsize for leaf in jax.tree.leaves((state, control)))
    rematerialized = (state_bytes * share(examples) + per_step * share(batch)) * copies
    if rematerialized > budget:
        raise InputError(f"the backward pass of {batch} examples x {horizon} steps{batched} needs up to "
                         f"{gigabytes(rematerialized)} even recomputing each step, more than the {gigabytes(budget)} "
                         f"this machine can give it: use a smaller TrainConfig.batch or a shorter Dynamics.horizon"
                         + (", or train the seeds one after another (--seed-batching map)" if batched else ""))
    return MemoryPlan(None, True, stored)
