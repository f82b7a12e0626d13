// The univariate root finder of addon/solver/polynomials/roots.py in OpenCL C (Yuksel 2022,
// "High-Performance Polynomial Root Finding for Graphics": derivative isolation, Newton
// safeguarded by bisection), step for step, shared by one_bounce.cl and two_bounce.cl: the host
// pastes it where a program says `// @INCLUDE roots.cl@` (opencl/backend.py).  Coefficients in
// the power basis, c[i] multiplies x^i; the derivative chain `chain` is stored by rows of growing
// length (row k, the degree-k level, starts at k (k + 1) / 2): its caller sizes it for its degree.
#define CH(k) (chain + (k) * ((k) + 1) / 2)
#define NEWTON_ITERATIONS 64
#define NEWTON_QUADRATIC_RATIO 1e-3

// Numba's float ** int is binary exponentiation
static double ipow(double a, int n) {
    double r = 1.0;
    for (; n != 0; n >>= 1) { if (n & 1) r *= a; a *= a; }
    return r;
}

// ---------------------------------------------------------------- univariate helpers
static double horner(const double *c, int deg, double x) {
    double f = c[deg];
    for (int i = deg - 1; i >= 0; --i) f = f * x + c[i];
    return f;
}

static double2 horner_d(const double *c, int deg, double x) {
    double f = c[deg], df = 0.0;
    for (int i = deg - 1; i >= 0; --i) { df = df * x + f; f = f * x + c[i]; }
    return (double2)(f, df);
}

static double magnitude_at(const double *c, int deg, double x) {
    double ax = fabs(x), m = fabs(c[deg]);
    for (int i = deg - 1; i >= 0; --i) m = m * ax + fabs(c[i]);
    return m;
}

// roots.py _newton_settled: the Newton step is below tol, or quadratic convergence (a step
// NEWTON_QUADRATIC_RATIO times the previous one at most) puts the new iterate within tol
static int newton_settled(double step, double previous_step, double tol) {
    if (step <= tol) return 1;
    return step * NEWTON_QUADRATIC_RATIO * NEWTON_QUADRATIC_RATIO <= tol && step <= NEWTON_QUADRATIC_RATIO * previous_step;
}

// roots.py _solve_monotone_from: started at x_start when inside (a, b), else at the regula-falsi point
static double solve_monotone_from(const double *c, int deg, double a, double b, double fa, double fb, double x_start,
                                  double tol) {
    double x = x_start;
    if (!(x > a && x < b)) x = a - fa * (b - a) / (fb - fa);
    if (!(x > a && x < b)) x = 0.5 * (a + b);
    int neg_a = fa < 0.0;
    double previous_step = INFINITY;
    for (int it = 0; it < NEWTON_ITERATIONS; ++it) {
        double2 fd = horner_d(c, deg, x);
        double f = fd.x, df = fd.y;
        if (f == 0.0) return x;
        if ((f < 0.0) == neg_a) a = x; else b = x;
        double xn = (df != 0.0) ? x - f / df : 0.5 * (a + b);
        // converged: tested before the bracket test, as in roots.py _solve_monotone_from
        if (df != 0.0) {
            double step = fabs(xn - x);
            if (newton_settled(step, previous_step, tol) && xn >= a && xn <= b) return xn;
            previous_step = step;
        } else {
            previous_step = INFINITY;
        }
        if (!(xn > a && xn < b)) { xn = 0.5 * (a + b); previous_step = INFINITY; }
        if (fabs(xn - x) <= tol || b - a <= tol) return xn;
        x = xn;
    }
    return x;
}

static double solve_monotone(const double *c, int deg, double a, double b, double fa, double fb, double tol) {
    return solve_monotone_from(c, deg, a, b, fa, fb, NAN, tol);
}

static int quadratic_roots_in(double c0, double c1, double c2, double lo, double hi, double *out) {
    int n = 0;
    if (c2 == 0.0) {
        if (c1 != 0.0) { double x = -c0 / c1; if (x >= lo && x <= hi) { out[0] = x; n = 1; } }
        return n;
    }
    double disc = c1 * c1 - 4.0 * c2 * c0;
    if (disc < 0.0) {
        if (disc > -1e-14 * (c1 * c1 + fabs(4.0 * c2 * c0))) disc = 0.0; else return 0;
    }
    double sq = sqrt(disc);
    double q = (c1 >= 0.0) ? -0.5 * (c1 + sq) : -0.5 * (c1 - sq);
    double r1 = q / c2, r2 = (q != 0.0) ? c0 / q : r1;
    if (r1 > r2) { double t = r1; r1 = r2; r2 = t; }
    if (r1 >= lo && r1 <= hi) out[n++] = r1;
    if (r2 >= lo && r2 <= hi && (n == 0 || r2 != out[0])) out[n++] = r2;
    return n;
}

