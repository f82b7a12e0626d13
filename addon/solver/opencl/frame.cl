// The per-orientation set-up of a two-bounce tuple (Fan et al. 2024 §3.4, §4.1) in OpenCL C:
// the same arithmetic, step for step, as addon/solver/spoly/two_bounce/frame.py (_corner_sides,
// tuple_frame, the sampling and centroid part of sqrt_pieces_to_solve) and the scalar parts of
// addon/solver/spoly/two_bounce/sqrt.py (sqrt_piece, centroid_piece, sqrt_band, beta_local,
// _quadratic_at, _heron_fit, heron_sqrt_cut), so both back ends set up the same systems, bit
// for bit (tests/solver/test_opencl_frame.py).
//
// Pasted by the host into another program after
//     #pragma OPENCL EXTENSION cl_khr_fp64 : enable
//     #pragma OPENCL FP_CONTRACT OFF
// (double precision, no fused multiply-adds), after two_bounce_tables() (SQRT_PIECES_T,
// HERON_CUTS_T) and two_vertex.cl (tv_pack_geometry), built with _two_bounce_defines() (STAT_SKIPPED,
// HERON_CUT, HERON_TOL, HERON_FIT_GRID, HERON_CHECK_GRID, SQRT_BANDS, SQRT_BAND_REACH,
// N_SQRT_PIECES, N_HERON_CUTS).  It defines no kernel, and every name starts with fr_ / FR_.
// geo and geo_l are the packed geometry of pack_geometry and its local frame: 15 rows x 3,
// row-major (45 doubles, private).
// Expressions keep Python's evaluation order (left to right, x ** 2 as x * x), no built-in dot,
// length, fma, mad; max(a, b) / min(a, b) as Numba's (b if b > a / b < a, else a: ties and NaN as
// Python's, not fmax's / fmin's).

#define FR_G(m, r, c) ((m)[3 * (r) + (c)])

// @INCLUDE numba_math.cl@ (NB_MAX, NB_MIN)

// What tuple_frame returns besides geo and geo_l (all zero / false where ok is false).
typedef struct {
    bool ok;
    double side0, side3, inv, S;
    bool any_front1, any_back1, any_front2, any_back2, flat2;
    double cx[3], c2[3];
} fr_frame;

static fr_frame fr_fail(void) {
    fr_frame F;
    F.ok = false;
    F.side0 = 0.0; F.side3 = 0.0; F.inv = 0.0; F.S = 0.0;
    F.any_front1 = false; F.any_back1 = false; F.any_front2 = false; F.any_back2 = false; F.flat2 = false;
    for (int a = 0; a < 3; ++a) { F.cx[a] = 0.0; F.c2[a] = 0.0; }
    return F;
}

// frame.py _corner_sides: least and greatest (q - o) . n x side over the corners q of the
// triangle (p0, e1, e2).
static void fr_corner_sides(const double *p0, const double *e1, const double *e2, const double *o, const double *n,
                            double side, double *lo, double *hi) {
    double l = INFINITY;
    double h = -INFINITY;
    for (int c = 0; c < 3; ++c) {
        double q[3] = {p0[0], p0[1], p0[2]};
        if (c == 1) {
            q[0] = p0[0] + e1[0]; q[1] = p0[1] + e1[1]; q[2] = p0[2] + e1[2];
        } else if (c == 2) {
            q[0] = p0[0] + e2[0]; q[1] = p0[1] + e2[1]; q[2] = p0[2] + e2[2];
        }
        double sd = (q[0] - o[0]) * n[0] + (q[1] - o[1]) * n[1] + (q[2] - o[2]) * n[2];
        l = NB_MIN(l, sd * side);
        h = NB_MAX(h, sd * side);
    }
    *lo = l;
    *hi = h;
}

