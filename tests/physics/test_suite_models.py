"""The DeepMind Control Suite's own model files, as a user passes them to --model.

Every suite model either becomes a task (scene line, memory plan, the model's
name in its messages) or is refused in one line that names the feature. A few
are checked against MuJoCo's C step and trained end to end.

The files are fetched from the dm_control package at test set-up rather than
kept here: the test then runs on exactly the files users have, and another
project's files are not copied into this repository. The wheel is cached in
.cache/ (git-ignored).
"""
from __future__ import annotations

import subprocess
import sys

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from stablebptt.engine.compiling import memory_plan
from stablebptt.engine.config import TrainConfig
from stablebptt.errors import InputError
from stablebptt.physics import lean_step, mjx_support, rigid_body, scene, simulator
from stablebptt.physics.mjx_internals import collision_driver
from stablebptt.tasks import mjcf, mjcf_spec

from conftest import ROOT

SUITE = ["acrobot", "ball_in_cup", "cartpole", "cheetah", "dog", "finger", "fish", "hopper", "humanoid",
         "humanoid_CMU", "lqr", "manipulator", "pendulum", "point_mass", "quadruped", "reacher", "stacker",
         "swimmer", "walker"]
# What the suite asks for that cannot be trained as the file stands, and the words of the refusal.
REFUSED = {
    "dog": "cylinder-box contacts",
    "quadruped": "hfield-cylinder contacts",
    "lqr": "no joints",  # dm_control adds the bodies in code: the file is a template
    "swimmer": "no actuators",  # likewise
}


PLANNED = ("pendulum", "hopper", "humanoid_CMU")


@pytest.mark.parametrize("name", SUITE)
def test_every_suite_model_becomes_a_task_or_is_refused_in_one_line(suite, name):
    config = mjcf.Config(model=str(suite / f"{name}.xml"))
    if name in REFUSED:
        with pytest.raises(InputError) as refusal:
            mjcf.make(config)
        message = str(refusal.value)
        assert message.startswith(f"{name}.xml: ") and REFUSED[name] in message and "\n" not in message, message
        return
    task = mjcf.make(config)
    assert task.name == name and task.summary.startswith(f"{name}.xml: scene: ")
    assert task.resolved["horizon_steps"] == task.dynamics.horizon
    # Diagnostics are skipped and named; the solver line says which solver runs.
    original = mujoco.MjModel.from_xml_path(config.model)
    if original.opt.enableflags & mujoco.mjtEnableBit.mjENBL_ENERGY:
        assert "energy diagnostic" in task.summary.split("skipped:")[1]
    effects = scene.analyze(original)
    if effects.constraints:
        assert "constraint solver: " in task.summary
    # Every input's tangent passes the solver: forward mode's Jacobians are built in one pass.
    assert task.plan.jacobian_per_input == (not effects.constraints)
    # The gradient path's memory is planned from a trace of its step, without an error, on models that span
    # the plans (forward mode, reverse mode with contacts, the largest tree), since tracing a large step's
    # derivative for the plan takes seconds per model (how a plan chunks or stores: tests/flows/test_flows.py).
    if name not in PLANNED:
        return
    initial = jax.tree.map(lambda a: a[0], task.sample_initial_states(jax.random.PRNGKey(0), 1))
    assert memory_plan(task, TrainConfig(), initial).estimate > 0


# Models whose differentiated step is checked against MuJoCo's C step: the energy flag (pendulum),
# RK4 (acrobot; both steps generated body by body), a joint limit with the model's own solver
# (reacher), contacts on the floor (hopper), friction loss at rest (finger's spinner: differentiating
# the solver's iterations instead of its solution put d qvel'/d qvel off by 12x there).
CHECKED = ["pendulum", "acrobot", "reacher", "hopper", "finger"]


