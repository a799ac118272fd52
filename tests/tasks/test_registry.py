"""The task registry: scripts learn everything task-specific from it, and a user's own task,
registered from Python, trains, renders and sweeps through the unchanged command line."""
from __future__ import annotations

import sys
import textwrap
from pathlib import Path

import pytest

from stablebptt import tasks
from stablebptt.commands import render as render_command
from stablebptt.commands import train as train_command
from stablebptt.errors import InputError
from stablebptt.runs import run_folder

pytestmark = pytest.mark.fast  # make test-fast: closed forms, invariants, tiny horizons

OWN_TASK = '''
"""A user's own system: a point mass pushed toward the origin, a hand-written JAX step."""
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp

from stablebptt import Dynamics, Task, mlp_apply, mlp_init

DEFAULT_EPOCHS = 3


@dataclass(frozen=True)
class Config:
    mass: float = field(default=2.0, metadata={"help": "mass of the point"})


def make(config: Config) -> Task:
    dt = 0.05

    def step(state, control):
        position, velocity = state
        velocity = velocity + dt * control / config.mass
        return position + dt * velocity, velocity

    dynamics = Dynamics(step=step, policy=lambda params, state: mlp_apply(params, jnp.concatenate(state)),
                        loss=lambda states, controls: jnp.sum(states[0][-1] ** 2), horizon=20)
    sample = lambda key, count: (jax.random.normal(key, (count, 2)), jnp.zeros((count, 2)))
    return Task(name="pointmass", dynamics=dynamics, sample_initial_states=sample,
                init_params=lambda key, zero_output: mlp_init(key, (4, 16, 2), zero_output))


def draw(request):
    request.picture.write_text(f"{request.label}: {len(request.titles)} rollouts of {request.controls.shape[1]} steps")
    return [request.picture]
'''


@pytest.fixture(scope="module")
def own_task(tmp_path_factory):
    folder = tmp_path_factory.mktemp("my_lab")
    (folder / "own_pointmass.py").write_text(textwrap.dedent(OWN_TASK))
    sys.path.insert(0, str(folder))
    tasks.register(tasks.Entry(name="pointmass", module="own_pointmass", label=lambda c: f"point mass of {c.mass:g} kg",
                               draw="own_pointmass:draw", picture="text"))
    yield
    sys.path.remove(str(folder))


def test_every_builtin_entry_names_a_module_a_label_a_drawer_and_grids():
    for name, entry in tasks.entries().items():
        if name == "pointmass":
            continue
        module = entry.load()
        assert callable(module.make) and module.DEFAULT_EPOCHS > 0
        assert entry.label(module.Config()) and callable(entry.drawer())
    presets = tasks.presets()
    assert {"cartpole", "repulsion", "quantum", "tiny"} <= set(presets)
    for task_name, option, values in presets.values():
        assert option in {f for f in tasks.load(task_name).Config.__dataclass_fields__} and values


def test_an_unknown_task_is_one_line():
    with pytest.raises(InputError, match="unknown task 'pendulum'"):
        tasks.entry("pendulum")


@pytest.mark.slow  # a command line that trains and renders: the full tier
def test_a_registered_own_task_trains_and_renders_through_the_command_line(own_task, tmp_path, capsys):
    run_dir = tmp_path / "own"
    assert train_command.main(["--task", "pointmass", "--mass", "3", "--train-size", "16", "--test-size", "16",
                               "--no-progress", "--out", str(run_dir)]) == 0
    record = run_folder.open_run(run_dir)
    assert record["task"] == "pointmass" and record["task_config"] == {"mass": 3.0} and record["train"]["epochs"] == 3
    losses = [row["test_loss"] for row in run_folder.read_metrics(run_dir / run_folder.METRICS_FILE)]
    assert losses[-1] < losses[0]  # the point moves toward the origin
    assert render_command.main([str(run_dir), "--rollouts", "2", "--no-video"]) == 0
    (picture,) = Path(run_dir).glob("*-text.png")
    assert picture.read_text() == "point mass of 3 kg, mode C, 3 epochs, seed 42: 2 rollouts of 20 steps"


