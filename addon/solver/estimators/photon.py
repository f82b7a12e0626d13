"""Photon tracing (forward light tracing) as a caustic method: texel-averaged irradiance.

Photons leave light samples (points with an emission profile, or parallel sun beams), are
traced through the scene's BVH (closest hit, :mod:`addon.solver.geometry.bvh`), reflect / refract at
casters with the interpolated corner normal, and deposit their flux into a texel histogram
of whichever receiver triangle they land on (hit triangle -> barycentrics -> UV -> texel).
Dividing a texel's flux by the world area the texel covers on the receiver gives the
*texel-averaged* irradiance E (W/m²), an unbiased estimate of the mean of the bake's
per-point irradiance over the texel.  This module never imports bpy; the bake side
(``addon.bake.estimators.photon``) builds the arrays and the texel areas.

Emission (``Emitters``, built by :func:`point_emitter` / :func:`sun_emitter`):

- point sample (intensity I, W/sr, profile f(w)): photons uniform in a cone containing every
  caster vertex (solid angle Ω = 2π(1 - cos_max); the full sphere from a hemisphere up), each
  I f(w) Ω / n; sun (irradiance S, direction d): parallel photons from a disc of radius R
  upstream of the scene, each S π R² / n.  Stratified: an s_x x s_y jittered grid of the
  emitter's 2D domain ((1 - cos θ, φ) for the cone, (r², φ) for the disc).

Transport at a caster triangle (roles of ``geometry.optics``; the side rules of CONTRACT.md,
``optics.scatter_direction``; outside -> inside is 1 -> IOR).  Weights: 'reflect' mirror x tint; 'refract' (1 - F) x tint;
'both' F x tint for R and (1 - F) x tint for T, F the unpolarised dielectric Fresnel
reflectance (1 under total internal reflection, where T is impossible).  When both R and
T lead to a chain being baked, one is chosen with probability F / 1 - F (the Fresnel factor
cancels); when only one does, it is taken with its Fresnel weight.  Russian roulette: when
the largest RGB component of a photon's throughput falls below ``RR_THRESHOLD`` of its
emitted value it survives with probability (throughput / threshold) and is divided by it
(unbiased).  Only chains in ``chains`` (subset of R, T, RR, RT, TR, TT) deposit; a photon
stops at the first receiver, occluder, miss, or caster that no baked chain continues
through.

Deposit on a receiver triangle: only from its front (geometric normal turned to the shading
normal's side, as the bake); the flux is scaled by cos_shading / cos_geometric so that the
estimate is the bake's irradiance convention E = integral L max(0, n_shading . w) dw.

Determinism: photon g's random numbers are a counter-based hash of (seed, g, dimension);
the kernel runs in parallel over blocks of photons and writes one deposit slot per photon;
the histogram is summed afterwards in photon order (np.bincount): the result is
bit-identical for any thread count and for a seed.
"""

import math
from collections import namedtuple

import numpy as np

from ..geometry.bvh import ray_closest, build_bvh
from ..runtime.jit import kernel, parallel_range
from ..geometry.optics import ROLE_BOTH, ROLE_REFLECT, ROLE_REFRACT, fresnel_dielectric, scatter_direction
from ..geometry.surface import plane_barycentrics, triangle_frame

CHAINS = ("R", "T", "RR", "RT", "TR", "TT")
RR_THRESHOLD = 0.05  # Russian roulette below this fraction of the emitted throughput
BLOCK = 1024  # photons per parallel work item
BATCH = 1 << 20  # photons per kernel call (deposit slots: 32 bytes each)
KIND_POINT, KIND_SUN = 0, 1

Emitters = namedtuple("Emitters", "kind pos axis cos_max radius rgb lobe spot_axis spot_cos spot_smooth start sx scale")
"""Emitter table (m emitters): ``kind`` KIND_*, ``pos`` cone apex / disc centre, ``axis`` cone
axis / travel direction, ``cos_max`` the cone's cosine, ``radius`` the disc's, ``rgb`` W/sr or
W/m², ``lobe`` Lambertian axis (zeros: isotropic), spot ``spot_axis`` / ``spot_cos`` /
``spot_smooth`` (zeros / -2 / inf: no spot), ``start`` (m+1,) first global photon index,
``sx`` strata along the first dimension, ``scale`` Omega / n or pi R² / n."""


