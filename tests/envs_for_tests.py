"""Small environments in Brax's protocol for the tests (importable as ``envs_for_tests:...``).

A cart on a line that should sit at the origin: its state carries what every
real environment's state has beside floats - a step counter, a PRNG key, a flag
- and the reward is chosen per test: smooth, a step function (of the position, or of the action's norm), a norm whose
derivative is NaN at zero action, a Gaussian that underflows, or one lost beside a term with a slope.
"""
from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

DT = 0.05


class State(NamedTuple):
    obs: jax.Array
    reward: jax.Array
    done: jax.Array
    data: dict[str, Any]


REWARDS = {
    "smooth": lambda position, action: -position ** 2 - 0.01 * jnp.sum(action ** 2),
    "step": lambda position, action: jnp.where(jnp.abs(position) < 0.1, 1.0, 0.0),
    # |action|: its derivative is NaN at exactly zero action (the norm's slope 0 / 0), finite elsewhere.
    "norm": lambda position, action: -position ** 2 - 0.01 * jnp.sqrt(jnp.sum(action ** 2)),
    "root": lambda position, action: -jnp.sqrt(position),  # NaN for every position below 0
    # A step in the action's norm: flat wherever it is defined; its smoothed comparison's derivative is NaN at
    # exactly zero action (through the norm), as "norm"'s is.
    "push": lambda position, action: jnp.where(jnp.sqrt(jnp.sum(action ** 2)) > 0.5, 1.0, 0.0),
    # A Gaussian of a margin far below the positions met: it underflows to 0 (value and slope) nearly everywhere.
    "narrow": lambda position, action: jnp.exp(-0.5 * (position / 1e-4) ** 2),
    # A slope of its own (the action's cost) beside a Gaussian whose value and slope, not 0, are lost beside it.
    "faint": lambda position, action: jnp.exp(-0.5 * (position / 0.1) ** 2) - 0.01 * jnp.sum(action ** 2),
}


class Cart:
    """A damped cart driven by a force in [-1, 1]; the episode ends (done) once it leaves |x| < 5."""

    observation_size = 2
    action_size = 1

    def __init__(self, reward: str = "smooth"):
        self.reward_of = REWARDS[reward]
        self._config = type("Config", (), {"episode_length": 30})()

    def reset(self, key: jax.Array) -> State:
        key, position_key = jax.random.split(key)
        position = jax.random.uniform(position_key, (), minval=-1.0, maxval=1.0)
        data = {"position": position, "velocity": jnp.zeros(()), "count": jnp.zeros((), jnp.int32), "rng": key,
                "moving": jnp.zeros((), bool)}
        return State(self._observe(data), jnp.zeros(()), jnp.zeros(()), data)

    def step(self, state: State, action: jax.Array) -> State:
        data = state.data
        rng, noise_key = jax.random.split(data["rng"])
        # The key feeds the physics (a tiny force noise): it must ride through the rollout untouched.
        force = action[0] + 1e-3 * jax.random.normal(noise_key, ())
        velocity = data["velocity"] + DT * (force - 0.5 * data["velocity"])
        position = data["position"] + DT * velocity
        data = {"position": position, "velocity": velocity, "count": data["count"] + 1, "rng": rng,
                "moving": jnp.abs(velocity) > 1e-3}
        done = jnp.where(jnp.abs(position) > 5.0, 1.0, 0.0)
        return State(self._observe(data), self.reward_of(position, action), done, data)

    @staticmethod
    def _observe(data) -> jax.Array:
        return jnp.stack([data["position"], data["velocity"]])


def make_cart() -> Cart:
    """A factory, as ``--env envs_for_tests:make_cart`` takes it."""
    return Cart()


def make_nothing_in_two_lines() -> Cart:
    """A factory that fails with a message of two lines, as a user's may."""
    raise RuntimeError("no cart today\nask again tomorrow")


step_reward_cart = Cart("step")


class TreeChangingCart(Cart):
    """Breaks the protocol: its step drops an entry of the state's data."""

    def step(self, state: State, action: jax.Array) -> State:
        reached = super().step(state, action)
        return reached._replace(data={k: v for k, v in reached.data.items() if k != "moving"})


tree_changing_cart = TreeChangingCart()


def position_reward(state: State) -> jax.Array:
    """A surrogate of the step reward's own making: the squared distance from the origin, negated
    (``--surrogate-reward envs_for_tests:position_reward``)."""
    return -state.data["position"] ** 2


class LateCart(Cart):
    """A reward that exists only late in the episode: 0 for the first ``LATE`` steps of 100, then the
    squared distance from the origin, negated (a target to be at once the clock has passed ``LATE``)."""

    LATE = 60

    def __init__(self):
        super().__init__()
        self._config = type("Config", (), {"episode_length": 100})()

    def step(self, state: State, action: jax.Array) -> State:
        reached = super().step(state, action)
        late = reached.data["count"] > self.LATE
        return reached._replace(reward=jnp.where(late, -reached.data["position"] ** 2, 0.0))


late_reward_cart = LateCart()


# Surrogate rewards that cannot be trained on, each as a user might write it by mistake.
def reward_of_state_and_action(state: State, action: jax.Array) -> jax.Array:
    return -state.data["position"] ** 2 - 0.01 * jnp.sum(action ** 2)


