"""Which MuJoCo Playground environments' rewards are flat at every sampled state, and which of those
train on a smooth surrogate: `env_task`'s reward check and smoothing alone, no training.

  python benchmarks/smoothing_survey.py PendulumSwingup FingerSpin ...   (default: the 13 the check finds flat)

One line per env: the reward check's verdict, and the comparisons smoothed (or the one-line refusal).
"""
from __future__ import annotations

import sys
import time

from stablebptt.envs import playground
from stablebptt.envs.adapter import env_task
from stablebptt.envs.protocol import EnvError

FLAT = ("AcrobotSwingupSparse", "CartpoleBalanceSparse", "CartpoleSwingupSparse", "BallInCup", "FingerSpin",
        "FingerTurnEasy", "FingerTurnHard", "HopperHop", "HopperStand", "PendulumSwingup", "PointMass", "ReacherEasy",
        "ReacherHard")


def main(names: list[str]) -> None:
    for name in names or FLAT:
        started = time.perf_counter()
        try:
            task = env_task(playground.load(name), horizon=8, name=name)
            verdict = f"{task.resolved['reward_gradient']} | {task.resolved.get('reward_smoothing', 'not smoothed')}"
        except EnvError as error:
            verdict = f"refused | {error}"
        print(f"{name} | {verdict} | {time.perf_counter() - started:.0f} s", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
