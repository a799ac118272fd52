"""Hard cases stay numerically stable: long horizons, coincident agents, divergence; and scripts/accuracy.py.

The quantum task over 10,000 steps (norm kept, every flow finite) is covered in
test_quantum.py: test_norm_preserved_float32/64, test_long_evolution_gradient_is_finite_and_balanced
and test_all_flows_finite_over_a_long_evolution.
"""
import csv
import functools
import math
import re
import subprocess
import sys
from dataclasses import replace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stablebptt.engine.config import TrainConfig, seed_array
from stablebptt.engine.optimizer import make_optimizer
from stablebptt.engine.training import make_trainer
from stablebptt.flows.gradients import flow_gradients, reference_rollout
from stablebptt.runs import run_folder
from stablebptt.tasks import mjcf, repulsion

from conftest import ROOT

PRECISIONS = (32, 64)
FLOWS = ("R", "M")
LONG = 1000  # steps (10 simulated seconds at the cart-pole's dt 0.01)
SHORT = 100


def finite(tree) -> bool:
    return all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree.leaves(tree))


def norm(tree) -> float:
    return float(np.sqrt(sum(np.sum(np.asarray(leaf, np.float64) ** 2) for leaf in jax.tree.leaves(tree))))


def row(grads, flow):
    return jax.tree.map(lambda a: a[FLOWS.index(flow)], grads)


def in_precision(tree, bits):
    """A pytree as float32 or float64 arrays; call float64 inside ``jax.enable_x64(True)``."""
    return jax.tree.map(lambda a: jnp.asarray(np.asarray(a), jnp.float64 if bits == 64 else jnp.float32), tree)


@functools.partial(jax.jit, static_argnums=0)  # optax's tree arithmetic in one program, not op by op
def updates(mode, grads, params):
    """The optimizer's update for ``mode`` from stacked (R, M) gradients, unclipped: the rawest case."""
    optimizer = make_optimizer(TrainConfig(mode=mode, clip="none"), FLOWS)
    return optimizer.update(grads, optimizer.init(params), params)[0]


# ----------------------------------------------------------------------------- cart-pole, 4 poles, 1000 steps

@pytest.fixture(scope="module")
def four_poles():
    """R and M gradients of the 4-pole cart-pole at 100 and 1000 steps, per precision and start.

    Starts: the paper's (poles hanging at pi +- 30 degrees: a regular swing) and
    upright (0 +- 30 degrees: the poles fall and tumble, a chaotic motion in
    which gradients grow exponentially). One program per precision serves both
    horizons: the loss reads the state after step h of a 1000-step rollout, so
    later steps get a zero cotangent and the gradient is that of an h-step
    rollout, without a second 20-60 s MJX compile. A batch of two copies of one
    start gives that start's own gradient, with the program's one shape.
    """
    results = {}
    task = mjcf.make(mjcf.Config(poles=4))
    params = task.init_params(jax.random.PRNGKey(0), False)  # Glorot output: R differs from M
    start = jax.tree.map(lambda a: a[:1], task.sample_initial_states(jax.random.PRNGKey(3), 1))
    upright = start._replace(qpos=start.qpos.at[:, 1:].add(-jnp.pi))
    for bits in PRECISIONS:
        with jax.enable_x64(bits == 64):
            task = mjcf.make(mjcf.Config(poles=4))  # MJX fixes the model's precision when it is built

            def gradients(params, states, h):
                def loss_at_h(trajectory, controls):
                    final = jax.tree.map(lambda a: jax.lax.dynamic_slice_in_dim(a, h - 1, 1), trajectory)
                    return task.dynamics.loss(final, controls)  # a final-state loss: it reads the last state given
                dynamics = replace(task.dynamics, loss=loss_at_h, horizon=LONG)
                return flow_gradients(dynamics, FLOWS, params, states, task.plan)

            program = jax.jit(gradients)
            # The float32 numbers in both precisions, so that the precisions differ in rounding only.
            params_in = in_precision(params, bits)
            for regime, one in (("hanging", start), ("upright", upright)):
                pair = in_precision(jax.tree.map(lambda a: jnp.concatenate([a, a]), one), bits)
                for h in (SHORT, LONG):
                    loss, grads = program(params_in, pair, h)
                    results[bits, regime, h] = (float(loss), jax.device_get(grads), jax.device_get(params_in))
    return results


