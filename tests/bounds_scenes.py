"""Benchmark scenes of the Bernstein-bounds paper and an exact forward tracer, for the bounds
tests (tests/test_bounds_*.py) and bench/bounds.py.  Pure numpy.

The meshes are the paper's (../shared/meshes, README there); lights and receivers of the
pool and plane rows are not published, so they are chosen here (stated in LIGHTS/RECEIVERS
and printed by the benchmark).
"""

import os

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MESH_DIR = os.environ.get("CAUSTIC_MESHES", os.path.join(os.path.dirname(ROOT), "shared", "meshes"))

# name -> (chain, light position, eta, floor (y, x_lo, x_hi, z_lo, z_hi))
SCENES = {
    "plane7k": ("R", (1.4, 1.5, 1.0), 1.0, (-0.2, -2.0, 5.0, -0.6, 8.0)),
    "pool4k": ("T", (0.5, 8.0, 0.5), 1.33, (-1.5, -12.0, 12.0, -14.0, 16.0)),
    "pool20k": ("T", (0.5, 8.0, 0.5), 1.33, (-1.5, -12.0, 12.0, -14.0, 16.0)),
    # the meshes README's configurations: slab lit from (1, 2, -2) over y = 0, x, z in [-3, 3];
    # the balls moved to (0, 1.1, 0) and lit from (1, 4, -1)
    "slab10k": ("TT", (1.0, 2.0, -2.0), 1.5, (0.0, -3.0, 3.0, -3.0, 3.0)),
    "ball80": ("TT", (1.0, 4.0, -1.0), 1.5, (0.0, -3.0, 3.0, -3.0, 3.0)),
    "ball320": ("TT", (1.0, 4.0, -1.0), 1.5, (0.0, -3.0, 3.0, -3.0, 3.0)),
    "ball1280": ("TT", (1.0, 4.0, -1.0), 1.5, (0.0, -3.0, 3.0, -3.0, 3.0)),
}
OFFSETS = {"ball80": (0.0, 1.1, 0.0), "ball320": (0.0, 1.1, 0.0), "ball1280": (0.0, 1.1, 0.0)}


def load_obj(path):
    """(P, N): (n,3,3) triangle corners and corner normals of an OBJ (v, vn, f v//vn or v/vt/vn;
    polygons fanned into triangles)."""
    V, VN, P, N = [], [], [], []
    with open(path) as f:
        for line in f:
            if line.startswith("v "):
                V.append([float(x) for x in line.split()[1:4]])
            elif line.startswith("vn "):
                VN.append([float(x) for x in line.split()[1:4]])
            elif line.startswith("f "):
                corners = [c.split("/") for c in line.split()[1:]]
                vi = [int(c[0]) - 1 for c in corners]
                ni = [int(c[2]) - 1 if len(c) > 2 and c[2] else int(c[0]) - 1 for c in corners]
                for k in range(1, len(vi) - 1):
                    P.append((vi[0], vi[k], vi[k + 1]))
                    N.append((ni[0], ni[k], ni[k + 1]))
    V, VN = np.asarray(V), np.asarray(VN)
    return V[np.asarray(P)], VN[np.asarray(N)]


def floor(y, x0, x1, z0, z1):
    """Two triangles of the plane y over [x0,x1]x[z0,z1], normals +y, UV = normalised (x, z)."""
    a, b, c, d = (x0, y, z0), (x1, y, z0), (x1, y, z1), (x0, y, z1)
    P = np.array([[a, b, c], [a, c, d]], dtype=float)
    UV = np.stack([(P[..., 0] - x0) / (x1 - x0), (P[..., 2] - z0) / (z1 - z0)], axis=-1)
    return P, UV


def scene(name):
    """dict(chain, light, eta, caster_P, caster_N, receiver_P, receiver_UV) of a benchmark scene."""
    chain, light, eta, fl = SCENES[name]
    P, N = load_obj(os.path.join(MESH_DIR, name + ".obj"))
    P = P + np.asarray(OFFSETS.get(name, (0.0, 0.0, 0.0)))
    RP, RUV = floor(*fl)
    return dict(name=name, chain=chain, light=np.asarray(light, float), eta=eta, caster_P=P, caster_N=N,
                receiver_P=RP, receiver_UV=RUV)


