"""Texels of a receiver in UV space: supersamples -> triangle, barycentrics, world point, normal.

Texture layout: texel (i, j) of a W x H texture covers u in [i/W, (i+1)/W], v in [j/H, (j+1)/H];
j = 0 is the bottom row (v = 0), as Blender stores image pixels.  The flat texel index is
j W + i.  EXR files are written top row first (exr.py flips).

Each texel holds S = s x s stratified supersamples: sample (a, b) lies at
((i + (a + xi_a) / s) / W, (j + (b + xi_b) / s) / H) with xi = 1/2 (regular grid) or, when
``jitter`` is on, a hash of (seed, texel, sample) — deterministic for a seed and independent
of how the texture is split into bands.  A sample belongs to the first receiver triangle
(lowest index) whose UV triangle contains it (edges inclusive, 1e-12 slack), so shared edges
are neither doubled nor lost.  Its barycentrics (u, v) in the UV triangle give the world
point x = p0 + u (p1 - p0) + v (p2 - p0) and the shading normal
normalize(n0 + u (n1 - n0) + v (n2 - n0)) — the triangle is affine in UV and in space.

A texel is *covered* when at least one of its samples lies on the receiver; its value is
the mean over its covered samples.  :func:`pad` then extends covered texels over the UV
seams by a margin of N texels, like Blender's bake margin ("Extend").
"""

from dataclasses import dataclass

import numpy as np

from ..solver.runtime.jit import kernel, parallel_range

UV_EPS = 1e-12


@dataclass
class SampleBand:
    """The covered supersamples of texel rows [row0, row1) of one receiver."""

    width: int
    height: int
    row0: int
    row1: int
    texel: np.ndarray  # (m,) int64 flat texel index j W + i
    tri: np.ndarray  # (m,) int64 global triangle index
    bary: np.ndarray  # (m,2) barycentrics (u, v) in the triangle
    uv: np.ndarray  # (m,2) texture coordinates of the sample
    position: np.ndarray  # (m,3) world point
    normal: np.ndarray  # (m,3) unit shading normal (interpolated corner normals)
    geo_normal: np.ndarray  # (m,3) unit geometric normal, turned to the shading normal's side

    @property
    def size(self):
        return self.texel.shape[0]


def grid_side(samples):
    """Side s of the s x s stratified grid for ``samples`` per texel (rounded up to a square)."""
    samples = int(samples)
    if samples < 1:
        raise ValueError("samples per texel must be >= 1")
    s = int(np.ceil(np.sqrt(samples) - 1e-9))
    return s


