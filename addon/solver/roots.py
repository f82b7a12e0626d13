"""Real roots of a univariate polynomial inside an interval.

The method of Yuksel (2022, "High-Performance Polynomial Root Finding for Graphics"), which
the Specular Polynomials paper uses for its univariate resultant (Fan et al. 2024, §4.2):
the roots of the derivative split the interval into monotonic pieces; each piece holds at
most one root, found by Newton iterations safeguarded by bisection.  The recursion is run
bottom-up: the quadratic (deg-2)-th derivative is solved in closed form, its roots bound the
monotonic pieces of the cubic derivative, and so on up to the polynomial itself.

Coefficients are in the power basis, ``c[i]`` multiplies ``x**i``.  All scratch memory is
passed in, so the per-solve loop allocates nothing.
"""

import numpy as np

from .jit import kernel

MAX_DEGREE = 24  # scratch arrays are (MAX_DEGREE + 1) wide; the one-bounce resultant has 12.
NEWTON_ITERATIONS = 64  # bisection fallback halves the bracket: 64 steps reach any float64 width.


def make_root_scratch():
    """Scratch arrays for :func:`roots_in_interval`: the derivative chain and two root lists."""
    return np.zeros((MAX_DEGREE + 1, MAX_DEGREE + 1)), np.zeros((2, MAX_DEGREE + 1))


@kernel
def horner(c, deg, x):
    """Value of the polynomial ``c[0..deg]`` at ``x``."""
    f = c[deg]
    for i in range(deg - 1, -1, -1):
        f = f * x + c[i]
    return f


@kernel
def horner_with_derivative(c, deg, x):
    """Value and first derivative of ``c[0..deg]`` at ``x`` (one Horner pass)."""
    f = c[deg]
    df = 0.0
    for i in range(deg - 1, -1, -1):
        df = df * x + f
        f = f * x + c[i]
    return f, df


@kernel
def magnitude_at(c, deg, x):
    """sum |c_i x^i|: the scale against which a value of the polynomial at x is 'zero'."""
    ax = abs(x)
    m = abs(c[deg])
    for i in range(deg - 1, -1, -1):
        m = m * ax + abs(c[i])
    return m


@kernel
def _solve_monotone(c, deg, a, b, fa, fb, x_tolerance):
    """The single root of ``c`` in [a, b], where fa = c(a) and fb = c(b) differ in sign.

    Newton from the regula-falsi point; any step leaving the bracket becomes a bisection,
    and the bracket shrinks on every evaluation, so the iteration always terminates.
    """
    x = a - fa * (b - a) / (fb - fa)
    if not (x > a and x < b):
        x = 0.5 * (a + b)
    negative_at_a = fa < 0.0
    for _ in range(NEWTON_ITERATIONS):
        f, df = horner_with_derivative(c, deg, x)
        if f == 0.0:
            return x
        if (f < 0.0) == negative_at_a:
            a = x
        else:
            b = x
        if df != 0.0:
            x_next = x - f / df
        else:
            x_next = 0.5 * (a + b)
        if not (x_next > a and x_next < b):
            x_next = 0.5 * (a + b)
        if abs(x_next - x) <= x_tolerance or b - a <= x_tolerance:
            return x_next
        x = x_next
    return x


@kernel
def _bernstein_sign_changes(c, deg, work, zero_tolerance):
    """Sign changes of the Bernstein coefficients of c[0..deg] on [0, 1] (2 = 'two or more').

    Bernstein coefficient k is sum_{i<=k} C(k,i)/C(deg,i) c_i.  Coefficients within
    ``zero_tolerance`` of zero count as a sign change: a root may touch there.
    """
    binom_deg = 1.0
    for i in range(deg + 1):
        # work[i] = c_i / C(deg, i)
        work[i] = c[i] / binom_deg
        binom_deg = binom_deg * (deg - i) / (i + 1)
    changes = 0
    prev_sign = 0
    scale = 0.0
    for i in range(deg + 1):
        scale = max(scale, abs(c[i]))
    # Forward differences: b_k = sum_i C(k,i) work_i, computed by the Pascal recurrence.
    for k in range(deg + 1):
        # b_k uses binomials of row k
        bk = 0.0
        binom = 1.0
        for i in range(k + 1):
            bk += binom * work[i]
            binom = binom * (k - i) / (i + 1)
        if abs(bk) <= zero_tolerance * scale:
            return 2
        sign = 1 if bk > 0.0 else -1
        if prev_sign != 0 and sign != prev_sign:
            changes += 1
            if changes >= 2:
                return 2
        prev_sign = sign
    return changes


