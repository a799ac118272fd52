"""Training on carried episodes: a window's return counts only its episode's steps, ended episodes start
again between windows from fresh states drawn once an epoch, and no others, clocks start spread, and the flows' gradient of a window is the
gradient of its plain rollout, in both derivative modes."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stablebptt.engine.config import TrainConfig, seed_array
from stablebptt.engine.episodes import (
    DEVIATION_BOUNDS,
    Carried,
    Episodes,
    Exploring,
    continue_from,
    first_population,
    refill_pool,
    start_window,
    updates_per_epoch,
    window_dynamics,
)
from stablebptt.engine.task import Task
from stablebptt.engine.training import make_trainer
from stablebptt.errors import InputError, TaskError
from stablebptt.flows.dynamics import Dynamics, Plan
from stablebptt.flows.gradients import flow_window, reference_loss, reference_rollout

from conftest import float64

pytestmark = pytest.mark.fast

LENGTH = 10


def drift(rate: float = 0.9) -> Dynamics:
    """x' = rate x + u, u = theta . (x, 1), the reward -x^2 of the state reached: smooth, closed form."""
    return Dynamics(step=lambda x, u: rate * x + u[0], policy=lambda theta, x: jnp.stack([theta[0] * x + theta[1]]),
                    loss=lambda states, controls: jnp.sum(states ** 2), horizon=4)


def episodes(done_beyond: float = 1e9) -> Episodes:
    return Episodes(reset=lambda key: jax.random.uniform(key, (), minval=-1.0, maxval=1.0), reward=lambda x: -x ** 2,
                    done=lambda x: jnp.abs(x) > done_beyond, length=LENGTH)


def carried(states, clocks) -> Carried:
    return Carried(jnp.asarray(states, jnp.float32), jnp.asarray(clocks, jnp.int32), jax.random.PRNGKey(0))


def test_a_window_counts_the_steps_of_its_episode_and_no_state_past_its_end():
    # A constant reward of 1 per step: a window's return is the number of steps its episode had left.
    counting = Episodes(reset=lambda key: jnp.zeros(()), reward=lambda x: jnp.ones(()), done=lambda x: x > 2.5,
                        length=LENGTH)
    step_by_one = Dynamics(step=lambda x, u: x + 1.0, policy=lambda theta, x: jnp.zeros(1), loss=lambda s, c: 0.0,
                           horizon=6)
    window = window_dynamics(step_by_one, counting, 6)
    start = start_window(carried([-10.0, -10.0, -10.0, 0.0], [0, 7, 9, 0]), jnp.float32)
    trajectory = jax.vmap(lambda x0: reference_rollout(window, None, x0))(start)
    returns = -jax.vmap(window.loss)(trajectory.states, trajectory.controls)
    # 6 steps left; 3 (clock 7 of 10); 1 (clock 9); done once x passes 2.5, at its third step: 3.
    np.testing.assert_array_equal(returns, [6, 3, 1, 3])
    last = jax.tree.map(lambda a: a[:, -1], trajectory.states)
    np.testing.assert_array_equal(last.running, [True, False, False, False])
    np.testing.assert_array_equal(last.clock, [6, 10, 10, 3])
    # The state stays as it was before the end: the done state (3.0) never enters a window.
    np.testing.assert_array_equal(last.state, [-4.0, -8.0, -10.0, 2.0])


def test_a_time_limit_valued_keeps_the_state_it_cut_at_and_adds_its_discounted_value_where_the_task_ended_none():
    counting = Episodes(reset=lambda key: jnp.zeros(()), reward=lambda x: jnp.ones(()), done=lambda x: x > 2.5,
                        length=LENGTH, discount=0.5)
    step_by_one = Dynamics(step=lambda x, u: x + 1.0, policy=lambda theta, x: jnp.zeros(1), loss=lambda s, c: 0.0,
                           horizon=6)
    value = lambda x: 100.0 + x  # noqa: E731
    returns, lasts, cuts = {}, {}, {}
    for valued in (False, True):
        window = window_dynamics(step_by_one, counting, 6, value=value, value_at_time_limit=valued)
        start = start_window(carried([-10.0, -10.0, 0.0], [0, 7, 0]), jnp.float32, value_at_time_limit=valued)
        trajectory = jax.vmap(lambda x0: reference_rollout(window, None, x0))(start)
        returns[valued] = -jax.vmap(window.loss)(trajectory.states, trajectory.controls)
        lasts[valued] = jax.tree.map(lambda a: a[:, -1], trajectory.states)
        cuts[valued] = trajectory.states.cut
    rewards = np.array([sum(0.5 ** t for t in range(n)) for n in (6, 3, 3)])
    # The first runs the whole window (its last state, -4, valued either way); the second is cut at clock 10,
    # at -7 after 3 steps; the third ends by its task at 3.0 after 3 steps: valued nowhere.
    np.testing.assert_allclose(returns[False], rewards + [0.5 ** 6 * 96.0, 0.0, 0.0], rtol=1e-6)
    np.testing.assert_allclose(returns[True], rewards + [0.5 ** 6 * 96.0, 0.5 ** 3 * 93.0, 0.0], rtol=1e-6)
    np.testing.assert_array_equal(lasts[True].state, [-4.0, -7.0, 2.0])  # the cut state kept, the ended one not
    np.testing.assert_array_equal(lasts[False].state, [-4.0, -8.0, 2.0])
    np.testing.assert_array_equal(cuts[True], np.arange(6)[None] == np.array([[-1], [2], [-1]]))  # at its cut alone
    assert cuts[False] is None  # off, a window holds what it held before the option: its programs unchanged
    np.testing.assert_array_equal(lasts[True].running, lasts[False].running)  # the cut episode starts again all the same


