"""The one-bounce test set of tests/solver/test_solver_random.py and its brute-force truth.

Per chain ("R", "T") a fixed-seed set of tuples (planted paths on tilted and sphere-like normal
fields, two-path tuples, random endpoints, near-TIR refraction; see that test's docstring) and the
paths tests/reference/bruteforce.py finds in them, computed once per process.  Also used by
test_solver_baselines.py, test_solver_curve_walk.py and bench/stability.py.
"""
from __future__ import annotations

import time

import numpy as np

from reference import bruteforce as bf

SEED = 20240805
MATCH_TOL = 1e-6  # |delta uv| to call a solver path and a brute-force path the same
FALSE_TOL = 1e-6  # direction residual above which a solver path is false
RECALL_MARGIN = 1e-7  # brute-force paths closer than this to an edge are not required
GRAZE_MARGIN = 1e-4  # ... nor those with cos_i below this
TIR_MARGIN = 1e-6  # ... nor T paths with k = 1 - r^2 sin^2 below this
SIGMA_MARGIN = 1e-5  # ... nor ill-conditioned (near-double) roots: sigma_min(dF/duv) below this
DUP_TOL = 1e-9  # two solver rows whose polished roots are this close are one path
POLISH_TOL = 1e-7  # a well-conditioned solver path must lie this close (uv) to a root of eq. 3

COUNTS = {
    "R": dict(planted_tilt=3500, planted_sphere=1500, two_path=2000, random=3000),
    "T": dict(planted_tilt=2500, planted_sphere=1000, two_path=2000, random=2500, near_tir=2000),
}


# ----------------------------------------------------------------------------------------------
# generators
# ----------------------------------------------------------------------------------------------
def mixed_normals(rng, P, sphere_frac):
    n = len(P)
    N = bf.random_normals(rng, P, "tilt", max_tilt_deg=45.0)
    curv = rng.choice([-1.0, 1.0], n) * rng.uniform(1.0, 2.5, n)
    Ns = bf.random_normals(rng, P, "sphere", curvature=curv)
    sph = rng.random(n) < sphere_frac
    N[sph] = Ns[sph]
    return N


def _gen_planted(rng, chain, n, sphere_frac):
    P = bf.random_triangles(rng, n)
    N = mixed_normals(rng, P, sphere_frac)
    eta = bf.random_eta(rng, n)
    x0, x2, uv, ok = bf.plant_paths(rng, chain, P, N, eta, dist_log10=(-0.7, 2.5))
    assert ok.all()
    return P, N, eta, x0, x2, uv


def _gen_two_path(rng, chain, n):
    Ps, Ns, es, x0s, x2s, u1s, u2s = [], [], [], [], [], [], []
    have = 0
    while have < n:
        m = 4000
        P = bf.random_triangles(rng, m)
        N = mixed_normals(rng, P, 0.85)
        eta = bf.random_eta(rng, m)
        x0, x2, uv1, uv2, ok = bf.plant_two_paths(
            rng, chain, P, N, eta, n_dir=8, n_tau=24, dist_log10=(-0.5, 1.5)
        )
        ok &= np.abs(uv1 - uv2).max(1) > 1e-4
        for lst, arr in zip((Ps, Ns, es, x0s, x2s, u1s, u2s), (P, N, eta, x0, x2, uv1, uv2)):
            lst.append(arr[ok])
        have += ok.sum()
    cat = [np.concatenate(l_)[:n] for l_ in (Ps, Ns, es, x0s, x2s, u1s, u2s)]
    return cat


def _gen_random(rng, chain, n):
    P = bf.random_triangles(rng, n)
    N = mixed_normals(rng, P, 0.4)
    eta = bf.random_eta(rng, n)
    size = bf.tri_size(P)
    c = P.mean(1)
    spread = size * 10.0 ** rng.uniform(0.0, 1.5, n)
    x0 = c + spread[:, None] * rng.uniform(-1, 1, (n, 3))
    x2 = c + spread[:, None] * rng.uniform(-1, 1, (n, 3))
    return P, N, eta, x0, x2


