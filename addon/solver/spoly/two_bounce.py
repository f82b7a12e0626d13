"""Two-bounce Specular Polynomials: the RR, RT, TR and TT chains (Fan et al. 2024, §3.4–4.3).

For a tuple (x0, triangle 1, triangle 2, x3) the unknowns are the barycentrics (u1, v1) of x1.
The scaled scattered direction d̃1 (reflection eq 19, degree 3; refraction eq 21–22 with √β
replaced by the piecewise rational r of eq 23, or by one Heron step on a fitted quadratic
where that fits the triangle, ``heron_sqrt_fit``) is mapped to triangle 2 by the rational
coordinate mapping (eq 14–17: u2 = ũ2/κ, v2 = ṽ2/κ), so that the constraints at vertex 2
become a bivariate polynomial system (Table 3): coplanarity a (eq 6) and the law at vertex 2,
b (R: product form eq 13; T: square form eq 10 with η_in on the light's side).  c2 is the
normal of the plane of incidence, so that neither form vanishes on whole curves.

Solve, per system (``solve_two_bounce_batch``):
1. *Pre-pass* (``live_pieces``): a and b in tensor Bernstein form on a quadtree over
   [-m, 1+m]²; boxes where a or b keeps one sign, that lie beyond u1 + v1 = 1 + m, whose ray
   misses triangle 2 (``_misses_second``) or where β leaves the √ piece's band are dropped.
2. *Resultant scan* (eq 28–31): u1 eliminated by the hybrid Bézout matrix (its determinant is
   the Sylvester resultant), evaluated at v1 by pivoted elimination carrying sign and log
   magnitude; the live v1 pieces are scanned for sign changes, each pinned by Illinois
   regula falsi to ``ROOT_TOL``; pieces around productive roots and convex kinks of the
   deflated log|det| are refined (``SUB_SAMPLES``, ``REFINE_LEVELS``), one-signed dips
   resolved (``_resolve_dip``).
3. *Paths* (§4.3): at each root the u1 roots of a(·, v1) are mapped to triangle 2 by the
   exact scattered ray and Gauss–Newton polished in path space (``two_vertex``), which
   removes the √ approximation error; validated (both vertices inside, sides, TIR, residual)
   and merged when two converge onto one path.
The chain is also solved reversed (reciprocity) to catch root pairs one orientation misses;
a candidate on the line x0 → x3 covers the normal-incidence path through parallel faces.

Invariants: float64; fixed-size scratch per work item, no allocation per tuple; the vector
kernels of ``simd.py`` do the scalar loops' operations in their order (bit for bit).
Tested in tests/solver/test_solver_two_bounce.py (analytic cases, planted paths, brute-force recall
on random and planted sets, the √ fit, the pre-pass hit test at 144 points per dropped box)
and bench/two_bounce_recall.py (10,000-tuple acceptance sets).  Design decisions and their
measurements: docs/decisions/two-bounce-solver.md.
"""

import math

import numpy as np

from ..runtime.jit import kernel, prange
from ..paths.one_vertex import line_crossing_barycentrics
from ..paths.two_vertex import pack_geometry, polish_and_validate2, trace_to_second
from ..geometry.vec3 import row
from ..polynomials.roots import MAX_DEGREE, roots_in_interval
from ..runtime.simd import CHUNK as SIMD_CHUNK
from ..runtime.simd import SMALL_BOX_DEGREE
from ..runtime.simd import (casteljau_halves, lanes_abs_argmax, lanes_sub_scaled, rows_add_scaled,
                            rows_add_scaled_exact, rows_scale, rows_scale_add, small_box_range, square_min_max_abs,
                            transpose_blocks)

MAX_PATHS_TWO_BOUNCE = 8
CHUNK = 16  # tuples per parallel work item (and per ~1.5 MB of zeroed scratch: at 4 its allocation was ~8 µs per tuple)
MAXD = 47  # bivariate arrays are (MAXD + 1)²; b has total degree ≤ 46 (TT)
N_SLOTS = 56  # 0, 1: a, b; 2-36 the system's intermediates, then the live pre-pass's stack (2-33) and its temporaries (34-36, 40-44), then a, b v-major (2, 3); 46: β, 47-50 its box conversion; 51-55: the map to triangle 2
DEFAULT_PIECES = 100
MAX_PIECES = 1024
ROOT_TOL = 1e-4  # v1 brackets are pinned to this; the path-space Newton polish takes it to ~1e-15
V_MARGIN_EXACT = 1e-6
V_MARGIN_APPROX = 2e-2  # √-approximated systems: their roots may sit a little off
REFINE_LEVELS = 1
KINK = 1.0  # second difference of log|det| that flags a root cluster nearby (2.0 loses TT paths: see below)
SUB_SAMPLES = 8
NOISY_CHANGES = 3  # sign changes among one piece's sub-samples beyond which it is noise
DIP_STEPS = 40  # steps resolving a one-signed dip (quadratic model of |det|, golden-section safeguard)
DIP_FLAT = 0.5  # the model's minimum above this fraction of the best sample: a complex pair, stop
STACK_CAP = 64
LIVE_DEPTH = 4  # quadtree levels of the (u1, v1) pre-pass: leaves 1/16 of the range wide (~6 pieces)
LIVE_DEPTH_LOW = 3  # ... where b's degree is at most LIVE_LOW_DEGREE (RR): its scan is cheap, the pre-pass less worth it
LIVE_LOW_DEGREE = 16
LIVE_TOL = 1e-11  # Bernstein coefficients within this fraction of the polynomial's largest count as either sign
LIVE_PREPASS = True
V_MAJOR_SLOT = 2  # biv slots 2, 3: a, b v-major for the determinants (after the pre-pass, whose stack they were)
HIT_TEST = True  # the pre-pass also drops boxes whose x1 cannot reach triangle 2 (``_misses_second``)
LIVE_SLOT0 = 2  # first biv slot of the pre-pass's box stack (two slots per box: a, b)
LIVE_STACK = 3 * LIVE_DEPTH + 1
LANES = 16  # det_bezout's sliding window: g's u-degree m at most this (a: 16 at most); the lane tuple below has 16
WINDOW_FROM = 24  # ... for matrices at least this large (below, the dense elimination is as fast)
TWO_PROJECTIONS = False  # also scan the other hidden variable (u1) of each orientation
BOTH_DIRECTIONS = True  # solve the chain forward and reversed (reciprocity)
TIR_FALLBACK_REFINE = False  # refine the TIR fallback's system (eq (23) piece 0, centroid in TIR) like the others
SQRT_ALL_PIECES = False  # solve once per √ piece overlapping the triangle's β range (slow)
SQRT_BANDS = True  # an eq (23) piece's system only where β/S² can lie in its band (the piece and its neighbours)
SQRT_BAND_REACH = 3  # ... and this many pieces on each side of it (1 and 2 lose paths: see the module doc)
BETA_GRID = 8  # boxes per side of the β-range grid that adds the √ pieces a path could need ...
BETA_MASK_FROM = 5  # ... from this piece up (below: next to TIR, where the bound is loose and pieces many)
HIT_SLOT = 51  # κ, ũ2, ṽ2, t̃ (eq 14-17: x2 = x1 + (t̃/κ) d̃1, (u2, v2) = (ũ2, ṽ2)/κ) for the pre-pass; 55 scratch
HIT_MARGIN_EXACT = 1e-3  # barycentric margin of triangle 2 in the pre-pass's hit test, exact d̃1
HIT_MARGIN_APPROX = 0.25  # ... √-approximated d̃1 (Heron: ~1e-3 rad; a piece used next to its interval: more)
BETA_SLOT = 46  # biv slot of β (eq 22, local frame, degree 4) for the bands
HERON_SQRT = True  # one system per orientation with √β ≈ Heron step from a fitted quadratic, where it fits
HERON_TOL = 1e-3  # the Heron √'s largest relative error over the check grid for the fit to be used
HERON_CUT = 0.03  # ... at the check points with β/S² at least this; the √ pieces below it (eq 23) stay
HERON_FIT_GRID = 10  # fit points: barycentric grid of this order on the triangle widened by the v margin
HERON_CHECK_GRID = 12  # check points (a finer grid of the same triangle)
PRODUCTIVE_RADIUS = 0.02  # a root is productive when a path it polished into lies this close (hidden variable)
B_RELATIVE = 1e-2  # a u-root of a(·, v*) is a candidate when |b| / Σ|b_i u^i| is below this
POLISH_STEPS = 40
ACCEPT_RESIDUAL = 1e-12
SAME_PATH = 1e-7
NEAR_PATH = 1e-5
N_SEEDS = 6  # seeded-polish fallback: grid divisions on triangle 1

# Statistics row (summed by the API's report).
STAT_ROOTS = 0
STAT_CANDIDATES = 1
STAT_PATHS = 2
STAT_SKIPPED = 3
STAT_DETS = 4
STAT_ACCEPTED = 5  # candidates that polished into a valid path (new or a copy)
STAT_NEAR = 6  # ... whose path lies within PRODUCTIVE_RADIUS of the root in the hidden variable
N_STATS = 7

# (lo, hi, c0, c1, d1): √x ≈ (c0 + c1 x) / (1 + d1 x) on [lo, hi].
SQRT_PIECES = np.array([
    [0.0, 8.446092340565198e-08, 7.902524043324177e-06, 9273.011659325857, 20933683.488983016],
    [8.446092340565198e-08, 7.382000202911856e-06, 0.0002833414823529851, 865.3912558767215, 204672.27299967175],
    [7.382000202911856e-06, 7.996008668082331e-05, 0.0016021152181714942, 190.08358008482014, 11150.216722758309],
    [7.996008668082331e-05, 0.0004273580422165819, 0.004470744106873375, 71.31728523639126, 1627.426048518019],
    [0.0004273580422165819, 0.0015686563924769323, 0.009457574738559115, 34.3184711592571, 382.77147728374246],
    [0.0015686563924769323, 0.004549308378447099, 0.01712939245697036, 19.11602546583693, 119.7286577063096],
    [0.004549308378447099, 0.011215438668410951, 0.028054589379623806, 11.73073766943272, 45.301964781877075],
    [0.011215438668410951, 0.02454642456699124, 0.04280101287940887, 7.713421305240593, 19.645973977707882],
    [0.02454642456699124, 0.04904548364121981, 0.061936514380999695, 5.341605188295157, 9.440828307171655],
    [0.04904548364121981, 0.09118830881277133, 0.08602895090623522, 3.851396317329236, 4.915076382580425],
    [0.09118830881277133, 0.15992975382726443, 0.11564618494862205, 2.8681479761581574, 2.728706973589053],
    [0.15992975382726443, 0.26726856704054847, 0.15135608405954754, 2.1932417983266723, 1.596886526213849],
    [0.26726856704054847, 0.4288701802945861, 0.19372652037895371, 1.71462827644936, 0.9765838960781249],
    [0.4288701802945861, 0.6647475381741225, 0.24332536975163052, 1.365797818199514, 0.6199467885521434],
    [0.6647475381741225, 1.0, 0.30072051142615275, 1.1055615503450655, 0.4063663121380604],
])


# where the Heron √ does not fit above HERON_CUT, higher cuts in turn (the starts of eq (23)'s
# pieces 10-14): the fit then covers less of the triangle, and the pieces below it are solved
HERON_CUTS = np.concatenate((np.array([HERON_CUT]), SQRT_PIECES[10:, 0]))


@kernel
def _centroid_piece(xc, mask):
    """(mask with the √ piece of the centroid's β/S² = xc (clamped to ≥ 0) added, the piece
    solved only as the TIR fallback or -2).  With the centroid in total internal reflection
    (xc ≤ 0) and piece 0 not sampled already, piece 0 (its band reaches β = 0) is solved for
    the paths next to the TIR curve, its sign changes only: that system is the noisiest of
    all (the √'s pole sits at the TIR curve) and its kink refinement cost 45 % of random TT's
    determinants for ~0.05 % of the paths (``TIR_FALLBACK_REFINE``; module doc)."""
    if xc > 0.0 or mask & 1 or TIR_FALLBACK_REFINE:
        return mask | (1 << _sqrt_piece(xc)), -2
    return mask | 1, 0


@kernel
def _sqrt_piece(x):
    k = 0
    while k < SQRT_PIECES.shape[0] - 1 and x > SQRT_PIECES[k, 1]:
        k += 1
    return k


@kernel
def sqrt_approx(x):
    """The piecewise rational √x of eq (23) (x clamped to [0, 1])."""
    x = min(max(x, 0.0), 1.0)
    k = 0
    while k < SQRT_PIECES.shape[0] - 1 and x > SQRT_PIECES[k, 1]:
        k += 1
    return (SQRT_PIECES[k, 2] + SQRT_PIECES[k, 3] * x) / (1.0 + SQRT_PIECES[k, 4] * x)


# --- bivariate polynomials: p[i, j] multiplies u^i v^j, total degree tracked by the caller --


@kernel
def _bzero(p, d):
    for i in range(d + 1):
        for j in range(d + 1 - i):
            p[i, j] = 0.0


@kernel
def _bmul_acc(p, dp, q, dq, out, coef):
    """out += coef p q (out must be sized for total degree dp + dq)."""
    for i1 in range(dp + 1):
        for j1 in range(dp + 1 - i1):
            c = p[i1, j1]
            if c == 0.0:
                continue
            c *= coef
            for i2 in range(dq + 1):
                rows_add_scaled_exact(out[i1 + i2, j1:], q[i2], c, dq + 1 - i2)


