"""Conservative cone tests: which (caster triangle, receiver sample) tuples can hold a path
(path-points' cone cull), and which first casters can light anything (forward-flux's skip,
:func:`first_casters_reaching`).  The Bernstein-bounds selection is in ``bounds_select.py``.

Every admissible path x0 -> x1 -> x2 (x1 on a caster triangle, CONTRACT.md) satisfies two
necessary conditions; a tuple failing either has no path, so the cull never drops a real one:

1. **Sides** (exact): R needs x0 and x2 strictly on the same side of the triangle's plane,
   T on opposite sides; the bake counts only light arriving on the front of the receiver, so
   a triangle whose bounding sphere lies wholly behind a sample's receiver plane is dropped.

2. **Cone of scattered directions** (a bound): the scattered direction wo(x1) over the
   triangle lies in a spherical cap C = (d, theta), and x2 - x1 must point into C.
   - incoming directions wi over the triangle lie in the cap (a, alpha) of the three vertex
     directions; shading normals (normalised convex combinations of the corner normals) in
     the cap (c, gamma) of the unit corner normals (gamma < 90 degrees);
   - R: reflection is an isometry in wi for a fixed n, and changing n by an angle g rotates
     the reflected direction by 2 g, so wo lies in (reflect(a, c), alpha + 2 gamma);
   - T: with Q the rotation taking c to n (angle <= gamma), wt(wi, n) = Q wt(Q^T wi, c), so
     angle(wt(wi, n), wt(a, c)) <= gamma + L (alpha + gamma), L the Lipschitz constant of
     wi -> wt(wi, c) on the cap of incidence angles <= theta_max = theta_a + alpha + gamma:
     L = max(r, r cos theta_max / cos theta_t(theta_max)) (the radial and the azimuthal
     stretch of Snell's map, r = eta_i / eta_t), valid when theta_max < 90 degrees and below
     the critical angle; otherwise no cone is used (theta = pi: only the side tests cull).
   - directions from the triangle's sphere (c_t, r_t) to a sphere (c_s, rho) lie in the cap
     (normalize(c_s - c_t), asin((r_t + rho)/|c_s - c_t|)); two caps share a direction only
     when the angle between their axes is at most the sum of their radii.
   Each angle gets a margin of 1e-6 rad (the solver accepts paths whose direction is within
   1e-7 of exact, and barycentrics 1e-9 outside the triangle).

The test runs on tiles of 8 x 8 texels (bounding spheres of their samples), then on the samples
of surviving (triangle, tile) pairs; tests/bake/test_bake_cull.py checks against enumeration.

Two bounces (x0 -> t1 -> t2 -> x3): a pair survives when t2's bounding sphere reaches t1's
required side and the directions from t1 to t2 (the cap of the segment between their
bounding spheres) meet t1's scattered cap; t2's incoming cap is the smaller of those two caps,
its incoming side is known when t1 lies wholly on one side of t2's plane, and t2's scattered
cap then follows as above.  Each candidate *emitter* (a triangle, or a pair) is described by
its last triangle's sphere and plane, the receiver side it requires and its outgoing cap
(:class:`Emitters`), so the tile / sample stage is the same for both.
"""

import math

import numpy as np

from ..solver.runtime.jit import kernel, parallel_range
from .scene import point_bounds

ANGLE_MARGIN = 1e-6
NO_CONE = 4.0  # > pi: "keep every direction"
TILE = 8
SUBDIVIDE = 4  # two bounces: t1 is cut into SUBDIVIDE² sub-triangles for the pair parts


def _unit(v):
    ln = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.divide(v, ln, out=np.zeros_like(v), where=ln > 0), ln[..., 0]


def _angle(a, b):
    """Angle between unit vectors (rows), robust near 0 and pi."""
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))


def vertex_cap(x0, tri_p):
    """Cap (axis (T,3), radius (T,)) of the directions from x0 (T,3) to the triangles' points."""
    w, _ = _unit(tri_p - x0[:, None, :])
    a, _ = _unit(w.sum(axis=1))
    alpha = np.max(np.stack([_angle(a, w[:, j]) for j in range(3)], 1), axis=1)
    alpha = np.where(alpha < 0.5 * math.pi - 1e-9, alpha, NO_CONE)
    return a, alpha


def normal_cap(tri_n):
    """Cap (axis, radius) of the normalised convex combinations of the normals ``tri_n`` (T, m, 3)
    (a triangle's corners, or the corners of any region the normal field is linear over)."""
    m, _ = _unit(tri_n)
    c, lc = _unit(m.sum(axis=1))
    gamma = np.max(np.stack([_angle(c, m[:, j]) for j in range(m.shape[1])], 1), axis=1)
    gamma = np.where((gamma < 0.5 * math.pi - 1e-9) & (lc > 0), gamma, NO_CONE)
    return c, gamma


def propagate_cap(kind, a, alpha, tri_n, ng, side, eta):
    """Cap (d, theta) of the directions scattered by triangles with corner normals ``tri_n``
    ((T, m, 3): the normal field over the region is linear in the m corners).

    ``kind`` "R" or "T"; (a, alpha) the cap of incoming directions; ``ng`` unit geometric
    normals (any orientation); ``side`` the sign of (x_prev - p0) . ng for every incoming
    point (+1 / -1; 0 when unknown: T then gets no cone); ``eta`` the IOR behind the surface.
    See the module docstring for the bounds.
    """
    c, gamma = normal_cap(tri_n)
    alpha = alpha + ANGLE_MARGIN
    gamma = gamma + ANGLE_MARGIN
    if kind == "R":
        d = a - 2.0 * np.sum(a * c, axis=1)[:, None] * c
        theta = np.where((alpha < NO_CONE) & (gamma < NO_CONE), alpha + 2.0 * gamma, NO_CONE)
        return d, theta
    # T: orient the normal cap with the geometric normal, then to the incoming side.
    m, _ = _unit(tri_n)
    mg = np.einsum("tjk,tk->tj", m, ng)
    consistent = np.all(mg > 0, axis=1) | np.all(mg < 0, axis=1)
    s = side * np.where(np.sum(ng * c, axis=1) >= 0, 1.0, -1.0)
    r = np.where(s > 0, 1.0 / eta, eta)
    no = s[:, None] * c
    cos_a = -np.sum(a * no, axis=1)
    theta_a = np.arccos(np.clip(cos_a, -1.0, 1.0))
    theta_max = theta_a + alpha + gamma
    sin_max = np.sin(np.minimum(theta_max, 0.5 * math.pi))
    ok = (consistent & (side != 0) & (alpha < NO_CONE) & (gamma < NO_CONE) & (cos_a > 0)
          & (theta_max < 0.5 * math.pi - 1e-6) & (r * sin_max < 1.0 - 1e-9))
    cos_t_max = np.sqrt(np.maximum(1e-300, 1.0 - (r * sin_max) ** 2))
    lip = np.maximum(r, r * np.cos(np.minimum(theta_max, 0.5 * math.pi)) / cos_t_max)
    k = 1.0 - r * r * (1.0 - cos_a * cos_a)
    d = r[:, None] * a + (r * cos_a - np.sqrt(np.maximum(k, 0.0)))[:, None] * no
    d, _ = _unit(d)
    # Tangential bound, valid up to and beyond the critical angle: a transmitted direction is
    # w(t) = t - sqrt(1 - |t|²) n_o with t = r x (tangential part of wi); over the cap of
    # radius beta = alpha + gamma the tangential parts lie within r 2 sin(beta / 2) of r t_a,
    # and those beyond |t| = 1 are totally reflected.  With t0 the centre clamped to the unit
    # disc and delta the disc's radius around it, two directions differ by at most
    # delta / sqrt(1 - rho²) (rho = |t0| + delta < 1: the arc length of the segment's image) and
    # always by at most the chord sqrt(delta² + 2 delta) (since (√x - √y)² <= |x - y|).
    beta = np.minimum(alpha + gamma, math.pi)
    t_vec = r[:, None] * (a + cos_a[:, None] * no)
    t_len = np.linalg.norm(t_vec, axis=1)
    t0 = t_vec * np.minimum(1.0, 1.0 / np.maximum(t_len, 1e-300))[:, None]
    t0_len = np.minimum(t_len, 1.0)
    axis_t, _ = _unit(t0 - np.sqrt(np.maximum(0.0, 1.0 - t0_len ** 2))[:, None] * no)
    delta = r * 2.0 * np.sin(0.5 * beta) + np.maximum(0.0, t_len - 1.0)
    rho = t0_len + delta
    arc = np.where(rho < 1.0, delta / np.sqrt(np.maximum(1e-300, 1.0 - rho ** 2)), np.inf)
    chord = 2.0 * np.arcsin(np.minimum(1.0, 0.5 * np.sqrt(delta ** 2 + 2.0 * delta)))
    tangential = gamma + np.minimum(arc, chord) + ANGLE_MARGIN
    ok_t = consistent & (side != 0) & (alpha < NO_CONE) & (gamma < NO_CONE) & (tangential < math.pi)
    theta = np.where(ok, np.minimum(gamma + lip * (alpha + gamma), tangential), np.where(ok_t, tangential, NO_CONE))
    d = np.where(ok[:, None], d, axis_t)
    return d, theta


