"""An independent caustic reference for the bake tests: forward light tracing (photons).

Photons leave a point light uniformly inside a cone that contains the casters, are traced to
their next hit by brute force over triangle clusters (no BVH, no solver), reflect or refract
at each caster as the chain says ("R", "T", "TT", "RT", ...) with the interpolated corner
normal and Fresnel weights (a 'glass' surface: F for R, 1 - F for T), and land on an
axis-aligned floor, where their power is binned per texel: E = flux / texel area (W/m²).
Only paths that follow the chain exactly are kept; everything else (direct light, another
specular hit, an occluder, total internal reflection) is dropped.

Counter-based random numbers (splitmix64 of the photon index): the same for any thread count.
"""

import math

import numpy as np

from addon.solver.runtime.jit import kernel, parallel_range

KIND_REFLECT = 0  # mirror: R with weight 1 (tint applied by the caller)
KIND_RECEIVER = 1
KIND_OCCLUDER = 2
KIND_GLASS = 3  # dielectric: R with Fresnel F, T with 1 - F
KIND_REFRACT = 4  # dielectric transmission only (1 - F); no R


@kernel(inline="always")
def _mix(z):
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@kernel(inline="always")
def _rand(seed, i, k):
    z = _mix(np.uint64(seed) * np.uint64(0x9E3779B97F4A7C15) + np.uint64(i) * np.uint64(0xD1B54A32D192ED03) + np.uint64(k) + np.uint64(1))
    z = _mix(z)
    return float(z >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@kernel(inline="always")
def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@kernel(inline="always")
def _cross(a, b):
    out = np.empty(3)
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]
    return out


@kernel(inline="always")
def _normalize(a):
    return a / math.sqrt(_dot(a, a))


@kernel
def _closest(o, d, tri_p, cl_start, cl_end, cl_min, cl_max, skip):
    best_t = np.inf
    best = -1
    bu = 0.0
    bv = 0.0
    for c in range(cl_start.shape[0]):
        # Slab test against the cluster's box.
        t0 = 0.0
        t1 = best_t
        ok = True
        for a in range(3):
            if d[a] == 0.0:
                if o[a] < cl_min[c, a] or o[a] > cl_max[c, a]:
                    ok = False
            else:
                ta = (cl_min[c, a] - o[a]) / d[a]
                tb = (cl_max[c, a] - o[a]) / d[a]
                if ta > tb:
                    ta, tb = tb, ta
                t0 = max(t0, ta)
                t1 = min(t1, tb)
        if not ok or t0 > t1 * (1 + 1e-9) + 1e-12:
            continue
        for t in range(cl_start[c], cl_end[c]):
            if t == skip:
                continue
            p0 = tri_p[t, 0]
            e1 = tri_p[t, 1] - p0
            e2 = tri_p[t, 2] - p0
            # Plane intersection then barycentrics (a different formulation from the BVH's).
            ng = _cross(e1, e2)
            den = _dot(ng, d)
            if den == 0.0:
                continue
            tt = _dot(ng, p0 - o) / den
            if not (tt > 1e-9 and tt < best_t):
                continue
            x = o + tt * d - p0
            d11 = _dot(e1, e1)
            d12 = _dot(e1, e2)
            d22 = _dot(e2, e2)
            b1 = _dot(x, e1)
            b2 = _dot(x, e2)
            det = d11 * d22 - d12 * d12
            u = (d22 * b1 - d12 * b2) / det
            v = (d11 * b2 - d12 * b1) / det
            if u >= 0.0 and v >= 0.0 and u + v <= 1.0:
                best_t = tt
                best = t
                bu = u
                bv = v
    return best, best_t, bu, bv


@kernel
def _fresnel(cos_i, n1, n2):
    sin_t = n1 / n2 * math.sqrt(max(0.0, 1.0 - cos_i * cos_i))
    if sin_t >= 1.0:
        return 1.0
    cos_t = math.sqrt(1.0 - sin_t * sin_t)
    rs = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)
    rp = (n1 * cos_t - n2 * cos_i) / (n1 * cos_t + n2 * cos_i)
    return 0.5 * (rs * rs + rp * rp)


