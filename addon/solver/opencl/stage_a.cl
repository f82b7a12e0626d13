// Stage A of addon/solver/spoly/two_bounce/staged.py on the device: per tuple and orientation
// (forward, reversed) the side tests and local frame (frame.cl), the √ pieces and orientations
// to solve, every bivariate system {a = 0, b = 0} built (system.cl: eq 6 with 10 or 13 after the
// map of eq 14-17), normalised and rejected early as _prepare_system does, its live scan pieces
// found by the (u1, v1) pre-pass (prepass.cl), and the system packed for the scan (row i of a
// total-degree-d polynomial: the coefficients of u^i v^j) — _stage_a_tuple and
// _stage_a_oriented step for step, so the systems, their order and their live pieces are the
// Numba stage's.  Then gather_systems compacts the staged tuples' systems, tuple by tuple, for
// the scan (two_bounce.cl).
//
// Each work-item has N_SLOTS x BIV_N x BIV_N doubles of global scratch (biv.cl) and MAX_PIECES
// bytes of live-piece scratch; the host runs the tuples in launches of as many work-items as
// its scratch holds.

// _pack: the triangle of p (total degree d) row by row into out[off ..]
static void pack_triangle(__global const double *p, int d, __global double *out, int off) {
    int k = off;
    for (int i = 0; i <= d; ++i)
        for (int j = 0; j <= d - i; ++j) out[k++] = AT(p, i, j);
}

// _stage_a_oriented: the systems of one orientation, stored from index nsys on (sysint7 rows
// (rev + 2 * not refined, status, da, db, na, nb, n), coef rows, live rows) while there is
// room (sys_cap); returns the new count (beyond sys_cap: the tuple goes to the one-kernel path).
static int stage_a_oriented(bool refract1, bool refract2, __global const double *x0, __global const double *x3,
                            __global const double *PA, __global const double *NA, __global const double *PB,
                            __global const double *NB, double eta, int rev, __global double *biv, int b_offset,
                            int stride, __global double *coef, __global int *sysint7, int nsys, int sys_cap,
                            __global long *stats, int pieces, __global char *live_mask, __global char *live) {
    double geo[45], geo_l[45];
    fr_frame F = fr_tuple_frame(refract1, refract2, x0, x3, PA, NA, PB, NB, geo, geo_l, stats);
    if (!F.ok) return nsys;
    int n_orient1 = refract1 ? 2 : 1, n_side2 = refract2 ? 2 : 1;
    int n_pieces_sqrt = refract1 ? N_SQRT_PIECES : 1;
    for (int o1 = 0; o1 < n_orient1; ++o1) {
        double sigma1 = o1 == 0 ? 1.0 : -1.0;
        if (refract1 && ((sigma1 > 0.0 && !F.any_front1) || (sigma1 < 0.0 && !F.any_back1))) continue;
        double s_in1 = sigma1 * (F.side0 > 0.0 ? 1.0 : -1.0);
        double r1 = s_in1 > 0.0 ? 1.0 / eta : eta;
        // sqrt_pieces_to_solve
        int mask = 0, fallback_piece = -2;
        double xlo = INFINITY, xhi = -INFINITY;
        if (refract1 && !fr_sqrt_sampling(refract1, geo, F.inv, F.S, F.cx, r1, &mask, &fallback_piece, &xlo, &xhi))
            continue;  // total internal reflection everywhere on the triangle
        if (refract1 && SQRT_BANDS) {
            bv_beta_poly(geo_l, r1, biv);
            if (xlo > 0.0) mask |= pp_beta_mask(biv, V_MARGIN_APPROX, F.S * F.S);
        }
        bool heron_ok = false;
        double heron_cut = HERON_CUT, heron[6] = {0.0, 0.0, 0.0, 0.0, 0.0, 0.0};
        if (refract1 && HERON_SQRT) heron_ok = fr_heron_sqrt_cut(geo_l, r1, V_MARGIN_APPROX, F.S * F.S, &heron_cut, heron);
        for (int piece = -1; piece < n_pieces_sqrt; ++piece) {
            // piece -1: the Heron √ (β/S² above its cut), then the eq (23) pieces (only those
            // reaching below the cut when the Heron √ is used)
            if (piece < 0 && !heron_ok) continue;
            if (piece >= 0 && heron_ok && SQRT_PIECES_T[piece][0] >= heron_cut) continue;
            if (piece >= 0 && refract1 && !((mask >> piece) & 1)) continue;
            for (int o2 = 0; o2 < n_side2; ++o2) {
                double eta_in2 = 1.0, eta_out2 = 1.0;
                if (refract2) {
                    double sigma2 = o2 == 0 ? 1.0 : -1.0;
                    if ((sigma2 > 0.0 && !F.any_front2) || (sigma2 < 0.0 && !F.any_back2)) continue;
                    double s_in2 = -sigma2 * (F.side3 > 0.0 ? 1.0 : -1.0);
                    eta_in2 = s_in2 > 0.0 ? 1.0 : eta;
                    eta_out2 = s_in2 > 0.0 ? eta : 1.0;
                }
                int da, db;
                bv_build_system(refract1, refract2, s_in1, r1, piece, F.S, heron, eta_in2, eta_out2, F.flat2, F.c2, geo_l,
                                biv, &da, &db);
                int na, nb, n;
                int status = bv_prepare_system(biv, da, db, refract1, stats, &na, &nb, &n);
                if (status == 0) continue;
                if (status == 1) {
                    if (LIVE_PREPASS) {
                        double blo, bhi;
                        fr_sqrt_band(piece, F.S * F.S, refract1, &blo, &bhi);
                        if (pp_live_pieces_band(SLOT(biv, 0), da, SLOT(biv, 1), db,
                                                refract1 ? V_MARGIN_APPROX : V_MARGIN_EXACT, pieces, biv, live, blo,
                                                bhi) == 0)
                            continue;  // as _eliminate: no common zero near the triangle
                    } else {
                        for (int k = 0; k < pieces; ++k) live[k] = 1;
                    }
                }
                if (nsys < sys_cap) {
                    __global int *si = sysint7 + 7 * nsys;
                    si[0] = rev + (piece == fallback_piece ? 2 : 0);  // bit 1: not refined
                    si[1] = status;
                    si[2] = da;
                    si[3] = db;
                    si[4] = na;
                    si[5] = nb;
                    si[6] = n;
                    if (status == 1) {
                        pack_triangle(SLOT(biv, 0), da, coef + (long)nsys * stride, 0);
                        pack_triangle(SLOT(biv, 1), db, coef + (long)nsys * stride, b_offset);
                        for (int k = 0; k < pieces; ++k) live_mask[(long)nsys * pieces + k] = live[k];
                    }
                }
                nsys += 1;
            }
        }
    }
    return nsys;
}

