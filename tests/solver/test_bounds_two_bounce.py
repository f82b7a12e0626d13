"""Two-bounce Bernstein bounds (Fan et al. 2025 §4.3 with remainder variables, §6.1 tuples) and
the two-bounce irradiance bound (eq 14–16, ``two_bounce_irradiance``: affine arithmetic on the exact map).

* Tuple construction through the BVH keeps every (T1, T2) pair that an exact forward-traced
  path uses, on the paper's slab and ball meshes, with a tuple count near the authors'.
* Position and irradiance bounds (RR, RT, TR, TT): every exact two-bounce path traced forward
  from (u1, v1) lies in the position bound of its tuple's piece containing (u1, v1) (receiver
  barycentrics and UV) and its irradiance (``path_irradiance``, an independent path-space
  computation) is <= the piece's Ē: zero violations; the bounds are tight (median width and
  median Ē/E asserted) and the share of paths under Ē = ∞ (focal, grazing) is capped.
* The reach grid (``two_bounce_irradiance.receivers_reached``, the quadtree's root test) never drops
  the cell of a traced path and proves most neighbour tuples on the slab empty; the affine √
  (Chebyshev form) encloses √x down to ranges that touch 0.
* Convergence: on a small box the position bound approaches the exact image of the box, and
  [E̲, Ē] shrinks onto the path's geometry term.
* Analytic: through a flat glass slab (parallel faces) the irradiance on the floor is
  sin θ0 / (ρ dρ/dθ0); the bound of a small box brackets it.
* The ξ2 endpoint bound (coefficients at ξ2 = 0 and 1 together) contains sampled values of the
  5-variable rational function.
"""

import numpy as np
import pytest

from fixtures import bounds_scenes as S
from addon.solver.bounds.layout import CHAIN_CODES, ior_ratio
from addon.solver.bounds.two_bounce import bound_two_bounce
from reference.bounds_two_bounce import piece_position_two
from addon.solver.bounds.tuples import two_bounce_pairs


WHOLE = np.array([0.0, 1.0, 0.0, 1.0])  # a receiver barycentric box covering the whole receiver triangle


def _scene(name, chain):
    sc = S.scene(name)
    sc["chain"] = chain
    return sc


@pytest.mark.parametrize("name,chain,n_first,most_per_first", [
    ("slab10k", "TT", 600, 20.0), ("slab10k", "RR", 600, 20.0), ("ball1280", "TT", 1280, 16.0)])
def test_tuples_contain_every_traced_pair(name, chain, n_first, most_per_first):
    sc = _scene(name, chain)
    first = np.random.default_rng(3).choice(sc["caster_P"].shape[0], n_first, replace=False)
    pairs, rep = two_bounce_pairs(chain, sc["light"], sc["caster_P"], sc["caster_N"], sc["eta"], first=first)
    rng = np.random.default_rng(4)
    tri = np.repeat(first, 32)
    a, b = rng.random(tri.size), rng.random(tri.size)
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    t2, _, _, _, _ = S.forward_trace_two(chain, sc["light"], sc["caster_P"], sc["caster_N"], sc["eta"], tri,
                                         np.stack([a, b], 1), sc["receiver_P"])
    ok = t2 >= 0
    traced = set(zip(tri[ok].tolist(), t2[ok].tolist()))
    have = set(map(tuple, pairs.tolist()))
    print(f"\n{name} {chain}: {rep['pairs']} pairs from {n_first} first triangles ({rep['pairs_per_first']:.2f} each; "
          f"authors' slab10k TT: 12.7), {len(traced)} traced pairs, {rep['node_tests']} node tests")
    assert len(traced) > 100
    assert traced <= have
    assert len(pairs) == len(set(map(tuple, pairs.tolist())))  # no duplicates
    assert rep["pairs_per_first"] <= most_per_first
    assert np.all(pairs[:, 0] != pairs[:, 1])


@pytest.mark.parametrize("name,chain,n_first,most_reached", [
    ("slab10k", "TT", 400, 0.35), ("slab10k", "RR", 400, 0.5), ("ball1280", "TT", 1280, 0.65)])
