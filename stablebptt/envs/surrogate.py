"""A smooth training surrogate of a step reward: the comparisons a reward turns into numbers become sigmoids.

A reward such as ``1.0 if lower <= x <= upper else 0.0`` (a tolerance with margin 0) or ``speed > 1``
made a number has a gradient of zero almost everywhere: BPTT has nothing to follow. ``smooth_reward``
traces the step once and reads its program. A comparison of floats whose result reaches the reward
and nothing else of the step's output is a candidate; where its truth is turned into a number (a
conversion to a float, or a choice between two values that do not depend on the step's inputs, as
``jnp.where(inside, 1.0, 0.0)``), the number becomes ``sigmoid(difference / temperature)`` instead,
with ``and``, ``or`` and ``not`` between such truths as products. Everything else of the step runs as
traced: the state it returns is the step's own to the last bit, only its reward changes (and the
records of the reward's terms a step may keep under ``metrics``, which no later step reads). Working on
the traced program, it smooths a lab's own reward as it does MuJoCo Playground's.

Each comparison's temperature is the median of the absolute difference it compared, over sampled
states (``temperatures``), times a scale the user may give: a typical sampled state then sits
within about one temperature of the threshold, where the sigmoid's slope is large. The two bounds
of an interval (two comparisons joined by ``and``) share the larger of their temperatures, except
where every sampled state keeps one of them and some cross the other: that one stays as written, so
the surrogate rises from below the box into it and is 1 across it.

A reward, or a term of it, can also be flat because an exponential that reaches it vanishes: a Gaussian
tolerance whose margin is small next to the sampled distances. Below the float's resolution next to 1
(its epsilon: an exponent below -15.9 in float32) the term and its slope are lost beside any term of
order 1 that the reward adds to it (FishSwim's ``in_target`` is exp(-35) at its median sampled state, beside its
``upright``); below the smallest float (exponent -87) they are exactly 0. Where the median exponent an
``exp`` of the reward meets at the sampled states is below the logarithm of the float's epsilon, the
exponent is scaled so that the median becomes -1 (over the same scale): for a Gaussian, a margin widened
to where the typical sampled state sits. The library smooths a reward whose gradient it finds zero at
every sampled state; a reward with a gradient whose term vanishes is smoothed where the user asks
(``env_task``'s ``smoothing="always"``).
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax._src import source_info_util
from jax.extend import core

from stablebptt.engine.compiling import beside
from stablebptt.envs.protocol import EnvError

PyTree = Any
COMPARISONS = {"lt": -1, "le": -1, "gt": 1, "ge": 1}  # the sign of (a - b) where the comparison is true
LOGICAL = {"and", "or", "not", "xor"}
REWARD, OTHER = "reward", "other"


class Soft(NamedTuple):
    """A truth with a smooth stand-in: ``hard`` is what the program computes, ``prob`` its sigmoid."""

    hard: jax.Array
    prob: jax.Array
    origins: frozenset  # the comparisons it was made from


@dataclass(frozen=True)
class Smoothing:
    """What ``smooth_reward`` smoothed: each comparison's place in the source and its temperature."""

    terms: tuple[str, ...]
    temperatures: tuple[float, ...]
    exponents: tuple[str, ...] = ()  # the vanishing exponentials' places, and the factor of each exponent
    exponent_scales: tuple[float, ...] = ()

    @property
    def anything(self) -> bool:
        return bool(self.terms or self.exponents)

    def describe(self) -> str:
        if not self.anything:
            return "smoothed: nothing (no comparison made a number of the reward, no exponential of it vanishing)"
        parts = []
        if self.terms:
            places = ", ".join(f"{term} (temperature {temperature:.3g})" for term, temperature in
                               zip(self.terms, self.temperatures))
            parts.append(f"{len(self.terms)} comparison{'s' if len(self.terms) > 1 else ''} of the reward into "
                         f"sigmoids: {places}")
        if self.exponents:
            places = ", ".join(f"{term} (exponent times {factor:.3g})" for term, factor in
                               zip(self.exponents, self.exponent_scales))
            parts.append(f"{len(self.exponents)} vanishing exponential{'s' if len(self.exponents) > 1 else ''} "
                         f"of the reward widened: {places}")
        return "smoothed " + "; ".join(parts)


