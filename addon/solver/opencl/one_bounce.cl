// One-bounce Specular Polynomials (R, T) in OpenCL C: the same algorithm, step for step, as
// addon/solver/spoly/one_bounce.py, polynomials/roots.py and paths/one_vertex.py (Fan et al.
// 2024, eq 6, 10, 13, 28-31), so both back ends return the same paths (tests/solver/
// test_solver_opencl.py).  One work-item per tuple; all scratch is private and fixed-size.
// Double precision (cl_khr_fp64) is required.
// The resultant is evaluated at Chebyshev nodes, its double-point factor divided out, and
// interpolated (piecewise where its values span more than 1e6), as spoly/one_bounce.py does; the
// node tables (NODES_*, TO_BERNSTEIN_*) are the solver's own, prepended by the host.
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL FP_CONTRACT OFF
// @NODE_TABLES@ (replaced by the host: __constant double NODES_R[9], TO_BERNSTEIN_R[81], NODES_T[13], TO_BERNSTEIN_T[169]
// and the deflated NODES_R_DEFLATED[8], NODES_T_DEFLATED[11] and their _WIDE sets, with their matrices)

#define MAXD 12            // degree of the one-bounce resultant at most
#define UNI 14             // univariate scratch width: the resultant's degree MAXD + 1, and a spare
#define DEPTH 5            // Bernstein halvings before derivative isolation
// Rows of the Bernstein subdivision stack: a depth-first subdivision holds at most DEPTH + 1 rows
// (rows 0..DEPTH; one spare), then the rows at STACK - 4 .. STACK (second and first derivative
// weights, weights, the whole-interval form, the de Casteljau work row).
#define STACK (DEPTH + 6)
// The derivative chain of roots_in_interval, stored by rows of growing length: row k (the
// degree-k derivative level, k + 1 coefficients) starts at k (k + 1) / 2.
#define CHAIN_SIZE ((MAXD + 1) * (MAXD + 2) / 2)
#define POLISH_ON_BERNSTEIN_STEPS 4
#define POLISH_STEPS 40
#define FAR_START -1.0       // the error polish_and_validate reports for a start rejected by max_first_step
#define RETURNED -2.0        // ... and for a fold probe abandoned on its way back to the known path
#define PROBE_RETURN 0.25    // that probe: its iterate within this share of its distance of the path
#define INEXACT_ROOT 1e-9      // |b| / sum |b_ij u^i v^j| above which a candidate is no exact root of the system
#define CANDIDATE_REACH 0.1  // a resultant candidate whose first Gauss-Newton step is longer is no path's root
#define V_MARGIN 1e-6
#define ROOT_X_TOLERANCE 1e-13
#define ROOT_TOUCH_TOLERANCE 1e-10
#define NEAR_TOUCH 1e-6
#define SPLIT_LOW 0.125     // a Bernstein piece is split no closer than this share of it to either end
#define CONVEX_MARGIN 1e-9  // second differences of a piece clear of zero by this: its second derivative keeps its sign
#define NEGLIGIBLE 1e-13
#define SAME_PATH 1e-7
#define NEAR_PATH 1e-5
#define ACCEPT_RESIDUAL 1e-12
#define DIRECTION_TOLERANCE 1e-7
#define INSIDE_EPSILON 1e-9
#define SETTLED_STEP 1e-9
#define FLOOR_RESIDUAL 1e-13  // residual and step at rounding level: the step is taken unevaluated
#define FLOOR_STEP 1e-12
#define FOLD_RATIO 1e-4
#define SINGULAR_MARGIN 0.01  // barycentric slack of the test for a path at normal incidence
#define SWITCH_RATIO 0.1
#define SPURIOUS_B 1e-3     // |b| / sum |b_ij u^i v^j| above which b clearly does not vanish at a u-root
#define DOUBLE_POINT_REACH 0.25  // the double point is divided out only within this distance of [0, 1]
#define DOUBLE_POINT_F3 1e-9  // |f3| / sum |f3_ij u^i v^j| under which a root of Res_u(a, g) is the double point
#define DYNAMIC_RANGE 1e-6  // node values spanning more than this: interpolate the resultant piecewise
#define SPLIT 4             // pieces per level of that refinement
#define SPLIT_DEPTH 2       // levels at most (16 pieces)
#define PIECE_STACK 8       // pieces pending at most: 1 + (SPLIT - 1) * SPLIT_DEPTH
#define MAX_V_ROOTS 25      // v roots kept per system (one_bounce.py's root_buf width)

typedef double3 vec;

