"""Tuple construction of two-bounce chains through a BVH (Fan et al. 2025 §6.1).

For each first triangle T1 the bound of x1 and of the outgoing direction d̃1 is taken over the
sub-boxes of a quadtree of T1's domain (``two_bounce_irradiance.first_bounce_rays``: the exact map
x1 -> d̃1 of eq 10 in affine arithmetic, √β by its Chebyshev enclosure).  A BVH over the caster
triangles is then traversed and a node (or triangle) is kept while the interval bound of
(x2 - x1) × d̃1 covers zero in every component and (x2 - x1)·d̃1 can be positive, with x2 in
the node's box: a path x1 -> x2 along d̃1 needs x2 - x1 = t d̃1 with t > 0.  A candidate T2
becomes a tuple when light leaving some sub-box can meet T2 forwards and inside it
(``two_bounce_irradiance.first_bounce_reaches``: eq 9 in affine arithmetic, sub-boxes refined up to
``refine`` levels where undecided).  Both tests are conservative, so every tuple with a path is
kept.  The work per T1 is a BVH traversal, so tuples grow with the triangles reached, not with
the square of the mesh.  Tested in tests/solver/test_bounds_two_bounce.py (every pair with an
exact path is kept).
"""

import time

import numpy as np

from ..geometry.bvh import build_bvh
from ..runtime.jit import kernel, run_chunks
from .two_bounce_irradiance import first_bounce_reaches, first_bounce_rays


@kernel(inline="always")
def _imul(a0, a1, b0, b1):
    """Interval product [a0, a1]·[b0, b1]."""
    p = a0 * b0
    q = a0 * b1
    r = a1 * b0
    s = a1 * b1
    return min(min(p, q), min(r, s)), max(max(p, q), max(r, s))


@kernel
def _may_hit(blo, bhi, xlo, xhi, dlo, dhi):
    """Can a ray from a point of the box [xlo, xhi] along a direction of the box [dlo, dhi] reach
    the box [blo, bhi]?  Interval test of (x2 - x1) × d = 0 (componentwise) and (x2 - x1)·d > 0."""
    r0 = np.empty(3)
    r1 = np.empty(3)
    for i in range(3):
        r0[i] = blo[i] - xhi[i]
        r1[i] = bhi[i] - xlo[i]
    dot_hi = 0.0
    for i in range(3):
        a, b = _imul(r0[i], r1[i], dlo[i], dhi[i])
        dot_hi += b
    if not dot_hi > 0.0:
        return False
    for i in range(3):
        j = (i + 1) % 3
        k = (i + 2) % 3
        a0, a1 = _imul(r0[j], r1[j], dlo[k], dhi[k])
        b0, b1 = _imul(r0[k], r1[k], dlo[j], dhi[j])
        if a0 - b1 > 0.0 or a1 - b0 < 0.0:
            return False
    return True


@kernel
def _pairs_of(t1, refract, x0, P, N, eta, levels, refine, node_min, node_max, node_child, node_count, node_start, order, out, stats):
    """Second triangles of first triangle t1 (module doc); writes up to out.shape[0] of them and
    returns how many there are (possibly more than written)."""
    nb = 1 << levels
    h = 1.0 / nb
    xlo = np.empty(3)
    xhi = np.empty(3)
    dlo = np.empty(3)
    dhi = np.empty(3)
    tlo = np.empty(3)
    thi = np.empty(3)
    box = np.zeros(4)
    stack = np.empty(64, dtype=np.int64)
    count = 0
    boxes = np.zeros((nb * nb, 17))  # (u1 lo, u1 hi, v1 lo, v1 hi), x1's box, d̃1's box, orientation bits
    n_boxes = 0
    for i in range(nb):
        for j in range(nb):
            if i + j >= nb:
                continue  # box beyond the triangle (its lower corner has u1 + v1 >= 1)
            box[0], box[1], box[2], box[3] = i * h, (i + 1) * h, j * h, (j + 1) * h
            bits = first_bounce_rays(refract, x0, P[t1], N[t1], eta, box, xlo, xhi, dlo, dhi)
            if bits:
                b = boxes[n_boxes]
                b[0], b[1], b[2], b[3] = box[0], box[1], box[2], box[3]
                for k in range(3):
                    b[4 + k] = xlo[k]
                    b[7 + k] = xhi[k]
                    b[10 + k] = dlo[k]
                    b[13 + k] = dhi[k]
                b[16] = bits
                n_boxes += 1
    if n_boxes == 0 or node_min.shape[0] == 0:
        return 0
    for bi in range(n_boxes):
        b = boxes[bi]
        for k in range(3):
            xlo[k] = b[4 + k]
            xhi[k] = b[7 + k]
            dlo[k] = b[10 + k]
            dhi[k] = b[13 + k]
        box[0], box[1], box[2], box[3] = b[0], b[1], b[2], b[3]
        bits = int(b[16])
        top = 1
        stack[0] = 0
        while top > 0:
            top -= 1
            k = stack[top]
            stats[0] += 1
            if not _may_hit(node_min[k], node_max[k], xlo, xhi, dlo, dhi):
                continue
            if node_count[k] == 0:
                stack[top] = node_child[k]
                stack[top + 1] = node_child[k] + 1
                top += 2
                continue
            for s in range(node_start[k], node_start[k] + node_count[k]):
                t2 = order[s]
                if t2 == t1:
                    continue
                dup = False
                for c in range(min(count, out.shape[0])):
                    if out[c] == t2:
                        dup = True
                        break
                if dup:
                    continue
                T2 = P[t2]
                for a in range(3):
                    tlo[a] = min(T2[0, a], T2[1, a], T2[2, a])
                    thi[a] = max(T2[0, a], T2[1, a], T2[2, a])
                if not _may_hit(tlo, thi, xlo, xhi, dlo, dhi):
                    continue
                stats[1] += 1
                if not first_bounce_reaches(refract, x0, P[t1], N[t1], T2, eta, box, bits, refine):
                    continue
                if count < out.shape[0]:
                    out[count] = t2
                count += 1
    return count


