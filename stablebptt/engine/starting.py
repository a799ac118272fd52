"""A run's start, in the order it happens (``prepare``): the epoch traced while the task's check
compiles beside, then compiled beside the check's run where it most likely keeps the step; the
trainer rebuilt where the check's answer smoothed the reward, and the surrogate's epoch compiled; and
the epoch's and each epoch's first program compiled for a state (``compiled_epoch``,
``compiled_refill``)."""
from __future__ import annotations

import concurrent.futures
import time
from typing import Any, Callable, NamedTuple

import jax

from stablebptt.engine.checks import require_task
from stablebptt.engine.compiling import CompiledBeside, beside, host_cpu, untimed_options
from stablebptt.engine.config import TrainConfig
from stablebptt.engine.lowering import LoweredEpoch, lowered_epoch, lowered_refill, programs_beside, refill_kept_also
from stablebptt.engine.program_store import cache_dir, compile_epoch
from stablebptt.engine.training import Trainer, make_trainer
from stablebptt.errors import InputError


class Prepared(NamedTuple):
    """A task settled and its trainer built, in the order a run starts (``prepare``)."""

    task: Any  # settled: its checks answered (a refusal raised), its reward smoothed where they said so
    trainer: Trainer
    lowered: LoweredEpoch | None  # the trainer's epoch traced and lowered, where asked for
    program_key: dict | None  # what decides the run's programs, a smoothed reward's included
    phases: dict[str, float]  # seconds of each start-up phase, in the order they ran


def prepare(task: Any, config: TrainConfig, program_key: dict | None = None, resuming: bool = False) -> Prepared:
    """A run's start, in the order it happens: the trainer built and its epoch traced while a check the
    task left running compiles beside (``Task.settle``: an environment's reward diagnosis); where the
    check most likely keeps the step (``Task.compile_while_settling``), the epoch's compile begun
    beside the check's answer, which may refuse the task; on an accelerator's host, the programs beside
    the epoch traced and compiling meanwhile, and where the epoch compiles early, its update traced first
    and those programs next, both before the check's own trace, which begins once asked; where it
    smoothed the reward, the trainer built again for the task as settled (keeping those programs where
    the task kept their parts), its epoch traced and compiled (once an early compile has ended) while
    the surrogate's own check compiles beside; that check's answer. ``program_key`` as
    ``train_epochs`` takes it. ``resuming``: the state will be read from a checkpoint (into
    ``lowered.shapes``), so init's programs are not compiled beside.

    A task its check refuses leaves an early compile running in its thread (XLA cannot stop it): a
    command's process ends at once all the same (``cli.leave``), a library caller's goes on beside it.

    Raises:
      InputError: the task refused by its checks, or by the trainer's set-up, named.
    """
    require_task(task)
    phases: dict[str, float] = {}
    lap = _lap_clock(phases)
    program_key = _smoothed_key(program_key, task)

    def build(task):
        try:
            return make_trainer(task, config, keep=program_key, lap=lap)
        except InputError as error:  # the memory plan may refuse the scene
            raise InputError(f"{task.name}: {error}") from None

    trainer = build(task)
    lap("trainer set-up")
    built, checking = task, task.settle is not None
    # The epoch is traced while the check compiles beside. Where the check most likely keeps the step, the epoch
    # compiles while it runs (the walkers waited 19-23 s for the check after the trace, the humanoid 45 s);
    # elsewhere (HopperStand's reward, which it smooths) once it has answered, the surrogate's alone. A reward
    # smoothed all the same leaves the early compile unused, and the surrogate's epoch compiles once it has
    # ended, so that on a GPU no other program's kernels run while its own are timed.
    early, apart = checking and task.compile_while_settling, _host_apart()
    # On an accelerator's host an epoch that compiles at once is traced whole here, before the check's own trace (begun
    # once settled() asks): traced in the compile's thread, a large step's update shared Python's lock with it. On a
    # CPU alone the check, traced as the task was built, runs in this thread once compiled, beside that trace; traced
    # here first, the update held the check's run back (docs/performance.md).
    lowered = lowered_epoch(trainer, config, program_key, beside=False, update_now=early and apart)
    lap("trace")
    compile_ended: list[float] = []  # when the early compile ended, once it has

    def compile_as_written(epoch=lowered.lowered):
        program = epoch.compile()
        compile_ended.append(time.perf_counter())
        return program

    as_written = beside(compile_as_written, "stablebptt-epoch") if early else None
    # On an accelerator's host the programs beside the epoch are traced next, and compile while the check runs
    # (beside an early compile, before the check's own trace): a smoothed reward leaves them as they are where the
    # settled task keeps their parts.
    ahead = checking and apart
    if ahead:
        lowered = programs_beside(lowered, trainer, config, program_key, init=not resuming)
        lap("trace")
    task = task.settled()  # a reward without a usable gradient is refused here
    if early:  # what the start waited while the epoch compiled beside the check, then for the check alone
        lap("compile beside the check", until=compile_ended[0] if compile_ended else None)
    lap("check's wait")
    smoothed = task.dynamics.step is not built.dynamics.step
    if smoothed:  # the check smoothed the reward: train the task as settled
        pending_key, program_key = program_key, _smoothed_key(program_key, task)
        trainer = build(task)
        lap("trainer set-up")
        checking = task.settle is not None  # the surrogate's own check, compiling beside
        begun, lowered = lowered, lowered_epoch(trainer, config, program_key, beside=False)
        ahead = ahead and _keeps_programs_beside(task, built)
        if ahead:
            lowered = lowered._replace(evaluation=begun.evaluation, init_rest=begun.init_rest, refill=begun.refill)
            refill_kept_also(trainer, lowered.shapes, pending_key, program_key)  # where a resume looks for it
    if not ahead:
        lowered = programs_beside(lowered, trainer, config, program_key, init=not resuming)
    lap("surrogate's trace" if smoothed else "trace")  # the epoch's where smoothed, and the programs beside
    if smoothed and as_written is not None:
        concurrent.futures.wait([as_written])  # its program (or its error) unused
        lap("unused compile's wait")
    if checking:
        lowered = _compiled_now(lowered, lap, None if smoothed else as_written)
    task = task.settled_fully()  # the surrogate's own check, compiled beside that compile, may refuse it here
    lap("surrogate check's wait")
    if lowered.init_rest is not None:  # init's part that waits for no check, compiling beside
        trainer = trainer._replace(init=trainer.init._replace(rest=lowered.init_rest))
    return Prepared(task, trainer, lowered, program_key, {name: seconds for name, seconds in phases.items() if seconds})


