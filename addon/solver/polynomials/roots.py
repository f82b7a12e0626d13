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

import math

import numpy as np

from ..runtime.jit import kernel

MAX_DEGREE = 24  # scratch arrays are (MAX_DEGREE + 1) wide; the one-bounce resultant has 12.
POLISH_ON_BERNSTEIN_STEPS = 4  # Newton steps on the Bernstein form for a root isolated on the power form
NEWTON_ITERATIONS = 64  # bisection fallback halves the bracket: 64 steps reach any float64 width.
NEWTON_QUADRATIC_RATIO = 1e-3  # a Newton step this much shorter than the one before: quadratic convergence


SUBDIVISION_DEPTH = 5  # Bernstein subdivisions before a piece falls back to derivative isolation
STACK_ROWS = 2 * SUBDIVISION_DEPTH + 4
SPLIT_LOW = 0.125  # a Bernstein piece is split no closer than this share of it to either end
NEAR_TOUCH = 1e-6  # a root-free Bernstein piece this close to zero is re-checked for touching roots
# Second differences of a piece's Bernstein coefficients (scaled to the largest coefficient of the
# whole interval) at least this large and of one sign: the second derivative cannot change sign
# there, not even under the rounding of the power form the derivative isolation evaluates (~1e-10
# of that scale at degree 12).
CONVEX_MARGIN = 1e-9


def _binomials(n):
    """C(i, k) for 0 <= k <= i <= n, as exact floats (zero above the diagonal)."""
    from math import comb

    return np.array([[float(comb(i, k)) if k <= i else 0.0 for k in range(n + 1)] for i in range(n + 1)])


BINOMIAL = _binomials(MAX_DEGREE)


def make_root_scratch():
    """Scratch arrays for the root finders: derivative chain, two root lists, Bernstein stack."""
    return (np.zeros((MAX_DEGREE + 1, MAX_DEGREE + 1)), np.zeros((2, MAX_DEGREE + 1)),
            np.zeros((STACK_ROWS + 1, MAX_DEGREE + 4)))


@kernel(refcounted=False)
def horner(c, deg, x):
    """Value of the polynomial ``c[0..deg]`` at ``x``."""
    f = c[deg]
    for i in range(deg - 1, -1, -1):
        f = f * x + c[i]
    return f


@kernel(refcounted=False)
def horner_with_derivative(c, deg, x):
    """Value and first derivative of ``c[0..deg]`` at ``x`` (one Horner pass)."""
    f = c[deg]
    df = 0.0
    for i in range(deg - 1, -1, -1):
        df = df * x + f
        f = f * x + c[i]
    return f, df


@kernel(refcounted=False)
def magnitude_at(c, deg, x):
    """sum |c_i x^i|: the scale against which a value of the polynomial at x is 'zero'."""
    ax = abs(x)
    m = abs(c[deg])
    for i in range(deg - 1, -1, -1):
        m = m * ax + abs(c[i])
    return m


@kernel(inline="always")
def _newton_settled(step, previous_step, x_tolerance):
    """Whether the Newton iterate x_next = x - step is within ``x_tolerance`` of the root:
    the step itself is that small, or the iteration converges quadratically (e_{k+1} ≈ C e_k²)
    with step / previous_step = r <= NEWTON_QUADRATIC_RATIO, so that x_next's error ≈ r² step
    <= x_tolerance for step <= x_tolerance / NEWTON_QUADRATIC_RATIO².  This saves the last
    evaluation, which would only confirm a step below the tolerance."""
    if step <= x_tolerance:
        return True
    return (step * NEWTON_QUADRATIC_RATIO * NEWTON_QUADRATIC_RATIO <= x_tolerance
            and step <= NEWTON_QUADRATIC_RATIO * previous_step)


@kernel(refcounted=False)
def _solve_monotone(c, deg, a, b, fa, fb, x_tolerance):
    """The single root of ``c`` in [a, b], where fa = c(a) and fb = c(b) differ in sign.

    Newton from the regula-falsi point (Yuksel 2022: Newton safeguarded by bisection);
    a step below ``x_tolerance`` ends the iteration, any other step leaving the bracket
    becomes a bisection, and the bracket shrinks on every evaluation, so the iteration
    always terminates.
    """
    return _solve_monotone_from(c, deg, a, b, fa, fb, math.nan, x_tolerance)


