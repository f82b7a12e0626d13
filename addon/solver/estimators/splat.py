"""Splatting a sub-triangle's flux over the texels its straight image covers, by exact texel
overlap (polygon clipping, Sutherland-Hodgman on the four half-planes of a texel) with a flux
density linear over the image: the forward-flux estimator's texture
(:mod:`addon.bake.estimators.forward_flux`)."""

import math

import numpy as np

from ..runtime.jit import kernel, parallel_range


@kernel(inline="always")
def _clip_half(xs, ys, n, axis, bound, keep_greater, ox, oy):
    """Sutherland-Hodgman: clip polygon (xs, ys)[:n] to x_axis >= bound (or <=); returns count."""
    m = 0
    for i in range(n):
        j = (i + 1) % n
        ai = xs[i] if axis == 0 else ys[i]
        aj = xs[j] if axis == 0 else ys[j]
        ini = ai >= bound if keep_greater else ai <= bound
        inj = aj >= bound if keep_greater else aj <= bound
        if ini:
            ox[m] = xs[i]
            oy[m] = ys[i]
            m += 1
        if ini != inj:
            t = (bound - ai) / (aj - ai)
            ox[m] = xs[i] + t * (xs[j] - xs[i])
            oy[m] = ys[i] + t * (ys[j] - ys[i])
            m += 1
    return m


@parallel_range(lambda a: a["band_first"].shape[0] - 1)
def _splat_bands(tri_uv, flux, W, H, out, density, band_first, first, last):
    """Rows [band_first[b], band_first[b + 1]) of the texture for bands b in [first, last):
    every triangle in order, clipped to the band's rows (see :func:`splat_triangles`)."""
    xs = np.empty(16)
    ys = np.empty(16)
    bx = np.empty(16)
    by = np.empty(16)
    for band in range(first, last):
        row_lo = band_first[band]
        row_hi = band_first[band + 1] - 1
        if row_hi < row_lo:
            continue
        for t in range(tri_uv.shape[0]):
            f0, f1, f2 = flux[t, 0], flux[t, 1], flux[t, 2]
            if not (f0 > 0.0 or f1 > 0.0 or f2 > 0.0):
                continue
            ax, ay = tri_uv[t, 0, 0] * W, tri_uv[t, 0, 1] * H
            bx_, by_ = tri_uv[t, 1, 0] * W, tri_uv[t, 1, 1] * H
            cx, cy = tri_uv[t, 2, 0] * W, tri_uv[t, 2, 1] * H
            j0 = max(row_lo, int(math.floor(min(ay, by_, cy))))
            j1 = min(row_hi, int(math.floor(max(ay, by_, cy))))
            det = (bx_ - ax) * (cy - ay) - (cx - ax) * (by_ - ay)
            area = 0.5 * abs(det)
            if not area > 1e-6:
                i = int(math.floor((ax + bx_ + cx) / 3.0))
                j = int(math.floor((ay + by_ + cy) / 3.0))
                if 0 <= i < W and 0 <= j < H and row_lo <= j <= row_hi:
                    k = j * W + i
                    out[k, 0] += f0
                    out[k, 1] += f1
                    out[k, 2] += f2
                continue
            if j1 < j0:
                continue
            r0, r1, r2 = density[t, 0], density[t, 1], density[t, 2]
            total = area * (r0 + r1 + r2) / 3.0
            i0 = max(0, int(math.floor(min(ax, bx_, cx))))
            i1 = min(W - 1, int(math.floor(max(ax, bx_, cx))))
            for j in range(j0, j1 + 1):
                for i in range(i0, i1 + 1):
                    xs[0], ys[0], xs[1], ys[1], xs[2], ys[2] = ax, ay, bx_, by_, cx, cy
                    n = _clip_half(xs, ys, 3, 0, float(i), True, bx, by)
                    n = _clip_half(bx, by, n, 0, float(i + 1), False, xs, ys)
                    n = _clip_half(xs, ys, n, 1, float(j), True, bx, by)
                    n = _clip_half(bx, by, n, 1, float(j + 1), False, xs, ys)
                    if n < 3:
                        continue
                    a = 0.0
                    gx = 0.0
                    gy = 0.0
                    for q in range(n):
                        r = (q + 1) % n
                        cr = xs[q] * ys[r] - xs[r] * ys[q]
                        a += cr
                        gx += (xs[q] + xs[r]) * cr
                        gy += (ys[q] + ys[r]) * cr
                    if a == 0.0:
                        continue
                    gx /= 3.0 * a
                    gy /= 3.0 * a
                    # the density at the overlap's centroid (barycentric in the triangle)
                    l1 = ((gx - ax) * (cy - ay) - (cx - ax) * (gy - ay)) / det
                    l2 = ((bx_ - ax) * (gy - ay) - (gx - ax) * (by_ - ay)) / det
                    rho = r0 + l1 * (r1 - r0) + l2 * (r2 - r0)
                    w = 0.5 * abs(a) * rho / total
                    k = j * W + i
                    out[k, 0] += f0 * w
                    out[k, 1] += f1 * w
                    out[k, 2] += f2 * w


SPLAT_BANDS = 16  # the parallel splat's bands of rows (each scans every triangle's bounding box)


def splat_triangles(tri_uv, flux, W, H, out, density, bands=SPLAT_BANDS):
    """Deposit each triangle's flux (m, 3) over the texels of a W x H texture by the exact
    overlap of the triangle (UV) with each texel (polygon clipping).  ``density`` (m, 3):
    relative flux density at the corners (linear over the triangle; all ones: uniform); a texel
    gets flux x ∫ density over the overlap / ∫ density over the triangle (the integral of a
    linear function over a polygon is its area times the value at its centroid).  A triangle
    smaller than 1e-6 texel² deposits into the texel of its centroid.  ``out`` (H W, 3).

    In parallel over ``bands`` bands of rows, each taking every triangle in order: a texel lies
    in one band, so it sums its triangles' shares in triangle order, bit for bit what one band
    (one thread) gives (tests/solver/test_solver_forward_image.py)."""
    H = int(H)
    rows = max(1, -(-H // max(1, int(bands))))
    band_first = np.append(np.arange(0, H, rows, dtype=np.int64), np.int64(H))
    if tri_uv.shape[0] and H > 0:
        _splat_bands(tri_uv, flux, int(W), H, out, density, band_first)