def _is_call(eqn) -> bool:
    """A call of a traced function (``jax.jit`` inside the step, ``jnp.where``'s own): read into, not bound."""
    return isinstance(eqn.params.get("jaxpr"), core.ClosedJaxpr) and eqn.primitive.name in ("jit", "pjit", "closed_call")


def _labels(jaxpr: core.Jaxpr, out_labels: list[frozenset]) -> tuple[list[frozenset], dict]:
    """Which outputs of ``jaxpr`` (REWARD, OTHER) each equation's results reach, and each variable."""
    reaches: dict = {}
    for var, label in zip(jaxpr.outvars, out_labels):
        if isinstance(var, core.Var):
            reaches[var] = reaches.get(var, frozenset()) | label
    per_equation = [frozenset()] * len(jaxpr.eqns)
    for index in range(len(jaxpr.eqns) - 1, -1, -1):
        eqn = jaxpr.eqns[index]
        label = frozenset().union(*(reaches.get(var, frozenset()) for var in eqn.outvars))
        per_equation[index] = label
        for var in eqn.invars:
            if isinstance(var, core.Var):
                reaches[var] = reaches.get(var, frozenset()) | label
    return per_equation, reaches


def _hard(value):
    return value.hard if isinstance(value, Soft) else value


def _bound(eqn, *invals):
    """``eqn``'s primitive applied to ``invals`` as ``jax.core.eval_jaxpr`` applies it: a primitive that
    calls functions (a custom derivative's) takes them back from its parameters."""
    return eqn.primitive.bind(*invals, **eqn.primitive.get_bind_params(eqn.params))


def _prob(value, dtype):
    return value.prob.astype(dtype) if isinstance(value, Soft) else jnp.asarray(value).astype(dtype)


