"""The per-sub-triangle flux terms of the ``forward-flux`` estimator as Numba kernels.

The forward image (:mod:`.forward_image`) gives final sub-triangles: their corners in the
first triangle's barycentrics, their corner and edge-midpoint images in UV.  Their flux is

- point light x0: Ω(x0, corners) (the solid angle, Van Oosterom & Strackee 1983) times the
  light's emission factor; sun of direction d: the area across the beam ½ |g · d|, g the
  cross product of the corners' edges;

spread over the image with a density linear over it, the corner densities
ρ_i = w_i f_i / |det J_i| (w the light's solid angle per barycentric area
|n · (p - x0)| / |p - x0|³, f the transport factor, J_i the quadratic image's Jacobian at
corner i), normalised to mean 1, or (1, 1, 1) near a fold (the det J_i differ in sign, or
by more than 4x), without midpoints, or for a sliver image (aspect above ``SLIVER``).
These are the same equations, evaluated in the same order, as the numpy forms
:func:`.forward_image.solid_angle` and :func:`.forward_image.corner_densities` (which stay
as the reference: tests/solver/test_solver_flux_kernel.py compares them); here one pass
over the rows, threads over independent rows, no temporaries.
"""

import math

import numpy as np

from ..runtime.jit import kernel, parallel_range

SLIVER = 4.0  # as forward_image.SLIVER
FOLD_RATIO = 4.0  # corner densities differing by more than this: the uniform splat


@kernel(inline="always")
def _corner(tri_p, t, b0, b1, k):
    """Coordinate k of the point (b0, b1) of triangle t."""
    a = tri_p[t, 0, k]
    return a + b0 * (tri_p[t, 1, k] - a) + b1 * (tri_p[t, 2, k] - a)


@parallel_range("emitter")
def subtriangle_geometry(tri_p, t1_of, emitter, bary, x0, sun, d, out_x1, out_power, first, last):
    """Centroid ``out_x1`` (m, 3) and power factor ``out_power`` (m,) of the sub-triangles
    with corners ``bary`` (m, 3, 2) on first triangles t1_of[emitter]: the solid angle seen
    from x0[emitter] (point light), or with ``sun`` the area across direction ``d`` (3,)."""
    for i in range(first, last):
        e = emitter[i]
        t = t1_of[e]
        ax = _corner(tri_p, t, bary[i, 0, 0], bary[i, 0, 1], 0)
        ay = _corner(tri_p, t, bary[i, 0, 0], bary[i, 0, 1], 1)
        az = _corner(tri_p, t, bary[i, 0, 0], bary[i, 0, 1], 2)
        bx = _corner(tri_p, t, bary[i, 1, 0], bary[i, 1, 1], 0)
        by = _corner(tri_p, t, bary[i, 1, 0], bary[i, 1, 1], 1)
        bz = _corner(tri_p, t, bary[i, 1, 0], bary[i, 1, 1], 2)
        cx = _corner(tri_p, t, bary[i, 2, 0], bary[i, 2, 1], 0)
        cy = _corner(tri_p, t, bary[i, 2, 0], bary[i, 2, 1], 1)
        cz = _corner(tri_p, t, bary[i, 2, 0], bary[i, 2, 1], 2)
        out_x1[i, 0] = (ax + bx + cx) / 3.0
        out_x1[i, 1] = (ay + by + cy) / 3.0
        out_x1[i, 2] = (az + bz + cz) / 3.0
        if sun:
            ux, uy, uz = bx - ax, by - ay, bz - az
            vx, vy, vz = cx - ax, cy - ay, cz - az
            gx = uy * vz - uz * vy
            gy = uz * vx - ux * vz
            gz = ux * vy - uy * vx
            out_power[i] = 0.5 * abs(gx * d[0] + gy * d[1] + gz * d[2])
        else:
            px, py, pz = x0[e, 0], x0[e, 1], x0[e, 2]
            ax, ay, az = ax - px, ay - py, az - pz
            bx, by, bz = bx - px, by - py, bz - pz
            cx, cy, cz = cx - px, cy - py, cz - pz
            la = math.sqrt(ax * ax + ay * ay + az * az)
            lb = math.sqrt(bx * bx + by * by + bz * bz)
            lc = math.sqrt(cx * cx + cy * cy + cz * cz)
            num = abs(ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx))
            den = la * lb * lc + (ax * bx + ay * by + az * bz) * lc + (ax * cx + ay * cy + az * cz) * lb \
                + (bx * cx + by * cy + bz * cz) * la
            out_power[i] = 2.0 * math.atan2(num, den)


