#!/usr/bin/env python3
"""The paper's toy problem: rotation stalls Adam, the sign-agreement combination restores convergence.

    python scripts/toy.py                    # -> results/toy.png

Adam minimises L(x, y) = (x^2 + a y^2) / 2 driven by three vector fields with
the same zero at the minimum: the gradient (like R), the gradient rotated by
``--angle`` degrees (like M: balanced but rotational, not a gradient of any
loss), and their element-wise sign-agreement combination (like C, through
stablebptt.flows.gradients.sign_agreement).
"""
from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

from stablebptt.cli import one_line_errors, parse_config
from stablebptt.errors import InputError
from stablebptt.reports.choices import format_problem


@dataclass(frozen=True)
class ToyConfig:
    angle: float = field(default=85.0, metadata={"help": "rotation of the modified field, degrees (|angle| < 90 keeps the minimum attracting on average)"})
    anisotropy: float = field(default=1.0, metadata={"help": "curvature of y relative to x"})
    steps: int = field(default=3000, metadata={"help": "Adam steps"})
    lr: float = field(default=0.002, metadata={"help": "Adam learning rate"})
    out: str = field(default="results/toy.png", metadata={"help": "figure to write"})

    def __post_init__(self):
        if not (0 <= abs(self.angle) < 90):
            raise InputError(f"--angle must be within (-90, 90) degrees, got {self.angle}")
        if not (math.isfinite(self.anisotropy) and self.anisotropy > 0):
            raise InputError(f"--anisotropy must be a positive number, got {self.anisotropy}")
        if self.steps <= 0:
            raise InputError(f"--steps must be positive, got {self.steps}")
        if not (math.isfinite(self.lr) and self.lr > 0):
            raise InputError(f"--lr must be a positive number, got {self.lr}")
        if problem := format_problem(self.out):  # known before Adam runs, not after
            raise InputError(f"--out {self.out}: {problem}")


def main(argv: list[str]) -> int:
    config = parse_config(ToyConfig, argv, __doc__, "toy")
    import jax
    import jax.numpy as jnp
    import numpy as np
    import optax
    from matplotlib.figure import Figure

    from stablebptt.flows.modes import sign_agreement
    from stablebptt.reports.plots import render

    curvature = jnp.array([1.0, config.anisotropy])
    loss = lambda p: 0.5 * jnp.sum(curvature * p**2)
    theta = np.deg2rad(config.angle)
    rotation = jnp.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    fields = {
        "gradient (R)": jax.grad(loss),
        f"rotated by {config.angle:g} deg (M)": lambda p: rotation @ jax.grad(loss)(p),
        "combined: sign agreement (C)": lambda p: sign_agreement(rotation @ jax.grad(loss)(p), jax.grad(loss)(p)),
    }
    optimizer = optax.adam(config.lr)
    start = jnp.array([-2.5, 1.2])

    def descend(vector_field):
        def step(carry, _):
            point, state = carry
            update, state = optimizer.update(vector_field(point), state)
            point = optax.apply_updates(point, update)
            return (point, state), point
        _, path = jax.lax.scan(step, (start, optimizer.init(start)), None, length=config.steps)
        return np.concatenate([np.asarray(start)[None], np.asarray(path)])

    paths = {name: descend(vector_field) for name, vector_field in fields.items()}
    colours = dict(zip(paths, ("#0072B2", "#D55E00", "#009E73")))
    figure = Figure(figsize=(11, 4.4), layout="constrained")
    trajectories, losses = figure.subplots(1, 2, width_ratios=(1.25, 1))
    grid = np.linspace(-3, 3, 241)
    xx, yy = np.meshgrid(grid, np.linspace(-2.2, 2.2, 161))
    trajectories.contour(xx, yy, 0.5 * (xx**2 + config.anisotropy * yy**2), levels=np.geomspace(0.02, 30, 12), colors="0.8", linewidths=0.8)
    for name, path in paths.items():
        trajectories.plot(path[:, 0], path[:, 1], color=colours[name], lw=1.4, label=name)
    trajectories.plot(*start, "ko", ms=5)
    trajectories.plot(0, 0, "k*", ms=10)
    trajectories.set(xlabel="x", ylabel="y", title="Adam on L = (x² + " + (f"{config.anisotropy:g} " if config.anisotropy != 1 else "") + "y²)/2", aspect="equal")
    trajectories.legend(loc="lower right", fontsize=8)
    for name, path in paths.items():
        losses.semilogy(np.asarray(jax.vmap(loss)(jnp.asarray(path))), color=colours[name], lw=1.4, label=name)
    losses.set(xlabel="Adam step", ylabel="loss", title="loss along the path")
    losses.grid(alpha=0.3, which="both")
    out = Path(config.out)
    with one_line_errors():
        try:
            out.parent.mkdir(parents=True, exist_ok=True)
        except OSError as error:
            raise InputError(f"cannot write {out}: {error.strerror}") from None
        render(figure, out)
    finals = {name: float(loss(jnp.asarray(path[-1]))) for name, path in paths.items()}
    print("final loss: " + ", ".join(f"{name} {value:.2e}" for name, value in finals.items()))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    from stablebptt.cli import stop_at_once_on_signals
    stop_at_once_on_signals()
    sys.exit(main(sys.argv[1:]))
