"""The two-bounce tuple cull (addon/bake/cull.py two_bounce_emitters, pair parts) never loses a path.

Independent check: true paths are made by forward tracing (random points on t1, the exact
reflection / refraction of CONTRACT.md with interpolated normals, ray-triangle hits on every
t2, then the receiver plane), not by the solver; every traced path's (t1, t2, receiver point)
must survive the cull, with and without the subdivision into pair parts.  The parts must also
cull much harder than the pair caps alone.
"""

import numpy as np
import pytest

from addon.bake.cull import TupleCull, sub_triangles, two_bounce_emitters

from fixtures.bake_scenes import uv_sphere


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _scatter(kind, x_prev, x, n_shade, ng, eta):
    """Scattered unit directions at points x (CONTRACT.md rules); NaN rows where there is none."""
    wi = _unit(x - x_prev)
    n = _unit(n_shade)
    ng = ng * np.sign(np.sum(ng * n, axis=1))[:, None]
    s = np.sign(np.sum((x_prev - x) * ng, axis=1))
    no = s[:, None] * n
    ci = -np.sum(wi * no, axis=1)
    if kind == "R":
        wo = wi + 2.0 * ci[:, None] * no
        ok = (ci > 1e-3) & (s * np.sum(wo * ng, axis=1) > 1e-3)
    else:
        r = np.where(s > 0, 1.0 / eta, eta)
        k = 1.0 - r * r * (1.0 - ci * ci)
        wo = r[:, None] * wi + (r * ci - np.sqrt(np.maximum(k, 0.0)))[:, None] * no
        ok = (ci > 1e-3) & (k > 1e-3) & (s * np.sum(wo * ng, axis=1) < -1e-3)
    wo[~ok] = np.nan
    return wo


def _hits(o, d, tri_p):
    """All (ray, triangle, t, u, v) with t > 0 and (u, v) inside (Möller-Trumbore, every pair)."""
    e1 = tri_p[None, :, 1] - tri_p[None, :, 0]
    e2 = tri_p[None, :, 2] - tri_p[None, :, 0]
    pv = np.cross(d[:, None], e2)
    det = np.sum(e1 * pv, axis=2)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        tv = o[:, None] - tri_p[None, :, 0]
        u = np.sum(tv * pv, axis=2) * inv
        qv = np.cross(tv, e1)
        v = np.sum(d[:, None] * qv, axis=2) * inv
        t = np.sum(e2 * qv, axis=2) * inv
    ok = (np.abs(det) > 1e-14) & (u >= 1e-7) & (v >= 1e-7) & (u + v <= 1 - 1e-7) & (t > 1e-7)
    r, k = np.nonzero(ok)
    return r, k, t[r, k], u[r, k], v[r, k]


def _trace(chain, x0, P1, N1, eta, P2, N2, rec_z, rec_up, n_points, rng):
    """Forward-traced two-bounce paths: (t1, t2, x3) arrays."""
    T1 = P1.shape[0]
    b = rng.dirichlet((1.0, 1.0, 1.0), size=(T1, n_points))  # random barycentrics per t1
    t1 = np.repeat(np.arange(T1), n_points)
    w = b.reshape(-1, 3)
    x1 = np.einsum("nj,njk->nk", w, P1[t1])
    n1 = np.einsum("nj,njk->nk", w, N1[t1])
    ng1 = np.cross(P1[t1, 1] - P1[t1, 0], P1[t1, 2] - P1[t1, 0])
    d1 = _scatter(chain[0], np.broadcast_to(x0, x1.shape), x1, n1, ng1, eta)
    live = np.flatnonzero(np.all(np.isfinite(d1), axis=1))
    out_t1, out_t2, out_x3 = [], [], []
    for c0 in range(0, live.size, 4000):
        idx = live[c0:c0 + 4000]
        r, k, t, u, v = _hits(x1[idx], d1[idx], P2)
        src = idx[r]
        x2 = x1[src] + t[:, None] * d1[src]
        n2 = N2[k, 0] + u[:, None] * (N2[k, 1] - N2[k, 0]) + v[:, None] * (N2[k, 2] - N2[k, 0])
        ng2 = np.cross(P2[k, 1] - P2[k, 0], P2[k, 2] - P2[k, 0])
        d2 = _scatter(chain[1], x1[src], x2, n2, ng2, eta)
        # receiver plane z = rec_z, light must arrive on its front (normal rec_up)
        with np.errstate(divide="ignore", invalid="ignore"):
            tr = (rec_z - x2[:, 2]) / d2[:, 2]
        ok = np.isfinite(tr) & (tr > 1e-6) & (d2[:, 2] * rec_up < 0)
        out_t1.append(t1[src][ok])
        out_t2.append(k[ok])
        out_x3.append(x2[ok] + tr[ok, None] * d2[ok])
    return np.concatenate(out_t1), np.concatenate(out_t2), np.concatenate(out_x3)


def _curved_layer(rng, n, z, bend_deg, up=True):
    c = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), np.full(n, z) + rng.uniform(-0.1, 0.1, n)])
    P = c[:, None, :] + rng.normal(scale=0.3, size=(n, 3, 3)) * [1, 1, 0.2]
    ng = _unit(np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]))
    ng *= np.sign(ng[:, 2:3]) * (1 if up else -1)
    N = ng[:, None, :] + np.tan(np.radians(bend_deg)) * rng.uniform(-1, 1, (n, 3, 3)) / np.sqrt(3)
    return P, _unit(N)