// frame.py tuple_frame: side tests, local frame and orientation cases of the tuple (triangle A
// first).  Fills geo (tv_pack_geometry) and geo_l (rows 0..12: the frame); returns the frame,
// ok false (and stats[STAT_SKIPPED] counted where a side / degeneracy test failed, not for a
// zero-area triangle) when no path can exist.
static fr_frame fr_tuple_frame(bool refract1, bool refract2, __global const double *x0, __global const double *x3,
                               __global const double *PA, __global const double *NA, __global const double *PB,
                               __global const double *NB, double *geo, double *geo_l, __global long *stats) {
    if (!tv_pack_geometry(x0, x3, PA, NA, PB, NB, geo)) return fr_fail();
    // --- cheap side tests ---
    double ng1[3] = {FR_G(geo, 13, 0), FR_G(geo, 13, 1), FR_G(geo, 13, 2)};
    double ng2[3] = {FR_G(geo, 14, 0), FR_G(geo, 14, 1), FR_G(geo, 14, 2)};
    double e11[3] = {FR_G(geo, 2, 0), FR_G(geo, 2, 1), FR_G(geo, 2, 2)};
    double e12[3] = {FR_G(geo, 3, 0), FR_G(geo, 3, 1), FR_G(geo, 3, 2)};
    double p20[3] = {FR_G(geo, 7, 0), FR_G(geo, 7, 1), FR_G(geo, 7, 2)};
    double e21[3] = {FR_G(geo, 8, 0), FR_G(geo, 8, 1), FR_G(geo, 8, 2)};
    double e22[3] = {FR_G(geo, 9, 0), FR_G(geo, 9, 1), FR_G(geo, 9, 2)};
    const double zero[3] = {0.0, 0.0, 0.0};
    double L1 = NB_MAX(sqrt(e11[0] * e11[0] + e11[1] * e11[1] + e11[2] * e11[2]),
                       sqrt(e12[0] * e12[0] + e12[1] * e12[1] + e12[2] * e12[2]));
    double L2 = NB_MAX(sqrt(e21[0] * e21[0] + e21[1] * e21[1] + e21[2] * e21[2]),
                       sqrt(e22[0] * e22[0] + e22[1] * e22[1] + e22[2] * e22[2]));
    double side0 = FR_G(geo, 0, 0) * ng1[0] + FR_G(geo, 0, 1) * ng1[1] + FR_G(geo, 0, 2) * ng1[2];
    if (fabs(side0) <= 1e-12 * L1) {
        stats[STAT_SKIPPED] += 1;
        return fr_fail();
    }
    // triangle 2's corners against plane 1 (through the origin p1,0)
    double lo2, hi2;
    fr_corner_sides(p20, e21, e22, zero, ng1, side0, &lo2, &hi2);
    double tol1 = 1e-9 * (L1 + L2) * fabs(side0);
    if ((!refract1 && hi2 <= tol1) || (refract1 && lo2 >= -tol1)) {
        stats[STAT_SKIPPED] += 1;
        return fr_fail();
    }
    // x3 and triangle 1's corners against plane 2
    double side3 = (FR_G(geo, 1, 0) - p20[0]) * ng2[0] + (FR_G(geo, 1, 1) - p20[1]) * ng2[1]
                   + (FR_G(geo, 1, 2) - p20[2]) * ng2[2];
    if (fabs(side3) <= 1e-12 * L2) {
        stats[STAT_SKIPPED] += 1;
        return fr_fail();
    }
    double lo1, hi1;
    fr_corner_sides(zero, e11, e12, p20, ng2, side3, &lo1, &hi1);
    double tol2 = 1e-9 * (L1 + L2) * fabs(side3);
    if ((!refract2 && hi1 <= tol2) || (refract2 && lo1 >= -tol2)) {
        stats[STAT_SKIPPED] += 1;
        return fr_fail();
    }

    // --- local frame: unit = L1, origin p1,0 (geo is already relative to p1,0) ---
    double inv = 1.0 / L1;
    for (int r = 0; r < 13; ++r) {
        double f = (r <= 3 || (r >= 7 && r <= 9)) ? inv : 1.0;
        for (int c = 0; c < 3; ++c) FR_G(geo_l, r, c) = FR_G(geo, r, c) * f;
    }
    // normal orientation over each face
    bool any_front1 = false, any_back1 = false, any_front2 = false, any_back2 = false;
    double nmax1 = 0.0;
    bool flat2 = true;
    double nscale2 = 0.0;
    for (int c = 0; c < 3; ++c) {
        double n1c[3] = {FR_G(geo, 4, 0), FR_G(geo, 4, 1), FR_G(geo, 4, 2)};
        double n2c[3] = {FR_G(geo, 10, 0), FR_G(geo, 10, 1), FR_G(geo, 10, 2)};
        if (c > 0) {
            for (int a = 0; a < 3; ++a) {
                n1c[a] = n1c[a] + FR_G(geo, 4 + c, a);
                n2c[a] = n2c[a] + FR_G(geo, 10 + c, a);
            }
        }
        double s_1 = n1c[0] * ng1[0] + n1c[1] * ng1[1] + n1c[2] * ng1[2];
        double s_2 = n2c[0] * ng2[0] + n2c[1] * ng2[1] + n2c[2] * ng2[2];
        any_front1 = any_front1 || s_1 > 0.0;
        any_back1 = any_back1 || s_1 < 0.0;
        any_front2 = any_front2 || s_2 > 0.0;
        any_back2 = any_back2 || s_2 < 0.0;
        nmax1 = NB_MAX(nmax1, n1c[0] * n1c[0] + n1c[1] * n1c[1] + n1c[2] * n1c[2]);
        nscale2 = NB_MAX(nscale2, sqrt(n2c[0] * n2c[0] + n2c[1] * n2c[1] + n2c[2] * n2c[2]));
    }
    for (int r = 11; r <= 12; ++r) {
        if (fabs(FR_G(geo, r, 0)) + fabs(FR_G(geo, r, 1)) + fabs(FR_G(geo, r, 2)) > 1e-12 * nscale2) flat2 = false;
    }
    if (!(nmax1 > 0.0 && nscale2 > 0.0)) {
        stats[STAT_SKIPPED] += 1;
        return fr_fail();
    }
    // plane-of-incidence normal at vertex 2: (x3 - centroid1) x mean n2
    double cx[3], w[3], nb[3], c2[3];
    for (int a = 0; a < 3; ++a) cx[a] = (e11[a] + e12[a]) / 3.0;
    for (int a = 0; a < 3; ++a) w[a] = FR_G(geo, 1, a) - cx[a];
    for (int a = 0; a < 3; ++a) nb[a] = 3.0 * FR_G(geo, 10, a) + FR_G(geo, 11, a) + FR_G(geo, 12, a);
    c2[0] = w[1] * nb[2] - w[2] * nb[1];
    c2[1] = w[2] * nb[0] - w[0] * nb[2];
    c2[2] = w[0] * nb[1] - w[1] * nb[0];
    double lc = sqrt(c2[0] * c2[0] + c2[1] * c2[1] + c2[2] * c2[2]);
    double lw = sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2]);
    double lnb = sqrt(nb[0] * nb[0] + nb[1] * nb[1] + nb[2] * nb[2]);
    if (!(lc > 1e-6 * lw * lnb)) {
        c2[0] = e21[1] * nb[2] - e21[2] * nb[1];
        c2[1] = e21[2] * nb[0] - e21[0] * nb[2];
        c2[2] = e21[0] * nb[1] - e21[1] * nb[0];
        lc = sqrt(c2[0] * c2[0] + c2[1] * c2[1] + c2[2] * c2[2]);
        if (!(lc > 0.0)) {
            stats[STAT_SKIPPED] += 1;
            return fr_fail();
        }
    }
    for (int a = 0; a < 3; ++a) c2[a] = c2[a] / lc;

    // sqrt(beta) scale S over triangle 1
    double dmax = 0.0;
    for (int c = 0; c < 3; ++c) {
        double q[3] = {0.0, 0.0, 0.0};
        if (c == 1) {
            q[0] = e11[0]; q[1] = e11[1]; q[2] = e11[2];
        } else if (c == 2) {
            q[0] = e12[0]; q[1] = e12[1]; q[2] = e12[2];
        }
        double dv[3] = {q[0] - FR_G(geo, 0, 0), q[1] - FR_G(geo, 0, 1), q[2] - FR_G(geo, 0, 2)};
        dmax = NB_MAX(dmax, (dv[0] * dv[0] + dv[1] * dv[1] + dv[2] * dv[2]) * inv * inv);
    }
    fr_frame F;
    F.ok = true;
    F.side0 = side0;
    F.side3 = side3;
    F.inv = inv;
    F.S = sqrt(nmax1 * dmax);
    F.any_front1 = any_front1;
    F.any_back1 = any_back1;
    F.any_front2 = any_front2;
    F.any_back2 = any_back2;
    F.flat2 = flat2;
    for (int a = 0; a < 3; ++a) {
        F.cx[a] = cx[a];
        F.c2[a] = c2[a];
    }
    return F;
}

