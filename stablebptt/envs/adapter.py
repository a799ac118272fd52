"""Environments as tasks: any environment in Brax's protocol trains through the gradient flows.

``env_task`` turns an environment in Brax's protocol (``stablebptt.envs.protocol``) into a ``Task``:

- the loss of a rollout of ``horizon`` steps is its negative (optionally
  discounted) return, rewards counted until the first ``done``;
- initial states come from ``env.reset`` (jitted, batched);
- the policy sees ``State.obs`` (and, asked for, the direction of its reward in its actions, which the
  task's states carry: ``reward_direction``) and its actions are squashed into [-1, 1];
- the train and test losses of every epoch are the negative EPISODE return (``episode_length`` steps,
  the deterministic policy, from fresh resets), the number Brax and MuJoCo Playground report;
- an ``mjx.step`` inside ``env.step`` is traced with its constraint solver differentiated implicitly
  (``constraint_derivatives``), so solvers of any iteration count pass reverse mode.

Before training, ``diagnose_env`` looks at the reward's gradient at states sampled along whole episodes
(where training will look): a reward whose gradient is zero everywhere (a step function) is smoothed, a NaN
derivative of a known form is repaired, and a NaN at exactly zero action is avoided by starting the
policy's output layer small instead of at zero (``RewardDiagnosis``). A resumed run skips it (``smoothing_choices``).
"""
from __future__ import annotations

import contextlib
import dataclasses
import functools
from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp

from stablebptt.engine import program_store
from stablebptt.engine.episodes import Episodes
from stablebptt.engine.observations import StandardizedNetwork, no_observations, refresh_from, standardized
from stablebptt.engine.shapes import shapes_only
from stablebptt.engine.task import Task
from stablebptt.envs import surrogate
from stablebptt.envs.arguments import check_env_task_arguments
from stablebptt.envs.derivative_model import (check_contacts, contact_cut, derivative_steps, has_constraint_solver,
                                              jit_traced_once, joined, loaded_states, own_substeps, steps_traced)
from stablebptt.envs.diagnosis import (PendingDiagnosis, RewardDiagnosis, check_device, sample_for_diagnosis,
                                       start_checks, start_diagnosis)
from stablebptt.envs.protocol import (EnvError, require_env_instance, check_protocol, check_same_states, check_step,
                                      check_surrogate_reward, function_name, sized_observation, trained_reward_words)
from stablebptt.envs.returns import EpisodeState, episode_dynamics, rollout_loss
from stablebptt.envs.reward_direction import Direction
from stablebptt.envs.unread_outputs import unread_outputs_off
from stablebptt.errors import keywords_named, whole_number
from stablebptt.flows.dynamics import Dynamics
from stablebptt.flows.gradients import reference_losses
from stablebptt.networks import floored_tanh, mlp_apply, mlp_init
from stablebptt.physics.backward_contacts import ContactSmoothing

PyTree = Any
# Output weights of a policy that must not start at exactly zero action: its first actions near zero, not at it.
SMALL_OUTPUT_SCALE = 1e-2


def _count(states: PyTree) -> int:
    return jax.tree.leaves(states)[0].shape[0]


def _is_playground(env: Any) -> bool:
    return type(env).__module__.startswith("mujoco_playground")


def observation_policy(params: Any, seen: jax.Array, squash: Callable = jnp.tanh) -> jax.Array:
    """An env task's deterministic policy on an observation: tanh (``squash``) of ``squashed_output``."""
    return squash(squashed_output(params, seen))


def squashed_output(params: Any, seen: jax.Array) -> jax.Array:
    """What an env task's policy squashes into its action: the MLP of the observation, standardised first by
    the statistics the parameters keep where the run normalises observations."""
    if isinstance(params, StandardizedNetwork):
        params, seen = params.network, standardized(params.statistics, seen)
    return mlp_apply(params, seen)


