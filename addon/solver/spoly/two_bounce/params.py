"""Constants of the two-bounce solver: array sizes and biv slot map, tolerances, the
switches of the pipeline's stages, the statistics row's indices, and the piecewise rational
√ of eq (23) (``SQRT_PIECES``, Fan et al. 2024) with the Heron cuts taken from it.

Every kernel module of the package imports these as Numba compile-time globals.  The
reasoning behind each value: docs/decisions/two-bounce-solver.md.
"""

import numpy as np

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
KINK = 1.0  # second difference of log|det| that flags a root cluster nearby (2.0 loses TT paths: docs/decisions/two-bounce-solver.md)
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
HIT_TEST = True  # the pre-pass also drops boxes whose x1 cannot reach triangle 2 (``misses_second``)
LIVE_SLOT0 = 2  # first biv slot of the pre-pass's box stack (two slots per box: a, b)
LIVE_STACK = 3 * LIVE_DEPTH + 1
LANES = 16  # det_bezout's sliding window: g's u-degree m at most this (a: 16 at most); the lane tuple below has 16
WINDOW_FROM = 24  # ... for matrices at least this large (below, the dense elimination is as fast)
BOTH_DIRECTIONS = True  # solve the chain forward and reversed (reciprocity)
SQRT_BANDS = True  # an eq (23) piece's system only where β/S² can lie in its band (the piece and its neighbours)
SQRT_BAND_REACH = 3  # ... and this many pieces on each side of it (1 and 2 lose paths: docs/decisions/two-bounce-solver.md)
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
