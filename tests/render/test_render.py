"""Headless rendering: backend choice, MuJoCo frames, frame strips, videos, task pictures and scripts/render.py.

MuJoCo fixes its OpenGL backend when first imported, and other test modules
import it without one, so everything that draws with OpenGL runs in a
subprocess that chooses the backend first (as scripts/render.py does).
"""
from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import imageio.v3 as iio
import jax
import numpy as np
import pytest

from stablebptt.engine.config import TrainConfig
from stablebptt.errors import InputError
from stablebptt.render import gl_backend, media, mujoco_frames
from stablebptt.runs import run_folder

from conftest import ROOT, needs_playground

RENDER = ROOT / "scripts" / "render.py"
TRAIN = ROOT / "scripts" / "train.py"
MODEL = ROOT / "stablebptt" / "models" / "cartpole_1.xml"
# Children here exec at once (python, ffmpeg): JAX's warning about fork in a threaded process does not apply.
pytestmark = pytest.mark.filterwarnings(r"ignore:os\.fork\(\) was called:RuntimeWarning")
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
WIDTH, HEIGHT = 160, 120  # small frames keep the software renderer fast


def run_script(script: Path, *args: str, cwd: Path | None = None) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, str(script), *map(str, args)], cwd=cwd,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def finish(process: subprocess.Popen, timeout: float = 120) -> tuple[str, str]:
    stdout, stderr = process.communicate(timeout=timeout)
    assert process.returncode == 0, stderr
    return stdout, stderr


def assert_not_blank(image: np.ndarray) -> None:
    assert image.std() > 0
    assert len(np.unique(image.reshape(-1, image.shape[-1]), axis=0)) > 1, "one colour only"


def write_run(path: Path, task_name: str, task_config: dict, seeds: int = 1, **train) -> Path:
    """A run directory as scripts/train.py leaves it (config.json, params.npz), without training."""
    from stablebptt import tasks

    module = tasks.load(task_name)
    config = TrainConfig(seeds=seeds, train_size=16, test_size=16, epochs=1, **train)
    task = module.make(module.Config(**task_config))
    keys = jax.random.split(jax.random.PRNGKey(0), seeds)
    params = jax.vmap(lambda key: task.init_params(key, False))(keys)  # Glorot output: the controls move things
    path.mkdir(parents=True)
    run_folder.write_config(path, run_folder.run_record(task_name, module.Config(**task_config), config))
    run_folder.save_params(path / run_folder.PARAMS_FILE, params)
    return path


# ---- the OpenGL backend ----

@pytest.fixture
def fresh_process(monkeypatch):
    """As if mujoco were not imported yet and MUJOCO_GL unset; restored afterwards."""
    for name in ("MUJOCO_GL", "PYOPENGL_PLATFORM"):
        monkeypatch.setenv(name, "")  # records the variable's state, so that what the test sets is undone
        monkeypatch.delenv(name)
    monkeypatch.delitem(sys.modules, "mujoco", raising=False)


def test_the_first_backend_that_renders_is_chosen(fresh_process):
    tried = []

    def probe(backend):
        tried.append(backend)
        return None if backend == "osmesa" else "no EGL display"

    assert gl_backend.select_gl_backend(probe=probe) == "osmesa"
    assert tried == ["egl", "osmesa"]
    assert os.environ["MUJOCO_GL"] == "osmesa"


def test_no_backend_is_one_line_naming_the_packages(fresh_process):
    with pytest.raises(gl_backend.NoHeadlessGL) as caught:
        gl_backend.select_gl_backend(probe=lambda backend: f"{backend} is broken")
    message = str(caught.value)
    assert "\n" not in message
    assert "apt-get install libosmesa6" in message and "libegl1" in message
    assert "MUJOCO_GL" not in os.environ


def test_a_backend_the_user_set_is_the_only_one_tried(fresh_process, monkeypatch):
    monkeypatch.setenv("MUJOCO_GL", "osmesa")
    tried = []
    with pytest.raises(gl_backend.NoHeadlessGL, match="MUJOCO_GL=osmesa.*libosmesa6"):
        gl_backend.select_gl_backend(probe=lambda backend: tried.append(backend) or "missing")
    assert tried == ["osmesa"]


