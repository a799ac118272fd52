"""The reward diagnosis: before training, the reward's gradient looked at in sampled states (``RewardDiagnosis``).

A reward whose gradient is zero at every sampled state (a step function) is refused, a NaN
derivative of a known form is repaired, and a NaN at exactly zero action is avoided by starting the
policy's output layer small instead of at zero. ``start_diagnosis`` compiles it beside the caller's
set-up (``PendingDiagnosis``), on the host's CPU where an accelerator trains (``check_device``)."""
from __future__ import annotations

import concurrent.futures
import functools
from typing import Any, Callable, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from stablebptt.engine.compiling import beside, compiler_options, host_cpu, untimed_options
from stablebptt.flows.dynamics import join, split

PyTree = Any
# Where the reward's gradient is looked at: episodes of random actions, each at its reset and at clocks
# spread over the episode's length (interleaved between the episodes), so that a reward that exists
# only late in an episode, or at its end, is found where training will meet it.
DIAGNOSIS_EPISODES = 8
DIAGNOSIS_CLOCKS = 6  # states of each episode: its reset and DIAGNOSIS_CLOCKS - 1 later ones
# The clocks are first spread over an episode's first steps alone (one clock a step), and over the whole
# episode only where the reward's gradient is flat there: rolling whole episodes on before every run cost
# a GPU 14 s of start-up on CheetahRun, 43-50 s on the walkers and 103 s on HumanoidStand. Both spreads
# run one program, the steps between clocks its arguments: looking further costs a run, not a compile.
NEAR_STEPS = DIAGNOSIS_EPISODES * (DIAGNOSIS_CLOCKS - 1) + 1


class RewardDiagnosis(NamedTuple):
    """What the reward's gradient looks like at sampled states, with zero and with random actions.

    ``kind`` is ``"usable"``, ``"nan at zero action"``, ``"nan"`` or ``"zero"``.
    """

    kind: str
    nan_at_zero: float  # share of sampled states whose gradient is NaN at zero action
    nan_at_random: float  # the same with random actions
    zero: bool  # the gradient is exactly zero at every sampled state and action

    def describe(self) -> str:
        return {"usable": "reward gradient: usable",
                "nan at zero action": "reward gradient: NaN at exactly zero action (the policy starts off zero)",
                "nan": f"reward gradient: NaN at {self.nan_at_random:.0%} of sampled states",
                "zero": "reward gradient: zero at every sampled state"}[self.kind]


def _gradient_checks(step: Callable) -> Callable:
    """``checks(states, actions)``: per state, whether the reward's gradient is finite and its largest
    finite entry, at zero action and at ``actions``: one gradient mapped over both halves, so a
    program holds one copy of the step's derivative. Mapped in turn, not vmapped: batching the
    step's derivative costs more tracing than the few states' run would gain."""
    def gradient(state, action):
        parts = split(state)
        grads = jax.grad(lambda floats, a: step(join(parts, floats), a).reward, argnums=(0, 1))(parts.floats, action)
        leaves = jax.tree.leaves(grads)
        finite = jnp.all(jnp.array([jnp.isfinite(leaf).all() for leaf in leaves]))
        size = jnp.max(jnp.array([jnp.max(jnp.abs(jnp.where(jnp.isfinite(leaf), leaf, 0.0)), initial=0.0)
                                  for leaf in leaves]))
        return finite, size

    def checks(states, actions):
        twice = jax.tree.map(lambda a: jnp.concatenate([a, a]), states)
        finite, size = jax.lax.map(lambda pair: gradient(*pair), (twice, jnp.concatenate([jnp.zeros_like(actions), actions])))
        count = actions.shape[0]
        return finite[:count], size[:count], finite[count:], size[count:]

    return checks


