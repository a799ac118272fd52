"""Learning-curve plots: smoothing, the seed band, run loading, the figure and scripts/plot.py."""
from __future__ import annotations

import copy
import csv
import os
import subprocess
import sys
import warnings
from pathlib import Path

import matplotlib
import numpy as np
import pytest
from matplotlib.colors import to_rgb

from stablebptt import storage
from stablebptt.engine.metrics import COLUMNS
from stablebptt.errors import InputError
from stablebptt.reports import curves, plots
from stablebptt.runs import run_folder

from conftest import ROOT

SCRIPT = ROOT / "scripts" / "plot.py"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def write_run(path: Path, mode: str = "C", clip: str = "value", rc: float = 0.1, epochs: int = 20,
              seeds: tuple[int, ...] = (42, 43), cosine: bool = True, update_norm: float | None = None,
              task: str = "repulsion", task_config: dict | None = None) -> Path:
    """A run directory as scripts/train.py writes it, with made-up, known metrics."""
    path.mkdir(parents=True)
    task_config = {"rc": rc, "steps": 60, "integrator": "euler"} if task_config is None else task_config
    train = {"mode": mode, "clip": clip, "epochs": epochs, "seeds": len(seeds), "lr": 0.001}
    run_folder.write_config(path, run_folder.run_record(task, task_config, train))
    with open(path / "metrics.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(COLUMNS)
        for epoch in range(1, epochs + 1):
            for k, seed in enumerate(seeds):
                loss = 5.0 * np.exp(-0.1 * epoch) * (1 + 0.1 * k) + 0.1
                norm = 0.05 / epoch if update_norm is None else update_norm
                writer.writerow([epoch, seed, loss, loss, loss, norm, 0.9 - 0.01 * epoch if cosine else float("nan"), 0.1,
                                 0.0, 1000 * epoch])
    return path


# ---- smoothing ----

@pytest.mark.parametrize("window", [0, 1, 2, 5, 30, 200])
def test_smoothing_keeps_a_constant(window):
    values = np.full((40, 3), 2.5)
    np.testing.assert_allclose(curves.moving_average(values, window), values, rtol=1e-12)


@pytest.mark.parametrize("window", [2, 7, 30, 200])
def test_smoothing_keeps_a_line_up_to_both_ends(window):
    epochs = np.arange(1, 61, dtype=float)
    values = np.stack([3.0 - 0.04 * epochs, 0.5 + 2.0 * epochs], axis=1)
    np.testing.assert_allclose(curves.moving_average(values, window), values, rtol=1e-9, atol=1e-9)


def test_smoothing_averages_known_values():
    # Inside: the mean of 3 neighbours; at the ends: a line fitted to the 3 nearest (flat here, through the mean).
    smoothed = curves.moving_average(np.array([0.0, 3.0, 0.0, 3.0, 0.0, 3.0]), 2)
    np.testing.assert_allclose(smoothed, [1.0, 1.0, 2.0, 1.0, 2.0, 2.0])


def test_smoothing_reduces_noise_everywhere_including_the_ends():
    noise = np.random.default_rng(0).standard_normal(300)
    smoothed = curves.moving_average(noise, 30)
    assert np.abs(smoothed).max() < 0.5 * np.abs(noise).max()
    assert abs(smoothed[-1]) < 0.6 and abs(smoothed[0]) < 0.6  # the ends are smoothed too, not left raw


def test_smoothing_skips_nan_and_keeps_all_nan_as_nan():
    line = np.linspace(1.0, 2.0, 30)
    holed = line.copy()
    holed[[0, 7, 8, 29]] = np.nan
    np.testing.assert_allclose(curves.moving_average(holed, 6), line, rtol=1e-9)
    assert np.all(np.isnan(curves.moving_average(np.full(10, np.nan), 4)))


def test_smoothing_rejects_a_negative_window():
    with pytest.raises(InputError, match="zero or positive"):
        curves.moving_average(np.ones(5), -1)


def test_short_runs_get_a_shorter_window():
    assert curves.effective_window(30, 1000) == 30
    assert curves.effective_window(30, 12) == 4
    assert curves.effective_window(30, 2) == 0
    assert curves.default_smooth(90) == 30
    assert curves.default_smooth(89) == 0


# ---- the band over seeds ----

def test_minmax_band_covers_every_seed():
    values = np.array([[1.0, 2.0, 6.0], [4.0, 6.0, 8.0], [3.0, np.nan, 5.0]])
    mean, low, high = curves.aggregate(values, "minmax")
    np.testing.assert_allclose(mean, [3.0, 6.0, 4.0])
    np.testing.assert_allclose(low, [1.0, 4.0, 3.0])
    np.testing.assert_allclose(high, [6.0, 8.0, 5.0])
    finite = np.where(np.isnan(values), mean[:, None], values)
    assert np.all(low[:, None] <= finite) and np.all(finite <= high[:, None])


def test_std_band_is_mean_plus_minus_std_and_all_nan_epochs_stay_quiet():
    values = np.array([[1.0, 3.0], [np.nan, np.nan]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an all-NaN epoch must not spam RuntimeWarnings
        mean, low, high = curves.aggregate(values, "std")
    np.testing.assert_allclose([mean[0], low[0], high[0]], [2.0, 1.0, 3.0])
    assert np.isnan(mean[1]) and np.isnan(low[1]) and np.isnan(high[1])
    with pytest.raises(InputError, match="minmax"):
        curves.aggregate(values, "iqr")


# ---- loading and labelling runs ----

def test_load_run_pivots_rows_by_epoch_and_seed(tmp_path):
    run = write_run(tmp_path / "run", epochs=2, seeds=(43, 42))
    rows = (run / "metrics.csv").read_text().splitlines()
    (run / "metrics.csv").write_text("\n".join([rows[0]] + rows[:0:-1][:-1]) + "\n")  # reversed, epoch 1 seed 43 dropped
    loaded = curves.load_run(run)
    assert loaded.epochs.tolist() == [1, 2] and loaded.seeds.tolist() == [42, 43]
    assert np.isnan(loaded.metrics["test_loss"][0, 1])
    assert loaded.metrics["test_loss"][1, 1] == pytest.approx(5.0 * np.exp(-0.2) * 1.0 + 0.1)  # seed 43 was k=0
    assert (loaded.mode, loaded.clip) == ("C", "value")


def test_labels_name_mode_clip_and_only_the_settings_that_differ(tmp_path):
    runs = [curves.load_run(write_run(tmp_path / name, mode=mode, clip=clip, rc=rc))
            for name, mode, clip, rc in [("a", "R", "value", 0.1), ("b", "C", "none", 0.1), ("c", "C", "none", 0.01)]]
    assert plots.run_labels(runs) == ["R, clip value, rc=0.1", "C, no clip, rc=0.1", "C, no clip, rc=0.01"]
    assert plots.run_labels(runs[:2]) == ["R, clip value", "C, no clip"]
    twin = curves.load_run(write_run(tmp_path / "twin", mode="R"))
    assert plots.run_labels([runs[0], twin]) == ["R, clip value (a)", "R, clip value (twin)"]
    # Across tasks: the task names the run; one task's options are not compared with another's.
    poles = [curves.load_run(write_run(tmp_path / f"cartpole{n}", mode="C", task="cartpole",
                                      task_config={"poles": n, "integrator": ""})) for n in (1, 2)]
    assert plots.run_labels([runs[1]] + poles) == ["C, no clip, repulsion", "C, clip value, cartpole, poles=1",
                                                    "C, clip value, cartpole, poles=2"]
    assert plots.draw(poles).get_suptitle().startswith("cartpole\n")  # no shared option to show: "" means unset


def test_labels_read_an_option_a_record_predates_as_the_run_trained_and_leave_its_budget_out(tmp_path):
    from stablebptt.engine.config import TrainConfig
    runs = [curves.load_run(write_run(tmp_path / name)) for name in ("old", "new", "critic")]
    for run, extra in zip(runs[1:], ({"normalize_critic_observations": False, "budget": 340.0},
                                     {"normalize_critic_observations": True, "budget": 380.0})):
        run.config["train"].update(extra)
    assert not TrainConfig().normalize_critic_observations and "normalize_critic_observations" not in runs[0].config["train"]
    assert plots.run_labels(runs) == ["C, clip value, normalize_critic_observations=False (old)",
                                      "C, clip value, normalize_critic_observations=False (new)",
                                      "C, clip value, normalize_critic_observations=True"]
    assert plots.run_labels(runs[:2]) == ["C, clip value (old)", "C, clip value (new)"]


# ---- the figure ----

def test_an_environment_run_is_drawn_as_its_return_against_env_steps_and_titled_in_the_commands_words(tmp_path):
    path = write_run(tmp_path / "env", task="env", epochs=4, seeds=(42,),
                     task_config={"env": "CartpoleSwingup", "steps": 128, "discount": 1.0, "episode_length": 0,
                                  "reward_check": False})
    record = storage.read_json(path / "config.json")
    storage.write_json(path / "config.json", {**record, "resolved_task": {"name": "CartpoleSwingup"},
                                              "steps_per_epoch": 8192})
    run = curves.load_run(path)
    figure = plots.draw([run], x_axis="env-steps")
    returns = figure.axes[0]
    assert returns.get_title() == "Episode return" and returns.get_yscale() == "linear"
    x, y = returns.get_lines()[0].get_data()
    np.testing.assert_array_equal(x, [1000, 2000, 3000, 4000])  # the rows' own count (a last epoch may be cut short)
    without_counts = run._replace(metrics={**run.metrics, "env_steps": np.full_like(run.metrics["env_steps"], np.nan)})
    np.testing.assert_array_equal(curves.x_values(without_counts, "env-steps")[0], [8192, 16384, 24576, 32768])
    np.testing.assert_allclose(y, -run.metrics["test_loss"][:, 0])  # the test loss is the negative return
    assert returns.get_xlabel() == "env steps per seed"
    # The name the run has, and what was set, as the flags that set it; 0 and True are the usual values.
    assert figure.get_suptitle().startswith("CartpoleSwingup: --discount 1 --no-reward-check --steps 128\n")
    seconds = plots.draw([run], x_axis="seconds").axes[0].get_lines()[0].get_data()[0]
    np.testing.assert_allclose(seconds, [0.1, 0.2, 0.3, 0.4])  # summed epoch times
    # A run resumed after its second epoch: each start's set-up counts from the epoch it trained first.
    storage.write_json(path / "startup.json", [{"seconds_to_training": 50.0, "ended": {"epoch": 2, "status": "budget"}},
                                               {"seconds_to_training": 10.0}])
    clock = plots.draw([run], x_axis="wall-clock").axes[0].get_lines()[0].get_data()[0]
    np.testing.assert_allclose(clock, [50.1, 50.2, 60.3, 60.4])
    # A start that ended without a record of it (killed): the next one's own first epoch places it.
    storage.write_json(path / "startup.json", [{"seconds_to_training": 50.0, "first_epoch": 1},
                                               {"seconds_to_training": 10.0, "first_epoch": 3}])
    np.testing.assert_allclose(curves.wall_clock(run), [50.1, 50.2, 60.3, 60.4])
    storage.write_json(path / "startup.json", [{"seconds_to_training": 50.0}, {"seconds_to_training": 10.0}])
    with pytest.raises(InputError, match="does not say where its start 2 began"):
        curves.wall_clock(run)
    storage.write_json(path / "startup.json", [{"seconds_to_training": 50.0, "first_epoch": 1},
                                               {"seconds_to_training": 10.0, "first_epoch": 3}])
    # An epoch without an evaluation is left out of the return's curve, not drawn as a gap in it.
    unevaluated = run._replace(metrics={**run.metrics, "test_loss": run.metrics["test_loss"] * np.array([[1.0], [np.nan], [1.0], [1.0]])})
    x, y = plots.draw([unevaluated], x_axis="wall-clock").axes[0].get_lines()[0].get_data()
    np.testing.assert_allclose(x, [50.1, 60.3, 60.4])
    assert np.all(np.isfinite(y))
    # A zero update (S at a zero gradient) stays a gap on the log axis: it is no epoch without an evaluation.
    stalled = run._replace(metrics={**run.metrics, "update_norm": run.metrics["update_norm"] * np.array([[1.0], [0.0], [1.0], [1.0]])})
    x, y = plots.draw([stalled], x_axis="wall-clock").axes[1].get_lines()[0].get_data()
    np.testing.assert_allclose(x, [50.1, 50.2, 60.3, 60.4])
    assert np.isnan(y[1]) and np.isfinite(y[[0, 2, 3]]).all()
    # Smoothed over 30 epochs, a run evaluated every fifth epoch averages 6 evaluations at a time.
    long = curves.load_run(write_run(tmp_path / "long", task="env", epochs=300, seeds=(42, 43),
                                     task_config={"env": "CartpoleSwingup", "steps": 128}))
    every_fifth = np.where((long.epochs % 5 == 0)[:, None], long.metrics["test_loss"], np.nan)
    long = long._replace(metrics={**long.metrics, "test_loss": every_fifth})
    drawn = plots.draw([long], smooth=30).axes[0].get_lines()[0].get_data()[1]
    np.testing.assert_allclose(drawn, -curves.moving_average(every_fifth[4::5], 6).mean(axis=1), rtol=1e-6)
    older = curves.load_run(write_run(tmp_path / "older"))
    with pytest.raises(InputError, match="does not record its env steps per epoch"):
        plots.draw([older], x_axis="env-steps")
    with pytest.raises(InputError, match="has no record of its starts"):
        plots.draw([older], x_axis="wall-clock")



def test_a_title_names_the_options_a_run_set_as_its_record_says_whatever_their_values(tmp_path):
    """A record made from the task's config says which options differ from their defaults: a flag set to
    True is named, one left at False is not, where a record without it is read by the values alone."""
    import dataclasses

    @dataclasses.dataclass
    class Options:
        env: str = ""
        steps: int = 0
        dense_reward: bool = False
        normalize_observations: bool = False
        reward_check: bool = True

    path = write_run(tmp_path / "env", task="env", epochs=4, seeds=(42,), task_config={})
    record = run_folder.run_record("env", Options(env="CheetahRun", steps=32, normalize_observations=True),
                                   {"mode": "C", "clip": "value", "epochs": 4, "seeds": 1})
    assert record["task_options_set"] == ["env", "normalize_observations", "steps"]
    storage.write_json(path / "config.json", record)
    assert plots.draw([curves.load_run(path)]).get_suptitle().startswith("env: --normalize-observations --steps 32\n")
    newer = curves.load_run(path)
    del record["task_options_set"]  # a record from before: True is taken for the usual value, False for one set
    storage.write_json(path / "config.json", record)
    assert plots.draw([curves.load_run(path)]).get_suptitle().startswith("env: --no-dense-reward --steps 32\n")
    # Beside a record that says, the older one's shared values are read as it says them.
    assert plots.draw([curves.load_run(path), newer]).get_suptitle().startswith("env: --normalize-observations --steps 32\n")


def test_figure_orders_flows_as_the_paper_and_styles_by_flow_and_clip(tmp_path):
    runs = [curves.load_run(write_run(tmp_path / mode, mode=mode, clip=clip))
            for mode, clip in [("S", "value"), ("C", "norm"), ("R", "value"), ("M", "value")]]
    figure = plots.draw(runs)
    loss_axis = figure.axes[0]
    lines = loss_axis.get_lines()
    assert [line.get_label().split(",")[0] for line in lines] == ["R", "M", "C", "S"]
    for line in lines:
        mode = line.get_label()[0]
        assert to_rgb(line.get_color()) == pytest.approx(to_rgb(plots.MODE_COLORS[mode]))
        assert line.get_linestyle() == ("--" if mode == "C" else "-")
    assert loss_axis.get_yscale() == "log" and figure.axes[1].get_yscale() == "log"
    assert "min to max" in figure.get_suptitle()


def test_learning_curves_writes_a_png_atomically(tmp_path):
    runs = [write_run(tmp_path / mode, mode=mode, epochs=100) for mode in ("R", "M", "C")]
    runs.append(write_run(tmp_path / "S", mode="S", epochs=100, update_norm=0.0))  # zero: not drawable on a log axis
    runs.append(write_run(tmp_path / "Cn", mode="C", clip="norm", epochs=100))
    out = plots.learning_curves(runs + [runs[0]], tmp_path / "curves.png", smooth=30)
    data = out.read_bytes()
    assert out == tmp_path / "curves.png" and data.startswith(PNG_SIGNATURE) and len(data) > 20_000
    from matplotlib.image import imread
    height, width = imread(out).shape[:2]
    assert width > 1500 and height > 500
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temporary file left


def test_nan_cosine_runs_are_skipped_in_the_cosine_panel(tmp_path):
    with_cosine = curves.load_run(write_run(tmp_path / "c", mode="C"))
    without = curves.load_run(write_run(tmp_path / "r", mode="R", cosine=False))
    figure = plots.draw([with_cosine, without])
    cosine_axis = figure.axes[2]
    assert [line.get_label() for line in cosine_axis.get_lines() if not line.get_label().startswith("_")] == ["C, clip value"]
    assert len([line for line in figure.axes[0].get_lines()]) == 2
    out = plots.learning_curves([tmp_path / "r"], tmp_path / "r" / "only.png")  # every cosine NaN
    assert out.read_bytes().startswith(PNG_SIGNATURE)


def test_plot_run_writes_into_the_run_directory_and_handles_a_single_epoch(tmp_path):
    run = write_run(tmp_path / "run", epochs=1, seeds=(42,))
    path = plots.plot_run(run)
    assert path == run / plots.FIGURE_FILE
    assert path.read_bytes().startswith(PNG_SIGNATURE)


@pytest.mark.parametrize("content, message", [
    ("", "empty .* not finished an epoch"),
    (",".join(COLUMNS) + "\n", "empty .* not finished an epoch"),
    (",".join(COLUMNS) + "\n1,42,0.", "cut in its first row"),
    (",".join(COLUMNS) + "\n1,42,x\n", "non-numeric"),
    ("epoch,seed,batch_loss\n1,42,0.5\n", "lacks the column 'test_loss'"),
])
def test_unusable_metrics_are_input_errors(tmp_path, content, message):
    run = write_run(tmp_path / "run")
    (run / "metrics.csv").write_text(content)
    with pytest.raises(InputError, match=message):
        curves.load_run(run)


def test_a_metrics_file_cut_mid_line_loses_only_its_cut_row(tmp_path):
    run = write_run(tmp_path / "run", epochs=5, seeds=(42,))
    whole = curves.load_run(run)
    text = (run / "metrics.csv").read_text()
    (run / "metrics.csv").write_text(text[:-4])  # the last value cut short still parses as a number
    cut = curves.load_run(run)
    assert "cut mid-line" in cut.note and list(cut.epochs) == [1, 2, 3, 4]
    np.testing.assert_array_equal(cut.metrics["test_loss"], whole.metrics["test_loss"][:4])


def test_run_paths_and_models_in_any_script_draw_without_a_warning(tmp_path):
    runs = [write_run(tmp_path / "运行 глиф" / f"𝔘☃-{mode}", mode=mode, task="mjcf",
                      task_config={"model": f"/模型/机器人-{mode}.xml"}) for mode in ("R", "C")]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for suffix in (".png", ".pdf"):  # raster and embedded fonts
            out = plots.learning_curves(runs, tmp_path / f"labels{suffix}")
            assert out.stat().st_size > 0
    legend = plots.run_labels([curves.load_run(run) for run in runs])
    assert all("机器人" in label for label in legend)  # the names are drawn, not dropped


def test_a_file_or_a_directory_without_config_is_not_a_run(tmp_path):
    (tmp_path / "file").write_text("")
    with pytest.raises(InputError, match="not a directory"):
        curves.load_run(tmp_path / "file")
    run = write_run(tmp_path / "run")
    (run / "config.json").unlink()
    with pytest.raises(InputError, match="config.json does not exist"):
        curves.load_run(run)


@pytest.mark.parametrize("field, value", [("task", 3), ("train.mode", 5), ("train.clip", ["norm"]),
                                          ("train.lr", "fast"), ("train.epochs", True)])
def test_a_config_whose_drawn_fields_have_the_wrong_types_is_not_a_run(tmp_path, field, value):
    run = write_run(tmp_path / "run")
    record = storage.read_json(run / "config.json")
    owner, _, key = field.rpartition(".")
    (record[owner] if owner else record)[key] = value
    storage.write_json(run / "config.json", record)
    with pytest.raises(InputError, match=f"config.json is not a run configuration: '{field}' is"):
        curves.load_run(run)


def test_out_of_range_arguments_are_input_errors(tmp_path):
    run = write_run(tmp_path / "run")
    for smooth in (-1, 2.5, "30", True):  # named as the function's parameter, not the command's option
        with pytest.raises(InputError, match=f"^smooth must be a whole number of epochs, zero or more, got {smooth!r}$"):
            plots.learning_curves([run], tmp_path / "x.png", smooth=smooth)
    with pytest.raises(InputError, match=r"\.png"):
        plots.learning_curves([run], tmp_path / "x.jpg")
    with pytest.raises(InputError, match="does not exist"):
        plots.learning_curves([run], tmp_path / "missing" / "x.png")
    for dpi in (0, -5, float("nan"), 10**6, "x"):
        with pytest.raises(InputError, match="dpi must be a number from 1 to"):
            plots.learning_curves([run], tmp_path / "x.png", dpi=dpi)
    assert plots.learning_curves(run, tmp_path / "one.png").is_file()  # one run directory, not a list of them


# ---- scripts/plot.py ----

def run_script(*args: str, env: dict | None = None) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, str(SCRIPT), *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env)


def font_cache_without_matplotlibs_fonts(folder: Path) -> Path:
    """A matplotlib configuration folder whose font cache lists no font matplotlib ships (its mathematics' fonts)."""
    from matplotlib import font_manager
    shipped = Path(matplotlib.get_data_path()).resolve()
    cache = copy.copy(font_manager.fontManager)
    cache.ttflist = [font for font in cache.ttflist if shipped not in Path(font.fname).resolve().parents]
    folder.mkdir()
    font_manager.json_dump(cache, folder / f"fontlist-v{font_manager.FontManager.__version__}.json")
    return folder


def test_script_writes_the_figure_names_it_and_says_nothing_else_though_the_font_cache_lacks_fonts(tmp_path):
    run = write_run(tmp_path / "run")
    config = font_cache_without_matplotlibs_fonts(tmp_path / "matplotlib")
    process = run_script(str(run), env={**os.environ, "MPLCONFIGDIR": str(config)})
    stdout, stderr = process.communicate(timeout=60)
    assert process.returncode == 0 and stderr == "", stderr
    assert stdout.strip().splitlines() == [f"wrote {run / plots.FIGURE_FILE}"]
    assert (run / plots.FIGURE_FILE).read_bytes().startswith(PNG_SIGNATURE)


def test_script_bad_input_is_one_line_and_exit_2(tmp_path):
    good = write_run(tmp_path / "good")
    (tmp_path / "bare").mkdir()
    empty = write_run(tmp_path / "empty")
    (empty / "metrics.csv").write_text("")
    cases = {
        "missing directory": [str(tmp_path / "nowhere")],
        "no metrics.csv": [str(tmp_path / "bare")],
        "empty metrics.csv": [str(empty)],
        "negative --smooth": [str(good), "--smooth", "-3"],
        "several runs without --out": [str(good), str(empty)],
    }
    processes = {name: run_script(*args) for name, args in cases.items()}  # concurrently: each pays the imports
    for name, process in processes.items():
        stdout, stderr = process.communicate(timeout=60)
        assert process.returncode == 2, f"{name}: exit {process.returncode}, stderr {stderr!r}"
        lines = stderr.splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: "), f"{name}: {stderr!r}"
        assert stdout == "", name
    assert not (good / plots.FIGURE_FILE).exists()