def _check(chain, x0, P1, N1, P2, N2, eta, rec_z, rec_up, n_points, rng, same_set=False):
    t1, t2, x3 = _trace(chain, x0, P1, N1, eta, P2, N2, rec_z, rec_up, n_points, rng)
    assert t1.size > 300, f"{chain}: the scene must carry paths ({t1.size})"
    if t1.size > 6000:
        pick = rng.choice(t1.size, 6000, replace=False)
        t1, t2, x3 = t1[pick], t2[pick], x3[pick]
    order = np.lexsort((x3[:, 0], x3[:, 1]))
    t1, t2, x3 = t1[order], t2[order], x3[order]
    geo = np.tile([0.0, 0.0, float(rec_up)], (x3.shape[0], 1))
    T1, T2 = P1.shape[0], P2.shape[0]
    ids = (np.arange(T1), np.arange(T2) + (0 if same_set else T1))
    kept = {}
    for sub in (1, 4):
        em = two_bounce_emitters(chain, np.broadcast_to(x0, (T1, 3)).copy(), P1, N1, np.full(T1, eta), P2, N2,
                                 np.full(T2, eta), ids1=ids[0], ids2=ids[1], subdivide=sub)
        cull = TupleCull(em, x3, geo, np.arange(x3.shape[0]), 64)
        n_smp = x3.shape[0]
        want = (t1 * T2 + t2) * n_smp + np.arange(n_smp)
        if same_set:
            want = want[t1 != t2]
        want = np.unique(want)
        found = np.zeros(want.size, dtype=bool)
        n_tuples = 0
        for e, s in cull.batches(1 << 20):
            n_tuples += e.size
            key = (em.index[e, 0] * T2 + em.index[e, 1]) * n_smp + s
            found |= np.isin(want, key)
        assert found.all(), f"{chain} subdivide={sub}: the cull dropped {int((~found).sum())} of {want.size} traced paths"
        kept[sub] = n_tuples
    return kept, x3.shape[0]


@pytest.mark.parametrize("chain", ["RR", "RT", "TR", "TT"])
def test_two_bounce_cull_keeps_forward_traced_paths(chain):
    rng = np.random.default_rng({"RR": 1, "RT": 2, "TR": 3, "TT": 4}[chain])
    # t1 layer at z = 1 under a light at z = 3; t2 layer where t1 sends the light; receiver
    # plane where t2 sends it.
    x0 = np.array([0.2, -0.1, 3.0])
    k1, k2 = chain
    z2 = 2.0 if k1 == "R" else 0.0
    P1, N1 = _curved_layer(rng, 40, 1.0, 15.0)
    P2, N2 = _curved_layer(rng, 40, z2, 15.0, up=(k1 == "T"))
    going_up = k1 == "R"
    after_up = going_up if k2 == "T" else not going_up
    rec_z = (z2 + 1.5) if after_up else (z2 - 1.5)
    kept, n_smp = _check(chain, x0, P1, N1, P2, N2, 1.5, rec_z, -1.0 if after_up else 1.0, 60, rng)
    assert kept[4] <= kept[1]


@pytest.mark.slow
def test_glass_sphere_tt_cull_keeps_every_traced_path_and_culls_hard():
    P, N = uv_sphere(segments=24, rings=12, radius=0.5, centre=(0.0, 0.0, 1.0))
    rng = np.random.default_rng(7)
    x0 = np.array([0.3, 0.2, 3.5])
    kept, n_smp = _check("TT", x0, P, N, P, N, 1.5, 0.0, 1.0, 40, rng, same_set=True)
    # Subdividing t1 follows each sub-triangle's light to t2: fewer (pair, sample) tuples
    # (measured 0.51x here; 0.37x on a regular floor grid, 0.22x with 8 x 8 sub-triangles).
    assert kept[4] < 0.6 * kept[1], kept


def test_sub_triangles_tile_the_triangle():
    for s in (1, 2, 3, 5):
        sub = sub_triangles(s)
        assert sub.shape == (s * s, 3, 2)
        area = 0.5 * np.abs((sub[:, 1, 0] - sub[:, 0, 0]) * (sub[:, 2, 1] - sub[:, 0, 1])
                            - (sub[:, 2, 0] - sub[:, 0, 0]) * (sub[:, 1, 1] - sub[:, 0, 1]))
        assert np.allclose(area, 0.5 / (s * s)) and abs(area.sum() - 0.5) < 1e-12
        # random points of the unit triangle fall in exactly one sub-triangle
        rng = np.random.default_rng(s)
        pts = rng.dirichlet((1, 1, 1), 500)[:, 1:]
        inside = np.zeros(500, dtype=int)
        for tri in sub:
            a, b, c = tri
            m = np.column_stack([b - a, c - a])
            lam = np.linalg.solve(m, (pts - a).T).T
            inside += (lam[:, 0] >= -1e-12) & (lam[:, 1] >= -1e-12) & (lam.sum(1) <= 1 + 1e-12)
        assert np.all(inside >= 1) and np.mean(inside == 1) > 0.95
