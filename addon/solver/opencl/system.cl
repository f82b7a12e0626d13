// The bivariate algebra and the per-system construction of the two-bounce solver in OpenCL C:
// the same arithmetic, step for step, as
//     addon/solver/polynomials/bivariate.py  (bzero .. bernstein_has_zero: bv_bzero ..),
//     addon/solver/spoly/two_bounce/system.py (build_system: bv_build_system),
//     addon/solver/spoly/two_bounce/sqrt.py   (beta_poly: bv_beta_poly),
//     addon/solver/spoly/two_bounce/staged.py (_prepare_system: bv_prepare_system),
// so both back ends build bit-identical systems {a(u1, v1) = 0, b(u1, v1) = 0} (Fan et al. 2024
// §3.4, Table 3; tests/solver/test_opencl_system.py).
//
// Pasted by the host after
//     #pragma OPENCL EXTENSION cl_khr_fp64 : enable
//     #pragma OPENCL FP_CONTRACT OFF
// the build options' defines (_two_bounce_defines: MAXD, N_SLOTS, HIT_SLOT, BETA_SLOT,
// HIT_MARGIN_EXACT, HIT_MARGIN_APPROX, STAT_SKIPPED, ...), the tables of two_bounce_tables
// (SQRT_PIECES_T) and biv.cl (BIV_N, BIV_SLOT_SIZE, SLOT, AT).  No kernel; every name starts
// with bv_ / BV_.
//
// A bivariate polynomial is one biv slot (__global double *p, coefficient of u^i v^j at
// AT(p, i, j)), its total degree tracked by the caller; a "vector polynomial" (Python's
// biv[k:k+3]) is the pointer to its first slot, component c at BV_COMP(V, c).  Constant
// 3-vectors, geo_l (13 rows x 3, row-major, rows as in system.py), heron (6) and c2 (3) are
// private pointers.  Every product is a multiply then an add (FP_CONTRACT OFF, no fma / mad /
// dot / cross / length), loops in the Python order; max / min are written out as Python's
// (max(a, b) = b if b > a else a).

#define BV_COMP(V, c) ((V) + (long)(c) * BIV_SLOT_SIZE)
#define BV_ROW(g, r, c) ((g)[3 * (r) + (c)])

// rows_add_scaled_exact (runtime/simd.py): dst[k] += s * x[k] for k < n
static void bv_rows_add_scaled(__global double *dst, __global const double *x, double s, int n) {
    for (int k = 0; k < n; ++k) dst[k] = dst[k] + s * x[k];
}

// bzero: the triangle i + j <= d of p
static void bv_bzero(__global double *p, int d) {
    for (int i = 0; i <= d; ++i)
        for (int j = 0; j <= d - i; ++j) AT(p, i, j) = 0.0;
}

// bmul_acc: out += coef p q (out sized for total degree dp + dq)
static void bv_bmul_acc(__global const double *p, int dp, __global const double *q, int dq, __global double *out,
                        double coef) {
    for (int i1 = 0; i1 <= dp; ++i1)
        for (int j1 = 0; j1 <= dp - i1; ++j1) {
            double c = AT(p, i1, j1);
            if (c == 0.0) continue;
            c *= coef;
            for (int i2 = 0; i2 <= dq; ++i2) bv_rows_add_scaled(&AT(out, i1 + i2, j1), &AT(q, i2, 0), c, dq + 1 - i2);
        }
}

// badd: out += ca a (da <= d; d unused, as in Python)
static void bv_badd(__global double *out, int d, __global const double *a, int da, double ca) {
    for (int i = 0; i <= da; ++i) bv_rows_add_scaled(&AT(out, i, 0), &AT(a, i, 0), ca, da + 1 - i);
}

// vlin: vector polynomial of degree 1, c0 + u cu + v cv
static void bv_vlin(__global double *V, const double *c0, const double *cu, const double *cv) {
    for (int c = 0; c < 3; ++c) {
        __global double *Vc = BV_COMP(V, c);
        bv_bzero(Vc, 1);
        AT(Vc, 0, 0) = c0[c];
        AT(Vc, 1, 0) = cu[c];
        AT(Vc, 0, 1) = cv[c];
    }
}

