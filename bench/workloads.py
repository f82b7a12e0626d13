"""Deterministic tuple workloads for the solver benchmarks.

Two distributions per chain, both with strongly varying interpolated normals (vertex
normals tilted ~0.3 rad-ish off the face normal):

* ``random``: random triangles and random endpoints, the raw input of an unculled solver;
  most tuples have no path and many fail the cheap side tests.
* ``planted``: every tuple is built around a true path (random point on the triangle,
  x0 on a random side, x2 along the exactly reflected / refracted ray), so every tuple
  exercises the whole pipeline; some also carry a second path.
"""

import numpy as np


def _normalize(a):
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def random_tuples(n, seed=0, tilt=0.3):
    rng = np.random.default_rng(seed)
    P = rng.normal(size=(n, 1, 3, 3))
    ng = _normalize(np.cross(P[:, 0, 1] - P[:, 0, 0], P[:, 0, 2] - P[:, 0, 0]))
    N = _normalize(ng[:, None, :] + tilt * rng.normal(size=(n, 3, 3)))[:, None]
    x0 = rng.normal(size=(n, 3)) * 3.0
    x2 = rng.normal(size=(n, 3)) * 3.0
    return x0, x2, P, N


def planted_tuples(n, chain, eta=1.5, seed=0, tilt=0.6):
    """Tuples that each contain the returned planted path (u, v); returns fewer than n
    when a drawn configuration is geometrically invalid (those are dropped)."""
    rng = np.random.default_rng(seed)
    P = rng.normal(size=(n, 3, 3))
    ng = _normalize(np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]))
    N = _normalize(ng[:, None, :] + tilt * rng.normal(size=(n, 3, 3)))
    bary = rng.dirichlet([1.0, 1.0, 1.0], size=n)
    u, v = bary[:, 1], bary[:, 2]
    x1 = P[:, 0] + u[:, None] * (P[:, 1] - P[:, 0]) + v[:, None] * (P[:, 2] - P[:, 0])
    nh = _normalize(N[:, 0] + u[:, None] * (N[:, 1] - N[:, 0]) + v[:, None] * (N[:, 2] - N[:, 0]))
    ngo = np.where((np.sum(ng * nh, 1) < 0)[:, None], -ng, ng)
    side = rng.choice([-1.0, 1.0], size=n) if chain == "T" else np.ones(n)
    w = _normalize(rng.normal(size=(n, 3)))
    w = w * np.sign(np.sum(w * ngo, 1) * side)[:, None]
    x0 = x1 + w * rng.uniform(0.5, 5.0, size=(n, 1))
    wi = _normalize(x1 - x0)
    no = nh * side[:, None]
    c = -np.sum(wi * no, 1)
    if chain == "R":
        wo = wi + 2.0 * c[:, None] * no
        ok = c > 0
    else:
        r = np.where(side > 0, 1.0 / eta, eta)
        k = 1.0 - r * r * (1.0 - c * c)
        ok = (c > 0) & (k > 0)
        wo = r[:, None] * wi + (r * c - np.sqrt(np.maximum(k, 0.0)))[:, None] * no
    x2 = x1 + wo * rng.uniform(0.5, 5.0, size=(n, 1))
    s_in = np.sum((x0 - x1) * ngo, 1)
    s_out = np.sum((x2 - x1) * ngo, 1)
    ok &= (s_in * s_out > 0) if chain == "R" else (s_in * s_out < 0)
    return x0[ok], x2[ok], P[ok][:, None], N[ok][:, None], np.column_stack([u, v])[ok]


def planted_recall(tuple_index, uv, planted_uv, tol=1e-6):
    """Fraction of planted paths the solver returned (matched within tol in (u, v))."""
    found = np.zeros(planted_uv.shape[0], dtype=bool)
    close = np.abs(uv - planted_uv[tuple_index]).sum(axis=1) < tol
    found[tuple_index[close]] = True
    return float(found.mean())
