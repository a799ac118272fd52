"""Environments in Brax's protocol as tasks: states with integer, bool and key leaves, the reward's
diagnosis, the command line's --env (MJX inside an environment and MuJoCo Playground's envs:
test_mjx_and_playground.py)."""
import os
import sys
import types
from dataclasses import replace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import stablebptt as sb
from stablebptt.engine import lowering, program_store, starting
from stablebptt.engine.config import seed_array
from stablebptt.engine.metrics import empty_rows
from stablebptt.envs import adapter
from stablebptt.envs.adapter import env_task
from stablebptt.envs.protocol import EnvError, load_env
from stablebptt.errors import InputError
from stablebptt.flows.gradients import flow_gradients, reference_loss
from stablebptt.runs import epochs, run_folder
from stablebptt.storage import read_json

from conftest import HAS_PLAYGROUND, ROOT, float64, refused_in_one_line, run_script, train_in_process
from envs_for_tests import Cart, LateCart

TINY = sb.TrainConfig(mode="C", epochs=3, train_size=8, test_size=8, batch=4, clip="norm", lr=1e-2)


def test_an_environment_trains_and_flow_r_is_the_gradient_of_the_plain_rollout():
    task = env_task(Cart(), horizon=12)
    assert task.resolved["reward_gradient"] == "usable" and task.resolved["episode_length"] == 30
    with float64():
        params = task.init_params(jax.random.PRNGKey(1), False)
        states = task.sample_initial_states(jax.random.PRNGKey(2), 4)
        assert states.data["count"].dtype == jnp.int32 and states.data["moving"].dtype == bool
        loss, grads = jax.jit(lambda p, s: flow_gradients(task.dynamics, ("R",), p, s))(params, states)
        plain = jax.jit(jax.grad(lambda p, s: reference_loss(task.dynamics, p, s)))(params, states)
        for ours, theirs in zip(jax.tree.leaves(grads), jax.tree.leaves(plain)):
            np.testing.assert_allclose(ours[0], theirs, rtol=1e-9, atol=1e-12)
    result = sb.train(task, replace(TINY, eval_every="epoch"))
    # The train and test losses are negative episode returns (30 steps, each reward <= 0).
    assert np.all(np.isfinite(result.test_loss)) and np.all(result.test_loss >= 0)
    assert result.test_loss[-1] < result.test_loss[0]  # it learns to hold the cart at the origin


def test_every_program_and_check_that_resets_reuses_one_trace_of_the_env_s_reset_and_the_env_is_left_as_it_was():
    # The protocol's check, the reward diagnosis, the initial states, init's first population and the
    # refill each reset: an env whose reset is costly to trace (CheetahRun's settles 200 physics steps)
    # is traced once for them all.
    traced = []

    class CountedCart(Cart):
        def reset(self, key):
            traced.append(key.shape)
            return super().reset(key)

    env = CountedCart()
    result = sb.train(env_task(env, horizon=10), replace(TINY, epochs=1))
    assert np.all(np.isfinite(result.test_loss))
    assert traced == [(2,)]
    assert "reset" not in vars(env)  # the user's env keeps its own method


def test_the_epoch_is_lowered_for_its_population_s_shapes_taken_from_one_reset_without_batching_the_reset(
        monkeypatch):
    """A start lowers the epoch for the shapes init gives (``lowering.state_shapes``). Its carried
    population's come from one reset's: the batched reset, a large trace, is left to init's own program,
    traced while the epoch compiles. The shapes are init's, a reset's weakly typed leaf (an MJX state's
    time) included, so the epoch lowered for them runs on init's state; init's population is reset."""
    class TimedCart(Cart):
        def reset(self, key):
            state = super().reset(key)
            return state._replace(data={**state.data, "time": 0.0})  # a Python float: weakly typed

        def step(self, state, action):
            reached = super().step(state, action)
            return reached._replace(data={**reached.data, "time": state.data["time"] + 0.1})

    task = env_task(TimedCart(), horizon=5)
    trainer = sb.make_trainer(task, TINY)
    seeds = seed_array(TINY)
    batched, vmap = [], jax.vmap
    monkeypatch.setattr(jax, "vmap", lambda function, *a, **k: batched.append(function) or vmap(function, *a, **k))
    shapes = lowering.state_shapes(trainer, seeds)
    assert task.episodes.reset not in batched
    state = trainer.init(seeds)
    assert task.episodes.reset in batched  # init's own program resets the population
    assert jax.tree.structure(shapes) == jax.tree.structure(state)
    described = lambda tree: [(leaf.shape, leaf.dtype, getattr(leaf, "weak_type", False))  # noqa: E731
                              for leaf in jax.tree.leaves(tree)]
    assert described(shapes) == described(state)
    assert starting.lowered_for(lowering.LoweredEpoch(None, shapes), state)
    positions = np.asarray(state.carried.states.data["position"])  # drawn in [-1, 1], none zero
    assert positions.shape == (TINY.seeds, TINY.batch) and np.all(positions != 0)


