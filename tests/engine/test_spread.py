"""One run spread over several devices (``TrainConfig.devices``), on two CPU devices that XLA makes of
one host (a flag read when JAX starts: the check runs in a process of its own)."""
import os
import subprocess
import sys
import textwrap

from conftest import ROOT

PROGRAM = textwrap.dedent("""
    import dataclasses
    import jax, numpy as np
    import stablebptt as sb
    from stablebptt.engine.config import seed_array
    from stablebptt.engine.training import make_trainer
    from envs_for_tests import Cart

    assert len(jax.devices()) == 2
    task = sb.env_task(Cart(), horizon=6, discount=0.99, diagnose=False)
    config = sb.TrainConfig(epochs=2, batch=4, train_size=4, test_size=2, seeds=2, critic=True, eval_every="epoch")

    def trained(devices):
        trainer = make_trainer(task, dataclasses.replace(config, devices=devices))
        state = trainer.init(seed_array(config))
        arguments = (trainer.batches, trainer.train_states, trainer.test_states)
        program = trainer.epoch.lower(state, *arguments).compile().as_text()
        history = []
        for _ in range(config.epochs):
            state, metrics = trainer.epoch(state, *arguments)
            history.append(jax.device_get(metrics))
        return trainer, state, history, program

    alone, alone_state, alone_history, alone_program = trained(1)
    spread, spread_state, spread_history, spread_program = trained(2)
    assert alone.spread is None and spread.spread.count == 2
    # The envs split: each device rolls half of them and the parameters' gradient is summed across the
    # two (a collective no program of one device holds).
    assert "all-reduce" in spread_program and "all-reduce" not in alone_program
    # The states come back whole on both devices, as a checkpoint and the next epoch take them.
    for leaf in jax.tree.leaves(spread_state):
        assert len(leaf.sharding.device_set) == 2 and leaf.sharding.is_fully_replicated
    # The same training, to float32 rounding (the gradient's sum runs in another order).
    for one, two in zip(alone_history, spread_history):
        for name in ("batch_loss", "update_norm", "train_loss", "test_loss"):
            np.testing.assert_allclose(two[name], one[name], rtol=2e-4, err_msg=name)
    for one, two in zip(jax.tree.leaves(alone_state.params), jax.tree.leaves(spread_state.params)):
        np.testing.assert_allclose(two, one, rtol=2e-3, atol=1e-6)
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
