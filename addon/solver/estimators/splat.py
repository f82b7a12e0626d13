"""Splatting a sub-triangle's flux over the texels its straight image covers, by exact texel
overlap (polygon clipping, Sutherland-Hodgman on the four half-planes of a texel) with a flux
density linear over the image: the forward-flux estimator's texture
(:mod:`addon.bake.estimators.forward_flux`).  An image reaching beyond a flat receiver's UV
region (its points extended there, :mod:`addon.solver.geometry.receiver_planes`) is first
clipped to the region's edges: only the part inside lands (:func:`region_shares` says how much)."""

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


MAX_POLYGON = 48  # a triangle clipped by a region (at most receiver_planes.PLANE_MAX_EDGES edges) and a texel


@kernel(inline="always")
def _clip_line(xs, ys, n, a, b, c, ox, oy):
    """Sutherland-Hodgman: clip polygon (xs, ys)[:n] to a x + b y + c >= 0; returns count."""
    m = 0
    for i in range(n):
        j = (i + 1) % n
        fi = a * xs[i] + b * ys[i] + c
        fj = a * xs[j] + b * ys[j] + c
        if fi >= 0.0:
            ox[m] = xs[i]
            oy[m] = ys[i]
            m += 1
        if (fi >= 0.0) != (fj >= 0.0):
            t = fi / (fi - fj)
            ox[m] = xs[i] + t * (xs[j] - xs[i])
            oy[m] = ys[i] + t * (ys[j] - ys[i])
            m += 1
    return m


@kernel(inline="always")
def _clip_to_region(ax, ay, bx, by, cx, cy, region, W, H, xs, ys, bx_buf, by_buf):
    """The triangle (texel units) clipped to ``region`` (K, 3): rows (a, b, c) of a u + b v + c
    >= 0 in UV units; the polygon in (xs, ys).  Returns (its count, whether an edge cut it)."""
    xs[0], ys[0], xs[1], ys[1], xs[2], ys[2] = ax, ay, bx, by, cx, cy
    n = 3
    cut = False
    for k in range(region.shape[0]):
        a = region[k, 0] / W
        b = region[k, 1] / H
        c = region[k, 2]
        if a * ax + b * ay + c >= 0.0 and a * bx + b * by + c >= 0.0 and a * cx + b * cy + c >= 0.0:
            continue
        cut = True
        n = _clip_line(xs, ys, n, a, b, c, bx_buf, by_buf)
        for q in range(n):
            xs[q] = bx_buf[q]
            ys[q] = by_buf[q]
        if n < 3:
            return 0, True
    return n, cut


@kernel(inline="always")
def _linear_integral(xs, ys, n, ax, ay, det, r0, r1, r2, bx_, by_, cx, cy):
    """The integral over polygon (xs, ys)[:n] of the density linear over triangle abc with
    corner values r0, r1, r2 (det: twice its signed area): area x the value at the centroid."""
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
        return 0.0
    gx /= 3.0 * a
    gy /= 3.0 * a
    l1 = ((gx - ax) * (cy - ay) - (cx - ax) * (gy - ay)) / det
    l2 = ((bx_ - ax) * (gy - ay) - (gx - ax) * (by_ - ay)) / det
    return 0.5 * abs(a) * (r0 + l1 * (r1 - r0) + l2 * (r2 - r0))


@parallel_range(lambda a: a["band_first"].shape[0] - 1)
def _splat_bands(tri_uv, flux, W, H, out, density, band_first, region, first, last):
    """Rows [band_first[b], band_first[b + 1]) of the texture for bands b in [first, last):
    every triangle in order, clipped to the band's rows (see :func:`splat_triangles`)."""
    px = np.empty(MAX_POLYGON)
    py = np.empty(MAX_POLYGON)
    xs = np.empty(MAX_POLYGON)
    ys = np.empty(MAX_POLYGON)
    bx = np.empty(MAX_POLYGON)
    by = np.empty(MAX_POLYGON)
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
            if max(row_lo, int(math.floor(min(ay, by_, cy)))) > min(row_hi, int(math.floor(max(ay, by_, cy)))):
                continue  # not in this band's rows (nor is its clipped polygon, inside the triangle)
            np_, cut = _clip_to_region(ax, ay, bx_, by_, cx, cy, region, W, H, px, py, bx, by)
            if np_ < 3:
                continue
            lo_y, hi_y, lo_x, hi_x = py[0], py[0], px[0], px[0]
            for q in range(1, np_):
                lo_y, hi_y = min(lo_y, py[q]), max(hi_y, py[q])
                lo_x, hi_x = min(lo_x, px[q]), max(hi_x, px[q])
            j0 = max(row_lo, int(math.floor(lo_y)))
            j1 = min(row_hi, int(math.floor(hi_y)))
            det = (bx_ - ax) * (cy - ay) - (cx - ax) * (by_ - ay)
            area = 0.5 * abs(det)
            if not area > 1e-6:
                i = int(math.floor((ax + bx_ + cx) / 3.0))
                j = int(math.floor((ay + by_ + cy) / 3.0))
                if 0 <= i < W and 0 <= j < H and row_lo <= j <= row_hi and not cut:
                    k = j * W + i
                    out[k, 0] += f0
                    out[k, 1] += f1
                    out[k, 2] += f2
                continue
            if j1 < j0:
                continue
            r0, r1, r2 = density[t, 0], density[t, 1], density[t, 2]
            total = area * (r0 + r1 + r2) / 3.0
            i0 = max(0, int(math.floor(lo_x)))
            i1 = min(W - 1, int(math.floor(hi_x)))
            for j in range(j0, j1 + 1):
                for i in range(i0, i1 + 1):
                    for q in range(np_):
                        xs[q] = px[q]
                        ys[q] = py[q]
                    n = _clip_half(xs, ys, np_, 0, float(i), True, bx, by)
                    n = _clip_half(bx, by, n, 0, float(i + 1), False, xs, ys)
                    n = _clip_half(xs, ys, n, 1, float(j), True, bx, by)
                    n = _clip_half(bx, by, n, 1, float(j + 1), False, xs, ys)
                    if n < 3:
                        continue
                    w = _linear_integral(xs, ys, n, ax, ay, det, r0, r1, r2, bx_, by_, cx, cy) / total
                    if w == 0.0:
                        continue
                    k = j * W + i
                    out[k, 0] += f0 * w
                    out[k, 1] += f1 * w
                    out[k, 2] += f2 * w


