"""The straight-border cut of partly landed sub-triangles in one kernel, threads over rows.

:func:`~addon.solver.estimators.forward_image._straight_border` locates the border of what
lands inside a sub-triangle whose 6 points fit one straight border: bisections on the two
crossed edges (X_exit, X_enter), then three points of the border itself on perpendiculars
through the chord's midpoint and the half-chords' (P, P_a, P_c); the border is straight when
each is within 1/16 of its chord; the landed polygon (landed corners, X_exit, P_a, P, P_c,
X_enter) is cut into a fan.  In numpy every bisection step is a separate call of the tracing
kernel (~30 per level); :func:`border_polygons` does a row's whole sequence in one kernel,
with the same points in the same order (the same arithmetic: tests/bake/test_bake_forward_flux.py
compares the bakes), tracing through :func:`~addon.solver.estimators.refine_kernel._trace_uv`.
"""

import numpy as np

from ..runtime.jit import kernel, parallel_range
from .refine_kernel import _trace_uv


@kernel(inline="always")
def _landed(e, u, v, rec, receiver_of_tri, x0, t1_of, bounces, refract1, refract2, second_ok, tri_rec, tri_uv, tri_p, tri_n,
            tri_ior, tri_role, node_min, node_max, node_child, node_start, node_count, order, v0, e1, e2, eps, planes, stack):
    """(landed on receiver ``rec``, landing u, v) of the point (u, v) of emitter e."""
    r, lu, lv, _f = _trace_uv(e, u, v, x0, t1_of, bounces, refract1, refract2, second_ok, tri_rec, tri_uv, tri_p, tri_n,
                              tri_ior, tri_role, node_min, node_max, node_child, node_start, node_count, order, v0, e1, e2,
                              eps, planes, stack)
    return r >= 0 and receiver_of_tri[r] == rec, lu, lv


@kernel
def _bisect(e, lb_u, lb_v, l_u, l_v, xb_u, xb_v, steps, rec, receiver_of_tri, x0, t1_of, bounces, refract1, refract2,
            second_ok, tri_rec, tri_uv, tri_p, tri_n, tri_ior, tri_role, node_min, node_max, node_child, node_start,
            node_count, order, v0, e1, e2, eps, planes, stack):
    """:func:`~addon.solver.estimators.forward_image._bisect_border` of one row: bisect between
    the landed point lb (landing l) and the lost point xb; returns (the border's estimate
    (u, v), the landing of the last landed point)."""
    for _ in range(steps):
        hu = 0.5 * (lb_u + xb_u)
        hv = 0.5 * (lb_v + xb_v)
        hit, su, sv = _landed(e, hu, hv, rec, receiver_of_tri, x0, t1_of, bounces, refract1, refract2, second_ok, tri_rec,
                              tri_uv, tri_p, tri_n, tri_ior, tri_role, node_min, node_max, node_child, node_start,
                              node_count, order, v0, e1, e2, eps, planes, stack)
        if hit:
            lb_u, lb_v, l_u, l_v = hu, hv, su, sv
        else:
            xb_u, xb_v = hu, hv
    return 0.5 * (lb_u + xb_u), 0.5 * (lb_v + xb_v), l_u, l_v