@pytest.mark.parametrize("regime", ["hanging", "upright"])
@pytest.mark.parametrize("bits", PRECISIONS)
def test_four_poles_over_1000_steps_give_finite_M_and_C_updates(four_poles, bits, regime):
    loss, grads, params = four_poles[bits, regime, LONG]
    assert math.isfinite(loss) and finite(grads)
    for mode in ("M", "C"):
        update = updates(mode, grads, params)
        assert finite(update) and norm(update) > 0, mode


def test_four_poles_R_gradient_growth_is_as_documented(four_poles):
    # scripts/accuracy.py measures (results/accuracy/gradient_growth.csv, batch 8): ||g_R|| grows
    # like e^(1.1 t) per simulated second while the poles tumble, e^(0.05 t) while they swing.
    def growth(regime):
        short, long = (norm(row(four_poles[64, regime, h][1], "R")) for h in (SHORT, LONG))
        return math.log(long / short) / ((LONG - SHORT) * 0.01)

    # Two horizons of one pair of states here (float64), where the records fit seven horizons of eight: seen 1.43
    # and 0.02 per s, within a factor of 1.5 of the float64 record's 1.125 upright and under 0.1 hanging (0.047).
    rate = {regime: growth(regime) for regime in ("hanging", "upright")}
    assert 1.125 / 1.5 < rate["upright"] < 1.125 * 1.5, rate
    assert rate["hanging"] < 0.1, rate
    for bits in PRECISIONS:  # and it stays a number: no overflow, no NaN
        assert finite(row(four_poles[bits, "upright", LONG][1], "R"))


def test_float32_and_float64_agree_while_the_poles_swing(four_poles):
    # Not after 10 s of tumbling: rounding grows as fast as the gradient, and float32's relative
    # error reaches 1 (results/accuracy/gradients.csv).
    g32, g64 = (row(four_poles[bits, "hanging", SHORT][1], "R") for bits in PRECISIONS)
    difference = jax.tree.map(lambda a, b: np.asarray(a, np.float64) - np.asarray(b, np.float64), g32, g64)
    assert norm(difference) < 1e-3 * norm(g64)


# ----------------------------------------------------------------------------- repulsion, coincident agents

DT_STEPS = 64  # T = 4 in steps of exactly 1/16: positions advance by exact binary fractions


def hard_starts() -> repulsion.State:
    """Two starts: everyone at one point at rest; and driver 0 landing exactly on evader 0 after one step.

    Explicit Euler moves positions with the old velocities, so x_1 = -0.5 + 8/16 = 0
    exactly, whatever the forces and the control at step 0: the driver passes
    through the evader's position inside the rollout, not at its start.
    """
    at_rest = repulsion.State(jnp.zeros((6, 2)), jnp.zeros((6, 2)))
    position = jnp.array([[-0.5, 0.0], [3.0, 0.0], [0.0, 0.0], [1.0, 0.0], [0.5, 0.5], [-0.5, -1.0]])
    through = repulsion.State(position, jnp.zeros((6, 2)).at[0].set(jnp.array([8.0, 0.0])))
    return jax.tree.map(lambda a, b: jnp.stack([a, b]), at_rest, through)


@pytest.fixture(scope="module", params=PRECISIONS, ids=["float32", "float64"])
def repulsion_hard_cases(request):
    """Rollouts and R, M, S gradients from ``hard_starts`` in one precision."""
    with jax.enable_x64(request.param == 64):
        task = repulsion.make(repulsion.Config(rc=0.01, steps=DT_STEPS))
        params = task.init_params(jax.random.PRNGKey(1), False)  # Glorot output: a nonzero control at once
        starts = hard_starts()
        rollout = jax.jit(jax.vmap(lambda x0: reference_rollout(task.dynamics, params, x0)))(starts)
        loss, grads = jax.jit(lambda p, x: flow_gradients(task.dynamics, ("R", "M", "S"), p, x))(params, starts)
        m_and_c = {mode: updates(mode, jax.tree.map(lambda a: a[:2], grads), params) for mode in ("M", "C")}
        return jax.device_get((rollout, loss, grads, m_and_c, params))


