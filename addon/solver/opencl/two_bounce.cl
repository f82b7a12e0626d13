// Two-bounce Specular Polynomials (RR, RT, TR, TT) in OpenCL C: stages B-E of
// addon/solver/spoly/two_bounce/staged.py (Fan et al. 2024, §4.2-4.3, eq 28-31), written step
// for step as resultant.py (det_bezout, det_checked, illinois, find_v_roots, refine_v_roots,
// resolve_dip) and solve.py (candidates_at, seeded, straight_candidate), so that both back ends
// see the same signs, pin the same roots and keep the same paths.
//
// The bivariate systems {a(u1, v1) = 0, b(u1, v1) = 0} are built and normalised by stage A
// (stage_a.cl on GPUs, Numba beside CPU devices) and packed row by row: row i of a polynomial of
// total degree d holds the coefficients of u^i v^j, j = 0 .. d - i.  One system is `stride`
// doubles: a at offset 0, b at offset `b_offset`.  sysint holds, per system, (da, db, n) with n
// the u-degree of the Bézout matrix (eq 29).  After stage A, a batch runs without the host:
//   scan_samples       det R(v) at each needed sample of each system (one work-item per sample);
//   scan_degenerate    find_v_roots' test: the determinant vanishes at most samples;
//   scan_pins          each sign change of a live piece pinned to ROOT_TOL by Illinois;
//   scan_roots         each system's roots in piece order (find_v_roots' list);
//   candidates_scan    per tuple, the candidates at its systems' scan roots (stage C);
//   refine_flags       refine_v_roots (REFINE_LEVELS = 1) per system: ghost samples, kink flags;
//   refine_samples     per flagged piece: its sub-samples, Illinois pins of new sign changes;
//   refine_assemble    per system: pins, deflation, one-signed dips (resolve_dip), in piece order;
//   candidates_refined per tuple, the candidates at the refined roots, the seeded polish, the
//                      straight line and the statistics (stage E);
//   det_batch          sign and log|det| at given (system, v) jobs (the tests' probe).
// The host pastes in the tables of params.py, the univariate root finder (roots.cl), the
// two-vertex polish (two_vertex.cl) and stage A (biv.cl, frame.cl, system.cl, prepass.cl,
// stage_a.cl: the kernels stage_a and gather_systems).  Double precision (cl_khr_fp64) is
// required.
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL FP_CONTRACT OFF

#define MAXN 46            // u-degree of b at most (TT: 46); n < MAXD = 47 in two_bounce/params.py
// ROOT_TOL, KINK, SUB_SAMPLES, NOISY_CHANGES, DIP_STEPS, DIP_FLAT, the candidates' constants and
// the STAT_* slots: two_bounce/params.py's (MAX_DEGREE: polynomials/roots.py's), given as build
// options by opencl/backend.py (_two_bounce_defines: one definition for both back ends)
#if !defined(ROOT_TOL) || !defined(SUB_SAMPLES) || !defined(MAX_PATHS_TWO_BOUNCE) || !defined(STAT_NEAR) || !defined(MAX_DEGREE)
#error "build with the two-bounce parameters (-D ROOT_TOL=... etc., opencl/backend.py)"
#endif
#define LN2 0.6931471805599453

// @TWO_BOUNCE_TABLES@ (the host's: SQRT_PIECES_T, HERON_CUTS_T)
// @INCLUDE roots.cl@ (the univariate root finder: candidates_at's u-roots)
// @INCLUDE two_vertex.cl@ (the two-vertex residual, polish and exact map: tv_*)
// @INCLUDE biv.cl@ (stage A's bivariate scratch)
// @INCLUDE frame.cl@ (stage A: side tests, local frame, √ set-up: fr_*)
// @INCLUDE system.cl@ (stage A: the bivariate algebra and the systems: bv_*)
// @INCLUDE prepass.cl@ (stage A: the live (u1, v1) pre-pass: pp_*)
// @INCLUDE stage_a.cl@ (stage A's kernels: stage_a, gather_systems)

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

// Root of det in [lo, hi] (opposite signs at the ends, slo at lo) pinned to ROOT_TOL: the
// Illinois variant of regula falsi on the signed log-magnitude, a bisection step every
// fourth iteration unless the bracket shrank well (as illinois).
static double illinois(const System *S, double lo, double hi, int slo, double llo, double lhi, int *dets) {
    int side = 0;
    double width_before = hi - lo;
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
        int s = det_checked(S, x, &lg, dets);
        if (s == 0) return x;
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
    return 0.5 * (lo + hi);
}

// ---- the resultant scan of a batch of systems (find_v_roots, refine_v_roots) -------------------
// System s is scanned over [-margin[s], 1 + margin[s]] in `pieces` pieces, only its live pieces
// (live[s * pieces + k], the pre-pass's) and the samples they need.  Per sample the sign (2: not
// sampled) and the raw log|det| stay on the device for the refinement.

// Sample k of the scan of system s, as find_v_roots computes it.
static double scan_v(double margin, int pieces, int k) {
    double lo = -margin, hi = 1.0 + margin;
    double h = (hi - lo) / (double)pieces;
    return lo + (double)k * h;
}

