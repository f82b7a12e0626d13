"""The live pre-pass of the two-bounce solver: where in (u1, v1) can a and b vanish together.

a and b are converted to tensor Bernstein form on boxes of a quadtree over [-m, 1 + m]²
(Fan et al. 2024 §4.1's range bound applied per box); a box is dropped where a or b keeps
one sign, beyond u1 + v1 = 1 + m, where the ray of its x1 misses triangle 2
(``misses_second``, the rational map of eq 14-17) or where β leaves the √ piece's band.
``live_pieces_band`` returns the v1 pieces the resultant scan still has to visit.

Tested in tests/solver/test_solver_two_bounce.py (the pieces cover every common zero, the
hit test at 144 points per dropped box) and tests/solver/test_solver_simd.py (the box
conversion against its scalar form).
"""

import math

from ...runtime.jit import kernel
from ...runtime.simd import CHUNK as SIMD_CHUNK
from ...runtime.simd import (SMALL_BOX_DEGREE, casteljau_halves, rows_add_scaled, rows_scale, small_box_range,
                             square_min_max_abs, transpose_blocks)
from .params import (BETA_SLOT, HIT_SLOT, HIT_TEST, LIVE_DEPTH, LIVE_DEPTH_LOW, LIVE_LOW_DEGREE, LIVE_SLOT0, LIVE_TOL,
                     MAXD)
from ...polynomials.bivariate import bmax


@kernel
def binomial_ratios(d, R):
    """R[k, i] = C(k, i) / C(d, i) for i ≤ k ≤ d (power -> Bernstein weights of degree d)."""
    cd = 1.0
    for i in range(d + 1):
        r = 1.0 / cd
        R[i, i] = r
        for k in range(i + 1, d + 1):
            r *= k / (k - i)
            R[k, i] = r
        cd = cd * (d - i) / (i + 1.0)