// Yuksel 2022: derivative isolation + safeguarded Newton (roots.roots_in_interval).
// roots.py _start_next_to_extremum: root of the quadratic model of chain level k at the extremum end
// of [a, b] (the one of smaller |p| if both are); NAN when the model has none.
static double start_next_to_extremum(const double *chain, int k, double a, double b, double fa, double fb,
                                     int a_is_extremum, int b_is_extremum) {
    int at_a = a_is_extremum && (!b_is_extremum || fabs(fa) <= fabs(fb));
    double x_m = at_a ? a : b, f_m = at_a ? fa : fb;
    double curvature = k * (k - 1) * horner(CH(k - 2), k - 2, x_m);
    if (!(f_m * curvature < 0.0)) return NAN;
    double half_width = sqrt(-2.0 * f_m / curvature);
    return at_a ? x_m + half_width : x_m - half_width;
}

// roots.py _derivative_isolation: roots_in_interval; convex: the second derivative keeps one sign on
// [lo, hi] (the isolation starts at the first derivative); model_start: Newton next to an extremum
// starts at the root of the quadratic model there.
static int derivative_isolation(const double *coeffs, int degree, double lo, double hi, double tol, double touch,
                                double *chain, double *critical, double *found, double *out, int convex,
                                int model_start) {
    double scale = fmax(fmax(fabs(lo), fabs(hi)), 1.0), norm = 0.0, p = 1.0;
    for (int i = 0; i <= degree; ++i) { norm = fmax(norm, fabs(coeffs[i]) * p); p *= scale; }
    if (norm == 0.0 || !isfinite(norm)) return 0;
    int deg = degree;
    p = ipow(scale, deg);
    while (deg > 0 && fabs(coeffs[deg]) * p <= 1e-15 * norm) { deg--; p /= scale; }
    if (deg == 0) return 0;
    double inv = 1.0 / norm;
    for (int i = 0; i <= deg; ++i) CH(deg)[i] = coeffs[i] * inv;
    if (deg <= 2) return quadratic_roots_in(CH(deg)[0], CH(deg)[1], deg == 2 ? CH(deg)[2] : 0.0, lo, hi, out);
    int shortcut = convex && deg >= 4;
    int first_level = shortcut ? deg - 1 : 3;
    for (int k = deg; k > first_level - 1; --k)
        for (int i = 0; i < k; ++i) CH(k - 1)[i] = CH(k)[i + 1] * (i + 1) / k;
    int n_critical = shortcut ? 0 : quadratic_roots_in(CH(2)[0], CH(2)[1], CH(2)[2], lo, hi, critical);
    for (int k = first_level; k <= deg; ++k) {
        const double *c = CH(k);
        int n_found = 0;
        double a = lo, fa = horner(c, k, a);
        for (int j = 0; j <= n_critical; ++j) {
            double b = (j < n_critical) ? critical[j] : hi;
            if (b <= a) continue;
            double fb = horner(c, k, b);
            if (fa == 0.0) {
                if (n_found == 0 || found[n_found - 1] != a) found[n_found++] = a;
            } else if (fb != 0.0 && ((fa < 0.0) != (fb < 0.0))) {
                double x_start = NAN;
                if (model_start && k >= 4 && (j > 0 || j < n_critical))
                    x_start = start_next_to_extremum(chain, k, a, b, fa, fb, j > 0, j < n_critical);
                found[n_found++] = solve_monotone_from(c, k, a, b, fa, fb, x_start, tol);
            } else if (k == deg && touch > 0.0 && j < n_critical && fb != 0.0) {
                if (fabs(fb) <= touch * magnitude_at(c, k, b)) found[n_found++] = b;
            }
            a = b; fa = fb;
        }
        if (fa == 0.0 && (n_found == 0 || found[n_found - 1] != a)) found[n_found++] = a;
        for (int j = 0; j < n_found; ++j) critical[j] = found[j];
        n_critical = n_found;
    }
    for (int j = 0; j < n_critical; ++j) out[j] = critical[j];
    return n_critical;
}

static int roots_in_interval(const double *coeffs, int degree, double lo, double hi, double tol, double touch,
                             double *chain, double *critical, double *found, double *out) {
    return derivative_isolation(coeffs, degree, lo, hi, tol, touch, chain, critical, found, out, 0, 0);
}