@kernel
def _border_point(e, a_u, a_v, b_u, b_v, c_u, c_v, steps, rec, receiver_of_tri, x0, t1_of, bounces, refract1, refract2,
                  second_ok, tri_rec, tri_uv, tri_p, tri_n, tri_ior, tri_role, node_min, node_max, node_child, node_start,
                  node_count, order, v0, e1, e2, eps, planes, stack):
    """:func:`~addon.solver.estimators.forward_image._border_point` of one row (chord a-b, landed
    centre c): (border point (u, v), its landing (u, v), found, offset in chord lengths)."""
    mu = 0.5 * (a_u + b_u)
    mv = 0.5 * (a_v + b_v)
    du = b_u - a_u
    dv = b_v - a_v
    nu, nv = -dv, du
    if (c_u - mu) * nu + (c_v - mv) * nv > 0:
        nu, nv = -nu, -nv  # toward the lost side
    au, av = mu - 0.25 * nu, mv - 0.25 * nv
    bu, bv = mu + 0.25 * nu, mv + 0.25 * nv
    hit_a, lu, lv = _landed(e, au, av, rec, receiver_of_tri, x0, t1_of, bounces, refract1, refract2, second_ok, tri_rec,
                            tri_uv, tri_p, tri_n, tri_ior, tri_role, node_min, node_max, node_child, node_start, node_count,
                            order, v0, e1, e2, eps, planes, stack)
    hit_b, _u, _v = _landed(e, bu, bv, rec, receiver_of_tri, x0, t1_of, bounces, refract1, refract2, second_ok, tri_rec,
                            tri_uv, tri_p, tri_n, tri_ior, tri_role, node_min, node_max, node_child, node_start, node_count,
                            order, v0, e1, e2, eps, planes, stack)
    pu, pv, qu, qv = _bisect(e, au, av, lu, lv, bu, bv, steps, rec, receiver_of_tri, x0, t1_of, bounces, refract1, refract2,
                             second_ok, tri_rec, tri_uv, tri_p, tri_n, tri_ior, tri_role, node_min, node_max, node_child,
                             node_start, node_count, order, v0, e1, e2, eps, planes, stack)
    t = ((pu - mu) * nu + (pv - mv) * nv) / max(nu * nu + nv * nv, 1e-300)
    return pu, pv, qu, qv, hit_a and not hit_b, t