class _Interpreter:
    """Evaluates a step's program with its reward's comparisons smoothed (or, recording, their differences)."""

    def __init__(self, temperatures: dict | None, exponent_scales: dict | None = None):
        self.temperatures = temperatures  # place -> temperature; None: record the differences instead
        self.exponent_scales = exponent_scales or {}  # place -> factor of a vanishing exponential's exponent
        self.differences: dict = {}
        self.exponents: dict = {}
        self.used: set = set()
        self.bounds: set = set()  # pairs of comparisons joined by ``and``: the two bounds of an interval
        self.places: dict = {}

    def run(self, jaxpr: core.Jaxpr, consts, args, constant_args, out_labels, path=()):
        values: dict = {}
        constant: dict = {}

        def read(var):
            if isinstance(var, core.Literal):
                return var.val, True
            return values[var], constant[var]

        for var, value in zip(jaxpr.constvars, consts):
            values[var], constant[var] = value, True
        for var, value, fixed in zip(jaxpr.invars, args, constant_args):
            values[var], constant[var] = value, fixed
        labels, reaches = _labels(jaxpr, out_labels)
        for index, eqn in enumerate(jaxpr.eqns):
            inputs = [read(var) for var in eqn.invars]
            invals, fixed = [value for value, _ in inputs], [flag for _, flag in inputs]
            inner_labels = [reaches.get(var, frozenset()) for var in eqn.outvars]
            outputs = self.equation(eqn, invals, fixed, labels[index], inner_labels, path + (index,))
            all_fixed = all(fixed)
            for var, value in zip(eqn.outvars, outputs):
                if not isinstance(var, core.DropVar):
                    values[var], constant[var] = value, all_fixed
        return [read(var)[0] for var in jaxpr.outvars]

    def equation(self, eqn, invals, fixed, label, out_labels, place):
        name = eqn.primitive.name
        soft_inputs = any(isinstance(value, Soft) for value in invals)
        if name == "exp" and label == frozenset({REWARD}) and not all(fixed) and not soft_inputs \
                and jnp.issubdtype(jnp.result_type(invals[0]), jnp.floating):
            self.places[place] = _where_written(eqn)
            if self.temperatures is None:
                self.exponents[place] = invals[0]
            elif place in self.exponent_scales:
                return [jnp.exp(invals[0] * self.exponent_scales[place]).astype(jnp.result_type(invals[0]))]
            return [_bound(eqn, invals[0])]  # the exponential as the step computes it
        if name in COMPARISONS and label == frozenset({REWARD}) and not all(fixed) \
                and jnp.issubdtype(jnp.result_type(*[_hard(v) for v in invals]), jnp.floating):
            a, b = (_hard(value) for value in invals)
            hard = _bound(eqn, a, b)
            difference = COMPARISONS[name] * (a - b)  # positive where the comparison is true
            self.places[place] = _where_written(eqn)
            if self.temperatures is None:
                self.differences[place] = difference
                prob = hard.astype(difference.dtype)
            elif place in self.temperatures:
                prob = jax.nn.sigmoid(difference / self.temperatures[place])
            else:  # not smoothed: no sampled state told its scale, or nothing made it a number
                return [hard]
            return [Soft(hard, prob, frozenset({place}))]
        if _is_call(eqn) and (soft_inputs or REWARD in label):
            inner = eqn.params["jaxpr"]
            return self.run(inner.jaxpr, inner.consts, invals, fixed, out_labels, place)
        if soft_inputs and name in LOGICAL:
            if name == "and" and all(isinstance(value, Soft) and len(value.origins) == 1 for value in invals):
                self.bounds.add(frozenset().union(*(value.origins for value in invals)))
            dtype = next(value.prob.dtype for value in invals if isinstance(value, Soft))
            probs = [_prob(value, dtype) for value in invals]
            hard = _bound(eqn, *(_hard(value) for value in invals))
            prob = {"and": lambda p, q: p * q, "or": lambda p, q: p + q - p * q, "not": lambda p: 1 - p,
                    "xor": lambda p, q: p + q - 2 * p * q}[name](*probs)
            return [Soft(hard, prob, frozenset().union(*(v.origins for v in invals if isinstance(v, Soft))))]
        if soft_inputs and name == "convert_element_type":
            value, dtype = invals[0], eqn.params["new_dtype"]
            if dtype == jnp.bool_:
                return [value]
            if jnp.issubdtype(dtype, jnp.floating):  # a truth made a number
                self.used.update(value.origins)
                return [value.prob.astype(dtype)]
        if soft_inputs and name == "select_n" and isinstance(invals[0], Soft) and len(invals) == 3 \
                and all(fixed[1:]) and not any(isinstance(v, Soft) for v in invals[1:]):
            predicate, when_false, when_true = invals
            if jnp.issubdtype(jnp.result_type(when_false), jnp.floating):  # a choice between two fixed numbers
                self.used.update(predicate.origins)
                prob = predicate.prob.astype(jnp.result_type(when_false))
                return [prob * when_true + (1 - prob) * when_false]
        outputs = _bound(eqn, *(_hard(value) for value in invals))
        return outputs if eqn.primitive.multiple_results else [outputs]


LIBRARY = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _where_written(eqn) -> str:
    """The line of the env's code that made the comparison: the innermost frame outside JAX and this
    library (whose repair of Playground's tolerance computes it), as ``folder/file.py:line (function)``."""
    frames = list(source_info_util.user_frames(eqn.source_info.traceback))
    outside = [frame for frame in frames if not os.path.abspath(frame.file_name).startswith(LIBRARY + os.sep)]
    frame = (outside or frames or [None])[0]
    if frame is None:
        return source_info_util.summarize(eqn.source_info)
    short = os.path.join(*os.path.normpath(frame.file_name).split(os.sep)[-2:])
    return f"{short}:{frame.start_line} ({frame.function_name})"


