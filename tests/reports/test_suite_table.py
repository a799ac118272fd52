"""The suite table's records (benchmarks/envs_vs_apg/suite_table.py): returns read at the marks of the
wall clock a run was budgeted to reach, and a command run again kept beside its earlier run."""
from __future__ import annotations

import csv
import importlib.util
import json
from pathlib import Path

from stablebptt.engine.metrics import COLUMNS

from conftest import ROOT

_spec = importlib.util.spec_from_file_location("suite_table", ROOT / "benchmarks" / "envs_vs_apg" / "suite_table.py")
suite_table = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(suite_table)

START_S, EPOCH_S = 50.0, 25.0  # each start's seconds to training, each epoch's


def env_run(path: Path, budgets: tuple[float, ...], started: str, epochs_per_start: int = 10) -> Path:
    """A run folder as `stablebptt train --env CheetahRun` writes it, one start per budget, each
    training ``epochs_per_start`` epochs; seed k's return at epoch e is 10 e + k."""
    path.mkdir(parents=True)
    config = {"task": "env", "task_config": {"env": "CheetahRun", "steps": 16},
              "train": {"batch": 4, "seeds": 2, "budget": budgets[-1], "epochs": 1_000_000},
              "steps_per_epoch": 64, "resolved_task": {"horizon_steps": 16}}
    (path / "config.json").write_text(json.dumps(config))
    epochs = epochs_per_start * len(budgets)
    with open(path / "metrics.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, COLUMNS)
        writer.writeheader()
        for epoch in range(1, epochs + 1):
            for k, seed in enumerate((42, 43)):
                writer.writerow({name: 0.0 for name in COLUMNS} | {
                    "epoch": epoch, "seed": seed, "test_loss": -(10.0 * epoch + k), "seconds": EPOCH_S,
                    "eval_seconds": 0.0, "env_steps": 64.0 * epoch})
    starts = [{"budget": budget, "device": "cpu", "seconds_to_training": START_S, "phases": {"compile": 30.0},
               "first_epoch": 1 + number * epochs_per_start,
               "ended": {"epoch": (number + 1) * epochs_per_start, "status": "budget"},
               "started": f"{started}:{number:02d}", "compile_seconds_from_cache": 25.0 * number}
              for number, budget in enumerate(budgets)]
    (path / "startup.json").write_text(json.dumps(starts))
    return path


def test_returns_stand_at_the_marks_a_run_was_budgeted_to_reach_and_no_further(tmp_path):
    # One start of 300 s: 50 s of set-up and 10 epochs of 25 s end at 300 s.
    once = suite_table.read_run(env_run(tmp_path / "once", (300.0,), "2026-01-01T10:00"))
    assert once["returns_by_wall_clock"] == {"300": [100.0, 101.0]} and once["wall_s"] == 300.0
    # Resumed for 300 s more: its second start's set-up counted, 20 epochs end at 600 s.
    resumed = suite_table.read_run(env_run(tmp_path / "resumed", (300.0, 300.0), "2026-01-01T11:00"))
    assert resumed["returns_by_wall_clock"] == {"300": [100.0, 101.0], "600": [200.0, 201.0]}
    assert resumed["command"].endswith("--budget 300, then --resume RUN --budget 300") and resumed["starts"] == 2
    # Each start's compile loaded from the cache: none at the first, 25 s at the resume.
    assert resumed["compile_seconds_from_cache"] == 0.0 and resumed["resumes"][0]["compile_seconds_from_cache"] == 25.0


def test_a_seed_stopped_apart_is_scored_by_its_last_evaluation_not_left_out(tmp_path):
    folder = env_run(tmp_path / "stopped", (300.0,), "2026-01-01T10:00")
    with open(folder / "metrics.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    for row in rows:  # seed 43 stops apart at epoch 6: from then on every number of its rows is NaN
        if row["seed"] == "43" and int(row["epoch"]) >= 6:
            row.update({name: "nan" for name in COLUMNS if name not in ("epoch", "seed", "seconds", "eval_seconds")})
    with open(folder / "metrics.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    record = suite_table.read_run(str(folder))
    # Seed 43's last evaluation was epoch 5's (10 * 5 + 1); left out, the run would score seed 42 alone.
    assert record["returns_by_wall_clock"] == {"300": [100.0, 51.0]} and record["final_return"] == [100.0, 51.0]
    assert "1 of 2 seeds stopped apart" in record["ended"]


def test_updates_are_counted_from_the_env_steps_each_epoch_trained_a_cut_last_epoch_its_own(tmp_path):
    """Epochs of 4 updates of 64 env steps, the last cut to 2 of them (it trained 128 steps, its rows count
    2432): 38 updates, also where the first seed's row holds NaN there (stopped apart); rows from before the
    count (NaN) are whole epochs."""
    folder = env_run(tmp_path / "cut", (300.0,), "2026-01-01T10:00")
    config = json.loads((folder / "config.json").read_text())
    (folder / "config.json").write_text(json.dumps({**config, "steps_per_epoch": 256}))
    with open(folder / "metrics.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))

    def rewrite(steps_of):
        for row in rows:
            row["env_steps"] = steps_of(int(row["epoch"]), row["seed"])
        with open(folder / "metrics.csv", "w", newline="") as handle:
            writer = csv.DictWriter(handle, COLUMNS)
            writer.writeheader()
            writer.writerows(rows)
        return suite_table.read_run(str(folder))["updates"]
    assert rewrite(lambda epoch, seed: 256.0 * epoch if epoch < 10 else 256.0 * 9 + 128) == 38
    assert rewrite(lambda epoch, seed: "nan" if epoch == 10 and seed == "42" else
                   256.0 * epoch if epoch < 10 else 256.0 * 9 + 128) == 38
    assert rewrite(lambda epoch, seed: "nan") == 40


def test_a_command_run_again_adds_a_row_and_a_folder_read_again_replaces_its_own(tmp_path):
    first = env_run(tmp_path / "first", (300.0,), "2026-01-01T10:00")
    again = env_run(tmp_path / "again", (300.0,), "2026-01-02T10:00")
    out = tmp_path / "table"
    suite_table.main(["--runs", str(first), "--out", str(out)])
    suite_table.main(["--runs", str(again), str(first), "--out", str(out)])
    records = json.loads((out / "records.json").read_text())
    assert [record["started"] for record in records] == ["2026-01-01T10:00:00", "2026-01-02T10:00:00"]
    assert len({record["command"] for record in records}) == 1
    table = (out / "suite.md").read_text()
    for started in ("2026-01-01T10:00:00", "2026-01-02T10:00:00"):
        assert f"(started {started}) | cpu |" in table


def test_an_env_counts_against_ppos_reference_by_its_best_command_at_300_s_on_the_reported_seeds_runs_pooled():
    def record(env, command, returns, budget, along=None, seeds=5, started="2026-01-01T10:00:00"):
        return {"env": env, "command": command, "started": started, "budget": budget, "starts": 1,
                "seeds": list(range(42, 42 + seeds)), "final_return": returns, "returns_by_wall_clock": along or {},
                "seconds_to_training": 60.0 + int(started[8:10]), "first_return": [0.0] * seeds}  # its own first start
    records = [
        record("CheetahRun", "cheetah", [430.0] * 5, 300.0),  # 51% of 850
        record("CheetahRun", "cheetah alone", [800.0], 300.0, seeds=1),  # one seed: not counted
        record("WalkerWalk", "walker", [400.0] * 5, 550.0, along={"300": [100.0] * 5}),  # read at 300 s
        record("PointMass", "point mass", [890.0] * 5, 900.0),  # never read at 300 s: no return by then
        record("HopperStand", "hopper", [900.0] * 5, 300.0),  # no reference
        # Budgeted 300 s, but its start took 315 s and its one epoch, which a budget always trains, ended
        # at 354 s: it has no return by 300 s.
        record("FingerTurnEasy", "finger", [500.0] * 5, 300.0) | {"wall_s": 354.0},
        # Its programs loaded from the cache, compiled by a run before on the machine: not a fresh start.
        record("WalkerWalk", "walker warm", [600.0] * 5, 300.0) | {"compile_seconds_from_cache": 60.0},
        # A screen of fixed epochs, given no budget (its GPU perhaps shared): its wall clock is not counted.
        record("WalkerWalk", "walker screen", [700.0] * 5, 0.0, along={"300": [700.0] * 5}),
        # One command run three times: a lucky run (560, 56% of 1000) does not count alone; the three pool
        # to 440 (44%), below the other command's 450, which then stands for the env.
        record("WalkerStand", "stand", [360.0] * 5, 300.0),
        record("WalkerStand", "stand", [400.0] * 5, 300.0, started="2026-01-02T10:00:00"),
        record("WalkerStand", "stand", [560.0] * 5, 300.0, started="2026-01-03T10:00:00"),
        record("WalkerStand", "stand wider", [450.0] * 5, 300.0),
        # The tuning seeds' run (--seed 100) chose an option: it is not reported against PPO's.
        record("WalkerStand", "stand tuned", [900.0] * 5, 300.0) | {"seeds": list(range(100, 105))},
    ]
    lines = suite_table.against_reference(records)
    assert f"1 of the {len(suite_table.PPO_REFERENCE)} envs" in lines[0] and "(CheetahRun)" in lines[0]
    rows = {line.split(" | ")[0].strip("| "): line for line in lines[4:]}
    assert set(rows) == {"CheetahRun", "WalkerWalk", "WalkerStand"}
    assert "| 430.0 [430.0, 430.0] | 51% | 1: 430.0 | `cheetah` |" in rows["CheetahRun"]
    assert "| 100.0 [100.0, 100.0] | 10% | 1: 100.0 | `walker` |" in rows["WalkerWalk"]
    assert "| 450.0 [450.0, 450.0] | 45% | 1: 450.0 | `stand wider` |" in rows["WalkerStand"]
    # Without the other command, the pooled runs stand for the env: each run's mean named, their seeds' interval.
    pooled = {line.split(" | ")[0].strip("| "): line for line in
              suite_table.against_reference([r for r in records if r["command"] != "stand wider"])[4:]}
    assert "| 440.0 [" in pooled["WalkerStand"] and "| 44% | 3: 360.0 / 400.0 / 560.0 | `stand` |" in pooled["WalkerStand"]


def test_a_commands_pooled_runs_give_one_interval_whatever_order_the_records_come_in():
    # The table written as a run is added and the table written again from records.json alone (sorted) read
    # the same records in two orders.
    def record(returns, started, budget=300):
        return {"env": "FishSwim", "command": f"fish --budget {budget}", "started": started, "budget": 300.0,
                "starts": 1, "seeds": list(range(42, 47)), "final_return": returns, "returns_by_wall_clock": {},
                "seconds_to_training": 60.0, "first_return": [float(started[-1])] * 5}
    records = [record([50.0, 60.0, 210.0, 90.0, 120.0], "2026-01-01T10:00:01", budget=560),  # pooled: the budget aside
               record([100.0, 300.0, 40.0, 80.0, 150.0], "2026-01-01T10:00:02"),
               record([200.0, 20.0, 130.0, 70.0, 110.0], "2026-01-01T10:00:03")]
    rows = {tuple(suite_table.against_reference(order)) for order in (records, records[::-1], records[1:] + records[:1])}
    assert len(rows) == 1
    assert "3: 106.0 / 134.0 / 106.0 | `fish` |" in "\n".join(rows.pop())  # in the order they started
    # The second run recorded again after two more starts: one run, its record of the most starts kept, in
    # either order (its returns by 300 s differ here only to tell the two records apart).
    again = record([0.0] * 5, "2026-01-01T10:00:02") | {
        "starts": 3, "returns_by_wall_clock": {"300": [0.0] * 5},
        "command": "fish --budget 300, then --resume RUN --budget 200, then --resume RUN --budget 200"}
    earlier = records[1] | {"starts": 2, "returns_by_wall_clock": {"300": records[1]["final_return"]},
                            "command": "fish --budget 300, then --resume RUN --budget 300"}
    for order in ([records[0], earlier, again, records[2]], [records[0], again, earlier, records[2]]):
        pooled = "\n".join(suite_table.against_reference(order))
        assert "3: 106.0 / 0.0 / 106.0 | `fish` |" in pooled


def test_runs_of_one_command_given_other_budgets_or_resumed_past_the_mark_pool_as_reruns():
    assert suite_table.what_trains("stablebptt train --env W --steps 2 --budget 545, then --resume RUN --budget 365") \
        == suite_table.what_trains("stablebptt train --env W --steps 2 --budget 300") == "stablebptt train --env W --steps 2"
    assert suite_table.what_trains("stablebptt train --env W --critic (resumed: 2 starts)") == "stablebptt train --env W --critic"
    records = [{"env": "WalkerWalk", "command": command, "started": started, "budget": budget, "starts": starts,
                "seeds": list(range(42, 47)), "final_return": final, "returns_by_wall_clock": along,
                "seconds_to_training": 60.0 + len(along), "first_return": [100.0 + len(along)] * 5}
               for command, started, budget, starts, final, along in (
                   ("walk --budget 300", "2026-01-01T10:00:00", 300.0, 1, [500.0] * 5, {}),
                   # the better run by 300 s, of a longer budget: a rerun of the same command, not a command of its own
                   ("walk --budget 545, then --resume RUN --budget 365", "2026-01-02T10:00:00", 365.0, 2, [900.0] * 5,
                    {"300": [700.0] * 5, "600": [880.0] * 5}))]
    (row,) = suite_table.against_reference(records)[4:]
    assert "| 600.0 [" in row and "| 62% | 2: 500.0 / 700.0 | `walk` |" in row
    # The second run's folder recorded again after a third start: the same run, counted once.
    again = dict(records[1], command=records[1]["command"] + ", then --resume RUN --budget 300", starts=3)
    assert suite_table.against_reference(records + [again])[4:] == [row]
    for record in records + [again]:  # records from before runs recorded their start time
        record.pop("started")
    assert suite_table.against_reference(records + [again])[4:] == [row]


def test_brax_ppos_runs_are_read_campaign_by_campaign_each_at_the_budget_it_was_started_with(monkeypatch):
    def run(seed, budget, returns, status="budget"):  # an evaluation every 100 s from 100 s, one return each
        points = [{"train_wall_s": 100.0 * (i + 1), "env_steps": i, "return": value} for i, value in enumerate(returns)]
        return {"env": "CheetahRun", "seed": seed, "budget_s": budget, "status": status,
                "final_return": returns[-1], "points": points}
    short = [run(seed, 300.0, [10.0, 20.0, 30.0 + seed]) for seed in range(2)]
    long = [run(0, 900.0, [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0]),
            run(1, 900.0, [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0], status="stopped")]  # stopped at 700 s
    monkeypatch.setattr(suite_table, "_ppo_runs", lambda: tuple(long + short))
    # At 300 s the shorter campaign's seeds, never the two campaigns' seeds mixed.
    assert suite_table.ppo_near("CheetahRun", 300.0) == [30.0, 31.0]
    # At 600 s the long campaign, where every seed evaluated near it; at 900 s one of its seeds had stopped.
    assert suite_table.ppo_near("CheetahRun", 600.0) == [6.0, 6.0] and suite_table.ppo_near("CheetahRun", 900.0) == []
    # At its budget a campaign with a seed stopped before it has no final return.
    assert suite_table.ppo_at_budget("CheetahRun") == "30.5 [30.0, 31.0] at 300 s"
    assert suite_table.ppo_at_budget("WalkerWalk") == "-"


def test_of_one_budget_the_campaign_on_the_runs_gpu_model_is_read_first_and_each_cell_names_its_model(monkeypatch):
    def run(seed, machine, final):
        return {"env": "HopperStand", "seed": seed, "budget_s": 300.0, "status": "budget", "machine": machine,
                "final_return": final, "points": [{"train_wall_s": 295.0, "env_steps": 1, "return": final}]}
    h200 = [run(seed, "one H200 of a host of two", 10.0 + seed) for seed in range(2)]
    h100 = [run(seed, "one H100 of a host of one", 20.0 + seed) for seed in range(2)]
    monkeypatch.setattr(suite_table, "_ppo_runs", lambda: tuple(h200 + h100))
    assert suite_table.card_of("gpu (NVIDIA H100 80GB HBM3)") == "H100" and suite_table.card_of("cpu") == ""
    assert suite_table.card_of("gpu (NVIDIA GH200 480GB)") == "GH200"  # not its H200, a card of another memory
    # Never the two cards' seeds mixed; the run's own card first, the other where it names none of them.
    assert suite_table.ppo_near("HopperStand", 300.0, card="H100") == [20.0, 21.0]
    assert suite_table.ppo_near("HopperStand", 300.0, card="H200") == [10.0, 11.0]
    assert suite_table.ppo_near("HopperStand", 300.0) == [20.0, 21.0]  # no card asked: by the models' names
    assert suite_table.ppo_at_budget("HopperStand", "H200") == ("10.5 [10.0, 11.0] at 300 s on an H200; "
                                                                "20.5 [20.0, 21.0] at 300 s on an H100")
    monkeypatch.setattr(suite_table, "_ppo_runs", lambda: tuple(h200))  # one model: the cell names none
    assert suite_table.ppo_at_budget("HopperStand", "H100") == "10.5 [10.0, 11.0] at 300 s"