def chain_code(chain):
    """The integer code of a chain: 1, then x2 per vertex, +1 for T (R = 2, T = 3, RR = 4 ... TT = 7)."""
    code = 1
    for c in chain:
        code = 2 * code + (1 if c == "T" else 0)
    return code


def chain_masks(chains):
    """(allowed, prefix) boolean arrays of length 8 indexed by chain code."""
    allowed = np.zeros(8, dtype=np.bool_)
    prefix = np.zeros(8, dtype=np.bool_)
    for c in chains:
        if c not in CHAINS:
            raise ValueError(f"photon tracing follows chains {', '.join(CHAINS)}, not {c!r}")
        allowed[chain_code(c)] = True
        for k in range(1, len(c) + 1):
            prefix[chain_code(c[:k])] = True
    return allowed, prefix


def caster_cone(x, vertices):
    """(axis, cos_max) of a cone from ``x`` containing every point of ``vertices`` (k,3);
    cos_max = -1 (the full sphere) when no cone narrower than a hemisphere does."""
    d = np.asarray(vertices, dtype=np.float64).reshape(-1, 3) - np.asarray(x, dtype=np.float64)
    ln = np.linalg.norm(d, axis=1)
    if d.shape[0] == 0 or not np.all(ln > 1e-12 * max(1.0, float(ln.max(initial=0.0)))):
        return np.array([0.0, 0.0, 1.0]), -1.0
    u = d / ln[:, None]
    m = u.mean(axis=0)
    nm = np.linalg.norm(m)
    if nm < 1e-6:
        return np.array([0.0, 0.0, 1.0]), -1.0
    axis = m / nm
    c = float(np.min(u @ axis))
    c = c - 1e-9 * (1.0 + abs(c))  # margin for rounding
    if c <= 1e-3:
        return axis, -1.0
    return axis, c