// --- sqrt.py: the pieces of eq (23) ---

// sqrt.py sqrt_piece: the eq (23) piece holding x = beta/S^2
static int fr_sqrt_piece(double x) {
    int k = 0;
    while (k < N_SQRT_PIECES - 1 && x > SQRT_PIECES_T[k][1]) k += 1;
    return k;
}

// sqrt.py centroid_piece: mask with the centroid's piece added (returned); *fallback_piece: the
// piece solved only as the TIR fallback (0) or -2.
static int fr_centroid_piece(double xc, int mask, int *fallback_piece) {
    if (xc > 0.0 || (mask & 1)) {
        *fallback_piece = -2;
        return mask | (1 << fr_sqrt_piece(xc));
    }
    *fallback_piece = 0;
    return mask | 1;
}

// sqrt.py sqrt_band: the beta band [*blo, *bhi] where piece's system is solved.
static void fr_sqrt_band(int piece, double S2, bool refract1, double *blo, double *bhi) {
    bool bands = SQRT_BANDS != 0;  // (a variable: no constant-operand warning)
    if (!refract1 || !bands) {
        *blo = -INFINITY;
        *bhi = INFINITY;
        return;
    }
    if (piece < 0) {
        *blo = 0.0;
        *bhi = INFINITY;
        return;
    }
    *blo = piece < SQRT_BAND_REACH ? 0.0 : S2 * SQRT_PIECES_T[piece - SQRT_BAND_REACH][0];
    *bhi = piece + SQRT_BAND_REACH >= N_SQRT_PIECES ? INFINITY : S2 * SQRT_PIECES_T[piece + SQRT_BAND_REACH][1];
}