def _host_apart() -> bool:
    """Whether a task's check compiles and runs on the CPU of an accelerator's host (``host_cpu``), whose cores
    have room for more (on two cores of a CPU alone, programs traced and compiled while the check ran slowed the
    start: docs/performance.md)."""
    return host_cpu() is not None


def _keeps_programs_beside(settled: Any, pending: Any) -> bool:
    """Whether a trainer of the task ``settled`` runs the programs beside the epoch (the evaluation, the population's
    first resets, each epoch's refill) that one of ``pending``, the task before its check answered, does: the
    settled task kept its evaluation (a rollout of its own, not its dynamics'), its episodes, its starts and its
    window (an environment's, where its states carry no direction of the trained reward, whatever the check
    smoothed)."""
    return (settled.evaluation is not None and settled.evaluation is pending.evaluation
            and settled.episodes is pending.episodes and settled.sample_initial_states is pending.sample_initial_states
            and settled.dynamics.horizon == pending.dynamics.horizon)


def _compiled_now(lowered: LoweredEpoch, lap: Callable[..., None],
                  begun: concurrent.futures.Future | None = None) -> LoweredEpoch:
    """``lowered`` compiled here (or its compile ``begun`` beside, waited for), where a task's check ran
    or still compiles (``Task.settle``): the programs of init and the evaluation, lowered with it,
    compile beside it rather than after it (a run's init waits for its own), and a surrogate's own
    check compiles beside it while its program runs only once this compile has ended, so on a GPU none
    of its kernels runs while the epoch's are timed. A check that refuses the task leaves this compile
    unused."""
    compiled = lowered.lowered.compile() if begun is None else begun.result()
    lap("compile")
    return lowered._replace(compiled=compiled)