@pytest.mark.parametrize("name", CHECKED)
def test_the_step_and_its_derivative_agree_with_mujocos_c_step(suite, x64, name):
    path = suite / f"{name}.xml"
    task = mjcf.make(mjcf.Config(model=str(path)))
    model = mujoco.MjModel.from_xml_path(str(path))
    data = mujoco.MjData(model)
    rng = np.random.default_rng(0)
    for _ in range(round(0.5 / model.opt.timestep)):  # a state reached by the model's own physics
        data.ctrl[:] = rng.uniform(-1, 1, model.nu)
        mujoco.mj_step(model, data)
    data.ctrl[:] = rng.uniform(-1, 1, model.nu)
    state = lean_step.State(jnp.array(data.qpos), jnp.array(data.qvel), jnp.array(data.act))
    velocity_direction, control_direction = rng.normal(size=model.nv), rng.normal(size=model.nu)

    def c_step(scale):
        copy = mujoco.MjData(model)
        copy.qpos[:], copy.qvel[:], copy.act[:] = data.qpos, data.qvel + scale * velocity_direction, data.act
        copy.ctrl[:] = data.ctrl + scale * control_direction
        copy.qacc_warmstart[:] = data.qacc_warmstart
        mujoco.mj_step(model, copy)
        return np.concatenate([copy.qpos, copy.qvel])

    step = jax.jit(lambda s, u, ds, du: jax.jvp(task.dynamics.step, (s, u), (ds, du)))
    following, tangent = step(state, jnp.array(data.ctrl),
                              lean_step.State(jnp.zeros(model.nq), jnp.array(velocity_direction), jnp.zeros(model.na)),
                              jnp.array(control_direction))
    ours = np.concatenate([following.qpos, following.qvel])
    np.testing.assert_allclose(ours, c_step(0.0), rtol=0, atol=1e-9)
    eps = 1e-6
    central = (c_step(eps) - c_step(-eps)) / (2 * eps)
    derivative = np.concatenate([tangent.qpos, tangent.qvel])
    assert np.linalg.norm(derivative - central) <= 1e-5 * np.linalg.norm(central)

    # At the task's initial states and zero control (an untrained policy's output) the derivative stays
    # finite and the controls move the model. On finger (contacts with an elliptic cone, joint limits,
    # friction loss at rest) both the one-iteration solver and MJX's elliptic cone once gave NaN there,
    # which mode C's update hid as zeros. A dense random direction carries a NaN of any Jacobian entry.
    starts = task.sample_initial_states(jax.random.PRNGKey(0), 2)
    for k in range(2):
        start = jax.tree.map(lambda a: a[k], starts)
        zero = jnp.zeros(model.nu)
        _, by_state = step(start, zero, lean_step.State(jnp.zeros(model.nq), jnp.array(velocity_direction),
                                                    jnp.zeros(model.na)), zero)
        _, by_control = step(start, zero, lean_step.State(jnp.zeros(model.nq), jnp.zeros(model.nv), jnp.zeros(model.na)),
                             jnp.array(control_direction))
        assert all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree.leaves((by_state, by_control))), name
        assert float(jnp.abs(by_control.qvel).max()) > 0, name


def test_the_models_own_solver_in_reverse_mode_steps_as_mujocos_c_step_and_agrees_with_forward_mode(suite, x64):
    """hopper on the floor: reverse mode passes the file's own solver (its while loop, not differentiated:
    the derivative is implicit at the solution), and a fixed iteration count steps as MuJoCo's C step does."""
    model = mujoco.MjModel.from_xml_path(str(suite / "hopper.xml"))
    effects = scene.analyze(model)
    data = mujoco.MjData(model)
    rng = np.random.default_rng(1)
    for _ in range(400):  # onto the floor, in contact
        data.ctrl[:] = rng.uniform(-1, 1, model.nu)
        mujoco.mj_step(model, data)
        if data.ncon:
            break
    assert data.ncon > 0
    state = lean_step.State(jnp.array(data.qpos), jnp.array(data.qvel), jnp.array(data.act))
    control = jnp.array(rng.uniform(-1, 1, model.nu))

    def c_step(simulated):
        copy = mujoco.MjData(simulated)
        copy.qpos[:], copy.qvel[:], copy.ctrl[:] = data.qpos, data.qvel, control
        mujoco.mj_step(simulated, copy)  # from a cold start, as the lean step solves
        return np.concatenate([copy.qpos, copy.qvel])

    flat = lambda s: np.concatenate([s.qpos, s.qvel])
    fixed = scene.lean_model(model, effects, solver_iterations=2)
    assert scene.fixed_iterations(fixed) and "2 Newton iterations, fixed" in scene.describe(effects, fixed, model)
    np.testing.assert_allclose(flat(jax.jit(lean_step.make_step(fixed, effects))(state, control)), c_step(fixed),
                               rtol=0, atol=1e-9)
    lean = scene.lean_model(model, effects)
    assert "the model's own (Newton, at most 100 iterations" in scene.describe(effects, lean, model)
    step = lean_step.make_step(lean, effects)
    # <J^T w, v> = <w, J v>: reverse mode agrees with forward mode.
    tangent = (lean_step.State(jnp.zeros(model.nq), jnp.array(rng.normal(size=model.nv)), jnp.zeros(0)),
               jnp.array(rng.normal(size=model.nu)))
    weight = lean_step.State(jnp.array(rng.normal(size=model.nq)), jnp.array(rng.normal(size=model.nv)), jnp.zeros(0))
    following, forward = jax.jit(lambda s, u, t: jax.jvp(step, (s, u), t))(state, control, tangent)
    np.testing.assert_allclose(flat(following), c_step(model), rtol=0, atol=1e-9)  # the step's value, from the jvp
    reverse = jax.jit(lambda s, u, w: jax.vjp(step, s, u)[1](w))(state, control, weight)
    dot = lambda a, b: sum(float(jnp.vdot(x, y)) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))
    assert np.isfinite(dot(reverse, reverse))
    np.testing.assert_allclose(dot(reverse, tangent), dot(weight, forward), rtol=1e-8)


