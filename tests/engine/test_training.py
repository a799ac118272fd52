"""The training engine and scripts/train.py: learning, seeds, resume, divergence, bad input."""
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
import pytest

from stablebptt import cli, storage, timing
from stablebptt.engine import fitting, per_update, training
from stablebptt.engine.config import TrainConfig, seed_array
from stablebptt.engine.metrics import COLUMNS, empty_rows
from stablebptt.engine.task import Task
from stablebptt.engine.training import make_trainer
from stablebptt.errors import InputError
from stablebptt.flows.dynamics import Dynamics, Plan
from stablebptt.runs import epochs, run_folder
from stablebptt.tasks import repulsion

from conftest import ROOT
from held_compile import CHECKPOINTED, held_command, release, wait_for

SMALL = TrainConfig(epochs=3, train_size=32, test_size=32, batch=8, mode="C")
TRAIN = [sys.executable, str(ROOT / "scripts" / "train.py")]
SMALL_CLI = ["--task", "repulsion", "--train-size", "32", "--test-size", "32", "--no-progress"]


@pytest.fixture(scope="module")
def task():
    return repulsion.make(repulsion.Config(rc=0.01))


def run_epochs(trainer, config, epochs):
    state = trainer.init(seed_array(config))
    history = []
    for _ in range(epochs):
        state, metrics = trainer.epoch(state, trainer.batches, trainer.train_states, trainer.test_states)
        history.append(jax.device_get(metrics))
    return state, history


@pytest.fixture(scope="module")
def three_seeds(task):
    config = replace(SMALL, seeds=3, seed=7, seed_batching="map")
    return run_epochs(make_trainer(task, config), config, 3)


def test_training_lowers_the_test_loss(three_seeds):
    _, history = three_seeds
    assert np.all(history[-1]["test_loss"] < history[0]["test_loss"])
    assert np.all([h["finite"] for h in history])
    assert np.all(np.abs(history[-1]["cosine"]) <= 1.0)


def scan_unrolls(jaxpr) -> set:
    """The ``unroll`` of every scan in a jaxpr, nested ones included."""
    found = set()
    for equation in jaxpr.eqns:
        if equation.primitive.name == "scan":
            found.add(equation.params["unroll"])
        for sub in jax.extend.core.jaxprs_in_params(equation.params):
            found |= scan_unrolls(sub)
    return found


@pytest.mark.parametrize("grid", [False, True])
def test_unroll_reaches_every_rollout_loop_and_leaves_the_numbers(task, grid):
    """--unroll is applied to the epoch's dynamics, in a single run and a grid's per-cell ones."""
    config = replace(SMALL, epochs=1, seeds=1, unroll=3)
    trainer, plain = make_trainer(task, config, grid=grid), make_trainer(task, replace(config, unroll=1), grid=grid)
    state = trainer.init(seed_array(config))
    values = (jnp.array([0.01]),) if grid else ()
    arguments = (state, *values, trainer.batches, trainer.train_states, trainer.test_states)
    # trace, not make_jaxpr: on a GPU the epoch is a program with XLA options, which JAX refuses nested.
    assert 3 in scan_unrolls(trainer.epoch.trace(*arguments).jaxpr.jaxpr)
    assert 3 not in scan_unrolls(plain.epoch.trace(*arguments).jaxpr.jaxpr)
    unrolled, rolled = trainer.epoch(*arguments)[1], plain.epoch(*arguments)[1]
    for name in ("batch_loss", "test_loss", "update_norm"):
        np.testing.assert_allclose(unrolled[name], rolled[name], rtol=1e-5)


