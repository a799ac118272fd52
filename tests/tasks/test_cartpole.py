"""Cart-pole through MJX and any MJCF: physics against closed forms, scene analysis, training, bad input."""
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

from stablebptt.engine.config import TrainConfig, seed_array
from stablebptt.engine.training import make_trainer
from stablebptt.flows.gradients import flow_gradients
from stablebptt.flows.linearized import step_jacobians
from stablebptt.physics import lean_step, scene, symmetries
from stablebptt.tasks import cartpole_equations, mjcf, mjcf_spec

from conftest import ROOT, float64

TRAIN = [sys.executable, str(ROOT / "scripts" / "train.py")]


def mjx_against_equations(poles, accelerations, dtype_x64):
    """Max deviation of MJX from the closed-form equations over 100 steps under random forces."""
    context = float64() if dtype_x64 else _nothing()
    with context:
        task = mjcf.make(mjcf.Config(poles=poles))
        reference = cartpole_equations.make_step(0.01, accelerations)
        start = jax.tree.map(lambda a: a[0], task.sample_initial_states(jax.random.PRNGKey(poles), 1))
        forces = 5.0 * jax.random.normal(jax.random.PRNGKey(10 + poles), (100, 1))

        def both(carry, force):
            mjx_state, closed_state = carry
            mjx_state, closed_state = task.dynamics.step(mjx_state, force), reference(closed_state, force)
            deviation = jnp.maximum(jnp.max(jnp.abs(mjx_state.qpos - closed_state.qpos)),
                                    jnp.max(jnp.abs(mjx_state.qvel - closed_state.qvel)))
            return (mjx_state, closed_state), deviation

        _, deviations = jax.jit(lambda s, f: jax.lax.scan(both, (s, s), f))(start, forces)
        return float(deviations.max())


class _nothing:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def test_one_pole_reproduces_the_classic_equations_in_float64():
    assert mjx_against_equations(1, cartpole_equations.classic_accelerations, True) <= 1e-10


def test_one_pole_reproduces_the_classic_equations_in_float32():
    assert mjx_against_equations(1, cartpole_equations.classic_accelerations, False) <= 1e-5


@pytest.mark.parametrize("poles", [2, 4])
def test_parallel_poles_match_the_exact_rigid_body_equations(poles):
    assert mjx_against_equations(poles, cartpole_equations.exact_accelerations, True) <= 1e-10


def test_the_models_declare_the_paper_set_up():
    for poles in range(1, 5):
        model = mjcf_spec.load_model(mjcf.MODELS / f"cartpole_{poles}.xml")
        spec = mjcf.read_spec(model)
        assert (model.nq, model.nu, spec.horizon, spec.loss) == (poles + 1, 1, 100, "final")
        assert model.opt.timestep == 0.01 and model.opt.gravity[2] == -9.8
        np.testing.assert_allclose(model.body_mass[1:], [1.0] + [0.1] * poles)
        # Exact uniform rod: m L^2 / 12 about the centre, so m (2l)^2 / 3 about the pivot.
        np.testing.assert_allclose(model.body_inertia[2:, 1] + 0.1 * 0.5**2, 0.1 * 1.0**2 / 3)
        np.testing.assert_allclose(np.asarray(spec.init.qpos), [0.0] + [np.pi] * poles)


@pytest.fixture(scope="module")
def three_pole_task():
    return mjcf.make(mjcf.Config(poles=3))


def test_initial_states_and_loss_follow_the_paper(three_pole_task):
    states = three_pole_task.sample_initial_states(jax.random.PRNGKey(0), 256)
    angles = np.asarray(states.qpos[:, 1:])
    assert np.all(np.abs(angles - np.pi) <= np.pi / 6) and np.all(np.abs(states.qpos[:, 0]) <= 1)
    assert np.all(np.abs(states.qvel) <= 1)
    # Final-state loss 1 - mean(cos(angles)): hanging straight down gives 2, upright 0.
    upright = jax.tree.map(lambda a: a[:1], states)._replace(qpos=jnp.zeros((1, 4)))
    down = upright._replace(qpos=jnp.array([[0.3, np.pi, np.pi, np.pi]]))
    assert np.isclose(three_pole_task.dynamics.loss(upright, None), 0.0)
    assert np.isclose(three_pole_task.dynamics.loss(down, None), 2.0)


