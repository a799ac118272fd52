"""A lab's env whose reward is a step function trains on its smooth surrogate (stablebptt.envs.surrogate),
from Python and from the command line, and reports its true return; a surrogate of the user's own (a
function, from Python or the command line) or the reward of another env on the same states (a sparse
env's dense variant) is trained as given; smoothing off refuses the reward as before."""
import dataclasses
import functools
import json
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import refused_in_one_line
from envs_for_tests import Cart, position_reward

import stablebptt as sb
from stablebptt.commands import train as train_command
from stablebptt.envs.adapter import env_task
from stablebptt.envs.protocol import EnvError, function_name


def test_a_labs_env_with_a_step_reward_trains_on_its_surrogate_and_reports_its_true_return():
    config = sb.TrainConfig(mode="C", epochs=2, train_size=8, test_size=8, batch=4, clip="norm", lr=1e-2)
    task = env_task(Cart("step"), horizon=5)  # 1 where |position| < 0.1, else 0: flat almost everywhere
    assert "smoothed 1 comparison of the reward into sigmoids: " in task.summary and "envs_for_tests.py" in task.summary
    assert task.resolved["reward_gradient"] == "usable" and "reward_smoothing" in task.resolved
    # A sparse env smoothed where a dense variant exists: the first line points to that variant's reward.
    assert "dense variant" not in task.summary
    hinted = env_task(Cart("step"), horizon=5, dense_variant="SmoothCart")
    assert "(SmoothCart's reward, its dense variant, may train further: --dense-reward)" in hinted.summary
    states = task.sample_initial_states(jax.random.PRNGKey(0), 8)
    params = task.init_params(jax.random.PRNGKey(1), True)
    # The returns it reports are the true reward's: those of the same env trained without a check.
    plain = env_task(Cart("step"), horizon=5, diagnose=False)
    np.testing.assert_array_equal(task.evaluation(params, states), plain.evaluation(params, states))
    # It trains on the surrogate: from the zero policy the true reward's update is exactly zero, this one is not.
    trained = sb.train(task, config)
    assert np.all(np.isfinite(trained.test_loss)) and float(jnp.abs(trained.params[-1][0]).max()) > 0
    flat = sb.train(plain, config)
    assert float(jnp.abs(flat.params[-1][0]).max()) == 0.0
    # A surrogate of the user's own is trained on as given, and diagnosed.
    own = env_task(Cart("step"), horizon=5, surrogate_reward=lambda state: -state.data["position"] ** 2)
    assert own.resolved["reward_gradient"] == "usable" and "reward_smoothing" not in own.resolved
    # From Python as from the command, the task says which reward it trains on, and the returns it reports.
    assert "; trained on the reward " in own.summary and ".<lambda> (returns reported: the env's own)" in own.summary
    reached = own.dynamics.step(jax.tree.map(lambda a: a[0], states), jnp.array([0.3]))
    assert float(reached.reward) == pytest.approx(-float(reached.data["position"]) ** 2)
    # Or the reward of another env's step on the same states (a sparse env's dense variant), reported on its own.
    dense = env_task(Cart("step"), horizon=5, reward_env=Cart())
    assert dense.resolved["reward_gradient"] == "usable" and "reward_smoothing" not in dense.resolved
    assert dense.resolved["trained_reward"] == "the reward of Cart" and "; trained on the reward of Cart" in dense.summary
    named = env_task(Cart("step"), horizon=5, reward_env=Cart(), dense_variant="SmoothCart", diagnose=False)
    assert named.resolved["trained_reward"] == "the reward of SmoothCart, its dense variant"
    # A reward with no qualified name of its own is named without its address, the same on every run.
    assert function_name(functools.partial(position_reward)) == "functools.partial(envs_for_tests:position_reward)"
    assert function_name(Cart()) == "envs_for_tests:Cart()"
    made_at_run_time = types.FunctionType(position_reward.__code__, {}, "position_reward")
    made_at_run_time.__module__ = None  # a function built from code, in no module: its name alone
    assert function_name(made_at_run_time) == "position_reward"
    reached = dense.dynamics.step(jax.tree.map(lambda a: a[0], states), jnp.array([0.3]))
    assert float(reached.reward) == pytest.approx(-float(reached.data["position"]) ** 2 - 0.01 * 0.3 ** 2)
    np.testing.assert_array_equal(dense.evaluation(params, states), plain.evaluation(params, states))
    from envs_for_tests import TreeChangingCart
    with pytest.raises(EnvError, match="Cart: the step whose reward is trained on does not return states like Cart's"):
        env_task(Cart("step"), horizon=5, reward_env=TreeChangingCart())
    with pytest.raises(EnvError, match="give a surrogate_reward or a reward_env to train on, not both"):
        env_task(Cart("step"), horizon=5, reward_env=Cart(), surrogate_reward=lambda state: state.reward)
    with pytest.raises(EnvError, match="gradient is zero at every sampled state"):
        env_task(Cart("step"), horizon=5, smoothing="off")
    with pytest.raises(EnvError, match="env_task's smoothing_scale must be a positive number"):
        env_task(Cart("step"), horizon=5, smoothing_scale=0.0)


