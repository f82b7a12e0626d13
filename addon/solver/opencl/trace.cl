// Forward tracing of chain points (forward-flux, step 1 of estimators/forward_image.py) in
// OpenCL C: trace_chain_points step for step — the point (u1, v1) of its first caster lit from
// x0 (a shadowed point is lost), scattered there (mirror / Snell about the interpolated normal,
// the side rules of CONTRACT.md), traced through the scene's BVH (geometry/bvh.py ray_closest:
// the same traversal order, slabs and Möller-Trumbore test) to a second caster and scattered
// again (two-vertex chains), then to the front of a receiver: its triangle, texture coordinates
// and the transport factor (Fresnel weights, cos_shading / cos_geometric).  Same arithmetic in the
// same order as the Numba kernels, so both back ends trace the same points.  One work-item per
// point; double precision (cl_khr_fp64) is required.
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL FP_CONTRACT OFF

#define ROLE_REFLECT 1
#define ROLE_BOTH 3
#define TRAVERSAL_STACK 256

typedef struct {
    __global const double *node_min, *node_max;
    __global const long *node_child, *node_start, *node_count, *order;
    __global const double *v0, *e1, *e2;
} Bvh;

// bvh.py _slab: clip [t0, t1] by one slab; a zero direction component (inv = inf) keeps or empties it
static void slab(double lo, double hi, double o, double inv, double *t0, double *t1) {
    if (inv == INFINITY) {
        if (o < lo || o > hi) { *t0 = 1.0; *t1 = 0.0; }
        return;
    }
    double a = (lo - o) * inv, b = (hi - o) * inv;
    if (a > b) { double s = a; a = b; b = s; }
    if (a > *t0) *t0 = a;
    if (b < *t1) *t1 = b;
}

static int box_hit(const Bvh *B, long k, double ox, double oy, double oz, double ix, double iy, double iz, double tmin,
                   double tmax) {
    double t0 = tmin, t1 = tmax;
    slab(B->node_min[3 * k], B->node_max[3 * k], ox, ix, &t0, &t1);
    slab(B->node_min[3 * k + 1], B->node_max[3 * k + 1], oy, iy, &t0, &t1);
    slab(B->node_min[3 * k + 2], B->node_max[3 * k + 2], oz, iz, &t0, &t1);
    return t0 <= t1 + 1e-12 * (fabs(t1) + 1.0);
}

// bvh.py _hit_triangle: Möller-Trumbore, inclusive edges; 1 when the ray hits leaf triangle q
// with t in [tmin, tmax] (*t_out set)
static int hit_triangle(const Bvh *B, long q, double ox, double oy, double oz, double dx, double dy, double dz,
                        double tmin, double tmax, double *t_out) {
    double e1x = B->e1[3 * q], e1y = B->e1[3 * q + 1], e1z = B->e1[3 * q + 2];
    double e2x = B->e2[3 * q], e2y = B->e2[3 * q + 1], e2z = B->e2[3 * q + 2];
    double px = dy * e2z - dz * e2y, py = dz * e2x - dx * e2z, pz = dx * e2y - dy * e2x;
    double det = e1x * px + e1y * py + e1z * pz;
    if (det == 0.0) return 0;
    double inv = 1.0 / det;
    double sx = ox - B->v0[3 * q], sy = oy - B->v0[3 * q + 1], sz = oz - B->v0[3 * q + 2];
    double u = (sx * px + sy * py + sz * pz) * inv;
    if (u < 0.0 || u > 1.0) return 0;
    double qx = sy * e1z - sz * e1y, qy = sz * e1x - sx * e1z, qz = sx * e1y - sy * e1x;
    double v = (dx * qx + dy * qy + dz * qz) * inv;
    if (v < 0.0 || u + v > 1.0) return 0;
    double t = (e2x * qx + e2y * qy + e2z * qz) * inv;
    if (t < tmin || t > tmax) return 0;
    *t_out = t;
    return 1;
}

