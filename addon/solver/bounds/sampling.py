"""Bound-driven sampling of triangle tuples (Fan et al. 2025 §5).

For one shading point (texel) with candidate tuples U and per-tuple bounds Ẽ(T) (eq 21),
each tuple is selected independently with probability P_T = min(γ Ẽ(T), 1) (eq 28) and the
estimator <E> = Σ_{T selected} E(T) / P_T (eq 24, Algorithm 1) is unbiased whenever P_T > 0
for every tuple with E(T) > 0, i.e. whenever Ẽ(T) >= E(T) > 0 and γ > 0.  γ = ∞ enumerates
(P = 1 for every tuple with Ẽ > 0).  The variance is bounded by Σ Ẽ²/P − μ² (eq 25).

γ is chosen from a user-facing quality setting (§5.4): the expected number of selected tuples
W = Σ_T min(γ Ẽ(T), 1) (monotone in γ, solved by bisection), or a target on the variance
bound Σ_T Ẽ(T)² / P_T (monotone decreasing in γ).  Plain numpy: this runs per texel list in
the bake, not in the bound precompute.
"""

import numpy as np


def selection_probability(E_bound, gamma):
    """P_T = min(γ Ẽ(T), 1) (eq 28); γ = inf gives 1 for Ẽ > 0 (enumeration), Ẽ = inf gives 1."""
    E_bound = np.asarray(E_bound, dtype=np.float64)
    if np.isinf(gamma):
        return (E_bound > 0).astype(np.float64)
    with np.errstate(invalid="ignore"):
        p = np.minimum(gamma * E_bound, 1.0)
    return np.where(np.isnan(p), 1.0, p)


def sample_tuples(E_bound, gamma, rng):
    """Algorithm 1: independent selection; returns (selected mask, P)."""
    p = selection_probability(E_bound, gamma)
    return rng.random(p.shape) < p, p


def estimate(E_true, E_bound, gamma, rng):
    """One estimate <E> = Σ_selected E(T)/P_T (eq 24) and the number of tuples solved."""
    sel, p = sample_tuples(E_bound, gamma, rng)
    return float(np.sum(np.asarray(E_true)[sel] / p[sel])), int(sel.sum())


def expected_count(E_bound, gamma):
    """W(γ) = E[|S|] = Σ P_T (§5.4)."""
    return float(selection_probability(E_bound, gamma).sum())


def variance_bound(E_bound, gamma):
    """Bound of the estimator's variance.  With independent selections (Algorithm 1) the
    variance is exactly Σ E(T)² (1 - P_T)/P_T, so Σ Ẽ² (1 - P_T)/P_T bounds it (tighter than
    μ̄2 = Σ Ẽ²/P_T of eq 25, and finite when tuples with Ẽ = inf are always taken: P = 1)."""
    E_bound = np.asarray(E_bound, dtype=np.float64)
    p = selection_probability(E_bound, gamma)
    keep = (E_bound > 0) & (p < 1.0)
    return float(np.sum(E_bound[keep] ** 2 * (1.0 - p[keep]) / p[keep]))


def gamma_for_expected_count(E_bound, W, iterations=200):
    """The γ with Σ min(γẼ, 1) = W (§5.4); inf when W >= the number of tuples with Ẽ > 0."""
    E_bound = np.asarray(E_bound, dtype=np.float64)
    positive = E_bound[E_bound > 0]
    if W >= positive.size:
        return np.inf
    if W <= 0:
        return 0.0
    finite = positive[np.isfinite(positive)]
    if W <= positive.size - finite.size:  # infinite bounds are always taken
        return 0.0
    lo, hi = 0.0, 1.0 / finite.min()
    while expected_count(E_bound, hi) < W:
        hi *= 2.0
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        if expected_count(E_bound, mid) < W:
            lo = mid
        else:
            hi = mid
    return hi


def gamma_for_variance(E_bound, target, iterations=200):
    """The smallest γ whose variance bound (:func:`variance_bound`, eq 25) is <= target (§5.4); inf for target <= 0."""
    E_bound = np.asarray(E_bound, dtype=np.float64)
    if target <= 0.0:
        return np.inf
    lo, hi = 0.0, 1.0
    while variance_bound(E_bound, hi) > target:
        hi *= 2.0
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        if mid == 0.0 or variance_bound(E_bound, mid) > target:
            lo = mid
        else:
            hi = mid
    return hi
