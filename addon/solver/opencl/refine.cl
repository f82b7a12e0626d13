// The landed part of the forward-image refinement on the device: estimators/refine_kernel.py
// refine_emitters step for step, one work-item per emitter (its first triangle, depth first from
// the start grid).  A sub-triangle whose 6 points (corners, edge midpoints 01, 12, 20) land on
// one receiver is final when its image is straight and its flux density linear (the rules of
// refine_kernel.py's module doc), dropped beyond a flat receiver's region, else split in four;
// any other one is handed back to the host's levels with its 6 traced points.  Points are
// traced by trace.cl's trace_one (the Numba arithmetic), shared within an emitter through an
// open-addressing table keyed by their dyadic coordinates (a smaller table than Numba's: a point
// not kept is traced again, with the same answer, so only the count of traced points differs).
//
// Records go to two global lists through atomic counters (counts[0] finals, counts[1] hand-backs;
// in no set order); each carries its emitter and its ordinal in that emitter's depth-first order, and per_emitter counts each
// emitter's finals, hand-backs and traced points, so the host puts the records back in the
// Numba kernel's order.  A list that overflows its capacity still counts: the host grows it to
// the count and runs the batch again.
//
// Build options: REFINE_STACK (the depth-first stack: start triangles + 3 x depth levels + 4),
// TABLE_BITS, and the record layouts F_* / H_* of refine_kernel.py.
// @INCLUDE trace.cl@

#define TABLE_SIZE (1 << TABLE_BITS)
#define TABLE_MASK (TABLE_SIZE - 1)
#define F_ROW (F_WIDTH + 1)  // a final record and its ordinal
#define H_ROW (H_WIDTH + 1)

// @INCLUDE numba_math.cl@ (NB_MAX, NB_MIN)

__constant int CHILD_CORNERS[12] = {0, 3, 5, 3, 1, 4, 5, 4, 2, 3, 4, 5};

// refine_kernel.py _light_weight: the light's flux per barycentric area of t at (u, v), up to a constant
static double light_weight(int parallel, __global const double *x0, __global const double *tri_p, long t, long e,
                           double u, double v) {
    if (parallel) return 1.0;
    __global const double *p = tri_p + 9 * t;
    double ax = p[0], ay = p[1], az = p[2];
    double bx = p[3] - ax, by = p[4] - ay, bz = p[5] - az;
    double cx = p[6] - ax, cy = p[7] - ay, cz = p[8] - az;
    double nx = by * cz - bz * cy, ny = bz * cx - bx * cz, nz = bx * cy - by * cx;
    double dx = ax + u * bx + v * cx - x0[3 * e];
    double dy = ay + u * by + v * cy - x0[3 * e + 1];
    double dz = az + u * bz + v * cz - x0[3 * e + 2];
    double ln = sqrt(dx * dx + dy * dy + dz * dz);
    return fabs(nx * dx + ny * dy + nz * dz) / (ln * ln * ln);
}