def test_evaluations_run_apart_on_their_cadence_and_a_hook_sees_every_epoch_and_may_stop_the_run():
    # Windows of 10 along episodes of 30: 3 updates an epoch. Every 6 updates: epochs 2 and 4, and the
    # last one (5) - not 1 or 3, whose returns are NaN.
    task = env_task(Cart(), horizon=10)
    seen = []

    def progress_fn(env_steps, metrics):
        seen.append((env_steps, bool(np.all(np.isfinite(metrics["test_loss"]))), metrics["eval_seconds"] > 0))

    result = sb.train(task, replace(TINY, epochs=5, eval_every="6"), progress_fn=progress_fn)
    steps = 3 * TINY.batch * 10
    assert seen == [(steps * epoch, epoch in (2, 4, 5), epoch in (2, 4, 5)) for epoch in range(1, 6)]
    assert np.isfinite(result.test_loss[[1, 3, 4]]).all() and np.isnan(result.test_loss[[0, 2]]).all()
    # A stop asked for once the hook has heard of epoch 2 ends the run before epoch 3.
    heard = []
    stopped = sb.train(task, replace(TINY, epochs=9, eval_every="6"), on_epoch=lambda epoch, metrics: heard.append(epoch),
                       should_stop=lambda: len(heard) == 2)
    assert heard == [1, 2]
    np.testing.assert_array_equal(stopped.metrics["batch_loss"], result.metrics["batch_loss"][:2])
    # A budget spent before the first epoch ends (in the set-up): that epoch is the last, and evaluated.
    budgeted = sb.train(task, replace(TINY, epochs=9, eval_every="6", budget=1e-6))
    assert budgeted.metrics["test_loss"].shape == (1, 1) and np.isfinite(budgeted.test_loss).all()
    np.testing.assert_allclose(budgeted.metrics["batch_loss"], result.metrics["batch_loss"][:1])
    # Evaluated inside every epoch instead, the same returns where both evaluate: evaluation changes no update.
    inside = sb.train(task, replace(TINY, epochs=5, eval_every="epoch"))
    np.testing.assert_allclose(inside.test_loss[[1, 3, 4]], result.test_loss[[1, 3, 4]], rtol=1e-5)
    # Two programs, fused apart by XLA: equal to float32 rounding.
    np.testing.assert_allclose(inside.metrics["batch_loss"], result.metrics["batch_loss"], rtol=1e-6)


@pytest.mark.parametrize("program", ["whole", "per-update"])
def test_an_epoch_cut_short_runs_its_first_updates_and_leaves_the_rest_out(program):
    """An epoch of 3 windows of 10 steps cut to its first 2 (a budget's last epoch): the same parameters
    and carried states as its 2 updates run one by one, and its metrics those of the 2 updates alone;
    the whole epoch's third update moves them on; an epoch is cut to 1 update or more."""
    from stablebptt.engine.training import make_trainer
    config = replace(TINY, epochs=1, epoch_program=program)
    trainer = make_trainer(env_task(Cart(), horizon=10), config)
    start = trainer.fresh(trainer.init(seed_array(config)))
    cut, metrics = trainer.epoch(start, trainer.epoch_batches(2), trainer.train_states, trainer.test_states)
    update = (trainer.epoch.update if program == "per-update" else
              make_trainer(env_task(Cart(), horizon=10), replace(config, epoch_program="per-update")).epoch.update)
    by_hand, losses = start, []
    for number in range(2):
        by_hand, output = update(by_hand, jnp.full((), number))
        losses.append(output.loss)
    for got, expected in zip(jax.tree.leaves((cut.params, cut.carried)), jax.tree.leaves((by_hand.params, by_hand.carried))):
        np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(metrics["batch_loss"], np.mean(losses, axis=0), rtol=1e-5)
    # The updates it skipped are no failures: the epoch stays finite, its flows' counts and norms its updates'.
    assert np.all(metrics["finite"]) and np.all(metrics["nonfinite_flow_updates"] == 0)
    assert np.all(np.isfinite(metrics["update_norm"])) and np.all(metrics["update_norm"] > 0)
    whole, whole_metrics = trainer.epoch(start, trainer.epoch_batches(), trainer.train_states, trainer.test_states)
    assert not all(np.allclose(a, b) for a, b in zip(jax.tree.leaves(whole.params), jax.tree.leaves(cut.params)))
    assert not np.allclose(whole_metrics["batch_loss"], metrics["batch_loss"])
    with pytest.raises(InputError, match="cut to 1 of them or more"):
        trainer.epoch_batches(0)
    if program == "whole":  # one flow and no cosine: the update's outputs still match the skipped ones'
        alone = make_trainer(env_task(Cart(), horizon=10), replace(config, mode="R", cosine=False))
        state = alone.fresh(alone.init(seed_array(config)))
        _, metrics = alone.epoch(state, alone.epoch_batches(2), alone.train_states, alone.test_states)
        assert np.all(metrics["finite"]) and np.all(np.isnan(metrics["cosine"]))