def test_the_command_line_names_the_smoothed_comparisons_in_its_first_line(tmp_path, capsys):
    code = train_command.main(["--env", "envs_for_tests:step_reward_cart", "--steps", "5", "--epochs", "1",
                               "--train-size", "4", "--test-size", "4", "--batch", "4", "--no-progress",
                               "--out", str(tmp_path / "run")])
    printed = capsys.readouterr().out.splitlines()
    assert code == 0 and printed[0].startswith("step_reward_cart: ") and "smoothed 1 comparison of the reward" in printed[0]
    from stablebptt.storage import read_json
    resolved = read_json(tmp_path / "run" / "config.json")["resolved_task"]
    assert resolved["reward_smoothing"] in printed[0] and resolved["reward_gradient"] == "usable"
    with pytest.raises(SystemExit) as refused:
        train_command.main(["--env", "envs_for_tests:step_reward_cart", "--smoothing-scale", "-1",
                            "--out", str(tmp_path / "refused")])
    err = capsys.readouterr().err.splitlines()
    assert refused.value.code == 2 and err == ["error: --smoothing-scale must be a positive number, got -1.0"]
    assert not (tmp_path / "refused").exists()


def test_a_reopened_run_whose_reward_was_smoothed_acts_as_its_policy_did_in_training(tmp_path, capsys):
    """Reopening (rendering, a study) rebuilds the surrogate the run trained on: a policy that observes its
    trained reward's direction acts on the surrogate's, which the reward as written (flat) would zero."""
    from dataclasses import replace

    from stablebptt.apps.trained import episodes_from_test_states, open_trained
    from stablebptt.storage import read_json
    from stablebptt.tasks import env as env_tasks
    code = train_command.main(["--env", "envs_for_tests:step_reward_cart", "--observe-reward-direction", "--steps", "5",
                               "--epochs", "1", "--train-size", "4", "--test-size", "4", "--batch", "4",
                               "--no-progress", "--out", str(tmp_path / "run")])
    assert code == 0
    capsys.readouterr()
    notes = []
    reopened = open_trained(tmp_path / "run", note=notes.append)
    recorded = read_json(tmp_path / "run" / "config.json")["resolved_task"]
    assert reopened.task.resolved["reward_smoothing"] == recorded["reward_smoothing"] and notes == []
    params = reopened.seed_params(0)
    def controls(task):
        return np.asarray(episodes_from_test_states(task, task.episodes, params, reopened.train, 4, steps=20).controls)
    as_trained = controls(env_tasks.make(reopened.task_config))  # the task as training built it
    np.testing.assert_array_equal(controls(reopened.task), as_trained)
    # The reward as written, unchecked, gives the policy another direction to see: it acts otherwise.
    as_written = controls(env_tasks.make(replace(reopened.task_config, reward_check=False)))
    assert np.abs(as_written - as_trained).max() > 0.1 * np.abs(as_trained).max() > 0


