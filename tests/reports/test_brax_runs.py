"""The Brax baselines' timed run (benchmarks/envs_vs_apg/brax_runs.py) keeps its record as it scores:
a run that a wall-clock limit stops keeps every point it scored, where it kept none; points scored once
the run has ended are the points scored during it, and their evaluation (evaluation.py) scores several
policies in one program as it scores each alone."""
from __future__ import annotations

import contextlib
import importlib.util
import json
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stablebptt.storage import write_json

from conftest import ROOT

_spec = importlib.util.spec_from_file_location("brax_runs", ROOT / "benchmarks" / "envs_vs_apg" / "brax_runs.py")
brax_runs = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(brax_runs)
_spec = importlib.util.spec_from_file_location("evaluation", ROOT / "benchmarks" / "envs_vs_apg" / "evaluation.py")
evaluation = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(evaluation)

RETURNS = [3.0, 5.0, 4.0, 9.0]  # the return scored at each of Brax's evaluator calls


def timed(tmp_path, stop_at: int | None, budget: float = 1e9, evaluate_after: bool = False, now=None,
          scoring_fails: bool = False):
    """A timed run whose trainer calls Brax's evaluator once per epoch (each a point: eval_every 0) with a
    policy that scores RETURNS[call], raising KeyboardInterrupt (a limit's SIGINT) after call ``stop_at``;
    its kept records, in turn, and the lists of policies each evaluator call was given. ``now``: a clock
    (a one-element list) its epochs advance by 10 s each; ``scoring_fails``: the points scored together fail."""
    from brax.training import acting
    path, kept, scored = tmp_path / "CheetahRun_ppo_s0.json", [], []

    def train():
        evaluator = acting.Evaluator.__new__(acting.Evaluator)  # the run's timed evaluator, in place
        for call in range(len(RETURNS)):
            if now is not None:
                now[0] += 10.0
            evaluator.run_evaluation({"w": np.full(2, RETURNS[call])}, {"training/sps": 1.0})
            if call == stop_at:
                raise KeyboardInterrupt

    def keep(rec):  # as the baselines keep theirs
        write_json(path, rec)
        kept.append(json.loads(path.read_text()))

    def evaluate(params):
        return {"mean_return": float(params["w"][0]), "std_return": 0.0, "num_done_early": 0}

    def many(policies):
        scored.append(policies)
        if scoring_fails:
            raise RuntimeError("out of memory")
        return [evaluate(params) for params in policies]
    evaluate.many = many

    rec = {"env": "CheetahRun", "algo": "brax_ppo", "seed": 0}
    run = lambda: brax_runs.timed_run(  # noqa: E731
        train, rec, evaluate=evaluate, evaluate_variant=None, budget=budget, eval_every=0.0, updates_per_epoch=2,
        env_steps_per_update=10, brax_eval="none", log=lambda message: None, keep=keep, evaluate_after=evaluate_after)
    return run, kept, path, scored


def test_a_run_stopped_by_a_limits_sigint_keeps_the_points_it_scored_and_stops(tmp_path):
    run, kept, path, _ = timed(tmp_path, stop_at=2)
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
    run, kept, path, _ = timed(tmp_path, stop_at=None, budget=0.0)
    rec = run()  # the first point is past a budget of 0 s: the run ends there
    assert rec["status"] == "budget" and json.loads(path.read_text()) == json.loads(json.dumps(rec))
    assert [each["status"] for each in kept] == ["running", "budget"]


@pytest.mark.parametrize("stop_at", [None, 2])
def test_points_scored_after_the_run_are_the_points_scored_during_it_in_one_call(tmp_path, monkeypatch, stop_at):
    now = [0.0]  # a clock only the epochs move: each point falls due at the same seconds in both runs
    monkeypatch.setattr(brax_runs.time, "perf_counter", lambda: now[0])
    records = []
    for later in (False, True):
        (tmp_path / str(later)).mkdir()
        now[0] = 0.0
        run, kept, path, scored = timed(tmp_path / str(later), stop_at, evaluate_after=later, now=now)
        with pytest.raises(KeyboardInterrupt) if stop_at is not None else contextlib.nullcontext():
            run()  # a limit's SIGINT is raised again once the points kept so far are scored
        records.append(json.loads(path.read_text()))
    inline, later = records
    assert len(inline["points"]) == (3 if stop_at is not None else len(RETURNS))
    assert [point["train_wall_s"] for point in inline["points"]][1:] == [20.0, 30.0, 40.0][:len(inline["points"]) - 1]
    assert [{k: v for k, v in point.items() if k != "eval_s"} for point in later["points"]] == \
        [{k: v for k, v in point.items() if k != "eval_s"} for point in inline["points"]]
    assert later["status"] == inline["status"] and later["final_return"] == inline["final_return"]
    assert len(scored) == 1 and len(scored[0]) == len(inline["points"])  # all in one call, once the run has ended
    assert all(not each["points"] for each in kept[:-1]) and kept[-1] == later and later["evaluate_after"]
    assert "compile_s" in kept[-2]  # a record kept while running still holds its epochs' times


def test_points_whose_scoring_fails_after_the_run_leave_its_epochs_an_error_and_a_sigint_raised_again(tmp_path):
    run, kept, path, _ = timed(tmp_path, stop_at=2, evaluate_after=True, scoring_fails=True)
    with pytest.raises(KeyboardInterrupt):
        run()
    record = json.loads(path.read_text())
    assert record["status"] == "error" and record["error"] == "scoring the points after the run: out of memory"
    assert not record["points"] and len(record["epochs"]) == 2 and "compile_s" in record


class Drifting(NamedTuple):
    obs: jax.Array
    reward: jax.Array
    done: jax.Array


class DriftingEnv:
    """A point pushed by its actions, paid minus its squared distance from the origin, done past 1.5."""

    def reset(self, key):
        return Drifting(jax.random.normal(key, (2,)), jnp.zeros(()), jnp.zeros(()))

    def step(self, state, action):
        obs = state.obs + 0.5 * action
        return Drifting(obs, -(obs ** 2).sum(), (jnp.abs(obs).max() > 1.5).astype(jnp.float32))


def test_several_policies_scored_in_one_program_score_as_each_alone():
    evaluate = evaluation.make_evaluator(DriftingEnv(), lambda params, obs: params["gain"] * obs + params["push"],
                                         num_envs=8, episode_length=12)
    policies = [{"gain": np.float32(gain), "push": np.full(2, push, np.float32)}
                for gain, push in ((-0.5, 0.0), (0.0, 0.0), (0.3, 0.4))]
    together, alone = evaluate.many(policies), [evaluate(params) for params in policies]
    for each, single in zip(together, alone):
        assert each["mean_return"] == pytest.approx(single["mean_return"], rel=1e-5)
        assert each["std_return"] == pytest.approx(single["std_return"], rel=1e-4, abs=1e-6)
        assert each["num_done_early"] == single["num_done_early"]
    assert len({round(single["mean_return"], 3) for single in alone}) == 3  # three policies, three scores
    assert alone[0]["num_done_early"] < alone[2]["num_done_early"]  # the push drives episodes past the bound
