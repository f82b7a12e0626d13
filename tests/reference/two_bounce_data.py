"""Random two-bounce tuples for the tests (plain numpy; builds on tests/reference/bruteforce.py).

* :func:`plant_two_bounce` -- a path planted through both triangles: vertex 1 as in
  ``bf.plant_paths`` (x0 on a random side, random incidence), the scattered ray followed a
  random distance to x2, a random triangle 2 placed so that x2 is a random point of it, the
  ray scattered again at x2 (its incoming side from the geometry) and x3 put along it.
* :func:`random_two_bounce` -- random triangle 2 near triangle 1 and random endpoints
  (mostly no path).
"""
from __future__ import annotations

import numpy as np

from reference import bruteforce as bf


def _normals(rng, P, sphere_frac, max_tilt=45.0):
    n = len(P)
    N = bf.random_normals(rng, P, "tilt", max_tilt_deg=max_tilt)
    curv = rng.choice([-1.0, 1.0], n) * rng.uniform(1.0, 2.5, n)
    Ns = bf.random_normals(rng, P, "sphere", curvature=curv)
    sph = rng.random(n) < sphere_frac
    N[sph] = Ns[sph]
    return N


def _shapes(rng, n, size):
    """Random triangles centred at 0 with sqrt(2 area) = size."""
    T = bf.random_triangles(rng, n, offset_frac=0.0)
    T = T - T.mean(1, keepdims=True)
    s = bf.tri_size(T)
    return T * (size / s)[:, None, None]


def plant_two_bounce(rng, chain, n, sphere_frac=0.3, dist1=(-0.7, 1.5), dist2=(-0.5, 1.5), size2=(-0.5, 0.7),
                     max_theta_deg=80.0, eta=None, max_tilt=45.0):
    """n tuples, each with a planted contract-valid two-bounce path.

    Returns dict x0, x3, P (n,2,3,3), N (n,2,3,3), eta (n,), uv (n,4)."""
    out = dict(x0=np.zeros((n, 3)), x3=np.zeros((n, 3)), P=np.zeros((n, 2, 3, 3)), N=np.zeros((n, 2, 3, 3)),
               eta=np.zeros(n), uv=np.zeros((n, 4)))
    filled = 0
    while filled < n:
        m = 2 * (n - filled) + 32
        P1 = bf.random_triangles(rng, m)
        N1 = _normals(rng, P1, sphere_frac, max_tilt)
        et = bf.random_eta(rng, m) if eta is None else np.full(m, float(eta))
        x0, xa, uv1, ok = bf.plant_paths(rng, chain[0], P1, N1, et, dist_log10=dist1, max_theta_deg=max_theta_deg)
        size1 = bf.tri_size(P1)
        x1, _, _, _ = bf.interpolate(P1, N1, uv1[:, 0], uv1[:, 1])
        wo1, _ = bf._unit(xa - x1)
        d1 = size1 * 10.0 ** rng.uniform(*dist1, m)
        x2 = x1 + d1[:, None] * wo1
        T = _shapes(rng, m, size1 * 10.0 ** rng.uniform(*size2, m))
        a = rng.random((m, 2))
        f = a.sum(1) > 1
        a[f] = 1 - a[f]
        xt = T[:, 0] + a[:, :1] * (T[:, 1] - T[:, 0]) + a[:, 1:] * (T[:, 2] - T[:, 0])
        P2 = T + (x2 - xt)[:, None, :]
        N2 = _normals(rng, P2, sphere_frac, max_tilt)
        _, nh2, ng2, _ = bf.interpolate(P2, N2, a[:, 0], a[:, 1])
        s2 = np.sign(bf._dot(x1 - x2, ng2))
        w_exp, cos_i, kk = bf.scatter(chain[1], wo1, nh2, s2, et)
        w_exp, _ = bf._unit(w_exp)
        so = s2 * bf._dot(w_exp, ng2)
        side2 = so > 0 if chain[1] == "R" else so < 0
        d2 = bf.tri_size(P2) * 10.0 ** rng.uniform(*dist2, m)
        x3 = x2 + d2[:, None] * w_exp
        uv = np.concatenate([uv1, a], 1)
        P = np.stack([P1, P2], 1)
        N = np.stack([N1, N2], 1)
        good = ok & (s2 != 0) & (cos_i > 1e-3) & (kk > 0) & side2 & np.isfinite(x3).all(1)
        if good.any():
            chk = bf.check_path(chain, x0[good], x3[good], P[good], N[good], et[good], uv[good])
            idx = np.flatnonzero(good)
            good[idx[~chk.valid]] = False
        g = np.flatnonzero(good)[: n - filled]
        sl = slice(filled, filled + len(g))
        out["x0"][sl], out["x3"][sl], out["P"][sl], out["N"][sl] = x0[g], x3[g], P[g], N[g]
        out["eta"][sl], out["uv"][sl] = et[g], uv[g]
        filled += len(g)
    return out


def random_two_bounce(rng, chain, n, sphere_frac=0.3):
    """Random triangle pairs (triangle 2 a few sizes away) and random endpoints."""
    P1 = bf.random_triangles(rng, n)
    size1 = bf.tri_size(P1)
    c1 = P1.mean(1)
    dirn = bf._random_unit(rng, n)
    c2 = c1 + (size1 * 10.0 ** rng.uniform(0.0, 1.3, n))[:, None] * dirn
    P2 = _shapes(rng, n, size1 * 10.0 ** rng.uniform(-0.3, 0.5, n)) + c2[:, None, :]
    N1 = _normals(rng, P1, sphere_frac)
    N2 = _normals(rng, P2, sphere_frac)
    spread = size1 * 10.0 ** rng.uniform(0.3, 1.5, n)
    mid = 0.5 * (c1 + c2)
    x0 = mid + spread[:, None] * rng.uniform(-1, 1, (n, 3))
    x3 = mid + spread[:, None] * rng.uniform(-1, 1, (n, 3))
    return dict(x0=x0, x3=x3, P=np.stack([P1, P2], 1), N=np.stack([N1, N2], 1), eta=bf.random_eta(rng, n),
                uv=np.full((n, 4), np.nan))
