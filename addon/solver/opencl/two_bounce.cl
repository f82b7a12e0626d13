// Two-bounce Specular Polynomials (RR, RT, TR, TT) in OpenCL C: the determinant work of
// addon/solver/spoly/two_bounce/resultant.py (Fan et al. 2024, §4.2, eq 28-31), written
// step for step as det_bezout, det_checked and illinois there, so that both back ends see
// the same signs and pin the same roots.
//
// The bivariate systems {a(u1, v1) = 0, b(u1, v1) = 0} are built and normalised by Numba
// (addon/solver/spoly/two_bounce/staged.py, stage A) and packed row by row: row i of a
// polynomial of total degree d holds the coefficients of u^i v^j, j = 0 .. d - i.  One
// system is `stride` doubles: a at offset 0, b at offset `b_offset`.  sysint holds, per
// system, (da, db, n) with n the u-degree of the Bézout matrix (eq 29).
//
// Two kernels, each one work-item per job, jobs of one system next to each other:
//   det_batch      sign and log|det R(v)| at given v (the piecewise sign scan of
//                  find_v_roots and the sub-samples of _refine_interval);
//   illinois_batch a sign change [lo, hi] pinned to ROOT_TOL by the Illinois variant of
//                  regula falsi on the signed log-magnitude (bisection safeguard).
// The bookkeeping between them (which pieces change sign, the kink rule, deflation) is
// cheap and stays on the host.  Double precision (cl_khr_fp64) is required.
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL FP_CONTRACT OFF

#define MAXN 46            // u-degree of b at most (TT: 46); n < MAXD = 47 in two_bounce/params.py
#define ROOT_TOL 1e-4   // = two_bounce.params.ROOT_TOL
#define LN2 0.6931471805599453

// p_i(v) for i <= n (row i of the packed polynomial p of total degree d), scaled to unit
// max-norm (as _coeffs_at); returns the scale.
static double coeffs_at(__global const double *p, int d, int n, double v, double *out) {
    double m = 0.0;
    int off = 0;
    for (int i = 0; i <= n; ++i) {
        double acc = 0.0;
        for (int j = d - i; j >= 0; --j) acc = acc * v + p[off + j];
        out[i] = acc;
        m = fmax(m, fabs(acc));
        off += d - i + 1;
    }
    if (m > 0.0 && isfinite(m)) {
        double inv = 1.0 / m;
        for (int i = 0; i <= n; ++i) out[i] *= inv;
    }
    return m;
}

// The u-degree of the packed polynomial p of total degree d, at most n (rows above it were
// zeroed by u_degree), as top_row.
static int top_row(__global const double *p, int d, int n) {
    int i = min(n, d);
    while (i > 0) {
        int off = i * (d + 1) - i * (i - 1) / 2;
        for (int j = 0; j <= d - i; ++j)
            if (p[off + j] != 0.0) return i;
        --i;
    }
    return 0;
}

// Sign and log|det| of the hybrid Bézout matrix of (a(., v), b(., v)) (eq 29; as
// det_bezout): f the polynomial of the larger u-degree n, g the other (degree m); rows
// k < n - m the shifts u^k g, rows n - c (c = m .. 1) the Bézoutian rows
// F_hi G_lo - G_hi F_lo (f = u^c F_hi + F_lo, g = u^c G_hi + G_lo); its determinant is the
// resultant.  Then Gaussian elimination with partial pivoting carrying the sign and the
// log-magnitude.  Sign 0 when a column is exactly zero or a coefficient vector vanishes.
static int det_bezout(__global const double *a, int da, __global const double *b, int db, int n, double v,
                      double *logdet) {
    double A[MAXN + 2], B[MAXN + 2];
    double mat[MAXN * MAXN];
    int na = top_row(a, da, n);
    int nb = top_row(b, db, n);
    double ma = coeffs_at(a, da, na, v, A);
    double mb = coeffs_at(b, db, nb, v, B);
    *logdet = -INFINITY;
    if (!(ma > 0.0 && mb > 0.0) || !(isfinite(ma) && isfinite(mb))) return 0;
    const double *F = B, *G = A;
    int m = na;
    n = nb;
    if (na > nb) { F = A; G = B; m = nb; n = na; }
    if (n == 0) { *logdet = 0.0; return 1; }
    for (int r = 0; r < n * n; ++r) mat[r] = 0.0;
    for (int r = 0; r < n - m; ++r)
        for (int i = 0; i <= m; ++i) mat[r * n + r + i] = G[i];
    // row n - c: φ_c by the recurrence up from φ_0 = 0 (as _bezoutian_rows):
    // φ_c[k] = φ_(c-1)[k + 1] + (G_(c-1) F_(k+1) - F_(c-1) G_(k+1))
    for (int c = 1; c <= m; ++c) {
        int r = n - c;
        double fc = F[c - 1], gc = G[c - 1];
        for (int k = 0; k < n - 1; ++k) {
            double gk = k + 1 <= m ? G[k + 1] : 0.0;
            double t = gc * F[k + 1] - fc * gk;
            mat[r * n + k] = c > 1 ? mat[(r + 1) * n + k + 1] + t : t;
        }
        mat[r * n + n - 1] = gc * F[n] - fc * (n <= m ? G[n] : 0.0);
    }
    int sign = 1;
    double logm = 0.0, prod = 1.0;  // log|det| = logm + log(prod) (as _log_accumulate)
    for (int k = 0; k < n; ++k) {
        int p = k;
        double big = fabs(mat[k * n + k]);
        for (int i = k + 1; i < n; ++i) {
            double x = fabs(mat[i * n + k]);
            if (x > big) { big = x; p = i; }
        }
        if (big == 0.0 || !isfinite(big)) return 0;
        if (p != k) {
            sign = -sign;
            for (int j = k; j < n; ++j) {
                double t = mat[k * n + j];
                mat[k * n + j] = mat[p * n + j];
                mat[p * n + j] = t;
            }
        }
        double piv = mat[k * n + k];
        if (piv < 0.0) sign = -sign;
        double x = fabs(piv);
        if (x > 1e-100 && x < 1e100) {
            prod *= x;
            if (prod < 1e-150 || prod > 1e150) { logm += log(prod); prod = 1.0; }
        } else {
            logm += log(x);
        }
        double inv = 1.0 / piv;
        for (int i = k + 1; i < n; ++i) {
            double f = mat[i * n + k] * inv;
            if (f != 0.0)
                for (int j = k + 1; j < n; ++j) mat[i * n + j] -= f * mat[k * n + j];
        }
    }
    *logdet = logm + log(prod);
    return sign;
}