def _gen_near_tir(rng, n):
    """Refraction with r = eta_i/eta_t > 1 at incidence close to the critical angle."""
    P = bf.random_triangles(rng, n)
    N = mixed_normals(rng, P, 0.3)
    inside = rng.random(n) < 0.85  # x0 in the medium (s = -1) with eta > 1 ...
    eta = np.where(inside, rng.uniform(1.1, 2.5, n), rng.uniform(0.6, 0.95, n))  # ... or eta < 1
    side = np.where(inside, -1.0, 1.0)
    r = np.where(inside, eta, 1.0 / eta)
    eps = 10.0 ** rng.uniform(-7, -1, n)
    theta = np.arcsin((1.0 - eps) / r)
    x0 = np.zeros((n, 3))
    x2 = np.zeros((n, 3))
    for sgn in (-1.0, 1.0):
        sel = side == sgn
        a, b, _, ok = bf.plant_paths(
            rng, "T", P[sel], N[sel], eta[sel], side=sgn, theta=theta[sel], dist_log10=(-0.5, 2.0)
        )
        # rows that could not be planted (outgoing grazing ray on the wrong side of the
        # geometric plane) fall back to an ordinary planted path
        if not ok.all():
            a2, b2, _, ok2 = bf.plant_paths(rng, "T", P[sel][~ok], N[sel][~ok], eta[sel][~ok], side=sgn)
            a[~ok], b[~ok] = a2, b2
        x0[sel], x2[sel] = a, b
    # half of them: push x0 sideways so the old planted point would now be past critical
    push = rng.random(n) < 0.5
    size = bf.tri_size(P)
    fn, _ = bf._unit(np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]))
    dv = x0 - P.mean(1)
    tang, _ = bf._unit(dv - fn * np.einsum("ij,ij->i", dv, fn)[:, None])  # away from the triangle
    amount = size * 10.0 ** rng.uniform(-4, -1, n)
    x0 = np.where(push[:, None], x0 + amount[:, None] * np.nan_to_num(tang), x0)
    return P, N, eta, x0, x2


def make_dataset(chain, counts=None, seed=SEED):
    """All tuples of one chain: dict with P (n,1,3,3), N, eta (n,), x0, x2, cat (n,) str, and
    planted uv lists for the planted categories (uv1, uv2: NaN where none)."""
    counts = counts or COUNTS[chain]
    rng = np.random.default_rng([seed, ord(chain)])
    parts = []
    for cat, n in counts.items():
        uv1 = np.full((n, 2), np.nan)
        uv2 = np.full((n, 2), np.nan)
        if cat == "planted_tilt":
            P, N, eta, x0, x2, uv1 = _gen_planted(rng, chain, n, 0.0)
        elif cat == "planted_sphere":
            P, N, eta, x0, x2, uv1 = _gen_planted(rng, chain, n, 1.0)
        elif cat == "two_path":
            P, N, eta, x0, x2, uv1, uv2 = _gen_two_path(rng, chain, n)
        elif cat == "random":
            P, N, eta, x0, x2 = _gen_random(rng, chain, n)
        elif cat == "near_tir":
            P, N, eta, x0, x2 = _gen_near_tir(rng, n)
        else:
            raise ValueError(cat)
        parts.append(dict(P=P, N=N, eta=eta, x0=x0, x2=x2, uv1=uv1, uv2=uv2, cat=np.full(n, cat, dtype=object)))
    out = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    out["P"] = out["P"][:, None].copy()
    out["N"] = out["N"][:, None].copy()
    out["chain"] = chain
    return out


# ----------------------------------------------------------------------------------------------
# fixtures (module cache: data + brute force computed once per chain)
# ----------------------------------------------------------------------------------------------
_CACHE: dict = {}


def dataset_with_truth(chain):
    if chain not in _CACHE:
        t = time.time()
        d = make_dataset(chain)
        tg = time.time() - t
        t = time.time()
        ti, uv, chk = bf.solve_bruteforce(chain, d["x0"], d["x2"], d["P"], d["N"], d["eta"], return_all=True)
        sig = bf.root_sigma_min(chain, d["x0"][ti], d["x2"][ti], d["P"][ti], d["N"][ti], d["eta"][ti], uv)
        tb = time.time() - t
        d.update(bf_t=ti, bf_uv=uv, bf_chk=chk, bf_sigma=sig, t_gen=tg, t_bf=tb)
        _CACHE[chain] = d
    return _CACHE[chain]


def match_paths(ta, ua, tb, ub, tol=MATCH_TOL):
    """For every row of (ta, ua): index of a row of (tb, ub) with same tuple and |duv| < tol, or -1."""
    out = np.full(len(ta), -1, np.int64)
    if len(tb) == 0 or len(ta) == 0:
        return out
    order = np.argsort(tb, kind="stable")
    tbs = tb[order]
    lo = np.searchsorted(tbs, ta, "left")
    hi = np.searchsorted(tbs, ta, "right")
    for i in np.flatnonzero(hi > lo):
        cand = order[lo[i] : hi[i]]
        dist = np.abs(ub[cand] - ua[i]).max(1)
        j = np.argmin(dist)
        if dist[j] < tol:
            out[i] = cand[j]
    return out
