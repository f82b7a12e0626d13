// The live pre-pass of the two-bounce solver in OpenCL C: addon/solver/spoly/two_bounce/prepass.py
// (a quadtree of tensor Bernstein forms over [-m, 1 + m]^2 deciding which v1 scan pieces the
// resultant scan has to visit, Fan et al. 2024 §4.1's range bound per box; the hit test of eq
// 14-17, the β band) and beta_mask of two_bounce/sqrt.py, written step for step so that both
// back ends give the same numbers bit for bit: the same IEEE operations in the same order
// (multiply, then add: the host builds with FP_CONTRACT OFF).
//
// Library of static functions (no kernel); every name is prefixed pp_ (macros PP_).  Pasted by
// the host after the two-bounce build options (-DMAXD=... : backend._two_bounce_defines), the
// tables (SQRT_PIECES_T: backend.two_bounce_tables) and biv.cl (SLOT, AT, BIV_N).  A 2-D array
// of the Python (biv[k], a, b, R, src, ...) is a slot pointer SLOT(biv, k) here.
//
// The simd helpers of addon/solver/runtime/simd.py are plain scalar loops with their meaning:
//   rows_add_scaled / rows_scale run on n elements rounded up to a multiple of PP_CHUNK, as the
//     intrinsics do (the extra elements are the triangle's zeros or columns beyond d: the same
//     numbers in [0, d]^2 either way, only the sign of a zero could differ without it);
//   casteljau_halves keeps the de Casteljau levels unscaled and scales each output row by 2^-r
//     once, as the intrinsic does (the halving loop's result bit for bit short of subnormals);
//   square_min_max_abs reduces per lane (column j mod PP_CHUNK), then folds the lanes from lane
//     0 up, as the intrinsic does (so even the sign of a zero result is the same);
//   small_box_range is the general path of box_range (the same numbers: its docstring).
// Private memory: pp_live_pieces_band holds its box stack (LIVE_STACK x 4 doubles) and the hit
// tolerances (4 doubles): 32 * LIVE_STACK + 32 bytes; the rest is scalars.
#if !defined(MAXD) || !defined(N_SLOTS) || !defined(LIVE_STACK) || !defined(BETA_SLOT) || !defined(HIT_SLOT) || \
    !defined(N_SQRT_PIECES)
#error "build with the two-bounce parameters (-DMAXD=... etc., opencl/backend.py _two_bounce_defines)"
#endif

#define PP_CHUNK 8  // simd.CHUNK: the lanes of the row operations and reductions
#define PP_ROUND(n) ((((n) + PP_CHUNK - 1) / PP_CHUNK) * PP_CHUNK)

// --- the simd helpers, scalar -----------------------------------------------------------------

// rows_add_scaled: dst[i] += s * x[i] for i < n rounded up to PP_CHUNK (never beyond BIV_N: n <= BIV_N)
static void pp_rows_add_scaled(__global double *dst, __global const double *x, double s, int n) {
    int m = PP_ROUND(n);
    for (int i = 0; i < m; ++i) dst[i] = dst[i] + s * x[i];
}

// rows_scale: dst[i] *= s for i < n rounded up to PP_CHUNK
static void pp_rows_scale(__global double *dst, double s, int n) {
    int m = PP_ROUND(n);
    for (int i = 0; i < m; ++i) dst[i] = dst[i] * s;
}

// transpose_square: dst[j][i] = src[i][j] for i, j <= d (src and dst distinct)
static void pp_transpose_square(__global const double *src, int d, __global double *dst) {
    for (int i = 0; i <= d; ++i)
        for (int j = 0; j <= d; ++j) AT(dst, j, i) = AT(src, i, j);
}

