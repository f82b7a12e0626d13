"""Position and irradiance bounds of two-bounce chains (RR, RT, TR, TT) from a point light (Fan et al. 2025).

For a tuple (light x0, caster triangle 1, caster triangle 2, receiver triangle k) a *piece* is a
box U1 of triangle 1's barycentrics (u1, v1) with

* its position bound (§4.2–4.3, eq 3–13): receiver barycentric and UV boxes holding every
  admissible path x0 -> x1 -> x2 -> xk with x1 in U1 (``two_bounce_position``: the forms of
  (u2, v2) with remainder after vertex 1, then eq 9 at the receiver with the remainder
  variables of eq 12–13 for √β and the degree reduction of §6.1);
* its irradiance bounds Ē, E̲ (§4.4, eq 14–16) by the exact forward map in affine arithmetic
  (``two_bounce_irradiance``), which also proves boxes empty (``prune``).

The pair-level quadtree (§6.1) starts from the reach grid of ``receivers_reached`` and bounds
every receiver of a pair in one traversal.  Tested in tests/solver/test_bounds_two_bounce.py
(no exact path outside its piece; the reference engine of tests/reference/bounds_two_bounce.py
gives the same pieces) and tests/solver/test_bounds_validity.py.
"""

import time
from dataclasses import dataclass, field

import numpy as np

from .layout import CHAIN_CODES, P_EHI, P_ELO, P_RECEIVER, P_X0, P_X1, P_Y0, P_Y1, PIECE_FIELDS, TWO_BOUNCE_STATS
from .two_bounce_irradiance import bound_irradiance_two, receivers_reached
from .two_bounce_position import batch


@dataclass
class TwoBounceBounds:
    """Result of :func:`bound_two_bounce`.

    tuples: (m, 3) int64 (triangle 1, triangle 2, receiver) of the tuples with at least one piece;
    piece_tuple, pieces, tuple_uv_box as ``one_bounce.OneBounceBounds`` (Ē = inf where the irradiance
    pass did not run or could not bound the piece)."""

    chain: str
    tuples: np.ndarray
    piece_tuple: np.ndarray
    pieces: np.ndarray
    tuple_uv_box: np.ndarray
    report: dict = field(default_factory=dict)


def _tuple_uv_boxes(pieces, starts):
    """UV box of each tuple: the union of its pieces' UV bounds (pieces of a tuple contiguous,
    starting at ``starts``)."""
    box = np.empty((starts.shape[0], 4))
    if starts.shape[0]:
        box[:, 0] = np.minimum.reduceat(pieces[:, P_X0], starts)
        box[:, 1] = np.maximum.reduceat(pieces[:, P_X1], starts)
        box[:, 2] = np.minimum.reduceat(pieces[:, P_Y0], starts)
        box[:, 3] = np.maximum.reduceat(pieces[:, P_Y1], starts)
    return box


