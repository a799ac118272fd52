"""Looks at a MuJoCo Playground environment where a run does not train: is the step's derivative
right, what does the trained policy do, can a policy of the observation learn the task at all, how
hard do its contacts push (where ``--contact-gradient-cut`` would cut), and what does a policy that
ignores the state score.

  python benchmarks/env_probe.py gradient ReacherEasy [--surrogate-reward env_probe:reacher_distance_reward]
          [--window 16] [--set-qpos 1=2.79]
      One reset (then one step with zero action, so every derived quantity is current), the joint
      positions set as given; a window of constant actions 0.3 from there. The gradient of the window's
      summed reward (the env's, or ``M:F`` of the state each step reaches) in each action of its first,
      middle and last step: the step's derivative as training takes it (the constraint solver
      differentiated at its solution) against central finite differences, in float64.
  python benchmarks/env_probe.py rollout RUN_DIR [--steps 300] [--seed-index 0]
      A trained environment run's policy for one episode from a reset: the env's return, the share of
      actions whose pre-squash output lies past +-2 (tanh > 0.96: saturated), each joint position's
      first, last, smallest and largest value, and each reward term the env records (Playground's
      ``metrics["reward/..."]``): its mean over the steps and the share of steps where it is exactly 0.
  python benchmarks/env_probe.py episodes RUN_DIR [--count 16] [--seed-index 0]
      A trained environment run's policy from the run's own test states (drawn as its evaluations draw
      them), whole episodes of the deterministic policy: each one's return (the env's reward), its count
      of rewarded steps and the first and last of them, its first and last joint positions and where its
      mocap bodies stand (a target the env placed, if any). Which starts a policy fails from, and when
      in an episode it earns, where its evaluation's mean alone says how often.
  python benchmarks/env_probe.py blind HopperStand [--count 16] [--scale 0] [--seed 7]
      What a policy that ignores the state scores: whole episodes from resets under actions uniform in
      +-scale (0: every action zero), each one's return, its count of rewarded steps and its first joint
      positions. The floor a trained policy's return stands on.
  python benchmarks/env_probe.py features ReacherEasy [--inputs observation|arm-frame] [--window 20]
          [--updates 400] [--batch 64] [--lr 1e-3] [--seed 1]
      Plain BPTT, none of the library's flows, critic or carried episodes: windows of the env's step from
      fresh resets, the loss the window's mean finger-to-target distance, jax.grad of it through the step
      as training takes it, Adam on a tanh MLP of 64 x 64 (the library's env policy). Inputs: the env's
      observation, or (arm-frame) the target seen in the joints' terms, J(q)^T (target - finger) with
      J the finger's Jacobian in the joint angles, beside the joint velocities. Every 50 updates: the
      window's mean distance, the env's return over 16 episodes of 1,000 steps (the deterministic
      policy) and the share of its actions saturated in their first 20 steps (as ``rollout`` counts
      them). Where arm-frame learns and the observation does not, the derivative leads and what
      fails is the policy's fit of the observation.
  python benchmarks/env_probe.py loads WalkerWalk [--envs 32] [--steps 150] [--scale 0.5] [--seed 0]
      The contact load of the states a population reaches from resets under uniform random actions in
      +-scale: the norm of MJX's constraint forces (qfrc_constraint) in the model's body weights, as
      ``--contact-gradient-cut`` reads it. Its percentiles, and the share of states above 1, 2, 5 and
      10 body weights: the share of the windows' steps a cut at that load would stop.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

ACTION = 0.3
EPSILON = 1e-5
SATURATED = 2.0  # a pre-squash output past this: tanh above 0.96, its derivative below 0.07


def reacher_distance_reward(state) -> jax.Array:
    """ReacherEasy's and ReacherHard's finger-to-target distance, negated: a dense reward of the state
    (its observation holds the joint positions, then the finger-to-target vector). Train on it with
    ``PYTHONPATH=benchmarks stablebptt train --env ReacherEasy --surrogate-reward env_probe:reacher_distance_reward``."""
    return -jnp.linalg.norm(state.obs[2:4])


FISH_RADII = 0.045  # FishSwim's mouth and target radii summed (its env's ``_radii``): in_target's bounds


def fish_target_pull_reward(state) -> jax.Array:
    """FishSwim's reward, (7 in_target + upright) / 8, with in_target's Gaussian tail given, in the derivative
    only, the slope its sigmoid falls by on average over its margin: far from the target the Gaussian's
    slope vanishes (below 1e-9 a margin further out), so nothing pulls the mouth there. The observation
    holds upright first and the mouth-to-target vector at 8:11. Train on it with
    ``PYTHONPATH=benchmarks stablebptt train --env FishSwim --surrogate-reward env_probe:fish_target_pull_reward``."""
    from stablebptt.envs.playground import safe_tolerance
    distance = jnp.linalg.norm(state.obs[8:11])
    margin = 2 * FISH_RADII
    in_target = safe_tolerance(distance, bounds=(0.0, FISH_RADII), margin=margin)
    past = jnp.maximum(distance - FISH_RADII, 0.0) * (1 - 0.1) / margin  # 0.9 over the margin, as the sigmoid falls
    pulled = in_target + jax.lax.stop_gradient(past) - past
    return (7 * pulled + 0.5 * (state.obs[0] + 1)) / 8


def gradient(name: str, window: int, surrogate: str, set_qpos: list[str]) -> None:
    jax.config.update("jax_enable_x64", True)
    from stablebptt.envs import playground
    from stablebptt.envs.protocol import load_reward
    from stablebptt.physics.constraint_derivatives import differentiable_mjx
    env = playground.load(name)

    # The step as env_task traces it, not env_task's own: its checks refuse Playground's step in float64,
    # whose scans change their carry's dtype.
    def step(state, action):
        with differentiable_mjx(implicit_solver=True), playground.repaired_rewards():
            return env.step(state, action)
    reward = load_reward(surrogate) if surrogate else (lambda state: state.reward)
    state = jax.jit(env.reset)(jax.random.PRNGKey(3))
    qpos = state.data.qpos
    for item in set_qpos:
        index, value = item.split("=")
        qpos = qpos.at[int(index)].set(float(value))
    zero = jnp.zeros(env.action_size)
    state = jax.jit(step)(state.replace(data=state.data.replace(qpos=qpos)), zero)

    def summed(actions):
        def body(current, action):
            reached = step(current, action)
            return reached, reward(reached)
        return jnp.sum(jax.lax.scan(body, state, actions)[1])

    actions = jnp.full((window, env.action_size), ACTION)
    value, derivative = jax.jit(summed), jax.jit(jax.grad(summed))(actions)
    print(f"{name}: a window of {window} steps, summed {'surrogate ' if surrogate else ''}reward "
          f"{float(value(actions)):.6g}, joint positions {np.round(np.asarray(qpos), 4)}")
    for t in sorted({0, window // 2, window - 1}):
        differences = []
        for j in range(env.action_size):
            nudge = jnp.zeros_like(actions).at[t, j].set(EPSILON)
            differences.append((value(actions + nudge) - value(actions - nudge)) / (2 * EPSILON))
        ours, theirs = np.asarray(derivative[t]), np.asarray(differences)
        worst = np.max(np.abs(ours - theirs) / np.maximum(np.abs(theirs), 1e-12))
        print(f"  step {t}: derivative {np.array2string(ours, precision=8)}, finite differences "
              f"{np.array2string(theirs, precision=8)}, largest relative difference {worst:.1e}")


def arm_frame(model) -> Callable[[jax.Array], jax.Array]:
    """The reacher's target in its joints' terms: J(q)^T (target - finger), scaled to order one, and the
    joint velocities, of an observation of the joint angles, the finger-to-target vector, the velocities.
    The arm's two lengths are ``model``'s (the hand's and the finger's offsets from their parents)."""
    arm, hand = float(model.body("hand").pos[0]), float(model.body("finger").pos[0])

    def seen(observation: jax.Array) -> jax.Array:
        shoulder, wrist = observation[0], observation[1]
        elbow_to_finger = hand * jnp.array([-jnp.sin(shoulder + wrist), jnp.cos(shoulder + wrist)])
        to_finger = arm * jnp.array([-jnp.sin(shoulder), jnp.cos(shoulder)]) + elbow_to_finger
        reach = jnp.stack([to_finger, elbow_to_finger], axis=1)  # the finger's Jacobian in the two angles
        return jnp.concatenate([reach.T @ observation[2:4] * 100, observation[4:6] * 0.2])
    return seen


def angles_periodic(observation: jax.Array) -> jax.Array:
    """The reacher's observation with its two joint angles given as their sines and cosines."""
    angles = observation[:2]
    return jnp.concatenate([jnp.sin(angles), jnp.cos(angles), observation[2:]])


