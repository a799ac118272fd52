"""The locomotion recipe beside Brax PPO across envs (benchmarks/envs_vs_apg/aggregate.py): the runs it
takes are the recipe's as it stands and trained until the mark, their returns over the largest return,
and rliable's aggregates agree with their closed forms."""
from __future__ import annotations

import importlib.util
import json

import numpy as np
import pytest
import scipy.stats

from stablebptt.cli import typed_option
from stablebptt.tasks import env as env_tasks

from conftest import ROOT

_spec = importlib.util.spec_from_file_location("aggregate", ROOT / "benchmarks" / "envs_vs_apg" / "aggregate.py")
aggregate = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(aggregate)

RETURNS = {"CheetahRun": [700.0, 650, 720, 690, 710], "WalkerWalk": [200.0, 250, 180, 230, 260]}
PPO_RETURNS = {"CheetahRun": [450.0, 440, 460, 430, 470], "WalkerWalk": [150.0, 100, 210, 120, 160]}


def record(env: str, returns, budget: float = 300.0, started: str = "2026-12-01T00:00:00", extra: str = "",
           seeds: int = 5, warm: float = 0.0, resumed_marks: dict | None = None) -> dict:
    """A record as suite_table.py keeps it, of the recipe's command on ``env`` (with ``extra`` options)."""
    command = aggregate.recipe_command(env) + extra + f" --budget {budget:g}"
    if resumed_marks is not None:
        command += ", then --resume RUN --budget 390"
    return {"env": env, "command": command, "seeds": list(range(42, 42 + seeds)), "budget": budget,
            "started": started, "starts": 1 if resumed_marks is None else 2, "final_return": list(returns),
            "returns_by_wall_clock": resumed_marks or {}, "compile_seconds_from_cache": warm}


def ppo_near(env, mark, card=""):
    return PPO_RETURNS.get(env, []) if mark == 300 else []


def test_the_recipes_command_spells_each_option_the_recipe_sets_on_the_env():
    for env in ("CheetahRun", "WalkerWalk", "HopperStand"):
        command = aggregate.recipe_command(env)
        assert command.startswith(f"stablebptt train --env {env} ") and "--seeds 5" in command
        for name, value in env_tasks.recipe_options("locomotion", env).items():
            assert typed_option(name, value) in command.split(" --budget")[0], (env, name)


def test_only_the_latest_run_of_the_recipe_as_it_stands_that_trained_until_the_mark_is_taken():
    records = [record("CheetahRun", [1.0] * 5, started="2026-11-30T00:00:00"),  # older
               record("CheetahRun", RETURNS["CheetahRun"]),
               record("CheetahRun", [999.0] * 5, started="2026-12-02T00:00:00", extra=" --lr 0.003"),  # other options
               record("CheetahRun", [999.0] * 5, started="2026-12-02T00:00:00", warm=60.0),  # a warm cache
               record("CheetahRun", [999.0] * 5, started="2026-12-02T00:00:00", seeds=3),
               record("WalkerWalk", RETURNS["WalkerWalk"], budget=510, resumed_marks={"300": RETURNS["WalkerWalk"],
                                                                                      "600": [400.0] * 5})]
    chosen = aggregate.recipe_runs(records, 300)
    assert sorted(chosen) == ["CheetahRun", "WalkerWalk"]
    assert chosen["CheetahRun"]["final_return"] == RETURNS["CheetahRun"]
    # A run of 300 s has no return at 900 s; the resumed run none past the marks it reached.
    assert aggregate.recipe_runs(records, 900) == {}
    assert list(aggregate.recipe_runs(records, 600)) == ["WalkerWalk"]

    scored, missing = aggregate.scores(records, 300, ppo_near=ppo_near)
    assert scored["envs"] == ["CheetahRun", "WalkerWalk"]
    np.testing.assert_allclose(scored[aggregate.OURS], np.array([RETURNS["CheetahRun"], RETURNS["WalkerWalk"]]).T / 1000)
    np.testing.assert_array_equal(scored["returns"][aggregate.OURS], np.array([RETURNS["CheetahRun"], RETURNS["WalkerWalk"]]).T)
    np.testing.assert_allclose(scored[aggregate.PPO],
                               np.array([PPO_RETURNS["CheetahRun"], PPO_RETURNS["WalkerWalk"]]).T / 1000)
    assert missing["HopperStand"] == "no run of the recipe as it stands that trained until this mark"
    _, missing_at_600 = aggregate.scores(records, 600, ppo_near=ppo_near)
    assert missing_at_600["WalkerWalk"] == "no Brax PPO campaign whose 5 seeds each evaluated near this mark"