// square_min_max_abs: (min, max, max |.|) of c[i][j], i, j <= d; per lane (j mod PP_CHUNK, rows
// then chunks), the lanes folded from lane 0 up; the comparisons skip NaN
static void pp_square_min_max_abs(__global const double *c, int d, double *lo, double *hi, double *big) {
    double rlo = 0.0, rhi = 0.0, rbig = 0.0;
    for (int lane = 0; lane < PP_CHUNK; ++lane) {
        double l = INFINITY, h = -INFINITY, b = 0.0;
        for (int i = 0; i <= d; ++i) {
            for (int j = lane; j <= d; j += PP_CHUNK) {
                double x = AT(c, i, j);
                if (x < l) l = x;
                if (x > h) h = x;
                double ax = fabs(x);
                if (ax > b) b = ax;
            }
        }
        if (lane == 0) {
            rlo = l;
            rhi = h;
            rbig = b;
        } else {
            if (l < rlo) rlo = l;
            if (h > rhi) rhi = h;
            if (b > rbig) rbig = b;
        }
    }
    *lo = rlo;
    *hi = rhi;
    *big = rbig;
}

// casteljau_halves: the de Casteljau halves of src (rows 0 .. d) at the midpoint, per column
// j <= d: left[k] = Σ_(i <= k) C(k, i) src[i] / 2^k, right[d - r] likewise from the other end.
// The levels unscaled (S_r[k] = S_(r-1)[k - 1] + S_(r-1)[k]), two per sweep, each output row
// multiplied by 2^-r at the end: the intrinsic's operations in its order.
static void pp_casteljau_halves(__global const double *src, int d, __global double *left, __global double *right) {
    for (int j = 0; j <= d; ++j) {
        for (int i = 0; i <= d; ++i) AT(left, i, j) = AT(src, i, j);
        AT(right, d, j) = AT(left, d, j);
        for (int pair = 0; pair < d / 2; ++pair) {
            int r = 2 * pair + 1;
            double top = AT(left, d, j);
            double below = AT(left, d - 1, j);
            double s_top = below + top;  // S_r[d]
            AT(right, d - r, j) = s_top;
            double prev = s_top;
            double carry = below;
            for (int step = 0; step < d - r; ++step) {
                int k = d - 1 - step;  // d - 1 .. r
                below = AT(left, k - 1, j);
                double s_k = below + carry;  // S_r[k]
                double s_up = s_k + prev;  // S_(r+1)[k + 1]
                AT(left, k + 1, j) = s_up;
                if (step == 0) AT(right, d - r - 1, j) = s_up;
                prev = s_k;
                carry = below;
            }
            AT(left, r, j) = prev;  // S_r[r]
        }
        if (d % 2 == 1) {  // the last level (r = d) alone
            double last = AT(left, d - 1, j) + AT(left, d, j);
            AT(left, d, j) = last;
            AT(right, 0, j) = last;
        }
        double scale = 1.0;
        for (int k = 0; k <= d; ++k) {
            AT(left, k, j) = AT(left, k, j) * scale;
            AT(right, d - k, j) = AT(right, d - k, j) * scale;
            scale = scale * 0.5;
        }
    }
}

// --- tensor Bernstein forms ---------------------------------------------------------------------

// bivariate.bmax: the largest |p[i][j]| over the triangle i + j <= d (0 for none; NaN skipped)
static double pp_bmax(__global const double *p, int d) {
    double m = 0.0;
    for (int i = 0; i <= d; ++i) {
        for (int j = 0; j <= d - i; ++j) {
            double x = fabs(AT(p, i, j));
            m = x > m ? x : m;
        }
    }
    return m;
}

// R[k][i] = C(k, i) / C(d, i) for i <= k <= d (power -> Bernstein weights of degree d)
static void pp_binomial_ratios(int d, __global double *R) {
    double cd = 1.0;
    for (int i = 0; i <= d; ++i) {
        double r = 1.0 / cd;
        AT(R, i, i) = r;
        for (int k = i + 1; k <= d; ++k) {
            r = r * ((double)k / (double)(k - i));
            AT(R, k, i) = r;
        }
        cd = cd * (double)(d - i) / ((double)i + 1.0);
    }
}

// Taylor shift s = lo + w t along the first axis of the triangular A, then row i scaled by w^i
static void pp_shift_rows(__global double *A, int d, double lo, double w) {
    for (int k = 0; k < d; ++k)
        for (int i = d - 1; i >= k; --i) pp_rows_add_scaled(A + i * BIV_N, A + (i + 1) * BIV_N, lo, d - i);
    double f = 1.0;
    for (int i = 0; i <= d; ++i) {
        pp_rows_scale(A + i * BIV_N, f, d + 1 - i);
        f = f * w;
    }
}