def test_the_run_plan_completes_the_task_plan_and_a_plan_a_user_gives_is_taken_whole(task):
    """Trainer.plan: the task's own plan, completed by the run (unroll, memory, one step's size); a
    plan passed to make_trainer is used as given, its defaults too (they override the task's hints)."""
    config = replace(SMALL, epochs=1, unroll=3)
    hinted = replace(task, plan=Plan(policy_gradient="per-step"))
    chosen = make_trainer(hinted, config).plan
    assert (chosen.policy_gradient, chosen.unroll, chosen.step_derivative) == ("per-step", 3, "reverse")
    assert chosen.jacobian_per_input and not chosen.rematerialize  # a small step whose path fits in memory
    given = Plan(unroll=2, step_derivative="forward")
    assert make_trainer(hinted, config, plan=given).plan is given  # policy_gradient "batched", the default
    changed = replace(chosen, step_derivative="forward")
    assert make_trainer(hinted, config, plan=changed).plan is changed
    one_pass = replace(task, plan=Plan(jacobian_per_input=False))  # a task may ask for one Jacobian pass
    assert not make_trainer(one_pass, config).plan.jacobian_per_input


class StaticData:
    """A pytree node whose static data is a NumPy array, printed by address (as MJX wraps such data)."""

    def __init__(self, values):
        self.values = values

    def __repr__(self):
        return f"<StaticData at {hex(id(self))}>"


jax.tree_util.register_pytree_node(StaticData, lambda node: ((0,), StaticData(node.values)),
                                   lambda data, children: StaticData(data.values))


def test_a_kept_traced_epoch_computes_what_the_traced_one_does_and_a_changed_key_traces_anew(task, tmp_path, monkeypatch):
    """program_store: the first compile traces, exports and keeps the epoch; the second loads it without
    tracing and gives the same numbers bit for bit; a damaged file is traced anew; the key follows
    everything it is given (the task's inputs, the arguments' shapes)."""
    from stablebptt.engine import program_store
    config = replace(SMALL, epochs=1, epoch_program="per-update")  # a PerUpdateEpoch: three programs kept
    trainer = make_trainer(task, config)
    arguments = (trainer.init(seed_array(config)), trainer.batches, trainer.train_states, trainer.test_states)
    key = {"task": "repulsion", "inputs": {}}
    plain = jax.device_get(trainer.epoch.lower(*arguments).compile()(*arguments))
    first, _ = program_store.compile_epoch(trainer.epoch, arguments, key, tmp_path, trainer.compiler_options)
    kept = sorted((tmp_path / program_store.FOLDER).iterdir())
    assert len(kept) == 3
    monkeypatch.setattr(program_store, "_traced", lambda *a: pytest.fail("traced although kept"))
    second, _ = program_store.compile_epoch(trainer.epoch, arguments, key, tmp_path, trainer.compiler_options)
    for result in (first, second):
        for ours, theirs in zip(jax.tree.leaves(jax.device_get(result(*arguments))), jax.tree.leaves(plain)):
            np.testing.assert_array_equal(ours, theirs)
    monkeypatch.undo()
    kept[0].write_bytes(b"damaged")
    program_store.compile_epoch(trainer.epoch, arguments, key, tmp_path, trainer.compiler_options)
    assert kept[0].read_bytes() != b"damaged"  # replaced
    # Static node data shown by address (as MJX's contact data is) keys the same in every process.
    same = [jax.tree.structure(jax.tree_util.tree_unflatten(jax.tree.structure(StaticData(np.arange(3))), [0]))
            for _ in range(2)]
    assert str(same[0]) != str(same[1]) and program_store._tree_digest(same[0]) == program_store._tree_digest(same[1])
    other = program_store.program_key({**key, "inputs": {"model": "0" * 64}}, arguments)
    assert other != program_store.program_key(key, arguments) != program_store.program_key(key, arguments[:2])
    # The set-up's traced measurements are kept the same way (in the session's compile cache here).
    calls = []
    for _ in range(2):
        assert program_store.kept_answer({**key, "test": str(tmp_path)}, "bytes", lambda: calls.append(1) or 58415) == 58415
    assert len(calls) == 1
    kept_key = {**key, "test": str(tmp_path)}
    fields = lambda plan: vars(plan)  # noqa: E731 - Plan compares by identity
    first = make_trainer(task, config, keep=kept_key)
    monkeypatch.setattr(training, "step_size", lambda *a: pytest.fail("the step's size traced although kept"))
    assert fields(first.plan) == fields(make_trainer(task, config, keep=kept_key).plan) == fields(trainer.plan)
    monkeypatch.undo()
    from stablebptt.tasks import env, mjcf
    assert env.program_inputs(env.Config(env="my_lab.envs:arm")) is None  # code outside the library: not kept
    models = [tmp_path / f"{name}.xml" for name in ("a", "b")]
    for path, size in zip(models, (0.1, 0.2)):
        path.write_text(f'<mujoco><worldbody><body><joint type="hinge"/><geom size="{size}"/></body></worldbody></mujoco>')
    assert len({mjcf.program_inputs(mjcf.Config(model=str(path)))["model"] for path in models}) == 2