def curved_plane(n=8, bend=0.3, seed=0):
    """A small curved reflector (height field z = bend·(x² + y²)) with analytic normals, facing +z."""
    xs = np.linspace(-0.5, 0.5, n + 1)
    X, Y = np.meshgrid(xs, xs, indexing="ij")
    Z = bend * (X ** 2 + Y ** 2)
    V = np.stack([X, Y, Z], -1)
    Nv = np.stack([-2 * bend * X, -2 * bend * Y, np.ones_like(X)], -1)
    Nv /= np.linalg.norm(Nv, axis=-1, keepdims=True)
    P, N = [], []
    for i in range(n):
        for j in range(n):
            for tri in (((i, j), (i + 1, j), (i + 1, j + 1)), ((i, j), (i + 1, j + 1), (i, j + 1))):
                P.append([V[a] for a in tri])
                N.append([Nv[a] for a in tri])
    return np.asarray(P), np.asarray(N)


def _scatter(kind, source, P, N, uv):
    """The incidence at the points uv (m,2) of triangles P, N (m,3,3) of light from the points
    ``source`` (m,3), by CONTRACT.md: the light's side s of the geometric normal turned to the
    interpolated shading normal gives the normal facing the light, no = s n̂.  Returns (x (m,3),
    wi (m,3) unit incoming direction, no, cos_i = -wi·no, s); ``_outgoing`` scatters."""
    e1 = P[:, 1] - P[:, 0]
    e2 = P[:, 2] - P[:, 0]
    u, v = uv[:, :1], uv[:, 1:]
    x1 = P[:, 0] + u * e1 + v * e2
    n = N[:, 0] + u * (N[:, 1] - N[:, 0]) + v * (N[:, 2] - N[:, 0])
    nh = n / np.linalg.norm(n, axis=1, keepdims=True)
    ng = np.cross(e1, e2)
    ng *= np.sign(np.sum(ng * nh, axis=1))[:, None]
    wi = x1 - source
    with np.errstate(divide="ignore", invalid="ignore"):  # rows without a path (source = x1) give NaN, never ok
        wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    s = np.sign(np.sum((source - x1) * ng, axis=1))
    no = s[:, None] * nh
    cos_i = -np.sum(wi * no, axis=1)
    return x1, wi, no, cos_i, s


def _outgoing(kind, wi, no, cos_i, s, eta):
    """Reflected or refracted unit direction (η' = 1/η entering, s > 0; η leaving) and ok (False at
    grazing incidence or total internal reflection)."""
    ok = cos_i > 1e-6
    if kind == "R":
        return wi + 2 * cos_i[:, None] * no, ok
    r = np.where(s > 0, 1.0 / eta, eta)
    k = 1 - r * r * (1 - cos_i * cos_i)
    ok &= k > 1e-9
    return r[:, None] * wi + (r * cos_i - np.sqrt(np.maximum(k, 0)))[:, None] * no, ok


def _hit_triangles(x1, w, ok, receiver_P):
    """Closest hit of the rays x1 + t w (t > 1e-9) among receiver_P: (index or -1, barycentrics, t)."""
    m = x1.shape[0]
    hit = np.full(m, -1)
    best_t = np.full(m, np.inf)
    buv = np.zeros((m, 2))
    for j, Q in enumerate(receiver_P):
        f1, f2 = Q[1] - Q[0], Q[2] - Q[0]
        h = np.cross(w, f2)
        a = h @ f1
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / a
            svec = x1 - Q[0]
            bu = np.sum(svec * h, axis=1) * inv
            qv = np.cross(svec, f1)
            bv = np.sum(qv * w, axis=1) * inv
            t = (qv @ f2) * inv
        good = ok & (np.abs(a) > 1e-14) & (bu >= 0) & (bv >= 0) & (bu + bv <= 1) & (t > 1e-9) & (t < best_t)
        hit[good] = j
        best_t[good] = t[good]
        buv[good, 0] = bu[good]
        buv[good, 1] = bv[good]
    return hit, buv, best_t


