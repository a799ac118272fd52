#!/usr/bin/env python3
"""Measure update times, in one run, and print them as Markdown tables.

    python scripts/bench.py                          # every task, poles 1 and 3
    python scripts/bench.py --tasks cartpole --poles 1,2,3,4 --out results/bench_cpu.md

Per task, one update (gradient of a batch-8 rollout, then clip and Adam) per mode:
R, M, S and C through the one-pass flows, and "R plain": jax.grad of the plain
rollout with no flow machinery, the baseline the ratios divide by. For the
cart-pole, also the MJX pipelines: the lean step (scene analysis; differentiated
through inverse dynamics), the same step differentiated by plain autodiff through
the mass matrix and its solve, the same step with MJX's dense mass matrix,
mjx.step with MuJoCo's default flags, and closed-form cart-pole equations as the
floor; and the parts of the lean R update (the rollout alone, and every step's
Jacobian built in one batched call, as the update builds them). Variants of one table are timed round-robin, so drift of
the machine hits all of them alike; tables are timed one after another.
"""
from __future__ import annotations

import sys
from pathlib import Path


import dataclasses
import os
import platform
from dataclasses import dataclass, field

from stablebptt.cli import fail, parse_config

MODE_FLOWS = {"R": ("R",), "M": ("M",), "S": ("S",), "C": ("R", "M")}


@dataclass(frozen=True)
class BenchConfig:
    tasks: str = field(default="repulsion,cartpole,quantum", metadata={"help": "comma-separated tasks"})
    poles: str = field(default="1,3", metadata={"help": "comma-separated pole counts for the cart-pole"})
    batch: int = field(default=8, metadata={"help": "initial states per update"})
    rounds: int = field(default=20, metadata={"help": "timed rounds per variant (median reported)"})
    out: str = field(default="", metadata={"help": "also write the tables to this Markdown file"})


def make_update(task, flows, batch_size, plain=False):
    """A jitted update: gradient (one-pass flows, or plain jax.grad), clip, Adam."""
    import jax
    import optax
    from stablebptt.flows import flow_gradients, reference_loss
    from stablebptt.training import TrainConfig, make_optimizer

    mode = "C" if flows == ("R", "M") else flows[0]
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
    from stablebptt import timing
    prepared, compile_seconds = {}, {}
    for name, (update, setup) in variants.items():
        arguments = setup()
        compile_seconds[name] = timing.timed(lambda: update(*arguments))[1]
        prepared[name] = lambda update=update, arguments=arguments: update(*arguments)
    medians = timing.round_robin(prepared, rounds)
    return {name: (1e3 * medians[name], compile_seconds[name]) for name in variants}


def mode_table(title: str, task, batch: int, rounds: int) -> list[str]:
    variants = {"R plain": make_update(task, ("R",), batch, plain=True)}
    variants.update({mode: make_update(task, flows, batch) for mode, flows in MODE_FLOWS.items()})
    variants["R + cosine"] = make_update(task, ("R", "M"), batch)
    times = time_variants(variants, rounds)
    base = times["R plain"][0]
    lines = [f"### {title}", "", "| update | ms (median) | / R plain | compile s |", "|---|---:|---:|---:|"]
    for name, (ms, compile_s) in times.items():
        lines.append(f"| {name} | {ms:.2f} | {ms / base:.2f} | {compile_s:.1f} |")
    lines.append(f"\nC / R = {times['C'][0] / times['R'][0]:.2f} (C needs g_M and g_R, both from one forward rollout).\n")
    return lines


