"""Why a two-bounce path was missed: the resultant of each system around its root.

Used by bench/two_bounce_recall.py ``--diag``.  Rebuilds, in Python, the systems that
``two_bounce.solve._solve_oriented`` builds for one tuple (both orientations: forward, hidden v1;
reversed by reciprocity, hidden v2 of the forward path), with the solver's own kernels
(``system.build_system``, ``det_bezout``, ``find_v_roots``, ``refine_v_roots``,
``roots_in_interval``, ``trace_to_second``, ``polish_and_validate2``), and reports for the
system that holds the missed root: the 100-piece scan's signs and log|det| around it, the
true resultant roots near it (dense sampling of its piece), the roots the scan and the
refinement see, the nearest of them, and where the candidates at that root polish to.
The set-up below mirrors ``_solve_oriented`` and must follow it when that changes.
"""
from __future__ import annotations

import math

import numpy as np

from addon.solver.polynomials import bivariate
from addon.solver.spoly.two_bounce import params, prepass, resultant, sqrt, system
from addon.solver.paths.two_vertex import pack_geometry, polish_and_validate2, trace_to_second
from addon.solver.polynomials.roots import MAX_DEGREE, roots_in_interval


def systems(refract1, refract2, x0, x3, PA, NA, PB, NB, eta):
    """Yield (label, a, da, b, db, margin, geo, (blo, bhi, β, hit)) for every system
    _solve_oriented would solve: the √ piece's β band, β's polynomial and the map to
    triangle 2 (``HIT_SLOT``) for the pre-pass."""
    geo = np.zeros((15, 3))
    if not pack_geometry(x0, x3, PA, NA, PB, NB, geo):
        return
    ng1, ng2 = geo[13].copy(), geo[14].copy()
    e11, e12, p20, e21, e22 = geo[2].copy(), geo[3].copy(), geo[7].copy(), geo[8].copy(), geo[9].copy()
    L1 = max(np.linalg.norm(e11), np.linalg.norm(e12))
    side0 = geo[0] @ ng1
    side3 = (geo[1] - p20) @ ng2
    # _solve_oriented's cheap side tests: x0 and x3 off the planes, each triangle reaching
    # the side of the other's plane that the chain needs
    L2 = max(np.linalg.norm(e21), np.linalg.norm(e22))
    if abs(side0) <= 1e-12 * L1 or abs(side3) <= 1e-12 * L2:
        return
    sd2 = [(q @ ng1) * side0 for q in (p20, p20 + e21, p20 + e22)]
    tol1 = 1e-9 * (L1 + L2) * abs(side0)
    if (not refract1 and max(sd2) <= tol1) or (refract1 and min(sd2) >= -tol1):
        return
    sd1 = [((q - p20) @ ng2) * side3 for q in (np.zeros(3), e11, e12)]
    tol2 = 1e-9 * (L1 + L2) * abs(side3)
    if (not refract2 and max(sd1) <= tol2) or (refract2 and min(sd1) >= -tol2):
        return
    inv = 1.0 / L1
    geo_l = geo.copy()
    for r in range(13):
        if r <= 3 or 7 <= r <= 9:
            geo_l[r] = geo[r] * inv
    s1 = [(geo[4] + (geo[4 + c] if c else 0)) @ ng1 for c in range(3)]
    s2 = [(geo[10] + (geo[10 + c] if c else 0)) @ ng2 for c in range(3)]
    any_front1, any_back1 = any(s > 0 for s in s1), any(s < 0 for s in s1)
    any_front2, any_back2 = any(s > 0 for s in s2), any(s < 0 for s in s2)
    nmax1 = max(np.sum((geo[4] + (geo[4 + c] if c else 0)) ** 2) for c in range(3))
    nscale2 = max(np.linalg.norm(geo[10] + (geo[10 + c] if c else 0)) for c in range(3))
    flat2 = all(np.abs(geo[r]).sum() <= 1e-12 * nscale2 for r in (11, 12))
    cx = (e11 + e12) / 3.0
    w = geo[1] - cx
    nb = 3.0 * geo[10] + geo[11] + geo[12]
    c2 = np.cross(w, nb)
    if not np.linalg.norm(c2) > 1e-6 * np.linalg.norm(w) * np.linalg.norm(nb):
        c2 = np.cross(e21, nb)
    c2 = c2 / np.linalg.norm(c2)
    dmax = max(np.sum((q - geo[0]) ** 2) * inv * inv for q in (np.zeros(3), e11, e12))
    S = math.sqrt(nmax1 * dmax)
    margin = params.V_MARGIN_APPROX if refract1 else params.V_MARGIN_EXACT
    for o1 in range(2 if refract1 else 1):
        sigma1 = 1.0 if o1 == 0 else -1.0
        if refract1 and ((sigma1 > 0 and not any_front1) or (sigma1 < 0 and not any_back1)):
            continue
        s_in1 = sigma1 * (1.0 if side0 > 0 else -1.0)
        r1 = (1.0 / eta) if s_in1 > 0 else eta
        mask = 0
        xs = [1.0]
        if refract1:
            xs = []
            pts = [(iu / 3.0, iv / 3.0) for iu in range(4) for iv in range(4 - iu)] + [(1 / 3.0, 1 / 3.0)]
            for k, (uu, vv) in enumerate(pts):
                nn = geo[4] + uu * geo[5] + vv * geo[6]
                dv = (uu * e11 + vv * e12 - geo[0]) * inv
                beta = (nn @ nn) * (dv @ dv) * (1 - r1 * r1) + r1 * r1 * (nn @ dv) ** 2
                x = beta / (S * S)
                if k == len(pts) - 1:
                    x = min(1.0, max(0.0, x))
                xs.append(x)
                if x >= 0:
                    mask |= 1 << int(sqrt.sqrt_piece(x))
            if max(xs[:-1]) <= 0:
                continue
        biv = np.zeros((params.N_SLOTS, params.MAXD + 1, params.MAXD + 1))
        if refract1 and params.SQRT_BANDS:
            sqrt.beta_poly(geo_l, r1, biv)
            if min(xs[:-1]) > 0.0:
                mask |= int(sqrt.beta_mask(biv, margin, S * S))
        beta_poly = biv[params.BETA_SLOT].copy()
        heron_ok, heron_cut, heron = False, params.HERON_CUT, (0.0,) * 6
        if refract1 and params.HERON_SQRT:
            heron_ok, heron_cut, heron = sqrt.heron_sqrt_cut(geo_l, r1, margin, S * S, np.zeros((6, 7)))
        for piece in range(-1, params.SQRT_PIECES.shape[0] if refract1 else 1):
            # as _solve_oriented: the Heron √ (piece -1) where it fits, the eq (23) pieces
            # below its cut (all of them without it) held by the mask
            if piece < 0 and not heron_ok:
                continue
            if piece >= 0 and heron_ok and params.SQRT_PIECES[piece, 0] >= heron_cut:
                continue
            if piece >= 0 and refract1 and not (mask >> piece) & 1:
                continue
            for o2 in range(2 if refract2 else 1):
                eta_in2 = eta_out2 = 1.0
                if refract2:
                    sigma2 = 1.0 if o2 == 0 else -1.0
                    if (sigma2 > 0 and not any_front2) or (sigma2 < 0 and not any_back2):
                        continue
                    s_in2 = -sigma2 * (1.0 if side3 > 0 else -1.0)
                    eta_in2 = 1.0 if s_in2 > 0 else eta
                    eta_out2 = eta if s_in2 > 0 else 1.0
                biv = np.zeros((params.N_SLOTS, params.MAXD + 1, params.MAXD + 1))
                da, db = system.build_system(refract1, refract2, s_in1, r1, piece, S, heron, eta_in2, eta_out2, flat2,
                                          (c2[0], c2[1], c2[2]), geo_l, biv)
                a = biv[0, :da + 1, :da + 1].copy()
                b = biv[1, :db + 1, :db + 1].copy()
                a /= np.abs(a).max()
                b /= np.abs(b).max()
                a[np.abs(a) <= 1e-14] = 0.0
                b[np.abs(b) <= 1e-15] = 0.0
                A = np.zeros((params.MAXD + 1, params.MAXD + 1))
                B = np.zeros((params.MAXD + 1, params.MAXD + 1))
                A[:da + 1, :da + 1] = a
                B[:db + 1, :db + 1] = b
                blo, bhi = sqrt.sqrt_band(piece, S * S, refract1)
                label = f"o1={o1} piece={'heron>=%.3g' % heron_cut if piece < 0 else piece} o2={o2}"
                hit = biv[params.HIT_SLOT:params.HIT_SLOT + 4].copy()  # the map to triangle 2 for the pre-pass's hit test
                yield label, A, da, B, db, margin, geo, (blo, bhi, beta_poly, hit)