@parallel_range("emitter")
def corner_densities_kernel(uv, mid_uv, tri_p, t1_of, emitter, bary, x0, sun, d, far, factor, out, first, last):
    """:func:`.forward_image.corner_densities` of the sub-triangles (images ``uv`` /
    ``mid_uv`` (m, 3, 2), corners ``bary`` (m, 3, 2) on t1_of[emitter]) lit from
    x0[emitter], or with ``sun`` from the centroid minus ``far`` x ``d``; ``factor`` (m, 6)
    the transport factors (NaN: 1).  Writes ``out`` (m, 3)."""
    for i in range(first, last):
        out[i, 0] = 1.0
        out[i, 1] = 1.0
        out[i, 2] = 1.0
        c0x, c0y = uv[i, 0, 0], uv[i, 0, 1]
        c1x, c1y = uv[i, 1, 0], uv[i, 1, 1]
        c2x, c2y = uv[i, 2, 0], uv[i, 2, 1]
        m01x, m01y = mid_uv[i, 0, 0], mid_uv[i, 0, 1]
        m12x, m12y = mid_uv[i, 1, 0], mid_uv[i, 1, 1]
        m20x, m20y = mid_uv[i, 2, 0], mid_uv[i, 2, 1]
        # det J at the corners (forward_image.quadratic_jacobian_dets)
        sx, sy = -3 * c0x - c1x + 4 * m01x, -3 * c0y - c1y + 4 * m01y
        tx, ty = -3 * c0x - c2x + 4 * m20x, -3 * c0y - c2y + 4 * m20y
        d0 = sx * ty - sy * tx
        sx, sy = c0x + 3 * c1x - 4 * m01x, c0y + 3 * c1y - 4 * m01y
        tx, ty = c0x - c2x - 4 * m01x + 4 * m12x, c0y - c2y - 4 * m01y + 4 * m12y
        d1 = sx * ty - sy * tx
        sx, sy = c0x - c1x + 4 * m12x - 4 * m20x, c0y - c1y + 4 * m12y - 4 * m20y
        tx, ty = c0x + 3 * c2x - 4 * m20x, c0y + 3 * c2y - 4 * m20y
        d2 = sx * ty - sy * tx
        if not ((d0 > 0.0 and d1 > 0.0 and d2 > 0.0) or (d0 < 0.0 and d1 < 0.0 and d2 < 0.0)):
            continue  # a fold, or no midpoints (NaN)
        # sliver: longest edge² / twice the area
        e0x, e0y = c0x - c1x, c0y - c1y
        e1x, e1y = c1x - c2x, c1y - c2y
        e2x, e2y = c2x - c0x, c2y - c0y
        area2 = abs(e0x * e2y - e0y * e2x)
        if not area2 > 0.0:
            continue
        aspect = max(e0x * e0x + e0y * e0y, e1x * e1x + e1y * e1y, e2x * e2x + e2y * e2y) / area2
        if not aspect <= SLIVER:
            continue
        e = emitter[i]
        t = t1_of[e]
        ux = tri_p[t, 1, 0] - tri_p[t, 0, 0]
        uy = tri_p[t, 1, 1] - tri_p[t, 0, 1]
        uz = tri_p[t, 1, 2] - tri_p[t, 0, 2]
        vx = tri_p[t, 2, 0] - tri_p[t, 0, 0]
        vy = tri_p[t, 2, 1] - tri_p[t, 0, 1]
        vz = tri_p[t, 2, 2] - tri_p[t, 0, 2]
        nx = uy * vz - uz * vy
        ny = uz * vx - ux * vz
        nz = ux * vy - uy * vx
        if sun:
            qx = qy = qz = 0.0
            for k in range(3):
                qx += _corner(tri_p, t, bary[i, k, 0], bary[i, k, 1], 0)
                qy += _corner(tri_p, t, bary[i, k, 0], bary[i, k, 1], 1)
                qz += _corner(tri_p, t, bary[i, k, 0], bary[i, k, 1], 2)
            lx = qx / 3.0 - far * d[0]
            ly = qy / 3.0 - far * d[1]
            lz = qz / 3.0 - far * d[2]
        else:
            lx, ly, lz = x0[e, 0], x0[e, 1], x0[e, 2]
        r0 = r1 = r2 = 0.0
        for k in range(3):
            px = _corner(tri_p, t, bary[i, k, 0], bary[i, k, 1], 0) - lx
            py = _corner(tri_p, t, bary[i, k, 0], bary[i, k, 1], 1) - ly
            pz = _corner(tri_p, t, bary[i, k, 0], bary[i, k, 1], 2) - lz
            ln = math.sqrt(px * px + py * py + pz * pz)
            w = abs(nx * px + ny * py + nz * pz) / (ln * ln * ln)
            f = factor[i, k]
            if f == f:
                w = w * f
            dk = d0 if k == 0 else (d1 if k == 1 else d2)
            rho = w / abs(dk)
            if k == 0:
                r0 = rho
            elif k == 1:
                r1 = rho
            else:
                r2 = rho
        lo = min(r0, r1, r2)
        hi = max(r0, r1, r2)
        if not (lo > 0.0 and hi <= FOLD_RATIO * lo and hi < np.inf):
            continue
        mean = (r0 + r1 + r2) / 3.0
        out[i, 0] = r0 / mean
        out[i, 1] = r1 / mean
        out[i, 2] = r2 / mean