def _reward_leaf(tree: PyTree) -> int:
    """The index of the leaf named ``reward`` among a step's output leaves."""
    paths = [path for path, _ in jax.tree_util.tree_flatten_with_path(tree)[0]]
    named = [index for index, path in enumerate(paths) if path and _names(path)[-1] == "reward"]
    if len(named) != 1:
        raise ValueError(f"a step's state must hold one leaf named reward to smooth it, found {len(named)}")
    return named[0]


def _names(path) -> list:
    return [getattr(key, "name", getattr(key, "key", None)) for key in path]


def trace_step(step: Callable, state: PyTree, action: jax.Array):
    """The step's program, its output's structure, and what each output leaf is: the reward, the
    reward's own records (a leaf under ``metrics``, as Playground logs each term of it: they follow the
    reward, and no later step reads them), or the state."""
    closed, shape = jax.make_jaxpr(step, return_shape=True)(state, action)
    paths = [path for path, _ in jax.tree_util.tree_flatten_with_path(shape)[0]]
    reward = _reward_leaf(shape)
    out_labels = [frozenset({REWARD}) if index == reward else frozenset() if "metrics" in _names(path)
                  else frozenset({OTHER}) for index, path in enumerate(paths)]
    return closed, jax.tree.structure(shape), out_labels


def _evaluate(closed, out_labels, structure, interpreter: _Interpreter, state, action):
    args = jax.tree.leaves((state, action))
    outputs = interpreter.run(closed.jaxpr, closed.consts, args, [False] * len(args), out_labels)
    return jax.tree.unflatten(structure, [_hard(value) for value in outputs])


def temperatures(step: Callable, states: PyTree, actions: jax.Array, scale: float = 1.0,
                 traced: tuple | None = None) -> tuple[dict, dict]:
    """Each smoothable comparison's temperature: ``scale`` times the median absolute difference it
    compares over the sampled ``states`` and ``actions`` (leading axis: samples), where that is above 0;
    and each vanishing exponential's factor, 1 / (``scale`` times its median exponent's magnitude).
    Both as place -> (number, where written). ``traced``: the step's ``trace_step`` program, where the
    caller has it already."""
    recorder, program = _recording(traced or trace_step(step, *one_sample(states, actions)))
    return _chosen(recorder, *jax.device_get(program(states, actions)), scale)


def choices_beside(traced: tuple, sample_shapes: tuple, samples: Callable[[], tuple],
                   scale: float = 1.0) -> Callable[[], dict]:
    """``smoothing_choices`` of the step ``traced`` (``trace_step``) at the ``samples()`` (states and actions,
    shaped as ``sample_shapes`` on the device they will lie on), its program lowered here and compiled
    beside the caller: begun while the reward check that samples them, and decides whether they are
    needed, runs. Called, it waits for the compile, reads the samples and gives the choices."""
    try:
        recorder, program = _recording(traced)
        compiling = beside(program.lower(*sample_shapes).compile, "stablebptt-smoothing-choices")
    except Exception:  # noqa: BLE001 - a look ahead refuses nothing: fitted once asked for, as without it
        return lambda: smoothing_choices(None, *samples(), scale, traced)
    return lambda: _as_choices(*_chosen(recorder, *jax.device_get(compiling.result()(*samples())), scale))


def _recording(traced: tuple) -> tuple[_Interpreter, Callable]:
    """An interpreter that records, and the program (jitted, mapped over samples) that evaluates the step
    ``traced`` with it: each comparison's difference and each exponential's exponent, by place. Tracing the
    program fills the interpreter's places, used comparisons and bounds."""
    closed, structure, out_labels = traced
    recorder = _Interpreter(None)

    def differences(state, action):
        recorder.differences.clear()
        recorder.exponents.clear()
        _evaluate(closed, out_labels, structure, recorder, state, action)
        return dict(recorder.differences), dict(recorder.exponents)

    return recorder, jax.jit(jax.vmap(differences))


