// Two-vertex specular constraint in path space in OpenCL C: the same arithmetic, step for step, as
// addon/solver/paths/two_vertex.py (pack_geometry, two_vertex_residual, polish_and_validate2,
// trace_to_second) and line_crossing_barycentrics of addon/solver/paths/one_vertex.py, so both
// back ends polish and validate two-bounce paths alike (tests/solver/test_opencl_two_vertex.py).
// The residual is the two-bounce generalisation of eq (3) of Fan et al. 2024 (Specular
// Polynomials): per vertex, the outgoing unit direction minus the reflected / refracted incoming
// one (the module docstring of two_vertex.py),
//     r1 = normalize(x2 - x1) - scatter1(normalize(x1 - x0), n1)
//     r2 = normalize(x3 - x2) - scatter2(normalize(x2 - x1), n2)
// over theta = (u1, v1, u2, v2), with the side rules of CONTRACT.md per vertex.
//
// Pasted by the host into another program after
//     #pragma OPENCL EXTENSION cl_khr_fp64 : enable
//     #pragma OPENCL FP_CONTRACT OFF
// (double precision, no fused multiply-adds); it defines no kernel, and every name starts with
// tv_ / TV_.  All pointers are private except tv_pack_geometry's __global inputs.  geo is the
// packed geometry of pack_geometry: 15 rows x 3, row-major (45 doubles).
// The vector products are written out in the order of geometry/vec3.py (no built-in dot, cross,
// length, normalize, fma, mad: those may fuse or rescale), and max(a, b) as Numba's (b if b > a,
// else a: NaN handling as Python's, not fmax's).

#define TV_DIRECTION_TOLERANCE 1e-7  // |r_i| per vertex for an accepted path (contract)
#define TV_INSIDE_EPSILON 1e-9       // barycentric slack at triangle edges
#define TV_SETTLED_STEP 1e-9         // a Gauss-Newton step this small means the iterate has converged
#define TV_TIR_FLOOR 1e-24           // k = 1 - r^2 sin^2 below this counts as total internal reflection
#define TV_INF ((double)INFINITY)

typedef struct { double x, y, z; } tv3;

