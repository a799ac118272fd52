"""Arithmetic on scalars that are the model's constants (Python floats) or traced arrays.

Folding the constants while tracing drops every product with a zero entry of an axis, a
position or an inertia - XLA may not (0 * x is NaN for infinite x) - so a planar
tree costs the arithmetic of its closed-form equations. The written-out terms
(``written_out``) are made of these; both forms solve with ``solve_spd``.
"""
from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np


def add(a, b):
    if isinstance(a, float) and isinstance(b, float):
        return a + b
    if isinstance(a, float) and a == 0.0:
        return b
    if isinstance(b, float) and b == 0.0:
        return a
    return a + b


def neg(a):
    return -a


def sub(a, b):
    return add(a, neg(b))


def mul(a, b):
    if isinstance(a, float) and isinstance(b, float):
        return a * b
    for constant, other in ((a, b), (b, a)):
        if isinstance(constant, float):
            if constant == 0.0:
                return 0.0
            if constant == 1.0:
                return other
            if constant == -1.0:
                return -other
    return a * b


def add_all(terms):
    total = 0.0
    for term in terms:
        total = add(total, term)
    return total


def div(a, b):
    if isinstance(a, float) and isinstance(b, float):
        return a / b
    if isinstance(a, float) and a == 0.0:
        return 0.0
    return a / b


def sqrt(a):
    return math.sqrt(a) if isinstance(a, float) else jnp.sqrt(a)


def as_constant(array) -> tuple:
    return tuple(as_constant(a) for a in array) if np.ndim(array) else float(array)


def v_add(a, b):
    return tuple(add(x, y) for x, y in zip(a, b))


def v_sub(a, b):
    return tuple(sub(x, y) for x, y in zip(a, b))


def v_scale(v, factor):
    return tuple(mul(x, factor) for x in v)


def dot(a, b):
    return add_all(mul(x, y) for x, y in zip(a, b))


def cross(a, b):
    return (sub(mul(a[1], b[2]), mul(a[2], b[1])), sub(mul(a[2], b[0]), mul(a[0], b[2])),
            sub(mul(a[0], b[1]), mul(a[1], b[0])))


def mv(matrix, vector):
    return tuple(dot(row, vector) for row in matrix)


def v_scale_each(v, factors):
    return tuple(mul(x, f) for x, f in zip(v, factors))


def transpose(matrix):
    return tuple(zip(*matrix))


def mm(a, b):
    columns = transpose(b)
    return tuple(tuple(dot(row, column) for column in columns) for row in a)


def quaternion_rotation(quat):
    """The rotation of a traced quaternion (w, x, y, z), normalised first as MuJoCo's kinematics does."""
    norm = jnp.sqrt(sum(q * q for q in quat))
    w, x, y, z = (q / norm for q in quat)
    return ((1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
            (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
            (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)))


def axis_rotation(axis: tuple, angle):
    """Rotation by ``angle`` about the constant unit ``axis``: c (1 - a a^T) + s [a]x + a a^T."""
    cosine, sine = jnp.cos(angle), jnp.sin(angle)
    skew = ((0.0, -axis[2], axis[1]), (axis[2], 0.0, -axis[0]), (-axis[1], axis[0], 0.0))
    return tuple(tuple(add(add(mul((i == j) - axis[i] * axis[j], cosine), mul(skew[i][j], sine)),
                            axis[i] * axis[j]) for j in range(3)) for i in range(3))


ZERO3 = (0.0, 0.0, 0.0)
IDENTITY = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))

def _cholesky_solve(matrix, vector):
    """Solve a symmetric positive-definite system written out entry by entry (no loops, no LAPACK)."""
    n = len(vector)
    lower = [[0.0] * n for _ in range(n)]
    for j in range(n):
        lower[j][j] = sqrt(sub(matrix[j][j], add_all(mul(lower[j][k], lower[j][k]) for k in range(j))))
        for i in range(j + 1, n):
            lower[i][j] = div(sub(matrix[i][j], add_all(mul(lower[i][k], lower[j][k]) for k in range(j))), lower[j][j])
    forward = [0.0] * n
    for i in range(n):
        forward[i] = div(sub(vector[i], add_all(mul(lower[i][k], forward[k]) for k in range(i))), lower[i][i])
    solution = [0.0] * n
    for i in reversed(range(n)):
        solution[i] = div(sub(forward[i], add_all(mul(lower[k][i], solution[k]) for k in range(i + 1, n))), lower[i][i])
    return solution


def solve_spd(matrix, rhs):
    """``matrix``^-1 ``rhs`` (an array): written out entry by entry for a matrix of scalars (``_WrittenOut``'s),
    LAPACK's Cholesky solve for an array (``_Arrays``')."""
    if not isinstance(matrix, (list, tuple)):
        return jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(matrix), rhs)
    return stack_scalars(_cholesky_solve(matrix, [rhs[i] for i in range(len(matrix))]), rhs)


def stack_scalars(scalars, like):
    return jnp.stack([jnp.full((), x, like.dtype) if isinstance(x, float) else x for x in scalars])


def frames_as_array(nested, empty_shape, like):
    """``as_array`` of a list of frames that may be empty (a model without geoms or sites)."""
    return as_array(nested, like) if len(nested) else jnp.zeros(empty_shape, like.dtype)


def as_array(nested, like):
    """Nested sequences of scalars (constants or traced) as one array of ``like``'s dtype."""
    if isinstance(nested[0], (tuple, list)):
        return jnp.stack([as_array(item, like) for item in nested])
    return stack_scalars(nested, like)
