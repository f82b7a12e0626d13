"""Position and irradiance bounds of one-bounce chains (R, T) from a point light (Fan et al. 2025).

For a tuple (light x0, caster triangle 1, receiver triangle k) and a box U1 of the caster's
barycentrics (u1, v1), a *piece* (a row of ``layout``) gets

* the position bound (eq 4–5): a box of receiver barycentrics (uk, vk) and of receiver UV
  texture coordinates that contains the hit point of every admissible path x0 -> x1 -> xk
  with x1 in U1 (∩ the triangle) and xk on the receiver triangle (``one_bounce_position``:
  x1, n1 affine in (u1, v1), eq 6–7; d0 = x1 - x0, eq 8; the outgoing direction d̃ of eq 10,
  for refraction with √β replaced by the linear approximation aβ + b plus a remainder
  variable ξ in [0, 1], eq 11–13; one shared denominator q = (d̃ × e_k2)·e_k1, eq 9);
* the irradiance bound (eq 14–15, §4.4): Ē >= dΩ0/dA_k of every such path (F, V <= 1 and
  I0 = 1 left out as in the paper) — explicit Jacobian for R (eq 15–16,
  ``one_bounce_position.box_irradiance_reflect``), implicit differentiation for T (eq 17–19,
  ``one_bounce_irradiance``).  m = 1 solution per tuple is assumed (eq 21).

Subdivision (§6.1, :func:`tuple_pieces`): the u1 box is split at the midpoint into four while
the position bound's area (in receiver barycentrics) is >= σ, Ē/E̲ >= α and the depth is below
the limit; pieces whose position bound misses the receiver triangle are dropped (the effective
domain).  Degrees stay at most 13 per variable, so no degree reduction is needed.

Tested in tests/solver/test_bounds_validity.py (no admissible path outside its piece's bounds,
brute force), tests/solver/test_bounds_bernstein.py and against the reference engine of
tests/reference/bounds_one_bounce.py.
"""

import time
from dataclasses import dataclass, field

import numpy as np

from ..runtime.jit import kernel, run_chunks
from .slot_algebra import MAXC, N4, SCR4
from .one_bounce_position import NSLOTS, box_irradiance_reflect, box_position, make_context, setup_caster, setup_reflect_irradiance, setup_tuple
from .one_bounce_irradiance import NU, UW, box_irradiance_refract
from .layout import ONE_BOUNCE_STATS, PIECE_FIELDS, P_BU0, P_DEPTH, P_EHI, P_ELO, P_U0, P_U1, P_V0, P_V1, P_X0, P_X1, P_Y0, P_Y1, push_children


# ---------------------------------------------------------------------------------------
# the quadtree per tuple


@kernel
def box_irradiance(W, U, work, scr, refract, x0, P, N, Q, eta, lo, hi, pos):
    if refract:
        return box_irradiance_refract(W, U, scr, x0, P, N, Q, eta, lo, hi, pos)
    return box_irradiance_reflect(W, work, Q, lo, hi)


@kernel
def refine_irradiance(W, U, work, scr, rstack, refract, x0, P, N, Q, UV, eta, lo, hi, levels, stats):
    """Ē, E̲ of a piece whose own Ē is infinite, as the max / min over a quadtree of sub-boxes
    of its (u1, v1) box (at most ``levels`` deep, splitting only sub-boxes that are still
    unbounded).  Each sub-box uses its own position bound as the (uk, vk) box of the implicit
    bound (eq 17–19) and is skipped when that bound misses the receiver (no path there), so
    the result bounds every path of the piece (eq 21 over a finer partition); it stays
    infinite when a sub-box at the last level is still unbounded (a focal point, or the
    0/0 of the implicit form at normal incidence).  The piece itself is unchanged."""
    slo = scr[36:38]
    shi = scr[38:40]
    spos = scr[40:48]
    res = scr[48:56]
    top = 0
    ehi = 0.0
    elo = np.inf
    found = False
    top = push_children(rstack, top, lo, hi, 0)
    while top > 0:
        top -= 1
        slo[0], shi[0], slo[1], shi[1] = rstack[top, 0], rstack[top, 1], rstack[top, 2], rstack[top, 3]
        level = int(rstack[top, 4])
        stats[0] += 1
        if not box_position(W, work, refract, x0, P, N, UV, eta, slo, shi, spos, res):
            continue
        stats[1] += 1
        h, l = box_irradiance(W, U, work, scr, refract, x0, P, N, Q, eta, slo, shi, spos)
        if not h < np.inf:
            if level >= levels:
                return np.inf, 0.0
            top = push_children(rstack, top, slo, shi, level)
            continue
        found = True
        ehi = max(ehi, h)
        elo = min(elo, l)
    if not found:
        return 0.0, 0.0
    return ehi, elo