def _rel(p, d, u, v):
    val = 0.0
    mag = 0.0
    for i in range(d + 1):
        for j in range(d + 1 - i):
            t = p[i, j] * u ** i * v ** j
            val += t
            mag += abs(t)
    return abs(val) / mag if mag > 0 else 0.0


def _list_roots(rel):
    if len(rel) > 12:
        near = rel[np.argsort(np.abs(rel))[:6]]
        return f"{len(rel)} (noisy; nearest {', '.join(f'{r:+.3g}' for r in np.sort(near))})"
    return ", ".join(f"{r:+.3g}" for r in rel) or "none"


def v_major(P, d):
    """P in the layout the determinant family reads (``resultant.v_major``)."""
    out = np.zeros((params.MAXD + 1, params.MAXD + 1))
    resultant.v_major(np.ascontiguousarray(P), d, out)
    return out


def det(A, da, B, db, n, v):
    cf = np.zeros((2, params.MAXD + 2))
    mat = np.zeros((params.MAXD + 1, params.MAXD + 1))
    return resultant.det_bezout(v_major(A, da), da, v_major(B, db), db, n, v, cf, mat)


def scan_roots(A, da, B, db, n, margin, pieces, productive_v, band=(-math.inf, math.inf, None, None)):
    cf = np.zeros((2, params.MAXD + 2))
    mat = np.zeros((params.MAXD + 1, params.MAXD + 1))
    scan = np.zeros((9, params.MAX_PIECES + 1))
    roots = np.zeros(4 * params.MAX_PIECES)
    stats = np.zeros(params.N_STATS, np.int64)
    live = scan[7]  # the solver's live pre-pass (pieces where a and b can vanish together)
    live[:pieces] = 1
    if params.LIVE_PREPASS:
        biv = np.zeros((params.N_SLOTS, params.MAXD + 1, params.MAXD + 1))
        blo, bhi, beta_poly, hit = band
        if beta_poly is not None:
            biv[params.BETA_SLOT] = beta_poly
        if hit is not None:
            biv[params.HIT_SLOT:params.HIT_SLOT + 4] = hit
        if prepass.live_pieces_band(A, da, B, db, margin, pieces, biv, np.zeros((params.LIVE_STACK, 4)), live, blo, bhi) == 0:
            return None, None, "no live piece (the pre-pass excluded the whole square)"
    At, Bt = v_major(A, da), v_major(B, db)
    nv = resultant.find_v_roots(At, da, Bt, db, n, -margin, 1.0 + margin, pieces, live, cf, mat, scan, roots, stats)
    if nv < 0:
        return None, None, None
    grid = (scan[0, :pieces + 1].copy(), scan[1, :pieces + 1].copy(), scan[2, :pieces + 1].copy(), live[:pieces].copy())
    productive = np.zeros(scan.shape[1])
    for i in range(nv):
        productive[i] = 1.0 if any(abs(roots[i] - pv) < 1e-5 for pv in productive_v) else 0.0
    scan[5] = productive
    nall = resultant.refine_v_roots(At, da, Bt, db, n, pieces, live, cf, mat, scan, roots, nv, scan[5], stats)
    return roots[:nv].copy(), roots[nv:nall].copy(), grid


