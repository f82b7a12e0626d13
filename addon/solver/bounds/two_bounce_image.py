"""Receiver boxes of two-bounce pieces from the exact map in affine arithmetic (Fan et al. 2025 eq 6–11, 9).

Where only part of a box's light meets triangle 2 the Bernstein position bound
(``two_bounce_position``) falls back to a constant form of (u2, v2) and loses the correlation
of x2 with x1.  :func:`image_box` encloses the receiver barycentrics of every admissible path
of a (u1, v1) box with the exact forward map (exact √β, eq 9 at both planes) in the affine
arithmetic of ``affine`` (value forms only), which keeps that correlation.
:func:`split_pieces_chunk` cuts each piece into split² sub-boxes and intersects the piece's
Bernstein box with each sub-box's image: conservative (no admissible path is dropped), and
much tighter on curved casters.  Used by the bake's tuple selection
(``addon.bake.bounds_select``); tested in tests/bake/test_bake_bounds_select.py (every exact
path of the cone cull survives).
"""

import math

import numpy as np

from ..runtime.jit import kernel
from .two_bounce_irradiance import BOUNDED, EDGE_TOL, NO_PATH, UNBOUNDED, hit_dual, scatter_dual, vertex_one_dual
from .layout import PIECE_FIELDS, POS_PAD, P_U0, P_U1, P_V0, P_V1, ior_ratio, orientation_mask
from .affine import cross3, dual_add, dual_add_const, dual_range, dual_scale, vec_dot_const


IMAGE_NONE, IMAGE_BOX, IMAGE_UNKNOWN = 0, 1, 2


@kernel
def image_box(refract1, refract2, x0, P1, N1, P2, N2, Q, eta, box, out):
    """Enclosure of the receiver barycentrics (uk, vk) of every admissible path x0 -> x1 -> x2
    -> receiver Q with x1 in the box (u_lo, u_hi, v_lo, v_hi) of triangle 1 and x2 on triangle
    2's plane: the exact map of eq 6–11 and eq 9 (exact √β) in the affine arithmetic of
    ``two_bounce_irradiance`` (the forward map ``sub_box_irradiance`` bounds eq 15 with), value forms
    only, the union over the orientations CONTRACT.md allows.  Writes out[0:4] = (uk_lo,
    uk_hi, vk_lo, vk_hi) and returns IMAGE_BOX; IMAGE_NONE when no admissible path of the box
    reaches the receiver triangle (total internal reflection, backward rays, u2 or uk
    enclosures outside their triangles); IMAGE_UNKNOWN where a ray can be parallel to a plane
    (no enclosure).  Conservative: where d̃ is grazing (√β's derivative unbounded) its value
    forms still enclose it."""
    if box[0] + box[2] > 1.0 + EDGE_TOL:
        return IMAGE_NONE
    x1, n1, d0, ng1, mask1 = vertex_one_dual(x0, P1, N1, box)
    f1 = P2[1] - P2[0]
    f2 = P2[2] - P2[0]
    g1 = N2[1] - N2[0]
    g2 = N2[2] - N2[0]
    ng2 = cross3(f1, f2)
    out[0] = np.inf
    out[1] = -np.inf
    out[2] = np.inf
    out[3] = -np.inf
    found = False
    for k1 in range(2):
        if not (mask1 >> k1) & 1:
            continue
        if not refract1 and k1 == 1 and (mask1 & 1):
            continue
        o1 = 1.0 if k1 == 0 else -1.0
        st, dt1 = scatter_dual(refract1, o1, ior_ratio(o1, eta), n1, d0)
        if st == NO_PATH:
            continue
        st, u2, v2 = hit_dual(x1, dt1, P2)
        if st == NO_PATH:
            continue
        if st >= UNBOUNDED:
            return IMAGE_UNKNOWN
        x2 = (dual_add_const(dual_add(dual_scale(u2, f1[0]), dual_scale(v2, f2[0])), P2[0, 0]),
              dual_add_const(dual_add(dual_scale(u2, f1[1]), dual_scale(v2, f2[1])), P2[0, 1]),
              dual_add_const(dual_add(dual_scale(u2, f1[2]), dual_scale(v2, f2[2])), P2[0, 2]))
        n2 = (dual_add_const(dual_add(dual_scale(u2, g1[0]), dual_scale(v2, g2[0])), N2[0, 0]),
              dual_add_const(dual_add(dual_scale(u2, g1[1]), dual_scale(v2, g2[1])), N2[0, 1]),
              dual_add_const(dual_add(dual_scale(u2, g1[2]), dual_scale(v2, g2[2])), N2[0, 2]))
        slo, shi = dual_range(vec_dot_const(dt1, ng2))
        nlo2, nhi2 = dual_range(vec_dot_const(n2, ng2))
        mask2 = orientation_mask(-shi, -slo, nlo2, nhi2)
        for k2 in range(2):
            if not (mask2 >> k2) & 1:
                continue
            if not refract2 and k2 == 1 and (mask2 & 1):
                continue
            o2 = 1.0 if k2 == 0 else -1.0
            st, dt2 = scatter_dual(refract2, o2, ior_ratio(o2, eta), n2, dt1)
            if st == NO_PATH:
                continue
            st, uk, vk = hit_dual(x2, dt2, Q)
            if st == NO_PATH:
                continue
            if st != BOUNDED:  # the last ray can be parallel to the receiver
                return IMAGE_UNKNOWN
            ulo, uhi = dual_range(uk)
            vlo, vhi = dual_range(vk)
            if not (math.isfinite(ulo) and math.isfinite(uhi) and math.isfinite(vlo) and math.isfinite(vhi)):
                return IMAGE_UNKNOWN
            out[0] = min(out[0], ulo)
            out[1] = max(out[1], uhi)
            out[2] = min(out[2], vlo)
            out[3] = max(out[3], vhi)
            found = True
    return IMAGE_BOX if found else IMAGE_NONE


