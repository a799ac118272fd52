"""Returns beside Brax PPO's (benchmarks/envs_vs_apg/against_ppo.py): where either side's mean passes the other's."""
from __future__ import annotations

import importlib.util

import numpy as np

from conftest import ROOT

_spec = importlib.util.spec_from_file_location("against_ppo", ROOT / "benchmarks" / "envs_vs_apg" / "against_ppo.py")
against_ppo = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(against_ppo)


def test_each_side_passes_the_other_where_the_gap_changes_sign_and_nowhere_the_run_is_missing():
    grid = np.arange(8.0) * 100
    # PPO ahead where the run starts (no passing: it was ahead already), the run passes at 300 s, PPO again at
    # 500 s; the run has no evaluation at 0 s or past 600 s.
    gap = np.array([np.nan, 2.0, 1.0, -1.0, -2.0, 3.0, 0.0, np.nan])
    ppo_passes, run_passes = against_ppo.passings(grid, gap)
    assert ppo_passes.tolist() == [500.0] and run_passes.tolist() == [300.0]
    # A tie then a lead counts once, at the lead.
    ppo_passes, run_passes = against_ppo.passings(np.arange(3.0), np.array([-1.0, 0.0, 1.0]))
    assert ppo_passes.tolist() == [2.0] and run_passes.tolist() == []


def test_the_campaign_drawn_beside_a_run_is_the_longest_on_its_gpu_model_else_the_longest_on_any(monkeypatch):
    def campaign(budget, machine):
        return [{"env": "HopperStand", "seed": seed, "budget_s": budget, "machine": machine} for seed in range(2)]
    h100 = campaign(300.0, "one H100 of a host of one")
    h200_short, h200_long = campaign(300.0, "one H200 of a host of two"), campaign(900.0, "one H200 of a host of two")
    monkeypatch.setattr(against_ppo.suite_table, "_ppo_runs", lambda: tuple(h200_long + h100 + h200_short))
    assert against_ppo.campaign("HopperStand", "H100") == h100
    assert against_ppo.campaign("HopperStand", "H200") == h200_long
    assert against_ppo.campaign("HopperStand", "A100") == h200_long  # none on its model: the longest on any
    assert against_ppo.campaign("CheetahRun", "H100") == []


def test_ppo_is_read_by_a_mark_at_each_seeds_last_evaluation_before_it_and_apart_at_its_nearest():
    def run(times, returns):
        return {"budget_s": 600.0, "points": [{"train_wall_s": t, "return": r} for t, r in zip(times, returns)]}
    # Seed 0 evaluates at 150, 295 and 310 s, seed 1 at 100, 200, 300 and 305 s: by 300 s, seed 0's at 295 s
    # and seed 1's at 300 s itself; by 600 s each's last, at 590 and 520 s.
    runs = [run((150.0, 295.0, 310.0, 590.0), (5.0, 10.0, 20.0, 60.0)),
            run((100.0, 200.0, 300.0, 305.0, 520.0, 620.0), (1.0, 2.0, 30.0, 50.0, 80.0, 90.0))]
    lines = [line.removeprefix("  Brax PPO's evaluations ") for line in against_ppo.at_marks(runs)]
    assert lines[0].startswith("nearest 300 s, at 295-300 s: 20.0 [") and lines[0].endswith("10 / 30")
    assert lines[1].startswith("by 300 s, at 295-300 s: 20.0 [") and lines[1].endswith("10 / 30")
    assert lines[2].startswith("nearest 600 s, at 590-620 s: 75.0 [") and lines[2].endswith("60 / 90")
    assert lines[3].startswith("by 600 s, at 520-590 s: 70.0 [") and lines[3].endswith("60 / 80")
    # A seed whose first evaluation lies past the mark has no return by it: the line is left out, not a mean of fewer.
    late = [run((310.0, 590.0), (20.0, 60.0)), run((280.0, 590.0), (30.0, 80.0))]
    assert not any(" by 300 s" in line for line in against_ppo.at_marks(late))
    # A campaign whose seeds stopped 15 s or more short of a mark of their budget is not read at it.
    stopped = [run((295.0, 560.0), (10.0, 60.0)), run((300.0, 590.0), (30.0, 80.0))]
    assert [line.split(",")[0].split("evaluations ")[1] for line in against_ppo.at_marks(stopped)] == [
        "nearest 300 s", "by 300 s"]
