"""The trajectory study: final-state error against a float64 reference, and the time per simulated second,
per integrator, time step and precision.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

from stablebptt.apps.measuring import (
    PRECISIONS,
    cast,
    compile_call,
    flat_states,
    policy_params,
    precision,
    rollout_program,
    run_once,
    time_round_robin,
    to_numpy,
)

if TYPE_CHECKING:
    from stablebptt.apps.accuracy import AccuracyConfig


@dataclass(frozen=True)
class TrajectorySetup:
    """One task's side of the trajectory study (a task's studies module makes it: ``stablebptt.apps.studies``).

    Attributes:
      task: the name its rows carry.
      label: the set-up in words (for tables and plots).
      duration: simulated time of every rollout.
      integrators: the schemes compared.
      dts: the time steps, each dividing ``duration`` into whole steps.
      paper: the paper's (integrator, dt), the baseline of the cost ratios.
      make_task: ``make_task(integrator, dt) -> Task``; call inside the precision wanted (MJX bakes it into the model).
      controls: ``controls(rng, batch)``: one fixed control per trajectory, held for the whole rollout.
      reference: ``reference(initial_states, controls) -> (final states [batch, numbers], description)`` in float64.
    """

    task: str
    label: str
    duration: float
    integrators: tuple[str, ...]
    dts: tuple[float, ...]
    paper: tuple[str, float]
    make_task: Callable
    controls: Callable
    reference: Callable


def trajectory_setups(config: AccuracyConfig) -> list[TrajectorySetup]:
    """Each task's set-up, from its studies module (``trajectory_setup``); a task without one is refused."""
    from stablebptt.apps.study_hooks import required_hook
    return [required_hook(name, "trajectory_setup", "trajectory")(config) for name in config.task_list]


def trajectory_study(setup: TrajectorySetup, config: AccuracyConfig, log: Callable) -> list[dict]:
    """Rows (one per integrator, dt and precision): final-state error and time per simulated second."""
    import jax
    import numpy as np

    from stablebptt.flows.gradients import flow_gradients

    rng = np.random.default_rng(config.seed)
    with precision(64):  # float64 initial states; float32 runs start from their rounding
        paper_task = setup.make_task(*setup.paper)
        initial_states = to_numpy(paper_task.sample_initial_states(jax.random.PRNGKey(config.seed), config.batch))
    controls = setup.controls(rng, config.batch)
    reference, description = setup.reference(initial_states, controls)
    log(f"{setup.task}: reference = {description}")

    forward, gradient, meta = {}, {}, {}
    params = policy_params(paper_task, config.seed)
    for integrator in setup.integrators:
        for dt in setup.dts:
            steps = round(setup.duration / dt)
            for bits in PRECISIONS:
                key = (integrator, dt, bits)
                with precision(bits):
                    task = setup.make_task(integrator, dt)
                    arguments = (cast(initial_states, bits), cast(controls, bits))
                    gradient_arguments = (cast(params, bits), cast(initial_states, bits))
                call, compile_seconds = compile_call(rollout_program(task.dynamics.step, steps), arguments, bits)
                if dt == setup.paper[1]:
                    # What a training update costs: the task's own loss, horizon and policy.
                    grad = jax.jit(lambda p, x, d=task.dynamics, plan=task.plan: flow_gradients(d, ("R",), p, x, plan))
                    gradient[key] = compile_call(grad, gradient_arguments, bits)[0]
                final = run_once(call)[0]
                error = float(np.max(np.abs(flat_states(final) - reference)))
                forward[key] = call
                meta[key] = dict(steps=steps, error=error, compile_s=compile_seconds)
                log(f"  {integrator:14s} dt {dt:<8.4g} float{bits}: error {error:.2e}  (compiled in {compile_seconds:.1f} s)")
    forward_seconds = time_round_robin(forward, config.rounds)
    gradient_seconds = time_round_robin(gradient, max(3, config.rounds // 3))

    baseline = forward_seconds[setup.paper + (32,)]
    rows = []
    for key, seconds in forward_seconds.items():
        integrator, dt, bits = key
        rows.append({
            "task": setup.task, "setup": setup.label, "integrator": integrator, "precision": f"float{bits}", "dt": dt,
            "steps": meta[key]["steps"], "paper_dt": setup.paper[1], "simulated_time": setup.duration, "batch": config.batch,
            "error": meta[key]["error"],
            "ms_per_simulated_second": 1e3 * seconds / setup.duration,
            "ms_per_step": 1e3 * seconds / meta[key]["steps"],
            "cost_vs_paper": seconds / baseline,
            "gradient_ms_per_simulated_second": 1e3 * gradient_seconds[key] / setup.duration if key in gradient else float("nan"),
            "compile_s": meta[key]["compile_s"],
            "reference": description,
        })
    return rows