// find_v_roots' samples: one work-item per (system, sample); sample k is needed by the live
// pieces k - 2 .. k + 1 (sign changes and the kink test one sample beyond).
__kernel void scan_samples(__global const double *coef, __global const int *sysint, const int stride, const int b_offset,
                           __global const char *live, __global const double *margin, __global const char *solve,
                           const int pieces, const int n_sys, __global int *sg, __global double *lg, __global int *dets) {
    long t = get_global_id(0);
    if (t >= (long)n_sys * (pieces + 1)) return;
    int s = (int)(t / (pieces + 1)), k = (int)(t % (pieces + 1));
    sg[t] = 2;
    lg[t] = 0.0;
    dets[t] = 0;
    if (!solve[s]) return;
    bool need = false;
    for (int q = max(0, k - 2); q <= min(pieces - 1, k + 1); ++q)
        if (live[(long)s * pieces + q]) need = true;
    if (!need) return;
    System S = load_system(coef, sysint, stride, b_offset, s);
    double l;
    int d = 0;
    sg[t] = det_checked(&S, scan_v(margin[s], pieces, k), &l, &d);
    lg[t] = l;
    dets[t] = d;
}

// find_v_roots' degeneracy test: the determinant vanishes at more than half the samples
// (those systems are polished from seeds instead, not scanned).
__kernel void scan_degenerate(__global const char *solve, const int pieces, const int n_sys, __global const int *sg,
                              __global char *degenerate) {
    int s = get_global_id(0);
    if (s >= n_sys) return;
    int zeros = 0, sampled = 0;
    if (solve[s])
        for (int k = 0; k <= pieces; ++k) {
            int g = sg[(long)s * (pieces + 1) + k];
            if (g != 2) sampled += 1;
            if (g == 0) zeros += 1;
        }
    degenerate[s] = zeros * 2 > sampled;
}

// find_v_roots' Illinois pins: one work-item per (system, piece) with a sign change.
__kernel void scan_pins(__global const double *coef, __global const int *sysint, const int stride, const int b_offset,
                        __global const char *live, __global const double *margin, __global const char *solve,
                        __global const char *degenerate, const int pieces, const int n_sys, __global const int *sg,
                        __global const double *lg, __global double *pin, __global int *pin_dets) {
    long t = get_global_id(0);
    if (t >= (long)n_sys * pieces) return;
    int s = (int)(t / pieces), k = (int)(t % pieces);
    pin_dets[t] = 0;
    if (!solve[s] || degenerate[s] || !live[t]) return;
    long j = (long)s * (pieces + 1) + k;
    int g0 = sg[j], g1 = sg[j + 1];
    if (g0 != g1 && g0 != 0 && g1 != 0) {
        System S = load_system(coef, sysint, stride, b_offset, s);
        int d = 0;
        pin[t] = illinois(&S, scan_v(margin[s], pieces, k), scan_v(margin[s], pieces, k + 1), g0, lg[j], lg[j + 1], &d);
        pin_dets[t] = d;
    }
}

// find_v_roots' root list per system: pinned sign changes and exact-zero samples of the live
// pieces in piece order, each root's piece; nv = -1 for a degenerate system.
__kernel void scan_roots(__global const char *live, __global const double *margin, __global const char *solve,
                         __global const char *degenerate, const int pieces, const int n_sys, __global const int *sg,
                         __global const int *sample_dets, __global const double *pin, __global const int *pin_dets,
                         __global int *nv, __global double *roots, __global int *piece_of, __global int *dets) {
    int s = get_global_id(0);
    if (s >= n_sys) return;
    long p0 = (long)s * pieces, q0 = (long)s * (pieces + 1);
    int d = 0;
    for (int k = 0; k <= pieces; ++k) d += sample_dets[q0 + k];
    if (!solve[s] || degenerate[s]) {
        nv[s] = solve[s] ? -1 : 0;
        dets[s] = d;
        return;
    }
    int count = 0;
    for (int k = 0; k < pieces; ++k) {
        d += pin_dets[p0 + k];
        if (!live[p0 + k]) continue;
        int g0 = sg[q0 + k], g1 = sg[q0 + k + 1];
        if (g0 != g1 && g0 != 0 && g1 != 0) {
            roots[p0 + count] = pin[p0 + k];
            piece_of[p0 + count] = k;
            count += 1;
        } else if (g0 == 0) {
            roots[p0 + count] = scan_v(margin[s], pieces, k);
            piece_of[p0 + count] = k;
            count += 1;
        }
    }
    nv[s] = count;
    dets[s] = d;
}

// The roots of one system during its refinement: the nv scan roots, then the new ones.
typedef struct {
    __global const double *scan;
    __global double *found;
    int nv;
} Roots;

static double root_at(const Roots *R, int i) { return i < R->nv ? R->scan[i] : R->found[i - R->nv]; }

// log|det(v)| minus the sum of log|v - r| over the first n roots (as deflate).
static double deflate(double v, double lg, const Roots *R, int n) {
    for (int i = 0; i < n; ++i) {
        double d = fabs(v - root_at(R, i));
        if (d > 0.0) lg -= log(d);
    }
    return lg;
}