def test_mapped_seeds_equal_the_same_seeds_trained_alone(task, three_seeds):
    state, history = three_seeds
    config = replace(SMALL, seeds=1, seed=8)  # the middle seed of 7, 8, 9
    alone_state, alone_history = run_epochs(make_trainer(task, config), config, 3)
    for together, alone in zip(history, alone_history):
        for name in ("batch_loss", "train_loss", "test_loss", "update_norm", "cosine"):
            assert together[name][1] == alone[name][0], name
    for together, alone in zip(jax.tree.leaves(state.params), jax.tree.leaves(alone_state.params)):
        np.testing.assert_array_equal(together[1], alone[0])


def test_vmapped_seeds_agree_with_mapped_seeds_to_rounding(task, three_seeds):
    _, history = three_seeds
    config = replace(SMALL, seeds=3, seed=7, seed_batching="vmap")
    _, vmapped = run_epochs(make_trainer(task, config), config, 1)
    np.testing.assert_allclose(vmapped[0]["test_loss"], history[0]["test_loss"], rtol=1e-5)


def test_mode_r_without_the_cosine_follows_the_same_gradient_as_with_it(task):
    """--no-cosine drops g_M from mode R's backward pass (the locomotion recipe's cheetah trains so):
    the update it takes is R's with the cosine on, to rounding, and only the cosine goes unlogged."""
    config = replace(SMALL, mode="R", epochs=2)
    (with_cosine, logged), (without, unlogged) = (
        run_epochs(make_trainer(task, replace(config, cosine=cosine)), config, 2) for cosine in (True, False))
    for a, b in zip(jax.tree.leaves(with_cosine.params), jax.tree.leaves(without.params)):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)
    assert np.all(np.isfinite(logged[-1]["cosine"])) and np.all(np.isnan(unlogged[-1]["cosine"]))


def test_an_epoch_compiled_per_update_trains_as_the_epoch_compiled_whole(task, three_seeds, tmp_path):
    """The same updates and metrics from separately compiled programs (large scenes) as from one."""
    state, history = three_seeds
    config = replace(SMALL, seeds=3, seed=7, epoch_program="per-update", seed_batching="map")
    trainer = make_trainer(task, config)
    assert type(trainer.epoch).__name__ == "PerUpdateEpoch"
    # Through the epoch loop of runs, which compiles ahead before timing.
    outcome = epochs.train_epochs(trainer, config, tmp_path, trainer.init(seed_array(config)), 0, empty_rows(),
                                np.asarray(seed_array(config)))
    assert outcome.status == "complete"
    for name in ("batch_loss", "train_loss", "test_loss", "update_norm", "cosine"):
        per_update = outcome.rows[:, COLUMNS.index(name)].reshape(3, 3)  # [epoch, seed]
        np.testing.assert_allclose(per_update, [h[name] for h in history], rtol=1e-5, err_msg=name)
    for whole, split in zip(jax.tree.leaves(state.params), jax.tree.leaves(outcome.state.params)):
        np.testing.assert_allclose(split, whole, rtol=1e-4, atol=1e-7)


