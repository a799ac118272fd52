"""A train.py run's update and evaluation programs (an epoch of separate programs), each traced,
compiled and run alone on this machine: seconds to trace and lower, to compile, and milliseconds per
call (the mean of five after one), with the compile cache off. Training on carried episodes, three more: the
program every epoch starts with, which draws the fresh states its ended episodes start from (``Trainer.refill``);
the update's floor, the forward rollout of the same window from the same carried states with the
same policy (every seed, every env), and jax.grad of that plain window's mean reward (the step's own
derivative, none of the flows' machinery, no critic).

    python benchmarks/update_program.py --model S/hopper.xml --train-size 32 --test-size 8 --batch 8 --steps 50
    python benchmarks/update_program.py --env CheetahRun --steps 32 --critic --discount 0.99 --seeds 5
    python benchmarks/update_program.py --flows-batched --model S/hopper.xml ...   # the reverse pass's
        # pullbacks batched over the flows (adjoint_step.pullbacks_in_turn off)
    python benchmarks/update_program.py --programs update --env CheetahRun --mode R --no-cosine   # these alone
    python benchmarks/update_program.py --bounded-solver-loop --env WalkerWalk ...   # MJX's solver loop run
        # exactly the model's iterations, MJX's values (bit for bit in float64, the last digit in float32 may
        # differ; constraint_derivatives.BOUNDED_SOLVER_ITERATIONS)
    python benchmarks/update_program.py --collision-held --env HumanoidStand ... --sizes   # what if the
        # contacts' geometry (points, frames, distances) were held in the derivative: MJX's collision
        # functions then have no derivative in the program (a what-if: no training option takes it)
    python benchmarks/update_program.py --self-collision-held --env HumanoidStand ...   # the same for the
        # contacts with no plane or height field in them (the humanoid's limbs against each other; in general
        # any pair without the ground), those with the floor differentiated
    python benchmarks/update_program.py --contact-gradient-geometry held --env HumanoidStand ...   # train.py's
        # option: the contacts' points and frames held, their distances by the closed form n . (v2 - v1)
    python benchmarks/update_program.py --substeps-unrolled --env HumanoidStand ...   # MuJoCo Playground's
        # loop over a control step's physics steps unrolled (a what-if; with --physics-step-residuals
        # stored, nothing stacked per physics step)
    python benchmarks/update_program.py --profile --env HumanoidStand ...   # each program's device time,
        # distinct ops and the kernels they launched by MJX stage and the call within it, and by name stack,
        # from one call under JAX's profiler
        # (benchmarks/device_time.py)
    python benchmarks/update_program.py --programs grad --gradient-file G.npz ...   # the plain window's
        # gradient per seed written to G.npz with the command, or compared with the one there (cosine,
        # relative difference)

--programs: a comma-separated choice of update, evaluation, refill, floor, grad (default: every one there is),
and memory: the memory plan's bytes stored for the update's backward pass, from its trace of one step
(``--programs memory`` alone prints that and times nothing); state (asked for only): the training state's
bytes and what a checkpoint keeps of them (the carried population without its pool), from its shapes.
--sizes: each chosen program's size as lowered (lines of StableHLO, while loops, dynamic_update_slice ops)
and the seconds its trace and lowering took, nothing compiled or run:
what a program holds, where its compile on a GPU is what costs (the same program on any backend).

Every other option is train.py's (--mode R --no-cosine: one flow). The task is built as train.py builds it,
its reward check run first; where the check keeps the reward as written (HumanoidStand's, the walkers'),
--no-reward-check gives the same programs sooner (on one H200 HumanoidStand's update had not been timed
295 s after the command began, its check and init run first).
"""
import contextlib
import os
import sys
import time

os.environ.setdefault("JAX_ENABLE_COMPILATION_CACHE", "false")

import jax  # noqa: E402
import numpy as np  # noqa: E402

import device_time  # noqa: E402  (beside this script)

from stablebptt import tasks  # noqa: E402
from stablebptt.commands import train as train_script  # noqa: E402
from stablebptt.engine.compiling import memory_plan  # noqa: E402
from stablebptt.engine.config import batched_seeds, seed_array  # noqa: E402
from stablebptt.engine.episodes import checkpointed  # noqa: E402
from stablebptt.engine.lowering import state_shapes  # noqa: E402
from stablebptt.engine.per_update import PerUpdateEpoch  # noqa: E402
from stablebptt.engine.training import make_trainer  # noqa: E402
from stablebptt.flows import adjoint_step  # noqa: E402
from stablebptt.physics import constraint_derivatives  # noqa: E402

arguments = sys.argv[1:]
chosen = {"memory", "update", "evaluation", "refill", "floor", "grad"}
if "--programs" in arguments:
    at = arguments.index("--programs")
    chosen = set(arguments[at + 1].split(","))
    del arguments[at:at + 2]
