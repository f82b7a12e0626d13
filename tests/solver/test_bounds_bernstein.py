"""Bernstein arithmetic and range bounds (Fan et al. 2025 §4.1, eq 1–3, 12–13) against dense
sampling, and against interval arithmetic on the same pieces (Fig. 4)."""

import numpy as np
import pytest

from addon.solver.polynomials import bernstein as B

RNG = np.random.default_rng(20261121)
LO, HI = np.zeros(4), np.ones(4)


def power_eval(a, x):
    """Power-basis tensor polynomial at points x (k,4)."""
    total = np.zeros(x.shape[0])
    for idx in np.ndindex(a.shape):
        total += a[idx] * np.prod([x[:, d] ** idx[d] for d in range(4)], axis=0)
    return total


def bern_eval(b, x):
    return np.array([B.evaluate(b, *row) for row in x])


def grid(n, dims):
    axes = [np.linspace(0, 1, n) if d < dims else np.zeros(1) for d in range(4)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 4)


def test_power_to_bernstein_and_operations_are_exact():
    x = RNG.random((50, 4))
    a = RNG.normal(size=(4, 3, 2, 2))
    b = RNG.normal(size=(2, 3, 3, 1))
    pa, pb = B.power_to_bernstein(a), B.power_to_bernstein(b)
    va, vb = power_eval(a, x), power_eval(b, x)
    assert np.allclose(bern_eval(pa, x), va, atol=1e-12)
    assert np.allclose(bern_eval(B.add(pa, pb), x), va + vb, atol=1e-12)
    assert np.allclose(bern_eval(B.sub(pa, pb), x), va - vb, atol=1e-12)
    assert np.allclose(bern_eval(B.lincomb(pa, 2.0, pb, -3.0), x), 2 * va - 3 * vb, atol=1e-12)
    assert np.allclose(bern_eval(B.mul(pa, pb), x), va * vb, atol=1e-11)
    assert np.allclose(bern_eval(B.elevate(pa, (9, 5, 3, 4)), x), va, atol=1e-12)
    assert np.allclose(bern_eval(B.elevate_dim(pa, 2, 6), x), va, atol=1e-12)
    # derivative with respect to a global variable on a box of width 0.5
    d = np.zeros_like(a)
    d[:-1] = a[1:] * np.arange(1, a.shape[0])[:, None, None, None]
    assert np.allclose(bern_eval(B.deriv(pa, 0, 0.5), x), power_eval(d, x) / 0.5, atol=1e-11)
    # de Casteljau midpoint subdivision in each variable
    for dim in range(3):
        left, right = B.subdivide(pa, dim, 0.5)
        xl, xr = x.copy(), x.copy()
        xl[:, dim] *= 0.5
        xr[:, dim] = 0.5 + 0.5 * xr[:, dim]
        assert np.allclose(bern_eval(left, x), power_eval(a, xl), atol=1e-12)
        assert np.allclose(bern_eval(right, x), power_eval(a, xr), atol=1e-12)


def test_range_bound_contains_dense_samples_and_tightens_under_subdivision():
    pts = grid(21, 3)
    widths = []
    for _ in range(20):
        p = B.power_to_bernstein(RNG.normal(size=(4, 4, 2, 1)))
        lo, hi = B.coef_range(p)
        v = bern_eval(p, pts)
        assert lo <= v.min() + 1e-12 and v.max() <= hi + 1e-12
        left, right = B.subdivide(p, 0, 0.5)
        l2, h2 = B.coef_range(left)
        l3, h3 = B.coef_range(right)
        assert min(l2, l3) >= lo - 1e-12 and max(h2, h3) <= hi + 1e-12  # subdivision never loosens
        widths.append((max(h2, h3) - min(l2, l3)) / (hi - lo))
    assert np.mean(widths) < 1.0


def test_range_bound_is_exact_when_extremes_are_at_corners():
    # x (1 + y) (2 + x): monotone in every variable, extremes at the corners (0 and 6)
    x = B.affine(0.0, np.array([1.0, 0, 0, 0]), LO, HI)
    y1 = B.affine(1.0, np.array([0, 1.0, 0, 0]), LO, HI)
    x2 = B.affine(2.0, np.array([1.0, 0, 0, 0]), LO, HI)
    assert B.coef_range(B.mul(B.mul(x, y1), x2)) == pytest.approx((0.0, 6.0), abs=1e-14)


def test_paper_footnote_example_bernstein_beats_intervals():
    """f = x (4 - x) on [0, 1]: intervals give [0, 4], Bernstein coefficients 0, 2, 3 give [0, 3]."""
    g = B.affine(0.0, np.array([1.0, 0, 0, 0]), LO, HI)
    h = B.affine(4.0, np.array([-1.0, 0, 0, 0]), LO, HI)
    f = B.mul(g, h)
    assert f.ravel() == pytest.approx([0.0, 2.0, 3.0])
    assert B.coef_range(f) == (0.0, 3.0)


