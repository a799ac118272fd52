"""A plain ``pip install .`` (not editable) is a working package: one top-level name, the
MJCF files as package data, the ``stablebptt`` command; and MuJoCo never writes a log file."""
from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

import mujoco
import numpy as np
import pytest

from stablebptt.physics import mujoco_log

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> tuple[Path, Path]:
    """(the wheel pip builds from this checkout, the folder it is installed into)."""
    base = tmp_path_factory.mktemp("package")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--wheel-dir", str(base / "dist"),
                    str(ROOT)], check=True, cwd=base)
    (wheel,) = (base / "dist").glob("stablebptt-*.whl")
    target = base / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--target", str(target), str(wheel)],
                   check=True, cwd=base)
    return wheel, target


def test_wheel_has_one_top_level_package_with_models_and_command(installed):
    wheel, _ = installed
    with zipfile.ZipFile(wheel) as archive:
        names = archive.namelist()
        entry_points = next(archive.read(n).decode() for n in names if n.endswith("entry_points.txt"))
    assert {name.split("/")[0] for name in names if not name.split("/")[0].endswith(".dist-info")} == {"stablebptt"}
    for poles in (1, 2, 3, 4):
        assert f"stablebptt/models/cartpole_{poles}.xml" in names
    for module in ("tasks/mjcf.py", "tasks/quantum.py", "commands/train.py", "commands/main.py", "physics/mjx_internals.py"):
        assert f"stablebptt/{module}" in names
    # Every module of the library is in the wheel, subpackages included.
    library = [path.relative_to(ROOT).as_posix() for path in (ROOT / "stablebptt").rglob("*.py")]
    assert "stablebptt/apps/studies/cartpole.py" in library
    assert [module for module in library if module not in names] == []
    assert "stablebptt = stablebptt.commands.main:main" in entry_points


def _run_installed(target: Path, cwd: Path, *argv: str) -> subprocess.CompletedProcess:
    # The installed copy only: PYTHONPATH puts it before this checkout's editable install.
    env = {**os.environ, "PYTHONPATH": str(target)}
    return subprocess.run(list(argv), cwd=cwd, env=env, capture_output=True, text=True, timeout=300)


def test_installed_package_finds_its_models_from_any_directory(installed, tmp_path):
    _, target = installed
    code = ("from stablebptt.tasks import mjcf, mjcf_spec; import stablebptt.tasks as t; "
            "path = mjcf.Config(poles=3).model_path; model = mjcf_spec.load_model(path); "
            "print(t.__file__); print(path); print(model.njnt)")
    result = _run_installed(target, tmp_path, sys.executable, "-c", code)
    assert result.returncode == 0, result.stderr
    tasks_file, model_path, joints = result.stdout.split()
    assert Path(tasks_file).is_relative_to(target) and Path(model_path).is_relative_to(target)
    assert int(joints) == 4  # the cart's slider and three hinges


def test_installed_command_runs_subcommands_and_refuses_bad_input_in_one_line(installed, tmp_path):
    _, target = installed
    command = target / "bin" / "stablebptt"
    listing = _run_installed(target, tmp_path, sys.executable, str(command), "--help")
    assert listing.returncode == 0 and "train" in listing.stdout and "render" in listing.stdout
    bad = _run_installed(target, tmp_path, sys.executable, str(command), "train", "--poles", "5")
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1, bad.stderr
    assert "poles" in bad.stderr
    unknown = _run_installed(target, tmp_path, sys.executable, str(command), "fly")
    assert unknown.returncode == 2 and "unknown subcommand" in unknown.stderr
    missing = _run_installed(target, tmp_path, sys.executable, str(command))
    assert missing.returncode == 2 and missing.stdout == "" and len(missing.stderr.strip().splitlines()) == 1, missing
    assert "give a subcommand" in missing.stderr and "train" in missing.stderr
    assert not list(tmp_path.iterdir())  # nothing written into the working directory


def test_mujoco_warnings_are_collected_or_printed_never_logged_to_a_file(tmp_path, monkeypatch, capfd):
    monkeypatch.chdir(tmp_path)
    model = mujoco.MjModel.from_xml_string("<mujoco><worldbody><body><joint/><geom size='.1'/></body></worldbody></mujoco>")
    data = mujoco.MjData(model)
    with mujoco_log.collected() as lines:
        data.qvel[:] = np.inf
        mujoco.mj_step(model, data)
    assert len(lines) == 1 and "unstable" in lines[0]
    data = mujoco.MjData(model)
    data.qpos[:] = np.nan
    mujoco.mj_step(model, data)
    assert "mujoco: Nan, Inf or huge value in QPOS" in capfd.readouterr().err
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists()