def all_tir(a, alpha, tri_n, ng, side, eta):
    """Where no incoming direction of the cap (a, alpha) refracts anywhere on the region with
    corner normals ``tri_n``: the smallest possible angle of incidence,
    angle(-a, n_o) - alpha - gamma (spherical triangle inequality over both caps), is beyond the
    critical angle, so every ray is totally reflected (or arrives from behind): no T path.
    ``side`` as in :func:`propagate_cap` (the light's side of the plane, ng oriented)."""
    c, gamma = normal_cap(tri_n)
    m, _ = _unit(tri_n)
    mg = np.einsum("tjk,tk->tj", m, ng)
    consistent = np.all(mg > 0, axis=1) | np.all(mg < 0, axis=1)
    s = side * np.where(np.sum(ng * c, axis=1) >= 0, 1.0, -1.0)
    r = np.where(s > 0, 1.0 / eta, eta)
    theta_a = np.arccos(np.clip(-np.sum(a * s[:, None] * c, axis=1), -1.0, 1.0))
    theta_min = theta_a - alpha - gamma - 2.0 * ANGLE_MARGIN
    return (consistent & (side != 0) & (alpha < NO_CONE) & (gamma < NO_CONE) & (r > 1.0) & (theta_min > 0.0)
            & (r * np.sin(np.minimum(theta_min, 0.5 * math.pi)) > 1.0 + 1e-9))


def geometric_normals(tri_p):
    e1 = tri_p[:, 1] - tri_p[:, 0]
    e2 = tri_p[:, 2] - tri_p[:, 0]
    return _unit(np.cross(e1, e2))


def scatter_caps(chain, x0, tri_p, tri_n, eta, incoming=None):
    """Per caster triangle: (side (T,), cap axis (T,3), cap radius (T,)) of scattered directions
    for light from the point x0 (T,3) (one point per triangle).

    ``incoming``: optional (axis, radius) of the incoming directions instead of the vertex cap
    from x0.  ``side``: sign of (x0 - p0) . ng with ng = e1 x e2 (0: x0 in the plane, no path).
    The caps of :func:`vertex_cap`, :func:`normal_cap` and :func:`propagate_cap`, computed per
    triangle in one kernel (:func:`_scatter_caps`; tests/bake/test_bake_cull.py compares the two).
    """
    T = tri_p.shape[0]
    side, d, theta = np.empty(T), np.empty((T, 3)), np.empty(T)
    if T == 0:
        return side, d, theta
    a, alpha = (np.zeros((T, 3)), np.zeros(T)) if incoming is None else incoming
    _scatter_caps(chain == "T", np.ascontiguousarray(np.broadcast_to(x0, (T, 3)), dtype=np.float64),
                  np.ascontiguousarray(tri_p, dtype=np.float64), np.ascontiguousarray(tri_n, dtype=np.float64),
                  np.ascontiguousarray(np.broadcast_to(eta, (T,)), dtype=np.float64),
                  np.ascontiguousarray(a, dtype=np.float64), np.ascontiguousarray(alpha, dtype=np.float64),
                  incoming is not None, side, d, theta)
    return side, d, theta


def scatter_caps_numpy(chain, x0, tri_p, tri_n, eta, incoming=None):
    """:func:`scatter_caps` in numpy (the reference the kernel is tested against)."""
    ng, lg = geometric_normals(tri_p)
    side = np.sign(np.sum((x0 - tri_p[:, 0]) * ng, axis=1))
    side[lg == 0] = 0.0
    a, alpha = vertex_cap(x0, tri_p) if incoming is None else incoming
    d, theta = propagate_cap(chain, a, alpha, tri_n, ng, side, eta)
    return side, d, theta


@kernel(inline="always")
def _unit3(x, y, z):
    ln = math.sqrt(x * x + y * y + z * z)
    if ln > 0.0:
        return x / ln, y / ln, z / ln, ln
    return 0.0, 0.0, 0.0, ln


@kernel(inline="always")
def _angle3(ax, ay, az, bx, by, bz):
    """Angle between unit vectors, robust near 0 and pi (as :func:`_angle`); 0 against a zero
    vector (the dot product summed from +0, as numpy's, so that atan2(0, -0) = pi never comes up)."""
    cx, cy, cz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    return math.atan2(math.sqrt(cx * cx + cy * cy + cz * cz), 0.0 + ax * bx + ay * by + az * bz)