def test_auto_compiles_a_step_that_solves_apart_on_several_cores_and_a_plain_step_whole(task, monkeypatch):
    """``epoch_program="auto"``: a step holding a loop of data-dependent length (a constraint solver's)
    makes the epoch three programs where the CPU compiles them side by side, one program where it
    cannot; a step without such a loop stays one program."""
    step = task.dynamics.step

    def solving_step(state, control):  # the step, then a loop that stops after one pass, as a solver converges
        return jax.lax.while_loop(lambda carry: carry[1] < 1, lambda carry: (carry[0], carry[1] + 1),
                                  (step(state, control), 0))[0]

    d = task.dynamics
    solving = replace(task, dynamics=Dynamics(step=solving_step, policy=d.policy, loss=d.loss, horizon=d.horizon))
    config = replace(SMALL, epochs=1)
    side_by_side = jax.default_backend() == "cpu" and timing.usable_cores() > 1
    split = lambda trainer: isinstance(trainer.epoch, per_update.PerUpdateEpoch)  # noqa: E731
    assert split(make_trainer(solving, config)) == side_by_side
    assert not split(make_trainer(task, config))
    monkeypatch.setattr(per_update, "usable_cores", lambda: 1)
    assert not split(make_trainer(solving, config))


def test_runs_are_bit_reproducible(task, three_seeds):
    config = replace(SMALL, seeds=3, seed=7, seed_batching="map")
    _, again = run_epochs(make_trainer(task, config), config, 3)
    for first, second in zip(three_seeds[1], again):
        for name in ("test_loss", "update_norm"):
            np.testing.assert_array_equal(first[name], second[name])


def exploding_task():
    """x_{t+1} = x + u, linear policy, a loss unbounded below: Adam walks p up by ~lr per update
    and its squared gradient, ~p^14, overflows float32 after a few epochs."""
    return Task(
        name="exploding",
        dynamics=Dynamics(step=lambda x, u: x + u, policy=lambda p, x: p * x,
                          loss=lambda states, controls: -jnp.sum(states[-1] ** 2), horizon=4),
        init_params=lambda key, zero_output: jnp.array([0.5]),
        sample_initial_states=lambda key, n: jax.random.uniform(key, (n, 1), minval=0.5, maxval=1.0),
    )


def test_divergence_stops_with_the_epoch_and_keeps_the_last_good_checkpoint(tmp_path):
    config = TrainConfig(epochs=50, train_size=16, test_size=8, batch=8, lr=100.0, clip="none", mode="R")
    trainer = make_trainer(exploding_task(), config)
    state = trainer.init(seed_array(config))
    outcome = epochs.train_epochs(trainer, config, tmp_path, state, 0, empty_rows(), np.asarray(seed_array(config)))
    assert outcome.status == "diverged"
    bad_epoch = outcome.epoch + 1
    assert f"epoch {bad_epoch}" in outcome.message
    epoch, saved, rows = run_folder.load_checkpoint(tmp_path, state)
    assert epoch == outcome.epoch and bad_epoch > 1
    assert np.all(np.isfinite(rows[:, 2:7])) and rows[:, 0].max() == epoch
    assert all(np.all(np.isfinite(leaf)) for leaf in jax.tree.leaves(saved))


def one_seed_exploding_task(modulus: int = 2):
    """The exploding task, its policy scaled by the seed key's last word modulo ``modulus``: at 2, the
    odd seeds explode and the even ones' policy is zero and their loss finite (the scale, the second
    parameter, has a zero gradient and so never moves); at 3, seeds of scale 2 explode sooner than 1."""
    def policy(p, x):
        return jax.lax.stop_gradient(p[1]) * p[0] * x

    return Task(
        name="one-exploding",
        dynamics=Dynamics(step=lambda x, u: x + u, policy=policy,
                          loss=lambda states, controls: -jnp.sum(states[-1] ** 2), horizon=4),
        init_params=lambda key, zero_output: jnp.stack([0.5, (jnp.asarray(key)[-1] % modulus).astype(jnp.float32)]),
        sample_initial_states=lambda key, n: jax.random.uniform(key, (n, 1), minval=0.5, maxval=1.0),
    )