// Append a root (the caller checked the capacity).
static void push_root(const Roots *R, int *count, double v) {
    R->found[*count - R->nv] = v;
    *count += 1;
}

// A one-signed dip of the deflated log|det| at xm (as resolve_dip): the vertex of the
// quadratic through the three samples (golden-section safeguard); a point of the other sign
// splits it into two pinned sign changes, a model minimum above DIP_FLAT stops (complex
// pair), else the deepest point is a (near-)double root candidate.
static void resolve_dip(const System *S, double xl, double xm, double xr, int sgn, double fl, double fm, double fr,
                        const Roots *R, int cap, int *count, int *dets) {
    for (int it = 0; it < DIP_STEPS; ++it) {
        double w = xr - xl;
        if (w <= ROOT_TOL) break;
        double ql = exp(fmin(fl - fm, 700.0));
        double qr = exp(fmin(fr - fm, 700.0));
        double d1 = (1.0 - ql) / (xm - xl);
        double d2 = (qr - 1.0) / (xr - xm);
        double A = (d2 - d1) / w;
        double x = xm, qmin = 1.0;
        if (A > 0.0) {
            x = 0.5 * (xl + xm) - d1 / (2.0 * A);
            qmin = ql + d1 * (x - xl) + A * (x - xl) * (x - xm);
        }
        if (qmin >= DIP_FLAT) break;
        if (!(x > xl + 0.01 * w && x < xr - 0.01 * w) || fabs(x - xm) < 0.01 * w) {
            if (xr - xm > xm - xl) x = xm + 0.3819660112501051 * (xr - xm);
            else x = xm - 0.3819660112501051 * (xm - xl);
        }
        double lg;
        int s = det_checked(S, x, &lg, dets);
        if (s == 0) break;
        if (s != sgn) {
            double p = x > xm ? xm : xl;
            double q = x > xm ? xr : xm;
            double lp, lq;
            int sp = det_checked(S, p, &lp, dets);
            int sq = det_checked(S, q, &lq, dets);
            if (*count + 2 <= cap && sp == sgn && sq == sgn) {
                double r0 = illinois(S, p, x, sp, lp, lg, dets);
                double r1 = illinois(S, x, q, s, lg, lq, dets);
                push_root(R, count, r0);
                push_root(R, count, r1);
                return;
            }
            break;
        }
        double f = deflate(x, lg, R, *count);
        if (f < fm) {
            if (x > xm) { xl = xm; fl = fm; }
            else { xr = xm; fr = fm; }
            xm = x;
            fm = f;
        } else if (x > xm) {
            xr = x;
            fr = f;
        } else {
            xl = x;
            fl = f;
        }
    }
    if (*count < cap) push_root(R, count, xm);
}

// Deflated log|det| of scan sample k (sampled ones only: the kink test reads no other).
static double deflated_sample(const Roots *R, __global const int *sg, __global const double *lg, double margin,
                              int pieces, int k) {
    return sg[k] != 2 ? deflate(scan_v(margin, pieces, k), lg[k], R, R->nv) : lg[k];
}

// refine_flags_one for piece k: next to a convex kink of the deflated log|det| (ghost samples
// g_lo, g_hi beyond the ends) or within one piece of a productive scan root.
static bool piece_flagged(const Roots *R, __global const int *sg, __global const double *lg, __global const char *live,
                          __global const char *productive, __global const int *piece_of, double margin, int pieces,
                          double g_lo, double g_hi, int k) {
    if (!live[k]) return false;
    double l0 = deflated_sample(R, sg, lg, margin, pieces, k), l1 = deflated_sample(R, sg, lg, margin, pieces, k + 1);
    double left = k == 0 ? g_lo : deflated_sample(R, sg, lg, margin, pieces, k - 1);
    double right = k + 2 > pieces ? g_hi : deflated_sample(R, sg, lg, margin, pieces, k + 2);
    if (left + l1 - 2.0 * l0 > KINK || l0 + right - 2.0 * l1 > KINK) return true;
    for (int i = 0; i < R->nv; ++i)
        if (productive[i] && abs(piece_of[i] - k) <= 1) return true;
    return false;
}

// refine_v_roots at REFINE_LEVELS = 1 in three kernels, so that the determinants of the
// sub-samples run one work-item per flagged piece: refine_flags (per system: the ghost samples,
// the flags), refine_samples (per flagged piece: its sub-samples and the Illinois pins of their
// new sign changes), refine_assemble (per system, in piece order: the pins taken, log|det|
// deflated by every root so far, one-signed dips resolved), as _refine_interval does them.  The
// kernels run over the systems [s0, s0 + n_sys) of the batch (the host cuts the batch so that
// the sub-samples of a cut fit its buffers); sub-sample storage is per piece of the cut:
// SUB_ROW = SUB_SAMPLES + 3 samples (0: the one before the piece, 1 .. M + 1 the piece's,
// M + 2: the one after it), SUB_SAMPLES pins.
#define SUB_ROW (SUB_SAMPLES + 3)