static tv3 tv_vec(double x, double y, double z) { tv3 r; r.x = x; r.y = y; r.z = z; return r; }
// vec3.row: row i of the packed geometry
static tv3 tv_row(const double *m, int i) { return tv_vec(m[3 * i], m[3 * i + 1], m[3 * i + 2]); }
static tv3 tv_sub(tv3 a, tv3 b) { return tv_vec(a.x - b.x, a.y - b.y, a.z - b.z); }
static tv3 tv_scale(tv3 a, double s) { return tv_vec(a.x * s, a.y * s, a.z * s); }
// vec3.madd: a + s b
static tv3 tv_madd(tv3 a, tv3 b, double s) { return tv_vec(a.x + s * b.x, a.y + s * b.y, a.z + s * b.z); }
static double tv_dot(tv3 a, tv3 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
static tv3 tv_cross(tv3 a, tv3 b) {
    return tv_vec(a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x);
}
static double tv_norm(tv3 a) { return sqrt(a.x * a.x + a.y * a.y + a.z * a.z); }
// vec3.tangent_derivative: derivative of normalize(x) along d, unit = x / |x|, length = |x|
static tv3 tv_tangent_derivative(tv3 unit, tv3 d, double length) {
    double s = tv_dot(unit, d);
    return tv_vec((d.x - s * unit.x) / length, (d.y - s * unit.y) / length, (d.z - s * unit.z) / length);
}
// @INCLUDE numba_math.cl@ (NB_MAX, NB_MIN)

// What _vertex returns besides ok: the residual and what its derivative needs.
typedef struct { tv3 res, wi, wo, nh; double li, lo, ln, s, c, r, sk; } tv_vertex_state;

// two_vertex.py _vertex: residual of one vertex (prev -> x -> nxt, unnormalised shading normal n,
// unit geometric normal ng_raw); returns ok.
static bool tv_vertex(tv3 prev, tv3 x, tv3 nxt, tv3 n, tv3 ng_raw, bool refract, double eta, tv_vertex_state *V) {
    tv3 di = tv_sub(x, prev);
    tv3 dov = tv_sub(nxt, x);
    double ln = tv_norm(n);
    double li = tv_norm(di);
    double lo = tv_norm(dov);
    if (!(ln > 0.0 && li > 0.0 && lo > 0.0)) return false;
    tv3 nh = tv_scale(n, 1.0 / ln);
    tv3 wi = tv_scale(di, 1.0 / li);
    tv3 wo = tv_scale(dov, 1.0 / lo);
    tv3 ng = tv_dot(ng_raw, nh) >= 0.0 ? ng_raw : tv_scale(ng_raw, -1.0);
    double side_in = -tv_dot(di, ng);
    double side_out = tv_dot(dov, ng);
    if (side_in == 0.0 || side_out == 0.0 || refract == (side_in * side_out > 0.0)) return false;
    double s = side_in > 0.0 ? 1.0 : -1.0;
    tv3 no = tv_scale(nh, s);
    double c = -tv_dot(wi, no);
    if (!(c > 0.0)) return false;
    double r, sk;
    tv3 expected;
    if (refract) {
        r = s > 0.0 ? 1.0 / eta : eta;
        double k = 1.0 - r * r * (1.0 - c * c);
        if (!(k > TV_TIR_FLOOR)) return false;
        sk = sqrt(k);
        expected = tv_madd(tv_scale(wi, r), no, r * c - sk);
    } else {
        r = 1.0;
        sk = 0.0;
        expected = tv_madd(wi, no, 2.0 * c);
    }
    V->res = tv_sub(wo, expected);
    V->wi = wi; V->wo = wo; V->nh = nh;
    V->li = li; V->lo = lo; V->ln = ln; V->s = s; V->c = c; V->r = r; V->sk = sk;
    return true;
}

// two_vertex.py _vertex_derivative: d(residual) when the incoming segment changes by ddi, the
// outgoing by ddo and the (unnormalised) normal by dn.
static tv3 tv_vertex_derivative(tv3 ddi, tv3 ddo, tv3 dn, const tv_vertex_state *V, bool refract) {
    tv3 no = tv_scale(V->nh, V->s);
    tv3 dwi = tv_tangent_derivative(V->wi, ddi, V->li);
    tv3 dwo = tv_tangent_derivative(V->wo, ddo, V->lo);
    tv3 dno = tv_scale(tv_tangent_derivative(V->nh, dn, V->ln), V->s);
    double dc = -(tv_dot(dwi, no) + tv_dot(V->wi, dno));
    double r = V->r, c = V->c, sk = V->sk;
    tv3 dexp;
    if (refract) {
        double dsk = r * r * c * dc / sk;
        dexp = tv_madd(tv_madd(tv_scale(dwi, r), no, r * dc - dsk), dno, r * c - sk);
    } else {
        dexp = tv_madd(tv_madd(dwi, no, 2.0 * dc), dno, 2.0 * c);
    }
    return tv_sub(dwo, dexp);
}

// two_vertex.py pack_geometry: fill geo (15 x 3, positions relative to triangle 1's first vertex:
// 0 x0, 1 x3, 2 e1,1, 3 e1,2, 4 n1,0, 5 m1,1, 6 m1,2, 7 p2,0, 8 e2,1, 9 e2,2, 10 n2,0, 11 m2,1,
// 12 m2,2, 13 / 14 the unit geometric normals of triangles 1 / 2).  P1, N1, P2, N2: 3 vertices x 3
// coordinates each (positions / vertex normals), row-major.  Returns false for a zero-area triangle.
static bool tv_pack_geometry(__global const double *x0, __global const double *x3, __global const double *P1,
                             __global const double *N1, __global const double *P2, __global const double *N2,
                             double *geo) {
    double o[3] = {P1[0], P1[1], P1[2]};
    for (int a = 0; a < 3; ++a) {
        geo[0 + a] = x0[a] - o[a];
        geo[3 + a] = x3[a] - o[a];
        geo[6 + a] = P1[3 + a] - P1[a];
        geo[9 + a] = P1[6 + a] - P1[a];
        geo[12 + a] = N1[a];
        geo[15 + a] = N1[3 + a] - N1[a];
        geo[18 + a] = N1[6 + a] - N1[a];
        geo[21 + a] = P2[a] - o[a];
        geo[24 + a] = P2[3 + a] - P2[a];
        geo[27 + a] = P2[6 + a] - P2[a];
        geo[30 + a] = N2[a];
        geo[33 + a] = N2[3 + a] - N2[a];
        geo[36 + a] = N2[6 + a] - N2[a];
    }
    bool ok = true;
    for (int t = 0; t < 2; ++t) {
        int ra = t == 0 ? 2 : 8;
        tv3 ea = tv_row(geo, ra);
        tv3 eb = tv_row(geo, ra + 1);
        tv3 g = tv_cross(ea, eb);
        double lg = tv_norm(g);
        double le = NB_MAX(tv_norm(ea), tv_norm(eb));
        if (!(lg > 1e-14 * le * le)) {
            ok = false;
            lg = 1.0;
        }
        geo[3 * (13 + t) + 0] = g.x / lg;
        geo[3 * (13 + t) + 1] = g.y / lg;
        geo[3 * (13 + t) + 2] = g.z / lg;
    }
    return ok;
}

// two_vertex.py two_vertex_residual: residual res (6) and Jacobian jac (6 x 4, row-major) at
// theta = th (4); returns ok (res and jac are written only when ok).
static bool tv_residual(const double *th, const double *geo, bool refract1, bool refract2, double eta, double *res,
                        double *jac) {
    const tv3 zero = tv_vec(0.0, 0.0, 0.0);
    // _unpack
    tv3 x0 = tv_row(geo, 0), x3 = tv_row(geo, 1), e11 = tv_row(geo, 2), e12 = tv_row(geo, 3), n10 = tv_row(geo, 4);
    tv3 m11 = tv_row(geo, 5), m12 = tv_row(geo, 6), p20 = tv_row(geo, 7), e21 = tv_row(geo, 8), e22 = tv_row(geo, 9);
    tv3 n20 = tv_row(geo, 10), m21 = tv_row(geo, 11), m22 = tv_row(geo, 12);
    tv3 ng1 = tv_row(geo, 13), ng2 = tv_row(geo, 14);
    tv3 x1 = tv_madd(tv_scale(e11, th[0]), e12, th[1]);
    tv3 x2 = tv_madd(tv_madd(p20, e21, th[2]), e22, th[3]);
    tv3 n1 = tv_madd(tv_madd(n10, m11, th[0]), m12, th[1]);
    tv3 n2 = tv_madd(tv_madd(n20, m21, th[2]), m22, th[3]);
    tv_vertex_state V1, V2;
    if (!tv_vertex(x0, x1, x2, n1, ng1, refract1, eta, &V1)) return false;
    if (!tv_vertex(x1, x2, x3, n2, ng2, refract2, eta, &V2)) return false;
    res[0] = V1.res.x; res[1] = V1.res.y; res[2] = V1.res.z;
    res[3] = V2.res.x; res[4] = V2.res.y; res[5] = V2.res.z;
    for (int p = 0; p < 4; ++p) {
        tv3 d1, dm1, d2, dm2;
        if (p == 0) { d1 = e11; dm1 = m11; d2 = zero; dm2 = zero; }
        else if (p == 1) { d1 = e12; dm1 = m12; d2 = zero; dm2 = zero; }
        else if (p == 2) { d1 = zero; dm1 = zero; d2 = e21; dm2 = m21; }
        else { d1 = zero; dm1 = zero; d2 = e22; dm2 = m22; }
        // vertex 1: incoming x1 - x0, outgoing x2 - x1, normal n1
        tv3 col1 = tv_vertex_derivative(d1, tv_sub(d2, d1), dm1, &V1, refract1);
        // vertex 2: incoming x2 - x1, outgoing x3 - x2, normal n2
        tv3 col2 = tv_vertex_derivative(tv_sub(d2, d1), tv_scale(d2, -1.0), dm2, &V2, refract2);
        jac[0 * 4 + p] = col1.x; jac[1 * 4 + p] = col1.y; jac[2 * 4 + p] = col1.z;
        jac[3 * 4 + p] = col2.x; jac[4 * 4 + p] = col2.y; jac[5 * 4 + p] = col2.z;
    }
    return true;
}

// two_vertex.py _solve4: the 4 x 4 system A x = b (row-major A; partial pivoting, A and b
// overwritten); false if singular.
static bool tv_solve4(double *A, double *b, double *out) {
    for (int k = 0; k < 4; ++k) {
        int p = k;
        double big = fabs(A[4 * k + k]);
        for (int i = k + 1; i < 4; ++i) {
            if (fabs(A[4 * i + k]) > big) {
                big = fabs(A[4 * i + k]);
                p = i;
            }
        }
        if (!(big > 0.0)) return false;
        if (p != k) {
            for (int j = 0; j < 4; ++j) {
                double t = A[4 * k + j];
                A[4 * k + j] = A[4 * p + j];
                A[4 * p + j] = t;
            }
            double t = b[k];
            b[k] = b[p];
            b[p] = t;
        }
        for (int i = k + 1; i < 4; ++i) {
            double f = A[4 * i + k] / A[4 * k + k];
            if (f != 0.0) {
                for (int j = k; j < 4; ++j) A[4 * i + j] -= f * A[4 * k + j];
                b[i] -= f * b[k];
            }
        }
    }
    for (int i = 3; i >= 0; --i) {
        double acc = b[i];
        for (int j = i + 1; j < 4; ++j) acc -= A[4 * i + j] * out[j];
        out[i] = acc / A[4 * i + i];
    }
    return true;
}

// two_vertex.py _normal_equations: A = J^T J, b = -J^T r (J 6 x 4 row-major, A 4 x 4 row-major)
static void tv_normal_equations(const double *jac, const double *res, double *A, double *b) {
    for (int i = 0; i < 4; ++i) {
        double acc = 0.0;
        for (int r = 0; r < 6; ++r) acc += jac[4 * r + i] * res[r];
        b[i] = -acc;
        for (int j = 0; j < 4; ++j) {
            acc = 0.0;
            for (int r = 0; r < 6; ++r) acc += jac[4 * r + i] * jac[4 * r + j];
            A[4 * i + j] = acc;
        }
    }
}

// two_vertex.py _max_vertex_error: the larger per-vertex residual norm
static double tv_max_vertex_error(const double *res) {
    double e1 = sqrt(res[0] * res[0] + res[1] * res[1] + res[2] * res[2]);
    double e2 = sqrt(res[3] * res[3] + res[4] * res[4] + res[5] * res[5]);
    return NB_MAX(e1, e2);
}

// two_vertex.py polish_and_validate2: Gauss-Newton (with backtracking) on the two-vertex residual
// from th (4, updated in place), then the acceptance test; returns accepted.  err_out: the larger
// per-vertex residual norm (INFINITY when the residual is undefined at the start), sigma_out: a
// lower bound of sigma_min(J), 1 / sqrt(trace((J^T J)^-1)) (0 when unknown).  The Python's
// scratch (work) is private here.
static bool tv_polish_and_validate(double *th, const double *geo, bool refract1, bool refract2, double eta,
                                   int max_steps, double tolerance, double *err_out, double *sigma_out) {
    double res[6], res2[6], jac[24], jac2[24], A[16], b[4], step[4], trial[4], tmp[16];
    if (!tv_residual(th, geo, refract1, refract2, eta, res, jac)) {
        *err_out = TV_INF;
        *sigma_out = 0.0;
        return false;
    }
    double err = sqrt((res[0] * res[0] + res[1] * res[1] + res[2] * res[2])
                      + (res[3] * res[3] + res[4] * res[4] + res[5] * res[5]));
    double last_step = TV_INF;
    for (int it = 0; it < max_steps; ++it) {
        if (err < 1e-15) {
            last_step = 0.0;
            break;
        }
        tv_normal_equations(jac, res, A, b);
        if (!tv_solve4(A, b, step)) break;
        last_step = NB_MAX(NB_MAX(fabs(step[0]), fabs(step[1])), NB_MAX(fabs(step[2]), fabs(step[3])));
        if (!(last_step < 10.0)) break;
        bool improved = false;
        double lam = 1.0, err2 = 0.0;
        for (int h = 0; h < 4; ++h) {  // backtracking: far candidates (sqrt approximation) may overshoot
            for (int i = 0; i < 4; ++i) trial[i] = th[i] + lam * step[i];
            if (tv_residual(trial, geo, refract1, refract2, eta, res2, jac2)) {
                err2 = 0.0;
                for (int r = 0; r < 6; ++r) err2 += res2[r] * res2[r];
                err2 = sqrt(err2);
                if (err2 < err) {
                    improved = true;
                    break;
                }
            }
            if (lam < 1.0 && err > 1e-9) lam *= 0.25;
            else if (err > 1e-9) lam = 0.5;
            else break;
        }
        if (!improved) break;
        for (int i = 0; i < 4; ++i) th[i] = trial[i];
        for (int r = 0; r < 6; ++r) res[r] = res2[r];
        for (int q = 0; q < 24; ++q) jac[q] = jac2[q];
        err = err2;
        if (lam < 1.0) last_step = TV_INF;
    }
    bool inside = true;
    for (int t = 0; t < 2; ++t) {
        double u = th[2 * t], v = th[2 * t + 1];
        if (!(u >= -TV_INSIDE_EPSILON && v >= -TV_INSIDE_EPSILON && u + v <= 1.0 + TV_INSIDE_EPSILON)) inside = false;
    }
    double verr = tv_max_vertex_error(res);
    bool settled = last_step <= TV_SETTLED_STEP;
    bool accepted = inside && (err <= tolerance || (settled && verr <= TV_DIRECTION_TOLERANCE));
    // Lower bound of sigma_min(J): 1 / sqrt(trace((J^T J)^-1)) (within a factor 2 of it).
    tv_normal_equations(jac, res, A, b);
    double tr = 0.0;
    for (int col = 0; col < 4; ++col) {
        for (int i = 0; i < 4; ++i) {
            b[i] = i == col ? 1.0 : 0.0;
            for (int j = 0; j < 4; ++j) tmp[4 * i + j] = A[4 * i + j];
        }
        if (!tv_solve4(tmp, b, step)) {
            tr = TV_INF;
            break;
        }
        tr += step[col];
    }
    *sigma_out = (tr > 0.0 && tr < TV_INF) ? 1.0 / sqrt(tr) : 0.0;
    *err_out = verr;
    return accepted;
}

// two_vertex.py trace_to_second: the exact mapping (u1, v1) -> (u2, v2): the ray x0 -> x1 scattered
// at vertex 1 and intersected with triangle 2's (unbounded) plane; returns ok (false under TIR, on
// the wrong side or without a hit: u2 = v2 = 0 then).
static bool tv_trace_to_second(double u1, double v1, const double *geo, bool refract1, double eta, double *u2,
                               double *v2) {
    *u2 = 0.0;
    *v2 = 0.0;
    tv3 x0 = tv_row(geo, 0), e11 = tv_row(geo, 2), e12 = tv_row(geo, 3);
    tv3 n1 = tv_madd(tv_madd(tv_row(geo, 4), tv_row(geo, 5), u1), tv_row(geo, 6), v1);
    tv3 ng1 = tv_row(geo, 13), p20 = tv_row(geo, 7), e21 = tv_row(geo, 8), e22 = tv_row(geo, 9);
    tv3 x1 = tv_madd(tv_scale(e11, u1), e12, v1);
    tv3 di = tv_sub(x1, x0);
    double li = tv_norm(di);
    double ln = tv_norm(n1);
    if (!(li > 0.0 && ln > 0.0)) return false;
    tv3 wi = tv_scale(di, 1.0 / li);
    tv3 nh = tv_scale(n1, 1.0 / ln);
    tv3 ng = tv_dot(ng1, nh) >= 0.0 ? ng1 : tv_scale(ng1, -1.0);
    double side_in = -tv_dot(di, ng);
    if (side_in == 0.0) return false;
    double s = side_in > 0.0 ? 1.0 : -1.0;
    tv3 no = tv_scale(nh, s);
    double c = -tv_dot(wi, no);
    if (!(c > 0.0)) return false;
    tv3 d;
    if (refract1) {
        double r = s > 0.0 ? 1.0 / eta : eta;
        double k = 1.0 - r * r * (1.0 - c * c);
        if (!(k > 0.0)) return false;
        d = tv_madd(tv_scale(wi, r), no, r * c - sqrt(k));
    } else {
        d = tv_madd(wi, no, 2.0 * c);
    }
    // Moller-Trumbore against the plane of triangle 2 (unbounded).
    tv3 pvec = tv_cross(d, e22);
    double det = tv_dot(e21, pvec);
    if (det == 0.0) return false;
    tv3 sv = tv_sub(x1, p20);
    double uu = tv_dot(sv, pvec) / det;
    tv3 qvec = tv_cross(sv, e21);
    double vv = tv_dot(d, qvec) / det;
    double t = tv_dot(e22, qvec) / det;
    if (!(t > 0.0) || !(isfinite(uu) && isfinite(vv))) return false;
    *u2 = uu;
    *v2 = vv;
    return true;
}

// one_vertex.py line_crossing_barycentrics: where the line x0 -> x2 crosses the plane of the
// triangle (p0, e1, e2) with unit normal ng, in barycentrics (Cramer's rule in the plane); false
// (u = v = 0) when the line is parallel to the plane or the triangle is degenerate.  No inside test.
static bool tv_line_crossing_barycentrics(const double *x0, const double *x2, const double *p0, const double *e1,
                                          const double *e2, const double *ng, double *u, double *v) {
    *u = 0.0;
    *v = 0.0;
    tv3 X0 = tv_vec(x0[0], x0[1], x0[2]), X2 = tv_vec(x2[0], x2[1], x2[2]), P0 = tv_vec(p0[0], p0[1], p0[2]);
    tv3 E1 = tv_vec(e1[0], e1[1], e1[2]), E2 = tv_vec(e2[0], e2[1], e2[2]), NG = tv_vec(ng[0], ng[1], ng[2]);
    tv3 w = tv_sub(X2, X0);
    double denom = tv_dot(w, NG);
    if (denom == 0.0) return false;
    tv3 rel = tv_sub(tv_madd(X0, w, tv_dot(tv_sub(P0, X0), NG) / denom), P0);
    double d11 = tv_dot(E1, E1);
    double d12 = tv_dot(E1, E2);
    double d22 = tv_dot(E2, E2);
    double r1 = tv_dot(rel, E1);
    double r2 = tv_dot(rel, E2);
    double det = d11 * d22 - d12 * d12;
    if (!(det > 0.0)) return false;
    *u = (r1 * d22 - r2 * d12) / det;
    *v = (d11 * r2 - d12 * r1) / det;
    return true;
}