def test_a_contact_rollout_follows_mujocos_c_step_with_the_files_own_solver(suite, x64):
    """hopper falling onto the floor and kicking for 1 s under random controls: the lean step, as
    training runs it, against MuJoCo's C step with the file's settings, state by state."""
    path = suite / "hopper.xml"
    task = mjcf.make(mjcf.Config(model=str(path)))
    model = mujoco.MjModel.from_xml_path(str(path))
    controls = np.random.default_rng(2).uniform(-1, 1, (round(1.0 / model.opt.timestep), model.nu))
    data, visited, touching = mujoco.MjData(model), [], 0
    for control in controls:
        data.ctrl[:] = control
        mujoco.mj_step(model, data)
        visited.append(np.concatenate([data.qpos, data.qvel]))
        touching += data.ncon > 0
    assert touching > len(controls) // 4  # mostly in contact: the solver works in most steps
    start = lean_step.initial_state(model)
    states = jax.jit(lambda s, us: jax.lax.scan(lambda x, u: (task.dynamics.step(x, u),) * 2, s, us)[1])(
        start, jnp.asarray(controls))
    ours = np.concatenate([states.qpos, states.qvel], axis=1)
    np.testing.assert_allclose(ours, np.array(visited), rtol=0, atol=1e-8)


def test_a_suite_model_trains_and_renders_from_the_command_line(suite, tmp_path):
    """stablebptt/models/README.md's worked example, shortened: dm_control's pendulum, file untouched, swung up from
    hanging by a task file: the command names the model, its record resolves the task file's pose and horizon
    against the file, the file is kept as it was, the loss falls below a quarter of hanging's, and it renders."""
    run, task_file = tmp_path / "run", tmp_path / "swing_up.task.json"
    task_file.write_text('{"init_pose": "hinge=3.14159", "horizon_seconds": 7}')
    train = subprocess.run([sys.executable, "scripts/train.py", "--model", str(suite / "pendulum.xml"),
                            "--task-file", str(task_file), "--epochs", "4", "--train-size", "64", "--test-size", "8",
                            "--lr", "3e-3", "--clip", "norm", "--no-progress", "--out", str(run)],
                           capture_output=True, text=True, cwd=ROOT)
    assert train.returncode == 0, train.stderr
    assert "time to the first update:" in train.stdout and "done: pendulum, mode C" in train.stdout
    import json
    saved = json.loads((run / "config.json").read_text())
    resolved = saved["resolved_task"]
    assert resolved["name"] == "pendulum" and resolved["horizon_steps"] == 350  # 7 s at the file's 0.02 s
    assert resolved["init"]["qpos"] == pytest.approx([3.14159]) and resolved["task_file"] == str(task_file)
    assert (run / "model.xml").read_bytes() == (suite / "pendulum.xml").read_bytes()
    # Hanging is a loss of 2; 32 updates of C already bring most test states up (the worked example: 0.11).
    final_losses = [float(line.split(",")[4]) for line in (run / "metrics.csv").read_text().splitlines()[1:]]
    assert final_losses[-1] < 0.5, final_losses
    render = subprocess.run([sys.executable, "scripts/render.py", str(run), "--rollouts", "1",
                             "--no-video"], capture_output=True, text=True, cwd=ROOT)
    assert render.returncode == 0, render.stderr
    assert list(run.glob("*-strip.png"))