def test_a_reward_only_late_in_the_episode_passes_the_check_and_trains_with_it_on(monkeypatch):
    # 0 for 60 steps of 100, then a target: the diagnosis looks along whole episodes, where training will look.
    from stablebptt.envs import diagnosis
    env, key = LateCart(), jax.random.PRNGKey(0)
    states, actions = jax.jit(lambda key: diagnosis.sample_for_diagnosis(env, env.step, key, 100))(key)
    lead, stride = diagnosis._spacing(100, diagnosis._clocks_after_reset(100))  # 19 and 2: clocks 21, 23, ..., 99
    np.testing.assert_array_equal(states.data["count"][:diagnosis.DIAGNOSIS_EPISODES], 0)  # the resets
    np.testing.assert_array_equal(states.data["count"][diagnosis.DIAGNOSIS_EPISODES:],
                                  lead + stride * np.arange(1, diagnosis._clocks_after_reset(100) + 1))
    near, _ = jax.jit(lambda key: diagnosis.sample_for_diagnosis(env, env.step, key, 100, diagnosis.NEAR_STEPS))(key)
    assert int(near.data["count"].max()) == diagnosis.NEAR_STEPS - 1  # one clock a step over the first steps
    # Flat over the first steps, it looks along whole episodes by running its programs again: compiled once.
    compiles, compiled_beside = [], diagnosis._compiled_beside
    monkeypatch.setattr(diagnosis, "_compiled_beside", lambda begun, compose: compiles.append(begun) or
                        compiled_beside(begun, compose))
    pending = diagnosis.start_diagnosis(env, env.step, key, 100)
    assert diagnosis.RewardDiagnosis(*pending()).kind == "usable" and len(compiles) == 1 and len(compiles[0]) == 3
    for checked, drawn in zip(jax.tree.leaves(pending.samples()), jax.tree.leaves((states, actions))):
        np.testing.assert_allclose(np.asarray(checked), np.asarray(drawn), rtol=1e-6, atol=1e-7)
    monkeypatch.undo()
    task = env_task(env, horizon=10)
    assert task.resolved["reward_gradient"] == "usable" and "reward_smoothing" not in task.resolved
    result = sb.train(task, replace(TINY, epochs=4, batch=8, eval_every="epoch"))  # windows of 10 on carried episodes of 100
    assert np.all(np.isfinite(result.test_loss)) and result.test_loss[-1] < 0.5 * result.test_loss[0]