// vdot: out = A . B; returns its degree dA + dB
static int bv_vdot(__global const double *A, int dA, __global const double *B, int dB, __global double *out) {
    int d = dA + dB;
    bv_bzero(out, d);
    for (int c = 0; c < 3; ++c) bv_bmul_acc(BV_COMP(A, c), dA, BV_COMP(B, c), dB, out, 1.0);
    return d;
}

// vcross: out = A x B (vector); returns dA + dB
static int bv_vcross(__global const double *A, int dA, __global const double *B, int dB, __global double *out) {
    int d = dA + dB;
    for (int c = 0; c < 3; ++c) bv_bzero(BV_COMP(out, c), d);
    for (int c = 0; c < 3; ++c) {
        int c1 = (c + 1) % 3, c2 = (c + 2) % 3;
        bv_bmul_acc(BV_COMP(A, c1), dA, BV_COMP(B, c2), dB, BV_COMP(out, c), 1.0);
        bv_bmul_acc(BV_COMP(A, c2), dA, BV_COMP(B, c1), dB, BV_COMP(out, c), -1.0);
    }
    return d;
}

// vdot_const: out = A . w (w a constant 3-vector); returns dA
static int bv_vdot_const(__global const double *A, int dA, const double *w, __global double *out) {
    bv_bzero(out, dA);
    for (int c = 0; c < 3; ++c) bv_badd(out, dA, BV_COMP(A, c), dA, w[c]);
    return dA;
}

// vcross_const: out = A x w (vector); returns dA
static int bv_vcross_const(__global const double *A, int dA, const double *w, __global double *out) {
    for (int c = 0; c < 3; ++c) bv_bzero(BV_COMP(out, c), dA);
    for (int c = 0; c < 3; ++c) {
        int c1 = (c + 1) % 3, c2 = (c + 2) % 3;
        bv_badd(BV_COMP(out, c), dA, BV_COMP(A, c1), dA, w[c2]);
        bv_badd(BV_COMP(out, c), dA, BV_COMP(A, c2), dA, -w[c1]);
    }
    return dA;
}

// bmax: the largest |coefficient| (0 at least; NaN coefficients skipped, as Python's max)
static double bv_bmax(__global const double *p, int d) {
    double m = 0.0;
    for (int i = 0; i <= d; ++i)
        for (int j = 0; j <= d - i; ++j) {
            double x = fabs(AT(p, i, j));
            m = x > m ? x : m;
        }
    return m;
}

// u_degree: the largest i with a coefficient above tiny in row i; the rows above are zeroed
static int bv_u_degree(__global double *p, int d, double tiny) {
    int n = d;
    while (n > 0) {
        double big = 0.0;
        for (int j = 0; j < d - n + 1; ++j) {
            double x = fabs(AT(p, n, j));
            big = x > big ? x : big;
        }
        if (big > tiny) break;
        for (int j = 0; j < d - n + 1; ++j) AT(p, n, j) = 0.0;
        n -= 1;
    }
    return n;
}

// bernstein_has_zero (without its unused work argument): false when p (total degree d)
// provably has no zero on the triangle u, v >= 0, u + v <= 1 (all triangular Bernstein
// coefficients of one sign by more than rel_margin times the largest)
static bool bv_bernstein_has_zero(__global const double *p, int d, double rel_margin) {
    double lo = INFINITY, hi = -INFINITY, big = 0.0;
    for (int i = 0; i <= d; ++i)
        for (int j = 0; j <= d - i; ++j) {
            double acc = 0.0;
            double fi = 1.0;  // i! / (i - i')!
            for (int i2 = 0; i2 <= i; ++i2) {
                double fj = 1.0;
                double g = 1.0;
                for (int t = 0; t < i2; ++t) g /= (double)(d - t);
                for (int j2 = 0; j2 <= j; ++j2) {
                    double c = AT(p, i2, j2);
                    if (c != 0.0) acc += c * fi * fj * g;
                    fj *= (double)(j - j2);
                    if (d - i2 - j2 > 0) g /= (double)(d - i2 - j2);
                }
                fi *= (double)(i - i2);
            }
            lo = acc < lo ? acc : lo;
            hi = acc > hi ? acc : hi;
            double x = fabs(acc);
            big = x > big ? x : big;
        }
    double margin = rel_margin * big;
    return !(lo > margin || hi < -margin);
}