def test_ended_episodes_alone_start_again_from_the_pool_in_turn_and_the_key_moves_on():
    task_episodes = episodes()
    window = window_dynamics(drift(), task_episodes, 4)
    population = refill_pool(carried([0.1, 0.2, 0.3], [0, 6, 8]), task_episodes)
    _, resets = jax.random.split(jax.random.PRNGKey(0))
    fresh = jax.vmap(task_episodes.reset)(jax.random.split(resets, 3))
    np.testing.assert_array_equal(population.pool, fresh)  # one reset per env, each from a key of its own
    final = jax.vmap(lambda x0: jax.tree.map(lambda a: a[-1], reference_rollout(window, jnp.array([0.0, 0.0]), x0).states))(
        start_window(population, jnp.float32))
    after = continue_from(final, population)
    np.testing.assert_array_equal(after.clocks, [4, 0, 0])  # 6 + 4 and 8 + 4 reach the length of 10
    np.testing.assert_allclose(after.states[0], 0.1 * 0.9 ** 4, rtol=1e-6)  # the running one goes on
    np.testing.assert_array_equal(after.states[1:], fresh[:2])  # the ended ones take the pool's first two
    assert int(after.pool_used) == 2 and not np.array_equal(after.key, population.key)
    # Two more end: the pool's last state, then its first again.
    again = continue_from(final, after)
    np.testing.assert_array_equal(again.states[1:], fresh[np.array([2, 0])])
    assert int(again.pool_used) == 4
    # A pool of two states per env (episodes cut sooner in training): the ended envs go on through it.
    deeper = refill_pool(carried([0.1, 0.2, 0.3], [0, 6, 8]), dataclasses.replace(task_episodes, pool_per_env=2))
    assert deeper.pool.shape == (6,)
    past_four = continue_from(final, deeper._replace(pool_used=jnp.int32(4)))  # 4 taken: the 5th and 6th, not the 2nd and 3rd
    np.testing.assert_array_equal(past_four.states[1:], deeper.pool[np.array([4, 5])])


def test_an_epoch_starts_with_its_pool_drawn_once_from_the_key_it_starts_with(tmp_path, monkeypatch):
    from stablebptt.engine import program_store
    from stablebptt.engine.metrics import empty_rows
    from stablebptt.runs import epochs
    task = Task(name="drift", dynamics=drift(), init_params=lambda key, zero: jnp.zeros(2),
                sample_initial_states=lambda key, n: jax.random.uniform(key, (n,)), episodes=episodes())
    config = TrainConfig(epochs=2, batch=3, train_size=2, test_size=2, lr=1e-2)
    trainer = make_trainer(task, config)
    start = state = trainer.init(seed_array(config))
    for _ in range(2):
        expected = refill_pool(jax.tree.map(lambda a: a[0], state.carried), episodes()).pool
        state, _ = trainer.epoch(trainer.fresh(state), trainer.batches, trainer.train_states, trainer.test_states)
        np.testing.assert_array_equal(state.carried.pool[0], expected)
        # 3 windows of 4 steps pass every episode's end of 10 once: each env took one fresh state.
        assert int(state.carried.pool_used[0]) == 3
    # A run's epochs start the same way; with a key, its programs (the refill's too) are kept as they are traced.
    key = {"test": str(tmp_path)}
    outcome = epochs.train_epochs(trainer, config, tmp_path, start, 0, empty_rows(), np.asarray(seed_array(config)),
                                  program_key=key)
    np.testing.assert_array_equal(outcome.state.carried.pool, state.carried.pool)
    np.testing.assert_array_equal(outcome.state.carried.states, state.carried.states)
    # Its checkpoint keeps the population without the pool, which the next epoch draws afresh before reading it:
    # read back, the pool is zeros and the rest as trained, and the epoch after it trains as after the state.
    from stablebptt.engine.episodes import checkpointed
    from stablebptt.runs import run_folder
    with np.load(tmp_path / run_folder.CHECKPOINT_FILE) as data:
        kept = [data[name] for name in sorted(data.files) if name.startswith("leaf_")]
    assert len(kept) == len(jax.tree.leaves(checkpointed(state))) < len(jax.tree.leaves(state))
    epoch, read, rows = run_folder.load_checkpoint(tmp_path, state)
    assert epoch == 2 and not np.any(read.carried.pool) and read.carried.pool.shape == state.carried.pool.shape
    for leaf, trained in zip(jax.tree.leaves(checkpointed(read)), jax.tree.leaves(checkpointed(state))):
        np.testing.assert_array_equal(leaf, trained)
    after_read, after_state = (trainer.epoch(trainer.fresh(start_from), trainer.batches, trainer.train_states,
                                             trainer.test_states)[0] for start_from in (read, state))
    for leaf, other in zip(jax.tree.leaves(after_read), jax.tree.leaves(after_state)):
        np.testing.assert_array_equal(leaf, other)
    # A checkpoint that kept the pool reads as it was written.
    run_folder.atomic_write(tmp_path / run_folder.CHECKPOINT_FILE, run_folder._npz_bytes(
        {"epoch": np.array(2), "metrics": rows, **run_folder._named_leaves(state)}))
    for leaf, trained in zip(jax.tree.leaves(run_folder.load_checkpoint(tmp_path, state)[1]), jax.tree.leaves(state)):
        np.testing.assert_array_equal(leaf, trained)
    # A resume (a new trainer) from the checkpoint's arrays, NumPy's with no weak types where init's had
    # them, traces neither program again.
    from stablebptt.engine import training
    monkeypatch.setattr(program_store, "_traced", lambda *a: pytest.fail("traced again although kept"))
    monkeypatch.setattr(training, "refill_pool", lambda *a: pytest.fail("the refill traced again although kept"))
    checkpoint = jax.tree.map(np.asarray, jax.device_get(start))
    resumed = epochs.train_epochs(make_trainer(task, config), config, tmp_path, checkpoint, 0, empty_rows(),
                                  np.asarray(seed_array(config)), program_key=key)
    for again, first in zip(jax.tree.leaves(resumed.state), jax.tree.leaves(outcome.state)):
        np.testing.assert_array_equal(again, first)