typedef struct {
    System S;
    Roots R;
    __global const char *live, *productive;
    __global const int *piece_of, *sg;
    __global const double *lg;
    double margin;
} RefineSystem;

static RefineSystem refine_system(__global const double *coef, __global const int *sysint, int stride, int b_offset,
                                  __global const char *live_all, __global const double *margins, int pieces,
                                  __global const int *sg_all, __global const double *lg_all, __global const int *nv_all,
                                  __global const double *roots_all, __global const int *piece_of_all,
                                  __global const char *productive_all, int cap_new, __global double *found_all, int s) {
    RefineSystem F;
    long p0 = (long)s * pieces, q0 = (long)s * (pieces + 1);
    F.S = load_system(coef, sysint, stride, b_offset, s);
    F.live = live_all + p0;
    F.productive = productive_all + p0;
    F.piece_of = piece_of_all + p0;
    F.sg = sg_all + q0;
    F.lg = lg_all + q0;
    F.margin = margins[s];
    F.R.scan = roots_all + p0;
    F.R.found = found_all + (long)s * cap_new;
    F.R.nv = nv_all[s];
    return F;
}

#define REFINE_SYSTEM_ARGS __global const double *coef, __global const int *sysint, const int stride, \
    const int b_offset, __global const char *live_all, __global const double *margins, \
    __global const char *refined, const int pieces, const int s0, const int n_sys, __global const int *sg_all, \
    __global const double *lg_all, __global const int *nv_all, __global const double *roots_all, \
    __global const int *piece_of_all, __global const char *productive_all, const int cap_new, \
    __global double *found_all
#define REFINE_SYSTEM(s) refine_system(coef, sysint, stride, b_offset, live_all, margins, pieces, sg_all, lg_all, \
    nv_all, roots_all, piece_of_all, productive_all, cap_new, found_all, s)

// refine_v_roots up to refine_flags_one: the ghost samples a piece outside either end (where
// that end's piece is live), the kink / productive flags of the pieces; dets_out[s] = the
// ghosts' determinants.
__kernel void refine_flags(REFINE_SYSTEM_ARGS, __global char *flags, __global int *dets_out) {
    int i = get_global_id(0);
    if (i >= n_sys) return;
    int s = s0 + i;
    dets_out[s] = 0;
    for (int k = 0; k < pieces; ++k) flags[(long)s * pieces + k] = 0;
    if (!refined[s] || nv_all[s] < 0) return;
    RefineSystem F = REFINE_SYSTEM(s);
    int dets = 0;
    double v0 = scan_v(F.margin, pieces, 0), vP = scan_v(F.margin, pieces, pieces);
    double h = scan_v(F.margin, pieces, 1) - v0;
    double g_lo = 0.0, g_hi = 0.0;
    if (F.live[0]) det_checked(&F.S, v0 - h, &g_lo, &dets);
    if (F.live[pieces - 1]) det_checked(&F.S, vP + h, &g_hi, &dets);
    g_lo = deflate(v0 - h, g_lo, &F.R, F.R.nv);
    g_hi = deflate(vP + h, g_hi, &F.R, F.R.nv);
    for (int k = 0; k < pieces; ++k)
        flags[(long)s * pieces + k] = piece_flagged(&F.R, F.sg, F.lg, F.live, F.productive, F.piece_of, F.margin, pieces,
                                                    g_lo, g_hi, k);
    dets_out[s] = dets;
}

// _refine_interval's samples of one flagged piece k (the ends are scan samples, taken as they
// are; the one before it only for the first piece of a run, the one after it for the last) and
// the Illinois pins of its new sign changes (none in a noisy piece, none around a scan root);
// NAN where a sub-piece has no pin.
__kernel void refine_samples(REFINE_SYSTEM_ARGS, __global const char *flags, __global double *sub_v,
                             __global int *sub_s, __global double *sub_l, __global double *sub_pin,
                             __global int *sub_dets) {
    long i = get_global_id(0);
    if (i >= (long)n_sys * pieces) return;
    int s = s0 + (int)(i / pieces), k = (int)(i % pieces);
    sub_dets[i] = 0;
    __global const char *fl = flags + (long)s * pieces;
    if (!fl[k]) return;
    RefineSystem F = REFINE_SYSTEM(s);
    const int M = SUB_SAMPLES;
    __global double *sv = sub_v + i * SUB_ROW, *sl = sub_l + i * SUB_ROW;
    __global int *ss = sub_s + i * SUB_ROW;
    int dets = 0;
    double lo = scan_v(F.margin, pieces, k), hi = scan_v(F.margin, pieces, k + 1);
    double hh = (hi - lo) / M;
    for (int j = 0; j <= M; ++j) {
        double v = j == M ? hi : lo + j * hh, l;
        int g;
        if (j == 0 && F.sg[k] != 2) { g = F.sg[k]; l = F.lg[k]; }
        else if (j == M && F.sg[k + 1] != 2) { g = F.sg[k + 1]; l = F.lg[k + 1]; }
        else g = det_checked(&F.S, v, &l, &dets);
        sv[j + 1] = v;
        ss[j + 1] = g;
        sl[j + 1] = l;
    }
    double l;
    if (k == 0 || !fl[k - 1]) {
        sv[0] = lo - hh;
        ss[0] = det_checked(&F.S, lo - hh, &l, &dets);
        sl[0] = l;
    }
    if (k + 1 == pieces || !fl[k + 1]) {
        sv[M + 2] = hi + hh;
        ss[M + 2] = det_checked(&F.S, hi + hh, &l, &dets);
        sl[M + 2] = l;
    }
    __global double *pins = sub_pin + i * SUB_SAMPLES;
    int changes = 0;
    for (int j = 1; j <= M; ++j) {
        pins[j - 1] = NAN;
        if (ss[j] != ss[j + 1]) changes += 1;
    }
    if (changes <= NOISY_CHANGES)
        for (int j = 1; j <= M; ++j) {
            if (ss[j] != ss[j + 1] && ss[j] != 0 && ss[j + 1] != 0) {
                bool known = false;
                for (int q = 0; q < F.R.nv; ++q)
                    if (F.R.scan[q] >= sv[j] && F.R.scan[q] <= sv[j + 1]) known = true;
                if (!known) pins[j - 1] = illinois(&F.S, sv[j], sv[j + 1], ss[j], sl[j], sl[j + 1], &dets);
            }
        }
    sub_dets[i] = dets;
}

