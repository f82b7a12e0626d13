"""γ-sampling of triangle tuples (Fan et al. 2025 §5, eq 24–28): unbiased, variance falls as γ grows."""

import numpy as np

from addon.solver.bounds import sampling as G


def _texel(rng, n=60):
    E = rng.lognormal(-2.0, 1.5, n)
    E[rng.random(n) < 0.3] = 0.0                       # tuples whose bound covers the texel but have no path
    bound = np.maximum(E, 1e-3) * rng.uniform(1.0, 8.0, n)  # conservative bounds Ẽ >= E
    bound[:2] = np.inf                                  # unbounded pieces (focal points) are always taken
    return E, bound


def test_estimator_is_unbiased_and_variance_falls_with_gamma():
    rng = np.random.default_rng(7)
    E, bound = _texel(rng)
    exact = E.sum()
    assert G.estimate(E, bound, np.inf, rng)[0] == exact   # γ = ∞ enumerates
    variances = []
    for W in (5, 10, 20, 40):
        gamma = G.gamma_for_expected_count(bound, W)
        assert abs(G.expected_count(bound, gamma) - W) < 1e-6
        runs = np.array([G.estimate(E, bound, gamma, rng)[0] for _ in range(20000)])
        se = runs.std(ddof=1) / np.sqrt(runs.size)
        print(f"W={W}: gamma={gamma:.4g} mean={runs.mean():.5f} exact={exact:.5f} se={se:.2e} var={runs.var():.3e}")
        assert abs(runs.mean() - exact) < 3 * se
        assert runs.var() <= 1.1 * G.variance_bound(bound, gamma)  # eq 25 (sample variance, 10% slack)
        variances.append(runs.var())
    assert all(a > b for a, b in zip(variances, variances[1:]))


def test_gamma_from_variance_target():
    rng = np.random.default_rng(3)
    E, bound = _texel(rng)
    finite = np.isfinite(bound)
    target = 4.0 * np.sum(bound[finite]) ** 2
    gamma = G.gamma_for_variance(bound, target)
    assert G.variance_bound(bound, gamma) <= target * (1 + 1e-9)
    assert G.variance_bound(bound, gamma * 0.99) > target * (1 - 1e-6)
    assert G.gamma_for_variance(bound, 0.0) == np.inf
