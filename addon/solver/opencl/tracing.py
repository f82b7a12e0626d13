"""Forward tracing of chain points on an OpenCL device (``trace.cl``): the device form of
``estimators.forward_image.trace_chain_points`` for the forward-flux estimator.

:func:`device_scene` keeps a scene's triangles and BVH on the device for as long as the BVH
lives (one upload per bake, whatever the passes and caster chunks), and a pass's receiver tables
stay there for its chunks (:func:`kept_buffers`); :class:`OpenCLPointTracer` adds the chunk's
emitters and traces batches of
(emitter, u1, v1) points, returning what the Numba kernel returns (second triangle, receiver
triangle, texture coordinates, transport factor), computed with the same arithmetic in the
same order.  Double precision is required (see :mod:`.backend`).
"""

import os
import weakref

import numpy as np

from ..geometry.receiver_planes import no_planes
from .backend import OpenCLUnavailable, _context

_KERNEL_FILE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "trace.cl")
_REFINE_FILE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "refine.cl")
REFINE_TABLE_BITS = 9  # refine.cl's per-emitter shared-point table: 512 slots (filled to half; then points are traced again)
REFINE_TABLE_BYTES = 64 << 20  # the tables of one refine launch on a CPU device (emitters per launch follow)
GPU_REFINE_TABLE_BYTES = 1 << 30  # ... on a GPU (within a 32nd of its memory)
REFINE_RECORDS_PER_EMITTER = (8, 1)  # first room for final / handed-back records per emitter of a launch (then grown to the count)
_kept = {}  # id of a host array -> (weak reference to it, {(device index, what): (sources, buffers)})


def _kernel(index):
    d = _context(index)
    return d, d.kernel(_KERNEL_FILE, "trace_chain_points")


def _refine_kernel(index, stack):
    """refine.cl's refine_emitters on device ``index`` for a depth-first stack of ``stack``
    entries, with refine_kernel.py's record layouts."""
    from ..estimators import refine_kernel as rk

    layout = [(name, getattr(rk, name)) for name in dir(rk) if name[:2] in ("F_", "H_") and name[2:].isupper()]
    defines = [("REFINE_STACK", int(stack)), ("TABLE_BITS", REFINE_TABLE_BITS)] + [(k, int(v)) for k, v in layout]
    return _context(index).kernel(_REFINE_FILE, "refine_emitters", defines)


def kept_buffers(index, what, sources, convert):
    """Device buffers of ``convert(sources)`` (a tuple of host arrays) on device ``index``,
    uploaded on first use and reused while the very same source arrays are passed again (``is``):
    a bake's passes and caster chunks share one upload of the scene, a pass's chunks one of its
    receiver tables.  They are dropped with the first source array."""
    key = sources[0]
    entry = _kept.get(id(key))
    if entry is None or entry[0]() is not key:
        entry = _kept[id(key)] = (weakref.ref(key), {})
        weakref.finalize(key, _kept.pop, id(key), None)
    held = entry[1].get((index, what))
    if held is None or len(held[0]) != len(sources) or any(r() is not a for r, a in zip(held[0], sources)):
        # weak references: holding the sources would keep the key alive, and the buffers forever
        held = entry[1][(index, what)] = (tuple(weakref.ref(a) for a in sources), _context(index).upload(convert(sources)))
    return held[1]


def _float_or_int64(a):
    return np.ascontiguousarray(a, dtype=np.int64 if a.dtype.kind in "iu" else np.float64)


def device_scene(index, tri_p, tri_n, tri_ior, tri_role, bvh_args):
    """The buffers of a scene's triangles (tri_p, tri_n, tri_ior, tri_role) and BVH (``bvh.BVH``
    fields in order) on device ``index`` (:func:`kept_buffers`: keyed by the BVH's arrays)."""
    return kept_buffers(index, "scene", (*bvh_args, tri_p, tri_n, tri_ior, tri_role),
                        lambda a: [_float_or_int64(x) for x in a[len(bvh_args):] + a[:len(bvh_args)]])