def test_a_drawer_of_the_earlier_eight_arguments_gets_them_from_the_request(tmp_path):
    from stablebptt.render.drawing import DrawRequest, DrawSettings
    received = []

    def legacy(task_config, states, controls, titles, label, settings, video, picture):
        received.append((task_config, states, controls, titles, label, settings, video, picture))
        return [picture]

    settings = DrawSettings(width=32, height=24, fps=10.0, strip_states=3)
    request = DrawRequest("config", "states", "controls", ["a", "b"], "label", settings, None, tmp_path / "p.png")
    assert tasks.Entry(name="legacy", module="unused", draw=legacy).drawer()(request) == [tmp_path / "p.png"]
    assert received == [("config", "states", "controls", ["a", "b"], "label", settings, None, tmp_path / "p.png")]
    new_style = lambda request: [request.picture]
    assert tasks.Entry(name="new", module="unused", draw=new_style).drawer() is new_style
    with pytest.raises(InputError, match="16x16"):
        DrawSettings(width=8)


def test_a_task_modules_reopening_hook_of_either_form_rebuilds_the_run_it_names():
    """A module's ``for_reopening(config, resolved)`` gets the run's record; one of the user's written in the
    hook's first form, ``for_reopening(config)``, is still called (no TypeError from ``stablebptt render``);
    a module without the hook reopens with the run's configuration as it is."""
    from types import SimpleNamespace

    from stablebptt.apps.trained import config_for_reopening
    resolved = {"reward_smoothing": "1 comparison"}
    both = SimpleNamespace(for_reopening=lambda config, resolved: (config, resolved["reward_smoothing"]))
    first_form = SimpleNamespace(for_reopening=lambda config: (config, "alone"))
    defaulted = SimpleNamespace(for_reopening=lambda config, resolved=None: (config, resolved))
    assert config_for_reopening(both, "config", resolved) == ("config", "1 comparison")
    assert config_for_reopening(first_form, "config", resolved) == ("config", "alone")
    assert config_for_reopening(defaulted, "config", resolved) == ("config", resolved)
    assert config_for_reopening(SimpleNamespace(), "config", resolved) == "config"


def test_runs_recorded_under_the_mjcf_tasks_former_name_reopen(tmp_path):
    """Run folders written when the MJCF task was named "cartpole" still name a task that resumes and renders."""
    import dataclasses

    from stablebptt.apps.trained import configs_of
    from stablebptt.engine.config import TrainConfig
    from stablebptt.tasks import mjcf
    assert tasks.entry("cartpole") is tasks.entry("mjcf") and tasks.canonical("cartpole") == "mjcf"
    record = {"task": "cartpole", "task_config": dataclasses.asdict(mjcf.Config(poles=2)),
              "train": dataclasses.asdict(TrainConfig(epochs=3))}
    task_config, train = configs_of(tmp_path, record)
    assert isinstance(task_config, mjcf.Config) and task_config.poles == 2 and train.epochs == 3


def test_the_help_says_each_tasks_training_defaults_as_a_new_run_records_them(capsys):
    import dataclasses
    import re

    from stablebptt.engine.config import TrainConfig
    with pytest.raises(SystemExit):
        train_command.parse(["--help"])
    text = " ".join(capsys.readouterr().out.split())  # argparse's wrapping undone
    recorded = {name: train_command.configure(*train_command.parse(["--task", name]))[2] for name in tasks.entries()}
    for field in dataclasses.fields(TrainConfig):
        option = "--" + field.name.replace("_", "-")
        said = re.search(rf"{option}(?: {field.name.upper()}|, --no-{option[2:]}) (?!\|).*?\(default: ([^)]*)\)", text)
        default, *by_task = said.group(1).split("; ")
        named = dict(words.split(": ") for words in ", ".join(by_task).split(", ") if words)
        for task_name, config in recorded.items():
            assert str(getattr(config, field.name)) == named.get(f"--task {task_name}", default), (option, task_name)


def test_a_recipe_sets_its_options_for_an_env_and_an_option_given_beside_it_wins():
    from stablebptt.tasks import env
    recipe = env.RECIPES["locomotion"]
    command = ["--env", "envs_for_tests:make_cart", "--recipe", "locomotion"]
    _, task_config, train, _, _ = train_command.configure(*train_command.parse(command))
    plain_task, plain_train = train_command.configure(*train_command.parse(command[:2]))[1:3]
    for name, value in recipe.items():
        config, plain = (task_config, plain_task) if hasattr(task_config, name) else (train, plain_train)
        assert getattr(config, name) == value != getattr(plain, name), name
    _, task_config, train, _, _ = train_command.configure(*train_command.parse(command + ["--batch", "32", "--steps", "8"]))
    assert (train.batch, task_config.steps, train.critic, task_config.discount) == (32, 8, True, 0.99)


