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