def test_choosing_after_mujoco_was_imported_is_refused(monkeypatch):
    monkeypatch.delenv("MUJOCO_GL", raising=False)
    monkeypatch.setitem(sys.modules, "mujoco", sys.modules.get("mujoco", object()))
    with pytest.raises(RuntimeError, match="imported before"):
        gl_backend.select_gl_backend(probe=lambda backend: None)


def test_a_headless_backend_renders_on_this_machine():
    reasons = {backend: gl_backend.probe_gl_backend(backend) for backend in gl_backend.BACKENDS}
    assert None in reasons.values(), f"neither EGL nor OSMesa renders (.ci/run installs them): {reasons}"


# ---- MuJoCo frames, through the library, in a process that chose its backend ----

_LIBRARY_RENDER = """
import sys
import numpy as np
from stablebptt.render import gl_backend, mujoco_frames
gl_backend.select_gl_backend()
model = mujoco_frames.render_model(sys.argv[1], framebuffer=(2 * {w}, 2 * {h}))
# A rollout with large motion: the cart slides 1 m while the pole swings from hanging to level.
qpos = np.zeros(({t}, model.nq))
qpos[:, 0] = np.linspace(-0.5, 0.5, {t})
qpos[:, 1] = np.linspace(np.pi, np.pi / 2, {t})
low, high = mujoco_frames.rollout_extent(model, qpos)
camera = mujoco_frames.frame_camera(model, low, high, {w}, {h})
frames, masks = mujoco_frames.render_frames(model, qpos, camera, {w}, {h}, supersample=2, with_masks=True)
np.savez(sys.argv[2], frames=frames, masks=masks, strip=mujoco_frames.frame_strip(frames, masks), low=low, high=high)
"""
LIBRARY_FRAMES = 6