def candidates(A, da, B, db, v, margin, geo_or, refract1, eta):
    """u-roots of a(., v) in range with their relative |b| (what candidates_at ranks)."""
    na = int(bivariate.u_degree(A.copy(), da, 1e-14))
    nb = int(bivariate.u_degree(B.copy(), db, 1e-15))
    coeffs = np.zeros(MAX_DEGREE + 1)
    for i in range(na + 1):
        coeffs[i] = sum(A[i, j] * v ** j for j in range(da - i + 1))
    chain = np.zeros((MAX_DEGREE + 1, MAX_DEGREE + 1))
    lists = np.zeros((3, MAX_DEGREE + 1))
    out = np.zeros(MAX_DEGREE + 1)
    if na == 0 or na > MAX_DEGREE:
        return []
    k = roots_in_interval(coeffs, na, -margin, 1.0 - v + margin, 1e-14, 1e-10, chain, lists[0:2], out)
    res = []
    for u in out[:k]:
        res.append((float(u), _rel(B, db, u, v)))
    return res


def polish_from(u1, v1, geo_or, refract1, refract2, eta, rev, geo_fwd):
    ok, u2, v2 = trace_to_second(u1, v1, geo_or, refract1, eta)
    if not ok:
        return None, "trace failed (TIR / side / no hit)"
    th = np.array([u2, v2, u1, v1]) if rev else np.array([u1, v1, u2, v2])
    work = np.zeros((25, 6))
    r1, r2 = (refract2, refract1) if rev else (refract1, refract2)
    acc, err, sig = polish_and_validate2(th, geo_fwd, r1, r2, eta, params.POLISH_STEPS, params.ACCEPT_RESIDUAL, work)
    return th, f"accepted={bool(acc)} err={err:.2g} sigma~{sig:.2g}"