def test_first_clocks_are_spread_over_an_episode_unless_a_window_holds_one():
    spread = first_population(jax.random.PRNGKey(0), episodes(), 256, window=3)
    assert spread.clocks.min() >= 0 and spread.clocks.max() < LENGTH and len(np.unique(spread.clocks)) == LENGTH
    whole = first_population(jax.random.PRNGKey(0), episodes(), 8, window=LENGTH)
    np.testing.assert_array_equal(whole.clocks, 0)
    assert updates_per_epoch(episodes(), 3) == 4 and updates_per_epoch(episodes(), 20) == 1


@pytest.mark.parametrize("step_derivative", ["reverse", "forward"])
@pytest.mark.parametrize("at_end, action_noise, learned_noise, at_time_limit",
                         [(None, 0.0, False, False), (lambda x: 3.0 * x ** 2 - x, 0.0, False, False),
                          (lambda x: 3.0 * x ** 2 - x, 0.0, False, True), (None, 0.3, False, False),
                          (None, 0.3, True, False)],
                         ids=["window", "with a value at its end", "with values where time limits cut",
                              "with exploration noise", "with learned noise"])
def test_each_flow_of_a_window_is_the_gradient_of_its_plain_rollout_and_ends_where_it_does(step_derivative, at_end,
                                                                                         action_noise, learned_noise,
                                                                                         at_time_limit):
    # Episodes that end inside the window, by their clock and by done: the masks must hold in the gradient too;
    # a value of the last state is a loss on it, which every flow keeps, as it keeps the value of a state a
    # time limit cuts an episode at; noise on the actions is part of the trajectory, which the flows evaluate
    # the policy along again; a learned deviation is a parameter as the policy's are.
    window = window_dynamics(drift(1.0), episodes(done_beyond=0.8), 5, value=at_end, action_noise=action_noise,
                             learned_noise=learned_noise, value_at_time_limit=at_time_limit)
    with float64():
        start = start_window(Carried(jnp.array([0.3, -0.5, 0.7, 0.1, 0.05]), jnp.array([0, 7, 2, 9, 1], jnp.int32),
                                     jax.random.PRNGKey(0)), jnp.float64, noise=action_noise > 0,
                             value_at_time_limit=at_time_limit)
        theta = jnp.array([0.2, -0.1])
        if learned_noise:
            theta = Exploring(theta, jnp.log(jnp.array([action_noise])))
        loss, grads, final, _ = flow_window(window, ("R", "M"), theta, start, Plan(step_derivative=step_derivative))
        for index, flow in enumerate(("R", "M")):
            plain = jax.grad(lambda p, flow=flow: reference_loss(window, p, start, flow))(theta)
            for ours, theirs in zip(jax.tree.leaves(grads), jax.tree.leaves(plain)):
                np.testing.assert_allclose(ours[index], theirs, rtol=1e-10)
        if learned_noise:  # the deviation moves the loss: its gradient is no zero that would pass by itself
            assert abs(float(grads.log_std[0, 0])) > 1e-3
        np.testing.assert_allclose(loss, reference_loss(window, theta, start), rtol=1e-12)
        reached = jax.vmap(lambda x0: jax.tree.map(lambda a: a[-1], reference_rollout(window, theta, x0).states))(start)
        for ours, theirs in zip(jax.tree.leaves(final), jax.tree.leaves(reached)):
            np.testing.assert_allclose(ours, theirs, rtol=1e-12)
        assert not np.all(final.running) and np.any(final.running)  # some episodes end inside the window, some not
        if at_time_limit:  # the clock-9 episode reaches the length of 10 (the clock-7 one its task ends first)
            cut = jax.vmap(lambda x0: reference_rollout(window, theta, x0).states.cut.any())(start)
            np.testing.assert_array_equal(cut, [False, False, False, True, False])