def _classify(finite_zero, size_zero, finite_random, size_random) -> RewardDiagnosis:
    nan_at_zero = float(1 - np.mean(finite_zero))
    nan_at_random = float(1 - np.mean(finite_random))
    zero = not (np.any(size_zero > 0) or np.any(size_random > 0))
    if nan_at_random > 0:
        kind = "nan"
    elif nan_at_zero > 0:
        kind = "nan at zero action"
    elif zero:
        kind = "zero"
    else:
        kind = "usable"
    return RewardDiagnosis(kind, nan_at_zero, nan_at_random, zero)


def diagnose_reward(step: Callable, states: PyTree, actions: jax.Array) -> RewardDiagnosis:
    """The gradient of one step's reward with respect to the state's floats and the action.

    Args:
      step: the environment's step.
      states: a batch of states (leading axis), e.g. resets and states along episodes of random actions.
      actions: random actions, one per state; zero actions are tried too.
    """
    return _classify(*jax.device_get(jax.jit(_gradient_checks(step), compiler_options=_diagnosis_options())(
        *on_check_device((states, actions)))))


def diagnose_env(env: Any, step: Callable, key: jax.Array, episode_length: int) -> RewardDiagnosis:
    """``diagnose_reward`` at states sampled from ``env`` along episodes of ``episode_length`` steps
    (``sample_for_diagnosis``), the
    sampling and the gradients compiled as ONE program: no operation runs eagerly, which on a GPU
    would compile each one apart. The gradients are taken at the states in turn (``lax.map``)."""
    return RewardDiagnosis(*start_diagnosis(env, step, key, episode_length)())


def _compiled_beside(compiles: Sequence[Callable[[], Any]], compose: Callable[[list], Callable]) -> concurrent.futures.Future:
    """Each of ``compiles`` (a lowered program's ``compile``) called in a thread of its own, and ``compose``
    of their compiled programs (or the first error) in the future returned. XLA compiles one program on
    under two cores: HopperStand's diagnosis as one program compiled in 30.7 s of wall clock and 48.4 s
    of CPU time on the 2-core CPU, its resets, walk and checks one after another in 8.9, 15.2 and 8.4 s.
    On one H200's host of 16 cores, HopperStand's start then waited 21.3 s for its check after the
    epoch's trace, against 27.8-31.7 s as one program, and reached training in 139 s against 143-144 s
    (docs/performance.md, "Noise from 0.6 on the hopper, the finger again")."""
    begun = [beside(compile, f"stablebptt-reward-diagnosis-{index}") for index, compile in enumerate(compiles)]
    return beside(lambda: compose([compiled.result() for compiled in begun]), "stablebptt-reward-diagnosis")


class _Sampled(NamedTuple):
    """The diagnosis's three programs compiled (``lowered_diagnosis``), run one after another: the
    episodes' resets, their walk to the clocks, the checks at the states it kept."""

    resets: Callable
    walk: Callable
    checks: Callable

    def __call__(self, argument: tuple) -> tuple:
        key, lead, stride = argument
        samples = self.walk(*self.resets(key), lead, stride)
        return self.checks(*samples), samples


def start_checks(step: Callable, states: PyTree, actions: jax.Array) -> "PendingDiagnosis":
    """``diagnose_reward`` begun as ``start_diagnosis`` begins its diagnosis: traced here, compiled
    beside the caller, run when called (a flat reward's surrogate, checked at the states its
    diagnosis sampled while the trainer's program is traced)."""
    samples = on_check_device((states, actions))
    lowered = jax.jit(lambda samples: (_gradient_checks(step)(*samples), None),  # the samples are the caller's
                      compiler_options=_diagnosis_options()).lower(samples)
    return PendingDiagnosis(_compiled_beside([lowered.compile], lambda compiled: compiled[0]), samples, [samples])


