"""Irradiance carried by a solved specular path, per unit light intensity.

E = I · (dΩ0/dA) · F  (docs/design.md): the generalised geometry term dΩ0/dA is the solid angle
of light leaving x0 per unit receiver area, found with the chain rule through the
specular vertex (the explicit Jacobian of Fan et al. 2025, eq 15, here for R and T):

    dΩ0        = |wi · ng| |e1 × e2| / |x1 - x0|²  du dv
    dA⊥ at x2  = |P⊥(∂x1/∂u + L ∂ωo/∂u) × P⊥(∂x1/∂v + L ∂ωo/∂v)| du dv

with ωo the scattered direction as a function of the vertex barycentrics, L = |x2 - x1| and
P⊥ the projector orthogonal to ωo.  F is the Fresnel factor (unpolarised dielectric,
conductor with complex IOR, or 1 for a tinted mirror whose colour the bake applies).
"""

from collections import namedtuple

import numpy as np

from ..spoly.api import CHAIN_LENGTH, validate_inputs
from ..runtime.jit import kernel, parallel_range
from .one_vertex import geometric_normal, scatter_residual, triangle_frame
from .two_vertex import pack_geometry, two_bounce_footprint
from ..geometry.optics import REFLECTANCE_MODELS, fresnel_conductor, fresnel_dielectric, vertex_fresnel
from ..geometry.vec3 import cross, dot, madd, norm, row, scale, sub, tangent_derivative

PathIrradiance = namedtuple("PathIrradiance", "irradiance geometry fresnel cos_receiver direction")

@kernel(inline="always")
def _write_solution(out, s, geometry, fresnel, w, receiver_normal, t, has_receiver):
    """out[s] = geometry, fresnel, |cos| at the receiver (1 without a normal), direction w."""
    cos_r = 1.0
    if has_receiver:
        nr = row(receiver_normal, t)
        lr = norm(nr)
        cos_r = abs(dot(w, nr)) / lr if lr > 0.0 else 0.0
    out[s, 0] = geometry
    out[s, 1] = fresnel
    out[s, 2] = cos_r
    out[s, 3] = w[0]
    out[s, 4] = w[1]
    out[s, 5] = w[2]


@parallel_range("tuple_index")
def _one_bounce_irradiance(refract, model, x_start, x_end, P, N, eta, kappa, tuple_index, uv, receiver_normal, has_receiver, out, first, last):
    """Per solution: out[:, 0..5] = geometry, fresnel, cos_receiver, direction xyz."""
    for s in range(first, last):
        t = tuple_index[s]
        x0 = row(x_start, t)
        x2 = row(x_end, t)
        p0, e1, e2, n0, m1, m2 = triangle_frame(P[t, 0], N[t, 0])
        u = uv[s, 0]
        v = uv[s, 1]
        for k in range(6):
            out[s, k] = 0.0
        ng, area2 = geometric_normal(e1, e2)
        ok, res, ju, jv = scatter_residual(u, v, x0, x2, p0, e1, e2, n0, m1, m2, ng, refract, eta[t])
        if not ok:
            continue
        n = madd(madd(n0, m1, u), m2, v)
        nh = scale(n, 1.0 / norm(n))
        di = madd(madd(sub(p0, x0), e1, u), e2, v)  # from p0: see one_vertex.scatter_residual
        li = norm(di)
        wi = scale(di, 1.0 / li)
        do = madd(madd(sub(x2, p0), e1, -u), e2, -v)
        big_l = norm(do)
        wo = scale(do, 1.0 / big_l)
        # Scattered-direction derivatives: the residual's Jacobian is d(wo)/d(uv) minus them.
        dexp_u = sub(scale(tangent_derivative(wo, e1, big_l), -1.0), ju)
        dexp_v = sub(scale(tangent_derivative(wo, e2, big_l), -1.0), jv)
        xu = madd(e1, dexp_u, big_l)
        xv = madd(e2, dexp_v, big_l)
        xu = madd(xu, wo, -dot(xu, wo))
        xv = madd(xv, wo, -dot(xv, wo))
        area_perp = norm(cross(xu, xv))
        solid_angle = abs(dot(wi, ng)) * area2 / (li * li)
        if not area_perp > 0.0:
            continue
        geometry = solid_angle / area_perp
        # Fresnel at the vertex, on the side the light arrives from.
        ngo = ng if dot(ng, nh) >= 0.0 else scale(ng, -1.0)
        from_front = dot(di, ngo) < 0.0
        no = nh if from_front else scale(nh, -1.0)
        cos_i = -dot(wi, no)
        eta_i = 1.0 if from_front else eta[t]
        eta_t = eta[t] if from_front else 1.0
        if refract:
            fresnel = 1.0 - fresnel_dielectric(cos_i, eta_i, eta_t)
        elif model == 1:
            fresnel = fresnel_dielectric(cos_i, eta_i, eta_t)
        elif model == 2:
            fresnel = fresnel_conductor(cos_i, eta[t], kappa[t])
        else:
            fresnel = 1.0
        _write_solution(out, s, geometry, fresnel, wo, receiver_normal, t, has_receiver)


