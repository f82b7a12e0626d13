"""The vector intrinsics of addon/solver/runtime/simd.py against plain scalar loops.

Each intrinsic promises the scalar loop's IEEE operations element by element (the
de Casteljau halves: its halvings deferred, exact short of subnormals), so the checks are
bit for bit, on random data spanning many orders of magnitude and with junk beyond the
elements an operation may read.
"""

import math

import numpy as np
import pytest
from numba import njit

from addon.solver.runtime.simd import (SMALL_BOX_DEGREE, casteljau_halves, lanes_abs_argmax, rows_add_scaled,
                               rows_add_scaled_exact, rows_scale, rows_scale_add, small_box_range, square_min_max_abs,
                               transpose_blocks)
from addon.solver.spoly.two_bounce.prepass import binomial_ratios, tensor_bernstein_box

RNG_SEED = 20261126


def _graded(rng, shape):
    """Random entries from 1e-12 to 1e12 in magnitude, both signs, some exact zeros."""
    x = rng.normal(size=shape) * 10.0 ** rng.integers(-12, 13, size=shape)
    x[rng.random(shape) < 0.1] = 0.0
    return x


@njit
def _rows_ops(dst, x, s, n, which):
    if which == 0:
        rows_add_scaled(dst, x, s, n)
    elif which == 1:
        rows_add_scaled_exact(dst, x, s, n)
    elif which == 2:
        rows_scale(dst, s, n)
    else:
        rows_scale_add(dst, x, s, n)


def test_row_operations_are_the_scalar_loops():
    rng = np.random.default_rng(RNG_SEED)
    for _ in range(300):
        n = int(rng.integers(0, 41))
        dst, x = _graded(rng, 48), _graded(rng, 48)
        s = float(_graded(rng, 1)[0])
        for which in range(4):
            got = dst.copy()
            _rows_ops(got, x, s, n, which)
            want = dst.copy()
            if which == 2:
                width = -(-n // 8) * 8
                want[:width] = want[:width] * s
            elif which == 3:
                width = -(-n // 8) * 8
                want[:width] = want[:width] * s + x[:width]
            else:
                width = n if which == 1 else -(-n // 8) * 8
                want[:width] = want[:width] + s * x[:width]
            assert np.array_equal(got, want), (which, n)
            if which == 1:
                assert np.array_equal(got[n:], dst[n:])  # the exact form touches nothing beyond n


@njit
def _transpose(src, dst, blocks):
    transpose_blocks(src, dst, blocks)


def test_transpose_blocks():
    rng = np.random.default_rng(RNG_SEED + 1)
    for blocks in range(1, 7):
        src, dst = _graded(rng, (48, 48)), _graded(rng, (48, 48))
        before = dst.copy()
        _transpose(src, dst, blocks)
        w = 8 * blocks
        assert np.array_equal(dst[:w, :w], src[:w, :w].T)
        assert np.array_equal(dst[w:], before[w:]) and np.array_equal(dst[:, w:], before[:, w:])


@njit
def _min_max(c, d):
    return square_min_max_abs(c, d)


def test_square_min_max_abs():
    rng = np.random.default_rng(RNG_SEED + 2)
    for _ in range(300):
        d = int(rng.integers(0, 48))
        c = _graded(rng, (48, 48))
        lo, hi, big = _min_max(c, d)
        sub = c[:d + 1, :d + 1]
        assert (lo, hi, big) == (sub.min(), sub.max(), np.abs(sub).max())


@njit
def _halves(src, d, left, right):
    casteljau_halves(src, d, left, right)


def _casteljau_reference(src, d):
    """The textbook midpoint de Casteljau along the rows, level by level."""
    work = src[:d + 1, :].copy()
    left = np.empty_like(work)
    right = np.empty_like(work)
    left[0] = work[0]
    right[d] = work[d]
    for r in range(1, d + 1):
        for k in range(d, r - 1, -1):
            work[k] = 0.5 * (work[k - 1] + work[k])
        left[r] = work[r]
        right[d - r] = work[d]
    return left, right


def test_casteljau_halves_are_the_halving_loop():
    rng = np.random.default_rng(RNG_SEED + 3)
    for _ in range(200):
        d = int(rng.integers(0, 48))
        src = _graded(rng, (48, 48))
        left, right = _graded(rng, (48, 48)), _graded(rng, (48, 48))
        _halves(src, d, left, right)
        want_left, want_right = _casteljau_reference(src, d)
        assert np.array_equal(left[:d + 1, :d + 1], want_left[:, :d + 1])
        assert np.array_equal(right[:d + 1, :d + 1], want_right[:, :d + 1])
    # and it is the polynomial's: Bernstein coefficients of x^3 on [0, 1] -> on the halves
    d = 3
    src = np.zeros((48, 48))
    src[:4, 0] = [0.0, 0.0, 0.0, 1.0]
    left, right = np.zeros((48, 48)), np.zeros((48, 48))
    _halves(src, d, left, right)
    assert np.allclose(left[:4, 0], [0.0, 0.0, 0.0, 0.125]) and np.allclose(right[:4, 0], [0.125, 0.25, 0.5, 1.0])


@njit
def _argmax(row, floor):
    return lanes_abs_argmax(row, floor, 16)


def test_lanes_abs_argmax_is_the_compare_loop():
    rng = np.random.default_rng(RNG_SEED + 5)
    for t in range(3000):
        row = _graded(rng, 20)
        if t % 5 == 0:
            row[:16] = np.round(row[:16] / 1e6)  # ties
        if t % 7 == 0:
            row[rng.integers(0, 16)] = math.nan
        floor = float(abs(rng.normal())) if t % 3 == 0 else 0.0
        top, p = floor, -1
        for i in range(16):
            if abs(row[i]) > top:
                top, p = abs(row[i]), i
        assert _argmax(row, floor) == (top, p)


@pytest.mark.parametrize("n", [0, 5, 16])
def test_lanes_abs_argmax_all_below_floor(n):
    row = np.zeros(16)
    row[:n] = 0.5
    assert _argmax(row, 1.0) == (1.0, -1)


@njit
def _small_box(p, d, u0, v0, w, R):
    return small_box_range(p, d, u0, v0, w, R)


@njit
def _box_by_rows(p, d, u0, v0, w, R, out, t0, t1):
    tensor_bernstein_box(p, d, u0, v0, w, R, out, t0, t1)
    lo, hi, _ = square_min_max_abs(out, d)
    return lo, hi


def test_small_box_range_is_the_row_by_row_conversion():
    """small_box_range against two_bounce's row-by-row tensor Bernstein conversion and the
    min/max of its coefficients: the same (min, max) for every degree it takes (the sign of
    a zero aside), junk beyond the triangle ignored; (nan, nan) outside its degrees."""

    rng = np.random.default_rng(RNG_SEED + 7)
    R = np.zeros((48, 48))
    out, t0, t1 = (np.zeros((48, 48)) for _ in range(3))
    for _ in range(1500):
        d = int(rng.integers(1, SMALL_BOX_DEGREE + 1))
        p = _graded(rng, (48, 48))
        u0, v0 = rng.uniform(-0.1, 1.0, 2)
        w = float(rng.uniform(1e-3, 1.1))
        binomial_ratios(d, R)
        got = _small_box(p, d, u0, v0, w, R)
        want = _box_by_rows(p, d, u0, v0, w, R, out, t0, t1)
        assert got == want, (d, got, want)
    assert all(math.isnan(x) for x in _small_box(p, SMALL_BOX_DEGREE + 1, 0.0, 0.0, 1.0, R))