# Eight reacher states (float32, zero control) from a 20-step rollout; at the last, MJX's line
# search met a search direction of rounding noise: its Newton step's derivative divided by the
# square of ~1e-20, which float32 flushes to 0 (stablebptt/physics/constraint_derivatives.py explains the remedy).
REACHER_QPOS = [[-0.05686615, 0.08633361], [-0.06332258, 0.02021889], [0.022796154, 0.06927885],
                [-0.020602277, -0.07723963], [-0.009803113, -0.018506018], [-0.022436908, 0.010405372],
                [0.03532419, -0.07883733], [-0.03214946, 0.06130206]]
REACHER_QVEL = [[-0.013969594, -0.0043659396], [-0.00890346, -0.0027836794], [0.027263714, 0.008518695],
                [0.020994965, 0.006562692], [0.026421068, 0.008260929], [0.022445856, 0.007017428],
                [0.019866386, 0.0062097562], [-0.007989659, -0.0024974558]]


def test_a_fixed_iteration_solvers_jacobians_stay_finite_where_the_line_search_direction_vanishes(suite):
    task = mjcf.make(mjcf.Config(model=str(suite / "reacher.xml"), step_derivative="reverse",
                                         solver_iterations=1, steps=5))
    states = lean_step.State(jnp.array(REACHER_QPOS, jnp.float32), jnp.array(REACHER_QVEL, jnp.float32), jnp.zeros((8, 0)))
    flat = lambda s: jnp.concatenate([s.qpos, s.qvel])
    jacobians = {}
    for name, jacobian in (("reverse", jax.jacrev), ("forward", jax.jacfwd)):
        by_example = jax.vmap(jacobian(lambda s, u: flat(task.dynamics.step(s, u)), argnums=(0, 1)))
        jacobians[name] = jax.jit(by_example)(states, jnp.zeros((8, 2), jnp.float32))
        assert all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree.leaves(jacobians[name])), name
    for a, b in zip(jax.tree.leaves(jacobians["reverse"]), jax.tree.leaves(jacobians["forward"])):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)


def test_clipping_an_edge_nearly_parallel_to_a_side_plane_keeps_reverse_mode_finite():
    # MJX clips a capsule's or box's edge against a convex body's side planes
    # (manipulator, stacker); an edge nearly parallel to a plane gave NaN
    # cotangents. Values: the clipped intersection of the closed form.
    from stablebptt.physics.constraint_derivatives import _closest_segment_point_plane_stable as point
    from stablebptt.physics.constraint_derivatives import differentiable_mjx
    from stablebptt.physics.mjx_internals import collision_convex
    normal = jnp.array([0.0, 0.0, 1.0], jnp.float32)
    cases = [((0, 0, 0), (1, 0, 1e-30), (0, 0, 1)),  # nearly parallel, clipped to b
             ((0, 0, 0), (1, 0, 0), (0, 0, 1)),  # exactly parallel (MJX divides by 1e-6)
             ((0, 0, -1), (1, 0, 1), (0, 0, 0.5)),  # crosses the plane at t = 0.75
             ((0, 0, 1), (1, 0, 2), (0, 0, 0.5))]  # plane behind a: clipped to a
    for a, b, on_plane in cases:
        a, b, on_plane = (jnp.array(v, jnp.float32) for v in (a, b, on_plane))
        along = float(b[2] - a[2])
        t = float(np.clip((on_plane[2] - a[2]) / (along if along else 1e-6), 0, 1))
        np.testing.assert_allclose(point(a, b, on_plane, normal), a + t * (b - a), atol=1e-6)
        gradients = jax.grad(lambda a, b, p: jnp.sum(point(a, b, p, normal)), argnums=(0, 1, 2))(a, b, on_plane)
        assert all(bool(jnp.all(jnp.isfinite(g))) for g in gradients), (a, b, gradients)
    # Where the intersection lies on the edge, its derivative is the closed form's:
    # the plane's height moves the point along the edge by 1 / (b - a)_z.
    a, b = jnp.array([0.0, 0.0, -1.0]), jnp.array([1.0, 0.0, 1.0])
    slope = jax.grad(lambda h: point(a, b, jnp.array([0.0, 0.0, h]), normal)[0])(0.5)
    np.testing.assert_allclose(slope, 0.5, rtol=1e-6)
    with differentiable_mjx():  # MJX's own edge clipping calls the remedy inside the context only
        assert collision_convex._closest_segment_point_plane is point
        edges = jax.grad(lambda p0: jnp.sum(collision_convex._clip_edge_to_planes(
            p0, jnp.array([1.0, 0.0, 1e-30]), jnp.array([[0.0, 0.0, 1.0]] * 4), jnp.tile(normal, (4, 1)))[0]))(
            jnp.zeros(3, jnp.float32))
    assert bool(jnp.all(jnp.isfinite(edges)))
    assert collision_convex._closest_segment_point_plane is not point  # undone on exit


