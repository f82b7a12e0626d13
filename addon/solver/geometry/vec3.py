"""3-vector arithmetic on tuples, which Numba keeps in registers (no allocation)."""

import math

from ..runtime.jit import kernel


@kernel(inline="always")
def add(a, b):
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


@kernel(inline="always")
def sub(a, b):
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


@kernel(inline="always")
def scale(a, s):
    return (a[0] * s, a[1] * s, a[2] * s)


@kernel(inline="always")
def madd(a, b, s):
    """a + s b"""
    return (a[0] + s * b[0], a[1] + s * b[1], a[2] + s * b[2])


@kernel(inline="always")
def dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@kernel(inline="always")
def cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


@kernel(inline="always")
def norm(a):
    return math.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])


@kernel(inline="always")
def row(m, i):
    """Row i of a (.., 3) array as a tuple."""
    return (m[i, 0], m[i, 1], m[i, 2])


@kernel(inline="always")
def tangent_derivative(unit, d, length):
    """Derivative of normalize(x) along dx = d, where unit = x/|x| and length = |x|."""
    s = dot(unit, d)
    return ((d[0] - s * unit[0]) / length, (d[1] - s * unit[1]) / length, (d[2] - s * unit[2]) / length)


@kernel(inline="always")
def tangent_derivative_by_inverse(unit, d, inverse_length):
    """:func:`tangent_derivative` given 1 / |x|: three multiplies instead of three divisions,
    for the per-candidate hot loop (the result differs from it in the last bit at most)."""
    s = dot(unit, d)
    return ((d[0] - s * unit[0]) * inverse_length, (d[1] - s * unit[1]) * inverse_length,
            (d[2] - s * unit[2]) * inverse_length)