def test_beside_an_accelerator_the_reward_check_compiles_and_runs_on_the_hosts_cpu(monkeypatch):
    # Its kernels never meet the epoch's compile on a GPU, which times its own there; its answer stays the same.
    # There it runs as soon as it has compiled, its further look along whole episodes too, before the caller asks.
    from stablebptt.envs import diagnosis
    env, key, cpu = LateCart(), jax.random.PRNGKey(0), jax.devices("cpu")[0]
    assert diagnosis.check_device() is None and diagnosis.on_check_device(key) is key  # a CPU run: as it was
    assert diagnosis.start_diagnosis(env, env.step, key, 100).answer is None  # run once called
    monkeypatch.setattr(diagnosis.jax, "default_backend", lambda: "gpu")
    assert diagnosis.check_device() == cpu and diagnosis._diagnosis_options() is None  # the CPU's own options
    pending = diagnosis.start_diagnosis(env, env.step, key, 100)
    assert pending.argument[0].committed and pending.argument[0].devices() == {cpu}
    ran = pending.answer.result()  # the run begun beside, the caller never having called
    # LateCart's reward is flat over the episodes' first steps: the samples are those along whole episodes.
    assert diagnosis.RewardDiagnosis(*ran).kind == "usable" and pending.samples()[1].shape[0] > 0
    assert int(np.max(np.asarray(pending.samples()[0].data["count"]))) >= LateCart.LATE
    assert diagnosis.RewardDiagnosis(*pending()).kind == "usable"
    assert all(leaf.devices() == {cpu} for leaf in jax.tree.leaves(pending.samples()))
    checks = diagnosis.start_checks(env.step, *pending.samples())  # a surrogate's check, at the same samples
    assert checks.argument[0].data["count"].committed and diagnosis.RewardDiagnosis(*checks()).kind == "usable"


def test_a_reward_without_a_usable_gradient_is_refused_and_a_nan_at_zero_action_starts_off_zero(tmp_path, monkeypatch):
    # Under a key (a registry env's name), the diagnosis is kept in the compile cache with the programs.
    key = lambda reward: {"env": f"Cart {reward} {tmp_path}"}  # noqa: E731
    for _ in range(2):  # the second time from what the first kept: a refusal is kept too
        with pytest.raises(EnvError, match="gradient is zero at every sampled state") as refusal:
            env_task(Cart("step"), horizon=5, dense_variant="SmoothCart", diagnosis_key=key("step"), smoothing="off")
        monkeypatch.setattr(adapter, "start_diagnosis", lambda *a: pytest.fail("diagnosed although kept"))
    monkeypatch.undo()
    assert "train SmoothCart, its dense variant; or give the reward a slope" in str(refusal.value)
    # Another reward under the same key is diagnosed, not read from the env's own refusal kept there.
    for named in ("", "SmoothCart"):
        dense = env_task(Cart("step"), horizon=5, reward_env=Cart(), dense_variant=named, diagnosis_key=key("step"),
                         smoothing="off")
        assert dense.resolved["reward_gradient"] == "usable"
    # Of another env's reward, a diagnosis is kept only where dense_variant names that env: not of its class alone.
    with pytest.raises(EnvError, match="gradient is zero") as refusal:
        env_task(Cart("step"), horizon=5, reward_env=Cart("step"), dense_variant="SmoothCart", smoothing="off")
    assert "dense variant" not in str(refusal.value)  # the windows train on it already
    with pytest.raises(EnvError, match="gradient is zero"):
        env_task(Cart("step"), horizon=5, reward_env=Cart("step"), diagnosis_key=key("class"), smoothing="off")
    unnamed = env_task(Cart("step"), horizon=5, reward_env=Cart(), diagnosis_key=key("class"), smoothing="off")
    assert unnamed.resolved["reward_gradient"] == "usable"  # another env of the class, diagnosed anew
    with pytest.raises(EnvError, match=r"gradient is NaN at \d+% of sampled states"):
        env_task(Cart("root"), horizon=5)
    task = env_task(Cart("norm"), horizon=5, diagnosis_key=key("norm"))
    states = task.sample_initial_states(jax.random.PRNGKey(3), 6)  # its reset is traced and kept too
    monkeypatch.setattr(adapter, "start_diagnosis", lambda *a: pytest.fail("diagnosed although kept"))
    monkeypatch.setattr(program_store, "_traced", lambda *a: pytest.fail("traced although kept"))
    monkeypatch.setattr(adapter, "check_protocol", lambda *a: pytest.fail("observation size read although kept"))
    again = env_task(Cart("norm"), horizon=5, diagnosis_key=key("norm"))
    assert again.resolved == task.resolved
    plain = jax.jit(jax.vmap(Cart("norm").reset))(jax.random.split(jax.random.PRNGKey(3), 6))
    for kept, traced in zip(jax.tree.leaves(again.sample_initial_states(jax.random.PRNGKey(3), 6)), jax.tree.leaves(plain)):
        np.testing.assert_array_equal(kept, traced)  # bit for bit, integer and bool leaves alike
    assert jax.tree.structure(states) == jax.tree.structure(plain)
    monkeypatch.undo()
    assert task.resolved["reward_gradient"] == "nan at zero action"
    assert task.resolved["policy_output_start"] == "small"
    params = task.init_params(jax.random.PRNGKey(0), True)
    assert 0 < float(jnp.max(jnp.abs(params[-1][0]))) < 0.1  # small output weights, not zero
    result = sb.train(task, replace(TINY, epochs=1))
    assert np.isfinite(result.test_loss).all()