def test_the_driver_passes_exactly_through_the_evader(repulsion_hard_cases):
    rollout = repulsion_hard_cases[0]
    after_one_step = rollout.states.position[1, 0]
    np.testing.assert_array_equal(after_one_step[0], after_one_step[2])  # driver 0 on evader 0
    assert not np.array_equal(rollout.states.position[1, 1, 0], after_one_step[0])  # and on through it


def test_coincident_agents_keep_states_gradients_and_updates_finite(repulsion_hard_cases):
    rollout, loss, grads, m_and_c, _ = repulsion_hard_cases
    assert finite(rollout.states) and finite(rollout.controls) and math.isfinite(loss)
    for index, flow in enumerate(("R", "M", "S")):
        grad = jax.tree.map(lambda a: a[index], grads)
        assert finite(grad) and norm(grad) > 0, flow
    for mode, update in m_and_c.items():
        assert finite(update) and norm(update) > 0, mode


# ----------------------------------------------------------------------------- divergence on a real task

def test_a_diverging_learning_rate_stops_with_the_epoch_and_keeps_the_last_good_checkpoint(tmp_path):
    run_dir = tmp_path / "diverged"
    # Adam's first steps move every weight by about lr: controls of order 1e5 overflow the positions.
    result = subprocess.run([sys.executable, str(ROOT / "scripts" / "train.py"), "--task", "repulsion", "--lr", "1e4",
                             "--clip", "none", "--epochs", "5", "--checkpoint-every", "5", "--train-size", "32",
                             "--test-size", "32", "--no-progress", "--out", str(run_dir)],
                            capture_output=True, text=True, cwd=ROOT)
    assert result.returncode == 1, result.stderr
    message = result.stderr.strip().splitlines()[-1]
    match = re.fullmatch(r"error: non-finite .*loss.* at epoch (\d+) \(seed 42\); stopped, "
                         r"the last good checkpoint \(epoch (\d+)\) is kept in (.+)", message)
    assert match and "Traceback" not in result.stderr, result.stderr
    bad_epoch, kept_epoch = int(match[1]), int(match[2])
    assert kept_epoch == bad_epoch - 1 and match[3] == str(run_dir)

    config = TrainConfig(epochs=5, train_size=32, test_size=32, lr=1e4, clip="none")
    initial = make_trainer(repulsion.make(repulsion.Config()), config).init(seed_array(config))
    epoch, saved, rows = run_folder.load_checkpoint(run_dir, initial)
    assert epoch == kept_epoch and finite(saved)
    assert len(rows) == kept_epoch and np.all(np.isfinite(rows))
    params = run_folder.load_params(run_dir / run_folder.PARAMS_FILE, initial.params)
    assert finite(params)
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(saved.params)):
        np.testing.assert_array_equal(a, b)
    if kept_epoch == 0:  # diverged in the first epoch: what is kept is exactly the initial state
        for a, b in zip(jax.tree.leaves(saved), jax.tree.leaves(initial)):
            np.testing.assert_array_equal(a, b)


# ----------------------------------------------------------------------------- scripts/accuracy.py