@kernel
def pairs_chunk(refract, x0, P, N, eta, levels, refine, first, node_min, node_max, node_child, node_count, node_start, order, out,
                counts, stats, start, stop):
    """Second triangles of first triangles first[start:stop] (``_pairs_of``), first[i] lit from
    x0[i] through IOR eta[i]."""
    for i in range(start, stop):
        counts[i] = _pairs_of(first[i], refract, x0[i], P, N, eta[i], levels, refine, node_min, node_max, node_child, node_count,
                              node_start, order, out[i], stats[i])


def _all_pairs(refract, x0, P, N, eta, levels, refine, first, node_min, node_max, node_child, node_count, node_start, order, out, counts, stats,
               chunks=256):
    """``_pairs_of`` for every first triangle, in about ``chunks`` chunks on Python threads
    (``jit.run_chunks``: ``_pairs_chunk`` releases the GIL)."""
    run_chunks(pairs_chunk, (refract, x0, P, N, eta, levels, refine, first, node_min, node_max, node_child, node_count, node_start,
                              order, out, counts, stats), first.shape[0], chunks)


def two_bounce_pairs(chain, light, caster_P, caster_N, eta=1.5, levels=1, first=None, capacity=64, refine=2):
    """(T1, T2) tuples of a two-bounce chain through the BVH over the caster triangles (§6.1).

    chain: "RR", "RT", "TR" or "TT" (only the first letter matters here: how light leaves T1);
    levels: T1's domain is cut into the boxes of a quadtree this deep (bounds of x1 and d̃1 per
    box); refine: most extra quadtree levels of a box's hit test on T2; first: the T1 indices to
    extend (default all); light (3,) or one point per entry of ``first`` (the sun's far points in
    the bake), eta a scalar or one IOR per entry of ``first``.  Returns (pairs (m,2) int64, sorted,
    report)."""
    t0 = time.perf_counter()
    P = np.ascontiguousarray(caster_P, dtype=np.float64)
    N = np.ascontiguousarray(caster_N, dtype=np.float64)
    first = np.arange(P.shape[0], dtype=np.int64) if first is None else np.ascontiguousarray(first, dtype=np.int64)
    nf = first.shape[0]
    light = np.array(np.broadcast_to(np.asarray(light, dtype=np.float64).reshape(-1, 3), (nf, 3)))
    eta = np.array(np.broadcast_to(np.asarray(eta, dtype=np.float64), (nf,)))
    bvh = build_bvh(P)
    t1 = time.perf_counter()
    refract = chain[0] == "T"
    counts = np.zeros(first.shape[0], dtype=np.int64)
    stats = np.zeros((first.shape[0], 2), dtype=np.int64)
    out = np.full((first.shape[0], capacity), -1, dtype=np.int64)
    tree = (bvh.node_min, bvh.node_max, bvh.node_child, bvh.node_count, bvh.node_start, bvh.order)
    _all_pairs(refract, light, P, N, eta, int(levels), int(refine), first, *tree, out, counts, stats)
    over = np.flatnonzero(counts > capacity)
    if over.size:  # the few T1 with more second triangles than fit: again with room for all
        big = int(counts[over].max())
        out2 = np.full((over.size, big), -1, dtype=np.int64)
        c2 = np.zeros(over.size, dtype=np.int64)
        s2 = np.zeros((over.size, 2), dtype=np.int64)
        _all_pairs(refract, np.ascontiguousarray(light[over]), P, N, np.ascontiguousarray(eta[over]), int(levels), int(refine),
                   np.ascontiguousarray(first[over]), *tree, out2, c2, s2)
    t2 = time.perf_counter()
    small = counts <= capacity
    kept = np.where(small, counts, 0)
    firsts = [np.repeat(first, kept)]
    seconds = [out[np.arange(capacity)[None, :] < kept[:, None]]]
    if over.size:
        firsts.append(np.repeat(first[over], c2))
        seconds.append(out2[np.arange(out2.shape[1])[None, :] < c2[:, None]])
    pairs = np.stack([np.concatenate(firsts), np.concatenate(seconds)], axis=1)
    pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]
    report = {"first_triangles": int(first.shape[0]), "pairs": int(pairs.shape[0]),
              "pairs_per_first": float(pairs.shape[0] / max(1, first.shape[0])),
              "node_tests": int(stats[:, 0].sum()), "stage_one_tests": int(stats[:, 1].sum()),
              "seconds": {"bvh": t1 - t0, "traverse": t2 - t1}}
    return pairs, report