def test_auto_takes_reverse_mode_only_where_forward_tangents_would_each_pass_a_large_constraint_system(suite):
    chosen = {}
    for name in ("reacher", "cheetah"):
        task = mjcf.make(mjcf.Config(model=str(suite / f"{name}.xml"), steps=5))
        chosen[name] = task.resolved["step_derivative"]
        model = mjcf_spec.load_model(suite / f"{name}.xml")
        rows = mjx_support.constraint_rows(scene.lean_model(model, scene.analyze(model)))
        work = (2 * model.nv + model.na + model.nq - model.nv + model.nu) * rows
        assert (work > simulator.FORWARD_MODE_MAX_SOLVER_WORK) == (chosen[name] == "reverse"), (name, work)
    assert chosen == {"reacher": "forward", "cheetah": "reverse"}
    assert "constraint rows: cheaper than forward" in mjcf.make(
        mjcf.Config(model=str(suite / "cheetah.xml"), steps=5)).summary


def test_geoms_that_can_touch_nothing_leave_the_collision_program(suite):
    """finger's floor lies below everything its hinged bodies can reach, and its proximal bone never
    reaches the spinner: of 15 geom pairs, the fingertip's 3 with the spinner stay. No contact MuJoCo's C
    step makes, from random joint angles under random controls, is between geoms left out."""
    model = mujoco.MjModel.from_xml_path(str(suite / "finger.xml"))
    effects = scene.analyze(model)
    touchable = set(scene.touchable_pairs(model))
    lean = scene.lean_model(model, effects)
    assert len(list(collision_driver.geom_pairs(model))) == 15
    assert {(first, second) for first, second, _ in collision_driver.geom_pairs(lean)} == touchable
    assert len(touchable) == 3
    assert "contacts (3 of 15 geom pairs can touch)" in scene.describe(effects, lean, model)
    rng = np.random.default_rng(0)
    data = mujoco.MjData(model)
    seen = set()
    for episode in range(20):
        data.qpos[:] = rng.uniform(-np.pi, np.pi, model.nq)
        data.qvel[:] = rng.uniform(-5, 5, model.nv)
        for _ in range(200):
            data.ctrl[:] = rng.uniform(-1, 1, model.nu)
            mujoco.mj_step(model, data)
            seen |= {tuple(sorted((int(c.geom1), int(c.geom2)))) for c in data.contact[:data.ncon]}
    assert seen and seen <= {tuple(sorted(pair)) for pair in touchable}


@pytest.mark.parametrize("height, touches", [(0.54, True), (0.56, False)])
def test_an_arm_that_can_just_reach_the_floor_keeps_its_contact(height, touches):
    """A 0.5 m capsule of radius 0.05 hinged at ``height`` above a floor reaches down 0.55 m: the bound
    is exact for it, and at rest it touches the floor exactly when the contact is kept."""
    model = mujoco.MjModel.from_xml_string(f"""<mujoco><worldbody><geom type="plane" size="1 1 0.1"/>
      <body pos="0 0 {height}"><joint type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.05"/></body></worldbody></mujoco>""")
    assert scene.analyze(model).contacts == touches
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    assert (data.ncon > 0) == touches


def test_a_mocap_body_keeps_its_contacts_wherever_it_starts():
    """A mocap body moves wherever its data says: its geom's pairs stay, while the hinged capsule that
    cannot reach the floor loses its pair with it."""
    model = mujoco.MjModel.from_xml_string("""<mujoco><worldbody><geom type="plane" size="1 1 0.1"/>
      <body name="target" mocap="true" pos="0 0 2"><geom type="sphere" size="0.1"/></body>
      <body pos="0 0 1"><joint type="hinge" axis="0 1 0"/><geom type="capsule" fromto="0 0 0 0 0 -0.3" size="0.05"/>
      </body></worldbody></mujoco>""")
    assert scene.touchable_pairs(model) == [(0, 1), (1, 2)]
    data = mujoco.MjData(model)
    data.mocap_pos[0] = [0.1, 0, 0.7]  # moved onto the capsule
    mujoco.mj_forward(model, data)
    assert {(int(c.geom1), int(c.geom2)) for c in data.contact[:data.ncon]} == {(1, 2)}