def features(name: str, inputs: str, window: int, updates: int, batch: int, lr: float, seed: int,
             squash_floor: float, saturation_cost: float, activation: str) -> None:
    import optax

    from stablebptt.envs import playground
    from stablebptt.envs.reward_direction import reward_direction
    from stablebptt.networks import floored_tanh, mlp_apply, mlp_init
    from stablebptt.physics.constraint_derivatives import differentiable_mjx
    env = playground.load(name)
    seen = {"arm-frame": arm_frame(env.mj_model), "angles-periodic": angles_periodic}.get(
        inputs, lambda observation: observation)

    def step(state, action):
        with differentiable_mjx(implicit_solver=True), playground.repaired_rewards():
            return env.step(state, action)

    squash = floored_tanh(squash_floor)
    hidden_activation = {"tanh": jnp.tanh, "silu": jax.nn.silu, "elu": jax.nn.elu, "gated": jnp.tanh}[activation]
    gated = activation == "gated"

    def output(layers, inputs):  # the library's MLP, its hidden layers' activation chosen
        if gated:  # the first layer's units multiplied by a second linear map of the inputs
            (weights, bias), (gate_weights, gate_bias) = layers[0], layers[-1]
            inputs = jnp.tanh(inputs @ weights + bias) * (inputs @ gate_weights + gate_bias)
            layers = layers[1:-1]
        return mlp_apply(layers, inputs, hidden_activation)

    def nearer(state, action):  # the step, rewarded by the finger's nearness to the target one control step on
        reached = step(state, action)
        return reached.replace(reward=-jnp.sqrt(jnp.sum(reached.obs[2:4] ** 2) + 1e-12))

    def features(state):  # what the policy sees
        if inputs != "distance-gradient":
            return seen(state.obs)
        # The direction in the actions that brings the finger nearest one step on, from still actions.
        return jnp.concatenate([state.obs, reward_direction(nearer, state, env.action_size)])

    def act(params, state):
        return squash(output(params, features(state)))

    def saturation(params, states):  # the squash's input past its knee, squared: what --saturation-cost weighs
        raw = jax.vmap(lambda state: output(params, features(state)))(states)
        return jnp.mean(jnp.maximum(jnp.abs(raw) - 1, 0) ** 2)

    def fresh(key, count):  # a reset, then one still step: the reset's observation places the target stale
        states = jax.vmap(env.reset)(jax.random.split(key, count))
        return jax.vmap(step)(states, jnp.zeros((count, env.action_size)))

    def mean_distance(params, states):
        def body(current, _):
            reached = jax.vmap(step)(current, jax.vmap(act, (None, 0))(params, current))
            return reached, jnp.sqrt(jnp.sum(reached.obs[:, 2:4] ** 2, axis=-1) + 1e-12)
        reached, distances = jax.lax.scan(body, states, None, length=window)
        return jnp.mean(distances) + saturation_cost * saturation(params, states)

    def episode_return(params, state):
        def body(current, _):
            raw = output(params, features(current))
            reached = step(current, jnp.tanh(raw))
            return reached, (reached.reward, jnp.mean(jnp.abs(raw) > SATURATED))
        rewards, saturated = jax.lax.scan(body, state, None, length=1000)[1]
        return jnp.sum(rewards), jnp.mean(saturated[:20])

    optimizer = optax.chain(optax.clip_by_global_norm(1.0), optax.adam(lr))

    @jax.jit
    def update(params, opt_state, key):
        distance, grads = jax.value_and_grad(mean_distance)(params, fresh(key, batch))
        moves, opt_state = optimizer.update(grads, opt_state, params)
        return optax.apply_updates(params, moves), opt_state, distance

    evaluate = jax.jit(lambda params: jax.tree.map(
        jnp.mean, jax.vmap(episode_return, (None, 0))(params, fresh(jax.random.PRNGKey(7), 16))))
    key = jax.random.PRNGKey(seed)
    key, init_key = jax.random.split(key)
    inputs_size = int(jax.eval_shape(features, env.reset(jax.random.PRNGKey(0))).shape[0])
    params = mlp_init(init_key, (inputs_size, 64, 64, env.action_size))
    if gated:  # the gate's map, kept last; its bias 1 so that each unit starts as tanh's
        key, gate_key = jax.random.split(key)
        params = params + [(mlp_init(gate_key, (inputs_size, 64), zero_output=False)[0][0], jnp.ones(64))]
    opt_state = optimizer.init(params)
    for number in range(1, updates + 1):
        key, update_key = jax.random.split(key)
        params, opt_state, distance = update(params, opt_state, update_key)
        if number % 50 == 0 or number == updates:
            episode_mean, saturated = evaluate(params)
            print(f"{name}, inputs {inputs}: update {number}: window's mean distance {float(distance):.4f}, "
                  f"return {float(episode_mean):.1f}, actions saturated in the first 20 steps {float(saturated):.0%}",
                  flush=True)