def test_a_run_whose_budget_ended_at_the_mark_comes_before_a_later_one_that_passed_it():
    ended_at_300 = record("WalkerWalk", RETURNS["WalkerWalk"])
    passed_300 = record("WalkerWalk", [344.0] * 5, budget=510, started="2026-12-03T00:00:00",
                        resumed_marks={"300": [344.0] * 5})
    passed_300["starts"] = 1  # one start of 510 s, read at 300 s on its way
    assert aggregate.recipe_runs([ended_at_300, passed_300], 300)["WalkerWalk"] is ended_at_300
    assert aggregate.recipe_runs([passed_300], 300)["WalkerWalk"] is passed_300  # none ended there: the one that passed
    later_at_300 = dict(ended_at_300, started="2026-12-04T00:00:00", final_return=[600.0] * 5)
    assert aggregate.recipe_runs([ended_at_300, passed_300, later_at_300], 300)["WalkerWalk"] is later_at_300


def test_the_aggregates_are_their_closed_forms_with_intervals_about_them():
    scored, _ = aggregate.scores([record(env, returns) for env, returns in RETURNS.items()], 300, ppo_near=ppo_near)
    state = np.random.get_state()
    summary = aggregate.aggregates(scored, draws=500)
    assert summary == aggregate.aggregates(scored, draws=500)  # the same records, the same intervals
    assert np.random.get_state()[1].tolist() == state[1].tolist()  # NumPy's global generator given back
    for name in (aggregate.OURS, aggregate.PPO):
        closed = {"IQM": scipy.stats.trim_mean(scored[name], 0.25, axis=None), "mean": scored[name].mean(),
                  "median": np.median(scored[name].mean(axis=0))}  # rliable's median: of the envs' means
        for metric, (point, low, high) in summary[name].items():
            assert point == pytest.approx(closed[metric]) and low <= point <= high, (name, metric)
    # Every seed of ours above every one of PPO's on the cheetah; on the walker, 23 of the 25 pairs (the
    # Mann-Whitney count): (1 + 23/25) / 2.
    point, low, high = summary["P(ours > PPO)"]
    assert point == pytest.approx((1 + 23 / 25) / 2) and low <= point <= high <= 1.0


def test_the_report_and_its_figure_name_the_envs_left_out_and_an_empty_one_has_no_figure(tmp_path, monkeypatch):
    monkeypatch.setattr(aggregate.suite_table, "ppo_near", ppo_near)
    monkeypatch.setattr(aggregate, "BOOTSTRAP_DRAWS", 200)
    records = tmp_path / "records"
    records.mkdir()
    (records / "records.json").write_text(json.dumps([record(env, returns) for env, returns in RETURNS.items()]))
    for mark in (300, 600):
        assert aggregate.main(["--records", str(records), "--mark", str(mark), "--out", str(tmp_path / f"at{mark}")]) == 0
    text, empty = (tmp_path / "at300.md").read_text(), (tmp_path / "at600.md").read_text()
    assert "Over 2 envs (CheetahRun, WalkerWalk)" in text and "| CheetahRun | 694.0 [" in text
    assert "| HopperStand | - | - |" in text and (tmp_path / "at300.png").stat().st_size > 0
    assert "nothing to aggregate" in empty and not (tmp_path / "at600.png").exists()
    assert all(f"| {env} | - | - |" in empty for env in aggregate.STUDY_ENVS)
