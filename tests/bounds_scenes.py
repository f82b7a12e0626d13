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
}


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


def forward_trace(chain, light, P, N, eta, uv, receiver_P):
    """Exact one-bounce paths from the caster points uv (m,2) of triangles P, N (m,3,3):
    reflect/refract with the interpolated normal (CONTRACT.md rules) and intersect the
    receiver triangles.  Returns (hit (m,) receiver index or -1, buv (m,2) receiver
    barycentrics, xk (m,3))."""
    m = uv.shape[0]
    e1 = P[:, 1] - P[:, 0]
    e2 = P[:, 2] - P[:, 0]
    u, v = uv[:, :1], uv[:, 1:]
    x1 = P[:, 0] + u * e1 + v * e2
    n = N[:, 0] + u * (N[:, 1] - N[:, 0]) + v * (N[:, 2] - N[:, 0])
    nh = n / np.linalg.norm(n, axis=1, keepdims=True)
    ng = np.cross(e1, e2)
    ng *= np.sign(np.sum(ng * nh, axis=1))[:, None]
    wi = x1 - light
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    s = np.sign(np.sum((light - x1) * ng, axis=1))
    no = s[:, None] * nh
    cos_i = -np.sum(wi * no, axis=1)
    ok = cos_i > 1e-6
    if chain == "R":
        w = wi + 2 * cos_i[:, None] * no
    else:
        r = np.where(s > 0, 1.0 / eta, eta)
        k = 1 - r * r * (1 - cos_i * cos_i)
        ok &= k > 1e-9
        w = r[:, None] * wi + (r * cos_i - np.sqrt(np.maximum(k, 0)))[:, None] * no
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
    xk = x1 + np.where(np.isfinite(best_t), best_t, 0.0)[:, None] * w
    return hit, buv, xk


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
    missing = piece < 0
    pc = res.pieces[np.maximum(piece, 0)]
    T = RUV[hit, 0] + buv[:, :1] * (RUV[hit, 1] - RUV[hit, 0]) + buv[:, 1:] * (RUV[hit, 2] - RUV[hit, 0])
    in_bary = (buv[:, 0] >= pc[:, C.P_BU0]) & (buv[:, 0] <= pc[:, C.P_BU1]) & (buv[:, 1] >= pc[:, C.P_BV0]) & (buv[:, 1] <= pc[:, C.P_BV1])
    in_uv = (T[:, 0] >= pc[:, C.P_X0]) & (T[:, 0] <= pc[:, C.P_X1]) & (T[:, 1] >= pc[:, C.P_Y0]) & (T[:, 1] <= pc[:, C.P_Y1])
    pos_viol = missing | ~in_bary | ~in_uv
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