@keywords_named
def env_task(env: Any, horizon: int, *, discount: float = 1.0, episode_length: int | None = None,
             hidden: Sequence[int] = (64, 64), name: str = "", reward_context: Callable | None = None,
             reward_repairs: str = "", diagnose: bool = True, diagnosis_seed: int = 0,
             dense_variant: str = "", diagnosis_key: dict | None = None, defer_diagnosis: bool = False,
             smoothing: str = "auto", smoothing_scale: float = 1.0,
             surrogate_reward: Callable[[Any], jax.Array] | None = None, normalize_observations: bool = False,
             reward_env: Any = None, contact_smoothing: ContactSmoothing | None = None,
             gradient_substeps: int | None = None, squash_gradient_floor: float = 0.0,
             contact_gradient_cut: float = 0.0, contact_geometry_held: bool = False,
             physics_steps_recomputed: bool | None = None, reward_direction_observed: bool = False,
             smoothing_choices: dict | None = None, physics_steps_carrying_state: bool = False) -> Task:
    """A ``Task`` that trains a policy on ``env`` (Brax's protocol) through the gradient flows.

    Args:
      env: the environment (``reset``, ``step``, ``observation_size``, ``action_size``).
      horizon: steps of one training rollout (the BPTT horizon).
      discount: per-step discount of the training loss's return (1: the plain return).
      episode_length: steps of the evaluation episodes whose return the train and test losses report (negated);
        None: the env's own (``env._config.episode_length``, as Playground and Brax evaluate), else 1000.
      hidden: widths of the policy's hidden layers.
      name: the task's name in run folders (default: the environment's class name).
      reward_context: a context manager entered whenever the step is traced (a repair of the reward's derivative;
        ``reward_repairs`` names it for the summary). None: for Playground's envs ``playground.repaired_rewards``.
      diagnose: look at the reward's gradient before training (``diagnose_env``); a reward with no usable
        gradient raises ``EnvError``.
      dense_variant: a dense-reward env of the task, suggested for a flat reward; with ``reward_env``, its name.
      diagnosis_key: what names ``env`` beyond the library and the package versions (e.g. its registry name):
        while JAX's compile cache is on, the diagnosis is kept under it (with ``reward_repairs``; not of a surrogate
        or of a reward_env without dense_variant, whose names tell no reward apart) for an identical later run to
        read instead of tracing the step's derivative again; so are the traced reset and the observation's size
        (Playground traces the reset to find it). None: diagnosed and traced every time.
      defer_diagnosis: return while the diagnosis compiles and runs beside the caller (``start_diagnosis``): the
        task's ``settled()`` waits for it and refuses a reward with no usable gradient; the parameters' values wait
        for it too, their shapes do not, so a trainer can be built meanwhile (``scripts/train.py`` does). Beside an
        accelerator, a reward that turns no comparison into a number is diagnosed once ``settled()`` first asks.
      smoothing: "auto": where the diagnosis finds the reward's gradient zero at every sampled state, train on a
        smooth surrogate (``envs.surrogate``), diagnosed in turn; the reported returns stay the true reward's. "always":
        the surrogate, the gradient zero or not (a term vanishing beside others: FishSwim's). "off": refuse a flat reward.
      smoothing_scale: the surrogate's temperatures are this times the sampled differences' median.
      surrogate_reward: ``reward(state) -> scalar`` of the state a step reaches, trained on in place of the env's
        reward (diagnosed, not smoothed); the reported returns stay the env's.
      reward_env: an environment whose step takes and returns ``env``'s states (a ``...Sparse`` env's dense variant):
        the windows train on its rewards (diagnosed as the env's would be); every reported return stays ``env``'s.
      normalize_observations: the policy sees its observations standardised by the running mean and deviation of
        every observation its training windows met (``engine.observations``); its parameters are then a
        ``StandardizedNetwork``, the statistics kept with the network.
      contact_smoothing: the step's values stay the env's, its derivative is that of the same step
        through the env's model with contacts acting from ``margin`` metres and ``softness`` times
        softer (``stablebptt.physics.backward_contacts``); for envs that keep their MJX model in
        ``_mjx_model`` (MuJoCo Playground's). None: the derivative of the model as its file says.
      gradient_substeps: the step's values stay the env's, its derivative is that of the same control step
        taken in this many physics steps of equal length (a divisor of the env's own ``n_substeps``; MuJoCo
        Playground's envs). None: through every physics step the env simulates.
      squash_gradient_floor: the derivative of the policy's tanh kept at least this, in [0, 1), its values
        unchanged (``networks.floored_tanh``): a saturated action still passes that share of its gradient on.
      contact_gradient_cut: the windows' derivative stops at a state under constraint forces above this many
        body weights (``derivative_model.contact_cut``; MJX's data in the state); 0: never.
      contact_geometry_held: the step's values stay the env's; its derivative holds the point and frame of each
        contact of ``backward_contacts.CLOSED_FORM_PAIRS`` and differentiates its distance by the closed form
        n . (v2 - v1), exact to first order there (``backward_contacts.geometry_held``): MJX's collision functions
        of those pairs are not differentiated; other pairs keep MJX's derivative. False: MJX's own derivative of
        its collision.
      physics_steps_recomputed: reverse mode stores the state each ``mjx.step`` starts from (and the constraint
        solver's solution, and the values of MJX's functions this package differentiates) and runs the rest of
        the step again in the backward pass (``jax.checkpoint``), rather than storing every intermediate of
        every physics step: the same derivative, and on the humanoid and the walker a shorter update
        (docs/performance.md). It reaches an env that calls ``mjx.step`` through MJX's package, as MuJoCo
        Playground's do. None: recomputed where the derivative's control step spans more than one physics
        step (MuJoCo Playground's ``n_substeps``, or ``gradient_substeps``), stored otherwise.
      reward_direction_observed: the policy also sees the unit direction in its actions that raises the reward
        it trains on one control step on (``reward_direction``), carried by each state: one more step and its
        derivative per state a step or a reset reaches.
      smoothing_choices: a flat reward's surrogate as a run recorded it (``reward_smoothing_choices``): the
        windows train on it, made of these rather than fitted on this machine's samples, and no check runs (the
        run's own chose and passed it): a resumed or reopened run keeps its temperatures.
      physics_steps_carrying_state: MuJoCo Playground's loop of a control step's physics steps carries only what
        a physics step reads (MuJoCo's integration state, the inputs and the solver's warm start) and takes its
        last step after the loop (``state_carried.steps``): the same physics, values equal to rounding, the step
        traced twice; on one H100 FishSwim's update took 13.6% less time and its forward window 16.5% less, its
        update compiling 6.2 s longer (docs/performance.md). It reaches an env that calls Playground's
        ``mjx_env.step`` through its module, as Playground's envs do. False: the env's own loop, the whole data.

    Example::

        env = mujoco_playground.registry.load("CartpoleSwingup", config_overrides={"impl": "jax"})
        task = sb.env_task(env, horizon=100)
        result = sb.train(task, sb.TrainConfig(mode="C", epochs=50, train_size=64, test_size=16))
    """
    check_env_task_arguments(**{argument: value for argument, value in locals().items() if argument != "env"})
    require_env_instance(env)
    if _is_playground(env):
        from stablebptt.envs import playground
        playground.require_jax_impl(env, type(env).__name__, EnvError)  # MuJoCo Warp, Playground's default
        if reward_context is None:
            reward_context, reward_repairs = playground.repaired_rewards, reward_repairs or playground.REPAIRS
    reward_context = reward_context or contextlib.nullcontext
    # The step searched as the task traces it, inside the reward's repair: the returns the same to the bit.
    # A user's surrogate or another env's reward reads states the search does not trace: then nothing is left out.
    left_out = unread_outputs_off(env, diagnosis_key, reward_context, surrogate_reward is None and reward_env is None)
    env = left_out.env
    # Playground traces the reset to tell the observation's size: kept, an identical later run reads it.
    observations = program_store.kept_answer(diagnosis_key, "observation size", lambda: check_protocol(env))
    if episode_length is None:
        episode_length = int(getattr(getattr(env, "_config", None), "episode_length", 1000))
    if not whole_number(episode_length) or episode_length < 1:
        raise EnvError(f"{type(env).__name__}'s episode_length must be a positive whole number of steps, got "
                       f"{episode_length!r}: give env_task(episode_length=...)")
    label = name or type(env).__name__
    if contact_smoothing is not None and contact_smoothing.exact:  # the file's own contacts: nothing to smooth
        contact_smoothing = None
    if gradient_substeps is not None and gradient_substeps == own_substeps(env):  # the env's own steps
        gradient_substeps = None
    if contact_geometry_held:
        check_contacts(env, "contacts' points and frames held in the derivative", label)
    recomputed_as_asked = physics_steps_recomputed is True
    if physics_steps_recomputed is None:  # where a control step's derivative runs through a loop of physics steps
        physics_steps_recomputed = (gradient_substeps or own_substeps(env) or 1) > 1
    traced = steps_traced(contact_geometry_held, physics_steps_recomputed, recomputed_as_asked, reward_context, label,
                          left_out.camera_poses_held, physics_steps_carrying_state)
    # Traced once per state shape: every program and check reuses the one trace, none re-runs the env's Python.
    own_steps = derivative_steps(traced, env, contact_smoothing, gradient_substeps, label)  # values, derivative
    step = jit_traced_once(joined(*own_steps))
    squash = floored_tanh(squash_gradient_floor)
    # The windows' step alone is cut; an env that cannot take the cut is refused here, in one line.
    loaded = loaded_states(env, contact_gradient_cut, label) if contact_gradient_cut else None
    # One cut step per step cut: a settled task keeps its pending task's step (a new one reads as smoothed: starting.py).
    cut = functools.cache(contact_cut(loaded)) if loaded else (lambda trained: trained)
    observed = sized_observation(observations, label)  # checked as traced: the reward check traces no policy

    # One per reward whose direction the states carry (trained; else None, one for all): a task the check settles into
    # keeps its pending task's policy, starts, evaluation and episodes, and a trainer of it the pending one's programs.
    @functools.cache
    def parts_of(trained):  # the direction its states carry, what the policy sees, the policy, the starts, ...
        direction = Direction(trained, int(env.action_size), reward_direction_observed)
        seen = direction.seen(observed)
        policy = lambda params, state: observation_policy(params, seen(state), squash)  # noqa: E731
        rollout = episode_dynamics(direction.stepping(step), policy, episode_length)
        evaluation = lambda params, states: reference_losses(rollout, params, EpisodeState(  # noqa: E731
            states, jnp.zeros(_count(states)), jnp.ones(_count(states), bool)))
        # Carried episodes: reset by the env's reset; their returns the env's own, whatever reward the windows train on.
        episodes = Episodes(reset=direction.resetting(env.reset), reward=lambda state: state.reward,
                            done=lambda state: state.done > 0, length=episode_length, discount=discount, observe=seen,
                            step=direction.stepping(step), gradient_cut=loaded)
        return direction, seen, policy, direction.sampling(sample_initial_states), evaluation, episodes

    # What the windows train on: the env's reward, the user's surrogate, or another env's step's reward (diagnosed alike).
    training_step, training_steps = step, own_steps
    trained_reward, told_apart = trained_reward_words(surrogate_reward, reward_env, dense_variant)
    if surrogate_reward is not None:  # checked where it is given, from shapes: a refusal names it in one line
        check_step(env, step, observations, label)
        check_surrogate_reward(env, step, surrogate_reward, label)
        training_step = jit_traced_once(surrogate.user_surrogate(step, surrogate_reward))
    if reward_env is not None:
        training_steps = derivative_steps(traced, reward_env, contact_smoothing, gradient_substeps, label)
        training_step = jit_traced_once(joined(*training_steps))
        check_same_states(env, training_step, label)
    # The step a flat reward's surrogate reads (one jit for every trace of it): the values' step.
    values_step = training_step if training_steps[1] is None else jit_traced_once(training_steps[0])

    seen_size = observations + (int(env.action_size) if reward_direction_observed else 0)
    sizes = (seen_size, *hidden, int(env.action_size))
    reset = jax.jit(jax.vmap(env.reset))
    resets = {}  # count -> the reset of that many states, kept under diagnosis_key

    def sample_initial_states(key, count):
        keys = jax.random.split(key, count)
        if count not in resets:
            resets[count] = program_store.kept_function(reset, (keys,), diagnosis_key, "reset")
        return resets[count](keys)

    answer_key = None if diagnosis_key is None or not told_apart else {  # kept of this reward alone
        **diagnosis_key, "diagnosis_seed": diagnosis_seed, "reward_repairs": reward_repairs,
        "episode_length": episode_length,
        # the diagnosis reads the derivative, which the contacts' smoothing changes
        **({} if contact_smoothing is None else
           {"contact_smoothing": [contact_smoothing.margin, contact_smoothing.softness]}),
        **({} if gradient_substeps is None else {"gradient_substeps": gradient_substeps}),
        **({"contact_geometry": "held"} if contact_geometry_held else {}),
        **({"trained_reward": trained_reward} if trained_reward else {})}
    started: list[PendingDiagnosis] = []  # the diagnosis begun, where none was kept
    at_shapes: list[tuple] = []  # the step a surrogate would be made of, traced at shapes (once)
    choosing: list[Callable[[], dict]] = []  # a surrogate's choices, begun beside the check
    smoothing_key = None if answer_key is None else {**answer_key, "smoothing_scale": smoothing_scale}

    def traced_at_shapes() -> tuple | None:
        """The step a surrogate would be made of, traced at shapes (once); None where its reward cannot be told."""
        try:
            at_shapes[:] = at_shapes or [surrogate.trace_step(values_step, *surrogate.step_example(env))]
        except ValueError:  # no single leaf of the state is named reward: no surrogate could be made of it either
            return None
        return at_shapes[0]

    @functools.cache  # asked as the check begins and as the pending task is made
    def reward_compares() -> bool:
        """Whether the trained reward turns a comparison into a number, which the check may smooth; unknown: True."""
        return traced_at_shapes() is None or surrogate.turns_comparisons_into_numbers(at_shapes[0], surrogate.step_example(env))

    def start() -> PendingDiagnosis:
        try:
            started.append(start_diagnosis(env, training_step, jax.random.PRNGKey(diagnosis_seed), episode_length))
        except (TypeError, ValueError, AttributeError):  # a step that breaks the protocol fails the diagnosis's trace: say how
            check_step(env, step, observations, label)
            raise
        return started[0]

    diagnose = diagnose and smoothing_choices is None  # a run's recorded surrogate: its checks chose and passed it
    if not diagnose:  # nothing traces the step before the trainer: see that it keeps the protocol
        program_store.kept_answer(diagnosis_key, "protocol", lambda: check_step(env, step, observations, label))

    # Where none is kept, beside an accelerator a reward the check most likely keeps (one turning no comparison into
    # a number) is checked once the start asks, as its epoch compiles: the check's trace then holds back no compile.
    later: list[bool] = []  # whether the diagnosis begins once asked, where none was kept (else it has begun)

    def begin() -> Callable[[], Any]:
        try:  # a step that breaks the protocol is checked now, where the check's trace says how
            later.append(defer_diagnosis and smoothing == "auto" and surrogate_reward is None and
                         check_device() is not None and not reward_compares())
        except (TypeError, ValueError, AttributeError):
            later.append(False)
        return (lambda: (started[0] if started else start())()) if later[0] else start()  # once, whatever it raised

    if diagnose:
        pending = program_store.kept_answer_later(answer_key, "reward diagnosis", begin)
    advice = (f"train {dense_variant}, its dense variant; or " if dense_variant and reward_env is None else ""
              ) + "give the reward a slope (a tolerance with a margin > 0) or train a reward of your own"

    def diagnosed() -> RewardDiagnosis:
        """The diagnosis, waited for; ``EnvError`` for a reward with no usable gradient (flat: where it is not smoothed)."""
        diagnosis = RewardDiagnosis(*pending())
        if surrogate_reward is not None and diagnosis.kind in ("zero", "nan"):
            own = function_name(surrogate_reward)
            if diagnosis.kind == "zero":
                raise EnvError(f"{label}: the surrogate reward {own}'s gradient is zero at every sampled state and "
                               f"action (a constant, or a step of the state such as a threshold): BPTT has nothing to "
                               f"follow; give {own} a slope toward what it rewards (a distance's negative square, say)")
            raise EnvError(f"{label}: the surrogate reward {own}'s gradient is NaN at {diagnosis.nan_at_random:.0%} of "
                           f"sampled states with random actions: fix {own} (a square root or a norm taken at zero or "
                           "below, a log of zero, a NaN it returns?)")
        if diagnosis.kind == "zero" and smoothing == "off":
            raise EnvError(f"{label}: the reward's gradient is zero at every sampled state and action "
                           f"(a step function such as a tolerance with margin 0, or a margin so small next to the sampled distances that its slope underflows): BPTT has nothing to follow; {advice}")
        if diagnosis.kind == "nan":
            coarser = "" if gradient_substeps is None else (
                f", its derivative taken through {gradient_substeps} physics steps per control step where the env "
                f"simulates {own_substeps(env)} (a longer step's derivative can diverge where the env's does not: "
                "take more of them)")
            raise EnvError(f"{label}: the reward's gradient is NaN at {diagnosis.nan_at_random:.0%} of sampled states "
                           f"with random actions{' even after repairing ' + reward_repairs if reward_repairs else ''}"
                           f"{coarser}: {advice} (a norm taken at zero, a tolerance with an infinite bound and no margin?)")
        return diagnosis

    def init_params(key, zero_output, answer: Callable[[], str]):
        # The start is the trained reward's check's choice (``answer``): the values wait for it, shapes need none.
        start_off_zero = zero_output and not shapes_only() and answer() == "nan at zero action"
        params = mlp_init(key, sizes, zero_output and not start_off_zero)
        if start_off_zero:  # small, not zero: the reward's derivative is NaN at zero action
            weights, bias = params[-1]
            params[-1] = (SMALL_OUTPUT_SCALE * weights, bias)
        return StandardizedNetwork(params, no_observations(seen_size)) if normalize_observations else params

    summary = (f"{label}: {sizes[0]} observations{' (standardised by running statistics)' if normalize_observations else ''}, "
               f"{sizes[-1]} actions in [-1, 1]; windows of {horizon} steps, "
               f"loss: negative {'discounted (' + format(discount, 'g') + ') ' if discount < 1 else ''}return; "
               f"train/test loss: negative return of {episode_length}-step episodes"
               + ("; constraint solver differentiated at its solution" if has_constraint_solver(env) else "")
               + ("" if contact_smoothing is None else
                  f"; contacts smoothed in the derivative alone (acting from {contact_smoothing.margin:g} m, "
                  f"time constants x{contact_smoothing.softness:g})")
               + ("" if gradient_substeps is None else f"; derivative through {gradient_substeps} physics steps per control step")
               + ("; the contacts' points and frames held in the derivative" if contact_geometry_held else "")
               + ("; each physics step recomputed in the backward pass" if physics_steps_recomputed else "")
               + ("; the physics steps' loop carrying the state alone" if physics_steps_carrying_state else "")
               + ("; the policy sees the direction of its trained reward in its actions" if reward_direction_observed else "")
               + (f"; the squash's derivative at least {squash_gradient_floor:g}" if squash_gradient_floor else "")
               + (f"; the derivative cut at contact loads above {contact_gradient_cut:g} body weights" if contact_gradient_cut else ""))
    summary += f"; repaired: {reward_repairs}" if reward_repairs else ""
    summary += f"; {left_out.sensors} sensors nothing returned reads not simulated" if left_out.sensors else ""
    summary += ("; camera poses nothing returned reads not computed (held at the reset's)"
                if left_out.camera_poses_held else "")
    summary += f"; trained on {trained_reward} (returns reported: the env's own)" if trained_reward else ""

    def task(diagnosis: RewardDiagnosis | None, gradient: str, smoothed: tuple | None = None,
             answer: Callable[[], str] | None = None) -> Task:  # answer: the pending check's kind, waited for
        start = {"pending": "pending", "nan at zero action": "small"}.get(gradient, "zero")
        trained_step, smoothed_terms, choices = smoothed or (training_step, "", None)
        direction, seen, policy, sample, evaluation, episodes = parts_of(trained_step if reward_direction_observed else None)
        if smoothed and dense_variant and reward_env is None:  # measured: a sparse env's surrogate trains less far
            smoothed_terms += f" ({dense_variant}'s reward, its dense variant, may train further: --dense-reward)"
        return Task(
            name=label,
            dynamics=Dynamics(step=direction.stepping(cut(trained_step)), policy=policy, loss=rollout_loss(discount), horizon=int(horizon)),
            init_params=functools.partial(init_params, answer=answer or (lambda: gradient)),
            sample_initial_states=sample,
            summary=summary + "".join(f"; {part}" for part in (smoothed_terms, diagnosis and diagnosis.describe()) if part),
            resolved={"env": label, "horizon_steps": int(horizon), "discount": discount, "episode_length": episode_length,
                      "hidden": list(hidden), "reward_gradient": gradient,
                      "reward_repairs": reward_repairs, "policy_output_start": start,
                      **({"normalize_observations": True} if normalize_observations else {}),
                      **({"squash_gradient_floor": squash_gradient_floor} if squash_gradient_floor else {}),
                      **({"reward_direction_observed": True} if reward_direction_observed else {}),
                      **({"trained_reward": trained_reward} if trained_reward else {}),
                      **({"contact_gradient_cut": contact_gradient_cut} if contact_gradient_cut else {}),
                      **({"reward_smoothing": smoothed_terms, "reward_smoothing_choices": choices} if smoothed else {})},
            evaluation=evaluation, episodes=episodes, refresh_statistics=refresh_from(seen) if normalize_observations else None)

    def settle(wait: bool = True) -> Task | None:
        if not wait and later and not (started and started[0].done()):
            return None
        diagnosis = diagnosed()
        if diagnosis.kind != "zero" and smoothing != "always":
            return task(diagnosis, diagnosis.kind)
        # Flat at every sampled state, or smoothed always: a surrogate, fitted on the diagnosis's samples, and checked.
        samples = started[0].samples() if started else None

        def choose(traced) -> dict:  # on the diagnosis's samples, drawn again where its answer was kept
            drawn = samples or jax.jit(lambda key: sample_for_diagnosis(env, training_step, key, episode_length))(
                jax.random.PRNGKey(diagnosis_seed))
            return surrogate.smoothing_choices(training_step, *drawn, smoothing_scale, traced)

        # Its choices: begun beside the check where a surrogate most likely followed it, else fitted (or read) now.
        smoothed = surrogate_of(surrogate.one_sample(*samples) if samples else surrogate.step_example(env),
                                lambda traced, example: surrogate.as_recorded(choosing[0]() if choosing else program_store.kept_answer(
                                    smoothing_key, "reward smoothing", functools.partial(choose, traced))))
        # Its gradient is checked at those samples (the states it reaches are the env's), compiled beside what follows.
        checking: list[PendingDiagnosis] = []
        checked = program_store.kept_answer_later(smoothing_key, "surrogate's diagnosis", lambda: checking.append(
            start_checks(smoothed[0], *samples) if samples else
            start_diagnosis(env, smoothed[0], jax.random.PRNGKey(diagnosis_seed), episode_length)) or checking[0])

        def settle_surrogate(wait: bool = True) -> Task | None:
            if not wait and checking and not checking[0].done():
                return None
            again = RewardDiagnosis(*checked())
            if again.kind in ("zero", "nan"):
                raise EnvError(f"{label}: the reward's gradient is {again.kind} at every sampled state even after "
                               f"{smoothed[1]}: some term of it is flat beyond these comparisons; {advice}")
            return task(again, again.kind, smoothed)

        return dataclasses.replace(task(None, "pending", smoothed, lambda: RewardDiagnosis(*checked()).kind),
                                   settle=settle_surrogate)

    def surrogate_of(example: tuple, choose: Callable[[tuple, tuple], dict]) -> tuple:
        """A flat reward's surrogate step, what it smoothed in words, and its choices (``choose(traced, example)``): one
        trace of the values' step, at shapes, serves the choice and the surrogate (a choice names places in it)."""
        traced = at_shapes[0] if at_shapes else surrogate.trace_step(values_step, *example)
        choices = choose(traced, example)
        smooth_step, smoothing_done = surrogate.smoothed_step(traced, choices)
        if not smoothing_done.anything:
            raise EnvError(f"{label}: " + ("smoothing always, but" if smoothing == "always" else "the reward's gradient is zero at every sampled state and action, and") + " no "
                           f"comparison of the reward could be smoothed (its steps are not comparisons made numbers) nor exponential of it widened (none vanishes): "
                           + ('train it as written (--smoothing auto; smoothing="auto" from Python)' if smoothing == "always" else advice))
        if training_steps[1] is not None:
            smooth_step = joined(smooth_step, surrogate.smoothed_alike(jax.jit(training_steps[1]), choices, example, label))
        # One jit, as the env's step has: each program tracing the surrogate reuses one interpretation per shape.
        return jit_traced_once(smooth_step), smoothing_done.describe(), choices

    if smoothing_choices is not None:  # a run's surrogate, as recorded: the checks that chose it are not run again
        return task(None, "as recorded", surrogate_of(surrogate.step_example(env), lambda traced, example:
                                                      surrogate.checked_places(traced, smoothing_choices, example, label)))
    if not diagnose:
        return task(None, "not checked")
    if defer_diagnosis and later:  # a kept diagnosis is read, and may refuse, at once
        compares = smoothing == "auto" and surrogate_reward is None and reward_compares()
        # A surrogate most likely follows the check: beside an accelerator its host's cores fit its choices meanwhile.
        if (compares or smoothing == "always") and check_device() is not None and traced_at_shapes() is not None:
            choosing.append(program_store.kept_answer_later(smoothing_key, "reward smoothing", lambda: surrogate.choices_beside(
                at_shapes[0], started[0].sample_shapes, lambda: started[0].samples(), smoothing_scale)))
        return dataclasses.replace(task(None, "pending", answer=lambda: diagnosed().kind), settle=settle, compile_while_settling=(
            (check_device() is not None or jax.default_backend() == "cpu") and smoothing != "always" and not compares))
    answered = settle()  # a flat reward's surrogate may still be checked beside: deferred, the caller waits
    return answered if defer_diagnosis else answered.settled_fully()
