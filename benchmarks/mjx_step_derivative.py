"""MJX's own step of an environment's model, alone: milliseconds of a rollout of ``--physics-steps``
physics steps of ``--batch`` states, and of jax.grad of a function of its end, which is MJX's
reverse-mode derivative through those steps (no policy, no reward, none of the library's flows);
the median over rounds of one call each (``stablebptt.timing.round_robin``).
It prices the step's derivative against its forward where the update stands far above its floor.

    python benchmarks/mjx_step_derivative.py FishSwim
    python benchmarks/mjx_step_derivative.py FishSwim --density 0    # the fluid's forces off

Reverse mode cannot pass MJX's constraint solver loop: a model with constraints is refused.
"""
import argparse
import sys

import jax
import jax.numpy as jnp

from stablebptt.physics import scene
from stablebptt.physics.mjx_internals import mjx
from stablebptt.timing import compile_ahead, round_robin


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("env", help="a name in MuJoCo Playground's registry")
    parser.add_argument("--physics-steps", type=int, default=40)
    parser.add_argument("--batch", type=int, default=16)
    parser.add_argument("--density", type=float, default=None, help="the fluid's density in place of the file's")
    parser.add_argument("--rounds", type=int, default=7, help="rounds of one call each, round-robin (the median)")
    args = parser.parse_args()
    from mujoco_playground import registry
    model = registry.load(args.env).mj_model
    if args.density is not None:
        model.opt.density = args.density
    if scene.analyze(model).constraints:
        print(f"error: {args.env}'s model has constraints: reverse mode cannot pass MJX's solver loop", file=sys.stderr)
        return 2
    device_model = mjx.put_model(model, impl="jax")
    start = mjx.make_data(device_model).replace(qpos=jnp.asarray(model.qpos0), ctrl=0.3 * jnp.ones(model.nu))
    velocities = 0.1 * jax.random.normal(jax.random.PRNGKey(0), (args.batch, model.nv))

    def end(qvel):
        def physics_step(data, _):
            return jax.vmap(lambda one: mjx.step(device_model, one))(data), None
        data = jax.vmap(lambda v: start.replace(qvel=v))(qvel)
        data, _ = jax.lax.scan(physics_step, data, None, length=args.physics_steps)
        return jnp.sum(data.qpos ** 2) + jnp.sum(data.qvel ** 2)

    forward = compile_ahead(jax.jit(end), velocities)[0]
    derivative = compile_ahead(jax.jit(jax.grad(end)), velocities)[0]
    seconds = round_robin({"forward": lambda: forward(velocities), "grad": lambda: derivative(velocities)}, args.rounds)
    forward_ms, derivative_ms = 1e3 * seconds["forward"], 1e3 * seconds["grad"]
    print(f"{args.env} (density {model.opt.density:g}), {args.batch} states x {args.physics_steps} physics steps on "
          f"{jax.default_backend()}: forward {forward_ms:.1f} ms, jax.grad {derivative_ms:.1f} ms "
          f"({derivative_ms / forward_ms:.1f}x)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