def test_the_command_line_trains_on_a_surrogate_of_the_users_own_and_refuses_what_cannot_be_in_one_line(
        tmp_path, capsys):
    code = train_command.main(["--env", "envs_for_tests:step_reward_cart", "--surrogate-reward",
                               "envs_for_tests:position_reward", "--steps", "5", "--epochs", "1", "--train-size", "4",
                               "--test-size", "4", "--batch", "4", "--no-progress", "--out", str(tmp_path / "run")])
    printed = capsys.readouterr().out.splitlines()
    assert code == 0 and "trained on the reward envs_for_tests:position_reward" in printed[0], printed
    from stablebptt.storage import read_json
    resolved = read_json(tmp_path / "run" / "config.json")["resolved_task"]
    assert resolved["trained_reward"] == "the reward envs_for_tests:position_reward" and "reward_smoothing" not in resolved
    for options, words in [(["--surrogate-reward", "no_such_module_here:reward"], "cannot import no_such_module_here"),
                           (["--surrogate-reward", "envs_for_tests:Cart"], "Cart is not a function of the state"),
                           (["--dense-reward"], "envs_for_tests:step_reward_cart has no dense variant"),
                           (["--dense-reward", "--surrogate-reward", "envs_for_tests:position_reward"], "not both")]:
        refused_in_one_line(capsys, tmp_path / "no", words, "--env", "envs_for_tests:step_reward_cart", *options)


def test_the_surrogate_is_fitted_on_the_diagnosis_own_samples_as_on_a_fresh_draw_of_them():
    from stablebptt.envs.diagnosis import RewardDiagnosis, sample_for_diagnosis, start_diagnosis
    from stablebptt.envs.surrogate import smooth_reward
    env, key = Cart("step"), jax.random.PRNGKey(3)
    pending = start_diagnosis(env, env.step, key, 30)
    assert pending.samples() is None  # not run yet
    assert RewardDiagnosis(*pending()).kind == "zero"
    states, actions = pending.samples()
    fresh_states, fresh_actions = jax.jit(lambda k: sample_for_diagnosis(env, env.step, k, 30))(key)
    for kept, fresh in zip(jax.tree.leaves((states, actions)), jax.tree.leaves((fresh_states, fresh_actions))):
        np.testing.assert_allclose(np.asarray(kept), np.asarray(fresh), rtol=1e-6, atol=1e-7)
    _, from_diagnosis = smooth_reward(env.step, states, actions)
    _, drawn_again = smooth_reward(env.step, fresh_states, fresh_actions)
    assert from_diagnosis.anything and from_diagnosis.terms == drawn_again.terms
    np.testing.assert_allclose(from_diagnosis.temperatures, drawn_again.temperatures, rtol=1e-6)


def test_a_deferred_flat_reward_settles_into_its_surrogate_whose_own_check_answers_afterwards():
    task = env_task(Cart("step"), horizon=5, defer_diagnosis=True)
    assert task.resolved["reward_gradient"] == "pending"
    smoothed = task.settled()  # the surrogate is built; its check compiles beside whatever comes next
    assert smoothed.settle is not None and smoothed.resolved["reward_gradient"] == "pending"
    assert "reward_smoothing" in smoothed.resolved and smoothed.dynamics.step is not task.dynamics.step
    final = smoothed.settled_fully()
    assert final.settle is None and final.dynamics.step is smoothed.dynamics.step
    assert final.resolved == env_task(Cart("step"), horizon=5).resolved  # as the undeferred call settles it
    assert final.summary == env_task(Cart("step"), horizon=5).summary


def test_a_surrogate_whose_derivative_is_nan_at_zero_action_starts_the_policy_off_zero_as_it_says():
    # The reward's own check finds it flat; the surrogate's finds its derivative NaN at exactly zero action (its
    # smoothed comparison reads the action's norm): the policy starts small, as the record says, whether the
    # trainer took its parameters from the task still pending (their values wait for the surrogate's check).
    for deferred in (False, True):
        pending = env_task(Cart("push"), horizon=5, defer_diagnosis=deferred).settled()
        params = pending.init_params(jax.random.PRNGKey(0), True)
        task = pending.settled_fully()
        assert task.resolved["reward_gradient"] == "nan at zero action" and task.resolved["policy_output_start"] == "small"
        weights = params[-1][0]
        assert 0 < np.abs(weights).max() < 0.1
        np.testing.assert_array_equal(weights, task.init_params(jax.random.PRNGKey(0), True)[-1][0])


