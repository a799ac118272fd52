"""The task registry: what the command line needs to know about each task.

A task is a module with ``Config`` (a typed dataclass: its command-line
options), ``make(config) -> stablebptt.engine.training.Task`` and ``DEFAULT_EPOCHS``
(optionally ``TRAIN_DEFAULTS``: training options the command line defaults to for the task;
``recorded_config(config, record) -> config``: a run's config as it trained, where a default changed since;
``make_as_recorded(config, resolved, deferred=False) -> Task``: ``make`` for a run that resumes or is reopened,
from what its record says the task resolved to (where absent, ``make``);
``for_reopening(config, resolved) -> config`` (or ``for_reopening(config)``): the configuration that rebuilds
a trained run's task (``resolved``: what its record says the task resolved to), checks that only matter
before training left out; and
``program_inputs(config) -> dict | None``: what its compiled programs read besides
the library and the config, so that ``stablebptt.engine.program_store`` may keep them),
described by an ``Entry``: how to name a configuration, how to draw its
rollouts, which grids the sweep offers. Entries import nothing: a task's module
(and MuJoCo with it) is imported only when the task is used, so rendering can
still choose MuJoCo's OpenGL backend first.

Your own task: write such a module and register it, either from Python before
calling a command's ``main``::

    from stablebptt import tasks
    tasks.register(tasks.Entry(name="arm", module="my_lab.arm_task", label=lambda c: f"arm, {c.links} links"))

or for every use of the installed command, through an entry point in your
package's pyproject.toml (the value is a module defining ``ENTRY``)::

    [project.entry-points."stablebptt.tasks"]
    arm = "my_lab.arm_task"
"""
from __future__ import annotations

import importlib
import inspect
from dataclasses import dataclass, field
from importlib.metadata import entry_points
from types import ModuleType
from typing import Any, Callable

DEFAULT_TASK = "mjcf"
MJCF_TASK = "mjcf"  # the task of any MJCF file (--model), which render.py draws under a zero policy
# Names that earlier versions wrote into run folders: they resolve to today's task.
LEGACY_NAMES = {"cartpole": "mjcf"}


def _import(dotted: str) -> Any:
    """``"package.module:attribute"`` -> the attribute; ``"package.module"`` -> the module."""
    module, _, attribute = dotted.partition(":")
    loaded = importlib.import_module(module)
    return getattr(loaded, attribute) if attribute else loaded


@dataclass(frozen=True)
class Entry:
    """A task as the command line sees it.

    Attributes:
      name: the ``--task`` value.
      module: import path of the module with ``Config``, ``make`` and ``DEFAULT_EPOCHS``.
      label: a configuration in a few words, for titles (``label(config) -> str``).
      draw: ``"module:function"`` (or the function) drawing rollouts, ``draw(request) -> [written paths]``
        with ``request`` a ``stablebptt.render.drawing.DrawRequest``: the task config, the rollouts' states
        [N, T+1, ...] and controls [N, T, ...] (NumPy), a title per rollout, a label, the
        ``DrawSettings`` (panel width and height, fps, strip_states), and the video (None: none)
        and picture to write. Empty: not drawable. A function of the earlier eight positional
        arguments (``task_config, states, controls, titles, label, settings, video, picture``)
        is still called that way.
      picture: suffix of the picture file ``draw`` writes (``rollout-<picture>.png``).
      mujoco_frames: ``draw`` renders with MuJoCo's OpenGL (a backend is chosen before MuJoCo loads).
      presets: sweep grids: preset name -> (the option that sets the complexity, its values).
      gpu_unroll: rollout steps per loop iteration for sweeps on a GPU (chosen per task by
        measurement; beyond it compile time grows faster than the gain).
      studies: import path of the module with the task's side of the accuracy studies and the
        benchmark (``trajectory_setup``, ``gradient_setup``, ``training_config``, ``bench_cases``,
        each optional: ``stablebptt.apps.studies``). Empty: the studies that need a set-up refuse
        the task; the training study and the benchmark's modes table take its defaults.
    """

    name: str
    module: str
    label: Callable[[Any], str] = lambda config: ""
    draw: str | Callable = ""
    picture: str = "picture"
    mujoco_frames: bool = False
    presets: dict[str, tuple[str, tuple]] = field(default_factory=dict)
    gpu_unroll: int = 1
    studies: str = ""

    def load(self) -> ModuleType:
        """The task's module, imported now."""
        return importlib.import_module(self.module)

    def drawer(self) -> Callable:
        """``draw(request) -> [written paths]``; a drawer of the earlier eight arguments is adapted."""
        draw = _import(self.draw) if isinstance(self.draw, str) else self.draw
        return _adapt_positional(draw)