def test_reach_grid_keeps_every_traced_path_and_prunes(name, chain, n_first, most_reached):
    """``receivers_reached`` (the root test of the position quadtree): the grid cell of every
    forward-traced exact path's (u1, v1) is reached for its pair and receiver; on the slab most
    (pair, receiver) tuples of neighbouring triangles are proven empty."""
    from addon.solver.bounds.two_bounce_irradiance import receivers_reached

    sc = _scene(name, chain)
    first = np.random.default_rng(8).choice(sc["caster_P"].shape[0], n_first, replace=False)
    pairs, _ = two_bounce_pairs(chain, sc["light"], sc["caster_P"], sc["caster_N"], sc["eta"], first=first)
    reach = receivers_reached(chain, sc["light"], sc["caster_P"], sc["caster_N"], sc["receiver_P"], pairs, sc["eta"], 2)
    paths = S.trace_two(sc, first, samples_per_triangle=64, seed=9)
    index = {tuple(p): k for k, p in enumerate(pairs.tolist())}
    k = np.array([index[(a, b)] for a, b in zip(paths["tri"].tolist(), paths["t2"].tolist())])
    cells = reach.shape[2]
    i = np.minimum((paths["uv"][:, 0] * cells).astype(int), cells - 1)
    j = np.minimum((paths["uv"][:, 1] * cells).astype(int), cells - 1)
    ok = reach[k, paths["hit"], i, j]
    share = reach.any(axis=(2, 3)).mean()
    print(f"\n{name} {chain}: {len(k)} paths, {(~ok).sum()} in unreached cells; {share:.3f} of "
          f"{reach.shape[0] * reach.shape[1]} (pair, receiver) reached")
    assert len(k) >= 200
    assert ok.all()
    assert share <= most_reached


def test_affine_sqrt_encloses_near_zero():
    """The Chebyshev √ of ``affine.aff_sqrt`` contains √x at sampled points of random affine
    forms whose range reaches down to 1e-9 of its top, and its total radius stays within
    5/4 of the exact range's half-width (the Taylor form's remainder grew without bound as the
    range approached 0)."""
    import addon.solver.bounds.affine as A

    rng = np.random.default_rng(12)
    worst = 0.0
    for _ in range(400):
        hi = 10.0 ** rng.uniform(-3, 3)
        lo = hi * 10.0 ** rng.uniform(-9, -0.01)
        mid, half = 0.5 * (hi + lo), 0.5 * (hi - lo)
        wa, wb, _ = rng.dirichlet([1.0, 1.0, 1.0]) * half
        p = (mid, wa * rng.choice([-1, 1]), wb * rng.choice([-1, 1]), half - wa - wb)
        c, a, b, r = A.aff_sqrt(p)
        du, dv, e = rng.uniform(-1, 1, (3, 200))
        x = p[0] + p[1] * du + p[2] * dv + p[3] * e
        err = np.abs(np.sqrt(x) - (c + a * du + b * dv))
        assert np.all(err <= r), (p, (c, a, b, r), err.max())
        # total radius against the exact range's half-width: (√hi - √lo)/2 + δ/2 <= 0.625 (√hi - √lo)
        worst = max(worst, (abs(a) + abs(b) + r) / (np.sqrt(hi) - np.sqrt(lo)))
    assert worst < 0.63


@pytest.mark.parametrize("name,chain,n_first,widest,unbounded_cap", [
    ("slab10k", "TT", 60, 0.05, 0.05), ("slab10k", "RT", 120, 0.1, 0.2), ("slab10k", "TR", 60, 0.1, 0.25),
    ("slab10k", "RR", 400, 0.2, 0.12), ("ball1280", "TT", 80, 0.05, 0.35)])
def test_bounds_hold_every_traced_path(name, chain, n_first, widest, unbounded_cap):
    sc = _scene(name, chain)
    first = np.random.default_rng(5).choice(sc["caster_P"].shape[0], n_first, replace=False)
    pairs, _ = two_bounce_pairs(chain, sc["light"], sc["caster_P"], sc["caster_N"], sc["eta"], first=first)
    res = bound_two_bounce(chain, sc["light"], sc["caster_P"], sc["caster_N"], sc["receiver_P"], sc["receiver_UV"],
                           eta=sc["eta"], pairs=pairs, max_depth=1)
    paths = S.trace_two(sc, first, samples_per_triangle=64)
    c = S.check_bounds_two(res, sc, paths)
    print(f"\n{name} {chain}: {c['paths']} paths, {res.report['tuples']} tuples, {res.report['pieces_per_tuple']:.2f} "
          f"pieces/tuple, violations {c['position_violations']} (missing tuple {c['missing_tuple']}, piece "
          f"{c['missing_piece']}), median width {c['median_width']}, constant forms {res.report['constant_forms']}; "
          f"irradiance violations {c['irradiance_violations']}, paths under Ē = inf {c['unbounded_paths']} "
          f"({res.report['unbounded_by_reason']}), median Ē/E {c['median_ratio']:.3f}")
    assert c["paths"] >= 200
    assert c["missing_tuple"] == 0
    assert c["position_violations"] == 0
    assert max(c["median_width"]) < widest
    assert c["irradiance_violations"] == 0
    assert c["unbounded_paths"] <= unbounded_cap * c["paths"]
    assert c["median_ratio"] < 2.0