def test_the_surrogate_is_interpreted_once_however_many_programs_trace_its_step(monkeypatch):
    # Each program of a run (the window, the reward direction's derivative, the evaluation, the critic)
    # traces the step; the surrogate's is an interpreter of the step's program, run once per shape.
    from stablebptt.envs import surrogate
    interpreted = []
    evaluate = surrogate._evaluate
    monkeypatch.setattr(surrogate, "_evaluate", lambda *args: interpreted.append(1) or evaluate(*args))
    task = env_task(Cart("step"), horizon=5, reward_direction_observed=True)
    assert "reward_smoothing" in task.resolved
    state = jax.tree.map(lambda a: a[0], task.sample_initial_states(jax.random.PRNGKey(0), 2))
    before = len(interpreted)
    for program in (lambda s, a: task.dynamics.step(s, a).reward,
                    lambda s, a: jax.grad(lambda a: task.dynamics.step(s, a).reward)(a),
                    lambda s, a: jax.vmap(task.dynamics.step, (None, 0))(s, jnp.stack([a, a])).reward):
        jax.make_jaxpr(program)(state, jnp.array([0.3]))
    # The step and the direction at the state it reaches: at most one interpretation for each shape.
    assert len(interpreted) - before <= 1, len(interpreted) - before


def test_the_epoch_compiles_beside_the_reward_check_where_it_most_likely_keeps_the_reward(monkeypatch):
    """The epoch is traced while the reward check compiles beside. A reward that turns no comparison into a
    number (smooth, or an underflowing Gaussian) begins its epoch's compile before the check answers; a usable
    one trains that compile, traced and compiled once. Where the check smooths the reward, the surrogate's epoch
    is compiled and trained: after the answer where the reward compares (the reward as written never compiled),
    after the unused early compile has ended where a Gaussian underflowed. A refusal leaves the early compile
    unused."""
    from stablebptt.engine import starting
    from stablebptt.engine.task import Task
    traced, compiled, events = [], [], []
    trace, settled, begin = starting.lowered_epoch, Task.settled, starting.beside
    monkeypatch.setattr(Task, "settled", lambda self, *a, **k: events.append("answer") or settled(self, *a, **k))
    monkeypatch.setattr(starting, "beside", lambda function, name: events.append("compile begun") or begin(function, name))

    class Counted:  # a lowered epoch whose compiles are counted, and the programs they gave
        def __init__(self, lowered, index):
            self.lowered, self.index = lowered, index

        def compile(self):
            program = self.lowered.compile()
            compiled.append((self.index, program))
            return program

    def counted(trainer, config, program_key=None, **beside):
        lowered = trace(trainer, config, program_key, **beside)
        traced.append(trainer), events.append("trace")
        return lowered._replace(lowered=Counted(lowered.lowered, len(traced) - 1))

    monkeypatch.setattr(starting, "lowered_epoch", counted)
    others = starting.programs_beside
    monkeypatch.setattr(starting, "programs_beside", lambda *a, **k: events.append("beside") or others(*a, **k))
    config = sb.TrainConfig(mode="C", epochs=1, train_size=8, test_size=8, batch=4, clip="norm")

    def started(reward, **options):
        traced.clear(), compiled.clear(), events.clear()
        task = env_task(Cart(reward), horizon=5, defer_diagnosis=True, **options)
        return task, starting.prepare(task, config)

    task, prepared = started("step")
    assert not task.compile_while_settling and "reward_smoothing" in prepared.task.resolved
    assert events == ["trace", "answer", "trace", "beside", "answer"]  # the last: the surrogate's own check
    assert [index for index, _ in compiled] == [1] and prepared.trainer.epoch is traced[1].epoch  # the surrogate's
    assert prepared.lowered.compiled is compiled[0][1] and prepared.task.settle is None
    task, usable = started("smooth")
    assert task.compile_while_settling and usable.task.resolved["reward_gradient"] == "usable"
    assert events == ["trace", "compile begun", "answer", "beside"] and len(traced) == 1  # the programs beside
    # the epoch (evaluation, init, refill) traced once the check has answered: on two cores, traced while it ran,
    # they shared the cores with both compiles and the start took longer (docs/performance.md)
    assert [index for index, _ in compiled] == [0] and usable.lowered.compiled is compiled[0][1]
    assert "compile beside the check" in usable.phases  # the start's wait while both ran: the compile's part
    assert "compile beside the check" not in prepared.phases
    task, widened = started("narrow")
    assert task.compile_while_settling and "vanishing exponential" in widened.task.resolved["reward_smoothing"]
    assert events == ["trace", "compile begun", "answer", "trace", "beside", "answer"]
    assert [index for index, _ in compiled] == [0, 1] and widened.trainer.epoch is traced[1].epoch
    assert widened.lowered.compiled is compiled[1][1] and "unused compile's wait" in widened.phases
    # Smoothed always, the reward's surrogate follows whatever the check answers: nothing compiles before it.
    task, always = started("faint", smoothing="always")
    assert not task.compile_while_settling and "vanishing exponential" in always.task.resolved["reward_smoothing"]
    assert events == ["trace", "answer", "trace", "beside", "answer"] and [index for index, _ in compiled] == [1]
    traced.clear(), compiled.clear(), events.clear()
    refused = env_task(Cart("root"), horizon=5, defer_diagnosis=True)  # its gradient NaN: compiled early, refused
    with pytest.raises(EnvError, match="NaN"):
        starting.prepare(refused, config)
    assert refused.compile_while_settling and events == ["trace", "compile begun", "answer"]


