"""MJX's constraint solver differentiated inside an environment's mjx.step, and MuJoCo Playground's
environments (tests that need the extra skip without it): the heaviest compiles of the environment
tests, in a module of their own so that a second worker shares them."""
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from stablebptt.engine.compiling import holds_while
from stablebptt.envs.protocol import with_reset_traced_once
from stablebptt.physics import constraint_derivatives
from stablebptt.physics.constraint_derivatives import differentiable_mjx
from stablebptt.physics.mjx_internals import forward as forward_module
from stablebptt.physics.mjx_internals import mjx

from conftest import float64, jitted_anew, needs_playground, refused_in_one_line


LIMIT_AND_CONTACT = """
<mujoco><option timestep="0.01" iterations="4" tolerance="1e-12" ls_tolerance="1e-12"/>
<worldbody><geom type="plane" size="2 2 .1"/>
<body pos="0 0 1"><joint name="hinge" type="hinge" axis="0 1 0" limited="true" range="-0.5 0.5" damping="0.1"/>
<geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.05"/></body>
<body pos="0.6 0 0.1"><joint type="slide" axis="1 0 0"/><joint type="slide" axis="0 0 1"/>
<geom type="sphere" size="0.1" friction="0.5"/></body>
</worldbody><actuator><motor joint="hinge"/></actuator></mujoco>"""


def test_mjx_step_inside_an_environment_is_differentiated_at_the_solver_solution_as_mujocos_c_step():
    model = mujoco.MjModel.from_xml_string(LIMIT_AND_CONTACT)
    x0 = np.array([0.52, 0.1, -0.002, 0.3, 0.2, -0.1])  # past the limit, the ball pressed into the floor
    ctrl = 0.5

    def c_step(x):
        data = mujoco.MjData(model)
        data.qpos[:], data.qvel[:], data.ctrl[:] = x[:3], x[3:], ctrl
        mujoco.mj_step(model, data)
        assert data.nefc >= 4  # the limit and the contact's pyramid stay active under the perturbations
        return np.concatenate([data.qpos, data.qvel])

    eps = 1e-6
    central = np.stack([(c_step(x0 + eps * e) - c_step(x0 - eps * e)) / (2 * eps) for e in np.eye(6)], axis=1)
    with float64():
        mjx_model = mjx.put_model(model, impl="jax")

        def step(x):  # what an environment's step does
            data = mjx.make_data(mjx_model, impl="jax").replace(qpos=x[:3], qvel=x[3:], ctrl=jnp.array([ctrl]))
            data = mjx.step(mjx_model, data)
            return jnp.concatenate([data.qpos, data.qvel])

        # Under jit the refusal comes at tracing: nothing runs op by op (each MJX operation compiled apart).
        with pytest.raises(ValueError, match="Reverse-mode differentiation does not work for lax.while_loop"):
            jax.jit(jax.jacrev(step))(jnp.asarray(x0))
        with differentiable_mjx(implicit_solver=True):
            np.testing.assert_allclose(jax.jit(step)(jnp.asarray(x0)), c_step(x0), atol=1e-12)
            reverse = jax.jit(jax.jacrev(step))(jnp.asarray(x0))  # forward mode: tests/physics/test_suite_models.py
    assert np.abs(central).max() > 10  # the constraints matter: these Jacobians are far from identity
    np.testing.assert_allclose(reverse, central, atol=1e-7)


UNCONSTRAINED_ARM = """
<mujoco><option timestep="0.01"><flag contact="disable"/></option>
<worldbody><body pos="0 0 1"><joint name="hinge" type="hinge" axis="0 1 0" damping="0.1"/>
<geom type="capsule" fromto="0 0 0 0.5 0 0" size="0.05"/><site name="tip" pos="0.5 0 0"/></body></worldbody>
<actuator><motor name="motor" joint="hinge"/></actuator>
<sensor><accelerometer site="tip"/><force site="tip"/><torque site="tip"/><touch site="tip"/>
<framelinacc objtype="site" objname="tip"/><frameangacc objtype="site" objname="tip"/><actuatorfrc actuator="motor"/>
</sensor></mujoco>"""


