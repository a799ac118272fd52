"""How long XLA takes to compile one scene's step, alone and differentiated: where a cold start goes.

    python benchmarks/step_compile.py S/hopper.xml [S/cheetah.xml ...]
    python benchmarks/step_compile.py --forms S/hopper.xml S/humanoid.xml
    python benchmarks/step_compile.py --jacobians S/finger.xml S/hopper.xml

With --jacobians, the step's Jacobians of 80 examples by forward and by reverse mode: compile seconds
and run milliseconds.

With --forms, only the generated rigid-body terms (stablebptt/physics/rigid_body.py) in both forms, written out
and in arrays: traced operations and compile seconds of the terms and of their JVP (the JVP
written out only up to 12 dofs: beyond, XLA's compile outgrows this machine's memory).

Per model and step (the default one; MJX's stages; the generated rigid-body part alone, its
constraints left out), three programs over a batch of 8 with the compile cache off: the step, its
vector-Jacobian product, and the gradient of a 10-step rollout. Seconds to trace, lower and compile.
"""
import os
import sys
import time

os.environ.setdefault("JAX_ENABLE_COMPILATION_CACHE", "false")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402

from stablebptt.physics import lean_step, rigid_body, simulator  # noqa: E402
from stablebptt.physics.array_terms import ArrayTerms  # noqa: E402
from stablebptt.physics.scene_terms import BALL, FREE  # noqa: E402
from stablebptt.physics.written_out import WrittenOut  # noqa: E402

BATCH, STEPS = 8, 10


def timed(label: str, function, *args) -> None:
    start = time.perf_counter()
    try:
        traced = jax.jit(function).trace(*args)
    except ValueError as error:  # mjx.step's solver loop (RK4 scenes' stages pipeline) has no reverse mode
        print(f"  {label}: {str(error).splitlines()[0]}", flush=True)
        return
    traced_at = time.perf_counter()
    lowered = traced.lower()
    lowered_at = time.perf_counter()
    lowered.compile()
    print(f"  {label}: trace {traced_at - start:.1f} s, lower {lowered_at - traced_at:.1f} s, "
          f"compile {time.perf_counter() - lowered_at:.1f} s", flush=True)


def programs(step, state, control) -> None:
    batched = jax.vmap(step)

    def pullback(state, control):
        out, pull = jax.vjp(batched, state, control)
        return pull(out)

    def rollout_gradient(state, control):
        def final(control):
            end = jax.lax.scan(lambda s, _: (batched(s, control), None), state, None, length=STEPS)[0]
            return sum(jnp.sum(leaf ** 2) for leaf in jax.tree.leaves(end))
        return jax.grad(final)(control)

    timed("step", batched, state, control)
    timed("its vjp", pullback, state, control)
    timed(f"gradient of a {STEPS}-step rollout", rollout_gradient, state, control)


def forms(path: str) -> None:
    model = simulator.build(mujoco.MjModel.from_xml_path(path)).lean
    inputs = (jnp.broadcast_to(jnp.asarray(model.qpos0, jnp.float32), (BATCH, model.nq)), jnp.zeros((BATCH, model.nv)),
              jnp.zeros((BATCH, model.nu)))
    for form in (WrittenOut, ArrayTerms):
        terms = form(model).rigid_body
        functions = {"terms": jax.vmap(terms)}
        if form is ArrayTerms or model.nv <= 12:
            functions["JVP"] = jax.vmap(lambda q, v, u: jax.jvp(terms, (q, v, u), (q, v, u)))
        for label, function in functions.items():
            traced = jax.jit(function).trace(*inputs)
            lowered = traced.lower()
            start = time.perf_counter()
            lowered.compile()
            print(f"{os.path.basename(path)}, {form.__name__}, {label}: {len(traced.jaxpr.eqns)} operations, "
                  f"compile {time.perf_counter() - start:.1f} s", flush=True)


def jacobians(path: str) -> None:
    """The step's Jacobians of 80 examples by forward and by reverse mode: compile seconds and the
    mean of five runs."""
    sim = simulator.build(mujoco.MjModel.from_xml_path(path))
    examples = 80
    state = jax.tree.map(lambda a: jnp.broadcast_to(a, (examples,) + a.shape), lean_step.initial_state(sim.lean))
    control = jnp.zeros((examples, sim.lean.nu))
    for label, jacobian in (("jacfwd", jax.jacfwd), ("jacrev", jax.jacrev)):
        program = jax.jit(jax.vmap(jacobian(sim.step, argnums=(0, 1))))
        start = time.perf_counter()
        compiled = program.lower(state, control).compile()
        compiled_in = time.perf_counter() - start
        jax.block_until_ready(compiled(state, control))
        start = time.perf_counter()
        for _ in range(5):
            jax.block_until_ready(compiled(state, control))
        print(f"{os.path.basename(path)}, {label} of {examples} examples: compile {compiled_in:.1f} s, "
              f"run {(time.perf_counter() - start) / 5 * 1000:.1f} ms", flush=True)


if sys.argv[1] in ("--forms", "--jacobians"):
    for path in sys.argv[2:]:
        (forms if sys.argv[1] == "--forms" else jacobians)(path)
    sys.exit()

for path in sys.argv[1:]:
    sim = simulator.build(mujoco.MjModel.from_xml_path(path))
    state = jax.tree.map(lambda a: jnp.broadcast_to(a, (BATCH,) + a.shape), lean_step.initial_state(sim.lean))
    control = jnp.zeros((BATCH, sim.lean.nu))
    stages = simulator.build(sim.model, simulator.SimulatorConfig(pipeline="stages")).step
    steps = {"default": sim.step, "stages": stages}
    if lean_step.generated_step_applies(sim.lean, sim.effects) and not set(sim.lean.jnt_type) & {FREE, BALL}:
        steps["generated rigid-body part, no constraints"] = rigid_body.make_step(sim.lean)
    for name, step in steps.items():
        print(f"{os.path.basename(path)}, {name}:", flush=True)
        programs(step, state, control)
