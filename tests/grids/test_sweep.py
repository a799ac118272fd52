"""The sweep machinery on a tiny grid: the grid optimizer, outputs, a vmapped cell against the cell alone, resume."""
import ctypes
import json
import os
import platform
import signal
import subprocess
import sys
from collections import namedtuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stablebptt import storage
from stablebptt.engine.config import CLIP_MODES, TrainConfig
from stablebptt.engine.optimizer import make_grid_optimizer, make_optimizer
from stablebptt.flows.modes import MODES
from stablebptt.grids.grid import place
from stablebptt.runs import run_folder

from conftest import ROOT

TINY = ["--preset", "tiny", "--modes", "C,R", "--clips", "value", "--seeds", "2", "--train-size", "16",
        "--test-size", "16", "--task-steps", "20", "--checkpoint-every", "1"]


def sweep(*args):
    return subprocess.run([sys.executable, str(ROOT / "scripts" / "sweep.py"), *args], capture_output=True, text=True, cwd=ROOT)


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("clip", CLIP_MODES)
def test_the_grid_optimizer_selects_exactly_what_the_single_run_chain_computes(mode, clip):
    """Traced mode and clip indices give the same updates as the static chain of a single run."""
    stacked = {"w": 3.0 * jax.random.normal(jax.random.PRNGKey(0), (3, 4, 5))}  # flows R, M, S
    params = {"w": jnp.zeros((4, 5))}
    config = TrainConfig(mode=mode, clip=clip, clip_threshold=0.5)
    grid, single = make_grid_optimizer(config), make_optimizer(config, ("R", "M", "S"))
    grid_state, single_state = grid.init(params), single.init(params)
    for _ in range(3):
        grid_update, grid_state = grid.update(stacked, grid_state, params)
        single_update, single_state = single.update(stacked, single_state, params)
        np.testing.assert_array_equal(grid_update["w"], single_update["w"])


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    out = tmp_path_factory.mktemp("sweeps")
    result = sweep(*TINY, "--epochs", "2", "--out", str(out))
    assert result.returncode == 0, result.stderr
    return out / "tiny"


CELLS = ["repulsion-rc0.1-C-value", "repulsion-rc0.1-R-value", "repulsion-rc1.0-C-value", "repulsion-rc1.0-R-value"]


def test_a_tiny_grid_writes_tidy_results(tiny):
    cells = sorted(p.name for p in tiny.iterdir() if p.is_dir() and p.name.startswith("repulsion-"))
    assert cells == CELLS
    for cell in cells:
        rows = run_folder.read_metrics(tiny / cell / run_folder.METRICS_FILE)
        assert sorted({(r["epoch"], r["seed"]) for r in rows}) == [(1, 42), (1, 43), (2, 42), (2, 43)]
        assert all(np.isfinite(r["test_loss"]) for r in rows)
    summary = (tiny / "summary.csv").read_text().splitlines()
    assert len(summary) == 5 and summary[0].startswith("cell,")
    tidy = (tiny / "test_loss.csv").read_text().splitlines()
    assert tidy[0] == "rc,mode,clip,seed,epoch,test_loss" and len(tidy) == 1 + 4 * 2  # the last epoch of 4 cells x 2 seeds
    records = list((tiny / "sweeps").glob("*.json"))
    assert len(records) == 1
    report = json.loads(records[0].read_text())
    # rc enters only the loss: both values share ONE program with 2 rc x 2 modes x 2 seeds.
    assert report["finished"] and len(report["programs"]) == 1 and report["programs"][0]["cells"] == 8
    assert (tiny / "repulsion-rc0.1.png").stat().st_size > 10_000