// The vector products (and roots.cl's integer powers) written out in the order Numba evaluates
// them (geometry/vec3.py; Numba's float ** int is binary exponentiation): OpenCL's built-in dot,
// cross, length and pown may fuse or rescale (NVIDIA's do), and a last-bit difference can move a
// root across a threshold on a GPU.
static double vdot(vec a, vec b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
static vec vcross(vec a, vec b) { return (vec)(a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x); }
static double vlength(vec a) { return sqrt(a.x * a.x + a.y * a.y + a.z * a.z); }
// @INCLUDE roots.cl@ (the univariate root finder, shared with two_bounce.cl)

// roots.py _second_differences_one_sign
static int second_differences_one_sign(const double *b, int deg, double margin) {
    double smallest = INFINITY, largest = -INFINITY;
    for (int k = 0; k < deg - 1; ++k) {
        double d = b[k + 2] - 2.0 * b[k + 1] + b[k];
        smallest = fmin(smallest, d);
        largest = fmax(largest, d);
    }
    return smallest > margin || largest < -margin;
}

static int sign_changes(const double *b, int deg, double zero_level) {
    int changes = 0, prev = 0;
    for (int k = 0; k <= deg; ++k) {
        if (fabs(b[k]) <= zero_level) return 2;
        int s = b[k] > 0.0 ? 1 : -1;
        if (prev != 0 && s != prev) { if (++changes >= 2) return 2; }
        prev = s;
    }
    return changes;
}

// De Casteljau halving of the Bernstein piece in stack[top] (coefficients 0..deg, then lo, hi,
// depth): its left half goes to stack[top + 1], its right half stays in stack[top], both one
// level deeper (stack[STACK] is the work row).
static void halve_piece(double stack[STACK + 1][MAXD + 4], int top, int deg, double lo, double hi, double depth) {
    double *row = stack[top], *left = stack[top + 1], *work = stack[STACK];
    int meta = deg + 1;
    for (int i = 0; i <= deg; ++i) work[i] = row[i];
    left[0] = work[0];
    row[deg] = work[deg];
    for (int r = 1; r <= deg; ++r) {
        for (int i = 0; i <= deg - r; ++i) work[i] = 0.5 * (work[i] + work[i + 1]);
        left[r] = work[0];
        row[deg - r] = work[deg - r];
    }
    double mid = 0.5 * (lo + hi);
    left[meta] = lo; left[meta + 1] = mid; left[meta + 2] = depth + 1.0;
    row[meta] = mid; row[meta + 1] = hi; row[meta + 2] = depth + 1.0;
}

// Appends a piece's ascending roots to out[0..n_out), skipping those within tol of the last one.
static int append_roots(double *out, int n_out, const double *roots, int n, double tol) {
    for (int j = 0; j < n; ++j)
        if (n_out == 0 || roots[j] - out[n_out - 1] > tol) out[n_out++] = roots[j];
    return n_out;
}

// Descartes/Bernstein isolation with de Casteljau halving (roots.roots_in_unit_interval).
static int roots_in_unit_interval(const double *coeffs, int degree, double tol, double touch,
                                  double *chain, double *critical, double *found,
                                  double stack[STACK + 1][MAXD + 4], double *out) {
    double norm = 0.0;
    for (int i = 0; i <= degree; ++i) norm = fmax(norm, fabs(coeffs[i]));
    if (norm == 0.0 || !isfinite(norm)) return 0;
    int deg = degree;
    while (deg > 0 && fabs(coeffs[deg]) <= 1e-15 * norm) deg--;
    if (deg <= 2) return roots_in_interval(coeffs, deg, 0.0, 1.0, tol, touch, chain, critical, found, out);
    double *work = stack[STACK];
    double binom_deg = 1.0;
    for (int i = 0; i <= deg; ++i) { work[i] = coeffs[i] / norm / binom_deg; binom_deg = binom_deg * (deg - i) / (i + 1); }
    double *top_row = stack[0];
    double scale = 0.0;
    for (int k = 0; k <= deg; ++k) {
        double bk = 0.0, binom = 1.0;
        for (int i = 0; i <= k; ++i) { bk += binom * work[i]; binom = binom * (k - i) / (i + 1); }
        top_row[k] = bk; scale = fmax(scale, fabs(bk));
    }
    double zero_level = touch * scale;
    int meta = deg + 1;
    top_row[meta] = 0.0; top_row[meta + 1] = 1.0; top_row[meta + 2] = 0.0;
    int top = 1, n_out = 0;
    double piece[MAXD + 1];
    while (top > 0) {
        top--;
        double *row = stack[top];
        double lo = row[meta], hi = row[meta + 1], depth = row[meta + 2];
        int changes = sign_changes(row, deg, zero_level);
        if (changes == 0) {
            double closest = fabs(row[0]);
            for (int k = 1; k <= deg; ++k) closest = fmin(closest, fabs(row[k]));
            if (closest > NEAR_TOUCH * scale) continue;
            changes = 2;
            depth = DEPTH;
        }
        if (changes == 1) {
            double fa = horner(coeffs, deg, lo), fb = horner(coeffs, deg, hi);
            if (fa != 0.0 && fb != 0.0 && ((fa < 0.0) != (fb < 0.0))) {
                double x = solve_monotone(coeffs, deg, lo, hi, fa, fb, tol);
                if (n_out == 0 || x - out[n_out - 1] > tol) out[n_out++] = x;
                continue;
            }
        }
        if (depth >= DEPTH) {
            int n_piece = roots_in_interval(coeffs, deg, lo, hi, tol, touch, chain, critical, found, piece);
            n_out = append_roots(out, n_out, piece, n_piece, tol);
            continue;
        }
        halve_piece(stack, top, deg, lo, hi, depth);
        top += 2;
    }
    return n_out;
}

// ---------------------------------------------------------------- roots of a Bernstein form
// roots.py bernstein_weights: w[k] = C(deg, k) b[k], dw[k] = deg C(deg - 1, k) (b[k+1] - b[k]).
static void bernstein_weights(const double *b, int deg, double *w, double *dw) {
    double binom = 1.0;
    for (int k = 0; k <= deg; ++k) { w[k] = binom * b[k]; binom = binom * (deg - k) / (k + 1); }
    binom = (double)deg;
    for (int k = 0; k < deg; ++k) { dw[k] = binom * (b[k + 1] - b[k]); binom = binom * (deg - 1 - k) / (k + 1); }
}

// roots.py bernstein_value_and_derivative: Horner in x on sum_k w[k] x^k s^(deg - k), s = 1 - x.
static double2 bernstein_value_and_derivative(const double *w, const double *dw, int deg, double x) {
    double s = 1.0 - x, f = w[deg], df = dw[deg - 1], s_power = 1.0;
    for (int k = deg - 1; k > 0; --k) {
        s_power *= s;
        f = f * x + w[k] * s_power;
        df = df * x + dw[k - 1] * s_power;
    }
    s_power *= s;
    return (double2)(f * x + w[0] * s_power, df);
}

// roots.py bernstein_second_weights: ddw[k] = deg (deg - 1) C(deg - 2, k) (b[k+2] - 2 b[k+1] + b[k]).
static void bernstein_second_weights(const double *b, int deg, double *ddw) {
    double binom = (double)(deg * (deg - 1));
    for (int k = 0; k < deg - 1; ++k) {
        ddw[k] = binom * (b[k + 2] - 2.0 * b[k + 1] + b[k]);
        binom = binom * (deg - 2 - k) / (k + 1);
    }
}

// roots.py bernstein_value_and_two_derivatives: three Horner chains in one loop (deg >= 2).
static double3 bernstein_value_and_two_derivatives(const double *w, const double *dw, const double *ddw, int deg,
                                                   double x) {
    double s = 1.0 - x, f = w[deg], df = dw[deg - 1], ddf = ddw[deg - 2], s_power = 1.0;
    for (int k = deg - 1; k > 1; --k) {
        s_power *= s;
        f = f * x + w[k] * s_power;
        df = df * x + dw[k - 1] * s_power;
        ddf = ddf * x + ddw[k - 2] * s_power;
    }
    s_power *= s;
    f = f * x + w[1] * s_power;
    df = df * x + dw[0] * s_power;
    s_power *= s;
    return (double3)(f * x + w[0] * s_power, df, ddf);
}

// roots.py _split_between_crossings: halfway between the control polygon's first two crossings,
// within [SPLIT_LOW, 1 - SPLIT_LOW]; 0.5 with fewer crossings
static double split_between_crossings(const double *b, int deg) {
    double first = -1.0;
    for (int k = 0; k < deg; ++k) {
        if ((b[k] < 0.0) != (b[k + 1] < 0.0)) {
            double crossing = (k + b[k] / (b[k] - b[k + 1])) / deg;
            if (first < 0.0) first = crossing;
            else return fmin(fmax(0.5 * (first + crossing), SPLIT_LOW), 1.0 - SPLIT_LOW);
        }
    }
    return 0.5;
}

// De Casteljau split of the Bernstein piece in stack[top] at t (roots.py
// roots_in_unit_interval_bernstein): as halve_piece, at lo + t (hi - lo).  Not halve_piece with
// t = 1/2: a + t (b - a) and (a + b) / 2 round differently, and each finder matches its roots.py
// twin bit for bit (control_polygon_crossing returns 1/2 when it finds no crossing).
static void split_piece(double stack[STACK + 1][MAXD + 4], int top, int deg, double lo, double hi, double depth,
                        double t) {
    double *row = stack[top], *left = stack[top + 1], *work = stack[STACK];
    int meta = deg + 1;
    for (int i = 0; i <= deg; ++i) work[i] = row[i];
    left[0] = work[0];
    row[deg] = work[deg];
    for (int r = 1; r <= deg; ++r) {
        for (int i = 0; i <= deg - r; ++i) work[i] = work[i] + t * (work[i + 1] - work[i]);
        left[r] = work[0];
        row[deg - r] = work[deg - r];
    }
    double mid = lo + t * (hi - lo);
    left[meta] = lo; left[meta + 1] = mid; left[meta + 2] = depth + 1.0;
    row[meta] = mid; row[meta + 1] = hi; row[meta + 2] = depth + 1.0;
}

// roots.py _control_polygon_crossing: where the control polygon (k / deg, b[k]) first crosses zero
static double control_polygon_crossing(const double *b, int deg) {
    for (int k = 0; k < deg; ++k)
        if ((b[k] < 0.0) != (b[k + 1] < 0.0)) return (k + b[k] / (b[k] - b[k + 1])) / deg;
    return 0.5;
}

// roots.py _halley_settled: the step is below tol, or cubic convergence (step ratio r at most
// NEWTON_QUADRATIC_RATIO, r^3 step <= tol); a first step is held to newton_settled's bound
static int halley_settled(double step, double previous_step, double tol) {
    if (step <= tol) return 1;
    if (previous_step == INFINITY) return step * NEWTON_QUADRATIC_RATIO * NEWTON_QUADRATIC_RATIO <= tol;
    double r = step / previous_step;
    return r <= NEWTON_QUADRATIC_RATIO && r * r * r * step <= tol;
}

// roots.py _solve_monotone_bernstein: Halley's step where |f f''| < f'^2, else Newton's
static double solve_monotone_bernstein(const double *w, const double *dw, const double *ddw, int deg, double a,
                                       double c, double fa, double fc, double x_start, double tol) {
    double x = x_start;
    if (!(x > a && x < c)) x = a - fa * (c - a) / (fc - fa);
    if (!(x > a && x < c)) x = 0.5 * (a + c);
    int neg_a = fa < 0.0;
    double previous_step = INFINITY;
    for (int it = 0; it < NEWTON_ITERATIONS; ++it) {
        double3 fd = bernstein_value_and_two_derivatives(w, dw, ddw, deg, x);
        double f = fd.x, df = fd.y, ddf = fd.z;
        if (f == 0.0) return x;
        if ((f < 0.0) == neg_a) a = x; else c = x;
        double xn;
        if (df != 0.0) {
            double curvature = f * ddf;
            if (fabs(curvature) < df * df) xn = x - 2.0 * f * df / (2.0 * df * df - curvature);
            else xn = x - f / df;
            double step = fabs(xn - x);
            if (halley_settled(step, previous_step, tol) && xn >= a && xn <= c) return xn;
            previous_step = step;
        } else {
            xn = 0.5 * (a + c);
            previous_step = INFINITY;
        }
        if (!(xn > a && xn < c)) { xn = 0.5 * (a + c); previous_step = INFINITY; }
        if (fabs(xn - x) <= tol || c - a <= tol) return xn;
        x = xn;
    }
    return x;
}

// roots.py _polish_on_bernstein: Newton steps on the Bernstein form while each is shorter than the
// one before, stays in [lo, hi] and lowers |p|
static double polish_on_bernstein(const double *w, const double *dw, int deg, double x, double lo, double hi,
                                  double tol) {
    double2 fd = bernstein_value_and_derivative(w, dw, deg, x);
    double f = fd.x, df = fd.y;
    double best = x, best_f = fabs(f), previous = INFINITY;
    for (int it = 0; it < POLISH_ON_BERNSTEIN_STEPS; ++it) {
        if (df == 0.0 || best_f == 0.0) break;
        double step = f / df;
        if (!(fabs(step) < previous)) break;
        double xn = x - step;
        if (!(xn >= lo && xn <= hi)) break;
        fd = bernstein_value_and_derivative(w, dw, deg, xn);
        f = fd.x;
        df = fd.y;
        if (!(fabs(f) < best_f)) break;
        best = xn;
        best_f = fabs(f);
        previous = fabs(step);
        x = xn;
        if (previous <= tol) break;
    }
    return best;
}

// roots.py roots_in_unit_interval_bernstein: the isolation of roots_in_unit_interval started
// from Bernstein coefficients bern[0..deg] (Newton on the Bernstein form; pieces still ambiguous
// after DEPTH halvings go to the derivative isolation on the power form, written to `power`).
static int roots_in_unit_interval_bernstein(const double *bern, int deg, double tol, double touch,
                                            double *chain, double *critical, double *found,
                                            double stack[STACK + 1][MAXD + 4], double *power, double *out) {
    double scale = 0.0;
    for (int k = 0; k <= deg; ++k) scale = fmax(scale, fabs(bern[k]));
    if (scale == 0.0 || !isfinite(scale)) return 0;
    double inv = 1.0 / scale;
    double *top_row = stack[0];
    for (int k = 0; k <= deg; ++k) top_row[k] = bern[k] * inv;
    double *src = stack[STACK - 1], *src_w = stack[STACK - 2], *src_dw = stack[STACK - 3];
    double *src_ddw = stack[STACK - 4];
    for (int k = 0; k <= deg; ++k) src[k] = top_row[k];
    int have_weights = 0, have_second = 0, have_power = 0;
    int meta = deg + 1;
    top_row[meta] = 0.0; top_row[meta + 1] = 1.0; top_row[meta + 2] = 0.0;
    int top = 1, n_out = 0;
    double piece[MAXD + 1];
    while (top > 0) {
        top--;
        double *row = stack[top];
        double lo = row[meta], hi = row[meta + 1], depth = row[meta + 2];
        int changes = sign_changes(row, deg, touch);
        if (changes == 0) {
            double closest = fabs(row[0]);
            for (int k = 1; k <= deg; ++k) closest = fmin(closest, fabs(row[k]));
            if (closest > NEAR_TOUCH) continue;
            changes = 2;
            depth = DEPTH;
        }
        if (changes == 1) {
            double fa = row[0], fb = row[deg];
            if (fa != 0.0 && fb != 0.0 && ((fa < 0.0) != (fb < 0.0))) {
                if (!have_weights) { bernstein_weights(src, deg, src_w, src_dw); have_weights = 1; }
                if (!have_second) { bernstein_second_weights(src, deg, src_ddw); have_second = 1; }
                // Halley starts where the piece's control polygon crosses zero (roots.py)
                double x_start = lo + (hi - lo) * control_polygon_crossing(row, deg);
                double x = solve_monotone_bernstein(src_w, src_dw, src_ddw, deg, lo, hi, fa, fb, x_start, tol);
                if (n_out == 0 || x - out[n_out - 1] > tol) out[n_out++] = x;
                continue;
            }
        }
        if (depth >= DEPTH) {
            if (!have_power) {
                double binom_deg = 1.0;
                for (int i = 0; i <= deg; ++i) {
                    double acc = 0.0, binom = 1.0;
                    for (int k = 0; k <= i; ++k) {
                        double sign = ((i - k) % 2 == 0) ? 1.0 : -1.0;
                        acc += sign * binom * src[k];
                        binom = binom * (i - k) / (k + 1);
                    }
                    power[i] = binom_deg * acc;
                    binom_deg = binom_deg * (deg - i) / (i + 1);
                }
                have_power = 1;
            }
            int convex = second_differences_one_sign(row, deg, CONVEX_MARGIN);
            int n_piece = derivative_isolation(power, deg, lo, hi, tol, touch, chain, critical, found, piece, convex, 1);
            if (n_piece && !have_weights) { bernstein_weights(src, deg, src_w, src_dw); have_weights = 1; }
            for (int j = 0; j < n_piece; ++j) piece[j] = polish_on_bernstein(src_w, src_dw, deg, piece[j], lo, hi, tol);
            n_out = append_roots(out, n_out, piece, n_piece, tol);
            continue;
        }
        split_piece(stack, top, deg, lo, hi, depth, split_between_crossings(row, deg));
        top += 2;
    }
    return n_out;
}

// ---------------------------------------------------------------- bivariate polynomials
// A bivariate polynomial of total degree d in (u, v), stored densely by rows: the coefficient of
// u^i v^j (i + j <= d) at p[i * (d + 1) + j], so a degree-2 polynomial takes 9 doubles and a
// degree-6 one 49 (private memory per work-item is what limits a GPU here).
#define BI(p, d, i, j) p[(i) * ((d) + 1) + (j)]
#define BIV2 9
#define BIV4 25
#define BIV6 49

// (a0 + u au + v av) . (b0 + u bu + v bv), degree 2
static void lin_dot(double *out, vec a0, vec au, vec av, vec b0, vec bu, vec bv) {
    for (int i = 0; i < BIV2; ++i) out[i] = 0.0;
    BI(out, 2, 0, 0) = vdot(a0, b0);
    BI(out, 2, 1, 0) = vdot(a0, bu) + vdot(au, b0);
    BI(out, 2, 0, 1) = vdot(a0, bv) + vdot(av, b0);
    BI(out, 2, 2, 0) = vdot(au, bu);
    BI(out, 2, 1, 1) = vdot(au, bv) + vdot(av, bu);
    BI(out, 2, 0, 2) = vdot(av, bv);
}

static void bmul(const double *p, int dp, const double *q, int dq, double *out) {
    int d = dp + dq;
    for (int i = 0; i <= d; ++i) for (int j = 0; j <= d - i; ++j) BI(out, d, i, j) = 0.0;
    for (int i1 = 0; i1 <= dp; ++i1)
        for (int j1 = 0; j1 <= dp - i1; ++j1) {
            double c = BI(p, dp, i1, j1);
            if (c == 0.0) continue;
            for (int i2 = 0; i2 <= dq; ++i2)
                for (int j2 = 0; j2 <= dq - i2; ++j2) BI(out, d, i1 + i2, j1 + j2) += c * BI(q, dq, i2, j2);
        }
}

static void bcombine(double *out, int d, double ca, const double *a, double cb, const double *b) {
    for (int i = 0; i <= d; ++i) for (int j = 0; j <= d - i; ++j) BI(out, d, i, j) = ca * BI(a, d, i, j) + cb * BI(b, d, i, j);
}

static double bmax(const double *p, int d) {
    double m = 0.0;
    for (int i = 0; i <= d; ++i) for (int j = 0; j <= d - i; ++j) m = fmax(m, fabs(BI(p, d, i, j)));
    return m;
}

// one_bounce.py _resultant_from_b_values (resultant_at_nodes, one node at a time): Res_u(a, b)
// at one v from the u-roots of a (q = -(a1 + sign(a1) sqrt(disc)) / 2; complex roots:
// a2^nb |b(rho)|^2); bv receives b_i(v), i = 0..nb.
static double resultant_at(const double *a, const double *b, int nb, int tb, double v, double *bv) {
    double a2 = BI(a, 2, 2, 0);
    double a1 = BI(a, 2, 1, 0) + BI(a, 2, 1, 1) * v;
    double a0 = BI(a, 2, 0, 0) + (BI(a, 2, 0, 1) + BI(a, 2, 0, 2) * v) * v;
    for (int i = 0; i <= nb; ++i) {
        double acc = 0.0;
        for (int j = tb - i; j >= 0; --j) acc = acc * v + BI(b, tb, i, j);
        bv[i] = acc;
    }
    double disc = a1 * a1 - 4.0 * a2 * a0;
    if (disc >= 0.0) {
        double q = -0.5 * (a1 + copysign(sqrt(disc), a1));
        if (q == 0.0) {
            if (a2 != 0.0) return ipow(a2, nb) * bv[0] * bv[0];
            return ipow(a0, nb) * bv[nb] * bv[nb];
        }
        double far = bv[nb], p = 1.0;
        for (int i = nb - 1; i >= 0; --i) { p *= a2; far = far * q + bv[i] * p; }
        double rho = a0 / q, near = bv[nb];
        for (int i = nb - 1; i >= 0; --i) near = near * rho + bv[i];
        return far * near;
    }
    double sa = sqrt(fabs(a2));
    double zr = -a1 / (2.0 * a2) * sa, zi = sqrt(-disc) / (2.0 * a2) * sa;
    double ar = bv[nb], ai = 0.0, p = 1.0;
    for (int i = nb - 1; i >= 0; --i) {
        p *= sa;
        double nr = ar * zr - ai * zi + bv[i] * p, ni = ar * zi + ai * zr;
        ar = nr; ai = ni;
    }
    double val = ar * ar + ai * ai;
    if (a2 < 0.0 && nb % 2 == 1) val = -val;
    return val;
}

static double nearest_node(__constant const double *nodes, int count, double s) {
    double d = INFINITY;
    for (int k = 0; k < count; ++k) d = fmin(d, fabs(nodes[k] - s));
    return d;
}

// one_bounce.py resultant_bernstein: Bernstein coefficients on s in [0, 1] of
// Res_u(a, b)(origin + width s), divided by (v - v_double)^m (m = 1 for R, 2 for T) when v_double
// is finite, from its values at the Chebyshev nodes (NODES_*, TO_BERNSTEIN_*: the solver's own
// tables, prepended to this source by the host; of the two deflated sets the one whose nodes lie
// farther from v_double); returns the degree 2 tb - m.
static int resultant_bernstein(const double *a, const double *b, int nb, int tb, double origin, double width,
                               double v_double, double *bv, double *values, double *out) {
    int multiplicity = 0;
    __constant const double *nodes = tb == 4 ? NODES_R : NODES_T;
    __constant const double *to_bernstein = tb == 4 ? TO_BERNSTEIN_R : TO_BERNSTEIN_T;
    if (isfinite(v_double)) {
        double s = (v_double - origin) / width;
        multiplicity = tb == 4 ? 1 : 2;
        int count = 2 * tb - multiplicity + 1;
        __constant const double *narrow = tb == 4 ? NODES_R_DEFLATED : NODES_T_DEFLATED;
        __constant const double *wide = tb == 4 ? NODES_R_DEFLATED_WIDE : NODES_T_DEFLATED_WIDE;
        if (nearest_node(narrow, count, s) >= nearest_node(wide, count, s)) {
            nodes = narrow;
            to_bernstein = tb == 4 ? TO_BERNSTEIN_R_DEFLATED : TO_BERNSTEIN_T_DEFLATED;
        } else {
            nodes = wide;
            to_bernstein = tb == 4 ? TO_BERNSTEIN_R_DEFLATED_WIDE : TO_BERNSTEIN_T_DEFLATED_WIDE;
        }
    }
    int deg = 2 * tb - multiplicity;
    for (int k = 0; k <= deg; ++k) {
        double v = origin + width * nodes[k];
        values[k] = resultant_at(a, b, nb, tb, v, bv);
        if (multiplicity > 0) {
            double d = v - v_double;
            values[k] /= multiplicity == 1 ? d : d * d;
        }
    }
    for (int i = 0; i <= deg; ++i) {
        double acc = 0.0;
        for (int k = 0; k <= deg; ++k) acc += to_bernstein[i * (deg + 1) + k] * values[k];
        out[i] = acc;
    }
    return deg;
}

// one_bounce.py _resultant_v_roots: roots in v in [-V_MARGIN, 1 + V_MARGIN] of Res_u(a, b),
// ascending: one interpolant over the range, cut in SPLIT pieces (down to SPLIT_DEPTH levels)
// where the node values span more than DYNAMIC_RANGE.
static int resultant_v_roots(const double *a, const double *b, int nb, int tb, double v_double, double *chain,
                             double *critical, double *found, double stack[STACK + 1][MAXD + 4], double *v_roots) {
    double bv[7], values[MAXD + 1], res[MAXD + 1], power[MAXD + 1], piece_roots[MAXD + 1];
    double piece_lo[PIECE_STACK], piece_hi[PIECE_STACK];
    int piece_depth[PIECE_STACK];
    piece_lo[0] = -V_MARGIN; piece_hi[0] = 1.0 + V_MARGIN; piece_depth[0] = 0;
    int top = 1, n_v = 0;
    while (top > 0) {
        top--;
        double lo = piece_lo[top], hi = piece_hi[top];
        int depth = piece_depth[top];
        int deg_r = resultant_bernstein(a, b, nb, tb, lo, hi - lo, v_double, bv, values, res);
        if (depth < SPLIT_DEPTH) {
            double big = 0.0, small = INFINITY;
            for (int k = 0; k <= deg_r; ++k) { big = fmax(big, fabs(values[k])); small = fmin(small, fabs(values[k])); }
            if (small < DYNAMIC_RANGE * big) {
                for (int j = SPLIT - 1; j >= 0; --j) {  // pushed right to left: they come off in ascending order
                    piece_lo[top] = lo + (hi - lo) * j / SPLIT;
                    piece_hi[top] = lo + (hi - lo) * (j + 1) / SPLIT;
                    piece_depth[top] = depth + 1;
                    top++;
                }
                continue;
            }
        }
        int n_piece = roots_in_unit_interval_bernstein(res, deg_r, ROOT_X_TOLERANCE, ROOT_TOUCH_TOLERANCE, chain, critical,
                                                       found, stack, power, piece_roots);
        for (int j = 0; j < n_piece; ++j) {
            double v = lo + (hi - lo) * piece_roots[j];
            if (n_v > 0 && v - v_roots[n_v - 1] <= ROOT_X_TOLERANCE) continue;  // the same root at a piece boundary
            if (n_v < MAX_V_ROOTS) v_roots[n_v++] = v;
        }
    }
    return n_v;
}

static void shift_to_unit_interval(double *c, int deg, double origin, double width) {
    for (int i = 0; i < deg; ++i) for (int j = deg - 1; j >= i; --j) c[j] += origin * c[j + 1];
    double p = 1.0;
    for (int k = 0; k <= deg; ++k) { c[k] *= p; p *= width; }
}

static int conic_misses_triangle(const double *a, double scale) {
    double a00 = BI(a, 2, 0, 0), a10 = BI(a, 2, 1, 0), a01 = BI(a, 2, 0, 1);
    double b200 = a00, b020 = a00 + a10 + BI(a, 2, 2, 0), b002 = a00 + a01 + BI(a, 2, 0, 2);
    double b110 = a00 + 0.5 * a10, b101 = a00 + 0.5 * a01;
    double b011 = a00 + 0.5 * (a10 + a01 + BI(a, 2, 1, 1));
    double lo = fmin(fmin(b200, b020), fmin(fmin(b002, b110), fmin(b101, b011)));
    double hi = fmax(fmax(b200, b020), fmax(fmax(b002, b110), fmax(b101, b011)));
    double margin = 1e-7 * scale;
    return lo > margin || hi < -margin;
}

static double3 eval_with_gradient(const double *p, int d, double u, double v) {
    double f = 0.0, fu = 0.0, fv = 0.0, ui = 1.0, ui_1 = 0.0;
    for (int i = 0; i <= d; ++i) {
        double vj = 1.0, vj_1 = 0.0;
        for (int j = 0; j <= d - i; ++j) {
            double c = BI(p, d, i, j);
            f += c * ui * vj;
            fv += c * ui * vj_1;
            if (i > 0) fu += c * i * ui_1 * vj;
            vj_1 = (j + 1) * vj;
            vj *= v;
        }
        ui_1 = ui;
        ui *= u;
    }
    return (double3)(f, fu, fv);
}

static double2 refine_on_polynomials(const double *a, const double *b, int db, double u, double v) {
    double3 A = eval_with_gradient(a, 2, u, v), B = eval_with_gradient(b, db, u, v);
    double size = fabs(A.x) + fabs(B.x);
    for (int it = 0; it < 4; ++it) {
        double det = A.y * B.z - A.z * B.y;
        if (det == 0.0 || size == 0.0) break;
        double du = -(A.x * B.z - A.z * B.x) / det, dv = -(A.y * B.x - A.x * B.y) / det;
        double3 GA = eval_with_gradient(a, 2, u + du, v + dv), GB = eval_with_gradient(b, db, u + du, v + dv);
        double ns = fabs(GA.x) + fabs(GB.x);
        if (!(ns < size)) break;
        u += du; v += dv; A = GA; B = GB; size = ns;
    }
    return (double2)(u, v);
}

// ---------------------------------------------------------------- path space
// derivative of normalize(x) along d, given unit = x / |x| and 1 / |x| (vec3.tangent_derivative_by_inverse)
static vec tangent_derivative(vec unit, vec d, double inverse_length) { return (d - vdot(unit, d) * unit) * inverse_length; }

typedef struct { vec p0, e1, e2, n0, m1, m2, ng, x0, x2; int refract; double eta; } Tuple;

// scatter_residual: residual wo - expected(wi, n̂) and its (u, v) Jacobian; returns ok.
static int scatter_residual(const Tuple *T, double u, double v, vec *res, vec *ju, vec *jv) {
    vec di = (T->p0 - T->x0) + u * T->e1 + v * T->e2;
    vec dov = (T->x2 - T->p0) - u * T->e1 - v * T->e2;
    vec n = T->n0 + u * T->m1 + v * T->m2;
    double ln = vlength(n), li = vlength(di), lo = vlength(dov);
    if (!(ln > 0.0 && li > 0.0 && lo > 0.0)) return 0;
    vec nh = n / ln, wi = di / li, wo = dov / lo;
    vec ng = vdot(T->ng, nh) >= 0.0 ? T->ng : -T->ng;
    double side_in = -vdot(di, ng), side_out = vdot(dov, ng);
    if (side_in == 0.0 || side_out == 0.0) return 0;
    if (T->refract == (side_in * side_out > 0.0)) return 0;
    double s = side_in > 0.0 ? 1.0 : -1.0;
    vec no = s * nh;
    double c = -vdot(wi, no);
    if (!(c > 0.0)) return 0;
    double r = 1.0, sk = 0.0;
    vec expected;
    if (T->refract) {
        r = s > 0.0 ? 1.0 / T->eta : T->eta;
        double k = 1.0 - r * r * (1.0 - c * c);
        if (!(k > 1e-24)) return 0;
        sk = sqrt(k);
        expected = r * wi + (r * c - sk) * no;
    } else {
        expected = wi + 2.0 * c * no;
    }
    *res = wo - expected;
    for (int axis = 0; axis < 2; ++axis) {
        vec d = axis == 0 ? T->e1 : T->e2;
        vec dm = axis == 0 ? T->m1 : T->m2;
        vec dwi = tangent_derivative(wi, d, 1.0 / li);
        vec dwo = -tangent_derivative(wo, d, 1.0 / lo);
        vec dno = s * tangent_derivative(nh, dm, 1.0 / ln);
        double dc = -(vdot(dwi, no) + vdot(wi, dno));
        vec dexp;
        if (T->refract) {
            double dsk = r * r * c * dc / sk;
            dexp = r * dwi + (r * dc - dsk) * no + (r * c - sk) * dno;
        } else {
            dexp = dwi + 2.0 * dc * no + 2.0 * c * dno;
        }
        if (axis == 0) *ju = dwo - dexp; else *jv = dwo - dexp;
    }
    return 1;
}

// polish_and_validate: returns accepted; writes u, v, err, sigma_min.
// (max_first_step, known_u, known_v, return_radius: paths/one_vertex.py
// polish_validate_normal_matrix's; INFINITY and 0 outside the candidate polish and the probes)
static int polish_and_validate(const Tuple *T, double *pu, double *pv, double *perr, double *psig, double max_first_step,
                               double known_u, double known_v, double return_radius) {
    double u = *pu, v = *pv;
    vec res, ju, jv;
    if (!scatter_residual(T, u, v, &res, &ju, &jv)) { *perr = INFINITY; *psig = 0.0; return 0; }
    double err = vlength(res), last_step = INFINITY;
    for (int it = 0; it < POLISH_STEPS; ++it) {
        if (err < 1e-15) { last_step = 0.0; break; }
        double a11 = vdot(ju, ju), a12 = vdot(ju, jv), a22 = vdot(jv, jv);
        double b1 = -vdot(ju, res), b2 = -vdot(jv, res);
        double det = a11 * a22 - a12 * a12;
        if (!(fabs(det) > 1e-300)) break;
        double du = (b1 * a22 - b2 * a12) / det, dv = (a11 * b2 - a12 * b1) / det;
        if (last_step == INFINITY && !(fmax(fabs(du), fabs(dv)) <= max_first_step)) {
            *perr = FAR_START; *psig = 0.0; return 0;
        }
        last_step = fmax(fabs(du), fabs(dv));
        if (fmax(fabs(u + du - known_u), fabs(v + dv - known_v)) < return_radius) {  // heading back to the known path
            *pu = u + du; *pv = v + dv; *perr = RETURNED; *psig = 0.0; return 0;
        }
        if (err <= FLOOR_RESIDUAL && last_step <= FLOOR_STEP) { u += du; v += dv; break; }  // at the rounding floor
        vec res2, ju2, jv2;
        if (!scatter_residual(T, u + du, v + dv, &res2, &ju2, &jv2)) break;
        double err2 = vlength(res2);
        if (!(err2 < err)) break;
        u += du; v += dv; res = res2; ju = ju2; jv = jv2; err = err2;
    }
    int inside = u >= -INSIDE_EPSILON && v >= -INSIDE_EPSILON && u + v <= 1.0 + INSIDE_EPSILON;
    int settled = last_step <= SETTLED_STEP;
    double a11 = vdot(ju, ju), a12 = vdot(ju, jv), a22 = vdot(jv, jv);
    double half_gap = sqrt(fmax(0.0, 0.25 * (a11 - a22) * (a11 - a22) + a12 * a12));
    *psig = sqrt(fmax(0.0, 0.5 * (a11 + a22) - half_gap));
    *pu = u; *pv = v; *perr = err;
    return inside && (err <= ACCEPT_RESIDUAL || (settled && err <= DIRECTION_TOLERANCE));
}

typedef struct { double u[8], v[8], err[8], sig[8]; int count; } Paths;

static void store_path(Paths *out, double uu, double vv, double err, double sig) {
    int n = min(out->count, 8);
    for (int q = 0; q < n; ++q) {
        double dist = fmax(fabs(out->u[q] - uu), fabs(out->v[q] - vv));
        double s = fmin(sig, out->sig[q]);
        double radius = s > 0.0 ? fmax(SAME_PATH, 4.0 * (err + out->err[q] + 1e-12) / s) : NEAR_PATH;
        if (dist < fmin(radius, NEAR_PATH)) {
            if (err < out->err[q]) { out->u[q] = uu; out->v[q] = vv; out->err[q] = err; out->sig[q] = sig; }
            return;
        }
    }
    if (out->count < 8) { int c = out->count; out->u[c] = uu; out->v[c] = vv; out->err[c] = err; out->sig[c] = sig; }
    out->count++;
}

static void probe_fold(const Tuple *T, double u, double v, Paths *out) {
    vec res, ju, jv;
    if (!scatter_residual(T, u, v, &res, &ju, &jv)) return;
    double a11 = vdot(ju, ju), a12 = vdot(ju, jv), a22 = vdot(jv, jv);
    double disc = sqrt(fmax(0.0, 0.25 * (a11 - a22) * (a11 - a22) + a12 * a12));
    double lam_min = 0.5 * (a11 + a22) - disc, lam_max = 0.5 * (a11 + a22) + disc;
    if (!(lam_max > 0.0) || lam_min > FOLD_RATIO * lam_max) return;
    double su, sv;
    if (fabs(a12) > 0.0) { su = a12; sv = lam_min - a11; }
    else if (a11 <= a22) { su = 1.0; sv = 0.0; }
    else { su = 0.0; sv = 1.0; }
    double ls = sqrt(su * su + sv * sv);
    su /= ls; sv /= ls;
    const double steps[3] = {1e-5, 1e-4, 1e-3};
    for (int k = 0; k < 6; ++k) {
        double step = steps[k / 2] * ((k % 2 == 0) ? 1.0 : -1.0);
        double uu = u + step * su, vv = v + step * sv, err, sig;
        if (polish_and_validate(T, &uu, &vv, &err, &sig, INFINITY, u, v, PROBE_RETURN * steps[k / 2]))
            store_path(out, uu, vv, err, sig);
    }
}

// one_bounce.py _singular_point_near_triangle: whether the conic a has a singular point (where a
// path at normal incidence lies) within SINGULAR_MARGIN of the triangle; 1 when it cannot tell
static int singular_point_near_triangle(const double *a) {
    double h11 = 2.0 * BI(a, 2, 2, 0), h12 = BI(a, 2, 1, 1), h22 = 2.0 * BI(a, 2, 0, 2);
    double det = h11 * h22 - h12 * h12;
    if (!(fabs(det) > 1e-12 * (h11 * h11 + h12 * h12 + h22 * h22))) return 1;
    double u = (-BI(a, 2, 1, 0) * h22 + BI(a, 2, 0, 1) * h12) / det;
    double v = (-BI(a, 2, 0, 1) * h11 + BI(a, 2, 1, 0) * h12) / det;
    return u >= -SINGULAR_MARGIN && v >= -SINGULAR_MARGIN && u + v <= 1.0 + SINGULAR_MARGIN;
}

static void on_axis_candidate(const Tuple *T, Paths *out, int *candidates) {
    vec w = T->x2 - T->x0;
    double denom = vdot(w, T->ng);
    if (denom == 0.0) return;
    double t = vdot(T->p0 - T->x0, T->ng) / denom;
    vec rel = (T->x0 + t * w) - T->p0;
    double d11 = vdot(T->e1, T->e1), d12 = vdot(T->e1, T->e2), d22 = vdot(T->e2, T->e2);
    double r1 = vdot(rel, T->e1), r2 = vdot(rel, T->e2), det = d11 * d22 - d12 * d12;
    if (!(det > 0.0)) return;
    double u = (r1 * d22 - r2 * d12) / det, v = (d11 * r2 - d12 * r1) / det;
    if (u < -1e-6 || v < -1e-6 || u + v > 1.0 + 1e-6) return;
    vec n = T->n0 + u * T->m1 + v * T->m2;
    double ln = vlength(n), lw = vlength(w);
    if (!(ln > 0.0 && lw > 0.0) || vlength(vcross(n, w)) > 1e-2 * ln * lw) return;
    (*candidates)++;
    double err, sig;
    if (polish_and_validate(T, &u, &v, &err, &sig, INFINITY, 0.0, 0.0, 0.0)) store_path(out, u, v, err, sig);
}

// one_bounce.py _row_sums: (sum_j p_ij v^j, sum_j |p_ij| |v|^j), row i of p at v and its terms' size
static double2 row_sums(const double *p, int d, int i, double v) {
    double value = 0.0, size = 0.0;
    for (int j = d - i; j >= 0; --j) {
        value = value * v + BI(p, d, i, j);
        size = size * fabs(v) + fabs(BI(p, d, i, j));
    }
    return (double2)(value, size);
}

// one_bounce.py _relative_size: |p(u, v)| / sum |p_ij u^i v^j| (p of total degree d)
static double relative_size(const double *p, int d, double u, double v) {
    double value = 0.0, size = 0.0, u_power = 1.0;
    for (int i = 0; i <= d; ++i) {
        double2 r = row_sums(p, d, i, v);
        value += r.x * u_power;
        size += r.y * fabs(u_power);
        u_power *= u;
    }
    return size > 0.0 ? fabs(value) / size : 0.0;
}

// one_bounce.py _rows_at_v: row_sums of every row at v, for several u at one v
static void rows_at_v(const double *p, int d, double v, double *row_value, double *row_size) {
    for (int i = 0; i <= d; ++i) {
        double2 r = row_sums(p, d, i, v);
        row_value[i] = r.x;
        row_size[i] = r.y;
    }
}

// one_bounce.py _relative_size_from_rows: relative_size at (u, v) from rows_at_v's rows at v
static double relative_size_from_rows(const double *row_value, const double *row_size, int d, double u) {
    double value = 0.0, size = 0.0, u_power = 1.0;
    for (int i = 0; i <= d; ++i) {
        value += row_value[i] * u_power;
        size += row_size[i] * fabs(u_power);
        u_power *= u;
    }
    return size > 0.0 ? fabs(value) / size : 0.0;
}

// one_bounce.py double_point_v: v of the point where the line g = 0 meets the conic a = 0 and
// d0.t = d1.t = 0 (the resultant's spurious double root for T, simple root for R), or NaN.
static double double_point_v(const double *a, const double *f3, const double *g) {
    double gu = BI(g, 2, 1, 0), gv = BI(g, 2, 0, 1), g0 = BI(g, 2, 0, 0);
    if (!(fabs(gu) > 1e-8 * (fabs(g0) + fabs(gv)))) return NAN;
    double a20 = BI(a, 2, 2, 0);
    double d2 = a20 * gv * gv - BI(a, 2, 1, 1) * gv * gu + BI(a, 2, 0, 2) * gu * gu;
    double d1 = 2.0 * a20 * g0 * gv - (BI(a, 2, 1, 0) * gv + BI(a, 2, 1, 1) * g0) * gu + BI(a, 2, 0, 1) * gu * gu;
    double d0 = a20 * g0 * g0 - BI(a, 2, 1, 0) * g0 * gu + BI(a, 2, 0, 0) * gu * gu;
    double best = NAN, best_size = DOUBLE_POINT_F3;
    for (int k = 0; k < 2; ++k) {
        double v;
        if (d2 == 0.0) {
            if (k == 1 || d1 == 0.0) break;
            v = -d0 / d1;
        } else {
            double disc = d1 * d1 - 4.0 * d2 * d0;
            if (disc < 0.0) break;
            double q = -0.5 * (d1 + copysign(sqrt(disc), d1));
            if (k == 0) v = q / d2;
            else if (q != 0.0) v = d0 / q;
            else break;
        }
        double u = -(g0 + gv * v) / gu;
        double size = relative_size(f3, 2, u, v);
        if (isfinite(v) && size < best_size) { best = v; best_size = size; }
    }
    return best;
}

// _solve_system: roots of {a = 0, b = 0} in the triangle -> validated paths.
static void solve_system(const Tuple *T, const double *a_poly, double max_a, double *b_poly, int total_b, double v_double,
                         Paths *out,
                         int *n_roots, int *n_candidates) {
    double max_b = bmax(b_poly, total_b);
    if (!(max_b > 0.0) || !isfinite(max_b)) return;
    int nb = total_b;
    while (nb > 0) {
        double big = 0.0;
        for (int j = 0; j <= total_b - nb; ++j) big = fmax(big, fabs(BI(b_poly, total_b, nb, j)));
        if (big > NEGLIGIBLE * max_b) break;
        for (int j = 0; j <= total_b - nb; ++j) BI(b_poly, total_b, nb, j) = 0.0;
        nb--;
    }
    double chain[CHAIN_SIZE];
    double stack[STACK + 1][MAXD + 4];
    double v_roots[MAX_V_ROOTS], critical[MAXD + 1], found[MAXD + 1];
    int n_v;
    if (nb == 0) {
        // b free of u: its own roots in v
        double res[UNI];
        int deg_r = total_b;
        for (int k = 0; k <= deg_r; ++k) res[k] = BI(b_poly, total_b, 0, k);
        shift_to_unit_interval(res, deg_r, -V_MARGIN, 1.0 + 2.0 * V_MARGIN);
        n_v = roots_in_unit_interval(res, deg_r, ROOT_X_TOLERANCE, ROOT_TOUCH_TOLERANCE, chain, critical, found, stack, v_roots);
        for (int iv = 0; iv < n_v; ++iv) v_roots[iv] = -V_MARGIN + (1.0 + 2.0 * V_MARGIN) * v_roots[iv];
    } else {
        // R and T: the resultant from its values at the Chebyshev nodes (the square form's
        // expansion cancels where b is small along the conic next to a path: grazing
        // refractions; for R the nine values cost less than the symbolic expansion)
        // the double point divides the resultant of the untrimmed b only
        n_v = resultant_v_roots(a_poly, b_poly, nb, total_b, nb == total_b ? v_double : NAN, chain, critical, found, stack,
                                v_roots);
    }
    *n_roots += n_v;
    double u_roots[MAXD + 1], b_at_v[MAXD + 1], row_value[7], row_size[7];
    for (int iv = 0; iv < n_v; ++iv) {
        double vr = v_roots[iv];
        int rows_at_vr = 0;  // row_value / row_size hold b(., vr) (rows_at_v), computed when first needed
        double a2 = BI(a_poly, 2, 2, 0), a1 = BI(a_poly, 2, 1, 0) + BI(a_poly, 2, 1, 1) * vr;
        double a0 = BI(a_poly, 2, 0, 0) + (BI(a_poly, 2, 0, 1) + BI(a_poly, 2, 0, 2) * vr) * vr;
        double u_hi = 1.0 - vr + V_MARGIN;
        int n_u;
        if (fabs(a2) + fabs(a1) > 1e-10 * max_a) {
            n_u = 0;
            if (a2 == 0.0) {
                double uu = -a0 / a1;
                if (uu >= -V_MARGIN && uu <= u_hi) u_roots[n_u++] = uu;
            } else {
                double disc = a1 * a1 - 4.0 * a2 * a0;
                if (disc < 0.0 && disc >= -1e-12 * (a1 * a1 + fabs(4.0 * a2 * a0))) disc = 0.0;
                if (disc >= 0.0) {
                    // both real u-roots of a(., v*), then those in range (one_bounce.py _solve_system)
                    double sq = sqrt(disc);
                    double q = a1 >= 0.0 ? -0.5 * (a1 + sq) : -0.5 * (a1 - sq);
                    double all_u[2];
                    int n_all = 0;
                    double r1 = q / a2;
                    if (r1 >= -INFINITY && r1 <= INFINITY) all_u[n_all++] = r1;
                    if (q != 0.0) {
                        double r2 = a0 / q;
                        if (r2 >= -INFINITY && r2 <= INFINITY && (n_all == 0 || r2 != r1)) all_u[n_all++] = r2;
                    }
                    // an in-range u-root where b is clearly nonzero while the other u-root accounts
                    // for the resultant's root is no root of the system, skipped
                    for (int k = 0; k < n_all; ++k) {
                        if (!(all_u[k] >= -V_MARGIN && all_u[k] <= u_hi)) continue;
                        if (n_all == 2) {
                            if (!rows_at_vr) { rows_at_v(b_poly, total_b, vr, row_value, row_size); rows_at_vr = 1; }
                            if (relative_size_from_rows(row_value, row_size, total_b, all_u[k]) > SPURIOUS_B &&
                                relative_size_from_rows(row_value, row_size, total_b, all_u[1 - k]) <= SPURIOUS_B) continue;
                        }
                        u_roots[n_u++] = all_u[k];
                    }
                }
            }
        } else {
            for (int i = 0; i <= nb; ++i) {
                double acc = 0.0;
                for (int j = total_b - i; j >= 0; --j) acc = acc * vr + BI(b_poly, total_b, i, j);
                b_at_v[i] = acc;
            }
            n_u = roots_in_interval(b_at_v, nb, -V_MARGIN, u_hi, ROOT_X_TOLERANCE, ROOT_TOUCH_TOLERANCE, chain, critical, found, u_roots);
        }
        for (int iu = 0; iu < n_u; ++iu) {
            (*n_candidates)++;
            double uu = u_roots[iu], vv = vr, err, sig;
            int ok = polish_and_validate(T, &uu, &vv, &err, &sig, CANDIDATE_REACH, 0.0, 0.0, 0.0);
            // the polynomial fallback, for a candidate rejected as far from any path only when it
            // is an inexact root of the system (one_bounce.py _solve_system)
            if (!ok && err == FAR_START && !rows_at_vr) { rows_at_v(b_poly, total_b, vr, row_value, row_size); rows_at_vr = 1; }
            if (!ok && (err != FAR_START || relative_size_from_rows(row_value, row_size, total_b, u_roots[iu]) > INEXACT_ROOT)) {
                double2 r = refine_on_polynomials(a_poly, b_poly, total_b, u_roots[iu], vr);
                uu = r.x; vv = r.y;
                ok = polish_and_validate(T, &uu, &vv, &err, &sig, CANDIDATE_REACH, 0.0, 0.0, 0.0);
            }
            if (!ok) continue;
            int before = out->count;
            store_path(out, uu, vv, err, sig);
            if (out->count == before) continue;
            probe_fold(T, uu, vv, out);
        }
    }
}

static vec load3(__global const double *a, long i) { return (vec)(a[3 * i], a[3 * i + 1], a[3 * i + 2]); }

static double fold_free_size(double g0, double g1, double g2) {
    if ((g0 > 0.0 && g1 > 0.0 && g2 > 0.0) || (g0 < 0.0 && g1 < 0.0 && g2 < 0.0)) return fmin(fabs(g0), fmin(fabs(g1), fabs(g2)));
    return 0.0;
}

// one_bounce.py elimination_labelling: 0 = (p0, p1, p2), 1 = (p0, p2, p1), 2 = (p1, p2, p0)
static int elimination_labelling(const Tuple *T) {
    vec w = T->x2 - T->x0;
    vec c0 = vcross(T->p0 - T->x0, w), c1 = vcross(T->e1, w), c2 = vcross(T->e2, w);
    double a20 = vdot(c1, T->m1), a02 = vdot(c2, T->m2), a11 = vdot(c1, T->m2) + vdot(c2, T->m1);
    double a10 = vdot(c0, T->m1) + vdot(c1, T->n0), a01 = vdot(c0, T->m2) + vdot(c2, T->n0);
    double du0 = a10, du1 = a10 + 2.0 * a20, du2 = a10 + a11;
    double dv0 = a01, dv1 = a01 + a11, dv2 = a01 + 2.0 * a02;
    double score_u = fabs(a20) + fold_free_size(du0, du1, du2);
    double score_v = fabs(a02) + fold_free_size(dv0, dv1, dv2);
    double score_s = fabs(a20 - a11 + a02) + fold_free_size(dv0 - du0, dv1 - du1, dv2 - du2);
    double best = fmax(score_v, score_s);
    if (!(score_u < SWITCH_RATIO * best)) return 0;
    return score_v >= score_s ? 1 : 2;
}

// The original corners of a tuple's triangle (positions q, shading normals k), kept so that a
// relabelled tuple is built from them exactly as one_bounce.py builds it.
typedef struct { vec q0, q1, q2, k0, k1, k2; } Corners;

// One tuple, as one_bounce.py _solve_one: the side tests, the corner labelling, the
// coplanarity conic a(u, v) (eq 6) and its triangle test, then the resultant in u and the
// roots (eq 10, 13, 28-31).  Returns 0 when the tuple is skipped (no path can exist), 1 when it
// needs the solve.  With solve == 0 it stops there (the filter stage: only the cheap set-up
// runs, so the expensive solve can be run over the surviving tuples alone, in full warps);
// with solve == 1 it solves, the paths in *out in the caller's corner order.
static int one_bounce_tuple(const Corners *C0, const int refract, const int solve, Tuple *T0, Paths *out,
                            int *n_roots, int *n_candidates) {
    Tuple T = *T0;
    T.p0 = C0->q0; T.e1 = C0->q1 - C0->q0; T.e2 = C0->q2 - C0->q0;
    T.n0 = C0->k0; T.m1 = C0->k1 - C0->k0; T.m2 = C0->k2 - C0->k0;
    T.refract = refract;
    int labelling = 0;
    vec g = vcross(T.e1, T.e2);
    double area2 = vlength(g);
    T.ng = area2 > 0.0 ? g / area2 : g;
    double len = fmax(vlength(T.e1), vlength(T.e2));
    double side0 = vdot(T.x0 - T.p0, T.ng), side2 = vdot(T.x2 - T.p0, T.ng);
    vec n_mean = 3.0 * T.n0 + T.m1 + T.m2;
    double tiny = 1e-12 * len;
    if (!(area2 > 1e-14 * len * len) || !(T.eta > 0.0) || fabs(side0) <= tiny || fabs(side2) <= tiny ||
        ((side0 * side2 < 0.0) != refract) || vlength(n_mean) == 0.0)
        return 0;
    // the corner labelling of one_bounce.py's elimination_labelling: u is eliminated along the
    // triangle edge where the coplanarity conic does not fold
    labelling = elimination_labelling(&T);
    if (labelling != 0) {
        if (labelling == 1) {  // (p0, p2, p1)
            T.e1 = C0->q2 - C0->q0; T.e2 = C0->q1 - C0->q0; T.m1 = C0->k2 - C0->k0; T.m2 = C0->k1 - C0->k0;
        } else {  // (p1, p2, p0)
            T.p0 = C0->q1; T.e1 = C0->q2 - C0->q1; T.e2 = C0->q0 - C0->q1;
            T.n0 = C0->k1; T.m1 = C0->k2 - C0->k1; T.m2 = C0->k0 - C0->k1;
        }
        g = vcross(T.e1, T.e2);
        area2 = vlength(g);
        T.ng = area2 > 0.0 ? g / area2 : g;
        len = fmax(vlength(T.e1), vlength(T.e2));
        side0 = vdot(T.x0 - T.p0, T.ng);
        side2 = vdot(T.x2 - T.p0, T.ng);
        n_mean = 3.0 * T.n0 + T.m1 + T.m2;
    }
    double inv_l = 1.0 / len;
    vec E1 = T.e1 * inv_l, E2 = T.e2 * inv_l, A = (T.x0 - T.p0) * inv_l, B = (T.x2 - T.p0) * inv_l;
    vec w = B - A;
    vec C = vcross(w, n_mean);
    if (!(vlength(C) > 1e-9 * vlength(w) * vlength(n_mean))) C = vcross(E1, n_mean);
    C = C / vlength(C);
    vec minus_a = -A;
    double a_poly[BIV2];
    lin_dot(a_poly, vcross(minus_a, w), vcross(E1, w), vcross(E2, w), T.n0, T.m1, T.m2);
    double max_a = bmax(a_poly, 2);
    if (!isfinite(max_a)) return 0;
    int on_axis = max_a <= 1e-13 * (vlength(A) + 1.0) * vlength(w) * (vlength(T.n0) + vlength(T.m1) + vlength(T.m2));
    if (!on_axis) {
        for (int i = 0; i < 3; ++i) for (int j = 0; j < 3 - i; ++j) if (fabs(BI(a_poly, 2, i, j)) <= NEGLIGIBLE * max_a) BI(a_poly, 2, i, j) = 0.0;
        if (conic_misses_triangle(a_poly, max_a)) return 0;
    }
    if (!solve) return 1;
    if (on_axis) {
        on_axis_candidate(&T, out, n_candidates);
    } else {
        vec zero = (vec)(0.0, 0.0, 0.0);
        vec t0 = vcross(T.n0, C), tu = vcross(T.m1, C), tv = vcross(T.m2, C);
        double f1[BIV2], f3[BIV2], g2[BIV2], h[BIV2];
        lin_dot(f1, minus_a, E1, E2, T.n0, T.m1, T.m2);
        lin_dot(f3, minus_a, E1, E2, t0, tu, tv);
        lin_dot(g2, w, zero, zero, t0, tu, tv);
        lin_dot(h, w, zero, zero, T.n0, T.m1, T.m2);
        double v_double = double_point_v(a_poly, f3, g2);
        if (!(v_double >= -DOUBLE_POINT_REACH && v_double <= 1.0 + DOUBLE_POINT_REACH)) v_double = NAN;
        if (!refract) {
            double t1[BIV4], t2[BIV4], t3[BIV4], b_poly[BIV4];
            bmul(f1, 2, g2, 2, t1);
            bmul(f3, 2, h, 2, t2);
            bmul(f1, 2, f3, 2, t3);
            for (int i = 0; i < 5; ++i) for (int j = 0; j < 5 - i; ++j)
                BI(b_poly, 4, i, j) = BI(t1, 4, i, j) + BI(t2, 4, i, j) - 2.0 * BI(t3, 4, i, j);
            solve_system(&T, a_poly, max_a, b_poly, 4, v_double, out, n_roots, n_candidates);
            if (singular_point_near_triangle(a_poly)) on_axis_candidate(&T, out, n_candidates);
        } else {
            double t6[BIV6], t7[BIV6], b_poly[BIV6];
            {  // the factors, scoped so that their private memory is reused by the solve
                double t1[BIV2], t2[BIV2], t3[BIV4], t4[BIV2], t5[BIV4];
                lin_dot(t1, minus_a, E1, E2, minus_a, E1, E2);
                lin_dot(t2, B, -E1, -E2, B, -E1, -E2);
                bmul(f3, 2, f3, 2, t3);
                bcombine(t4, 2, 1.0, g2, -1.0, f3);
                bmul(t4, 2, t4, 2, t5);
                bmul(t2, 2, t3, 4, t6);
                bmul(t1, 2, t5, 4, t7);
            }
            double s0 = vdot(T.ng, T.n0), s1 = vdot(T.ng, T.n0 + T.m1), s2 = vdot(T.ng, T.n0 + T.m2);
            int any_front = s0 > 0.0 || s1 > 0.0 || s2 > 0.0, any_back = s0 < 0.0 || s1 < 0.0 || s2 < 0.0;
            for (int pass = 0; pass < 2; ++pass) {
                int outward = pass == 0;
                if ((outward && !any_front) || (!outward && !any_back)) continue;
                int from_outside = (side0 > 0.0) == outward;
                double eta_in = from_outside ? 1.0 : T.eta, eta_out = from_outside ? T.eta : 1.0;
                bcombine(b_poly, 6, eta_in * eta_in, t6, -eta_out * eta_out, t7);
                solve_system(&T, a_poly, max_a, b_poly, 6, v_double, out, n_roots, n_candidates);
            }
            if (singular_point_near_triangle(a_poly)) on_axis_candidate(&T, out, n_candidates);
        }
    }
    for (int q = 0; q < min(out->count, 8); ++q) {
        double up = out->u[q], vp = out->v[q];
        if (labelling == 1) { out->u[q] = vp; out->v[q] = up; }
        else if (labelling == 2) { out->u[q] = 1.0 - up - vp; out->v[q] = up; }
    }
    return 1;
}

// The kernel's stages: WHOLE solves every tuple and appends its paths to the output with an
// atomic counter (CPU devices, where a work-item that leaves early costs its neighbours nothing;
// the host sorts the paths).  On GPUs the work is split so that warps solve in full and the
// output comes out in canonical order: FILTER runs the set-up of every tuple and flags those
// that need the solve; the flags' prefix sums (scan.cl) place the survivors, in tuple order
// (scatter_survivors); SOLVE solves survivor i into slots i (its paths sorted by (u, v) as
// paths/order.py sorts them) and writes their count; the counts' prefix sums place the records
// (gather_paths), so the paths arrive sorted by tuple, then u, then v.
#define STAGE_WHOLE 0
#define STAGE_FILTER 1
#define STAGE_SOLVE 2
#define SLOTS 8

// Tuple t's inputs: x_start, P, N, eta at row e and x_end at row s, where (e, s) = (t, t), or
// (tuple_e[t], tuple_s[t]) when `paired` (a device-resident table of emitters and one of receiver
// points, addressed by index pairs: only 8 bytes per tuple cross to the device).  A pair outside
// the tables (rows_e emitters, rows_s points) is not read: it is counted in acc[1 + 5 n_slots]
// and the host refuses the call, so the host need not scan the pairs first.
//
// WHOLE: a tuple's stored paths (at most 8) take consecutive records from the atomic counter
// acc[0] (records past `capacity` are counted but not written: the host grows the buffers and runs
// again), in whatever order the work-items get there.  All stages sum the statistics into
// acc[1 + 5 s .. 5 + 5 s] (roots, candidates, paths, skipped, tuples with more than 8 paths) for
// slot s = t % n_slots, so that no single counter takes every work-item's atomic.
// FILTER: flags[t] = 1 when tuple t needs the solve, else 0.
// SOLVE: work-item i < count (= counts[count_at], the survivors) solves tuple list[i] into
// slot_uv[SLOTS i ..] and writes slot_count[i]; work-items count <= i < n write slot_count[i] = 0.
__kernel void solve_one_bounce(const int refract, const int stage, const int paired,
                               __global const int *tuple_e, __global const int *tuple_s, const int rows_e,
                               const int rows_s,
                               __global const double *x_start, __global const double *x_end,
                               __global const double *P, __global const double *N, __global const double *eta,
                               const int n, const int first, const int capacity, const int n_slots,
                               __global int *acc, __global int *path_tuple, __global double *path_uv,
                               __global int *list, __global const int *counts, const int count_at,
                               __global double *slot_uv, __global int *slot_count) {
    int gid = get_global_id(0);
    if (gid >= n) return;
    int t = gid;
    if (stage == STAGE_SOLVE) {
        if (gid >= counts[count_at]) { slot_count[gid] = 0; return; }
        t = list[gid];
    }
    long e = paired ? (long)tuple_e[t] : (long)t, s = paired ? (long)tuple_s[t] : (long)t;
    if (paired && (e < 0 || e >= rows_e || s < 0 || s >= rows_s)) {
        if (stage == STAGE_FILTER) list[t] = 0;
        if (stage != STAGE_SOLVE) atomic_add(acc + 1 + 5 * n_slots, 1);
        return;
    }
    Corners C0;
    C0.q0 = load3(P, 3L * e); C0.q1 = load3(P, 3L * e + 1); C0.q2 = load3(P, 3L * e + 2);
    C0.k0 = load3(N, 3L * e); C0.k1 = load3(N, 3L * e + 1); C0.k2 = load3(N, 3L * e + 2);
    Tuple T;
    T.x0 = load3(x_start, e);
    T.x2 = load3(x_end, s);
    T.eta = eta[e];
    Paths out;
    out.count = 0;
    int n_roots = 0, n_candidates = 0;
    __global int *sum = acc + 1 + 5 * (t % n_slots);
    int needs = one_bounce_tuple(&C0, refract, stage != STAGE_FILTER, &T, &out, &n_roots, &n_candidates);
    if (stage == STAGE_FILTER) list[t] = needs;
    if (!needs) {
        atomic_add(sum + 3, 1);
        return;
    }
    if (stage == STAGE_FILTER) return;
    int stored = min(out.count, SLOTS);
    if (stage == STAGE_SOLVE) {
        // insertion sort by (u, v), stable: paths/order.py's order within a tuple
        for (int i = 1; i < stored; ++i)
            for (int j = i; j > 0 && (out.u[j] < out.u[j - 1] || (out.u[j] == out.u[j - 1] && out.v[j] < out.v[j - 1])); --j) {
                double tu = out.u[j], tv = out.v[j];
                out.u[j] = out.u[j - 1]; out.v[j] = out.v[j - 1];
                out.u[j - 1] = tu; out.v[j - 1] = tv;
            }
        for (int q = 0; q < stored; ++q) {
            slot_uv[2L * (SLOTS * (long)gid + q)] = out.u[q];
            slot_uv[2L * (SLOTS * (long)gid + q) + 1] = out.v[q];
        }
        slot_count[gid] = stored;
    } else if (stored > 0) {
        int base = atomic_add(acc, stored);
        for (int q = 0; q < stored && base + q < capacity; ++q) {
            path_tuple[base + q] = first + t;
            path_uv[2L * (base + q)] = out.u[q];
            path_uv[2L * (base + q) + 1] = out.v[q];
        }
    }
    if (n_roots) atomic_add(sum, n_roots);
    if (n_candidates) atomic_add(sum + 1, n_candidates);
    if (out.count) atomic_add(sum + 2, out.count);
    if (out.count > SLOTS) atomic_add(sum + 4, 1);
}

// survivors[pos[t]] = t for every flagged tuple (pos: the flags' exclusive prefix sums).
__kernel void scatter_survivors(__global const int *flags, __global const int *pos, __global int *survivors,
                                const int n) {
    int t = get_global_id(0);
    if (t < n && flags[t]) survivors[pos[t]] = t;
}

// Survivor i's slot_count[i] paths go to records offset[i] .. (offset: the counts' exclusive
// prefix sums; records past `capacity` are not written, the host grows the buffers and gathers
// again).
__kernel void gather_paths(const int first, __global const int *survivors, __global const int *counts,
                           const int count_at, __global const double *slot_uv, __global const int *slot_count,
                           __global const int *offset, const int capacity, __global int *path_tuple,
                           __global double *path_uv) {
    int i = get_global_id(0);
    if (i >= counts[count_at]) return;
    int c = slot_count[i], base = offset[i], t = first + survivors[i];
    for (int q = 0; q < c && base + q < capacity; ++q) {
        path_tuple[base + q] = t;
        path_uv[2L * (base + q)] = slot_uv[2L * (SLOTS * (long)i + q)];
        path_uv[2L * (base + q) + 1] = slot_uv[2L * (SLOTS * (long)i + q) + 1];
    }
}
