"""A task for a model nobody annotated: task files, task options, reaching a point, limited actuators.

Everything here builds tasks and evaluates losses; nothing trains.
"""
from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stablebptt.errors import InputError
from stablebptt.physics.lean_step import State
from stablebptt.tasks import mjcf, mjcf_spec

pytestmark = pytest.mark.fast  # make test-fast: closed forms, invariants, tiny horizons

# A pendulum of length 1 hanging from the origin (qpos 0: the tip at z = -1), with a site at its
# tip, a torque limited to [-2, 1], and one keyframe the task convention does not use.
PENDULUM = """<mujoco>
  <option timestep="0.02"/>
  <worldbody>
    <body name="arm"><joint name="hinge" type="hinge" axis="0 1 0"/>
      <geom type="capsule" size="0.05" fromto="0 0 0 0 0 -1"/><site name="tip" pos="0 0 -1"/></body>
  </worldbody>
  <actuator><motor joint="hinge" ctrlrange="-2 1" ctrllimited="true"/></actuator>
  <keyframe><key name="upright" qpos="3.14159265"/></keyframe>
</mujoco>"""


@pytest.fixture
def pendulum(tmp_path):
    path = tmp_path / "pendulum.xml"
    path.write_text(PENDULUM)
    return path


def test_a_task_file_next_to_the_model_sets_the_task_and_the_command_line_wins(pendulum):
    pendulum.with_suffix(".task.json").write_text(json.dumps(
        {"init_pose": "upright", "target_pose": "hinge=1.5", "horizon_seconds": 0.5, "loss": "mean"}))
    task = mjcf.make(mjcf.Config(model=str(pendulum), target_pose="hinge=-1"))
    resolved = task.resolved
    assert resolved["init"]["qpos"] == pytest.approx([3.14159265])  # from the file, by keyframe name
    assert resolved["target_qpos"] == [-1.0]  # the command line over the file
    assert (resolved["horizon_steps"], resolved["loss"]) == (25, "mean")  # 0.5 s at dt 0.02
    assert resolved["task_file"] == str(pendulum.with_suffix(".task.json").resolve())
    assert task.dynamics.horizon == 25


def test_unused_keyframes_are_named_in_a_warning(pendulum, capsys):
    mjcf.make(mjcf.Config(model=str(pendulum)))
    assert "keyframe upright not used by the task" in capsys.readouterr().err
    mjcf.make(mjcf.Config(model=str(pendulum), init_pose="upright"))
    assert "not used" not in capsys.readouterr().err


def test_reaching_a_point_is_the_squared_distance_of_the_site(pendulum):
    task = mjcf.make(mjcf.Config(model=str(pendulum), reach="tip=1,0,0"))
    assert task.resolved["reach"] == {"site": "tip", "point": [1.0, 0.0, 0.0]}
    angles = jnp.array([0.0, 0.7, -2.0])
    states = State(angles[:, None], jnp.zeros((3, 1)), jnp.zeros((3, 0)))
    # Hinge about +y: the tip (0, 0, -1) turns to (-sin q, 0, -cos q); without --loss-joints only the distance counts.
    expected = (-np.sin(angles[-1]) - 1.0) ** 2 + np.cos(angles[-1]) ** 2
    # Jitted: run eagerly, MJX's kinematics would compile operation by operation.
    np.testing.assert_allclose(float(jax.jit(task.dynamics.loss)(states, None)), expected, rtol=1e-5)
    both = mjcf.make(mjcf.Config(model=str(pendulum), reach="tip=1,0,0", loss_joints="hinge"))
    pose = 1.0 - np.cos(angles[-1])  # the reference pose is qpos 0
    np.testing.assert_allclose(float(jax.jit(both.dynamics.loss)(states, None)), expected + pose, rtol=1e-5)


def test_a_limited_actuator_never_leaves_its_range_and_keeps_a_gradient(pendulum):
    task = mjcf.make(mjcf.Config(model=str(pendulum)))
    params = task.init_params(jax.random.PRNGKey(0), False)
    state = State(jnp.zeros(1), jnp.zeros(1), jnp.zeros(0))
    scaled = lambda factor: jax.tree.map(lambda a: factor * a, params)
    for factor in (1.0, 1e3, -1e3):
        control = task.dynamics.policy(scaled(factor), state)
        assert -2.0 < float(control[0]) < 1.0
    zero_output = task.init_params(jax.random.PRNGKey(0), True)
    assert float(task.dynamics.policy(zero_output, state)[0]) == pytest.approx(-0.5)  # the range's centre
    slope = jax.grad(lambda p: task.dynamics.policy(p, state)[0])(scaled(30.0))
    assert any(float(jnp.abs(leaf).max()) > 0 for leaf in jax.tree.leaves(slope))