def forward_trace(chain, light, P, N, eta, uv, receiver_P):
    """Exact one-bounce paths from the caster points uv (m,2) of triangles P, N (m,3,3):
    reflect/refract with the interpolated normal (CONTRACT.md rules) and intersect the
    receiver triangles.  Returns (hit (m,) receiver index or -1, buv (m,2) receiver
    barycentrics, xk (m,3))."""
    m = uv.shape[0]
    x1, wi, no, cos_i, s = _scatter(chain, np.broadcast_to(light, (m, 3)), P, N, uv)
    w, ok = _outgoing(chain, wi, no, cos_i, s, eta)
    hit, buv, best_t = _hit_triangles(x1, w, ok, receiver_P)
    xk = x1 + np.where(np.isfinite(best_t), best_t, 0.0)[:, None] * w
    return hit, buv, xk


def forward_trace_two(chain, light, P, N, eta, tri, uv, receiver_P):
    """Exact two-bounce paths light -> triangle tri (uv (m,2) on it) -> the first caster triangle
    the scattered ray hits (any of P, except tri itself) -> receiver.  Returns (t2 (m,) second
    triangle or -1, hit (m,) receiver index or -1, buv (m,2) receiver barycentrics, x2 (m,3)).
    The receiver is tested without occlusion by the casters (as the bounds, which ignore V)."""
    from addon.solver.bvh import build_bvh, rays_closest

    m = uv.shape[0]
    x1, wi, no, cos_i, s = _scatter(chain[0], np.broadcast_to(light, (m, 3)), P[tri], N[tri], uv)
    w, ok = _outgoing(chain[0], wi, no, cos_i, s, eta)
    bvh = build_bvh(np.ascontiguousarray(P, dtype=float))
    t2, tt = rays_closest(bvh, x1, np.where(ok[:, None], w, 1.0), ignore=tri.astype(np.int64), tmin=1e-9)
    t2 = np.where(ok & (t2 >= 0), t2, -1)
    # barycentrics of the hit on its triangle
    x2 = x1 + np.where(t2 >= 0, tt, 0.0)[:, None] * w
    T2 = P[np.maximum(t2, 0)]
    e1, e2 = T2[:, 1] - T2[:, 0], T2[:, 2] - T2[:, 0]
    G = np.stack([np.sum(e1 * e1, 1), np.sum(e1 * e2, 1), np.sum(e2 * e2, 1)], 1)
    r = x2 - T2[:, 0]
    b1, b2 = np.sum(r * e1, 1), np.sum(r * e2, 1)
    det = G[:, 0] * G[:, 2] - G[:, 1] ** 2
    uv2 = np.stack([(G[:, 2] * b1 - G[:, 1] * b2) / det, (G[:, 0] * b2 - G[:, 1] * b1) / det], 1)
    uv2 = np.clip(uv2, 0.0, 1.0)
    _, wi2, no2, cos2, s2 = _scatter(chain[1], x1, T2, N[np.maximum(t2, 0)], uv2)
    w2, ok2 = _outgoing(chain[1], wi2, no2, cos2, s2, eta)
    ok2 &= t2 >= 0
    hit, buv, _ = _hit_triangles(x2, w2, ok2, receiver_P)
    return t2, hit, buv, x2, uv2


