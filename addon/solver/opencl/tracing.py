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
from .backend import _context

_KERNEL_FILE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "trace.cl")
_programs = {}  # device index -> the built trace kernel
_kept = {}  # id of a host array -> (weak reference to it, {(device index, what): (sources, buffers)})


def _kernel(index):
    d = _context(index)
    if index not in _programs:
        _programs[index] = d.cl.Kernel(d._build(_KERNEL_FILE), "trace_chain_points")
    return d, _programs[index]


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
