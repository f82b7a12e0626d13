"""Bivariate polynomials in (u, v): p[i, j] multiplies u^i v^j in a square float64 array,
the total degree tracked by the caller.  Products, sums, 3-vectors of polynomials (dot and
cross products, with constant vectors too), the u-degree, and a Bernstein-form test for a
zero on [0, 1]².

The algebra in which the two-bounce solver builds its constraint system (Fan et al. 2024,
§3.4, Table 3: ``spoly/two_bounce/system.py``); tested through it in
tests/solver/test_solver_two_bounce.py.
"""

import math

from ..runtime.jit import kernel
from ..runtime.simd import rows_add_scaled_exact


@kernel
def bzero(p, d):
    for i in range(d + 1):
        for j in range(d + 1 - i):
            p[i, j] = 0.0


@kernel
def bmul_acc(p, dp, q, dq, out, coef):
    """out += coef p q (out must be sized for total degree dp + dq)."""
    for i1 in range(dp + 1):
        for j1 in range(dp + 1 - i1):
            c = p[i1, j1]
            if c == 0.0:
                continue
            c *= coef
            for i2 in range(dq + 1):
                rows_add_scaled_exact(out[i1 + i2, j1:], q[i2], c, dq + 1 - i2)


@kernel
def badd(out, d, a, da, ca):
    """out += ca a (da ≤ d)."""
    for i in range(da + 1):
        rows_add_scaled_exact(out[i], a[i], ca, da + 1 - i)


@kernel
def vlin(V, c0, cu, cv):
    """Vector polynomial of degree 1: c0 + u cu + v cv."""
    for c in range(3):
        bzero(V[c], 1)
        V[c, 0, 0] = c0[c]
        V[c, 1, 0] = cu[c]
        V[c, 0, 1] = cv[c]


@kernel
def vdot(A, dA, B, dB, out):
    d = dA + dB
    bzero(out, d)
    for c in range(3):
        bmul_acc(A[c], dA, B[c], dB, out, 1.0)
    return d


@kernel
def vcross(A, dA, B, dB, out):
    d = dA + dB
    for c in range(3):
        bzero(out[c], d)
    for c in range(3):
        c1 = (c + 1) % 3
        c2 = (c + 2) % 3
        bmul_acc(A[c1], dA, B[c2], dB, out[c], 1.0)
        bmul_acc(A[c2], dA, B[c1], dB, out[c], -1.0)
    return d


@kernel
def vdot_const(A, dA, w, out):
    bzero(out, dA)
    for c in range(3):
        badd(out, dA, A[c], dA, w[c])
    return dA


@kernel
def vcross_const(A, dA, w, out):
    """out = A × w."""
    for c in range(3):
        bzero(out[c], dA)
    for c in range(3):
        c1 = (c + 1) % 3
        c2 = (c + 2) % 3
        badd(out[c], dA, A[c1], dA, w[c2])
        badd(out[c], dA, A[c2], dA, -w[c1])
    return dA


@kernel
def bmax(p, d):
    m = 0.0
    for i in range(d + 1):
        for j in range(d + 1 - i):
            m = max(m, abs(p[i, j]))
    return m


@kernel
def u_degree(p, d, tiny):
    """Largest i with a coefficient above tiny in row i; smaller rows are zeroed."""
    n = d
    while n > 0:
        big = 0.0
        for j in range(d - n + 1):
            big = max(big, abs(p[n, j]))
        if big > tiny:
            break
        for j in range(d - n + 1):
            p[n, j] = 0.0
        n -= 1
    return n


@kernel
def bernstein_has_zero(p, d, rel_margin, work):
    """False when p (total degree d) provably has no zero on the triangle u, v ≥ 0, u+v ≤ 1:
    all triangular Bernstein coefficients share one sign by more than rel_margin · max."""
    lo = math.inf
    hi = -math.inf
    big = 0.0
    # falling factorial ratios via work[0]: log-free direct products (d ≤ 16 here)
    for i in range(d + 1):
        for j in range(d + 1 - i):
            acc = 0.0
            fi = 1.0  # i! / (i - i')!
            for i2 in range(i + 1):
                fj = 1.0
                # (d - i2 - j2)! / d!  = 1 / (d (d-1) ... (d - i2 - j2 + 1))
                g = 1.0
                for t in range(i2):
                    g /= (d - t)
                for j2 in range(j + 1):
                    c = p[i2, j2]
                    if c != 0.0:
                        acc += c * fi * fj * g
                    fj *= (j - j2)
                    if d - i2 - j2 > 0:
                        g /= (d - i2 - j2)
                fi *= (i - i2)
            lo = min(lo, acc)
            hi = max(hi, acc)
            big = max(big, abs(acc))
    margin = rel_margin * big
    return not (lo > margin or hi < -margin)