@pytest.mark.slow  # trains an epoch: the full tier
def test_an_mjcf_task_given_episode_seconds_trains_on_carried_episodes_rewarded_by_its_state_loss(pendulum):
    from stablebptt.engine.config import TrainConfig, seed_array
    from stablebptt.engine.training import make_trainer
    assert mjcf.make(mjcf.Config(model=str(pendulum))).episodes is None  # the paper's protocol unless asked
    task = mjcf.make(mjcf.Config(model=str(pendulum), target_pose="upright", steps=3, episode_seconds=0.1))
    episodes = task.episodes
    assert (episodes.length, task.resolved["episode_steps"]) == (5, 5)  # 0.1 s at dt 0.02
    angles = jnp.array([0.0, 1.0, 3.14159265])
    states = State(angles[:, None], jnp.zeros((3, 1)), jnp.zeros((3, 0)))
    # Each step's reward is the negative state loss: the pose loss of a hinge, 1 - cos(q - target).
    np.testing.assert_allclose(jax.vmap(episodes.reward)(states), -(1 - np.cos(angles - 3.14159265)), atol=1e-6)
    nan = State(jnp.array([jnp.nan]), jnp.zeros(1), jnp.zeros(0))
    assert bool(episodes.done(nan)) and not bool(episodes.done(State(jnp.zeros(1), jnp.zeros(1), jnp.zeros(0))))
    reset, sampled = episodes.reset(jax.random.PRNGKey(7)), task.sample_initial_states(jax.random.PRNGKey(7), 1)
    np.testing.assert_array_equal(reset.qpos, sampled.qpos[0])  # an episode starts as the initial states are drawn
    config = TrainConfig(epochs=1, batch=2, train_size=2, test_size=2, lr=1e-2)
    trainer = make_trainer(task, config)
    assert trainer.episodes is episodes and trainer.updates_per_epoch == 2  # ceil(5 / 3)
    state = trainer.init(seed_array(config))
    state, metrics = trainer.epoch(state, trainer.batches, trainer.train_states, trainer.test_states)
    assert bool(metrics["finite"][0]) and state.carried.clocks.shape == (1, 2)


@pytest.mark.parametrize("options, words", [
    (dict(init_pose="elbow=1"), "no joint named 'elbow'"),
    (dict(episode_seconds=-1.0), "episode_seconds must be a finite time"),
    (dict(episode_seconds=0.001), "episode_seconds 0.001 is 0 steps"),
    (dict(target_pose="sideways"), "no keyframe named 'sideways'"),
    (dict(init_pose="hinge=nan"), "finite"),
    (dict(reach="tip=1,0"), "NAME=X,Y,Z"),
    (dict(reach="hand=1,0,0"), "no site or body named 'hand'"),
    (dict(loss_joints="none"), "the loss compares nothing"),
    (dict(horizon_seconds=float("nan")), "mjcf.Config.horizon_seconds"),
    (dict(horizon_seconds=0.001), "less than one step"),
    (dict(loss="sometimes"), "must be final or mean"),
    (dict(task_file="missing.json"), "does not exist"),
])
def test_bad_task_options_are_one_clear_error(pendulum, options, words):
    with pytest.raises(InputError, match=words.replace("(", r"\(")):
        mjcf.make(mjcf.Config(model=str(pendulum), **options))


@pytest.mark.parametrize("content, words", [
    ('{"target": 3}', "unknown option 'target'"),
    ('{"horizon_seconds": "two"}', "horizon_seconds must be float"),
    ("[1, 2]", "one JSON object"),
    ("{", "not JSON"),
])
def test_a_bad_task_file_is_one_clear_error(pendulum, content, words):
    pendulum.with_suffix(".task.json").write_text(content)
    with pytest.raises(InputError, match=words):
        mjcf.make(mjcf.Config(model=str(pendulum)))


def test_a_spread_whose_states_square_past_the_largest_float_is_refused_before_compiling(pendulum):
    model = mjcf_spec.load_model(pendulum)
    largest = float(np.sqrt(np.finfo(np.float32).max))  # the run's precision: float32 here
    at_most = largest / mjcf_spec.DEFAULT_SPREAD  # the pendulum hangs at 0 and declares no spread of its own
    below = mjcf.read_spec(model, mjcf.Config(model=str(pendulum), spread=0.99 * at_most))
    with np.errstate(over="ignore"):
        assert np.isfinite(np.float32(below.qvel_spread.max()) ** 2)  # its squares are still numbers
    with pytest.raises(InputError, match=r"mjcf.Config.spread .* overflow float32: give at most"):  # 1% more: not
        mjcf.read_spec(model, mjcf.Config(model=str(pendulum), spread=1.01 * at_most))


def test_float64_takes_a_spread_float32_cannot(pendulum, x64):
    spec = mjcf.read_spec(mjcf_spec.load_model(pendulum), mjcf.Config(model=str(pendulum), spread=1e30))
    assert spec.qvel_spread.max() == pytest.approx(1e29)