@pytest.mark.parametrize("poles", [2, 4])  # 1 pole: tests/tasks/test_smoke.py
def test_all_flows_give_finite_gradients(poles):
    task = mjcf.make(mjcf.Config(poles=poles, steps=30))
    params = task.init_params(jax.random.PRNGKey(0), False)
    batch = task.sample_initial_states(jax.random.PRNGKey(1), 2)
    loss, grads = jax.jit(lambda p, x: flow_gradients(task.dynamics, ("R", "M", "S"), p, x, task.plan))(params, batch)
    assert np.isfinite(loss)
    assert all(np.all(np.isfinite(leaf)) for leaf in jax.tree.leaves(grads))


def test_a_short_training_lowers_the_test_loss(three_pole_task):
    config = TrainConfig(mode="C", train_size=16, test_size=16, batch=8, lr=3e-3)
    trainer = make_trainer(three_pole_task, config)
    state = trainer.init(seed_array(config))
    losses = []
    for _ in range(3):
        state, metrics = trainer.epoch(state, trainer.batches, trainer.train_states, trainer.test_states)
        losses.append(float(metrics["test_loss"][0]))
    assert losses[-1] < losses[0]


SCENE = """<mujoco>
  <option timestep="0.01"/>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.1" {floor}/>
    <body pos="0 0 0.5">
      <joint name="a" type="hinge" axis="0 1 0" {joint}/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.05" {geom}/>
    </body>
  </worldbody>
  <actuator><motor joint="a" {motor}/></actuator>
</mujoco>"""


def analyze(floor="", joint="", geom="", motor=""):
    return scene.analyze(mujoco.MjModel.from_xml_string(SCENE.format(floor=floor, joint=joint, geom=geom, motor=motor)))


def test_scene_analysis_finds_what_a_scene_can_do():
    bare = analyze(floor='contype="0" conaffinity="0"')
    assert not any([bare.contacts, bare.joint_limits, bare.dampers, bare.springs, bare.control_clamp, bare.constraints])
    assert analyze().contacts  # a capsule that swings down to a plane can touch it
    limited = analyze(floor='contype="0" conaffinity="0"', joint='limited="true" range="-1 1"')
    assert limited.joint_limits and limited.constraints and not limited.contacts
    damped = analyze(floor='contype="0" conaffinity="0"', joint='damping="0.5" stiffness="2"', motor='ctrlrange="-1 1"')
    assert damped.dampers and damped.springs and damped.control_clamp and damped.passive


def test_lean_model_keeps_what_the_scene_has_and_differentiates_constraints():
    model = mujoco.MjModel.from_xml_string(SCENE.format(floor="", joint='damping="0.5" limited="true" range="-1 1"',
                                                        geom="", motor='ctrlrange="-1 1"'))
    effects = scene.analyze(model)
    lean = scene.lean_model(model, effects, solver_iterations=1)
    flags = int(lean.opt.disableflags)
    for kept in ("mjDSBL_CONTACT", "mjDSBL_LIMIT", "mjDSBL_DAMPER", "mjDSBL_CLAMPCTRL", "mjDSBL_EULERDAMP"):
        assert not flags & int(getattr(mujoco.mjtDisableBit, kept)), kept
    # No stiffness anywhere, but MJX's spring flag would switch the damper off too.
    assert not flags & int(mujoco.mjtDisableBit.mjDSBL_SPRING)
    assert lean.opt.iterations == 1 and model.opt.iterations != 1  # the user's model is untouched
    assert "1 Newton iteration, fixed" in scene.describe(effects, lean)
    assert scene.lean_model(model, effects).opt.iterations == model.opt.iterations  # the model's own by default
    # And the constrained, damped, clamped scene differentiates end to end.
    step = lean_step.make_step(lean, effects)
    start = lean_step.State(jnp.array([0.9]), jnp.array([2.0]), jnp.zeros(0))

    def final_angle(force):
        state, _ = jax.lax.scan(lambda s, _: (step(s, force), None), start, None, length=20)
        return state.qpos[0]

    value, gradient = jax.jit(jax.value_and_grad(final_angle))(jnp.array([0.5]))
    assert np.isfinite(value) and np.all(np.isfinite(gradient))
    assert value <= 1.0 + 0.05  # the limit holds the hinge near its range