def pipeline_table(poles: int, batch: int, rounds: int) -> list[str]:
    import mujoco
    from stablebptt import scene
    from stablebptt.tasks import cartpole, cartpole_equations
    lean = cartpole.make(cartpole.Config(poles=poles))
    default = cartpole.make(cartpole.Config(poles=poles, pipeline="mjx"))
    with_step = lambda step: dataclasses.replace(lean, dynamics=dataclasses.replace(lean.dynamics, step=step))
    closed = with_step(cartpole_equations.make_step(0.01))
    model = cartpole.load_model(cartpole.Config(poles=poles).model_path)
    effects = scene.analyze(model)
    autodiff = with_step(scene.make_step(scene.lean_model(model, effects), effects, implicit=False))
    dense_model = scene.lean_model(model, effects)
    dense_model.opt.jacobian = mujoco.mjtJacobian.mjJAC_DENSE  # what lean_model replaces by the sparse path
    dense = with_step(scene.make_step(dense_model, effects))
    variants = {name: make_update(task, ("R",), batch) for name, task in
                (("MJX lean step (scene analysis)", lean), ("MJX lean step, autodiff through M and its solve", autodiff),
                 ("MJX lean step, dense mass matrix", dense),
                 ("mjx.step, MuJoCo default flags", default), ("closed-form equations (floor)", closed))}
    for name, task in (("MJX lean step (scene analysis)", lean), ("closed-form equations (floor)", closed)):
        variants[name + ", C"] = make_update(task, ("R", "M"), batch)
    times = time_variants(variants, rounds)
    base = times["mjx.step, MuJoCo default flags"][0]
    lines = [f"### Cart-pole, {poles} pole{'s' if poles > 1 else ''}: where the time goes", "",
             "| simulator | mode | ms (median) | / mjx.step default | compile s |", "|---|---|---:|---:|---:|"]
    for name, (ms, compile_s) in times.items():
        label, _, mode = name.partition(", C")
        lines.append(f"| {label} | {'C' if _ else 'R'} | {ms:.2f} | {ms / base:.2f} | {compile_s:.1f} |")
    return lines + [""] + parts_table(lean, poles, batch, rounds, variants["MJX lean step (scene analysis)"])


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
    lines = [f"### Cart-pole, {poles} pole{'s' if poles > 1 else ''}: parts of the lean R update", "",
             "| part | ms (median) | / whole R update | compile s |", "|---|---:|---:|---:|"]
    for name, (ms, compile_s) in times.items():
        lines.append(f"| {name} | {ms:.2f} | {ms / whole_ms:.2f} | {compile_s:.1f} |")
    rest = whole_ms - sum(ms for ms, _ in times.values())
    lines.append(f"| the rest, by difference (adjoint recurrence, policy Jacobians and pullback, Adam) | {rest:.2f} | "
                 f"{rest / whole_ms:.2f} | |")
    lines.append(f"| whole R update (timed with the parts) | {whole_ms:.2f} | 1.00 | |")
    return lines + [""]


def main(argv: list[str]) -> int:
    config = parse_config(BenchConfig, argv, __doc__, "benchmark")
    from stablebptt import tasks
    names = [t for t in config.tasks.split(",") if t]
    unknown = [t for t in names if t not in tasks.entries()]
    if unknown:
        fail(f"unknown task {unknown[0]!r}: choose from {', '.join(sorted(tasks.entries()))}")
    try:
        poles = [int(p) for p in config.poles.split(",") if p]
    except ValueError:
        fail(f"--poles takes comma-separated integers, got {config.poles!r}")
    if config.rounds <= 0 or config.batch <= 0:
        fail("--rounds and --batch must be positive")
    import jax
    header = [f"Measured by `python scripts/bench.py {' '.join(argv)}`".rstrip()
              + f" on {platform.machine()} ({jax.devices()[0].platform}, {jax.device_count()} device, "
              f"{len(os.sched_getaffinity(0))} of {os.cpu_count()} cores), "
              f"jax {jax.__version__}, batch {config.batch}, median of {config.rounds} rounds.", ""]
    print("\n".join(header), flush=True)
    report = list(header)
    for name in names:
        module = tasks.load(name)
        if name == "cartpole":
            section = []
            for count in poles:
                task = module.make(module.Config(poles=count))
                section += mode_table(f"Cart-pole (MJX), {count} pole{'s' if count > 1 else ''}", task, config.batch, config.rounds)
                section += pipeline_table(count, config.batch, config.rounds)
        else:
            section = mode_table(name.capitalize(), module.make(module.Config()), config.batch, config.rounds)
        print("\n".join(section), flush=True)
        report += section
        if config.out:  # after every task, so a long benchmark keeps what it measured
            from stablebptt.runs import atomic_write
            Path(config.out).parent.mkdir(parents=True, exist_ok=True)
            atomic_write(Path(config.out), ("\n".join(report) + "\n").encode())
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