// _refine_interval's bookkeeping per system, pieces ascending: a run's inner piece takes the
// previous piece's last sub-sample as its left neighbour; the pins are appended; the samples'
// log|det| deflated by every root so far; a one-signed dip resolved (resolve_dip) or, at the
// rounding floor, its deepest sample taken.  The new roots go to found[s * cap ..],
// found_count[s] of them; -1 when within 2 of cap (a dip adds two at once): the tuple is solved
// on the host.  dets_out[s] += the sub-samples', pins' and dips' determinants.
__kernel void refine_assemble(REFINE_SYSTEM_ARGS, __global const char *flags, __global const double *sub_v,
                              __global const int *sub_s, __global const double *sub_l, __global const double *sub_pin,
                              __global const int *sub_dets, __global int *found_count, __global int *dets_out) {
    int i = get_global_id(0);
    if (i >= n_sys) return;
    int s = s0 + i;
    found_count[s] = 0;
    if (!refined[s] || nv_all[s] < 0) return;
    RefineSystem F = REFINE_SYSTEM(s);
    const int M = SUB_SAMPLES;
    __global const char *fl = flags + (long)s * pieces;
    double sv[SUB_ROW], sl[SUB_ROW];
    int ss[SUB_ROW];
    int count = F.R.nv, cap = F.R.nv + cap_new, dets = 0;
    for (int k = 0; k < pieces; ++k) {
        if (!fl[k]) continue;
        long row = (long)i * pieces + k;
        bool has_right = k + 1 == pieces || !fl[k + 1];
        for (int j = 1; j <= M + 1; ++j) {
            sv[j] = sub_v[row * SUB_ROW + j];
            ss[j] = sub_s[row * SUB_ROW + j];
            sl[j] = sub_l[row * SUB_ROW + j];
        }
        long left = k > 0 && fl[k - 1] ? (row - 1) * SUB_ROW + M : row * SUB_ROW;  // carry, or its own
        sv[0] = sub_v[left];
        ss[0] = sub_s[left];
        sl[0] = sub_l[left];
        if (has_right) {
            sv[M + 2] = sub_v[row * SUB_ROW + M + 2];
            ss[M + 2] = sub_s[row * SUB_ROW + M + 2];
            sl[M + 2] = sub_l[row * SUB_ROW + M + 2];
        }
        dets += sub_dets[row];
        int changes = 0;
        for (int j = 1; j <= M; ++j)
            if (ss[j] != ss[j + 1]) changes += 1;
        if (changes > NOISY_CHANGES) continue;
        for (int j = 1; j <= M; ++j) {
            double pin = sub_pin[row * SUB_SAMPLES + j - 1];
            if (!isnan(pin) && count < cap) push_root(&F.R, &count, pin);
        }
        int j_hi = has_right ? M + 2 : M + 1;
        for (int j = 0; j <= j_hi; ++j) sl[j] = deflate(sv[j], sl[j], &F.R, count);
        for (int j = 1; j <= (has_right ? M + 1 : M); ++j) {
            if (count < cap && sl[j - 1] + sl[j + 1] - 2.0 * sl[j] > KINK && ss[j] == ss[j - 1] && ss[j] == ss[j + 1] &&
                ss[j] != 0 && sl[j] < sl[j - 1] && sl[j] < sl[j + 1]) {
                if ((j - 2 < 0 || sl[j - 2] >= sl[j - 1]) && (j + 2 > j_hi || sl[j + 2] >= sl[j + 1]))
                    resolve_dip(&F.S, sv[j - 1], sv[j], sv[j + 1], ss[j], sl[j - 1], sl[j], sl[j + 1], &F.R, cap, &count,
                                &dets);
                else
                    push_root(&F.R, &count, sv[j]);  // log|det| at its rounding floor: the deepest sample as it is
            }
        }
    }
    found_count[s] = count + 2 > cap ? -1 : count - F.R.nv;
    dets_out[s] += dets;
}

