"""Hand-built scene models (numpy, no Blender) shared by the bake tests."""

import numpy as np

from addon.bake.scene import Light, build_scene


def floor(half=2.0, z=0.0, resolution=64, name="floor", cx=0.0, cy=0.0):
    """A square floor [cx-half, cx+half] x [cy-half, cy+half] at height z, UV = the unit square."""
    x0, x1, y0, y1 = cx - half, cx + half, cy - half, cy + half
    P = np.array([[[x0, y0, z], [x1, y0, z], [x1, y1, z]], [[x0, y0, z], [x1, y1, z], [x0, y1, z]]], float)
    UV = (P[:, :, :2] - [x0, y0]) / (2 * half)
    return dict(name=name, tri_p=P, uv=UV, receiver=True, resolution=(resolution, resolution))


def tilted_mirror(size=1.5, centre=(0.0, 0.0, 2.0), tilt_deg=20.0, facing=-1.0):
    """A square mirror (2 triangles) rotated by ``tilt_deg`` about x, normal (0,0,facing) before the tilt."""
    a = np.radians(tilt_deg)
    R = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    h = size / 2
    sq = np.array([[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0]]) @ R.T + np.asarray(centre)
    P = np.array([[sq[0], sq[2], sq[1]], [sq[0], sq[3], sq[2]]])
    normal = R @ np.array([0.0, 0.0, facing])
    return P, np.broadcast_to(normal, (2, 3, 3)).copy(), R, normal, sq


def mirror_facing(normal, size=1.5, centre=(0.0, 0.0, 2.0)):
    """A square mirror (2 triangles) with the given normal; returns like :func:`tilted_mirror`."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    helper = np.array([0.0, 1.0, 0.0]) if abs(n[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(helper, n)
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    R = np.column_stack([u, v, n])
    h = size / 2
    sq = np.array([[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0]]) @ R.T + np.asarray(centre)
    P = np.array([[sq[0], sq[1], sq[2]], [sq[0], sq[2], sq[3]]])
    return P, np.broadcast_to(n, (2, 3, 3)).copy(), R, n, sq


def ring(segments=48, r_in=1.0, r_out=1.06, height=0.5, z0=0.0, inner_only=False):
    """A metal ring (open cylinder tube) standing on z = z0: inner wall (normals inward, smooth),
    outer wall (normals outward, smooth) and top annulus (flat, up)."""
    phi = 2 * np.pi * np.arange(segments) / segments
    c, s = np.cos(phi), np.sin(phi)
    tris, norms = [], []
    for k in range(segments):
        k1 = (k + 1) % segments
        for r, sign in ((r_in, -1.0), (r_out, 1.0)):
            if inner_only and sign > 0:
                continue
            a0 = np.array([r * c[k], r * s[k], z0])
            a1 = np.array([r * c[k1], r * s[k1], z0])
            b0 = a0 + [0, 0, height]
            b1 = a1 + [0, 0, height]
            n0 = sign * np.array([c[k], s[k], 0.0])
            n1 = sign * np.array([c[k1], s[k1], 0.0])
            if sign < 0:
                tris += [[a0, b1, a1], [a0, b0, b1]]
                norms += [[n0, n1, n1], [n0, n0, n1]]
            else:
                tris += [[a0, a1, b1], [a0, b1, b0]]
                norms += [[n0, n1, n1], [n0, n1, n0]]
        if not inner_only:
            i0 = np.array([r_in * c[k], r_in * s[k], z0 + height])
            i1 = np.array([r_in * c[k1], r_in * s[k1], z0 + height])
            o0 = np.array([r_out * c[k], r_out * s[k], z0 + height])
            o1 = np.array([r_out * c[k1], r_out * s[k1], z0 + height])
            up = [0.0, 0.0, 1.0]
            tris += [[i0, o0, o1], [i0, o1, i1]]
            norms += [[up] * 3, [up] * 3]
    return np.array(tris, float), np.array(norms, float)


def mirror_scene(resolution=48, intensity=10.0, light=(0.4, 0.3, 1.0), tint=(0.9, 0.8, 0.7)):
    P, N, R, normal, sq = tilted_mirror()
    sc = build_scene([floor(resolution=resolution), dict(name="mirror", tri_p=P, tri_n=N, role="reflect", tint=tint)],
                     [Light("Point", "point", (1.0, 1.0, 1.0), intensity, position=light)])
    return sc, dict(R=R, normal=normal, corners=sq, centre=np.array([0.0, 0.0, 2.0]), half=0.75, light=np.asarray(light, float), tint=np.asarray(tint))


def ring_scene(resolution=48, segments=48, light=(2.6, 0.0, 1.3), intensity=50.0, half=1.6):
    P, N = ring(segments)
    sc = build_scene([floor(half=half, resolution=resolution), dict(name="ring", tri_p=P, tri_n=N, role="reflect", tint=(1.0, 0.9, 0.6))],
                     [Light("Point", "point", (1.0, 1.0, 1.0), intensity, position=light)])
    return sc


def uv_sphere(segments=32, rings=16, radius=0.5, centre=(0.0, 0.0, 1.0)):
    """A closed UV sphere (outward winding) with exact radial corner normals."""
    c = np.asarray(centre, float)
    th = np.pi * np.arange(rings + 1) / rings
    ph = 2 * np.pi * np.arange(segments) / segments
    def v(i, j):
        n = np.array([np.sin(th[i]) * np.cos(ph[j % segments]), np.sin(th[i]) * np.sin(ph[j % segments]), np.cos(th[i])])
        return c + radius * n, n
    tris, norms = [], []
    for i in range(rings):
        for j in range(segments):
            a, b, cc, d = v(i, j), v(i + 1, j), v(i + 1, j + 1), v(i, j + 1)
            if i > 0:
                tris.append([a[0], b[0], d[0]]), norms.append([a[1], b[1], d[1]])
            if i < rings - 1:
                tris.append([d[0], b[0], cc[0]]), norms.append([d[1], b[1], cc[1]])
    return np.array(tris), np.array(norms)


def glass_sphere_scene(resolution=32, half=1.6, light=(0.0, 0.0, 3.0), intensity=80.0, segments=32, rings=16):
    P, N = uv_sphere(segments, rings)
    return build_scene([floor(half=half, resolution=resolution), dict(name="sphere", tri_p=P, tri_n=N, role="both", ior=1.5)],
                       [Light("Point", "point", (1.0, 1.0, 1.0), intensity, position=light)])


def box(centre=(0.0, 0.0, 1.0), half=(0.6, 0.6, 0.06)):
    """A closed box (12 triangles, outward winding, flat face normals)."""
    c = np.asarray(centre, float)
    h = np.asarray(half, float)
    tris, norms = [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            n = np.zeros(3)
            n[axis] = sign
            a, b = [k for k in range(3) if k != axis]
            quad = []
            for s, t in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                p = np.zeros(3)
                p[axis] = sign * h[axis]
                p[a] = s * h[a]
                p[b] = t * h[b]
                quad.append(c + p)
            q = np.array(quad)
            for tri in ((0, 1, 2), (0, 2, 3)):
                T = q[list(tri)]
                if np.dot(np.cross(T[1] - T[0], T[2] - T[0]), n) < 0:
                    T = T[[0, 2, 1]]
                tris.append(T)
                norms.append(np.broadcast_to(n, (3, 3)))
    return np.array(tris), np.array(norms)