def diagnose_path(chain, d, t, uv_missed, pieces=None, all_uv=None):
    pieces = pieces or params.DEFAULT_PIECES
    refract1, refract2 = chain[0] == "T", chain[1] == "T"
    x0, x3, P, N, eta = d["x0"][t], d["x3"][t], d["P"][t], d["N"][t], float(d["eta"][t])
    same = d["bf_uv"][d["bf_t"] == t]
    geo_fwd = np.zeros((15, 3))
    pack_geometry(x0, x3, P[0], N[0], P[1], N[1], geo_fwd)
    out = []
    for rev in (False, True):
        if rev:
            args = (refract2, refract1, x3, x0, P[1], N[1], P[0], N[0], eta)
            us, vs = uv_missed[2], uv_missed[3]
            prod_v = list(same[:, 3])
        else:
            args = (refract1, refract2, x0, x3, P[0], N[0], P[1], N[1], eta)
            us, vs = uv_missed[0], uv_missed[1]
            prod_v = list(same[:, 1])
        r1o, r2o = args[0], args[1]
        best = None
        for label, A, da, B, db, margin, geo_or, band in systems(*args):
            ra, rb = _rel(A, da, us, vs), _rel(B, db, us, vs)
            if best is None or max(ra, rb) < best[0]:
                best = (max(ra, rb), label, A, da, B, db, margin, geo_or.copy(), ra, rb, band)
        name = "reversed" if rev else "forward"
        if best is None:
            out.append(f"  [{name}] no system")
            continue
        _, label, A, da, B, db, margin, geo_or, ra, rb, band = best
        na = int(bivariate.u_degree(A.copy(), da, 1e-14))
        nb = int(bivariate.u_degree(B.copy(), db, 1e-15))
        n = max(na, nb)
        sr, rr, grid = scan_roots(A, da, B, db, n, margin, pieces, prod_v, band)
        head = f"  [{name}] system {label} (rel |a|={ra:.2g}, |b|={rb:.2g}) n={n}; hidden v*={vs:.12f} u*={us:.9f}"
        if sr is None:
            out.append(head + ": " + (grid or "degenerate (det zero at most samples)"))
            continue
        vgrid, sgrid, lgrid, live = grid
        h = (vgrid[-1] - vgrid[0]) / pieces
        k = int(min(pieces - 1, max(0, math.floor((vs - vgrid[0]) / h))))
        lo, hi = max(0, k - 2), min(pieces, k + 3)
        head += f"; its piece {k} {'live' if live[k] else 'NOT live (pre-pass)'}"
        samp = " ".join(f"{sgrid[i]:+.0f}/{lgrid[i]:.2f}" for i in range(lo, hi + 1))
        allr = np.concatenate([sr, rr])
        near = np.sort(np.abs(allr - vs))[:3] if len(allr) else []
        # dense truth in the piece (and neighbours)
        vv = np.linspace(vgrid[max(0, k - 1)], vgrid[min(pieces, k + 2)], 3001)
        ss = np.array([det(A, da, B, db, n, v)[0] for v in vv])
        ll = np.array([det(A, da, B, db, n, v)[1] for v in vv])
        ch = np.flatnonzero((ss[:-1] != ss[1:]) & (ss[:-1] != 0) & (ss[1:] != 0))
        true_roots = 0.5 * (vv[ch] + vv[ch + 1])
        d2 = (lgrid[k - 1] + lgrid[k + 1] - 2 * lgrid[k]) if 0 < k < pieces else float("nan")
        d2b = (lgrid[k] + lgrid[k + 2] - 2 * lgrid[k + 1]) if k + 2 <= pieces else float("nan")
        out.append(head + f"\n     piece {k} [{vgrid[k]:.6f}, {vgrid[k + 1]:.6f}] sign/log|det| at pieces {lo}..{hi}: {samp}"
                   f"\n     raw 2nd diff at k, k+1: {d2:.3f}, {d2b:.3f}; scan roots {len(sr)}, refine roots {len(rr)}; "
                   f"nearest found roots |dv|: {', '.join(f'{x:.3g}' for x in near)}"
                   f"\n     dense sign changes in pieces {k - 1}..{k + 1}: "
                   f"{_list_roots(true_roots - vs)} (relative to v*); "
                   f"min log|det| there {ll.min():.2f} at {vv[np.argmin(ll)] - vs:+.3g}")
        if len(allr):
            vr = allr[np.argmin(np.abs(allr - vs))]
            cands = candidates(A, da, B, db, vr, margin, geo_or, r1o, eta)
            best_rel = min((c[1] for c in cands), default=None)
            for u, rel in cands:
                mark = "*" if abs(u - us) < 1e-4 else " "
                taken = rel == best_rel or rel < params.B_RELATIVE
                u1, v1 = min(max(u, 0.0), 1.0), min(max(vr, 0.0), 1.0)
                if u1 + v1 > 1.0:
                    ex = 0.5 * (u1 + v1 - 1.0)
                    u1, v1 = u1 - ex, v1 - ex
                th, msg = polish_from(u1, v1, geo_or, r1o, r2o, eta, rev, geo_fwd)
                land = "" if th is None else f" -> dist to missed {np.abs(th - uv_missed).max():.2g}; {msg}"
                out.append(f"     {mark}cand u={u:.9f} at v={vr:.12f} rel|b|={rel:.2g} taken={taken}{land}")
    return "\n".join(out)


