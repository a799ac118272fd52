"""Bad and hostile input - options, models, files: one line on stderr, exit code 2, nothing trained or written.

Run in-process through scripts/train.py's ``main``: each case fails before anything compiles.
"""
from __future__ import annotations

import importlib.util
import re

import pytest

from conftest import ROOT, needs_playground

pytestmark = pytest.mark.fast  # make test-fast: closed forms, invariants, tiny horizons

PENDULUM = """<mujoco>
  <option timestep="{timestep}"/>
  <worldbody>
    <body><joint name="hinge" type="hinge"/><geom type="capsule" size="0.05" fromto="0 0 0 0 0 -1"/></body>
    {extra_body}
  </worldbody>
  <actuator><motor joint="hinge"/></actuator>
  {custom}
</mujoco>"""

CASES = {
    "zero time step": (dict(timestep="0"), [], "timestep"),
    "negative time step": (dict(timestep="-0.01"), [], "timestep"),
    "zero horizon": (dict(custom='<custom><numeric name="bptt_horizon" data="0"/></custom>'), [], "bptt_horizon"),
    "negative horizon": (dict(custom='<custom><numeric name="bptt_horizon" data="-5"/></custom>'), [], "bptt_horizon"),
    "fractional horizon": (dict(custom='<custom><numeric name="bptt_horizon" data="2.5"/></custom>'), [], "bptt_horizon"),
    "NaN horizon": (dict(custom='<custom><numeric name="bptt_horizon" data="nan"/></custom>'), [], "bptt_horizon"),
    "NaN spread field": (dict(custom='<custom><numeric name="bptt_qvel_spread" data="nan"/></custom>'), [], "bptt_qvel_spread"),
    "infinite weight": (dict(custom='<custom><numeric name="bptt_joint_weight" data="inf"/></custom>'), [], "bptt_joint_weight"),
    "NaN target": (dict(custom='<keyframe><key name="target" qpos="nan"/></keyframe>'), [], "target"),
    "undecodable loss text": (dict(custom='<custom><text name="bptt_loss" data="fin\udcffal"/></custom>'), [], "UTF-8"),
    "NaN --dt": ({}, ["--dt", "nan"], "--dt"),
    "infinite --dt": ({}, ["--dt", "inf"], "--dt"),
    "--dt leaving no step": ({}, ["--dt", "1e6"], "less than one step"),
    "--dt leaving too many steps": ({}, ["--dt", "1e-300"], "steps"),
    "NaN --spread": ({}, ["--spread", "nan"], "--spread"),
    "--spread overflowing float32": ({}, ["--spread", "1e305"], "--spread"),
    "negative --steps": ({}, ["--steps", "-1"], "--steps"),
    "huge --data-seed": ({}, ["--data-seed", str(2**70)], "--data-seed"),
    "negative --seed": ({}, ["--seed", "-1"], "--seed"),
    "seeds past the last seed": ({}, ["--seed", str(2**32 - 2), "--seeds", "3"], "--seed"),
    "negative --budget": ({}, ["--budget", "-5"], "--budget"),
    "NaN --budget": ({}, ["--budget", "nan"], "--budget"),
    "negative --devices": ({}, ["--devices", "-1"], "--devices"),
    "more --devices than JAX sees": ({}, ["--devices", "64"], "--devices 64: JAX sees"),
    "--eval-every of no updates": ({}, ["--eval-every", "0"], "--eval-every"),
    "--eval-every of negative seconds": ({}, ["--eval-every", "-3s"], "--eval-every"),
    "--eval-every of no number": ({}, ["--eval-every", "often"], "--eval-every"),
    "--eval-every past a count": ({}, ["--eval-every", str(2**70)], "--eval-every"),
    "--eval-every past a float": ({}, ["--eval-every", "1" * 400], "--eval-every"),
    "a collision pair MJX lacks": (dict(extra_body='<body pos="0 0 -3"><freejoint/><geom type="cylinder" size="0.1 0.1"/>'
                                                   '</body><geom type="box" size="1 1 0.1" pos="0 0 -4"/>'),
                                   [], "cylinder-box contacts"),
    "the noslip solver, which MJX lacks": (dict(timestep='0.01" noslip_iterations="5',
                                                extra_body='<body pos="0 0 -3"><freejoint/><geom size="0.1"/></body>'
                                                           '<geom type="plane" size="1 1 0.1" pos="0 0 -4"/>'),
                                           [], "noslip"),
    "an actuator's damping, which MJX ignores": (dict(custom='<actuator><motor joint="hinge" damping="0.5"/></actuator>'),
                                                  [], "damping"),
    "reverse mode through mjx.step's solver loop": (dict(extra_body='<body pos="0 0 -3"><freejoint/><geom size="0.1"/>'
                                                                    '</body><geom type="plane" size="1 1 0.1" pos="0 0 -4"/>'),
                                                    ["--pipeline", "mjx", "--step-derivative", "reverse"], "forward"),
}