typedef struct {
    __global const double *a, *b;
    int da, db, n;
} System;

static System load_system(__global const double *coef, __global const int *sysint, int stride, int b_offset, int s) {
    System S;
    S.a = coef + (long)s * stride;
    S.b = S.a + b_offset;
    S.da = sysint[3 * s];
    S.db = sysint[3 * s + 1];
    S.n = sysint[3 * s + 2];
    return S;
}

// det_bezout, with an exact zero re-checked a hair away (as det_checked).
static int det_checked(const System *S, double v, double *lg, int *dets) {
    *dets += 1;
    int s = det_bezout(S->a, S->da, S->b, S->db, S->n, v, lg);
    if (s != 0) return s;
    const double tens[3] = {10.0, 100.0, 1000.0};  // 10.0 ** k, exactly
    for (int k = 1; k < 4; ++k) {
        double h = 1e-13 * tens[k - 1];
        *dets += 1;
        s = det_bezout(S->a, S->da, S->b, S->db, S->n, v + h, lg);
        if (s != 0) return s;
    }
    *lg = -INFINITY;
    return 0;
}

__kernel void det_batch(__global const double *coef, __global const int *sysint, const int stride, const int b_offset,
                        __global const int *job_sys, __global const double *job_v, const int n_jobs,
                        __global int *out_sign, __global double *out_log, __global int *out_dets) {
    int t = get_global_id(0);
    if (t >= n_jobs) return;
    System S = load_system(coef, sysint, stride, b_offset, job_sys[t]);
    double lg;
    int dets = 0;
    out_sign[t] = det_checked(&S, job_v[t], &lg, &dets);
    out_log[t] = lg;
    out_dets[t] = dets;
}

// Root of det in [lo, hi] (opposite signs slo, shi at the ends) pinned to ROOT_TOL: the
// Illinois variant of regula falsi on the signed log-magnitude, a bisection step every
// fourth iteration unless the bracket shrank well (as illinois).
__kernel void illinois_batch(__global const double *coef, __global const int *sysint, const int stride, const int b_offset,
                             __global const int *job_sys, __global const double *job_f, __global const int *job_s,
                             const int n_jobs, __global double *out_root, __global int *out_dets) {
    int t = get_global_id(0);
    if (t >= n_jobs) return;
    System S = load_system(coef, sysint, stride, b_offset, job_sys[t]);
    double lo = job_f[4 * t], hi = job_f[4 * t + 1], llo = job_f[4 * t + 2], lhi = job_f[4 * t + 3];
    int slo = job_s[2 * t];
    int side = 0, dets = 0;
    double width_before = hi - lo;
    double root = NAN;
    for (int it = 0; it < 200; ++it) {
        double w = hi - lo;
        if (w <= ROOT_TOL) break;
        double dl = lhi - llo, tt;
        if (dl > 700.0) tt = 0.0;
        else if (dl < -700.0) tt = 1.0;
        else tt = 1.0 / (1.0 + exp(dl));
        if (it % 4 == 3) {
            if (w > 0.25 * width_before) tt = 0.5;
            width_before = w;
        }
        double x = lo + tt * w;
        if (!(x > lo && x < hi)) {
            x = lo + 0.5 * w;
            if (!(x > lo && x < hi)) break;
        }
        double lg;
        int s = det_checked(&S, x, &lg, &dets);
        if (s == 0) { root = x; break; }
        if (s == slo) {
            lo = x;
            llo = lg;
            if (side == -1) lhi -= LN2;
            side = -1;
        } else {
            hi = x;
            lhi = lg;
            if (side == 1) llo -= LN2;
            side = 1;
        }
    }
    out_root[t] = isnan(root) ? 0.5 * (lo + hi) : root;
    out_dets[t] = dets;
}