def test_a_deferred_diagnosis_lets_a_trainer_be_built_and_holds_back_the_parameters_until_it_answers(tmp_path, monkeypatch):
    config, seeds = replace(TINY, epochs=1), seed_array(replace(TINY, epochs=1))
    refused = env_task(Cart("step"), horizon=5, defer_diagnosis=True, diagnosis_key={"env": f"step {tmp_path}"},
                       smoothing="off")
    assert refused.resolved["reward_gradient"] == "pending"
    trainer = sb.make_trainer(refused, config)  # shapes only: built while the diagnosis compiles
    with pytest.raises(EnvError, match="gradient is zero at every sampled state"):
        refused.settled()
    with pytest.raises(EnvError, match="gradient is zero at every sampled state"):
        trainer.init(seeds)  # the parameters' values wait for the diagnosis: no silent start
    with pytest.raises(EnvError, match="gradient is zero at every sampled state"):  # kept: refused at once
        env_task(Cart("step"), horizon=5, defer_diagnosis=True, diagnosis_key={"env": f"step {tmp_path}"},
                 smoothing="off")
    pending = env_task(Cart("norm"), horizon=5, defer_diagnosis=True)
    trainer = sb.make_trainer(pending, config)
    lowered = lowering.lowered_epoch(trainer, config)  # the epoch traced for the parameters' shapes
    # init traced and run after that, with the seeds train.py gives, before settling: the start is
    # still the diagnosis's (small, not zero).
    state = trainer.init(seeds)
    output_weights = state.params[-1][0]
    assert 0 < float(jnp.max(jnp.abs(output_weights))) < 0.1
    settled = pending.settled()
    assert settled.settle is None and settled.resolved == env_task(Cart("norm"), horizon=5).resolved
    assert settled.resolved["policy_output_start"] == "small"
    arguments = (trainer.fresh(state), trainer.batches, trainer.train_states, trainer.test_states)
    plain = jax.jit(trainer.epoch)(*arguments)
    monkeypatch.setattr(starting, "compile_epoch", lambda *a, **k: pytest.fail("traced again although lowered"))
    (tmp_path / "run").mkdir()
    outcome = epochs.train_epochs(trainer, config, tmp_path / "run", state, 0, empty_rows(),
                                   np.asarray(seeds), lowered=lowered)
    assert outcome.status == "complete"
    for early, again in zip(jax.tree.leaves(outcome.state), jax.tree.leaves(plain[0])):
        np.testing.assert_array_equal(early, again)  # the epoch lowered from shapes computes the same bits


def test_a_step_that_breaks_the_protocol_is_refused_in_its_words_where_the_check_traces_it():
    # The diagnosis's trace is the first to meet the step: its failure (here reading a field of an array) is
    # told as the protocol says, whether the check is waited for or runs beside the caller.
    breaking = types.SimpleNamespace(reset=Cart().reset, step=lambda state, action: state.obs,
                                     observation_size=Cart().observation_size, action_size=1)
    for deferred in (False, True):
        with pytest.raises(EnvError, match="step.state, action. must return a state of the tree it is given"):
            env_task(breaking, horizon=5, defer_diagnosis=deferred)


def test_a_wrapper_of_an_environment_that_lacks_a_size_is_refused_in_one_line():
    class Wrapper:  # its class has every name of the protocol; reading one reaches the wrapped env
        def __init__(self, env):
            self.env = env

        reset = property(lambda self: self.env.reset)
        step = property(lambda self: self.env.step)
        observation_size = property(lambda self: self.env.observation_size)
        action_size = property(lambda self: self.env.action_size)

    cart = Cart()
    incomplete = types.SimpleNamespace(reset=cart.reset, step=cart.step, action_size=1)  # no observation_size
    with pytest.raises(EnvError, match="reading its observation_size or action_size failed"):
        env_task(Wrapper(incomplete), horizon=5)