@kernel
def tuple_pieces(W, U, work, scr, stack, rstack, refract, x0, P, N, Q, UV, eta, max_depth, sigma, alpha, irradiance,
                      irr_refine, out, stats):
    """The reference tuple_pieces with this engine's kernels: same stopping rules (§6.1), same piece rows.

    The root's position bound is computed before the per-tuple polynomials of the irradiance
    so that a tuple whose caustic misses the receiver triangle costs one position bound.
    The caller has built the caster's polynomials (:func:`setup_caster`) in W."""
    cap = out.shape[0]
    setup_tuple(W, refract, x0, P, Q)
    have_irr = False
    stack[0, 0], stack[0, 1], stack[0, 2], stack[0, 3], stack[0, 4] = 0.0, 1.0, 0.0, 1.0, 0.0
    top = 1
    count = 0
    lo = scr[0:2]
    hi = scr[2:4]
    pos = scr[4:12]
    res = scr[12:20]
    while top > 0:
        top -= 1
        lo[0], hi[0], lo[1], hi[1] = stack[top, 0], stack[top, 1], stack[top, 2], stack[top, 3]
        depth = int(stack[top, 4])
        stats[0] += 1
        if not box_position(W, work, refract, x0, P, N, UV, eta, lo, hi, pos, res):
            continue
        if irradiance and not refract and not have_irr:
            setup_reflect_irradiance(W)
            have_irr = True
        can_split = depth < max_depth and count + top + 4 <= cap
        area = (pos[1] - pos[0]) * (pos[3] - pos[2])
        ehi = np.inf
        elo = 0.0
        split = False
        if area >= sigma and can_split:
            if irradiance:
                stats[1] += 1
                ehi, elo = box_irradiance(W, U, work, scr, refract, x0, P, N, Q, eta, lo, hi, pos)
                split = not (elo > 0.0 and ehi < alpha * elo)
            else:
                split = True
        elif irradiance:
            stats[1] += 1
            ehi, elo = box_irradiance(W, U, work, scr, refract, x0, P, N, Q, eta, lo, hi, pos)
        if split:
            top = push_children(stack, top, lo, hi, depth)
            continue
        if depth < max_depth and area >= sigma and not can_split:
            stats[3] += 1
        if irradiance and not ehi < np.inf and irr_refine > 0:
            ehi, elo = refine_irradiance(W, U, work, scr, rstack, refract, x0, P, N, Q, UV, eta, lo, hi, irr_refine, stats)
        if irradiance and not ehi < np.inf:
            stats[2] += 1
        row = out[count]
        row[P_U0], row[P_U1], row[P_V0], row[P_V1] = lo[0], hi[0], lo[1], hi[1]
        for k in range(8):
            row[P_BU0 + k] = pos[k]
        row[P_EHI] = ehi
        row[P_ELO] = elo
        row[P_DEPTH] = depth
        count += 1
    return count


@kernel
def workspace():
    return np.zeros((NSLOTS, MAXC)), np.zeros(16), np.zeros(SCR4 + 3 * N4), np.zeros((NU, UW))


@kernel
def _batch_chunk(refract, x0, P, N, Q, UV, eta, pairs, max_depth, sigma, alpha, irradiance, irr_refine, out, counts, stats,
                 start, stop):
    """Tuples start..stop-1 on one workspace (``batch``); x0[c] is caster c's light point."""
    W, work, scr, U = workspace()
    stack = np.empty((4 * (max_depth + 2), 5))
    rstack = np.empty((4 * (irr_refine + 2), 5))
    last = -1
    for t in range(start, stop):
        c = pairs[t, 0]
        r = pairs[t, 1]
        if c != last:  # pairs are usually grouped by caster: its polynomials are reused
            setup_caster(W, refract, x0[c], P[c], N[c])
            last = c
        counts[t] = tuple_pieces(W, U, work, scr, stack, rstack, refract, x0[c], P[c], N[c], Q[r], UV[r], eta, max_depth, sigma,
                                 alpha, irradiance, irr_refine, out[t], stats[t])