@kernel(refcounted=False)
def _solve_monotone_from(c, deg, a, b, fa, fb, x_start, x_tolerance):
    """:func:`_solve_monotone` started at ``x_start`` when it lies inside (a, b), else at the
    regula-falsi point."""
    x = x_start
    if not (x > a and x < b):
        x = a - fa * (b - a) / (fb - fa)
    if not (x > a and x < b):
        x = 0.5 * (a + b)
    negative_at_a = fa < 0.0
    previous_step = math.inf
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
            step = abs(x_next - x)
            if _newton_settled(step, previous_step, x_tolerance) and x_next >= a and x_next <= b:
                # Converged (the step is below the tolerance, or quadratic convergence puts
                # x_next within it: see _newton_settled).  Tested before the bracket test: a
                # step onto the bracket's end (x itself, once the step rounds to zero) would
                # otherwise become a bisection, and the bisections would run on until the
                # bracket is x_tolerance wide.
                return x_next
            previous_step = step
        else:
            x_next = 0.5 * (a + b)
            previous_step = math.inf
        if not (x_next > a and x_next < b):
            x_next = 0.5 * (a + b)
            previous_step = math.inf  # the next iterate is no Newton step's
        if abs(x_next - x) <= x_tolerance or b - a <= x_tolerance:
            return x_next
        x = x_next
    return x


@kernel(inline="always")
def _sign_changes(b, deg, zero_level):
    """Sign changes in b[0..deg] (2 means 'two or more'); an entry within zero_level of zero
    counts as 2: a root may touch there, so the piece must be looked at more closely.
    Counted without branches (data-dependent exits mispredict more often than not)."""
    changes = 0
    smallest = abs(b[0])
    negative = b[0] < 0.0
    for k in range(1, deg + 1):
        next_negative = b[k] < 0.0
        changes += 1 if next_negative != negative else 0
        negative = next_negative
        smallest = min(smallest, abs(b[k]))
    if smallest <= zero_level:
        return 2
    return min(changes, 2)


@kernel(refcounted=False)
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


@kernel(refcounted=False)
def roots_in_interval(coeffs, degree, lo, hi, x_tolerance, touch_tolerance, chain, lists, out):
    """All real roots of ``coeffs[0..degree]`` in [lo, hi], ascending; returns their count.

    Yuksel 2022: derivative isolation + safeguarded Newton.  ``chain`` and ``lists`` are
    scratch from :func:`make_root_scratch`.  ``touch_tolerance`` > 0 also reports a critical
    point where |p| <= touch_tolerance * sum|c_i x^i| (a double root, or two roots closer
    than rounding can separate): callers validate candidates, so a near-touch is cheap to
    report and expensive to miss.
    """
    return _derivative_isolation(coeffs, degree, lo, hi, x_tolerance, touch_tolerance, chain, lists, out, False, False)


@kernel(refcounted=False)
def _start_next_to_extremum(chain, k, a, b, fa, fb, a_is_extremum, b_is_extremum):
    """Where the quadratic model of chain level k (a polynomial with derivatives k chain[k-1],
    k (k-1) chain[k-2]) at the extremum end of [a, b] (the one of smaller |p| if both are)
    crosses zero; NaN when the model has no such root."""
    at_a = a_is_extremum and (not b_is_extremum or abs(fa) <= abs(fb))
    x_m = a if at_a else b
    f_m = fa if at_a else fb
    curvature = k * (k - 1) * horner(chain[k - 2], k - 2, x_m)
    if not (f_m * curvature < 0.0):
        return math.nan
    half_width = math.sqrt(-2.0 * f_m / curvature)
    return x_m + half_width if at_a else x_m - half_width