// build_system: biv slot 0 = a (degree *da), slot 1 = b (degree *db) in the local frame geo_l,
// and the hit-test copies in slots HIT_SLOT .. HIT_SLOT + 3 (kappa, u2~, v2~ of degree ddt,
// ddt + 1, ddt + 1 over the full (ddt + 2)^2 square; t~ of degree 1), with ddt and the hit
// margin in AT(SLOT(biv, HIT_SLOT), MAXD, 0 .. 1).  orient1: +-1, the sign turning n1 to the
// incoming side (refraction only); eta1_ratio: eta' at vertex 1; piece: row of SQRT_PIECES_T
// and S the sqrt(beta) scale, or piece < 0: the Heron sqrt with the quadratic heron[6];
// eta_in2, eta_out2: the IORs at vertex 2 (refraction); flat2: constant n2; c2: the plane-of-
// incidence normal at vertex 2.  Slots 2-36 are scratch.
static void bv_build_system(bool refract1, bool refract2, double orient1, double eta1_ratio, int piece, double S,
                            const double *heron, double eta_in2, double eta_out2, bool flat2, const double *c2,
                            const double *geo_l, __global double *biv, int *da_out, int *db_out) {
    double x0[3], x3[3], e11[3], e12[3], n10[3], m11[3], m12[3], p20[3], e21[3], e22[3], n20[3], m21[3], m22[3];
    for (int c = 0; c < 3; ++c) {
        x0[c] = BV_ROW(geo_l, 0, c);
        x3[c] = BV_ROW(geo_l, 1, c);
        e11[c] = BV_ROW(geo_l, 2, c);
        e12[c] = BV_ROW(geo_l, 3, c);
        n10[c] = BV_ROW(geo_l, 4, c);
        m11[c] = BV_ROW(geo_l, 5, c);
        m12[c] = BV_ROW(geo_l, 6, c);
        p20[c] = BV_ROW(geo_l, 7, c);
        e21[c] = BV_ROW(geo_l, 8, c);
        e22[c] = BV_ROW(geo_l, 9, c);
        n20[c] = BV_ROW(geo_l, 10, c);
        m21[c] = BV_ROW(geo_l, 11, c);
        m22[c] = BV_ROW(geo_l, 12, c);
    }
    __global double *a = SLOT(biv, 0);
    __global double *b = SLOT(biv, 1);
    __global double *s1 = SLOT(biv, 2);
    __global double *s2 = SLOT(biv, 3);
    __global double *s3 = SLOT(biv, 4);
    __global double *s4 = SLOT(biv, 5);
    __global double *s5 = SLOT(biv, 6);
    __global double *D0 = SLOT(biv, 7);
    __global double *N1 = SLOT(biv, 10);
    __global double *DT = SLOT(biv, 13);  // d~1
    __global double *V1 = SLOT(biv, 16);
    __global double *N2 = SLOT(biv, 19);  // kappa n2
    __global double *D2 = SLOT(biv, 22);  // kappa (x3 - x2)
    __global double *T2 = SLOT(biv, 25);
    __global double *V2 = SLOT(biv, 28);
    __global double *S1 = SLOT(biv, 31);  // x1 - p20
    __global double *Q = SLOT(biv, 34);
    double mx0[3] = {-x0[0], -x0[1], -x0[2]};
    bv_vlin(D0, mx0, e11, e12);
    bv_vlin(N1, n10, m11, m12);
    // --- d~1
    bv_vdot(D0, 1, N1, 1, s1);  // d0 . n1
    bv_vdot(N1, 1, N1, 1, s2);  // |n1|^2
    int ddt = 3;
    if (!refract1) {
        // d~ = -2 (d0 . n) n + d0 |n|^2
        for (int c = 0; c < 3; ++c) {
            bv_bzero(BV_COMP(DT, c), 3);
            bv_bmul_acc(s1, 2, BV_COMP(N1, c), 1, BV_COMP(DT, c), -2.0);
            bv_bmul_acc(s2, 2, BV_COMP(D0, c), 1, BV_COMP(DT, c), 1.0);
        }
    } else {
        double r = eta1_ratio;
        bv_vdot(D0, 1, D0, 1, s3);  // |d0|^2
        // beta = |n|^2 |d0|^2 (1 - r^2) + r^2 (d0 . n)^2   (degree 4) -> s4
        bv_bzero(s4, 4);
        bv_bmul_acc(s2, 2, s3, 2, s4, 1.0 - r * r);
        bv_bmul_acc(s1, 2, s1, 2, s4, r * r);
        // sqrt(beta) ~ Rn / Rd: Rn -> s5, Rd -> s3, degrees 4, dd
        int dd;
        if (piece < 0) {
            // Heron step from the fitted quadratic q: Rn = beta + q^2, Rd = 2 q
            __global double *Q2 = SLOT(biv, 28);
            bv_bzero(Q2, 2);
            AT(Q2, 0, 0) = heron[0];
            AT(Q2, 1, 0) = heron[1];
            AT(Q2, 0, 1) = heron[2];
            AT(Q2, 2, 0) = heron[3];
            AT(Q2, 1, 1) = heron[4];
            AT(Q2, 0, 2) = heron[5];
            bv_bzero(s5, 4);
            bv_badd(s5, 4, s4, 4, 1.0);
            bv_bmul_acc(Q2, 2, Q2, 2, s5, 1.0);
            bv_bzero(s3, 2);
            bv_badd(s3, 2, Q2, 2, 2.0);
            dd = 2;
        } else {
            // eq (23): sqrt(beta) ~ (S c0 S^2 + S c1 beta) / (S^2 + d1 beta)
            double c0 = SQRT_PIECES_T[piece][2];
            double c1 = SQRT_PIECES_T[piece][3];
            double d1 = SQRT_PIECES_T[piece][4];
            double S2 = S * S;
            bv_bzero(s5, 4);
            bv_badd(s5, 4, s4, 4, S * c1);
            AT(s5, 0, 0) = AT(s5, 0, 0) + S * c0 * S2;
            bv_bzero(s3, 4);
            bv_badd(s3, 4, s4, 4, d1);
            AT(s3, 0, 0) = AT(s3, 0, 0) + S2;
            dd = 4;
        }
        // d~ = Rd r (d0 |n|^2 - (d0 . n) n) - orient Rn n   (degree dd + 3)
        ddt = dd + 3;
        for (int c = 0; c < 3; ++c) {
            bv_bzero(BV_COMP(V1, c), 3);
            bv_bmul_acc(s2, 2, BV_COMP(D0, c), 1, BV_COMP(V1, c), r);
            bv_bmul_acc(s1, 2, BV_COMP(N1, c), 1, BV_COMP(V1, c), -r);
            bv_bzero(BV_COMP(DT, c), ddt);
            bv_bmul_acc(s3, dd, BV_COMP(V1, c), 3, BV_COMP(DT, c), 1.0);
            bv_bmul_acc(s5, 4, BV_COMP(N1, c), 1, BV_COMP(DT, c), -orient1);
        }
    }
    // --- map to triangle 2: PV = d~ x e22, kappa = PV . e21, u~ = PV . (x1 - p20), v~ = d~ . ((x1 - p20) x e21)
    double mp20[3] = {-p20[0], -p20[1], -p20[2]};
    bv_vlin(S1, mp20, e11, e12);
    bv_vcross_const(DT, ddt, e22, V1);  // PV
    bv_vdot_const(V1, ddt, e21, s1);    // kappa (degree ddt)
    bv_vdot(V1, ddt, S1, 1, s2);        // u~ (degree ddt + 1)
    bv_vcross_const(S1, 1, e21, Q);     // (x1 - p20) x e21
    bv_vdot(DT, ddt, Q, 1, s3);         // v~
    int dm = ddt + 1;
    // copies for the pre-pass's hit test: kappa, u~, v~ and t~ = e22 . ((x1 - p20) x e21)
    __global double *h0 = SLOT(biv, HIT_SLOT);
    __global double *h1 = SLOT(biv, HIT_SLOT + 1);
    __global double *h2 = SLOT(biv, HIT_SLOT + 2);
    __global double *h3 = SLOT(biv, HIT_SLOT + 3);
    for (int i = 0; i <= dm; ++i)
        for (int j = 0; j <= dm; ++j) {
            AT(h0, i, j) = i + j <= ddt ? AT(s1, i, j) : 0.0;
            AT(h1, i, j) = AT(s2, i, j);
            AT(h2, i, j) = AT(s3, i, j);
        }
    bv_bzero(h3, 1);
    for (int c = 0; c < 3; ++c) {
        __global const double *Qc = BV_COMP(Q, c);
        AT(h3, 0, 0) = AT(h3, 0, 0) + e22[c] * AT(Qc, 0, 0);
        AT(h3, 1, 0) = AT(h3, 1, 0) + e22[c] * AT(Qc, 1, 0);
        AT(h3, 0, 1) = AT(h3, 0, 1) + e22[c] * AT(Qc, 0, 1);
    }
    AT(h0, MAXD, 0) = (double)ddt;
    AT(h0, MAXD, 1) = refract1 ? HIT_MARGIN_APPROX : HIT_MARGIN_EXACT;
    // kappa n2 and kappa (x3 - p20) - u~ e21 - v~ e22
    double x3r[3] = {x3[0] - p20[0], x3[1] - p20[1], x3[2] - p20[2]};
    for (int c = 0; c < 3; ++c) {
        __global double *D2c = BV_COMP(D2, c);
        bv_bzero(D2c, dm);
        bv_badd(D2c, dm, s1, ddt, x3r[c]);
        bv_badd(D2c, dm, s2, dm, -e21[c]);
        bv_badd(D2c, dm, s3, dm, -e22[c]);
    }
    int dn2;
    if (flat2) {
        dn2 = 0;
        for (int c = 0; c < 3; ++c) {
            bv_bzero(BV_COMP(N2, c), 0);
            AT(BV_COMP(N2, c), 0, 0) = n20[c];
        }
    } else {
        dn2 = dm;
        for (int c = 0; c < 3; ++c) {
            __global double *N2c = BV_COMP(N2, c);
            bv_bzero(N2c, dm);
            bv_badd(N2c, dm, s1, ddt, n20[c]);
            bv_badd(N2c, dm, s2, dm, m21[c]);
            bv_badd(N2c, dm, s3, dm, m22[c]);
        }
    }
    // --- a = (d~ x (x3 - x1)) . kappa n2
    double me11[3] = {-e11[0], -e11[1], -e11[2]}, me12[3] = {-e12[0], -e12[1], -e12[2]};
    bv_vlin(S1, x3, me11, me12);  // x3 - x1
    bv_vcross(DT, ddt, S1, 1, V1);
    int da = bv_vdot(V1, ddt + 1, N2, dn2, a);
    // --- b
    int db;
    if (!refract2) {
        bv_vcross_const(N2, dn2, c2, T2);        // t2 = kappa n2 x c2
        int d_a = bv_vdot(DT, ddt, N2, dn2, s1);  // d~ . n
        int d_b = bv_vdot(D2, dm, T2, dn2, s2);   // d2 . t
        bv_vdot(DT, ddt, T2, dn2, s3);           // d~ . t
        bv_vdot(D2, dm, N2, dn2, s4);            // d2 . n
        db = d_a + d_b;
        bv_bzero(b, db);
        bv_bmul_acc(s1, d_a, s2, d_b, b, 1.0);
        bv_bmul_acc(s3, d_a, s4, d_b, b, 1.0);
    } else {
        // eta_in^2 |d2|^2 ((d~ x n) . c)^2 - eta_out^2 |d~|^2 ((d2 x n) . c)^2
        bv_vcross(DT, ddt, N2, dn2, V1);
        int dq1 = bv_vdot_const(V1, ddt + dn2, c2, s1);  // (d~ x n) . c
        bv_vcross(D2, dm, N2, dn2, V2);
        int dq2 = bv_vdot_const(V2, dm + dn2, c2, s2);   // (d2 x n) . c
        bv_vdot(D2, dm, D2, dm, s3);                     // |d2|^2
        bv_vdot(DT, ddt, DT, ddt, s4);                   // |d~|^2
        bv_bzero(s5, 2 * dq1);
        bv_bmul_acc(s1, dq1, s1, dq1, s5, 1.0);
        db = 2 * dm + 2 * dq1;
        bv_bzero(b, db);
        bv_bmul_acc(s3, 2 * dm, s5, 2 * dq1, b, eta_in2 * eta_in2);
        bv_bzero(s5, 2 * dq2);
        bv_bmul_acc(s2, dq2, s2, dq2, s5, 1.0);
        bv_bmul_acc(s4, 2 * ddt, s5, 2 * dq2, b, -eta_out2 * eta_out2);
    }
    *da_out = da;
    *db_out = db;
}