@pytest.fixture(scope="module")
def library_frames(tmp_path_factory):
    out = tmp_path_factory.mktemp("library") / "frames.npz"
    code = _LIBRARY_RENDER.format(w=WIDTH, h=HEIGHT, t=LIBRARY_FRAMES)
    result = subprocess.run([sys.executable, "-c", code, str(MODEL), str(out)], cwd=ROOT, capture_output=True,
                            text=True, timeout=120, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert result.returncode == 0, result.stderr
    with np.load(out) as data:
        return {key: data[key] for key in data.files}


def test_frames_have_the_asked_count_and_size_and_are_not_blank(library_frames):
    frames = library_frames["frames"]
    assert frames.shape == (LIBRARY_FRAMES, HEIGHT, WIDTH, 3) and frames.dtype == np.uint8
    for frame in frames:
        assert_not_blank(frame)


def test_consecutive_frames_differ(library_frames):
    frames = library_frames["frames"].astype(float)
    assert all(np.abs(frames[t + 1] - frames[t]).mean() > 0.1 for t in range(len(frames) - 1))


def test_the_camera_frames_the_whole_rollout(library_frames):
    masks = library_frames["masks"]
    assert all(mask.sum() > 20 for mask in masks), "a moving body is out of view"
    border = np.concatenate([masks[:, 0, :], masks[:, -1, :], masks[:, :, 0], masks[:, :, -1]], axis=1)
    assert border.max() == 0, "a moving body touches the edge of the frame"
    low, high = library_frames["low"], library_frames["high"]
    # The cart (half-width 0.2) slides from -0.5 to 0.5; the level pole reaches 1 m past the cart.
    assert low[0] <= -0.7 and high[0] >= 1.5 and low[2] <= -1.0


def test_the_strip_of_rendered_frames_is_an_image(library_frames):
    strip = library_frames["strip"]
    assert strip.ndim == 3 and strip.shape[2] == 3
    assert strip.shape[0] <= HEIGHT and strip.shape[1] <= WIDTH
    assert_not_blank(strip)


# ---- frame strips, tiles and files: plain arrays, no OpenGL ----

def moving_square(count: int = 5, height: int = 40, width: int = 100):
    """White frames with a red square moving right, and the square's masks."""
    frames = np.full((count, height, width, 3), 255, dtype=np.uint8)
    masks = np.zeros((count, height, width), dtype=np.float32)
    for t in range(count):
        masks[t, 15:25, 10 + 15 * t:20 + 15 * t] = 1.0
        frames[t][masks[t] > 0] = (200, 0, 0)
    return frames, masks


def test_the_strip_draws_the_last_state_opaque_and_earlier_ones_fainter():
    frames, masks = moving_square()
    strip = mujoco_frames.frame_strip(frames, masks, min_alpha=0.2, margin=None)
    assert strip.shape == frames[0].shape
    redness = [255 - float(strip[20, 15 + 15 * t, 1]) for t in range(len(frames))]  # green drops where red covers
    assert redness[-1] == 255 and redness[0] == pytest.approx(0.2 * 255, abs=1)
    assert all(a < b for a, b in zip(redness, redness[1:])), redness


def test_the_strip_is_cropped_to_the_moving_bodies():
    frames, masks = moving_square()
    strip = mujoco_frames.frame_strip(frames, masks, margin=0.0)
    assert strip.shape == (10, 70, 3)  # rows 15-24, columns 10-79


def test_tiles_keep_the_panels_and_the_gaps():
    frames, _ = moving_square(count=3)
    tiled = media.tile([frames, frames], gap=2)
    assert tiled.shape == (3, 40, 202, 3)
    assert np.array_equal(tiled[:, :, 102:], frames)


@pytest.mark.parametrize("suffix", [".mp4", ".gif"])
def test_a_video_reads_back_with_every_frame(tmp_path, suffix):
    frames, _ = moving_square(count=7, height=41, width=99)  # odd sizes: H.264 needs even ones
    path = media.write_video(tmp_path / f"clip{suffix}", frames, fps=10)
    back = iio.imread(path)
    assert back.shape[0] == 7 and back.shape[1:3] in ((41, 99), (42, 100))
    assert np.abs(back[-1].astype(float) - back[0]).mean() > 1, "the square does not move"
    assert [p.name for p in tmp_path.iterdir()] == [f"clip{suffix}"], "a temporary file was left behind"


@pytest.mark.parametrize("total", [1, 2, 21, mujoco_frames.MAX_VIDEO_FRAMES, mujoco_frames.MAX_VIDEO_FRAMES + 1, 1001])
def test_a_video_draws_evenly_spaced_states_from_the_first_to_the_last(total):
    stride = mujoco_frames.video_stride(total)
    drawn = mujoco_frames.video_indices(total, stride)
    assert drawn[0] == 0 and drawn[-1] == total - 1
    assert len(drawn) <= mujoco_frames.MAX_VIDEO_FRAMES
    gaps = np.diff(drawn)
    assert np.all(gaps[:-1] == stride) and np.all((0 < gaps) & (gaps <= stride))
    if total <= mujoco_frames.MAX_VIDEO_FRAMES:
        assert stride == 1 and len(drawn) == total  # a rollout that fits is drawn step by step
    assert mujoco_frames.video_stride(total, every=3) == 3


def test_a_video_needs_a_video_suffix(tmp_path):
    with pytest.raises(InputError, match=r"\.mp4 or \.gif"):
        media.write_video(tmp_path / "clip.avi", moving_square()[0])


# ---- repulsion and quantum pictures, from made-up rollouts ----

def test_repulsion_paths_and_animation(tmp_path):
    from stablebptt.apps import figures

    # Six agents on spirals into the origin: [N=2, T+1=9, agents=6, 2].
    time = np.linspace(0, 1, 9)[:, None]
    angle = np.arange(6)[None, :] + 3 * time
    radius = np.where(np.arange(6) < 2, 3.5, 1.5)[None, :] * (1 - 0.7 * time)
    positions = np.stack([radius * np.cos(angle), radius * np.sin(angle)], axis=-1)
    positions = np.stack([positions, -positions])
    path = figures.repulsion_paths(positions, tmp_path / "paths.png", titles=["a", "b"], title="paths")
    assert path.read_bytes().startswith(PNG_SIGNATURE)
    assert_not_blank(iio.imread(path)[..., :3])
    frames = figures.repulsion_frames(positions, duration=4.0, panel=(WIDTH, HEIGHT))
    assert frames.shape == (9, HEIGHT, 2 * WIDTH, 3) and frames.dtype == np.uint8
    assert all(np.any(a != b) for a, b in zip(frames, frames[1:])), "a frame repeats the one before"


def test_quantum_density_and_animation(tmp_path):
    from stablebptt.apps import figures
    from stablebptt.tasks import quantum

    # Eigenstates 1 and 2 in equal parts, each turning at its own frequency: the density sloshes. [N=2, T+1=11, nx, 2]
    physics, dt = quantum.Physics(), 0.0625
    energies = np.array([1.0, 4.0]) * (np.pi / physics.length) ** 2
    basis = np.stack([quantum.eigenstate(1, physics.nx), quantum.eigenstate(2, physics.nx)])
    psi = np.einsum("tk,kx->tx", np.exp(-1j * energies[None] * dt * np.arange(11)[:, None]), basis) / np.sqrt(2)
    states = np.stack([np.stack([psi.real, psi.imag], axis=-1)] * 2)
    controls = np.zeros((2, 10))
    path = figures.quantum_density(states, controls, dt, 3, tmp_path / "density.png")
    assert path.read_bytes().startswith(PNG_SIGNATURE)
    assert_not_blank(iio.imread(path)[..., :3])
    frames = figures.quantum_frames(states, controls, dt, 3, panel=(WIDTH, HEIGHT))
    assert frames.shape == (11, HEIGHT, 2 * WIDTH, 3)
    assert all(np.any(a != b) for a, b in zip(frames, frames[1:])), "a frame repeats the one before"


# ---- scripts/render.py ----

@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """render.py on an MJCF (zero policy), a repulsion run trained by train.py and a quantum run, side by side."""
    root = tmp_path_factory.mktemp("render")
    repulsion_run = root / "repulsion-run"
    training = run_script(TRAIN, "--task", "repulsion", "--steps", 8, "--epochs", 1, "--train-size", 16,
                          "--test-size", 16, "--no-progress", "--out", repulsion_run)
    quantum_run = write_run(root / "quantum-run", "quantum", {"steps": 10})
    (quantum_run / "rollout-density.png").write_bytes(b"an earlier picture")  # must survive: a fresh name is taken
    small = ("--width", WIDTH, "--height", HEIGHT, "--rollouts", 2)
    mjcf = run_script(RENDER, "--model", MODEL, "--steps", 20, "--strip-states", 4, "--out", root / "cartpole.mp4", *small)
    quantum = run_script(RENDER, quantum_run, *small)
    finish(training)
    repulsion = run_script(RENDER, repulsion_run, "--gif", *small)
    outputs = {name: finish(process, timeout=240)[0] for name, process in
               (("mjcf", mjcf), ("quantum", quantum), ("repulsion", repulsion))}
    return root, repulsion_run, quantum_run, outputs


def test_mjcf_video_has_one_frame_per_step_for_each_rollout(rendered):
    root, *_ = rendered
    frames = iio.imread(root / "cartpole.mp4")
    assert frames.shape == (21, HEIGHT, 2 * WIDTH + 2, 3)  # 20 steps and the initial state; two panels, a gap
    for frame in frames[::5]:
        assert_not_blank(frame)
    assert np.abs(frames[-1].astype(float) - frames[0]).mean() > 0.1, "nothing moved"


def test_mjcf_frame_strip_is_a_png(rendered):
    root, *_ = rendered
    strip = root / "cartpole-strip.png"
    assert strip.read_bytes().startswith(PNG_SIGNATURE)
    image = iio.imread(strip)
    assert image.shape[0] <= 2 * HEIGHT and image.shape[1] <= 2 * WIDTH
    assert_not_blank(image)


def test_the_script_names_what_it_wrote(rendered):
    root, repulsion_run, quantum_run, outputs = rendered
    assert outputs["mjcf"].strip().splitlines()[-2:] == [f"wrote {root / 'cartpole.mp4'}", f"wrote {root / 'cartpole-strip.png'}"]
    assert outputs["repulsion"].strip().splitlines()[-2:] == [f"wrote {repulsion_run / 'rollout.gif'}",
                                                              f"wrote {repulsion_run / 'rollout-paths.png'}"]
    assert "zero policy" in outputs["mjcf"] and "mode C" in outputs["repulsion"]


def test_repulsion_run_gets_an_animation_and_the_paths(rendered):
    _, repulsion_run, _, _ = rendered
    assert iio.imread(repulsion_run / "rollout.gif").shape[:2] == (9, HEIGHT)
    assert (repulsion_run / "rollout-paths.png").read_bytes().startswith(PNG_SIGNATURE)


def test_quantum_run_gets_the_density_and_an_animation_under_fresh_names(rendered):
    _, _, quantum_run, outputs = rendered
    assert outputs["quantum"].strip().splitlines()[-2:] == [f"wrote {quantum_run / 'rollout-2.mp4'}",
                                                            f"wrote {quantum_run / 'rollout-2-density.png'}"]
    assert (quantum_run / "rollout-density.png").read_bytes() == b"an earlier picture"
    assert (quantum_run / "rollout-2-density.png").read_bytes().startswith(PNG_SIGNATURE)
    assert iio.imread(quantum_run / "rollout-2.mp4").shape[:3] == (11, HEIGHT, 2 * WIDTH)


@pytest.fixture(scope="module")
def render_main():
    """scripts/render.py's ``main``, to run the bad-input cases in this process (no start-up cost each)."""
    spec = importlib.util.spec_from_file_location("render_script", RENDER)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    try:
        spec.loader.exec_module(module)
        yield module.main
    finally:
        del sys.modules[spec.name]


def bad_inputs(root: Path, repulsion_run: Path, tmp_path: Path) -> dict[str, list]:
    (tmp_path / "bare").mkdir()
    (tmp_path / "file").write_text("")
    config = (repulsion_run / "config.json").read_text()
    for name in ("no-params", "broken-params", "other-task"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "config.json").write_text(config)
    (tmp_path / "broken-params" / "params.npz").write_bytes(b"not an npz")
    run_folder.write_config(tmp_path / "other-task", run_folder.run_record("pendulum", {}, {}))
    (tmp_path / "not-json").mkdir()
    (tmp_path / "not-json" / "config.json").write_text("{")
    return {
        "a file, not a run directory": [tmp_path / "file"],
        "no config.json": [tmp_path / "bare"],
        "config.json not JSON": [tmp_path / "not-json"],
        "no params.npz": [tmp_path / "no-params"],
        "unreadable params.npz": [tmp_path / "broken-params"],
        "unknown task": [tmp_path / "other-task"],
        "missing MJCF": ["--model", tmp_path / "missing.xml"],
        "neither a run nor a model": [],
        "both a run and a model": [repulsion_run, "--model", MODEL],
        "seed out of range": [repulsion_run, "--seed-index", 5],
        "--steps with a run": [repulsion_run, "--steps", 5],
        "zero width": [repulsion_run, "--width", 0],
        "a width no framebuffer holds": [repulsion_run, "--width", 100000000],
        "more rollouts than the run tested": [repulsion_run, "--rollouts", 99],
        "not a video name": [repulsion_run, "--out", tmp_path / "x.avi"],
        "--gif with an .mp4 name": [repulsion_run, "--gif", "--out", tmp_path / "x.mp4"],
        "existing --out": ["--model", MODEL, "--out", root / "cartpole.mp4"],
    }


def test_bad_input_is_one_line_and_exit_2(rendered, render_main, tmp_path, capsys):
    root, repulsion_run, _, _ = rendered
    for name, args in bad_inputs(root, repulsion_run, tmp_path).items():
        with pytest.raises(SystemExit) as caught:
            render_main([str(arg) for arg in args])
        stdout, stderr = capsys.readouterr()
        assert caught.value.code == 2, f"{name}: exit {caught.value.code}, stderr {stderr!r}"
        lines = stderr.splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: "), f"{name}: {stderr!r}"
        assert stdout == "", name
    assert not list(tmp_path.rglob("*.mp4")) and not list(tmp_path.rglob("*.png"))


def test_bad_input_from_the_command_line(rendered, tmp_path):
    """As a user sees it: exit code 2 and one line, no traceback; a broken MJCF fails after the backend probe."""
    root, *_ = rendered
    (tmp_path / "broken.xml").write_text("<mujoco><worldbody><geom type='nonsense'/></worldbody></mujoco>")
    cases = {
        "missing run directory": [tmp_path / "nowhere"],
        "malformed MJCF": ["--model", tmp_path / "broken.xml"],
    }
    processes = {name: run_script(RENDER, *args, cwd=tmp_path) for name, args in cases.items()}
    errors = {}
    for name, process in processes.items():
        _, errors[name] = process.communicate(timeout=120)
        assert process.returncode == 2, f"{name}: exit {process.returncode}, stderr {errors[name]!r}"
        lines = errors[name].splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: "), f"{name}: {errors[name]!r}"
    assert "broken.xml" in errors["malformed MJCF"]
    assert not (tmp_path / "renders").exists()


# ---- a run on carried episodes: whole episodes, their returns ----

EPISODE_LENGTH = 20


@pytest.fixture(scope="module")
def episode_renders(tmp_path_factory):
    """A CartpoleSwingup run on carried episodes, windows of 8 steps along episodes of EPISODE_LENGTH that training
    cuts at 12 steps, rendered as it comes (whole episodes: the cut is training's alone) and with --steps and
    --frame-every."""
    root = tmp_path_factory.mktemp("episodes")
    run = root / "cartpole-run"
    trained, _ = finish(run_script(TRAIN, "--env", "CartpoleSwingup", "--epochs", 1, "--batch", 2, "--train-size", 2,
                                   "--test-size", 2, "--steps", 8, "--episode-length", EPISODE_LENGTH,
                                   "--training-episode-length", 12, "--no-reward-check",
                                   "--no-progress", "--out", run), timeout=600)
    small = ("--width", WIDTH, "--height", HEIGHT, "--rollouts", 2)
    whole = run_script(RENDER, run, *small)
    short = run_script(RENDER, run, "--steps", 10, "--frame-every", 3, "--out", root / "short.mp4", *small)
    outputs = {name: (process.communicate(timeout=300), process.returncode) for name, process in
               (("whole", whole), ("short", short))}
    outputs["train"] = ((trained, ""), 0)
    return root, run, outputs


def printed(outputs: dict, name: str) -> list[str]:
    """The lines a render of ``episode_renders`` printed, once it succeeded."""
    (stdout, stderr), code = outputs[name]
    assert code == 0, stderr
    return stdout.splitlines()


@needs_playground
def test_an_episode_run_renders_whole_episodes_with_their_returns(episode_renders):
    _, run, outputs = episode_renders
    line = printed(outputs, "whole")[0]
    assert f"2 episodes of {EPISODE_LENGTH} steps from fresh resets, returns " in line, line
    returns = [float(value) for value in line.rpartition("returns ")[2].split(", ")]
    # The test states are the run's own: their mean return is what the run logged as its test loss (negated).
    test_loss = run_folder.read_metrics(run / run_folder.METRICS_FILE)[-1]["test_loss"]
    assert np.mean(returns) == pytest.approx(-test_loss, rel=2e-3)
    frames = iio.imread(run / "rollout.mp4")
    assert frames.shape == (EPISODE_LENGTH + 1, HEIGHT, 2 * WIDTH + 2, 3)  # the episode and its first state
    assert (run / "rollout-strip.png").read_bytes().startswith(PNG_SIGNATURE)


@needs_playground
def test_a_playground_env_trained_unchecked_says_its_repairs_and_records_its_reward_as_not_checked(episode_renders):
    _, run, outputs = episode_renders
    summary = "\n".join(printed(outputs, "train"))
    assert "repaired: Playground's reward tolerance" in summary and "reward gradient" not in summary, summary
    from stablebptt.apps.trained import open_trained
    assert open_trained(run).task.resolved["reward_gradient"] == "not checked"


@needs_playground
def test_steps_shortens_the_episodes_and_frame_every_thins_the_video(episode_renders):
    root, _, outputs = episode_renders
    lines = printed(outputs, "short")
    assert "2 episodes of 10 steps from fresh resets, returns " in lines[0], lines
    assert "video: a frame every 3 steps, 5 frames for 10 steps" in lines, lines
    assert iio.imread(root / "short.mp4").shape[0] == 5  # steps 0, 3, 6, 9 and the last, 10


@needs_playground
def test_steps_beyond_the_episode_length_is_one_line_and_exit_2(episode_renders):
    _, run, _ = episode_renders
    process = run_script(RENDER, run, "--steps", EPISODE_LENGTH + 1, "--no-video")
    stdout, stderr = process.communicate(timeout=120)
    assert process.returncode == 2 and stdout == ""
    assert stderr.splitlines() == [f"error: --steps {EPISODE_LENGTH + 1}: the run's episodes are {EPISODE_LENGTH} "
                                   f"steps long (give 1 to {EPISODE_LENGTH})"]
    assert not list(run.glob("rollout-2*")), "a refused render wrote a file"


@needs_playground
def test_the_probes_look_at_a_runs_episodes_reads_the_whole_episodes_of_its_test_states(episode_renders, capsys):
    """benchmarks/env_probe.py's ``episodes`` on a run whose training cut its episodes: the task's whole episodes
    from the run's test states, as the render rolled them, and when in each the reward was earned."""
    _, run, outputs = episode_renders
    spec = importlib.util.spec_from_file_location("env_probe", ROOT / "benchmarks" / "env_probe.py")
    env_probe = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(env_probe)
    env_probe.episodes_of_run(run, 2, 0)
    lines = capsys.readouterr().out.splitlines()
    rendered = [float(value) for value in printed(outputs, "whole")[0].rpartition("returns ")[2].split(", ")]
    assert "2 test episodes, mean return " in lines[0], lines
    assert float(lines[0].rpartition(" ")[2]) == pytest.approx(np.mean(rendered), abs=0.051)  # printed to 0.1
    assert len(lines) == 3 and all(f" of {EPISODE_LENGTH} steps rewarded, from step " in line
                                   or "no step rewarded" in line for line in lines[1:]), lines


def test_an_episode_return_is_the_envs_own_reward_the_runs_evaluation_sums():
    """An env trained on a surrogate reward: its rendered episodes return what its evaluation reports, the env's
    own reward, not the surrogate the windows trained on."""
    from envs_for_tests import Cart

    from stablebptt.apps.trained import episodes_from_test_states
    from stablebptt.engine.initial_states import sample_states
    from stablebptt.envs.adapter import env_task

    task = env_task(Cart(), horizon=4, episode_length=6, diagnose=False,
                    surrogate_reward=lambda state: jax.numpy.ones_like(state.reward))
    train = TrainConfig(test_size=3)
    params = task.init_params(jax.random.PRNGKey(1), False)
    episode = episodes_from_test_states(task, task.episodes, params, train, 3)
    _, test_key = jax.random.split(jax.random.PRNGKey(train.data_seed))
    evaluated = task.evaluation(params, sample_states(task, test_key, train.test_size))
    np.testing.assert_allclose(episode.returns, -np.asarray(evaluated), rtol=1e-5)
    assert np.all(episode.returns < 0), "the surrogate's reward (1 a step) was summed"
    assert episode.controls.shape[:2] == (3, 6) and episode.lengths.tolist() == [6, 6, 6]