def _chosen(recorder: _Interpreter, sampled: dict, exponents: dict, scale: float) -> tuple[dict, dict]:
    """``temperatures``' answer from what the recording program gave at the samples."""
    chosen = {}
    for place, values in sampled.items():
        magnitudes = np.abs(np.asarray(values, float)).ravel()
        positive = magnitudes[magnitudes > 0]
        if place in recorder.used and positive.size:
            chosen[place] = (float(scale * np.median(positive)), recorder.places[place])
    for pair in recorder.bounds:  # the two bounds of an interval
        if len(pair) == 2 and pair <= chosen.keys():
            # A bound every sampled state keeps while some cross the other (HopperStand's height <= 2, an
            # upright pole's cos <= 1) stays as written: smoothed, it only slopes the reward down across
            # the box, and at a temperature wider than the box leaves the box level with the states below
            # it (HopperStand: 2.0 against a box 1.4 wide).
            kept = [place for place in pair if np.all(np.asarray(sampled[place]) > 0)]
            if len(kept) == 1:
                del chosen[kept[0]]
                continue
            # Otherwise they share the larger temperature: a state inside a narrow box sits close to both.
            shared = max(chosen[place][0] for place in pair)
            for place in pair:
                chosen[place] = (shared, chosen[place][1])
    widened = {}
    for place, values in exponents.items():  # where the median sample's exponential is lost beside 1
        median = float(np.median(np.asarray(values, float)))
        if median < np.log(np.finfo(np.asarray(values).dtype).eps):
            widened[place] = (1.0 / (scale * abs(median)), recorder.places[place])
    return chosen, widened


def smooth_reward(step: Callable, states: PyTree, actions: jax.Array, scale: float = 1.0) -> tuple[Callable, Smoothing]:
    """``step`` with its reward's comparisons smoothed, temperatures from the sampled ``states`` and
    ``actions`` (module docstring); and what was smoothed. The state it returns is ``step``'s."""
    traced = trace_step(step, *one_sample(states, actions))  # one trace serves both passes
    return smoothed_step(traced, smoothing_choices(step, states, actions, scale, traced))


def turns_comparisons_into_numbers(traced: tuple, example: tuple) -> bool:
    """Whether the reward of the step ``traced`` (``trace_step``, at ``example``'s shapes) turns a
    comparison into a number, which a flat reward's surrogate makes a sigmoid: read at shapes, nothing
    run. Where none does, a surrogate could only widen an exponential that vanishes at the sampled
    states (none of the study's rewards that are not smoothed turns one: walkers, cheetah, humanoid, fish)."""
    closed, structure, out_labels = traced
    recorder = _Interpreter(None)
    jax.eval_shape(lambda state, action: _evaluate(closed, out_labels, structure, recorder, state, action), *example)
    return bool(recorder.used)


def one_sample(states: PyTree, actions: jax.Array) -> tuple:
    """The shapes of one sampled state and action, weak types dropped as ``step_example`` drops them: the
    step traced at either numbers its operations alike (the places ``smoothing_choices`` names)."""
    return jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape[1:], a.dtype), (states, actions))


def smoothing_choices(step: Callable, states: PyTree, actions: jax.Array, scale: float = 1.0,
                      traced: tuple | None = None) -> dict:
    """``temperatures``' choices at the sampled ``states`` and ``actions``, as a kept answer holds them:
    per kind ("temperatures", "exponents") each smoothed place in the step's program, its number and
    where it is written."""
    return _as_choices(*temperatures(step, states, actions, scale, traced))


def _as_choices(chosen: dict, widened: dict) -> dict:
    return {kind: [[list(place), number, where] for place, (number, where) in sorted(choices.items())]
            for kind, choices in (("temperatures", chosen), ("exponents", widened))}


