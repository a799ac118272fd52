"""The Brax baselines' timed run (benchmarks/envs_vs_apg/brax_runs.py) keeps its record as it scores:
a run that a wall-clock limit stops keeps every point it scored, where it kept none."""
from __future__ import annotations

import importlib.util
import json

import numpy as np
import pytest

from stablebptt.storage import write_json

from conftest import ROOT

_spec = importlib.util.spec_from_file_location("brax_runs", ROOT / "benchmarks" / "envs_vs_apg" / "brax_runs.py")
brax_runs = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(brax_runs)

RETURNS = [3.0, 5.0, 4.0, 9.0]  # the return scored at each of Brax's evaluator calls


def timed(tmp_path, stop_at: int | None, budget: float = 1e9):
    """A timed run whose trainer calls Brax's evaluator once per epoch (each a point: eval_every 0),
    raising KeyboardInterrupt (a limit's SIGINT) after call ``stop_at``; its kept records, in turn."""
    from brax.training import acting
    path, kept = tmp_path / "CheetahRun_ppo_s0.json", []
    scores = iter(RETURNS)

    def train():
        evaluator = acting.Evaluator.__new__(acting.Evaluator)  # the run's timed evaluator, in place
        for call in range(len(RETURNS)):
            evaluator.run_evaluation({"w": np.zeros(2)}, {"training/sps": 1.0})
            if call == stop_at:
                raise KeyboardInterrupt

    def keep(rec):  # as the baselines keep theirs
        write_json(path, rec)
        kept.append(json.loads(path.read_text()))

    rec = {"env": "CheetahRun", "algo": "brax_ppo", "seed": 0}
    run = lambda: brax_runs.timed_run(  # noqa: E731
        train, rec, evaluate=lambda params: {"mean_return": next(scores), "std_return": 0.0, "num_done_early": 0},
        evaluate_variant=None, budget=budget, eval_every=0.0, updates_per_epoch=2, env_steps_per_update=10,
        brax_eval="none", log=lambda message: None, keep=keep)
    return run, kept, path


def test_a_run_stopped_by_a_limits_sigint_keeps_the_points_it_scored_and_stops(tmp_path):
    run, kept, path = timed(tmp_path, stop_at=2)
    with pytest.raises(KeyboardInterrupt):
        run()
    record = json.loads(path.read_text())
    assert record["status"] == "interrupted"
    assert [point["return"] for point in record["points"]] == RETURNS[:3]
    assert record["final_return"] == RETURNS[2] and record["best_return"] == max(RETURNS[:3])
    assert [len(each["points"]) for each in kept] == [1, 2, 3, 3]  # a record at every point, then the last
    assert [each["status"] for each in kept] == ["running"] * 3 + ["interrupted"]
    # Each record kept while running holds its epochs' times so far: a run killed there keeps its compile.
    running = kept[2]
    steady = float(np.median([epoch["wall_s"] for epoch in running["epochs"][1:]]))
    assert running["steady_epoch_s"] == pytest.approx(steady) and running["update_s"] == pytest.approx(steady / 2)
    assert running["compile_s"] == pytest.approx(running["setup_s"] + running["epochs"][0]["wall_s"] - steady)
    assert "compile_s" not in kept[0]  # no epoch yet
    assert list(tmp_path.iterdir()) == [path]  # no temporary file left beside it


def test_a_run_its_budget_ends_keeps_its_record_with_the_budgets_status(tmp_path):
    run, kept, path = timed(tmp_path, stop_at=None, budget=0.0)
    rec = run()  # the first point is past a budget of 0 s: the run ends there
    assert rec["status"] == "budget" and json.loads(path.read_text()) == json.loads(json.dumps(rec))
    assert [each["status"] for each in kept] == ["running", "budget"]