def test_beside_an_accelerator_a_reward_the_check_most_likely_keeps_is_checked_once_its_epoch_compiles(monkeypatch):
    """Beside an accelerator (the check on its host's CPU), a reward that turns no comparison into a number begins
    its check once the start asks for it, its epoch's compile begun: the check's trace holds back no compile. On the
    accelerator's host a per-update epoch's update (a large step's) is traced before its compile begins, in the
    start's own thread, where it shares Python's lock with no other trace, and the programs beside the epoch next,
    so that they too compile while the check is traced and runs; elsewhere the update is traced as it compiles. A
    reward that compares, which the check most likely smooths, has its check begun as the task is built."""
    import threading

    from stablebptt.engine import starting
    from stablebptt.engine.per_update import PerUpdateEpoch
    from stablebptt.envs import adapter, diagnosis
    cpu = jax.devices("cpu")[0]
    for module in (adapter, diagnosis):
        monkeypatch.setattr(module, "check_device", lambda: cpu)
    events = []
    begin, start, others, lowered_update = (starting.beside, adapter.start_diagnosis, starting.programs_beside,
                                            PerUpdateEpoch.lowered_update)
    monkeypatch.setattr(starting, "beside", lambda function, name: events.append("compile begun") or begin(function, name))
    monkeypatch.setattr(adapter, "start_diagnosis", lambda *a: events.append("check begun") or start(*a))
    monkeypatch.setattr(starting, "programs_beside", lambda *a, **k: events.append("beside") or others(*a, **k))
    monkeypatch.setattr(PerUpdateEpoch, "lowered_update", lambda *a: events.append(
        ("update traced", threading.current_thread().name)) or lowered_update(*a))
    config = sb.TrainConfig(mode="C", epochs=1, train_size=8, test_size=8, batch=4, clip="norm")
    kept = env_task(Cart("smooth"), horizon=5, defer_diagnosis=True)
    assert kept.compile_while_settling and events == [] and kept.settled(wait=False) is kept
    prepared = starting.prepare(kept, config)
    assert events == ["compile begun", "check begun", "beside"] and prepared.task.resolved["reward_gradient"] == "usable"
    for apart in (False, True):
        monkeypatch.setattr(starting, "_host_apart", lambda apart=apart: apart)
        events.clear()
        here = threading.current_thread().name
        prepared = starting.prepare(env_task(Cart("smooth"), horizon=5, defer_diagnosis=True),
                                    dataclasses.replace(config, epoch_program="per-update"))
        if apart:  # each trace alone, the longest compile's first
            assert events == [("update traced", here), "compile begun", "beside", "check begun"], events
        else:  # on a CPU alone the start's thread runs the check meanwhile (traced as the task was built elsewhere)
            assert set(events) == {"compile begun", ("update traced", "stablebptt-epoch"), "check begun", "beside"}
            assert events.index("check begun") < events.index("beside"), events
        assert isinstance(prepared.trainer.epoch, PerUpdateEpoch) and prepared.lowered.compiled.update is not None
    events.clear()
    smoothed = env_task(Cart("step"), horizon=5, defer_diagnosis=True)
    assert not smoothed.compile_while_settling and events == ["check begun"]
    assert "reward_smoothing" in smoothed.settled_fully().resolved