// bvh.py ray_closest: the closest triangle (not `ig`) hit with t in [tmin, tmax], or -1
static long ray_closest(const Bvh *B, double ox, double oy, double oz, double dx, double dy, double dz, double tmin,
                        double tmax, long ig, double *t_best) {
    double ix = dx != 0.0 ? 1.0 / dx : INFINITY;
    double iy = dy != 0.0 ? 1.0 / dy : INFINITY;
    double iz = dz != 0.0 ? 1.0 / dz : INFINITY;
    double best_t = tmax;
    long best = -1;
    int stack[TRAVERSAL_STACK];
    stack[0] = 0;
    int sp = 1;
    while (sp > 0) {
        sp--;
        long k = stack[sp];
        if (!box_hit(B, k, ox, oy, oz, ix, iy, iz, tmin, best_t)) continue;
        long c = B->node_child[k];
        if (c < 0) {
            long s = B->node_start[k];
            for (long q = s; q < s + B->node_count[k]; ++q) {
                long tid = B->order[q];
                if (tid == ig) continue;
                double t;
                // ties (a ray through an edge two triangles share): the smallest id, whatever the tree
                if (hit_triangle(B, q, ox, oy, oz, dx, dy, dz, tmin, best_t, &t)
                    && (t < best_t || best < 0 || (t == best_t && tid < best))) {
                    best_t = t;
                    best = tid;
                }
            }
        } else {
            stack[sp] = (int)c;
            stack[sp + 1] = (int)c + 1;
            sp += 2;
        }
    }
    *t_best = best_t;
    return best;
}

// surface.py triangle_frame (with forward_image.py _bary_point's ok: area and a nonzero normal):
// the point, the unit shading normal n and the unit geometric normal g on n's side
static int bary_point(__global const double *tri_p, __global const double *tri_n, long t, double u, double v,
                      double3 *x, double3 *n, double3 *g) {
    __global const double *p = tri_p + 9 * t, *k = tri_n + 9 * t;
    double p0x = p[0], p0y = p[1], p0z = p[2];
    double e1x = p[3] - p0x, e1y = p[4] - p0y, e1z = p[5] - p0z;
    double e2x = p[6] - p0x, e2y = p[7] - p0y, e2z = p[8] - p0z;
    *x = (double3)(p0x + u * e1x + v * e2x, p0y + u * e1y + v * e2y, p0z + u * e1z + v * e2z);
    double nx = k[0] + u * (k[3] - k[0]) + v * (k[6] - k[0]);
    double ny = k[1] + u * (k[4] - k[1]) + v * (k[7] - k[1]);
    double nz = k[2] + u * (k[5] - k[2]) + v * (k[8] - k[2]);
    double gx = e1y * e2z - e1z * e2y, gy = e1z * e2x - e1x * e2z, gz = e1x * e2y - e1y * e2x;
    double gl = sqrt(gx * gx + gy * gy + gz * gz), nl = sqrt(nx * nx + ny * ny + nz * nz);
    if (gl > 0.0) { gx = gx / gl; gy = gy / gl; gz = gz / gl; }
    if (nl > 0.0) { nx = nx / nl; ny = ny / nl; nz = nz / nl; }
    else { nx = gx; ny = gy; nz = gz; }
    if (gx * nx + gy * ny + gz * nz < 0.0) { gx = -gx; gy = -gy; gz = -gz; }
    *n = (double3)(nx, ny, nz);
    *g = (double3)(gx, gy, gz);
    return gl > 0.0 && nl > 0.0;
}

