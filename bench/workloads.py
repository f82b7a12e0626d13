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


def random_pairs(n, rng=None, emitters=65536):
    """A table of ``emitters`` random emitter rows and as many random points (``random_tuples``,
    seed 4) and n random int32 (emitter, point) pairs over them, drawn from ``rng`` (default: a
    fresh generator of seed 3): (x0, P, N, x2, e, s), the tuples of ``spoly.api.TupleTable``."""
    rng = np.random.default_rng(3) if rng is None else rng
    x0, x2, P, N = random_tuples(emitters, seed=4)
    e = rng.integers(0, emitters, n, dtype=np.int32)
    s = rng.integers(0, emitters, n, dtype=np.int32)
    return x0, P, N, x2, e, s


def planted_pairs(n, chain):
    """``planted_tuples(n, chain, seed=1)`` as a table with each emitter paired with its own
    point: (x0, P, N, x2, e, s), e = s = 0..m-1 (int32)."""
    x0, x2, P, N, _ = planted_tuples(n, chain, seed=1)
    index = np.arange(x0.shape[0], dtype=np.int32)
    return x0, P, N, x2, index, index


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


def _scatter(wi, nh, side, eta, refract):
    """Contract vertex rule (side: +1 light from the normal's side)."""
    no = nh * side[:, None]
    c = -np.sum(wi * no, 1)
    if not refract:
        return wi + 2.0 * c[:, None] * no, c > 0
    r = np.where(side > 0, 1.0 / eta, eta)
    k = 1.0 - r * r * (1.0 - c * c)
    wo = r[:, None] * wi + (r * c - np.sqrt(np.maximum(k, 0.0)))[:, None] * no
    return wo, (c > 0) & (k > 0)


def planted_two_bounce(n, chain, eta=1.5, seed=0, tilt=0.4):
    """Two-bounce tuples (x0, x3, P (m,2,3,3), N, uv (m,4)) each built around a true path: a
    random point on triangle 1 lit from a random direction, the scattered ray followed to a
    random point of a random triangle 2 placed there, scattered again, x3 along that ray.
    Drawn configurations that break a side rule are dropped (fewer than n come back)."""
    rng = np.random.default_rng(seed)
    tris, norms, bary, pts = [], [], [], []
    for _ in range(2):
        P = rng.normal(size=(n, 3, 3))
        ng = _normalize(np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]))
        N = _normalize(ng[:, None, :] + tilt * rng.normal(size=(n, 3, 3)))
        b = rng.dirichlet([1.0, 1.0, 1.0], size=n)
        tris.append(P)
        norms.append(N)
        bary.append(b)
    def point(P, N, b):
        x = P[:, 0] + b[:, 1:2] * (P[:, 1] - P[:, 0]) + b[:, 2:3] * (P[:, 2] - P[:, 0])
        nh = _normalize(N[:, 0] + b[:, 1:2] * (N[:, 1] - N[:, 0]) + b[:, 2:3] * (N[:, 2] - N[:, 0]))
        ng = _normalize(np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]))
        ng = np.where((np.sum(ng * nh, 1) < 0)[:, None], -ng, ng)
        return x, nh, ng
    x1, nh1, ng1 = point(tris[0], norms[0], bary[0])
    side1 = rng.choice([-1.0, 1.0], size=n)
    w = _normalize(rng.normal(size=(n, 3)))
    w = w * np.sign(np.sum(w * ng1, 1) * side1)[:, None]
    x0 = x1 + w * rng.uniform(1.0, 5.0, size=(n, 1))
    wi = _normalize(x1 - x0)
    s1 = np.sign(np.sum((x0 - x1) * ng1, 1))
    wo1, ok = _scatter(wi, nh1, s1, eta, chain[0] == "T")
    wo1 = _normalize(wo1)
    so1 = s1 * np.sum(wo1 * ng1, 1)
    ok &= (so1 > 0) if chain[0] == "R" else (so1 < 0)
    x2 = x1 + wo1 * rng.uniform(1.0, 5.0, size=(n, 1))
    # move triangle 2 so that its barycentric point lands on x2
    xt, _, _ = point(tris[1], norms[1], bary[1])
    tris[1] = tris[1] + (x2 - xt)[:, None, :]
    _, nh2, ng2 = point(tris[1], norms[1], bary[1])
    s2 = np.sign(np.sum((x1 - x2) * ng2, 1))
    wo2, ok2 = _scatter(wo1, nh2, s2, eta, chain[1] == "T")
    wo2 = _normalize(wo2)
    so2 = s2 * np.sum(wo2 * ng2, 1)
    ok &= ok2 & (s2 != 0) & ((so2 > 0) if chain[1] == "R" else (so2 < 0))
    x3 = x2 + wo2 * rng.uniform(1.0, 5.0, size=(n, 1))
    P = np.stack(tris, 1)
    N = np.stack(norms, 1)
    uv = np.column_stack([bary[0][:, 1:], bary[1][:, 1:]])
    return x0[ok], x3[ok], P[ok], N[ok], uv[ok]


def random_two_bounce(n, seed=0, tilt=0.3):
    """Random triangle pairs and endpoints (the raw input of an unculled solver)."""
    rng = np.random.default_rng(seed)
    P = rng.normal(size=(n, 2, 3, 3))
    P[:, 1] += rng.normal(size=(n, 1, 3)) * 3.0
    ng = _normalize(np.cross(P[:, :, 1] - P[:, :, 0], P[:, :, 2] - P[:, :, 0]))
    N = _normalize(ng[:, :, None, :] + tilt * rng.normal(size=(n, 2, 3, 3)))
    x0 = rng.normal(size=(n, 3)) * 3.0
    x3 = rng.normal(size=(n, 3)) * 3.0
    return x0, x3, P, N
