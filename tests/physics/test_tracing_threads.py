"""``differentiable_mjx``'s per-trace choices (the contacts' geometry held, each physics step recomputed)
are flags of the tracing thread over one shared patch of MJX: two threads tracing at once, each with
its own choices, trace the programs each would trace alone."""
import threading

import jax
import jax.numpy as jnp
import mujoco
from mujoco import mjx

from stablebptt.physics.constraint_derivatives import differentiable_mjx

from envs_for_tests import BALL

CHOICES = ((True, True), (False, False))  # (contact_geometry_held, physics_steps_recomputed) of each thread


def _traced(held: bool, recomputed: bool, model, data) -> str:
    """The program of the ball's velocity after two physics steps, differentiated in its start height."""
    def velocity_after(qpos):
        stepped = data.replace(qpos=qpos)
        for _ in range(2):
            stepped = mjx.step(model, stepped)  # looked up in MJX's package, as environments call it
        return stepped.qvel[0]
    with differentiable_mjx(implicit_solver=True, contact_geometry_held=held, physics_steps_recomputed=recomputed):
        return str(jax.make_jaxpr(jax.grad(velocity_after))(data.qpos))


def test_two_threads_tracing_at_once_each_trace_their_own_choices():
    model = mjx.put_model(mujoco.MjModel.from_xml_string(BALL))
    data = mjx.make_data(model).replace(qpos=jnp.array([-0.103]))  # the ball 3 mm in the plane: a contact
    alone = {choice: _traced(*choice, model, data) for choice in CHOICES}
    assert alone[CHOICES[0]] != alone[CHOICES[1]]
    assert "remat" in alone[CHOICES[0]] and "remat" not in alone[CHOICES[1]]
    both_inside = threading.Barrier(len(CHOICES))
    together = {}

    def trace(choice):
        held, recomputed = choice
        try:
            with differentiable_mjx(implicit_solver=True, contact_geometry_held=held, physics_steps_recomputed=recomputed):
                both_inside.wait()  # each thread's context open while the other traces
                together[choice] = _traced(held, recomputed, model, data)
                both_inside.wait()
        except BaseException:
            both_inside.abort()  # the other thread stops waiting: the missing program fails the test
            raise

    threads = [threading.Thread(target=trace, args=(choice,)) for choice in CHOICES]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert together == alone