def compiled_epoch(trainer: Trainer, state: Any, lowered: LoweredEpoch | None = None,
                   program_key: dict | None = None) -> tuple[Callable, float]:
    """The trainer's epoch compiled for ``state`` and the seconds it took: ``lowered``'s where it was
    lowered for states of ``state``'s shapes, else traced anew (kept under ``program_key``: ``program_store``)."""
    arguments = (trainer.batches, trainer.train_states, trainer.test_states)
    if lowered_for(lowered, state):
        started = time.perf_counter()
        epoch_fn = lowered.compiled or lowered.lowered.compile()
        return epoch_fn, time.perf_counter() - started
    return compile_epoch(trainer.epoch, (state, *arguments), trainer.kept_under(program_key), cache_dir(),
                         trainer.compiler_options)


def compiled_then_made(trainer: Trainer, state: Any, lowered: LoweredEpoch | None = None,
                       program_key: dict | None = None) -> tuple[Callable, float, Any, float | None]:
    """The trainer's epoch compiled (``compiled_epoch``), the seconds it took, the state to train from and
    the seconds its making took: ``state`` itself (None), or where ``state`` is a function that makes a
    fresh one, its result made once the epoch has compiled for ``lowered``'s shapes. Init's programs,
    compiling beside since the start (``programs_beside``), then compile beside the epoch's rather than
    before it, and run once it has ended: on a GPU none of their kernels runs while the epoch's are timed."""
    if not callable(state):
        return (*compiled_epoch(trainer, state, lowered, program_key), state, None)
    if lowered is None:  # no shapes to compile the epoch for: the state first
        state, made = _made(state)
        return (*compiled_epoch(trainer, state, None, program_key), state, made)
    epoch_fn, seconds = compiled_epoch(trainer, lowered.shapes, lowered, program_key)
    state, made = _made(state)
    if not lowered_for(lowered, state):  # made otherwise than the epoch was lowered for: compiled for it
        epoch_fn, more = compiled_epoch(trainer, state, None, program_key)
        seconds += more
    return epoch_fn, seconds, state, made


def _made(fresh: Callable[[], Any]) -> tuple[Any, float]:
    started = time.perf_counter()
    state = jax.block_until_ready(fresh())
    return state, time.perf_counter() - started


def compiled_refill(trainer: Trainer, state: Any, beside: CompiledBeside | None = None,
                    program_key: dict | None = None) -> tuple[Callable, float]:
    """The program every epoch starts with (``Trainer.fresh``) compiled for ``state`` before any epoch is
    timed, and the seconds it took: ``beside``'s (``LoweredEpoch.refill``) where it was lowered for
    ``state``'s shapes, else from its traced program kept under ``program_key`` (a resume's: its first
    start kept it, ``programs_beside``). Compiled with a first start's options, so a resume finds it
    in XLA's cache."""
    if trainer.refill is None:
        return trainer.fresh, 0.0
    if lowered_for(beside, state):
        return beside, beside.wait()
    started = time.perf_counter()
    program = lowered_refill(trainer, state, program_key).compile(untimed_options() or None)
    return program, time.perf_counter() - started


def lowered_for(program: LoweredEpoch | CompiledBeside | None, arguments: Any) -> bool:
    """Whether ``program`` (lowered already, beside or not) was lowered for arguments shaped as ``arguments``."""
    return program is not None and _leaf_shapes(arguments) == _leaf_shapes(program.shapes)


def _leaf_shapes(tree: Any) -> list[tuple]:
    # Leaves alone: a carried env state's tree holds NumPy arrays in its static fields, which == cannot compare.
    # A checkpoint's NumPy arrays carry no weak type where init's may: such a state is lowered anew.
    return [(leaf.shape, leaf.dtype, bool(getattr(leaf, "weak_type", False))) for leaf in jax.tree.leaves(tree)]


def _smoothed_key(program_key: dict | None, task: Any) -> dict | None:
    """The key of a run's kept programs: a task training a smoothed reward steps through other programs."""
    smoothing = getattr(task, "resolved", {}).get("reward_smoothing")
    return program_key if program_key is None or smoothing is None else {**program_key, "reward_smoothing": smoothing}


def _lap_clock(phases: dict[str, float]) -> Callable[..., None]:
    """``lap(name)`` adds the seconds since the previous lap (the first: since this call) to ``phases[name]``;
    ``lap(name, until=t)`` those until ``t``, a ``time.perf_counter()`` already passed."""
    last = [time.perf_counter()]

    def lap(name: str, until: float | None = None) -> None:
        now = time.perf_counter() if until is None else until
        phases[name] = phases.get(name, 0.0) + now - last[0]
        last[0] = now
    return lap