def test_the_summary_speaks_of_a_constraint_solver_only_where_the_env_simulates_one():
    import mujoco
    solver = "constraint solver differentiated at its solution"
    assert solver not in env_task(Cart(), horizon=5, diagnose=False).summary  # plain JAX: no solver

    def with_model(limited: bool) -> Cart:  # the Cart's own step, beside a MuJoCo model as Playground's envs keep one
        cart = Cart()
        cart.mj_model = mujoco.MjModel.from_xml_string(
            f"<mujoco><worldbody><body><joint type='slide' limited='{str(limited).lower()}' range='-1 1'/>"
            "<geom size='.1'/></body></worldbody></mujoco>")
        return cart

    assert solver in env_task(with_model(limited=True), horizon=5, diagnose=False).summary  # a limit: the solver's rows
    assert solver not in env_task(with_model(limited=False), horizon=5, diagnose=False).summary


def test_the_command_line_trains_an_importable_environment_and_refuses_bad_ones_in_one_line(tmp_path, capsys):
    on_path = {"PYTHONPATH": os.pathsep.join([str(ROOT / "tests"), os.environ.get("PYTHONPATH", "")])}
    done = run_script("scripts/train.py", "--env", "envs_for_tests:make_cart", "--steps", "6", "--epochs", "2",
                      "--train-size", "4", "--test-size", "4", "--batch", "4", "--policy-width", "8",
                      "--policy-depth", "3", "--no-progress", "--out", str(tmp_path / "run"), env=on_path)
    assert done.returncode == 0, done.stderr
    assert "make_cart" in done.stdout and "reward gradient: usable" in done.stdout
    assert "training on carried episodes: 4 per seed, each update one window of 6 steps" in done.stdout
    record = read_json(tmp_path / "run" / "config.json")
    assert record["task"] == "env" and record["task_config"]["env"] == "envs_for_tests:make_cart"
    assert record["resolved_task"]["hidden"] == [8, 8, 8]
    for args, expected in ((["--env", "envs_for_tests:step_reward_cart", "--smoothing", "off"],
                            "gradient is zero at every sampled state"),
                           (["--env", "no_such_module:env"], "cannot import no_such_module"),
                           (["--env", "envs_for_tests:nothing"], "has no attribute 'nothing'"),
                           (["--env", "envs_for_tests:make_cart", "--discount", "0"], "--discount must be in (0, 1]"),
                           (["--env", "envs_for_tests:make_cart", "--squash-gradient-floor", "-0.1"],
                            "--squash-gradient-floor must be in [0, 1)"),
                           (["--env", "envs_for_tests:make_cart", "--policy-width", "0"],
                            "--policy-width must be a whole number of units from 1 to 2147483647, got 0"),
                           (["--env", "envs_for_tests:make_cart", "--policy-depth", "-1"],
                            "--policy-depth must be a whole number of layers from 0 to 1000, got -1")):
        refused_in_one_line(capsys, tmp_path / "refused", expected, *args, "--epochs", "1")


# A hinge pressed past its limit and a ball in sliding contact with the floor; the model's own
# Newton solver runs 4 iterations, which plain reverse mode cannot pass (a while loop).
@pytest.mark.parametrize("argument, value", [("discount", "0.5"), ("discount", None), ("discount", True),
                                             ("episode_length", True), ("episode_length", 2.5), ("horizon", 2.5),
                                             ("hidden", "64"), ("diagnose", "yes"), ("name", 3),
                                             ("squash_gradient_floor", 1.0), ("squash_gradient_floor", float("nan"))])
def test_every_argument_of_env_task_is_refused_in_the_librarys_terms(argument, value):
    arguments = {"horizon": 5, argument: value}
    with pytest.raises(EnvError, match=f"env_task's {argument} must be"):
        env_task(Cart(), **arguments)


@pytest.mark.parametrize("diagnose", [True, False])
def test_a_step_that_returns_a_state_of_another_tree_is_refused_before_anything_is_scanned(diagnose):
    from envs_for_tests import TreeChangingCart
    with pytest.raises(EnvError, match="TreeChangingCart: step.state, action. must return a state of the tree"):
        env_task(TreeChangingCart(), horizon=5, diagnose=diagnose)


def test_an_observation_size_its_observations_break_is_named_with_the_reward_check_on():
    # The check traces the step and the reward, no policy: the observation's size is kept as the policy is traced.
    WrongSize = type("WrongSize", (Cart,), {"observation_size": 3})
    task = env_task(WrongSize(), horizon=5, diagnose=True)
    with pytest.raises(EnvError, match=r"WrongSize: its states' observations have shape \(2,\), but observation_size is 3"):
        sb.make_trainer(task, sb.TrainConfig(epochs=1, batch=4))