// surface.py plane_barycentrics: where the ray crosses triangle t's plane (not clamped)
static double2 plane_barycentrics(__global const double *tri_p, long t, double3 o, double3 d) {
    __global const double *p = tri_p + 9 * t;
    double p0x = p[0], p0y = p[1], p0z = p[2];
    double e1x = p[3] - p0x, e1y = p[4] - p0y, e1z = p[5] - p0z;
    double e2x = p[6] - p0x, e2y = p[7] - p0y, e2z = p[8] - p0z;
    double px = d.y * e2z - d.z * e2y, py = d.z * e2x - d.x * e2z, pz = d.x * e2y - d.y * e2x;
    double det = e1x * px + e1y * py + e1z * pz;
    if (det == 0.0) return (double2)(0.0, 0.0);
    double inv = 1.0 / det;
    double sx = o.x - p0x, sy = o.y - p0y, sz = o.z - p0z;
    double u = (sx * px + sy * py + sz * pz) * inv;
    double qx = sy * e1z - sz * e1y, qy = sz * e1x - sx * e1z, qz = sx * e1y - sy * e1x;
    double v = (d.x * qx + d.y * qy + d.z * qz) * inv;
    return (double2)(u, v);
}

// optics.py fresnel_dielectric (cos_i clamped to [0, 1]; 1 under total internal reflection)
static double fresnel_dielectric(double cos_i, double eta_i, double eta_t) {
    cos_i = fmin(fmax(cos_i, 0.0), 1.0);
    double sin_t = eta_i / eta_t * sqrt(fmax(0.0, 1.0 - cos_i * cos_i));
    if (sin_t >= 1.0) return 1.0;
    double cos_t = sqrt(fmax(0.0, 1.0 - sin_t * sin_t));
    double rs = (eta_i * cos_i - eta_t * cos_t) / (eta_i * cos_i + eta_t * cos_t);
    double rp = (eta_i * cos_t - eta_t * cos_i) / (eta_i * cos_t + eta_t * cos_i);
    return 0.5 * (rs * rs + rp * rp);
}

// forward_image.py _weight: the bake's surface weight of one vertex
static double vertex_weight(double3 d, double3 n, double3 g, int refract, double eta, long role) {
    if (role == ROLE_REFLECT) return 1.0;
    int outside = d.x * g.x + d.y * g.y + d.z * g.z < 0.0;
    double ci = fabs(d.x * n.x + d.y * n.y + d.z * n.z);
    double F = outside ? fresnel_dielectric(ci, 1.0, eta) : fresnel_dielectric(ci, eta, 1.0);
    if (refract) return 1.0 - F;
    return role == ROLE_BOTH ? F : 1.0;
}

// optics.py scatter_direction: mirror reflection or refraction with the side rules; 0 when none
static int scatter(double3 *dir, double3 n, double3 g, int refract, double eta) {
    double dx = dir->x, dy = dir->y, dz = dir->z;
    int outside = dx * g.x + dy * g.y + dz * g.z < 0.0;
    double sg = outside ? 1.0 : -1.0;
    double nox = sg * n.x, noy = sg * n.y, noz = sg * n.z;
    double ngx = sg * g.x, ngy = sg * g.y, ngz = sg * g.z;
    double ci = -(dx * nox + dy * noy + dz * noz);
    if (!(ci > 0.0)) return 0;
    double ox, oy, oz, ln;
    if (refract) {
        double rr = outside ? 1.0 / eta : eta;
        double kk = 1.0 - rr * rr * (1.0 - ci * ci);
        if (!(kk > 0.0)) return 0;
        double c2 = rr * ci - sqrt(kk);
        ox = rr * dx + c2 * nox; oy = rr * dy + c2 * noy; oz = rr * dz + c2 * noz;
        ln = sqrt(ox * ox + oy * oy + oz * oz);
        ox = ox / ln; oy = oy / ln; oz = oz / ln;
        if (!(ox * ngx + oy * ngy + oz * ngz < 0.0)) return 0;
    } else {
        ox = dx + 2.0 * ci * nox; oy = dy + 2.0 * ci * noy; oz = dz + 2.0 * ci * noz;
        ln = sqrt(ox * ox + oy * oy + oz * oz);
        ox = ox / ln; oy = oy / ln; oz = oz / ln;
        if (!(ox * ngx + oy * ngy + oz * ngz > 0.0)) return 0;
    }
    *dir = (double3)(ox, oy, oz);
    return 1;
}