@kernel
def split_pieces_chunk(chain_code, x0, P, N, Q, UV, eta, pairs, piece_pair, piece_receiver, pieces, split, rows, counts, start, stop):
    """Cut the (u1, v1) box of pieces start..stop-1 into split x split sub-boxes and give each the
    intersection of its piece's Bernstein bound (eq 3–5) with the affine image of the sub-box
    (:func:`image_box`); sub-boxes without an admissible path are dropped.  Piece i's rows go
    to rows[i * split², ...], counts[i] of them; Ē and E̲ stay the piece's (they bound every
    sub-box of it)."""
    refract1 = (chain_code & 1) != 0
    refract2 = (chain_code & 2) != 0
    box = np.empty(4)
    img = np.empty(4)
    for i in range(start, stop):
        t = piece_pair[i]
        a = pairs[t, 0]
        b = pairs[t, 1]
        r = piece_receiver[i]
        pc = pieces[i]
        hu = (pc[P_U1] - pc[P_U0]) / split
        hv = (pc[P_V1] - pc[P_V0]) / split
        c = 0
        for ia in range(split):
            for ib in range(split):
                box[0] = pc[P_U0] + ia * hu
                box[1] = pc[P_U0] + (ia + 1) * hu if ia + 1 < split else pc[P_U1]
                box[2] = pc[P_V0] + ib * hv
                box[3] = pc[P_V0] + (ib + 1) * hv if ib + 1 < split else pc[P_V1]
                st = image_box(refract1, refract2, x0[t], P[a], N[a], P[b], N[b], Q[r], eta[t], box, img)
                if st == IMAGE_NONE:
                    continue
                row = rows[i * split * split + c]
                for k in range(PIECE_FIELDS):
                    row[k] = pc[k]
                row[P_U0], row[P_U1], row[P_V0], row[P_V1] = box[0], box[1], box[2], box[3]
                if st == IMAGE_BOX:
                    row[4] = max(row[4], img[0] - POS_PAD)
                    row[5] = min(row[5], img[1] + POS_PAD)
                    row[6] = max(row[6], img[2] - POS_PAD)
                    row[7] = min(row[7], img[3] + POS_PAD)
                    if row[4] > row[5] or row[6] > row[7]:
                        continue
                    # UV box of the barycentric box (UV is affine in (uk, vk): extremes at the corners)
                    for d in range(2):
                        lo = np.inf
                        hi = -np.inf
                        for cu in range(2):
                            for cv in range(2):
                                uu = row[4 + cu]
                                vv = row[6 + cv]
                                x = UV[r, 0, d] + uu * (UV[r, 1, d] - UV[r, 0, d]) + vv * (UV[r, 2, d] - UV[r, 0, d])
                                lo = min(lo, x)
                                hi = max(hi, x)
                        row[8 + 2 * d] = max(row[8 + 2 * d], lo - POS_PAD)
                        row[9 + 2 * d] = min(row[9 + 2 * d], hi + POS_PAD)
                c += 1
        counts[i] = c
