// The forward-flux splat on the device: estimators/splat.py _splat_bands step for step.  Each
// sub-triangle's flux is spread over the texels its straight image (UV) covers by exact overlap
// (Sutherland-Hodgman on a texel's four half-planes) with a density linear over the image,
// after clipping the image to a flat receiver's UV region when it has one.  One work-item per
// band of rows takes every triangle in order, so each texel sums its triangles' shares in
// triangle order: the same bits as the Numba splat, whatever the bands.
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL FP_CONTRACT OFF

#define MAX_POLYGON 48  // splat.py MAX_POLYGON

// @INCLUDE numba_math.cl@ (NB_MAX, NB_MIN)

// splat.py _clip_half: polygon (xs, ys)[:n] clipped to x_axis >= bound (or <=) into (ox, oy)
static int clip_half(const double *xs, const double *ys, int n, int axis, double bound, int keep_greater, double *ox,
                     double *oy) {
    int m = 0;
    for (int i = 0; i < n; i++) {
        int j = (i + 1) % n;
        double ai = axis == 0 ? xs[i] : ys[i];
        double aj = axis == 0 ? xs[j] : ys[j];
        int ini = keep_greater ? ai >= bound : ai <= bound;
        int inj = keep_greater ? aj >= bound : aj <= bound;
        if (ini) {
            ox[m] = xs[i];
            oy[m] = ys[i];
            m++;
        }
        if (ini != inj) {
            double t = (bound - ai) / (aj - ai);
            ox[m] = xs[i] + t * (xs[j] - xs[i]);
            oy[m] = ys[i] + t * (ys[j] - ys[i]);
            m++;
        }
    }
    return m;
}

// splat.py _clip_line: polygon (xs, ys)[:n] clipped to a x + b y + c >= 0 into (ox, oy)
static int clip_line(const double *xs, const double *ys, int n, double a, double b, double c, double *ox, double *oy) {
    int m = 0;
    for (int i = 0; i < n; i++) {
        int j = (i + 1) % n;
        double fi = a * xs[i] + b * ys[i] + c;
        double fj = a * xs[j] + b * ys[j] + c;
        if (fi >= 0.0) {
            ox[m] = xs[i];
            oy[m] = ys[i];
            m++;
        }
        if ((fi >= 0.0) != (fj >= 0.0)) {
            double t = fi / (fi - fj);
            ox[m] = xs[i] + t * (xs[j] - xs[i]);
            oy[m] = ys[i] + t * (ys[j] - ys[i]);
            m++;
        }
    }
    return m;
}

// splat.py _clip_to_region: the triangle (texel units) clipped to the region's half-planes
// (rows a, b, c in UV units) into (xs, ys); returns its count, *cut whether an edge cut it
static int clip_to_region(double ax, double ay, double bx, double by, double cx, double cy,
                          __global const double *region, int n_region, long W, long H, double *xs, double *ys,
                          double *bx_buf, double *by_buf, int *cut) {
    xs[0] = ax; ys[0] = ay; xs[1] = bx; ys[1] = by; xs[2] = cx; ys[2] = cy;
    int n = 3;
    *cut = 0;
    for (int k = 0; k < n_region; k++) {
        double a = region[3 * k] / (double)W;
        double b = region[3 * k + 1] / (double)H;
        double c = region[3 * k + 2];
        if (a * ax + b * ay + c >= 0.0 && a * bx + b * by + c >= 0.0 && a * cx + b * cy + c >= 0.0) continue;
        *cut = 1;
        n = clip_line(xs, ys, n, a, b, c, bx_buf, by_buf);
        for (int q = 0; q < n; q++) {
            xs[q] = bx_buf[q];
            ys[q] = by_buf[q];
        }
        if (n < 3) return 0;
    }
    return n;
}

// splat.py _linear_integral: the integral over polygon (xs, ys)[:n] of the density linear over
// triangle abc with corner values r0, r1, r2 (det: twice its signed area)
static double linear_integral(const double *xs, const double *ys, int n, double ax, double ay, double det, double r0,
                              double r1, double r2, double bx, double by, double cx, double cy) {
    double a = 0.0, gx = 0.0, gy = 0.0;
    for (int q = 0; q < n; q++) {
        int r = (q + 1) % n;
        double cr = xs[q] * ys[r] - xs[r] * ys[q];
        a += cr;
        gx += (xs[q] + xs[r]) * cr;
        gy += (ys[q] + ys[r]) * cr;
    }
    if (a == 0.0) return 0.0;
    gx /= 3.0 * a;
    gy /= 3.0 * a;
    double l1 = ((gx - ax) * (cy - ay) - (cx - ax) * (gy - ay)) / det;
    double l2 = ((bx - ax) * (gy - ay) - (gx - ax) * (by - ay)) / det;
    return 0.5 * fabs(a) * (r0 + l1 * (r1 - r0) + l2 * (r2 - r0));
}