FLOATING_BALL_AND_SPRING = """<mujoco>
  <option timestep="0.01"/>
  <default><geom contype="0" conaffinity="0"/></default>
  <worldbody>
    <body pos="0 0 1"><freejoint name="float"/>
      <geom type="capsule" fromto="0 0 0 0.3 0.1 -0.5" size="0.05"/>
      <body pos="0.3 0.1 -0.5"><joint name="ball" type="ball" stiffness="3"/>
        <geom type="box" size="0.05 0.1 0.2" pos="0 0 -0.2"/>
      </body>
    </body>
  </worldbody>
  <actuator><motor joint="ball" gear="0 2 0"/><motor joint="float" gear="0 1 0 0 0 1"/></actuator>
</mujoco>"""


@pytest.mark.parametrize("source", ["cartpole_3", "floating_ball_and_spring"])
def test_implicit_step_derivative_equals_autodiff_through_the_mass_matrix(x64, source):
    """d qacc = -M^-1 d(inverse dynamics) must give the Jacobians plain autodiff gives, forward and reverse."""
    if source == "floating_ball_and_spring":  # quaternions (nq != nv), a spring, two actuators, no cart
        model = mujoco.MjModel.from_xml_string(FLOATING_BALL_AND_SPRING)
    else:
        model = mujoco.MjModel.from_xml_path(str(ROOT / "stablebptt" / "models" / f"{source}.xml"))
    effects = scene.analyze(model)
    lean = scene.lean_model(model, effects)
    assert lean_step.implicit_derivative_applies(lean, effects)
    implicit, autodiff = lean_step.make_step(lean, effects), lean_step.make_step(lean, effects, implicit=False)
    rng = np.random.default_rng(3)
    qpos = rng.normal(size=model.nq)
    if source == "floating_ball_and_spring":
        qpos[3:7] /= np.linalg.norm(qpos[3:7])
        qpos[7:] /= np.linalg.norm(qpos[7:])
    state = lean_step.State(jnp.array(qpos), jnp.array(rng.normal(size=model.nv)), jnp.zeros(0))
    control = jnp.array(rng.normal(size=model.nu))
    expected = jax.jit(jax.jacfwd(autodiff, argnums=(0, 1)))(state, control)
    # Both directions on the cart-pole; reverse alone on the free body, whose float64 compiles are the
    # costly ones (forward mode goes through the same implicit solve).
    for jacobian in (jax.jacfwd, jax.jacrev) if source == "cartpole_3" else (jax.jacrev,):
        got = jax.jit(jacobian(implicit, argnums=(0, 1)))(state, control)
        for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(expected)):
            np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-11)
    # expected nests: output field -> (by state, by control) -> input field.
    rows = lambda block: np.reshape(block, (np.shape(block)[0], int(np.prod(np.shape(block)[1:]))))
    fields = lean_step.State._fields
    state_matrix = np.block([[rows(getattr(getattr(expected, out)[0], into)) for into in fields] for out in fields])
    control_matrix = np.concatenate([rows(getattr(expected, out)[1]) for out in fields])
    # The symmetries the analysis claims hold: shifting the cart's (the free body's) position shifts
    # the next position alone; a Galilean boost shifts the next velocity by as much, the position by dt as much.
    known, _ = symmetries.symmetries(lean, effects)
    translations = [0] if source == "cartpole_3" else [0, 1, 2]
    assert sorted(known.indices.tolist()) == sorted(translations + [model.nq + k for k in translations])
    np.testing.assert_allclose(state_matrix[:, known.indices], known.columns, atol=1e-11)
    # One input at a time, as the training's batched Jacobians go (the others are symbolic zeros),
    # with the known columns copied instead of computed.
    # Large scenes push every input's tangents through one differentiated step: the same Jacobians.
    # On the cart-pole only: the free body's symmetry columns are checked against autodiff above, and
    # its float64 compiles of the step's derivative are the costly ones.
    batch = jax.tree.map(lambda a: a[None], (state, control))
    for per_input in (True, False) if source == "cartpole_3" else ():
        by_input = jax.jit(lambda s, u: step_jacobians(implicit, s, u, known, per_input=per_input))(*batch)
        np.testing.assert_allclose(by_input[0][0], state_matrix, rtol=1e-9, atol=1e-11)
        np.testing.assert_allclose(by_input[1][0], control_matrix, rtol=1e-9, atol=1e-11)
    # The velocity rows are not trivial: they carry dt * d qacc.
    velocity_by_position = np.asarray(expected.qvel[0].qpos)  # d qvel_next / d qpos
    assert np.abs(velocity_by_position).max() > 1e-3