def test_a_vmapped_cell_equals_the_same_cell_run_alone(tiny, tmp_path):
    """Equal to float32 rounding: XLA fuses batched cells differently, which moves the last bits
    (a single run with --seed-batching map is bit-exact against itself; see README). The cell's rc
    came in as a per-cell value next to a cell with rc 1.0, which must differ from it."""
    alone = tmp_path / "alone"
    result = subprocess.run([sys.executable, str(ROOT / "scripts" / "train.py"), "--task", "repulsion", "--rc", "0.1",
                             "--steps", "20", "--mode", "C", "--clip", "value", "--epochs", "2", "--train-size", "16",
                             "--test-size", "16", "--seed", "43", "--out", str(alone), "--no-progress"],
                            capture_output=True, text=True, cwd=ROOT)
    assert result.returncode == 0, result.stderr
    single = run_folder.read_metrics(alone / run_folder.METRICS_FILE)
    cell = [r for r in run_folder.read_metrics(tiny / "repulsion-rc0.1-C-value" / run_folder.METRICS_FILE) if r["seed"] == 43]
    other_rc = [r for r in run_folder.read_metrics(tiny / "repulsion-rc1.0-C-value" / run_folder.METRICS_FILE) if r["seed"] == 43]
    assert len(single) == len(cell) == 2
    for a, b in zip(single, cell):
        for name in ("batch_loss", "train_loss", "test_loss", "update_norm", "cosine"):
            assert np.isclose(a[name], b[name], rtol=1e-5, atol=0), name
    assert not np.isclose(single[-1]["train_loss"], other_rc[-1]["train_loss"], rtol=1e-5, atol=0)


def test_a_sweep_resumes_from_its_checkpoints(tiny, tmp_path):
    assert sweep(*TINY, "--epochs", "1", "--out", str(tmp_path)).returncode == 0
    assert sweep(*TINY, "--epochs", "2", "--out", str(tmp_path)).returncode == 0
    for cell in CELLS:
        resumed = run_folder.read_metrics(tmp_path / "tiny" / cell / run_folder.METRICS_FILE)
        whole = run_folder.read_metrics(tiny / cell / run_folder.METRICS_FILE)
        strip = lambda rows: [{k: v for k, v in r.items() if k != "seconds"} for r in rows]
        assert strip(resumed) == strip(whole)


def test_bad_sweep_input_gets_one_line_and_exit_code_2():
    """In this process: every refusal comes before anything compiles."""
    for arguments in (["--preset", "pendulum"], ["--modes", "X"], ["--seeds", "0"], ["--complexity", "7"],
                      ["--preset", "tiny", "--rc", "0.5"], ["--lrs", "0.01"], ["--task", "repulsion", "--complexity", "1"],
                      ["--task", "repulsion", "--lrs", "-1"], ["--seed-range", "3:2"], ["--seed-range", "0:1", "--merge"],
                      ["--task", "repulsion", "--steps", "5", "--task-steps", "5"], ["--preset", "repulsion", "--poles", "2"],
                      ["--modes", "R,R"], ["--clips", "value,norm,value"], ["--task", "repulsion", "--lrs", ","],
                      ["--task", "repulsion", "--lrs", "0.01,1e-2"]):  # a value twice: each is a cell of the grid
        code, stderr = sweep_in_process(*arguments)
        lines = [line for line in stderr.splitlines() if line.strip()]
        assert code == 2 and len(lines) == 1 and lines[0].startswith("error:"), (arguments, stderr)


@pytest.mark.parametrize("arguments, line", [
    (["--process-id", "3", "--num-processes", "2"], "error: --coordinator, --num-processes and --process-id go together"),
    (["--merge", "--report"], "error: --merge reports too, from the pieces it merges: give --merge, or --report alone")])
def test_options_that_cannot_go_together_are_refused_before_the_grid_is_planned(monkeypatch, tmp_path, arguments, line):
    from stablebptt.commands import sweep as sweep_command
    monkeypatch.setattr(sweep_command, "plan_grid", lambda *args, **kwargs: pytest.fail("the grid planned first"))
    code, stderr = sweep_in_process("--task", "repulsion", "--out", str(tmp_path), *arguments)
    assert code == 2 and stderr.splitlines() == [line]


def test_running_out_of_device_memory_ends_a_sweep_in_one_line(tmp_path, capsys, monkeypatch):
    from stablebptt.commands import sweep as sweep_command
    from stablebptt.grids import grid

    def allocation_fails(*args, **kwargs):
        raise jax.errors.JaxRuntimeError("RESOURCE_EXHAUSTED: Out of memory while trying to allocate 1073741824 bytes.")

    monkeypatch.setattr(grid, "run_grid", allocation_fails)
    with pytest.raises(SystemExit) as exit_:
        sweep_command.main([*TINY, "--epochs", "1", "--out", str(tmp_path)])
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert exit_.value.code == 1 and len(lines) == 1 and "out of memory on cpu" in lines[0] and "resume" in lines[0], lines