def test_on_an_accelerators_host_the_programs_beside_the_epoch_compile_while_the_check_runs(tmp_path, monkeypatch):
    """On an accelerator's host, where nothing compiles beside the check (a reward it most likely smooths), the
    programs beside the epoch (the evaluation, the population's first resets, each epoch's refill) are traced and
    compile while the check runs. The surrogate's trainer runs them, traced once, where the settled task kept their
    parts (its states carry no direction of the trained reward), and trains as a start that traced them after the
    answer does. Where the states carry the trained reward's direction, the surrogate's own are traced."""
    from stablebptt.engine import starting
    from stablebptt.engine.task import Task
    events = []
    settled, others = Task.settled, starting.programs_beside
    monkeypatch.setattr(Task, "settled", lambda self, *a, **k: events.append("answer") or settled(self, *a, **k))
    monkeypatch.setattr(starting, "programs_beside", lambda *a, **k: events.append("beside") or others(*a, **k))
    config = sb.TrainConfig(mode="C", epochs=2, train_size=8, test_size=8, batch=4, clip="norm", lr=1e-2)

    def trained(apart: bool, **options):
        monkeypatch.setattr(starting, "_host_apart", lambda: apart)
        events.clear()
        task = env_task(Cart("step"), horizon=5, defer_diagnosis=True, **options)
        return sb.train(task, config), list(events)

    ahead, begun = trained(True)
    after, answered = trained(False)
    assert begun == ["beside", "answer", "answer"] and answered == ["answer", "beside", "answer"]
    assert np.all(np.isfinite(ahead.metrics["test_loss"]))
    for name in ("train_loss", "test_loss", "batch_loss"):
        np.testing.assert_array_equal(ahead.metrics[name], after.metrics[name])
    for leaf, other in zip(jax.tree.leaves(ahead.params), jax.tree.leaves(after.params)):
        np.testing.assert_array_equal(leaf, other)
    monkeypatch.setattr(starting, "_host_apart", lambda: True)
    events.clear()
    directed = env_task(Cart("step"), horizon=5, defer_diagnosis=True, reward_direction_observed=True)
    prepared = starting.prepare(directed, config)
    assert "reward_smoothing" in prepared.task.resolved and events == ["beside", "answer", "beside", "answer"]
    assert not starting._keeps_programs_beside(prepared.task, directed)
    # Under a key (a registry env's), the refill traced before the answer is kept where a resume, made as
    # recorded under the smoothed reward's key, looks for it: the resume traces it no more.
    from stablebptt.engine import lowering, program_store
    assert program_store.cache_dir() is not None
    events.clear()
    first = starting.prepare(env_task(Cart("step"), horizon=5, defer_diagnosis=True), config, {"test": str(tmp_path)})
    assert "reward_smoothing" in first.program_key and events == ["beside", "answer", "answer"]
    monkeypatch.setattr(program_store, "_traced", lambda *a: pytest.fail("the refill traced again"))
    lowering.lowered_refill(first.trainer, first.lowered.shapes, first.program_key)


def test_the_surrogates_choices_compile_beside_the_check_where_a_surrogate_most_likely_follows(monkeypatch):
    """Beside an accelerator (the check on its host's CPU), where the reward turns a comparison into a number or
    smoothing is always, the program that fits the surrogate's temperatures on the check's samples is lowered
    as the task is built and compiles beside the check (else it stands after the check's answer, in the start's
    wait); it fits, on the samples of the check's further look along whole episodes, the surrogate the check
    fits once answered. Elsewhere (a smooth reward, smoothing off, the user's own surrogate, a CPU alone) nothing
    begins."""
    from stablebptt.envs import adapter, diagnosis, surrogate
    begun = []
    begin = surrogate.beside
    monkeypatch.setattr(surrogate, "beside", lambda function, name: begun.append(name) or begin(function, name))
    length = diagnosis.NEAR_STEPS + 19  # flat over the first steps: the check looks along whole episodes too
    env_task(Cart("step"), horizon=5, episode_length=length, defer_diagnosis=True).settled().settled_fully()
    assert begun == []  # on a CPU alone its cores run the check's compiles and the set-up already
    fitted_after = env_task(Cart("step"), horizon=5, episode_length=length)  # undeferred: fitted once answered
    for module in (adapter, diagnosis):  # as beside a GPU: the check's samples on the host's CPU
        monkeypatch.setattr(module, "check_device", lambda: jax.devices("cpu")[0])
    pending = env_task(Cart("step"), horizon=5, episode_length=length, defer_diagnosis=True)
    assert begun == ["stablebptt-smoothing-choices"] and pending.resolved["reward_gradient"] == "pending"
    monkeypatch.setattr(surrogate, "temperatures", lambda *a, **k: pytest.fail("fitted again after the check"))
    settled = pending.settled().settled_fully()
    assert settled.resolved == fitted_after.resolved and "reward_smoothing_choices" in settled.resolved
    state = jax.tree.map(lambda a: a[0], settled.sample_initial_states(jax.random.PRNGKey(0), 2))
    for position in (-0.3, 0.05, 0.2):
        action = jnp.array([position])
        np.testing.assert_array_equal(settled.dynamics.step(state, action).reward,
                                      fitted_after.dynamics.step(state, action).reward)
    env_task(Cart("faint"), horizon=5, defer_diagnosis=True, smoothing="always").settled().settled_fully()
    assert len(begun) == 2
    env_task(Cart("smooth"), horizon=5, defer_diagnosis=True).settled()
    env_task(Cart("step"), horizon=5, defer_diagnosis=True, smoothing="off")
    env_task(Cart("step"), horizon=5, defer_diagnosis=True, surrogate_reward=lambda state: state.obs[0])
    assert len(begun) == 2