// B[k][:] = Σ_(i <= k) R[k][i] A[i][:] (power -> Bernstein along the first axis)
static void pp_bernstein_rows(__global const double *A, int d, __global const double *R, __global double *B,
                              bool triangular) {
    for (int k = 0; k <= d; ++k) {
        for (int q = 0; q <= d; ++q) AT(B, k, q) = 0.0;
        for (int i = 0; i <= k; ++i)
            pp_rows_add_scaled(B + k * BIV_N, A + i * BIV_N, AT(R, k, i), triangular ? d + 1 - i : d + 1);
    }
}

// p (triangular power basis, total degree d) -> its tensor Bernstein coefficients of degree
// (d, d) over [u0, u0 + w] x [v0, v0 + w] into out (u index i, v index j); t0, t1 scratch
static void pp_tensor_bernstein_box(__global const double *p, int d, double u0, double v0, double w,
                                    __global const double *R, __global double *out, __global double *t0,
                                    __global double *t1) {
    for (int i = 0; i <= d; ++i)
        for (int j = 0; j <= d; ++j) AT(out, i, j) = i + j <= d ? AT(p, i, j) : 0.0;
    pp_shift_rows(out, d, u0, w);
    pp_transpose_square(out, d, t0);
    pp_shift_rows(t0, d, v0, w);
    pp_transpose_square(t0, d, out);
    pp_bernstein_rows(out, d, R, t1, true);
    pp_transpose_square(t1, d, t0);
    pp_bernstein_rows(t0, d, R, t1, false);
    pp_transpose_square(t1, d, out);
}

// pp_tensor_bernstein_box over the square [lo, lo + w]^2
static void pp_tensor_bernstein(__global const double *p, int d, double lo, double w, __global const double *R,
                                __global double *out, __global double *t0, __global double *t1) {
    pp_tensor_bernstein_box(p, d, lo, lo, w, R, out, t0, t1);
}

// de Casteljau at the midpoint of the u axis (rows)
static void pp_split_u(__global const double *src, int d, __global double *left, __global double *right) {
    pp_casteljau_halves(src, d, left, right);
}

// de Casteljau at the midpoint of the v axis: pp_split_u of the transpose (t0, t1, t2 scratch)
static void pp_split_v(__global const double *src, int d, __global double *left, __global double *right,
                       __global double *t0, __global double *t1, __global double *t2) {
    pp_transpose_square(src, d, t0);
    pp_split_u(t0, d, t1, t2);
    pp_transpose_square(t1, d, left);
    pp_transpose_square(t2, d, right);
}

// false when the coefficients c all exceed tol or all lie below -tol
static bool pp_may_vanish(__global const double *c, int d, double tol) {
    double lo, hi, big;
    pp_square_min_max_abs(c, d, &lo, &hi, &big);
    return !(lo > tol || hi < -tol);
}

static double pp_max_abs(__global const double *c, int d) {
    double lo, hi, big;
    pp_square_min_max_abs(c, d, &lo, &hi, &big);
    return big;
}

// the scan pieces k0 .. k1 a leaf [v0, v0 + w] in v1 marks: its own, one more on each side
static void pp_piece_span(double v0, double w, double margin, double h, int pieces, int *k0, int *k1) {
    int a = (int)floor((v0 + margin) / h) - 1;
    int b = (int)floor((v0 + w + margin) / h) + 1;
    *k0 = a > 0 ? a : 0;
    *k1 = b < pieces - 1 ? b : pieces - 1;
}

// true when every piece a leaf inside the box could mark is live already
static bool pp_pieces_covered(double v0, double w, double margin, double h, int pieces, __global const char *live) {
    int k0, k1;
    pp_piece_span(v0, w, margin, h, pieces, &k0, &k1);
    for (int k = k0; k <= k1; ++k)
        if (live[k] == 0) return false;
    return true;
}