def test_an_option_given_beside_a_recipe_leaves_out_what_the_recipe_set_for_the_value_it_replaces():
    # Turned off beside the recipe, an option takes with it the recipe's values chosen for it, in turn: the user
    # is not told to drop an option the recipe set.
    command = ["--env", "envs_for_tests:make_cart", "--recipe", "locomotion", "--train-size", "64"]
    chosen = lambda *beside: train_command.configure(*train_command.parse(command + list(beside)))[2]  # noqa: E731
    plain = train_command.configure(*train_command.parse(command[:2]))[2]
    without_critic = chosen("--no-critic")
    assert (without_critic.critic, without_critic.normalize_critic_observations, without_critic.value_at_time_limit) == (
        False, False, False)
    assert (without_critic.learn_action_noise, without_critic.entropy) == (True, 0.01)  # the noise's own are kept
    assert (chosen("--no-learn-action-noise").entropy, chosen("--no-learn-action-noise").action_noise) == (0.0, 0.3)
    silent = chosen("--action-noise", "0")
    assert (silent.action_noise, silent.learn_action_noise, silent.entropy, silent.critic) == (0.0, False, 0.0, True)
    fixed = chosen("--episodes", "off")
    assert (fixed.critic, fixed.normalize_critic_observations, fixed.batch) == (False, False, plain.batch)
    assert (fixed.action_noise, fixed.learn_action_noise, fixed.entropy) == (0.0, False, 0.0)
    # and the trainer takes it (its set-up refused the noise that needs carried episodes)
    from envs_for_tests import make_cart

    import stablebptt as sb
    assert sb.make_trainer(sb.env_task(make_cart(), horizon=16, diagnose=False), fixed).episodes is None
    # From fixed starts an env's default batch of carried states, which does not split its 16 starts, is all of them.
    alone = lambda *beside: train_command.configure(*train_command.parse(command[:2] + list(beside)))[2]  # noqa: E731
    assert (alone("--episodes", "off").batch, alone("--episodes", "off", "--train-size", "128").batch) == (16, 64)
    with pytest.raises(InputError, match="does not divide"):
        alone("--episodes", "off", "--batch", "7")
    # Given beside, a value the recipe would leave out stays, and is refused as it is alone.
    with pytest.raises(InputError, match="needs TrainConfig.learn_action_noise"):
        train_command.configure(*train_command.parse(command + ["--no-learn-action-noise", "--entropy", "0.01"]))


def test_a_recipe_names_each_task_option_as_env_task_takes_it(monkeypatch):
    import inspect

    import stablebptt as sb
    from stablebptt.tasks import env
    # A task option that env_task takes under another name, or as another value, reaches it so.
    monkeypatch.setitem(env.RECIPES, "trial", {"steps": 8, "observe_reward_direction": True,
                                               "physics_step_carry": "state", "physics_step_residuals": "stored",
                                               "smoothing": "always", "batch": 4})
    task_options, train_options = sb.recipe("trial")
    assert task_options == {"horizon": 8, "reward_direction_observed": True, "physics_steps_carrying_state": True,
                            "physics_steps_recomputed": False, "smoothing": "always"}
    assert train_options == {"batch": 4}
    assert set(task_options) <= set(inspect.signature(sb.env_task).parameters)


def test_a_recipe_from_python_is_env_tasks_arguments_and_the_train_configs_fields():
    import inspect

    import stablebptt as sb
    from stablebptt.engine.config import TrainConfig
    from stablebptt.tasks import env
    task_options, train_options = sb.recipe("locomotion")
    # The task option --steps is env_task's horizon.
    assert set(task_options) <= set(inspect.signature(sb.env_task).parameters)
    assert task_options["horizon"] == env.RECIPES["locomotion"]["steps"]
    config = TrainConfig(**train_options)
    assert all(getattr(config, name) == value for name, value in train_options.items())
    # The same options as the command line's --recipe sets.
    _, task_config, train, _, _ = train_command.configure(*train_command.parse(
        ["--env", "envs_for_tests:make_cart", "--recipe", "locomotion"]))
    assert (task_config.steps, task_config.discount) == (task_options["horizon"], task_options["discount"])
    assert all(getattr(train, name) == value for name, value in train_options.items())
    with pytest.raises(InputError, match="no recipe 'swimming': choose one of locomotion"):
        sb.recipe("swimming")
    # An env of the user's own takes the common options; a registry name spelled otherwise is refused, not
    # given the common ones in place of its own.
    assert sb.recipe("locomotion", "MyLabsHexapod") == sb.recipe("locomotion")
    with pytest.raises(InputError, match="options of its own for CheetahRun, not 'cheetahrun'"):
        sb.recipe("locomotion", "cheetahrun")