if "--bounded-solver-loop" in arguments:
    arguments.remove("--bounded-solver-loop")
    constraint_derivatives.BOUNDED_SOLVER_ITERATIONS = constraint_derivatives.BOUND_OVER_PLAYGROUND_ITERATIONS
    print("MJX's solver loop runs exactly the model's iterations (--bounded-solver-loop)", flush=True)
if "--collision-held" in arguments:
    arguments.remove("--collision-held")
    from stablebptt.physics.mjx_internals import collision_driver  # noqa: E402  (MJX calls it through its module)
    collide = collision_driver.collision

    def collision_held(model, data):
        found = collide(model, data)
        return found.tree_replace({"_impl.contact": jax.lax.stop_gradient(found._impl.contact)})
    collision_driver.collision = collision_held
    print("the contacts' geometry held in the derivative (--collision-held)", flush=True)
if "--substeps-unrolled" in arguments:  # MuJoCo Playground's loop over a control step's physics steps, unrolled
    arguments.remove("--substeps-unrolled")
    from mujoco_playground._src import mjx_env  # noqa: E402  (its envs call it through the module)
    from stablebptt.physics.mjx_internals import mjx  # noqa: E402

    def physics_steps(model, data, action, n_substeps=1):
        def physics_step(data, _):  # mjx.step looked up at each call: --physics-step-residuals still applies
            return mjx.step(model, data.replace(ctrl=action)), None
        return jax.lax.scan(physics_step, data, (), n_substeps, unroll=n_substeps)[0]
    mjx_env.step = physics_steps
    print("MuJoCo Playground's physics steps per control step unrolled (--substeps-unrolled)", flush=True)
if "--self-collision-held" in arguments:
    arguments.remove("--self-collision-held")
    from stablebptt.physics.mjx_internals import collision_driver  # noqa: E402
    from stablebptt.physics.mjx_internals import types as mjx_types  # noqa: E402
    grounds = {mjx_types.GeomType.PLANE, mjx_types.GeomType.HFIELD}

    def held(function):  # the pairs' collision function on the data held: it has no derivative in the program
        def collide_held(model, data, key, geoms):
            return function(model, jax.lax.stop_gradient(data), key, geoms)
        collide_held.ncon = function.ncon
        return collide_held
    # Before the groups' contacts are joined: held after, every group's derivative would still run, times zero.
    collision_driver._COLLISION_FUNC.update({types: held(function) for types, function in
                                             collision_driver._COLLISION_FUNC.items() if not set(types) & grounds})
    print("the geometry of contacts with no plane or height field in them held in the derivative "
          "(--self-collision-held)", flush=True)
gradient_file = None
if "--gradient-file" in arguments:
    at = arguments.index("--gradient-file")
    gradient_file = arguments[at + 1]
    del arguments[at:at + 2]
if gradient_file is not None and ("grad" not in chosen or "--sizes" in arguments):
    sys.exit("--gradient-file compares the grad program's output: give --programs with grad, without --sizes")
profiled = "--profile" in arguments
if profiled:
    arguments.remove("--profile")
    named_calls = contextlib.ExitStack()  # held open for the script's life: every trace below is named
    named_calls.enter_context(device_time.calls_named())
sizes_only = "--sizes" in arguments
if sizes_only:
    arguments.remove("--sizes")
if "--flows-batched" in arguments:
    arguments.remove("--flows-batched")
    adjoint_step.pullbacks_in_turn = lambda: False
options, owners = train_script.parse(arguments + ["--epoch-program", "per-update"])
task_name, task_config, train_config, _, _ = train_script.configure(options, owners)
task = tasks.load(task_name).make(task_config)
trainer = make_trainer(task, train_config)
assert isinstance(trainer.epoch, PerUpdateEpoch)
if "memory" in chosen:
    one_state = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape[1:], a.dtype), trainer.train_states)
    stored = memory_plan(task, train_config, one_state).estimate  # the plan's bound, every batched seed's path
    copies = batched_seeds(train_config)
    per_step = stored / (trainer.horizon * train_config.batch * copies)
    print(f"{' '.join(arguments)}: memory plan: {per_step / 2**20:.2f} MiB a step stored for the backward pass, "
          f"{stored / copies / 2**30:.1f} GiB a seed, {stored / 2**30:.1f} GiB for {copies} seed(s) "
          f"({train_config.batch} envs x {trainer.horizon} steps each)", flush=True)
    if chosen == {"memory"}:
        sys.exit(0)
if "state" in chosen:
    shapes = state_shapes(trainer, seed_array(train_config))
    mib = lambda tree: sum(np.prod(leaf.shape) * np.dtype(leaf.dtype).itemsize for leaf in jax.tree.leaves(tree)) / 2**20  # noqa: E731
    print(f"{' '.join(arguments)}: training state {mib(shapes):.1f} MiB, of which a checkpoint keeps "
          f"{mib(checkpointed(shapes)):.1f} MiB", flush=True)
    if chosen <= {"memory", "state"}:
        sys.exit(0)
