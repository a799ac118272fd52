"""The options of a training run (``TrainConfig``) and its seeds."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import jax
import jax.extend
import jax.numpy as jnp

from stablebptt.errors import InputError, check_field_types, config_field, keywords_named
from stablebptt.flows.modes import MODE_TABLE, MODES

CLIP_MODES = ("value", "norm", "none")
SEED_BATCHING = ("auto", "map", "vmap")
EPOCH_PROGRAMS = ("auto", "whole", "per-update")
EPISODE_CHOICES = ("auto", "on", "off")
NONFINITE_FLOW_CHOICES = ("stop", "zero")
# What a run's record that lacks a field trained with: the field came later, and its default is not
# what such a run did (an environment's run before episode training trained from fixed resets).
# A run recorded before evaluations had a cadence evaluated inside every epoch.
RECORDED_BEFORE = {"episodes": "off", "eval_every": "epoch"}
# Operations in one traced step above which a scene counts as large: ``epoch_program="auto"``
# compiles it per update, and forward mode pushes all its tangents in one pass. XLA's CPU compiler
# can take many minutes and gigabytes for a program that inlines a contact model's step many times
# (updates, rollouts, one Jacobian pass per input, evaluation), where fewer copies compiled apart
# take a few minutes. The built-in tasks' steps (the cart-poles: about 4,000) are small; so are the
# DeepMind Control Suite's contact scenes whose step is generated (stablebptt/physics/rigid_body.py), while
# through MJX's stages they are large.
LARGE_STEP = 8_000
MAX_SEED = 2**32 - 1  # seeds are unsigned 32-bit PRNG seeds
MAX_COUNT = 2**31 - 1  # a count of states, units or networks: an array's dimension XLA indexes
MAX_DEPTH = 1000  # a network's hidden layers, built and traced one by one in Python
# JAX's names of float32 matrix products' precision (jax.default_matmul_precision).
MATMUL_PRECISIONS = ("default", "high", "highest")
# Training options that decide when a run stops or saves, and nothing it computes: a checkpoint and the
# kept programs belong to a run whatever they are (a resume may ask for more epochs or another budget).
STOPPING_OPTIONS = ("epochs", "budget", "checkpoint_every")
# A budget plans each epoch to come as long as the slowest of this start's last few after its first: a GPU's
# epochs of equal updates differ by a few percent, and a stalled one (a busy host) is forgotten after these.
PACE_EPOCHS = 3
# ... and leaves this share of the planned seconds spare: a cut epoch's updates ran up to 7% slower than the
# whole epochs' before it and an evaluation up to 5% longer than the longest before it (FingerTurnHard ended
# a budget of 300 s at 301.3 s without it; docs/performance.md, "The finger's hard turn with noise from 0.6").
BUDGET_MARGIN = 0.1


@keywords_named
@dataclass(frozen=True)
class TrainConfig:
    """Training options shared by every task; the defaults are the paper's."""

    mode: str = field(default="C", metadata={"help": "gradient flow: " + ", ".join(f"{m.name} ({m.description})" for m in MODE_TABLE.values()), "choices": MODES})
    clip: str = field(default="value", metadata={"help": "gradient clipping: value (each element to +-threshold), norm (global norm), none", "choices": CLIP_MODES})
    clip_threshold: float = field(default=1.0, metadata={"help": "threshold of value and norm clipping"})
    epochs: int = field(default=1000, metadata={"help": "number of passes over the training set"})
    seeds: int = field(default=1, metadata={"help": "independent seeds trained in one compiled program"})
    seed: int = field(default=42, metadata={"help": "first network seed; seed k uses seed+k"})
    lr: float = field(default=1e-3, metadata={"help": "Adam learning rate"})
    adam_b1: float = field(default=0.9, metadata={"help": "Adam's decay of its gradient average, in [0, 1), the policy's and the critic's (SHAC and Brax APG: 0.7)"})
    adam_b2: float = field(default=0.999, metadata={"help": "Adam's decay of its squared-gradient average, in [0, 1), the policy's and the critic's (SHAC and Brax APG: 0.95)"})
    lr_decay: float = field(default=1.0, metadata={"help": "the learning rate's factor per update, in (0, 1] (1: constant; Brax APG decays by 0.997)"})
    batch: int = field(default=8, metadata={"help": "initial states per update (training on episodes: the states carried from update to update)"})
    train_size: int = field(default=256, metadata={"help": "training initial states (training on episodes: the fresh starts whose episode return the train loss reports)"})
    test_size: int = field(default=256, metadata={"help": "test initial states"})
    data_seed: int = field(default=42, metadata={"help": "seed of the training and test initial states (shared by all network seeds)"})
    zero_output: bool = field(default=True, metadata={"help": "start the output layer at zero as the original run scripts do (--no-zero-output: Glorot)"})
    cosine: bool = field(default=True, metadata={"help": "also compute g_M and g_R in every mode to log their cosine (--no-cosine: only the flows the mode needs)"})
    x64: bool = field(default=False, metadata={"help": "run everything in float64"})
    matmul_precision: str = field(default="default", metadata={"help": "float32 matrix products: default (JAX's: a GPU may take TF32, about 3 decimal digits), high (on a GPU TF32 as well), highest (full float32; a CPU computes in full at every setting)", "choices": MATMUL_PRECISIONS})
    unroll: int = field(default=1, metadata={"help": "rollout steps per loop iteration (1 is fastest on a CPU, and for envs on a GPU; 5-10 for the paper's tasks on a GPU, see Plan.unroll)"})
    checkpoint_every: int = field(default=1, metadata={"help": "epochs between checkpoints"})
    seed_batching: str = field(default="auto", metadata={"help": "how seeds share one program: vmap (batched: on a GPU an update of 5 seeds costs little more than one seed's; equal to a solo run only to float rounding), map (one after another, each bit-identical to the seed trained alone), auto (vmap for several seeds)", "choices": SEED_BATCHING})
    devices: int = field(default=1, metadata={"help": "devices (GPUs) one run spreads over, the first N that JAX sees (0: all): the states each update rolls (--batch) split evenly across them, the parameters held whole on each"})
    episodes: str = field(default="auto", metadata={"help": "on: train on whole episodes, --batch states carried from update to update, each update one window of the horizon from where they stand, an ended episode started again from a fresh state (drawn once an epoch), an epoch one episode's length of windows; off: the paper's protocol, one window from each of the fixed training states; auto: on for tasks with episodes (environments), off for the others", "choices": EPISODE_CHOICES})
    action_noise: float = field(default=0.0, metadata={"help": "training on episodes: standard deviation of Gaussian noise added to every action of a training window (exploration; evaluation stays deterministic)"})
    learn_action_noise: bool = field(default=False, metadata={"help": "training on episodes: learn the standard deviation of each action's noise, starting at --action-noise, by the windows' own gradient through the noisy actions (a stochastic actor, as short-horizon actor-critic's); kept within [0.001, 1]"})
    entropy: float = field(default=0.0, metadata={"help": "with --learn-action-noise: each window's loss less this times the noise's entropy at each step, discounted as the rewards (a maximum-entropy actor at a fixed temperature)"})
    critic: bool = field(default=False, metadata={"help": "training on episodes: add a learned value of the window's last state to each window's return (short-horizon actor-critic), the critic fitted to TD(lambda) targets of the windows' rewards"})
    critic_lr: float = field(default=1e-3, metadata={"help": "the critic's Adam learning rate"})
    normalize_critic_observations: bool = field(default=False, metadata={"help": "training with the critic: it sees its observations standardised by the running mean and deviation of all those the training windows met (statistics of its own, kept with it), as the policy does under an environment's --normalize-observations"})
    td_lambda: float = field(default=0.95, metadata={"help": "lambda of the critic's TD(lambda) targets, in [0, 1]"})
    training_episode_length: int = field(default=0, metadata={"help": "training on episodes: the windows' episodes are cut at this many steps and started again from a fresh state, so an epoch starts more of them (an epoch still advances every state one task episode's length; with --value-at-time-limit the critic values each cut state); the evaluations keep the task's length (0: the task's length)"})
    value_at_time_limit: bool = field(default=False, metadata={"help": "training with the critic: an episode cut at its length (a time limit, not its task's end) is valued there, the critic's value of the state it reached standing for what follows, in the critic's targets and the window's loss (off: nothing after the length counts)"})
    value_at_gradient_cut: bool = field(default=False, metadata={"help": "training with the critic, where the task's step cuts the windows' derivative (an env's --contact-gradient-cut): the actions before a state it cuts at are pulled by that state's discounted value's derivative too, as if the window ended there (AHAC); the loss's value unchanged"})
    critic_width: int = field(default=64, metadata={"help": "units in each of the critic's hidden layers (tanh)"})
    critic_depth: int = field(default=2, metadata={"help": "the critic's hidden layers"})
    critics: int = field(default=1, metadata={"help": "training with the critic: its networks, each fitted to the same targets; of 2 or more the least value is the critic's, in its targets and the window's loss (TD3's clipped double learning: the actor finds no state one network alone overvalues)"})
    nonfinite_flows: str = field(default="stop", metadata={"help": "stop: a non-finite gradient of any computed flow stops training, also where the update stays finite; zero (mode C): its components, which C's sign agreement turns into zero updates, are left at zero and training goes on, each epoch where it happened named in a line", "choices": NONFINITE_FLOW_CHOICES})
    budget: float = field(default=0.0, metadata={"help": "wall-clock seconds from the command's start (set-up and compile included) that the run keeps within: it evaluates, saves and stops after the epoch past which one more epoch as long as the slowest of this start's last " f"{PACE_EPOCHS} after its first and an evaluation as long as the longest so far would overrun them (planned " f"{1 + BUDGET_MARGIN:g} times as long, and the longest save so far twice), training on episodes after one more epoch cut to the updates that fit (the first epoch always trains); --resume DIR --budget S trains S seconds more (0: no budget)"})
    eval_every: str = field(default="auto", metadata={"help": "when the train and test returns are evaluated: epoch (at every epoch's end, inside its program: the paper's test loss per epoch), N (updates: at the first epoch's end past every N), Ns (seconds of training), auto (epoch from fixed starts; on episodes, as often as keeps the evaluations within a tenth of the run); the last epoch is always evaluated"})
    epoch_program: str = field(default="auto", metadata={"help": "whole: an epoch is one compiled program (fastest for small scenes, and on a GPU); per-update: the epoch loops in Python over one compiled update and one evaluation (large scenes compile in a fraction of the time and memory); auto: per-update for steps of more than " + f"{LARGE_STEP} operations, and on a CPU of several cores for steps with a constraint solver (update and evaluation compile side by side)", "choices": EPOCH_PROGRAMS})

    def __post_init__(self):
        check_field_types(self)
        if self.mode not in MODES:
            raise InputError(f"unknown mode {self.mode!r}: choose one of {', '.join(MODES)}")
        if self.clip not in CLIP_MODES:
            raise InputError(f"unknown clip mode {self.clip!r}: choose one of {', '.join(CLIP_MODES)}")
        for name in ("epochs", "seeds", "batch", "train_size", "test_size", "checkpoint_every", "unroll", "critic_width",
                     "critic_depth", "critics"):
            value = getattr(self, name)
            if value <= 0:
                raise InputError(f"{config_field(self, name)} must be a positive integer, got {value}")
            # Epochs and checkpoints are counted in Python; the others size arrays, or a critic's layers built one by one.
            most = {"epochs": None, "checkpoint_every": None, "critic_depth": MAX_DEPTH}.get(name, MAX_COUNT)
            if most is not None and value > most:
                raise InputError(f"{config_field(self, name)} must be at most {most}, got {value}")
        if self.devices < 0:
            raise InputError(f"{config_field(self, 'devices')} must be a whole number >= 0 (0: every device), got {self.devices}")
        if not (math.isfinite(self.td_lambda) and 0 <= self.td_lambda <= 1):
            raise InputError(f"{config_field(self, 'td_lambda')} must be in [0, 1], got {self.td_lambda}")
        if not (math.isfinite(self.lr_decay) and 0 < self.lr_decay <= 1):
            raise InputError(f"{config_field(self, 'lr_decay')} must be in (0, 1], got {self.lr_decay}")
        for name in ("adam_b1", "adam_b2"):
            if not (math.isfinite(getattr(self, name)) and 0 <= getattr(self, name) < 1):
                raise InputError(f"{config_field(self, name)} must be in [0, 1), got {getattr(self, name)}")
        if self.matmul_precision not in MATMUL_PRECISIONS:
            raise InputError(f"unknown {config_field(self, 'matmul_precision')} {self.matmul_precision!r}: "
                             f"choose one of {', '.join(MATMUL_PRECISIONS)}")
        if not (math.isfinite(self.action_noise) and self.action_noise >= 0):
            raise InputError(f"{config_field(self, 'action_noise')} must be a number >= 0, got {self.action_noise}")
        if self.training_episode_length < 0:
            raise InputError(f"{config_field(self, 'training_episode_length')} must be a whole number of steps >= 0 "
                             f"(0: the task's length), got {self.training_episode_length!r}")
        if self.learn_action_noise and self.action_noise == 0:
            raise InputError(f"{config_field(self, 'learn_action_noise')} learns the noise's deviation from "
                             f"{config_field(self, 'action_noise')}, which is 0: give it a starting deviation > 0")
        if not (math.isfinite(self.entropy) and self.entropy >= 0):
            raise InputError(f"{config_field(self, 'entropy')} must be a number >= 0, got {self.entropy}")
        if self.entropy and not self.learn_action_noise:
            raise InputError(f"{config_field(self, 'entropy')} weighs the entropy of a learned noise: it needs "
                             f"{config_field(self, 'learn_action_noise')}")
        for name in ("lr", "clip_threshold", "critic_lr"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise InputError(f"{config_field(self, name)} must be a positive number, got {value}")
        for name, last in (("seed", self.seed + self.seeds - 1), ("data_seed", self.data_seed)):
            if not 0 <= getattr(self, name) <= last <= MAX_SEED:
                raise InputError(f"{config_field(self, name)} must be from 0 to {MAX_SEED}"
                                 + (f" with {config_field(self, 'seeds')} {self.seeds}" if name == "seed" else "")
                                 + f", got {getattr(self, name)}")
        if self.seed_batching not in SEED_BATCHING:
            raise InputError(f"unknown seed batching {self.seed_batching!r}: choose one of {', '.join(SEED_BATCHING)}")
        if self.epoch_program not in EPOCH_PROGRAMS:
            raise InputError(f"unknown epoch program {self.epoch_program!r}: choose one of {', '.join(EPOCH_PROGRAMS)}")
        if self.episodes not in EPISODE_CHOICES:
            raise InputError(f"unknown {config_field(self, 'episodes')} {self.episodes!r}: choose one of {', '.join(EPISODE_CHOICES)}")
        if self.nonfinite_flows not in NONFINITE_FLOW_CHOICES:
            raise InputError(f"unknown {config_field(self, 'nonfinite_flows')} {self.nonfinite_flows!r}: choose stop or zero")
        if not (math.isfinite(self.budget) and self.budget >= 0):
            raise InputError(f"{config_field(self, 'budget')} must be a number of seconds >= 0 (0: no budget), got {self.budget}")
        eval_cadence(self)  # refuses a cadence it cannot read
        if self.episodes == "off":
            check_batches(self)


# The evaluations' share of a run that eval_every "auto" keeps to, training on episodes.
EVALUATION_SHARE = 0.1


def eval_cadence(config: TrainConfig, episodes: bool = True) -> tuple[str, float]:
    """When ``config`` evaluates (``TrainConfig.eval_every``) a run that trains on episodes or not:
    ("epoch", 0) inside every epoch, ("updates", N), ("seconds", S) of training, or ("share", f): as often
    as keeps the evaluations within the share f of the training time."""
    text = config.eval_every.strip()
    if text == "auto":
        return ("share", EVALUATION_SHARE) if episodes else ("epoch", 0.0)
    if text == "epoch":
        return "epoch", 0.0
    kind, number = ("seconds", text[:-1]) if text.endswith("s") else ("updates", text)
    try:
        value = float(number) if kind == "seconds" else int(number)
    except ValueError:
        value = math.nan
    if kind == "updates" and value > MAX_COUNT:  # counted in the epoch's program, as a count of its loop
        raise InputError(f"{config_field(config, 'eval_every')} counts at most {MAX_COUNT} updates, got {number}")
    if not (math.isfinite(value) and value > 0):
        raise InputError(f"{config_field(config, 'eval_every')} must be epoch, auto, a number of updates (10) or of "
                         f"seconds (30s), got {config.eval_every!r}")
    return kind, float(value)


def require_train_config(config, who: str = "expected") -> None:
    """``InputError`` unless ``config`` is a ``TrainConfig``; ``who`` begins the message (a function's argument)."""
    if not isinstance(config, TrainConfig):
        raise InputError(f"{who} a stablebptt.TrainConfig, got {type(config).__name__}")


def batches_divide(train_size: int, batch: int) -> bool:
    """Whether ``batch`` divides ``train_size`` training states into whole minibatches (the paper's protocol)."""
    return train_size % batch == 0


def check_batches(config: TrainConfig) -> None:
    """``InputError`` where the batch does not divide the training states (``batches_divide``)."""
    if not batches_divide(config.train_size, config.batch):
        raise InputError(f"{config_field(config, 'batch')} {config.batch} does not divide the {config.train_size} "
                         "training states: pick a divisor")


def seed_batching(config: TrainConfig) -> str:
    """How ``config``'s seeds share one program: "vmap" or "map" (``TrainConfig.seed_batching``).

    "auto" batches several seeds (vmap): on a GPU, mapped seeds run one after another, 5 seeds 5x
    one seed's time per update (docs/performance.md, "Seeds in one program"); on a CPU vmap is as
    fast or faster. Map is for seeds bit-identical to the same seed trained alone."""
    if config.seed_batching != "auto":
        return config.seed_batching
    return "vmap" if config.seeds > 1 else "map"


def batched_seeds(config: TrainConfig) -> int:
    """How many of ``config``'s seeds run at once in one program: all of them batched (vmap), else one."""
    return config.seeds if seed_batching(config) == "vmap" else 1


def data_keys(data_seed: int) -> tuple[jax.Array, jax.Array]:
    """The PRNG keys of a run's training and test initial states (``TrainConfig.data_seed``): the test
    states of an environment's run are the fresh resets its evaluations roll whole episodes from."""
    train_key, test_key = jax.random.split(jax.random.PRNGKey(data_seed))
    return train_key, test_key


def seed_array(config: TrainConfig) -> jax.Array:
    return jnp.arange(config.seed, config.seed + config.seeds, dtype=jnp.uint32)