class OpenCLPointTracer:
    """One forward-flux pass on OpenCL device ``index``: the scene (:func:`device_scene`), the
    receiver tables (tri_rec, tri_uv), the second-vertex mask, the flat receivers' ``planes``
    (:mod:`~addon.solver.geometry.receiver_planes`; None: none) and the emitters (light points
    x0, first triangles t1_of).  :meth:`trace` takes the arguments and fills the outputs of
    ``trace_chain_points`` for one batch of points."""

    def __init__(self, index, bounces, refract1, refract2, second_ok, tri_rec, tri_uv, tri_p, tri_n, tri_ior, tri_role,
                 bvh_args, x0, t1_of, eps, planes=None):
        self.device, self.kernel = _kernel(index)
        self.index = index
        d = self.device
        self.local = d.work_group(self.kernel)
        self.name = d.label
        self.scene = device_scene(index, tri_p, tri_n, tri_ior, tri_role, bvh_args)
        planes = no_planes() if planes is None else planes
        self.receivers = kept_buffers(index, "receivers", (tri_rec, tri_uv, second_ok, planes),
                                      lambda a: [_float_or_int64(a[0]), _float_or_int64(a[1]),
                                                 np.ascontiguousarray(a[2], dtype=np.uint8),
                                                 np.ascontiguousarray(a[3], dtype=np.float64)])
        self.n_planes = np.int32(planes.shape[0])
        self.n_emitters = int(np.shape(t1_of)[0])
        self._caps = (0, 0)  # the record lists' room on the device (refine_emitters)
        self.refined_here = True  # False once refine_landed fell back to Numba for this tracer
        self.scalars = (np.int32(bounces), np.int32(1 if refract1 else 0), np.int32(1 if refract2 else 0))
        self.eps = np.float64(eps)
        self.emitters = d.upload((np.ascontiguousarray(x0, dtype=np.float64), np.ascontiguousarray(t1_of, dtype=np.int64)))

    def trace(self, e, u, v, out_t2, out_rec, out_uv, out_factor):
        """Trace points (e[i], u[i], v[i]) into the output arrays (as ``trace_chain_points``)."""
        d = self.device
        n = e.shape[0]
        if n == 0:
            return
        inputs = [d.write(f"trace_{k}", np.ascontiguousarray(a, dtype=dt))
                  for k, a, dt in (("e", e, np.int64), ("u", u, np.float64), ("v", v, np.float64))]
        outs = [d.buffer(f"trace_out{k}", a.nbytes) for k, a in enumerate((out_t2, out_rec, out_uv, out_factor))]
        x0, t1_of = self.emitters
        tri_rec, tri_uv, second_ok, planes = self.receivers
        tri_p, tri_n, tri_ior, tri_role = self.scene[:4]
        d.launch(self.kernel, "kernel trace_chain_points", n, self.local, *inputs, x0, t1_of, *self.scalars, second_ok,
                 tri_rec, tri_uv, tri_p, tri_n, tri_ior, tri_role, *self.scene[4:], self.eps, planes, self.n_planes, np.int32(n),
                 *outs)
        for a, b in zip((out_t2, out_rec, out_uv, out_factor), outs):
            d.read(a, b, wait=False)
        d.queue.finish()
        if d.profiler is not None:
            d.profiler.syncs += 1

    def trace_points(self, e, u, v):
        """(second triangle, receiver triangle, UV, transport factor) of points (e[i], u[i], v[i])."""
        m = e.shape[0]
        out = (np.empty(m, dtype=np.int64), np.empty(m, dtype=np.int64), np.empty((m, 2)), np.empty(m))
        self.trace(e, u, v, *out)
        return out

    def refine_emitters(self, n_emitters, base, depth0, dyadic, receiver_of_tri, texel_size, tolerance, relative,
                        coarse_texels, coarse_linear_texels, max_depth, density, parallel, top):
        """``refine_kernel.refine_emitters`` of emitters [0, ``n_emitters``) on the device
        (refine.cl, the same decisions and points), in launches of as many emitters as their
        shared-point tables allow.  Returns (final records (nf, F_WIDTH), handed-back records
        (nh, H_WIDTH), points traced), the records in the Numba kernel's order (emitter, then
        depth first).  OpenCLUnavailable when the device cannot (its program rejected, no room
        for the tables or records): the caller refines on Numba."""
        d = self.device
        try:
            return self._refine_emitters(n_emitters, base, depth0, dyadic, receiver_of_tri, texel_size, tolerance, relative,
                                         coarse_texels, coarse_linear_texels, max_depth, density, parallel, top)
        except d.cl.Error as ex:
            raise OpenCLUnavailable(f"refine_emitters failed on {d.label}: {ex}") from ex

    def _refine_emitters(self, n_emitters, base, depth0, dyadic, receiver_of_tri, texel_size, tolerance, relative,
                         coarse_texels, coarse_linear_texels, max_depth, density, parallel, top):
        from ..estimators.refine_kernel import F_WIDTH, H_WIDTH

        d = self.device
        n_emitters = int(n_emitters)
        base = np.ascontiguousarray(base, dtype=np.float64)
        stack = base.shape[0] + 3 * (max(0, int(max_depth) - int(depth0)) + 1) + 4
        kernel = _refine_kernel(self.index, stack)
        slots = 1 << REFINE_TABLE_BITS
        budget = REFINE_TABLE_BYTES if d.is_cpu else min(GPU_REFINE_TABLE_BYTES, d.dev.global_mem_size // 32)
        batch = max(1, min(n_emitters, budget // (40 * slots)))
        has_top = base.shape[0] == 1 and top[0].shape[0] == self.n_emitters
        top = tuple(np.ascontiguousarray(a, dtype=dt) for a, dt in zip(top, (np.int64, np.float64, np.float64)))
        fixed_in = [d.write(f"refine_{k}", a) for k, a in (
            ("base", base), ("receiver_of_tri", np.ascontiguousarray(receiver_of_tri, dtype=np.int64)),
            ("texel", np.ascontiguousarray(texel_size, dtype=np.float64)), ("top_rec", top[0]), ("top_uv", top[1]),
            ("top_fac", top[2]))]
        tables = [d.buffer("refine_key", 8 * slots * batch), d.buffer("refine_rec", 8 * slots * batch),
                  d.buffer("refine_val", 24 * slots * batch)]
        per_buf = d.buffer("refine_per_emitter", 24 * batch)
        count_buf = d.buffer("refine_counts", 8)
        caps = [max(self._caps[k], REFINE_RECORDS_PER_EMITTER[k] * batch) for k in range(2)]
        x0, t1_of = self.emitters
        tri_rec, tri_uv, second_ok, planes = self.receivers
        tri_p, tri_n, tri_ior, tri_role = self.scene[:4]
        local = d.small_work_group(kernel)  # a chunk's emitters: ~10^3, each a depth-first walk
        finals, hands, traced = [], [], 0
        counts = np.zeros(2, dtype=np.int32)
        for a in range(0, n_emitters, batch):
            m = min(batch, n_emitters - a)
            while True:
                outs = [d.buffer("refine_finals", 8 * (F_WIDTH + 1) * caps[0]), d.buffer("refine_hands", 8 * (H_WIDTH + 1) * caps[1])]
                d.write("refine_counts", np.zeros(2, dtype=np.int32))
                d.launch(kernel, "kernel refine_emitters", m, local, np.int64(a), np.int32(m), fixed_in[0],
                         np.int32(base.shape[0]), np.int64(depth0), np.int64(dyadic), x0, t1_of, *self.scalars, second_ok,
                         tri_rec, tri_uv, tri_p, tri_n, tri_ior, tri_role, *self.scene[4:], self.eps, planes, self.n_planes,
                         fixed_in[1], fixed_in[2], np.float64(tolerance), np.float64(relative), np.float64(coarse_texels),
                         np.float64(coarse_linear_texels), np.int64(max_depth), np.int32(bool(density)),
                         np.int32(bool(parallel)), np.int32(has_top), *fixed_in[3:], *tables, outs[0], np.int32(caps[0]),
                         outs[1], np.int32(caps[1]), count_buf, per_buf)
                d.read(counts, count_buf)
                if counts[0] <= caps[0] and counts[1] <= caps[1]:
                    break
                caps = [max(caps[0], int(1.25 * counts[0]) + 1), max(caps[1], int(1.25 * counts[1]) + 1)]
            self._caps = caps
            per = np.empty((m, 3), dtype=np.int64)
            d.read(per, per_buf, wait=False)
            f = np.empty((int(counts[0]), F_WIDTH + 1))
            h = np.empty((int(counts[1]), H_WIDTH + 1))
            d.read(f, outs[0], wait=False)
            d.read(h, outs[1], wait=False)
            d.queue.finish()
            if d.profiler is not None:
                d.profiler.syncs += 1
            finals.append(_in_order(f, per[:, 0], a))
            hands.append(_in_order(h, per[:, 1], a))
            traced += int(per[:, 2].sum())
        f = np.concatenate(finals) if finals else np.zeros((0, F_WIDTH))
        h = np.concatenate(hands) if hands else np.zeros((0, H_WIDTH))
        return f, h, traced


def _in_order(rows, count, first):
    """Records (k, width + 1) of emitters first.. (column 0 the emitter, the last column its
    ordinal in that emitter's depth-first order; ``count`` per emitter) in emitter, then
    depth-first order, without the ordinal."""
    start = np.cumsum(count) - count
    out = np.empty((rows.shape[0], rows.shape[1] - 1))
    if rows.shape[0]:
        out[start[rows[:, 0].astype(np.int64) - first] + rows[:, -1].astype(np.int64)] = rows[:, :-1]
    return out