def _position_check(res, t, uv, hit, buv, RUV):
    """For paths of tuple t (index into res.tuples, -1: none) starting at uv on the first
    triangle and reaching receiver barycentrics buv on receiver ``hit``: the piece containing uv
    (-1: none) and whether the path violates its position bound (no piece, or outside the
    barycentric or UV box)."""
    from addon.solver.bounds import chain1 as C

    m = t.shape[0]
    counts = np.bincount(res.piece_tuple, minlength=res.tuples.shape[0])
    starts = np.cumsum(counts) - counts
    piece = np.full(m, -1)
    has = t >= 0
    for j in range(int(counts.max()) if counts.size else 0):
        idx = np.where(has & (j < counts[np.maximum(t, 0)]), starts[np.maximum(t, 0)] + j, -1)
        cand = idx >= 0
        pc = res.pieces[np.maximum(idx, 0)]
        inside = cand & (piece < 0) & (uv[:, 0] >= pc[:, C.P_U0]) & (uv[:, 0] <= pc[:, C.P_U1]) \
            & (uv[:, 1] >= pc[:, C.P_V0]) & (uv[:, 1] <= pc[:, C.P_V1])
        piece[inside] = idx[inside]
    pc = res.pieces[np.maximum(piece, 0)]
    T = RUV[hit, 0] + buv[:, :1] * (RUV[hit, 1] - RUV[hit, 0]) + buv[:, 1:] * (RUV[hit, 2] - RUV[hit, 0])
    in_bary = (buv[:, 0] >= pc[:, C.P_BU0]) & (buv[:, 0] <= pc[:, C.P_BU1]) & (buv[:, 1] >= pc[:, C.P_BV0]) & (buv[:, 1] <= pc[:, C.P_BV1])
    in_uv = (T[:, 0] >= pc[:, C.P_X0]) & (T[:, 0] <= pc[:, C.P_X1]) & (T[:, 1] >= pc[:, C.P_Y0]) & (T[:, 1] <= pc[:, C.P_Y1])
    return piece, (piece < 0) | ~in_bary | ~in_uv


def trace_two(sc, first, samples_per_triangle=16, seed=1):
    """Forward-traced exact two-bounce paths from ``first`` triangles (uniform (u1, v1) samples)
    that reach the receiver: dict(tri, uv, t2, hit, buv)."""
    rng = np.random.default_rng(seed)
    tri = np.repeat(np.asarray(first), samples_per_triangle)
    a, b = rng.random(tri.shape[0]), rng.random(tri.shape[0])
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    uv = np.stack([a, b], 1)
    t2, hit, buv, _, uv2 = forward_trace_two(sc["chain"], sc["light"], sc["caster_P"], sc["caster_N"], sc["eta"], tri, uv,
                                             sc["receiver_P"])
    sel = hit >= 0
    return dict(tri=tri[sel], uv=uv[sel], t2=t2[sel], hit=hit[sel], buv=buv[sel], uv2=uv2[sel])


def check_bounds_two(res, sc, paths):
    """Validity of two-bounce bounds: every traced path (``trace_two``) must belong to a tuple
    (t1, t2, receiver) of ``res``, lie in the position bound of the piece containing its (u1, v1),
    and carry an irradiance (``path_irradiance`` of the two-bounce chain, receiver normal given:
    dΩ0/dA_k · F) <= that piece's Ē.  Returns counts, the median barycentric width of the pieces
    hit and the median Ē/E over the paths with a finite Ē."""
    from addon.solver import path_irradiance
    from addon.solver.bounds import chain1 as C

    nc, nr = sc["caster_P"].shape[0], sc["receiver_P"].shape[0]
    keys = (res.tuples[:, 0] * nc + res.tuples[:, 1]) * nr + res.tuples[:, 2]
    order = np.argsort(keys)
    want = (paths["tri"] * nc + paths["t2"]) * nr + paths["hit"]
    at = np.minimum(np.searchsorted(keys[order], want), max(0, keys.shape[0] - 1))
    t = np.full(want.shape[0], -1)
    if keys.shape[0]:
        t = np.where(keys[order[at]] == want, order[at], -1)
    piece, viol = _position_check(res, t, paths["uv"], paths["hit"], paths["buv"], sc["receiver_UV"])
    pc = res.pieces[piece[piece >= 0]]
    widths = np.stack([pc[:, C.P_BU1] - pc[:, C.P_BU0], pc[:, C.P_BV1] - pc[:, C.P_BV0]], 1)
    # irradiance of each traced path (two-bounce geometry term through both vertices, Fresnel product)
    m = t.shape[0]
    RP, P, N = sc["receiver_P"], sc["caster_P"], sc["caster_N"]
    hit, buv, tri, t2 = paths["hit"], paths["buv"], paths["tri"], paths["t2"]
    xk = RP[hit, 0] + buv[:, :1] * (RP[hit, 1] - RP[hit, 0]) + buv[:, 1:] * (RP[hit, 2] - RP[hit, 0])
    nk = np.cross(RP[hit, 1] - RP[hit, 0], RP[hit, 2] - RP[hit, 0])
    E = path_irradiance(sc["chain"], np.broadcast_to(sc["light"], (m, 3)), xk, np.stack([P[tri], P[t2]], 1),
                        np.stack([N[tri], N[t2]], 1), sc["eta"], np.arange(m), np.concatenate([paths["uv"], paths["uv2"]], 1),
                        receiver_normal=nk).irradiance if m else np.zeros(0)
    has = piece >= 0
    ehi = res.pieces[np.maximum(piece, 0), C.P_EHI]
    irr_viol = has & ~(E <= ehi)
    finite = has & np.isfinite(ehi)
    ratio = ehi[finite] / np.maximum(E[finite], 1e-300)
    return dict(paths=int(m), missing_tuple=int((t < 0).sum()), missing_piece=int((piece < 0).sum()),
                position_violations=int(viol.sum()), irradiance_violations=int(irr_viol.sum()),
                unbounded_paths=int((has & ~np.isfinite(ehi)).sum()),
                median_ratio=float(np.median(ratio)) if ratio.size else float("nan"),
                worst_irradiance=np.flatnonzero(irr_viol)[:5].tolist(),
                median_width=np.median(widths, axis=0).tolist() if widths.size else [float("nan")] * 2)