def test_implicit_derivative_is_not_used_where_its_equation_does_not_hold():
    damped = mujoco.MjModel.from_xml_string(SCENE.format(floor='contype="0" conaffinity="0"', joint='damping="0.5"',
                                                         geom="", motor=""))
    limited = mujoco.MjModel.from_xml_string(SCENE.format(floor='contype="0" conaffinity="0"',
                                                          joint='limited="true" range="-1 1"', geom="", motor=""))
    for model in (damped, limited):  # implicit damping solves with M + dt D; a limit adds constraint forces
        effects = scene.analyze(model)
        assert not lean_step.implicit_derivative_applies(scene.lean_model(model, effects), effects)


SLIDER = """<mujoco>
  <option {option}/>
  <default><geom contype="0" conaffinity="0"/></default>
  <worldbody>
    {floor}
    <body name="cart"><joint name="x" type="slide" axis="1 0 0" {slide}/><geom type="box" size="0.2 0.1 0.1"/>
      <body name="pole"><joint name="a" type="hinge" axis="0 1 0"/><geom type="capsule" fromto="0 0 0 0 0 1" size="0.05"/>
        <body name="tip"><joint name="z" type="slide" axis="0 0 1"/><geom type="sphere" size="0.1" pos="0 0 1"/></body>
      </body>
    </body>
  </worldbody>
  <actuator>{actuator}</actuator>
</mujoco>"""


@pytest.mark.parametrize("option, floor, slide, actuator, position, velocity", [
    ("", "", "", '<motor joint="x"/>', True, True),
    ("", "", 'damping="0.3"', '<motor joint="x"/>', True, False),  # damping: a force from the velocity
    ("", "", "", '<motor joint="x"/><velocity joint="a" kv="2"/>', True, True),  # relative velocity only
    ("", "", 'stiffness="2"', '<motor joint="x"/>', False, True),  # a spring pulls towards its rest position
    ("", "", 'limited="true" range="-1 1"', '<motor joint="x"/>', False, False),
    ("", "", "", '<position joint="x" kp="5"/>', False, True),  # a servo's force depends on the position
    ("", "", "", '<velocity joint="x" kv="2"/>', True, False),
    ('density="1.2" viscosity="0.1"', "", "", '<motor joint="x"/>', True, False),  # air at rest in the world
    ("", '<geom type="plane" size="5 5 0.1"/>', "", '<motor joint="x"/>', False, False),  # the floor can be touched
])
def test_symmetries_are_claimed_only_where_nothing_ties_the_tree_to_the_world(option, floor, slide, actuator,
                                                                               position, velocity):
    model = mujoco.MjModel.from_xml_string(SLIDER.format(option=option, floor=floor, slide=slide, actuator=actuator))
    if floor:  # let every geom collide
        model.geom_contype[:] = model.geom_conaffinity[:] = 1
    known, joints = symmetries.symmetries(model, scene.analyze(model))
    # Only the cart can be symmetric: the tip's slide moves along the turning pole.
    assert sorted(known.indices.tolist()) == [0] * position + [3] * velocity  # qpos x, qvel x
    assert joints == (["x"] if position or velocity else [])