# --- exact check of the determinant --------------------------------------------------------


def _exact_det(M):
    """sign and log|det| of a matrix of Fractions (Gaussian elimination, exact)."""
    from fractions import Fraction

    n = len(M)
    M = [row[:] for row in M]
    det = Fraction(1)
    for k in range(n):
        p = next((i for i in range(k, n) if M[i][k] != 0), None)
        if p is None:
            return 0, -math.inf
        if p != k:
            M[k], M[p] = M[p], M[k]
            det = -det
        det *= M[k][k]
        for i in range(k + 1, n):
            f = M[i][k] / M[k][k]
            if f:
                for j in range(k + 1, n):
                    M[i][j] -= f * M[k][j]
    return (1 if det > 0 else -1), math.log(abs(det.numerator)) - math.log(det.denominator)


def _padded_bezout(A, B, n, zero):
    """The paper's Bézout matrix (eq 29) of coefficient vectors A, B padded to degree n."""
    M = [[zero] * n for _ in range(n)]
    for j in range(n):
        M[0][j] = A[0] * B[j + 1] - B[0] * A[j + 1]
    for i in range(1, n):
        for j in range(n):
            t = A[i] * B[j + 1] - B[i] * A[j + 1]
            if j + 1 < n:
                t += M[i - 1][j + 1]
            M[i][j] = t
    return M