def test_a_recipe_takes_its_values_for_the_env_named_where_it_has_them_and_an_option_beside_still_wins():
    import inspect

    from envs_for_tests import Cart

    import stablebptt as sb
    from stablebptt.tasks import env
    for name, by_env in env.RECIPES_BY_ENV.items():
        for env_name, options in by_env.items():
            command = ["--env", env_name, "--recipe", name]
            _, task_config, train, _, _ = train_command.configure(*train_command.parse(command))
            task_options, train_options = sb.recipe(name, env_name)
            # From Python, env_task's own arguments (the reachers' and the fingers' direction is named there otherwise).
            assert set(task_options) <= set(inspect.signature(sb.env_task).parameters), env_name
            for option, value in {**env.RECIPES[name], **options}.items():
                config = task_config if hasattr(task_config, option) else train
                assert getattr(config, option) == value, (env_name, option)
                if option not in env.ENV_TASK_ARGUMENTS:  # those renamed: the test of each renamed option above
                    assert {**task_options, **train_options}[option] == value
            assert train_command.configure(*train_command.parse(command + ["--steps", "12"]))[1].steps == 12
    # An env the recipe has nothing of its own for takes the recipe as it is.
    assert sb.recipe("locomotion", "HopperHop") == sb.recipe("locomotion")
    # The cheetah's R trains without g_M; another mode given beside takes its own flows, not a refusal.
    cheetah = ["--env", "CheetahRun", "--recipe", "locomotion"]
    chosen = lambda *beside: train_command.configure(*train_command.parse(cheetah + list(beside)))[2]
    assert (chosen().mode, chosen().cosine) == ("R", False)
    assert (chosen("--mode", "C").mode, chosen("--mode", "C").cosine) == ("C", True)
    assert (chosen("--mode", "R").cosine, chosen("--cosine").cosine, chosen("--cosine").mode) == (False, True, "R")
    # The finger's turn goes on through a flow's non-finite gradient, which C alone can: R given beside stops.
    finger = lambda *beside: train_command.configure(*train_command.parse(  # noqa: E731
        ["--env", "FingerTurnHard", "--recipe", "locomotion", *beside]))[2]
    assert (finger().mode, finger().nonfinite_flows, finger("--mode", "C").nonfinite_flows) == ("C", "zero", "zero")
    assert (finger("--mode", "R").nonfinite_flows, finger("--mode", "R", "--nonfinite-flows", "stop").mode) == ("stop", "R")
    # The fish's surrogate is made of the reward check's samples: without the check it trains its reward as written.
    fish = lambda *beside: train_command.configure(*train_command.parse(  # noqa: E731
        ["--env", "FishSwim", "--recipe", "locomotion", *beside]))[1]
    assert (fish().smoothing, fish("--no-reward-check").smoothing, fish("--no-reward-check").reward_check) == (
        "always", "auto", False)
    assert fish("--surrogate-reward", "envs_for_tests:position_reward").smoothing == "auto"  # trained as given
    assert sb.recipe("locomotion", "ReacherEasy")[0]["reward_direction_observed"] is True
    # The hopper's cut was measured on carried episodes of the env's own length with the cut state valued:
    # without any of those it is left out, and a cut given beside stays.
    hopper = lambda *beside: train_command.configure(*train_command.parse(  # noqa: E731
        ["--env", "HopperStand", "--recipe", "locomotion", *beside]))[2]
    assert hopper().training_episode_length == 64
    assert [hopper(*beside).training_episode_length for beside in (
        ("--episodes", "off"), ("--no-critic",), ("--no-value-at-time-limit",), ("--episode-length", "50"))] == [0] * 4
    assert hopper("--training-episode-length", "128").training_episode_length == 128
    assert {sb.recipe("locomotion", walker)[0]["horizon"] for walker in ("WalkerWalk", "WalkerStand", "WalkerRun")} \
        == {2} != {env.RECIPES["locomotion"]["steps"]}
    with pytest.raises(InputError, match="a recipe's env is the env's name .* got Cart"):
        sb.recipe("locomotion", Cart())  # the env itself, not its name