@parallel_range("out_side", 1024)
def _scatter_caps(refract, x0, tri_p, tri_n, eta, inc_a, inc_alpha, has_incoming, out_side, out_d, out_theta, first,
                  last):
    """:func:`scatter_caps` per triangle: the vertex cap from x0 (or the incoming one), the cap
    of the corner normals, and the cap of the directions they scatter (:func:`propagate_cap`:
    R mirrors the cap, T bounds the refracted directions, Lipschitz or tangential)."""
    T = out_side.shape[0]
    m = tri_n.shape[1]
    half = 0.5 * math.pi
    for blk in range(first, last):
        w = np.empty((3, 3))  # per block: the unit directions to the corners ...
        mu = np.empty((m, 3))  # ... and the unit corner normals of one triangle
        for t in range(blk * 1024, min(T, blk * 1024 + 1024)):
            p0x, p0y, p0z = tri_p[t, 0, 0], tri_p[t, 0, 1], tri_p[t, 0, 2]
            e1x, e1y, e1z = tri_p[t, 1, 0] - p0x, tri_p[t, 1, 1] - p0y, tri_p[t, 1, 2] - p0z
            e2x, e2y, e2z = tri_p[t, 2, 0] - p0x, tri_p[t, 2, 1] - p0y, tri_p[t, 2, 2] - p0z
            ngx, ngy, ngz, lg = _unit3(e1y * e2z - e1z * e2y, e1z * e2x - e1x * e2z, e1x * e2y - e1y * e2x)
            sd = (x0[t, 0] - p0x) * ngx + (x0[t, 1] - p0y) * ngy + (x0[t, 2] - p0z) * ngz
            side = 0.0 if lg == 0.0 else (1.0 if sd > 0.0 else (-1.0 if sd < 0.0 else 0.0))
            out_side[t] = side
            # incoming cap (a, alpha)
            if has_incoming:
                ax, ay, az, alpha = inc_a[t, 0], inc_a[t, 1], inc_a[t, 2], inc_alpha[t]
            else:
                sx = sy = sz = 0.0
                for j in range(3):
                    w[j, 0], w[j, 1], w[j, 2], _l = _unit3(tri_p[t, j, 0] - x0[t, 0], tri_p[t, j, 1] - x0[t, 1],
                                                           tri_p[t, j, 2] - x0[t, 2])
                    sx += w[j, 0]
                    sy += w[j, 1]
                    sz += w[j, 2]
                ax, ay, az, _l = _unit3(sx, sy, sz)
                alpha = 0.0
                for j in range(3):
                    alpha = max(alpha, _angle3(ax, ay, az, w[j, 0], w[j, 1], w[j, 2]))
                if not alpha < half - 1e-9:
                    alpha = NO_CONE
            # normal cap (c, gamma) and whether the corner normals agree with the plane's side
            sx = sy = sz = 0.0
            pos = neg = 0
            for j in range(m):
                mu[j, 0], mu[j, 1], mu[j, 2], _l = _unit3(tri_n[t, j, 0], tri_n[t, j, 1], tri_n[t, j, 2])
                sx += mu[j, 0]
                sy += mu[j, 1]
                sz += mu[j, 2]
                mg = mu[j, 0] * ngx + mu[j, 1] * ngy + mu[j, 2] * ngz
                if mg > 0.0:
                    pos += 1
                elif mg < 0.0:
                    neg += 1
            cx, cy, cz, lc = _unit3(sx, sy, sz)
            gamma = 0.0
            for j in range(m):
                gamma = max(gamma, _angle3(cx, cy, cz, mu[j, 0], mu[j, 1], mu[j, 2]))
            if not (gamma < half - 1e-9 and lc > 0.0):
                gamma = NO_CONE
            consistent = pos == m or neg == m
            alpha += ANGLE_MARGIN
            gamma += ANGLE_MARGIN
            capped = alpha < NO_CONE and gamma < NO_CONE
            if not refract:
                ac = ax * cx + ay * cy + az * cz
                out_d[t, 0], out_d[t, 1], out_d[t, 2] = ax - 2.0 * ac * cx, ay - 2.0 * ac * cy, az - 2.0 * ac * cz
                out_theta[t] = alpha + 2.0 * gamma if capped else NO_CONE
                continue
            s = side * (1.0 if ngx * cx + ngy * cy + ngz * cz >= 0.0 else -1.0)
            r = 1.0 / eta[t] if s > 0.0 else eta[t]
            nox, noy, noz = s * cx, s * cy, s * cz
            cos_a = -(ax * nox + ay * noy + az * noz)
            theta_a = math.acos(min(1.0, max(-1.0, cos_a)))
            theta_max = theta_a + alpha + gamma
            sin_max = math.sin(min(theta_max, half))
            ok = (consistent and side != 0.0 and capped and cos_a > 0.0 and theta_max < half - 1e-6
                  and r * sin_max < 1.0 - 1e-9)
            cos_t_max = math.sqrt(max(1e-300, 1.0 - (r * sin_max) ** 2))
            lip = max(r, r * math.cos(min(theta_max, half)) / cos_t_max)
            k = 1.0 - r * r * (1.0 - cos_a * cos_a)
            f = r * cos_a - math.sqrt(max(k, 0.0))
            dx, dy, dz, _l = _unit3(r * ax + f * nox, r * ay + f * noy, r * az + f * noz)
            beta = min(alpha + gamma, math.pi)
            tx, ty, tz = r * (ax + cos_a * nox), r * (ay + cos_a * noy), r * (az + cos_a * noz)
            t_len = math.sqrt(tx * tx + ty * ty + tz * tz)
            sc = min(1.0, 1.0 / max(t_len, 1e-300))
            t0_len = min(t_len, 1.0)
            rest = math.sqrt(max(0.0, 1.0 - t0_len ** 2))
            axx, axy, axz, _l = _unit3(tx * sc - rest * nox, ty * sc - rest * noy, tz * sc - rest * noz)
            delta = r * 2.0 * math.sin(0.5 * beta) + max(0.0, t_len - 1.0)
            rho = t0_len + delta
            arc = delta / math.sqrt(max(1e-300, 1.0 - rho ** 2)) if rho < 1.0 else np.inf
            chord = 2.0 * math.asin(min(1.0, 0.5 * math.sqrt(delta ** 2 + 2.0 * delta)))
            tangential = gamma + min(arc, chord) + ANGLE_MARGIN
            ok_t = consistent and side != 0.0 and capped and tangential < math.pi
            if ok:
                out_theta[t] = min(gamma + lip * (alpha + gamma), tangential)
                out_d[t, 0], out_d[t, 1], out_d[t, 2] = dx, dy, dz
            else:
                out_theta[t] = tangential if ok_t else NO_CONE
                out_d[t, 0], out_d[t, 1], out_d[t, 2] = axx, axy, axz


class Emitters:
    """Per candidate emitter (a caster triangle, or a pair of them for two bounces): the last
    triangle's bounding sphere, plane and side rule, and the cap of scattered directions.

    ``side_req``: +1 / -1 the side of the last triangle's plane (ng = e1 x e2) the receiver
    point must be on, 0 no path at all, 2 unknown (no side test).  ``index`` (m, k) the
    caster indices (into the arrays the emitters were built from) of each emitter.

    Parts: an emitter may be split into parts (sub-regions of its first triangle), each with a
    smaller sphere that holds the last vertex and a narrower cap; a receiver point passes when
    one part accepts it.  By default an emitter is one part: its last triangle's bounding
    sphere and ``cap_d``/``cap_t``.  ``parts``: (start (n+1,), centre (p,3), radius (p,),
    cap axis (p,3), cap radius (p,)) in emitter order.
    """

    def __init__(self, index, tri_p_last, side_req, cap_d, cap_t, extra=None, parts=None):
        self.index = np.ascontiguousarray(index, dtype=np.int64).reshape(len(side_req), -1)
        self.tri_c, self.tri_r = tri_spheres(tri_p_last) if len(side_req) else (np.zeros((0, 3)), np.zeros(0))
        self.tri_ng = np.ascontiguousarray(geometric_normals(tri_p_last)[0]) if len(side_req) else np.zeros((0, 3))
        self.tri_p0 = np.ascontiguousarray(tri_p_last[:, 0]) if len(side_req) else np.zeros((0, 3))
        self.side_req = np.ascontiguousarray(side_req, dtype=np.float64)
        self.cap_d = np.ascontiguousarray(cap_d, dtype=np.float64)
        self.cap_t = np.ascontiguousarray(cap_t, dtype=np.float64)
        self.extra = extra or {}
        if parts is None:
            parts = (np.arange(self.size + 1, dtype=np.int64), self.tri_c, self.tri_r, self.cap_d, self.cap_t)
        self.part_start, self.part_c, self.part_r, self.part_d, self.part_t = (np.ascontiguousarray(a) for a in parts)
        self.part_start = self.part_start.astype(np.int64)

    @property
    def size(self):
        return self.side_req.shape[0]

    def without_cone(self):
        """Keep only the side tests: one part per emitter, its last triangle's sphere, no cap."""
        self.cap_t = np.full_like(self.cap_t, NO_CONE)
        self.part_start = np.arange(self.size + 1, dtype=np.int64)
        self.part_c, self.part_r, self.part_d, self.part_t = self.tri_c, self.tri_r, self.cap_d, self.cap_t
        return self