def rollout(run_dir: Path, steps: int, seed_index: int) -> None:
    from stablebptt.apps.trained import open_trained
    from stablebptt.envs.adapter import squashed_output
    trained = open_trained(run_dir)
    episodes, params = trained.task.episodes, trained.seed_params(seed_index)
    output = jax.jit(lambda state: squashed_output(params, episodes.observe(state)))
    state = jax.jit(episodes.reset)(jax.random.PRNGKey(7))
    total, saturated, positions, terms = 0.0, [], [], {}
    for _ in range(steps):
        raw = output(state)
        saturated.append(np.abs(np.asarray(raw)) > SATURATED)
        state = episodes.step(state, jnp.tanh(raw))  # the env's own step: its reward, not a surrogate's
        total += float(state.reward)
        positions.append(np.asarray(state.data.qpos))
        for name, value in getattr(state, "metrics", {}).items():
            if name.startswith("reward/"):
                terms.setdefault(name, []).append(float(value))
    positions = np.array(positions)
    print(f"{trained.task.name} ({run_dir}, seed index {seed_index}): return {total:.1f} over {steps} steps; "
          f"actions saturated (|pre-squash| > 2): {np.mean(saturated):.0%}")
    for index in range(positions.shape[1]):
        column = positions[:, index]
        print(f"  qpos[{index}]: first {column[0]:.3f}, last {column[-1]:.3f}, from {column.min():.3f} "
              f"to {column.max():.3f}")
    for name, values in terms.items():  # a term exactly 0 on many steps may be flat there (no gradient)
        print(f"  {name}: mean {np.mean(values):.3f}, exactly 0 at {np.mean(np.array(values) == 0):.0%} of steps")


