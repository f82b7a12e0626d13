"""Optics of a specular vertex: surface role codes, Fresnel reflectance, the scattered direction.

* Roles (the bake's material classification, ``addon.bake.scene``): ``ROLE_REFLECT`` mirror or
  metal (chain R, reflectance = tint), ``ROLE_REFRACT`` one refracting interface such as water
  (chain T, weight 1 - F), ``ROLE_BOTH`` glass (R weighted by F, T by 1 - F).
* Fresnel: unpolarised dielectric reflectance F = (r_s² + r_p²) / 2 with 1 under total internal
  reflection; unpolarised conductor reflectance for a complex IOR η + iκ seen from air.
* :func:`scatter_direction`: mirror reflection / Snell refraction about the interpolated
  shading normal, with the side rules of addon/solver/CONTRACT.md (the light arrives against the
  normal turned to its side; a reflection stays on that side, a refraction crosses the
  geometric plane).

Tested in tests/solver/test_solver_analytic.py (Fresnel against the textbook formula) and
tests/solver/test_geometry_term.py (path weights), and through every bake test.
"""

import math

import numpy as np

from ..runtime.jit import kernel

ROLE_NONE, ROLE_REFLECT, ROLE_REFRACT, ROLE_BOTH = 0, 1, 2, 3
REFLECTANCE_MODELS = {"mirror": 0, "dielectric": 1, "conductor": 2}


@kernel
def fresnel_dielectric(cos_i, eta_i, eta_t):
    """Unpolarised Fresnel reflectance at a dielectric interface from IOR eta_i into eta_t
    (1 under total internal reflection); cos_i is clamped to [0, 1]."""
    cos_i = min(max(cos_i, 0.0), 1.0)
    sin_t = eta_i / eta_t * math.sqrt(max(0.0, 1.0 - cos_i * cos_i))
    if sin_t >= 1.0:
        return 1.0
    cos_t = math.sqrt(max(0.0, 1.0 - sin_t * sin_t))
    rs = (eta_i * cos_i - eta_t * cos_t) / (eta_i * cos_i + eta_t * cos_t)
    rp = (eta_i * cos_t - eta_t * cos_i) / (eta_i * cos_t + eta_t * cos_i)
    return 0.5 * (rs * rs + rp * rp)


@kernel
def fresnel_dielectric_many(cos_i, eta_i, eta_t):
    """:func:`fresnel_dielectric` element by element over equal-length float64 arrays."""
    out = np.empty(cos_i.shape[0])
    for k in range(cos_i.shape[0]):
        out[k] = fresnel_dielectric(cos_i[k], eta_i[k], eta_t[k])
    return out


@kernel
def fresnel_conductor(cos_i, eta, k):
    """Unpolarised Fresnel reflectance of a conductor with complex IOR eta + i k (from air)."""
    c = min(max(cos_i, 0.0), 1.0)
    c2 = c * c
    s2 = 1.0 - c2
    t0 = eta * eta - k * k - s2
    a2b2 = math.sqrt(t0 * t0 + 4.0 * eta * eta * k * k)
    a = math.sqrt(max(0.0, 0.5 * (a2b2 + t0)))
    rs = (a2b2 - 2.0 * a * c + c2) / (a2b2 + 2.0 * a * c + c2)
    t1 = c2 * a2b2 + s2 * s2
    t2 = 2.0 * a * c * s2
    rp = rs * (t1 - t2) / (t1 + t2)
    return 0.5 * (rs + rp)


@kernel
def vertex_fresnel(refract, model, cos_i, side, eta, kappa):
    """Fresnel factor of one vertex (model: a ``REFLECTANCE_MODELS`` code); side > 0: the light
    arrives from outside (IOR 1).  A refraction carries 1 - F."""
    eta_i = 1.0 if side > 0.0 else eta
    eta_t = eta if side > 0.0 else 1.0
    if refract:
        return 1.0 - fresnel_dielectric(cos_i, eta_i, eta_t)
    if model == 1:
        return fresnel_dielectric(cos_i, eta_i, eta_t)
    if model == 2:
        return fresnel_conductor(cos_i, eta, kappa)
    return 1.0


@kernel(inline="always")
def scatter_direction(dx, dy, dz, nx, ny, nz, gx, gy, gz, refract, eta):
    """Scatter the unit direction d at a vertex with unit shading normal n and geometric normal
    g (on n's side): mirror reflection, or refraction 1 -> eta entering (against g) and
    eta -> 1 leaving; the side rules of addon/solver/CONTRACT.md (cos_i > 0 against the normal turned to
    the incoming side; a reflection stays on that side, a refraction crosses).  Returns
    (ok, unit direction)."""
    outside = dx * gx + dy * gy + dz * gz < 0.0
    sg = 1.0 if outside else -1.0
    nox, noy, noz = sg * nx, sg * ny, sg * nz
    ngx, ngy, ngz = sg * gx, sg * gy, sg * gz
    ci = -(dx * nox + dy * noy + dz * noz)
    if not ci > 0.0:
        return False, 0.0, 0.0, 0.0
    if refract:
        rr = 1.0 / eta if outside else eta
        kk = 1.0 - rr * rr * (1.0 - ci * ci)
        if not kk > 0.0:
            return False, 0.0, 0.0, 0.0
        c2 = rr * ci - math.sqrt(kk)
        ox, oy, oz = rr * dx + c2 * nox, rr * dy + c2 * noy, rr * dz + c2 * noz
        ln = math.sqrt(ox * ox + oy * oy + oz * oz)
        ox, oy, oz = ox / ln, oy / ln, oz / ln
        if not ox * ngx + oy * ngy + oz * ngz < 0.0:
            return False, 0.0, 0.0, 0.0
        return True, ox, oy, oz
    ox, oy, oz = dx + 2.0 * ci * nox, dy + 2.0 * ci * noy, dz + 2.0 * ci * noz
    ln = math.sqrt(ox * ox + oy * oy + oz * oz)
    ox, oy, oz = ox / ln, oy / ln, oz / ln
    if not ox * ngx + oy * ngy + oz * ngz > 0.0:
        return False, 0.0, 0.0, 0.0
    return True, ox, oy, oz
