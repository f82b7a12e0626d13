"""The written-out products of addon/solver/polynomials/small_products.py: the generated section
is what generated_source() gives; each product matches an exact (rational) product to rounding,
and the scatter loop it replaces bit for bit (its terms are summed in that loop's order)."""
from fractions import Fraction

import numpy as np

from addon.solver.polynomials import small_products
from addon.solver.polynomials.small_products import GENERATED_MARKER, generated_source, mul_quadratic_quartic, mul_quadratics


def _random_poly(rng, degree):
    p = np.zeros((7, 7))
    for i in range(degree + 1):
        for j in range(degree + 1 - i):
            p[i, j] = rng.normal() * 10.0 ** rng.integers(-3, 4)
    return p


def _scatter_product(p, dp, q, dq):
    out = np.zeros((7, 7))
    for i1 in range(dp + 1):
        for j1 in range(dp + 1 - i1):
            for i2 in range(dq + 1):
                for j2 in range(dq + 1 - i2):
                    out[i1 + i2, j1 + j2] += p[i1, j1] * q[i2, j2]
    return out


def _exact_product(p, dp, q, dq):
    out = [[Fraction(0)] * 7 for _ in range(7)]
    size = np.zeros((7, 7))
    for i1 in range(dp + 1):
        for j1 in range(dp + 1 - i1):
            for i2 in range(dq + 1):
                for j2 in range(dq + 1 - i2):
                    out[i1 + i2][j1 + j2] += Fraction(p[i1, j1]) * Fraction(q[i2, j2])
                    size[i1 + i2, j1 + j2] += abs(p[i1, j1] * q[i2, j2])
    return np.array([[float(x) for x in r] for r in out]), size


def test_generated_section_is_current():
    source = open(small_products.__file__).read()
    section = source.split("\n" + GENERATED_MARKER + "\n", 1)[1].split('if __name__ == "__main__":', 1)[0]
    assert section.strip() == generated_source().strip()


def test_products_match_exact_and_loop():
    rng = np.random.default_rng(3)
    for _ in range(200):
        for function, dq in ((mul_quadratics, 2), (mul_quadratic_quartic, 4)):
            p = _random_poly(rng, 2)
            q = _random_poly(rng, dq)
            out = np.full((7, 7), np.nan)
            function(p, q, out)
            d = 2 + dq
            mask = np.add.outer(np.arange(7), np.arange(7)) <= d
            exact, size = _exact_product(p, 2, q, dq)
            assert np.all(np.abs(out - exact)[mask] <= 4e-16 * 15 * size[mask])
            assert np.array_equal(out[mask], _scatter_product(p, 2, q, dq)[mask])
            assert np.all(np.isnan(out[~mask]))  # nothing written outside the product's terms
