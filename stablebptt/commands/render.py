#!/usr/bin/env python3
"""Render rollouts headless: a trained controller from a run directory, or any MJCF under a zero policy.

    python scripts/render.py runs/cartpole_3-20261122-101500    # rollout.mp4 and rollout-strip.png in the run
    python scripts/render.py runs/repulsion-20261122-101500 --gif   # rollout.gif and rollout-paths.png
    python scripts/render.py runs/quantum-20261122-101500     # rollout.mp4 and rollout-density.png
    python scripts/render.py --model stablebptt/models/cartpole_3.xml    # renders/cartpole_3-<time>.mp4 and -strip.png

The controller is rolled out from the run's first test initial states, the rollouts
side by side: a run on carried episodes (an environment's, by default) over whole
episodes of the run's episode length (--steps: fewer) with its deterministic policy,
each episode's return printed; any other run over the horizon it trained on, each
rollout's loss printed. A video draws one frame per step, or for a long rollout
evenly spaced ones (--frame-every: a stride of your own); how MuJoCo scenes are
drawn: stablebptt/render/mujoco_frames.py, stablebptt/render/drawing.py.
Existing files are never overwritten: default names get a suffix -2, -3, ...; an
existing --out is refused.
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

from stablebptt.cli import Parser, add_options, build, fail, one_line_errors, path_named
from stablebptt.errors import InputError
from stablebptt.render.media import fresh_outputs
from stablebptt.render.drawing import MAX_PANEL_PIXELS, MIN_PANEL_PIXELS
from stablebptt.render.mujoco_frames import MAX_VIDEO_FRAMES, video_indices, video_stride

RENDERS_ROOT = Path("renders")
STEM = "rollout"  # default name of the files written into a run directory
DEFAULT_ROLLOUTS = 3


@dataclass(frozen=True)
class RenderConfig:
    """Options of scripts/render.py."""

    rollouts: int = field(default=0, metadata={
        "help": f"rollouts to show, from the first test initial states, at most the run's test size "
                f"(0: {DEFAULT_ROLLOUTS}, or all where it tested fewer)"})
    seed_index: int = field(default=0, metadata={"help": "which of the run's seeds to roll out (0: the first)"})
    steps: int = field(default=0, metadata={"help": "steps of each rollout: with --model, 0 for the MJCF's bptt_horizon, else 100; a run on carried episodes, 0 for its episode length (at most that); a run from fixed starts rolls out its horizon"})
    width: int = field(default=400, metadata={
        "help": f"width in pixels of one rollout's video panel ({MIN_PANEL_PIXELS} to {MAX_PANEL_PIXELS})"})
    height: int = field(default=300, metadata={
        "help": f"height in pixels of one rollout's video panel ({MIN_PANEL_PIXELS} to {MAX_PANEL_PIXELS})"})
    fps: float = field(default=30.0, metadata={"help": "video frames per second (one frame per drawn step: --frame-every)"})
    gif: bool = field(default=False, metadata={"help": "write a GIF instead of an MP4"})
    video: bool = field(default=True, metadata={"help": "write the video (--no-video: only the pictures)"})
    strip_states: int = field(default=8, metadata={"help": "MuJoCo scenes: states overlaid in the frame strip"})
    frame_every: int = field(default=0, metadata={"help": f"MuJoCo scenes: the video draws every this many steps' state, and the last (0: every step's up to {MAX_VIDEO_FRAMES - 1} steps, else the smallest stride that keeps the video within {MAX_VIDEO_FRAMES} frames)"})

    def __post_init__(self):
        for name in ("width", "height", "strip_states"):
            if getattr(self, name) <= 0:
                raise InputError(f"--{name.replace('_', '-')} must be a positive integer, got {getattr(self, name)}")
        for name in ("rollouts", "seed_index", "steps", "frame_every"):
            if getattr(self, name) < 0:
                raise InputError(f"--{name.replace('_', '-')} must be zero or positive, got {getattr(self, name)}")
        if not self.fps > 0:
            raise InputError(f"--fps must be a positive number, got {self.fps}")
        # before the rollouts compile (DrawSettings, made once they have run, checks the same)
        if not all(MIN_PANEL_PIXELS <= side <= MAX_PANEL_PIXELS for side in (self.width, self.height)):
            raise InputError(f"--width and --height must be {MIN_PANEL_PIXELS} to {MAX_PANEL_PIXELS} pixels, "
                             f"got {self.width}x{self.height}")


def parse(argv: list[str]) -> tuple[argparse.Namespace, RenderConfig]:
    parser = Parser(description=__doc__, formatter_class=lambda prog: argparse.RawDescriptionHelpFormatter(prog, max_help_position=32))
    parser.add_argument("run_dir", type=path_named, nargs="?", default=None, help="a run directory written by scripts/train.py")
    parser.add_argument("--model", type=path_named, default=None, help="render this MJCF under a zero policy instead of a run")
    parser.add_argument("--out", type=path_named, default=None,
                        help="the video to write (.mp4 or .gif); the pictures are named after it "
                             "(default: RUN_DIR/rollout.mp4, or renders/MODEL-TIME.mp4 with --model)")
    add_options(parser, RenderConfig, "rendering")
    args = parser.parse_args(argv)
    if (args.run_dir is None) == (args.model is None):
        fail("give a run directory or --model FILE.xml (one of the two)")
    with one_line_errors():
        config = build(RenderConfig, vars(args))  # build ignores what is not a rendering option
    if args.model is not None and "seed_index" in vars(args):
        fail("--seed-index chooses a seed of a run: it needs a run directory, not --model")
    return args, config


def build_controller(args, config: RenderConfig):
    """(task name, task config, train config, task, parameters of one seed, label) of the run or the --model."""
    import jax

    from stablebptt import tasks
    from stablebptt.apps.trained import open_trained
    from stablebptt.engine.config import TrainConfig

    if args.run_dir is None:
        module = tasks.load(tasks.MJCF_TASK)
        task_config = module.Config(model=str(args.model), steps=config.steps)
        task = module.make(task_config)
        params = task.init_params(jax.random.PRNGKey(0), True)  # a zero output layer: the policy outputs 0
        return tasks.MJCF_TASK, task_config, TrainConfig(), task, params, f"{args.model.name}, zero policy"
    trained = open_trained(args.run_dir)
    params = trained.seed_params(config.seed_index)
    label = f"{trained.label}, seed {trained.train.seed + config.seed_index}"
    return trained.task_name, trained.task_config, trained.train, trained.task, params, label


def roll_out(args, config: RenderConfig, task, train, params):
    """(states [N, T+1, ...], controls [N, T, ...], a title per rollout, what was rolled out in words): whole
    episodes for a run on carried episodes, else rollouts of the horizon the run trained on (or the --model's)."""
    from stablebptt.apps.trained import episodes_from_test_states, rollouts_from_test_states
    from stablebptt.engine.training import episodes_of

    # Whether the run trained on carried episodes; rolled out at the task's length, however soon training cut them.
    episodes = None if args.run_dir is None or episodes_of(task, train) is None else task.episodes
    if args.run_dir is not None and config.rollouts > train.test_size:
        raise InputError(f"--rollouts {config.rollouts}: the run tested {train.test_size} states "
                         f"(give 1 to {train.test_size})")
    count = config.rollouts or min(DEFAULT_ROLLOUTS, train.test_size)
    if episodes is None:
        if args.run_dir is not None and config.steps:
            raise InputError(f"--steps applies to --model and to runs on carried episodes: this run trained from fixed "
                             f"starts and is rolled out over its horizon of {task.dynamics.horizon} steps")
        states, controls, losses = rollouts_from_test_states(task, train, params, count)
        titles = [f"test state {i + 1}: loss {loss:.3g}" for i, loss in enumerate(losses)]
        return states, controls, titles, (f"{plural(len(losses), 'rollout')} of {controls.shape[1]} steps, "
                                          f"losses {', '.join(f'{loss:.4g}' for loss in losses)}")
    if config.steps > episodes.length:
        raise InputError(f"--steps {config.steps}: the run's episodes are {episodes.length} steps long "
                         f"(give 1 to {episodes.length})")
    episode = episodes_from_test_states(task, episodes, params, train, count, config.steps)
    steps = episode.controls.shape[1]
    ended = [f"episode {i + 1} ended after {length} steps" for i, length in enumerate(episode.lengths) if length < steps]
    titles = [f"test state {i + 1}: return {value:.3g}" for i, value in enumerate(episode.returns)]
    return episode.states, episode.controls, titles, (
        f"{plural(len(episode.returns), 'episode')} of {steps} steps from fresh resets, "
        f"returns {', '.join(f'{value:.4g}' for value in episode.returns)}" + "".join(f"; {words}" for words in ended))


def plural(count: int, noun: str) -> str:
    return f"{count} {noun}{'s' if count != 1 else ''}"


def main(argv: list[str]) -> int:
    args, config = parse(argv)
    with one_line_errors():
        from stablebptt import tasks
        if args.run_dir is not None:
            from stablebptt.runs import run_folder  # imports JAX: only once there is a run to read
            task_name = run_folder.open_run(args.run_dir)["task"]
        else:
            if not args.model.is_file():  # as loading it would say, before a task is built
                from stablebptt.tasks.mjcf_spec import model_file_missing
                raise InputError(model_file_missing(args.model))
            task_name = tasks.MJCF_TASK
        entry = tasks.entry(task_name)
        if not entry.draw:
            raise InputError(f"the task {task_name} has no drawing (its registry entry gives no draw)")
        default_stem = (args.run_dir / STEM if args.run_dir is not None
                        else RENDERS_ROOT / f"{args.model.stem}-{datetime.now():%Y%m%d-%H%M%S}")
        video, picture = fresh_outputs(args.out, default_stem, entry.picture, config.gif, config.video)
        if entry.mujoco_frames:
            # Before mujoco is imported: it reads MUJOCO_GL once.
            from stablebptt.render.gl_backend import select_gl_backend
            select_gl_backend()

    from stablebptt.cli import leave_out_unused_backends
    from stablebptt.runtime import use_compile_cache
    leave_out_unused_backends()  # after the GL backend is chosen: it imports MJX, and MJX mujoco
    use_compile_cache()

    try:
        task_name, task_config, train, task, params, label = build_controller(args, config)
    except (InputError, TypeError) as error:  # TypeError: a config.json value of the wrong type
        fail(str(error))
    from stablebptt.apps.trained import first_nonfinite_step

    with one_line_errors():
        states, controls, titles, line = roll_out(args, config, task, train, params)
    for index, step in enumerate(first_nonfinite_step(states)):
        if step >= 0:  # a diverged rollout has nothing to draw
            fail(f"the rollout from test state {index + 1} is not finite from step {step} on "
                 "(the controller or the simulation diverged): nothing to draw", code=1)
    print(f"{label}: {line}")
    from stablebptt.render.drawing import DrawRequest, DrawSettings
    video = video if config.video else None
    picture.parent.mkdir(parents=True, exist_ok=True)  # renders/ for --model
    try:
        settings = DrawSettings(width=config.width, height=config.height, fps=config.fps,
                                strip_states=config.strip_states, frame_every=config.frame_every)
        written = entry.drawer()(DrawRequest(task_config, states, controls, titles, label, settings, video, picture))
    except InputError as error:
        fail(str(error))
    except OSError as error:  # a full disk, a directory without write permission
        fail(f"cannot write next to {picture}: {error.strerror or error}")
    stride = video_stride(controls.shape[1] + 1, config.frame_every)
    if video is not None and entry.mujoco_frames and stride > 1:
        print(f"video: a frame every {stride} steps, {len(video_indices(controls.shape[1] + 1, stride))} frames "
              f"for {controls.shape[1]} steps")
    for path in written:
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    from stablebptt.cli import stop_at_once_on_signals
    stop_at_once_on_signals()
    sys.exit(main(sys.argv[1:]))