// _stage_a_tuple for the tuples t0 + i, i < n_items: its systems (at most sys_cap kept) into
// coef / sysint7 / live_mask rows t * sys_cap .., their count nsys[t], state[t] (0 nothing to
// solve, 1 staged, 2 more than sys_cap systems), its statistics (zeroed first).
__kernel void stage_a(const int refract1, const int refract2, __global const double *x_start,
                      __global const double *x_end, __global const double *P, __global const double *N,
                      __global const double *eta_all, const int b_offset, const int stride, const int sys_cap,
                      const int pieces, const int t0, const int n_items, __global double *coef, __global int *sysint7,
                      __global int *nsys, __global char *state, __global long *stats, __global char *live_mask,
                      __global double *scratch, __global char *live_scratch) {
    int g = get_global_id(0);
    if (g >= n_items) return;
    int t = t0 + g;
    __global double *biv = scratch + (long)g * N_SLOTS * BIV_SLOT_SIZE;
    __global char *live = live_scratch + (long)g * MAX_PIECES;
    __global long *st = stats + (long)t * N_STATS;
    for (int k = 0; k < N_STATS; ++k) st[k] = 0;
    nsys[t] = 0;
    __global const double *x0 = x_start + 3 * (long)t, *x3 = x_end + 3 * (long)t;
    __global const double *PA = P + 18 * (long)t, *NA = N + 18 * (long)t, *PB = PA + 9, *NB = NA + 9;
    double eta = eta_all[t], geo[45];
    if (!tv_pack_geometry(x0, x3, PA, NA, PB, NB, geo) || !(eta > 0.0)) {
        st[STAT_SKIPPED] = 1;
        state[t] = 0;
        return;
    }
    __global double *c = coef + (long)t * sys_cap * stride;
    __global int *si = sysint7 + (long)t * sys_cap * 7;
    __global char *lm = live_mask + (long)t * sys_cap * pieces;
    int m = stage_a_oriented(refract1, refract2, x0, x3, PA, NA, PB, NB, eta, 0, biv, b_offset, stride, c, si, 0, sys_cap,
                             st, pieces, lm, live);
    if (BOTH_DIRECTIONS)
        m = stage_a_oriented(refract2, refract1, x3, x0, PB, NB, PA, NA, eta, 1, biv, b_offset, stride, c, si, m, sys_cap,
                             st, pieces, lm, live);
    nsys[t] = m;
    state[t] = m > sys_cap ? 2 : 1;
}

// The staged tuples' systems in stage A's order, tuple by tuple (system s is slot slot[s] of
// tuple owner[s]): packed coefficients, sysint7, sysint3 = (da, db, n), live pieces, the scan's
// v margin (V_MARGIN_APPROX where the oriented chain refracts at its first vertex), solve
// (status 1) and refinable (status 1 and not the TIR fallback's system).
__kernel void gather_systems(__global const int *owner, __global const int *slot, const int n_sys, const int refract1,
                             const int refract2, const int stride, const int sys_cap, const int pieces,
                             __global const double *coef_all, __global const int *sysint7_all,
                             __global const char *live_all, __global double *coef, __global int *sysint7,
                             __global int *sysint3, __global char *live, __global double *margin, __global char *solve,
                             __global char *refinable) {
    int s = get_global_id(0);
    if (s >= n_sys) return;
    long r = (long)owner[s] * sys_cap + slot[s];
    for (int k = 0; k < stride; ++k) coef[(long)s * stride + k] = coef_all[r * stride + k];
    for (int k = 0; k < 7; ++k) sysint7[7 * s + k] = sysint7_all[7 * r + k];
    for (int k = 0; k < pieces; ++k) live[(long)s * pieces + k] = live_all[r * pieces + k];
    __global const int *si = sysint7_all + 7 * r;
    sysint3[3 * s] = si[2];
    sysint3[3 * s + 1] = si[3];
    sysint3[3 * s + 2] = si[6];
    bool r1 = (si[0] & 1) ? refract2 : refract1;
    margin[s] = r1 ? V_MARGIN_APPROX : V_MARGIN_EXACT;
    solve[s] = si[1] == 1;
    refinable[s] = si[1] == 1 && (si[0] & 2) == 0;
}