// receiver_planes.py (rows of PLANE_WIDTH doubles; see there)
#define PLANE_HEAD 16
#define PLANE_WIDTH (PLANE_HEAD + 3 * 32)

// receiver_planes.py region_value: the smallest signed distance of (u, v) to the region's edges
static double region_value(__global const double *row, double u, double v) {
    double lo = INFINITY;
    int k_n = (int)row[14];
    for (int k = 0; k < k_n; k++) {
        __global const double *h = row + PLANE_HEAD + 3 * k;
        lo = fmin(lo, h[0] * u + h[1] * v + h[2]);
    }
    return lo;
}

// receiver_planes.py extended_landing: the plane row whose front the ray crosses nearest (t > eps)
// outside its receiver's UV region, or -1
static int extended_landing(__global const double *planes, int n_planes, double3 x, double3 d, double eps) {
    int best = -1;
    double best_t = INFINITY;
    for (int p = 0; p < n_planes; p++) {
        __global const double *row = planes + PLANE_WIDTH * p;
        double den = row[0] * d.x + row[1] * d.y + row[2] * d.z;
        if (!(den < 0.0)) continue;
        double t = (row[3] - (row[0] * x.x + row[1] * x.y + row[2] * x.z)) / den;
        if (!(t > eps && t < best_t)) continue;
        double hx = x.x + t * d.x, hy = x.y + t * d.y, hz = x.z + t * d.z;
        double u = row[4] * hx + row[5] * hy + row[6] * hz + row[7];
        double v = row[8] * hx + row[9] * hy + row[10] * hz + row[11];
        double value = region_value(row, u, v);
        if (value < 0.0 && value >= -row[15]) {
            best = p;
            best_t = t;
        }
    }
    return best;
}

// forward_image.py _land: the closest hit must be the front of a receiver; its triangle (or -1),
// barycentrics and cos_shading / cos_geometric there; a ray landing on none but crossing a flat
// receiver's plane outside its region lands there, extended (factor 1)
static long land(const Bvh *B, __global const long *tri_rec, __global const double *tri_p,
                 __global const double *tri_n, double3 x, double3 d, long prev, double eps,
                 __global const double *planes, int n_planes, double *ur, double *vr, double *c) {
    double th;
    long tr = ray_closest(B, x.x, x.y, x.z, d.x, d.y, d.z, eps, INFINITY, prev, &th);
    if (tr < 0 || tri_rec[tr] < 0) {
        int p = extended_landing(planes, n_planes, x, d, eps);
        if (p < 0) return -1;
        long tp = (long)planes[PLANE_WIDTH * p + 12];
        double2 b = plane_barycentrics(tri_p, tp, x, d);
        *ur = b.x;
        *vr = b.y;
        *c = 1.0;
        return tp;
    }
    double2 b = plane_barycentrics(tri_p, tr, x, d);
    double3 h, n, g;
    int ok = bary_point(tri_p, tri_n, tr, b.x, b.y, &h, &n, &g);
    double cg = -(d.x * g.x + d.y * g.y + d.z * g.z);
    if (!ok || cg <= 0.0) return -1;  // the back of the receiver (the bake's front rule)
    *ur = b.x;
    *vr = b.y;
    *c = fmax(0.0, -(d.x * n.x + d.y * n.y + d.z * n.z)) / cg;
    return tr;
}