// frame.py sqrt_pieces_to_solve without beta_poly / beta_mask: the beta/S^2 range sampled over
// triangle 1 (*xlo, *xhi: inf / -inf without refract1), the pieces holding it (*mask) and the
// centroid's (*fallback_piece).  Returns false where Python returns ok=False (TIR everywhere:
// *mask 0, *fallback_piece -2).  The caller adds beta_mask's bits where refract1, SQRT_BANDS and
// *xlo > 0, as Python does.
static bool fr_sqrt_sampling(bool refract1, const double *geo, double inv, double S, const double *cx, double r1,
                             int *mask, int *fallback_piece, double *xlo, double *xhi) {
    double e11[3] = {FR_G(geo, 2, 0), FR_G(geo, 2, 1), FR_G(geo, 2, 2)};
    double e12[3] = {FR_G(geo, 3, 0), FR_G(geo, 3, 1), FR_G(geo, 3, 2)};
    double lo = INFINITY;
    double hi = -INFINITY;
    int fb = -2;
    int m = 0;
    if (refract1) {
        for (int iu = 0; iu < 4; ++iu) {
            for (int iv = 0; iv < 4 - iu; ++iv) {
                double uu = (double)iu / 3.0;
                double vv = (double)iv / 3.0;
                double nn[3], dv[3];
                for (int a = 0; a < 3; ++a) {
                    nn[a] = FR_G(geo, 4, a) + uu * FR_G(geo, 5, a) + vv * FR_G(geo, 6, a);
                    dv[a] = (uu * e11[a] + vv * e12[a] - FR_G(geo, 0, a)) * inv;
                }
                double n2_ = nn[0] * nn[0] + nn[1] * nn[1] + nn[2] * nn[2];
                double d2_ = dv[0] * dv[0] + dv[1] * dv[1] + dv[2] * dv[2];
                double dn = nn[0] * dv[0] + nn[1] * dv[1] + nn[2] * dv[2];
                double beta = n2_ * d2_ * (1.0 - r1 * r1) + r1 * r1 * dn * dn;
                double x = beta / (S * S);
                lo = NB_MIN(lo, x);
                hi = NB_MAX(hi, x);
                if (x >= 0.0) m |= 1 << fr_sqrt_piece(x);
            }
        }
        double nn[3], dv[3];
        for (int a = 0; a < 3; ++a) {
            nn[a] = FR_G(geo, 4, a) + (FR_G(geo, 5, a) + FR_G(geo, 6, a)) / 3.0;
            dv[a] = (cx[a] - FR_G(geo, 0, a)) * inv;
        }
        double n2_ = nn[0] * nn[0] + nn[1] * nn[1] + nn[2] * nn[2];
        double d2_ = dv[0] * dv[0] + dv[1] * dv[1] + dv[2] * dv[2];
        double dn = nn[0] * dv[0] + nn[1] * dv[1] + nn[2] * dv[2];
        double xc = NB_MIN(1.0, NB_MAX(0.0, (n2_ * d2_ * (1.0 - r1 * r1) + r1 * r1 * dn * dn) / (S * S)));
        *xlo = lo;
        *xhi = hi;
        if (hi <= 0.0) {  // TIR everywhere on the triangle
            *mask = 0;
            *fallback_piece = -2;
            return false;
        }
        m = fr_centroid_piece(xc, m, &fb);
    }
    *xlo = lo;
    *xhi = hi;
    *mask = m;
    *fallback_piece = fb;
    return true;
}