@parallel_range("tri_uv")
def _region_shares(tri_uv, density, region, out, first, last):
    px = np.empty(MAX_POLYGON)
    py = np.empty(MAX_POLYGON)
    bx = np.empty(MAX_POLYGON)
    by = np.empty(MAX_POLYGON)
    for t in range(first, last):
        ax, ay = tri_uv[t, 0, 0], tri_uv[t, 0, 1]
        bx_, by_ = tri_uv[t, 1, 0], tri_uv[t, 1, 1]
        cx, cy = tri_uv[t, 2, 0], tri_uv[t, 2, 1]
        n, cut = _clip_to_region(ax, ay, bx_, by_, cx, cy, region, 1.0, 1.0, px, py, bx, by)
        if not cut:
            out[t] = 1.0
            continue
        det = (bx_ - ax) * (cy - ay) - (cx - ax) * (by_ - ay)
        r0, r1, r2 = density[t, 0], density[t, 1], density[t, 2]
        total = 0.5 * abs(det) * (r0 + r1 + r2) / 3.0
        if n < 3 or not total > 0.0:
            out[t] = 0.0
            continue
        out[t] = min(1.0, max(0.0, _linear_integral(px, py, n, ax, ay, det, r0, r1, r2, bx_, by_, cx, cy) / total))


def region_shares(tri_uv, density, region):
    """(m,) the share of each triangle's flux (UV corners ``tri_uv`` (m, 3, 2), linear ``density``
    (m, 3) as :func:`splat_triangles`) inside ``region`` ((K, 3) rows (a, b, c): a u + b v + c >= 0,
    :mod:`~addon.solver.geometry.receiver_planes`); 1 where no edge cuts it (a degenerate
    triangle cut by an edge: 0)."""
    out = np.ones(tri_uv.shape[0])
    if tri_uv.shape[0] and region.shape[0]:
        _region_shares(np.ascontiguousarray(tri_uv, dtype=np.float64), np.ascontiguousarray(density, dtype=np.float64),
                       np.ascontiguousarray(region, dtype=np.float64), out)
    return out


SPLAT_BANDS = 16  # the parallel splat's bands of rows (each scans every triangle's bounding box)


def band_first_rows(H, bands):
    """(b + 1,) the first row of each of at most ``bands`` equal bands of rows [0, H), then H."""
    rows = max(1, -(-int(H) // max(1, int(bands))))
    return np.append(np.arange(0, int(H), rows, dtype=np.int64), np.int64(H))


def splat_triangles(tri_uv, flux, W, H, out, density, bands=SPLAT_BANDS, region=None):
    """Deposit each triangle's flux (m, 3) over the texels of a W x H texture by the exact
    overlap of the triangle (UV) with each texel (polygon clipping).  ``density`` (m, 3):
    relative flux density at the corners (linear over the triangle; all ones: uniform); a texel
    gets flux x ∫ density over the overlap / ∫ density over the triangle (the integral of a
    linear function over a polygon is its area times the value at its centroid).  A triangle
    smaller than 1e-6 texel² deposits into the texel of its centroid (nothing when an edge of
    ``region`` cuts it).  ``out`` (H W, 3).  ``region`` (K, 3) (optional): rows (a, b, c), the
    half-planes a u + b v + c >= 0 (UV) of a flat receiver's region; each triangle is clipped to
    them first, so only the part of its flux inside lands (:func:`region_shares` of it).

    In parallel over ``bands`` bands of rows, each taking every triangle in order: a texel lies
    in one band, so it sums its triangles' shares in triangle order, bit for bit what one band
    (one thread) gives (tests/solver/test_solver_forward_image.py)."""
    H = int(H)
    band_first = band_first_rows(H, bands)
    region = np.zeros((0, 3)) if region is None else np.ascontiguousarray(region, dtype=np.float64)
    if tri_uv.shape[0] and H > 0:
        _splat_bands(tri_uv, flux, int(W), H, out, density, band_first, region)
