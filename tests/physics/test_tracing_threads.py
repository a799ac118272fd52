"""``differentiable_mjx``'s per-trace choices (the solver differentiated at its solution, the contacts'
geometry held, each physics step recomputed) are flags of the tracing thread over one shared patch of MJX: threads tracing at once, each with its
own choices, trace the programs each would trace alone, and a recomputed step's program follows the
trace's other choices, not the first trace of it."""
import threading

import jax
import jax.numpy as jnp
import mujoco
from mujoco import mjx

from stablebptt.physics.constraint_derivatives import differentiable_mjx

from envs_for_tests import BALL

# (implicit_solver, contact_geometry_held, physics_steps_recomputed) of each thread: two recompute, so the held
# geometry must reach inside the recomputed step in the thread that holds it and not in the other; one
# differentiates the solver's iterations while the others take it at its solution.
CHOICES = ((True, True, True), (True, False, True), (True, False, False), (False, False, False))


def _traced(implicit: bool, held: bool, recomputed: bool, model, data) -> str:
    """The program of the ball's velocity after two physics steps and its derivative in its start height."""
    def velocity_after(qpos):
        stepped = data.replace(qpos=qpos)
        for _ in range(2):
            stepped = mjx.step(model, stepped)  # looked up in MJX's package, as environments call it
        return stepped.qvel[0]
    with differentiable_mjx(implicit_solver=implicit, contact_geometry_held=held, physics_steps_recomputed=recomputed):
        # Forward mode: the solver's own iterations (implicit off) are a while loop reverse mode cannot pass.
        return str(jax.make_jaxpr(lambda qpos: jax.jvp(velocity_after, (qpos,), (jnp.ones_like(qpos),)))(data.qpos))


def test_threads_tracing_at_once_each_trace_their_own_choices():
    model = mjx.put_model(mujoco.MjModel.from_xml_string(BALL))
    data = mjx.make_data(model).replace(qpos=jnp.array([-0.103]))  # the ball 3 mm in the plane: a contact
    alone = {choice: _traced(*choice, model, data) for choice in CHOICES}
    assert len(set(alone.values())) == len(CHOICES)
    assert ["remat" in alone[choice] for choice in CHOICES] == [recomputed for *_, recomputed in CHOICES]
    # A deadlock guard, not a wait: each thread passes as soon as the others reach it.
    all_inside = threading.Barrier(len(CHOICES), timeout=600)
    together = {}

    def trace(choice):
        implicit, held, recomputed = choice
        try:
            with differentiable_mjx(implicit_solver=implicit, contact_geometry_held=held,
                                    physics_steps_recomputed=recomputed):
                all_inside.wait()  # every thread's context open while the others trace
                together[choice] = _traced(implicit, held, recomputed, model, data)
                all_inside.wait()
        except BaseException:
            all_inside.abort()  # the others stop waiting: the missing program fails the test
            raise

    # Daemons: a thread stuck tracing fails the test at its join and does not keep the test process alive.
    threads = [threading.Thread(target=trace, args=(choice,), daemon=True) for choice in CHOICES]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=1200)
    assert together == alone