// beta_poly: beta = |n1|^2 |d0|^2 (1 - r^2) + r^2 (d0 . n1)^2 (eq 22) into slot BETA_SLOT
// (local frame, degree 4; slots 2-4, 7-12 as scratch)
static void bv_beta_poly(const double *geo_l, double r, __global double *biv) {
    double mx0[3], r2[3], r3[3], r4[3], r5[3], r6[3];
    for (int c = 0; c < 3; ++c) {
        mx0[c] = -BV_ROW(geo_l, 0, c);
        r2[c] = BV_ROW(geo_l, 2, c);
        r3[c] = BV_ROW(geo_l, 3, c);
        r4[c] = BV_ROW(geo_l, 4, c);
        r5[c] = BV_ROW(geo_l, 5, c);
        r6[c] = BV_ROW(geo_l, 6, c);
    }
    __global double *D0 = SLOT(biv, 7);
    __global double *N1 = SLOT(biv, 10);
    bv_vlin(D0, mx0, r2, r3);
    bv_vlin(N1, r4, r5, r6);
    bv_vdot(D0, 1, N1, 1, SLOT(biv, 2));
    bv_vdot(N1, 1, N1, 1, SLOT(biv, 3));
    bv_vdot(D0, 1, D0, 1, SLOT(biv, 4));
    __global double *beta = SLOT(biv, BETA_SLOT);
    bv_bzero(beta, 4);
    bv_bmul_acc(SLOT(biv, 3), 2, SLOT(biv, 4), 2, beta, 1.0 - r * r);
    bv_bmul_acc(SLOT(biv, 2), 2, SLOT(biv, 2), 2, beta, r * r);
}