def test_a_seed_that_diverges_alone_stops_with_its_last_good_state_and_the_other_trains_on_across_a_resume(
        tmp_path):
    config = TrainConfig(epochs=40, train_size=16, test_size=8, batch=8, lr=100.0, clip="none", mode="R", seeds=2)
    trainer = make_trainer(one_seed_exploding_task(), config)
    seeds = np.asarray(seed_array(config))  # 42 trains finite, 43 explodes
    initial = trainer.init(seed_array(config))
    notices = {}
    first = epochs.train_epochs(trainer, replace(config, epochs=30), tmp_path, initial, 0, empty_rows(), seeds,
                                on_epoch=lambda epoch, metrics: notices.update({epoch: metrics["notice"]}))
    assert first.status == "complete" and first.epoch == 30
    said = {epoch: line for epoch, line in notices.items() if line}
    assert len(said) == 1, said
    (stopped, line), = said.items()
    assert stopped > 1  # an epoch of numbers before it
    assert f"at epoch {stopped} (seed 43): it stops with the parameters of epoch {stopped - 1}" in line, line
    assert "non-finite" in line and "the other 1 train on" in line, line

    def rows_of(rows, seed):
        return rows[rows[:, 1] == seed]

    def numbers(rows):  # the metric columns that every trained epoch fills
        return rows[:, [COLUMNS.index(name) for name in ("batch_loss", "update_norm")]]

    # Seed 43 kept numbers up to the epoch before it stopped and none after; seed 42 all of them.
    assert np.all(np.isfinite(numbers(rows_of(first.rows, 43)[:stopped - 1])))
    assert np.all(np.isnan(numbers(rows_of(first.rows, 43)[stopped - 1:])))
    assert np.all(np.isfinite(numbers(rows_of(first.rows, 42))))
    params = first.state.params
    assert np.all(np.isfinite(np.asarray(params)))
    # Its state is the one it had after epoch stopped - 1: a run of that many epochs ends there.
    (tmp_path / "before").mkdir()
    before = epochs.train_epochs(trainer, replace(config, epochs=stopped - 1), tmp_path / "before", initial, 0,
                                 empty_rows(), seeds)
    for kept, reference in zip(jax.tree.leaves(first.state), jax.tree.leaves(before.state)):
        np.testing.assert_array_equal(np.asarray(kept)[1], np.asarray(reference)[1])

    # A resume from the checkpoint knows seed 43 stopped: it stays put and says nothing again.
    epoch, saved, rows = run_folder.load_checkpoint(tmp_path, initial)
    notices.clear()
    resumed = epochs.train_epochs(trainer, config, tmp_path, saved, epoch, rows, seeds,
                                  on_epoch=lambda epoch, metrics: notices.update({epoch: metrics["notice"]}))
    assert resumed.status == "complete" and not any(notices.values()), notices
    assert np.all(np.isnan(numbers(rows_of(resumed.rows, 43)[stopped - 1:])))
    assert np.all(np.isfinite(numbers(rows_of(resumed.rows, 42)))) and len(rows_of(resumed.rows, 42)) == 40
    for kept, reference in zip(jax.tree.leaves(resumed.state), jax.tree.leaves(before.state)):
        np.testing.assert_array_equal(np.asarray(kept)[1], np.asarray(reference)[1])


def test_seeds_that_fail_in_turn_stop_apart_and_the_last_ends_the_run_named_alone(tmp_path):
    config = TrainConfig(epochs=60, train_size=16, test_size=8, batch=8, lr=100.0, clip="none", mode="R", seeds=2,
                         seed=43)
    trainer = make_trainer(one_seed_exploding_task(modulus=3), config)  # seed 44 (scale 2) explodes first, 43 later
    seeds = np.asarray(seed_array(config))
    notices = {}
    outcome = epochs.train_epochs(trainer, config, tmp_path, trainer.init(seed_array(config)), 0, empty_rows(), seeds,
                                  on_epoch=lambda epoch, metrics: notices.update({epoch: metrics["notice"]}))
    said = [line for line in notices.values() if line]
    assert len(said) == 1 and "(seed 44): it stops" in said[0], said
    assert outcome.status == "diverged" and "(seed 43); stopped" in outcome.message, outcome.message