// refine_kernel.py _density_nonlinearity: the worst edge midpoint's departure from linear of
// rho = w / |det J| (the 6-node quadratic element), relative to the corners' mean; inf at a fold
static double density_nonlinearity(const double *pu, const double *pv, const double *w) {
    double c0u = pu[0], c1u = pu[1], c2u = pu[2], m01u = pu[3], m12u = pu[4], m20u = pu[5];
    double c0v = pv[0], c1v = pv[1], c2v = pv[2], m01v = pv[3], m12v = pv[4], m20v = pv[5];
    double ds_u[6] = {-3 * c0u - c1u + 4 * m01u, c0u + 3 * c1u - 4 * m01u, c0u - c1u + 4 * m12u - 4 * m20u,
                      c1u - c0u, c0u + c1u - 2 * m01u + 2 * m12u - 2 * m20u, -c0u - c1u + 2 * m01u + 2 * m12u - 2 * m20u};
    double ds_v[6] = {-3 * c0v - c1v + 4 * m01v, c0v + 3 * c1v - 4 * m01v, c0v - c1v + 4 * m12v - 4 * m20v,
                      c1v - c0v, c0v + c1v - 2 * m01v + 2 * m12v - 2 * m20v, -c0v - c1v + 2 * m01v + 2 * m12v - 2 * m20v};
    double dt_u[6] = {-3 * c0u - c2u + 4 * m20u, c0u - c2u - 4 * m01u + 4 * m12u, c0u + 3 * c2u - 4 * m20u,
                      -c0u - c2u - 2 * m01u + 2 * m12u + 2 * m20u, c0u + c2u - 2 * m01u + 2 * m12u - 2 * m20u, c2u - c0u};
    double dt_v[6] = {-3 * c0v - c2v + 4 * m20v, c0v - c2v - 4 * m01v + 4 * m12v, c0v + 3 * c2v - 4 * m20v,
                      -c0v - c2v - 2 * m01v + 2 * m12v + 2 * m20v, c0v + c2v - 2 * m01v + 2 * m12v - 2 * m20v, c2v - c0v};
    int pos = 0, neg = 0;
    double rho[6];
    for (int k = 0; k < 6; k++) {
        double d = ds_u[k] * dt_v[k] - ds_v[k] * dt_u[k];
        pos += d > 0.0;
        neg += d < 0.0;
        rho[k] = fabs(w[k]) / fabs(d);
    }
    if (pos != 6 && neg != 6) return INFINITY;  // a fold inside (or a degenerate corner)
    double mean = (rho[0] + rho[1] + rho[2]) / 3.0;
    double worst = 0.0;
    for (int k = 0; k < 3; k++) {
        double lin = 0.5 * (rho[k] + rho[(k + 1) % 3]);
        worst = NB_MAX(worst, fabs(rho[3 + k] - lin));
    }
    double out = worst / mean;
    if (!isfinite(out) || isnan(worst)) return INFINITY;
    return out;
}

// receiver_planes.py beyond_region: the points all beyond one edge of the receiver's region by more than margin
static int beyond_region(__global const double *planes, int n_planes, long receiver, const double *pu,
                         const double *pv, double margin) {
    for (int p = 0; p < n_planes; p++) {
        __global const double *row = planes + PLANE_WIDTH * p;
        if ((long)row[13] != receiver) continue;
        int k_n = (int)row[14];
        for (int k = 0; k < k_n; k++) {
            __global const double *h = row + PLANE_HEAD + 3 * k;
            double hi = -INFINITY;
            for (int q = 0; q < 6; q++) hi = NB_MAX(hi, h[0] * pu[q] + h[1] * pv[q] + h[2]);
            if (hi < -margin) return 1;
        }
    }
    return 0;
}