// forward_image.py _trace_one: the chain of `bounces` (1 or 2) vertices from (u1, v1) on t1 lit
// from x0; returns the receiver triangle or -1 and sets the second triangle, the receiver's
// barycentrics and the transport factor (0 wherever the chain is lost, as the Numba kernel)
static long trace_one(const Bvh *B, double x0x, double x0y, double x0z, long t1, double u1, double v1, int bounces,
                      int refract1, int refract2, __global const uchar *second_ok, __global const long *tri_rec,
                      __global const double *tri_p, __global const double *tri_n, __global const double *tri_ior,
                      __global const long *tri_role, double eps, __global const double *planes, int n_planes,
                      long *t2, double *ur, double *vr, double *fac) {
    *t2 = -1;
    *fac = 0.0;
    double3 x, nrm, g;
    if (!bary_point(tri_p, tri_n, t1, u1, v1, &x, &nrm, &g)) return -1;
    double dx = x.x - x0x, dy = x.y - x0y, dz = x.z - x0z;
    double ln = sqrt(dx * dx + dy * dy + dz * dz);
    if (!(ln > 0.0)) return -1;
    double3 d = (double3)(dx / ln, dy / ln, dz / ln);
    // the light must reach the point: a shadowed point is lost like a missed receiver
    double th;
    if (ray_closest(B, x0x, x0y, x0z, d.x, d.y, d.z, eps, ln * (1.0 - 1e-9) - eps, t1, &th) >= 0) return -1;
    double w = vertex_weight(d, nrm, g, refract1, tri_ior[t1], tri_role[t1]);
    if (!scatter(&d, nrm, g, refract1, tri_ior[t1])) return -1;
    long last = t1;
    if (bounces == 2) {
        long s2 = ray_closest(B, x.x, x.y, x.z, d.x, d.y, d.z, eps, INFINITY, t1, &th);
        if (s2 < 0 || !second_ok[s2]) return -1;
        *t2 = s2;
        double2 b = plane_barycentrics(tri_p, s2, x, d);
        double u2 = fmin(fmax(b.x, 0.0), 1.0);
        double v2 = fmin(fmax(b.y, 0.0), 1.0 - u2);
        if (!bary_point(tri_p, tri_n, s2, u2, v2, &x, &nrm, &g)) return -1;
        w *= vertex_weight(d, nrm, g, refract2, tri_ior[t1], tri_role[s2]);
        if (!scatter(&d, nrm, g, refract2, tri_ior[t1])) return -1;
        last = s2;
    }
    double c = 0.0;
    long tr = land(B, tri_rec, tri_p, tri_n, x, d, last, eps, planes, n_planes, ur, vr, &c);
    *fac = w * c;  // c = 0 for a lost landing, as _land's
    return tr;
}

__kernel void trace_chain_points(__global const long *emitter, __global const double *u1, __global const double *v1,
                                 __global const double *x0, __global const long *t1_of, const int bounces,
                                 const int refract1, const int refract2, __global const uchar *second_ok,
                                 __global const long *tri_rec, __global const double *tri_uv,
                                 __global const double *tri_p, __global const double *tri_n,
                                 __global const double *tri_ior, __global const long *tri_role,
                                 __global const double *node_min, __global const double *node_max,
                                 __global const long *node_child, __global const long *node_start,
                                 __global const long *node_count, __global const long *order,
                                 __global const double *bv0, __global const double *be1, __global const double *be2,
                                 const double eps, __global const double *planes, const int n_planes,
                                 const int n, __global long *out_t2, __global long *out_rec,
                                 __global double *out_uv, __global double *out_factor) {
    int i = get_global_id(0);
    if (i >= n) return;
    Bvh B = {node_min, node_max, node_child, node_start, node_count, order, bv0, be1, be2};
    long e = emitter[i], t2;
    double ur = 0.0, vr = 0.0, fac;
    long tr = trace_one(&B, x0[3 * e], x0[3 * e + 1], x0[3 * e + 2], t1_of[e], u1[i], v1[i], bounces, refract1, refract2,
                        second_ok, tri_rec, tri_p, tri_n, tri_ior, tri_role, eps, planes, n_planes, &t2, &ur, &vr,
                        &fac);
    out_t2[i] = t2;
    out_rec[i] = tr;
    out_factor[i] = fac;
    if (tr >= 0) {
        __global const double *w = tri_uv + 6 * tr;
        out_uv[2 * i] = w[0] + ur * (w[2] - w[0]) + vr * (w[4] - w[0]);
        out_uv[2 * i + 1] = w[1] + ur * (w[3] - w[1]) + vr * (w[5] - w[1]);
    } else {
        out_uv[2 * i] = NAN;
        out_uv[2 * i + 1] = NAN;
    }
}