def test_an_env_module_that_fails_as_it_imports_is_one_line_and_the_current_folder_is_searched(
        tmp_path, monkeypatch, capsys):
    (tmp_path / "lab_env_divides.py").write_text("RATE = 1 / 0\n")
    (tmp_path / "lab_env_typo.py").write_text("def make(:\n    pass\n")
    (tmp_path / "lab_env_good.py").write_text("from envs_for_tests import Cart\n\ndef make():\n    return Cart()\n")
    monkeypatch.chdir(tmp_path)  # a user in their own project folder
    monkeypatch.setattr(sys, "path", [entry for entry in sys.path if entry not in ("", str(tmp_path))])
    with pytest.raises(EnvError, match=r"importing lab_env_divides failed: ZeroDivisionError: division by zero"):
        load_env("lab_env_divides:make")
    with pytest.raises(EnvError, match=r"importing lab_env_typo failed \(line 1\): SyntaxError"):
        load_env("lab_env_typo:make")
    assert isinstance(load_env("lab_env_good:make"), Cart)
    refused_in_one_line(capsys, tmp_path / "refused", "ZeroDivisionError", "--env", "lab_env_divides:make")
    line = refused_in_one_line(capsys, tmp_path / "refused", "step(state, action) must return a state of the tree",
                               "--env", "envs_for_tests:tree_changing_cart", "--no-reward-check")
    assert "--step" not in line


def test_an_interrupted_episode_run_resumes_to_the_metrics_of_an_uninterrupted_one_and_says_what_it_cannot_check(
        tmp_path, capsys, monkeypatch):
    # Windows of 4 steps along carried episodes of 6: episodes end inside windows and are reset between them;
    # the observation statistics ride in the parameters' checkpoint, the learned noise's deviations in the
    # state's. A budget spent in the set-up stops the run after its first epoch, evaluated and saved; the
    # resume, with no budget, trains on to --epochs.
    sizes = ["--steps", "4", "--train-size", "4", "--test-size", "4", "--batch", "4", "--episode-length", "6",
             "--seeds", "2", "--no-progress", "--normalize-observations", "--eval-every", "2",
             "--action-noise", "0.2", "--learn-action-noise", "--entropy", "0.01"]
    code, err = train_in_process(capsys, "--env", "envs_for_tests:make_cart", *sizes, "--epochs", "3",
                                 "--budget", "0.001", "--out", str(tmp_path / "run"))
    assert code == 0 and not err, err
    assert [int(row["epoch"]) for row in run_folder.read_metrics(tmp_path / "run" / run_folder.METRICS_FILE)] == [1, 1]
    # The resume lowers its epoch as a first start does, for the shapes its checkpoint is read into (the
    # reset's weakly typed leaves stored strongly): the lowered program serves it, none is traced after.
    # Its reward, which the first start's check passed as written, is not checked again.
    with monkeypatch.context() as patched:
        patched.setattr(starting, "compile_epoch", lambda *a, **k: pytest.fail("the resume's epoch traced again"))
        patched.setattr(adapter, "start_diagnosis", lambda *a: pytest.fail("the resume checked the reward again"))
        code, err = train_in_process(capsys, "--resume", str(tmp_path / "run"), "--budget", "0")
    assert code == 0, err
    # It says so, and the task reopened from the run (a resume or a render) records the reward as usable still.
    from stablebptt.apps.trained import open_trained
    reopened = open_trained(tmp_path / "run").task
    assert "reward gradient: usable (as the run's first check found)" in reopened.summary
    assert reopened.resolved["reward_gradient"] == "usable"
    from stablebptt.commands import train as train_command
    assert train_command.main(["--env", "envs_for_tests:make_cart", *sizes, "--epochs", "3",
                               "--out", str(tmp_path / "straight")]) == 0
    assert "the actions' noise, learned: deviations" in capsys.readouterr().out
    resumed, straight = (run_folder.read_metrics(tmp_path / name / run_folder.METRICS_FILE) for name in ("run", "straight"))
    assert len(resumed) == len(straight) == 6
    timings = ("seconds", "eval_seconds")
    for one, other in zip(resumed, straight):
        assert {k: v for k, v in one.items() if k not in timings} == {k: v for k, v in other.items() if k not in timings}
    # Two updates of 4 windows of 4 steps an epoch; evaluated apart, every 2 updates: at every epoch.
    assert [row["env_steps"] for row in straight] == [32.0, 32.0, 64.0, 64.0, 96.0, 96.0]
    assert all(row["eval_seconds"] > 0 for row in straight)
    starts = read_json(tmp_path / "run" / run_folder.STARTUP_FILE)
    assert len(starts) == 2 and all(start["phases"]["compile"] > 0 for start in starts), starts
    # The trainer's set-up by its parts (a part answered from the cache in no time is left out).
    parts = [name for name in starts[0]["phases"] if name.startswith("trainer set-up")]
    assert "trainer set-up: initial states" in parts and set(parts) <= {
        "trainer set-up: task check", "trainer set-up: initial states",
        "trainer set-up: step's trace and memory plan", "trainer set-up"}, parts
    assert starts[0]["budget"] == 0.001 and "budget" not in starts[1]  # each start's own; the resume had none
    assert [start["first_epoch"] for start in starts] == [1, 2]
    assert len({row["test_loss"] for row in straight}) > 2  # it trains: the returns move
    # A run recorded before episode training trained from fixed starts, and resumes so.
    from stablebptt.apps.trained import configs_of
    from stablebptt.tasks import env
    record = read_json(tmp_path / "run" / "config.json")
    assert record["train"]["episodes"] == "auto" and record["resolved_task"]["normalize_observations"] is True
    del record["train"]["episodes"]
    assert configs_of(tmp_path / "run", record)[1].episodes == "off"
    # 'steps 0' is the default of the run's day: the window its resolved task records.
    assert configs_of(tmp_path / "run", record)[0].steps == 4
    record["task_config"]["steps"] = 0
    assert configs_of(tmp_path / "run", record)[0].steps == 4
    del record["resolved_task"]["horizon_steps"]
    assert configs_of(tmp_path / "run", record)[0].steps == env.FORMER_DEFAULT_STEPS == 100
    assert [line for line in err if line.startswith("note:")] == [
        "note: the run trains envs_for_tests:make_cart, code of your own that the library cannot check: if "
        "envs_for_tests changed since the run began, its metrics change at the resume"]
    if HAS_PLAYGROUND:
        config = env.Config(env="CartpoleSwingup")
        assert env.check_resume(config, {"resolved_task": {"playground_version": env._playground_version()}}) == ""
        with pytest.raises(InputError, match=r"the run began on MuJoCo Playground 0.0.1, and .* is installed"):
            env.check_resume(config, {"resolved_task": {"playground_version": "0.0.1"}})