def test_a_state_the_step_cuts_the_derivative_at_is_valued_in_the_gradient_alone_as_its_closed_form_says():
    # x' = x + u with u = theta: the step holds x constant where |x| > 0.4; no reward, V(x) = x, discount 0.5.
    # From x0 = 0 with theta = 0.6 the window of two reaches x1 = 0.6 (cut there) and x2 = 1.2, valued at its end:
    # the loss is -0.25 x2 either way; its slope in theta -0.25 through x2 = x1 + theta with x1 held, and with
    # x1 valued -0.5 more, the slope of its value 0.5 x1; uncut, x2 = 2 theta: -0.5.
    cut_at = lambda x: jnp.abs(x) > 0.4  # noqa: E731
    held = lambda x: jnp.where(cut_at(x), jax.lax.stop_gradient(x), x)  # noqa: E731
    value = lambda x: x  # noqa: E731
    start = start_window(carried([0.0], [0]), jnp.float32)
    theta = jnp.array([0.6])
    found = {}
    for cuts, valued in ((False, False), (True, False), (True, True)):
        dynamics = Dynamics(step=lambda x, u, cuts=cuts: (held(x) if cuts else x) + u[0],
                            policy=lambda th, x: jnp.stack([th[0]]), loss=lambda s, c: 0.0, horizon=2)
        episodes_here = Episodes(reset=lambda key: jnp.zeros(()), reward=lambda x: 0.0 * x, done=lambda x: x > 9.0,
                                 length=LENGTH, discount=0.5, gradient_cut=cut_at if cuts else None)
        window = window_dynamics(dynamics, episodes_here, 2, value=value, value_at_gradient_cut=valued)
        loss, grads, _, _ = flow_window(window, ("R", "M"), theta, start, Plan())
        found[cuts, valued] = float(loss), np.asarray(grads)[:, 0]
    for (cuts, valued), slope in (((False, False), -0.5), ((True, False), -0.25), ((True, True), -0.75)):
        loss, slopes = found[cuts, valued]
        np.testing.assert_allclose(loss, -0.25 * 1.2, rtol=1e-6)  # the value is the same in all three
        np.testing.assert_allclose(slopes, [slope, slope], rtol=1e-6)  # flows R and M alike


@pytest.mark.parametrize("step_derivative", ["reverse", "forward"])
def test_each_flow_of_a_window_valued_where_its_step_cuts_is_the_gradient_of_its_plain_rollout(step_derivative):
    cut_at = lambda x: jnp.abs(x) > 0.4  # noqa: E731
    plain = drift(1.0)
    dynamics = Dynamics(step=lambda x, u: plain.step(jnp.where(cut_at(x), jax.lax.stop_gradient(x), x), u),
                        policy=plain.policy, loss=plain.loss, horizon=plain.horizon)
    cutting = dataclasses.replace(episodes(done_beyond=0.8), gradient_cut=cut_at)
    window = window_dynamics(dynamics, cutting, 5, value=lambda x: 3.0 * x ** 2 - x, value_at_gradient_cut=True)
    with float64():
        start = start_window(Carried(jnp.array([0.3, -0.5, 0.7, 0.1, 0.05]), jnp.array([0, 7, 2, 9, 1], jnp.int32),
                                     jax.random.PRNGKey(0)), jnp.float64)
        theta = jnp.array([0.2, -0.1])
        _, grads, _, _ = flow_window(window, ("R", "M"), theta, start, Plan(step_derivative=step_derivative))
        for index, flow in enumerate(("R", "M")):
            expected = jax.grad(lambda p, flow=flow: reference_loss(window, p, start, flow))(theta)
            np.testing.assert_allclose(grads[index], expected, rtol=1e-10)
        states = jax.vmap(lambda x0: reference_rollout(window, theta, x0).states.state)(start)
        assert np.any(np.abs(np.asarray(states[:, :-1])) > 0.4)  # some window passes a state it cuts at


def test_exploration_noise_is_gaussian_of_its_deviation_fresh_at_every_step_and_window_and_absent_without_it():
    sigma, envs = 0.3, 4096
    window = window_dynamics(drift(), episodes(), 3, action_noise=sigma)
    theta = jnp.array([0.5, 0.2])
    population = carried(np.linspace(-0.5, 0.5, envs), np.zeros(envs))
    noisy = jax.vmap(lambda x0: reference_rollout(window, theta, x0))(start_window(population, jnp.float32, noise=True))
    visited = jax.tree.map(lambda a, b: jnp.concatenate([a[:, None], b[:, :-1]], axis=1),
                           start_window(population, jnp.float32, noise=True), noisy.states)
    deviations = noisy.controls[..., 0] - (theta[0] * visited.state + theta[1])  # [envs, steps]
    np.testing.assert_allclose(deviations.std(axis=0), sigma, rtol=0.05)
    np.testing.assert_allclose(deviations.mean(axis=0), 0.0, atol=4 * sigma / np.sqrt(envs))
    assert abs(np.corrcoef(deviations[:, 0], deviations[:, 1])[0, 1]) < 0.1  # a fresh draw at every step
    moved_on = start_window(population._replace(key=jax.random.PRNGKey(1)), jnp.float32, noise=True)
    again = jax.vmap(lambda x0: reference_rollout(window, theta, x0))(moved_on)
    assert not np.allclose(again.controls, noisy.controls)  # and with every window's key
    plain = window_dynamics(drift(), episodes(), 3)
    assert start_window(population, jnp.float32).noise_key is None
    np.testing.assert_array_equal(jax.vmap(lambda x: plain.policy(theta, x))(start_window(population, jnp.float32)),
                                  theta[0] * population.states[:, None] + theta[1])