def one_bounce_emitters(chain, x0, tri_p, tri_n, eta):
    """Emitters of chain "R" or "T": one per caster triangle."""
    side, d, theta = scatter_caps(chain, x0, tri_p, tri_n, eta)
    return Emitters(np.arange(tri_p.shape[0]), tri_p, side if chain == "R" else -side, d, theta)


def two_bounce_emitters(chain, x0, tri_p1, tri_n1, eta1, tri_p2, tri_n2, eta2, ids1=None, ids2=None, same_ior=True, chunk=256,
                        subdivide=SUBDIVIDE):
    """Emitters of a two-bounce chain ("RR", "RT", "TR", "TT"): the (t1, t2) caster pairs that
    can carry light x0 -> t1 -> t2, with the cap of directions leaving t2.

    Pair test (conservative): t2's bounding sphere must reach t1's required side and the
    directions from t1 to t2 must meet t1's scattered cap; t2's incoming cap is the smaller of
    that scattered cap and the cap of directions t1 -> t2; t2's incoming side is known when t1
    lies wholly on one side of t2's plane (else T at t2 gets no cone and the receiver side is
    not tested).  ``ids1`` / ``ids2``: global triangle ids; pairs of a triangle with itself are
    skipped (a flat triangle cannot scatter light back onto itself).  ``same_ior``: keep only
    pairs with eta1 == eta2 (solve_tuples takes one IOR per tuple).

    ``subdivide`` > 1 splits every surviving pair into parts (:func:`pair_parts`): t1 is cut
    into subdivide² sub-triangles whose light is followed to t2 separately; a pair whose light
    misses t2 from every sub-triangle is dropped.
    """
    k1, k2 = chain[0], chain[1]
    side1, d1, th1 = scatter_caps(k1, x0, tri_p1, tri_n1, eta1)
    req1 = side1 if k1 == "R" else -side1
    c1, r1 = tri_spheres(tri_p1)
    c2, r2 = tri_spheres(tri_p2)
    ng1 = geometric_normals(tri_p1)[0]
    ng2, lg2 = geometric_normals(tri_p2)
    idx1, idx2, caps_d, caps_t, reqs, sides2 = [], [], [], [], [], []
    T1, T2 = tri_p1.shape[0], tri_p2.shape[0]
    for a0 in range(0, T1, chunk):
        a1 = min(T1, a0 + chunk)
        i1 = np.repeat(np.arange(a0, a1), T2)
        i2 = np.tile(np.arange(T2), a1 - a0)
        keep = (req1[i1] != 0) & (lg2[i2] > 0)
        if ids1 is not None:
            keep &= ids1[i1] != ids2[i2]
        if same_ior:
            keep &= eta1[i1] == eta2[i2]
        sd = np.sum((c2[i2] - tri_p1[i1, 0]) * ng1[i1], axis=1)
        keep &= req1[i1] * sd > -r2[i2]
        i1, i2 = i1[keep], i2[keep]
        u = c2[i2] - c1[i1]
        dist = np.linalg.norm(u, axis=1)
        reach = r1[i1] + r2[i2]
        u = u / np.maximum(dist, 1e-300)[:, None]
        beta = np.where(dist > reach, np.arcsin(np.minimum(1.0, reach / np.maximum(dist, 1e-300))) + ANGLE_MARGIN, NO_CONE)
        theta1 = th1[i1]
        ang = np.arctan2(np.linalg.norm(np.cross(d1[i1], u), axis=1), np.sum(d1[i1] * u, axis=1))
        meets = (theta1 >= NO_CONE) | (beta >= NO_CONE) | (theta1 + beta >= math.pi) | (ang <= theta1 + beta)
        i1, i2, u, beta, theta1 = i1[meets], i2[meets], u[meets], beta[meets], theta1[meets]
        use1 = theta1 <= beta
        a_in = np.where(use1[:, None], d1[i1], u)
        al_in = np.where(use1, theta1, beta)
        # Side of t2 the light comes from: all of t1 on one side of t2's plane.
        sv = np.einsum("tjk,tk->tj", tri_p1[i1] - tri_p2[i2, 0][:, None, :], ng2[i2])
        # (a vertex shared with t2 lies in its plane: the rest of t1 decides; points of t1 in
        # t2's plane carry no path through t2's interior)
        tol = 1e-12 * (r1[i1] + r2[i2])[:, None]
        s2 = np.where(np.all(sv >= -tol, axis=1) & np.any(sv > tol, axis=1), 1.0,
                      np.where(np.all(sv <= tol, axis=1) & np.any(sv < -tol, axis=1), -1.0, 0.0))
        d2, th2 = propagate_cap(k2, a_in, al_in, tri_n2[i2], ng2[i2], s2, eta2[i2])
        req2 = np.where(s2 == 0, 2.0, s2 if k2 == "R" else -s2)
        idx1.append(i1)
        idx2.append(i2)
        caps_d.append(d2)
        caps_t.append(th2)
        reqs.append(req2)
        sides2.append(s2)
    cat = (lambda xs, shape: np.concatenate(xs) if xs else np.zeros(shape))  # noqa: E731
    i1, i2 = cat(idx1, (0,)).astype(np.int64), cat(idx2, (0,)).astype(np.int64)
    req2, d2, th2, s2 = cat(reqs, (0,)), cat(caps_d, (0, 3)), cat(caps_t, (0,)), cat(sides2, (0,))
    if subdivide <= 1 or i1.size == 0:
        return Emitters(np.column_stack([i1, i2]), tri_p2[i2], req2, d2, th2)
    keep, parts = pair_parts(chain, x0, tri_p1, tri_n1, eta1, tri_p2, tri_n2, eta2, i1, i2, d2, th2, s2, subdivide, chunk)
    return Emitters(np.column_stack([i1[keep], i2[keep]]), tri_p2[i2[keep]], req2[keep], d2[keep], th2[keep], parts=parts)


def sub_triangles(s):
    """Barycentric corners (s², 3, 2) of the s² congruent sub-triangles of the unit triangle."""
    out = []
    for i in range(s):
        for j in range(s - i):
            out.append([(i, j), (i + 1, j), (i, j + 1)])
            if i + j < s - 1:
                out.append([(i + 1, j), (i + 1, j + 1), (i, j + 1)])
    return np.array(out, dtype=np.float64) / s