def test_from_python_a_seed_that_stops_apart_is_named_in_a_warning_and_every_seed_failing_raises():
    config = TrainConfig(epochs=30, train_size=16, test_size=8, batch=8, lr=100.0, clip="none", mode="R", seeds=2)
    with pytest.warns(fitting.NonFiniteFlowWarning, match=r"\(seed 43\): it stops"):
        trained = fitting.train(one_seed_exploding_task(), config)
    test_loss = trained.metrics["test_loss"]
    assert np.isfinite(test_loss[-1, 0]) and np.isnan(test_loss[-1, 1])
    assert trained.test_loss[-1] == test_loss[-1, 0]  # the mean over the seeds scored
    with pytest.raises(fitting.TrainingDiverged, match="non-finite"):
        fitting.train(exploding_task(), replace(config, epochs=50, seed=43))


def nan_through_the_policy_input_task():
    """g_R is NaN (the policy's input passes a square root at 0, times 0) while g_M, the loss and
    mode C's sign-agreement update stay finite: C's update is a finite zero that hides the NaN."""
    return Task(
        name="hidden-nan",
        dynamics=Dynamics(step=lambda x, u: x + u, policy=lambda p, x: p * x + 0.0 * jnp.sqrt(jnp.abs(x - x)),
                          loss=lambda states, controls: jnp.sum((states[-1] - 2.0) ** 2), horizon=3),
        init_params=lambda key, zero_output: jnp.array([0.5]),
        sample_initial_states=lambda key, n: jax.random.uniform(key, (n, 1), minval=0.5, maxval=1.0),
    )


def test_a_non_finite_gradient_of_any_flow_stops_training_even_when_the_update_is_finite(tmp_path):
    config = TrainConfig(epochs=3, train_size=8, test_size=8, batch=8, mode="C")
    trainer = make_trainer(nan_through_the_policy_input_task(), config)
    state = trainer.init(seed_array(config))
    _, metrics = trainer.epoch(state, trainer.batches, trainer.train_states, trainer.test_states)
    assert np.isfinite(metrics["update_norm"][0]) and np.isfinite(metrics["test_loss"][0])  # nothing else shows it
    outcome = epochs.train_epochs(trainer, config, tmp_path, state, 0, empty_rows(), np.asarray(seed_array(config)))
    assert outcome.status == "diverged" and outcome.epoch == 0
    assert "gradient of flow R" in outcome.message and "flow M" not in outcome.message, outcome.message


def test_with_nonfinite_flows_zero_mode_c_trains_on_through_a_nan_of_g_r_and_says_so_every_epoch(tmp_path):
    config = TrainConfig(epochs=2, train_size=8, test_size=8, batch=8, mode="C", seeds=2, nonfinite_flows="zero")
    trainer = make_trainer(nan_through_the_policy_input_task(), config)
    state = trainer.init(seed_array(config))
    notices = []
    outcome = epochs.train_epochs(trainer, config, tmp_path, state, 0, empty_rows(), np.asarray(seed_array(config)),
                                  on_epoch=lambda epoch, metrics: notices.append(metrics["notice"]))
    assert outcome.status == "complete" and outcome.epoch == 2, outcome.message
    # g_R is NaN in every element: C's sign agreement zeroes the whole update, so nothing moved.
    assert np.array_equal(np.asarray(outcome.state.params), np.asarray(state.params))
    assert len(notices) == 2 and all("gradient of flow R" in notice and "flow M" not in notice and
                                     "seed 42: 1" in notice and "seed 43: 1" in notice for notice in notices), notices


def test_the_python_api_warns_of_a_flow_left_at_zero_and_refuses_zero_outside_mode_c():
    config = TrainConfig(epochs=1, train_size=8, test_size=8, batch=8, mode="C", nonfinite_flows="zero")
    with pytest.warns(fitting.NonFiniteFlowWarning, match="gradient of flow R non-finite"):
        fitting.train(nan_through_the_policy_input_task(), config)
    with pytest.raises(InputError, match="nonfinite_flows"):
        fitting.train(nan_through_the_policy_input_task(), replace(config, mode="R"))


