"""An environment in Brax's protocol as a task: MuJoCo Playground's registry by name, or any importable env.

    python scripts/train.py --env CartpoleSwingup --steps 128
    python scripts/train.py --env my_lab.envs:make_arm_env --steps 50

The loss of a training rollout is its negative return; every epoch's train and
test losses are the negative episode return from fresh resets, as Playground
and Brax report it (``stablebptt.envs.adapter``).
"""
from __future__ import annotations

import functools
import importlib.metadata
import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from typing import Callable

from stablebptt.engine.config import MAX_COUNT, MAX_DEPTH, TrainConfig
from stablebptt.engine.task import Task
from stablebptt.envs.adapter import env_task
from stablebptt.envs.protocol import load_env, load_reward
from stablebptt.errors import InputError, check_field_types, config_field, keywords_named
from stablebptt.physics.backward_contacts import ContactSmoothing, check_smoothing

DEFAULT_EPOCHS = 200
# Windows of 128 steps along carried episodes beat 32 and 512 for R and C on CartpoleSwingup and
# AcrobotSwingup (the window study of results/LOG.md). Runs recorded with steps 0
# before trained windows of the former default, and keep them (``recorded_config``).
DEFAULT_STEPS = 128
FORMER_DEFAULT_STEPS = 100
# Training on carried episodes: the states carried per seed, and the fresh starts of the train and test returns.
# Norm clipping: every measured run on an environment clipped the gradient's global norm at 1
# (results/LOG.md); value clipping, the paper's default, was never measured there.
TRAIN_DEFAULTS = {"batch": 64, "train_size": 16, "test_size": 16, "clip": "norm"}
MAX_STEPS = 100_000
# Options measured together on the contact-rich envs, named so that one word trains with them
# (``--recipe``; docs/performance.md, "The locomotion recipe"): windows of 16 steps whose return a
# critic of standardised observations bootstraps, discounted, 256 carried envs per seed, a
# stochastic actor (noise of deviations learned from 0.3, its entropy weighed 0.01), and the state a
# time limit cuts an episode at valued by the critic. An epoch's time follows its env steps, not its
# windows, so windows of 16 make twice the updates of 32 in a second.
# Each key is a training or task option; an option given beside the recipe wins.
RECIPES = {"locomotion": {"steps": 16, "discount": 0.99, "critic": True, "normalize_critic_observations": True,
                          "batch": 256, "action_noise": 0.3, "learn_action_noise": True, "entropy": 0.01,
                          "value_at_time_limit": True}}