@kernel(inline="always")
def _mix64(z):
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@kernel(inline="always")
def hash_uniform(seed, a, b):
    """A uniform number in [0, 1) from three integers (splitmix64 mixing)."""
    z = _mix64(np.uint64(seed) * np.uint64(0x9E3779B97F4A7C15) + np.uint64(0x632BE59BD9B4E019))
    z = _mix64(z ^ (np.uint64(a) * np.uint64(0xD1B54A32D192ED03)))
    z = _mix64(z ^ (np.uint64(b) * np.uint64(0x8CB92BA72F3D8DD7)))
    return float(z >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@parallel_range(lambda a: a["row1"] - a["row0"])
def _raster_rows(uv, tri_list, W, H, row0, row1, s, seed, jitter, geometry, owner, bary, suv, first, last):
    """owner[r, i, k] = index into tri_list of the triangle holding sample k of texel (i, row0 + r);
    with ``geometry``, the sample's barycentrics and UV in bary and suv too."""
    S = s * s
    for r in range(first, last):
        j = row0 + r
        vlo = j / H
        vhi = (j + 1) / H
        for i in range(W):
            for k in range(S):
                owner[r, i, k] = -1
        for q in range(tri_list.shape[0]):
            t = tri_list[q]
            au = uv[t, 0, 0]
            av = uv[t, 0, 1]
            bu = uv[t, 1, 0] - au
            bv = uv[t, 1, 1] - av
            cu = uv[t, 2, 0] - au
            cv = uv[t, 2, 1] - av
            den = bu * cv - bv * cu
            if den == 0.0:
                continue
            tv0 = min(av, av + bv, av + cv)
            tv1 = max(av, av + bv, av + cv)
            if tv1 < vlo or tv0 > vhi:
                continue
            tu0 = min(au, au + bu, au + cu)
            tu1 = max(au, au + bu, au + cu)
            i0 = max(0, int(np.floor(tu0 * W)) - 1)
            i1 = min(W - 1, int(np.floor(tu1 * W)) + 1)
            for i in range(i0, i1 + 1):
                texel = j * W + i
                for k in range(S):
                    if owner[r, i, k] >= 0:
                        continue
                    a = k % s
                    b = k // s
                    if jitter:
                        xa = hash_uniform(seed, texel, 2 * k)
                        xb = hash_uniform(seed, texel, 2 * k + 1)
                    else:
                        xa = 0.5
                        xb = 0.5
                    pu = (i + (a + xa) / s) / W
                    pv = (j + (b + xb) / s) / H
                    du = pu - au
                    dv = pv - av
                    l1 = (du * cv - dv * cu) / den
                    l2 = (bu * dv - bv * du) / den
                    if l1 >= -UV_EPS and l2 >= -UV_EPS and l1 + l2 <= 1.0 + UV_EPS:
                        l1 = min(max(l1, 0.0), 1.0)
                        l2 = min(max(l2, 0.0), 1.0 - l1)
                        owner[r, i, k] = q
                        if geometry:
                            bary[r, i, k, 0] = l1
                            bary[r, i, k, 1] = l2
                            suv[r, i, k, 0] = pu
                            suv[r, i, k, 1] = pv


def raster_texels(receiver, samples=1, seed=0, jitter=False, rows=None):
    """(texel (m,), global triangle (m,)) of the covered supersamples of a receiver: the
    first two fields of :func:`rasterise`'s band, without the samples' geometry (what texel
    areas and supersample counts need)."""
    texel, tri, _keep, _bary, _suv, _rows = _raster(receiver, samples, seed, jitter, rows, geometry=False)
    return texel, tri


def _raster(receiver, samples, seed, jitter, rows, geometry=True):
    W, H = receiver.resolution
    row0, row1 = (0, H) if rows is None else (max(0, int(rows[0])), min(H, int(rows[1])))
    s = grid_side(samples)
    S = s * s
    uv = receiver.uv
    # Triangles whose UV bounding box meets the band.
    vmin = uv[:, :, 1].min(1)
    vmax = uv[:, :, 1].max(1)
    tri_list = np.flatnonzero((vmax >= row0 / H) & (vmin <= row1 / H)).astype(np.int64)
    nr = max(0, row1 - row0)
    owner = np.empty((nr, W, S), dtype=np.int64)
    # without the samples' geometry (raster_texels) no band-sized barycentric / UV tables
    shape = (nr, W, S, 2) if geometry else (0, 0, 0, 2)
    bary = np.zeros(shape)
    suv = np.zeros(shape)
    if nr and tri_list.size:
        _raster_rows(uv, tri_list, W, H, row0, row1, s, int(seed) & 0x7FFFFFFFFFFFFFFF, bool(jitter), bool(geometry), owner,
                     bary, suv)
    else:
        owner.fill(-1)
    own = owner.reshape(-1)
    keep = np.flatnonzero(own >= 0)
    texel = (np.arange(nr * W * S, dtype=np.int64) // S + row0 * W)[keep]
    local = tri_list[own[keep]] if keep.size else np.zeros(0, dtype=np.int64)
    return texel, receiver.tri_index[local], keep, bary, suv, (row0, row1)


def rasterise(scene, receiver, samples=1, seed=0, jitter=False, rows=None):
    """The covered supersamples of a receiver (all rows, or texel rows ``rows`` = (j0, j1)).

    Returns a :class:`SampleBand`; see the module docstring for the conventions.
    """
    texel, tri, keep, bary, suv, (row0, row1) = _raster(receiver, samples, seed, jitter, rows)
    bc = bary.reshape(-1, 2)[keep]
    p = scene.tri_p[tri]
    n = scene.tri_n[tri]
    u = bc[:, :1]
    v = bc[:, 1:2]
    position = p[:, 0] + u * (p[:, 1] - p[:, 0]) + v * (p[:, 2] - p[:, 0])
    normal = n[:, 0] + u * (n[:, 1] - n[:, 0]) + v * (n[:, 2] - n[:, 0])
    normal = _normalise(normal)
    geo = _normalise(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]))
    flip = np.sum(geo * normal, axis=1) < 0
    geo[flip] *= -1.0
    W, H = receiver.resolution
    return SampleBand(W, H, row0, row1, texel, tri, bc, suv.reshape(-1, 2)[keep], position, normal, geo)


def _normalise(a):
    ln = np.linalg.norm(a, axis=1, keepdims=True)
    return np.divide(a, ln, out=np.zeros_like(a), where=ln > 0)