def test_a_slide_pushed_past_its_range_keeps_its_contact():
    """MuJoCo's joint limits are soft: a motor holds this sphere past its slide's range, against a wall
    0.4 mm beyond the range's reach; the pair stays, and MuJoCo's C step does make the contact."""
    model = mujoco.MjModel.from_xml_string("""<mujoco><option gravity="0 0 0"/><worldbody>
      <geom type="box" size="0.05 0.5 0.5" pos="0.3504 0 0"/>
      <body><joint name="slide" type="slide" axis="1 0 0" range="-0.2 0.2"/><geom type="sphere" size="0.1"/></body>
      </worldbody><actuator><motor joint="slide" gear="100"/></actuator></mujoco>""")
    assert len(scene.touchable_pairs(model)) == 1 and scene.analyze(model).contacts
    data = mujoco.MjData(model)
    data.ctrl[:] = 1.0
    for _ in range(2000):
        mujoco.mj_step(model, data)
    assert data.ncon > 0


def test_springs_and_dampers_of_higher_order_are_found_and_the_generated_step_refuses_them():
    """A tendon's stiffness and damping with a quadratic coefficient alone: no linear coefficient shows them, yet
    the scene's analysis finds both, and the generated rigid-body step, which has no such terms, refuses the scene."""
    model = mujoco.MjModel.from_xml_string("""<mujoco><worldbody><body><joint name="a" type="slide" axis="1 0 0"/>
      <geom type="sphere" size="0.1" contype="0" conaffinity="0"/></body></worldbody>
      <tendon><fixed stiffness="0 50" damping="0 5"><joint joint="a" coef="1"/></fixed></tendon></mujoco>""")
    effects = scene.analyze(model)
    assert effects.springs and effects.dampers
    assert "tendons with stiffness" in rigid_body.unsupported(model, effects)


# Spheres and a box pressed sliding onto a floor, with elliptic cones of three, four and six dimensions.
SLIDING = """<mujoco model="sliding">
  <option cone="elliptic" solver="Newton"/>
  <worldbody>
    <geom type="plane" size="5 5 0.1"/>
    <body pos="0 0 0.1"><freejoint/><geom type="sphere" size="0.1" condim="3"/></body>
    <body pos="0.5 0 0.1"><freejoint/><geom type="box" size="0.1 0.1 0.1" condim="4"/></body>
    <body pos="1 0 0.1"><freejoint/><geom type="sphere" size="0.1" condim="6"/></body>
  </worldbody>
</mujoco>"""


def test_the_elliptic_cones_newton_hessian_summed_by_blocks_is_mjxs(x64):
    """``_update_gradient_by_blocks`` (manipulator's 281 cone blocks in two contractions, not 281 updates of
    a dense matrix) against MJX's own, away from the solution and with contacts in the cone's middle zone."""
    from stablebptt.physics import constraint_derivatives
    from stablebptt.physics.mjx_internals import mjx, solver
    model = mujoco.MjModel.from_xml_string(SLIDING)
    data = mujoco.MjData(model)
    data.qpos[[2, 9, 16]] = 0.099  # pressed in
    data.qvel[[0, 6, 13]] = [1.0, -1.0, 0.5]  # sliding
    data.qvel[[4, 11, 17]] = [2.0, 1.0, -3.0]  # turning: the six-dimensional cone's torsion and rolling
    mujoco.mj_forward(model, data)
    assert sorted(set(data.contact.dim[:data.ncon])) == [3, 4, 6]
    mjx_model, mjx_data = mjx.put_model(model, impl="jax"), mjx.put_data(model, data, impl="jax")
    mjx_data = jax.jit(mjx.forward)(mjx_model, mjx_data)
    start = mjx_data.replace(qacc=mjx_data.qacc + jnp.array(np.random.default_rng(0).normal(size=model.nv)))
    context = jax.jit(lambda d: solver.Context.create(mjx_model, d))(start)
    assert np.abs(np.asarray(context.h)).max() > 1.0  # cones in their middle zone
    ours = jax.jit(lambda c: constraint_derivatives._update_gradient_by_blocks(mjx_model, start, c))(context)
    theirs = jax.jit(lambda c: constraint_derivatives._UPDATE_GRADIENT(mjx_model, start, c))(context)
    np.testing.assert_allclose(ours.Mgrad, theirs.Mgrad, rtol=1e-12, atol=1e-12 * np.abs(theirs.Mgrad).max())
    np.testing.assert_allclose(ours.grad, theirs.grad, rtol=0, atol=0)
    assert np.abs(np.asarray(theirs.Mgrad)).max() > 1e-3