# A recipe's values for the envs that measured better with others (docs/performance.md): the walker's
# control step spans 10 physics steps, and on each of its three tasks windows of 8 steps (80 physics
# steps) learned faster than 16 at every epoch ("Windows of 8 on the walker"); on WalkerWalk and
# WalkerStand windows of 4 faster again by 300 s, twice the updates for the same env steps ("Windows
# of 4 on the walker"; WalkerRun learned no faster with them), and windows of 2 faster than 4 on those
# two and than 8 on WalkerRun ("Windows of 2 on the walker"); on the cheetah, C and R learn alike epoch for
# epoch, and R alone (no g_M for the cosine) updates in 0.84x C's time ("R alone on the cheetah"); on
# the reacher and the finger's turn the policy sees the reward's direction in its actions, which
# lifts the reachers from 9% of PPO's published return to 103% by 300 s ("The direction to push,
# observed") and FingerTurnEasy from 15% to 60% ("The direction carried by the state"; FingerTurnHard,
# the same finger with a smaller target, was measured with it alone); on the walkers it learned no
# faster epoch for epoch and its update took 1.75x the time. On the finger's turn one seed in five met a
# non-finite gradient of flows R and M (C's update finite) that stopped it; left at zero, every seed trains
# on ("A seed that goes on through non-finite flows"). FingerTurnHard reaches its targets above the spinner's
# hinge with none of them: with windows of 4 and noise from 0.6 (its entropy weighed 0.003) some seeds find
# the flick those targets need, 41-52% of PPO's published return by 300 s in two runs of the reported seeds
# and 44% on the tuning seeds, against 42% with noise from 0.3 ("The finger's hard turn with noise from
# 0.6"; "Noise from 0.6 on the hopper, the finger again"). HopperStand must rise from the floor: noise
# from 0.6 stood it at 2.0 by 300 s on the reported seeds against 1.0 from 0.3, 16.2 on the tuning seeds;
# its training episodes cut at 64 steps show the windows a hopper's first steps, where it rises, 15 times
# as often: level with the uncut recipe's 2.0 by 300 s (1.5-2.7 in three runs from empty compile caches),
# 154.3 by 891 s against Brax PPO's 28.7 ("HopperStand cut at 64 for 900 s").
# FingerSpin must find the spin from nothing: noise from 0.6 reached 20% of PPO's published return by 300 s
# on the reported seeds against 14% from 0.3, 26% on the tuning seeds ("Noise from 0.6 on the spinner's
# reported seeds, a decaying step on the hopper, the humanoid's start on one host"). FishSwim's target term
# is exp(-35) at its median sampled state, lost beside its upright term: widened (smoothing always), the
# reported seeds reached 125.7 by 300 s against 76.2 ("The fish's target widened").
RECIPES_BY_ENV = {"locomotion": {"WalkerWalk": {"steps": 2}, "WalkerStand": {"steps": 2}, "WalkerRun": {"steps": 2},
                                 "CheetahRun": {"mode": "R", "cosine": False},
                                 **{env: {"observe_reward_direction": True} for env in ("ReacherEasy", "ReacherHard")},
                                 "FingerTurnEasy": {"observe_reward_direction": True, "nonfinite_flows": "zero"},
                                 "FingerTurnHard": {"observe_reward_direction": True, "nonfinite_flows": "zero",
                                                    "steps": 4, "action_noise": 0.6, "entropy": 0.003},
                                 "FingerSpin": {"action_noise": 0.6},
                                 "HopperStand": {"action_noise": 0.6, "training_episode_length": 64},
                                 "FishSwim": {"smoothing": "always"}}}
# A recipe's value chosen for a value of another option (a test of that option's value): given a value beside the
# recipe that fails it, the option keeps its own default, and what was chosen for it goes in turn (docs/running.md).
RECIPE_VALUES_CHOSEN_FOR = {
    "cosine": (("mode", lambda mode: mode == "R"),), "nonfinite_flows": (("mode", lambda mode: mode == "C"),),
    "smoothing": (("reward_check", lambda check: check), ("surrogate_reward", lambda reward: not reward)),
    **{option: (("episodes", lambda episodes: episodes != "off"),) for option in ("critic", "batch", "action_noise")},
    # The cut was measured with the cut state valued, on the env's own episodes.
    "training_episode_length": (("value_at_time_limit", lambda valued: valued), ("episode_length", lambda length: not length)),
    **{option: (("critic", lambda critic: critic),) for option in ("normalize_critic_observations", "value_at_time_limit")},
    "learn_action_noise": (("action_noise", lambda noise: noise > 0),),
    "entropy": (("learn_action_noise", lambda learned: learned),)}
# --physics-step-residuals: each choice as env_task's physics_steps_recomputed (None: by the env's physics steps).
PHYSICS_STEP_RESIDUALS = {"auto": None, "recomputed": True, "stored": False}
# --physics-step-carry: each choice as env_task's physics_steps_carrying_state.
PHYSICS_STEP_CARRIES_STATE = {"data": False, "state": True}
# A task option whose env_task argument has another name or value: that name, and the value from the option's
# (a run's task is made through it, and a recipe's options given from Python; --steps 0 is the task's own horizon).
ENV_TASK_ARGUMENTS = {"steps": ("horizon", int), "observe_reward_direction": ("reward_direction_observed", bool),
                      "physics_step_carry": ("physics_steps_carrying_state", PHYSICS_STEP_CARRIES_STATE.__getitem__),
                      "physics_step_residuals": ("physics_steps_recomputed", PHYSICS_STEP_RESIDUALS.__getitem__)}