@parallel_range("tuple_index")
def _two_bounce_irradiance(refract1, refract2, model, x_start, x_end, P, N, eta, kappa, tuple_index, uv, receiver_normal,
                           has_receiver, out, first, last):
    """Per solution: out[:, 0..5] = geometry, fresnel (product over both vertices),
    cos_receiver, direction xyz."""
    for s in range(first, last):
        t = tuple_index[s]
        geo = np.empty((15, 3))
        th = np.empty(4)
        for k in range(6):
            out[s, k] = 0.0
        x0 = row(x_start, t)
        x3 = row(x_end, t)
        if not pack_geometry(x0, x3, P[t, 0], N[t, 0], P[t, 1], N[t, 1], geo):
            continue
        for k in range(4):
            th[k] = uv[s, k]
        ok, geometry, c1, s1, c2, s2, w2 = two_bounce_footprint(th, geo, refract1, refract2, eta[t])
        if not ok:
            continue
        fresnel = vertex_fresnel(refract1, model, c1, s1, eta[t], kappa[t]) * \
            vertex_fresnel(refract2, model, c2, s2, eta[t], kappa[t])
        _write_solution(out, s, geometry, fresnel, w2, receiver_normal, t, has_receiver)


def path_irradiance(chain, x_start, x_end, P, N, eta, tuple_index, uv, receiver_normal=None,
                    reflectance="mirror", conductor_k=None):
    """Irradiance at x_end of each solved path per unit intensity of a point light at x_start.

    Fan et al. 2025 eq 15 (chain-rule Jacobian) for the geometry term; Fresnel per
    ``reflectance`` ("mirror": 1, "dielectric": IOR eta, "conductor": eta + i·conductor_k)
    for R, dielectric transmittance for T; for two bounces (RR, RT, TR, TT) the geometry term
    is chained through both vertices and the Fresnel factor is the product of the vertices'.
    ``receiver_normal``: (n,3) per tuple, or None for irradiance on the plane perpendicular to the arriving ray.  See CONTRACT.md.
    """
    x_start, x_end, P, N, eta = validate_inputs(chain, x_start, x_end, P, N, eta)
    if reflectance not in REFLECTANCE_MODELS:
        raise ValueError(f"reflectance must be one of {sorted(REFLECTANCE_MODELS)}, got {reflectance!r}")
    n = x_start.shape[0]
    tuple_index = np.ascontiguousarray(tuple_index, dtype=np.int64)
    uv = np.ascontiguousarray(uv, dtype=np.float64)
    k = CHAIN_LENGTH[chain]
    if tuple_index.ndim != 1 or uv.shape != (tuple_index.shape[0], 2 * k):
        raise ValueError(f"tuple_index must be (m,) and uv (m, {2 * k}); got {tuple_index.shape} and {uv.shape}")
    if tuple_index.size and (tuple_index.min() < 0 or tuple_index.max() >= n):
        raise ValueError("tuple_index out of range")
    kappa = np.zeros(n)
    if reflectance == "conductor":
        if conductor_k is None:
            raise ValueError("reflectance='conductor' needs conductor_k (imaginary part of the IOR)")
        kappa = np.broadcast_to(np.asarray(conductor_k, dtype=np.float64), (n,)).copy()
    has_receiver = receiver_normal is not None
    rn = np.zeros((n, 3)) if not has_receiver else np.array(np.broadcast_to(np.asarray(receiver_normal, dtype=np.float64), (n, 3)))
    out = np.zeros((tuple_index.shape[0], 6))
    if tuple_index.shape[0] and k == 2:
        _two_bounce_irradiance(chain[0] == "T", chain[1] == "T", REFLECTANCE_MODELS[reflectance], x_start, x_end, P, N,
                               eta, kappa, tuple_index, uv, rn, has_receiver, out)
    elif tuple_index.shape[0]:
        _one_bounce_irradiance(chain == "T", REFLECTANCE_MODELS[reflectance], x_start, x_end, P, N, eta, kappa,
                               tuple_index, uv, rn, has_receiver, out)
    geometry, fresnel, cos_r = out[:, 0], out[:, 1], out[:, 2]
    return PathIrradiance(geometry * fresnel * cos_r, geometry, fresnel, cos_r, out[:, 3:6].copy())