@pytest.mark.parametrize("integrator", ["rk4", "implicitfast"])
def test_symmetry_columns_hold_for_the_other_integrators(x64, integrator):
    """Every integrator advances positions with the velocities it reaches: the boost column is e_v + dt e_q."""
    model = mujoco.MjModel.from_xml_path(str(ROOT / "stablebptt" / "models" / "cartpole_1.xml"))
    effects = scene.analyze(model)
    lean = scene.lean_model(model, effects, integrator=integrator, timestep=0.02)
    step = lean_step.make_step(lean, effects)
    known, _ = symmetries.symmetries(lean, effects)
    assert known.indices.tolist() == [0, model.nq] and known.columns[0, 1] == 0.02
    rng = np.random.default_rng(0)
    flat, unravel = ravel_pytree(lean_step.State(jnp.array(rng.normal(size=model.nq)), jnp.array(rng.normal(size=model.nv)),
                                             jnp.zeros(0)))
    control = jnp.array(rng.normal(size=model.nu))
    jacobian = jax.jit(jax.jacfwd(lambda x: ravel_pytree(step(unravel(x), control))[0]))(flat)
    np.testing.assert_allclose(np.asarray(jacobian)[:, known.indices], known.columns, atol=1e-12)
    assert np.abs(np.asarray(jacobian)[model.nq:, 1]).max() > 1e-3  # the pole's column is not trivial


ARM = """<mujoco model="two-link arm">
  <option timestep="0.01"/>
  <default><geom contype="0" conaffinity="0"/></default>
  <worldbody>
    <body name="upper"><joint name="shoulder" type="hinge" axis="0 0 1" damping="0.05"/>
      <geom type="capsule" fromto="0 0 0 0.5 0 0" size="0.04"/>
      <body name="lower" pos="0.5 0 0"><joint name="elbow" type="hinge" axis="0 0 1" damping="0.05"/>
        <geom type="capsule" fromto="0 0 0 0.4 0 0" size="0.03"/>
      </body>
    </body>
  </worldbody>
  <actuator><motor joint="shoulder" ctrlrange="-2 2"/><motor joint="elbow" ctrlrange="-2 2"/></actuator>
  {custom}
</mujoco>"""


def test_an_unannotated_arm_with_two_actuators_trains_with_no_code_change(tmp_path):
    model_file = tmp_path / "arm.xml"
    model_file.write_text(ARM.format(custom=textwrap.dedent("""
        <custom><numeric name="bptt_horizon" data="40"/></custom>
        <keyframe><key name="target" qpos="1.2 -0.8"/></keyframe>""")))
    result = subprocess.run(TRAIN + ["--model", str(model_file), "--epochs", "5", "--train-size", "16",
                                     "--test-size", "16", "--lr", "3e-3", "--out", str(tmp_path / "run"),
                                     "--no-progress"], capture_output=True, text=True, cwd=ROOT)
    assert result.returncode == 0, result.stderr
    assert "dampers" in result.stdout.split("skipped")[0] and "control clamping" in result.stdout.split("skipped")[0]
    import csv
    rows = list(csv.DictReader(open(tmp_path / "run" / "metrics.csv")))
    assert float(rows[-1]["test_loss"]) < float(rows[0]["test_loss"])