def test_a_kept_smoothing_rebuilds_the_surrogate_without_sampling_or_checking_again(tmp_path, monkeypatch):
    """The same command again, or a resume, reads the surrogate's temperatures and its check kept with the
    reward's diagnosis: no episodes are rolled and no check runs (HopperStand's took 103 s on a GPU), and
    the surrogate steps as the one first fitted."""
    from stablebptt.envs import adapter
    key = {"env": f"step {tmp_path}"}
    first = env_task(Cart("step"), horizon=5, diagnosis_key=key)
    for name in ("sample_for_diagnosis", "start_diagnosis", "start_checks"):
        monkeypatch.setattr(adapter, name, lambda *a, name=name, **k: pytest.fail(f"{name} ran although kept"))
    again = env_task(Cart("step"), horizon=5, diagnosis_key=key)
    assert "reward_smoothing" in again.resolved and again.resolved == first.resolved
    states = first.sample_initial_states(jax.random.PRNGKey(0), 8)
    for position in (-0.3, 0.05, 0.2):
        state, action = jax.tree.map(lambda a: a[0], states), jnp.array([position])
        np.testing.assert_array_equal(again.dynamics.step(state, action).reward, first.dynamics.step(state, action).reward)
    assert 0 < float(first.dynamics.step(state, action).reward) < 1  # the surrogate's, not the step of the written reward


def test_a_resumed_or_reopened_run_keeps_the_surrogate_temperatures_its_record_holds(tmp_path, capsys, monkeypatch):
    """A run's record holds its surrogate's temperatures; resuming it or reopening it makes the surrogate of
    those, not of a fit on this machine's samples (another backend's draw moves them): here the record's
    temperature, three times the fitted one, is the one the rebuilt step uses; the checks that chose and
    passed it are not run again."""
    from stablebptt.apps.trained import open_trained
    from stablebptt.envs import adapter, surrogate
    from stablebptt.storage import atomic_write, read_json
    run = tmp_path / "run"
    common = ["--train-size", "4", "--test-size", "4", "--batch", "4", "--no-progress"]
    assert train_command.main(["--env", "envs_for_tests:step_reward_cart", "--steps", "5", "--epochs", "1",
                               *common, "--out", str(run)]) == 0
    record = read_json(run / "config.json")
    resolved = record["resolved_task"]
    (place, fitted, where), = resolved["reward_smoothing_choices"]["temperatures"]
    assert fitted > 0 and f"(temperature {fitted:.3g})" in resolved["reward_smoothing"]
    # As if the run had begun on another machine whose samples gave three times the temperature.
    resolved["reward_smoothing_choices"]["temperatures"] = [[place, 3 * fitted, where]]
    resolved["reward_smoothing"] = resolved["reward_smoothing"].replace(f"{fitted:.3g}", f"{3 * fitted:.3g}")
    atomic_write(run / "config.json", json.dumps(record).encode())
    made, checked = [], []
    original = surrogate.smoothed_step
    monkeypatch.setattr(surrogate, "smoothed_step", lambda traced, choices: made.append(choices) or original(traced, choices))
    for check in ("start_diagnosis", "start_checks"):  # the checks that chose the surrogate are not run again
        monkeypatch.setattr(adapter, check, lambda *arguments, _check=getattr(adapter, check):
                            checked.append(_check) or _check(*arguments))
    notes = []
    reopened = open_trained(run, note=notes.append)
    assert notes == [] and reopened.task.resolved["reward_smoothing_choices"] == resolved["reward_smoothing_choices"]
    assert made[-1]["temperatures"] == [[place, 3 * fitted, where]]
    # A record in another release's words, its choices the same: rebuilt from them, nothing to note.
    worded = json.loads(json.dumps(record))
    worded["resolved_task"]["reward_smoothing"] = "smoothed 1 comparison, in older words"
    atomic_write(run / "config.json", json.dumps(worded).encode())
    assert open_trained(run, note=notes.append) and notes == []
    atomic_write(run / "config.json", json.dumps(record).encode())
    made.clear()
    assert train_command.main(["--resume", str(run), "--epochs", "2", "--no-progress"]) == 0
    assert made and all(choices["temperatures"] == [[place, 3 * fitted, where]] for choices in made)
    assert checked == []
    capsys.readouterr()
    # The step as written compares at the recorded place, and a step that no longer does is refused, named.
    fitted_anew = env_task(Cart("step"), horizon=5)
    assert fitted_anew.resolved["reward_smoothing_choices"]["temperatures"][0][1] == pytest.approx(fitted)
    with pytest.raises(EnvError, match=r"Cart: the run trained on a surrogate of the reward that smoothed nowhere\.py:1, "
                                       r"and the env's step no longer compares there"):
        env_task(Cart("step"), horizon=5, smoothing_choices={"temperatures": [[[999], 1.0, "nowhere.py:1"]], "exponents": []})
    with pytest.raises(EnvError, match="env_task's smoothing_choices must be"):
        env_task(Cart("step"), horizon=5, smoothing_choices="0.6")