// (min, max) of the tensor Bernstein coefficients of biv[src] (degree d) over the box
// [u0, u0 + w] x [v0, v0 + w]; slots BETA_SLOT + 1 .. + 4 as scratch
static void pp_box_range(__global double *biv, int src, int d, double u0, double v0, double w, double *lo,
                         double *hi) {
    __global double *R = SLOT(biv, BETA_SLOT + 1);
    __global double *out = SLOT(biv, BETA_SLOT + 2);
    pp_binomial_ratios(d, R);
    pp_tensor_bernstein_box(SLOT(biv, src), d, u0, v0, w, R, out, SLOT(biv, BETA_SLOT + 3), SLOT(biv, BETA_SLOT + 4));
    double big;
    pp_square_min_max_abs(out, d, lo, hi, &big);
}

// true when β (biv[BETA_SLOT]) provably stays outside [blo, bhi] (widened by tol) on the box
static bool pp_out_of_band(__global double *biv, double u0, double v0, double w, double blo, double bhi,
                           double tol) {
    if (blo == -INFINITY && bhi == INFINITY) return false;
    double lo, hi;
    pp_box_range(biv, BETA_SLOT, 4, u0, v0, w, &lo, &hi);
    return hi < blo - tol || lo > bhi + tol;
}

// upper bound of sign * biv[src] (degree d, sign ±1) on the box
static double pp_box_max(__global double *biv, int src, int d, double u0, double v0, double w, double sign) {
    double lo, hi;
    pp_box_range(biv, src, d, u0, v0, w, &lo, &hi);
    return sign > 0.0 ? hi : -lo;
}

// true when no x1 of the box maps to a point of triangle 2 (widened by the stored margin)
// ahead of it (the rational map of eq 14-17 in slots HIT_SLOT .. + 3; + 4 scratch)
static bool pp_misses_second(__global double *biv, double u0, double v0, double w, const double *tol) {
    __global double *kappa = SLOT(biv, HIT_SLOT);
    int dk = (int)AT(kappa, MAXD, 0);
    double m = AT(kappa, MAXD, 1);
    if (dk <= 0) return false;
    double k_lo, k_hi, sg;
    pp_box_range(biv, HIT_SLOT, dk, u0, v0, w, &k_lo, &k_hi);
    if (k_lo > tol[0])
        sg = 1.0;
    else if (k_hi < -tol[0])
        sg = -1.0;
    else
        return false;
    if (pp_box_max(biv, HIT_SLOT + 3, 1, u0, v0, w, sg) < -tol[3]) return true;
    int d = dk + 1;
    __global double *P = SLOT(biv, HIT_SLOT + 4);
    __global const double *U2 = SLOT(biv, HIT_SLOT + 1);
    __global const double *V2 = SLOT(biv, HIT_SLOT + 2);
    for (int q = 0; q < 3; ++q) {
        for (int i = 0; i <= d; ++i) {
            for (int j = 0; j <= d - i; ++j) {
                double kap = AT(kappa, i, j);
                if (q == 0)
                    AT(P, i, j) = AT(U2, i, j) + m * kap;
                else if (q == 1)
                    AT(P, i, j) = AT(V2, i, j) + m * kap;
                else
                    AT(P, i, j) = (1.0 + m) * kap - AT(U2, i, j) - AT(V2, i, j);
            }
        }
        if (pp_box_max(biv, HIT_SLOT + 4, d, u0, v0, w, sg) < -tol[q < 2 ? 1 : 2]) return true;
    }
    return false;
}