// --- sqrt.py: one sqrt for the whole triangle, a Heron step from a fitted quadratic ---

// sqrt.py beta_local: beta(u1, v1) of eq (22) at one point (local frame geo_l)
static double fr_beta_local(double u, double v, const double *geo_l, double r) {
    double d0[3], n1[3];
    for (int a = 0; a < 3; ++a) {
        d0[a] = u * FR_G(geo_l, 2, a) + v * FR_G(geo_l, 3, a) - FR_G(geo_l, 0, a);
        n1[a] = FR_G(geo_l, 4, a) + u * FR_G(geo_l, 5, a) + v * FR_G(geo_l, 6, a);
    }
    double nn = n1[0] * n1[0] + n1[1] * n1[1] + n1[2] * n1[2];
    double dd = d0[0] * d0[0] + d0[1] * d0[1] + d0[2] * d0[2];
    double dn = d0[0] * n1[0] + d0[1] * n1[1] + d0[2] * n1[2];
    return nn * dd * (1.0 - r * r) + r * r * dn * dn;
}

// sqrt.py _quadratic_at: c (1, u, v, u^2, uv, v^2) at (u, v)
static double fr_quadratic_at(const double *c, double u, double v) {
    return c[0] + u * c[1] + v * c[2] + u * u * c[3] + u * v * c[4] + v * v * c[5];
}