def test_smoothing_always_widens_a_term_lost_beside_a_reward_that_has_a_slope_where_auto_leaves_it():
    """FishSwim's case: the action's cost gives the reward a slope at every sampled state, so the check finds
    it usable and auto trains it as written; its Gaussian of the position, far narrower than the positions met,
    adds a slope some 1e-12 of its own scale a little past the median sampled position. Always, the surrogate
    widens that Gaussian to the sampled positions."""
    as_written = env_task(Cart("faint"), horizon=5)
    assert as_written.resolved["reward_gradient"] == "usable" and "reward_smoothing" not in as_written.resolved
    always = env_task(Cart("faint"), horizon=5, smoothing="always")
    assert "smoothed 1 vanishing exponential of the reward widened" in always.summary
    # Not an underflow: the median sampled exponent lies between the smallest float's logarithm and epsilon's.
    (_, factor, _), = always.resolved["reward_smoothing_choices"]["exponents"]
    assert 1 / abs(np.log(np.finfo(np.float32).tiny)) < factor < 1 / abs(np.log(np.finfo(np.float32).eps))
    assert always.resolved["reward_gradient"] == "usable" and set(always.resolved["reward_smoothing_choices"]) == {
        "temperatures", "exponents"}
    state = jax.tree.map(lambda a: a[0], always.sample_initial_states(jax.random.PRNGKey(0), 1))
    at = lambda position: state._replace(data={**state.data, "position": position})  # noqa: E731
    action = jnp.array([0.0])  # the action's cost has no slope in the position: the Gaussian's alone is left
    slope = {name: float(jax.grad(lambda position: task.dynamics.step(at(position), action).reward)(jnp.float32(0.8)))
             for name, task in (("as written", as_written), ("always", always))}
    state = at(jnp.float32(0.8))
    assert abs(slope["as written"]) < 1e-9 and slope["always"] < -1e-2, slope  # towards the origin
    reached, smoothed = (task.dynamics.step(state, action) for task in (as_written, always))
    np.testing.assert_array_equal(np.asarray(reached.obs), np.asarray(smoothed.obs))  # the step's own state
    with pytest.raises(EnvError, match="smoothing always, but no comparison of the reward could be smoothed.*train it as written"):
        env_task(Cart(), horizon=5, smoothing="always")  # a smooth reward: nothing to make a surrogate of
    with pytest.raises(EnvError, match="smoothing always .* not with a surrogate_reward of your own"):
        env_task(Cart("faint"), horizon=5, smoothing="always", surrogate_reward=lambda state: state.reward)