__kernel void refine_emitters(
    const long e_first, const int n, __global const double *base, const int n_base, const long depth0,
    const long dyadic, __global const double *x0, __global const long *t1_of, const int bounces, const int refract1,
    const int refract2, __global const uchar *second_ok, __global const long *tri_rec, __global const double *tri_uv,
    __global const double *tri_p, __global const double *tri_n, __global const double *tri_ior,
    __global const long *tri_role, __global const double *node_min, __global const double *node_max,
    __global const long *node_child, __global const long *node_start, __global const long *node_count,
    __global const long *order, __global const double *bv0, __global const double *be1, __global const double *be2,
    const double eps, __global const double *planes, const int n_planes, __global const long *receiver_of_tri,
    __global const double *texel_size, const double tolerance, const double relative, const double coarse_texels,
    const double coarse_linear_texels, const long max_depth, const int density, const int parallel,
    const int has_top, __global const long *top_rec, __global const double *top_uv, __global const double *top_fac,
    __global long *table_key, __global long *table_rec, __global double *table_val, __global double *finals,
    const int final_cap, __global double *hands, const int hand_cap, volatile __global int *counts,
    __global long *per_emitter) {
    int i = get_global_id(0);
    if (i >= n) return;
    long e = e_first + i;
    Bvh B = {node_min, node_max, node_child, node_start, node_count, order, bv0, be1, be2};
    __global long *t_key = table_key + (long)i * TABLE_SIZE;
    __global long *t_rec = table_rec + (long)i * TABLE_SIZE;
    __global double *t_val = table_val + (long)i * 3 * TABLE_SIZE;
    for (int s = 0; s < TABLE_SIZE; s++) t_key[s] = -1;
    double s_bary[REFINE_STACK][6], s_uv[REFINE_STACK][6], s_fac[REFINE_STACK][3], s_inh[REFINE_STACK];
    long s_rec[REFINE_STACK][3], s_depth[REFINE_STACK];
    double p_bary[6][2], p_uv[6][2], p_fac[6], pu[6], pv[6], w6[6];
    long p_rec[6], robj[6];
    long nf = 0, nh = 0, traced = 0, n_used = 0;
    long t1 = t1_of[e];
    long s1 = dyadic + 1;
    double x0x = x0[3 * e], x0y = x0[3 * e + 1], x0z = x0[3 * e + 2];
    int top = 0;
    for (int k = n_base - 1; k >= 0; k--) {  // the start grid, first triangle on top
        for (int c = 0; c < 6; c++) s_bary[top][c] = base[6 * k + c];
        s_depth[top] = depth0;
        s_inh[top] = INFINITY;
        top++;
    }
    while (top > 0) {
        top--;
        long depth = s_depth[top];
        double inherited = depth == 0 ? INFINITY : s_inh[top];
        for (int c = 0; c < 3; c++) {
            int c2 = (c + 1) % 3;
            p_bary[c][0] = s_bary[top][2 * c];
            p_bary[c][1] = s_bary[top][2 * c + 1];
            p_bary[3 + c][0] = 0.5 * (s_bary[top][2 * c] + s_bary[top][2 * c2]);
            p_bary[3 + c][1] = 0.5 * (s_bary[top][2 * c + 1] + s_bary[top][2 * c2 + 1]);
        }
        // the start grid's corners are traced here (table-shared); a child's come from its parent
        int k0 = depth == depth0 ? 0 : 3;
        if (k0 == 3) {
            for (int k = 0; k < 3; k++) {
                p_rec[k] = s_rec[top][k];
                p_uv[k][0] = s_uv[top][2 * k];
                p_uv[k][1] = s_uv[top][2 * k + 1];
                p_fac[k] = s_fac[top][k];
            }
        }
        if (k0 == 0 && has_top) {  // the whole triangle: its points traced once for the mesh
            for (int k = 0; k < 6; k++) {
                p_rec[k] = top_rec[6 * e + k];
                p_uv[k][0] = top_uv[12 * e + 2 * k];
                p_uv[k][1] = top_uv[12 * e + 2 * k + 1];
                p_fac[k] = top_fac[6 * e + k];
            }
            k0 = 6;
        }
        for (int k = k0; k < 6; k++) {
            double u = p_bary[k][0], v = p_bary[k][1];
            long key = (long)rint(u * (double)dyadic) * s1 + (long)rint(v * (double)dyadic);
            long slot = (key * 40503) & TABLE_MASK;
            while (t_key[slot] != -1 && t_key[slot] != key) slot = (slot + 1) & TABLE_MASK;
            if (t_key[slot] == key) {
                p_rec[k] = t_rec[slot];
                p_uv[k][0] = t_val[3 * slot];
                p_uv[k][1] = t_val[3 * slot + 1];
                p_fac[k] = t_val[3 * slot + 2];
                continue;
            }
            long t2;
            double ur = 0.0, vr = 0.0, fac, lu = NAN, lv = NAN;
            long r = trace_one(&B, x0x, x0y, x0z, t1, u, v, bounces, refract1, refract2, second_ok, tri_rec, tri_p,
                               tri_n, tri_ior, tri_role, eps, planes, n_planes, &t2, &ur, &vr, &fac);
            if (r >= 0) {
                __global const double *w = tri_uv + 6 * r;
                lu = w[0] + ur * (w[2] - w[0]) + vr * (w[4] - w[0]);
                lv = w[1] + ur * (w[3] - w[1]) + vr * (w[5] - w[1]);
            }
            traced++;
            p_rec[k] = r;
            p_uv[k][0] = lu;
            p_uv[k][1] = lv;
            p_fac[k] = fac;
            if (n_used < TABLE_SIZE / 2) {
                t_key[slot] = key;
                t_rec[slot] = r;
                t_val[3 * slot] = lu;
                t_val[3 * slot + 1] = lv;
                t_val[3 * slot + 2] = fac;
                n_used++;
            }
        }
        for (int k = 0; k < 6; k++) robj[k] = p_rec[k] >= 0 ? receiver_of_tri[p_rec[k]] : -1;
        int landed = robj[0] >= 0;
        for (int k = 1; k < 6; k++) landed = landed && robj[k] == robj[0];
        if (!landed) {  // the host's levels go on from here
            int at = atomic_inc(counts + 1);
            if (at < hand_cap) {
                __global double *row = hands + (long)at * H_ROW;
                row[H_EMITTER] = (double)e;
                row[H_DEPTH] = (double)depth;
                row[H_INHERITED] = inherited;
                for (int c = 0; c < 3; c++) {
                    row[H_BARY + 2 * c] = p_bary[c][0];
                    row[H_BARY + 2 * c + 1] = p_bary[c][1];
                }
                for (int k = 0; k < 6; k++) {
                    row[H_REC + k] = (double)p_rec[k];
                    row[H_UV + 2 * k] = p_uv[k][0];
                    row[H_UV + 2 * k + 1] = p_uv[k][1];
                    row[H_FAC + k] = p_fac[k];
                }
                row[H_WIDTH] = (double)nh;
            }
            nh++;
            continue;
        }
        double dev = 0.0, edge = 0.0;
        for (int c = 0; c < 3; c++) {
            int c2 = (c + 1) % 3;
            for (int a = 0; a < 2; a++) {
                dev = NB_MAX(dev, fabs(p_uv[3 + c][a] - 0.5 * (p_uv[c][a] + p_uv[c2][a])));
                edge = NB_MAX(edge, fabs(p_uv[c][a] - p_uv[c2][a]));
            }
        }
        double tex = texel_size[robj[0]];
        for (int k = 0; k < 6; k++) {
            pu[k] = p_uv[k][0];
            pv[k] = p_uv[k][1];
        }
        // beyond an edge of a flat receiver's region: lands nowhere (receiver_planes)
        if (n_planes > 0 && beyond_region(planes, n_planes, robj[0], pu, pv, 2.0 * dev + tex)) continue;
        double rel = relative;
        if (depth < 0) {
            double q = coarse_linear_texels * tex / NB_MAX(edge, 1e-300);
            rel = relative * NB_MIN(1.0, q * q);
        }
        int linear = dev <= rel * edge;
        if (linear && density) {
            for (int k = 0; k < 6; k++)
                w6[k] = light_weight(parallel, x0, tri_p, t1, e, p_bary[k][0], p_bary[k][1]) * p_fac[k];
            linear = density_nonlinearity(pu, pv, w6) <= rel;
        }
        int final;
        if (depth < 0) final = dev <= tolerance * tex && linear && edge <= coarse_texels * tex;
        else final = dev <= tolerance * tex && (linear || edge <= tex);
        if (final || depth >= max_depth) {
            int at = atomic_inc(counts);
            if (at < final_cap) {
                __global double *row = finals + (long)at * F_ROW;
                row[F_EMITTER] = (double)e;
                row[F_RECEIVER] = (double)robj[0];
                row[F_DEPTH] = (double)depth;
                row[F_DEV] = dev;
                for (int c = 0; c < 3; c++) {
                    row[F_BARY + 2 * c] = p_bary[c][0];
                    row[F_BARY + 2 * c + 1] = p_bary[c][1];
                    row[F_UV + 2 * c] = p_uv[c][0];
                    row[F_UV + 2 * c + 1] = p_uv[c][1];
                    row[F_MID_UV + 2 * c] = p_uv[3 + c][0];
                    row[F_MID_UV + 2 * c + 1] = p_uv[3 + c][1];
                    row[F_FACTOR + c] = p_fac[c];
                    row[F_FACTOR + 3 + c] = p_fac[3 + c];
                }
                row[F_WIDTH] = (double)nf;
            }
            nf++;
            continue;
        }
        // split in four; child 0 ends on top of the stack (popped first), child 3 takes the
        // parent's row (its corners are all midpoints, held in p_*)
        double scale = 0.5 * edge / tex;
        for (int child = 0; child < 4; child++) {
            int dst = top + 3 - child;
            for (int c = 0; c < 3; c++) {
                int p = CHILD_CORNERS[3 * child + c];
                s_bary[dst][2 * c] = p_bary[p][0];
                s_bary[dst][2 * c + 1] = p_bary[p][1];
                s_rec[dst][c] = p_rec[p];
                s_uv[dst][2 * c] = p_uv[p][0];
                s_uv[dst][2 * c + 1] = p_uv[p][1];
                s_fac[dst][c] = p_fac[p];
            }
            s_depth[dst] = depth + 1;
            s_inh[dst] = scale;
        }
        top += 4;
    }
    per_emitter[3 * i] = nf;
    per_emitter[3 * i + 1] = nh;
    per_emitter[3 * i + 2] = traced;
}