def recipe_options(name: str, env: str = "", given: Mapping[str, object] | None = None) -> dict:
    """The options recipe ``name`` sets, for the env named ``env`` (its name in MuJoCo Playground's
    registry) where ``RECIPES_BY_ENV`` has values of its own for it. ``given``: the options a user sets
    beside it, which win, and which leave out the recipe's values chosen for another value of theirs
    (``RECIPE_VALUES_CHOSEN_FOR``)."""
    if not isinstance(name, str) or name not in RECIPES:
        raise InputError(f"no recipe {name!r}: choose one of {', '.join(sorted(RECIPES))}")
    if not isinstance(env, str):
        raise InputError(f"a recipe's env is the env's name (a string, as --env takes it), got {type(env).__name__}")
    own = RECIPES_BY_ENV.get(name, {})
    spelled = [known for known in own if known.lower() == env.lower() and known != env]
    if spelled:  # its own values would be left out without a word: a name of yours alone takes the common ones
        raise InputError(f"recipe {name} has options of its own for {spelled[0]}, not {env!r}: name the env as the "
                         f"registry does")
    options = {**RECIPES[name], **own.get(env, {})}
    defaults = {option.name: option.default for config in (TrainConfig, Config) for option in fields(config)}
    while True:  # until no value left out leaves another's reason gone
        chosen = {**defaults, **options, **(given or {})}  # every option's value as the run will take it
        apart = {option for option in options if option not in (given or {}) and
                 any(not test(chosen[other]) for other, test in RECIPE_VALUES_CHOSEN_FOR.get(option, ()))}
        if not apart:
            return options
        options = {option: value for option, value in options.items() if option not in apart}


def recipe(name: str, env: str = "") -> tuple[dict, dict]:
    """A recipe of ``RECIPES`` from Python, for the env named ``env``: ``env_task``'s keyword arguments
    and ``TrainConfig``'s fields.

        task_options, train_options = sb.recipe("locomotion", "CheetahRun")
        sb.train(sb.env_task(env, **task_options), sb.TrainConfig(**train_options, seeds=5))
    """
    options = recipe_options(name, env)
    task_fields = {option.name for option in fields(Config)}
    task_options = {}
    for key, value in options.items():  # the task option --steps is env_task's horizon, and so on
        if key in task_fields:
            argument, value_of = ENV_TASK_ARGUMENTS.get(key, (key, lambda given: given))
            task_options[argument] = value_of(value)
    return task_options, {key: value for key, value in options.items() if key not in task_fields}


