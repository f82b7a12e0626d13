"""Forward tracing of chain points on an OpenCL device (``trace.cl``): the device form of
``estimators.forward_image.trace_chain_points`` for the forward-flux estimator.

:func:`device_scene` keeps a scene's triangles and BVH on the device for as long as the BVH
lives (one upload per bake, whatever the passes and caster chunks); :class:`OpenCLPointTracer`
adds one pass's tables (receivers, second-vertex mask, emitters) and traces batches of
(emitter, u1, v1) points, returning what the Numba kernel returns (second triangle, receiver
triangle, texture coordinates, transport factor), computed with the same arithmetic in the
same order.  Double precision is required (see :mod:`.backend`).
"""

import os
import weakref

import numpy as np

from .backend import _context

_KERNEL_FILE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "trace.cl")
_programs = {}  # device index -> the built trace kernel
_scenes = {}  # id of a BVH's node_min array -> (weak reference to it, {device index: DeviceScene})


def _kernel(index):
    d = _context(index)
    if index not in _programs:
        _programs[index] = d.cl.Kernel(d._build(_KERNEL_FILE), "trace_chain_points")
    return d, _programs[index]


class DeviceScene:
    """Triangles (tri_p, tri_n, tri_ior, tri_role) and the BVH (``bvh.BVH`` fields in order) of
    one scene on one device."""

    def __init__(self, d, tri_p, tri_n, tri_ior, tri_role, bvh_args):
        self.tri_p = tri_p  # the host array it was made from (checked on reuse)
        arrays = [np.ascontiguousarray(tri_p, dtype=np.float64), np.ascontiguousarray(tri_n, dtype=np.float64),
                  np.ascontiguousarray(tri_ior, dtype=np.float64), np.ascontiguousarray(tri_role, dtype=np.int64)]
        arrays += [np.ascontiguousarray(a, dtype=np.int64 if a.dtype.kind in "iu" else np.float64) for a in bvh_args]
        self.buffers = d.upload(arrays)


def device_scene(index, tri_p, tri_n, tri_ior, tri_role, bvh_args):
    """The :class:`DeviceScene` of these arrays on device ``index``: uploaded on first use and
    kept while the BVH's arrays live (a bake's passes and chunks share one upload)."""
    d = _context(index)
    key = bvh_args[0]
    entry = _scenes.get(id(key))
    if entry is None or entry[0]() is not key:
        entry = _scenes[id(key)] = (weakref.ref(key), {})
        weakref.finalize(key, _scenes.pop, id(key), None)  # the device buffers go with the BVH
    held = entry[1]
    scene = held.get(index)
    if scene is None or scene.tri_p is not tri_p:
        scene = held[index] = DeviceScene(d, tri_p, tri_n, tri_ior, tri_role, bvh_args)
    return scene


class OpenCLPointTracer:
    """One forward-flux pass on OpenCL device ``index``: the scene (:func:`device_scene`), the
    receiver tables (tri_rec, tri_uv), the second-vertex mask and the emitters (light points
    x0, first triangles t1_of).  :meth:`trace` takes the arguments and fills the outputs of
    ``trace_chain_points`` for one batch of points."""

    def __init__(self, index, bounces, refract1, refract2, second_ok, tri_rec, tri_uv, tri_p, tri_n, tri_ior, tri_role,
                 bvh_args, x0, t1_of, eps):
        self.device, self.kernel = _kernel(index)
        d = self.device
        self.local = d.work_group(self.kernel)
        self.name = d.label
        self.scene = device_scene(index, tri_p, tri_n, tri_ior, tri_role, bvh_args)
        self.scalars = (np.int32(bounces), np.int32(1 if refract1 else 0), np.int32(1 if refract2 else 0))
        self.eps = np.float64(eps)
        self.tables = d.upload((np.ascontiguousarray(x0, dtype=np.float64), np.ascontiguousarray(t1_of, dtype=np.int64),
                                np.ascontiguousarray(second_ok, dtype=np.uint8), np.ascontiguousarray(tri_rec, dtype=np.int64),
                                np.ascontiguousarray(tri_uv, dtype=np.float64)))

    def trace(self, e, u, v, out_t2, out_rec, out_uv, out_factor):
        """Trace points (e[i], u[i], v[i]) into the output arrays (as ``trace_chain_points``)."""
        d = self.device
        n = e.shape[0]
        if n == 0:
            return
        inputs = [d.write(f"trace_{k}", np.ascontiguousarray(a, dtype=dt))
                  for k, a, dt in (("e", e, np.int64), ("u", u, np.float64), ("v", v, np.float64))]
        outs = [d.buffer(f"trace_out{k}", a.nbytes) for k, a in enumerate((out_t2, out_rec, out_uv, out_factor))]
        x0, t1_of, second_ok, tri_rec, tri_uv = self.tables
        tri_p, tri_n, tri_ior, tri_role = self.scene.buffers[:4]
        d.launch(self.kernel, "kernel trace_chain_points", n, self.local, *inputs, x0, t1_of, *self.scalars, second_ok,
                 tri_rec, tri_uv, tri_p, tri_n, tri_ior, tri_role, *self.scene.buffers[4:], self.eps, np.int32(n), *outs)
        for a, b in zip((out_t2, out_rec, out_uv, out_factor), outs):
            d.read(a, b, wait=False)
        d.queue.finish()
        if d.profiler is not None:
            d.profiler.syncs += 1
