"""One run spread over several devices (``TrainConfig.devices``), on two CPU devices that XLA makes of
one host (a flag read when JAX starts: the check runs in a process of its own)."""
import os
import subprocess
import sys
import textwrap

from conftest import ROOT

PROGRAM = textwrap.dedent("""
    import dataclasses, re
    import jax, numpy as np
    import stablebptt as sb
    from stablebptt.engine.config import seed_array
    from stablebptt.engine.training import make_trainer
    from envs_for_tests import Cart

    assert len(jax.devices()) == 2
    task = sb.env_task(Cart(), horizon=6, discount=0.99, diagnose=False)
    # 2 seeds of 6 carried envs, 2 observations each: f32[2,6,2] whole, f32[2,3,2] on each of two devices.
    # The evaluations run apart from the epoch (eval_every's default), so the epoch's program is the updates'.
    config = sb.TrainConfig(epochs=2, batch=6, train_size=4, test_size=2, seeds=2, critic=True)
    HALF, WHOLE = "f32[2,3,2]", "f32[2,6,2]"

    def trained(devices, **changes):
        trainer = make_trainer(task, dataclasses.replace(config, devices=devices, **changes))
        state = trainer.init(seed_array(config))
        arguments = (trainer.batches, trainer.train_states, trainer.test_states)
        program = trainer.epoch.lower(state, *arguments).compile().as_text()
        history = []
        for _ in range(config.epochs):
            state, metrics = trainer.epoch(trainer.fresh(state), *arguments)
            history.append(jax.device_get(metrics))
        evaluated = jax.device_get(trainer.evaluation(state.params, trainer.train_states, trainer.test_states))
        return trainer, state, history, evaluated, program

    alone = trained(1)
    assert alone[0].spread is None and HALF not in alone[4] and WHOLE in alone[4]
    for changes in ({}, {"seed_batching": "map"}):
        spread, state, history, evaluated, program = trained(2, **changes)
        assert spread.spread.count == 2
        # Each device rolls half of the carried envs, and the gradient of the two halves is summed.
        assert HALF in program and "all-reduce" in program, changes
        # The states come back whole on both devices, as a checkpoint and the next epoch take them.
        for leaf in jax.tree.leaves(state):
            assert len(leaf.sharding.device_set) == 2 and leaf.sharding.is_fully_replicated
        # The same training, to float32 rounding (the gradient's sum runs in another order).
        for one, two in zip(alone[2], history):
            for name in ("batch_loss", "update_norm"):
                np.testing.assert_allclose(two[name], one[name], rtol=2e-4, err_msg=f"{name} {changes}")
        for name in ("train_loss", "test_loss"):
            np.testing.assert_allclose(evaluated[name], alone[3][name], rtol=2e-4, err_msg=f"{name} {changes}")
        for one, two in zip(jax.tree.leaves(alone[1].params), jax.tree.leaves(state.params)):
            np.testing.assert_allclose(two, one, rtol=2e-3, atol=1e-6)
    # A memory plan that computes the step Jacobians in chunks (forward mode: 1-pole cart-pole, 100 steps x 4
    # states, chunks of 80) splits each chunk too: 40 Jacobians of 4 x 4 at once on each device, never 80.
    from stablebptt import tasks
    mjcf = tasks.load("mjcf")
    cartpole = mjcf.make(mjcf.Config(poles=1))
    fixed = sb.TrainConfig(epochs=1, batch=4, train_size=8, test_size=6, devices=2)
    chunked = make_trainer(cartpole, fixed, plan=dataclasses.replace(cartpole.plan, step_derivative="forward",
                                                                   jacobian_chunk=80))
    state = chunked.init(seed_array(fixed))
    program = chunked.epoch.lower(state, chunked.batches, chunked.train_states, chunked.test_states).compile().as_text()
    assert "f32[40,4,4]" in program and "f32[80,4,4]" not in program
    try:
        make_trainer(task, dataclasses.replace(config, batch=3, devices=0))
    except sb.InputError as error:
        assert str(error) == "TrainConfig.devices: TrainConfig.batch (3) must split evenly over the 2 devices: make it a multiple of 2", error
    else:
        raise AssertionError("a batch of 3 was split over 2 devices")
    print("ok")
""")


def test_a_run_spread_over_two_devices_splits_its_envs_and_trains_as_on_one():
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=2".strip()
    env = dict(os.environ, XLA_FLAGS=flags, PYTHONPATH=os.pathsep.join([str(ROOT), str(ROOT / "tests")]))
    result = subprocess.run([sys.executable, "-c", PROGRAM], env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.endswith("ok\n"), result.stdout


def test_a_spread_run_resumes_on_one_device_where_told_and_says_so_where_not(tmp_path):
    """The devices a run spans change its numbers only in their rounding: ``--resume`` may change them,
    and a run resumed where fewer devices are seen than it recorded is refused in one line naming the option."""
    train = [sys.executable, str(ROOT / "scripts" / "train.py")]
    small = ["--env", "envs_for_tests:make_cart", "--batch", "4", "--steps", "4", "--train-size", "2", "--test-size",
             "2", "--no-progress"]
    plain = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(ROOT / "tests")]))
    two = dict(plain, XLA_FLAGS=f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=2".strip())
    run = tmp_path / "run"
    first = subprocess.run(train + small + ["--devices", "2", "--epochs", "1", "--out", str(run)], env=two,
                           capture_output=True, text=True, timeout=300)
    assert first.returncode == 0, first.stderr[-2000:]
    assert "split over 2 devices" in first.stdout, first.stdout
    refused = subprocess.run(train + ["--resume", str(run), "--epochs", "2"], env=plain, capture_output=True, text=True,
                             timeout=300)
    errors = [line for line in refused.stderr.splitlines() if line.startswith("error")]  # after a note on the user's env
    assert refused.returncode == 2 and len(errors) == 1 and "--devices 2: JAX sees 1" in errors[0], refused.stderr
    assert "Traceback" not in refused.stderr
    resumed = subprocess.run(train + ["--resume", str(run), "--epochs", "2", "--devices", "1"], env=plain,
                             capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert "done: make_cart, mode C, 2 epochs" in resumed.stdout, resumed.stdout