@pytest.fixture(scope="module")
def train_main():
    spec = importlib.util.spec_from_file_location("train_script", ROOT / "scripts" / "train.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.main


@pytest.mark.parametrize("case", list(CASES))
def test_hostile_input_is_one_line_and_exit_code_2(train_main, tmp_path, capsys, case):
    fields, options, words = CASES[case]
    text = PENDULUM.format(**{"timestep": "0.01", "extra_body": "", "custom": "", **fields})
    model = tmp_path / "hostile.xml"
    model.write_bytes(text.encode("utf-8", errors="surrogateescape"))  # \udcff becomes the raw byte 0xff
    out = tmp_path / "run"
    with pytest.raises(SystemExit) as exit_:
        train_main(["--model", str(model), "--epochs", "1", "--out", str(out), "--no-progress"] + options)
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert exit_.value.code == 2 and len(lines) == 1, lines
    assert lines[0].startswith("error: ") and words in lines[0], lines[0]
    assert not out.exists()  # nothing was written that could be neither resumed nor reused


# Bad options and broken model files ({dir}: the test's folder; a file named last is written with the content).
BAD_COMMAND_LINES = [
    (["--task", "pendulum"], None),
    (["--mode", "X"], None),
    (["--clip", "maybe"], None),
    (["--task", "repulsion", "--epochs", "0"], None),
    (["--task", "repulsion", "--seeds", "-1"], None),
    (["--task", "repulsion", "--lr", "0"], None),
    (["--task", "repulsion", "--lr", "-1e-3"], None),
    (["--task", "repulsion", "--batch", "0"], None),
    (["--task", "repulsion", "--batch", "7"], None),
    (["--task", "repulsion", "--poles", "3"], None),
    (["--env", "envs_for_tests:make_cart", "--sloped-reward-tails", "--epochs", "1"], None),
    (["--epochs", "many"], None),
    (["--resume", "/nonexistent/run"], None),
    (["--poles", "5"], None),
    (["--poles", "0"], None),
    (["--model", "missing.xml"], None),
    (["--model", "{dir}/broken.xml"], "<mujoco><worldbody><body></mujoco>"),
    (["--model", "{dir}/no_actuator.xml"], "<mujoco><worldbody><body><joint type='hinge'/><geom size='.1'/></body></worldbody></mujoco>"),
    (["--model", "{dir}/bad_key.xml"], "<mujoco><worldbody><body><joint type='hinge'/><geom size='.1'/></body></worldbody>"
                                       "<actuator><motor joint='0'/></actuator><keyframe><key name='init' qpos='1 2 3'/></keyframe></mujoco>"),
    (["--model", "{dir}/bad_spread.xml"], "<mujoco><worldbody><body><joint name='j' type='hinge'/><geom size='.1'/></body></worldbody>"
                                          "<actuator><motor joint='j'/></actuator><custom><numeric name='bptt_qpos_spread' data='1 2'/></custom></mujoco>"),
]

# Options given together where one makes the other meaningless: (arguments, the options the line names).
CONFLICTS = [
    (["--task", "repulsion", "--clip", "none", "--clip-threshold", "0.5"], ("--clip-threshold", "--clip none")),
    (["--task", "repulsion", "--seed-batching", "vmap"], ("--seed-batching", "--seeds")),
    (["--task", "repulsion", "--mode", "C", "--no-cosine"], ("--cosine", "mode C")),
    (["--poles", "3", "--model", "{models}/cartpole_2.xml"], ("--poles", "--model")),
    (["--poles", "2", "--steps", "50", "--horizon-seconds", "2"], ("--steps", "--horizon-seconds")),
    (["--poles", "2", "--pipeline", "mjx", "--solver-iterations", "3"], ("--solver-iterations", "--pipeline mjx")),
    (["--poles", "2", "--target-pose", "slider=0.5", "--loss-joints", "none"], ("--target-pose", "--loss-joints")),
    (["--env", "CartpoleSwingup", "--poles", "2"], ("--poles of --task mjcf", "--env is an option of --task env")),
    (["--env", "envs_for_tests:make_cart", "--model", "{models}/cartpole_2.xml"], ("--model of --task mjcf", "--env")),
    (["--task", "repulsion", "--critic-lr", "0.01"], ("--critic-lr 0.01", "--critic is off")),
    (["--task", "repulsion", "--td-lambda", "0.5"], ("--td-lambda 0.5", "--critic is off")),
    (["--task", "repulsion", "--critic-width", "256"], ("--critic-width 256", "--critic is off")),
    (["--task", "repulsion", "--normalize-critic-observations"], ("--normalize-critic-observations", "--critic is off")),
    (["--task", "repulsion", "--value-at-time-limit"], ("--value-at-time-limit", "--critic is off")),
    (["--env", "envs_for_tests:make_cart", "--no-reward-check", "--smoothing", "off"], ("--smoothing off", "--reward-check")),
    (["--env", "envs_for_tests:make_cart", "--no-reward-check", "--smoothing", "always"],
     ("--smoothing always makes its surrogate of the check's sampled states", "--reward-check")),
    (["--env", "envs_for_tests:make_cart", "--smoothing", "always", "--surrogate-reward", "envs_for_tests:position_reward"],
     ("--smoothing always smooths the env's reward", "--surrogate-reward envs_for_tests:position_reward")),
    (["--env", "envs_for_tests:make_cart", "--recipe", "locomotion", "--no-critic", "--value-at-time-limit"],
     ("--value-at-time-limit", "--critic is off")),
    (["--env", "envs_for_tests:make_cart", "--recipe", "locomotion", "--action-noise", "0", "--learn-action-noise"],
     ("--learn-action-noise", "--action-noise, which is 0", "--recipe locomotion sets")),
    (["--recipe", "locomotion", "--poles", "3"], ("--recipe locomotion", "--env NAME", "--task mjcf")),
    (["--resume", "{dir}/run", "--recipe", "locomotion"], ("--resume", "got --recipe")),
    (["--env", "envs_for_tests:make_cart", "--smoothing", "off", "--smoothing-scale", "0.5"],
     ("--smoothing-scale 0.5", "--smoothing is off")),
    (["--env", "envs_for_tests:make_cart", "--no-reward-check", "--smoothing-scale", "0.5"],
     ("--smoothing-scale 0.5", "--reward-check is off")),
]
# Bad values and what the line names: counts past what an array's dimension holds, named before anything is traced;
# networks past memory, before anything compiles; a loop unrolled past the run's longest; an env named by nothing.
NAMED_REFUSALS = [
    *[(["--env", "envs_for_tests:make_cart", *extra, option, "99999999999999999999"], (option, "2147483647"))
      for extra, option in (((), "--train-size"), ((), "--test-size"), ((), "--policy-width"),
                            (("--critic",), "--critic-width"), (("--critic",), "--critics"), ((), "--unroll"))],
    (["--env", "envs_for_tests:make_cart", "--policy-depth", "1001"], ("--policy-depth", "from 0 to 1000")),
    (["--env", "envs_for_tests:make_cart", "--critic", "--critic-depth", "1001"], ("--critic-depth", "at most 1000")),
    (["--env", "envs_for_tests:make_cart", "--policy-width", "1000000"], ("the networks' parameters need", "policy")),
    (["--env", "envs_for_tests:make_cart", "--critic", "--critics", "100000", "--critic-width", "1000"],
     ("the networks' parameters need", "--critic-width")),
    (["--env", "envs_for_tests:make_cart", "--steps", "4", "--episode-length", "6", "--unroll", "7"],
     ("--unroll 7", "has 6 steps")),
    (["--env", ":"], ("package.module:attribute",)),
    (["--env", "envs_for_tests:make_nothing_in_two_lines"], ("no cart today / ask again tomorrow",)),
    # Playground's cheetah as shipped uses an attribute MuJoCo has deprecated: no line of its own.
    (["--env", "CheetahRun", "--devices", "99"], ("CheetahRun", "--devices 99")),
]
BAD_COMMAND_LINES += [(arguments, None) for arguments, _ in CONFLICTS + NAMED_REFUSALS]


# Loading Playground's cheetah takes 12 s: the full tier.
@pytest.mark.parametrize("arguments, content", [pytest.param(*case, marks=[needs_playground, pytest.mark.slow])
                                                if "CheetahRun" in case[0] else case for case in BAD_COMMAND_LINES],
                         ids=[" ".join(a) for a, _ in BAD_COMMAND_LINES])
def test_bad_command_line_is_one_line_and_exit_code_2(train_main, tmp_path, capsys, arguments, content):
    from stablebptt import models
    named = dict((tuple(given), words) for given, words in CONFLICTS + NAMED_REFUSALS).get(tuple(arguments), ())
    arguments = [a.format(dir=tmp_path, models=models.DIRECTORY) for a in arguments]
    if content is not None:
        (tmp_path / arguments[-1].split("/")[-1]).write_text(content)
    out = tmp_path / "run"
    with pytest.raises(SystemExit) as exit_:
        train_main(arguments + ["--out", str(out), "--no-progress"] if "--resume" not in arguments else arguments)
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert exit_.value.code == 2 and len(lines) == 1 and lines[0].startswith("error: "), lines
    assert not out.exists()
    assert all(option in lines[0] for option in named), lines[0]


def test_an_empty_path_is_refused_rather_than_read_as_the_current_folder(train_main, tmp_path, capsys, monkeypatch):
    from stablebptt.commands import plot, render
    monkeypatch.chdir(tmp_path)  # where an empty --out would have written the run
    for command, arguments in ((train_main, ["--env", "envs_for_tests:make_cart", "--out", ""]),
                               (train_main, ["--resume", " "]), (render.parse, ["run", "--out", ""]),
                               (plot.parse, ["run", "--out", ""]), (plot.parse, [""])):
        with pytest.raises(SystemExit) as exit_:
            command(arguments)
        lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
        assert exit_.value.code == 2 and len(lines) == 1 and "an empty path" in lines[0], (arguments, lines)
    assert not list(tmp_path.iterdir())


@needs_playground
def test_a_playground_robot_whose_models_cannot_be_fetched_is_one_line_naming_where_they_go(
        train_main, tmp_path, capsys, monkeypatch):
    import importlib
    import subprocess
    from pathlib import Path

    from stablebptt.envs import playground
    playground.registry()
    mjx_env = importlib.import_module("mujoco_playground._src.mjx_env")
    menagerie = tmp_path / "external_deps" / "mujoco_menagerie"
    monkeypatch.setattr(mjx_env, "EXTERNAL_DEPS_PATH", Path(menagerie.parent))
    monkeypatch.setattr(mjx_env, "MENAGERIE_PATH", Path(menagerie))

    def no_network(url, target, commit):  # what git clone does without network
        raise subprocess.CalledProcessError(128, ["git", "clone"])

    monkeypatch.setattr(mjx_env, "_clone_with_progress", no_network)
    out = tmp_path / "run"
    for made, words in ((False, "fetching them failed (git clone"), (True, "lacks what it loads")):
        if made:
            menagerie.mkdir()  # a checkout without the robot's files
        with pytest.raises(SystemExit) as exit_:
            train_main(["--env", "Go1JoystickFlatTerrain", "--epochs", "1", "--out", str(out), "--no-progress"])
        lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
        assert exit_.value.code == 2 and len(lines) == 1, lines
        assert words in lines[0] and str(menagerie) in lines[0] and mjx_env.MENAGERIE_COMMIT_SHA in lines[0], lines[0]
        assert "Warp" not in lines[0] and not out.exists()


def test_the_python_api_refuses_options_that_make_each_other_meaningless_and_takes_each_alone():
    import stablebptt as sb
    from stablebptt.engine.checks import check_options
    from stablebptt.runs import run_folder
    from stablebptt.tasks import env, mjcf
    train_cases = {"TrainConfig.clip_threshold 0.5 has no effect": dict(clip="none", clip_threshold=0.5),
                   "TrainConfig.seed_batching vmap": dict(seed_batching="vmap"),
                   "TrainConfig.cosine is off, but mode C": dict(mode="C", cosine=False),
                   "TrainConfig.critic_lr 0.01 sets the critic's learning rate": dict(critic_lr=0.01),
                   "TrainConfig.td_lambda 0.5 sets the critic's": dict(td_lambda=0.5),
                   "TrainConfig.critic_depth 3 sets the critic's layers": dict(critic_depth=3),
                   "TrainConfig.critics 2 sets the critic's networks": dict(critics=2),
                   "TrainConfig.critics must be a positive integer, got 0": dict(critic=True, critics=0),
                   "TrainConfig.normalize_critic_observations standardises": dict(normalize_critic_observations=True),
                   "TrainConfig.value_at_time_limit values": dict(value_at_time_limit=True),
                   "TrainConfig.value_at_gradient_cut values": dict(value_at_gradient_cut=True)}
    for words, fields in train_cases.items():
        with pytest.raises(sb.InputError, match=words):
            sb.train(_pendulum(), sb.TrainConfig(epochs=1, **fields))  # refused before anything compiles
    task_cases = {"mjcf.Config.poles 3 picks": dict(poles=3, model=str(mjcf.MODELS / "cartpole_2.xml")),
                  "mjcf.Config.steps 50 overrides": dict(steps=50, horizon_seconds=2.0),
                  "mjcf.Config.solver_iterations 3": dict(pipeline="mjx", solver_iterations=3),
                  "mjcf.Config.target_pose": dict(target_pose="slider=0.5", reach="pole_1=0,0,1")}
    for words, fields in task_cases.items():
        with pytest.raises(sb.InputError, match=words):
            run_folder.new_record("mjcf", mjcf.Config(**fields), None, sb.TrainConfig())  # before a run records them
    env_cases = {"env.Config.smoothing off refuses": dict(reward_check=False, smoothing="off"),
                 "env.Config.smoothing_scale 0.5 .* env.Config.smoothing is off": dict(smoothing="off", smoothing_scale=0.5),
                 "env.Config.smoothing_scale 0.5 .* env.Config.reward_check is off": dict(reward_check=False, smoothing_scale=0.5)}
    for words, fields in env_cases.items():
        with pytest.raises(sb.InputError, match=words):
            run_folder.new_record("env", env.Config(env="envs_for_tests:make_cart", **fields), None, sb.TrainConfig())
    # Each option alone, or with what gives it a meaning, is taken.
    for fields in (dict(clip="norm", clip_threshold=0.5), dict(seeds=3, seed_batching="vmap"), dict(mode="R", cosine=False),
                   dict(critic=True, critic_lr=0.01, td_lambda=0.5, normalize_critic_observations=True, critic_width=256,
                        critic_depth=3, critics=2)):
        check_options(sb.TrainConfig(**fields))
    for fields in (dict(smoothing="off"), dict(smoothing_scale=0.5), dict(reward_check=False)):
        check_options(sb.TrainConfig(), env.Config(env="envs_for_tests:make_cart", **fields))
    for fields in (dict(model=str(mjcf.MODELS / "cartpole_2.xml")), dict(poles=3, steps=50), dict(horizon_seconds=2.0),
                   dict(pipeline="mjx"), dict(solver_iterations=3), dict(target_pose="slider=0.5", loss_joints="slider")):
        check_options(sb.TrainConfig(), mjcf.Config(**fields))


# The README's pendulum, as a Python user builds it: each case spoils one field.
def _pendulum():
    import jax
    import jax.numpy as jnp

    import stablebptt as sb

    def step(state, torque):
        angle, speed = state
        speed = speed + 0.05 * (-9.81 * jnp.sin(angle) + torque[0])
        return angle + 0.05 * speed, speed

    dynamics = sb.Dynamics(step=step, policy=lambda p, s: sb.mlp_apply(p, jnp.stack([jnp.sin(s[0]), s[1]])),
                           loss=lambda states, torques: 1 + jnp.cos(states[0][-1]), horizon=5)
    return sb.Task(name="pendulum", dynamics=dynamics,
                   init_params=lambda key, zero_output: sb.mlp_init(key, (2, 8, 1), zero_output),
                   sample_initial_states=lambda key, n: (jax.random.uniform(key, (n,)), jnp.zeros(n)))


def _spoiled(case):
    import dataclasses

    import jax.numpy as jnp

    import stablebptt as sb
    task = _pendulum()
    d = task.dynamics
    change = {
        "horizon 0": lambda: dataclasses.replace(task, dynamics=dataclasses.replace(d, horizon=0)),
        "horizon -3": lambda: dataclasses.replace(task, dynamics=dataclasses.replace(d, horizon=-3)),
        "horizon 2.5": lambda: dataclasses.replace(task, dynamics=dataclasses.replace(d, horizon=2.5)),
        "plan a string": lambda: dataclasses.replace(task, plan="forward"),
        "step changes structure": lambda: dataclasses.replace(task, dynamics=dataclasses.replace(
            d, step=lambda s, u: {"angle": s[0], "speed": s[1]})),
        "vector loss": lambda: dataclasses.replace(task, dynamics=dataclasses.replace(
            d, loss=lambda states, torques: 1 + jnp.cos(states[0]))),
        "wrong control shape": lambda: dataclasses.replace(task, dynamics=dataclasses.replace(
            d, policy=lambda p, s: jnp.zeros((3, 2)))),
        "sampler size": lambda: dataclasses.replace(task, sample_initial_states=lambda key, n: (jnp.zeros(n + 1), jnp.zeros(n + 1))),
        "integer states": lambda: dataclasses.replace(
            task, sample_initial_states=lambda key, n: (jnp.zeros(n, int),) * 2),
        "integer parameters": lambda: dataclasses.replace(task, init_params=lambda key, zero_output: [jnp.zeros(3, int)]),
        "dynamics a string": lambda: dataclasses.replace(task, dynamics="pendulum"),
        "name a number": lambda: dataclasses.replace(task, name=3),
        "episodes a string": lambda: dataclasses.replace(task, episodes="yes"),
        "evaluation a string": lambda: dataclasses.replace(task, evaluation="mean return"),
        "evaluation a mean": lambda: dataclasses.replace(task, evaluation=lambda params, states: jnp.cos(states[0]).mean()),
        "evaluation a number": lambda: dataclasses.replace(task, evaluation=lambda params, states: 0.5),
    }[case]
    return sb, change()


TASK_CASES = {
    "horizon 0": "Dynamics.horizon must be a positive whole number of steps, got 0",
    "horizon -3": "Dynamics.horizon must be a positive whole number of steps, got -3",
    "horizon 2.5": "Dynamics.horizon must be a positive whole number of steps, got 2.5",
    "plan a string": "Task.plan must be a stablebptt.Plan, got str",
    "step changes structure": "Dynamics.step must return a state like the one it is given",
    "vector loss": "Dynamics.loss must return one float for a trajectory",
    "wrong control shape": "Dynamics.step must return a state like the one it is given",  # it broadcast the control
    "sampler size": "Task.sample_initial_states(key, 8) must return 8 states",  # the training states' count
    "integer states": "only the dtypes differ: the step keeps those of the states Task.sample_initial_states gives",
    "integer parameters": "Task.init_params must return float parameters",
    "dynamics a string": "Task.dynamics must be a stablebptt.Dynamics, got str",
    "name a number": "Task.name must be a string, got 3",
    "episodes a string": "Task.episodes must be a stablebptt.Episodes or None, got str",
    "evaluation a string": "Task.evaluation must be a function or None, got 'mean return'",
}


def test_a_playground_env_on_mujoco_warp_is_refused_naming_the_setting_that_fixes_it():
    import types

    import stablebptt as sb
    from stablebptt.envs.protocol import EnvError
    # As Playground's registry.load gives it without config_overrides: simulated by MuJoCo Warp.
    OnWarp = type("OnWarp", (), {"__module__": "mujoco_playground._src.dm_control_suite.cartpole",
                                 "mjx_model": types.SimpleNamespace(impl=types.SimpleNamespace(value="warp"))})
    with pytest.raises(EnvError, match=r"OnWarp runs on warp, .* config_overrides=\{'impl': 'jax'\}"):
        sb.env_task(OnWarp(), horizon=16, diagnose=False)


def test_env_task_given_an_environments_class_refuses_it_and_leaves_the_class_as_it_was():
    import stablebptt as sb
    from envs_for_tests import Cart
    from stablebptt.envs.protocol import EnvError
    reset = Cart.reset
    with pytest.raises(EnvError, match=r"got the class Cart: give an instance of it \(Cart\(...\)\)"):
        sb.env_task(Cart, horizon=4, diagnose=False)
    assert Cart.reset is reset
    import envs_for_tests
    with pytest.raises(sb.EnvError, match="got the module envs_for_tests: give the environment it makes"):
        sb.env_task(envs_for_tests, horizon=4, diagnose=False)


def test_load_env_and_recipe_name_a_name_that_is_no_string():
    import stablebptt as sb
    with pytest.raises(sb.EnvError, match="an environment is named by a string"):
        sb.load_env(3)
    with pytest.raises(sb.InputError, match=r"no recipe \['locomotion'\]: choose one of locomotion"):
        sb.recipe(["locomotion"])


def test_train_given_no_task_says_so_in_its_own_terms():
    import stablebptt as sb
    from stablebptt.engine.checks import TaskError
    with pytest.raises(TaskError, match="expected a stablebptt.Task, got str"):
        sb.train("CartpoleSwingup", sb.TrainConfig(epochs=1))


@pytest.mark.parametrize("case", sorted(TASK_CASES))
def test_the_python_api_names_what_is_wrong_with_a_task_before_compiling(case):
    from stablebptt.engine.checks import TaskError
    sb, task = _spoiled(case)
    with pytest.raises(TaskError, match=TASK_CASES[case].replace("(", r"\(").replace(")", r"\)")):
        sb.make_trainer(task, sb.TrainConfig(epochs=1, train_size=8, test_size=8))


@pytest.mark.parametrize("case, given", [("evaluation a mean", "float32"), ("evaluation a number", "float")])
def test_an_evaluation_of_another_shape_than_a_loss_per_state_is_named_as_it_is_traced(case, given):
    from stablebptt.engine.checks import TaskError
    # A mean over the states, or a Python number, where a loss per state is asked for: here its 8 training and 8
    # test states at once.
    sb, task = _spoiled(case)
    with pytest.raises(TaskError, match=r"Task.evaluation\(params, initial_states\) must return one float loss per "
                                        r"initial state \(float\[16\] for 16 states\), got PyTreeDef\(\*\) with leaves "
                                        rf"{given}\[\]"):
        sb.train(task, sb.TrainConfig(epochs=1, train_size=8, test_size=8, batch=8))


def test_a_plan_names_its_wrong_field_and_dynamics_sends_engine_settings_to_plan():
    import stablebptt as sb
    for field, value, message in [
            ("step_derivative", "bogus", "Plan.step_derivative must be one of reverse, forward, got 'bogus'"),
            ("policy_gradient", "bogus", "Plan.policy_gradient must be one of batched, per-step, got 'bogus'"),
            ("unroll", 0, "Plan.unroll must be a positive whole number, got 0"),
            ("jacobian_chunk", 2.5, "Plan.jacobian_chunk must be None or a positive whole number, got 2.5"),
            ("rematerialize", "yes", "Plan.rematerialize must be True or False, got 'yes'"),
            ("chunk_placement", "envs", "Plan.chunk_placement must be None or a function, got str")]:
        with pytest.raises(sb.InputError, match=message):
            sb.Plan(**{field: value})
    physics = {name: getattr(_pendulum().dynamics, name) for name in ("step", "policy", "loss", "horizon")}
    with pytest.raises(sb.InputError, match="^Dynamics takes step, policy, loss and horizon only: step_derivative, "
                                            "unroll belong to stablebptt.Plan; pass a Plan"):
        sb.Dynamics(**physics, unroll=5, step_derivative="forward")
    with pytest.raises(sb.InputError, match="make_trainer's plan must be a stablebptt.Plan or None, got dict"):
        sb.make_trainer(_pendulum(), sb.TrainConfig(epochs=1, train_size=8, test_size=8), plan={"unroll": 5})


@pytest.mark.parametrize("field, value", [("epochs", 2.5), ("lr", "0.1"), ("batch", None), ("seeds", True),
                                          ("clip", 1), ("x64", "yes"), ("lr", 10**400)])
def test_a_train_config_field_of_the_wrong_type_is_named(field, value):
    import stablebptt as sb
    with pytest.raises(sb.InputError, match=f"TrainConfig.{field} (must be|is past the largest float)"):
        sb.TrainConfig(**{field: value})


def test_a_misspelt_keyword_is_named_beside_the_nearest_one_taken_and_the_right_one_still_taken():
    import stablebptt as sb
    from stablebptt.errors import keywords_named
    from stablebptt.physics.simulator import SimulatorConfig
    from stablebptt.tasks import env, mjcf, quantum, repulsion

    class Inherited(sb.TrainConfig):
        pass

    refused = [(lambda: sb.TrainConfig(critc=True), "^no field TrainConfig.critc: did you mean TrainConfig.critic\\?$"),
               (lambda: sb.TrainConfig(zzz=1), "^no field TrainConfig.zzz$"),
               (lambda: sb.TrainConfig(lr=0.1, zzz=1, critc=True), "^no field TrainConfig.zzz$"),  # the first
               (lambda: mjcf.Config(dtt=0.01), "^no field mjcf.Config.dtt: did you mean mjcf.Config.dt\\?$"),
               (lambda: env.Config(discont=0.9), "did you mean env.Config.discount\\?$"),
               (lambda: quantum.Config(stepz=3), "^no field quantum.Config.stepz"),
               (lambda: repulsion.Config(stepz=3), "^no field repulsion.Config.stepz"),
               (lambda: sb.Plan(unrol=2), "did you mean Plan.unroll\\?$"),
               (lambda: sb.ContactSmoothing(marginn=0.1), "did you mean ContactSmoothing.margin\\?$"),
               (lambda: sb.Task(nme="x"), "^no field Task.nme: did you mean Task.name\\?$"),
               (lambda: sb.Episodes(lenght=3), "did you mean Episodes.length\\?$"),
               (lambda: sb.Dynamics(None, None, None, 3, stepp=1), "^no field Dynamics.stepp: did you mean "
                                                                   "Dynamics.step\\?$"),
               (lambda: SimulatorConfig(dtt=0.1), "^no field SimulatorConfig.dtt: did you mean SimulatorConfig.dt\\?$"),
               (lambda: Inherited(zzz=1), "^no field Inherited.zzz$"),  # a subclass named as itself
               (lambda: sb.train(None, confg=sb.TrainConfig()), "^train\\(\\) takes no argument 'confg': did you mean "
                                                                 "'config'\\?$"),
               (lambda: sb.env_task(None, 3, horizn=2), "^env_task\\(\\) takes no argument 'horizn': did you mean "
                                                         "'horizon'\\?$")]
    for call, message in refused:
        with pytest.raises(sb.InputError, match=message):
            call()
    assert sb.TrainConfig(critic=True).critic and mjcf.Config(dt=0.02).dt == 0.02  # the fields spelt right
    with pytest.raises(sb.TaskError, match="expected a stablebptt.Task, got NoneType"):  # spelt right: train's own
        sb.train(None, config=sb.TrainConfig())
    with pytest.raises(TypeError, match="takes any keyword"):  # it would refuse every keyword it passes on
        keywords_named(lambda **options: options)


@pytest.mark.parametrize("callback", ["on_epoch", "progress_fn", "should_stop"])
def test_train_refuses_a_callback_that_is_no_function_before_compiling(callback, monkeypatch):
    import stablebptt as sb
    from stablebptt.engine import fitting
    monkeypatch.setattr(fitting, "prepare", lambda *args, **kwargs: pytest.fail("the run's start began first"))
    with pytest.raises(sb.InputError, match=f"train's {callback} must be a function"):
        sb.train(_pendulum(), sb.TrainConfig(epochs=1, train_size=8, test_size=8), **{callback: True})


def test_a_should_stop_that_answers_more_than_one_truth_value_is_named():
    import numpy as np

    import stablebptt as sb
    config = sb.TrainConfig(epochs=2, train_size=8, test_size=8)
    with pytest.raises(sb.InputError, match=r"should_stop must return one bool, got array\(\[ True, False\]\)"):
        sb.train(_pendulum(), config, should_stop=lambda: np.array([True, False]))
    stopped = sb.train(_pendulum(), config, should_stop=lambda: np.bool_(True))  # one NumPy truth value: taken
    assert len(stopped.test_loss) == 0


def test_a_dict_for_the_train_config_and_a_float64_trainer_made_in_float32_are_named():
    import stablebptt as sb
    with pytest.raises(sb.InputError, match="expected a stablebptt.TrainConfig, got dict"):
        sb.train(_pendulum(), {"epochs": 1})
    with pytest.raises(sb.InputError, match="TrainConfig.x64 asks for float64.*jax.enable_x64"):
        sb.make_trainer(_pendulum(), sb.TrainConfig(epochs=1, x64=True))


def test_x64_from_python_trains_in_float64_as_the_command_line_and_leaves_jax_as_it_was():
    import jax
    import jax.numpy as jnp
    import numpy as np

    import stablebptt as sb

    from conftest import float64
    config = sb.TrainConfig(epochs=2, train_size=8, test_size=8, x64=True, matmul_precision="highest")
    assert not jax.config.jax_enable_x64
    precision = jax.config.jax_default_matmul_precision
    scoped = sb.train(_pendulum(), config)
    assert not jax.config.jax_enable_x64 and jnp.ones(1).dtype == jnp.float32  # the user's settings are kept
    assert jax.config.jax_default_matmul_precision == precision != "highest"
    assert {leaf.dtype for leaf in jax.tree.leaves(scoped.params)} == {np.dtype(np.float64)}
    with float64():  # as the command line's --x64: JAX in float64 from the start
        whole = sb.train(_pendulum(), config)
    for a, b in zip(jax.tree.leaves(scoped.params), jax.tree.leaves(whole.params)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_array_equal(scoped.metrics["test_loss"], whole.metrics["test_loss"])


# A refusal while a compile runs beside (the reward check's, XLA cannot stop it): work that never ends by itself.
REFUSED_WHILE_WORKING = """
import threading
from stablebptt.cli import fail, stop_at_once_on_signals
from stablebptt.engine.compiling import beside
{arm}
never = threading.Event()
beside(never.wait, "stablebptt-held")
print("written before", end="")
fail("refused")
"""


def test_a_command_refused_while_a_compile_runs_beside_exits_at_once_with_its_output_flushed():
    """A plain exit waits for every thread that is not a daemon; the command's exits without waiting, so the
    held thread (which never ends) cannot hold its one line and exit code 2 back. Without that this hangs."""
    import subprocess
    import sys
    done = subprocess.run([sys.executable, "-c", REFUSED_WHILE_WORKING.format(arm="stop_at_once_on_signals()")],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert (done.returncode, done.stdout, done.stderr) == (2, "written before", "error: refused\n")


def test_a_library_users_process_refused_while_work_runs_beside_exits_as_python_does():
    import threading
    from stablebptt.cli import fail
    from stablebptt.engine.compiling import beside
    release = threading.Event()
    beside(release.wait, "stablebptt-held")
    try:
        with pytest.raises(SystemExit) as exited:  # the test's own process goes on
            fail("refused")
        assert exited.value.code == 2
    finally:
        release.set()


@pytest.mark.parametrize("arguments", [["--anisotropy", "nan"], ["--anisotropy", "-1"], ["--lr", "inf"],
                                       ["--steps", "0"], ["--out", "toy.txt"]])
def test_the_toy_problem_refuses_bad_input_before_adam_runs(capsys, arguments):
    from stablebptt.commands import toy
    with pytest.raises(SystemExit) as exit_:
        toy.main(arguments)
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert exit_.value.code == 2 and len(lines) == 1 and arguments[0] in lines[0], lines


@pytest.mark.parametrize("config, field, value", [("mjcf", "poles", "2"), ("mjcf", "dt", "0.01"), ("mjcf", "model", 5),
                                                  ("env", "env", 5), ("env", "discount", "0.9"),
                                                  ("repulsion", "steps", 2.5), ("quantum", "dt", "0.1")])
def test_a_task_config_field_of_the_wrong_type_is_named(config, field, value):
    from stablebptt.errors import InputError
    from stablebptt.tasks import env, mjcf, quantum, repulsion
    module = {"mjcf": mjcf, "env": env, "repulsion": repulsion, "quantum": quantum}[config]
    with pytest.raises(InputError, match=f"{config}.Config.{field} must be"):
        module.Config(**{field: value})


def test_numpys_scalars_are_numbers_and_truth_values_in_configs_as_pythons_are(tmp_path):
    import json
    from fractions import Fraction

    import numpy as np

    import stablebptt as sb
    from stablebptt.runs import run_folder
    from stablebptt.tasks import env, mjcf
    assert sb.TrainConfig(x64=np.False_, epochs=np.int64(3), lr=np.float32(1e-3)).epochs == 3
    assert mjcf.Config(poles=np.int64(2), dt=np.float64(0.01)).poles == 2
    assert env.Config(reward_check=np.False_, discount=np.float32(0.99)).reward_check == np.False_
    # ... and a run folder records them as the numbers written (a float32's 1e-3 as 0.001): the same config.json
    # and identity as Python's.
    records = [run_folder.run_record("mjcf", mjcf.Config(poles=poles, dt=0.01),
                                     sb.TrainConfig(x64=x64, epochs=epochs, lr=lr, clip_threshold=threshold))
               for poles, x64, epochs, lr, threshold in ((np.int64(2), np.False_, np.int64(3), np.float32(1e-3),
                                                          Fraction(1, 2)), (2, False, 3, 1e-3, 0.5))]
    for name, record in zip(("numpy", "python"), records):
        (tmp_path / name).mkdir()
        run_folder.write_config(tmp_path / name, record)
    written = [json.loads((tmp_path / name / run_folder.CONFIG_FILE).read_text()) for name in ("numpy", "python")]
    assert written[0] == written[1] and written[0]["train"]["epochs"] == 3 and written[0]["train"]["lr"] == 0.001
    assert run_folder.identity(records[0]) == run_folder.identity(records[1])


@pytest.mark.parametrize("sizes", [(3,), (3, 0, 1), (3, 2.5, 1), (3, True), "31", 3])
def test_mlp_init_names_sizes_that_make_no_network(sizes):
    import jax

    import stablebptt as sb
    with pytest.raises(sb.InputError, match=r"^mlp_init's sizes are the layers' widths, .*; got "):
        sb.mlp_init(jax.random.PRNGKey(0), sizes)


@pytest.mark.parametrize("key, shown", [(0, "0"), ("a", "'a'"), ((3,), "an array of shape (3,)"),
                                        ((4, 2), "an array of shape (4, 2)")])
def test_mlp_init_names_a_key_that_is_no_prng_key(key, shown):
    import jax.numpy as jnp

    import stablebptt as sb
    with pytest.raises(sb.InputError) as refused:
        sb.mlp_init(jnp.zeros(key, jnp.uint32) if isinstance(key, tuple) else key, (3, 2, 1))
    assert str(refused.value) == f"mlp_init's key is one PRNG key, e.g. jax.random.PRNGKey(0); got {shown}"


def test_mlp_init_takes_a_tuple_a_list_or_a_vector_of_widths():
    import jax
    import numpy as np

    import stablebptt as sb
    for good in ((3, 4, 1), [3, 4, 1], np.array([3, 4, 1])):
        assert [weights.shape for weights, _ in sb.mlp_init(jax.random.PRNGKey(0), good)] == [(3, 4), (4, 1)]


def test_flow_gradients_names_a_horizon_that_makes_no_window():
    import dataclasses

    import jax
    import jax.numpy as jnp

    import stablebptt as sb
    from stablebptt.errors import TaskError
    task = _pendulum()
    params = task.init_params(jax.random.PRNGKey(0), False)
    states = task.sample_initial_states(jax.random.PRNGKey(1), 4)
    loss, grads = sb.flow_gradients(task.dynamics, ("R",), params, states)
    assert loss.shape == () and all(jnp.all(jnp.isfinite(leaf)) for leaf in jax.tree.leaves(grads))
    for horizon in (0, 2.5):
        with pytest.raises(TaskError, match=f"^Dynamics.horizon must be a positive whole number of steps, got {horizon}$"):
            sb.flow_gradients(dataclasses.replace(task.dynamics, horizon=horizon), ("R",), params, states)
    unfit = sb.mlp_init(jax.random.PRNGKey(0), (5, 8, 1), False)  # the pendulum's policy reads 2 numbers
    with pytest.raises(TaskError, match=r"^Dynamics.policy\(params, state\) fails on the params given and one of "
                                        r"initial_states: TypeError: dot_general"):
        sb.flow_gradients(task.dynamics, ("R",), unfit, states)
    with pytest.raises(TaskError, match="^initial_states must be a batch of states, every leaf's leading axis"):
        sb.flow_gradients(task.dynamics, ("R",), params, jax.tree.map(lambda leaf: leaf[0], states))


def test_known_columns_outside_the_state_are_named_before_they_change_a_gradient():
    import dataclasses

    import jax
    import numpy as np

    import stablebptt as sb
    from stablebptt.flows.dynamics import KnownColumns
    task = _pendulum()  # a state of 2 entries: index 2 would be the control's column
    params = task.init_params(jax.random.PRNGKey(0), False)
    states = task.sample_initial_states(jax.random.PRNGKey(1), 4)
    good = KnownColumns(np.array([1]), np.zeros((2, 1)))
    sb.flow_gradients(task.dynamics, ("R",), params, states, sb.Plan(step_derivative="forward", known_columns=good))
    for indices, columns in (([2], (2, 1)), ([0, 0], (2, 2)), ([1], (3, 1))):
        plan = sb.Plan(step_derivative="forward", known_columns=KnownColumns(np.array(indices), np.zeros(columns)))
        expected = (f"Plan.known_columns must give distinct indices of the flattened state's 2 entries and columns of "
                    f"shape (2, indices), got indices {indices} and columns of shape {columns}")
        with pytest.raises(sb.InputError, match=f"^{re.escape(expected)}$"):
            sb.flow_gradients(task.dynamics, ("R",), params, states, plan)
        with pytest.raises(sb.InputError, match=f"^{re.escape(expected)}$"):  # a task's: before its memory plan
            sb.make_trainer(dataclasses.replace(task, plan=plan), sb.TrainConfig(epochs=1, train_size=8, test_size=8))