def start_diagnosis(env: Any, step: Callable, key: jax.Array, episode_length: int) -> "PendingDiagnosis":
    """``diagnose_env`` begun: its program is traced here, then XLA compiles it in a thread of its own
    while the caller goes on (XLA lets go of Python while it compiles). Calling the result waits for
    the compile, runs the program and gives the diagnosis (the fields of a ``RewardDiagnosis``).
    The states are sampled over the episodes' first ``NEAR_STEPS`` steps; where the gradient is flat
    at all of them, the same program runs again with its clocks spread along whole episodes (a reward
    that exists only late in an episode), and its answer is the diagnosis.

    The step is traced here, where the reward's repairs and MJX's derivative remedies are in place for
    this trace alone. XLA compiles it beside the caller; on a CPU alone the program runs in the caller,
    once waited for. Beside an accelerator it runs on the host's CPU (``check_device``), where nothing of
    it meets a program the caller compiles meanwhile for the accelerator, which times its kernels there
    (autotuning); there it runs beside the caller too, as soon as it has compiled.
    """
    lowered, near, whole = lowered_diagnosis(env, step, key, episode_length)
    compiled = _compiled_beside([program.compile for program in lowered], lambda compiled: _Sampled(*compiled))
    along_whole_episodes = None if whole is None else lambda: PendingDiagnosis(compiled, whole, [])  # noqa: E731
    # Its samples come back when it runs; their shapes are known now.
    pending = PendingDiagnosis(compiled, near, [], along_whole_episodes, _check_device_shapes(lowered[1].out_info))
    # Beside an accelerator it runs on the host's CPU as soon as it has compiled, while the caller traces its programs:
    # called only once the caller waits, it rolled its episodes inside that wait.
    return pending if check_device() is None else pending._replace(answer=beside(pending.diagnosed, "stablebptt-reward-check"))


def lowered_diagnosis(env: Any, step: Callable, key: jax.Array, episode_length: int) -> tuple[tuple, tuple, tuple | None]:
    """``start_diagnosis``'s three programs, lowered with the diagnosis's options: the episodes' resets
    (from a key), their walk to the clocks (``_walk``) and the checks at the states it kept; and the
    arguments of the whole (``_Sampled``): its clocks over the episodes' first ``NEAR_STEPS`` steps, and
    along whole episodes (None where an episode is no longer). Three programs, so that they compile at
    once (``_compiled_beside``); the samples come back too: a flat reward's surrogate is fitted and
    checked on them."""
    clocks = _clocks_after_reset(episode_length)
    options = _diagnosis_options()
    key = on_check_device(key)  # the programs run where their arguments lie
    near = (key, *_spacing(min(episode_length, NEAR_STEPS), clocks))
    whole = (key, *_spacing(episode_length, clocks)) if episode_length > NEAR_STEPS else None
    resets = jax.jit(functools.partial(_resets, env), compiler_options=options)
    walk = jax.jit(functools.partial(_walk, env, step, clocks=clocks), compiler_options=options)
    checks = jax.jit(_gradient_checks(step), compiler_options=options)
    resets = resets.lower(key)
    walk = walk.lower(*_check_device_shapes((*resets.out_info, *near[1:])))
    return (resets, walk, checks.lower(*_check_device_shapes(walk.out_info))), near, whole


def _check_device_shapes(tree: PyTree) -> PyTree:
    """``tree``'s shapes and dtypes, on the device the diagnosis runs on (``check_device``): a program
    lowered for them runs there."""
    device = check_device()
    sharding = None if device is None else jax.sharding.SingleDeviceSharding(device)
    return jax.tree.map(lambda leaf: jax.ShapeDtypeStruct(leaf.shape, leaf.dtype, sharding=sharding), tree)