// sqrt.py _heron_fit: returns ok, *enough (enough fit points above the cut), c (6: q's
// coefficients; zero where too few points or a singular pivot, the fitted ones after a failed
// check).
static bool fr_heron_fit(const double *geo_l, double r, double margin, double S2, double cut, bool *enough,
                         double *c) {
    double M[6][7];
    for (int k = 0; k < 6; ++k) c[k] = 0.0;
    for (int i = 0; i < 6; ++i)
        for (int j = 0; j < 7; ++j) M[i][j] = 0.0;
    double w = 1.0 + 3.0 * margin;
    int G = HERON_FIT_GRID;
    int n_fit = 0;
    for (int i = 0; i < G + 1; ++i) {
        for (int j = 0; j < G + 1 - i; ++j) {
            double u = -margin + w * (double)i / (double)G;
            double v = -margin + w * (double)j / (double)G;
            double beta = fr_beta_local(u, v, geo_l, r);
            if (!(beta >= cut * S2)) continue;
            n_fit += 1;
            double y = sqrt(beta);
            double wt = 1.0 / beta;
            double phi[6] = {1.0, u, v, u * u, u * v, v * v};
            for (int k = 0; k < 6; ++k) {
                for (int l = 0; l < 6; ++l) M[k][l] += wt * phi[k] * phi[l];
                M[k][6] += wt * phi[k] * y;
            }
        }
    }
    if (n_fit < 12) {
        *enough = false;
        return false;
    }
    *enough = true;
    // Gaussian elimination with partial pivoting on the 6 x 7 augmented matrix
    for (int k = 0; k < 6; ++k) {
        int p = k;
        for (int i = k + 1; i < 6; ++i)
            if (fabs(M[i][k]) > fabs(M[p][k])) p = i;
        if (!(fabs(M[p][k]) > 1e-300)) return false;
        if (p != k) {
            for (int j = 0; j < 7; ++j) {
                double t = M[k][j];
                M[k][j] = M[p][j];
                M[p][j] = t;
            }
        }
        for (int i = k + 1; i < 6; ++i) {
            double f = M[i][k] / M[k][k];
            for (int j = k; j < 7; ++j) M[i][j] -= f * M[k][j];
        }
    }
    for (int k = 5; k >= 0; --k) {
        double acc = M[k][6];
        for (int j = k + 1; j < 6; ++j) acc -= M[k][j] * M[j][6];
        M[k][6] = acc / M[k][k];
    }
    for (int k = 0; k < 6; ++k) c[k] = M[k][6];
    G = HERON_CHECK_GRID;
    for (int i = 0; i < G + 1; ++i) {
        for (int j = 0; j < G + 1 - i; ++j) {
            double u = -margin + w * (double)i / (double)G;
            double v = -margin + w * (double)j / (double)G;
            double beta = fr_beta_local(u, v, geo_l, r);
            if (!(beta >= cut * S2)) continue;
            double q = fr_quadratic_at(c, u, v);
            if (!(q > 0.0)) return false;
            double y = sqrt(beta);
            if (!((q - y) * (q - y) <= HERON_TOL * 2.0 * q * y)) return false;
        }
    }
    return true;
}

// sqrt.py heron_sqrt_cut: the Heron fit above the first cut of HERON_CUTS_T where it fits;
// returns ok, *cut and q's six coefficients (coeffs6).
static bool fr_heron_sqrt_cut(const double *geo_l, double r, double margin, double S2, double *cut,
                              double *coeffs6) {
    bool ok = false;
    double k_cut = HERON_CUTS_T[0];
    for (int k = 0; k < 6; ++k) coeffs6[k] = 0.0;
    for (int k = 0; k < N_HERON_CUTS; ++k) {
        k_cut = HERON_CUTS_T[k];
        bool enough;
        ok = fr_heron_fit(geo_l, r, margin, S2, k_cut, &enough, coeffs6);
        if (ok || !enough) break;
    }
    *cut = k_cut;
    return ok;
}
