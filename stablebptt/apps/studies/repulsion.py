"""The repulsion task in the studies: RK4 references, coefficients held fixed, rc 0.01 for training."""
from __future__ import annotations

from typing import TYPE_CHECKING

from stablebptt.apps.gradient_study import GradientSetup
from stablebptt.apps.measuring import cast, compile_call, flat_states, precision, rollout_program, run_once
from stablebptt.apps.trajectory_study import TrajectorySetup

if TYPE_CHECKING:
    from stablebptt.apps.accuracy import AccuracyConfig

REPULSION_DURATION = 4.0
TRAINING_RC = 0.01  # where the paper's modes differ most


def repulsion_setup(quick: bool) -> TrajectorySetup:
    from stablebptt.tasks import repulsion

    def make_task(integrator, dt):
        return repulsion.make(repulsion.Config(integrator=integrator, steps=round(REPULSION_DURATION / dt)))

    def controls(rng, batch):
        return rng.uniform(-1.0, 1.0, (batch, 4))  # (c0, c1) per driver; c0 < 0 pulls a driver through the evaders

    def reference(initial_states, coefficients):
        finals = []
        with precision(64):
            arguments = (cast(initial_states, 64), cast(coefficients, 64))
        for steps in (7680, 15360):
            step = make_task("rk4", REPULSION_DURATION / steps).dynamics.step
            finals.append(flat_states(run_once(compile_call(rollout_program(step, steps), arguments, 64)[0])[0]))
        agreement = float(abs(finals[0] - finals[1]).max())
        return finals[1], (f"float64 RK4 with 15360 steps (dt {REPULSION_DURATION / 15360:.2g}); "
                           f"half as many steps agree to {agreement:.1e}")

    steps = (30, 60, 120) if quick else (30, 60, 120, 240, 480, 960)
    return TrajectorySetup("repulsion", "Repulsion", REPULSION_DURATION, ("euler", "rk4"),
                           tuple(REPULSION_DURATION / s for s in steps), ("euler", REPULSION_DURATION / 60),
                           make_task, controls, reference)


def trajectory_setup(config: AccuracyConfig) -> TrajectorySetup:
    return repulsion_setup(config.quick)


def gradient_setup(config: AccuracyConfig) -> GradientSetup:
    from stablebptt.tasks import repulsion
    return GradientSetup("repulsion", "repulsion, explicit Euler", lambda: repulsion.make(repulsion.Config()),
                         REPULSION_DURATION / 60, (20, 60) if config.quick else (100, 300, 1000), {"paper": lambda s: s})


def training_config(module):
    return module.Config(rc=TRAINING_RC)