def test_a_learned_deviation_follows_the_windows_gradient_and_the_entropys_pull_within_its_bounds():
    # Rewards -x^2: noise on the actions only costs, so without an entropy term the deviation shrinks; a large
    # entropy weight outpulls that cost and the deviation grows to its upper bound, no further. The evaluation
    # stays the deterministic policy's: its parameters are the policy's alone.
    task = Task(name="drift", dynamics=drift(), init_params=lambda key, zero: jnp.zeros(2),
                sample_initial_states=lambda key, n: jax.random.uniform(key, (n,)), episodes=episodes())
    config = TrainConfig(epochs=1, batch=16, train_size=2, test_size=2, lr=5e-2, action_noise=0.3,
                         learn_action_noise=True, clip="none")
    deviations = {}
    for entropy in (0.0, 10.0):
        trainer = make_trainer(task, dataclasses.replace(config, entropy=entropy))
        state = trainer.init(seed_array(config))
        np.testing.assert_allclose(jnp.exp(state.log_std), [[0.3]], rtol=1e-6)
        for _ in range(10):
            state, metrics = trainer.epoch(state, trainer.batches, trainer.train_states, trainer.test_states)
            assert bool(metrics["finite"][0])
        deviations[entropy] = float(jnp.exp(state.log_std[0, 0]))
        assert jax.tree.structure(state.params) == jax.tree.structure(jnp.zeros((1, 2)))
        noiseless = make_trainer(task, dataclasses.replace(config, action_noise=0.0, learn_action_noise=False))
        np.testing.assert_array_equal(trainer.evaluate(state.params, trainer.test_states),
                                      noiseless.evaluate(state.params, noiseless.test_states))
    assert deviations[0.0] < 0.2 and deviations[10.0] == pytest.approx(DEVIATION_BOUNDS[1], rel=1e-5)
    with pytest.raises(InputError, match="learn_action_noise learns the noise's deviation from TrainConfig.action_noise"):
        TrainConfig(learn_action_noise=True)
    with pytest.raises(InputError, match="entropy weighs the entropy of a learned noise"):
        TrainConfig(action_noise=0.1, entropy=0.1)
    with pytest.raises(InputError, match="entropy must be a number >= 0"):
        TrainConfig(action_noise=0.1, learn_action_noise=True, entropy=-1.0)


def test_a_decaying_learning_rate_scales_every_update_by_its_factor_per_update():
    from stablebptt.engine.optimizer import make_optimizer
    # Adam's update of a constant gradient is lr times its sign, bias correction included: the decay is all that moves.
    optimizer = make_optimizer(TrainConfig(mode="R", clip="none", lr=0.1, lr_decay=0.5), ("R",))
    params = jnp.zeros(3)
    state = optimizer.init(params)
    gradient = jnp.array([[2.0, -3.0, 0.5]])  # one flow's row
    for count in range(4):
        updates, state = optimizer.update(gradient, state, params)
        np.testing.assert_allclose(updates, -0.1 * 0.5 ** count * np.sign(gradient[0]), rtol=1e-4)
    assert make_optimizer(TrainConfig(mode="R"), ("R",)).init(params).hyperparams.keys() == state.hyperparams.keys()
    with pytest.raises(InputError, match="lr_decay must be in"):
        TrainConfig(lr_decay=1.5)


def test_adams_decays_are_the_runs_own_and_refused_outside_0_to_1():
    from stablebptt.engine.optimizer import make_optimizer
    b1, b2, lr = 0.7, 0.95, 0.1
    optimizer = make_optimizer(TrainConfig(mode="R", clip="none", lr=lr, adam_b1=b1, adam_b2=b2), ("R",))
    params = jnp.zeros(2)
    state = optimizer.init(params)
    average, squares = np.zeros(2), np.zeros(2)
    for count, gradient in enumerate(np.array([[2.0, -1.0], [-1.0, 0.5], [0.5, 3.0]]), start=1):
        updates, state = optimizer.update(jnp.asarray(gradient)[None], state, params)
        average, squares = b1 * average + (1 - b1) * gradient, b2 * squares + (1 - b2) * gradient ** 2
        expected = -lr * (average / (1 - b1 ** count)) / (np.sqrt(squares / (1 - b2 ** count)) + 1e-8)
        np.testing.assert_allclose(updates, expected, rtol=1e-5)
    for field, value in (("adam_b1", 1.0), ("adam_b2", -0.1), ("adam_b1", float("nan"))):
        with pytest.raises(InputError, match=f"{field} must be in \\[0, 1\\)"):
            TrainConfig(**{field: value})


def test_td_lambda_targets_are_the_closed_forms_at_lambda_0_and_1_and_stop_where_an_episode_ends():
    from stablebptt.engine.critic import td_lambda_targets
    rewards = jnp.array([[1.0], [2.0], [3.0]])
    values = jnp.array([[10.0], [20.0], [30.0]])  # of x_1, x_2, x_3
    running = jnp.array([[True], [True], [True]])
    one_step = td_lambda_targets(rewards, values, running, 0.5, 0.0)
    np.testing.assert_allclose(one_step[:, 0], [1 + 0.5 * 10, 2 + 0.5 * 20, 3 + 0.5 * 30])
    whole = td_lambda_targets(rewards, values, running, 0.5, 1.0)
    np.testing.assert_allclose(whole[:, 0], [1 + 0.5 * 2 + 0.25 * 3 + 0.125 * 30, 2 + 0.5 * 3 + 0.25 * 30, 3 + 0.5 * 30])
    ended = td_lambda_targets(rewards, values, jnp.array([[True], [False], [False]]), 0.5, 1.0)
    np.testing.assert_allclose(ended[:, 0], [1 + 0.5 * 2, 2, 3])  # nothing after x_2's end counts
    # A time limit cut x_2's episode: x_2's value stands for what follows it, at any lambda.
    cut = jnp.array([[False], [True], [False]])
    for td_lambda in (0.0, 0.7, 1.0):
        valued = td_lambda_targets(rewards, values, jnp.array([[True], [False], [False]]), 0.5, td_lambda, cut)
        second = 1 + 0.5 * ((1 - td_lambda) * 10 + td_lambda * (2 + 0.5 * 20))
        np.testing.assert_allclose(valued[:, 0], [second, 2 + 0.5 * 20, 3])