// splat.py _splat_bands: rows [band_first[b], band_first[b + 1]) of out (H W, 3) for band b =
// the work-item, every triangle in order
__kernel void splat_bands(__global const double *tri_uv, __global const double *flux, __global const double *density,
                          const int n_tri, const long W, const long H, __global double *out,
                          __global const long *band_first, const int n_bands, __global const double *region,
                          const int n_region) {
    int band = get_global_id(0);
    if (band >= n_bands) return;
    double px[MAX_POLYGON], py[MAX_POLYGON], xs[MAX_POLYGON], ys[MAX_POLYGON], bx[MAX_POLYGON], by[MAX_POLYGON];
    long row_lo = band_first[band];
    long row_hi = band_first[band + 1] - 1;
    if (row_hi < row_lo) return;
    for (int t = 0; t < n_tri; t++) {
        double f0 = flux[3 * t], f1 = flux[3 * t + 1], f2 = flux[3 * t + 2];
        if (!(f0 > 0.0 || f1 > 0.0 || f2 > 0.0)) continue;
        __global const double *p = tri_uv + 6 * t;
        double ax = p[0] * (double)W, ay = p[1] * (double)H;
        double bx_ = p[2] * (double)W, by_ = p[3] * (double)H;
        double cx = p[4] * (double)W, cy = p[5] * (double)H;
        // not in this band's rows (nor is its clipped polygon, inside the triangle)
        if (NB_MAX(row_lo, (long)floor(NB_MIN(NB_MIN(ay, by_), cy))) > NB_MIN(row_hi, (long)floor(NB_MAX(NB_MAX(ay, by_), cy))))
            continue;
        int cut;
        int np_ = clip_to_region(ax, ay, bx_, by_, cx, cy, region, n_region, W, H, px, py, bx, by, &cut);
        if (np_ < 3) continue;
        double lo_y = py[0], hi_y = py[0], lo_x = px[0], hi_x = px[0];
        for (int q = 1; q < np_; q++) {
            lo_y = NB_MIN(lo_y, py[q]);
            hi_y = NB_MAX(hi_y, py[q]);
            lo_x = NB_MIN(lo_x, px[q]);
            hi_x = NB_MAX(hi_x, px[q]);
        }
        long j0 = NB_MAX(row_lo, (long)floor(lo_y));
        long j1 = NB_MIN(row_hi, (long)floor(hi_y));
        double det = (bx_ - ax) * (cy - ay) - (cx - ax) * (by_ - ay);
        double area = 0.5 * fabs(det);
        if (!(area > 1e-6)) {
            long i = (long)floor((ax + bx_ + cx) / 3.0);
            long j = (long)floor((ay + by_ + cy) / 3.0);
            if (0 <= i && i < W && 0 <= j && j < H && row_lo <= j && j <= row_hi && !cut) {
                long k = j * W + i;
                out[3 * k] += f0;
                out[3 * k + 1] += f1;
                out[3 * k + 2] += f2;
            }
            continue;
        }
        if (j1 < j0) continue;
        double r0 = density[3 * t], r1 = density[3 * t + 1], r2 = density[3 * t + 2];
        double total = area * (r0 + r1 + r2) / 3.0;
        long i0 = NB_MAX(0, (long)floor(lo_x));
        long i1 = NB_MIN(W - 1, (long)floor(hi_x));
        for (long j = j0; j <= j1; j++) {
            for (long i = i0; i <= i1; i++) {
                for (int q = 0; q < np_; q++) {
                    xs[q] = px[q];
                    ys[q] = py[q];
                }
                int n = clip_half(xs, ys, np_, 0, (double)i, 1, bx, by);
                n = clip_half(bx, by, n, 0, (double)(i + 1), 0, xs, ys);
                n = clip_half(xs, ys, n, 1, (double)j, 1, bx, by);
                n = clip_half(bx, by, n, 1, (double)(j + 1), 0, xs, ys);
                if (n < 3) continue;
                double w = linear_integral(xs, ys, n, ax, ay, det, r0, r1, r2, bx_, by_, cx, cy) / total;
                if (w == 0.0) continue;
                long k = j * W + i;
                out[3 * k] += f0 * w;
                out[3 * k + 1] += f1 * w;
                out[3 * k + 2] += f2 * w;
            }
        }
    }
}
