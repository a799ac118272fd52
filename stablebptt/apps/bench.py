"""The benchmark's measurements: update times per mode, the cart-pole's MJX pipelines against the
closed-form floor, and the parts of an update, as Markdown tables (scripts/bench.py prints them).

Variants of one table are timed round-robin (``stablebptt.timing``), so drift of the
machine hits all of them alike; compare times within one table only.
"""
from __future__ import annotations

import dataclasses

from stablebptt import timing

def make_update(task, mode, batch_size, plain=False, with_cosine=False):
    """A jitted update: gradient (one-pass flows, or plain jax.grad), clip, Adam."""
    import jax
    import optax
    from stablebptt.flows import flow_gradients, flows_needed, reference_loss
    from stablebptt.training import TrainConfig, make_optimizer

    flows = flows_needed(mode, with_cosine)
    optimizer = make_optimizer(TrainConfig(mode=mode), flows)

    def update(params, opt_state, batch):
        if plain:
            loss, grad = jax.value_and_grad(reference_loss, argnums=1)(task.dynamics, params, batch)
            grads = jax.tree.map(lambda g: g[None], grad)
        else:
            loss, grads = flow_gradients(task.dynamics, flows, params, batch)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss

    def setup():
        import jax.random as random
        params = task.init_params(random.PRNGKey(0), False)
        batch = task.sample_initial_states(random.PRNGKey(1), batch_size)
        return params, optimizer.init(params), batch

    return jax.jit(update), setup


def time_variants(variants: dict, rounds: int) -> dict[str, tuple[float, float]]:
    """Median milliseconds per call and compile seconds (the first call), timed round-robin."""
    prepared, compile_seconds = {}, {}
    for name, (update, setup) in variants.items():
        arguments = setup()
        compile_seconds[name] = timing.timed(lambda: update(*arguments))[1]
        prepared[name] = lambda update=update, arguments=arguments: update(*arguments)
    medians = timing.round_robin(prepared, rounds)
    return {name: (1e3 * medians[name], compile_seconds[name]) for name in variants}


def combined_modes() -> list[str]:
    """The modes that combine several flows (``flows.MODE_TABLE``), which share one forward rollout."""
    from stablebptt.flows import MODE_TABLE
    return [mode.name for mode in MODE_TABLE.values() if len(mode.flows) > 1]


def mode_table(title: str, task, batch: int, rounds: int) -> list[str]:
    from stablebptt.flows import MODE_TABLE, MODES
    regular = MODES[0]  # regular BPTT, the baseline of every ratio
    variants = {f"{regular} plain": make_update(task, regular, batch, plain=True)}
    variants.update({mode: make_update(task, mode, batch) for mode in MODES})
    variants[f"{regular} + cosine"] = make_update(task, regular, batch, with_cosine=True)
    times = time_variants(variants, rounds)
    base = times[f"{regular} plain"][0]
    lines = [f"### {title}", "", f"| update | ms (median) | / {regular} plain | compile s |", "|---|---:|---:|---:|"]
    for name, (ms, compile_s) in times.items():
        lines.append(f"| {name} | {ms:.2f} | {ms / base:.2f} | {compile_s:.1f} |")
    lines.append("")
    for mode in combined_modes():
        needs = " and ".join(f"g_{flow}" for flow in MODE_TABLE[mode].flows)
        lines.append(f"{mode} / {regular} = {times[mode][0] / times[regular][0]:.2f} "
                     f"({mode} needs {needs}, all from one forward rollout).")
    return lines + [""]


# The cart-pole simulators of the steps table: option name -> row label.
SIMULATORS = {"generated": "generated step, body by body (the default)", "stages": "MJX stages (scene analysis)",
              "autodiff": "MJX stages, autodiff through M and its solve", "dense": "MJX stages, dense mass matrix",
              "mjx": "mjx.step, MuJoCo default flags", "floor": "closed-form equations (floor)"}