def test_rational_bound_cases():
    pts = grid(41, 2)
    for _ in range(20):
        p = B.power_to_bernstein(RNG.normal(size=(3, 3, 1, 1)))
        q = B.affine(3.0, np.array([1.0, -1.0, 0, 0]), LO, HI)
        q = B.mul(q, q)  # positive on the box
        lo1, hi1, lo2, hi2 = B.rational_bound(p, q)
        assert lo2 > hi2  # one interval
        v = bern_eval(p, pts) / bern_eval(q, pts)
        assert lo1 <= v.min() + 1e-12 and v.max() <= hi1 + 1e-12
    # reciprocal case: (4 - x)/(x - 0.5) on [0,1] is (-inf, -8] U [6, inf)
    num = B.affine(4.0, np.array([-1.0, 0, 0, 0]), LO, HI)
    den = B.affine(-0.5, np.array([1.0, 0, 0, 0]), LO, HI)
    assert B.rational_bound(num, den) == pytest.approx((-np.inf, -8.0, 6.0, np.inf))
    assert B.clip_hull(*B.rational_bound(num, den), 0.0, 10.0) == pytest.approx((6.0, 10.0))
    assert B.clip_hull(*B.rational_bound(num, den), 0.0, 1.0)[0] > 1.0  # empty
    # reciprocal with one interval: 1/(x - 2) on [0,1] -> denominator one-signed, fine; x-0.5 over 3: reciprocal
    lo1, hi1, lo2, hi2 = B.rational_bound(B.affine(3.0, np.zeros(4), LO, HI), B.affine(2.0, np.array([1.0, 0, 0, 0]), LO, HI))
    assert (lo1, hi1) == pytest.approx((1.0, 1.5))
    # unbounded: both numerator and denominator change sign
    assert B.rational_bound(den, den)[:2] == (-np.inf, np.inf)


def test_sqrt_linearisation_encloses_the_error_and_converges():
    for lo, hi in ((0.0, 1.0), (1.0, 4.0), (0.3, 0.31), (1e-8, 2.0), (5.0, 5.0)):
        a, b, dlo, dhi = B.sqrt_linearisation(lo, hi)
        beta = np.linspace(lo, hi, 10001)
        err = np.sqrt(beta) - (a * beta + b)
        assert dlo <= err.min() and err.max() <= dhi
    gaps = [np.subtract(*B.sqrt_linearisation(1.0, 1.0 + w)[3:1:-1]) for w in (0.1, 0.05, 0.025)]
    assert gaps[0] / gaps[1] > 3.5 and gaps[1] / gaps[2] > 3.5  # O(width²) away from β = 0


def _interval_reflect_uk(x0, P, N, Q, lo, hi):
    """Interval arithmetic bound of uk (eq 9–10, reflection) over the piece: the comparison of Fig. 4."""
    def iv(c, gu, gv):
        a = c + gu * np.array([lo[0], hi[0]])[:, None, None] + gv * np.array([lo[1], hi[1]])[None, :, None]
        return np.array([a.min(), a.max()])

    def imul(a, b):
        p = [a[0] * b[0], a[0] * b[1], a[1] * b[0], a[1] * b[1]]
        return np.array([min(p), max(p)])

    def iadd(*xs):
        return np.array([sum(x[0] for x in xs), sum(x[1] for x in xs)])

    def ineg(a):
        return np.array([-a[1], -a[0]])

    def iscale(a, s):
        return np.sort(a * s)

    e1, e2 = P[1] - P[0], P[2] - P[0]
    x = [iv(P[0, i], e1[i], e2[i]) for i in range(3)]
    n = [iv(N[0, i], N[1, i] - N[0, i], N[2, i] - N[0, i]) for i in range(3)]
    d = [iv(P[0, i] - x0[i], e1[i], e2[i]) for i in range(3)]
    nn = iadd(*[imul(n[i], n[i]) for i in range(3)])
    dn = iadd(*[imul(d[i], n[i]) for i in range(3)])
    dt = [iadd(imul(nn, d[i]), ineg(iscale(imul(dn, n[i]), 2.0))) for i in range(3)]
    ek1, ek2 = Q[1] - Q[0], Q[2] - Q[0]
    c = [iadd(iscale(dt[1], ek2[2]), ineg(iscale(dt[2], ek2[1]))), iadd(iscale(dt[2], ek2[0]), ineg(iscale(dt[0], ek2[2]))),
         iadd(iscale(dt[0], ek2[1]), ineg(iscale(dt[1], ek2[0])))]
    r = [x[i] - Q[0, i] for i in range(3)]
    pu = iadd(*[imul(c[i], r[i]) for i in range(3)])
    q = iadd(*[iscale(c[i], ek1[i]) for i in range(3)])
    if q[0] <= 0 <= q[1]:
        return np.array([-np.inf, np.inf])
    inv = np.sort(1.0 / q)
    return imul(pu, inv)


@pytest.mark.slow
def test_bernstein_position_bound_is_tighter_than_interval_arithmetic():
    """Same reflector pieces: width of the uk bound, Bernstein (eq 3, 9) vs interval arithmetic."""
    from fixtures.bounds_scenes import curved_plane
    from reference import bounds_one_bounce as C

    P, N = curved_plane(4, 0.3)
    Q = np.array([[-40, -40, 3.0], [40, -40, 3.0], [-40, 40, 3.0]])
    UV = np.array([[0, 0], [1, 0], [0, 1.0]])
    x0 = np.array([0.3, 0.2, 1.5])
    ratios = []
    out = np.zeros(8)
    for t in range(P.shape[0]):
        for lo, hi in (((0.0, 0.0), (1.0, 1.0)), ((0.0, 0.0), (0.5, 0.5)), ((0.25, 0.25), (0.5, 0.5))):
            lo, hi = np.array(lo), np.array(hi)
            if not C.piece_position(False, x0, P[t], N[t], Q, UV, 1.0, lo, hi, out):
                continue
            ia = _interval_reflect_uk(x0, P[t], N[t], Q, lo, hi)
            ia = np.clip(ia, 0, 1)
            ratios.append((out[1] - out[0]) / (ia[1] - ia[0]))
    ratios = np.array(ratios)
    print(f"Bernstein/interval width ratio of the uk bound: mean {ratios.mean():.3f}, max {ratios.max():.3f} over {ratios.size} pieces")
    assert ratios.size > 50
    assert np.all(ratios <= 1.0 + 1e-6)
    assert ratios.mean() < 0.8
