"""The double point the one-bounce resultant carries for every tuple (spoly/one_bounce.py
``double_point_v``), checked against an independent evaluation of the resultant.

With the fixed projection vector C of the one-bounce forms, d0·t and d1·t both vanish where the
line g = w·t = 0 meets the coplanarity conic away from the point where n ∥ w: the square form
(T, eq 10) has a double zero there, the product form (R, eq 13) a simple one.  The solver divides
that factor out of Res_u(a, b) before isolating its roots.  Here the polynomials are built from
their definitions with numpy (world frame, no local scaling), the resultant is evaluated as
a2^n b(ρ1) b(ρ2) from numpy's roots of a(·, v), and the tests assert that

* the point found is on the conic and on g = 0, with d0·t = d1·t = 0 there;
* the resultant vanishes there, with (R) or without (T) a change of sign;
* the solver's deflated Bernstein interpolant times (v - v_d)^m is the resultant on [0, 1].
"""

import numpy as np
import pytest

from addon.solver.spoly import one_bounce as ob


def _lin(a0, au, av, b0, bu, bv):
    """(a0 + u au + v av)·(b0 + u bu + v bv) as a 7x7 coefficient array p[i, j] of u^i v^j."""
    p = np.zeros((7, 7))
    p[0, 0] = a0 @ b0
    p[1, 0] = a0 @ bu + au @ b0
    p[0, 1] = a0 @ bv + av @ b0
    p[2, 0] = au @ bu
    p[1, 1] = au @ bv + av @ bu
    p[0, 2] = av @ bv
    return p


def _mul(p, q):
    out = np.zeros((7, 7))
    for i, j in zip(*np.nonzero(p)):
        for k, l in zip(*np.nonzero(q)):
            out[i + k, j + l] += p[i, j] * q[k, l]
    return out


def _value(p, u, v):
    return sum(p[i, j] * u ** i * v ** j for i in range(7) for j in range(7 - i))


def _system(rng, refract):
    """a, b, f3, g of a random tuple with a smooth (tilted) normal field, in the solver's form."""
    P = rng.normal(size=(3, 3))
    Nv = np.array([0.0, 0.0, 1.0]) + 0.6 * rng.normal(size=(3, 3))
    p0, e1, e2 = P[0], P[1] - P[0], P[2] - P[0]
    n0, m1, m2 = Nv[0], Nv[1] - Nv[0], Nv[2] - Nv[0]
    x0 = np.array([0.3, -0.2, 3.0]) + rng.normal(size=3)
    x2 = np.array([0.1, 0.4, -2.5 if refract else 2.0]) + rng.normal(size=3)
    A, B = x0 - p0, x2 - p0
    w = B - A
    C = np.cross(w, 3.0 * n0 + m1 + m2)
    C /= np.linalg.norm(C)
    t0, tu, tv = np.cross(n0, C), np.cross(m1, C), np.cross(m2, C)
    zero = np.zeros(3)
    a = _lin(np.cross(-A, w), np.cross(e1, w), np.cross(e2, w), n0, m1, m2)
    f1 = _lin(-A, e1, e2, n0, m1, m2)
    f3 = _lin(-A, e1, e2, t0, tu, tv)
    g = _lin(w, zero, zero, t0, tu, tv)
    h = _lin(w, zero, zero, n0, m1, m2)
    if not refract:
        return a, _mul(f1, g) + _mul(f3, h) - 2.0 * _mul(f1, f3), 4, f3, g
    d0sq = _lin(-A, e1, e2, -A, e1, e2)
    d1sq = _lin(B, -e1, -e2, B, -e1, -e2)
    d1t = g - f3
    eta = 1.5
    return a, eta ** 2 * _mul(d1sq, _mul(f3, f3)) - _mul(d0sq, _mul(d1t, d1t)), 6, f3, g


def _resultant(a, b, n, v):
    """Res_u(a, b) at v = a2^n b(ρ1) b(ρ2), ρ numpy's roots of a(·, v) (complex ones included)."""
    a2 = a[2, 0]
    rho = np.roots([a2, a[1, 0] + a[1, 1] * v, a[0, 0] + a[0, 1] * v + a[0, 2] * v * v])
    value = a2 ** n
    for r in rho:
        value *= sum(b[i, j] * r ** i * v ** j for i in range(n + 1) for j in range(n + 1 - i))
    return float(np.real(value))


@pytest.mark.parametrize("refract", [False, True])
def test_double_point_divides_the_resultant(refract):
    rng = np.random.default_rng(7 if refract else 8)
    n = 6 if refract else 4
    multiplicity = 2 if refract else 1
    checked = 0
    for _ in range(200):
        a, b, n_b, f3, g = _system(rng, refract)
        v_d = ob.double_point_v(a, f3, g)
        if not np.isfinite(v_d):
            continue
        u_d = -(g[0, 0] + g[0, 1] * v_d) / g[1, 0]
        scale_a = np.abs(a).sum() * (1 + abs(u_d) + abs(v_d)) ** 2
        scale_t = np.abs(f3).sum() * (1 + abs(u_d) + abs(v_d)) ** 2
        assert abs(_value(a, u_d, v_d)) < 1e-10 * scale_a
        assert abs(_value(f3, u_d, v_d)) < 1e-10 * scale_t
        assert abs(_value(g - f3, u_d, v_d)) < 1e-10 * scale_t
        if not (-0.5 < v_d < 1.5):
            continue
        # a root of the resultant, which changes sign there for R (simple) and not for T (double);
        # that it is a root of exactly that order shows in the interpolant below
        size = max(abs(_resultant(a, b, n, v)) for v in np.linspace(0.0, 1.0, 11))
        assert abs(_resultant(a, b, n, v_d)) < 1e-9 * size
        left, right = _resultant(a, b, n, v_d - 1e-5), _resultant(a, b, n, v_d + 1e-5)
        assert (left * right > 0.0) == (multiplicity == 2)
        # the deflated interpolant, times the factor, is the resultant over the unit interval
        b_at_nodes = np.zeros((ob.NODE_ROWS, 32))
        coeffs = np.zeros(16)
        deg = ob.resultant_bernstein(a, b, n, n_b, 0.0, 1.0, v_d, b_at_nodes, np.zeros(16), coeffs)
        assert deg == 2 * n_b - multiplicity
        from math import comb

        vs = np.linspace(0.0, 1.0, 23)
        bern = np.array([sum(coeffs[k] * comb(deg, k) * v ** k * (1 - v) ** (deg - k) for k in range(deg + 1)) for v in vs])
        want = np.array([_resultant(a, b, n, v) for v in vs])
        got = bern * (vs - v_d) ** multiplicity
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9 * np.abs(want).max())
        checked += 1
    assert checked >= 20