@parallel_range("emitter", 16)
def border_polygons(emitter, bary, mid, uv, muv, robj, receiver_of_tri, steps, x0, t1_of, bounces, refract1, refract2,
                    second_ok, tri_rec, tri_uv, tri_p, tri_n, tri_ior, tri_role, node_min, node_max, node_child,
                    node_start, node_count, order, v0, e1, e2, eps, planes, out_straight, out_count, out_poly_b, out_poly_uv,
                    out_span, first, last):
    """Rows (sub-triangles fitting one straight border, see the module doc): whether the
    border is straight (``out_straight``), the landed polygon's ``out_count`` points
    ``out_poly_b`` (bary) / ``out_poly_uv`` (landing UV), and the seeding margin ``out_span``
    (1/16 of the landed points' UV span)."""
    stack = np.empty(256, dtype=np.int64)
    c = np.empty(3, dtype=np.bool_)
    ok = np.empty(6, dtype=np.bool_)
    cross = np.empty((2, 4))  # X_exit, X_enter: (u, v) in the first triangle, then their landing UV
    for chunk in range(first, last):
        for i in range(chunk * 16, min(emitter.shape[0], chunk * 16 + 16)):
            e = emitter[i]
            rec = robj[i, 0]
            for k in range(1, 6):
                rec = max(rec, robj[i, k])
            nc = 0
            for k in range(6):
                ok[k] = robj[i, k] == rec
            for k in range(3):
                c[k] = ok[k]
                nc += ok[k]
            start = 0
            for k in range(3):
                if c[k] and not c[(k + 2) % 3]:
                    start = k
                    break
            last_c = (start + nc - 1) % 3
            # X_exit on edge (last, last + 1) (midpoint index last); X_enter on edge (start - 1, start)
            for side in range(2):
                if side == 0:
                    land, lost, mi = last_c, (last_c + 1) % 3, last_c
                else:
                    land, lost, mi = start, (start + 2) % 3, (start + 2) % 3
                if ok[3 + mi]:
                    lb_u, lb_v, l_u, l_v = mid[i, mi, 0], mid[i, mi, 1], muv[i, mi, 0], muv[i, mi, 1]
                    xb_u, xb_v = bary[i, lost, 0], bary[i, lost, 1]
                else:
                    lb_u, lb_v, l_u, l_v = bary[i, land, 0], bary[i, land, 1], uv[i, land, 0], uv[i, land, 1]
                    xb_u, xb_v = mid[i, mi, 0], mid[i, mi, 1]
                cross[side, 0], cross[side, 1], cross[side, 2], cross[side, 3] = _bisect(
                    e, lb_u, lb_v, l_u, l_v, xb_u, xb_v, steps, rec, receiver_of_tri, x0, t1_of, bounces, refract1, refract2,
                    second_ok, tri_rec, tri_uv, tri_p, tri_n, tri_ior, tri_role, node_min, node_max, node_child, node_start,
                    node_count, order, v0, e1, e2, eps, planes, stack)
            cu = ((bary[i, 0, 0] * c[0] + bary[i, 1, 0] * c[1]) + bary[i, 2, 0] * c[2]) / nc
            cv = ((bary[i, 0, 1] * c[0] + bary[i, 1, 1] * c[1]) + bary[i, 2, 1] * c[2]) / nc
            pu, pv, pqu, pqv, ok0, t0 = _border_point(
                e, cross[0, 0], cross[0, 1], cross[1, 0], cross[1, 1], cu, cv, steps, rec, receiver_of_tri, x0, t1_of, bounces,
                refract1, refract2, second_ok, tri_rec, tri_uv, tri_p, tri_n, tri_ior, tri_role, node_min, node_max,
                node_child, node_start, node_count, order, v0, e1, e2, eps, planes, stack)
            au, av, aqu, aqv, ok1, t1 = _border_point(
                e, cross[0, 0], cross[0, 1], pu, pv, cu, cv, steps, rec, receiver_of_tri, x0, t1_of, bounces, refract1,
                refract2, second_ok, tri_rec, tri_uv, tri_p, tri_n, tri_ior, tri_role, node_min, node_max, node_child,
                node_start, node_count, order, v0, e1, e2, eps, planes, stack)
            bu, bv, bqu, bqv, ok2, t2 = _border_point(
                e, pu, pv, cross[1, 0], cross[1, 1], cu, cv, steps, rec, receiver_of_tri, x0, t1_of, bounces, refract1,
                refract2, second_ok, tri_rec, tri_uv, tri_p, tri_n, tri_ior, tri_role, node_min, node_max, node_child,
                node_start, node_count, order, v0, e1, e2, eps, planes, stack)
            out_straight[i] = ok0 and ok1 and ok2 and max(max(abs(t0), abs(t1)), abs(t2)) <= 1.0 / 16.0
            ok1 = ok1 and ok0
            ok2 = ok2 and ok0
            # polygon: landed corners from `start`, X_exit, [P_a, P, P_c], X_enter
            n = 0
            for k in range(min(nc, 2)):
                ck = (start + k) % 3
                out_poly_b[i, n, 0], out_poly_b[i, n, 1] = bary[i, ck, 0], bary[i, ck, 1]
                out_poly_uv[i, n, 0], out_poly_uv[i, n, 1] = uv[i, ck, 0], uv[i, ck, 1]
                n += 1
            out_poly_b[i, n, 0], out_poly_b[i, n, 1] = cross[0, 0], cross[0, 1]
            out_poly_uv[i, n, 0], out_poly_uv[i, n, 1] = cross[0, 2], cross[0, 3]
            n += 1
            if ok1:
                out_poly_b[i, n, 0], out_poly_b[i, n, 1] = au, av
                out_poly_uv[i, n, 0], out_poly_uv[i, n, 1] = aqu, aqv
                n += 1
            if ok0:
                out_poly_b[i, n, 0], out_poly_b[i, n, 1] = pu, pv
                out_poly_uv[i, n, 0], out_poly_uv[i, n, 1] = pqu, pqv
                n += 1
            if ok2:
                out_poly_b[i, n, 0], out_poly_b[i, n, 1] = bu, bv
                out_poly_uv[i, n, 0], out_poly_uv[i, n, 1] = bqu, bqv
                n += 1
            out_poly_b[i, n, 0], out_poly_b[i, n, 1] = cross[1, 0], cross[1, 1]
            out_poly_uv[i, n, 0], out_poly_uv[i, n, 1] = cross[1, 2], cross[1, 3]
            out_count[i] = n + 1
            # seeding margin: 1/16 of the landed points' UV span
            span2 = 0.0
            for a in range(2):
                hi = -np.inf
                lo = np.inf
                for k in range(6):
                    if ok[k]:
                        q = uv[i, k, a] if k < 3 else muv[i, k - 3, a]
                        hi = max(hi, q)
                        lo = min(lo, q)
                w = hi - lo
                if not np.isfinite(w):
                    w = np.inf
                span2 += w * w
            out_span[i] = np.sqrt(span2) / 16.0