def _coeff_vectors(A, da, B, db, n, v):
    na = int(resultant.top_row(v_major(A, da), da, n))
    nb = int(resultant.top_row(v_major(B, db), db, n))
    a = np.array([sum(A[i, j] * v ** j for j in range(da - i, -1, -1)) if i <= na else 0.0 for i in range(n + 1)])
    b = np.array([sum(B[i, j] * v ** j for j in range(db - i, -1, -1)) if i <= nb else 0.0 for i in range(n + 1)])
    return a / np.abs(a).max(), b / np.abs(b).max(), na, nb


def exact_check(chain, d, t, uv_path, rev=False, width=0.004, npts=7):
    """At npts values of the hidden variable within ±width of a path's, the sign and
    log|det| of (1) ``det_bezout`` and (2) the paper's padded Bézout matrix eliminated in
    doubles (LAPACK), each against the exact determinant (Fractions) of the same matrix built
    from the same double coefficients.  Returns {name: [(sign ok, |log error|), ...]}."""
    from fractions import Fraction

    refract1, refract2 = chain[0] == "T", chain[1] == "T"
    x0, x3, P, N, eta = d["x0"][t], d["x3"][t], d["P"][t], d["N"][t], float(d["eta"][t])
    if rev:
        args = (refract2, refract1, x3, x0, P[1], N[1], P[0], N[0], eta)
        us, vs = uv_path[2], uv_path[3]
    else:
        args = (refract1, refract2, x0, x3, P[0], N[0], P[1], N[1], eta)
        us, vs = uv_path[0], uv_path[1]
    best = None
    for label, A, da, B, db, margin, geo, _band in systems(*args):
        r = max(_rel(A, da, us, vs), _rel(B, db, us, vs))
        if best is None or r < best[0]:
            best = (r, A, da, B, db)
    _, A, da, B, db = best
    n = max(int(bivariate.u_degree(A.copy(), da, 1e-14)), int(bivariate.u_degree(B.copy(), db, 1e-15)))
    out = {"det_bezout": [], "padded": []}
    for v in vs + np.linspace(-width, width, npts):
        a, b, na, nb = _coeff_vectors(A, da, B, db, n, v)
        # det_bezout's matrix (the hybrid Bézout matrix) in exact arithmetic
        m, nf, g, f = (na, nb, a, b) if na <= nb else (nb, na, b, a)
        F = [Fraction(float(x)) for x in f[:nf + 1]]
        G = [Fraction(float(x)) for x in g[:m + 1]]
        S = [[Fraction(0)] * nf for _ in range(nf)]
        for r in range(nf - m):
            for k in range(m + 1):
                S[r][r + k] = G[k]
        for c in range(m, 0, -1):
            for j in range(nf):
                t_ = Fraction(0)
                for l in range(max(0, j - (nf - c)), min(c - 1, j) + 1):
                    t_ += F[j - l + c] * G[l]
                for l in range(max(0, j - (m - c)), min(c - 1, j) + 1):
                    t_ -= G[j - l + c] * F[l]
                S[nf - c][j] = t_
        se, le = _exact_det(S)
        s1, l1 = det(A, da, B, db, n, v)
        out["det_bezout"].append((s1, l1, se, le))
        pe = _exact_det(_padded_bezout([Fraction(float(x)) for x in a], [Fraction(float(x)) for x in b], n, Fraction(0)))
        ps, pl = np.linalg.slogdet(np.array(_padded_bezout(a, b, n, 0.0)))
        out["padded"].append((int(ps), pl, pe[0], pe[1]))
    return {name: [(r[0] == r[2], abs(r[1] - r[3])) for r in rows] for name, rows in out.items()}
