"""Grazing and near-critical refraction (T) tuples with a planted path, and their brute-force truth.

The region of issue 27: a low sun over a pool.  Each tuple is built around a true path
(``bruteforce.plant_paths`` at a fixed incidence angle), in one of three categories:

  enter_grazing   light outside (x0 on the normal's side), cos_i in [0.005, 0.45] to the
                  interpolated normal, refracted into the medium close to its critical angle
  exit_grazing    light inside the medium, incidence just under the critical angle so that the
                  ray leaves at cos_o in [0.005, 0.45] (the reverse path of enter_grazing)
  exit_critical   light inside, sin(theta_i) = (1 - eps) / eta with eps in [1e-6, 0.1]

eta is 1.33 (water) or 1.5 (glass).  Normal fields: nearly flat (corner normals tilted by up
to 0.5-15 deg: the coplanarity conic is then nearly linear), tilted up to 45 deg, and
sphere-like (curved, concave and convex).  Distances in triangle sizes: half the tuples have
both endpoints close to the triangle (light 10^-1.5..10^0.5, receiver 10^-2.5..10^-0.5: a
large water-surface triangle over a shallow floor, where the resultant spans many orders of
magnitude), a quarter a far light (a sun, up to ~10^4), a quarter both ends farther out.
Shapes, sizes, offsets, winding and non-unit normals as in ``bruteforce.random_triangles`` /
``random_normals``.  Used by tests/solver/test_solver_grazing.py.
"""
from __future__ import annotations

import numpy as np

from reference import bruteforce as bf
from reference.truth import mixed_normals

SEED = 20261127
CATEGORIES = ("enter_grazing", "exit_grazing", "exit_critical")
FIELDS = ("near_flat", "tilt", "sphere")


def _normals(rng, P, field):
    n = len(P)
    if field == "near_flat":
        return bf.random_normals(rng, P, "tilt", max_tilt_deg=10.0 ** rng.uniform(np.log10(0.5), np.log10(15.0)))
    if field == "tilt":
        return mixed_normals(rng, P, 0.0)
    return mixed_normals(rng, P, 1.0)


def make_grazing(n, seed=SEED):
    """n tuples (fewer when a draw cannot be planted): dict with P (m,1,3,3), N, eta (m,),
    x0, x2 (m,3), uv (m,2) the planted path, cat and field (m,) str."""
    rng = np.random.default_rng(seed)
    parts = []
    per = n // (len(CATEGORIES) * len(FIELDS))
    for cat in CATEGORIES:
        for field in FIELDS:
            m = per
            P = bf.random_triangles(rng, m)
            N = _normals(rng, P, field)
            eta = np.where(rng.random(m) < 0.5, 1.33, 1.5)
            c = 10.0 ** rng.uniform(np.log10(0.005), np.log10(0.45), m)
            if cat == "enter_grazing":
                side, theta = 1.0, np.arccos(c)
            elif cat == "exit_grazing":
                side, theta = -1.0, np.arcsin(np.sqrt(1.0 - c * c) / eta)
            else:
                eps = 10.0 ** rng.uniform(-6.0, -1.0, m)
                side, theta = -1.0, np.arcsin((1.0 - eps) / eta)
            # endpoints close to the triangle (the hard case for the resultant) for half of them
            close = rng.random(m) < 0.5
            x0, x2, uv, ok = bf.plant_paths(rng, "T", P, N, eta, side=side, theta=theta, dist_log10=(-1.5, 0.5),
                                            far_x2=(-2.5, -0.5))
            # a quarter with the light far away (a sun), a quarter with both ends farther out
            x1, _, _, _ = bf.interpolate(P, N, uv[:, 0], uv[:, 1])
            sun = ~close & (rng.random(m) < 0.5)
            x0 = x1 + (x0 - x1) * np.where(sun, 10.0 ** rng.uniform(2.0, 3.5, m), np.where(close, 1.0, 10.0))[:, None]
            x2 = x1 + (x2 - x1) * np.where(close, 1.0, 10.0 ** rng.uniform(0.5, 2.0, m))[:, None]
            # rounding of far-off triangles can push a planted path past the contract's 1e-7: drop those
            ok &= bf.check_path("T", x0, x2, P[:, None], N[:, None], eta, uv).valid
            parts.append(dict(P=P[ok], N=N[ok], eta=eta[ok], x0=x0[ok], x2=x2[ok], uv=uv[ok],
                              cat=np.full(int(ok.sum()), cat, dtype=object), field=np.full(int(ok.sum()), field, dtype=object)))
    out = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    out["P"] = out["P"][:, None].copy()
    out["N"] = out["N"][:, None].copy()
    out["chain"] = "T"
    return out


_CACHE: dict = {}


def grazing_with_truth(n):
    """make_grazing(n) plus the brute-force paths (bf_t, bf_uv, bf_chk, bf_sigma), once per process."""
    if n not in _CACHE:
        d = make_grazing(n)
        A = (d["x0"], d["x2"], d["P"], d["N"], d["eta"])
        ti, uv, chk = bf.solve_bruteforce("T", *A, return_all=True)
        sig = bf.root_sigma_min("T", *[a[ti] for a in A], uv)
        d.update(bf_t=ti, bf_uv=uv, bf_chk=chk, bf_sigma=sig)
        _CACHE[n] = d
    return _CACHE[n]