// _prepare_system: normalise a (slot 0, degree da) and b (slot 1, degree db), the Bernstein
// early exit, the u-degrees.  Returns the status: 1 to solve, 0 rejected early (and
// stats[STAT_SKIPPED] = 1), -1 degenerate (seeded polish); *na, *nb: the u-degrees of a and b,
// *n = max(na, nb) (all 0 for status 0 and for a degenerate scale).
static int bv_prepare_system(__global double *biv, int da, int db, bool refract1, __global long *stats, int *na_out,
                             int *nb_out, int *n_out) {
    __global double *a = SLOT(biv, 0);
    __global double *b = SLOT(biv, 1);
    *na_out = 0;
    *nb_out = 0;
    *n_out = 0;
    double ma = bv_bmax(a, da);
    double mb = bv_bmax(b, db);
    if (!(ma > 0.0 && mb > 0.0) || !(isfinite(ma) && isfinite(mb))) return -1;
    for (int i = 0; i <= da; ++i)
        for (int j = 0; j <= da - i; ++j) {
            AT(a, i, j) /= ma;
            if (fabs(AT(a, i, j)) <= 1e-14) AT(a, i, j) = 0.0;
        }
    for (int i = 0; i <= db; ++i)
        for (int j = 0; j <= db - i; ++j) {
            AT(b, i, j) /= mb;
            if (fabs(AT(b, i, j)) <= 1e-15) AT(b, i, j) = 0.0;
        }
    if (da <= 20 && !bv_bernstein_has_zero(a, da, refract1 ? 1e-2 : 1e-9)) {
        stats[STAT_SKIPPED] = 1;
        return 0;
    }
    int na = bv_u_degree(a, da, 1e-14);
    int nb = bv_u_degree(b, db, 1e-15);
    int n = nb > na ? nb : na;
    *na_out = na;
    *nb_out = nb;
    *n_out = n;
    if (n == 0 || n >= MAXD) return -1;
    return 1;
}