def bands(receiver, samples, max_samples=1 << 20):
    """Row ranges [(j0, j1), ...] so that each band holds at most ~``max_samples`` samples."""
    W, H = receiver.resolution
    S = grid_side(samples) ** 2
    rows = max(1, int(max_samples // max(1, W * S)))
    return [(j, min(H, j + rows)) for j in range(0, H, rows)]


TEXEL_BLOCK = 4096  # texels per work item of texel_irradiance (its partial statistics: one row per block)


def texel_irradiance(sums, cover, flux=None, area=None):
    """A receiver's (W*H, 3) texel values and their statistics.  A covered texel (``cover``
    > 0 samples) holds the mean of its samples, ``sums`` / ``cover``, plus, where a flux
    estimator deposited ``flux`` (W*H, 3) watts and the texel has world ``area`` > 0 (m²,
    ``texel_areas``), the irradiance flux / area; other texels are 0.  Returns (values,
    {"texels_covered", "texels_touched" (a positive channel), "max_irradiance",
    "mean_irradiance_covered"}).  One pass over the texels in parallel blocks."""
    n = cover.shape[0]
    img = np.zeros((n, 3))
    has_flux = flux is not None
    if not has_flux:
        flux, area = np.zeros((0, 3)), np.zeros(0)
    partial = np.zeros((-(-n // TEXEL_BLOCK), 4))
    _texel_values(np.ascontiguousarray(sums, dtype=np.float64), np.ascontiguousarray(cover, dtype=np.int64),
                  np.ascontiguousarray(flux, dtype=np.float64), np.ascontiguousarray(area, dtype=np.float64), has_flux,
                  img, partial)
    covered = int(partial[:, 0].sum())
    peak = float(partial[:, 2].max()) if n else 0.0
    return img, {"texels_covered": covered, "texels_touched": int(partial[:, 1].sum()), "max_irradiance": peak,
                 "mean_irradiance_covered": float(partial[:, 3].sum() / (3 * covered)) if covered else 0.0}


@parallel_range("partial")
def _texel_values(sums, cover, flux, area, has_flux, img, partial, first, last):
    """:func:`texel_irradiance` for blocks [first, last) of TEXEL_BLOCK texels; partial[block]
    = (covered, touched, max (NaN if any value is), sum over covered texels and channels)."""
    n = cover.shape[0]
    for blk in range(first, last):
        covered = 0.0
        touched = 0.0
        peak = 0.0  # the uncovered texels' 0
        nan = False
        total = 0.0
        for t in range(blk * TEXEL_BLOCK, min(n, blk * TEXEL_BLOCK + TEXEL_BLOCK)):
            if cover[t] <= 0:
                continue
            covered += 1.0
            positive = False
            for c in range(3):
                v = sums[t, c] / cover[t]
                if has_flux and area[t] > 0.0:
                    v = v + flux[t, c] / area[t]
                img[t, c] = v
                total += v
                if v > 0.0:
                    positive = True
                    if v > peak:
                        peak = v
                elif v != v:
                    nan = True
            if positive:
                touched += 1.0
        partial[blk, 0] = covered
        partial[blk, 1] = touched
        partial[blk, 2] = np.nan if nan else peak
        partial[blk, 3] = total


@kernel
def _pad(img, covered, margin):
    H, W, C = img.shape
    done = covered.copy()
    todo = 0
    for j in range(H):
        for i in range(W):
            if not done[j, i]:
                todo += 1
    # a pass's new texels are held aside (at most every texel not yet covered) and written
    # after the pass, so each pass reads only the texels done before it
    new_at = np.empty(todo, dtype=np.int64)
    new_value = np.empty((todo, C))
    acc = np.zeros(C)
    for _ in range(margin):
        n_new = 0
        for j in range(H):
            for i in range(W):
                if done[j, i]:
                    continue
                cnt = 0.0
                for c in range(C):
                    acc[c] = 0.0
                for dj in range(-1, 2):
                    for di in range(-1, 2):
                        jj = j + dj
                        ii = i + di
                        if 0 <= jj < H and 0 <= ii < W and done[jj, ii]:
                            cnt += 1.0
                            for c in range(C):
                                acc[c] += img[jj, ii, c]
                if cnt > 0.0:
                    for c in range(C):
                        new_value[n_new, c] = acc[c] / cnt
                    new_at[n_new] = j * W + i
                    n_new += 1
        if n_new == 0:
            break
        for k in range(n_new):
            j = new_at[k] // W
            i = new_at[k] - j * W
            for c in range(C):
                img[j, i, c] = new_value[k, c]
            done[j, i] = True
    return done


def pad(image, covered, margin=16):
    """Extend covered texels outwards by ``margin`` texels (Blender's "Extend" bake margin).

    Each pass gives every uncovered texel that touches a covered one (8-neighbourhood) the
    mean of those neighbours, then counts it as covered.  ``image``: (H, W, C) or (H, W);
    returns (padded copy, mask of texels with a value).
    """
    img = np.array(image, dtype=np.float64, copy=True)
    squeeze = img.ndim == 2
    if squeeze:
        img = img[:, :, None]
    cov = np.ascontiguousarray(covered, dtype=np.bool_)
    if img.shape[:2] != cov.shape:
        raise ValueError(f"image {img.shape[:2]} and coverage {cov.shape} differ")
    np.copyto(img, 0.0, where=~cov[:, :, None])
    done = _pad(img, cov, int(max(0, margin)))
    return (img[:, :, 0] if squeeze else img), done