// ---- candidates and path-space polish (stages C and E of staged.py; solve.py's candidates_at) ----
// One work-item per tuple, its systems in stage A's order, as stage_c / stage_e: every scan root's
// candidates first (and which roots were productive, for the refinement), then per system its
// refined roots' candidates, the seeded polish of degenerate systems and the straight line.
// Per tuple: geo (15 x 3) of the forward chain and of the reversed one (two_vertex.cl), the paths
// found (out_uv, MAX_PATHS_TWO_BOUNCE x 4, and their (error, sigma) in meta) and its statistics.

#define ROOTS_CHAIN ((MAX_DEGREE + 1) * (MAX_DEGREE + 2) / 2)

typedef struct {
    __global double *uv;    // MAX_PATHS_TWO_BOUNCE x 4: the tuple's paths, forward order
    __global double *meta;  // (MAX_PATHS_TWO_BOUNCE + 1) x 2: their (error, sigma)
    __global long *stats;   // N_STATS
    int count;
} Paths;

// solve.py _store_path2: a new path, or a better copy of one within its merge radius.
static void store_path(Paths *out, const double *th, double err, double sigma) {
    for (int q = 0; q < min(out->count, MAX_PATHS_TWO_BOUNCE); ++q) {
        double dist = 0.0;
        for (int i = 0; i < 4; ++i) dist = fmax(dist, fabs(out->uv[4 * q + i] - th[i]));
        double sig = fmin(sigma, out->meta[2 * q + 1]);
        double radius = SAME_PATH;
        if (sig > 0.0) radius = fmax(radius, 4.0 * (err + out->meta[2 * q] + 1e-12) / sig);
        else radius = NEAR_PATH;
        if (dist < fmin(radius, NEAR_PATH)) {
            if (err < out->meta[2 * q]) {
                for (int i = 0; i < 4; ++i) out->uv[4 * q + i] = th[i];
                out->meta[2 * q] = err;
                out->meta[2 * q + 1] = sigma;
            }
            return;
        }
    }
    if (out->count < MAX_PATHS_TWO_BOUNCE) {
        for (int i = 0; i < 4; ++i) out->uv[4 * out->count + i] = th[i];
        out->meta[2 * out->count] = err;
        out->meta[2 * out->count + 1] = sigma;
    }
    out->count += 1;
}

// solve.py _try_candidate: (u1, v1) on the oriented chain's first triangle -> exact map to the
// second -> polish and validate in forward path space; th holds the polished path after.
static void try_candidate(Paths *out, double u1, double v1, const double *geo, bool refract1, bool refract2, double eta,
                          bool rev, const double *geo_fwd, double *th) {
    out->stats[STAT_CANDIDATES] += 1;
    double u2, v2;
    if (!tv_trace_to_second(u1, v1, geo, refract1, eta, &u2, &v2)) return;
    double err, sigma;
    bool accepted;
    if (rev) {
        th[0] = u2; th[1] = v2; th[2] = u1; th[3] = v1;
        accepted = tv_polish_and_validate(th, geo_fwd, refract2, refract1, eta, POLISH_STEPS, ACCEPT_RESIDUAL, &err, &sigma);
    } else {
        th[0] = u1; th[1] = v1; th[2] = u2; th[3] = v2;
        accepted = tv_polish_and_validate(th, geo_fwd, refract1, refract2, eta, POLISH_STEPS, ACCEPT_RESIDUAL, &err, &sigma);
    }
    if (!accepted) return;
    out->stats[STAT_ACCEPTED] += 1;
    store_path(out, th, err, sigma);
}

// solve.py _already_stored
static bool already_stored(const Paths *out, double u1, double v1, int off) {
    for (int q = 0; q < min(out->count, MAX_PATHS_TWO_BOUNCE); ++q)
        if (fabs(out->uv[4 * q + off] - u1) < 1e-9 && fabs(out->uv[4 * q + off + 1] - v1) < 1e-9) return true;
    return false;
}

// Row i of the packed polynomial p (total degree d) at v, by Horner from its top coefficient.
static double packed_row_at(__global const double *p, int d, int i, double v) {
    int off = i * (d + 1) - i * (i - 1) / 2;
    double acc = 0.0;
    for (int j = d - i; j >= 0; --j) acc = acc * v + p[off + j];
    return acc;
}