def smoothed_step(traced: tuple, choices: dict) -> tuple[Callable, Smoothing]:
    """The step ``traced`` (``trace_step``, at shapes) with the comparisons and exponentials ``choices``
    names smoothed (``smoothing_choices``); and what was smoothed."""
    closed, structure, out_labels = traced
    temperature_of = {tuple(place): number for place, number, _ in choices["temperatures"]}
    factor_of = {tuple(place): number for place, number, _ in choices["exponents"]}

    def smoothed(state, action):
        return _evaluate(closed, out_labels, structure, _Interpreter(temperature_of, factor_of), state, action)

    named = [tuple(entry[part] for entry in choices[kind]) for kind in ("temperatures", "exponents") for part in (2, 1)]
    return smoothed, Smoothing(*named)


def as_recorded(choices: dict) -> dict:
    """``choices`` (``smoothing_choices``) as a run's record holds them, plain JSON: the same whether
    fitted now or read where they were kept."""
    return json.loads(json.dumps(choices, default=float))


def _misplaced(traced: tuple, choices: dict, example: tuple) -> str | None:
    """Where ``choices`` name a comparison or exponential that the program ``traced`` does not make at the
    same place, written in the same line (that line), else None."""
    closed, structure, out_labels = traced
    recorder = _Interpreter(None)  # records where its program compares, at shapes alone
    jax.eval_shape(lambda state, action: _evaluate(closed, out_labels, structure, recorder, state, action), *example)
    return next((where for kind in ("temperatures", "exponents") for place, _, where in choices[kind]
                 if recorder.places.get(tuple(place)) != where), None)


def checked_places(traced: tuple, choices: dict, example: tuple, label: str) -> dict:
    """A run's recorded ``choices``, where the step ``traced`` still compares at each of their places;
    ``EnvError`` naming the env ``label`` where it does not (its code changed since the run began)."""
    choices = as_recorded(choices)
    if (where := _misplaced(traced, choices, example)) is not None:
        raise EnvError(f"{label}: the run trained on a surrogate of the reward that smoothed {where}, and the "
                       "env's step no longer compares there (its code changed since the run began): its "
                       "surrogate cannot be made again; train anew")
    return choices


def smoothed_alike(step: Callable, choices: dict, example: tuple, label: str) -> Callable:
    """``step`` (the derivative's model of the step ``choices`` were made for: ``derivative_model``) with the
    same comparisons and exponentials smoothed by the same numbers, traced at ``example``'s shapes.
    ``EnvError`` naming the env ``label`` where its program does not make them at the same places, written
    in the same lines."""
    traced = trace_step(step, *example)
    if (where := _misplaced(traced, choices, example)) is not None:
        raise EnvError(f"{label}: the reward's gradient is zero at every sampled state and action, and the "
                       f"derivative's model (contacts smoothed, or fewer physics steps) computes the reward "
                       f"otherwise than the env's step (nothing at {where}, where the env's step compares), so "
                       "its smooth surrogate cannot be made alike: drop those options")
    return smoothed_step(traced, choices)[0]


def step_example(env: Any) -> tuple:
    """A state and an action of ``env`` as the shapes its step is traced at where no samples are at hand."""
    state = jax.eval_shape(env.reset, jax.random.PRNGKey(0))
    action = jax.ShapeDtypeStruct((int(env.action_size),), jnp.result_type(float))
    return jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype), (state, action))


def with_reward(state: PyTree, reward: jax.Array) -> PyTree:
    """``state`` with its leaf named ``reward`` replaced."""
    leaves, structure = jax.tree.flatten(state)
    leaves[_reward_leaf(state)] = reward
    return jax.tree.unflatten(structure, leaves)


def user_surrogate(step: Callable, reward: Callable[[PyTree], jax.Array]) -> Callable:
    """``step`` whose reward is ``reward(state reached)``, in the dtype of the step's own: a surrogate of the
    user's own (``protocol.check_surrogate_reward`` sees that it is one float per state)."""
    def surrogate_step(state, action):
        reached = step(state, action)
        return with_reward(reached, jnp.asarray(reward(reached)).astype(reached.reward.dtype))

    return surrogate_step