def read_rows(path):
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def test_accuracy_script_quick_run_writes_tables_and_figures(tmp_path):
    out = tmp_path / "accuracy"
    script = [sys.executable, str(ROOT / "scripts" / "accuracy.py")]
    # The cheapest task and study: the MJX ones would cost minutes of compilation (the full run is made by hand).
    result = subprocess.run(script + ["--quick", "--tasks", "repulsion", "--studies", "trajectory", "--out", str(out)],
                            capture_output=True, text=True, cwd=ROOT)
    assert result.returncode == 0, result.stderr
    for name in ("trajectory.csv", "trajectory.png", "summary.md", "meta.json"):
        assert (out / name).is_file(), name
    assert (out / "trajectory.png").read_bytes().startswith(b"\x89PNG")
    trajectory = read_rows(out / "trajectory.csv")
    error = {(r["integrator"], r["precision"], float(r["dt"])): float(r["error"]) for r in trajectory}
    dts = sorted({dt for _, _, dt in error})
    assert len(dts) >= 3 and all(float(r["ms_per_simulated_second"]) > 0 for r in trajectory)
    for dt in dts:  # invariants, not numbers: RK4 beats Euler at every step size...
        assert error["rk4", "float64", dt] < error["euler", "float64", dt]
    rk4 = [error["rk4", "float64", dt] for dt in dts]  # ...and converges as dt shrinks
    assert rk4 == sorted(rk4)
    # The key table goes to stdout and into summary.md; --replot redraws from the CSVs alone.
    assert "| repulsion | Euler | float32 |" in result.stdout
    (out / "summary.md").unlink()
    replot = subprocess.run(script + ["--replot", "--out", str(out)], capture_output=True, text=True, cwd=ROOT)
    assert replot.returncode == 0 and "| repulsion | RK4 | float64 |" in (out / "summary.md").read_text(), replot.stderr


def refused_in_process(main, argv, capsys):
    """A command's ``main`` (the one its script and the installed command run) in this process, on input
    it refuses while parsing: (exit code, stderr lines). The scripts' own start is tested on their runs."""
    try:
        code = main(argv)
    except SystemExit as exit_:
        code = exit_.code
    return code, capsys.readouterr().err.strip().splitlines()


def test_accuracy_script_rejects_bad_input_in_one_line(tmp_path, capsys):
    from stablebptt.commands.accuracy import main
    for arguments in (["--tasks", "pendulum"], ["--studies", "speed"], ["--replot", "--out", str(tmp_path)]):
        code, lines = refused_in_process(main, arguments, capsys)  # each refused before it computes anything
        assert code == 2 and len(lines) == 1 and lines[0].startswith("error: "), (arguments, lines)
    assert not any(tmp_path.iterdir())


def test_bench_command_writes_the_tables_it_is_asked_for(tmp_path, capsys):
    """`stablebptt bench` (through the installed command's dispatcher): a row per mode for repulsion; for the
    cart-pole with `--tables steps --simulators generated,floor`, only those simulators and the parts."""
    from stablebptt.commands import bench as bench_command
    for arguments, named in ((["--rounds", "1", "--tasks", "cartpole", "--simulators", "generated,warp"],
                              "--simulators"),
                             (["--tasks", "cartpole", "--poles", ","], "--poles"), (["--envs", "CheetahRun"], "--envs"),
                             (["--batch", "0"], "--batch"), (["--startup", "--timeout", "nan"], "--timeout"),
                             # each table's options are refused beside the other
                             (["--timeout", "60"], "--timeout"), (["--train-args", "--epochs 2"], "--train-args"),
                             (["--startup", "--rounds", "1"], "--rounds"), (["--startup", "--poles", "2"], "--poles"),
                             (["--startup", "--rounds", "20"], "--rounds"), (["--timeout", "300"], "--timeout")):  # defaults
        code, lines = refused_in_process(bench_command.main, arguments, capsys)
        assert code == 2 and len(lines) == 1 and named in lines[0], (arguments, lines)
    command = [sys.executable, "-m", "stablebptt.commands.main", "bench", "--rounds", "1"]
    modes, steps = tmp_path / "modes.md", tmp_path / "steps.md"
    # Side by side: the two commands share nothing but the machine.
    processes = [subprocess.Popen(command + arguments, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)
                 for arguments in (["--tasks", "repulsion", "--out", str(modes)],
                                   ["--tasks", "cartpole", "--poles", "1", "--tables", "steps", "--simulators",
                                    "generated,floor", "--out", str(steps)])]
    outputs = [process.communicate() for process in processes]
    for process, (_, stderr) in zip(processes, outputs):
        assert process.returncode == 0, stderr

    table = lambda text: [[cell.strip() for cell in line.split("|")[1:-1]] for line in text.splitlines() if line.startswith("| ")]
    rows = {row[0]: row for row in table(modes.read_text())}
    for variant in ("R plain", "R", "M", "S", "C", "R + cosine"):
        assert float(rows[variant][1]) > 0, variant
    assert "C / R = " in modes.read_text() and modes.read_text() in outputs[0][0] + "\n"

    text = steps.read_text()
    assert "### Cart-pole (MJX)" not in text and "where the time goes" in text and "parts of the default R update" in text
    rows = table(text)
    simulators = [(row[0], row[1]) for row in rows if row[1] in ("R", "C")]
    assert simulators == [("generated step, body by body (the default)", "R"), ("closed-form equations (floor)", "R"),
                          ("generated step, body by body (the default)", "C"), ("closed-form equations (floor)", "C")]
    floor_row = next(row for row in rows if row[:2] == ["closed-form equations (floor)", "R"])
    assert floor_row[3] == "" and floor_row[4] == "1.00"  # no mjx.step row to divide by; the floor over itself