@kernel
def check_whole_vectors(A, d):
    """The simd row operations below run on whole vectors: d + 1 rounded up to a multiple
    of SIMD_CHUNK elements of a row (they do not check; the biv slots are 48 x 48)."""
    if A.shape[0] < d + 1 or A.shape[1] < SIMD_CHUNK * ((d + SIMD_CHUNK) // SIMD_CHUNK):
        raise ValueError("tensor Bernstein arrays must hold whole vectors of simd.CHUNK elements")


@kernel
def _shift_rows(A, d, lo, w):
    """A[i, :] are the coefficients of s^i along the first axis: substitute s = lo + w t
    (Taylor shift, then scaling), whole rows at a time (simd row operations).  A is
    triangular (row i zero beyond column d - i; the shift keeps it so): each row operation
    covers the columns where its source row may be nonzero (the others would add zeros)."""
    for k in range(d):
        for i in range(d - 1, k - 1, -1):
            rows_add_scaled(A[i], A[i + 1], lo, d - i)
    f = 1.0
    for i in range(d + 1):
        rows_scale(A[i], f, d + 1 - i)
        f *= w


@kernel
def _bernstein_rows(A, d, R, B, triangular):
    """B[k, :] = Σ_(i ≤ k) R[k, i] A[i, :]: power -> Bernstein along the first axis
    (triangular: row i of A is zero beyond column d - i, so its operations stop there)."""
    for k in range(d + 1):
        for q in range(d + 1):
            B[k, q] = 0.0
        for i in range(k + 1):
            rows_add_scaled(B[k], A[i], R[k, i], d + 1 - i if triangular else d + 1)


@kernel
def tensor_bernstein(p, d, lo, w, R, out, t0, t1):
    """:func:`tensor_bernstein_box` over the square [lo, lo + w]²."""
    tensor_bernstein_box(p, d, lo, lo, w, R, out, t0, t1)


@kernel
def tensor_bernstein_box(p, d, u0, v0, w, R, out, t0, t1):
    """p (triangular power basis, p[i, j] u^i v^j, total degree d) -> its tensor Bernstein
    coefficients of degree (d, d) over the square [u0, u0 + w] × [v0, v0 + w] (out[i, j]: u
    index i, v index j).  Taylor shift and scaling along u, then v, then the power -> Bernstein weights
    R (:func:`binomial_ratios`) along u, then v; every step is a positive combination or an
    exact shift, so the coefficients carry rounding of the size of the polynomial's max-norm
    only.  Each step runs on whole rows (the v steps on the transpose, t0 and t1 scratch);
    the zeros above the triangle stay zero."""
    check_whole_vectors(out, d)
    check_whole_vectors(t0, d)
    check_whole_vectors(t1, d)
    for i in range(d + 1):
        for j in range(d + 1):
            out[i, j] = p[i, j] if i + j <= d else 0.0
    _shift_rows(out, d, u0, w)
    transpose_square(out, d, t0)
    _shift_rows(t0, d, v0, w)
    transpose_square(t0, d, out)
    _bernstein_rows(out, d, R, t1, True)
    transpose_square(t1, d, t0)
    _bernstein_rows(t0, d, R, t1, False)
    transpose_square(t1, d, out)


@kernel
def _split_u(src, d, left, right):
    """de Casteljau at the midpoint of the u axis (rows i) of the tensor Bernstein form src
    into left and right (:func:`simd.casteljau_halves`: whole rows, the arrays hold 48 x 48,
    the columns up to the block edge are computed on and never read)."""
    check_whole_vectors(src, d)
    check_whole_vectors(left, d)
    check_whole_vectors(right, d)
    casteljau_halves(src, d, left, right)


@kernel
def transpose_square(src, d, dst):
    """dst[j, i] = src[i, j] for i, j ≤ d; by 8 x 8 blocks in registers where both arrays
    hold whole blocks (the biv slots: 48 x 48), which also moves the elements up to the
    block edge (never read)."""
    blocks = (d + SIMD_CHUNK) // SIMD_CHUNK
    w = SIMD_CHUNK * blocks
    if min(src.shape[0], src.shape[1], dst.shape[0], dst.shape[1]) >= w:
        transpose_blocks(src, dst, blocks)
        return
    for i in range(d + 1):
        for j in range(d + 1):
            dst[j, i] = src[i, j]


@kernel
def _split_v(src, d, left, right, t0, t1, t2):
    """de Casteljau at the midpoint of the v axis: :func:`_split_u` of the transpose (t0, t1,
    t2 scratch), the same arithmetic in the same order as along u."""
    transpose_square(src, d, t0)
    _split_u(t0, d, t1, t2)
    transpose_square(t1, d, left)
    transpose_square(t2, d, right)


@kernel
def _may_vanish(c, d, tol):
    """False when the tensor Bernstein coefficients c all exceed tol or all lie below -tol
    (tol absolute: the rounding of the conversion is relative to the whole polynomial's
    scale, not to a small box's, where |p| may be far below it)."""
    lo, hi, _ = square_min_max_abs(c, d)
    return not (lo > tol or hi < -tol)


@kernel
def _max_abs(c, d):
    return square_min_max_abs(c, d)[2]


@kernel
def _piece_span(v0, w, margin, h, pieces):
    """The scan pieces (k0 .. k1) a leaf [v0, v0 + w] in v1 marks: its own, widened by one
    piece on each side."""
    k0 = max(0, int(math.floor((v0 + margin) / h)) - 1)
    k1 = min(pieces - 1, int(math.floor((v0 + w + margin) / h)) + 1)
    return k0, k1


@kernel
def _pieces_covered(v0, w, margin, h, pieces, live):
    """True when every piece a leaf inside the box [v0, v0 + w] (in v1) could mark is live
    already: the box cannot change the result of :func:`live_pieces` (a leaf's marks are a
    subset of these, floor being monotone)."""
    k0, k1 = _piece_span(v0, w, margin, h, pieces)
    for k in range(k0, k1 + 1):
        if live[k] == 0:
            return False
    return True


@kernel
def live_pieces(a, da, b, db, margin, pieces, biv, boxes, live):
    """:func:`live_pieces_band` without a β band."""
    return live_pieces_band(a, da, b, db, margin, pieces, biv, boxes, live, -math.inf, math.inf)


@kernel
def box_range(biv, src, d, u0, v0, w):
    """(min, max) of the tensor Bernstein coefficients of biv[src] (degree d) over the box
    [u0, u0 + w] × [v0, v0 + w]: bounds of the polynomial there (convex hull property);
    slots BETA_SLOT + 1 .. + 4 as scratch.  Degrees up to simd.SMALL_BOX_DEGREE in registers
    (:func:`simd.small_box_range`: the same numbers, ~5x faster)."""
    R = biv[BETA_SLOT + 1]
    out = biv[BETA_SLOT + 2]
    binomial_ratios(d, R)
    if 1 <= d <= SMALL_BOX_DEGREE:
        return small_box_range(biv[src], d, u0, v0, w, R)
    tensor_bernstein_box(biv[src], d, u0, v0, w, R, out, biv[BETA_SLOT + 3], biv[BETA_SLOT + 4])
    lo, hi, _ = square_min_max_abs(out, d)
    return lo, hi


@kernel
def _out_of_band(biv, u0, v0, w, blo, bhi, tol):
    """True when β provably stays outside [blo, bhi] (widened by tol) on the box."""
    if blo == -math.inf and bhi == math.inf:
        return False
    lo, hi = box_range(biv, BETA_SLOT, 4, u0, v0, w)
    return hi < blo - tol or lo > bhi + tol


@kernel
def _box_max(biv, src, d, u0, v0, w, sign):
    """Upper bound of sign * biv[src] (degree d, sign ±1) on the box (:func:`box_range`)."""
    lo, hi = box_range(biv, src, d, u0, v0, w)
    return hi if sign > 0.0 else -lo


@kernel
def misses_second(biv, u0, v0, w, tol):
    """True when no x1 of the box maps to a point of triangle 2 (widened by the margin stored
    with the system) ahead of it: with κ of one sign σ on the box, σ ũ2 + m σ κ, σ ṽ2 + m σ κ,
    σ ((1 + m) κ - ũ2 - ṽ2) or σ t̃ provably negative (u2 < -m, v2 < -m, u2 + v2 > 1 + m, or
    the scattered ray pointing away from triangle 2's plane).  False where κ may vanish (the
    ray grazes the plane) or no map is stored (degree 0)."""
    dk = int(biv[HIT_SLOT, MAXD, 0])
    m = biv[HIT_SLOT, MAXD, 1]
    if dk <= 0:
        return False
    k_lo, k_hi = box_range(biv, HIT_SLOT, dk, u0, v0, w)
    if k_lo > tol[0]:
        sg = 1.0
    elif k_hi < -tol[0]:
        sg = -1.0
    else:
        return False
    if _box_max(biv, HIT_SLOT + 3, 1, u0, v0, w, sg) < -tol[3]:
        return True
    d = dk + 1
    P = biv[HIT_SLOT + 4]
    for q in range(3):
        for i in range(d + 1):
            for j in range(d + 1 - i):
                kap = biv[HIT_SLOT, i, j]
                if q == 0:
                    P[i, j] = biv[HIT_SLOT + 1, i, j] + m * kap
                elif q == 1:
                    P[i, j] = biv[HIT_SLOT + 2, i, j] + m * kap
                else:
                    P[i, j] = (1.0 + m) * kap - biv[HIT_SLOT + 1, i, j] - biv[HIT_SLOT + 2, i, j]
        if _box_max(biv, HIT_SLOT + 4, d, u0, v0, w, sg) < -tol[1 if q < 2 else 2]:
            return True
    return False


@kernel
def live_pieces_band(a, da, b, db, margin, pieces, biv, boxes, live, blo, bhi):
    """live[k] = 1 for the scan pieces whose v1 range a common zero of a and b with
    u1 ∈ [-m, 1 - v1 + m] can lie in; returns their count.

    Quadtree over [-m, 1 + m]² (LIVE_DEPTH levels) on the tensor Bernstein forms of a and b
    (convex hull property: a box where the coefficients of a, or of b, share one sign holds
    no zero of it; rounding is absorbed by LIVE_TOL of the polynomial's largest coefficient
    over the whole square — de Casteljau only averages, so it never grows); a box entirely
    beyond u1 + v1 = 1 + m is dropped.  The v1 range of every leaf left, widened by one piece on each side, marks
    its pieces.  Resultant roots elsewhere have their common u1 outside the triangle (or
    complex): most of a planted tuple's ~100 real roots (RT, TT), each of which costs
    Illinois determinants, refinement of its kinks and candidates that lead nowhere.

    With a band [blo, bhi] (not ±inf), a box where β (biv[BETA_SLOT]) provably stays
    outside it is dropped as well (:func:`_out_of_band`): an eq (23) √ piece's system
    approximates the refraction only where β/S² lies in (or next to) the piece's interval,
    and the paths elsewhere are the roots of the other pieces' systems (``SQRT_BANDS``).

    Only the v1 pieces are the result, so a box whose pieces are all live already (another
    box of the same v1 column marked them) is not split further (:func:`_pieces_covered`):
    the same live pieces for fewer de Casteljau splits of b (the a-curve crosses a column
    of boxes several times)."""
    h = (1.0 + 2.0 * margin) / pieces
    for k in range(pieces):
        live[k] = 0
    # rounding allowances of the hit test: of the size of each polynomial's coefficients
    dk = int(biv[HIT_SLOT, MAXD, 0])
    hit_tol = (0.0, 0.0, 0.0, 0.0)
    if HIT_TEST and dk > 0:
        mk = bmax(biv[HIT_SLOT], dk)
        mu = bmax(biv[HIT_SLOT + 1], dk + 1) + bmax(biv[HIT_SLOT + 2], dk + 1)
        mt = bmax(biv[HIT_SLOT + 3], 1)
        hit_tol = (1e-11 * mk, 1e-11 * (mu + mk), 1e-11 * (mu + 2.0 * mk), 1e-11 * mt)
        if misses_second(biv, -margin, -margin, 1.0 + 2.0 * margin, hit_tol):
            return 0
    else:
        dk = 0
    depth = LIVE_DEPTH_LOW if db <= LIVE_LOW_DEGREE else LIVE_DEPTH
    R = biv[40]
    dm = max(da, db)
    binomial_ratios(da, R)
    tensor_bernstein(a, da, -margin, 1.0 + 2.0 * margin, R, biv[LIVE_SLOT0], biv[34], biv[35])
    binomial_ratios(db, R)
    tensor_bernstein(b, db, -margin, 1.0 + 2.0 * margin, R, biv[LIVE_SLOT0 + 1], biv[34], biv[35])
    tol_a = LIVE_TOL * _max_abs(biv[LIVE_SLOT0], da)
    tol_b = LIVE_TOL * _max_abs(biv[LIVE_SLOT0 + 1], db)
    tol_beta = 0.0
    if blo != -math.inf or bhi != math.inf:
        tol_beta = 1e-12 * (_max_abs(biv[BETA_SLOT], 4) + max(abs(blo) if blo != -math.inf else 0.0,
                                                             abs(bhi) if bhi != math.inf else 0.0))
    boxes[0, 0] = -margin
    boxes[0, 1] = -margin
    boxes[0, 2] = 1.0 + 2.0 * margin
    boxes[0, 3] = 0.0
    top = 1
    n_live = 0
    while top > 0:
        top -= 1
        u0 = boxes[top, 0]
        v0 = boxes[top, 1]
        w = boxes[top, 2]
        level = boxes[top, 3]
        ca = biv[LIVE_SLOT0 + 2 * top]
        cb = biv[LIVE_SLOT0 + 2 * top + 1]
        if level < 0.0 or u0 + v0 > 1.0 + margin:
            continue
        if _pieces_covered(v0, w, margin, h, pieces, live):
            continue
        if level == 0.0 and _out_of_band(biv, u0, v0, w, blo, bhi, tol_beta):
            continue
        if not _may_vanish(ca, da, tol_a) or not _may_vanish(cb, db, tol_b):
            continue
        if level >= depth:
            k0, k1 = _piece_span(v0, w, margin, h, pieces)
            for k in range(k0, k1 + 1):
                if live[k] == 0:
                    live[k] = 1
                    n_live += 1
            continue
        # children in slots top .. top + 3 (u half su, v half sv -> top + 2 su + sv): a's
        # first; b (up to 3x a's degree, ~25x the work) only for the u halves where one of
        # a's children may vanish
        _split_u(ca, da, biv[41], biv[42])
        hw = 0.5 * w
        for c in range(4):
            boxes[top + c, 0] = u0 + (c // 2) * hw
            boxes[top + c, 1] = v0 + (c % 2) * hw
            boxes[top + c, 2] = hw
            boxes[top + c, 3] = level + 1.0
        for su in range(2):
            _split_v(biv[41 + su], da, biv[LIVE_SLOT0 + 2 * (top + 2 * su)], biv[LIVE_SLOT0 + 2 * (top + 2 * su + 1)],
                     biv[34], biv[35], biv[36])
        keep = 0
        for su in range(2):
            for sv in range(2):
                c = 2 * su + sv
                if boxes[top + c, 0] + boxes[top + c, 1] > 1.0 + margin or \
                        _pieces_covered(boxes[top + c, 1], hw, margin, h, pieces, live) or \
                        _out_of_band(biv, boxes[top + c, 0], boxes[top + c, 1], hw, blo, bhi, tol_beta) or \
                        not _may_vanish(biv[LIVE_SLOT0 + 2 * (top + c)], da, tol_a) or \
                        (dk > 0 and misses_second(biv, boxes[top + c, 0], boxes[top + c, 1], hw, hit_tol)):
                    boxes[top + c, 3] = -1.0  # dead
                else:
                    keep |= 1 << su
        if keep != 0:
            _split_u(cb, db, biv[43], biv[44])
            for su in range(2):
                if (keep >> su) & 1:
                    _split_v(biv[43 + su], db, biv[LIVE_SLOT0 + 2 * (top + 2 * su) + 1],
                             biv[LIVE_SLOT0 + 2 * (top + 2 * su + 1) + 1], biv[34], biv[35], biv[36])
        top += 4
    return n_live