def test_a_critic_that_standardises_counts_the_running_states_and_fits_the_same_values_in_any_units():
    """Standardised, the critic sees the same inputs whatever the observation's offset and scale, so it
    fits the same values; raw, it does not. Its statistics are those of the window's running states."""
    import optax

    from stablebptt.engine.critic import bootstrap, fit_to_window, init_critic, seen, value
    from stablebptt.engine.episodes import Window
    steps, batch = 4, 6
    states = jax.random.normal(jax.random.PRNGKey(3), (steps + 1, batch))
    running = jnp.ones((steps + 1, batch), bool).at[3:, 0].set(False)  # one episode ends within the window
    rewards = -states ** 2 * running
    window = lambda t: Window(states[t], jnp.zeros(batch, jnp.int32), running[t], rewards[t])  # noqa: E731
    visited = jax.tree.map(lambda *a: jnp.stack(a), *[window(t) for t in range(steps)])
    optimizer = optax.adam(1e-2)

    def fitted_values(standardize, offset, scale):
        observe = lambda x: jnp.stack([offset + scale * x])  # noqa: E731
        critic = init_critic(jax.random.PRNGKey(0), 1, optimizer, (64, 64), standardize)
        for _ in range(3):
            critic = fit_to_window(critic, visited, window(steps), observe, 0.9, 0.95, optimizer)
        # What the critic fits, and what a window's loss adds at its end (the target critic's value).
        return critic, jnp.stack([jax.vmap(lambda x: value(critic.params, seen(critic, observe(x))))(states[0]),
                                  jax.vmap(bootstrap(critic, observe))(states[0])])

    critic, in_units = fitted_values(True, 0.0, 1.0)
    counted = states[:steps][running[:steps]]
    assert float(critic.statistics.count) == 3 * counted.size  # three windows, the ended states left out
    np.testing.assert_allclose(critic.statistics.mean, [jnp.mean(counted)], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(critic.statistics.squares / critic.statistics.count, [jnp.var(counted)], rtol=1e-5)
    _, in_other_units = fitted_values(True, 40.0, 1000.0)
    np.testing.assert_allclose(in_other_units, in_units, rtol=2e-4, atol=1e-5)
    _, raw, = fitted_values(False, 0.0, 1.0)
    _, raw_in_other_units = fitted_values(False, 40.0, 1000.0)
    assert float(jnp.max(jnp.abs(raw_in_other_units - raw))) > 1e-2


def test_several_critics_each_fit_the_targets_as_alone_and_their_least_value_is_the_critics():
    """Of ``Members``, each network is fitted as if alone (the loss sums their errors, Adam acts per weight),
    the first is the single critic of the same seed, and the critic's value, in the window's loss and in
    the TD targets, is the least of the target networks'."""
    import optax

    from stablebptt.engine.critic import Critic, Members, bootstrap, fit_critic, init_critic, members_values, value
    from stablebptt.networks import mlp_apply
    optimizer = optax.adam(1e-2)
    observations = jax.random.normal(jax.random.PRNGKey(1), (12, 2))
    targets, weights = jnp.sin(observations[:, 0]) + observations[:, 1], jnp.ones(12).at[:3].set(0.0)
    single, pair = (init_critic(jax.random.PRNGKey(0), 2, optimizer, (16,), members=count) for count in (1, 2))
    assert isinstance(pair.params, Members) and jax.tree.leaves(pair.params)[0].shape[0] == 2
    member = lambda params, k: jax.tree.map(lambda a: a[k], params.stacked)  # noqa: E731
    for a, b in zip(jax.tree.leaves(member(pair.params, 0)), jax.tree.leaves(single.params)):
        np.testing.assert_array_equal(a, b)
    at = observations[0]
    both = [float(mlp_apply(member(pair.params, k), at)[0]) for k in (0, 1)]
    assert both[0] != both[1] and float(value(pair.params, at)) == min(both)
    np.testing.assert_allclose(members_values(pair.params, at), both, rtol=1e-6)

    fitted, _ = fit_critic(pair, observations, targets, weights, optimizer, iterations=5)
    for k in (0, 1):
        alone = Critic(member(pair.params, k), optimizer.init(member(pair.params, k)), member(pair.params, k))
        fitted_alone, _ = fit_critic(alone, observations, targets, weights, optimizer, iterations=5)
        for a, b in zip(jax.tree.leaves((member(fitted.params, k), member(fitted.target, k))),
                        jax.tree.leaves((fitted_alone.params, fitted_alone.target))):
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    observe = lambda x: x  # noqa: E731
    least = min(float(mlp_apply(member(fitted.target, k), at)[0]) for k in (0, 1))
    assert float(bootstrap(fitted, observe)(at)) == pytest.approx(least, rel=1e-6)


@pytest.mark.slow  # trains: the full tier
def test_a_critic_trains_beside_the_policy_and_its_target_follows_it():
    task = Task(name="drift", dynamics=drift(), init_params=lambda key, zero: jnp.zeros(2),
                sample_initial_states=lambda key, n: jax.random.uniform(key, (n,)),
                episodes=Episodes(**{**episodes().__dict__, "observe": lambda x: jnp.stack([x]), "discount": 0.9}))
    config = TrainConfig(epochs=1, batch=8, train_size=2, test_size=2, lr=1e-2, critic=True, critic_lr=1e-2)
    trainer = make_trainer(task, config)
    state = trainer.init(seed_array(config))
    first = state.critic
    np.testing.assert_array_equal(jax.tree.leaves(first.params)[0], jax.tree.leaves(first.target)[0])
    for _ in range(3):
        state, metrics = trainer.epoch(state, trainer.batches, trainer.train_states, trainer.test_states)
        assert bool(metrics["finite"][0])
    moved = lambda a, b: float(jnp.max(jnp.abs(a - b)))  # noqa: E731
    assert moved(state.critic.params[0][0], first.params[0][0]) > 0 and moved(state.critic.target[0][0], first.target[0][0]) > 0
    # The value of x^2-like returns: under a policy held still (u = 0, so x decays by 0.9 a step) the critic
    # learns that states far from 0 are worth less (rewards -x^2); 3 epochs leave it at noise, 20 do not.
    from stablebptt.engine.critic import value
    still = make_trainer(task, dataclasses.replace(config, lr=1e-9))
    state = still.init(seed_array(config))
    for _ in range(20):
        state, _ = still.epoch(state, still.batches, still.train_states, still.test_states)
    one = jax.tree.map(lambda a: a[0], state.critic.params)
    at = lambda x: float(value(one, jnp.array([x])))  # noqa: E731
    assert at(-0.9) < at(0.0) and at(0.9) < at(0.0)
    # Standardising what it sees, the trainer's critic counts every state its windows visited while running.
    standardizing = make_trainer(task, dataclasses.replace(config, normalize_critic_observations=True))
    state, metrics = standardizing.epoch(standardizing.init(seed_array(config)), standardizing.batches,
                                         standardizing.train_states, standardizing.test_states)
    windows = len(standardizing.batches) * task.dynamics.horizon * config.batch
    assert bool(metrics["finite"][0]) and 0 < float(state.critic.statistics.count[0]) <= windows
    # Its layers as asked: three of 8 between the observation and the value, the target critic alike.
    narrow = make_trainer(task, dataclasses.replace(config, critic_width=8, critic_depth=3)).init(seed_array(config)).critic
    shapes = [tuple(a.shape[1:]) for a in jax.tree.leaves(narrow.params)]
    assert sorted(shapes) == sorted([(1, 8), (8,), (8, 8), (8,), (8, 8), (8,), (8, 1), (1,)]), shapes
    assert [a.shape for a in jax.tree.leaves(narrow.target)] == [a.shape for a in jax.tree.leaves(narrow.params)]
    # Two networks, trained beside the policy: each seed's critic holds both, and an epoch stays finite.
    doubled = make_trainer(task, dataclasses.replace(config, critics=2))
    state, metrics = doubled.epoch(doubled.init(seed_array(config)), doubled.batches, doubled.train_states,
                                   doubled.test_states)
    assert bool(metrics["finite"][0]) and [a.shape[:2] for a in jax.tree.leaves(state.critic.target)][0] == (1, 2)
    with pytest.raises(InputError, match="action_noise: exploration noise on a window's actions needs carried episodes"):
        make_trainer(task, TrainConfig(batch=1, train_size=2, episodes="off", action_noise=0.1))
    with pytest.raises(InputError, match="critic: a learned value at a window's end needs carried episodes"):
        make_trainer(task, TrainConfig(batch=1, train_size=2, episodes="off", critic=True))


def test_a_trainer_carries_episodes_where_the_task_has_them_and_refuses_to_where_it_has_none():
    task = Task(name="drift", dynamics=drift(), init_params=lambda key, zero: jnp.zeros(2),
                sample_initial_states=lambda key, n: jax.random.uniform(key, (n,)), episodes=episodes())
    config = TrainConfig(epochs=1, batch=3, train_size=2, test_size=2, lr=1e-2)  # 3 does not divide 2: no minibatches
    trainer = make_trainer(task, config)
    assert trainer.episodes is not None and trainer.updates_per_epoch == 3  # ceil(10 / 4)
    state = trainer.init(seed_array(config))
    assert state.carried.clocks.shape == (1, 3)
    state, metrics = trainer.epoch(state, trainer.batches, trainer.train_states, trainer.test_states)
    assert bool(metrics["finite"][0])
    # Episodes cut sooner in training: an epoch still advances every state the task's 10 steps, each episode
    # starting again past 6 (3 windows of 4 steps: every env takes a fresh state once or twice, not once),
    # each start from a pool state of its own (2 a env: ceil(10 / 6)), none taken twice in the epoch.
    sooner = make_trainer(task, dataclasses.replace(config, training_episode_length=6))
    assert (sooner.episodes.length, sooner.episodes.pool_per_env, sooner.updates_per_epoch) == (6, 2, 3)
    begun = sooner.fresh(sooner.init(seed_array(config)))
    assert begun.carried.pool.shape == (1, 6) and begun.carried.states.shape == (1, 3)
    cut, _ = sooner.epoch(begun, sooner.batches, sooner.train_states, sooner.test_states)
    assert int(cut.carried.clocks.max()) < 6 and 3 < int(cut.carried.pool_used[0]) <= 6
    with pytest.raises(InputError, match="training_episode_length must be a whole number of steps >= 0"):
        TrainConfig(training_episode_length=-1)
    with pytest.raises(InputError, match="training_episode_length 10: drift's episodes are 10 steps; cut them sooner"):
        make_trainer(task, dataclasses.replace(config, training_episode_length=LENGTH))
    fixed = make_trainer(task, TrainConfig(epochs=1, batch=1, train_size=2, test_size=2, episodes="off"))
    assert fixed.episodes is None and fixed.init(seed_array(config)).carried is None
    with pytest.raises(InputError, match="training_episode_length: episodes cut sooner in training needs carried episodes"):
        make_trainer(task, TrainConfig(batch=1, train_size=2, episodes="off", training_episode_length=6))
    with pytest.raises(InputError, match="batch 3 does not divide the 2 training states"):
        make_trainer(task, TrainConfig(batch=3, train_size=2, episodes="off"))
    no_episodes = Task(name="plain", dynamics=drift(), init_params=task.init_params,
                       sample_initial_states=task.sample_initial_states)
    with pytest.raises(InputError, match="plain has no episodes to carry"):
        make_trainer(no_episodes, TrainConfig(batch=1, train_size=2, episodes="on"))
    with pytest.raises(InputError, match="batch 3 does not divide"):
        make_trainer(no_episodes, TrainConfig(batch=3, train_size=2))


def test_carried_episodes_draw_their_initial_states_while_the_epoch_is_lowered_and_draw_the_same_states(
        monkeypatch):
    import threading

    from stablebptt.engine import initial_states
    from stablebptt.engine.config import data_keys
    from stablebptt.engine.lowering import lowered_epoch
    task = Task(name="drift", dynamics=drift(), init_params=lambda key, zero: jnp.zeros(2),
                sample_initial_states=lambda key, n: jax.random.uniform(key, (n,)), episodes=episodes())
    config = TrainConfig(epochs=1, batch=3, train_size=2, test_size=5, lr=1e-2)
    drawing, released = initial_states.sample_states, threading.Event()

    def held(*arguments):  # the draw waits until the epoch is lowered; a lowering that needs it gets it late
        released.wait(timeout=120)
        return drawing(*arguments)
    monkeypatch.setattr(initial_states, "sample_states", held)
    trainer = make_trainer(task, config)
    lowered = lowered_epoch(trainer, config)
    assert not trainer.initial_states.drawn.done()  # lowered from the states' shapes alone
    released.set()
    train_key, test_key = data_keys(config.data_seed)
    for states, key, count, shapes in zip((trainer.train_states, trainer.test_states), (train_key, test_key),
                                          (2, 5), trainer.initial_states.shapes):
        np.testing.assert_array_equal(states, drawing(task, key, count))  # as drawn at once
        assert (states.shape, states.dtype) == (shapes.shape, shapes.dtype) == ((count,), jnp.float32)
    # The epoch lowered from the shapes runs on the drawn states; fixed starts draw theirs at once.
    state, metrics = lowered.lowered.compile()(trainer.init(seed_array(config)), trainer.batches,
                                               trainer.train_states, trainer.test_states)
    assert bool(metrics["finite"][0])
    fixed = make_trainer(task, TrainConfig(epochs=1, batch=1, train_size=2, test_size=2, episodes="off"))
    assert fixed.initial_states.drawn.done()


def test_the_task_check_samples_at_the_counts_the_states_are_drawn_at_and_no_other():
    """The trainer's set-up checks the task's sampler at the counts its training and test states are drawn
    at: an environment's batched reset, a large trace, is traced for no count of the check's own
    (docs/performance.md). A sampler that ignores the count is refused at the test states' count too."""
    counts = []
    task = Task(name="drift", dynamics=drift(), init_params=lambda key, zero: jnp.zeros(2),
                sample_initial_states=lambda key, n: counts.append(n) or jax.random.uniform(key, (n,)),
                episodes=episodes())
    trainer = make_trainer(task, TrainConfig(epochs=1, batch=3, train_size=6, test_size=4))
    trainer.initial_states.drawn.result()
    assert set(counts) == {6, 4}
    fixed = dataclasses.replace(task, sample_initial_states=lambda key, n: jax.random.uniform(key, (6,)))
    with pytest.raises(InputError, match=r"sample_initial_states\(key, 4\) must return 4 states"):
        make_trainer(fixed, TrainConfig(epochs=1, batch=3, train_size=6, test_size=4))


@pytest.mark.parametrize("name, function, words", [
    ("reward", lambda x: jnp.stack([-x, x]), r"Episodes.reward\(state\) must return one float for one state, got .*float32\[2\]"),
    ("done", lambda x: jnp.stack([x > 0, x < 0]), r"Episodes.done\(state\) must return one bool or number for one state"),
    ("observe", lambda x: x, r"Episodes.observe\(state\) must return a float vector for one state, got .*float32\[\]"),
    ("reward", lambda x: x.missing, r"Episodes.reward\(state\) fails on one sampled state: AttributeError"),
    # and-ed with the running mask in the window's loop, which takes a bool alone
    ("gradient_cut", lambda x: x * 0.5, r"Episodes.gradient_cut\(state\) must return one bool for one state")])
def test_an_episodes_function_of_another_shape_is_named_before_compiling(name, function, words):
    """A vector reward would be summed into each env's return, or broadcast over the batch, without a word."""
    task = Task(name="drift", dynamics=drift(), init_params=lambda key, zero: jnp.zeros(2),
                sample_initial_states=lambda key, n: jax.random.uniform(key, (n,)),
                episodes=dataclasses.replace(episodes(), **{"observe": lambda x: jnp.stack([x]), name: function}))
    with pytest.raises(TaskError, match=f"^{words}"):
        make_trainer(task, TrainConfig(epochs=1, batch=8, train_size=2, test_size=2, critic=True))