@keywords_named
@dataclass(frozen=True)
class Config:
    env: str = field(default="", metadata={"help": "an environment: a name in MuJoCo Playground's registry (e.g. CartpoleSwingup; pip install 'stablebptt[playground]'), or package.module:attribute, an environment in Brax's protocol or a factory of one"})
    steps: int = field(default=0, metadata={"help": "override the horizon in steps (0: the task's own)"})
    discount: float = field(default=1.0, metadata={"help": "per-step discount of the training rollout's return, in (0, 1]"})
    episode_length: int = field(default=0, metadata={"help": "steps of the evaluation episodes whose return every epoch logs (0: the environment's own)"})
    reward_check: bool = field(default=True, metadata={"help": "before training, look at the reward's gradient at sampled states and refuse a reward that has none (--no-reward-check skips it: a quicker start, no refusal)"})
    smoothing: str = field(default="auto", metadata={"help": "auto: where the reward check finds the reward's gradient zero at every sampled state, train on a smooth surrogate (the comparisons the reward makes numbers of become sigmoids, its exponentials that vanish at the sampled states widen; the reported returns stay the true reward's); always: the surrogate whatever the check finds (a term that vanishes beside the others, as FishSwim's target does); off: refuse a reward whose gradient is zero", "choices": ("auto", "always", "off")})
    surrogate_reward: str = field(default="", metadata={"help": "package.module:function, a reward of the state a step reaches that the windows train on in place of the env's (its gradient diagnosed, not smoothed); every reported return stays the env's"})
    dense_reward: bool = field(default=False, metadata={"help": "a ...Sparse env of MuJoCo Playground's trains on its dense variant's reward (the same model and states); every reported return stays the sparse one's"})
    policy_width: int = field(default=64, metadata={"help": "units in each of the policy's hidden layers (tanh)"})
    policy_depth: int = field(default=2, metadata={"help": "the policy's hidden layers (0: actions linear in the observations, then squashed)"})
    normalize_observations: bool = field(default=False, metadata={"help": "the policy sees its observations standardised by the running mean and deviation of all those its training windows met (the statistics are kept with its parameters)"})
    smoothing_scale: float = field(default=1.0, metadata={"help": "the surrogate's temperatures: this times the median difference each smoothed comparison meets at the sampled states"})
    contact_gradient_margin: float = field(default=0.0, metadata={"help": "metres: the derivative is taken through the env's model with every contact acting from this far (the simulation stays the file's; 0: contacts as the file says)"})
    contact_gradient_softness: float = field(default=1.0, metadata={"help": "the derivative is taken through the env's model with every contact's time constant this many times the file's, >= 1 (the simulation stays the file's)"})
    contact_gradient_geometry: str = field(default="exact", metadata={"help": "held: the derivative holds the point and frame of each contact between planes, spheres, capsules and boxes on a plane, and differentiates its distance by the closed form n . (v2 - v1), exact to first order for those pairs, so MJX's collision functions of those pairs are not differentiated (a shorter update: docs/performance.md); other pairs keep MJX's derivative. exact: MJX's own derivative of its collision. The simulation stays the file's", "choices": ("exact", "held")})
    physics_step_residuals: str = field(default="auto", metadata={"help": "what reverse mode keeps of each physics step for the backward pass: recomputed, the state it starts from, the constraint solver's solution and the values of MJX's functions this package differentiates, the rest of the step run again in the backward pass (jax.checkpoint: the same derivative, a shorter update where a control step spans several physics steps, as the walkers' and the humanoids' do: docs/performance.md); stored, every intermediate; auto: recomputed where a control step's derivative spans more than one physics step", "choices": tuple(PHYSICS_STEP_RESIDUALS)})
    physics_step_carry: str = field(default="data", metadata={"help": "what MuJoCo Playground's loop of a control step's physics steps carries from one to the next: data, the whole of MJX's data (the env's own loop); state, only what a physics step reads (MuJoCo's integration state, the inputs and the solver's warm start), the last step taken after the loop: the same physics, values equal to rounding, the step traced twice (on one H100 FishSwim's update ran in 250.8 ms against 290.3, compiling 6.2 s longer: docs/performance.md)", "choices": tuple(PHYSICS_STEP_CARRIES_STATE)})
    gradient_substeps: int = field(default=0, metadata={"help": "the derivative is taken through each control step in this many physics steps of equal length, a divisor of the env's own count (MuJoCo Playground's WalkerWalk simulates 10; 0: the env's own): a shorter backward pass; the simulation stays the file's"})
    squash_gradient_floor: float = field(default=0.0, metadata={"help": "the derivative of the policy's tanh squash is kept at least this, in [0, 1): an action at its bound, where tanh's slope is nearly 0, still passes this share of its gradient back to the policy; its values, and every action taken, stay tanh's (0: tanh's own derivative)"})
    contact_gradient_cut: float = field(default=0.0, metadata={"help": "the windows' derivative stops at a state whose constraint forces pass this many body weights (the norm of MJX's qfrc_constraint over the model's weight): a window's later rewards reach no earlier state or action through a hard contact, the reward of that state still does; its values, and every return, stay the env's (0: no cut; MuJoCo Playground's envs)"})
    observe_reward_direction: bool = field(default=False, metadata={"help": "the policy also sees, after its observation, the unit direction in its actions that raises the reward it trains on one control step on, computed by the differentiable step at still actions (held as an observation; one more step and its derivative for every state a step or a reset reaches, which the state carries): the reacher's policy, parked by its raw observation, reaches PPO's return with it in the probe of docs/performance.md"})
    sloped_reward_tails: bool = field(default=False, metadata={"help": "a MuJoCo Playground env's tolerance rewards whose linear, quadratic or cosine sigmoid ends at 0 (the walker's move reward at speed <= 0, the cheetah's run reward) keep, in the derivative only, the sigmoid's mean slope past that end: where the reward was flat the windows' gradient points towards its bounds; its values, and every return, stay as written"})

    def __post_init__(self):
        check_field_types(self)
        if not 0 <= self.steps <= MAX_STEPS:
            raise InputError(f"{config_field(self, 'steps')} must be between 1 and {MAX_STEPS} (or 0 for {DEFAULT_STEPS}), got {self.steps}")
        if not (math.isfinite(self.discount) and 0 < self.discount <= 1):
            raise InputError(f"{config_field(self, 'discount')} must be in (0, 1], got {self.discount}")
        if self.smoothing not in ("auto", "always", "off"):
            raise InputError(f"{config_field(self, 'smoothing')} must be auto, always or off, got {self.smoothing!r}")
        if not (math.isfinite(self.smoothing_scale) and self.smoothing_scale > 0):
            raise InputError(f"{config_field(self, 'smoothing_scale')} must be a positive number, got {self.smoothing_scale}")
        if self.surrogate_reward and self.dense_reward:
            raise InputError(f"give {config_field(self, 'surrogate_reward')} or {config_field(self, 'dense_reward')}, "
                             "not both: the windows train on one reward")
        check_smoothing(self.contact_gradient_margin, self.contact_gradient_softness,
                        config_field(self, "contact_gradient_margin"), config_field(self, "contact_gradient_softness"))
        if self.contact_gradient_geometry not in ("exact", "held"):
            raise InputError(f"{config_field(self, 'contact_gradient_geometry')} must be exact or held, "
                             f"got {self.contact_gradient_geometry!r}")
        if self.physics_step_residuals not in PHYSICS_STEP_RESIDUALS:
            raise InputError(f"{config_field(self, 'physics_step_residuals')} must be auto, recomputed or stored, "
                             f"got {self.physics_step_residuals!r}")
        if self.physics_step_carry not in PHYSICS_STEP_CARRIES_STATE:
            raise InputError(f"{config_field(self, 'physics_step_carry')} must be data or state, "
                             f"got {self.physics_step_carry!r}")
        if self.gradient_substeps < 0:
            raise InputError(f"{config_field(self, 'gradient_substeps')} must be a whole number of physics steps >= 1 "
                             f"(or 0 for the env's own), got {self.gradient_substeps}")
        if not (math.isfinite(self.squash_gradient_floor) and 0 <= self.squash_gradient_floor < 1):
            raise InputError(f"{config_field(self, 'squash_gradient_floor')} must be in [0, 1), got {self.squash_gradient_floor}")
        if not (math.isfinite(self.contact_gradient_cut) and self.contact_gradient_cut >= 0):
            raise InputError(f"{config_field(self, 'contact_gradient_cut')} must be a number of body weights >= 0 (0: no cut), "
                             f"got {self.contact_gradient_cut}")
        if not 1 <= self.policy_width <= MAX_COUNT:
            raise InputError(f"{config_field(self, 'policy_width')} must be a whole number of units from 1 to {MAX_COUNT}, got {self.policy_width}")
        if not 0 <= self.policy_depth <= MAX_DEPTH:
            raise InputError(f"{config_field(self, 'policy_depth')} must be a whole number of layers from 0 to {MAX_DEPTH}, got {self.policy_depth}")
        if not 0 <= self.episode_length <= MAX_STEPS:
            raise InputError(f"{config_field(self, 'episode_length')} must be between 1 and {MAX_STEPS} (or 0 for the environment's own), got {self.episode_length}")

    def conflicts(self) -> list[str]:
        """Options set together where one makes the other meaningless (``checks.check_options``): what the
        smoothing options change happens only where the reward check runs (auto: where it finds the reward flat)."""
        field = lambda name: config_field(self, name)  # noqa: E731
        defaults = Config()
        problems = []
        if self.smoothing == "always" and self.surrogate_reward:
            problems.append(f"{field('smoothing')} always smooths the env's reward, and {field('surrogate_reward')} "
                            f"{self.surrogate_reward} is trained as given: drop one")
        if not self.reward_check and self.smoothing != defaults.smoothing:
            does = ("refuses a reward the check finds flat" if self.smoothing == "off"
                    else "makes its surrogate of the check's sampled states")
            problems.append(f"{field('smoothing')} {self.smoothing} {does}, and "
                            f"{field('reward_check')} is off: drop it, or leave the check on")
        if self.smoothing_scale != defaults.smoothing_scale and (self.smoothing == "off" or not self.reward_check):
            off, keep = ((field("smoothing"), f"{field('smoothing')} auto") if self.smoothing == "off"
                         else (field("reward_check"), "the check on"))
            problems.append(f"{field('smoothing_scale')} {self.smoothing_scale:g} scales the surrogate trained where "
                            f"the reward check finds the reward flat, and {off} is off: no surrogate is made; drop it, "
                            f"or leave {keep}")
        return problems


