"""The benchmark's measurements: update times per mode of any registered task, and each task's own
tables, as Markdown (scripts/bench.py prints them).

What a task is timed as comes from its studies module (``bench_cases``, see
``stablebptt.apps.studies``): the cart-pole's pole counts and its steps table (its MJX
pipelines against the closed-form floor, and the parts of an update); any other
task is timed with its defaults. Variants of one table are timed round-robin
(``stablebptt.timing``), so drift of the machine hits all of them alike; compare
times within one table only.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

from stablebptt import timing
from stablebptt.errors import InputError

TABLES = ("modes", "steps")


@dataclass(frozen=True)
class BenchConfig:
    """Options of the benchmark."""

    tasks: str = field(default="repulsion,cartpole,quantum", metadata={"help": "comma-separated tasks"})
    poles: str = field(default="1,3", metadata={"help": "comma-separated pole counts for the cart-pole"})
    batch: int = field(default=8, metadata={"help": "initial states per update"})
    rounds: int = field(default=20, metadata={"help": "timed rounds per variant (median reported)"})
    out: str = field(default="", metadata={"help": "also write the tables to this Markdown file"})
    tables: str = field(default="modes,steps", metadata={"help": "tables to time: modes (an update per mode, every task), steps (a task's own table where it has one: the cart-pole's simulators against the closed-form floor, and the parts of its update)"})
    simulators: str = field(default="", metadata={"help": "the simulators of the cart-pole's steps table (default: every one): generated, stages, autodiff, dense, mjx, floor"})
    startup: bool = field(default=False, metadata={"help": "time the start-up instead: per model, a fresh scripts/train.py process to its first update, set-up, compiling and first epoch, with an empty compile cache (cold) and again with the cache it filled (warm); --out also gets a .json record"})
    models: str = field(default="", metadata={"help": "for --startup: comma-separated MJCF files or names of dm_control's suite models in --suite (default, without --envs: stablebptt/models/cartpole_1.xml and cartpole_3.xml, then the suite's models that train)"})
    envs: str = field(default="", metadata={"help": "for --startup: comma-separated environments, trained as scripts/train.py --env NAME (MuJoCo Playground names or package.module:attribute), after the models"})
    suite: str = field(default="", metadata={"help": "for --startup: the folder of dm_control's suite/*.xml"})
    train_args: str = field(default="--epochs 1 --train-size 8 --test-size 8 --batch 8 --steps 10", metadata={"help": "for --startup: scripts/train.py's options besides --model"})
    env_args: str = field(default="--epochs 1", metadata={"help": "for --startup: scripts/train.py's options besides --env"})
    timeout: float = field(default=300.0, metadata={"help": "for --startup: seconds a run may take before it is stopped and recorded as a timeout"})

    @property
    def task_list(self) -> list[str]:
        return [name for name in self.tasks.split(",") if name]

    @property
    def table_list(self) -> list[str]:
        return [name for name in self.tables.split(",") if name]

    @property
    def simulator_list(self) -> tuple[str, ...]:
        return tuple(name for name in self.simulators.split(",") if name)

    @property
    def model_list(self) -> list[str]:
        return [name for name in self.models.split(",") if name]

    @property
    def env_list(self) -> list[str]:
        return [name for name in self.envs.split(",") if name]

    @property
    def pole_list(self) -> list[int]:
        try:
            counts = [int(count) for count in self.poles.split(",") if count.strip()]
        except ValueError:
            counts = []
        if not counts:
            raise InputError(f"--poles takes comma-separated integers, got {self.poles!r}")
        return counts


@dataclass(frozen=True)
class BenchCase:
    """One configuration of a task the benchmark times.

    Attributes:
      title: the heading of its modes table.
      task_config: the task's ``Config``.
      steps: ``steps() -> Markdown lines``, the task's own table (``--tables steps``), if it has one.
    """

    title: str
    task_config: Any
    steps: Callable[[], list[str]] | None = None


def bench_cases(task: str, config: BenchConfig) -> list[BenchCase]:
    """What the benchmark times of ``task``: its studies module's ``bench_cases``, else its defaults."""
    from stablebptt import tasks
    from stablebptt.apps.study_hooks import hook
    module = tasks.load(task)
    cases = hook(task, "bench_cases")
    if cases is not None:
        return cases(module, config)
    return [BenchCase(tasks.canonical(task).capitalize(), module.Config())]

def make_update(task, mode, batch_size, plain=False, with_cosine=False):
    """A jitted update: gradient (one-pass flows, or plain jax.grad), clip, Adam."""
    import jax
    import optax

    from stablebptt.engine.config import TrainConfig
    from stablebptt.engine.optimizer import make_optimizer
    from stablebptt.flows.gradients import flow_gradients, reference_loss
    from stablebptt.flows.modes import flows_needed

    flows = flows_needed(mode, with_cosine)
    optimizer = make_optimizer(TrainConfig(mode=mode), flows)

    def update(params, opt_state, batch):
        if plain:
            loss, grad = jax.value_and_grad(reference_loss, argnums=1)(task.dynamics, params, batch)
            grads = jax.tree.map(lambda g: g[None], grad)
        else:
            loss, grads = flow_gradients(task.dynamics, flows, params, batch, task.plan)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss

    def setup():
        import jax.random as random
        params = task.init_params(random.PRNGKey(0), False)
        batch = task.sample_initial_states(random.PRNGKey(1), batch_size)
        return params, optimizer.init(params), batch

    return jax.jit(update), setup


def time_variants(variants: dict, rounds: int) -> dict[str, tuple[float, float]]:
    """Median milliseconds per call and compile seconds (the first call), timed round-robin."""
    prepared, compile_seconds = {}, {}
    for name, (update, setup) in variants.items():
        arguments = setup()
        compile_seconds[name] = timing.timed(lambda: update(*arguments))[1]
        prepared[name] = lambda update=update, arguments=arguments: update(*arguments)
    medians = timing.round_robin(prepared, rounds)
    return {name: (1e3 * medians[name], compile_seconds[name]) for name in variants}


def combined_modes() -> list[str]:
    """The modes that combine several flows (``flows.MODE_TABLE``), which share one forward rollout."""
    from stablebptt.flows.modes import MODE_TABLE
    return [mode.name for mode in MODE_TABLE.values() if len(mode.flows) > 1]


def mode_table(title: str, task, batch: int, rounds: int) -> list[str]:
    from stablebptt.flows.modes import MODE_TABLE, MODES
    regular = MODES[0]  # regular BPTT, the baseline of every ratio
    variants = {f"{regular} plain": make_update(task, regular, batch, plain=True)}
    variants.update({mode: make_update(task, mode, batch) for mode in MODES})
    variants[f"{regular} + cosine"] = make_update(task, regular, batch, with_cosine=True)
    times = time_variants(variants, rounds)
    base = times[f"{regular} plain"][0]
    lines = [f"### {title}", "", f"| update | ms (median) | / {regular} plain | compile s |", "|---|---:|---:|---:|"]
    for name, (ms, compile_s) in times.items():
        lines.append(f"| {name} | {ms:.2f} | {ms / base:.2f} | {compile_s:.1f} |")
    lines.append("")
    for mode in combined_modes():
        needs = " and ".join(f"g_{flow}" for flow in MODE_TABLE[mode].flows)
        lines.append(f"{mode} / {regular} = {times[mode][0] / times[regular][0]:.2f} "
                     f"({mode} needs {needs}, all from one forward rollout).")
    return lines + [""]