class PendingDiagnosis(NamedTuple):
    """A reward diagnosis compiling beside the caller (``start_diagnosis``)."""

    compiled: concurrent.futures.Future  # the diagnosis's compiled program
    argument: Any  # a PRNG key and the clocks' spacing (start_diagnosis), or the samples themselves (start_checks)
    ran: list  # the states and actions checked, (states, actions): given, or once called, those it sampled
    further: Callable[[], "PendingDiagnosis"] | None = None  # where the gradient is flat at every state: look further
    sample_shapes: tuple | None = None  # the shapes of the states and actions it samples (start_diagnosis)
    answer: concurrent.futures.Future | None = None  # ``diagnosed()`` run beside the caller, where it is begun there

    def __call__(self) -> list:
        """Waits for the compile, runs the program (or waits for its run begun beside): the fields of a
        ``RewardDiagnosis``."""
        return self.diagnosed() if self.answer is None else self.answer.result()

    def diagnosed(self) -> list:
        """Waits for the compile, runs the program: the fields of a ``RewardDiagnosis``."""
        checked, samples = self.compiled.result()(self.argument)
        if samples is not None:
            self.ran[:] = [samples]
        diagnosis = _classify(*jax.device_get(checked))
        if diagnosis.kind == "zero" and self.further is not None:
            further = self.further()
            diagnosis = RewardDiagnosis(*further())
            self.ran[:] = further.ran
        return list(diagnosis)

    def samples(self) -> tuple[PyTree, jax.Array] | None:
        """The states and actions checked: given, or sampled once the program has run; else None."""
        return self.ran[0] if self.ran else None

    def done(self) -> bool:
        """Whether calling waits no longer than the program's run: its compile has ended (its run too, where
        begun beside)."""
        return self.compiled.done() if self.answer is None else self.answer.done()


def check_device() -> jax.Device | None:
    """Where the diagnosis runs: the host's CPU beside an accelerator, else the default device (None).

    On a GPU its compile outlasted the set-up and the trace (the run then waited 20-43 s for it on
    CheetahRun and the walkers), and its kernels could not run while the epoch's compile timed its
    own there (a GPU's autotuning), so the epoch could not compile before the check had answered. On
    the host's CPU the check compiles and runs whatever the GPU does meanwhile."""
    return host_cpu()


def on_check_device(tree: PyTree) -> PyTree:
    """``tree``'s arrays put where the diagnosis runs (``check_device``): a compiled program runs where its
    arguments lie, and its closed-over model follows them."""
    device = check_device()
    return tree if device is None else jax.device_put(tree, device)


def _diagnosis_options() -> dict | None:
    """XLA options of the diagnosis. On the host's CPU beside an accelerator (``check_device``), the
    CPU's defaults. On a GPU, the training's with none of its kernels timed (autotuning level 0): it
    compiles beside the trainer's set-up (``start_diagnosis``), whose reset program times its own
    kernels meanwhile, and must choose them undisturbed. On one H100 level 0
    compiled it in 8.7 s against the training options' 8.9 s for CartpoleSwingup, 7.0 against 8.1 s
    for AcrobotSwingup, each after another compile in the same process (the record:
    ``git show fb065bd:results/startup/gpu-diagnosis-in-turn/diagnosis-compile-after.txt``).
    On a CPU LLVM optimises it as it does the training's programs: unoptimised (LLVM -O0), HopperStand's
    diagnosis compiled in 33.1 s where optimised it took 36.5 s, but ran 38.1 s instead of 0.21 s
    over the episodes' first steps and 989 s instead of 3.3 s along whole episodes on the 2-core CPU
    (``python benchmarks/diagnosis_compile.py HopperStand`` at 02b1d6d, before the walk became one loop)."""
    if check_device() is not None:
        return None
    return {**(compiler_options() or {}), **untimed_options()} or None


def sample_for_diagnosis(env: Any, step: Callable, key: jax.Array, episode_length: int,
                         span: int | None = None) -> tuple[PyTree, jax.Array]:
    """States along episodes of random actions, with a random action for each (traceable):
    every episode's reset, and states at clocks spread evenly over the first ``span`` steps (default
    ``episode_length``: up to the last step's), each clock taken from one episode in turn. The episodes
    step together (``vmap``); an episode that ends (``done``) goes on from its reset."""
    clocks = _clocks_after_reset(episode_length)
    return _sample_spaced(env, step, key, *_spacing(episode_length if span is None else min(span, episode_length),
                                                    clocks), clocks)