def run_name(config: Config) -> str:
    """The environment's name in run folders: the registry name, or the attribute of package.module:attribute."""
    return config.env.rpartition(":")[2] or config.env


def make(config: Config) -> Task:
    return _make(config, defer_diagnosis=False)


def make_deferred(config: Config) -> Task:
    """``make``, returned while the reward diagnosis compiles and runs beside the caller: the task's
    ``settled()`` waits for it and may refuse the reward (``env_task(defer_diagnosis=True)``)."""
    return _make(config, defer_diagnosis=True)


def make_as_recorded(config: Config, resolved: dict, deferred: bool = False) -> Task:
    """``make`` (``make_deferred`` where ``deferred``) for a run that resumes or is reopened, its record saying
    what the task resolved to (``resolved``): a reward the run trained on a surrogate of keeps that surrogate's
    temperatures, rather than fitting them again on this machine's samples (another backend's draw moves them
    in their third digit), and its checks, which chose and passed it, are not run again. A reward its check
    passed as written (usable, the policy started at zero) is not checked again either: a resume on a machine
    whose compile cache does not hold the answer compiled and ran the check anew."""
    if not resolved.get("reward_smoothing") and resolved.get("reward_gradient") == "usable":
        task = _make(replace(config, reward_check=False), defer_diagnosis=deferred)
        # Said as the run's own check found it, and recorded so: a later resume of it skips the check too.
        return replace(task, summary=f"{task.summary}; reward gradient: usable (as the run's first check found)",
                       resolved={**task.resolved, "reward_gradient": "usable"})
    return _make(config, defer_diagnosis=deferred, smoothing_choices=resolved.get("reward_smoothing_choices"))