def episodes_of_run(run_dir: Path, count: int, seed_index: int) -> None:
    from stablebptt.apps.trained import episodes_from_test_states, open_trained
    trained = open_trained(run_dir)
    episode = episodes_from_test_states(trained.task, trained.task.episodes, trained.seed_params(seed_index),
                                        trained.train, count)
    data = episode.states.data  # [episodes, steps + 1, ...]; a Directed state reads through to its own
    positions, targets = np.asarray(data.qpos), np.asarray(data.mocap_pos)
    print(f"{trained.task.name} ({run_dir}, seed index {seed_index}): {count} test episodes, mean return "
          f"{np.mean(episode.returns):.1f}")
    rewards = np.asarray(episode.states.reward)[:, 1:]  # each step's reward (the first state's is the reset's)
    rounded = lambda values: " ".join(f"{value:.2f}" for value in np.ravel(values))  # noqa: E731
    for index, value in enumerate(episode.returns):
        # When the reward is earned (as blind counts it): at the start alone (a fall), later (a rise), throughout.
        earned = np.flatnonzero(rewards[index, :episode.lengths[index]] > 0)  # a state held past done is not stepped
        when = (f"{earned.size} of {episode.lengths[index]} steps rewarded, from step {earned[0] + 1} to {earned[-1] + 1}"
                if earned.size else "no step rewarded")
        print(f"  {index}: return {value:.0f}; {when}; qpos first {rounded(positions[index, 0])}, last "
              f"{rounded(positions[index, -1])}" + (f"; mocap {rounded(targets[index, 0])}" if targets.size else ""))


def _uniform_actions_from_resets(env, envs: int, steps: int, scale: float, seed: int, read: Callable) -> tuple:
    """``envs`` resets of ``env`` stepped ``steps`` times under actions uniform in +-``scale``: the resets,
    and ``read`` of every state reached ([steps, envs, ...])."""
    @jax.jit
    def rolled(key):
        reset_key, action_key = jax.random.split(key)
        states = jax.vmap(env.reset)(jax.random.split(reset_key, envs))

        def body(current, key):
            actions = scale * jax.random.uniform(key, (envs, env.action_size), minval=-1, maxval=1)
            reached = jax.vmap(env.step)(current, actions)
            return reached, read(reached)
        return states, jax.lax.scan(body, states, jax.random.split(action_key, steps))[1]
    return rolled(jax.random.PRNGKey(seed))