// live[k] = 1 for the scan pieces (of `pieces` over [-margin, 1 + margin]) whose v1 range a
// common zero of a (degree da) and b (degree db) with u1 in [-m, 1 - v1 + m] can lie in; returns
// their count.  a, b: slots of biv (as the Python's biv[0], biv[1]); blo, bhi: the β band
// (-INFINITY, INFINITY: none).  Scratch: slots 34-36, 40-44, LIVE_SLOT0 .. LIVE_SLOT0 +
// 2 LIVE_STACK - 1, BETA_SLOT + 1 .. + 4, HIT_SLOT + 4.
static int pp_live_pieces_band(__global const double *a, int da, __global const double *b, int db, double margin,
                               int pieces, __global double *biv, __global char *live, double blo, double bhi) {
    double boxes[LIVE_STACK][4];
    double hit_tol[4] = {0.0, 0.0, 0.0, 0.0};
    double h = (1.0 + 2.0 * margin) / (double)pieces;
    for (int k = 0; k < pieces; ++k) live[k] = 0;
    // rounding allowances of the hit test: of the size of each polynomial's coefficients
    int dk = (int)AT(SLOT(biv, HIT_SLOT), MAXD, 0);
    if (HIT_TEST && dk > 0) {
        double mk = pp_bmax(SLOT(biv, HIT_SLOT), dk);
        double mu = pp_bmax(SLOT(biv, HIT_SLOT + 1), dk + 1) + pp_bmax(SLOT(biv, HIT_SLOT + 2), dk + 1);
        double mt = pp_bmax(SLOT(biv, HIT_SLOT + 3), 1);
        hit_tol[0] = 1e-11 * mk;
        hit_tol[1] = 1e-11 * (mu + mk);
        hit_tol[2] = 1e-11 * (mu + 2.0 * mk);
        hit_tol[3] = 1e-11 * mt;
        if (pp_misses_second(biv, -margin, -margin, 1.0 + 2.0 * margin, hit_tol)) return 0;
    } else {
        dk = 0;
    }
    int depth = db <= LIVE_LOW_DEGREE ? LIVE_DEPTH_LOW : LIVE_DEPTH;
    __global double *R = SLOT(biv, 40);
    pp_binomial_ratios(da, R);
    pp_tensor_bernstein(a, da, -margin, 1.0 + 2.0 * margin, R, SLOT(biv, LIVE_SLOT0), SLOT(biv, 34), SLOT(biv, 35));
    pp_binomial_ratios(db, R);
    pp_tensor_bernstein(b, db, -margin, 1.0 + 2.0 * margin, R, SLOT(biv, LIVE_SLOT0 + 1), SLOT(biv, 34),
                        SLOT(biv, 35));
    double tol_a = LIVE_TOL * pp_max_abs(SLOT(biv, LIVE_SLOT0), da);
    double tol_b = LIVE_TOL * pp_max_abs(SLOT(biv, LIVE_SLOT0 + 1), db);
    double tol_beta = 0.0;
    if (blo != -INFINITY || bhi != INFINITY) {
        double alo = blo != -INFINITY ? fabs(blo) : 0.0;
        double ahi = bhi != INFINITY ? fabs(bhi) : 0.0;
        tol_beta = 1e-12 * (pp_max_abs(SLOT(biv, BETA_SLOT), 4) + (ahi > alo ? ahi : alo));
    }
    boxes[0][0] = -margin;
    boxes[0][1] = -margin;
    boxes[0][2] = 1.0 + 2.0 * margin;
    boxes[0][3] = 0.0;
    int top = 1;
    int n_live = 0;
    while (top > 0) {
        top -= 1;
        double u0 = boxes[top][0];
        double v0 = boxes[top][1];
        double w = boxes[top][2];
        double level = boxes[top][3];
        __global double *ca = SLOT(biv, LIVE_SLOT0 + 2 * top);
        __global double *cb = SLOT(biv, LIVE_SLOT0 + 2 * top + 1);
        if (level < 0.0 || u0 + v0 > 1.0 + margin) continue;
        if (pp_pieces_covered(v0, w, margin, h, pieces, live)) continue;
        if (level == 0.0 && pp_out_of_band(biv, u0, v0, w, blo, bhi, tol_beta)) continue;
        if (!pp_may_vanish(ca, da, tol_a) || !pp_may_vanish(cb, db, tol_b)) continue;
        if (level >= (double)depth) {
            int k0, k1;
            pp_piece_span(v0, w, margin, h, pieces, &k0, &k1);
            for (int k = k0; k <= k1; ++k) {
                if (live[k] == 0) {
                    live[k] = 1;
                    n_live += 1;
                }
            }
            continue;
        }
        // children in slots top .. top + 3 (u half su, v half sv -> top + 2 su + sv): a's
        // first; b only for the u halves where one of a's children may vanish
        pp_split_u(ca, da, SLOT(biv, 41), SLOT(biv, 42));
        double hw = 0.5 * w;
        for (int c = 0; c < 4; ++c) {
            boxes[top + c][0] = u0 + (double)(c / 2) * hw;
            boxes[top + c][1] = v0 + (double)(c % 2) * hw;
            boxes[top + c][2] = hw;
            boxes[top + c][3] = level + 1.0;
        }
        for (int su = 0; su < 2; ++su)
            pp_split_v(SLOT(biv, 41 + su), da, SLOT(biv, LIVE_SLOT0 + 2 * (top + 2 * su)),
                       SLOT(biv, LIVE_SLOT0 + 2 * (top + 2 * su + 1)), SLOT(biv, 34), SLOT(biv, 35), SLOT(biv, 36));
        int keep = 0;
        for (int su = 0; su < 2; ++su) {
            for (int sv = 0; sv < 2; ++sv) {
                int c = 2 * su + sv;
                if (boxes[top + c][0] + boxes[top + c][1] > 1.0 + margin ||
                    pp_pieces_covered(boxes[top + c][1], hw, margin, h, pieces, live) ||
                    pp_out_of_band(biv, boxes[top + c][0], boxes[top + c][1], hw, blo, bhi, tol_beta) ||
                    !pp_may_vanish(SLOT(biv, LIVE_SLOT0 + 2 * (top + c)), da, tol_a) ||
                    (dk > 0 && pp_misses_second(biv, boxes[top + c][0], boxes[top + c][1], hw, hit_tol)))
                    boxes[top + c][3] = -1.0;  // dead
                else
                    keep |= 1 << su;
            }
        }
        if (keep != 0) {
            pp_split_u(cb, db, SLOT(biv, 43), SLOT(biv, 44));
            for (int su = 0; su < 2; ++su)
                if ((keep >> su) & 1)
                    pp_split_v(SLOT(biv, 43 + su), db, SLOT(biv, LIVE_SLOT0 + 2 * (top + 2 * su) + 1),
                               SLOT(biv, LIVE_SLOT0 + 2 * (top + 2 * su + 1) + 1), SLOT(biv, 34), SLOT(biv, 35),
                               SLOT(biv, 36));
        }
        top += 4;
    }
    return n_live;
}