def batch(refract, x0, P, N, Q, UV, eta, pairs, max_depth, sigma, alpha, irradiance, irr_refine, out, counts, stats, chunk):
    """Every (caster, receiver) tuple of ``pairs`` (x0: (n, 3) light point per caster) in chunks
    of ``chunk`` tuples, one workspace per chunk, on ``jit.run_chunks`` threads (``_batch_chunk``
    releases the GIL; a ``parallel=True`` loop over the chunks compiles seconds longer)."""
    n = pairs.shape[0]
    run_chunks(_batch_chunk, (refract, x0, P, N, Q, UV, eta, pairs, max_depth, sigma, alpha, irradiance, irr_refine, out, counts,
                              stats), n, max(1, -(-n // max(1, int(chunk)))))


@kernel
def eval_box(refract, x0, P, N, Q, UV, eta, lo, hi, pos):
    """One box of one tuple, for tests: writes the position bound into pos[0:8] and returns
    (inside, Ē, E̲) as the reference piece_position / piece_irradiance_* would."""
    W, work, scr, U = workspace()
    make_context(W, refract, False, x0, P, N, Q)
    res = np.zeros(8)
    if not box_position(W, work, refract, x0, P, N, UV, eta, lo, hi, pos, res):
        return False, 0.0, 0.0
    if not refract:
        setup_reflect_irradiance(W)
    ehi, elo = box_irradiance(W, U, work, scr, refract, x0, P, N, Q, eta, lo, hi, pos)
    return True, ehi, elo



@dataclass
class OneBounceBounds:
    """Result of :func:`bound_one_bounce`.

    tuples: (m, 2) int64 (caster index, receiver index) of the tuples with at least one piece;
    piece_tuple: (p,) index into ``tuples`` per piece; pieces: (p, PIECE_FIELDS) rows (P_*).
    tuple_uv_box: (m, 4) hull of the pieces' UV boxes (x_lo, x_hi, y_lo, y_hi);
    tuple_E: (m,) Ẽ = m_solutions · max piece Ē (eq 21, inf where some piece is unbounded).
    """

    chain: str
    tuples: np.ndarray
    piece_tuple: np.ndarray
    pieces: np.ndarray
    tuple_uv_box: np.ndarray
    tuple_E: np.ndarray
    report: dict = field(default_factory=dict)


def bound_one_bounce(chain, light, caster_P, caster_N, receiver_P, receiver_UV, eta=1.5, pairs=None, max_depth=4,
                     sigma=1e-4, alpha=2.0, irradiance=True, capacity=64, solutions_per_tuple=1, irr_refine=0,
                     engine=None):
    """Position and irradiance bounds of every (caster triangle, receiver triangle) tuple for
    a point light (Fan et al. 2025 §4, eq 3–19; subdivision §6.1).

    chain: "R" or "T"; light: (3,) point-light position; caster_P, caster_N: (n,3,3) caster
    triangle corners and corner normals; receiver_P: (r,3,3); receiver_UV: (r,3,2) UV per
    corner; eta: IOR behind the caster surface (normals point away from it; T only);
    pairs: (t,2) candidate (caster, receiver) index pairs (default all n·r);
    max_depth, sigma, alpha: the stopping rules (α = 2 for single scattering);
    irradiance: also compute Ē (else Ē = inf); capacity: most pieces per tuple;
    solutions_per_tuple: m of eq 21 (1 by default: one path per tuple);
    light may also be (n, 3), one point per caster (the sun's far points in the bake);
    irr_refine: a leaf piece whose Ē is infinite gets Ē, E̲ as the max / min over sub-boxes of
    its (u1, v1) box, up to this many quadtree levels deep (pieces and position bounds
    unchanged; see :func:`refine_irradiance`);
    engine: the batch driver, :func:`batch` by default (tests pass the reference engine of
    tests/reference/bounds_one_bounce.py, which has the same signature).
    """
    if chain not in ("R", "T"):
        raise ValueError(f"bound_one_bounce handles chains R and T, got {chain!r}")
    t0 = time.perf_counter()
    light = np.asarray(light, dtype=np.float64)
    caster_P = np.ascontiguousarray(caster_P, dtype=np.float64)
    caster_N = np.ascontiguousarray(caster_N, dtype=np.float64)
    receiver_P = np.ascontiguousarray(receiver_P, dtype=np.float64)
    receiver_UV = np.ascontiguousarray(receiver_UV, dtype=np.float64)
    if pairs is None:
        ci, ri = np.meshgrid(np.arange(caster_P.shape[0]), np.arange(receiver_P.shape[0]), indexing="ij")
        pairs = np.stack([ci.ravel(), ri.ravel()], axis=1)
    pairs = np.ascontiguousarray(pairs, dtype=np.int64).reshape(-1, 2)
    n = pairs.shape[0]
    points = np.array(np.broadcast_to(light.reshape(-1, 3), (caster_P.shape[0], 3)))
    # A quadtree of depth max_depth has at most 4**max_depth leaves, and the split test
    # (count + pending + 4 <= capacity) never refuses a split below that many rows (finished
    # leaves, pending boxes and the split box's children lie in disjoint subtrees), so the
    # smaller capacity gives the same pieces.  It keeps the row buffer small: 64 rows x 40k
    # tuples would be 307 MB whose first-touch page faults cost more than the pool20k bound.
    capacity = max(1, min(int(capacity), 4 ** int(max_depth)))
    out = np.empty((n, capacity, PIECE_FIELDS))
    counts = np.zeros(n, dtype=np.int64)
    stats = np.zeros((n, ONE_BOUNCE_STATS), dtype=np.int64)
    t1 = time.perf_counter()
    if n:
        (engine or batch)(chain == "T", points, caster_P, caster_N, receiver_P, receiver_UV, float(eta), pairs, int(max_depth),
                          float(sigma), float(alpha), bool(irradiance), int(irr_refine), out, counts, stats,
                          max(32, n // 128))  # one workspace per chunk: about 128 chunks, not n / 32 allocations
    t2 = time.perf_counter()
    keep = np.flatnonzero(counts > 0)
    kept_counts = counts[keep]
    piece_tuple = np.repeat(np.arange(keep.shape[0]), kept_counts)
    slot = np.arange(piece_tuple.shape[0]) - np.repeat(np.cumsum(kept_counts) - kept_counts, kept_counts)
    pieces = out[keep[piece_tuple], slot] if piece_tuple.shape[0] else np.empty((0, PIECE_FIELDS))
    del out
    m = keep.shape[0]
    box = np.empty((m, 4))
    tuple_E = np.zeros(m)
    if m:
        starts = np.cumsum(kept_counts) - kept_counts
        box[:, 0] = np.minimum.reduceat(pieces[:, P_X0], starts)
        box[:, 1] = np.maximum.reduceat(pieces[:, P_X1], starts)
        box[:, 2] = np.minimum.reduceat(pieces[:, P_Y0], starts)
        box[:, 3] = np.maximum.reduceat(pieces[:, P_Y1], starts)
        tuple_E = solutions_per_tuple * np.maximum.reduceat(pieces[:, P_EHI], starts)
    t3 = time.perf_counter()
    total = stats.sum(axis=0)
    report = {
        "tuples_tried": int(n), "tuples": int(m), "pieces": int(pieces.shape[0]),
        "pieces_per_tuple": float(pieces.shape[0] / m) if m else 0.0,
        "position_evaluations": int(total[0]), "irradiance_evaluations": int(total[1]),
        "unbounded_pieces": int(total[2]), "capacity_stops": int(total[3]),
        "memory_mb": (pieces.nbytes + box.nbytes + tuple_E.nbytes + piece_tuple.nbytes) / 2**20,
        "seconds": {"prepare": t1 - t0, "bound": t2 - t1, "compact": t3 - t2},
    }
    return OneBounceBounds(chain, pairs[keep], piece_tuple, pieces, box, tuple_E, report)