def _make(config: Config, defer_diagnosis: bool, smoothing_choices: dict | None = None) -> Task:
    if not config.env:
        raise InputError(f"give {config_field(config, 'env')}: a MuJoCo Playground name or package.module:attribute")
    env = load_env(config.env)
    dense, reward_context, reward_repairs = "", None, ""
    if ":" not in config.env:  # a name of MuJoCo Playground's registry (load_env has imported it)
        from stablebptt.envs import playground
        dense = playground.dense_variant(config.env)
        if config.sloped_reward_tails:
            reward_context = functools.partial(playground.repaired_rewards, sloped_tails=True)
            reward_repairs = playground.SLOPED_TAILS
    elif config.sloped_reward_tails:
        raise InputError(f"{config_field(config, 'sloped_reward_tails')} slopes MuJoCo Playground's reward tolerances "
                         f"in a registry env's step, and {config.env} is not a registry name: drop it")
    # A registry env's name and the package versions say what its reward computes: its diagnosis is
    # kept for an identical later run, like its programs.
    inputs = program_inputs(config)
    reward_env = dense_reward_env(config, dense)
    smoothing = ContactSmoothing(config.contact_gradient_margin, config.contact_gradient_softness)
    task = env_task(env, horizon=config.steps or DEFAULT_STEPS, discount=config.discount,
                    hidden=(config.policy_width,) * config.policy_depth,
                    episode_length=config.episode_length or None, name=run_name(config), dense_variant=dense,
                    reward_context=reward_context, reward_repairs=reward_repairs,
                    diagnose=config.reward_check, defer_diagnosis=defer_diagnosis, smoothing=config.smoothing,
                    smoothing_scale=config.smoothing_scale, normalize_observations=config.normalize_observations,
                    surrogate_reward=load_reward(config.surrogate_reward) if config.surrogate_reward else None,
                    reward_env=reward_env,
                    contact_smoothing=smoothing, gradient_substeps=config.gradient_substeps or None,
                    squash_gradient_floor=config.squash_gradient_floor,
                    contact_gradient_cut=config.contact_gradient_cut,
                    contact_geometry_held=config.contact_gradient_geometry == "held",
                    smoothing_choices=smoothing_choices,
                    **{argument: value_of(getattr(config, option))  # the options env_task names otherwise
                       for option, (argument, value_of) in ENV_TASK_ARGUMENTS.items() if option != "steps"},
                    diagnosis_key=None if inputs is None else {"env": config.env, "inputs": inputs})
    if ":" in config.env:
        return task
    # A registry env is its name and the package's release: the run records which, and resumes only on it.
    return _with_release(task, _playground_version())