def pair_parts(chain, x0, tri_p1, tri_n1, eta1, tri_p2, tri_n2, eta2, i1, i2, d2, th2, s2, subdivide, chunk=256):
    """Split two-bounce pairs (t1 = tri_p1[i1], t2 = tri_p2[i2]) into parts; returns (keep (n,) bool,
    parts in the layout of :class:`Emitters`) for the kept pairs.

    For each sub-triangle of t1 (its corners and interpolated corner normals; the normal field is
    linear over it, so the cap bounds hold for it as for a triangle):
    1. the cap (a, alpha) of directions it scatters light from x0 into (:func:`scatter_caps`);
    2. the footprint of those rays on t2's plane (unit normal n2): for a ray origin o = c + δ in
       the sub-triangle's sphere (c, r) and a direction d in the cap, the hit is
       x2 = [c + (h_c / (d.n2)) d] + [δ - ((δ.n2) / (d.n2)) d] with h_c = (p2 - c).n2; the second
       term is an oblique projection of δ, at most r / |d.n2| long.  When d.n2 keeps one sign over
       the cap (d.n2 in [cos(phi + alpha), cos(phi - alpha)], phi = angle(a, n2)), the distance
       t = |h_c| / |d.n2| is in [t_lo, t_hi] and x2 lies within
       r / min|d.n2| + t_hi 2 sin(alpha / 2) + (t_hi - t_lo) / 2 of c ± a (t_lo + t_hi) / 2
       (the sign of h_c d.n2: hits behind the origin are included, which only loosens the bound);
    3. the footprint must reach t2: with the barycentric gradients g_u, g_v on t2's plane, the
       barycentrics of the footprint lie within R |g| of the centre's; a footprint wholly outside
       the triangle (beyond 1e-6) carries no path, and the part is dropped;
    4. t2's normals over that barycentric box (the four box corners of the linear normal field)
       and the incoming cap (the smaller of the scattered cap and the cap of directions from the
       sub-triangle's sphere to the footprint) give the cap of directions leaving t2
       (:func:`propagate_cap`); a refraction at t2 that is total everywhere (:func:`all_tir`)
       drops the part.
    The part is (footprint sphere, that cap).  Where a footprint is not bounded (no cap at t1,
    a ray that may run parallel to t2's plane) the pair keeps one part: t2's sphere and the
    pair's own cap (d2, th2), as without subdivision.  A pair with no part left is dropped.
    """
    k1, k2 = chain[0], chain[1]
    sub = sub_triangles(subdivide)  # (K, 3, 2)
    K = sub.shape[0]
    c2, r2 = tri_spheres(tri_p2)
    ng2, lg2 = geometric_normals(tri_p2)
    e21 = tri_p2[:, 1] - tri_p2[:, 0]
    e22 = tri_p2[:, 2] - tri_p2[:, 0]
    twice_area = np.maximum(lg2, 1e-300)[:, None]
    g_u = np.cross(e22, ng2) / twice_area  # u(x) = g_u . (x - p0): barycentric gradients on the plane
    g_v = np.cross(ng2, e21) / twice_area
    n = i1.size
    keep = np.zeros(n, dtype=bool)
    count = np.zeros(n, dtype=np.int64)
    pc, pr, pd, pt = [], [], [], []
    for q0 in range(0, n, chunk):
        q1 = min(n, q0 + chunk)
        a1, a2 = i1[q0:q1], i2[q0:q1]
        m = q1 - q0
        # sub-triangle corners and normals: (m, K, 3, 3)
        bu = sub[None, :, :, 0, None]
        bv = sub[None, :, :, 1, None]
        P1 = tri_p1[a1][:, None, None, :, :]
        N1 = tri_n1[a1][:, None, None, :, :]
        sp = P1[..., 0, :] + bu * (P1[..., 1, :] - P1[..., 0, :]) + bv * (P1[..., 2, :] - P1[..., 0, :])
        sn = N1[..., 0, :] + bu * (N1[..., 1, :] - N1[..., 0, :]) + bv * (N1[..., 2, :] - N1[..., 0, :])
        sp = sp.reshape(m * K, 3, 3)
        sn = sn.reshape(m * K, 3, 3)
        rep = np.repeat(np.arange(q0, q1), K)  # pair index per row
        t1r, t2r = i1[rep], i2[rep]
        _, a, alpha = scatter_caps(k1, x0[t1r], sp, sn, eta1[t1r])
        cs, rs = tri_spheres(sp)
        nrm = ng2[t2r]
        hc = np.abs(np.sum((tri_p2[t2r, 0] - cs) * nrm, axis=1))
        phi = np.arccos(np.clip(np.sum(a * nrm, axis=1), -1.0, 1.0))
        al = np.minimum(alpha, math.pi)
        dn_hi = np.cos(np.maximum(phi - al, 0.0))
        dn_lo = np.cos(np.minimum(phi + al, math.pi))
        pos = dn_lo > 1e-6
        neg = dn_hi < -1e-6
        bounded = (alpha < NO_CONE) & (pos | neg)
        dn_min = np.where(pos, dn_lo, -dn_hi)
        dn_max = np.where(pos, dn_hi, -dn_lo)
        with np.errstate(divide="ignore", invalid="ignore"):
            t_lo = np.where(bounded, hc / dn_max, 0.0)
            t_hi = np.where(bounded, hc / dn_min, 0.0)
            shift = np.where(bounded, rs / dn_min, 0.0)
        cf = cs + np.sign(np.sum(a * nrm, axis=1) * np.sum((tri_p2[t2r, 0] - cs) * nrm, axis=1))[:, None] * 0.5 * (t_lo + t_hi)[:, None] * a
        rad = (shift + t_hi * 2.0 * np.sin(0.5 * al) + 0.5 * (t_hi - t_lo)) * (1.0 + 1e-9) + 1e-12 * (rs + r2[t2r])
        # barycentric box of the footprint on t2
        rel = cf - tri_p2[t2r, 0]
        uc = np.sum(g_u[t2r] * rel, axis=1)
        vc = np.sum(g_v[t2r] * rel, axis=1)
        du = rad * np.linalg.norm(g_u[t2r], axis=1)
        dv = rad * np.linalg.norm(g_v[t2r], axis=1)
        dw = rad * np.linalg.norm(g_u[t2r] + g_v[t2r], axis=1)
        tol = 1e-6
        reaches = (uc + du >= -tol) & (vc + dv >= -tol) & (1.0 - uc - vc + dw >= -tol)
        # pairs with an unbounded sub-triangle keep their pair-level part only
        fallback = np.zeros(m, dtype=bool)
        np.logical_or.at(fallback, rep - q0, ~bounded)
        use = bounded & reaches & ~fallback[rep - q0]
        ulo = np.clip(uc - du, -tol, 1.0 + tol)[use]
        uhi = np.clip(uc + du, -tol, 1.0 + tol)[use]
        vlo = np.clip(vc - dv, -tol, 1.0 + tol)[use]
        vhi = np.clip(vc + dv, -tol, 1.0 + tol)[use]
        tu = t2r[use]
        N2 = tri_n2[tu]
        corners = []
        for uu, vv in ((ulo, vlo), (uhi, vlo), (ulo, vhi), (uhi, vhi)):
            corners.append(N2[:, 0] + uu[:, None] * (N2[:, 1] - N2[:, 0]) + vv[:, None] * (N2[:, 2] - N2[:, 0]))
        n4 = np.stack(corners, axis=1)
        # incoming cap at t2: the scattered cap or the directions sub-triangle -> footprint
        dvec = cf[use] - cs[use]
        dist = np.linalg.norm(dvec, axis=1)
        reach = rs[use] + rad[use]
        u_dir = dvec / np.maximum(dist, 1e-300)[:, None]
        beta = np.where(dist > reach, np.arcsin(np.minimum(1.0, reach / np.maximum(dist, 1e-300))) + ANGLE_MARGIN, NO_CONE)
        take_dir = beta < alpha[use]
        a_in = np.where(take_dir[:, None], u_dir, a[use])
        al_in = np.where(take_dir, beta, alpha[use])
        d_out, t_out = propagate_cap(k2, a_in, al_in, n4, ng2[tu], s2[rep[use]], eta2[tu])
        owner = rep[use]
        if k2 == "T":  # light that is totally reflected at t2 everywhere carries no path
            live = ~all_tir(a_in, al_in, n4, ng2[tu], s2[owner], eta2[tu])
            owner, d_out, t_out = owner[live], d_out[live], t_out[live]
            use[np.flatnonzero(use)[~live]] = False
        fb = np.flatnonzero(fallback) + q0
        # parts in pair order: the refined ones, then one fallback part per fallback pair
        o_all = np.concatenate([owner, fb])
        c_all = np.concatenate([cf[use], c2[i2[fb]]])
        r_all = np.concatenate([rad[use], r2[i2[fb]]])
        d_all = np.concatenate([d_out, d2[fb]])
        t_all = np.concatenate([t_out, th2[fb]])
        order = np.argsort(o_all, kind="stable")
        pc.append(c_all[order])
        pr.append(r_all[order])
        pd.append(d_all[order])
        pt.append(t_all[order])
        np.add.at(count, o_all, 1)
    keep = count > 0
    start = np.concatenate([[0], np.cumsum(count[keep])]).astype(np.int64)
    cat = (lambda xs, shape: np.concatenate(xs) if xs else np.zeros(shape))  # noqa: E731
    return keep, (start, cat(pc, (0, 3)), cat(pr, (0,)), cat(pd, (0, 3)), cat(pt, (0,)))