seeds = seed_array(train_config)
# Sizes need the state's shapes alone: its values would cost init's compiles and runs first.
state = state_shapes(trainer, seeds) if sizes_only else trainer.init(seeds)
programs = [("update", trainer.epoch.update, (state, jax.tree.map(lambda a: a[0], trainer.batches)))]
if trainer.epoch.evaluate is not None:
    programs.append(("evaluation", trainer.epoch.evaluate, (state.params, trainer.train_states, trainer.test_states)))
elif trainer.evaluation is not None:
    programs.append(("evaluation", trainer.evaluation, (state.params, trainer.train_states, trainer.test_states)))
if trainer.episodes is not None:
    programs.append(("refill", trainer.refill, (state,)))
    step, policy, reward = task.dynamics.step, task.dynamics.policy, trainer.episodes.reward

    def window(params, states):  # every env of one seed one window on: (final states, mean reward)
        def advance(states, _):
            reached = jax.vmap(lambda s: step(s, policy(params, s)))(states)
            return reached, jax.vmap(reward)(reached).mean()
        final, rewards = jax.lax.scan(advance, states, None, length=trainer.horizon)
        return final, rewards.mean()

    forward = jax.jit(jax.vmap(window), compiler_options=trainer.compiler_options)
    plain_grad = jax.jit(jax.vmap(jax.grad(lambda params, states: window(params, states)[1])),
                         compiler_options=trainer.compiler_options)
    carried = state.carried.states
    programs += [("floor", forward, (state.params, carried)), ("grad", plain_grad, (state.params, carried))]
    envs = len(seed_array(train_config)) * train_config.batch
    print(f"{' '.join(arguments)}: {envs} envs (seeds x batch), windows of {trainer.horizon} steps", flush=True)
described = {"refill": "an epoch's fresh states (refill)", "floor": "forward window (floor)",
             "grad": "jax.grad of the plain window"}


def milliseconds(compiled, inputs) -> float:
    """Per call, the mean of five after one."""
    jax.block_until_ready(compiled(*inputs))
    started = time.perf_counter()
    for _ in range(5):
        jax.block_until_ready(compiled(*inputs))
    return (time.perf_counter() - started) / 5 * 1000


def compare_gradients(gradient, path: str, label: str) -> None:
    """Writes each seed's gradient (its parameters' leaves flattened) to ``path``, or where it holds one
    already, compares with it: the cosine and the relative difference per seed."""
    flat = np.concatenate([np.asarray(leaf).reshape(leaf.shape[0], -1) for leaf in jax.tree.leaves(gradient)], 1)
    if not os.path.exists(path):
        with open(path, "wb") as handle:  # the command beside the gradient: a comparison names what it compares with
            np.savez(handle, gradient=flat, command=label)
        print(f"{label}: gradient written to {path}", flush=True)
        return
    with np.load(path) as kept:
        reference, reference_command = kept["gradient"], str(kept["command"])
    if reference.shape != flat.shape:
        sys.exit(f"{path} holds a gradient of shape {reference.shape} ({reference_command}), this one's is {flat.shape}")
    print(f"{label}: compared with {reference_command}", flush=True)
    norms = np.linalg.norm(flat, axis=1) * np.linalg.norm(reference, axis=1)
    cosine = np.sum(flat * reference, 1) / norms
    relative = np.linalg.norm(flat - reference, axis=1) / np.linalg.norm(reference, axis=1)
    print(f"{label}: against {path}, per seed: cosine {np.array2string(cosine, precision=5)}, relative difference "
          f"{np.array2string(relative, precision=4)}", flush=True)


for name, program, inputs in [program for program in programs if program[0] in chosen]:
    start = time.perf_counter()
    lowered = program.lower(*inputs)
    lowered_at = time.perf_counter()
    if sizes_only:
        text = lowered.as_text()
        print(f"{' '.join(arguments)}: {described.get(name, name)}: trace and lower {lowered_at - start:.1f} s, "
              f"{text.count(chr(10))} lines of StableHLO, "
              f"{text.count('stablehlo.while')} while loops, {text.count('stablehlo.dynamic_update_slice')} "
              f"dynamic_update_slice ops (a loop's stores of what its backward pass reads among them)", flush=True)
        continue
    compiled = lowered.compile()
    compiled_at = time.perf_counter()
    print(f"{' '.join(arguments)}: {described.get(name, name)}: trace and lower {lowered_at - start:.1f} s, compile "
          f"{compiled_at - lowered_at:.1f} s, run {milliseconds(compiled, inputs):.1f} ms", flush=True)
    if name == "grad" and gradient_file is not None:
        compare_gradients(compiled(*inputs), gradient_file, f"{' '.join(arguments)}: {described[name]}")
    if profiled:
        device_time.split(compiled, inputs, f"{' '.join(arguments)}: {described.get(name, name)}")
