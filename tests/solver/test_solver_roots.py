"""The Bernstein root finder of addon/solver/polynomials/roots.py against numpy's companion-matrix roots.

Polynomials of degree 8 and 12 built from known roots (some in [0, 1], some outside, some
complex pairs), given by their Bernstein coefficients on [0, 1]: every real root in [0, 1]
that is 1e-2 or more from the other roots is found (within 1e-6 of the designed root, and the
exact input polynomial changes sign within 1e-10 of it); every reported root is a sign change
or a near-touch (|p| <= 1e-9 sum |c_i x^i|) of the exact input; the Bernstein evaluation matches the
power form.
"""
import numpy as np
from fractions import Fraction
from math import comb

from addon.solver.polynomials.roots import (bernstein_second_weights, bernstein_value_and_derivative,
                                            bernstein_value_and_two_derivatives, bernstein_weights, make_root_scratch,
                                            roots_in_unit_interval_bernstein)


def _to_bernstein(c):
    n = len(c) - 1
    return np.array([sum(comb(k, i) / comb(n, i) * c[i] for i in range(k + 1)) for k in range(n + 1)])


def _exact_value(b, x):
    x = Fraction(x)
    n = len(b) - 1
    return float(sum(Fraction(b[k]) * comb(n, k) * x ** k * (1 - x) ** (n - k) for k in range(n + 1)))


def _exact_sign(b, x):
    return np.sign(_exact_value(b, x))