// solve.py candidates_at: back-substitution at a resultant root v (§4.3): the roots u of
// a(., v) (or of b(., v) where a(., v) vanishes) in the widened triangle whose relative
// |b(u, v)| is small (the smallest always) are polished as paths.
static void candidates_at(Paths *out, double v, __global const double *a, int da, __global const double *b, int db, int na,
                          int nb, bool refract1, bool refract2, double margin, const double *geo, double eta, bool rev,
                          const double *geo_fwd) {
    double coeffs[MAX_DEGREE + 1], chain[ROOTS_CHAIN], critical[MAX_DEGREE + 1], found[MAX_DEGREE + 1];
    double u_roots[MAX_DEGREE + 1], rel[MAX_DEGREE + 1], th[4];
    int deg_u = na;
    double big = 0.0;
    for (int i = 0; i <= na; ++i) {
        double c = packed_row_at(a, da, i, v);
        if (i <= MAX_DEGREE) coeffs[i] = c;
        big = fmax(big, fabs(c));
    }
    if (!(big > 1e-12) || na == 0) {
        if (nb > MAX_DEGREE) return;
        deg_u = nb;
        for (int i = 0; i <= nb; ++i) coeffs[i] = packed_row_at(b, db, i, v);
    }
    if (deg_u > MAX_DEGREE || deg_u == 0) return;
    int n_u = roots_in_interval(coeffs, deg_u, -margin, 1.0 - v + margin, 1e-14, 1e-10, chain, critical, found, u_roots);
    int best = -1;
    double best_rel = INFINITY;
    for (int iu = 0; iu < n_u; ++iu) {
        double u = u_roots[iu], val = 0.0, mag = 0.0, up = 1.0;
        for (int i = 0; i <= nb; ++i) {
            double acc = packed_row_at(b, db, i, v);
            val += acc * up;
            mag += fabs(acc * up);
            up *= u;
        }
        rel[iu] = mag > 0.0 ? fabs(val) / mag : 0.0;
        if (rel[iu] < best_rel) {
            best_rel = rel[iu];
            best = iu;
        }
    }
    for (int iu = 0; iu < n_u; ++iu) {
        if (iu != best && !(rel[iu] < B_RELATIVE)) continue;
        double u1 = fmin(fmax(u_roots[iu], 0.0), 1.0), v1 = fmin(fmax(v, 0.0), 1.0);
        if (u1 + v1 > 1.0) {
            double excess = 0.5 * (u1 + v1 - 1.0);
            u1 -= excess;
            v1 -= excess;
        }
        if (already_stored(out, u1, v1, rev ? 2 : 0)) {
            out->stats[STAT_ACCEPTED] += 1;
            if (fabs(v1 - v) <= PRODUCTIVE_RADIUS) out->stats[STAT_NEAR] += 1;
            continue;
        }
        long accepted = out->stats[STAT_ACCEPTED];
        try_candidate(out, u1, v1, geo, refract1, refract2, eta, rev, geo_fwd, th);
        if (out->stats[STAT_ACCEPTED] > accepted && fabs(th[(rev ? 2 : 0) + 1] - v) <= PRODUCTIVE_RADIUS)
            out->stats[STAT_NEAR] += 1;
    }
}

// solve.py seeded: the fallback for a degenerate system (determinant identically zero):
// polish from a grid on the oriented chain's first triangle.
static void seeded(Paths *out, const double *geo, bool refract1, bool refract2, double eta, bool rev, const double *geo_fwd) {
    double th[4];
    for (int i = 0; i <= N_SEEDS; ++i)
        for (int j = 0; j <= N_SEEDS - i; ++j) {
            double u = (i + 1.0 / 3.0) / (N_SEEDS + 1.0), v = (j + 1.0 / 3.0) / (N_SEEDS + 1.0);
            try_candidate(out, u, v, geo, refract1, refract2, eta, rev, geo_fwd, th);
        }
}

// solve.py straight_candidate: the line x0 -> x3 through triangle 1's plane (normal incidence
// through parallel faces, where the coplanarity polynomial vanishes identically).
static void straight_candidate(Paths *out, const double *geo, bool refract1, bool refract2, double eta) {
    const double origin[3] = {0.0, 0.0, 0.0};
    double u, v, th[4];
    if (!tv_line_crossing_barycentrics(geo + 0, geo + 3, origin, geo + 6, geo + 9, geo + 39, &u, &v)) return;
    if (u < -1e-6 || v < -1e-6 || u + v > 1.0 + 1e-6) return;
    try_candidate(out, u, v, geo, refract1, refract2, eta, false, geo, th);
}

typedef struct {
    double fwd[45], rev[45];
} TupleGeometry;

// A staged tuple's two packed geometries (forward, reversed), as stage C / E pack them.
static void tuple_geometry(TupleGeometry *G, __global const double *x_start, __global const double *x_end,
                           __global const double *P, __global const double *N, int t) {
    __global const double *x0 = x_start + 3 * t, *x3 = x_end + 3 * t, *p = P + 18 * t, *n = N + 18 * t;
    tv_pack_geometry(x0, x3, p, n, p + 9, n + 9, G->fwd);
    tv_pack_geometry(x3, x0, p + 9, n + 9, p, n, G->rev);
}

static Paths tuple_paths(__global double *out_uv, __global double *meta, __global long *stats, int t, int count) {
    Paths out;
    out.uv = out_uv + (long)t * MAX_PATHS_TWO_BOUNCE * 4;
    out.meta = meta + (long)t * (MAX_PATHS_TWO_BOUNCE + 1) * 2;
    out.stats = stats + (long)t * N_STATS;
    out.count = count;
    return out;
}