def tri_spheres(tri_p):
    """Bounding spheres (centre = centroid, radius = max vertex distance) of triangles."""
    c = tri_p.mean(axis=1)
    r = np.max(np.linalg.norm(tri_p - c[:, None, :], axis=2), axis=1)
    return c, r * (1.0 + 1e-12) + 1e-300


def tile_spheres(texel, width, position):
    """Group samples by 8x8-texel tiles: (order, tile_start (nt+1,), centre (nt,3), radius (nt,)).

    ``order`` sorts the samples tile by tile (stable), tile k holding
    order[tile_start[k]:tile_start[k+1]].
    """
    i = texel % width
    j = texel // width
    tiles_x = (width + TILE - 1) // TILE
    key = (j // TILE) * tiles_x + i // TILE
    order = np.argsort(key, kind="stable")
    k_sorted = key[order]
    uniq, start = np.unique(k_sorted, return_index=True)
    tile_start = np.append(start, order.size).astype(np.int64)
    pos = position[order]
    nt = uniq.size
    centre = np.add.reduceat(pos, start, axis=0) / np.diff(tile_start)[:, None] if nt else np.zeros((0, 3))
    tile_of = np.repeat(np.arange(nt), np.diff(tile_start))
    radius = np.zeros(nt)
    if nt:
        dist = np.linalg.norm(pos - centre[tile_of], axis=1)
        np.maximum.at(radius, tile_of, dist)
    return order.astype(np.int64), tile_start, centre, radius * (1.0 + 1e-12) + 1e-12


@kernel(inline="always")
def _cap_meets(dx, dy, dz, cx, cy, cz, theta, reach):
    """Whether cap (d, theta) meets the cap of directions to a sphere at c (relative) of radius ``reach``."""
    if theta >= NO_CONE:
        return True
    dist = math.sqrt(cx * cx + cy * cy + cz * cz)
    if not dist > reach:
        return True
    beta = math.asin(reach / dist) + ANGLE_MARGIN
    if theta + beta >= math.pi:
        return True
    crx = dy * cz - dz * cy
    cry = dz * cx - dx * cz
    crz = dx * cy - dy * cx
    ang = math.atan2(math.sqrt(crx * crx + cry * cry + crz * crz), dx * cx + dy * cy + dz * cz)
    return ang <= theta + beta


# The emitter arrays every kernel below takes, in this order (``E`` in the signatures):
# part_start, part_c, part_r, part_d, part_t, tri_ng, tri_p0, side_req.


@parallel_range("side_req")
def count_cone_pairs(part_start, part_c, part_r, part_d, part_t, tri_ng, tri_p0, side_req, tile_c, tile_r, count, first, last):
    for t in range(first, last):
        c = 0
        for k in range(tile_c.shape[0]):
            if _tile_ok(t, k, part_start, part_c, part_r, part_d, part_t, tri_ng, tri_p0, side_req, tile_c, tile_r):
                c += 1
        count[t] = c


@parallel_range("side_req")
def fill_cone_pairs(part_start, part_c, part_r, part_d, part_t, tri_ng, tri_p0, side_req, tile_c, tile_r, offset, out_tile, first, last):
    for t in range(first, last):
        o = offset[t]
        for k in range(tile_c.shape[0]):
            if _tile_ok(t, k, part_start, part_c, part_r, part_d, part_t, tri_ng, tri_p0, side_req, tile_c, tile_r):
                out_tile[o] = k
                o += 1


@kernel(inline="always")
def _tile_ok(t, k, part_start, part_c, part_r, part_d, part_t, tri_ng, tri_p0, side_req, tile_c, tile_r):
    req = side_req[t]
    if req == 0.0:
        return False
    # Side: the tile's sphere must reach the required side of the caster's plane.
    sd = ((tile_c[k, 0] - tri_p0[t, 0]) * tri_ng[t, 0] + (tile_c[k, 1] - tri_p0[t, 1]) * tri_ng[t, 1]
          + (tile_c[k, 2] - tri_p0[t, 2]) * tri_ng[t, 2])
    if req != 2.0 and req * sd <= -tile_r[k]:
        return False
    for p in range(part_start[t], part_start[t + 1]):
        if _cap_meets(part_d[p, 0], part_d[p, 1], part_d[p, 2], tile_c[k, 0] - part_c[p, 0], tile_c[k, 1] - part_c[p, 1],
                      tile_c[k, 2] - part_c[p, 2], part_t[p], part_r[p] + tile_r[k]):
            return True
    return False


@kernel(inline="always")
def sample_in_cones(t, s, part_start, part_c, part_r, part_d, part_t, tri_ng, tri_p0, side_req, pos, rec_ng):
    req = side_req[t]
    sd = ((pos[s, 0] - tri_p0[t, 0]) * tri_ng[t, 0] + (pos[s, 1] - tri_p0[t, 1]) * tri_ng[t, 1]
          + (pos[s, 2] - tri_p0[t, 2]) * tri_ng[t, 2])
    if req == 0.0 or (req != 2.0 and not req * sd > 0.0):
        return False
    for p in range(part_start[t], part_start[t + 1]):
        # Receiver front side: some point of the part's sphere must be in front of the sample.
        cx = part_c[p, 0] - pos[s, 0]
        cy = part_c[p, 1] - pos[s, 1]
        cz = part_c[p, 2] - pos[s, 2]
        if cx * rec_ng[s, 0] + cy * rec_ng[s, 1] + cz * rec_ng[s, 2] <= -part_r[p]:
            continue
        if _cap_meets(part_d[p, 0], part_d[p, 1], part_d[p, 2], -cx, -cy, -cz, part_t[p], part_r[p]):
            return True
    return False


@parallel_range("pair_tri")
def _emit_count(pair_tri, pair_tile, tile_start, order, part_start, part_c, part_r, part_d, part_t, tri_ng, tri_p0, side_req,
                pos, rec_ng, count, first, last):
    for q in range(first, last):
        t = pair_tri[q]
        k = pair_tile[q]
        c = 0
        for z in range(tile_start[k], tile_start[k + 1]):
            if sample_in_cones(t, order[z], part_start, part_c, part_r, part_d, part_t, tri_ng, tri_p0, side_req, pos, rec_ng):
                c += 1
        count[q] = c


@parallel_range("pair_tri")
def _emit_fill(pair_tri, pair_tile, tile_start, order, part_start, part_c, part_r, part_d, part_t, tri_ng, tri_p0, side_req,
               pos, rec_ng, offset, out_tri, out_sample, first, last):
    for q in range(first, last):
        t = pair_tri[q]
        k = pair_tile[q]
        o = offset[q]
        for z in range(tile_start[k], tile_start[k + 1]):
            s = order[z]
            if sample_in_cones(t, s, part_start, part_c, part_r, part_d, part_t, tri_ng, tri_p0, side_req, pos, rec_ng):
                out_tri[o] = t
                out_sample[o] = s
                o += 1


class TupleCull:
    """Candidate (emitter, sample) tuples of one chain, one light point set and one sample band.

    ``emitters``: :class:`Emitters` (one_bounce_emitters / two_bounce_emitters).  Iterate
    :meth:`batches` for (emitter index (n,), sample index (n,)) arrays of at most about
    ``max_tuples`` tuples (one tile pair may exceed it), in a fixed order.
    """

    def __init__(self, emitters, band_pos, band_geo_normal, band_texel, width):
        e = emitters
        self.emitters = e
        self.arrays = (e.part_start, e.part_c, e.part_r, e.part_d, e.part_t, e.tri_ng, e.tri_p0, e.side_req)
        self.pos = np.ascontiguousarray(band_pos)
        self.rec_ng = np.ascontiguousarray(band_geo_normal)
        self.order, self.tile_start, self.tile_c, self.tile_r = tile_spheres(band_texel, width, band_pos)
        T = e.size
        count = np.zeros(T, dtype=np.int64)
        args = self.arrays + (self.tile_c, self.tile_r)
        if T and self.tile_c.shape[0]:
            count_cone_pairs(*args, count)
        offset = np.concatenate([[0], np.cumsum(count)]).astype(np.int64)
        self.pair_tile = np.zeros(offset[-1], dtype=np.int64)
        if offset[-1]:
            fill_cone_pairs(*args, offset[:-1].copy(), self.pair_tile)
        self.pair_tri = np.repeat(np.arange(T, dtype=np.int64), count)
        self.pair_size = np.diff(self.tile_start)[self.pair_tile] if self.pair_tile.size else np.zeros(0, dtype=np.int64)

    @property
    def upper_bound(self):
        """Tuples in the surviving tiles (before the per-sample test)."""
        return int(self.pair_size.sum())

    def batches(self, max_tuples):
        n_pairs = self.pair_tri.shape[0]
        q = 0
        csum = np.cumsum(self.pair_size)
        while q < n_pairs:
            base = csum[q - 1] if q else 0
            q1 = int(np.searchsorted(csum, base + max_tuples, side="right"))
            q1 = max(q1, q + 1)
            pt = self.pair_tri[q:q1]
            pk = self.pair_tile[q:q1]
            cnt = np.zeros(pt.shape[0], dtype=np.int64)
            common = (self.tile_start, self.order) + self.arrays + (self.pos, self.rec_ng)
            _emit_count(pt, pk, *common, cnt)
            off = np.concatenate([[0], np.cumsum(cnt)]).astype(np.int64)
            out_t = np.empty(off[-1], dtype=np.int64)
            out_s = np.empty(off[-1], dtype=np.int64)
            if off[-1]:
                _emit_fill(pt, pk, *common, off[:-1].copy(), out_t, out_s)
            q = q1
            if out_t.size:
                yield out_t, out_s


REACH_DEPTH = 6  # levels of the target sphere tree below its root: 64 leaves
REACH_PIECES = 1 << 14  # target triangles are cut to at most about this many pieces
REACH_BLOCK = 256  # emitters per parallel work item of the reach test


def _split_large(tri_p, max_radius, max_pieces):
    """Midpoint-subdivide the triangles whose bounding sphere exceeds ``max_radius`` (at most
    about ``max_pieces`` pieces in all); the pieces cover the triangles exactly."""
    _, r = tri_spheres(tri_p)
    while tri_p.shape[0] < max_pieces and np.any(r > max_radius):
        big = r > max_radius
        budget = (max_pieces - tri_p.shape[0]) // 3
        if budget <= 0:
            break
        idx = np.flatnonzero(big)[np.argsort(-r[big], kind="stable")][:budget]
        a, b, c = tri_p[idx, 0], tri_p[idx, 1], tri_p[idx, 2]
        ab, bc, ca = 0.5 * (a + b), 0.5 * (b + c), 0.5 * (c + a)
        pieces = np.stack([np.stack(q, 1) for q in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
        rest = np.ones(tri_p.shape[0], dtype=bool)
        rest[idx] = False
        tri_p = np.concatenate([tri_p[rest], pieces.reshape(-1, 3, 3)])
        _, r = tri_spheres(tri_p)
    return tri_p


def sphere_tree(tri_p, depth=REACH_DEPTH, pieces=REACH_PIECES):
    """A complete binary tree of bounding spheres over triangles (node k's children 2k+1 and
    2k+2; ``depth`` levels below the root; an empty node has radius -1).  Large triangles are
    first cut into pieces so that the leaves are small (radius about 1/32 of the whole set's);
    groups are split at the median of their pieces' centroids along the longest extent.  Every
    node's sphere holds every piece below it whole.  Returns (centre (n,3), radius (n,))."""
    tri_p = np.asarray(tri_p, dtype=np.float64)
    n_nodes = (1 << (depth + 1)) - 1
    centre = np.zeros((n_nodes, 3))
    radius = np.full(n_nodes, -1.0)
    if tri_p.shape[0] == 0:
        return centre, radius
    lo, hi = point_bounds(tri_p.reshape(-1, 3))
    tri_p = _split_large(tri_p, 0.5 * np.linalg.norm(hi - lo) / 32.0, pieces)
    c, r = tri_spheres(tri_p)
    groups = {0: np.arange(c.shape[0])}
    for k in range(n_nodes):
        g = groups.pop(k, None)
        if g is None or g.size == 0:
            continue
        lo, hi = c[g].min(axis=0), c[g].max(axis=0)
        centre[k] = 0.5 * (lo + hi)
        radius[k] = np.max(np.linalg.norm(c[g] - centre[k], axis=1) + r[g]) * (1.0 + 1e-12) + 1e-12
        if 2 * k + 2 < n_nodes:
            if g.size == 1:
                groups[2 * k + 1] = g
                continue
            order = g[np.argsort(c[g, int(np.argmax(hi - lo))], kind="stable")]
            groups[2 * k + 1], groups[2 * k + 2] = order[:g.size // 2], order[g.size // 2:]
    return centre, radius


def first_casters_reaching(chain, x0, tri_p1, tri_n1, eta1, target_p, tree=None):
    """Mask (T1,) of the first-vertex caster triangles whose scattered light can reach a target
    triangle: the receivers' triangles for a one-bounce chain, the second-vertex casters' for
    a two-bounce one (light that reaches no second caster reaches no receiver through it).

    The test is the cone test of this module (side rule of the first vertex and the cap of
    its scattered directions, :func:`one_bounce_emitters`) against the spheres of
    :func:`sphere_tree` over the targets, descended from the root while a node passes (a leaf
    that passes keeps the triangle): conservative, a triangle with a path is never dropped
    (``tests/bake/test_bake_bounds_select.py`` checks it against forward-traced paths), and its
    cost is O(T1 log leaves) for most triangles.  ``x0`` (3,) or (T1, 3); ``tree`` the
    targets' :func:`sphere_tree` when the caller has it (casters tested in several calls)."""
    T1 = tri_p1.shape[0]
    keep = np.zeros(T1, dtype=np.bool_)
    target_p = np.asarray(target_p, dtype=np.float64)
    if T1 == 0 or target_p.shape[0] == 0:
        return keep
    tri_p1 = np.ascontiguousarray(tri_p1, dtype=np.float64)
    x0 = np.asarray(x0, dtype=np.float64)
    x0 = np.array(np.broadcast_to(x0.reshape(-1, 3), (T1, 3)))
    eta1 = np.array(np.broadcast_to(np.asarray(eta1, dtype=np.float64), (T1,)))
    side, cap_d, cap_t = scatter_caps(chain[0], x0, tri_p1, np.ascontiguousarray(tri_n1, dtype=np.float64), eta1)
    centre, radius = sphere_tree(target_p) if tree is None else tree
    _reach_casters(tri_p1, side if chain[0] == "R" else -side, cap_d, cap_t, centre, radius, keep)
    return keep


@kernel(inline="always")
def _sphere_in_cap(dx, dy, dz, cos_t, sin_t, cx, cy, cz, reach):
    """:func:`_cap_meets` without trigonometry, for a cap of radius theta given as cos_t, sin_t
    of theta + ANGLE_MARGIN (< pi): the sphere at c (relative) of radius ``reach`` is seen
    within the cap when angle(d, c) <= theta + ANGLE_MARGIN + asin(reach / |c|), i.e. d . c >=
    |c| cos(theta + ANGLE_MARGIN + beta) = |c| (cos_t cos(beta) - sin_t sin(beta)), the sum of
    the angles being below pi (else every direction)."""
    dist = math.sqrt(cx * cx + cy * cy + cz * cz)
    if not dist > reach:
        return True
    sb = reach / dist
    cb = math.sqrt(max(0.0, 1.0 - sb * sb))
    if sin_t * cb + cos_t * sb <= 0.0:
        return True  # theta + beta >= pi (its sine <= 0 on [0, 3 pi / 2)): every direction
    return dx * cx + dy * cy + dz * cz >= dist * (cos_t * cb - sin_t * sb) - 1e-12 * dist


@parallel_range("side_req", REACH_BLOCK)
def _reach_casters(tri_p, side_req, cap_d, cap_t, node_c, node_r, keep, first, last):
    """keep[t] = some leaf of the sphere tree passes the cone test of caster t: the side rule of
    its plane (``side_req`` +1 / -1, 0 no path) and the cap (``cap_d``, ``cap_t``) of its scattered
    directions from its bounding sphere (centroid, farthest corner) meeting the node's sphere
    (:func:`_sphere_in_cap`), depth first, a node that fails pruning its subtree, the child
    nearer the cap's axis descended first.  The stack holds at most 2 (depth + 1) nodes."""
    n_nodes = node_r.shape[0]
    n = side_req.shape[0]
    for block in range(first, last):
        stack = np.empty(128, dtype=np.int64)
        for t in range(block * REACH_BLOCK, min(n, (block + 1) * REACH_BLOCK)):
            req = side_req[t]
            if req == 0.0:
                continue
            p0x, p0y, p0z = tri_p[t, 0, 0], tri_p[t, 0, 1], tri_p[t, 0, 2]
            qx = (p0x + tri_p[t, 1, 0] + tri_p[t, 2, 0]) / 3.0
            qy = (p0y + tri_p[t, 1, 1] + tri_p[t, 2, 1]) / 3.0
            qz = (p0z + tri_p[t, 1, 2] + tri_p[t, 2, 2]) / 3.0
            rt = 0.0
            for j in range(3):
                ex, ey, ez = tri_p[t, j, 0] - qx, tri_p[t, j, 1] - qy, tri_p[t, j, 2] - qz
                rt = max(rt, math.sqrt(ex * ex + ey * ey + ez * ez))
            rt = rt * (1.0 + 1e-12) + 1e-300
            e1x, e1y, e1z = tri_p[t, 1, 0] - p0x, tri_p[t, 1, 1] - p0y, tri_p[t, 1, 2] - p0z
            e2x, e2y, e2z = tri_p[t, 2, 0] - p0x, tri_p[t, 2, 1] - p0y, tri_p[t, 2, 2] - p0z
            ngx, ngy, ngz, _lg = _unit3(e1y * e2z - e1z * e2y, e1z * e2x - e1x * e2z, e1x * e2y - e1y * e2x)
            theta = cap_t[t] + ANGLE_MARGIN
            every = cap_t[t] >= NO_CONE or theta >= math.pi
            cos_t, sin_t = math.cos(theta), math.sin(theta)
            dx, dy, dz = cap_d[t, 0], cap_d[t, 1], cap_d[t, 2]
            stack[0] = 0
            top = 1
            while top > 0:
                top -= 1
                k = stack[top]
                if node_r[k] < 0.0:
                    continue
                # side: the node's sphere must reach the required side of the caster's plane
                sd = (node_c[k, 0] - p0x) * ngx + (node_c[k, 1] - p0y) * ngy + (node_c[k, 2] - p0z) * ngz
                if req != 2.0 and req * sd <= -node_r[k]:
                    continue
                if not every and not _sphere_in_cap(dx, dy, dz, cos_t, sin_t, node_c[k, 0] - qx, node_c[k, 1] - qy,
                                                    node_c[k, 2] - qz, rt + node_r[k]):
                    continue
                if 2 * k + 2 >= n_nodes:  # a leaf
                    keep[t] = True
                    break
                a, b = 2 * k + 1, 2 * k + 2
                ax, ay, az = node_c[a, 0] - qx, node_c[a, 1] - qy, node_c[a, 2] - qz
                bx, by, bz = node_c[b, 0] - qx, node_c[b, 1] - qy, node_c[b, 2] - qz
                la = math.sqrt(ax * ax + ay * ay + az * az)
                lb = math.sqrt(bx * bx + by * by + bz * bz)
                # the child nearer the cap's axis on top (popped first): a reaching caster stops sooner
                if (dx * ax + dy * ay + dz * az) * lb >= (dx * bx + dy * by + dz * bz) * la:
                    stack[top] = b
                    stack[top + 1] = a
                else:
                    stack[top] = a
                    stack[top + 1] = b
                top += 2


class OneBounceCull(TupleCull):
    """TupleCull of a one-bounce chain: emitter index = caster index.  ``use_cone`` False keeps
    only the side tests."""

    def __init__(self, chain, x0, tri_p, tri_n, eta, band_pos, band_geo_normal, band_texel, width, use_cone=True):
        e = one_bounce_emitters(chain, x0, tri_p, tri_n, eta)
        if not use_cone:
            e.without_cone()
        super().__init__(e, band_pos, band_geo_normal, band_texel, width)