def blind(name: str, count: int, scale: float, seed: int) -> None:
    from stablebptt.envs import playground
    env = playground.load(name)
    length = int(env._config.episode_length)
    states, rewards = _uniform_actions_from_resets(env, count, length, scale, seed, lambda reached: reached.reward)
    first, returns, rewarded = np.asarray(states.data.qpos), np.asarray(rewards.sum(0)), np.asarray((rewards > 0).sum(0))
    print(f"{name}: {count} episodes of {length} steps, actions uniform in +-{scale:g}: mean return "
          f"{returns.mean():.2f}")
    for index in range(count):
        print(f"  {index}: return {returns[index]:.1f}, {rewarded[index]} steps rewarded; qpos first "
              + " ".join(f"{value:.2f}" for value in first[index]))


def loads(name: str, envs: int, steps: int, scale: float, seed: int) -> None:
    from stablebptt.envs import playground
    from stablebptt.envs.derivative_model import contact_load
    env = playground.load(name)
    load_of = contact_load(env, name)  # as --contact-gradient-cut reads it
    _, reached_loads = _uniform_actions_from_resets(env, envs, steps, scale, seed, jax.vmap(load_of))

    load = np.asarray(reached_loads)
    percentiles = ", ".join(f"{p}%: {value:.2f}" for p, value in zip((50, 75, 90, 95, 99),
                                                                      np.percentile(load, (50, 75, 90, 95, 99))))
    above = ", ".join(f"{k}: {np.mean(load > k):.1%}" for k in (1, 2, 5, 10))
    print(f"{name}: contact load over {envs} envs x {steps} steps (actions uniform in "
          f"+-{scale:g}), in body weights: {percentiles}, largest {load.max():.1f}; share of states above {above}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    looks = parser.add_subparsers(dest="look", required=True)
    one = looks.add_parser("gradient")
    one.add_argument("env")
    one.add_argument("--window", type=int, default=16)
    one.add_argument("--surrogate-reward", default="")
    one.add_argument("--set-qpos", action="append", default=[], metavar="INDEX=VALUE")
    other = looks.add_parser("rollout")
    other.add_argument("run_dir", type=Path)
    other.add_argument("--steps", type=int, default=300)
    other.add_argument("--seed-index", type=int, default=0)
    third = looks.add_parser("features")
    third.add_argument("env", choices=("ReacherEasy", "ReacherHard"))
    third.add_argument("--inputs", choices=("observation", "angles-periodic", "arm-frame", "distance-gradient"), default="observation")
    third.add_argument("--window", type=int, default=20)
    third.add_argument("--updates", type=int, default=400)
    third.add_argument("--batch", type=int, default=64)
    third.add_argument("--lr", type=float, default=1e-3)
    third.add_argument("--seed", type=int, default=1)
    third.add_argument("--squash-floor", type=float, default=0.0)
    third.add_argument("--saturation-cost", type=float, default=0.0)
    third.add_argument("--activation", choices=("tanh", "silu", "elu", "gated"), default="tanh")
    fifth = looks.add_parser("episodes")
    fifth.add_argument("run_dir", type=Path)
    fifth.add_argument("--count", type=int, default=16)
    fifth.add_argument("--seed-index", type=int, default=0)
    sixth = looks.add_parser("blind")
    sixth.add_argument("env")
    sixth.add_argument("--count", type=int, default=16)
    sixth.add_argument("--scale", type=float, default=0.0)
    sixth.add_argument("--seed", type=int, default=7)
    fourth = looks.add_parser("loads")
    fourth.add_argument("env")
    fourth.add_argument("--envs", type=int, default=32)
    fourth.add_argument("--steps", type=int, default=150)
    fourth.add_argument("--scale", type=float, default=0.5)
    fourth.add_argument("--seed", type=int, default=0)
    arguments = parser.parse_args()
    try:
        if arguments.look == "gradient":
            gradient(arguments.env, arguments.window, arguments.surrogate_reward, arguments.set_qpos)
        elif arguments.look == "episodes":
            episodes_of_run(arguments.run_dir, arguments.count, arguments.seed_index)
        elif arguments.look == "blind":
            blind(arguments.env, arguments.count, arguments.scale, arguments.seed)
        elif arguments.look == "loads":
            loads(arguments.env, arguments.envs, arguments.steps, arguments.scale, arguments.seed)
        elif arguments.look == "features":
            features(arguments.env, arguments.inputs, arguments.window, arguments.updates, arguments.batch,
                     arguments.lr, arguments.seed, arguments.squash_floor, arguments.saturation_cost,
                     arguments.activation)
        else:
            rollout(arguments.run_dir, arguments.steps, arguments.seed_index)
    except KeyboardInterrupt:
        print("stopped", file=sys.stderr)
        sys.exit(130)


if __name__ == "__main__":
    main()