def dense_reward_env(config: Config, dense: str) -> object:
    """The env whose step's reward the windows train on where ``--dense-reward`` asks for ``dense``, the
    env's dense variant; None: the env's own step (or the user's surrogate on it)."""
    if not config.dense_reward:
        return None
    if not dense:
        raise InputError(f"{config_field(config, 'dense_reward')}: {config.env} has no dense variant in MuJoCo "
                         "Playground's registry (its ...Sparse envs have one); give --surrogate-reward instead")
    return load_env(dense)


def _with_release(task: Task, version: str) -> Task:
    """``task`` resolved with MuJoCo Playground's release, also once its pending check has settled."""
    return _also_once_settled(task, lambda known: replace(known, resolved={**known.resolved,
                                                                          "playground_version": version}))


def _also_once_settled(task: Task, change: Callable[[Task], Task]) -> Task:
    """``change(task)``, and ``change`` of the task its pending check settles into (``Task.settle``)."""
    settle = task.settle
    if settle is not None:
        def settle_changed(wait: bool = True) -> Task | None:
            settled = settle(wait)
            return None if settled is None else _also_once_settled(settled, change)
        task = replace(task, settle=settle_changed)
    return change(task)


def _playground_version() -> str:
    return importlib.metadata.version("playground")


def check_resume(config: Config, record: dict) -> str:
    """Before a run of ``config`` resumes from its ``record``: ``InputError`` where MuJoCo Playground's
    release differs from the one the run began with; else the line to tell the user of what the library
    cannot check (an environment of their own package), or ''."""
    own = [spec for spec in (config.env, config.surrogate_reward) if ":" in spec]
    if own:
        modules = " or ".join(spec.partition(":")[0] for spec in own)
        return (f"note: the run trains {' on '.join(own)}, code of your own that the library cannot check: if "
                f"{modules} changed since the run began, its metrics change at the resume")
    began = record.get("resolved_task", {}).get("playground_version")
    now = _playground_version()
    if began is not None and began != now:
        raise InputError(f"the run began on MuJoCo Playground {began}, and {now} is installed: {config.env}'s "
                         f"rewards may differ; install playground=={began} to resume it, or train anew")
    return ""


def recorded_config(config: Config, record: dict) -> Config:
    """``config`` as the run of ``record`` trained it: 'steps 0' meant the default of the run's day,
    which its resolved task records."""
    if config.steps == 0:
        steps = (record.get("resolved_task") or {}).get("horizon_steps", FORMER_DEFAULT_STEPS)
        return replace(config, steps=int(steps))
    return config


def for_reopening(config: Config, resolved: dict) -> Config:
    """A trained run's task needs no reward check: it was made before training, and a rendering or
    a study of the run would otherwise compile the check's program again. Where the check smoothed the
    reward (``resolved``, the run's record, says so) the check stays on: the task is made as recorded
    (``make_as_recorded``), its surrogate of the record's temperatures with no check; a record older than
    them has them fitted again on the check's samples. Without the surrogate the windows' reward, and the
    direction a policy observes of it, would be the reward as written."""
    return config if resolved.get("reward_smoothing") else replace(config, reward_check=False)


def program_inputs(config: Config) -> dict | None:
    """What the task's compiled programs read besides the library and ``config``: a Playground env is
    its registry name and the package's version (in every key); an env or a surrogate reward of the
    user's own package could change unseen (None: traced every run)."""
    return None if ":" in config.env or config.surrogate_reward else {}