@pytest.mark.parametrize("sizes, words", [((2, 0), "action_size is 0"), ((0, 1), "observation_size is 0"),
                                          ((2, True), "action_size is True")])
def test_an_environment_of_degenerate_sizes_is_refused_rather_than_trained_with_zero_updates(sizes, words):
    class Degenerate(Cart):
        observation_size, action_size = sizes

    with pytest.raises(EnvError, match=f"Degenerate's {words}"):
        env_task(Degenerate(), horizon=5)


def test_a_squash_gradient_floor_leaves_the_policys_actions_and_passes_a_saturated_actions_gradient_on():
    """The task's policy takes the same actions with a floor as without; where an action saturates, its
    gradient in the output layer's bias is the floor, where tanh's own is nearly 0."""
    cart = Cart()
    plain, floored = (env_task(cart, horizon=5, diagnose=False, squash_gradient_floor=floor) for floor in (0.0, 0.2))
    assert "squash's derivative at least 0.2" in floored.summary and floored.resolved["squash_gradient_floor"] == 0.2
    params = plain.init_params(jax.random.PRNGKey(0), False)
    params[-1] = (params[-1][0], params[-1][1] + 5.0)  # every pre-squash output near 5: tanh' about 2e-4
    state = cart.reset(jax.random.PRNGKey(1))

    def action_and_bias_slope(task):
        action = task.dynamics.policy(params, state)
        slope = jax.grad(lambda bias: task.dynamics.policy([*params[:-1], (params[-1][0], bias)], state).sum())(params[-1][1])
        return action, slope

    (plain_action, plain_slope), (floored_action, floored_slope) = (action_and_bias_slope(t) for t in (plain, floored))
    np.testing.assert_array_equal(np.asarray(plain_action), np.asarray(floored_action))
    assert float(jnp.max(plain_slope)) < 1e-2
    np.testing.assert_allclose(np.asarray(floored_slope), 0.2, rtol=1e-6)