def vector_reward(state: State) -> jax.Array:
    return -state.obs ** 2  # one number per coordinate, not per state


def raising_reward(state: State) -> jax.Array:
    raise ValueError("no target in this state")


def string_reward(state: State) -> str:
    return "near"


def nan_reward(state: State) -> jax.Array:
    return -jnp.sqrt(-1.0 - state.data["position"] ** 2)  # the root of a negative number: NaN everywhere


def constant_reward(state: State) -> jax.Array:
    return jnp.ones(())


BALL = """<mujoco><option timestep="0.01"/><worldbody><geom type="plane" size="1 1 .1"/>
<body pos="0 0 0.2"><joint name="z" type="slide" axis="0 0 1"/><geom type="sphere" size="0.1" mass="1"/></body>
</worldbody><actuator><motor joint="z" gear="5"/></actuator></mujoco>"""


class Ball:
    """A ball on a vertical slide above a plane, pushed by a motor, that should hover 5 cm clear of the
    plane: an env that keeps its MJX model in ``_mjx_model``, as MuJoCo Playground's do."""

    observation_size = 2
    action_size = 1

    def __init__(self):
        import mujoco
        from mujoco import mjx
        self._mjx_model = mjx.put_model(mujoco.MjModel.from_xml_string(BALL))
        self._config = type("Config", (), {"episode_length": 20})()

    def reset(self, key: jax.Array) -> State:
        clearance = jax.random.uniform(key, (), minval=0.0, maxval=0.1)  # the slide starts 10 cm clear
        data = {"qpos": (clearance - 0.1)[None], "qvel": jnp.zeros(1), "count": jnp.zeros((), jnp.int32)}
        return State(self._observe(data), jnp.zeros(()), jnp.zeros(()), data)

    def step(self, state: State, action: jax.Array) -> State:
        from mujoco import mjx
        data = mjx.make_data(self._mjx_model).replace(qpos=state.data["qpos"], qvel=state.data["qvel"], ctrl=action)
        data = self._advance(data)
        stepped = {"qpos": data.qpos, "qvel": data.qvel, "count": state.data["count"] + 1}
        return State(self._observe(stepped), -(data.qpos[0] + 0.05) ** 2, jnp.zeros(()), stepped)

    def _advance(self, data):
        """One control step of the MJX data: here one physics step."""
        from mujoco import mjx
        return mjx.step(self._mjx_model, data)

    @staticmethod
    def _observe(data) -> jax.Array:
        return jnp.concatenate([data["qpos"], data["qvel"]])


class SubsteppedBall(Ball):
    """The ball stepped as MuJoCo Playground steps its envs: a control step of ``dt`` seconds in
    ``n_substeps`` physics steps of ``_sim_dt`` each (the model's time step)."""

    dt = 0.02

    def __init__(self, sim_dt: float = 0.002):
        super().__init__()
        self._sim_dt = sim_dt
        self._mjx_model = self._mjx_model.replace(opt=self._mjx_model.opt.replace(timestep=sim_dt))

    @property
    def n_substeps(self) -> int:
        return int(round(self.dt / self._sim_dt))

    def _advance(self, data):
        from mujoco import mjx
        return jax.lax.fori_loop(0, self.n_substeps, lambda _, data: mjx.step(self._mjx_model, data), data)


def make_substepped_ball() -> SubsteppedBall:
    return SubsteppedBall()


class PlaygroundLoopBall(SubsteppedBall):
    """The substepped ball whose control step is MuJoCo Playground's loop of physics steps (``mjx_env.step``,
    called through its module, as Playground's envs call it)."""

    def _advance(self, data):
        from mujoco_playground._src import mjx_env
        return mjx_env.step(self._mjx_model, data, data.ctrl, self.n_substeps)


def _bound_mjx_step():
    from mujoco import mjx
    return mjx.step


class BoundStepBall(SubsteppedBall):
    """The substepped ball whose step calls ``mjx.step`` as bound when the class was made (``from
    mujoco.mjx import step``), not through MJX's package."""

    _physics_step = staticmethod(_bound_mjx_step())

    def _advance(self, data):
        return jax.lax.fori_loop(0, self.n_substeps, lambda _, data: self._physics_step(self._mjx_model, data), data)


def make_bound_step_ball() -> BoundStepBall:
    return BoundStepBall()


class MjxDataBall(Ball):
    """The ball whose state carries MJX's whole data, as MuJoCo Playground's states do: its constraint
    forces (``data.qfrc_constraint``) among them."""

    def reset(self, key: jax.Array) -> State:
        from mujoco import mjx
        clearance = jax.random.uniform(key, (), minval=0.0, maxval=0.1)
        data = mjx.forward(self._mjx_model, mjx.make_data(self._mjx_model).replace(qpos=(clearance - 0.1)[None]))
        return State(self._observe({"qpos": data.qpos, "qvel": data.qvel}), jnp.zeros(()), jnp.zeros(()), data)

    def step(self, state: State, action: jax.Array) -> State:
        data = self._advance(state.data.replace(ctrl=action))
        return State(self._observe({"qpos": data.qpos, "qvel": data.qvel}), -(data.qpos[0] + 0.05) ** 2,
                     jnp.zeros(()), data)


def make_mjx_data_ball() -> MjxDataBall:
    return MjxDataBall()
