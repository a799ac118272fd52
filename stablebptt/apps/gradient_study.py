"""The gradient study: the R and M gradients in float32 against float64 as the horizon grows, and their norm.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

from stablebptt.apps.measuring import (
    PRECISIONS,
    cast,
    compile_call,
    policy_params,
    precision,
    run_once,
    to_numpy,
    tree_norm,
)

if TYPE_CHECKING:
    from stablebptt.apps.accuracy import AccuracyConfig


@dataclass(frozen=True)
class GradientSetup:
    """One task's side of the gradient study (a task's studies module makes it: ``stablebptt.apps.studies``).

    Attributes:
      task: the name its rows carry.
      label: the set-up in words (for tables and plots).
      make_task: ``make_task() -> Task`` at the paper's time step; call inside the precision wanted.
      dt: its time step.
      horizons: rollout lengths in steps, each compiled in float32 and float64.
      regimes: name -> transform of the float64 initial states (a NumPy pytree).
    """

    task: str
    label: str
    make_task: Callable
    dt: float
    horizons: tuple[int, ...]
    regimes: dict


def gradient_setups(config: AccuracyConfig) -> list[GradientSetup]:
    """Each task's set-up, from its studies module (``gradient_setup``); a task without one is refused."""
    from stablebptt.apps.study_hooks import required_hook
    return [required_hook(name, "gradient_setup", "gradient")(config) for name in config.task_list]


def gradient_study(setup: GradientSetup, config: AccuracyConfig, log: Callable) -> list[dict]:
    """Rows (one per regime, horizon, flow and precision): gradient norm, and float32's error against float64."""
    import jax
    import numpy as np

    from stablebptt.flows.gradients import flow_gradients

    flows = ("R", "M")  # the study's subject, not a list of modes: how g_R grows against g_M, the physics path
    with precision(64):
        base = setup.make_task()
        sampled = to_numpy(base.sample_initial_states(jax.random.PRNGKey(config.seed + 1), config.batch))
    params = policy_params(base, config.seed)
    regimes = {name: transform(sampled) for name, transform in setup.regimes.items()}
    results, rows = {}, []
    for horizon in setup.horizons:
        for bits in PRECISIONS:
            with precision(bits):
                task = setup.make_task()
                dynamics = dataclasses.replace(task.dynamics, horizon=horizon)
                program = jax.jit(lambda p, x, d=dynamics, plan=task.plan: flow_gradients(d, flows, p, x, plan))
                arguments = {regime: (cast(params, bits), cast(states, bits)) for regime, states in regimes.items()}
            compiled = None
            for regime, regime_arguments in arguments.items():
                if compiled is None:  # one executable serves every regime: same shapes
                    compiled, compile_seconds = compile_call(program, regime_arguments, bits)
                call = compiled._replace(arguments=regime_arguments)
                loss, grads = run_once(call)[0]
                seconds = min(run_once(call)[1] for _ in range(3))
                grads = to_numpy(grads)
                results[regime, horizon, bits] = grads
                for index, flow in enumerate(flows):
                    grad = jax.tree.map(lambda a: a[index], grads)
                    finite = all(np.all(np.isfinite(leaf)) for leaf in jax.tree.leaves(grad))
                    rows.append({
                        "task": setup.task, "setup": setup.label, "regime": regime, "horizon": horizon,
                        "simulated_time": horizon * setup.dt, "flow": flow, "precision": f"float{bits}",
                        "loss": float(loss), "norm": tree_norm(grad), "finite": finite,
                        "relative_error_vs_float64": float("nan"), "ms_per_gradient": 1e3 * seconds,
                    })
            log(f"  {setup.task} horizon {horizon:5d} float{bits}: compiled in {compile_seconds:.1f} s, "
                f"{1e3 * seconds:.0f} ms per R+M gradient (batch {config.batch})")
    for row in rows:
        if row["precision"] == "float32":
            index = flows.index(row["flow"])
            g32, g64 = (jax.tree.map(lambda a: a[index], results[row["regime"], row["horizon"], bits]) for bits in PRECISIONS)
            row["relative_error_vs_float64"] = tree_norm(jax.tree.map(np.subtract, g32, g64)) / tree_norm(g64)
    return rows
