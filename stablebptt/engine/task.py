"""What a task supplies to the engine (``Task``), and the option a sweep may vary per cell (``CellOption``)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import jax

from stablebptt.engine.episodes import Episodes
from stablebptt.errors import keywords_named
from stablebptt.flows.dynamics import Dynamics, Plan, PyTree


@dataclass(frozen=True)
class CellOption:
    """A task option that changes numbers but not the compiled program (a loss weight, a target).

    A sweep passes its values as a traced per-cell array, so cells with
    different values vmap into one program.

    Attributes:
      name: the option's name in the task's Config, e.g. ``"rc"``.
      dynamics: ``dynamics(value) -> Dynamics`` for a (traced) scalar value.
    """

    name: str
    dynamics: Callable[[jax.Array], Dynamics]


@keywords_named
@dataclass(frozen=True)
class Task:
    """What a task supplies to the engine: physics, data and a network.

    Attributes:
      name: registry name, e.g. ``"repulsion"``.
      dynamics: policy, simulator step, trajectory loss and horizon.
      init_params: ``init_params(key, zero_output) -> params``.
      sample_initial_states: ``sample_initial_states(key, n) -> batch`` (leading axis n).
      summary: one line on the set-up (what is simulated), printed by scripts.
      cell_option: the option a sweep may vmap per cell, if the task has one.
      resolved: the task as resolved from its sources (model file, defaults,
        options), JSON-serialisable; runs record it in their config.
      evaluation: ``evaluation(params, initial_states) -> losses [n]``, what the
        train and test losses of an epoch report (an environment's negative
        episode return); None: the loss of ``dynamics``' rollout from each state.
      plan: what the task knows of how to differentiate its step (a simulator's
        derivative and known Jacobian columns, a policy's gradient path);
        ``make_trainer`` completes it into the run's plan.
      settle: a check of the task still running beside the caller (an environment's reward
        diagnosis, ``env_task(defer_diagnosis=True)``), None where none is: ``settled()``
        waits for it. Until then ``summary`` and ``resolved`` do not tell its answer, and the
        parameters' values wait for it (their shapes do not): a trainer may be built meanwhile.
        ``settle(wait)``: the task as checked, or None where ``wait`` is false and the check has
        not answered yet.
      compile_while_settling: whether a program traced before the pending check answers is worth
        compiling meanwhile: the answer most likely keeps ``dynamics.step`` (an environment whose
        reward turns no comparison into a number: its check could only smooth an exponential that
        underflows), and the check runs apart from the accelerator the program's compile times its
        kernels on. False where none is pending, or where either may well not hold.
      episodes: what the task knows of its episodes (reset, reward, done, length): a trainer
        may then train on carried episodes (``TrainConfig.episodes``; ``stablebptt.engine.episodes``),
        an environment's by default. None: the paper's protocol only.
      refresh_statistics: what the parameters keep of the states the policy meets besides their
        gradient (running observation statistics, ``stablebptt.engine.observations``):
        ``refresh_statistics(params, states [T, B, ...], counted [T, B]) -> params``, applied after
        every update to the states its window visited (where ``counted``: an episode's states before
        its end). The policy must take no gradient through what it refreshes. None: nothing is kept.
    """

    name: str
    dynamics: Dynamics
    init_params: Callable[[jax.Array, bool], PyTree]
    sample_initial_states: Callable[[jax.Array, int], PyTree]
    summary: str = ""
    cell_option: CellOption | None = None
    resolved: dict = field(default_factory=dict)
    evaluation: Callable[[PyTree, PyTree], jax.Array] | None = None
    plan: Plan = Plan()
    settle: Callable[[bool], "Task | None"] | None = None
    compile_while_settling: bool = False
    episodes: Episodes | None = None
    refresh_statistics: Callable[[PyTree, PyTree, jax.Array], PyTree] | None = None

    def settled(self, wait: bool = True) -> "Task":
        """The task once its pending check has answered (``settle``), which may refuse it; itself where
        none is pending, or where ``wait`` is false and the check has not answered yet."""
        answered = None if self.settle is None else self.settle(wait)
        return self if answered is None else answered

    def settled_fully(self) -> "Task":
        """The task once every pending check has answered: a check's answer may leave another pending
        (a flat reward's surrogate, itself checked beside the caller)."""
        task = self
        while task.settle is not None:
            task = task.settled()
        return task
