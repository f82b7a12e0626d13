"""Surface queries shared by the forward tracers (photon.py, forward_image.py): the point and
frame of a triangle at barycentrics and where a ray crosses a triangle's plane (the scattered
direction at a vertex is :func:`addon.solver.geometry.optics.scatter_direction`).

Conventions as the bake's (CONTRACT.md): the shading normal is the normalised interpolation
of the corner normals; the geometric normal e1 x e2, normalised and turned to the shading
normal's side.
"""

import math

from ..runtime.jit import kernel


@kernel(inline="always")
def triangle_frame(tri_p, tri_n, t, u, v):
    """(has_area, x, y, z, n (unit shading normal; the geometric one where the interpolated
    normal is zero), g (unit geometric normal on n's side), has_normal) of triangle t at
    barycentrics (u, v)."""
    p0x, p0y, p0z = tri_p[t, 0, 0], tri_p[t, 0, 1], tri_p[t, 0, 2]
    e1x, e1y, e1z = tri_p[t, 1, 0] - p0x, tri_p[t, 1, 1] - p0y, tri_p[t, 1, 2] - p0z
    e2x, e2y, e2z = tri_p[t, 2, 0] - p0x, tri_p[t, 2, 1] - p0y, tri_p[t, 2, 2] - p0z
    x = p0x + u * e1x + v * e2x
    y = p0y + u * e1y + v * e2y
    z = p0z + u * e1z + v * e2z
    nx = tri_n[t, 0, 0] + u * (tri_n[t, 1, 0] - tri_n[t, 0, 0]) + v * (tri_n[t, 2, 0] - tri_n[t, 0, 0])
    ny = tri_n[t, 0, 1] + u * (tri_n[t, 1, 1] - tri_n[t, 0, 1]) + v * (tri_n[t, 2, 1] - tri_n[t, 0, 1])
    nz = tri_n[t, 0, 2] + u * (tri_n[t, 1, 2] - tri_n[t, 0, 2]) + v * (tri_n[t, 2, 2] - tri_n[t, 0, 2])
    gx = e1y * e2z - e1z * e2y
    gy = e1z * e2x - e1x * e2z
    gz = e1x * e2y - e1y * e2x
    gl = math.sqrt(gx * gx + gy * gy + gz * gz)
    nl = math.sqrt(nx * nx + ny * ny + nz * nz)
    if gl > 0.0:
        gx, gy, gz = gx / gl, gy / gl, gz / gl
    if nl > 0.0:
        nx, ny, nz = nx / nl, ny / nl, nz / nl
    else:
        nx, ny, nz = gx, gy, gz
    if gx * nx + gy * ny + gz * nz < 0.0:
        gx, gy, gz = -gx, -gy, -gz
    return gl > 0.0, x, y, z, nx, ny, nz, gx, gy, gz, nl > 0.0


@kernel(inline="always")
def plane_barycentrics(tri_p, t, ox, oy, oz, dx, dy, dz):
    """Barycentrics (u, v) where the ray o + s d crosses triangle t's plane (Möller-Trumbore,
    not clamped; (0, 0) for a ray parallel to the plane)."""
    p0x, p0y, p0z = tri_p[t, 0, 0], tri_p[t, 0, 1], tri_p[t, 0, 2]
    e1x, e1y, e1z = tri_p[t, 1, 0] - p0x, tri_p[t, 1, 1] - p0y, tri_p[t, 1, 2] - p0z
    e2x, e2y, e2z = tri_p[t, 2, 0] - p0x, tri_p[t, 2, 1] - p0y, tri_p[t, 2, 2] - p0z
    px = dy * e2z - dz * e2y
    py = dz * e2x - dx * e2z
    pz = dx * e2y - dy * e2x
    det = e1x * px + e1y * py + e1z * pz
    if det == 0.0:
        return 0.0, 0.0
    inv = 1.0 / det
    sx, sy, sz = ox - p0x, oy - p0y, oz - p0z
    u = (sx * px + sy * py + sz * pz) * inv
    qx = sy * e1z - sz * e1y
    qy = sz * e1x - sx * e1z
    qz = sx * e1y - sy * e1x
    v = (dx * qx + dy * qy + dz * qz) * inv
    return u, v