def test_the_progress_line_names_a_notice_and_stays_quiet_without_one(capsys):
    progress = cli.EpochProgress(time.perf_counter(), 2, 0, 1, "task", disable=True)
    progress.on_compiled(1.0)
    progress.on_epoch(1, {"test_loss": np.array([1.0]), "seconds": 0.1, "notice": ""})
    progress.on_epoch(2, {"test_loss": np.array([1.0]), "seconds": 0.1, "notice": "gradient of flow R non-finite"})
    progress.close()
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert lines == ["epoch 2: gradient of flow R non-finite"], lines


def train_cli(*args, **kwargs):
    return subprocess.run(TRAIN + list(args), capture_output=True, text=True, cwd=kwargs.pop("cwd", ROOT), **kwargs)


def metrics_without_time(run_dir):
    return [{k: v for k, v in row.items() if k != "seconds"} for row in run_folder.read_metrics(run_dir / run_folder.METRICS_FILE)]


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("runs") / "whole"
    result = train_cli(*SMALL_CLI, "--epochs", "4", "--out", str(run_dir))
    assert result.returncode == 0, result.stderr
    return run_dir


def test_a_run_directory_holds_config_metrics_params_and_checkpoint(uninterrupted):
    for name in (run_folder.CONFIG_FILE, run_folder.METRICS_FILE, run_folder.PARAMS_FILE, run_folder.CHECKPOINT_FILE):
        assert (uninterrupted / name).is_file(), name
    rows = run_folder.read_metrics(uninterrupted / run_folder.METRICS_FILE)
    assert [row["epoch"] for row in rows] == [1, 2, 3, 4]
    assert set(COLUMNS) <= set(rows[0])
    assert storage.read_json(uninterrupted / run_folder.CONFIG_FILE)["train"]["epochs"] == 4


def test_resume_after_sigkill_ends_with_the_uninterrupted_metrics(uninterrupted, tmp_path):
    # Killed once its first checkpoint is written, before its metrics and its second epoch (held there:
    # tests/held_compile.py); the checkpoint holds the metrics the resume writes again.
    run_dir, hold = tmp_path / "killed", tmp_path / "hold"
    hold.mkdir()
    release(hold)  # its compile is not held
    process = subprocess.Popen(held_command(hold, *TRAIN[1:], *SMALL_CLI, "--epochs", "4", "--out", str(run_dir),
                                            at_checkpoint=True), cwd=ROOT, stdout=subprocess.DEVNULL,
                               stderr=subprocess.PIPE, text=True)
    wait_for(hold / CHECKPOINTED, process)
    process.send_signal(signal.SIGKILL)
    assert process.wait() == -signal.SIGKILL
    with np.load(run_dir / run_folder.CHECKPOINT_FILE) as checkpoint:
        assert int(checkpoint["epoch"]) == 1
    result = train_cli("--resume", str(run_dir), "--no-progress")
    assert result.returncode == 0, result.stderr
    assert metrics_without_time(run_dir) == metrics_without_time(uninterrupted)


def test_resume_extends_a_finished_run_exactly(uninterrupted, tmp_path):
    run_dir = tmp_path / "extended"
    assert train_cli(*SMALL_CLI, "--epochs", "2", "--out", str(run_dir)).returncode == 0
    result = train_cli("--resume", str(run_dir), "--epochs", "4", "--no-progress")
    assert result.returncode == 0, result.stderr
    assert metrics_without_time(run_dir) == metrics_without_time(uninterrupted)