def test_bernstein_roots_match_numpy():
    rng = np.random.default_rng(5)
    chain, lists, stack = make_root_scratch()
    power = np.zeros(32)
    out = np.zeros(32)
    w = np.zeros(32)
    dw = np.zeros(32)
    ddw = np.zeros(32)
    checked = 0
    for trial in range(400):
        deg = 8 if trial % 2 else 12
        n_real = rng.integers(1, deg // 2 + 1)
        real = rng.uniform(-0.3, 1.3, n_real)
        pairs = (deg - n_real) // 2
        cplx = rng.uniform(-0.5, 1.5, pairs) + 1j * 10.0 ** rng.uniform(-3, 0, pairs)
        rest = deg - n_real - 2 * pairs
        roots = np.concatenate([real, rng.uniform(2, 4, rest), cplx, cplx.conj()])
        c = np.real(np.polynomial.polynomial.polyfromroots(roots)) * 10.0 ** rng.uniform(-20, 5)
        b = _to_bernstein(c)
        bernstein_weights(b, deg, w, dw)
        bernstein_second_weights(b, deg, ddw)
        size = np.abs(c).sum()
        for x in (0.1, 0.5, 0.9):
            f, df = bernstein_value_and_derivative(w, dw, deg, x)
            assert abs(f - np.polynomial.polynomial.polyval(x, c)) <= 1e-12 * size
            assert abs(df - np.polynomial.polynomial.polyval(x, np.polynomial.polynomial.polyder(c))) <= 1e-11 * size * deg
            f2, df2, ddf2 = bernstein_value_and_two_derivatives(w, dw, ddw, deg, x)
            assert f2 == f and df2 == df  # the same chains as the two-value evaluation
            want_dd = np.polynomial.polynomial.polyval(x, np.polynomial.polynomial.polyder(c, 2))
            assert abs(ddf2 - want_dd) <= 1e-11 * size * deg * deg
        n = roots_in_unit_interval_bernstein(b, deg, 1e-13, 1e-10, chain, lists, stack, power, out)
        got = np.sort(out[:n])
        assert np.all(np.diff(got) > 0)
        want = np.sort(real[(real >= 0) & (real <= 1)])
        for r in want:
            others = np.abs(roots - r)
            if np.sort(others)[1] < 1e-2 or min(r, 1 - r) < 1e-6:
                continue
            assert n and np.abs(got - r).min() < 1e-6, (trial, r, got)
            g = got[np.argmin(np.abs(got - r))]
            # the input polynomial (exact rationals) changes sign across g +- 1e-10
            assert _exact_sign(b, g - 1e-10) * _exact_sign(b, g + 1e-10) < 0, (trial, r, g)
            checked += 1
        # nothing else: every reported root is a sign change of the exact input polynomial, or a
        # near-touch (|p| <= 1e-9 sum |c_i| x^i: the caller validates it like any candidate)
        for g in got:
            crossing = _exact_sign(b, g - 1e-9) * _exact_sign(b, g + 1e-9) <= 0
            touch = abs(_exact_value(b, g)) <= 1e-9 * np.polyval(np.abs(c)[::-1], g)
            assert crossing or touch, (trial, g, real, cplx)
    assert checked > 200


def test_roots_from_the_power_form_are_polished_on_the_bernstein_form():
    """A root the power-form fallback found to ~1e-9 (cancellation near a close complex pair)
    comes back to the Bernstein form's digits; at a near-touch (a minimum just above zero, no
    crossing) the polish only ever lowers |p| and stays in its piece."""
    from addon.solver.polynomials.roots import _polish_on_bernstein

    root = 0.591291002316
    c = np.real(np.polynomial.polynomial.polyfromroots([root, 0.27, 1.7, 0.5695 + 0.002j, 0.5695 - 0.002j, 2.5]))
    b = _to_bernstein(c)
    w, dw = np.zeros(32), np.zeros(32)
    bernstein_weights(b, 6, w, dw)
    x = _polish_on_bernstein(w, dw, 6, root + 2e-9, 0.58, 0.6, 1e-13)
    assert abs(x - root) <= 1e-11  # from 2e-9: the digits the Bernstein form holds
    assert _exact_sign(b, x - 1e-11) * _exact_sign(b, x + 1e-11) < 0
    touch = _to_bernstein(np.real(np.polynomial.polynomial.polyfromroots([0.4 + 1e-4j, 0.4 - 1e-4j, 1.5])))
    bernstein_weights(touch, 3, w, dw)
    y = _polish_on_bernstein(w, dw, 3, 0.4003, 0.3, 0.5, 1e-13)
    assert 0.3 <= y <= 0.5 and abs(_exact_value(touch, y)) <= abs(_exact_value(touch, 0.4003))


def test_close_real_roots_are_separated_and_converged():
    """Pairs of real roots 1e-4 .. 1e-2 apart inside [0, 1] (the pieces are split between the
    control polygon's crossings, the roots solved by Halley's iteration): both roots of every pair
    are found (and no point that is neither a crossing nor a near-touch), near the designed roots, and the exact input polynomial changes sign within 2e-12
    of each (the designed roots themselves moved when the coefficients were rounded)."""
    rng = np.random.default_rng(11)
    chain, lists, stack = make_root_scratch()
    power = np.zeros(32)
    out = np.zeros(32)
    for trial in range(200):
        deg = 8 if trial % 2 else 12
        centre = rng.uniform(0.1, 0.9)
        gap = 10.0 ** rng.uniform(-4, -2)
        pair = np.array([centre - 0.5 * gap, centre + 0.5 * gap])
        rest = np.concatenate([rng.uniform(1.5, 3.0, deg - 4), [0.3 + 0.5j, 0.3 - 0.5j]])
        c = np.real(np.polynomial.polynomial.polyfromroots(np.concatenate([pair, rest])))
        b = _to_bernstein(c)
        n = roots_in_unit_interval_bernstein(b, deg, 1e-13, 1e-10, chain, lists, stack, power, out)
        got = out[:n]
        for r in pair:
            g = got[np.argmin(np.abs(got - r))]
            assert abs(g - r) <= 1e-3 * gap, (trial, pair, got)
            assert _exact_sign(b, g - 2e-12) * _exact_sign(b, g + 2e-12) < 0, (trial, pair, g)
        for g in got:  # anything else is a near-touch (the minimum between the pair), as above
            crossing = _exact_sign(b, g - 1e-9) * _exact_sign(b, g + 1e-9) <= 0
            assert crossing or abs(_exact_value(b, g)) <= 1e-9 * np.polyval(np.abs(c)[::-1], g), (trial, g)