// sysint: per system (rev + 2 * not refined, status, da, db, na, nb, n) from stage A; status
// 1: solved, -1: degenerate (seeded polish); nv[s] = -1: found degenerate by the scan.

// Stage C: the candidates at every scan root of the tuple's systems; productive[s, i] = 1 when
// root i polished into a path within PRODUCTIVE_RADIUS of it (the refinement's rule).
__kernel void candidates_scan(__global const double *coef, __global const int *sysint7, const int stride,
                              const int b_offset, __global const int *sys_first, __global const char *state,
                              __global const double *x_start, __global const double *x_end, __global const double *P,
                              __global const double *N, __global const double *eta_all, const int refract1,
                              const int refract2, const int pieces, __global const int *nv_all,
                              __global const double *roots_all, __global char *productive, __global double *out_uv,
                              __global double *meta, __global int *out_count, __global long *stats, const int n) {
    int t = get_global_id(0);
    if (t >= n) return;
    if (state[t] != 1) return;
    TupleGeometry G;
    tuple_geometry(&G, x_start, x_end, P, N, t);
    Paths out = tuple_paths(out_uv, meta, stats, t, 0);
    double eta = eta_all[t];
    for (int s = sys_first[t]; s < sys_first[t + 1]; ++s) {
        __global const int *si = sysint7 + 7 * s;
        if (si[1] != 1 || nv_all[s] <= 0) continue;
        bool rev = (si[0] & 1) == 1;
        bool r1 = rev ? refract2 : refract1, r2 = rev ? refract1 : refract2;
        __global const double *a = coef + (long)s * stride;
        double margin = r1 ? V_MARGIN_APPROX : V_MARGIN_EXACT;
        for (int iv = 0; iv < nv_all[s]; ++iv) {
            long near = out.stats[STAT_NEAR];
            candidates_at(&out, roots_all[(long)s * pieces + iv], a, si[2], a + b_offset, si[3], si[4], si[5], r1, r2,
                          margin, rev ? G.rev : G.fwd, eta, rev, G.fwd);
            productive[(long)s * pieces + iv] = out.stats[STAT_NEAR] > near;
        }
    }
    out_count[t] = out.count;
}

// Stage E: per system the candidates at its refined roots (or the seeded polish of a
// degenerate one), the straight line after the forward systems, the statistics (determinants
// of the scan and the refinement summed per tuple).  A tuple with a system whose refinement
// overflowed (found_count -1) is left to the host (the one-kernel path).
__kernel void candidates_refined(__global const double *coef, __global const int *sysint7, const int stride,
                                 const int b_offset, __global const int *sys_first, __global const char *state,
                                 __global const double *x_start, __global const double *x_end, __global const double *P,
                                 __global const double *N, __global const double *eta_all, const int refract1,
                                 const int refract2, __global const int *nv_all, __global const int *scan_dets,
                                 const int cap_new, __global const double *found_all, __global const int *found_count,
                                 __global const int *refine_dets, __global double *out_uv, __global double *meta,
                                 __global int *out_count, __global long *stats, const int n) {
    int t = get_global_id(0);
    if (t >= n) return;
    if (state[t] != 1) return;
    for (int s = sys_first[t]; s < sys_first[t + 1]; ++s)
        if (found_count[s] < 0) return;  // redone on the host
    TupleGeometry G;
    tuple_geometry(&G, x_start, x_end, P, N, t);
    Paths out = tuple_paths(out_uv, meta, stats, t, out_count[t]);
    double eta = eta_all[t];
    bool straight = false;
    long dets = 0;
    for (int s = sys_first[t]; s < sys_first[t + 1]; ++s) {
        __global const int *si = sysint7 + 7 * s;
        bool rev = (si[0] & 1) == 1;
        dets += scan_dets[s] + refine_dets[s];
        if (rev && !straight) {
            straight_candidate(&out, G.fwd, refract1, refract2, eta);
            straight = true;
        }
        bool r1 = rev ? refract2 : refract1, r2 = rev ? refract1 : refract2;
        if (si[1] == -1 || nv_all[s] < 0) {
            seeded(&out, rev ? G.rev : G.fwd, r1, r2, eta, rev, G.fwd);
            continue;
        }
        int m = found_count[s];
        if (m > 0) {
            __global const double *a = coef + (long)s * stride;
            double margin = r1 ? V_MARGIN_APPROX : V_MARGIN_EXACT;
            for (int iv = 0; iv < m; ++iv)
                candidates_at(&out, found_all[(long)s * cap_new + iv], a, si[2], a + b_offset, si[3], si[4], si[5], r1, r2,
                              margin, rev ? G.rev : G.fwd, eta, rev, G.fwd);
        }
        out.stats[STAT_ROOTS] += nv_all[s] + m;
    }
    if (!straight) straight_candidate(&out, G.fwd, refract1, refract2, eta);
    out.stats[STAT_SKIPPED] = out.stats[STAT_SKIPPED] >= (BOTH_DIRECTIONS ? 2 : 1) ? 1 : 0;
    out.stats[STAT_PATHS] = out.count;
    out.stats[STAT_DETS] += dets;
    out_count[t] = out.count;
}