def _clocks_after_reset(episode_length: int) -> int:
    """How many clocks are sampled after the resets: as many for every span of one episode length,
    so that one program samples them all (``_sample_spaced``)."""
    return min(DIAGNOSIS_EPISODES * (DIAGNOSIS_CLOCKS - 1), episode_length - 1)


def _spacing(span: int, clocks: int) -> tuple[np.int32, np.int32]:
    """Steps before the first sampled clock and between two, so that ``clocks`` clocks end at the
    ``span``-th step: arguments of the sampling's program, not constants of it (host numbers: the
    set-up puts nothing on the device)."""
    last = span - 1
    stride = max(1, last // max(clocks, 1))
    return np.int32(last - clocks * stride), np.int32(stride)


def _sample_spaced(env: Any, step: Callable, key: jax.Array, lead: jax.Array, stride: jax.Array,
                   clocks: int) -> tuple[PyTree, jax.Array]:
    """``sample_for_diagnosis`` with the clocks at ``lead + stride``, ``lead + 2 stride``, ... (``clocks``
    of them): ``lead`` and ``stride`` may be traced."""
    return _walk(env, step, *_resets(env, key), lead, stride, clocks=clocks)


def _resets(env: Any, key: jax.Array) -> tuple[PyTree, jax.Array, jax.Array]:
    """The episodes' resets, and the keys of their walk's actions and of the actions checked."""
    reset_key, walk_key, action_key = jax.random.split(key, 3)
    return jax.lax.map(env.reset, jax.random.split(reset_key, DIAGNOSIS_EPISODES)), walk_key, action_key


def _walk(env: Any, step: Callable, starts: PyTree, walk_key: jax.Array, action_key: jax.Array, lead: jax.Array,
          stride: jax.Array, *, clocks: int) -> tuple[PyTree, jax.Array]:
    """The episodes from ``starts`` on, in ONE loop of ``lead + clocks stride`` steps that keeps each
    clock's state as it passes, so the program holds one copy of the step (a loop to the first clock
    and another between clocks would hold, and compile, one each); the resets and the kept states,
    with a random action for each."""
    kept = jax.tree.map(lambda leaf: jnp.zeros((clocks,) + leaf.shape[1:], leaf.dtype), starts)

    def advance(index, carried):  # every episode one step on; the clock it reaches kept, from one episode in turn
        states, kept = carried
        actions = jax.random.uniform(jax.random.fold_in(walk_key, index), (DIAGNOSIS_EPISODES, env.action_size),
                                     minval=-1.0, maxval=1.0)
        reached = jax.vmap(step)(states, actions)
        ended = reached.done > 0
        states = jax.tree.map(lambda start, now: jnp.where(ended.reshape(ended.shape + (1,) * (now.ndim - 1)), start, now),
                              starts, reached)
        since_lead = index + 1 - lead
        clock = since_lead // stride - 1
        at_clock = (since_lead > 0) & (since_lead % stride == 0)
        slot = jnp.clip(clock, 0, clocks - 1)
        kept = jax.tree.map(lambda all_kept, now: all_kept.at[slot].set(
            jnp.where(at_clock, now[slot % DIAGNOSIS_EPISODES], all_kept[slot])), kept, states)
        return states, kept

    _, kept = jax.lax.fori_loop(0, lead + clocks * stride, advance, (starts, kept))
    states = jax.tree.map(lambda first, along: jnp.concatenate([first, along]), starts, kept)
    actions = jax.random.uniform(action_key, (DIAGNOSIS_EPISODES + clocks, env.action_size), minval=-1.0, maxval=1.0)
    return states, actions