@kernel
def _quadratic_roots_in(c0, c1, c2, lo, hi, out):
    """Real roots of c2 x^2 + c1 x + c0 in [lo, hi], ascending; returns the count.

    Uses the cancellation-free form q = -(c1 + sign(c1) sqrt(disc)) / 2.
    """
    n = 0
    if c2 == 0.0:
        if c1 != 0.0:
            x = -c0 / c1
            if x >= lo and x <= hi:
                out[0] = x
                n = 1
        return n
    disc = c1 * c1 - 4.0 * c2 * c0
    if disc < 0.0:
        # A double root whose discriminant rounded below zero is still a root to report
        # (the caller validates every candidate).
        if disc > -1e-14 * (c1 * c1 + abs(4.0 * c2 * c0)):
            disc = 0.0
        else:
            return 0
    sq = np.sqrt(disc)
    q = -0.5 * (c1 + sq) if c1 >= 0.0 else -0.5 * (c1 - sq)
    r1 = q / c2
    r2 = c0 / q if q != 0.0 else r1
    if r1 > r2:
        r1, r2 = r2, r1
    if r1 >= lo and r1 <= hi:
        out[n] = r1
        n += 1
    if r2 >= lo and r2 <= hi and (n == 0 or r2 != out[0]):
        out[n] = r2
        n += 1
    return n


@kernel
def roots_in_interval(coeffs, degree, lo, hi, x_tolerance, touch_tolerance, chain, lists, out):
    """All real roots of ``coeffs[0..degree]`` in [lo, hi], ascending; returns their count.

    Yuksel 2022: derivative isolation + safeguarded Newton.  ``chain`` and ``lists`` are
    scratch from :func:`make_root_scratch`.  ``touch_tolerance`` > 0 also reports a critical
    point where |p| <= touch_tolerance * sum|c_i x^i| (a double root, or two roots closer
    than rounding can separate): callers validate candidates, so a near-touch is cheap to
    report and expensive to miss.
    """
    # Drop leading coefficients that cannot change a value on the interval.
    scale = max(abs(lo), abs(hi), 1.0)
    norm = 0.0
    p = 1.0
    for i in range(degree + 1):
        norm = max(norm, abs(coeffs[i]) * p)
        p *= scale
    if norm == 0.0 or not np.isfinite(norm):
        return 0
    deg = degree
    p = scale ** deg
    while deg > 0 and abs(coeffs[deg]) * p <= 1e-15 * norm:
        deg -= 1
        p /= scale
    if deg == 0:
        return 0
    inv = 1.0 / norm
    for i in range(deg + 1):
        chain[deg, i] = coeffs[i] * inv
    if deg > 2 and lo == 0.0 and hi == 1.0:
        # Descartes' rule on the Bernstein coefficients over [0, 1]: no sign change means
        # no root, exactly one means exactly one root, bracketed by the endpoint values.
        changes = _bernstein_sign_changes(chain[deg], deg, lists[0], touch_tolerance)
        if changes == 0:
            return 0
        if changes == 1:
            fa = horner(chain[deg], deg, 0.0)
            fb = horner(chain[deg], deg, 1.0)
            if fa != 0.0 and fb != 0.0 and (fa < 0.0) != (fb < 0.0):
                out[0] = _solve_monotone(chain[deg], deg, 0.0, 1.0, fa, fb, x_tolerance)
                return 1
    if deg <= 2:
        c2 = chain[deg, 2] if deg == 2 else 0.0
        return _quadratic_roots_in(chain[deg, 0], chain[deg, 1], c2, lo, hi, out)
    # Derivative chain, each level divided by its degree to keep magnitudes comparable.
    for k in range(deg, 2, -1):
        for i in range(k):
            chain[k - 1, i] = chain[k, i + 1] * (i + 1) / k
    critical = lists[0]
    found = lists[1]
    n_critical = _quadratic_roots_in(chain[2, 0], chain[2, 1], chain[2, 2], lo, hi, critical)
    for k in range(3, deg + 1):
        c = chain[k]
        n_found = 0
        a = lo
        fa = horner(c, k, a)
        for j in range(n_critical + 1):
            b = critical[j] if j < n_critical else hi
            if b <= a:
                continue
            fb = horner(c, k, b)
            if fa == 0.0:
                if n_found == 0 or found[n_found - 1] != a:
                    found[n_found] = a
                    n_found += 1
            elif fb != 0.0 and (fa < 0.0) != (fb < 0.0):
                found[n_found] = _solve_monotone(c, k, a, b, fa, fb, x_tolerance)
                n_found += 1
            elif k == deg and touch_tolerance > 0.0 and j < n_critical and fb != 0.0:
                # b is a local extremum that comes within rounding of zero: a near-double root.
                if abs(fb) <= touch_tolerance * magnitude_at(c, k, b):
                    found[n_found] = b
                    n_found += 1
            a = b
            fa = fb
        if fa == 0.0 and (n_found == 0 or found[n_found - 1] != a):
            found[n_found] = a
            n_found += 1
        # The roots of this level are the critical points of the next one.
        for j in range(n_found):
            critical[j] = found[j]
        n_critical = n_found
    for j in range(n_critical):
        out[j] = critical[j]
    return n_critical