def check_bounds(res, sc, samples_per_triangle=16, seed=1):
    """The paper's validity check (Fig. 17/18) by forward tracing: sample (u1, v1) uniformly on
    every caster triangle, trace the exact path, and check that a path reaching receiver
    triangle r lies in the position bound (barycentric and UV boxes) of the piece of tuple
    (caster, r) containing (u1, v1), and that its irradiance (path_irradiance, receiver normal
    given, dΩ0/dA_k · F) is <= that piece's Ē.  Returns a dict of counts."""
    from addon.solver import path_irradiance
    from addon.solver.bounds import chain1 as C

    rng = np.random.default_rng(seed)
    P, N, RP, RUV = sc["caster_P"], sc["caster_N"], sc["receiver_P"], sc["receiver_UV"]
    nc, nr = P.shape[0], RP.shape[0]
    tri = np.repeat(np.arange(nc), samples_per_triangle)
    a, b = rng.random(tri.shape[0]), rng.random(tri.shape[0])
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    uv = np.stack([a, b], 1)
    hit, buv, xk = forward_trace(sc["chain"], sc["light"], P[tri], N[tri], sc["eta"], uv, RP)
    sel = np.flatnonzero(hit >= 0)
    tri, uv, hit, buv, xk = tri[sel], uv[sel], hit[sel], buv[sel], xk[sel]
    m = sel.shape[0]
    tuple_of = np.full((nc, nr), -1)
    tuple_of[res.tuples[:, 0], res.tuples[:, 1]] = np.arange(res.tuples.shape[0])
    t = tuple_of[tri, hit]
    piece, pos_viol = _position_check(res, t, uv, hit, buv, RUV)
    missing = piece < 0
    pc = res.pieces[np.maximum(piece, 0)]
    nk = np.cross(RP[hit, 1] - RP[hit, 0], RP[hit, 2] - RP[hit, 0])
    E = path_irradiance(sc["chain"], np.broadcast_to(sc["light"], (m, 3)), xk, P[tri][:, None], N[tri][:, None], sc["eta"],
                        np.arange(m), uv, receiver_normal=nk).irradiance if m else np.zeros(0)
    ehi = pc[:, C.P_EHI]
    irr_viol = ~missing & ~(E <= ehi)
    finite = np.isfinite(ehi) & ~missing
    ratio = ehi[finite] / np.maximum(E[finite], 1e-300)
    return dict(paths=int(m), position_violations=int(pos_viol.sum()), missing_piece=int(missing.sum()),
                irradiance_violations=int(irr_viol.sum()), unbounded_paths=int((~np.isfinite(ehi) & ~missing).sum()),
                median_ratio=float(np.median(ratio)) if ratio.size else float("nan"),
                worst_position=np.flatnonzero(pos_viol)[:5].tolist(), worst_irradiance=np.flatnonzero(irr_viol)[:5].tolist())
