"""Independent ground truth for specular paths (reference for the tests only).

Written from addon/solver/CONTRACT.md alone; nothing here imports or mirrors addon.solver.
Plain numpy, vectorised over (tuple x seed) rows.

Contents
--------
* vertex rules of the contract: :func:`interpolate`, :func:`scatter`
* :func:`check_path`        -- is (tuple, uv) a valid path per the contract? (any chain length k)
* :func:`solve_bruteforce`  -- dense seeds + Levenberg-Marquardt on the full constraint
                               (eq. 3: h_i x n_i = 0 at every vertex) for chains of any length k
* :func:`trace_one_bounce`  -- forward tracer x0 -> triangle -> receiver plane
* fresnel helpers           -- unpolarised dielectric / conductor Fresnel reflectance
* random tuple generators   -- planted paths, curved mirrors / lenses, plain random, near-TIR

Conventions (CONTRACT.md): P, N are (n, k, 3, 3) [tuple, vertex, corner, xyz]; uv is (n, 2k);
x = p0 + u (p1 - p0) + v (p2 - p0); n = n0 + u (n1 - n0) + v (n2 - n0), normalised;
eta is the IOR behind the surface (normals point away from it).
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

INSIDE_EPS = 1e-9  # contract: u >= -1e-9, v >= -1e-9, u + v <= 1 + 1e-9
DIR_TOL = 1e-7  # contract: |wo - expected| <= 1e-7
DEFLATE_RADII = (1e-4, 5e-4, 2e-3, 1e-2, 5e-2)
DEFLATE_ANGLES = 6


# ----------------------------------------------------------------------------------------
# small vector helpers (last axis = xyz)
# ----------------------------------------------------------------------------------------
def _dot(a, b):
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _cross(a, b):
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _norm(a):
    return np.sqrt(_dot(a, a))


def _unit(a):
    n = _norm(a)
    with np.errstate(invalid="ignore", divide="ignore"):
        return a / n[..., None], n


def _as_eta(eta, n):
    eta = np.asarray(eta, dtype=np.float64)
    if eta.ndim == 0:
        return np.full(n, float(eta))
    return eta.reshape(n)


# ----------------------------------------------------------------------------------------
# the contract's vertex rules
# ----------------------------------------------------------------------------------------
def interpolate(P, N, u, v):
    """Point, normalised interpolated normal and oriented geometric normal.

    P, N: (..., 3, 3); u, v: (...). Returns x, nhat, ng, |n| (all (...,3) / (...)).
    ng = normalize(e1 x e2) flipped so that ng . nhat > 0 (contract).
    """
    p0 = P[..., 0, :]
    e1 = P[..., 1, :] - p0
    e2 = P[..., 2, :] - p0
    x = p0 + u[..., None] * e1 + v[..., None] * e2
    n = N[..., 0, :] + u[..., None] * (N[..., 1, :] - N[..., 0, :]) + v[..., None] * (N[..., 2, :] - N[..., 0, :])
    nhat, nlen = _unit(n)
    ng, _ = _unit(_cross(e1, e2))
    flip = np.where(_dot(ng, nhat) < 0.0, -1.0, 1.0)
    ng = ng * flip[..., None]
    return x, nhat, ng, nlen


def scatter(kind, wi, nhat, s, eta):
    """Expected outgoing direction for incoming unit direction wi (contract rules).

    kind 'R' or 'T'; s = +-1 incoming side (sign((x_prev - x).ng)); eta IOR behind the surface.
    Returns (expected, cos_i, k) with k = 1 - r^2 (1 - cos_i^2) for T (k < 0: TIR), +1 for R.
    """
    n_o = s[..., None] * nhat
    cos_i = -_dot(wi, n_o)
    if kind == "R":
        w = wi + 2.0 * cos_i[..., None] * n_o
        k = np.ones_like(cos_i)
    elif kind == "T":
        r = np.where(s > 0, 1.0 / eta, eta)
        k = 1.0 - r * r * (1.0 - cos_i * cos_i)
        w = r[..., None] * wi + (r * cos_i - np.sqrt(np.maximum(k, 0.0)))[..., None] * n_o
    else:
        raise ValueError(kind)
    return w, cos_i, k


@dataclass
class PathCheck:
    valid: np.ndarray  # (m,) bool: all contract conditions hold (direction within tol)
    residual: np.ndarray  # (m,) max over vertices of |wo - expected|
    inside: np.ndarray  # (m,) bool, contract epsilon
    inside_margin: np.ndarray  # (m,) min over vertices of min(u, v, 1-u-v)
    cos_i: np.ndarray  # (m,) min over vertices of cos_i (shading normal, incoming side)
    k_min: np.ndarray  # (m,) min over T vertices of k (inf when no T vertex)
    sides_ok: np.ndarray  # (m,) bool: every vertex has s != 0 and the outgoing side of its type
    plane_rel: np.ndarray  # (m,) min over vertices of |dist of prev/next to plane| / |segment|
    reason: np.ndarray  # (m,) object: '' when valid, else the first failing check


def _vertex_points(P, uv):
    """x_i for all vertices: P (m,k,3,3), uv (m,2k) -> (m,k,3)."""
    u = uv[:, 0::2]
    v = uv[:, 1::2]
    p0 = P[:, :, 0, :]
    return p0 + u[..., None] * (P[:, :, 1, :] - p0) + v[..., None] * (P[:, :, 2, :] - p0)


def check_path(chain, x_start, x_end, P, N, eta, uv, tol=DIR_TOL, eps=INSIDE_EPS):
    """Independent check of the contract's path validity, for any chain length k.

    x_start, x_end (m,3); P, N (m,k,3,3); eta scalar or (m,); uv (m,2k). Returns PathCheck.
    Everything is computed relative to P[:,0,0] (translation invariance, less cancellation).
    """
    k = len(chain)
    x_start = np.asarray(x_start, np.float64)
    x_end = np.asarray(x_end, np.float64)
    P = np.asarray(P, np.float64)
    N = np.asarray(N, np.float64)
    uv = np.asarray(uv, np.float64).reshape(len(x_start), 2 * k)
    m = len(x_start)
    eta = _as_eta(eta, m)
    origin = P[:, 0, 0, :].copy()
    x_start = x_start - origin
    x_end = x_end - origin
    P = P - origin[:, None, None, :]

    residual = np.zeros(m)
    inside_margin = np.full(m, np.inf)
    cos_min = np.full(m, np.inf)
    k_min = np.full(m, np.inf)
    sides_ok = np.ones(m, bool)
    plane_rel = np.full(m, np.inf)
    reason = np.full(m, "", dtype=object)

    X = _vertex_points(P, uv)
    pts = [x_start] + [X[:, i] for i in range(k)] + [x_end]
    with np.errstate(invalid="ignore", divide="ignore"):
        for i in range(k):
            u = uv[:, 2 * i]
            v = uv[:, 2 * i + 1]
            x, nhat, ng, nlen = interpolate(P[:, i], N[:, i], u, v)
            prev, nxt = pts[i], pts[i + 2]
            wi, li = _unit(x - prev)
            wo, lo = _unit(nxt - x)
            dprev = _dot(prev - x, ng)
            dnext = _dot(nxt - x, ng)
            s = np.sign(dprev)
            w_exp, cos_i, kk = scatter(chain[i], wi, nhat, s, eta)
            if chain[i] == "R":
                side = (s != 0) & (s * dnext > 0)
            else:
                side = (s != 0) & (s * dnext < 0)
                k_min = np.minimum(k_min, np.where(np.isfinite(kk), kk, -np.inf))
            res = _norm(wo - w_exp)
            res = np.where(np.isfinite(res), res, np.inf)
            residual = np.maximum(residual, res)
            inside_margin = np.minimum(inside_margin, np.minimum(np.minimum(u, v), 1.0 - u - v))
            cos_min = np.minimum(cos_min, np.where(np.isfinite(cos_i), cos_i, -np.inf))
            sides_ok &= side
            plane_rel = np.minimum(plane_rel, np.minimum(np.abs(dprev) / li, np.abs(dnext) / lo))
            bad_normal = ~(nlen > 0) | ~np.isfinite(nhat).all(-1) | ~np.isfinite(ng).all(-1)
            for cond, name in (
                (bad_normal, f"v{i}:degenerate"),
                (~side, f"v{i}:side"),
                (~(cos_i > 0), f"v{i}:cos_i<=0"),
                (~(kk >= 0), f"v{i}:TIR"),
                (~(res <= tol), f"v{i}:residual"),
            ):
                reason = np.where((reason == "") & cond, name, reason)
    inside = (uv[:, 0::2] >= -eps).all(1) & (uv[:, 1::2] >= -eps).all(1) & (
        (uv[:, 0::2] + uv[:, 1::2]) <= 1.0 + eps
    ).all(1)
    reason = np.where((reason == "") & ~inside, "outside", reason)
    valid = reason == ""
    return PathCheck(valid, residual, inside, inside_margin, cos_min, k_min, sides_ok, plane_rel, reason)


# ----------------------------------------------------------------------------------------
# brute force: dense seeds + Levenberg-Marquardt on F_i = (b_i wo_i - a_i wi_i) x nhat_i = 0
# ----------------------------------------------------------------------------------------
def barycentric_seeds(n_div=11, margin=0.1):
    """Grid of (u, v) over the triangle enlarged by `margin` (barycentric) on every side."""
    pts = []
    for i in range(n_div + 1):
        for j in range(n_div + 1 - i):
            a, b = i / n_div, j / n_div
            pts.append((a, b))
    g = np.array(pts)
    # map the unit triangle onto the enlarged one: corners (-m,-m), (1+2m,-m), (-m,1+2m)
    return -margin + g * (1.0 + 3.0 * margin)


class _Problem:
    """Rows of the LM problem (one row = tuple x seed x side configuration)."""

    def __init__(self, x0, xe, P, N, a, b):
        self.x0, self.xe = x0, xe  # (M,3)
        self.p0 = P[:, :, 0, :]  # (M,k,3)
        self.e1 = P[:, :, 1, :] - self.p0
        self.e2 = P[:, :, 2, :] - self.p0
        self.n0 = N[:, :, 0, :]
        self.dn1 = N[:, :, 1, :] - self.n0
        self.dn2 = N[:, :, 2, :] - self.n0
        self.a, self.b = a, b  # (M,k): IOR on the incoming / outgoing side of every vertex
        self.k = P.shape[1]

    def take(self, idx):
        new = object.__new__(_Problem)
        for name in ("x0", "xe", "p0", "e1", "e2", "n0", "dn1", "dn2", "a", "b"):
            setattr(new, name, getattr(self, name)[idx])
        new.k = self.k
        return new

    def evaluate(self, theta, jac=True):
        """Residual (M,3k) and optionally Jacobian (M,3k,2k) at theta (M,2k)."""
        k = self.k
        u = theta[:, 0::2]
        v = theta[:, 1::2]
        X = self.p0 + u[..., None] * self.e1 + v[..., None] * self.e2
        n = self.n0 + u[..., None] * self.dn1 + v[..., None] * self.dn2
        nl = _norm(n)
        nh = n / nl[..., None]
        pts = [self.x0] + [X[:, i] for i in range(k)] + [self.xe]
        W, L = [], []
        for j in range(k + 1):
            w, l_ = _unit(pts[j + 1] - pts[j])
            W.append(w)
            L.append(l_)
        M = theta.shape[0]
        r = np.empty((M, 3 * k))
        J = np.zeros((M, 3 * k, 2 * k)) if jac else None
        for i in range(k):
            ai = self.a[:, i][:, None]
            bi = self.b[:, i][:, None]
            wi, wo = W[i], W[i + 1]
            h = bi * wo - ai * wi
            nhi = nh[:, i]
            r[:, 3 * i : 3 * i + 3] = _cross(h, nhi)
            if not jac:
                continue

            def proj(j, d):  # derivative of W[j] when its end point moves by d
                w = W[j]
                return (d - w * _dot(w, d)[:, None]) / L[j][:, None]

            for mv in (i - 1, i, i + 1):  # vertex index (0-based) whose coordinates move
                if mv < 0 or mv >= k:
                    continue
                for c, (E, DN) in enumerate(((self.e1, self.dn1), (self.e2, self.dn2))):
                    d = E[:, mv]
                    # W[i] = wi runs pts[i] -> pts[i+1] (vertex i-1 -> vertex i, 0-based vertex)
                    # W[i+1] = wo runs vertex i -> vertex i+1
                    dh = np.zeros_like(h)
                    if mv == i - 1:
                        dh -= ai * (-proj(i, d))
                    if mv == i:
                        dh -= ai * proj(i, d)
                        dh += bi * (-proj(i + 1, d))
                    if mv == i + 1:
                        dh += bi * proj(i + 1, d)
                    col = _cross(dh, nhi)
                    if mv == i:
                        dnv = DN[:, i]
                        dnh = (dnv - nhi * _dot(nhi, dnv)[:, None]) / nl[:, i][:, None]
                        col = col + _cross(h, dnh)
                    J[:, 3 * i : 3 * i + 3, 2 * mv + c] = col
        return r, J


class _Deflated:
    """Deflation (Farrell et al.): G = (1/|theta - theta*|^2 + 1) F, to find a second root
    next to a known one theta* (close root pairs near folds have tiny Newton basins)."""

    def __init__(self, base, theta_star):
        self.base, self.ts = base, theta_star

    def take(self, idx):
        return _Deflated(self.base.take(idx), self.ts[idx])

    def evaluate(self, theta, jac=True):
        r, J = self.base.evaluate(theta, jac)
        d = theta - self.ts
        q = (d * d).sum(1)
        with np.errstate(all="ignore"):
            Mf = 1.0 / q + 1.0
            out_r = r * Mf[:, None]
            if not jac:
                return out_r, None
            gM = -2.0 * d / (q * q)[:, None]
            out_J = J * Mf[:, None, None] + r[:, :, None] * gM[:, None, :]
        return out_r, out_J


def _lm(prob, theta, max_iter=80, tol_done=1e-14, box=3.0):
    """Vectorised Levenberg-Marquardt. Returns (theta, |r|) for every row."""
    M, nv = theta.shape
    theta = theta.copy()
    rnorm = np.full(M, np.inf)
    lam = np.full(M, 1e-3)
    idx = np.arange(M)  # global rows of the current sub-problem
    live = np.ones(M, bool)  # rows of the sub-problem still iterating
    sub = prob
    th = theta.copy()
    r, J = sub.evaluate(th, jac=True)
    cur = _norm_rows(r)
    eye = np.eye(nv)
    for _ in range(max_iter):
        if nv == 2:
            J0, J1 = J[:, :, 0], J[:, :, 1]
            A00 = (J0 * J0).sum(1)
            A01 = (J0 * J1).sum(1)
            A11 = (J1 * J1).sum(1)
            g0 = (J0 * r).sum(1)
            g1 = (J1 * r).sum(1)
            B00 = A00 * (1.0 + lam) + 1e-300
            B11 = A11 * (1.0 + lam) + 1e-300
            with np.errstate(all="ignore"):
                det = B00 * B11 - A01 * A01
                step = np.stack([-(B11 * g0 - A01 * g1) / det, -(-A01 * g0 + B00 * g1) / det], axis=1)
        else:
            A = np.einsum("mki,mkj->mij", J, J)
            g = np.einsum("mki,mk->mi", J, r)
            diag = np.einsum("mii->mi", A)
            Ad = A + (lam[:, None] * (diag + 1e-30))[:, :, None] * eye
            with np.errstate(all="ignore"):
                step = -np.linalg.solve(Ad + 1e-300 * eye, g[..., None])[..., 0]
        with np.errstate(all="ignore"):
            trial = th + step
            r_t, _ = sub.evaluate(trial, jac=False)
        new = _norm_rows(r_t)
        ok = live & np.isfinite(new) & (new < cur)
        th[ok] = trial[ok]
        cur = np.where(ok, new, cur)
        lam = np.where(ok, np.maximum(lam / 5.0, 1e-12), lam * 8.0)
        stepn = np.abs(step).max(1)
        done = (
            (cur < tol_done)
            | (ok & (stepn < 1e-15))
            | (lam > 1e12)
            | (np.abs(th).max(1) > box)
            | ~np.isfinite(cur)
        )
        live &= ~done
        if not live.any():
            break
        if live.sum() < 0.7 * len(live):
            theta[idx] = th
            rnorm[idx] = cur
            keep = np.flatnonzero(live)
            idx, th, cur, lam = idx[keep], th[keep], cur[keep], lam[keep]
            sub = sub.take(keep)
            live = np.ones(len(idx), bool)
        r, J = sub.evaluate(th, jac=True)
        cur = np.where(live, _norm_rows(r), cur)
    theta[idx] = th
    rnorm[idx] = cur
    return theta, rnorm


def _norm_rows(r):
    out = np.sqrt((r * r).sum(1))
    return np.where(np.isfinite(out), out, np.inf)


def _side_configs(chain):
    """All (incoming, outgoing) IOR assignments: R -> one, T -> 'enter' / 'exit'."""
    opts = [("R",) if c == "R" else ("enter", "exit") for c in chain]
    return list(itertools.product(*opts))


def solve_bruteforce(
    chain,
    x_start,
    x_end,
    P,
    N,
    eta,
    n_div=None,
    margin=0.1,
    res_tol=1e-12,
    dedup=1e-6,
    chunk_rows=200_000,
    check_tol=DIR_TOL,
    max_iter=100,
    return_all=False,
    deflate=True,
):
    """All paths per tuple found by dense-seeded LM on eq. (3); validated by check_path.

    Returns (tuple_index (m,) int64 ascending, uv (m,2k)). With return_all=True also returns the
    PathCheck of the kept rows. For k = 1 the side configuration of each seed is taken from the
    seed's geometry (the side of x0 is a per-triangle constant); for k >= 2 all 2^(#T)
    assignments are tried.
    """
    k = len(chain)
    x_start = np.asarray(x_start, np.float64)
    x_end = np.asarray(x_end, np.float64)
    P = np.asarray(P, np.float64).reshape(len(x_start), k, 3, 3)
    N = np.asarray(N, np.float64).reshape(len(x_start), k, 3, 3)
    n = len(x_start)
    eta_arr = _as_eta(eta, n)
    origin = P[:, 0, 0, :].copy()
    X0 = x_start - origin
    XE = x_end - origin
    PP = P - origin[:, None, None, :]
    if n_div is None:
        n_div = 11 if k == 1 else 5
    s1 = barycentric_seeds(n_div, margin)
    seeds = np.array([np.concatenate(c) for c in itertools.product(*([s1] * k))])  # (S, 2k)
    S = len(seeds)

    if k == 1:
        configs = [None]
    else:
        configs = _side_configs(chain)

    found_t, found_uv = [], []
    per_tuple = max(1, chunk_rows // (S * len(configs)))
    for t0 in range(0, n, per_tuple):
        t1 = min(n, t0 + per_tuple)
        nt = t1 - t0
        for cfg in configs:
            ti = np.repeat(np.arange(t0, t1), S)
            th = np.tile(seeds, (nt, 1))
            a = np.ones((len(ti), k))
            b = np.ones((len(ti), k))
            e = eta_arr[ti]
            if cfg is None:  # k == 1: side of x0 at the seed
                x, nhat, ng, _ = interpolate(PP[ti, 0], N[ti, 0], th[:, 0], th[:, 1])
                s = np.sign(_dot(X0[ti] - x, ng))
                if chain[0] == "T":
                    a[:, 0] = np.where(s > 0, 1.0, e)
                    b[:, 0] = np.where(s > 0, e, 1.0)
            else:
                for i, c in enumerate(cfg):
                    if c == "enter":
                        b[:, i] = e
                    elif c == "exit":
                        a[:, i] = e
            prob = _Problem(X0[ti], XE[ti], PP[ti], N[ti], a, b)
            th_out, rn = _lm(prob, th, max_iter=max_iter)
            good = rn < res_tol
            found_t.append(ti[good])
            found_uv.append(th_out[good])
    ti = np.concatenate(found_t) if found_t else np.zeros(0, np.int64)
    uv = np.concatenate(found_uv) if found_uv else np.zeros((0, 2 * k))
    if deflate and len(ti):
        # second pass: around every distinct root, look for a close partner by deflation
        ti0, uv0, _ = _dedup(ti, uv, dedup)
        ring = []
        for rad in DEFLATE_RADII:
            for ang in np.linspace(0, 2 * np.pi, DEFLATE_ANGLES, endpoint=False):
                dvec = np.zeros(2 * k)
                dvec[0::2] = rad * np.cos(ang)
                dvec[1::2] = rad * np.sin(ang)
                ring.append(dvec)
        ring = np.array(ring)
        R_ = len(ring)
        rt = np.repeat(ti0, R_)
        ts = np.repeat(uv0, R_, axis=0)
        th = ts + np.tile(ring, (len(ti0), 1))
        a = np.ones((len(rt), k))
        b = np.ones((len(rt), k))
        e = eta_arr[rt]
        if k == 1:
            x, nhat, ng, _ = interpolate(PP[rt, 0], N[rt, 0], ts[:, 0], ts[:, 1])
            s = np.sign(_dot(X0[rt] - x, ng))
            if chain[0] == "T":
                a[:, 0] = np.where(s > 0, 1.0, e)
                b[:, 0] = np.where(s > 0, e, 1.0)
            cfgs = [(a, b)]
        else:
            cfgs = []
            for cfg in configs:
                a = np.ones((len(rt), k))
                b = np.ones((len(rt), k))
                for i, c in enumerate(cfg):
                    if c == "enter":
                        b[:, i] = e
                    elif c == "exit":
                        a[:, i] = e
                cfgs.append((a, b))
        for a, b in cfgs:
            base = _Problem(X0[rt], XE[rt], PP[rt], N[rt], a, b)
            th1, _ = _lm(_Deflated(base, ts), th, max_iter=50)
            th2, rn = _lm(base, th1, max_iter=50)  # polish on the plain residual
            good = rn < res_tol
            ti = np.concatenate([ti, rt[good]])
            uv = np.concatenate([uv, th2[good]])
    # validate with the contract (includes inside-the-triangle with the contract epsilon)
    chk = check_path(chain, x_start[ti], x_end[ti], P[ti], N[ti], eta_arr[ti], uv, tol=check_tol)
    ti, uv = ti[chk.valid], uv[chk.valid]
    ti, uv, keep = _dedup(ti, uv, dedup)
    if return_all:
        chk = check_path(chain, x_start[ti], x_end[ti], P[ti], N[ti], eta_arr[ti], uv, tol=check_tol)
        return ti, uv, chk
    return ti, uv


def root_sigma_min(chain, x_start, x_end, P, N, eta, uv):
    """Smallest singular value of d(h_i x nhat_i)/d(uv) at the given paths (any k).

    A small value means an ill-conditioned (near-double / near-degenerate) root: its position in
    uv is not determined to better than ~residual / sigma_min.
    """
    k = len(chain)
    x_start = np.asarray(x_start, np.float64)
    m = len(x_start)
    P = np.asarray(P, np.float64).reshape(m, k, 3, 3)
    N = np.asarray(N, np.float64).reshape(m, k, 3, 3)
    uv = np.asarray(uv, np.float64).reshape(m, 2 * k)
    eta = _as_eta(eta, m)
    origin = P[:, 0, 0, :].copy()
    X = _vertex_points(P - origin[:, None, None, :], uv)
    pts = [x_start - origin] + [X[:, i] for i in range(k)] + [np.asarray(x_end, np.float64) - origin]
    a = np.ones((m, k))
    b = np.ones((m, k))
    for i in range(k):
        if chain[i] == "T":
            _, _, ng, _ = interpolate(P[:, i] - origin[:, None, :], N[:, i], uv[:, 2 * i], uv[:, 2 * i + 1])
            s = np.sign(_dot(pts[i] - pts[i + 1], ng))
            a[:, i] = np.where(s > 0, 1.0, eta)
            b[:, i] = np.where(s > 0, eta, 1.0)
    prob = _Problem(pts[0], pts[-1], P - origin[:, None, None, :], N, a, b)
    _, J = prob.evaluate(uv, jac=True)
    return np.linalg.svd(J, compute_uv=False)[:, -1]


def _dedup(ti, uv, tol):
    """Per tuple, merge solutions closer than tol (max-norm in uv), keeping the first of each
    cluster in (tuple, u) order. Returns (ti, uv, rows kept of the input)."""
    if len(ti) == 0:
        return ti.astype(np.int64), uv, np.zeros(0, np.int64)
    order = np.lexsort((uv[:, 0], ti))
    ti, uv = ti[order], uv[order]
    keep = np.zeros(len(ti), bool)
    bounds = np.flatnonzero(np.diff(ti)) + 1
    starts = np.concatenate([[0], bounds])
    ends = np.concatenate([bounds, [len(ti)]])
    for s_, e_ in zip(starts, ends):
        if e_ - s_ == 1:
            keep[s_] = True
            continue
        blk = uv[s_:e_]
        left = np.ones(len(blk), bool)
        while left.any():
            j = np.argmax(left)
            keep[s_ + j] = True
            left &= np.abs(blk - blk[j]).max(1) >= tol
    return ti[keep].astype(np.int64), uv[keep], order[keep]


# ----------------------------------------------------------------------------------------
# forward tracer
# ----------------------------------------------------------------------------------------
def trace_one_bounce(x0, direction, P, N, eta, chain, plane_point, plane_normal):
    """Trace rays x0 + t d, bounce once on the (extended) triangle plane, hit a receiver plane.

    x0, direction (m,3); P, N (m,3,3); eta scalar/(m,); chain 'R' or 'T';
    plane_point, plane_normal (m,3). The triangle plane is treated as unbounded and the normal
    field is the linear interpolation extended beyond the edges (smooth), so finite differences
    near edges stay meaningful. Returns dict with x1, uv, nhat, s, cos_i, k, wo, hit, ok
    (ok: forward hits, cos_i > 0, no TIR, outgoing side right per the contract, receiver ahead).
    """
    x0 = np.asarray(x0, np.float64)
    d, _ = _unit(np.asarray(direction, np.float64))
    P = np.asarray(P, np.float64)
    N = np.asarray(N, np.float64)
    m = len(x0)
    eta = _as_eta(eta, m)
    p0 = P[:, 0]
    e1 = P[:, 1] - p0
    e2 = P[:, 2] - p0
    fn = _cross(e1, e2)
    with np.errstate(all="ignore"):
        t1 = _dot(p0 - x0, fn) / _dot(d, fn)
        x1 = x0 + t1[:, None] * d
        q = x1 - p0
        g11, g12, g22 = _dot(e1, e1), _dot(e1, e2), _dot(e2, e2)
        b1, b2 = _dot(q, e1), _dot(q, e2)
        det = g11 * g22 - g12 * g12
        u = (g22 * b1 - g12 * b2) / det
        v = (g11 * b2 - g12 * b1) / det
        _, nhat, ng, _ = interpolate(P, N, u, v)
        s = np.sign(_dot(x0 - x1, ng))
        wo, cos_i, kk = scatter(chain, d, nhat, s, eta)
        wo, _ = _unit(wo)
        side_out = s * _dot(wo, ng)
        side_ok = side_out > 0 if chain == "R" else side_out < 0
        t2 = _dot(plane_point - x1, plane_normal) / _dot(wo, plane_normal)
        hit = x1 + t2[:, None] * wo
    ok = (t1 > 0) & (s != 0) & (cos_i > 0) & (kk >= 0) & side_ok & (t2 > 0) & np.isfinite(hit).all(1)
    return dict(x1=x1, uv=np.stack([u, v], 1), nhat=nhat, ng=ng, s=s, cos_i=cos_i, k=kk, wo=wo, hit=hit, ok=ok)


# ----------------------------------------------------------------------------------------
# Fresnel (unpolarised)
# ----------------------------------------------------------------------------------------
def fresnel_dielectric(cos_i, eta_i, eta_t):
    """Unpolarised reflectance of a smooth dielectric interface eta_i -> eta_t (TIR -> 1)."""
    cos_i = np.clip(np.asarray(cos_i, np.float64), 0.0, 1.0)
    eta_i = np.asarray(eta_i, np.float64)
    eta_t = np.asarray(eta_t, np.float64)
    sin_t2 = (eta_i / eta_t) ** 2 * (1.0 - cos_i**2)
    tir = sin_t2 >= 1.0
    cos_t = np.sqrt(np.maximum(0.0, 1.0 - sin_t2))
    rs = (eta_i * cos_i - eta_t * cos_t) / (eta_i * cos_i + eta_t * cos_t)
    rp = (eta_t * cos_i - eta_i * cos_t) / (eta_t * cos_i + eta_i * cos_t)
    return np.where(tir, 1.0, 0.5 * (rs * rs + rp * rp))


def fresnel_conductor(cos_i, eta, k):
    """Unpolarised reflectance from IOR-1 medium onto a conductor of complex IOR eta + i k."""
    cos_i = np.clip(np.asarray(cos_i, np.float64), 0.0, 1.0).astype(np.complex128)
    n = np.asarray(eta, np.float64) + 1j * np.asarray(k, np.float64)
    sin_i2 = 1.0 - cos_i**2
    cos_t = np.sqrt(1.0 - sin_i2 / (n * n))
    rs = (cos_i - n * cos_t) / (cos_i + n * cos_t)
    rp = (n * cos_i - cos_t) / (n * cos_i + cos_t)
    return 0.5 * (np.abs(rs) ** 2 + np.abs(rp) ** 2)


# ----------------------------------------------------------------------------------------
# random tuple generators (one bounce)
# ----------------------------------------------------------------------------------------
def _random_unit(rng, n):
    v = rng.normal(size=(n, 3))
    return v / _norm(v)[:, None]


def _perp_basis(w):
    """Two unit vectors orthogonal to unit w (and to each other)."""
    a = np.where((np.abs(w[:, 0]) < 0.9)[:, None], np.array([1.0, 0, 0]), np.array([0, 1.0, 0]))
    t1, _ = _unit(_cross(w, a))
    t2 = _cross(w, t1)
    return t1, t2


def random_triangles(rng, n, min_angle_deg=3.0, offset_frac=0.3):
    """Random triangles: shapes (min angle >= min_angle), sizes 1e-3..10, offsets up to 500."""
    out = np.empty((n, 3, 3))
    filled = 0
    while filled < n:
        m = 2 * (n - filled) + 16
        T = rng.normal(size=(m, 3, 3))
        a = _angles(T)
        T = T[a.min(1) >= np.deg2rad(min_angle_deg)]
        take = min(len(T), n - filled)
        out[filled : filled + take] = T[:take]
        filled += take
    c = out.mean(1, keepdims=True)
    out = out - c
    size = np.sqrt(_norm(_cross(out[:, 1] - out[:, 0], out[:, 2] - out[:, 0])))
    scale = 10.0 ** rng.uniform(-3, 1, n) / size
    out = out * scale[:, None, None]
    far = rng.random(n) < offset_frac
    off = np.where(
        far[:, None],
        _random_unit(rng, n) * rng.uniform(100, 500, n)[:, None],
        rng.uniform(-2, 2, (n, 3)),
    )
    return out + off[:, None, :]


def _angles(T):
    e = [T[:, 1] - T[:, 0], T[:, 2] - T[:, 1], T[:, 0] - T[:, 2]]
    out = []
    for i in range(3):
        a, b = -e[i - 1], e[i]
        a, _ = _unit(a)
        b, _ = _unit(b)
        out.append(np.arccos(np.clip(_dot(a, b), -1, 1)))
    return np.nan_to_num(np.stack(out, 1))


def tri_size(P):
    """sqrt(2 * area) of (m,3,3) triangles: the length scale of the triangle."""
    return np.sqrt(_norm(_cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])))


def random_normals(rng, P, mode="tilt", max_tilt_deg=40.0, curvature=None, nonunit_frac=0.3):
    """Vertex normals for (m,3,3) triangles.

    mode 'tilt': each corner normal = face normal tilted by up to max_tilt in a random direction.
    mode 'sphere': normals of a sphere (centre on the face-normal axis through the centroid at
        signed distance `curvature` * (max centroid-corner distance); +: centre in front ->
        concave (converging), -: behind -> convex), i.e. a strongly curved mirror / lens.
    Normals point to +fn or -fn at random (orientation vs. winding random); a fraction gets
    random lengths 0.5..2 (the contract uses vertex normals as given).
    """
    m = len(P)
    fn, _ = _unit(_cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]))
    if mode == "tilt":
        tilt = np.deg2rad(rng.uniform(0, max_tilt_deg, (m, 3)))
        Nn = np.empty((m, 3, 3))
        t1, t2 = _perp_basis(fn)
        for j in range(3):
            phi = rng.uniform(0, 2 * np.pi, m)
            d = np.cos(phi)[:, None] * t1 + np.sin(phi)[:, None] * t2
            Nn[:, j] = np.cos(tilt[:, j])[:, None] * fn + np.sin(tilt[:, j])[:, None] * d
    elif mode == "sphere":
        cen = P.mean(1)
        rmax = _norm(P - cen[:, None, :]).max(1)
        c = cen + (curvature * rmax)[:, None] * fn  # tilt at the corners <= atan(1/|curvature|)
        Nn = np.empty((m, 3, 3))
        for j in range(3):
            w, _ = _unit(c - P[:, j])  # towards the centre
            # concave (centre in front): normal towards the centre; convex (centre behind):
            # away from it. Both have a positive +fn component:
            Nn[:, j] = w * np.sign(_dot(w, fn))[:, None]
    else:
        raise ValueError(mode)
    flip = np.where(rng.random(m) < 0.5, -1.0, 1.0)
    Nn = Nn * flip[:, None, None]
    lens = np.where(rng.random((m, 1)) < nonunit_frac, rng.uniform(0.5, 2.0, (m, 3)), 1.0)
    return Nn * lens[..., None]


def random_eta(rng, n, low_frac=0.1):
    e = rng.uniform(1.1, 2.5, n)
    low = rng.random(n) < low_frac
    e[low] = rng.uniform(0.6, 0.95, low.sum())
    return e


def plant_paths(rng, chain, P, N, eta, side=None, uv_margin=0.0, dist_log10=(-0.5, 2.5),
                max_theta_deg=85.0, theta=None, far_x2=None):
    """Build x0, x2 so that (P,N) has a contract-valid path at a random (u,v).

    side: +1 (x0 on the ng side, i.e. 'outside' for T), -1, or None (random per tuple).
    theta: optional (m,) fixed incidence angles (radians, w.r.t. the shading normal).
    far_x2: optional (m,) multiplier range for x2 distance (log10 range override).
    Rows whose draw fails the contract conditions are redrawn (up to 200 times); returns
    (x0, x2, uv, ok) with ok False for rows that never succeeded.
    """
    m = len(P)
    size = tri_size(P)
    x0 = np.zeros((m, 3))
    x2 = np.zeros((m, 3))
    uvp = np.zeros((m, 2))
    ok = np.zeros(m, bool)
    todo = np.arange(m)
    for _ in range(200):
        if todo.size == 0:
            break
        q = len(todo)
        a = rng.random((q, 2))
        flipm = a.sum(1) > 1
        a[flipm] = 1 - a[flipm]
        a = uv_margin + a * (1 - 3 * uv_margin)
        x, nhat, ng, _ = interpolate(P[todo], N[todo], a[:, 0], a[:, 1])
        s = side if side is not None else np.where(rng.random(q) < 0.5, 1.0, -1.0)
        s = np.broadcast_to(np.asarray(s, np.float64), (q,)).copy()
        n_o = s[:, None] * nhat
        th = np.arccos(rng.uniform(np.cos(np.deg2rad(max_theta_deg)), 1.0, q)) if theta is None else theta[todo]
        phi = rng.uniform(0, 2 * np.pi, q)
        t1, t2 = _perp_basis(n_o)
        back = np.cos(th)[:, None] * n_o + np.sin(th)[:, None] * (np.cos(phi)[:, None] * t1 + np.sin(phi)[:, None] * t2)
        wi = -back  # travelling towards the surface
        d0 = size[todo] * 10.0 ** rng.uniform(*dist_log10, q)
        lo, hi = dist_log10 if far_x2 is None else far_x2
        d2 = size[todo] * 10.0 ** rng.uniform(lo, hi, q)
        xx0 = x - d0[:, None] * wi
        w_exp, cos_i, kk = scatter(chain, wi, nhat, s, eta[todo])
        w_exp, _ = _unit(w_exp)
        xx2 = x + d2[:, None] * w_exp
        side0 = s * _dot(xx0 - x, ng) > 0
        so = s * _dot(w_exp, ng)
        side2 = so > 0 if chain == "R" else so < 0
        good = side0 & (cos_i > 1e-3) & (kk > 0) & side2 & np.isfinite(xx2).all(1)
        # re-express through P so the planted uv is consistent
        g = todo[good]
        x0[g], x2[g], uvp[g], ok[g] = xx0[good], xx2[good], a[good], True
        todo = todo[~good]
    return x0, x2, uvp, ok


def plant_two_paths(rng, chain, P, N, eta, side=None, n_dir=8, n_tau=48, **plant_kw):
    """Tuples with (at least) two planted paths: two outgoing rays that really intersect.

    A first path is planted as in :func:`plant_paths`; then along random lines uv1 + tau*dir in
    the triangle the outgoing ray of x(tau) (same x0) is followed until it becomes coplanar
    with the first outgoing ray (sign change of det[x(tau)-x1, wo1, wo(tau)], refined by
    bisection); x2 := the intersection point when it lies ahead on both rays. Returns
    (x0, x2, uv1, uv2, ok).
    """
    m = len(P)
    x0, _, uv1, ok0 = plant_paths(rng, chain, P, N, eta, side=side, **plant_kw)
    x1, nh1, ng1, _ = interpolate(P, N, uv1[:, 0], uv1[:, 1])
    s = np.sign(_dot(x0 - x1, ng1))
    wi1, _ = _unit(x1 - x0)
    wo1, _, _ = scatter(chain, wi1, nh1, s, eta)
    wo1, _ = _unit(wo1)
    x2 = np.full((m, 3), np.nan)
    uv2 = np.full((m, 2), np.nan)
    ok = np.zeros(m, bool)

    def ray(idx, uv):
        x, nh, ng, _ = interpolate(P[idx], N[idx], uv[:, 0], uv[:, 1])
        wi, _ = _unit(x - x0[idx])
        ss = np.sign(_dot(x0[idx] - x, ng))
        wo, ci, kk = scatter(chain, wi, nh, ss, eta[idx])
        wo, _ = _unit(wo)
        so = ss * _dot(wo, ng)
        valid = (ss == s[idx]) & (ci > 1e-3) & (kk > 0) & ((so > 0) if chain == "R" else (so < 0))
        return x, wo, valid

    def f(idx, uv):
        x, wo, valid = ray(idx, uv)
        return _dot(_cross(x - x1[idx], wo1[idx]), wo), valid

    for _ in range(n_dir):
        todo = np.flatnonzero(ok0 & ~ok)
        if todo.size == 0:
            break
        q = len(todo)
        ang = rng.uniform(0, 2 * np.pi, q)
        d = np.stack([np.cos(ang), np.sin(ang)], 1)
        # largest tau keeping uv1 + tau d inside the triangle
        with np.errstate(divide="ignore", invalid="ignore"):
            lim = np.full(q, np.inf)
            for comp in (0, 1):
                tt = np.where(d[:, comp] < 0, -uv1[todo, comp] / d[:, comp], np.inf)
                lim = np.minimum(lim, tt)
            sd = d.sum(1)
            tt = np.where(sd > 0, (1 - uv1[todo].sum(1)) / sd, np.inf)
            lim = np.minimum(lim, tt)
        taus = np.linspace(0, 1, n_tau + 1)[1:][None, :] * lim[:, None]  # (q, n_tau)
        rep = np.repeat(todo, n_tau)
        uvg = (uv1[todo][:, None, :] + taus[:, :, None] * d[:, None, :]).reshape(-1, 2)
        F, V = f(rep, uvg)
        F = F.reshape(q, n_tau)
        V = V.reshape(q, n_tau)
        # first sign change between consecutive valid samples, skipping the first 2 samples
        ch = (np.sign(F[:, 2:-1]) != np.sign(F[:, 3:])) & V[:, 2:-1] & V[:, 3:]
        has = ch.any(1)
        jj = np.argmax(ch, 1) + 2
        sel = np.flatnonzero(has)
        if sel.size == 0:
            continue
        idx = todo[sel]
        lo = taus[sel, jj[sel]]
        hi = taus[sel, jj[sel] + 1]
        flo, _ = f(idx, uv1[idx] + lo[:, None] * d[sel])
        for _ in range(50):
            mid = 0.5 * (lo + hi)
            fm, _ = f(idx, uv1[idx] + mid[:, None] * d[sel])
            same = np.sign(fm) == np.sign(flo)
            lo = np.where(same, mid, lo)
            flo = np.where(same, fm, flo)
            hi = np.where(same, hi, mid)
        uvb = uv1[idx] + (0.5 * (lo + hi))[:, None] * d[sel]
        xb, wob, vb = ray(idx, uvb)
        # closest points of the two (now coplanar) lines x1 + a wo1, xb + b wob
        w0 = x1[idx] - xb
        A = _dot(wo1[idx], wo1[idx])
        B = _dot(wo1[idx], wob)
        C = _dot(wob, wob)
        D = _dot(wo1[idx], w0)
        E = _dot(wob, w0)
        den = A * C - B * B
        with np.errstate(divide="ignore", invalid="ignore"):
            a = (B * E - C * D) / den
            b = (A * E - B * D) / den
        p = x1[idx] + a[:, None] * wo1[idx]
        size = tri_size(P[idx])
        good = vb & (a > 0.05 * size) & (b > 0.05 * size) & (a < 1e4 * size) & np.isfinite(p).all(1)
        g = idx[good]
        x2[g] = p[good]
        uv2[g] = uvb[good]
        ok[g] = True
    return x0, x2, uv1, uv2, ok


def polish(chain, x_start, x_end, P, N, eta, uv, max_iter=100):
    """Run the reference LM from given uv (one row per path) on eq. (3); returns polished uv.

    The side configuration of every T vertex is taken from the given point. Rows whose LM does
    not reach |F| < 1e-12 are returned unchanged (NaN-free)."""
    k = len(chain)
    x_start = np.asarray(x_start, np.float64)
    m = len(x_start)
    P = np.asarray(P, np.float64).reshape(m, k, 3, 3)
    N = np.asarray(N, np.float64).reshape(m, k, 3, 3)
    uv = np.asarray(uv, np.float64).reshape(m, 2 * k)
    eta = _as_eta(eta, m)
    origin = P[:, 0, 0, :].copy()
    PP = P - origin[:, None, None, :]
    X = _vertex_points(PP, uv)
    pts = [x_start - origin] + [X[:, i] for i in range(k)] + [np.asarray(x_end, np.float64) - origin]
    a = np.ones((m, k))
    b = np.ones((m, k))
    for i in range(k):
        if chain[i] == "T":
            _, _, ng, _ = interpolate(PP[:, i], N[:, i], uv[:, 2 * i], uv[:, 2 * i + 1])
            s = np.sign(_dot(pts[i] - pts[i + 1], ng))
            a[:, i] = np.where(s > 0, 1.0, eta)
            b[:, i] = np.where(s > 0, eta, 1.0)
    prob = _Problem(pts[0], pts[-1], PP, N, a, b)
    th, rn = _lm(prob, uv, max_iter=max_iter)
    return np.where((rn < 1e-12)[:, None], th, uv)