@parallel_range(lambda a: a["n_chunks"])
def _trace(light, axis, cos_max, n_photons, seed, events, tri_p, tri_n, kind, ior, cl_start, cl_end, cl_min, cl_max,
           floor_min, floor_size, W, H, n_chunks, hist, first, last):
    ax = _normalize(axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(ax[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    tu = _normalize(_cross(helper, ax))
    tv = _cross(ax, tu)
    per = (n_photons + n_chunks - 1) // n_chunks
    for ch in range(first, last):
        for i in range(ch * per, min(n_photons, (ch + 1) * per)):
            cz = 1.0 - _rand(seed, i, 0) * (1.0 - cos_max)
            sz = math.sqrt(max(0.0, 1.0 - cz * cz))
            phi = 2.0 * math.pi * _rand(seed, i, 1)
            d = cz * ax + sz * math.cos(phi) * tu + sz * math.sin(phi) * tv
            o = light.copy()
            w = 1.0
            prev = -1
            alive = True
            for j in range(events.shape[0]):
                t1, tt, u, v = _closest(o, d, tri_p, cl_start, cl_end, cl_min, cl_max, prev)
                if t1 < 0:
                    alive = False
                    break
                k = kind[t1]
                if k == KIND_RECEIVER or k == KIND_OCCLUDER:
                    alive = False
                    break
                x1 = o + tt * d
                n = tri_n[t1, 0] + u * (tri_n[t1, 1] - tri_n[t1, 0]) + v * (tri_n[t1, 2] - tri_n[t1, 0])
                n = _normalize(n)
                ng = _cross(tri_p[t1, 1] - tri_p[t1, 0], tri_p[t1, 2] - tri_p[t1, 0])
                if _dot(ng, n) < 0:
                    ng = -ng
                outside = _dot(d, ng) < 0.0
                no = n if outside else -n
                ngo = ng if outside else -ng
                ci = -_dot(d, no)
                if ci <= 0.0:
                    alive = False
                    break
                n1 = 1.0 if outside else ior[t1]
                n2 = ior[t1] if outside else 1.0
                if events[j] == 0:  # R
                    if k == KIND_REFRACT:
                        alive = False
                        break
                    d2 = d + 2.0 * ci * no
                    if _dot(d2, ngo) <= 0.0:
                        alive = False
                        break
                    if k == KIND_GLASS:
                        w *= _fresnel(ci, n1, n2)
                else:  # T
                    if k == KIND_REFLECT:
                        alive = False
                        break
                    r = n1 / n2
                    kk = 1.0 - r * r * (1.0 - ci * ci)
                    if kk <= 0.0:
                        alive = False
                        break
                    d2 = _normalize(r * d + (r * ci - math.sqrt(kk)) * no)
                    if _dot(d2, ngo) >= 0.0:
                        alive = False
                        break
                    w *= 1.0 - _fresnel(ci, n1, n2)
                o = x1
                d = d2
                prev = t1
            if not alive:
                continue
            t2, tt2, u2, v2 = _closest(o, d, tri_p, cl_start, cl_end, cl_min, cl_max, prev)
            if t2 < 0 or kind[t2] != KIND_RECEIVER:
                continue
            if d[2] >= 0.0:  # the floor is lit from above only
                continue
            x2 = o + tt2 * d
            fi = (x2[0] - floor_min[0]) / floor_size[0] * W
            fj = (x2[1] - floor_min[1]) / floor_size[1] * H
            ii = min(W - 1, max(0, int(math.floor(fi))))
            jj = min(H - 1, max(0, int(math.floor(fj))))
            hist[ch, jj, ii] += w


def trace_caustic(light, intensity, tri_p, tri_n, kind, ior, floor_min, floor_size, resolution, n_photons, seed=1,
                  target_centre=None, target_radius=None, cluster=8, n_chunks=64, chain=None):
    """Irradiance (H, W) in W/m² from the paths of ``chain`` (default: one vertex, R or T by
    the kind of the caster hit), by light tracing.

    ``kind`` per triangle (KIND_*); the floor is the axis-aligned rectangle floor_min +
    [0, floor_size] in x, y (lit from +z); photons go into the cone from ``light`` around the
    sphere (target_centre, target_radius), each carrying I * cone solid angle / n_photons.
    """
    tri_p = np.ascontiguousarray(tri_p, float)
    tri_n = np.ascontiguousarray(tri_n, float)
    n = tri_p.shape[0]
    cl_start = np.arange(0, n, cluster)
    cl_end = np.minimum(cl_start + cluster, n)
    cl_min = np.array([tri_p[a:b].reshape(-1, 3).min(0) for a, b in zip(cl_start, cl_end)]) - 1e-9
    cl_max = np.array([tri_p[a:b].reshape(-1, 3).max(0) for a, b in zip(cl_start, cl_end)]) + 1e-9
    light = np.asarray(light, float)
    axis = np.asarray(target_centre, float) - light
    dist = np.linalg.norm(axis)
    sin_max = min(1.0, target_radius / dist)
    cos_max = math.sqrt(1.0 - sin_max * sin_max) if sin_max < 1 else -1.0
    W, H = resolution
    hist = np.zeros((n_chunks, H, W))
    kind = np.asarray(kind, np.int64)
    if chain is None:  # one vertex: reflect on mirrors, refract on refracting surfaces
        kinds = set(np.unique(kind).tolist()) - {KIND_RECEIVER, KIND_OCCLUDER}
        if kinds == {KIND_REFLECT}:
            chain = "R"
        elif kinds <= {KIND_REFRACT}:
            chain = "T"
        else:
            raise ValueError("give the chain explicitly for mixed casters")
    events = np.array([0 if c == "R" else 1 for c in chain], dtype=np.int64)
    _trace(light, axis, cos_max, int(n_photons), int(seed), events, tri_p, tri_n, np.asarray(kind, np.int64), np.asarray(ior, float),
           cl_start, cl_end, cl_min, cl_max, np.asarray(floor_min, float), np.asarray(floor_size, float), W, H, n_chunks, hist)
    power = intensity * 2.0 * math.pi * (1.0 - cos_max) / n_photons
    texel_area = floor_size[0] * floor_size[1] / (W * H)
    return hist.sum(0) * power / texel_area