def test_sigint_stops_cleanly_after_saving(tmp_path):
    run_dir = tmp_path / "interrupted"
    process = subprocess.Popen(TRAIN + SMALL_CLI + ["--epochs", "500", "--out", str(run_dir)], cwd=ROOT,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not (run_dir / run_folder.CHECKPOINT_FILE).exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    process.send_signal(signal.SIGINT)
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == 130 and "--resume" in stderr and "Traceback" not in stderr
    epoch, _, rows = run_folder.load_checkpoint(run_dir, make_trainer(repulsion.make(repulsion.Config()), replace(
        SMALL, train_size=32, test_size=32)).init(seed_array(SMALL)))
    assert 1 <= epoch < 500 and rows[:, 0].max() == epoch


def test_an_existing_or_unwritable_out_is_refused_and_left_untouched(uninterrupted, tmp_path):
    before = {p.name: p.stat().st_mtime_ns for p in uninterrupted.iterdir()}
    blocker = tmp_path / "a-file"
    blocker.write_text("not a directory")
    for out in (uninterrupted, blocker / "run"):
        result = train_cli(*SMALL_CLI, "--epochs", "1", "--out", str(out))
        assert result.returncode == 2 and len(result.stderr.strip().splitlines()) == 1, result.stderr
    assert {p.name: p.stat().st_mtime_ns for p in uninterrupted.iterdir()} == before


def test_compiled_programs_are_kept_between_runs_unless_turned_off(tmp_path):
    """The command line's persistent compilation cache: filled by a run, left empty with --no-compile-cache."""
    runs = {}
    # XLA's optimisations on, as a user's runs have them: the tests' unoptimised programs compile quicker
    # than they load, and a start records only the compile the cache saved.
    optimised = os.environ["XLA_FLAGS"].replace("--xla_backend_optimization_level=0", "")
    for flag, cache in (("--compile-cache", tmp_path / "kept"), ("--no-compile-cache", tmp_path / "off")):
        env = {**os.environ, "STABLEBPTT_COMPILE_CACHE": str(cache), "XLA_FLAGS": optimised}
        # Side by side: the two runs share nothing but the machine.
        runs[flag, cache] = subprocess.Popen(TRAIN + SMALL_CLI + ["--epochs", "1", "--out", str(tmp_path / flag), flag],
                                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path, env=env)
    for (flag, cache), process in runs.items():
        _, stderr = process.communicate()
        assert process.returncode == 0, stderr
        entries = list(cache.glob("*")) if cache.exists() else []
        assert bool(entries) == (flag == "--compile-cache"), (flag, entries)
        # Each start records the compile the cache saved it: none in an empty cache or without one.
        start, = storage.read_json(tmp_path / flag / run_folder.STARTUP_FILE)
        assert start["compile_seconds_from_cache"] == 0.0, start
    # The same command again in the kept cache loads what the first run compiled: its start says so.
    warm = subprocess.run(TRAIN + SMALL_CLI + ["--epochs", "1", "--out", str(tmp_path / "again")], capture_output=True,
                          text=True, cwd=tmp_path, env={**os.environ, "STABLEBPTT_COMPILE_CACHE": str(tmp_path / "kept"), "XLA_FLAGS": optimised})
    assert warm.returncode == 0, warm.stderr
    start, = storage.read_json(tmp_path / "again" / run_folder.STARTUP_FILE)
    assert start["compile_seconds_from_cache"] > 0, (start, warm.stderr)
    assert start["host"] == timing.machine()  # the host named, so that starts on different hosts are told apart


def test_a_fresh_state_still_to_be_made_is_made_once_the_epoch_has_compiled(task):
    """A start that no check compiled the epoch for compiles it before init runs, init's programs beside it:
    the state is the one init makes at once, and a state given is trained from as it is."""
    from stablebptt.engine import starting
    prepared, order = starting.prepare(task, SMALL), []

    class Counted:  # the lowered epoch, its compile noted
        def compile(self):
            order.append("compile")
            return prepared.lowered.lowered.compile()

    lowered = prepared.lowered._replace(lowered=Counted())
    fresh = lambda: order.append("init") or prepared.trainer.init(seed_array(SMALL))  # noqa: E731
    epoch_fn, _, state, made = starting.compiled_then_made(prepared.trainer, fresh, lowered)
    assert order == ["compile", "init"] and made is not None and starting.lowered_for(lowered, state)
    for made_later, at_once in zip(jax.tree.leaves(state), jax.tree.leaves(prepared.trainer.init(seed_array(SMALL)))):
        np.testing.assert_array_equal(made_later, at_once)
    _, _, given, none = starting.compiled_then_made(prepared.trainer, state, lowered._replace(compiled=epoch_fn))
    assert given is state and none is None and order == ["compile", "init"]  # compiled already: not again