@kernel
def _badd(out, d, a, da, ca):
    """out += ca a (da ≤ d)."""
    for i in range(da + 1):
        rows_add_scaled_exact(out[i], a[i], ca, da + 1 - i)


@kernel
def _vlin(V, c0, cu, cv):
    """Vector polynomial of degree 1: c0 + u cu + v cv."""
    for c in range(3):
        _bzero(V[c], 1)
        V[c, 0, 0] = c0[c]
        V[c, 1, 0] = cu[c]
        V[c, 0, 1] = cv[c]


@kernel
def _vdot(A, dA, B, dB, out):
    d = dA + dB
    _bzero(out, d)
    for c in range(3):
        _bmul_acc(A[c], dA, B[c], dB, out, 1.0)
    return d


@kernel
def _vcross(A, dA, B, dB, out):
    d = dA + dB
    for c in range(3):
        _bzero(out[c], d)
    for c in range(3):
        c1 = (c + 1) % 3
        c2 = (c + 2) % 3
        _bmul_acc(A[c1], dA, B[c2], dB, out[c], 1.0)
        _bmul_acc(A[c2], dA, B[c1], dB, out[c], -1.0)
    return d


@kernel
def _vdot_const(A, dA, w, out):
    _bzero(out, dA)
    for c in range(3):
        _badd(out, dA, A[c], dA, w[c])
    return dA


@kernel
def _vcross_const(A, dA, w, out):
    """out = A × w."""
    for c in range(3):
        _bzero(out[c], dA)
    for c in range(3):
        c1 = (c + 1) % 3
        c2 = (c + 2) % 3
        _badd(out[c], dA, A[c1], dA, w[c2])
        _badd(out[c], dA, A[c2], dA, -w[c1])
    return dA


@kernel
def _bmax(p, d):
    m = 0.0
    for i in range(d + 1):
        for j in range(d + 1 - i):
            m = max(m, abs(p[i, j]))
    return m


@kernel
def _u_degree(p, d, tiny):
    """Largest i with a coefficient above tiny in row i; smaller rows are zeroed."""
    n = d
    while n > 0:
        big = 0.0
        for j in range(d - n + 1):
            big = max(big, abs(p[n, j]))
        if big > tiny:
            break
        for j in range(d - n + 1):
            p[n, j] = 0.0
        n -= 1
    return n


@kernel
def _bernstein_has_zero(p, d, rel_margin, work):
    """False when p (total degree d) provably has no zero on the triangle u, v ≥ 0, u+v ≤ 1:
    all triangular Bernstein coefficients share one sign by more than rel_margin · max."""
    lo = math.inf
    hi = -math.inf
    big = 0.0
    # falling factorial ratios via work[0]: log-free direct products (d ≤ 16 here)
    for i in range(d + 1):
        for j in range(d + 1 - i):
            acc = 0.0
            fi = 1.0  # i! / (i - i')!
            for i2 in range(i + 1):
                fj = 1.0
                # (d - i2 - j2)! / d!  = 1 / (d (d-1) ... (d - i2 - j2 + 1))
                g = 1.0
                for t in range(i2):
                    g /= (d - t)
                for j2 in range(j + 1):
                    c = p[i2, j2]
                    if c != 0.0:
                        acc += c * fi * fj * g
                    fj *= (j - j2)
                    if d - i2 - j2 > 0:
                        g /= (d - i2 - j2)
                fi *= (i - i2)
            lo = min(lo, acc)
            hi = max(hi, acc)
            big = max(big, abs(acc))
    margin = rel_margin * big
    return not (lo > margin or hi < -margin)


# --- the live pre-pass: where in (u1, v1) can a and b vanish together ----------------------


@kernel
def _binomial_ratios(d, R):
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
def _check_whole_vectors(A, d):
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
def _tensor_bernstein(p, d, lo, w, R, out, t0, t1):
    """:func:`_tensor_bernstein_box` over the square [lo, lo + w]²."""
    _tensor_bernstein_box(p, d, lo, lo, w, R, out, t0, t1)


@kernel
def _tensor_bernstein_box(p, d, u0, v0, w, R, out, t0, t1):
    """p (triangular power basis, p[i, j] u^i v^j, total degree d) -> its tensor Bernstein
    coefficients of degree (d, d) over the square [u0, u0 + w] × [v0, v0 + w] (out[i, j]: u
    index i, v index j).  Taylor shift and scaling along u, then v, then the power -> Bernstein weights
    R (:func:`_binomial_ratios`) along u, then v; every step is a positive combination or an
    exact shift, so the coefficients carry rounding of the size of the polynomial's max-norm
    only.  Each step runs on whole rows (the v steps on the transpose, t0 and t1 scratch);
    the zeros above the triangle stay zero."""
    _check_whole_vectors(out, d)
    _check_whole_vectors(t0, d)
    _check_whole_vectors(t1, d)
    for i in range(d + 1):
        for j in range(d + 1):
            out[i, j] = p[i, j] if i + j <= d else 0.0
    _shift_rows(out, d, u0, w)
    _transpose_square(out, d, t0)
    _shift_rows(t0, d, v0, w)
    _transpose_square(t0, d, out)
    _bernstein_rows(out, d, R, t1, True)
    _transpose_square(t1, d, t0)
    _bernstein_rows(t0, d, R, t1, False)
    _transpose_square(t1, d, out)


@kernel
def _split_u(src, d, left, right):
    """de Casteljau at the midpoint of the u axis (rows i) of the tensor Bernstein form src
    into left and right (:func:`simd.casteljau_halves`: whole rows, the arrays hold 48 x 48,
    the columns up to the block edge are computed on and never read)."""
    _check_whole_vectors(src, d)
    _check_whole_vectors(left, d)
    _check_whole_vectors(right, d)
    casteljau_halves(src, d, left, right)


@kernel
def _transpose_square(src, d, dst):
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
    _transpose_square(src, d, t0)
    _split_u(t0, d, t1, t2)
    _transpose_square(t1, d, left)
    _transpose_square(t2, d, right)


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
def _box_range(biv, src, d, u0, v0, w):
    """(min, max) of the tensor Bernstein coefficients of biv[src] (degree d) over the box
    [u0, u0 + w] × [v0, v0 + w]: bounds of the polynomial there (convex hull property);
    slots BETA_SLOT + 1 .. + 4 as scratch.  Degrees up to simd.SMALL_BOX_DEGREE in registers
    (:func:`simd.small_box_range`: the same numbers, ~5x faster)."""
    R = biv[BETA_SLOT + 1]
    out = biv[BETA_SLOT + 2]
    _binomial_ratios(d, R)
    if 1 <= d <= SMALL_BOX_DEGREE:
        return small_box_range(biv[src], d, u0, v0, w, R)
    _tensor_bernstein_box(biv[src], d, u0, v0, w, R, out, biv[BETA_SLOT + 3], biv[BETA_SLOT + 4])
    lo, hi, _ = square_min_max_abs(out, d)
    return lo, hi


@kernel
def _out_of_band(biv, u0, v0, w, blo, bhi, tol):
    """True when β provably stays outside [blo, bhi] (widened by tol) on the box."""
    if blo == -math.inf and bhi == math.inf:
        return False
    lo, hi = _box_range(biv, BETA_SLOT, 4, u0, v0, w)
    return hi < blo - tol or lo > bhi + tol


@kernel
def _box_max(biv, src, d, u0, v0, w, sign):
    """Upper bound of sign * biv[src] (degree d, sign ±1) on the box (:func:`_box_range`)."""
    lo, hi = _box_range(biv, src, d, u0, v0, w)
    return hi if sign > 0.0 else -lo


@kernel
def _misses_second(biv, u0, v0, w, tol):
    """True when no x1 of the box maps to a point of triangle 2 (widened by the margin stored
    with the system) ahead of it: with κ of one sign σ on the box, σ ũ2 + m σ κ, σ ṽ2 + m σ κ,
    σ ((1 + m) κ - ũ2 - ṽ2) or σ t̃ provably negative (u2 < -m, v2 < -m, u2 + v2 > 1 + m, or
    the scattered ray pointing away from triangle 2's plane).  False where κ may vanish (the
    ray grazes the plane) or no map is stored (degree 0)."""
    dk = int(biv[HIT_SLOT, MAXD, 0])
    m = biv[HIT_SLOT, MAXD, 1]
    if dk <= 0:
        return False
    k_lo, k_hi = _box_range(biv, HIT_SLOT, dk, u0, v0, w)
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
        mk = _bmax(biv[HIT_SLOT], dk)
        mu = _bmax(biv[HIT_SLOT + 1], dk + 1) + _bmax(biv[HIT_SLOT + 2], dk + 1)
        mt = _bmax(biv[HIT_SLOT + 3], 1)
        hit_tol = (1e-11 * mk, 1e-11 * (mu + mk), 1e-11 * (mu + 2.0 * mk), 1e-11 * mt)
        if _misses_second(biv, -margin, -margin, 1.0 + 2.0 * margin, hit_tol):
            return 0
    else:
        dk = 0
    depth = LIVE_DEPTH_LOW if db <= LIVE_LOW_DEGREE else LIVE_DEPTH
    R = biv[40]
    dm = max(da, db)
    _binomial_ratios(da, R)
    _tensor_bernstein(a, da, -margin, 1.0 + 2.0 * margin, R, biv[LIVE_SLOT0], biv[34], biv[35])
    _binomial_ratios(db, R)
    _tensor_bernstein(b, db, -margin, 1.0 + 2.0 * margin, R, biv[LIVE_SLOT0 + 1], biv[34], biv[35])
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
                        (dk > 0 and _misses_second(biv, boxes[top + c, 0], boxes[top + c, 1], hw, hit_tol)):
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


# --- the resultant's determinant at one v1 -----------------------------------------------


