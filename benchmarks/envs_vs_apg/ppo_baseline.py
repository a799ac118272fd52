"""Brax PPO on MuJoCo Playground envs under a wall-clock budget, with Playground's own hyperparameters.

Runs `brax.training.agents.ppo.train` with `mujoco_playground.config.dm_control_suite_params.brax_ppo_config`
for the env (its tuned DeepMind Control Suite settings: 2048 envs, unrolls of 30, minibatches of 1024,
observation normalisation, ...), the env wrapped with `wrap_for_brax_training` as Playground's own
launcher does, and scores the current policy with the shared `evaluation.py` at regular points of
training wall time, off the clock (`brax_runs.timed_run`).

One change to the schedule, which leaves training as it is: Playground's config evaluates 9 times in
60M steps and resets every env after each training step (num_resets_per_eval 10 of one training step
each). Here an epoch is one training step followed by the same reset (num_resets_per_eval 1), so that
the budget can stop the run and a point can be scored after any training step, not every ten.

  python benchmarks/envs_vs_apg/ppo_baseline.py --envs CartpoleSwingup --seeds 1 --seed0 0 --budget 240 --out DIR
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import jax

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import brax_runs  # noqa: E402
import evaluation  # noqa: E402

brax_runs.install_jax_shims()

from brax.training.acme import running_statistics  # noqa: E402
from brax.training.agents.ppo import networks as ppo_networks  # noqa: E402
from brax.training.agents.ppo import train as ppo_train  # noqa: E402
from mujoco_playground import wrapper as mjp_wrapper  # noqa: E402
from mujoco_playground.config import dm_control_suite_params  # noqa: E402
from stablebptt.storage import write_json  # noqa: E402

EVALS_UNBOUNDED = 1_000_001  # the budget ends the run, not the count of evaluations


def playground_config(env_name: str, overrides: dict) -> dict:
    """Playground's PPO config for the env, with the one-training-step epoch (module docstring)."""
    config = dict(dm_control_suite_params.brax_ppo_config(env_name))
    config.pop("network_factory", None)  # the dm_control configs use Brax's default networks
    config.update(num_evals=EVALS_UNBOUNDED, num_resets_per_eval=1)
    config.update(overrides)
    return config


def env_steps_per_training_step(hp: dict) -> int:
    return hp["batch_size"] * hp["unroll_length"] * hp["num_minibatches"] * hp["action_repeat"]


def training_steps_per_epoch(hp: dict) -> int:
    """Brax's own arithmetic (ppo.train): training steps between two evaluator calls."""
    steps = env_steps_per_training_step(hp)
    per_epoch = -(-hp["num_timesteps"] // (max(hp["num_evals"] - 1, 1) * steps * max(hp["num_resets_per_eval"], 1)))
    return int(per_epoch) * max(hp["num_resets_per_eval"], 1)


def run_one(env_name, seed, budget, eval_every, hp, eval_envs, log, brax_eval="none", keep=lambda rec: None,
            evaluate_after=False):
    env = evaluation.load_env(env_name)
    episode_length = int(env._config.episode_length)
    rec = {
        "env": env_name,
        "seed": seed,
        "algo": "brax_ppo",
        "budget_s": budget,
        "episode_length": episode_length,
        "hyperparams": {k: (list(v) if isinstance(v, tuple) else v) for k, v in hp.items()},
        "solver_train_env": brax_runs.solver_info(env),
        "eval": {"num_envs": eval_envs, "seed": evaluation.EVAL_SEED, "deterministic": True},
        "device": str(jax.devices()[0]),
        "jax": jax.__version__,
    }
    normalize = running_statistics.normalize if hp["normalize_observations"] else (lambda x, y: x)
    net = ppo_networks.make_ppo_networks(env.observation_size, env.action_size, preprocess_observations_fn=normalize)
    make_policy = ppo_networks.make_inference_fn(net)

    def apply(params, obs):  # params: (normalizer, policy, value), as Brax hands them to its evaluator
        return make_policy(params, deterministic=True)(obs, jax.random.PRNGKey(0))[0]

    evaluate = evaluation.make_evaluator(env, apply, num_envs=eval_envs)

    def train():
        ppo_train.train(environment=env, eval_env=evaluation.load_env(env_name), wrap_env_fn=mjp_wrapper.wrap_for_brax_training,
                        seed=seed, **hp)

    return brax_runs.timed_run(train, rec, evaluate=evaluate, evaluate_variant=None, budget=budget, eval_every=eval_every,
                               updates_per_epoch=training_steps_per_epoch(hp),
                               env_steps_per_update=env_steps_per_training_step(hp), brax_eval=brax_eval, log=log,
                               keep=keep, evaluate_after=evaluate_after)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--envs", default="CartpoleSwingup")
    p.add_argument("--seeds", type=int, default=1, help="seeds seed0..seed0+N-1, one after another")
    p.add_argument("--set", action="append", default=[], help="override a hyperparameter: key=JSON value")
    brax_runs.add_common_arguments(p, budget=240.0, eval_envs=evaluation.NUM_EVAL_ENVS, brax_eval="none")
    a = p.parse_args(argv)
    overrides = {k: json.loads(v) for k, v in (kv.split("=", 1) for kv in a.set)}
    os.makedirs(a.out, exist_ok=True)
    with open(os.path.join(a.out, "log.txt"), "a") as logf:
        def log(msg):
            print(msg, flush=True)
            logf.write(msg + "\n")
            logf.flush()

        for env_name in a.envs.split(","):
            hp = playground_config(env_name, overrides)
            log(f"jax {jax.__version__} devices {jax.devices()} {env_name} hp {hp}")
            for seed in range(a.seed0, a.seed0 + a.seeds):
                # The record is written at every point scored: a run stopped by a wall-clock limit keeps them.
                path = Path(a.out) / f"{env_name}_ppo_s{seed}.json"
                rec = run_one(env_name, seed, a.budget, a.eval_every or a.budget / 10, hp, a.eval_envs, log, a.brax_eval,
                              keep=lambda rec, path=path: write_json(path, {**rec, "argv": sys.argv}),
                              evaluate_after=a.evaluate_after)
                log(f"   -> {env_name} s{seed} {rec['status']} final {rec['final_return']} within budget "
                    f"{rec['return_within_budget']} compile {rec.get('compile_s')} env steps/s {rec.get('env_steps_per_s')}")


if __name__ == "__main__":
    try:
        main()
    except KeyboardInterrupt:  # a wall-clock limit's SIGINT: the records keep the points scored
        print("stopped: each seed's record keeps the points it scored", file=sys.stderr)
        sys.exit(130)