def pipeline_table(poles: int, batch: int, rounds: int, simulators: tuple = tuple(SIMULATORS)) -> list[str]:
    """R updates of the cart-pole through each simulator in ``simulators`` (C too for the generated step and
    the floor), with the parts of the generated step's update where it is among them."""
    import mujoco
    from stablebptt import scene
    from stablebptt.flows import MODES
    from stablebptt.tasks import cartpole_equations, mjcf
    generated = mjcf.make(mjcf.Config(poles=poles))
    stages = mjcf.make(mjcf.Config(poles=poles, pipeline="stages"))
    with_step = lambda step: dataclasses.replace(stages, dynamics=dataclasses.replace(stages.dynamics, step=step))
    model = mjcf.load_model(mjcf.Config(poles=poles).model_path)
    effects = scene.analyze(model)

    def dense():
        dense_model = scene.lean_model(model, effects)
        dense_model.opt.jacobian = mujoco.mjtJacobian.mjJAC_DENSE  # what lean_model replaces by the sparse path
        return with_step(scene.make_step(dense_model, effects, "stages"))

    build = {"generated": lambda: generated, "stages": lambda: stages,
             "autodiff": lambda: with_step(scene.make_step(scene.lean_model(model, effects), effects, "stages", implicit=False)),
             "dense": dense, "mjx": lambda: mjcf.make(mjcf.Config(poles=poles, pipeline="mjx")),
             "floor": lambda: with_step(cartpole_equations.make_step(0.01))}
    chosen = {name: build[name]() for name in SIMULATORS if name in simulators}
    regular = MODES[0]
    variants = {(SIMULATORS[name], regular): make_update(task, regular, batch) for name, task in chosen.items()}
    for name in ("generated", "floor"):  # the combined modes too, on the default step and the floor
        if name in chosen:
            variants.update({(SIMULATORS[name], mode): make_update(chosen[name], mode, batch) for mode in combined_modes()})
    times = time_variants(variants, rounds)
    base, lowest = (times.get((SIMULATORS[name], regular), (None,))[0] for name in ("mjx", "floor"))
    ratio = lambda ms, reference: f"{ms / reference:.2f}" if reference else ""
    lines = [f"### Cart-pole, {poles} pole{'s' if poles > 1 else ''}: where the time goes", "",
             f"| simulator | mode | ms (median) | / mjx.step default | / floor ({regular}) | compile s |",
             "|---|---|---:|---:|---:|---:|"]
    for (label, mode), (ms, compile_s) in times.items():
        lines.append(f"| {label} | {mode} | {ms:.2f} | {ratio(ms, base)} | {ratio(ms, lowest)} | {compile_s:.1f} |")
    if "generated" not in chosen:
        return lines + [""]
    return lines + [""] + parts_table(generated, poles, batch, rounds, variants[SIMULATORS["generated"], regular])


def parts_table(task, poles: int, batch: int, rounds: int, whole_update) -> list[str]:
    """The lean R update split: the rollout alone, and every step's Jacobian in one batched call.

    ``whole_update`` (the pipeline table's compiled lean R update and its
    setup, not compiled again) is timed in the same round-robin, so the rest
    by difference does not mix two tables' machine states.
    """
    import jax
    import jax.random as random
    from stablebptt.flows import reference_loss, reference_rollout, step_jacobians

    dynamics = task.dynamics
    params = task.init_params(random.PRNGKey(0), False)
    starts = task.sample_initial_states(random.PRNGKey(1), batch)
    # The (state, control) pairs of one rollout, all steps and examples in one batch.
    visited = jax.jit(jax.vmap(lambda x0: reference_rollout(dynamics, params, x0)))(starts)
    merge = lambda tree: jax.tree.map(lambda a: a.reshape((a.shape[0] * a.shape[1],) + a.shape[2:]), tree)
    pairs = (merge(visited.states), merge(visited.controls))

    def jacobians(states, controls):
        return jax.tree.map(lambda a: a.sum(), step_jacobians(dynamics.step, states, controls, dynamics.known_columns))

    whole = "whole R update"
    times = time_variants({"rollout only (policy and lean step, no derivatives)": (
                               jax.jit(lambda p, x: reference_loss(dynamics, p, x)), lambda: (params, starts)),
                           f"every step's Jacobian, one batched call ({dynamics.horizon} x {batch} examples)": (
                               jax.jit(jacobians), lambda: pairs),
                           whole: whole_update}, rounds)
    whole_ms = times.pop(whole)[0]
    lines = [f"### Cart-pole, {poles} pole{'s' if poles > 1 else ''}: parts of the default R update", "",
             "| part | ms (median) | / whole R update | compile s |", "|---|---:|---:|---:|"]
    for name, (ms, compile_s) in times.items():
        lines.append(f"| {name} | {ms:.2f} | {ms / whole_ms:.2f} | {compile_s:.1f} |")
    rest = whole_ms - sum(ms for ms, _ in times.values())
    lines.append(f"| the rest, by difference (adjoint recurrence, policy Jacobians and pullback, Adam) | {rest:.2f} | "
                 f"{rest / whole_ms:.2f} | |")
    lines.append(f"| whole R update (timed with the parts) | {whole_ms:.2f} | 1.00 | |")
    return lines + [""]


