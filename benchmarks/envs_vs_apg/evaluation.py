"""The evaluation of the Brax baselines (`apg_baseline.py`, `ppo_baseline.py`); `stablebptt train` evaluates
its own runs (`--test-size` fresh resets, the deterministic policy, the same episode length and reward).

Protocol:
  * env: the Playground env as shipped, `registry.load(name, config_overrides={"impl": "jax"})`,
    unwrapped (no Brax training wrappers, so no auto-reset and no action repeat);
  * reset keys: those of `stablebptt train`'s test states (`eval_keys`), the same for all runs;
  * policy: deterministic, `apply(params, obs) -> action`, obs is the env's raw flat observation
    (any normalisation belongs to the policy), the action is clipped to [-1, 1] here;
  * length: the env config's `episode_length` (1000 for the DM Control Suite);
  * return: sum of rewards up to and including the step at which `done` first becomes 1, later
    rewards masked to 0; the score is the mean over the envs.
"""

from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

# The episodes `stablebptt train` scores an environment's run on: its --test-size (16) test states, fresh
# resets drawn from its --data-seed (42). A baseline scored here meets the same episodes.
EVAL_SEED = 42
NUM_EVAL_ENVS = 16


def load_env(name: str, **overrides):
    """The env as the benchmark defines it: Playground's, with MJX's JAX implementation."""
    from mujoco_playground import registry

    return registry.load(name, config_overrides={"impl": "jax", **overrides})


def eval_keys(num_envs: int = NUM_EVAL_ENVS, seed: int = EVAL_SEED) -> jax.Array:
    """The reset keys of `stablebptt train`'s test states with ``--test-size num_envs --data-seed seed``."""
    from stablebptt.engine.config import data_keys
    return jax.random.split(data_keys(seed)[1], num_envs)


def make_evaluator(
    env,
    apply: Callable[[Any, jax.Array], jax.Array],
    num_envs: int = NUM_EVAL_ENVS,
    seed: int = EVAL_SEED,
    episode_length: int | None = None,
) -> Callable[[Any], dict]:
    """Returns a jitted `evaluate(params) -> dict` for one env and one policy family, and as its attribute
    `evaluate.many(params_list) -> list[dict]` the same for several params at once, in one program.

    Params are an argument (not closed over) so one compilation serves every evaluation of a run. An
    episode's 1,000 steps run one after another, which on a GPU takes longer than their arithmetic:
    `many` runs them once for all of a run's points, scored together once it has ended.
    """
    if episode_length is None:
        episode_length = int(env._config.episode_length)
    keys = eval_keys(num_envs, seed)

    def rollout(params, key):
        state = env.reset(key)

        def body(carry, _):
            state, ret, alive = carry
            action = jnp.clip(apply(params, state.obs), -1.0, 1.0)
            state = env.step(state, action)
            # where(), not multiplication: a diverged env may report a NaN reward.
            ret = ret + jnp.where(alive, state.reward, 0.0)
            alive = alive & (state.done == 0)
            return (state, ret, alive), None

        init = (state, jnp.zeros(()), jnp.ones((), bool))
        (_, ret, alive), _ = jax.lax.scan(body, init, None, length=episode_length)
        return ret, alive

    def episodes(params):
        return jax.vmap(rollout, in_axes=(None, 0))(params, keys)

    evaluate_device, evaluate_stacked = jax.jit(episodes), jax.jit(jax.vmap(episodes))

    def scored(rets, alive) -> dict:
        return {
            "mean_return": float(rets.mean()),
            "std_return": float(rets.std()),
            "num_envs": int(num_envs),
            "episode_length": int(episode_length),
            "num_done_early": int((~alive).sum()),
        }

    def evaluate(params) -> dict:
        return scored(*jax.device_get(evaluate_device(params)))

    def many(params_list) -> list[dict]:
        stacked = jax.tree.map(lambda *leaves: np.stack(leaves), *params_list)
        rets, alive = jax.device_get(evaluate_stacked(stacked))
        return [scored(*each) for each in zip(rets, alive)]

    evaluate.many = many
    return evaluate


def evaluate(env, act: Callable[[jax.Array], jax.Array], **kwargs) -> float:
    """One-off form: mean episode return of a parameter-free `act(obs)`."""
    return make_evaluator(env, lambda _, obs: act(obs), **kwargs)(None)["mean_return"]