def _adapt_positional(draw: Callable) -> Callable:
    """A drawer written for the eight positional arguments earlier versions passed, called with a request."""
    try:
        parameters = inspect.signature(draw).parameters.values()
    except (TypeError, ValueError):  # no signature to read (a builtin): call it as the protocol says
        return draw
    positional = [p for p in parameters if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
    if len(positional) < 8:
        return draw
    return lambda request: draw(request.task_config, request.states, request.controls, request.titles, request.label,
                                request.settings, request.video, request.picture)


_BUILTIN = (
    Entry("mjcf", "stablebptt.tasks.mjcf", label=lambda c: c.model_path.name,
          draw="stablebptt.render.drawing:draw_mujoco_rollouts", picture="strip", mujoco_frames=True,
          presets={"cartpole": ("poles", (1, 2, 3, 4))}, gpu_unroll=5, studies="stablebptt.apps.studies.cartpole"),
    Entry("repulsion", "stablebptt.tasks.repulsion", label=lambda c: f"repulsion, rc={c.rc:g}",
          draw="stablebptt.apps.figures:draw_repulsion", picture="paths",
          presets={"repulsion": ("rc", (1.0, 0.1, 0.01, 0.001)),
                   "tiny": ("rc", (1.0, 0.1))},  # the CPU test of the sweep's machinery
          gpu_unroll=10, studies="stablebptt.apps.studies.repulsion"),
    Entry("quantum", "stablebptt.tasks.quantum", label=lambda c: f"quantum, target state {c.target}",
          draw="stablebptt.apps.figures:draw_quantum", picture="density",
          presets={"quantum": ("target", (3, 4, 5))}, gpu_unroll=8, studies="stablebptt.apps.studies.quantum"),
    Entry("env", "stablebptt.tasks.env", label=lambda c: c.env or "an environment",
          draw="stablebptt.render.drawing:draw_env_rollouts", picture="strip", mujoco_frames=True),
)
_REGISTRY: dict[str, Entry] = {}
_discovered = False


def register(entry: Entry) -> None:
    """Make ``entry`` a task of every command (``--task NAME``); a later entry of the same name replaces it."""
    _REGISTRY[entry.name] = entry


def _discover() -> None:
    global _discovered
    if _discovered:
        return
    _discovered = True
    registered = dict(_REGISTRY)  # register() calls made before discovery take precedence
    for entry in _BUILTIN:
        register(entry)
    for point in entry_points(group="stablebptt.tasks"):
        register(point.load().ENTRY)
    _REGISTRY.update(registered)


def entries() -> dict[str, Entry]:
    """Every registered task by name: the built-in ones, entry points, and ``register`` calls."""
    _discover()
    return dict(_REGISTRY)


def canonical(name: str) -> str:
    """The registry name of ``name``, which may be a name earlier versions recorded (``LEGACY_NAMES``)."""
    return LEGACY_NAMES.get(name, name) if name not in entries() else name


def entry(name: str) -> Entry:
    from stablebptt.errors import InputError
    name = canonical(name)
    known = entries()
    if name not in known:
        raise InputError(f"unknown task {name!r}: one of {', '.join(sorted(known))}")
    return known[name]


def load(name: str) -> ModuleType:
    """The task module; imported lazily so that a task's heavy imports are paid only when used."""
    return entry(name).load()


def train_defaults(name: str) -> dict[str, Any]:
    """The training options the command line defaults to for task ``name``: its ``DEFAULT_EPOCHS`` and
    ``TRAIN_DEFAULTS``."""
    module = load(name)
    return {"epochs": module.DEFAULT_EPOCHS, **getattr(module, "TRAIN_DEFAULTS", {})}


def presets() -> dict[str, tuple[str, str, tuple]]:
    """Every sweep grid: preset name -> (task, option, values)."""
    return {preset: (e.name, option, values) for e in entries().values() for preset, (option, values) in e.presets.items()}