def bound_two_bounce(chain, light, caster_P, caster_N, receiver_P, receiver_UV, eta=1.5, pairs=None, max_depth=1,
                     sigma=1e-4, capacity=16, irradiance=True, irr_depth=4, irr_ratio=2.0, prune=True,
                     reach_depth=2, engine=None):
    """Position bounds of two-bounce tuples (Fan et al. 2025 §4.2–4.3, eq 3–13; subdivision §6.1).

    chain: "RR", "RT", "TR" or "TT"; caster_P, caster_N: (n,3,3) corners and corner normals of
    the specular triangles (both vertices index into them); receiver_P (r,3,3), receiver_UV
    (r,3,2); eta: IOR behind the caster surfaces (normals point away from it);
    pairs: (t,2) (triangle 1, triangle 2) candidates, each bounded against every receiver
    (``tuples.two_bounce_pairs`` builds them; default all n·(n-1), only for tiny meshes);
    max_depth, sigma: the stopping rules; capacity: most pieces per tuple;
    irradiance: also bound Ē, E̲ per piece (``two_bounce_irradiance.bound_irradiance_two`` with
    irr_depth, irr_ratio), else Ē = inf; prune: then drop the pieces (and tuples) that pass
    proved to hold no path; reach_depth: a box of the position quadtree lives for a receiver
    only where ``two_bounce_irradiance.receivers_reached`` (triangle 1 and its 2^reach_depth
    grid) does not prove it empty (None: no such test); engine: the batch driver,
    ``two_bounce_position.batch`` by default (tests pass the reference engine of
    tests/reference/bounds_two_bounce.py, which has the same signature)."""
    if chain not in CHAIN_CODES:
        raise ValueError(f"bound_two_bounce handles chains RR, RT, TR and TT, got {chain!r}")
    t0 = time.perf_counter()
    light = np.ascontiguousarray(light, dtype=np.float64).reshape(3)
    caster_P = np.ascontiguousarray(caster_P, dtype=np.float64)
    caster_N = np.ascontiguousarray(caster_N, dtype=np.float64)
    receiver_P = np.ascontiguousarray(receiver_P, dtype=np.float64)
    receiver_UV = np.ascontiguousarray(receiver_UV, dtype=np.float64)
    if pairs is None:
        n = caster_P.shape[0]
        a, b = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
        keep = (a != b).ravel()
        pairs = np.stack([a.ravel()[keep], b.ravel()[keep]], axis=1)
    pairs = np.ascontiguousarray(pairs, dtype=np.int64).reshape(-1, 2)
    n = pairs.shape[0]
    nr = receiver_P.shape[0]
    capacity = max(1, min(int(capacity), 4 ** int(max_depth)))
    rows = np.empty((n * capacity * nr, PIECE_FIELDS + 1))
    row_start = np.arange(n + 1, dtype=np.int64) * (capacity * nr)
    counts = np.zeros(n, dtype=np.int64)
    stats = np.zeros((n, TWO_BOUNCE_STATS), dtype=np.int64)
    t1 = time.perf_counter()
    if reach_depth is None or not (n and nr):
        reach = np.ones((n, nr, 1, 1), dtype=np.bool_)
    else:
        reach = receivers_reached(chain, light, caster_P, caster_N, receiver_P, pairs, eta, int(reach_depth))
    t_reach = time.perf_counter()
    if n and nr:
        points = np.array(np.broadcast_to(light, (n, 3)))
        (engine or batch)(CHAIN_CODES[chain], points, caster_P, caster_N, receiver_P, receiver_UV, np.full(n, float(eta)), pairs,
                          reach, np.full(n, nr, dtype=np.int64), row_start, int(max_depth), float(sigma), rows, counts, stats)
    t2 = time.perf_counter()
    pair_of = np.repeat(np.arange(n), counts)
    slot = np.arange(pair_of.shape[0]) - np.repeat(np.cumsum(counts) - counts, counts)
    rows = rows[row_start[pair_of] + slot]
    receiver = rows[:, P_RECEIVER].astype(np.int64)
    order = np.lexsort((receiver, pair_of))  # tuples (pair, receiver) contiguous
    rows, pair_of, receiver = rows[order], pair_of[order], receiver[order]
    key = pair_of * max(nr, 1) + receiver
    new = np.ones(key.shape[0], dtype=bool)
    new[1:] = key[1:] != key[:-1]
    starts = np.flatnonzero(new)
    piece_tuple = np.cumsum(new) - 1
    tuples = np.stack([pairs[pair_of[starts], 0], pairs[pair_of[starts], 1], receiver[starts]], axis=1) if starts.size \
        else np.zeros((0, 3), dtype=np.int64)
    pieces = np.ascontiguousarray(rows[:, :PIECE_FIELDS])
    m = starts.shape[0]
    box = _tuple_uv_boxes(pieces, starts)
    t3 = time.perf_counter()
    total = stats.sum(axis=0)
    report = {
        "pairs": int(n), "receivers": int(nr), "tuples": int(m), "pieces": int(pieces.shape[0]),
        "pieces_per_tuple": float(pieces.shape[0] / m) if m else 0.0,
        "box_evaluations": int(total[0]), "stage_one_misses": int(total[1]), "constant_forms": int(total[2]),
        "capacity_stops": int(total[3]), "reach_tuples": int(reach.any(axis=(2, 3)).sum()), "reach_depth": reach_depth,
        "memory_mb": (pieces.nbytes + box.nbytes + piece_tuple.nbytes + tuples.nbytes) / 2**20,
        "seconds": {"prepare": t1 - t0, "reach": t_reach - t1, "bound": t2 - t_reach, "compact": t3 - t2},
    }
    result = TwoBounceBounds(chain, tuples, piece_tuple, pieces, box, report)
    if irradiance:
        bound_irradiance_two(result, light, caster_P, caster_N, receiver_P, eta, irr_depth=irr_depth, irr_ratio=irr_ratio)
        if prune:
            result = drop_pieces_without_paths(result)
    return result


def drop_pieces_without_paths(bounds):
    """Remove the pieces the irradiance pass proved empty (Ē = E̲ = 0: no admissible path in the
    box reaches the receiver — backward rays, u2 outside triangle 2 or total internal reflection
    on the whole box, which the position bound's relaxations cannot see) and the tuples left
    without a piece.  Returns a new ``TwoBounceBounds``; the report keeps the counts before."""
    keep = ~((bounds.pieces[:, P_EHI] == 0.0) & (bounds.pieces[:, P_ELO] == 0.0))
    pieces = np.ascontiguousarray(bounds.pieces[keep])
    old_tuple = bounds.piece_tuple[keep]
    used, piece_tuple = np.unique(old_tuple, return_inverse=True)  # old_tuple is sorted: order kept
    tuples = bounds.tuples[used]
    m = tuples.shape[0]
    box = _tuple_uv_boxes(pieces, np.flatnonzero(np.r_[True, piece_tuple[1:] != piece_tuple[:-1]]))
    report = dict(bounds.report)
    report.update({
        "tuples_before_pruning": bounds.report["tuples"], "pieces_before_pruning": bounds.report["pieces"],
        "pairs_with_tuples": int(np.unique(tuples[:, :2], axis=0).shape[0]),
        "tuples": int(m), "pieces": int(pieces.shape[0]), "pieces_per_tuple": float(pieces.shape[0] / m) if m else 0.0,
        "memory_mb": (pieces.nbytes + box.nbytes + piece_tuple.nbytes + tuples.nbytes) / 2**20,
    })
    return TwoBounceBounds(bounds.chain, tuples, piece_tuple.astype(np.int64), pieces, box, report)
