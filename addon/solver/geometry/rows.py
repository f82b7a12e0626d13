"""Equal rows of an array, found in one pass (open addressing on a hash of each row): the
vertex ids of a triangle soup welded by position (:meth:`addon.bake.scene.Scene.closed_objects`), the
mesh points that emitters share (:func:`addon.solver.estimators.refine_kernel.mesh_points`)."""

import numpy as np

from ..runtime.jit import kernel


@kernel(inline="always")
def _mix64(x):
    """splitmix64's finaliser: every input bit reaches every output bit (small integers, such
    as quantised positions on a grid, spread over the whole table)."""
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


@kernel
def group_rows(bits):
    """Ids of equal rows of ``bits`` (m, k) uint64 (bit patterns: a float64 or int64 array viewed as uint64): (ids (m,),
    numbered by first occurrence, first (n,) the row where each id first occurs).  Open
    addressing on a hash of the row, rows compared whole: exact."""
    m, k = bits.shape
    size = 1
    while size < 2 * m + 2:
        size *= 2
    mask = size - 1
    table = np.full(size, -1, dtype=np.int64)  # the first row of the id in each slot
    ids = np.empty(m, dtype=np.int64)
    first = np.empty(m, dtype=np.int64)
    n = 0
    for i in range(m):
        h = np.uint64(1469598103934665603)
        for j in range(k):
            h = _mix64(h ^ bits[i, j])
        slot = np.int64(h >> np.uint64(16)) & mask
        while True:
            r = table[slot]
            if r < 0:
                table[slot] = i
                ids[i] = n
                first[n] = i
                n += 1
                break
            same = True
            for j in range(k):
                if bits[r, j] != bits[i, j]:
                    same = False
                    break
            if same:
                ids[i] = ids[r]
                break
            slot = (slot + 1) & mask
    return ids, first[:n]
