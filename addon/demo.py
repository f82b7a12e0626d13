"""The README demo: solve the caustic paths of two small scenes and show the irradiance.

No Blender needed.  A concave spherical mirror (chain R) and a wavy water surface over a
floor (chain T) are lit by a point light; every (triangle, receiver point) pair of a grid
on the receiver plane is solved with the Specular Polynomials solver, the irradiance of
each path is summed per receiver point, and the pattern is printed as ASCII shading along
with a few of the solved paths.  (It grows into a full .blend bake with the bake pipeline.)
"""

import time

import numpy as np

from .solver import path_irradiance
from .solver.spoly.api import SpecularPolynomialSolver

SHADES = " .:-=+*#%@"


def concave_mirror(rings=6, segments=24, radius=2.0, half_angle=0.5):
    """A spherical cap (centre (0, radius, 0)) with exact sphere normals pointing inward."""
    centre = np.array([0.0, radius, 0.0])
    verts = [centre + radius * np.array([0.0, -1.0, 0.0])]
    for i in range(1, rings + 1):
        theta = half_angle * i / rings
        for j in range(segments):
            phi = 2 * np.pi * j / segments
            verts.append(centre + radius * np.array([np.sin(theta) * np.cos(phi), -np.cos(theta), np.sin(theta) * np.sin(phi)]))
    verts = np.array(verts)
    normals = (centre - verts) / radius
    tris = []
    for j in range(segments):
        tris.append((0, 1 + j, 1 + (j + 1) % segments))
    for i in range(1, rings):
        a, b = 1 + (i - 1) * segments, 1 + i * segments
        for j in range(segments):
            j1 = (j + 1) % segments
            tris.append((a + j, b + j, b + j1))
            tris.append((a + j, b + j1, a + j1))
    tris = np.array(tris)
    return verts[tris], normals[tris]


def wavy_water(cells=12, size=2.0, amplitude=0.06):
    """A height field y = A sin(3x) cos(2z) with analytic normals (normals point up, out of the water)."""
    xs = np.linspace(-size, size, cells + 1)
    X, Z = np.meshgrid(xs, xs, indexing="ij")
    Y = amplitude * np.sin(3 * X) * np.cos(2 * Z)
    dYdx = 3 * amplitude * np.cos(3 * X) * np.cos(2 * Z)
    dYdz = -2 * amplitude * np.sin(3 * X) * np.sin(2 * Z)
    V = np.stack([X, Y, Z], -1).reshape(-1, 3)
    Nv = np.stack([-dYdx, np.ones_like(X), -dYdz], -1).reshape(-1, 3)
    Nv /= np.linalg.norm(Nv, axis=1, keepdims=True)
    idx = np.arange((cells + 1) ** 2).reshape(cells + 1, cells + 1)
    tris = []
    for i in range(cells):
        for j in range(cells):
            a, b, c, d = idx[i, j], idx[i + 1, j], idx[i + 1, j + 1], idx[i, j + 1]
            tris += [(a, c, b), (a, d, c)]  # counter-clockwise seen from above: normals up
    tris = np.array(tris)
    return V[tris], Nv[tris]


def receiver_grid(y, half, nx, nz):
    xs = (np.arange(nx) + 0.5) / nx * 2 * half - half
    zs = (np.arange(nz) + 0.5) / nz * 2 * half - half
    X, Z = np.meshgrid(xs, zs, indexing="xy")
    return np.stack([X, np.full_like(X, y), Z], -1).reshape(-1, 3)


def solve_scene(chain, light, tri_p, tri_n, points, receiver_normal, eta):
    """Solve all (triangle, point) tuples; return irradiance per point and the solve data."""
    n_tri, n_pts = tri_p.shape[0], points.shape[0]
    tri_idx = np.repeat(np.arange(n_tri), n_pts)
    pt_idx = np.tile(np.arange(n_pts), n_tri)
    x_start = np.broadcast_to(light, (tri_idx.size, 3))
    P = tri_p[tri_idx][:, None]
    N = tri_n[tri_idx][:, None]
    t0 = time.perf_counter()
    result = SpecularPolynomialSolver().solve(chain, x_start, points[pt_idx], P, N, eta)
    irr = path_irradiance(chain, x_start, points[pt_idx], P, N, eta, result.tuple_index, result.uv,
                          receiver_normal=np.broadcast_to(receiver_normal, (tri_idx.size, 3)),
                          reflectance="mirror")
    seconds = time.perf_counter() - t0
    E = np.bincount(pt_idx[result.tuple_index], weights=irr.irradiance, minlength=n_pts)
    return E, result, irr, seconds, tri_idx, pt_idx


def ascii_map(E, nx, nz, reference):
    rows = []
    for k in range(nz):
        line = ""
        for i in range(nx):
            level = E[k * nx + i] / reference
            idx = 0 if level <= 0 else min(len(SHADES) - 1, 1 + int(np.log2(1 + level) * 2))
            line += SHADES[idx]
        rows.append(line)
    return "\n".join(rows)


def run_demo(nx=64, nz=28):
    print("Caustic Bake demo: Specular Polynomials (Fan et al. 2024), point light, all tuples solved.\n")
    scenes = [
        ("Concave mirror (R)", "R", np.array([0.35, 3.0, 0.15]), concave_mirror(), 0.95, 1.0, np.array([0.0, -1.0, 0.0]), 1.5),
        ("Wavy water over a floor (T, IOR 1.33)", "T", np.array([0.2, 2.5, -0.1]), wavy_water(), -0.8, 1.6, np.array([0.0, 1.0, 0.0]), 1.33),
    ]
    for title, chain, light, (tri_p, tri_n), y, half, nr, eta in scenes:
        points = receiver_grid(y, half, nx, nz)
        E, result, irr, seconds, tri_idx, pt_idx = solve_scene(chain, light, tri_p, tri_n, points, nr, eta)
        rep = result.report
        # Reference: the unobstructed irradiance of the light straight below/above, per unit intensity.
        reference = 1.0 / (light[1] - y) ** 2
        print(f"== {title}: {tri_p.shape[0]} triangles x {points.shape[0]} receiver points = {rep.tuples:,} tuples")
        print(f"   {rep.paths:,} paths found ({rep.skipped:,} tuples rejected early, {rep.roots:,} resultant roots, "
              f"{rep.candidates:,} candidates) in {seconds:.3f} s")
        print(f"   peak irradiance {E.max() / reference:.1f}x the direct irradiance of the light at the receiver "
              f"(shading: log scale, '{SHADES[1]}' dim … '{SHADES[-1]}' brightest)")
        print(ascii_map(E, nx, nz, reference))
        order = np.argsort(-irr.irradiance)[:3]
        for s in order:
            t = result.tuple_index[s]
            u, v = result.uv[s]
            p = tri_p[tri_idx[t]]
            x1 = p[0] + u * (p[1] - p[0]) + v * (p[2] - p[0])
            print(f"   path: light {np.round(light, 3)} -> vertex {np.round(x1, 4)} (triangle {tri_idx[t]}, u={u:.4f}, v={v:.4f}) "
                  f"-> receiver {np.round(points[pt_idx[t]], 3)}; E/I = {irr.irradiance[s]:.4f} /m², Fresnel {irr.fresnel[s]:.3f}")
        print()
