"""What accuracy costs in time, measured: the options of the studies, and the studies themselves.

The command line is scripts/accuracy.py (``stablebptt accuracy``), whose help
describes the studies; ``stablebptt.reports.accuracy_report`` turns their rows into
tables, figures and summary.md. Each study lives in its own module: ``trajectory_study``,
``gradient_study``, ``training_study``, ``contact_study``, and what they share, ``measuring``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from stablebptt.errors import InputError

TASKS = ("cartpole", "repulsion", "quantum")  # the default --tasks: the built-in tasks with study set-ups


@dataclass(frozen=True)
class AccuracyConfig:
    """Options of the accuracy study."""

    tasks: str = field(default=",".join(TASKS), metadata={"help": "comma-separated tasks of the trajectory and gradient studies (any registered task with study set-ups)"})
    studies: str = field(default="trajectory,gradients,training", metadata={"help": "comma-separated studies: trajectory, gradients, training, contact"})
    suite: str = field(default="", metadata={"help": "folder of the DeepMind Control Suite's model files (dm_control/suite), for the contact study"})
    contact_models: str = field(default="hopper,walker,cheetah,finger,ball_in_cup", metadata={"help": "comma-separated suite models of the contact study"})
    poles: int = field(default=1, metadata={"help": "poles of the cart-pole in the trajectory study (1-4)"})
    gradient_poles: int = field(default=4, metadata={"help": "poles of the cart-pole in the gradient study (1-4)"})
    batch: int = field(default=8, metadata={"help": "trajectories per rollout and gradient"})
    rounds: int = field(default=20, metadata={"help": "timed rounds per variant (median reported)"})
    train_task: str = field(default="repulsion", metadata={"help": "task of the training study (any registered task)"})
    epochs: int = field(default=150, metadata={"help": "epochs per mode in the training study"})
    train_size: int = field(default=64, metadata={"help": "training initial states in the training study"})
    seed: int = field(default=0, metadata={"help": "seed of the initial states, controls and parameters"})
    quick: bool = field(default=False, metadata={"help": "a small smoke version: few time steps, short horizons, 3 epochs"})
    replot: bool = field(default=False, metadata={"help": "only redraw the figures and summary.md from the CSVs in --out"})
    out: str = field(default="results/accuracy", metadata={"help": "directory for the CSVs, figures and summary.md"})

    @property
    def task_list(self) -> list[str]:
        return [name for name in self.tasks.split(",") if name]

    @property
    def study_list(self) -> list[str]:
        return [name for name in self.studies.split(",") if name]


def check_tasks(config: AccuracyConfig) -> None:
    """Refuse, before anything is measured, a task that is not registered or that a chosen study cannot take.

    Raises:
      InputError: naming the task and what is missing.
    """
    from stablebptt import tasks
    from stablebptt.apps.study_hooks import required_hook
    for name in (*config.task_list, config.train_task):
        if tasks.canonical(name) not in tasks.entries():
            raise InputError(f"unknown task {name!r}: choose from {', '.join(sorted(tasks.entries()))}")
    for study, function in (("trajectory", "trajectory_setup"), ("gradients", "gradient_setup")):
        if study in config.study_list:
            for name in config.task_list:
                required_hook(name, function, study)