@pytest.mark.parametrize("devices_per_host, hosts, programs", [(1, 1, 3), (4, 1, 4), (4, 1, 3), (4, 1, 1), (2, 1, 4), (2, 2, 3), (4, 2, 1)])
def test_placement_runs_every_program_once_on_devices_of_one_host(devices_per_host, hosts, programs):
    """Every program lands on exactly one group; groups are disjoint, never span hosts, and use
    as many devices as the programs can: no device idles while programs queue on another."""
    Device = namedtuple("Device", "id process_index")
    devices = [Device(h * devices_per_host + i, h) for h in range(hosts) for i in range(devices_per_host)]
    placed = [place(list(range(programs)), devices, host) for host in range(hosts)]
    queues = [queue for per_host in placed for _, queue in per_host]
    assert sorted(p for queue in queues for p in queue) == list(range(programs))
    groups = [group for per_host in placed for group, _ in per_host]
    used = [d.id for group in groups for d in group]
    assert len(used) == len(set(used))
    for host, per_host in enumerate(placed):
        assert all(d.process_index == host for group, _ in per_host for d in group)
    if programs >= hosts * devices_per_host:  # every device its own group, the queues as even as can be
        assert len(groups) == hosts * devices_per_host
        assert max(map(len, queues)) - min(map(len, queues)) <= 1
    else:  # every program alone on its group, each group as large as the host allows
        assert all(len(queue) == 1 for queue in queues)
        assert all(len(group) >= devices_per_host // -(-programs // hosts) for group in groups)


def interrupt_another_thread(pid: int) -> None:
    """SIGINT delivered to a thread other than the main one, as the OS may do with Ctrl-C."""
    others = sorted(int(tid) for tid in os.listdir(f"/proc/{pid}/task") if int(tid) != pid)
    if not others:  # a single-threaded process: the main thread is the only one to get it
        os.kill(pid, signal.SIGINT)
        return
    tgkill = {"x86_64": 234, "aarch64": 131}[platform.machine()]  # Linux syscall numbers
    assert ctypes.CDLL(None, use_errno=True).syscall(tgkill, pid, others[-1], signal.SIGINT) == 0


def test_ctrl_c_checkpoints_and_the_same_command_resumes(tmp_path):
    """SIGINT after the first logged epoch: exit 130, a checkpoint at the epoch reached, and a rerun finishes.

    The hard way round, as it hung two CI runs: the sweep starts with SIGINT ignored (what a
    shell gives a background job), and where it can, the test sends the signal to a thread other
    than the main one, which a main thread blocked in a plain wait would never see.
    """
    arguments = [sys.executable, str(ROOT / "scripts" / "sweep.py"), *TINY, "--epochs", "100000", "--out", str(tmp_path)]
    # The shell ignores SIGINT and execs the sweep in its place (same pid), which inherits that.
    process = subprocess.Popen(["sh", "-c", 'trap "" INT; exec "$0" "$@"', *arguments], stderr=subprocess.PIPE,
                               stdout=subprocess.DEVNULL, text=True, cwd=ROOT)
    for line in process.stderr:
        if "epoch " in line:
            break
    if sys.platform == "linux" and platform.machine() in ("x86_64", "aarch64"):
        interrupt_another_thread(process.pid)
    else:
        process.send_signal(signal.SIGINT)
    try:
        _, rest = process.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        process.kill()
        pytest.fail(f"still running 120 s after SIGINT; its stderr ends: {process.communicate()[1][-2000:]}")
    assert process.returncode == 130, rest
    with np.load(tmp_path / "tiny" / "_programs" / "rc1.0_0.1" / run_folder.CHECKPOINT_FILE) as saved:
        reached = int(saved["epoch"])
    assert 1 <= reached < 100000
    finish = sweep(*TINY, "--epochs", str(reached + 1), "--out", str(tmp_path))
    assert finish.returncode == 0, finish.stderr
    rows = run_folder.read_metrics(tmp_path / "tiny" / CELLS[0] / run_folder.METRICS_FILE)
    assert sorted({r["epoch"] for r in rows}) == list(range(1, reached + 2))


def free_port() -> int:
    import socket
    with socket.socket() as probe:
        probe.bind(("localhost", 0))
        return probe.getsockname()[1]


def test_two_processes_under_jax_distributed_give_the_results_of_one(tiny, tmp_path):
    """Two local CPU processes (one device each) share the tiny grid, one program each, and
    write the cells one process writes alone (there, as one program of both rc values: equal to
    float32 rounding); process 0 reports once both are done."""
    grid = [*TINY, "--no-group-values", "--epochs", "2"]
    port = free_port()
    processes = [subprocess.Popen([sys.executable, str(ROOT / "scripts" / "sweep.py"), *grid, "--out", str(tmp_path / "two"),
                                   "--coordinator", f"localhost:{port}", "--num-processes", "2", "--process-id", str(i)],
                                  cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                 for i in range(2)]
    outputs = [process.communicate(timeout=600) for process in processes]
    assert [process.returncode for process in processes] == [0, 0], [err[-2000:] for _, err in outputs]
    # Named <time>-host<i>-...: the two processes may finish in either order.
    records = sorted((tmp_path / "two" / "tiny" / "sweeps").glob("*.json"), key=lambda r: r.name.split("-")[1])
    assert [r.name.split("-")[1] for r in records] == ["host0", "host1"]
    ran = [[program["complexity"] for program in storage.read_json(r)["programs"]] for r in records]
    assert sorted(ran) == [[[0.1]], [[1.0]]]  # one program on each host
    assert_same_cells(tiny, tmp_path / "two" / "tiny", CELLS)
    summary = (tmp_path / "two" / "tiny" / "summary.csv").read_text().splitlines()
    assert [line.split(",")[:2] for line in summary] == [line.split(",")[:2] for line in (tiny / "summary.csv").read_text().splitlines()]


def test_distributed_options_go_together():
    for arguments in (["--coordinator", "localhost:1"], ["--num-processes", "2", "--process-id", "2", "--coordinator", "h:1"]):
        code, stderr = sweep_in_process(*TINY, *arguments)
        assert code == 2 and len(stderr.strip().splitlines()) == 1, stderr


def test_a_cell_is_a_run_folder_that_renders(tiny, tmp_path):
    """A cell's config.json has the single-run schema and its params.npz the cell's seeds."""
    cell = tiny / "repulsion-rc0.1-C-value"
    record = run_folder.open_run(cell)
    assert record["train"]["mode"] == "C" and record["train"]["seeds"] == 2 and record["train"]["seed"] == 42
    assert record["task_config"]["rc"] == 0.1 and record["task_config"]["steps"] == 20
    rendered = subprocess.run([sys.executable, str(ROOT / "scripts" / "render.py"), str(cell), "--rollouts", "1",
                               "--seed-index", "1", "--no-video"], capture_output=True, text=True, cwd=tmp_path)
    assert rendered.returncode == 0, rendered.stderr
    assert list(cell.glob("*.png"))


def test_paired_bootstrap_intervals_decide_only_what_the_seeds_support(tmp_path):
    from stablebptt.grids.report import claim_intervals, paired_bootstrap, verdicts
    mean, low, high = paired_bootstrap(np.array([-0.3, -0.2, -0.25, -0.35, -0.28]))
    assert low <= mean <= high < 0
    mean, low, high = paired_bootstrap(np.array([-1.0, 1.0, -0.5, 0.5, 0.1]))
    assert low < 0 < high and paired_bootstrap(np.array([-1.0, 1.0, -0.5, 0.5, 0.1])) == (mean, low, high)
    # C beats R on every seed; C and M differ by noise: "C better" and "not resolved".
    lines = ["rc,mode,clip,seed,epoch,test_loss"]
    for seed, noise in enumerate([0.02, -0.01, 0.03, -0.02, 0.0]):
        lines += [f"0.1,R,none,{seed},100,{1.0 + noise}", f"0.1,C,none,{seed},100,{0.5 + noise}",
                  f"0.1,M,none,{seed},100,{0.5 - noise}", f"0.1,C,none,{seed},50,9"]
    (tmp_path / "test_loss.csv").write_text("\n".join(lines) + "\n")
    row = claim_intervals(tmp_path / "test_loss.csv", "rc")[2]
    assert row.startswith("| 0.1 | none | 5 | -0.5 [-0.5, -0.5] | C better |") and row.endswith("| not resolved |"), row
    # M's mean loss (0.496) is the lowest; read as a score (minus the loss) it is the highest.
    said = verdicts(tmp_path / "test_loss.csv", "rc")[1]
    assert said == "rc=0.1, clip none: best M (test loss 0.496); C - R: C better; C - M: not resolved", said
    said = verdicts(tmp_path / "test_loss.csv", "rc", ("return", -1.0))[1]
    assert said.startswith("rc=0.1, clip none: best M (return -0.496);"), said


def test_a_sweep_never_writes_over_cells_another_grid_filled(tiny, tmp_path):
    """Rerunning part of a grid (other values, so other programs) with other --epochs is refused, cells untouched."""
    import shutil
    shutil.copytree(tiny, tmp_path / "tiny", ignore=shutil.ignore_patterns("_programs"))
    before = {cell: (tmp_path / "tiny" / cell / run_folder.METRICS_FILE).read_bytes() for cell in CELLS}
    refused = sweep(*TINY, "--epochs", "1", "--out", str(tmp_path))
    lines = [line for line in refused.stderr.splitlines() if line.strip()]
    assert refused.returncode == 2 and len(lines) == 1 and "another grid filled" in lines[0], refused.stderr
    assert "(epochs)" in lines[0]
    assert before == {cell: (tmp_path / "tiny" / cell / run_folder.METRICS_FILE).read_bytes() for cell in CELLS}


def read_rows(cell):
    return [{k: v for k, v in row.items() if k != "seconds"} for row in run_folder.read_metrics(cell / run_folder.METRICS_FILE)]


def assert_same_cells(a, b, cells):
    """Equal to float32 rounding: cells vmapped in batches of other sizes may fuse differently."""
    for cell in cells:
        rows_a, rows_b = read_rows(a / cell), read_rows(b / cell)
        assert [(r["epoch"], r["seed"]) for r in rows_a] == [(r["epoch"], r["seed"]) for r in rows_b], cell
        for x, y in zip(rows_a, rows_b):
            for name in ("batch_loss", "train_loss", "test_loss", "update_norm", "cosine"):
                assert np.isclose(x[name], y[name], rtol=1e-5, atol=1e-7), (cell, name, x, y)
        with np.load(a / cell / run_folder.PARAMS_FILE) as pa, np.load(b / cell / run_folder.PARAMS_FILE) as pb:
            assert pa.files == pb.files
            for leaf in pa.files:
                np.testing.assert_allclose(pa[leaf], pb[leaf], rtol=1e-4, atol=1e-6)


def sweep_in_process(*args) -> tuple[int, str]:
    """The sweep command in this process (sharing its compiled programs): (exit code, stderr)."""
    import contextlib
    import io

    from stablebptt.commands import sweep as sweep_command
    stderr = io.StringIO()
    with contextlib.redirect_stderr(stderr):
        try:
            code = sweep_command.main(list(args))
        except SystemExit as exit_:
            code = exit_.code
    return code, stderr.getvalue()


def refused_in_one_line(outcome, text) -> bool:
    code, stderr = outcome
    lines = [line for line in stderr.splitlines() if line.strip()]
    return code == 2 and len(lines) == 1 and text in lines[0]


def test_a_grid_in_seed_pieces_merges_into_the_grid_run_whole(tiny, tmp_path):
    """Two pieces of one seed each, trained apart, merge into the cells the whole grid wrote; no pieces,
    a missing piece, a piece of another grid and a piece that has not finished are refused in one line."""
    piece = lambda *more: sweep_in_process(*TINY, "--epochs", "2", "--out", str(tmp_path), *more)
    assert refused_in_one_line(piece("--merge"), "no pieces")
    assert piece("--seed-range", "0:1")[0] == 0
    assert refused_in_one_line(piece("--merge"), "seeds without a piece yet: run --seed-range 1:2")
    assert refused_in_one_line(piece("--seed-range", "0:1", "--clips", "none"), "holds a piece of another grid")
    assert piece("--seed-range", "1:2")[0] == 0
    pieces = tmp_path / "tiny" / "pieces"
    manifest = pieces / "seeds1-1" / "piece.json"
    original = manifest.read_text()
    changed = json.loads(original)
    changed["grid"]["epochs"] = 3
    manifest.write_text(json.dumps(changed))
    assert refused_in_one_line(piece("--merge"), "is a piece of another grid (--epochs: 3 there, 2 here)")
    manifest.write_text(original)
    metrics = pieces / "seeds1-1" / CELLS[0] / run_folder.METRICS_FILE
    whole = metrics.read_text()
    metrics.write_text("\n".join(whole.splitlines()[:2]) + "\n")  # the header and epoch 1 only
    assert refused_in_one_line(piece("--merge"), "has trained 1 of 2 epochs")
    metrics.write_text(whole)
    assert piece("--merge")[0] == 0
    assert_same_cells(tiny, tmp_path / "tiny", CELLS)
    for cell in CELLS:
        record = run_folder.open_run(tmp_path / "tiny" / cell)
        assert (record["train"]["seed"], record["train"]["seeds"]) == (42, 2)
    assert "C - R" in (tmp_path / "tiny" / "intervals.md").read_text()


def test_a_grid_over_any_task_varies_the_learning_rate_per_cell(tiny, tmp_path):
    """--task with its options and --lrs: the cell at the default learning rate is the preset's cell of the
    same task options; the cell at ten times that rate trained differently."""
    code, stderr = sweep_in_process("--task", "repulsion", "--rc", "0.1", "--steps", "20", "--lrs", "0.001,0.01",
                                    "--modes", "C,R", "--clips", "value", "--seeds", "2", "--train-size", "16",
                                    "--test-size", "16", "--epochs", "2", "--out", str(tmp_path))
    assert code == 0, stderr
    root = tmp_path / "repulsion"
    for mode in ("C", "R"):
        (root / f"repulsion-rc0.1-{mode}-value").symlink_to(root / f"repulsion-lr0.001-{mode}-value")
    assert_same_cells(tiny, root, [f"repulsion-rc0.1-{mode}-value" for mode in ("C", "R")])
    slow, fast = (read_rows(root / f"repulsion-lr{lr}-C-value")[-1]["train_loss"] for lr in ("0.001", "0.01"))
    assert not np.isclose(slow, fast, rtol=1e-3)
    assert run_folder.open_run(root / "repulsion-lr0.01-C-value")["train"]["lr"] == 0.01
    assert (root / "repulsion-lr0.01.png").is_file() and "lr=0.01, clip value: best " in (root / "verdicts.txt").read_text()


def test_a_grid_over_an_mjcf_file_and_over_an_environment_reports_intervals(suite, tmp_path, capsys, monkeypatch):
    """The issue's two commands at tiny sizes: dm_control's pendulum from the hanging pose, and an
    environment, whose report speaks of episode returns."""
    from stablebptt.commands import sweep as sweep_command
    from stablebptt.runs import model_store
    compile_model, compiled = model_store.compiled_model, []
    monkeypatch.setattr(model_store, "compiled_model", lambda path: compiled.append(path) or compile_model(path))
    tiny_sizes = ["--modes", "R,M,C", "--clips", "norm", "--seeds", "2", "--epochs", "1", "--train-size", "8",
                  "--test-size", "8", "--out", str(tmp_path)]
    assert sweep_command.main(["--model", str(suite / "pendulum.xml"), "--init-pose", "hinge=3.14159",
                               "--horizon-seconds", "0.2", *tiny_sizes]) == 0
    intervals = (tmp_path / "pendulum" / "intervals.md").read_text().splitlines()
    assert intervals[0].startswith("| lr | clip | seeds | C - R") and intervals[2].startswith("| 0.001 | norm | 2 | ")
    record = run_folder.open_run(tmp_path / "pendulum" / "mjcf-lr0.001-C-norm")
    assert record["task_config"]["init_pose"] == "hinge=3.14159" and record["task_config"]["horizon_seconds"] == 0.2
    # The cells keep one compressed copy of the model between them, which each reopens; it was compiled once.
    assert len(list((tmp_path / "pendulum" / "models").glob("*.mjb.gz"))) == 1 and len(compiled) == 1, compiled
    for cell in (tmp_path / "pendulum").glob("mjcf-lr*-norm"):
        kept = cell / storage.read_json(cell / "model.json")["compiled"]
        assert kept.is_file() and (cell / "model.xml").read_bytes() == (suite / "pendulum.xml").read_bytes()
    assert sweep_command.main(["--env", "envs_for_tests:make_cart", "--steps", "6", "--episode-length", "8", *tiny_sizes]) == 0
    out = capsys.readouterr().out
    assert "best " in out and "(episode return " in out, out
    cells = sorted(p.name for p in (tmp_path / "make_cart").glob("env-lr*") if p.is_dir())
    assert cells == ["env-lr0.001-C-norm", "env-lr0.001-M-norm", "env-lr0.001-R-norm"], cells


def test_a_merge_names_overlapping_pieces_and_the_option_in_which_a_piece_differs(tmp_path):
    """Read from the pieces' manifests alone, before anything is merged."""
    from stablebptt.errors import InputError
    from stablebptt.grids import pieces

    grid = {"task": "mjcf", "name": "m", "option": "lr", "train_option": "lr", "values": [0.001, 0.003],
            "modes": ["R", "C"], "clips": ["value"], "first_seed": 0, "seeds": 4, "epochs": 2,
            "task_configs": [{"dt": 0.01}, {"dt": 0.01}], "code": "abc"}
    for start, stop in ((0, 2), (1, 3)):
        pieces.write_manifest(pieces.piece_root(tmp_path, start, stop), grid, start, stop)
    with pytest.raises(InputError, match=r"the pieces of seeds 0-1 and 1-2 overlap in seeds 1-1: remove one"):
        pieces.check_pieces(tmp_path, grid, [])
    other_lrs = {**grid, "values": [0.01, 0.03]}
    with pytest.raises(InputError, match=r"\(--lrs: 0.001, 0.003 there, 0.01, 0.03 here\)"):
        pieces.check_pieces(tmp_path, other_lrs, [])
    other_dt = {**grid, "task_configs": [{"dt": 0.01}, {"dt": 0.02}]}
    with pytest.raises(InputError, match=r"\(--dt: 0.01 there, 0.02 here\)"):
        pieces.check_pieces(tmp_path, other_dt, [])


SWINGING = """<mujoco><option timestep="0.02"/><worldbody><body><joint name="hinge" type="hinge" axis="0 1 0"/>
<geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.05" mass="{mass}"/></body></worldbody>
<actuator><motor joint="hinge" ctrlrange="-1 1" ctrllimited="true"/></actuator></mujoco>"""


def test_a_grid_its_pieces_and_their_merge_refuse_a_model_file_whose_contents_changed(tmp_path):
    """A mass edited between two pieces, or before a grid resumes: refused in one line, nothing mixed."""
    model = tmp_path / "swinging.xml"
    model.write_text(SWINGING.format(mass=1))
    sizes = ["--model", str(model), "--horizon-seconds", "0.1", "--modes", "C", "--clips", "norm", "--seeds", "2",
             "--epochs", "1", "--train-size", "8", "--test-size", "4", "--out", str(tmp_path / "out")]
    assert sweep_in_process(*sizes, "--seed-range", "0:1")[0] == 0
    model.write_text(SWINGING.format(mass=2))
    assert refused_in_one_line(sweep_in_process(*sizes, "--seed-range", "0:1"),  # the same command again
                               "holds a piece of another grid (the model file's contents")
    assert sweep_in_process(*sizes, "--seed-range", "1:2")[0] == 0
    assert refused_in_one_line(sweep_in_process(*sizes, "--merge"), "is a piece of another grid (the model file's contents")
    whole = [*sizes[:-1], str(tmp_path / "whole")]
    assert sweep_in_process(*whole)[0] == 0
    model.write_text(SWINGING.format(mass=3))
    assert refused_in_one_line(sweep_in_process(*whole), "the model file's contents changed")


def test_a_second_process_on_the_same_piece_or_grid_is_refused_while_the_first_holds_it(tmp_path):
    from stablebptt.grids import pieces
    from stablebptt.runs.run_folder import RunLock
    for folder, more in ((pieces.piece_root(tmp_path / "tiny", 0, 1), ["--seed-range", "0:1"]), (tmp_path / "tiny", [])):
        folder.mkdir(parents=True, exist_ok=True)
        held = RunLock(folder)  # the first process, training
        try:
            assert refused_in_one_line(sweep_in_process(*TINY, "--epochs", "1", "--out", str(tmp_path), *more),
                                       f"{folder} is in use by another run (process {os.getpid()})")
        finally:
            held.release()