// pp_live_pieces_band without a β band
static int pp_live_pieces(__global const double *a, int da, __global const double *b, int db, double margin,
                          int pieces, __global double *biv, __global char *live) {
    return pp_live_pieces_band(a, da, b, db, margin, pieces, biv, live, -INFINITY, INFINITY);
}

// sqrt.beta_mask: bit k set for every eq (23) piece k >= BETA_MASK_FROM whose interval β/S2 can
// reach on triangle 1 widened by the margin (β in biv[BETA_SLOT]; bounds on a BETA_GRID^2 grid of
// boxes over [-m, 1 + m]^2, boxes beyond u1 + v1 = 1 + m skipped); N_SQRT_PIECES <= 31 bits
static int pp_beta_mask(__global double *biv, double margin, double S2) {
    int mask = 0;
    double w = (1.0 + 2.0 * margin) / (double)BETA_GRID;
    for (int i = 0; i < BETA_GRID; ++i) {
        for (int j = 0; j < BETA_GRID; ++j) {
            double u0 = -margin + (double)i * w;
            double v0 = -margin + (double)j * w;
            if (u0 + v0 > 1.0 + margin) continue;
            double lo, hi;
            pp_box_range(biv, BETA_SLOT, 4, u0, v0, w, &lo, &hi);
            lo = lo / S2;
            hi = hi / S2;
            for (int k = BETA_MASK_FROM; k < N_SQRT_PIECES; ++k)
                if (hi >= SQRT_PIECES_T[k][0] && (lo <= SQRT_PIECES_T[k][1] || k == N_SQRT_PIECES - 1)) mask |= 1 << k;
        }
    }
    return mask;
}