@kernel(refcounted=False)
def _derivative_isolation(coeffs, degree, lo, hi, x_tolerance, touch_tolerance, chain, lists, out, convex,
                          model_start):
    """:func:`roots_in_interval`; ``convex``: the caller has shown that the second derivative
    keeps one sign on [lo, hi], so the first derivative has at most one root there and the
    levels below it (Yuksel 2022: the roots of each derivative bound the monotonic pieces
    of the next) would find no critical points: the isolation starts at the first derivative
    (the result is the same as the full recursion's).

    ``model_start``: Newton for a root next to an extremum x_m starts at the root of the
    quadratic model there, x_m ± √(-2 p(x_m) / p''(x_m)), instead of the regula-falsi point.
    Two roots δ apart about an extremum in a piece of width w otherwise cost Newton
    ~log2(w / δ) halving steps from the far side (a pair 1e-7 apart in a piece 1/32 wide:
    ~18); the roots found agree to the tolerance.
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
    if deg <= 2:
        c2 = chain[deg, 2] if deg == 2 else 0.0
        return _quadratic_roots_in(chain[deg, 0], chain[deg, 1], c2, lo, hi, out)
    shortcut = convex and deg >= 4
    first_level = deg - 1 if shortcut else 3
    # Derivative chain, each level divided by its degree to keep magnitudes comparable.
    for k in range(deg, first_level - 1, -1):
        for i in range(k):
            chain[k - 1, i] = chain[k, i + 1] * (i + 1) / k
    critical = lists[0]
    found = lists[1]
    if shortcut:
        n_critical = 0  # the first derivative is monotonic on [lo, hi]
    else:
        n_critical = _quadratic_roots_in(chain[2, 0], chain[2, 1], chain[2, 2], lo, hi, critical)
    for k in range(first_level, deg + 1):
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
                x_start = math.nan
                if model_start and k >= 4 and (j > 0 or j < n_critical):
                    x_start = _start_next_to_extremum(chain, k, a, b, fa, fb, j > 0, j < n_critical)
                found[n_found] = _solve_monotone_from(c, k, a, b, fa, fb, x_start, x_tolerance)
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


@kernel(refcounted=False)
def roots_in_unit_interval(coeffs, degree, x_tolerance, touch_tolerance, chain, lists, stack, out):
    """All real roots of ``coeffs[0..degree]`` in [0, 1], ascending; returns their count.

    Isolation by Descartes' rule of signs on Bernstein coefficients (a piece whose
    coefficients change sign once holds exactly one root, none if they never do), halving
    pieces by de Casteljau; each isolated root is found by the same safeguarded Newton as
    :func:`roots_in_interval`.  Pieces still ambiguous after ``SUBDIVISION_DEPTH`` halvings
    (clustered or touching roots) are handed to the derivative isolation of Yuksel 2022.
    Cost adapts to the number of roots instead of always walking the whole derivative chain.
    """
    norm = 0.0
    for i in range(degree + 1):
        norm = max(norm, abs(coeffs[i]))
    if norm == 0.0 or not np.isfinite(norm):
        return 0
    deg = degree
    while deg > 0 and abs(coeffs[deg]) <= 1e-15 * norm:
        deg -= 1
    if deg <= 2:
        return roots_in_interval(coeffs, deg, 0.0, 1.0, x_tolerance, touch_tolerance, chain, lists, out)
    # Power -> Bernstein on [0, 1]: b_k = sum_{i<=k} C(k,i)/C(deg,i) c_i.
    work = stack[STACK_ROWS]
    binom_deg = 1.0
    for i in range(deg + 1):
        work[i] = coeffs[i] / norm / binom_deg
        binom_deg = binom_deg * (deg - i) / (i + 1)
    top_row = stack[0]
    scale = 0.0
    for k in range(deg + 1):
        bk = 0.0
        binom = 1.0
        for i in range(k + 1):
            bk += binom * work[i]
            binom = binom * (k - i) / (i + 1)
        top_row[k] = bk
        scale = max(scale, abs(bk))
    zero_level = touch_tolerance * scale
    # The stack: row j holds Bernstein coefficients, then lo, hi, depth in the last slots.
    meta = deg + 1
    top_row[meta] = 0.0
    top_row[meta + 1] = 1.0
    top_row[meta + 2] = 0.0
    top = 1
    n_out = 0
    while top > 0:
        top -= 1
        row = stack[top]
        lo = row[meta]
        hi = row[meta + 1]
        depth = row[meta + 2]
        changes = _sign_changes(row, deg, zero_level)
        if changes == 0:
            # No root, unless the piece comes close to touching zero: there rounding can
            # hide a pair of real roots (a fold of the caustic), which the derivative
            # isolation's touch test still reports as a candidate.
            closest = abs(row[0])
            for k in range(1, deg + 1):
                closest = min(closest, abs(row[k]))
            if closest > NEAR_TOUCH * scale:
                continue
            changes = 2
            depth = SUBDIVISION_DEPTH
        if changes == 1:
            fa = horner(coeffs, deg, lo)
            fb = horner(coeffs, deg, hi)
            if fa != 0.0 and fb != 0.0 and (fa < 0.0) != (fb < 0.0):
                x = _solve_monotone(coeffs, deg, lo, hi, fa, fb, x_tolerance)
                if n_out == 0 or x - out[n_out - 1] > x_tolerance:
                    out[n_out] = x
                    n_out += 1
                continue
        if depth >= SUBDIVISION_DEPTH:
            n_piece = roots_in_interval(coeffs, deg, lo, hi, x_tolerance, touch_tolerance, chain, lists, lists[1])
            # roots_in_interval used lists[0..1] as scratch; its result sits in lists[1].
            for j in range(n_piece):
                x = lists[1, j]
                if n_out == 0 or x - out[n_out - 1] > x_tolerance:
                    out[n_out] = x
                    n_out += 1
            continue
        # de Casteljau at the midpoint: right half into this row, left half on top of it,
        # so the left half is processed first and roots come out in ascending order.
        for i in range(deg + 1):
            work[i] = row[i]
        left = stack[top + 1]
        left[0] = work[0]
        row[deg] = work[deg]
        for r in range(1, deg + 1):
            for i in range(deg - r + 1):
                work[i] = 0.5 * (work[i] + work[i + 1])
            left[r] = work[0]
            row[deg - r] = work[deg - r]
        mid = 0.5 * (lo + hi)
        left[meta] = lo
        left[meta + 1] = mid
        left[meta + 2] = depth + 1.0
        row[meta] = mid
        row[meta + 1] = hi
        row[meta + 2] = depth + 1.0
        top += 2
    return n_out


@kernel(inline="always")
def _control_polygon_crossing(b, deg):
    """Where in [0, 1] the control polygon of the Bernstein coefficients b[0..deg] first
    crosses zero (the points (k / deg, b[k])); 0.5 without a crossing."""
    for k in range(deg):
        if (b[k] < 0.0) != (b[k + 1] < 0.0):
            return (k + b[k] / (b[k] - b[k + 1])) / deg
    return 0.5


@kernel(inline="always")
def _split_between_crossings(b, deg):
    """Where in (0, 1) to split a Bernstein piece: halfway between the first two zero crossings of
    its control polygon, kept within [SPLIT_LOW, 1 - SPLIT_LOW]; 0.5 with fewer crossings."""
    first = -1.0
    for k in range(deg):
        if (b[k] < 0.0) != (b[k + 1] < 0.0):
            crossing = (k + b[k] / (b[k] - b[k + 1])) / deg
            if first < 0.0:
                first = crossing
            else:
                return min(max(0.5 * (first + crossing), SPLIT_LOW), 1.0 - SPLIT_LOW)
    return 0.5


@kernel(refcounted=False)
def _second_differences_one_sign(b, deg, margin):
    """True when the second differences of the Bernstein coefficients b[0..deg] all exceed
    ``margin`` in size and share one sign: then the polynomial's second derivative keeps that
    sign on the piece (convex hull property), well clear of the rounding of a power-form
    evaluation."""
    smallest = math.inf
    largest = -math.inf
    for k in range(deg - 1):
        d = b[k + 2] - 2.0 * b[k + 1] + b[k]
        smallest = min(smallest, d)
        largest = max(largest, d)
    return smallest > margin or largest < -margin


@kernel(refcounted=False)
def bernstein_weights(b, deg, w, dw):
    """w[k] = C(deg, k) b[k] and dw[k] = deg C(deg - 1, k) (b[k+1] - b[k]): the scaled power
    coefficients that :func:`bernstein_value_and_derivative` runs Horner on."""
    for k in range(deg + 1):
        w[k] = BINOMIAL[deg, k] * b[k]
    for k in range(deg):
        dw[k] = (deg * BINOMIAL[deg - 1, k]) * (b[k + 1] - b[k])


@kernel(refcounted=False)
def bernstein_value_and_derivative(w, dw, deg, x):
    """Value and derivative at x in [0, 1] of sum_k b[k] C(deg, k) x^k (1 - x)^(deg - k), from
    the weights of :func:`bernstein_weights`.

    Horner in x on the homogeneous form sum_k w[k] x^k s^(deg - k), s = 1 - x, the powers of
    s built alongside: O(deg), no division, and with x, s in [0, 1] no term grows, so the
    rounding is bounded by that of the terms' absolute sum (as for de Casteljau).  The
    derivative is the degree deg - 1 form with coefficients deg (b[k+1] - b[k]) (``dw``), in
    the same loop: its chain and the value's wait on different multiply-adds.
    """
    s = 1.0 - x
    f = w[deg]
    df = dw[deg - 1]
    s_power = 1.0  # s^(deg - k) at step k
    for k in range(deg - 1, 0, -1):
        s_power *= s
        f = f * x + w[k] * s_power
        df = df * x + dw[k - 1] * s_power
    s_power *= s
    return f * x + w[0] * s_power, df


@kernel(refcounted=False)
def bernstein_second_weights(b, deg, ddw):
    """ddw[k] = deg (deg - 1) C(deg - 2, k) (b[k+2] - 2 b[k+1] + b[k]): the weights of the second
    derivative, a degree deg - 2 Bernstein form, for :func:`bernstein_value_and_two_derivatives`."""
    for k in range(deg - 1):
        ddw[k] = (deg * (deg - 1) * BINOMIAL[deg - 2, k]) * (b[k + 2] - 2.0 * b[k + 1] + b[k])


@kernel(inline="always")
def bernstein_value_and_two_derivatives(w, dw, ddw, deg, x):
    """Value, first and second derivative at x in [0, 1] of the Bernstein form of
    :func:`bernstein_value_and_derivative` (``ddw`` from :func:`bernstein_second_weights`,
    deg >= 2): three Horner chains in one loop, none waiting on another."""
    s = 1.0 - x
    f = w[deg]
    df = dw[deg - 1]
    ddf = ddw[deg - 2]
    s_power = 1.0  # s^(deg - k) at step k
    for k in range(deg - 1, 1, -1):
        s_power *= s
        f = f * x + w[k] * s_power
        df = df * x + dw[k - 1] * s_power
        ddf = ddf * x + ddw[k - 2] * s_power
    s_power *= s
    f = f * x + w[1] * s_power
    df = df * x + dw[0] * s_power
    s_power *= s
    return f * x + w[0] * s_power, df, ddf


@kernel(refcounted=False)
def _solve_monotone_bernstein(w, dw, ddw, deg, a, c, fa, fc, x_start, x_tolerance):
    """:func:`_solve_monotone_from` for a polynomial in Bernstein form on [0, 1] (weights as in
    :func:`bernstein_weights` and :func:`bernstein_second_weights`), with Halley's step
    x - 2 f f' / (2 f'² - f f'') where |f f''| < f'² (else Newton's): cubic convergence, so
    from the control polygon's crossing two evaluations usually settle the root.  Settled
    (``_halley_settled``) when the step ratio r to the step before gives r³ step <= tolerance."""
    x = x_start
    if not (x > a and x < c):
        x = a - fa * (c - a) / (fc - fa)
    if not (x > a and x < c):
        x = 0.5 * (a + c)
    negative_at_a = fa < 0.0
    previous_step = math.inf
    for _ in range(NEWTON_ITERATIONS):
        f, df, ddf = bernstein_value_and_two_derivatives(w, dw, ddw, deg, x)
        if f == 0.0:
            return x
        if (f < 0.0) == negative_at_a:
            a = x
        else:
            c = x
        if df != 0.0:
            curvature = f * ddf
            if abs(curvature) < df * df:
                x_next = x - 2.0 * f * df / (2.0 * df * df - curvature)
            else:
                x_next = x - f / df
            step = abs(x_next - x)
            if _halley_settled(step, previous_step, x_tolerance) and x_next >= a and x_next <= c:
                return x_next
            previous_step = step
        else:
            x_next = 0.5 * (a + c)
            previous_step = math.inf
        if not (x_next > a and x_next < c):
            x_next = 0.5 * (a + c)
            previous_step = math.inf  # the next iterate is no Halley step's
        if abs(x_next - x) <= x_tolerance or c - a <= x_tolerance:
            return x_next
        x = x_next
    return x


@kernel(inline="always")
def _halley_settled(step, previous_step, x_tolerance):
    """Whether the Halley iterate x_next = x - step is within ``x_tolerance`` of the root: the
    step is that small, or the iteration converges cubically (e_{k+1} ≈ K e_k³, so with the
    ratio r = step / previous_step <= NEWTON_QUADRATIC_RATIO, x_next's error ≈ r³ step; a first
    step, without a ratio, is held to _newton_settled's bound)."""
    if step <= x_tolerance:
        return True
    if previous_step == math.inf:
        # no ratio yet: the first step's bound, as for Newton's (_newton_settled)
        return step * NEWTON_QUADRATIC_RATIO * NEWTON_QUADRATIC_RATIO <= x_tolerance
    r = step / previous_step
    return r <= NEWTON_QUADRATIC_RATIO and r * r * r * step <= x_tolerance


@kernel(inline="always")
def _polish_on_bernstein(w, dw, deg, x, lo, hi, x_tolerance):
    """Newton steps from ``x`` on the Bernstein form (weights of :func:`bernstein_weights`),
    kept while each step is shorter than the one before, stays in [lo, hi] and lowers |p|:
    a root found on the power form to the digits its conditioning left, brought to those of
    the Bernstein form; a near-touch (no crossing), where Newton does not contract, stays put."""
    f, df = bernstein_value_and_derivative(w, dw, deg, x)
    best = x
    best_f = abs(f)
    previous = math.inf
    for _ in range(POLISH_ON_BERNSTEIN_STEPS):
        if df == 0.0 or best_f == 0.0:
            break
        step = f / df
        if not abs(step) < previous:
            break
        x_next = x - step
        if not (x_next >= lo and x_next <= hi):
            break
        f, df = bernstein_value_and_derivative(w, dw, deg, x_next)
        if not abs(f) < best_f:
            break
        best = x_next
        best_f = abs(f)
        previous = abs(step)
        x = x_next
        if previous <= x_tolerance:
            break
    return best


@kernel(refcounted=False)
def roots_in_unit_interval_bernstein(bern, deg, x_tolerance, touch_tolerance, chain, lists, stack, power, out):
    """All real roots in [0, 1] of the polynomial with Bernstein coefficients ``bern[0..deg]``,
    ascending; returns their count.

    The isolation of :func:`roots_in_unit_interval` (Descartes' rule on Bernstein pieces,
    de Casteljau subdivision), started from the Bernstein form itself, which is the better
    conditioned input when the coefficients come from values (interpolation at nodes):
    Halley's iteration evaluates the Bernstein form.  A piece is split between its control
    polygon's first two crossings (``_split_between_crossings``), not at its midpoint, so that
    one split usually separates two roots.  Pieces still ambiguous after ``SUBDIVISION_DEPTH``
    splits go to the derivative isolation of :func:`roots_in_interval` on the power form
    (written to ``power``, a row of at least deg + 1).  Tested in tests/solver/test_solver_roots.py.
    """
    scale = 0.0
    for k in range(deg + 1):
        scale = max(scale, abs(bern[k]))
    if scale == 0.0 or not np.isfinite(scale):
        return 0
    inv = 1.0 / scale
    top_row = stack[0]
    for k in range(deg + 1):
        top_row[k] = bern[k] * inv
    src = stack[STACK_ROWS - 1]  # the whole-interval form, kept for evaluation
    for k in range(deg + 1):
        src[k] = top_row[k]
    have_weights = False
    have_second = False
    src_w = stack[STACK_ROWS - 2]
    src_dw = stack[STACK_ROWS - 3]
    src_ddw = stack[STACK_ROWS - 4]
    have_power = False
    zero_level = touch_tolerance
    work = stack[STACK_ROWS]
    meta = deg + 1
    top_row[meta] = 0.0
    top_row[meta + 1] = 1.0
    top_row[meta + 2] = 0.0
    top = 1
    n_out = 0
    while top > 0:
        top -= 1
        row = stack[top]
        lo = row[meta]
        hi = row[meta + 1]
        depth = row[meta + 2]
        changes = _sign_changes(row, deg, zero_level)
        if changes == 0:
            closest = abs(row[0])
            for k in range(1, deg + 1):
                closest = min(closest, abs(row[k]))
            if closest > NEAR_TOUCH:
                continue
            changes = 2
            depth = SUBDIVISION_DEPTH
        if changes == 1:
            # the piece's end values are its first and last Bernstein coefficients
            fa = row[0]
            fb = row[deg]
            if fa != 0.0 and fb != 0.0 and (fa < 0.0) != (fb < 0.0):
                if not have_weights:
                    bernstein_weights(src, deg, src_w, src_dw)
                    have_weights = True
                if not have_second:
                    bernstein_second_weights(src, deg, src_ddw)
                    have_second = True
                # Halley starts where the piece's control polygon crosses zero: it follows the
                # polynomial far more closely than the chord through the piece's end values
                # (regula falsi), so fewer steps are needed.
                x_start = lo + (hi - lo) * _control_polygon_crossing(row, deg)
                x = _solve_monotone_bernstein(src_w, src_dw, src_ddw, deg, lo, hi, fa, fb, x_start, x_tolerance)
                if n_out == 0 or x - out[n_out - 1] > x_tolerance:
                    out[n_out] = x
                    n_out += 1
                continue
        if depth >= SUBDIVISION_DEPTH:
            if not have_power:
                # Bernstein -> power: c_i = C(deg, i) sum_{k<=i} (-1)^(i-k) C(i, k) b_k
                binom_deg = 1.0
                for i in range(deg + 1):
                    acc = 0.0
                    binom = 1.0
                    for k in range(i + 1):
                        sign = 1.0 if (i - k) % 2 == 0 else -1.0
                        acc += sign * binom * src[k]
                        binom = binom * (i - k) / (k + 1)
                    power[i] = binom_deg * acc
                    binom_deg = binom_deg * (deg - i) / (i + 1)
                have_power = True
            convex = _second_differences_one_sign(row, deg, CONVEX_MARGIN)
            n_piece = _derivative_isolation(power, deg, lo, hi, x_tolerance, touch_tolerance, chain, lists, lists[1],
                                            convex, True)
            if n_piece and not have_weights:
                bernstein_weights(src, deg, src_w, src_dw)
                have_weights = True
            for j in range(n_piece):
                # the power form loses digits to cancellation near clustered roots: polished
                # on the Bernstein form the root regains them
                x = _polish_on_bernstein(src_w, src_dw, deg, lists[1, j], lo, hi, x_tolerance)
                if n_out == 0 or x - out[n_out - 1] > x_tolerance:
                    out[n_out] = x
                    n_out += 1
            continue
        # split between the control polygon's first two crossings, where the piece most likely
        # separates its first root from the next (the midpoint without two crossings)
        t = _split_between_crossings(row, deg)
        for i in range(deg + 1):
            work[i] = row[i]
        left = stack[top + 1]
        left[0] = work[0]
        row[deg] = work[deg]
        for r in range(1, deg + 1):
            for i in range(deg - r + 1):
                work[i] = work[i] + t * (work[i + 1] - work[i])
            left[r] = work[0]
            row[deg - r] = work[deg - r]
        mid = lo + t * (hi - lo)
        left[meta] = lo
        left[meta + 1] = mid
        left[meta + 2] = depth + 1.0
        row[meta] = mid
        row[meta + 1] = hi
        row[meta + 2] = depth + 1.0
        top += 2
    return n_out