def test_bench_startup_times_a_cold_and_a_warm_fresh_process_per_model(tmp_path, capsys):
    """`bench --startup`: per model, two fresh train.py processes sharing one compile cache that starts empty;
    the table and its record hold each run's parts, the exact commands and the load average."""
    import json

    from stablebptt.commands import bench as bench_command
    out = tmp_path / "startup.md"
    model = ROOT / "stablebptt" / "models" / "cartpole_1.xml"
    with pytest.raises(SystemExit) as refused:
        bench_command.main(["--startup", "--models", f"{model},no_such_model", "--out", str(out)])
    assert refused.value.code == 2 and len(capsys.readouterr().err.strip().splitlines()) == 1 and not out.exists()
    with pytest.raises(SystemExit) as refused:  # checked before any process starts (or the extra is missing)
        bench_command.main(["--startup", "--models", str(model), "--envs", "NoSuchEnv", "--out", str(out)])
    assert refused.value.code == 2 and len(capsys.readouterr().err.strip().splitlines()) == 1 and not out.exists()

    assert bench_command.main(["--startup", "--models", str(model), "--train-args",
                               "--epochs 1 --train-size 8 --test-size 8 --batch 8 --steps 2", "--out", str(out)]) == 0
    record = json.loads(out.with_suffix(".json").read_text())
    (row,) = record["rows"]
    assert row["model"] == "cartpole_1" and record["machine"] and record["command"].startswith("python scripts/bench.py --startup")
    cache = row["cold_command"].split()[0]
    assert cache.startswith("STABLEBPTT_COMPILE_CACHE=") and row["warm_command"].split()[0] == cache  # warm reuses it
    for kind in ("cold", "warm"):
        run = row[kind]
        assert f"python scripts/train.py --model {model} --epochs 1" in row[f"{kind}_command"]
        assert run["status"] == "ok" and all(run[part] >= 0 for part in ("setup_s", "compile_s", "epoch_s"))
        assert run["device"] == jax.devices()[0].device_kind  # the device the training process ran on
        assert math.isclose(run["first_update_s"], run["setup_s"] + run["compile_s"] + run["epoch_s"], rel_tol=1e-9)
        assert run["first_update_s"] <= run["wall_s"]  # the process lives on past its first update
    assert all(len(row["load"][moment]) == 3 for moment in ("start", "end"))

    lines = [line for line in out.read_text().splitlines() if line.startswith("| ")]
    header, cells = [c.strip() for c in lines[0].split("|")[1:-1]], [c.strip() for c in lines[1].split("|")[1:-1]]
    assert len(header) == len(cells) == 11 and header[0] == "model or env" and header[9] == "warm <= cold"
    assert cells[0] == "cartpole_1" and [float(c) for c in cells[1:9]] == [
        round(row[kind][part], 1) for kind in ("cold", "warm") for part in ("setup_s", "compile_s", "epoch_s", "first_update_s")]
    assert cells[9] == ("yes" if row["warm"]["first_update_s"] <= row["cold"]["first_update_s"] else "no")