def _alloc(weights, n_photons):
    """Photons per emitter in proportion to ``weights``, each rounded to a full s_x x s_y grid."""
    w = np.asarray(weights, dtype=np.float64)
    total = float(w.sum())
    counts, sx = [], []
    for wi in w:
        n = 0 if total <= 0 or wi <= 0 else max(1, int(round(n_photons * wi / total)))
        s = max(1, int(math.isqrt(n))) if n else 1
        sy = -(-n // s) if n else 0
        counts.append(s * sy)
        sx.append(s)
    return np.array(counts, dtype=np.int64), np.array(sx, dtype=np.int64)


def make_emitters(samples, caster_vertices, extent, n_photons):
    """The :data:`Emitters` table for light samples and the caster vertices they must reach.

    ``samples``: list of dicts, one per light sample, with ``kind`` ("point" or "sun"),
    ``position`` (point) or ``direction`` (sun, travel direction), ``rgb`` (W/sr or W/m²),
    optional ``lobe`` (3,), ``spot_axis`` (3,), ``spot_cos``, ``spot_smooth``.
    ``caster_vertices`` (k,3): where photons must be able to go.  ``extent``: scene size
    (the sun disc starts 1.01 x extent upstream of the casters' centre).  ``n_photons`` is
    split over the samples in proportion to the power they send towards the casters.
    """
    V = np.asarray(caster_vertices, dtype=np.float64).reshape(-1, 3)
    rows = []
    for s in samples:
        rgb = np.asarray(s["rgb"], dtype=np.float64).reshape(3)
        lobe = np.asarray(s.get("lobe", np.zeros(3)), dtype=np.float64).reshape(3)
        spot_axis = np.asarray(s.get("spot_axis", np.zeros(3)), dtype=np.float64).reshape(3)
        spot_cos = float(s.get("spot_cos", -2.0))
        spot_smooth = float(s.get("spot_smooth", math.inf))
        if s["kind"] == "sun":
            d = np.asarray(s["direction"], dtype=np.float64).reshape(3)
            d = d / np.linalg.norm(d)
            c = 0.5 * (V.min(0) + V.max(0)) if V.size else np.zeros(3)
            rel = V - c
            proj = rel - np.outer(rel @ d, d)
            radius = float(np.linalg.norm(proj, axis=1).max(initial=0.0)) * (1 + 1e-9) + 1e-12 * extent
            pos = c - 1.01 * extent * d
            omega = math.pi * radius * radius
            rows.append((KIND_SUN, pos, d, 1.0, radius, rgb, lobe, spot_axis, spot_cos, spot_smooth, omega))
        else:
            x = np.asarray(s["position"], dtype=np.float64).reshape(3)
            axis, cos_max = caster_cone(x, V)
            omega = 2.0 * math.pi * (1.0 - cos_max)
            rows.append((KIND_POINT, x, axis, cos_max, 0.0, rgb, lobe, spot_axis, spot_cos, spot_smooth, omega))
    power = [r[10] * float(np.sum(r[5])) for r in rows]
    counts, sx = _alloc(power, int(n_photons)) if rows else (np.zeros(0, np.int64), np.zeros(0, np.int64))
    start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    m = len(rows)
    col = lambda k, shape=(): np.array([r[k] for r in rows], dtype=np.float64).reshape((m,) + shape)  # noqa: E731
    scale = np.array([r[10] / c if c else 0.0 for r, c in zip(rows, counts)], dtype=np.float64)
    return Emitters(np.array([r[0] for r in rows], dtype=np.int64).reshape(m), col(1, (3,)), col(2, (3,)), col(3), col(4),
                    col(5, (3,)), col(6, (3,)), col(7, (3,)), col(8), col(9), start, sx, scale)


@kernel(inline="always")
def _mix(z):
    z = (z ^ (z >> np.uint64(33))) * np.uint64(0xFF51AFD7ED558CCD)
    z = (z ^ (z >> np.uint64(33))) * np.uint64(0xC4CEB9FE1A85EC53)
    return z ^ (z >> np.uint64(33))


@kernel(inline="always")
def _rand(seed, g, dim):
    """Uniform in [0, 1) from (seed, photon index, dimension): murmur3 finaliser of a Weyl mix."""
    z = _mix(np.uint64(seed) * np.uint64(0x9E3779B97F4A7C15) ^ np.uint64(0x2545F4914F6CDD1D))
    z = _mix(z + np.uint64(g) * np.uint64(0xD6E8FEB86659FD93))
    z = _mix(z + np.uint64(dim + 1) * np.uint64(0xA0761D6478BD642F))
    return float(z >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@kernel(inline="always")
def _frame(ax, ay, az):
    if abs(ax) < 0.9:
        hx, hy, hz = 1.0, 0.0, 0.0
    else:
        hx, hy, hz = 0.0, 1.0, 0.0
    ux = hy * az - hz * ay
    uy = hz * ax - hx * az
    uz = hx * ay - hy * ax
    ln = math.sqrt(ux * ux + uy * uy + uz * uz)
    ux, uy, uz = ux / ln, uy / ln, uz / ln
    return ux, uy, uz, ay * uz - az * uy, az * ux - ax * uz, ax * uy - ay * ux


@kernel(inline="always")
def _hit_frame(tri_p, tri_n, tid, ox, oy, oz, dx, dy, dz):
    """Barycentrics (u, v) of the hit of ray o + t d on triangle tid (clamped to it), the unit
    shading normal and the unit geometric normal turned to its side."""
    u, v = plane_barycentrics(tri_p, tid, ox, oy, oz, dx, dy, dz)
    u = min(max(u, 0.0), 1.0)
    v = min(max(v, 0.0), 1.0 - u)
    ok, _x, _y, _z, nx, ny, nz, gx, gy, gz, _hn = triangle_frame(tri_p, tri_n, tid, u, v)
    return u, v, nx, ny, nz, gx, gy, gz, ok


@parallel_range(lambda a: (a["g1"] - a["g0"] + BLOCK - 1) // BLOCK)
def _trace_batch(g0, g1, seed, em_kind, em_pos, em_axis, em_cos, em_radius, em_rgb, em_lobe, em_spot_axis, em_spot_cos,
                 em_spot_smooth, em_start, em_sx, em_scale, allowed, prefix, node_min, node_max, node_child, node_start,
                 node_count, order, v0, e1, e2, tri_p, tri_n, tri_role, tri_ior, tri_tint, tri_rec, tri_uv, rec_w, rec_h,
                 rec_off, eps, out_texel, out_w, out_code, first, last):
    n = g1 - g0
    for blk in range(first, last):
        stack = np.empty(256, dtype=np.int64)
        for s in range(blk * BLOCK, min(n, (blk + 1) * BLOCK)):
            g = g0 + s
            out_texel[s] = -1
            out_code[s] = 0
            m = np.searchsorted(em_start, g, side="right") - 1
            i = g - em_start[m]
            sx = em_sx[m]
            sy = (em_start[m + 1] - em_start[m]) // sx
            xa = ((i % sx) + _rand(seed, g, 0)) / sx
            xb = ((i // sx) + _rand(seed, g, 1)) / sy
            ax, ay, az = em_axis[m, 0], em_axis[m, 1], em_axis[m, 2]
            ux, uy, uz, vx, vy, vz = _frame(ax, ay, az)
            phi = 2.0 * math.pi * xb
            cp = math.cos(phi)
            sp = math.sin(phi)
            prof = 1.0
            if em_kind[m] == KIND_SUN:
                r = em_radius[m] * math.sqrt(xa)
                ox = em_pos[m, 0] + r * (cp * ux + sp * vx)
                oy = em_pos[m, 1] + r * (cp * uy + sp * vy)
                oz = em_pos[m, 2] + r * (cp * uz + sp * vz)
                dx, dy, dz = ax, ay, az
            else:
                cz = 1.0 - xa * (1.0 - em_cos[m])
                sz = math.sqrt(max(0.0, 1.0 - cz * cz))
                dx = cz * ax + sz * (cp * ux + sp * vx)
                dy = cz * ay + sz * (cp * uy + sp * vy)
                dz = cz * az + sz * (cp * uz + sp * vz)
                ln = math.sqrt(dx * dx + dy * dy + dz * dz)
                dx, dy, dz = dx / ln, dy / ln, dz / ln
                ox, oy, oz = em_pos[m, 0], em_pos[m, 1], em_pos[m, 2]
                lx, ly, lz = em_lobe[m, 0], em_lobe[m, 1], em_lobe[m, 2]
                if lx != 0.0 or ly != 0.0 or lz != 0.0:
                    prof *= max(0.0, lx * dx + ly * dy + lz * dz)
                sax, say, saz = em_spot_axis[m, 0], em_spot_axis[m, 1], em_spot_axis[m, 2]
                if sax != 0.0 or say != 0.0 or saz != 0.0:
                    ca = sax * dx + say * dy + saz * dz
                    if em_spot_smooth[m] == np.inf:
                        prof *= 1.0 if ca > em_spot_cos[m] else 0.0
                    else:
                        f = min(max((ca - em_spot_cos[m]) * em_spot_smooth[m], 0.0), 1.0)
                        prof *= f * f * (3.0 - 2.0 * f)
            w0 = em_rgb[m, 0] * em_scale[m] * prof
            w1 = em_rgb[m, 1] * em_scale[m] * prof
            w2 = em_rgb[m, 2] * em_scale[m] * prof
            wmax0 = max(w0, w1, w2)
            if not wmax0 > 0.0:
                continue
            code = 1
            prev = -1
            depth = 0
            while True:
                tid, t = ray_closest(node_min, node_max, node_child, node_start, node_count, order, v0, e1, e2,
                                      ox, oy, oz, dx, dy, dz, eps, np.inf, prev, stack)
                if tid < 0:
                    break
                hx, hy, hz = ox + t * dx, oy + t * dy, oz + t * dz
                u, v, nx, ny, nz, gx, gy, gz, ok = _hit_frame(tri_p, tri_n, tid, ox, oy, oz, dx, dy, dz)
                if not ok:
                    break
                if tri_rec[tid] >= 0:
                    if not allowed[code]:
                        break
                    cg = -(dx * gx + dy * gy + dz * gz)
                    if cg <= 0.0:
                        break  # the back of the receiver
                    cs = max(0.0, -(dx * nx + dy * ny + dz * nz))
                    f = cs / cg
                    rec = tri_rec[tid]
                    U = tri_uv[tid, 0, 0] + u * (tri_uv[tid, 1, 0] - tri_uv[tid, 0, 0]) + v * (tri_uv[tid, 2, 0] - tri_uv[tid, 0, 0])
                    V = tri_uv[tid, 0, 1] + u * (tri_uv[tid, 1, 1] - tri_uv[tid, 0, 1]) + v * (tri_uv[tid, 2, 1] - tri_uv[tid, 0, 1])
                    W = rec_w[rec]
                    H = rec_h[rec]
                    fi = np.floor(U * W)
                    fj = np.floor(V * H)
                    if fi < 0.0 or fj < 0.0 or fi >= W or fj >= H:
                        break
                    out_texel[s] = rec_off[rec] + int(fj) * W + int(fi)
                    out_w[s, 0] = w0 * f
                    out_w[s, 1] = w1 * f
                    out_w[s, 2] = w2 * f
                    out_code[s] = code
                    break
                role = tri_role[tid]
                if role == 0 or depth >= 2:
                    break
                # Incoming side, cos_i against the shading normal turned to it.
                outside = dx * gx + dy * gy + dz * gz < 0.0
                sg = 1.0 if outside else -1.0
                nox, noy, noz = sg * nx, sg * ny, sg * nz
                ci = -(dx * nox + dy * noy + dz * noz)
                if not ci > 0.0:
                    break
                eta = tri_ior[tid]
                n1 = 1.0 if outside else eta
                n2 = eta if outside else 1.0
                can_r = (role == ROLE_REFLECT or role == ROLE_BOTH) and prefix[2 * code]
                can_t = (role == ROLE_REFRACT or role == ROLE_BOTH) and prefix[2 * code + 1]
                F = 1.0 if role == ROLE_REFLECT else fresnel_dielectric(ci, n1, n2)
                rx, ry, rz = 0.0, 0.0, 0.0
                tx, ty, tz = 0.0, 0.0, 0.0
                if can_r:
                    can_r, rx, ry, rz = scatter_direction(dx, dy, dz, nx, ny, nz, gx, gy, gz, False, eta)
                if can_t:
                    can_t, tx, ty, tz = scatter_direction(dx, dy, dz, nx, ny, nz, gx, gy, gz, True, eta)
                    can_t = can_t and F < 1.0
                if can_r and can_t:
                    take_r = _rand(seed, g, 2 + 2 * depth) < F
                    fac = 1.0
                elif can_r:
                    take_r = True
                    fac = F
                elif can_t:
                    take_r = False
                    fac = 1.0 - F
                else:
                    break
                w0 *= fac * tri_tint[tid, 0]
                w1 *= fac * tri_tint[tid, 1]
                w2 *= fac * tri_tint[tid, 2]
                wm = max(w0, w1, w2)
                if not wm > 0.0:
                    break
                if wm < RR_THRESHOLD * wmax0:
                    q = wm / (RR_THRESHOLD * wmax0)
                    if _rand(seed, g, 3 + 2 * depth) >= q:
                        break
                    w0 /= q
                    w1 /= q
                    w2 /= q
                if take_r:
                    dx, dy, dz = rx, ry, rz
                    code = 2 * code
                else:
                    dx, dy, dz = tx, ty, tz
                    code = 2 * code + 1
                ox, oy, oz = hx, hy, hz
                prev = tid
                depth += 1


PhotonResult = namedtuple("PhotonResult", "flux photons deposited per_chain")
"""``flux`` (texels, 3) W per texel of the concatenated receiver textures; ``photons`` traced;
``deposited`` photons that reached a texel; ``per_chain`` chain -> deposited count."""


def trace_photons(*args, **kwargs):
    """Trace every photon and bin its flux per texel: :func:`photon_steps` run to the end.
    Returns a :data:`PhotonResult`."""
    steps = photon_steps(*args, **kwargs)
    while True:
        try:
            next(steps)
        except StopIteration as done:
            return done.value


def photon_steps(tri_p, tri_n, tri_role, tri_ior, tri_tint, tri_rec, tri_uv, rec_res, emitters, chains, seed=0,
                 bvh=None, eps=1e-6, batch=BATCH):
    """Trace every photon of ``emitters`` (:func:`make_emitters`) and bin their flux per texel;
    a generator yielding ``(photons done, total)`` after every batch of ``batch`` photons and
    returning a :data:`PhotonResult`.  The batches are summed one after the other, so another
    ``batch`` changes the rounding of the sums: keep the default for bit-identical results.

    ``tri_*`` (n, ...): the scene's triangles (positions, corner normals, role codes 0..3, IOR
    behind the surface, tint); ``tri_rec`` (n,) receiver index or -1, ``tri_uv`` (n,3,2) the
    receivers' corner UVs (anything for others); ``rec_res`` [(W, H), ...] per receiver;
    ``chains``: the chains that deposit.  Receiver r's texel (i, j) (u in [i/W, (i+1)/W],
    j = 0 at v = 0) is row ``offset_r + j W + i`` of ``flux`` (offsets in receiver order).
    ``eps``: the ray offset (world units).
    """
    tri_p = np.ascontiguousarray(tri_p, dtype=np.float64).reshape(-1, 3, 3)
    n = tri_p.shape[0]
    tri_n = np.ascontiguousarray(tri_n, dtype=np.float64).reshape(n, 3, 3)
    tri_role = np.ascontiguousarray(tri_role, dtype=np.int64).reshape(n)
    tri_ior = np.ascontiguousarray(tri_ior, dtype=np.float64).reshape(n)
    tri_tint = np.ascontiguousarray(tri_tint, dtype=np.float64).reshape(n, 3)
    tri_rec = np.ascontiguousarray(tri_rec, dtype=np.int64).reshape(n)
    tri_uv = np.ascontiguousarray(tri_uv, dtype=np.float64).reshape(n, 3, 2)
    rec_w = np.array([int(r[0]) for r in rec_res], dtype=np.int64)
    rec_h = np.array([int(r[1]) for r in rec_res], dtype=np.int64)
    rec_off = np.concatenate([[0], np.cumsum(rec_w * rec_h)]).astype(np.int64)
    n_texels = int(rec_off[-1])
    allowed, prefix = chain_masks(chains)
    if bvh is None:
        bvh = build_bvh(tri_p)
    e = emitters
    total = int(e.start[-1]) if e.start.size else 0
    flux = np.zeros((n_texels, 3))
    per_code = np.zeros(8, dtype=np.int64)
    seed = int(seed) & 0x7FFFFFFFFFFFFFFF
    batch = max(BLOCK, int(batch))
    out_texel = np.empty(min(batch, max(total, 1)), dtype=np.int64)
    out_w = np.empty((out_texel.size, 3))
    out_code = np.empty(out_texel.size, dtype=np.int64)
    for g0 in range(0, total, batch):
        g1 = min(total, g0 + batch)
        k = g1 - g0
        if n and n_texels:
            _trace_batch(g0, g1, seed, e.kind, e.pos, e.axis, e.cos_max, e.radius, e.rgb, e.lobe, e.spot_axis, e.spot_cos,
                         e.spot_smooth, e.start, e.sx, e.scale, allowed, prefix, bvh.node_min, bvh.node_max, bvh.node_child,
                         bvh.node_start, bvh.node_count, bvh.order, bvh.v0, bvh.e1, bvh.e2, tri_p, tri_n, tri_role, tri_ior,
                         tri_tint, tri_rec, tri_uv, rec_w, rec_h, rec_off, float(eps), out_texel[:k], out_w[:k], out_code[:k])
            hit = np.flatnonzero(out_texel[:k] >= 0)
            tex = out_texel[hit]
            for c in range(3):
                flux[:, c] += np.bincount(tex, weights=out_w[hit, c], minlength=n_texels)
            per_code += np.bincount(out_code[hit], minlength=8)[:8]
        yield g1, total
    per_chain = {c: int(per_code[chain_code(c)]) for c in CHAINS if allowed[chain_code(c)]}
    return PhotonResult(flux, total, int(per_code.sum()), per_chain)