def test_a_models_acceleration_sensors_without_constraint_rows_are_mujocos_c_values_and_derivative():
    model = mujoco.MjModel.from_xml_string(UNCONSTRAINED_ARM)
    qpos = 0.3

    def c_sensors(ctrl, stepped):
        data = mujoco.MjData(model)
        data.qpos[:], data.ctrl[:] = qpos, ctrl
        (mujoco.mj_step if stepped else mujoco.mj_forward)(model, data)
        return data.sensordata.copy()

    with float64():
        mjx_model = mjx.put_model(model, impl="jax")

        class Arm:  # an environment's reset and step, on MJX's data
            def reset(self, key):
                return mjx.forward(mjx_model, mjx.make_data(mjx_model, impl="jax").replace(qpos=jnp.array([qpos])))

            def step(self, data, ctrl):
                return mjx.step(mjx_model, data.replace(ctrl=ctrl))

        # MJX's own, untouched by this library
        mjxs_own, mjxs_forward = jitted_anew(Arm().reset)(None).sensordata, forward_module.forward
        arm = with_reset_traced_once(Arm())
        data = arm.reset(jax.random.PRNGKey(0))
        with differentiable_mjx():
            def sensors(ctrl):
                return arm.step(data, ctrl).sensordata
            stepped = jax.jit(sensors)(jnp.array([0.5]))
            forward_mode = jax.jit(jax.jacfwd(sensors))(jnp.array([0.5]))
            reverse_mode = jax.jit(jax.jacrev(sensors))(jnp.array([0.5]))
    assert mjx.forward is mjxs_forward and forward_module.forward is mjxs_forward  # undone on exit
    # MJX alone leaves them at zero here (should MJX compute them one day, this fails and the patch can go)
    assert data._impl.efc_J.size == 0 and np.all(np.asarray(mjxs_own) == 0)
    at_reset = c_sensors(0.0, False)
    assert np.abs(at_reset).max() > 1
    np.testing.assert_allclose(data.sensordata, at_reset, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(stepped, c_sensors(0.5, True), rtol=1e-10, atol=1e-12)
    eps = 1e-6
    central = (c_sensors(0.5 + eps, True) - c_sensors(0.5 - eps, True)) / (2 * eps)
    assert np.abs(central).max() > 1  # the motor moves the accelerations the sensors read
    np.testing.assert_allclose(forward_mode[:, 0], central, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(reverse_mode, forward_mode, rtol=1e-12, atol=1e-12)


RK4_PENDULUM = """
<mujoco><option integrator="RK4" timestep="0.05"/>
<worldbody><body><joint name="hinge" type="hinge" axis="0 1 0" damping="0.2"/>
<geom type="capsule" fromto="0 0 0 0 0 -1" size="0.05"/><site name="tip" pos="0 0 -1"/></body></worldbody>
<actuator><motor name="motor" joint="hinge"/></actuator>
<sensor><jointpos joint="hinge"/><jointvel joint="hinge"/><framepos objtype="site" objname="tip"/>
<accelerometer site="tip"/></sensor></mujoco>"""


def test_a_step_under_rk4_keeps_the_sensors_of_the_state_it_began_from_as_mujocos_c_step():
    model = mujoco.MjModel.from_xml_string(RK4_PENDULUM)
    qpos, qvel = 1.0, -0.5

    def c_sensors(ctrl):
        data = mujoco.MjData(model)
        data.qpos[:], data.qvel[:], data.ctrl[:] = qpos, qvel, ctrl
        mujoco.mj_step(model, data)
        return data.sensordata.copy()

    with float64():
        mjx_model = mjx.put_model(model, impl="jax")
        start = mjx.make_data(mjx_model, impl="jax").replace(qpos=jnp.array([qpos]), qvel=jnp.array([qvel]))

        def sensors(ctrl):
            return mjx.step(mjx_model, start.replace(ctrl=ctrl)).sensordata
        # MJX's own through a lambda, so that jax.jit(sensors) inside the context is traced afresh.
        mjxs_own, mjxs_rk4 = jax.jit(lambda ctrl: sensors(ctrl))(jnp.array([0.5])), forward_module.rungekutta4
        with differentiable_mjx():
            stepped = jax.jit(sensors)(jnp.array([0.5]))
            forward_mode = jax.jit(jax.jacfwd(sensors))(jnp.array([0.5]))
            reverse_mode = jax.jit(jax.jacrev(sensors))(jnp.array([0.5]))
    assert mjx.rungekutta4 is mjxs_rk4 and forward_module.rungekutta4 is mjxs_rk4  # undone on exit
    # MJX alone gives its last stage's sensors (should MJX give C's one day, this fails and the patch can go).
    assert np.abs(np.asarray(mjxs_own) - c_sensors(0.5)).max() > 1e-3
    np.testing.assert_allclose(stepped, c_sensors(0.5), rtol=1e-10, atol=1e-12)
    eps = 1e-6
    central = (c_sensors(0.5 + eps) - c_sensors(0.5 - eps)) / (2 * eps)
    assert np.abs(central).max() > 0.1  # the motor moves the acceleration the accelerometer reads
    np.testing.assert_allclose(forward_mode[:, 0], central, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(reverse_mode, forward_mode, rtol=1e-12, atol=1e-12)


def test_the_solver_loop_bounded_by_the_models_iterations_keeps_mjxs_values_to_the_bit_and_no_loop_of_unknown_length(
        monkeypatch):
    # In float64 to the bit (in float32 XLA may fuse the two loops' arithmetic apart: the last digit).
    with float64():
        _bounded_and_mjxs_loop_step_alike(monkeypatch)


def _bounded_and_mjxs_loop_step_alike(monkeypatch):
    mjx_model = mjx.put_model(mujoco.MjModel.from_xml_string(LIMIT_AND_CONTACT), impl="jax")  # 4 iterations
    # Past the limit with the ball pressed into the floor (every iteration taken), and clear of both (the
    # solver's test ends it after the first): alone, and in one batch where the first keeps the second going.
    states = jnp.array([[0.52, 0.1, -0.002, 0.3, 0.2, -0.1], [0.0, 0.3, 0.5, 0.0, 0.0, 0.0]])

    def step(x):
        data = mjx.make_data(mjx_model, impl="jax").replace(qpos=x[:3], qvel=x[3:], ctrl=jnp.array([0.5]))
        with differentiable_mjx(implicit_solver=True):
            data = mjx.step(mjx_model, data)
        return jnp.concatenate([data.qpos, data.qvel, data.qacc, data.qfrc_constraint])

    def stepped(bound):
        monkeypatch.setattr(constraint_derivatives, "BOUNDED_SOLVER_ITERATIONS", bound)
        loops = holds_while(jax.make_jaxpr(jax.vmap(step))(states).jaxpr)
        return loops, jax.jit(jax.vmap(step))(states), [jax.jit(step)(x) for x in states]

    mjx_loops, mjx_batch, mjx_alone = stepped(0)
    bounded_loops, bounded_batch, bounded_alone = stepped(constraint_derivatives.BOUND_OVER_PLAYGROUND_ITERATIONS)
    assert mjx_loops and not bounded_loops
    np.testing.assert_array_equal(bounded_batch, mjx_batch)
    for bounded, own in zip(bounded_alone, mjx_alone):
        np.testing.assert_array_equal(bounded, own)
    assert np.abs(mjx_batch[0, 9:]).max() > 1  # the first state's constraint force is at work
    many = mjx.put_model(mujoco.MjModel.from_xml_string(LIMIT_AND_CONTACT.replace('iterations="4"', 'iterations="100"')),
                         impl="jax")
    with differentiable_mjx(implicit_solver=True):  # a file's default of 100 keeps MJX's early end
        assert holds_while(jax.make_jaxpr(lambda: mjx.step(many, mjx.make_data(many, impl="jax")))().jaxpr)


@needs_playground
def test_playgrounds_tolerance_keeps_its_values_and_loses_its_nan_derivative():
    from mujoco_playground._src import reward

    from stablebptt.envs.playground import safe_tolerance
    x = jnp.linspace(-3.0, 3.0, 61)
    repaired = 0
    for sigmoid in ("gaussian", "hyperbolic", "long_tail", "reciprocal", "tanh_squared", "cosine", "linear", "quadratic"):
        for bounds in ((0.0, 0.0), (1.0, np.inf), (-np.inf, 0.5), (-1.0, 1.0)):
            for margin in (0.0, 1.0, 2.0):
                theirs = lambda v: reward.tolerance(v, bounds, margin, sigmoid, 0.1)  # noqa: E731
                ours = lambda v: safe_tolerance(v, bounds, margin, sigmoid, 0.1)  # noqa: E731
                np.testing.assert_allclose(ours(x), theirs(x), atol=1e-6)
                slope, their_slope = jax.vmap(jax.grad(ours))(x), jax.vmap(jax.grad(theirs))(x)
                assert np.isfinite(slope).all(), (sigmoid, bounds, margin)
                finite = np.isfinite(their_slope)
                np.testing.assert_allclose(slope[finite], their_slope[finite], atol=1e-5)
                repaired += int((~finite).sum())
    assert repaired > 0  # the infinite upper bound's NaN is there to repair
    # Sloped tails: the same values everywhere; past a compact sigmoid's end, where the tolerance was flat, a
    # slope towards the bounds equal to the sigmoid's mean slope over its reach (1 over its reach in x).
    x = jnp.linspace(-12.0, 12.0, 241)
    for sigmoid, value_at_margin, reach in (("linear", 0.5, 2.0), ("linear", 0.0, 1.0), ("quadratic", 0.19, 1 / 0.9),
                                            ("cosine", 0.5, 2.0)):
        for bounds, margin in (((1.0, np.inf), 0.5), ((-1.0, 1.0), 2.0)):
            flat = lambda v: safe_tolerance(v, bounds, margin, sigmoid, value_at_margin)  # noqa: E731
            sloped = lambda v: safe_tolerance(v, bounds, margin, sigmoid, value_at_margin, sloped_tails=True)  # noqa: E731
            np.testing.assert_array_equal(sloped(x), flat(x))
            slope, flat_slope = jax.vmap(jax.grad(sloped))(x), jax.vmap(jax.grad(flat))(x)
            beyond = np.maximum(bounds[0] - x, x - bounds[1]) - reach * margin  # the distance past the end
            past_end, before_end = beyond > 1e-4, beyond < -1e-4  # a point at the end itself falls either way
            np.testing.assert_array_equal(flat_slope[past_end], 0.0)
            towards_bounds = np.where(x < bounds[0], 1.0, -1.0) / (reach * margin)
            np.testing.assert_allclose(slope[past_end], towards_bounds[past_end], rtol=1e-5)
            np.testing.assert_array_equal(slope[before_end], flat_slope[before_end])
            assert past_end.sum() >= 10 and before_end.sum() >= 10
    # The task option puts the sloped form in the registry env's step, and says so; outside the step nothing changes.
    from stablebptt.envs.playground import SLOPED_TAILS, repaired_rewards
    from stablebptt.tasks import env as env_tasks
    task = env_tasks.make(env_tasks.Config(env="CartpoleSwingup", sloped_reward_tails=True, reward_check=False))
    assert SLOPED_TAILS in task.summary and SLOPED_TAILS not in env_tasks.make(
        env_tasks.Config(env="CartpoleSwingup", reward_check=False)).summary
    moving = lambda v: reward.tolerance(v, (1.0, np.inf), 0.5, "linear", 0.5)  # noqa: E731 - the walker's move reward
    with repaired_rewards(sloped_tails=True):
        assert float(jax.grad(moving)(-1.0)) == 1.0 and float(moving(-1.0)) == 0.0
    assert float(jax.grad(moving)(-1.0)) == 0.0
    # A block holds for its thread alone: another thread's block (no sloped tails) entered meanwhile does not reach
    # this one, and this one left first does not end the other's, whose gaussian keeps its finite derivative
    # inside an infinite bound (Playground's own is NaN there).
    import threading
    gaussian = lambda v: reward.tolerance(v, (1.0, np.inf), 0.5, "gaussian", 0.1)  # noqa: E731
    entered, left, seen = threading.Event(), threading.Event(), []

    def other_thread():
        with repaired_rewards():
            seen.append(float(jax.grad(moving)(-1.0)))
            entered.set()
            left.wait()
            seen.append(float(jax.grad(gaussian)(2.0)))
    other = threading.Thread(target=other_thread, daemon=True)  # a failed assertion here leaves it waiting
    with repaired_rewards(sloped_tails=True):
        other.start()
        assert entered.wait(timeout=300)  # a bound, should the other thread fail before it enters
        assert float(jax.grad(moving)(-1.0)) == 1.0  # still this block's sloped tails
    left.set()
    other.join()
    assert seen == [0.0, 0.0] and float(jax.grad(moving)(-1.0)) == 0.0 and np.isnan(float(jax.grad(gaussian)(2.0)))
    # A refusal suggests the dense variant only where the registry has one.
    from stablebptt.envs.playground import dense_variant
    assert dense_variant("CartpoleSwingupSparse") == "CartpoleSwingup" and dense_variant("PendulumSwingup") == ""


@needs_playground
def test_a_misspelt_playground_name_is_refused_naming_the_closest(tmp_path, capsys):
    # A Playground env trained and rendered from the command line: tests/render/test_render.py's episode runs.
    refused_in_one_line(capsys, tmp_path / "no", "did you mean CartpoleSwingup?", "--env", "cartpoleswingup")


@needs_playground
def test_a_playground_env_of_several_physics_steps_a_control_step_recomputes_each_in_the_backward_pass():
    from stablebptt.envs import playground
    from stablebptt.envs.adapter import env_task
    from stablebptt.envs.derivative_model import own_substeps
    env = playground.load("ReacherEasy")  # a small model stepped in several physics steps a control step
    assert own_substeps(env) > 1
    state = jitted_anew(env.reset)(jax.random.PRNGKey(0))

    def gradient_program(recomputed):  # Playground's mjx_env.step calls mjx.step through MJX's package
        task = env_task(env, horizon=2, diagnose=False, physics_steps_recomputed=recomputed)
        return str(jax.make_jaxpr(jax.grad(lambda action: task.dynamics.step(state, action).obs.sum()))(
            jnp.full(env.action_size, 0.3)))
    assert "remat" in gradient_program(None)  # the default, where a control step spans several physics steps
    assert "remat" not in gradient_program(False)