@kernel
def v_major(p, d, out):
    """out[j, i] = p[i, j] for i + j ≤ d and 0 beyond, in rows j ≤ d up to the block edge:
    a bivariate polynomial (p[i, j] u^i v^j, total degree d) in the layout the determinant
    family reads (``det_bezout`` and its callers: their ``at``, ``bt``).  There one Horner
    step in v of all the u-coefficients at once is one vector operation on a row, where
    on p it gathers a column (:func:`_coeffs_at`)."""
    _check_whole_vectors(out, d)
    _transpose_square(p, d, out)
    w = SIMD_CHUNK * ((d + SIMD_CHUNK) // SIMD_CHUNK)
    for j in range(d + 1):
        for i in range(d - j + 1, w):
            out[j, i] = 0.0


@kernel
def _coeffs_at(pt, d, n, v, out):
    """out[i] = p_i(v) (coefficient of u^i) for i ≤ n, scaled to unit max-norm; returns the scale.
    pt: p in the v-major layout (:func:`v_major`).

    Horner in v for all rows at once: step j is out = out v + pt[j], a vector operation on
    whole vectors (rows_scale_add; pt's zeros beyond the triangle keep each out[i] at 0
    until its first term, so every out[i] for i ≤ n gets exactly one Horner loop's
    operations; out[n + 1 ..] up to the block edge is scratch).  Gathering the column p[:, j]
    instead was ~0.5 µs of a ~4 µs (16, 34) determinant."""
    w = SIMD_CHUNK * ((n + SIMD_CHUNK) // SIMD_CHUNK)
    for i in range(w):
        out[i] = 0.0
    for j in range(d, -1, -1):
        rows_scale_add(out, pt[j], v, min(n, d - j) + 1)
    m = 0.0
    for i in range(n + 1):
        m = max(m, abs(out[i]))
    if m > 0.0 and np.isfinite(m):
        inv = 1.0 / m
        for i in range(n + 1):
            out[i] *= inv
    return m


@kernel
def _top_row(pt, d, n):
    """The u-degree of p, at most n (rows above it were zeroed by ``_u_degree``); pt: p
    v-major (:func:`v_major`)."""
    i = min(n, d)
    while i > 0:
        for j in range(d - i + 1):
            if pt[j, i] != 0.0:
                return i
        i -= 1
    return 0


@kernel
def det_bezout(at, da, bt, db, n, v, cf, mat):
    """Sign and log|det| of the hybrid Bézout matrix of (a(·, v), b(·, v)): the resultant
    in u1 at v1 (eq 29), up to a sign that is constant for the system.

    The paper (../shared/seeds/specular_polynomials.txt §2, §4.1-4.2) takes the Bézout
    matrix of eq 29 "due to its numerical stability" and evaluates its determinant by
    Gaussian elimination.  For f of u-degree n and g of u-degree m < n (a has u-degree 8 or
    16 against b's 15 … 46) that matrix has n - m rows that are multiples of g by the leading
    coefficients of f: its determinant is lc(f)^(n-m) times the resultant, and tiny leading
    coefficients (|b_n| ~ 1e-11 of max|b_i| is common) grade those rows so steeply that the
    elimination in doubles loses the determinant: within ±0.004 of the v1 of 18 planted RT
    paths the sign came out wrong at 19 % of the samples (24 of 126, against exact rational
    arithmetic on the same double coefficients: ``bench/two_bounce_recall.py --exact``), so a
    root pair closer than a piece was invisible to the scan and to its refinement, and some
    RT systems were sign noise over whole pieces.  The hybrid Bézout matrix replaces those
    rows by the plain shifts u^k g (k < n - m) and keeps the m rows φ_c = F_hi G_lo - G_hi F_lo
    (f = u^c F_hi + F_lo, g = u^c G_hi + G_lo, c = m … 1) of the Bézoutian: the same size n,
    its determinant the Sylvester resultant (lc(f)^(n-m) divided out, and with it the sign
    changes of lc(f), roots at infinity), and the elimination keeps the sign (wrong at 4 of
    those 126 samples; median log error 8e-8 instead of 1.5).  RT recall at 10,000 tuples:
    99.756 % -> 99.866 % with half the determinant evaluations (sign noise made roots).

    The elimination (:func:`_det_hybrid_window` for n ≥ WINDOW_FROM, else
    :func:`_det_hybrid_dense`) gives the same numbers bit for bit either way.

    at, bt: a and b in the v-major layout (:func:`v_major`).  cf: (2, MAXD + 2) scratch, mat:
    (MAXD, MAXD) scratch.  Returns (sign, log|det|); sign 0 when the elimination meets an
    exactly zero column (or a coefficient vector vanishes)."""
    A = cf[0]
    B = cf[1]
    na = _top_row(at, da, n)
    nb = _top_row(bt, db, n)
    ma = _coeffs_at(at, da, na, v, A)
    mb = _coeffs_at(bt, db, nb, v, B)
    if not (ma > 0.0 and mb > 0.0) or not (np.isfinite(ma) and np.isfinite(mb)):
        return 0, -math.inf
    # f: the polynomial of the larger u-degree nf, g: the other one (degree m)
    F = B
    G = A
    nf = nb
    m = na
    if na > nb:
        F = A
        G = B
        nf = na
        m = nb
    n = nf
    if n == 0:
        return 1, 0.0
    if m == 0:
        # n shift rows of the constant g: G_0^n
        if G[0] == 0.0:
            return 0, -math.inf
        return (-1 if G[0] < 0.0 and n % 2 == 1 else 1), n * math.log(abs(G[0]))
    if m <= LANES and n >= WINDOW_FROM:
        return _det_hybrid_window(F, G, n, m, mat)
    return _det_hybrid_dense(F, G, n, m, A, mat)


@kernel
def _bezoutian_rows(F, G, n, m, out, stride_rows):
    """The m Bézoutian rows φ_c (c = m … 1) of the hybrid Bézout matrix of (f, g) (u-degrees
    n, m ≤ n; F, G their coefficient vectors): φ_c = F_hi G_lo - G_hi F_lo with
    F_hi = Σ_(i ≥ c) F_i u^(i-c), G_lo = Σ_(l < c) G_l u^l (G_hi, F_lo alike), by the
    recurrence up from φ_0 = 0: φ_c[k] = φ_(c-1)[k + 1] + (G_(c-1) F_(k+1) - F_(c-1) G_(k+1))
    (F_hi = F_(c-1) + u F_hi', G_lo = G_lo' + G_(c-1) u^(c-1)): φ_c[k] is the direct sum
    Σ_(l < c) (G_l F_(c+k-l) - F_l G_(c+k-l)), its 2c terms in pairs by ascending l, in
    O(n m) instead of O(n m²) (a (16, 34) determinant 4.2 -> 3.6 µs).  Every rounding
    variant tried moved the 10,000-tuple recall by a few paths either way (the direct sums,
    G terms first: TT 43 missed, RT 7, TR 2; this: 49, 4, 1; the recurrence down from φ_m:
    47, 6, 1; the direct sums along diagonals, one subtraction per element: 46, 7, 1).
    φ_c[k] goes to out[k, m - c] (stride_rows: the rows are columns of out) or out[n - c, k]."""
    for c in range(1, m + 1):
        fc = F[c - 1]
        gc = G[c - 1]
        lane = m - c  # stride_rows: φ_c in column lane of out, φ_(c-1) in lane + 1
        r = n - c  # else: φ_c in row r, φ_(c-1) in row r + 1
        for k in range(n):
            gk = G[k + 1] if k + 1 <= m else 0.0
            t = gc * F[k + 1] - fc * gk
            if c > 1 and k < n - 1:  # φ_(c-1)[n] = 0
                t = (out[k + 1, lane + 1] if stride_rows else out[r + 1, k + 1]) + t
            if stride_rows:
                out[k, lane] = t
            else:
                out[r, k] = t


@kernel
def _log_accumulate(prod, logm, x):
    """log of a product of positive factors, one log per ~100 orders of magnitude instead
    of one per factor: x joins the running product prod (kept within 1e±150, so a factor
    within 1e±100 neither overflows nor underflows it); a factor outside that range, or a
    product leaving it, goes into logm.  The result is log(prod) + logm; its rounding is
    that of the product, ~n ulp, as the sum of n logs (34 logs were ~5 % of a (16, 34)
    determinant)."""
    if x > 1e-100 and x < 1e100:
        prod *= x
        if prod < 1e-150 or prod > 1e150:
            return 1.0, logm + math.log(prod)
        return prod, logm
    return prod, logm + math.log(x)


@kernel
def _det_hybrid_window(F, G, n, m, mat):
    """det of the hybrid Bézout matrix (shift rows u^r g, r < n - m, then the Bézoutian rows
    φ_m … φ_1) by Gaussian elimination with partial pivoting on a sliding window.

    Column k of the elimination involves only m + 1 rows: the m that are not yet pivots among
    the Bézoutian rows and the shift rows reached so far, and the shift row u^k g, whose
    first nonzero is column k (the others are zero there: the dense loop skips them).  The m
    rows live column-major in LANES lanes, W[j, lane] = mat[j, lane], so one column update
    is a fixed-length vector operation; the shift row enters untouched (g's coefficients) and
    takes the place of the pivot when that is not it itself.  The arithmetic on every entry
    is the dense elimination's (f = x_ik / pivot, x_ij -= f x_kj), the pivot the largest in
    the column (ties may pick another row than the dense order), so the result is the
    dense elimination's (tests/solver/test_solver_two_bounce.py, bit for bit).  The sign is that of
    the pivots and of the permutation (original row of each pivot, parity by cycles).
    F is overwritten (the multipliers)."""
    L = LANES
    perm = mat[:, L]  # original row of the k-th pivot
    ids = mat[:, L + 1]  # original row in each lane
    seen = mat[:, L + 2]
    for j in range(n):
        for i in range(L):
            mat[j, i] = 0.0
    _bezoutian_rows(F, G, n, m, mat, True)
    f = F  # no longer needed: the multipliers
    for i in range(L):
        ids[i] = n - m + i if i < m else -1.0
    sign = 1
    logm = 0.0
    prod = 1.0  # the pivots' product not yet in logm (_log_accumulate)
    n_shift = n - m
    for k in range(n):
        entering = k < n_shift
        # pivot: the largest |x_ik| over the lanes and the entering row (g's constant term)
        row = mat[k]
        # the first lane whose |x| exceeds g's constant term (entering) and every other lane
        big, p = lanes_abs_argmax(row, abs(G[0]) if entering else 0.0, LANES)
        if big == 0.0 or not np.isfinite(big):
            return 0, -math.inf
        piv = G[0] if p < 0 else row[p]
        if piv < 0.0:
            sign = -sign
        prod, logm = _log_accumulate(prod, logm, abs(piv))
        inv = 1.0 / piv
        for i in range(L):
            f[i] = row[i] * inv
        if p >= 0:
            f[p] = 0.0  # the pivot lane is not updated (it is replaced or retired)
        fv = (f[0], f[1], f[2], f[3], f[4], f[5], f[6], f[7], f[8], f[9], f[10], f[11], f[12], f[13], f[14], f[15])
        if p < 0:
            # the entering shift row is the pivot: g's coefficients, zero beyond column k + m
            perm[k] = k
            for j in range(k + 1, min(n, k + m + 1)):
                lanes_sub_scaled(mat[j], fv, G[j - k])
        else:
            perm[k] = ids[p]
            fs = G[0] * inv if entering else 0.0
            for j in range(k + 1, n):
                row = mat[j]
                x = row[p]
                lanes_sub_scaled(row, fv, x)
                # lane p: the entering row (updated by the pivot row) takes its place
                if entering:
                    row[p] = (G[j - k] if j - k <= m else 0.0) - fs * x
                else:
                    row[p] = 0.0
            ids[p] = k if entering else -1.0
    # the permutation's parity: n minus its number of cycles
    for k in range(n):
        seen[k] = 0.0
    cycles = 0
    for k in range(n):
        if seen[k] == 0.0:
            cycles += 1
            q = k
            while seen[q] == 0.0:
                seen[q] = 1.0
                q = int(perm[q])
    if (n - cycles) % 2 == 1:
        sign = -sign
    return sign, logm + math.log(prod)


@kernel
def _det_hybrid_dense(F, G, n, m, A, mat):
    """det of the hybrid Bézout matrix built in full (n < WINDOW_FROM, where the window does
    not pay, or m > LANES, not met by the systems of this module): dense Gaussian elimination
    with partial pivoting, skipping the rows with a zero in the pivot column.  A: scratch
    (MAXD)."""
    for r in range(n - m):
        for j in range(n):
            mat[r, j] = 0.0
    for r in range(n - m):
        for i in range(m + 1):
            mat[r, r + i] = G[i]
    _bezoutian_rows(F, G, n, m, mat, False)
    sign = 1
    logm = 0.0
    prod = 1.0  # the pivots' product not yet in logm (_log_accumulate)
    for k in range(n):
        p = k
        big = abs(mat[k, k])
        for i in range(k + 1, n):
            x = abs(mat[i, k])
            if x > big:
                big = x
                p = i
        if big == 0.0 or not np.isfinite(big):
            return 0, -math.inf
        if p != k:
            sign = -sign
            for j in range(k, n):
                t = mat[k, j]
                mat[k, j] = mat[p, j]
                mat[p, j] = t
        piv = mat[k, k]
        if piv < 0.0:
            sign = -sign
        prod, logm = _log_accumulate(prod, logm, abs(piv))
        inv = 1.0 / piv
        # the pivot row's tail in a separate buffer (A: the coefficients are in the matrix
        # now): the row updates then provably do not alias it and vectorise
        w = n - k - 1
        for j in range(w):
            A[j] = mat[k, k + 1 + j]
        for i in range(k + 1, n):
            f = mat[i, k] * inv
            if f != 0.0:
                for j in range(w):
                    mat[i, k + 1 + j] -= f * A[j]
    return sign, logm + math.log(prod)


@kernel
def _det_checked(at, da, bt, db, n, v, cf, mat, stats):
    """det_bezout, with an exact zero re-checked a hair away (never taken as a root as is)."""
    stats[STAT_DETS] += 1
    s, lg = det_bezout(at, da, bt, db, n, v, cf, mat)
    if s != 0:
        return s, lg
    for k in range(1, 4):
        h = 1e-13 * (10.0 ** k)
        stats[STAT_DETS] += 1
        s, lg = det_bezout(at, da, bt, db, n, v + h, cf, mat)
        if s != 0:
            return s, lg
    return 0, -math.inf


@kernel
def _illinois(at, da, bt, db, n, lo, hi, slo, llo, shi, lhi, cf, mat, stats):
    """Root of det in [lo, hi] (opposite signs at the ends) pinned to ROOT_TOL."""
    side = 0
    width_before = hi - lo
    for it in range(200):
        w = hi - lo
        if w <= ROOT_TOL:
            break
        dl = lhi - llo
        if dl > 700.0:
            t = 0.0
        elif dl < -700.0:
            t = 1.0
        else:
            t = 1.0 / (1.0 + math.exp(dl))
        if it % 4 == 3:
            # safeguard: bisect unless the last steps shrank the bracket well
            if w > 0.25 * width_before:
                t = 0.5
            width_before = w
        x = lo + t * w
        if not (x > lo and x < hi):
            x = lo + 0.5 * w
            if not (x > lo and x < hi):
                break
        s, lg = _det_checked(at, da, bt, db, n, x, cf, mat, stats)
        if s == 0:
            return x
        if s == slo:
            lo = x
            llo = lg
            if side == -1:
                lhi -= 0.6931471805599453
            side = -1
        else:
            hi = x
            lhi = lg
            if side == 1:
                llo -= 0.6931471805599453
            side = 1
    return 0.5 * (lo + hi)


@kernel
def find_v_roots(at, da, bt, db, n, lo, hi, pieces, live, cf, mat, scan, out_roots, stats):
    """Real roots of det R(v) in [lo, hi] seen by the piecewise sign scan, pinned by Illinois.

    The range is cut into ``pieces``; every sign change is pinned to ROOT_TOL (the path-space
    polish of its candidates takes v1 the rest of the way).  The scan (v, sign, log|det|)
    stays in scan[0:3] and each root's piece index in scan[4], for :func:`refine_v_roots`.
    Only the pieces with ``live[k]`` (:func:`live_pieces`) are scanned (their samples and
    the neighbours the kink test needs; the others hold sign 2).
    scan: (9, MAX_PIECES + 1) scratch.  Returns the root count, or -1 when the determinant
    vanishes at most samples (degenerate system)."""
    vs = scan[0]
    sg = scan[1]
    lgs = scan[2]
    piece_of = scan[4]
    h = (hi - lo) / pieces
    zeros = 0
    sampled = 0
    for k in range(pieces + 1):
        v = lo + k * h
        vs[k] = v
        # a sample is needed by the live pieces k - 1, k (sign changes) and k - 2, k + 1
        # (the kink test of refine_flags_one looks one sample beyond each end)
        need = False
        for q in range(max(0, k - 2), min(pieces - 1, k + 1) + 1):
            if live[q] != 0:
                need = True
        if not need:
            sg[k] = 2  # not sampled
            lgs[k] = 0.0
            continue
        s, lg = _det_checked(at, da, bt, db, n, v, cf, mat, stats)
        sg[k] = s
        lgs[k] = lg
        sampled += 1
        if s == 0:
            zeros += 1
    if zeros * 2 > sampled:
        return -1
    cap = min(out_roots.shape[0], piece_of.shape[0])
    count = 0
    for k in range(pieces):
        if live[k] == 0:
            continue
        if sg[k] != sg[k + 1] and sg[k] != 0 and sg[k + 1] != 0 and count < cap:
            out_roots[count] = _illinois(at, da, bt, db, n, vs[k], vs[k + 1], sg[k], lgs[k], sg[k + 1], lgs[k + 1], cf, mat, stats)
            piece_of[count] = k
            count += 1
        elif sg[k] == 0 and count < cap:
            out_roots[count] = vs[k]
            piece_of[count] = k
            count += 1
    return count


@kernel
def refine_v_roots(at, da, bt, db, n, pieces, live, cf, mat, scan, out_roots, n_found, productive, stats):
    """Roots the uniform scan of :func:`find_v_roots` missed; returns the new root count.

    Solutions cluster (all paths through a small or distant second triangle lie in a small
    patch of the first), so the pieces around a sign change whose root polished into a path
    (``productive[i]`` for root i) are cut again; so is a piece next to a convex kink of
    log|det| deflated by the roots found (what is left of a kink is a root the scan did not
    see: a pair inside one piece).  Sign changes whose roots gave no path are resultant roots
    with their common u1 outside the triangle or the path invalid — most of them — and are
    not refined around: that is most of the cost of the old always-refine rule.

    The kink rule needs both neighbours of a sample, so the scan's two end samples get one
    more (a "ghost" a piece outside the range, 2 determinants per system): a pair of roots
    in the first or last piece, next to the end of the range, was never refined (the paper's
    §4.2 scan has no refinement at all).  Consecutive flagged pieces are refined as one run
    (:func:`_refine_interval`'s ``carry``), so that a one-signed dip at a sample the pieces
    share — a root pair next to a scan sample — is seen with its neighbours on both sides."""
    if REFINE_LEVELS == 0:
        return n_found
    stack = scan[3, 0:STACK_CAP * 7].reshape((STACK_CAP, 7))
    sub = scan[3, STACK_CAP * 7:STACK_CAP * 7 + 3 * (SUB_SAMPLES + 3)].reshape((3, SUB_SAMPLES + 3))
    flags = scan[6]
    vs = scan[0]
    sg = scan[1]
    lgs = scan[2]
    piece_of = scan[4]
    h = vs[1] - vs[0]
    g_lo = 0.0
    g_hi = 0.0
    if live[0] != 0:
        _, g_lo = _det_checked(at, da, bt, db, n, vs[0] - h, cf, mat, stats)
    if live[pieces - 1] != 0:
        _, g_hi = _det_checked(at, da, bt, db, n, vs[pieces] + h, cf, mat, stats)
    g_lo = _deflate(vs[0] - h, g_lo, out_roots, n_found)
    g_hi = _deflate(vs[pieces] + h, g_hi, out_roots, n_found)
    raw = scan[8]  # the scan's log|det| before deflation: the ends of a refined piece
    for k in range(pieces + 1):
        raw[k] = lgs[k]
        if sg[k] != 2:  # unsampled (no live piece needs it): never read by the kink test
            lgs[k] = _deflate(vs[k], lgs[k], out_roots, n_found)
    refine_flags_one(lgs, g_lo, g_hi, out_roots, n_found, piece_of, productive, pieces, live, flags)
    count = n_found
    carry = False
    cv = 0.0
    cs = 0
    cl = 0.0
    for k in range(pieces):
        if flags[k] == 0.0:
            carry = False
            continue
        last_of_run = k + 1 >= pieces or flags[k + 1] == 0.0
        count, carry, cv, cs, cl = _refine_interval(at, da, bt, db, n, vs[k], vs[k + 1], cf, mat, stack, sub, out_roots,
                                                     n_found, count, stats, carry, cv, cs, cl, last_of_run,
                                                     int(sg[k]), raw[k], int(sg[k + 1]), raw[k + 1])
    return count


@kernel
def refine_flags_one(lgs, g_lo, g_hi, roots, n_found, piece_of, productive, pieces, live, flags):
    """flags[k] = 1 for a live piece next to a convex kink of the deflated log|det| lgs
    (ghost samples g_lo, g_hi outside the two ends) or within one piece of a productive root."""
    for k in range(pieces):
        if live[k] == 0:
            flags[k] = 0
            continue
        left = g_lo if k == 0 else lgs[k - 1]
        right = g_hi if k + 2 > pieces else lgs[k + 2]
        flagged = left + lgs[k + 1] - 2.0 * lgs[k] > KINK or lgs[k] + right - 2.0 * lgs[k + 1] > KINK
        if not flagged:
            for i in range(n_found):
                if productive[i] and abs(int(piece_of[i]) - k) <= 1:
                    flagged = True
                    break
        flags[k] = 1 if flagged else 0


@kernel
def _deflate(v, lg, roots, n_roots):
    """log|det(v)| minus Σ log|v - r| over known roots r (their share of the curvature)."""
    for i in range(n_roots):
        d = abs(v - roots[i])
        if d > 0.0:
            lg -= math.log(d)
    return lg


@kernel
def _refine_interval(at, da, bt, db, n, lo, hi, cf, mat, stack, sub, out_roots, n_scan, count, stats, carry, cv, cs, cl,
                     last_of_run, s_lo, l_lo, s_hi, l_hi):
    """Roots in [lo, hi] the uniform scan missed: recursive sub-sampling (explicit stack); a
    sub-piece next to a convex kink of the deflated log|det| is cut again (up to
    REFINE_LEVELS levels); new sign changes (not around one of the n_scan scan roots) are
    pinned by Illinois; at the last level a one-signed dip of the deflated log|det| — a
    local minimum with a convex kink, one sign at it and its neighbours — is resolved by
    :func:`_resolve_dip` where log|det| falls monotonically into it over two samples on
    each side, and otherwise (log|det| at its rounding floor, where dips are noise) its
    deepest sample is a candidate as it is (the paths near grazing incidence whose
    resultant is that flat are still found from there).

    A flagged piece is one of a run of consecutive flagged pieces: (carry, cv, cs, cl) is
    the previous piece's last sub-sample before lo (v, sign, raw log|det|), so that the dip
    rule sees the sample at lo with both neighbours; the first piece of a run takes one
    more sample below lo instead, the last one (``last_of_run``) one above hi.  The ends lo
    and hi are scan samples: their (sign, raw log|det|) (s_lo, l_lo), (s_hi, l_hi) are
    taken as they are instead of being evaluated again (the same v, so the same values:
    2 of the SUB_SAMPLES + 1 determinants per piece).  Returns (count, carry, cv, cs, cl)
    for the next piece."""
    cap = out_roots.shape[0]
    stack[0, 0] = lo
    stack[0, 1] = hi
    stack[0, 6] = 1.0
    top = 1
    # sub[:, 1 .. M + 1] the samples of the interval, sub[:, 0] and sub[:, M + 2] their
    # neighbours outside it (the top-level interval only)
    sv = sub[0]
    ss = sub[1]
    sl = sub[2]
    M = SUB_SAMPLES
    out_carry = False
    out_v = 0.0
    out_s = 0
    out_l = 0.0
    while top > 0:
        top -= 1
        lo = stack[top, 0]
        hi = stack[top, 1]
        level = stack[top, 6]
        outer = level == 1.0
        h = (hi - lo) / M
        for k in range(M + 1):
            v = lo + k * h
            if k == M:
                v = hi
            if outer and k == 0 and s_lo != 2:
                s, lg = s_lo, l_lo
            elif outer and k == M and s_hi != 2:
                s, lg = s_hi, l_hi
            else:
                s, lg = _det_checked(at, da, bt, db, n, v, cf, mat, stats)
            sv[k + 1] = v
            ss[k + 1] = s
            sl[k + 1] = lg
        has_left = False
        has_right = False
        if outer:
            if carry:
                sv[0] = cv
                ss[0] = cs
                sl[0] = cl
            else:
                s, lg = _det_checked(at, da, bt, db, n, lo - h, cf, mat, stats)
                sv[0] = lo - h
                ss[0] = s
                sl[0] = lg
            has_left = True
            if last_of_run:
                s, lg = _det_checked(at, da, bt, db, n, hi + h, cf, mat, stats)
                sv[M + 2] = hi + h
                ss[M + 2] = s
                sl[M + 2] = lg
                has_right = True
        if outer:
            out_carry = True
            out_v = sv[M]
            out_s = ss[M]
            out_l = sl[M]
        # new sign changes (a sub-piece around a scan root is skipped); more than
        # NOISY_CHANGES of them in one piece is a stretch where the determinant's sign is at
        # rounding level (no polynomial of this degree wiggles like that): left alone
        changes = 0
        for k in range(1, M + 1):
            if ss[k] != ss[k + 1]:
                changes += 1
        if changes > NOISY_CHANGES:
            continue
        for k in range(1, M + 1):
            if ss[k] != ss[k + 1] and ss[k] != 0 and ss[k + 1] != 0 and count < cap:
                known = False
                for i in range(n_scan):
                    if out_roots[i] >= sv[k] and out_roots[i] <= sv[k + 1]:
                        known = True
                if not known:
                    out_roots[count] = _illinois(at, da, bt, db, n, sv[k], sv[k + 1], ss[k], sl[k], ss[k + 1], sl[k + 1], cf, mat, stats)
                    count += 1
        k_lo = 0 if has_left else 1
        k_hi = M + 2 if has_right else M + 1
        for k in range(k_lo, k_hi + 1):
            sl[k] = _deflate(sv[k], sl[k], out_roots, count)
        last = level >= REFINE_LEVELS
        if not last:
            for k in range(1, M + 1):
                kink_l = k > 1 and sl[k - 1] + sl[k + 1] - 2.0 * sl[k] > KINK
                kink_r = k < M and sl[k] + sl[k + 2] - 2.0 * sl[k + 1] > KINK
                if (kink_l or kink_r) and top < stack.shape[0]:
                    stack[top, 0] = sv[k]
                    stack[top, 1] = sv[k + 1]
                    stack[top, 6] = level + 1.0
                    top += 1
            continue
        # a one-signed dip of the deflated log|det| at a sample with both neighbours (the
        # shared end of two pieces of a run is judged by the right-hand piece)
        for k in range(max(k_lo + 1, 1), min(k_hi - 1, M + 1 if has_right else M) + 1):
            if count < cap and sl[k - 1] + sl[k + 1] - 2.0 * sl[k] > KINK and ss[k] == ss[k - 1] \
                    and ss[k] == ss[k + 1] and ss[k] != 0 and sl[k] < sl[k - 1] and sl[k] < sl[k + 1]:
                if (k - 2 < k_lo or sl[k - 2] >= sl[k - 1]) and (k + 2 > k_hi or sl[k + 2] >= sl[k + 1]):
                    count = _resolve_dip(at, da, bt, db, n, sv[k - 1], sv[k], sv[k + 1], ss[k], sl[k - 1], sl[k],
                                         sl[k + 1], cf, mat, out_roots, count, stats)
                else:
                    # not monotone over the next samples: log|det| at its rounding floor, where a
                    # dip is noise; its deepest sample is still a (cheap) candidate
                    out_roots[count] = sv[k]
                    count += 1
    return count, out_carry, out_v, out_s, out_l


@kernel
def _resolve_dip(at, da, bt, db, n, xl, xm, xr, sgn, fl, fm, fr, cf, mat, out_roots, count, stats):
    """A one-signed dip of the deflated log|det| at xm (fm below fl at xl and fr at xr, one
    sign at all three): a root pair closer than the samples, or a complex pair next to the
    real axis.  The issue's "refine pieces where |det| dips towards zero without a sign
    change, so clustered roots separate" (the paper, §4.2 Discussion: the piecewise
    bisection "requires a large number of pieces in the case that solutions are
    clustered").  Near either pair |det| is a quadratic factor times a slowly varying rest,
    so each step evaluates det at the vertex of the quadratic through the three samples
    (golden-section step when the vertex is too close to a sample or outside): a point of
    the other sign splits the dip into two sign changes, both pinned by Illinois; a model
    minimum above DIP_FLAT of the deepest sample is a complex pair whose bottom is reached
    (no real root: stop); otherwise the deepest point (to ROOT_TOL, DIP_STEPS at most) is
    reported as a (near-)double root candidate.  Before, the deepest sample was that
    candidate: up to half a sub-piece off the pair, too far for the path-space polish of a
    path near grazing (RT at 10,000 tuples: 4 paths).  Typically 3-8 determinants per dip.
    ``fl, fm, fr`` are deflated by ``out_roots[:count]``; returns the new count."""
    cap = out_roots.shape[0]
    for it in range(DIP_STEPS):
        w = xr - xl
        if w <= ROOT_TOL:
            break
        # |det| / |det(xm)| near a root pair (or a complex pair next to the axis) is a
        # quadratic factor times a slowly varying rest: fit q through the three samples
        ql = math.exp(min(fl - fm, 700.0))
        qr = math.exp(min(fr - fm, 700.0))
        d1 = (1.0 - ql) / (xm - xl)
        d2 = (qr - 1.0) / (xr - xm)
        A = (d2 - d1) / w
        x = xm
        qmin = 1.0
        if A > 0.0:
            x = 0.5 * (xl + xm) - d1 / (2.0 * A)
            qmin = ql + d1 * (x - xl) + A * (x - xl) * (x - xm)
        if qmin >= DIP_FLAT:
            break  # a complex pair whose bottom is reached: no real root here
        if not (x > xl + 0.01 * w and x < xr - 0.01 * w) or abs(x - xm) < 0.01 * w:
            # golden-section step into the larger side
            if xr - xm > xm - xl:
                x = xm + 0.3819660112501051 * (xr - xm)
            else:
                x = xm - 0.3819660112501051 * (xm - xl)
        s, lg = _det_checked(at, da, bt, db, n, x, cf, mat, stats)
        if s == 0:
            break
        if s != sgn:
            # the pair straddles x: (xl or xm) .. x .. (xm or xr), all of sign sgn but x
            p = xm if x > xm else xl
            q = xr if x > xm else xm
            sp, lp = _det_checked(at, da, bt, db, n, p, cf, mat, stats)
            sq, lq = _det_checked(at, da, bt, db, n, q, cf, mat, stats)
            if count + 2 <= cap and sp == sgn and sq == sgn:
                out_roots[count] = _illinois(at, da, bt, db, n, p, x, sp, lp, s, lg, cf, mat, stats)
                out_roots[count + 1] = _illinois(at, da, bt, db, n, x, q, s, lg, sq, lq, cf, mat, stats)
                return count + 2
            break
        f = _deflate(x, lg, out_roots, count)
        if f < fm:
            if x > xm:
                xl = xm
                fl = fm
            else:
                xr = xm
                fr = fm
            xm = x
            fm = f
        elif x > xm:
            xr = x
            fr = f
        else:
            xl = x
            fl = f
    if count < cap:
        out_roots[count] = xm  # (near-)double root candidate
        count += 1
    return count


# --- one √ for the whole triangle: a Heron step from a fitted quadratic ---------------------


@kernel
def _beta_local(u, v, geo_l, r):
    """β(u1, v1) = |n1|²|d0|²(1 - η'²) + η'²(d0·n1)² of eq (22) at one point (local frame)."""
    d0 = (u * geo_l[2, 0] + v * geo_l[3, 0] - geo_l[0, 0], u * geo_l[2, 1] + v * geo_l[3, 1] - geo_l[0, 1],
          u * geo_l[2, 2] + v * geo_l[3, 2] - geo_l[0, 2])
    n1 = (geo_l[4, 0] + u * geo_l[5, 0] + v * geo_l[6, 0], geo_l[4, 1] + u * geo_l[5, 1] + v * geo_l[6, 1],
          geo_l[4, 2] + u * geo_l[5, 2] + v * geo_l[6, 2])
    nn = n1[0] * n1[0] + n1[1] * n1[1] + n1[2] * n1[2]
    dd = d0[0] * d0[0] + d0[1] * d0[1] + d0[2] * d0[2]
    dn = d0[0] * n1[0] + d0[1] * n1[1] + d0[2] * n1[2]
    return nn * dd * (1.0 - r * r) + r * r * dn * dn


@kernel
def _quadratic_at(c, u, v):
    return c[0] + u * c[1] + v * c[2] + u * u * c[3] + u * v * c[4] + v * v * c[5]


@kernel
def heron_sqrt_fit(geo_l, r, margin, S2, cut, M):
    """A quadratic q(u1, v1) ≈ √β over triangle 1 widened by the v margin, for the Heron
    step √β ≈ (β + q²) / (2q) (exact where q = √β; relative error (q - √β)² / (2 q √β), the
    square of the fit's); returns (ok, q's coefficients (1, u, v, u², uv, v²)).

    Replaces eq (23)'s piecewise rational in x = β/S² where it fits: that approximation is
    accurate only on its own x interval, and β/S² spans several intervals over a triangle
    (β grows with |x1 - x0|²), so the system had to be solved once per interval (TT planted:
    7.2 systems per tuple); the Heron form is one system, and d̃1 has degree 5 instead of 7
    (numerator β + q² of degree 4 times n1, denominator 2q of degree 2 times the degree-3
    tangential part), so b has total degree 34 instead of 46 for TT.  Only the part of the
    triangle with β/S² ≥ ``cut`` is fitted and checked: near β = 0 (grazing exit, the TIR
    border) √ is too steep for any smooth fit, and the √ pieces of eq (23) that lie below the
    cut are still solved as before (each its own system; :func:`heron_sqrt_cut` picks the
    cut).  ok is False where fewer than 12 fit points lie above the cut, q ≤ 0 at a check
    point above it, or the relative error there exceeds HERON_TOL.  Weighted least squares
    (weight 1/β: relative error) on a barycentric grid of order HERON_FIT_GRID; M: (6, 7)
    scratch."""
    ok, _, c = _heron_fit(geo_l, r, margin, S2, cut, M)
    return ok, c


@kernel
def _heron_fit(geo_l, r, margin, S2, cut, M):
    """:func:`heron_sqrt_fit`, also returning whether enough fit points lie above the cut
    (ok, enough, c): with too few, every higher cut has too few as well."""
    c = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    for i in range(6):
        for j in range(7):
            M[i, j] = 0.0
    w = 1.0 + 3.0 * margin
    G = HERON_FIT_GRID
    n_fit = 0
    for i in range(G + 1):
        for j in range(G + 1 - i):
            u = -margin + w * i / G
            v = -margin + w * j / G
            beta = _beta_local(u, v, geo_l, r)
            if not beta >= cut * S2:
                continue
            n_fit += 1
            y = math.sqrt(beta)
            wt = 1.0 / beta
            phi = (1.0, u, v, u * u, u * v, v * v)
            for k in range(6):
                for l in range(6):
                    M[k, l] += wt * phi[k] * phi[l]
                M[k, 6] += wt * phi[k] * y
    if n_fit < 12:
        return False, False, c
    # Gaussian elimination with partial pivoting on the 6 x 7 augmented matrix
    for k in range(6):
        p = k
        for i in range(k + 1, 6):
            if abs(M[i, k]) > abs(M[p, k]):
                p = i
        if not abs(M[p, k]) > 1e-300:
            return False, True, c
        if p != k:
            for j in range(7):
                t = M[k, j]
                M[k, j] = M[p, j]
                M[p, j] = t
        for i in range(k + 1, 6):
            f = M[i, k] / M[k, k]
            for j in range(k, 7):
                M[i, j] -= f * M[k, j]
    for k in range(5, -1, -1):
        acc = M[k, 6]
        for j in range(k + 1, 6):
            acc -= M[k, j] * M[j, 6]
        M[k, 6] = acc / M[k, k]
    c = (M[0, 6], M[1, 6], M[2, 6], M[3, 6], M[4, 6], M[5, 6])
    G = HERON_CHECK_GRID
    for i in range(G + 1):
        for j in range(G + 1 - i):
            u = -margin + w * i / G
            v = -margin + w * j / G
            beta = _beta_local(u, v, geo_l, r)
            if not beta >= cut * S2:
                continue
            q = _quadratic_at(c, u, v)
            if not q > 0.0:
                return False, True, c
            y = math.sqrt(beta)
            if not (q - y) * (q - y) <= HERON_TOL * 2.0 * q * y:
                return False, True, c
    return True, True, c


@kernel
def heron_sqrt_cut(geo_l, r, margin, S2, M):
    """:func:`heron_sqrt_fit` above the first cut of HERON_CUTS where it fits; returns (ok,
    cut, q's coefficients).  The eq (23) pieces starting at or above the cut are replaced by
    the one Heron system, those below it are solved each on its own.

    At HERON_CUT alone the fit failed for ~40 % of the planted TT orientations (β/S² spanning
    much of [0, 1] over the triangle: √ is steep at its low end), which then solved ~3 eq
    (23) pieces of degree 46 instead; a higher cut drops that steep part from the fit
    (measurements: docs/decisions/two-bounce-solver.md)."""
    ok = False
    cut = HERON_CUTS[0]
    c = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    for k in range(HERON_CUTS.shape[0]):
        cut = HERON_CUTS[k]
        ok, enough, c = _heron_fit(geo_l, r, margin, S2, cut, M)
        if ok or not enough:
            break
    return ok, cut, c


# --- √ pieces: which to solve, and where ----------------------------------------------------


@kernel
def _beta_poly(geo_l, r, biv):
    """β = |n1|²|d0|²(1 - r²) + r²(d0·n1)² (eq 22) into biv[BETA_SLOT] (local frame, degree
    4; the same arithmetic as :func:`_build_system`'s; slots 2-4, 7-12 as scratch)."""
    x0 = (geo_l[0, 0], geo_l[0, 1], geo_l[0, 2])
    D0 = biv[7:10]
    N1 = biv[10:13]
    _vlin(D0, (-x0[0], -x0[1], -x0[2]), (geo_l[2, 0], geo_l[2, 1], geo_l[2, 2]), (geo_l[3, 0], geo_l[3, 1], geo_l[3, 2]))
    _vlin(N1, (geo_l[4, 0], geo_l[4, 1], geo_l[4, 2]), (geo_l[5, 0], geo_l[5, 1], geo_l[5, 2]),
          (geo_l[6, 0], geo_l[6, 1], geo_l[6, 2]))
    _vdot(D0, 1, N1, 1, biv[2])
    _vdot(N1, 1, N1, 1, biv[3])
    _vdot(D0, 1, D0, 1, biv[4])
    beta = biv[BETA_SLOT]
    _bzero(beta, 4)
    _bmul_acc(biv[3], 2, biv[4], 2, beta, 1.0 - r * r)
    _bmul_acc(biv[2], 2, biv[2], 2, beta, r * r)


@kernel
def _sqrt_band(piece, S2, refract1):
    """The β band [blo, bhi] where the system of eq (23)'s piece ``piece`` is solved: the
    piece's interval and SQRT_BAND_REACH neighbours' on each side (the piece's error grows outside its own
    interval; a root found there belongs to a neighbour, whose own system holds it more
    accurately).  β ≥ 0 below for the first pieces and for the Heron √ (piece < 0): β < 0 is
    total internal reflection at vertex 1, no refracted ray (β is exact, eq 22: the pre-pass
    drops a box where it is provably negative; TT, 10,000 tuples: 5.53M -> 5.26M determinants,
    the same paths); unbounded above for the last.  (-inf, inf) without a refraction at vertex 1
    or without ``SQRT_BANDS`` (β is not computed then)."""
    if not refract1 or not SQRT_BANDS:
        return -math.inf, math.inf
    if piece < 0:
        return 0.0, math.inf
    K = SQRT_PIECES.shape[0]
    blo = 0.0 if piece < SQRT_BAND_REACH else S2 * SQRT_PIECES[piece - SQRT_BAND_REACH, 0]
    bhi = math.inf if piece + SQRT_BAND_REACH >= K else S2 * SQRT_PIECES[piece + SQRT_BAND_REACH, 1]
    return blo, bhi


@kernel
def _beta_mask(biv, margin, S2):
    """Bit k set for every eq (23) piece k ≥ BETA_MASK_FROM whose interval β/S² can reach
    on triangle 1 widened by the margin: bounds of β (biv[BETA_SLOT]) on a BETA_GRID² grid
    of boxes over [-m, 1 + m]² (boxes beyond u1 + v1 = 1 + m skipped).  With the pieces at
    the sample points (which can miss the extremes of β over the triangle), a path whose
    β/S² lies in such a piece has that piece's own system solved (``SQRT_BANDS``)."""
    mask = 0
    K = SQRT_PIECES.shape[0]
    w = (1.0 + 2.0 * margin) / BETA_GRID
    for i in range(BETA_GRID):
        for j in range(BETA_GRID):
            u0 = -margin + i * w
            v0 = -margin + j * w
            if u0 + v0 > 1.0 + margin:
                continue
            lo, hi = _box_range(biv, BETA_SLOT, 4, u0, v0, w)
            lo /= S2
            hi /= S2
            for k in range(BETA_MASK_FROM, K):
                if hi >= SQRT_PIECES[k, 0] and (lo <= SQRT_PIECES[k, 1] or k == K - 1):
                    mask |= 1 << k
    return mask


# --- building the bivariate system ---------------------------------------------------------


@kernel
def _build_system(refract1, refract2, orient1, eta1_ratio, piece, S, heron, eta_in2, eta_out2, flat2, c2, geo_l, biv):
    """Fill biv[0] = a (returned da) and biv[1] = b (returned db) in the local frame geo_l.

    orient1: ±1, the sign turning n1 to the incoming side (refraction only);
    eta1_ratio: η' at vertex 1; piece: row of SQRT_PIECES, S: √β scale; piece < 0: the
    Heron √ of :func:`heron_sqrt_fit` with the quadratic's coefficients ``heron``."""
    x0 = (geo_l[0, 0], geo_l[0, 1], geo_l[0, 2])
    x3 = (geo_l[1, 0], geo_l[1, 1], geo_l[1, 2])
    e11 = (geo_l[2, 0], geo_l[2, 1], geo_l[2, 2])
    e12 = (geo_l[3, 0], geo_l[3, 1], geo_l[3, 2])
    n10 = (geo_l[4, 0], geo_l[4, 1], geo_l[4, 2])
    m11 = (geo_l[5, 0], geo_l[5, 1], geo_l[5, 2])
    m12 = (geo_l[6, 0], geo_l[6, 1], geo_l[6, 2])
    p20 = (geo_l[7, 0], geo_l[7, 1], geo_l[7, 2])
    e21 = (geo_l[8, 0], geo_l[8, 1], geo_l[8, 2])
    e22 = (geo_l[9, 0], geo_l[9, 1], geo_l[9, 2])
    n20 = (geo_l[10, 0], geo_l[10, 1], geo_l[10, 2])
    m21 = (geo_l[11, 0], geo_l[11, 1], geo_l[11, 2])
    m22 = (geo_l[12, 0], geo_l[12, 1], geo_l[12, 2])
    zero = (0.0, 0.0, 0.0)
    # slots: vector polys use biv[k:k+3]
    a = biv[0]
    b = biv[1]
    s1 = biv[2]
    s2 = biv[3]
    s3 = biv[4]
    s4 = biv[5]
    s5 = biv[6]
    D0 = biv[7:10]
    N1 = biv[10:13]
    DT = biv[13:16]  # d̃1
    V1 = biv[16:19]
    N2 = biv[19:22]  # κ n2
    D2 = biv[22:25]  # κ (x3 - x2)
    T2 = biv[25:28]
    V2 = biv[28:31]
    S1 = biv[31:34]  # x1 - p20
    Q = biv[34:37]
    _vlin(D0, (-x0[0], -x0[1], -x0[2]), e11, e12)
    _vlin(N1, n10, m11, m12)
    # --- d̃1
    dd0n = _vdot(D0, 1, N1, 1, s1)  # d0·n1
    _vdot(N1, 1, N1, 1, s2)  # |n1|²
    ddt = 3
    if not refract1:
        # d̃ = -2 (d0·n) n + d0 |n|²
        for c in range(3):
            _bzero(DT[c], 3)
            _bmul_acc(s1, 2, N1[c], 1, DT[c], -2.0)
            _bmul_acc(s2, 2, D0[c], 1, DT[c], 1.0)
    else:
        r = eta1_ratio
        _vdot(D0, 1, D0, 1, s3)  # |d0|²
        # β = |n|²|d0|² (1 - r²) + r² (d0·n)²   (degree 4)  -> s4
        _bzero(s4, 4)
        _bmul_acc(s2, 2, s3, 2, s4, 1.0 - r * r)
        _bmul_acc(s1, 2, s1, 2, s4, r * r)
        # √β ≈ Rn / Rd: Rn -> s5, Rd -> s3 (|d0|² no longer needed), degrees dn, dd
        if piece < 0:
            # Heron step from the fitted quadratic q: Rn = β + q², Rd = 2q
            Q2 = biv[28]
            _bzero(Q2, 2)
            Q2[0, 0] = heron[0]
            Q2[1, 0] = heron[1]
            Q2[0, 1] = heron[2]
            Q2[2, 0] = heron[3]
            Q2[1, 1] = heron[4]
            Q2[0, 2] = heron[5]
            _bzero(s5, 4)
            _badd(s5, 4, s4, 4, 1.0)
            _bmul_acc(Q2, 2, Q2, 2, s5, 1.0)
            _bzero(s3, 2)
            _badd(s3, 2, Q2, 2, 2.0)
            dd = 2
        else:
            # eq (23): √β ≈ S (c0 + c1 β/S²) / (1 + d1 β/S²) = (S c0 S² + S c1 β) / (S² + d1 β)
            c0 = SQRT_PIECES[piece, 2]
            c1 = SQRT_PIECES[piece, 3]
            d1 = SQRT_PIECES[piece, 4]
            S2 = S * S
            _bzero(s5, 4)
            _badd(s5, 4, s4, 4, S * c1)
            s5[0, 0] += S * c0 * S2
            _bzero(s3, 4)
            _badd(s3, 4, s4, 4, d1)
            s3[0, 0] += S2
            dd = 4
        # d̃ = Rd r (d0 |n|² - (d0·n) n) - orient Rn n       (degree dd + 3: 5 Heron, 7 pieces)
        ddt = dd + 3
        for c in range(3):
            _bzero(V1[c], 3)
            _bmul_acc(s2, 2, D0[c], 1, V1[c], r)
            _bmul_acc(s1, 2, N1[c], 1, V1[c], -r)
            _bzero(DT[c], ddt)
            _bmul_acc(s3, dd, V1[c], 3, DT[c], 1.0)
            _bmul_acc(s5, 4, N1[c], 1, DT[c], -orient1)
    # --- mapping to triangle 2: PV = d̃ × e22, κ = PV·e21, ũ = PV·(x1 - p20), ṽ = d̃·((x1 - p20) × e21)
    _vlin(S1, (-p20[0], -p20[1], -p20[2]), e11, e12)
    _vcross_const(DT, ddt, e22, V1)  # PV
    _vdot_const(V1, ddt, e21, s1)  # κ      (degree ddt)
    _vdot(V1, ddt, S1, 1, s2)  # ũ        (degree ddt + 1)
    # (x1 - p20) × e21 is linear: Q
    _vcross_const(S1, 1, e21, Q)
    _vdot(DT, ddt, Q, 1, s3)  # ṽ
    dm = ddt + 1
    # copies for the pre-pass's hit test (the slots above are reused below): κ, ũ, ṽ and
    # t̃ = e22·((x1 - p20) × e21) (the ray parameter times κ); degree and margin in a spare corner
    for i in range(dm + 1):
        for j in range(dm + 1):
            biv[HIT_SLOT, i, j] = s1[i, j] if i + j <= ddt else 0.0
            biv[HIT_SLOT + 1, i, j] = s2[i, j]
            biv[HIT_SLOT + 2, i, j] = s3[i, j]
    _bzero(biv[HIT_SLOT + 3], 1)
    for c in range(3):
        biv[HIT_SLOT + 3, 0, 0] += e22[c] * Q[c, 0, 0]
        biv[HIT_SLOT + 3, 1, 0] += e22[c] * Q[c, 1, 0]
        biv[HIT_SLOT + 3, 0, 1] += e22[c] * Q[c, 0, 1]
    biv[HIT_SLOT, MAXD, 0] = ddt
    biv[HIT_SLOT, MAXD, 1] = HIT_MARGIN_APPROX if refract1 else HIT_MARGIN_EXACT
    # κ n2 and κ (x3 - p20) - ũ e21 - ṽ e22
    x3r = (x3[0] - p20[0], x3[1] - p20[1], x3[2] - p20[2])
    for c in range(3):
        _bzero(D2[c], dm)
        _badd(D2[c], dm, s1, ddt, x3r[c])
        _badd(D2[c], dm, s2, dm, -e21[c])
        _badd(D2[c], dm, s3, dm, -e22[c])
    if flat2:
        dn2 = 0
        for c in range(3):
            _bzero(N2[c], 0)
            N2[c, 0, 0] = n20[c]
    else:
        dn2 = dm
        for c in range(3):
            _bzero(N2[c], dm)
            _badd(N2[c], dm, s1, ddt, n20[c])
            _badd(N2[c], dm, s2, dm, m21[c])
            _badd(N2[c], dm, s3, dm, m22[c])
    # --- a = (d̃ × (x3 - x1)) · κn2
    _vlin(S1, x3, (-e11[0], -e11[1], -e11[2]), (-e12[0], -e12[1], -e12[2]))  # x3 - x1
    _vcross(DT, ddt, S1, 1, V1)
    da = _vdot(V1, ddt + 1, N2, dn2, a)
    # --- b
    if not refract2:
        _vcross_const(N2, dn2, c2, T2)  # t2 = κn2 × c2
        d_a = _vdot(DT, ddt, N2, dn2, s1)  # d̃·n
        d_b = _vdot(D2, dm, T2, dn2, s2)  # d2·t
        _vdot(DT, ddt, T2, dn2, s3)  # d̃·t
        _vdot(D2, dm, N2, dn2, s4)  # d2·n
        db = d_a + d_b
        _bzero(b, db)
        _bmul_acc(s1, d_a, s2, d_b, b, 1.0)
        _bmul_acc(s3, d_a, s4, d_b, b, 1.0)
    else:
        # η_in² |d2|² ((d̃ × n)·c)² - η_out² |d̃|² ((d2 × n)·c)²
        _vcross(DT, ddt, N2, dn2, V1)
        dq1 = _vdot_const(V1, ddt + dn2, c2, s1)  # (d̃ × n)·c
        _vcross(D2, dm, N2, dn2, V2)
        dq2 = _vdot_const(V2, dm + dn2, c2, s2)  # (d2 × n)·c
        _vdot(D2, dm, D2, dm, s3)  # |d2|²
        _vdot(DT, ddt, DT, ddt, s4)  # |d̃|²
        # s5 = s1², then b = η_in² s3 s5
        _bzero(s5, 2 * dq1)
        _bmul_acc(s1, dq1, s1, dq1, s5, 1.0)
        db = 2 * dm + 2 * dq1
        _bzero(b, db)
        _bmul_acc(s3, 2 * dm, s5, 2 * dq1, b, eta_in2 * eta_in2)
        _bzero(s5, 2 * dq2)
        _bmul_acc(s2, dq2, s2, dq2, s5, 1.0)
        _bmul_acc(s4, 2 * ddt, s5, 2 * dq2, b, -eta_out2 * eta_out2)
    return da, db


# --- per tuple ------------------------------------------------------------------------------


@kernel
def _store_path2(th, err, sigma, out_uv, meta, count):
    for q in range(min(count, out_uv.shape[0])):
        dist = 0.0
        for i in range(4):
            dist = max(dist, abs(out_uv[q, i] - th[i]))
        sig = min(sigma, meta[q, 1])
        radius = SAME_PATH
        if sig > 0.0:
            radius = max(radius, 4.0 * (err + meta[q, 0] + 1e-12) / sig)
        else:
            radius = NEAR_PATH
        if dist < min(radius, NEAR_PATH):
            if err < meta[q, 0]:
                for i in range(4):
                    out_uv[q, i] = th[i]
                meta[q, 0] = err
                meta[q, 1] = sigma
            return count
    if count < out_uv.shape[0]:
        for i in range(4):
            out_uv[count, i] = th[i]
        meta[count, 0] = err
        meta[count, 1] = sigma
    return count + 1


@kernel
def _try_candidate(u1, v1, geo, refract1, refract2, eta, rev, geo_fwd, work, th, out_uv, meta, count, stats):
    """(u1, v1) on the first triangle of the oriented chain -> exact map to the second ->
    polish and validate in forward path space (``rev``: the chain was solved reversed,
    from x3, and (u1, v1) are the forward (u2, v2))."""
    stats[STAT_CANDIDATES] += 1
    ok, u2, v2 = trace_to_second(u1, v1, geo, refract1, eta)
    if not ok:
        return count
    if rev:
        th[0] = u2
        th[1] = v2
        th[2] = u1
        th[3] = v1
        acc, err, sig = polish_and_validate2(th, geo_fwd, refract2, refract1, eta, POLISH_STEPS, ACCEPT_RESIDUAL, work)
    else:
        th[0] = u1
        th[1] = v1
        th[2] = u2
        th[3] = v2
        acc, err, sig = polish_and_validate2(th, geo_fwd, refract1, refract2, eta, POLISH_STEPS, ACCEPT_RESIDUAL, work)
    if not acc:
        return count
    stats[STAT_ACCEPTED] += 1
    return _store_path2(th, err, sig, out_uv, meta, count)


@kernel
def _seeded(geo, refract1, refract2, eta, rev, geo_fwd, work, th, out_uv, meta, count, stats):
    """Fallback for degenerate systems (determinant identically zero): polish from a grid."""
    for i in range(N_SEEDS + 1):
        for j in range(N_SEEDS + 1 - i):
            u = (i + 1.0 / 3.0) / (N_SEEDS + 1.0)
            v = (j + 1.0 / 3.0) / (N_SEEDS + 1.0)
            count = _try_candidate(u, v, geo, refract1, refract2, eta, rev, geo_fwd, work, th, out_uv, meta, count, stats)
    return count


@kernel
def _straight_candidate(geo, refract1, refract2, eta, work, th, out_uv, meta, count, stats):
    """The straight line x0 -> x3 through triangle 1's plane as a candidate: the path at
    normal incidence through parallel faces (light and receiver on the normal of a slab),
    where the coplanarity polynomial vanishes identically and the resultant carries no root."""
    # geo holds positions relative to triangle 1's first vertex (p0 = origin).
    ok, u, v = line_crossing_barycentrics(row(geo, 0), row(geo, 1), (0.0, 0.0, 0.0), row(geo, 2), row(geo, 3), row(geo, 13))
    if not ok:
        return count
    if u < -1e-6 or v < -1e-6 or u + v > 1.0 + 1e-6:
        return count
    return _try_candidate(u, v, geo, refract1, refract2, eta, False, geo, work, th, out_uv, meta, count, stats)


@kernel
def solve_two_bounce_tuple(refract1, refract2, x0, x3, P, N, eta, pieces, stop_after, sc_biv, sc_cf, sc_mat, sc_scan,
                           sc_geo, sc_work, sc_roots, sc_chain, sc_lists, out_uv, stats):
    """All admissible two-bounce paths of one tuple; returns their count (may exceed the
    capacity of out_uv: the caller reports the overflow).

    The system is solved twice: parametrised by triangle 1 (x0 -> 1 -> 2 -> x3) and, by
    reciprocity, by triangle 2 on the reversed chain (x3 -> 2 -> 1 -> x0).  When the first
    bounce magnifies (a curved or small triangle 1 seeing a large or far triangle 2), every
    solution through triangle 2 lies in a tiny patch of (u1, v1), where a sign scan cannot
    separate their v1 roots; on the reversed chain the same solutions spread over (u2, v2)."""
    for k in range(N_STATS):
        stats[k] = 0
    geo_fwd = sc_geo[0]
    meta = sc_roots[0:out_uv.shape[0] + 1, 0:2]
    if not pack_geometry(x0, x3, P[0], N[0], P[1], N[1], geo_fwd) or not (eta > 0.0):
        stats[STAT_SKIPPED] = 1
        return 0
    count = _solve_oriented(refract1, refract2, x0, x3, P[0], N[0], P[1], N[1], eta, pieces, stop_after, sc_biv, sc_cf,
                            sc_mat, sc_scan, sc_geo[0], sc_geo[1], False, geo_fwd, sc_work, sc_roots, sc_chain, sc_lists,
                            out_uv, meta, 0, stats)
    if stop_after == 0:
        count = _straight_candidate(geo_fwd, refract1, refract2, eta, sc_work, sc_roots[out_uv.shape[0] + 1, 0:4],
                                    out_uv, meta, count, stats)
    if BOTH_DIRECTIONS:
        pack_geometry(x3, x0, P[1], N[1], P[0], N[0], sc_geo[2])
        count = _solve_oriented(refract2, refract1, x3, x0, P[1], N[1], P[0], N[0], eta, pieces, stop_after, sc_biv,
                                sc_cf, sc_mat, sc_scan, sc_geo[2], sc_geo[1], True, geo_fwd, sc_work, sc_roots, sc_chain,
                                sc_lists, out_uv, meta, count, stats)
    # skipped: every orientation's system was rejected before solving
    stats[STAT_SKIPPED] = 1 if stats[STAT_SKIPPED] >= (2 if BOTH_DIRECTIONS else 1) else 0
    stats[STAT_PATHS] = count
    return count


@kernel
def _solve_oriented(refract1, refract2, x0, x3, PA, NA, PB, NB, eta, pieces, stop_after, sc_biv, sc_cf, sc_mat, sc_scan,
                    geo, geo_l, rev, geo_fwd, sc_work, sc_roots, sc_chain, sc_lists, out_uv, meta, count_in, stats):
    """The pipeline for one orientation of the chain (triangle A first); see
    :func:`solve_two_bounce_tuple`.  Returns the new path count."""
    th = sc_roots[out_uv.shape[0] + 1, 0:4]
    v_roots = sc_roots[out_uv.shape[0] + 2]
    u_roots = sc_roots[out_uv.shape[0] + 3]
    coeffs = sc_roots[out_uv.shape[0] + 4]
    if not pack_geometry(x0, x3, PA, NA, PB, NB, geo):
        return count_in
    # --- cheap side tests -------------------------------------------------------------------
    ng1 = (geo[13, 0], geo[13, 1], geo[13, 2])
    ng2 = (geo[14, 0], geo[14, 1], geo[14, 2])
    e11 = (geo[2, 0], geo[2, 1], geo[2, 2])
    e12 = (geo[3, 0], geo[3, 1], geo[3, 2])
    p20 = (geo[7, 0], geo[7, 1], geo[7, 2])
    e21 = (geo[8, 0], geo[8, 1], geo[8, 2])
    e22 = (geo[9, 0], geo[9, 1], geo[9, 2])
    L1 = max(math.sqrt(e11[0] ** 2 + e11[1] ** 2 + e11[2] ** 2), math.sqrt(e12[0] ** 2 + e12[1] ** 2 + e12[2] ** 2))
    L2 = max(math.sqrt(e21[0] ** 2 + e21[1] ** 2 + e21[2] ** 2), math.sqrt(e22[0] ** 2 + e22[1] ** 2 + e22[2] ** 2))
    side0 = geo[0, 0] * ng1[0] + geo[0, 1] * ng1[1] + geo[0, 2] * ng1[2]
    if abs(side0) <= 1e-12 * L1:
        stats[STAT_SKIPPED] += 1
        return count_in
    # triangle 2's corners against plane 1 (through the origin p1,0)
    lo2 = math.inf
    hi2 = -math.inf
    for c in range(3):
        q = p20
        if c == 1:
            q = (p20[0] + e21[0], p20[1] + e21[1], p20[2] + e21[2])
        elif c == 2:
            q = (p20[0] + e22[0], p20[1] + e22[1], p20[2] + e22[2])
        sd = q[0] * ng1[0] + q[1] * ng1[1] + q[2] * ng1[2]
        lo2 = min(lo2, sd * side0)
        hi2 = max(hi2, sd * side0)
    tol1 = 1e-9 * (L1 + L2) * abs(side0)
    if (not refract1 and hi2 <= tol1) or (refract1 and lo2 >= -tol1):
        stats[STAT_SKIPPED] += 1
        return count_in
    # x3 and triangle 1's corners against plane 2
    side3 = (geo[1, 0] - p20[0]) * ng2[0] + (geo[1, 1] - p20[1]) * ng2[1] + (geo[1, 2] - p20[2]) * ng2[2]
    if abs(side3) <= 1e-12 * L2:
        stats[STAT_SKIPPED] += 1
        return count_in
    lo1 = math.inf
    hi1 = -math.inf
    for c in range(3):
        q = (0.0, 0.0, 0.0)
        if c == 1:
            q = e11
        elif c == 2:
            q = e12
        sd = (q[0] - p20[0]) * ng2[0] + (q[1] - p20[1]) * ng2[1] + (q[2] - p20[2]) * ng2[2]
        lo1 = min(lo1, sd * side3)
        hi1 = max(hi1, sd * side3)
    tol2 = 1e-9 * (L1 + L2) * abs(side3)
    if (not refract2 and hi1 <= tol2) or (refract2 and lo1 >= -tol2):
        stats[STAT_SKIPPED] += 1
        return count_in

    # --- local frame: unit = L1, origin p1,0 (geo is already relative to p1,0) ------------
    inv = 1.0 / L1
    for r in range(13):
        f = inv if (r <= 3 or (r >= 7 and r <= 9)) else 1.0
        for c in range(3):
            geo_l[r, c] = geo[r, c] * f
    # normal orientation over each face (a normal field that turns over the face gives two
    # side assignments to try)
    any_front1 = False
    any_back1 = False
    any_front2 = False
    any_back2 = False
    nmax1 = 0.0
    flat2 = True
    nscale2 = 0.0
    for c in range(3):
        n1c = (geo[4, 0], geo[4, 1], geo[4, 2])
        n2c = (geo[10, 0], geo[10, 1], geo[10, 2])
        if c > 0:
            n1c = (n1c[0] + geo[4 + c, 0], n1c[1] + geo[4 + c, 1], n1c[2] + geo[4 + c, 2])
            n2c = (n2c[0] + geo[10 + c, 0], n2c[1] + geo[10 + c, 1], n2c[2] + geo[10 + c, 2])
        s_1 = n1c[0] * ng1[0] + n1c[1] * ng1[1] + n1c[2] * ng1[2]
        s_2 = n2c[0] * ng2[0] + n2c[1] * ng2[1] + n2c[2] * ng2[2]
        any_front1 = any_front1 or s_1 > 0.0
        any_back1 = any_back1 or s_1 < 0.0
        any_front2 = any_front2 or s_2 > 0.0
        any_back2 = any_back2 or s_2 < 0.0
        nmax1 = max(nmax1, n1c[0] ** 2 + n1c[1] ** 2 + n1c[2] ** 2)
        nscale2 = max(nscale2, math.sqrt(n2c[0] ** 2 + n2c[1] ** 2 + n2c[2] ** 2))
    for r in (11, 12):
        if abs(geo[r, 0]) + abs(geo[r, 1]) + abs(geo[r, 2]) > 1e-12 * nscale2:
            flat2 = False
    if not (nmax1 > 0.0 and nscale2 > 0.0):
        stats[STAT_SKIPPED] += 1
        return count_in
    # plane-of-incidence normal at vertex 2: (x3 - centroid1) × mean n2
    cx = ((e11[0] + e12[0]) / 3.0, (e11[1] + e12[1]) / 3.0, (e11[2] + e12[2]) / 3.0)
    w = (geo[1, 0] - cx[0], geo[1, 1] - cx[1], geo[1, 2] - cx[2])
    nb = (3.0 * geo[10, 0] + geo[11, 0] + geo[12, 0], 3.0 * geo[10, 1] + geo[11, 1] + geo[12, 1], 3.0 * geo[10, 2] + geo[11, 2] + geo[12, 2])
    c2 = (w[1] * nb[2] - w[2] * nb[1], w[2] * nb[0] - w[0] * nb[2], w[0] * nb[1] - w[1] * nb[0])
    lc = math.sqrt(c2[0] ** 2 + c2[1] ** 2 + c2[2] ** 2)
    lw = math.sqrt(w[0] ** 2 + w[1] ** 2 + w[2] ** 2)
    lnb = math.sqrt(nb[0] ** 2 + nb[1] ** 2 + nb[2] ** 2)
    if not lc > 1e-6 * lw * lnb:
        c2 = (e21[1] * nb[2] - e21[2] * nb[1], e21[2] * nb[0] - e21[0] * nb[2], e21[0] * nb[1] - e21[1] * nb[0])
        lc = math.sqrt(c2[0] ** 2 + c2[1] ** 2 + c2[2] ** 2)
        if not lc > 0.0:
            stats[STAT_SKIPPED] += 1
            return count_in
    c2 = (c2[0] / lc, c2[1] / lc, c2[2] / lc)

    # √β scale and the x = β/S² range over triangle 1 (for the pieces to use)
    dmax = 0.0
    for c in range(3):
        q = (0.0, 0.0, 0.0)
        if c == 1:
            q = e11
        elif c == 2:
            q = e12
        dv = (q[0] - geo[0, 0], q[1] - geo[0, 1], q[2] - geo[0, 2])
        dmax = max(dmax, (dv[0] ** 2 + dv[1] ** 2 + dv[2] ** 2) * inv * inv)
    S = math.sqrt(nmax1 * dmax)

    count = count_in
    margin = V_MARGIN_APPROX if refract1 else V_MARGIN_EXACT
    biv = sc_biv
    n_orient1 = 2 if refract1 else 1
    n_side2 = 2 if refract2 else 1
    n_pieces_sqrt = SQRT_PIECES.shape[0] if refract1 else 1
    for o1 in range(n_orient1):
        sigma1 = 1.0 if o1 == 0 else -1.0  # orientation of the shading normal vs ng1
        if refract1 and ((sigma1 > 0.0 and not any_front1) or (sigma1 < 0.0 and not any_back1)):
            continue
        s_in1 = sigma1 * (1.0 if side0 > 0.0 else -1.0)  # incoming side at vertex 1
        r1 = (1.0 / eta) if s_in1 > 0.0 else eta
        # x = β/S² range: sample the triangle
        xlo = math.inf
        xhi = -math.inf
        fallback_piece = -2  # the √ piece solved only as the TIR fallback (piece -1 is Heron)
        mask = 0  # √ pieces holding β/S² at the sample points
        if refract1:
            for iu in range(4):
                for iv in range(4 - iu):
                    uu = iu / 3.0
                    vv = iv / 3.0
                    nn = (geo[4, 0] + uu * geo[5, 0] + vv * geo[6, 0], geo[4, 1] + uu * geo[5, 1] + vv * geo[6, 1], geo[4, 2] + uu * geo[5, 2] + vv * geo[6, 2])
                    dv = ((uu * e11[0] + vv * e12[0] - geo[0, 0]) * inv, (uu * e11[1] + vv * e12[1] - geo[0, 1]) * inv, (uu * e11[2] + vv * e12[2] - geo[0, 2]) * inv)
                    n2_ = nn[0] ** 2 + nn[1] ** 2 + nn[2] ** 2
                    d2_ = dv[0] ** 2 + dv[1] ** 2 + dv[2] ** 2
                    dn = nn[0] * dv[0] + nn[1] * dv[1] + nn[2] * dv[2]
                    beta = n2_ * d2_ * (1.0 - r1 * r1) + r1 * r1 * dn * dn
                    x = beta / (S * S)
                    xlo = min(xlo, x)
                    xhi = max(xhi, x)
                    if x >= 0.0:
                        mask |= 1 << _sqrt_piece(x)
            nn = (geo[4, 0] + (geo[5, 0] + geo[6, 0]) / 3.0, geo[4, 1] + (geo[5, 1] + geo[6, 1]) / 3.0, geo[4, 2] + (geo[5, 2] + geo[6, 2]) / 3.0)
            dv = ((cx[0] - geo[0, 0]) * inv, (cx[1] - geo[0, 1]) * inv, (cx[2] - geo[0, 2]) * inv)
            n2_ = nn[0] ** 2 + nn[1] ** 2 + nn[2] ** 2
            d2_ = dv[0] ** 2 + dv[1] ** 2 + dv[2] ** 2
            dn = nn[0] * dv[0] + nn[1] * dv[1] + nn[2] * dv[2]
            xc = min(1.0, max(0.0, (n2_ * d2_ * (1.0 - r1 * r1) + r1 * r1 * dn * dn) / (S * S)))
            if xhi <= 0.0:
                continue  # TIR everywhere on the triangle
            if SQRT_ALL_PIECES:
                xlo = max(0.0, xlo * 0.8)
                xhi = min(1.0, xhi * 1.25)
            else:
                # the pieces holding x at the corners, edge thirds and centroid (the
                # Gauss-Newton polish in path space removes the error of a piece used
                # a little outside its interval)
                mask, fallback_piece = _centroid_piece(xc, mask)
        if refract1 and SQRT_BANDS:
            _beta_poly(geo_l, r1, biv)
            if xlo > 0.0:
                mask |= _beta_mask(biv, margin, S * S)
        heron_ok = False
        heron_cut = HERON_CUT
        heron = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        if refract1 and HERON_SQRT:
            heron_ok, heron_cut, heron = heron_sqrt_cut(geo_l, r1, margin, S * S, biv[45, 0:6, 0:7])
        for piece in range(-1, n_pieces_sqrt):
            # piece -1: the Heron √ (β/S² above its cut), then the eq (23) pieces (only
            # those reaching below the cut when the Heron √ is used)
            if piece < 0 and not heron_ok:
                continue
            if piece >= 0 and heron_ok and SQRT_PIECES[piece, 0] >= heron_cut:
                continue
            if piece >= 0 and refract1 and SQRT_ALL_PIECES and (SQRT_PIECES[piece, 1] < xlo or SQRT_PIECES[piece, 0] > xhi):
                continue
            if piece >= 0 and refract1 and not SQRT_ALL_PIECES and not (mask >> piece) & 1:
                continue
            for o2 in range(n_side2):
                eta_in2 = 1.0
                eta_out2 = 1.0
                if refract2:
                    sigma2 = 1.0 if o2 == 0 else -1.0
                    if (sigma2 > 0.0 and not any_front2) or (sigma2 < 0.0 and not any_back2):
                        continue
                    # incoming side at vertex 2: x1's side of plane 2 (ng2 oriented by σ2),
                    # which for a refraction is the side opposite to x3's
                    s_in2 = -sigma2 * (1.0 if side3 > 0.0 else -1.0)
                    eta_in2 = 1.0 if s_in2 > 0.0 else eta
                    eta_out2 = eta if s_in2 > 0.0 else 1.0
                da, db = _build_system(refract1, refract2, s_in1, r1, piece, S, heron, eta_in2,
                                       eta_out2, flat2, c2, geo_l, biv)
                blo, bhi = _sqrt_band(piece, S * S, refract1)
                count = _solve_system(biv, da, db, blo, bhi, refract1, refract2, margin, pieces, stop_after,
                                      piece != fallback_piece, geo, eta, sc_cf,
                                      sc_mat, sc_scan, sc_work, th, v_roots, u_roots, coeffs, sc_chain, sc_lists, rev, geo_fwd, out_uv, meta,
                                      count, stats)
                if count < 0:
                    count = -count - 1
                    count = _seeded(geo, refract1, refract2, eta, rev, geo_fwd, sc_work, th, out_uv, meta, count, stats)
    return count


@kernel
def _solve_system(biv, da, db, blo, bhi, refract1, refract2, margin, pieces, stop_after, refine, geo, eta, cf, mat, scan, work, th,
                  v_roots, u_roots, coeffs, chain, lists, rev, geo_fwd, out_uv, meta, count, stats):
    """Roots of {a = 0, b = 0} -> polished paths, where β lies in [blo, bhi] (the √ piece's
    band, :func:`_sqrt_band`); ``refine``: refine the scan (:func:`refine_v_roots`) or take
    its sign changes only.  Returns the new count, or -(count + 1) when the system is
    degenerate (identically vanishing resultant)."""
    a = biv[0]
    b = biv[1]
    ma = _bmax(a, da)
    mb = _bmax(b, db)
    if not (ma > 0.0 and mb > 0.0) or not (np.isfinite(ma) and np.isfinite(mb)):
        return -(count + 1)
    for i in range(da + 1):
        for j in range(da + 1 - i):
            a[i, j] /= ma
            if abs(a[i, j]) <= 1e-14:
                a[i, j] = 0.0
    for i in range(db + 1):
        for j in range(db + 1 - i):
            b[i, j] /= mb
            if abs(b[i, j]) <= 1e-15:
                b[i, j] = 0.0
    # early exit: the coplanarity polynomial has no zero on triangle 1
    if da <= 20 and not _bernstein_has_zero(a, da, 1e-2 if refract1 else 1e-9, coeffs):
        stats[STAT_SKIPPED] = 1
        return count
    if stop_after == 1:
        return count
    # Hidden variable v1 (u1 eliminated), then hidden u1 (v1 eliminated) on the transposed
    # system: two solutions whose projections on one axis fall within one piece are a root
    # pair no sign scan separates, but they are seldom that close on both axes.
    count = _eliminate(a, da, b, db, blo, bhi, False, refract1, refract2, margin, pieces, stop_after, refine, geo, eta, cf, mat, scan,
                       work, th, biv, v_roots, u_roots, coeffs, chain, lists, rev, geo_fwd, out_uv, meta, count, stats)
    if count < 0:
        return count
    if not TWO_PROJECTIONS:
        return count
    at = biv[37]
    bt = biv[38]
    _transpose(a, da, at)
    _transpose(b, db, bt)
    return _eliminate(at, da, bt, db, -math.inf, math.inf, True, refract1, refract2, margin, pieces, stop_after, refine, geo, eta, cf, mat, scan,
                      work, th, biv, v_roots, u_roots, coeffs, chain, lists, rev, geo_fwd, out_uv, meta, count, stats)


@kernel
def _transpose(src, d, dst):
    for i in range(d + 1):
        for j in range(d + 1 - i):
            dst[j, i] = src[i, j]


@kernel
def _eliminate(a, da, b, db, blo, bhi, swapped, refract1, refract2, margin, pieces, stop_after, refine, geo, eta, cf, mat, scan, work, th,
               biv, v_roots, u_roots, coeffs, chain, lists, rev, geo_fwd, out_uv, meta, count, stats):
    """Eliminate the first variable (rows of a, b), scan the hidden one (columns), back-solve,
    polish.  ``swapped``: the hidden variable is u1 (the arrays are transposed)."""
    na = _u_degree(a, da, 1e-14)
    nb = _u_degree(b, db, 1e-15)
    n = max(na, nb)
    if n == 0 or n >= MAXD:
        return -(count + 1)
    live = scan[7]
    if swapped:
        biv[HIT_SLOT, MAXD, 0] = 0.0  # the stored map to triangle 2 is in (u1, v1), not transposed: no hit test
    if LIVE_PREPASS:
        boxes = scan[3, 0:LIVE_STACK * 4].reshape((LIVE_STACK, 4))
        if live_pieces_band(a, da, b, db, margin, pieces, biv, boxes, live, blo, bhi) == 0:
            return count
    else:
        for k in range(pieces):
            live[k] = 1
    # the determinant family reads the system v-major (the pre-pass's slots are free now)
    at = biv[V_MAJOR_SLOT]
    bt = biv[V_MAJOR_SLOT + 1]
    v_major(a, da, at)
    v_major(b, db, bt)
    nv = find_v_roots(at, da, bt, db, n, -margin, 1.0 + margin, pieces, live, cf, mat, scan, v_roots, stats)
    if nv < 0:
        return -(count + 1)
    if stop_after == 2:
        stats[STAT_ROOTS] += nv
        return count
    productive = scan[5]  # per scan root: did one of its candidates polish into a path?
    for iv in range(nv):
        near = stats[STAT_NEAR]
        count = _candidates_at(v_roots[iv], a, da, b, db, na, nb, swapped, refract1, refract2, margin, geo, eta,
                               work, th, u_roots, coeffs, chain, lists, rev, geo_fwd, out_uv, meta, count, stats)
        productive[iv] = 1.0 if stats[STAT_NEAR] > near else 0.0
    nv_all = refine_v_roots(at, da, bt, db, n, pieces, live, cf, mat, scan, v_roots, nv, productive, stats) if refine else nv

    for iv in range(nv, nv_all):
        count = _candidates_at(v_roots[iv], a, da, b, db, na, nb, swapped, refract1, refract2, margin, geo, eta,
                               work, th, u_roots, coeffs, chain, lists, rev, geo_fwd, out_uv, meta, count, stats)
    stats[STAT_ROOTS] += max(nv, nv_all)
    return count


@kernel
def _candidates_at(v, a, da, b, db, na, nb, swapped, refract1, refract2, margin, geo, eta, work, th, u_roots, coeffs,
                   chain, lists, rev, geo_fwd, out_uv, meta, count, stats):
    """Back-substitution at a resultant root v (§4.3): the roots u of a(·, v) in the
    triangle whose b(u, v) is relatively small (the smallest always) are polished as paths."""
    # a(·, v) coefficients
    deg_u = na
    for i in range(na + 1):
        acc = 0.0
        for j in range(da - i, -1, -1):
            acc = acc * v + a[i, j]
        coeffs[i] = acc
    use_b = False
    big = 0.0
    for i in range(na + 1):
        big = max(big, abs(coeffs[i]))
    if not big > 1e-12 or na == 0:
        use_b = True
    if use_b:
        if nb > MAX_DEGREE:
            return count
        deg_u = nb
        for i in range(nb + 1):
            acc = 0.0
            for j in range(db - i, -1, -1):
                acc = acc * v + b[i, j]
            coeffs[i] = acc
    if deg_u > MAX_DEGREE or deg_u == 0:
        return count
    n_u = roots_in_interval(coeffs, deg_u, -margin, 1.0 - v + margin, 1e-14, 1e-10, chain, lists[0:2], u_roots)
    # rank by relative |b(u, v)|
    best = -1
    best_rel = math.inf
    for iu in range(n_u):
        u = u_roots[iu]
        val = 0.0
        mag = 0.0
        up = 1.0
        for i in range(nb + 1):
            acc = 0.0
            for j in range(db - i, -1, -1):
                acc = acc * v + b[i, j]
            val += acc * up
            mag += abs(acc * up)
            up *= u
        rel = abs(val) / mag if mag > 0.0 else 0.0
        lists[2, iu] = rel
        if rel < best_rel:
            best_rel = rel
            best = iu
    for iu in range(n_u):
        if iu != best and not lists[2, iu] < B_RELATIVE:
            continue
        u1 = min(max(u_roots[iu], 0.0), 1.0)
        v1 = min(max(v, 0.0), 1.0)
        if u1 + v1 > 1.0:
            excess = 0.5 * (u1 + v1 - 1.0)
            u1 -= excess
            v1 -= excess
        if swapped:
            u1, v1 = v1, u1
        if _already_stored(u1, v1, out_uv, 2 if rev else 0, count):
            stats[STAT_ACCEPTED] += 1
            if abs((u1 if swapped else v1) - v) <= PRODUCTIVE_RADIUS:
                stats[STAT_NEAR] += 1
            continue
        accepted = stats[STAT_ACCEPTED]
        count = _try_candidate(u1, v1, geo, refract1, refract2, eta, rev, geo_fwd, work, th, out_uv, meta, count, stats)
        if stats[STAT_ACCEPTED] > accepted:
            # th: the polished path, forward order; the oriented chain's (u1, v1) are th[2:4]
            # when solved reversed
            hidden = th[(2 if rev else 0) + (0 if swapped else 1)]
            if abs(hidden - v) <= PRODUCTIVE_RADIUS:
                stats[STAT_NEAR] += 1
    return count


@kernel
def _already_stored(u1, v1, out_uv, off, count):
    for q in range(min(count, out_uv.shape[0])):
        if abs(out_uv[q, off] - u1) < 1e-9 and abs(out_uv[q, off + 1] - v1) < 1e-9:
            return True
    return False


@kernel(parallel=True)
def solve_two_bounce_batch(refract1, refract2, x_start, x_end, P, N, eta, pieces, stop_after, out_uv, out_count, stats):
    n = x_start.shape[0]
    n_chunks = (n + CHUNK - 1) // CHUNK
    for ch in prange(n_chunks):
        biv, cf, mat, scan, geo, work, roots, chain, lists = make_scratch2()
        for t in range(ch * CHUNK, min(n, (ch + 1) * CHUNK)):
            x0 = (x_start[t, 0], x_start[t, 1], x_start[t, 2])
            x3 = (x_end[t, 0], x_end[t, 1], x_end[t, 2])
            out_count[t] = solve_two_bounce_tuple(refract1, refract2, x0, x3, P[t], N[t], eta[t], pieces, stop_after,
                                                  biv, cf, mat, scan, geo, work, roots, chain, lists, out_uv[t], stats[t])


@kernel
def make_scratch2():
    biv = np.zeros((N_SLOTS, MAXD + 1, MAXD + 1))
    cf = np.zeros((2, MAXD + 2))
    mat = np.zeros((MAXD + 1, MAXD + 1))
    scan = np.zeros((9, MAX_PIECES + 1))
    geo = np.zeros((3, 15, 3))
    work = np.zeros((25, 6))
    roots = np.zeros((MAX_PATHS_TWO_BOUNCE + 5, 4 * MAX_PIECES))
    chain = np.zeros((MAX_DEGREE + 1, MAX_DEGREE + 1))
    lists = np.zeros((3, MAX_DEGREE + 1))
    return biv, cf, mat, scan, geo, work, roots, chain, lists
