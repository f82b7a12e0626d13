"""The canonical order of a solve's paths: by tuple, then by the path's coordinates (u, v, ...)
lexicographically, each tuple's paths in a stable order.

The order in which candidates happen to be found (or a device writes them in) is not part of
a result and must not differ between back ends.  Both kernels are O(n + m) for n tuples and m
paths: a tuple holds a handful of paths at most (one-bounce capacity 8), so each tuple's run
is insertion-sorted in place.
"""

import numpy as np

from ..runtime.jit import kernel


@kernel
def _row_less(uv, a, b):
    for k in range(uv.shape[1]):
        if uv[a, k] < uv[b, k]:
            return True
        if uv[a, k] > uv[b, k]:
            return False
    return False


@kernel
def sort_rows(uv, lo, hi, row):
    """Stable insertion sort of rows lo..hi-1 of uv (row: scratch of one row)."""
    w = uv.shape[1]
    for i in range(lo + 1, hi):
        j = i
        while j > lo and _row_less(uv, j, j - 1):
            for k in range(w):
                row[k] = uv[j, k]
                uv[j, k] = uv[j - 1, k]
                uv[j - 1, k] = row[k]
            j -= 1


@kernel
def gather_sorted(out_uv, out_count, tuple_index, uv):
    """Per-tuple slots out_uv (n, cap, w) with counts out_count (n,) (at most cap stored) ->
    tuple_index (m,), uv (m, w) in canonical order; m = sum of min(count, cap)."""
    cap = out_uv.shape[1]
    w = out_uv.shape[2]
    row = np.empty(w)
    r = 0
    for t in range(out_uv.shape[0]):
        c = min(out_count[t], cap)
        for s in range(c):
            tuple_index[r + s] = t
            for k in range(w):
                uv[r + s, k] = out_uv[t, s, k]
        if c > 1:
            sort_rows(uv, r, r + c, row)
        r += c


@kernel
def order_by_tuple(tuple_index, uv, n, out_index, out_uv):
    """Paths (tuple_index (m,), uv (m, w)) in any order, tuples in [0, n) -> out_index, out_uv
    in canonical order (a counting sort by tuple keeps each tuple's paths in their order,
    then each tuple's run is sorted)."""
    m = tuple_index.shape[0]
    w = uv.shape[1]
    start = np.zeros(n + 1, dtype=np.int64)
    for i in range(m):
        start[tuple_index[i] + 1] += 1
    for t in range(n):
        start[t + 1] += start[t]
    fill = start[:n].copy()
    for i in range(m):
        t = tuple_index[i]
        d = fill[t]
        fill[t] = d + 1
        out_index[d] = t
        for k in range(w):
            out_uv[d, k] = uv[i, k]
    row = np.empty(w)
    for t in range(n):
        if start[t + 1] - start[t] > 1:
            sort_rows(out_uv, start[t], start[t + 1], row)


@kernel
def gather_chunks(chunk_index, chunk_uv, chunk_paths, stride, tuple_index, uv):
    """Paths written densely per chunk (chunk c's chunk_paths[c] rows from row c * stride of
    chunk_index (rows,) and chunk_uv (rows, w), each already in canonical order, the chunks in
    tuple order) -> tuple_index (m,), uv (m, w) one after the other."""
    w = chunk_uv.shape[1]
    r = 0
    for c in range(chunk_paths.shape[0]):
        start = c * stride
        for s in range(chunk_paths[c]):
            tuple_index[r] = chunk_index[start + s]
            for k in range(w):
                uv[r, k] = chunk_uv[start + s, k]
            r += 1


@kernel
def stat_totals(stats, paths_column, capacity, totals):
    """totals[k] = the sum of column k of the per-tuple statistics stats (n, k); returns how many
    tuples found more paths (column ``paths_column``) than the ``capacity`` they could store.
    One pass over the rows (numpy's axis-0 sum of a narrow int64 table strides far slower)."""
    for k in range(totals.shape[0]):
        totals[k] = 0
    over = 0
    for t in range(stats.shape[0]):
        for k in range(totals.shape[0]):
            totals[k] += stats[t, k]
        if stats[t, paths_column] > capacity:
            over += 1
    return over