def test_irradiance_bound_shrinks_onto_the_path_geometry_term():
    """Boxes of side 1e-4 around traced paths (slab TT, RT, RR; ball TT): E̲ <= G <= Ē with
    G = dΩ0/dA_k of the path computed independently (two_vertex's chained footprint, Fresnel
    left out), and Ē/E̲ < 1.01: the affine enclosure of eq 16 converges to the exact Jacobian."""
    from addon.solver import path_irradiance
    from addon.solver.bounds.two_bounce_irradiance import piece_irradiance_two

    stats = np.zeros(6, dtype=np.int64)
    checked = 0
    for name, chain in (("slab10k", "TT"), ("slab10k", "RT"), ("slab10k", "RR"), ("ball1280", "TT")):
        sc = _scene(name, chain)
        n = sc["caster_P"].shape[0]
        paths = S.trace_two(sc, np.arange(0, n, max(1, n // 40)), samples_per_triangle=2, seed=3)
        RP = sc["receiver_P"]
        for i in range(min(25, paths["tri"].shape[0])):
            t1, t2, r = paths["tri"][i], paths["t2"][i], paths["hit"][i]
            uv, uv2, buv = paths["uv"][i], paths["uv2"][i], paths["buv"][i]
            lo = uv - 5e-5
            hi = uv + 5e-5
            eh, el = piece_irradiance_two(CHAIN_CODES[chain], sc["light"], sc["caster_P"][t1], sc["caster_N"][t1],
                                          sc["caster_P"][t2], sc["caster_N"][t2], RP[r], sc["eta"], lo, hi, WHOLE, 0, 2.0,
                                          stats)
            if not np.isfinite(eh):
                continue  # a focal or grazing path: no finite bound expected
            xk = RP[r, 0] + buv[0] * (RP[r, 1] - RP[r, 0]) + buv[1] * (RP[r, 2] - RP[r, 0])
            nk = np.cross(RP[r, 1] - RP[r, 0], RP[r, 2] - RP[r, 0])
            out = path_irradiance(chain, sc["light"][None], xk[None], np.stack([sc["caster_P"][t1], sc["caster_P"][t2]])[None],
                                  np.stack([sc["caster_N"][t1], sc["caster_N"][t2]])[None], sc["eta"], np.zeros(1, dtype=int),
                                  np.concatenate([uv, uv2])[None], receiver_normal=nk[None])
            G = float(out.geometry[0] * out.cos_receiver[0])
            assert el <= G <= eh, (name, chain, i, el, G, eh)
            assert eh <= 1.01 * el
            checked += 1
    assert checked >= 60


def _path_geometry(sc, chain, t1, t2, r, uv, uv2, buv):
    """dΩ0/dA_k of one traced path by path_irradiance (two_vertex's chained footprint), no Fresnel."""
    from addon.solver import path_irradiance

    RP = sc["receiver_P"]
    xk = RP[r, 0] + buv[0] * (RP[r, 1] - RP[r, 0]) + buv[1] * (RP[r, 2] - RP[r, 0])
    nk = np.cross(RP[r, 1] - RP[r, 0], RP[r, 2] - RP[r, 0])
    out = path_irradiance(chain, sc["light"][None], xk[None], np.stack([sc["caster_P"][t1], sc["caster_P"][t2]])[None],
                          np.stack([sc["caster_N"][t1], sc["caster_N"][t2]])[None], sc["eta"], np.zeros(1, dtype=int),
                          np.concatenate([uv, uv2])[None], receiver_normal=nk[None])
    return float(out.geometry[0] * out.cos_receiver[0])


@pytest.mark.parametrize("name,chain", [("slab10k", "TT"), ("slab10k", "RT"), ("slab10k", "TR"), ("ball1280", "TT")])
def test_implicit_last_vertex_bound_brackets_the_path_jacobian(name, chain):
    """The implicit form at the last vertex (eq 17–19; ``two_bounce_irradiance``'s fallback where the
    explicit Jacobian cannot be bounded) over a (u1, v1) box times a (uk, vk) box around a traced
    path brackets the path's |det ∂u1/∂uk| (from its independently computed geometry term), for
    boxes of 1e-2 and 1e-4, with both tangent vectors b."""
    import addon.solver.bounds.affine as A
    import addon.solver.bounds.two_bounce_irradiance as I

    sc = _scene(name, chain)
    n = sc["caster_P"].shape[0]
    paths = S.trace_two(sc, np.arange(0, n, max(1, n // 300)), samples_per_triangle=4, seed=11)
    r1, r2 = chain[0] == "T", chain[1] == "T"
    x0, eta = sc["light"], sc["eta"]
    finite = 0
    for i in range(min(400, paths["tri"].shape[0])):
        t1, t2, r = paths["tri"][i], paths["t2"][i], paths["hit"][i]
        uv, uv2, buv = paths["uv"][i], paths["uv2"][i], paths["buv"][i]
        P1, N1, P2, N2, Q = sc["caster_P"][t1], sc["caster_N"][t1], sc["caster_P"][t2], sc["caster_N"][t2], sc["receiver_P"][r]
        G = _path_geometry(sc, chain, t1, t2, r, uv, uv2, buv)
        for w in (1e-2, 1e-4):
            box = np.array([uv[0] - w, uv[0] + w, uv[1] - w, uv[1] + w])
            e1, e2 = P1[1] - P1[0], P1[2] - P1[0]
            x1 = tuple(A.dual_affine(P1[0, k], e1[k], e2[k], box) for k in range(3))
            n1 = tuple(A.dual_affine(N1[0, k], N1[1, k] - N1[0, k], N1[2, k] - N1[0, k], box) for k in range(3))
            d0 = tuple(A.dual_add_const(x1[k], -x0[k]) for k in range(3))
            ng1 = np.cross(e1, e2)
            o1 = np.sign((x0 - P1[0]) @ ng1) * np.sign(N1[0] @ ng1)  # the path's side (interpolated normals turn slowly)
            st, dt1 = I.scatter_dual(r1, o1, ior_ratio(o1, eta), n1, d0)
            if st != I.BOUNDED:
                continue
            st, u2, v2 = I.hit_dual(x1, dt1, P2)
            if st != I.BOUNDED:
                continue
            f1, f2, g1, g2 = P2[1] - P2[0], P2[2] - P2[0], N2[1] - N2[0], N2[2] - N2[0]
            x2 = tuple(A.dual_add_const(A.dual_add(A.dual_scale(u2, f1[k]), A.dual_scale(v2, f2[k])), P2[0, k]) for k in range(3))
            n2 = tuple(A.dual_add_const(A.dual_add(A.dual_scale(u2, g1[k]), A.dual_scale(v2, g2[k])), N2[0, k]) for k in range(3))
            ng2 = np.cross(f1, f2)
            o2 = -np.sign(sum(dt1[k][0][0] * ng2[k] for k in range(3))) * np.sign(N2[0] @ ng2)
            eta_f = 1.0 / ior_ratio(o2, eta) if r2 else 1.0
            t_a = f1 / np.linalg.norm(f1)
            t_b = np.cross(ng2, t_a)
            t_b /= np.linalg.norm(t_b)
            rbox = np.array([buv[0] - 30 * w, buv[0] + 30 * w, buv[1] - 30 * w, buv[1] + 30 * w])
            for b in (t_a, t_b):
                lo, hi = I.implicit_last_vertex(dt1, n2, x2, Q, rbox, eta_f, b)
                if not np.isfinite(hi):
                    continue
                finite += 1
                ratio_lo, ratio_hi = lo, hi
                # G = light(x1) · |det ∂u1/∂uk| / ak: check the Jacobian part through G / light(x1 of the path)
                x1p = P1[0] + uv[0] * e1 + uv[1] * e2
                dp = x1p - x0
                lightp = abs(dp @ ng1) / (dp @ dp) ** 1.5
                ak = np.linalg.norm(np.cross(Q[1] - Q[0], Q[2] - Q[0]))
                jac = G * ak / lightp
                assert ratio_lo * (1 - 1e-9) <= jac <= ratio_hi * (1 + 1e-9), (name, chain, i, w, ratio_lo, jac, ratio_hi)
    print(f"\n{name} {chain}: {finite} finite implicit bounds checked")
    assert finite >= 50


def test_irradiance_bound_flat_slab_analytic():
    """A flat glass slab (top z = 0, bottom z = -t, flat normals), a point light at height h0,
    the floor at z = -(t + h3): a path leaving the light at θ0 lands at ρ = (h0 + h3) tan θ0 +
    t tan θ1 (sin θ0 = η sin θ1) and the floor irradiance is dΩ0/dA = sin θ0 / (ρ dρ/dθ0).  For
    boxes of triangle 1 around the analytic entry point, every corner's analytic irradiance lies
    in [E̲, Ē], and the bound is tight (Ē within 1 + 60 × the box's half-width in barycentrics of
    the analytic maximum over the box, E̲ of the minimum)."""
    from addon.solver.bounds.two_bounce_irradiance import piece_irradiance_two

    eta, t, h0, h3 = 1.5, 0.7, 2.0, 1.3
    big = 20.0
    top = np.array([[-big, -big, 0.0], [3 * big, -big, 0.0], [-big, 3 * big, 0.0]])
    bottom = top[[0, 2, 1]] - [0.0, 0.0, t]
    N1 = np.tile([0.0, 0.0, 1.0], (3, 1))
    N2 = np.tile([0.0, 0.0, -1.0], (3, 1))
    floor = np.array([[-4 * big, -4 * big, -(t + h3)], [4 * big, -4 * big, -(t + h3)], [0.0, 4 * big, -(t + h3)]])
    x0 = np.array([0.3, -0.2, h0])
    e1, e2 = top[1] - top[0], top[2] - top[0]

    def analytic(x1):
        r = np.hypot(*(x1[:2] - x0[:2]))
        th0 = np.arctan2(r, h0)
        th1 = np.arcsin(np.sin(th0) / eta)
        rho = (h0 + h3) * np.tan(th0) + t * np.tan(th1)
        drho = (h0 + h3) / np.cos(th0) ** 2 + t * np.cos(th0) / (eta * np.cos(th1) ** 3)
        return np.sin(th0) / (rho * drho)

    stats = np.zeros(6, dtype=np.int64)
    for dx, dy in ((0.4, 0.1), (1.5, -0.8), (-2.5, 2.0), (3.0, 3.0)):
        x1 = x0[:2] + [dx, dy]
        # barycentrics of (x1, 0) on the top triangle (its edges are axis-aligned)
        u = (x1[0] - top[0, 0]) / e1[0]
        v = (x1[1] - top[0, 1]) / e2[1]
        for half in (1e-3, 1e-4):
            lo, hi = np.array([u - half, v - half]), np.array([u + half, v + half])
            eh, el = piece_irradiance_two(CHAIN_CODES["TT"], x0, top, N1, bottom, N2, floor, eta, lo, hi, WHOLE, 0, 2.0, stats)
            corners = [analytic(top[0] + a * e1 + b * e2) for a in (lo[0], hi[0]) for b in (lo[1], hi[1])]
            assert el <= min(corners) and max(corners) <= eh, (dx, dy, half, el, corners, eh)
            # tight: the enclosure exceeds the true range over the box by a second-order amount
            # (measured: 1.02-1.05 at half = 1e-3, i.e. a box 0.16 wide; <= 1.0015 at 1e-4)
            assert eh <= (1.0 + 60 * half) * max(corners) and min(corners) <= (1.0 + 60 * half) * el


def test_irradiance_bound_degenerate_inputs_never_nan():
    """Zero-area triangles, a light in the first triangle's plane, coincident triangles, NaN-free
    grazing boxes: the bound is a number (0, finite or inf), never NaN, and no crash."""
    from addon.solver.bounds.two_bounce_irradiance import piece_irradiance_two

    stats = np.zeros(6, dtype=np.int64)
    rng = np.random.default_rng(9)
    tri = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]])
    flat = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [2.0, 0.0, 1.0]])  # zero area
    nz = np.tile([0.0, 0.0, 1.0], (3, 1))
    floor = np.array([[-9.0, -9.0, -1.0], [9.0, -9.0, -1.0], [0.0, 9.0, -1.0]])
    lo, hi = np.zeros(2), np.ones(2)
    cases = [(np.array([0.2, 0.2, 3.0]), flat, nz, tri - [0, 0, 0.5], -nz),
             (np.array([0.2, 0.2, 1.0]), tri, nz, tri - [0, 0, 0.5], -nz),   # light in triangle 1's plane
             (np.array([0.2, 0.2, 3.0]), tri, nz, tri, nz),                   # triangle 2 = triangle 1
             (np.array([0.2, 0.2, 3.0]), tri, nz, flat - [0, 0, 0.5], -nz),
             (np.array([0.2, 0.2, 3.0]), tri, np.zeros((3, 3)), tri - [0, 0, 0.5], -nz)]  # zero normals
    for _ in range(20):
        P = rng.normal(size=(2, 3, 3))
        cases.append((rng.normal(size=3) * 3, P[0], rng.normal(size=(3, 3)), P[1], rng.normal(size=(3, 3))))
    for x0, P1, N1, P2, N2 in cases:
        for code in range(4):
            eh, el = piece_irradiance_two(code, x0, P1, N1, P2, N2, floor, 1.5, lo, hi, WHOLE, 3, 2.0, stats)
            assert not np.isnan(eh) and not np.isnan(el)
            assert eh >= 0.0 and el >= 0.0 and el <= eh


@pytest.mark.slow
def test_position_bound_converges_to_the_image_of_a_small_box():
    """Slab TT: around traced paths, a box of side 1e-3 in (u1, v1): the bound's width is within
    a factor 1.5 of the exact image's width (a 25 x 25 grid traced forward), and contains it."""
    sc = _scene("slab10k", "TT")
    paths = S.trace_two(sc, np.arange(0, 9999, 997), samples_per_triangle=4, seed=7)
    checked = 0
    out = np.zeros(8)
    stats = np.zeros(4, dtype=np.int64)
    for i in range(paths["tri"].shape[0]):
        t1, t2, r = paths["tri"][i], paths["t2"][i], paths["hit"][i]
        lo = np.clip(paths["uv"][i] - 5e-4, 0.0, None)
        hi = lo + 1e-3
        if hi[0] + hi[1] > 1.0:
            continue
        g = np.linspace(0.0, 1.0, 25)
        uu, vv = np.meshgrid(lo[0] + 1e-3 * g, lo[1] + 1e-3 * g)
        uv = np.stack([uu.ravel(), vv.ravel()], 1)
        tt2, hit, buv, _, _ = S.forward_trace_two("TT", sc["light"], sc["caster_P"], sc["caster_N"], sc["eta"],
                                                  np.full(uv.shape[0], t1), uv, sc["receiver_P"])
        same = (tt2 == t2) & (hit == r)
        if not same.all():
            continue  # the box straddles an edge of T2 or of the receiver: widths not comparable
        assert piece_position_two(CHAIN_CODES["TT"], sc["light"], sc["caster_P"][t1], sc["caster_N"][t1], sc["caster_P"][t2],
                                  sc["caster_N"][t2], sc["receiver_P"][r], sc["receiver_UV"][r], sc["eta"], lo, hi, out, stats)
        wu = buv[:, 0].max() - buv[:, 0].min()
        wv = buv[:, 1].max() - buv[:, 1].min()
        assert out[0] <= buv[:, 0].min() and buv[:, 0].max() <= out[1]
        assert out[2] <= buv[:, 1].min() and buv[:, 1].max() <= out[3]
        assert out[1] - out[0] <= 1.5 * wu + 4e-9
        assert out[3] - out[2] <= 1.5 * wv + 4e-9
        checked += 1
    assert checked >= 10


def test_remainder_endpoint_bound_contains_the_function_of_the_remainder_variable():
    """pu/q with pu = (1-ξ) p0 + ξ p1, q likewise: eq 3 over the ξ = 0 and ξ = 1 coefficient sets
    together (the position engines' handling of ξ2) bounds it over the 5-variable box."""
    from addon.solver.polynomials.bernstein import bound_of_coefficients, evaluate, power_to_bernstein
    from reference.bounds_two_bounce import _flat_common

    rng = np.random.default_rng(11)
    for _ in range(20):
        p0 = power_to_bernstein(rng.normal(size=(3, 3, 2, 2)))
        p1 = power_to_bernstein(rng.normal(size=(3, 3, 2, 2)))
        q0 = power_to_bernstein(np.abs(rng.normal(size=(2, 2, 1, 1))) + 0.5)
        q1 = power_to_bernstein(np.abs(rng.normal(size=(2, 2, 1, 1))) + 0.5)
        fp, _, fq = _flat_common(p0, p0, q0, p1, p1, q1)
        lo, hi, lo2, hi2 = bound_of_coefficients(fp, fq)
        assert lo2 > hi2  # q has one sign: a single interval
        x = rng.random((400, 5))
        vals = []
        for a, b, c, d, xi in x:
            num = (1 - xi) * evaluate(p0, a, b, c, d) + xi * evaluate(p1, a, b, c, d)
            den = (1 - xi) * evaluate(q0, a, b, c, d) + xi * evaluate(q1, a, b, c, d)
            vals.append(num / den)
        vals = np.array(vals)
        assert lo <= vals.min() and vals.max() <= hi
        # and tight: the corners of the box (ξ in {0, 1}) reach within the coefficient hull
        assert hi - lo <= 6.0 * (vals.max() - vals.min())


@pytest.mark.slow
@pytest.mark.parametrize("name,chain,n_first", [("slab10k", "TT", 40), ("slab10k", "RR", 40), ("slab10k", "RT", 40),
                                                 ("slab10k", "TR", 40), ("ball80", "TT", 80)])
def test_fast_engine_gives_the_reference_pieces(name, chain, n_first):
    """The production engine (``two_bounce_position``) against the reference engine
    (tests/reference/bounds_two_bounce.py): the same tuples and pieces
    (boxes, depths, receivers); position bounds equal up to rounding (the fast engine
    re-associates eq 9 and works in scaled Bernstein form), except where rounding flips the sign
    of a near-zero numerator coefficient in the reciprocal case of eq 3 (one piece of ball80 TT):
    there the fast bound is the wider one.  Never narrower than the reference's."""
    from addon.solver.bounds.layout import P_BU0, P_BU1, P_BV0, P_BV1, P_X0, P_X1, P_Y0, P_Y1

    sc = _scene(name, chain)
    first = np.random.default_rng(8).choice(sc["caster_P"].shape[0], n_first, replace=False)
    pairs, _ = two_bounce_pairs(chain, sc["light"], sc["caster_P"], sc["caster_N"], sc["eta"], first=first)
    from reference.bounds_two_bounce import batch as reference_batch

    res = {}
    for engine, batch in (("reference", reference_batch), ("fast", None)):
        res[engine] = bound_two_bounce(chain, sc["light"], sc["caster_P"], sc["caster_N"], sc["receiver_P"], sc["receiver_UV"],
                                       eta=sc["eta"], pairs=pairs, max_depth=2 if name.startswith("ball") else 1, engine=batch,
                                       irradiance=False)  # the position engines alone
    a, b = res["reference"], res["fast"]
    assert a.tuples.shape[0] > 20
    np.testing.assert_array_equal(a.tuples, b.tuples)
    np.testing.assert_array_equal(a.piece_tuple, b.piece_tuple)
    assert a.report["box_evaluations"] == b.report["box_evaluations"]
    np.testing.assert_array_equal(a.pieces[:, :4], b.pieces[:, :4])
    np.testing.assert_array_equal(a.pieces[:, 12:], b.pieces[:, 12:])
    lo = [P_BU0, P_BV0, P_X0, P_Y0]
    hi = [P_BU1, P_BV1, P_X1, P_Y1]
    assert np.all(b.pieces[:, lo] <= a.pieces[:, lo] + 1e-12) and np.all(b.pieces[:, hi] >= a.pieces[:, hi] - 1e-12)
    same = np.all(np.abs(a.pieces[:, 4:12] - b.pieces[:, 4:12]) <= 1e-12, axis=1)
    print(f"\n{name} {chain}: {a.pieces.shape[0]} pieces, {int((~same).sum())} wider in the fast engine")
    assert same.mean() >= 0.999
