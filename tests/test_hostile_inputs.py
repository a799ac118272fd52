"""Bad and hostile input - options, models, files: one line on stderr, exit code 2, nothing trained or written.

Run in-process through scripts/train.py's ``main``: each case fails before anything compiles.
"""
from __future__ import annotations

import importlib.util

import pytest

from conftest import ROOT

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
    "negative --steps": ({}, ["--steps", "-1"], "--steps"),
    "huge --data-seed": ({}, ["--data-seed", str(2**70)], "--data-seed"),
    "negative --seed": ({}, ["--seed", "-1"], "--seed"),
    "seeds past the last seed": ({}, ["--seed", str(2**32 - 2), "--seeds", "3"], "--seed"),
    "a collision pair MJX lacks": (dict(extra_body='<body pos="0 0 -3"><freejoint/><geom type="cylinder" size="0.1 0.1"/>'
                                                   '</body><geom type="box" size="1 1 0.1" pos="0 0 -4"/>'),
                                   [], "cylinder-box contacts"),
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


@pytest.mark.parametrize("arguments, content", BAD_COMMAND_LINES, ids=[" ".join(a) for a, _ in BAD_COMMAND_LINES])
def test_bad_command_line_is_one_line_and_exit_code_2(train_main, tmp_path, capsys, arguments, content):
    arguments = [a.format(dir=tmp_path) for a in arguments]
    if content is not None:
        (tmp_path / arguments[-1].split("/")[-1]).write_text(content)
    out = tmp_path / "run"
    with pytest.raises(SystemExit) as exit_:
        train_main(arguments + ["--out", str(out), "--no-progress"] if "--resume" not in arguments else arguments)
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert exit_.value.code == 2 and len(lines) == 1 and lines[0].startswith("error: "), lines
    assert not out.exists()
