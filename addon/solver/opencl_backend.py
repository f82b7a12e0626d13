"""Optional OpenCL back end of the solver (pyopencl).

One bounce: the kernel (``opencl/one_bounce.cl``) is the Numba pipeline of ``one_bounce.py``
written in OpenCL C, step for step, so both return the same paths.  Two bounces: the
pipeline of ``two_bounce.py`` runs in stages over a batch (``two_bounce_staged.py``); the
Bézout determinants (Fan et al. 2024, eq 29) of the sign scan, the Illinois brackets and the
refinement's sub-samples run on the device (``opencl/two_bounce.cl``), the systems'
construction and the path-space polish on Numba.  Double precision is required: a
device without ``cl_khr_fp64`` is refused with a clear message.  Without pyopencl or any
OpenCL device, callers get :class:`OpenCLUnavailable` and fall back to Numba.

On Linux CPUs, Debian's ``pocl-opencl-icd`` provides a device; set
``OCL_ICD_VENDORS=/etc/OpenCL/vendors`` if pyopencl's bundled ICD loader does not find it.
"""

import os

import numpy as np

_KERNEL_FILE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "opencl", "one_bounce.cl")
_KERNEL_FILE_2 = os.path.join(os.path.dirname(os.path.abspath(__file__)), "opencl", "two_bounce.cl")
_MAX_PATHS = 8
WORK_GROUP = 8
_cache = {}
_cache2 = {}


class OpenCLUnavailable(RuntimeError):
    """pyopencl or an OpenCL device is missing: the Numba back end should be used."""


class OpenCLNoDoublePrecision(RuntimeError):
    """The selected device has no cl_khr_fp64; the solver needs float64."""


def parse_device(device):
    """'numba' -> None; 'opencl' -> 0; 'opencl:N' -> N.  Anything else is a ValueError."""
    if device in (None, "numba"):
        return None
    if device == "opencl":
        return 0
    if isinstance(device, str) and device.startswith("opencl:"):
        try:
            index = int(device.split(":", 1)[1])
        except ValueError:
            index = -1
        if index >= 0:
            return index
    raise ValueError(f"device must be 'numba', 'opencl' or 'opencl:N' (N a device index), got {device!r}")


def list_devices():
    """[(index, platform name, device name, has fp64)] for every OpenCL device, in index order."""
    try:
        import pyopencl as cl
    except ImportError as ex:
        raise OpenCLUnavailable(f"pyopencl is not installed ({ex})") from None
    os.environ.setdefault("OCL_ICD_VENDORS", "/etc/OpenCL/vendors")
    try:
        platforms = cl.get_platforms()
    except Exception as ex:  # pyopencl raises LogicError / RuntimeError when no ICD is found
        raise OpenCLUnavailable(f"no OpenCL platform found ({ex})") from None
    found = []
    for platform in platforms:
        for dev in platform.get_devices():
            found.append((len(found), platform.name.strip(), dev.name.strip(), "cl_khr_fp64" in dev.extensions, dev))
    return found


def _context(index):
    if index in _cache:
        return _cache[index]
    devices = list_devices()  # raises OpenCLUnavailable without pyopencl or a platform
    import pyopencl as cl

    if not devices:
        raise OpenCLUnavailable("no OpenCL device found")
    if index >= len(devices):
        raise OpenCLUnavailable(f"OpenCL device {index} does not exist (found {len(devices)}: "
                                + ", ".join(f"{i}: {d}" for i, _, d, _, _ in devices) + ")")
    _, platform, name, fp64, dev = devices[index]
    if not fp64:
        raise OpenCLNoDoublePrecision(f"OpenCL device {index} ({name}) has no double precision (cl_khr_fp64); "
                                      "the caustic solver needs it: choose another device or the Numba back end")
    ctx = cl.Context([dev])
    queue = cl.CommandQueue(ctx)
    with open(_KERNEL_FILE) as f:
        source = f.read()
    program = cl.Program(ctx, source).build(options=["-cl-std=CL1.2"])
    entry = (ctx, queue, cl.Kernel(program, "solve_one_bounce"), f"{platform}: {name}")
    _cache[index] = entry
    return entry


def device_name(index):
    return _context(index)[3]


def solve_one_bounce_opencl(index, refract, x_start, x_end, P, N, eta):
    """Run the OpenCL kernel; returns (out_uv (n, 8, 2), out_count (n,), stats (n, 4)) like the
    Numba batch kernel."""
    import pyopencl as cl

    ctx, queue, kernel, _ = _context(index)
    n = x_start.shape[0]
    out_uv = np.zeros((n, _MAX_PATHS, 2))
    out_count = np.zeros(n, dtype=np.int64)
    stats = np.zeros((n, 4), dtype=np.int64)
    if n == 0:
        return out_uv, out_count, stats
    mf = cl.mem_flags
    bufs = [cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(a, dtype=np.float64))
            for a in (x_start, x_end, P[:, 0], N[:, 0], eta)]
    uv_buf = cl.Buffer(ctx, mf.WRITE_ONLY, out_uv.nbytes)
    count_buf = cl.Buffer(ctx, mf.WRITE_ONLY, out_count.nbytes)
    stats_buf = cl.Buffer(ctx, mf.WRITE_ONLY, stats.nbytes)
    # Small work-groups: every work-item holds ~13 KB of private scratch, and CPU drivers
    # (PoCL) place a whole work-group's private memory on one thread's stack.
    local = WORK_GROUP
    padded = (n + local - 1) // local * local
    kernel(queue, (padded,), (local,), np.int32(1 if refract else 0), *bufs, np.int32(n), uv_buf, count_buf, stats_buf)
    cl.enqueue_copy(queue, out_uv, uv_buf)
    cl.enqueue_copy(queue, out_count, count_buf)
    cl.enqueue_copy(queue, stats, stats_buf)
    queue.finish()
    return out_uv, out_count, stats


# --- two bounces --------------------------------------------------------------------------------


def _two_bounce_program(index):
    """(context, queue, det_batch, illinois_batch, local size) on device index, built once."""
    if index in _cache2:
        return _cache2[index]
    import pyopencl as cl

    ctx, queue, _, _ = _context(index)  # OpenCLUnavailable / OpenCLNoDoublePrecision as for one bounce
    with open(_KERNEL_FILE_2) as f:
        source = f.read()
    program = cl.Program(ctx, source).build(options=["-cl-std=CL1.2"])
    # ~18 KB of private scratch per work-item (the Bézout matrix): CPU drivers (PoCL) put a
    # whole work-group's private memory on one thread's stack, so small groups there; a GPU
    # keeps it in per-thread local memory.
    local = WORK_GROUP if ctx.devices[0].type & cl.device_type.CPU else 64
    entry = (ctx, queue, cl.Kernel(program, "det_batch"), cl.Kernel(program, "illinois_batch"), local)
    _cache2[index] = entry
    return entry


def two_bounce_device_name(index):
    """Like :func:`device_name`, and builds the two-bounce program (so a build error surfaces
    before any work)."""
    _two_bounce_program(index)
    return device_name(index)


class OpenCLDeterminants:
    """Stages B and D of ``two_bounce_staged`` on an OpenCL device: batches of sign and
    log|det| of Bézout matrices at given v1 (eq 29) and of Illinois brackets, over the
    packed systems given to :meth:`load`.  One work-item per job."""

    def __init__(self, index):
        self.ctx, self.queue, self.k_det, self.k_ill, self.local = _two_bounce_program(index)
        self.name = device_name(index)

    def load(self, coef, sysint3, b_offset):
        """coef (S, stride) packed systems, sysint3 (S, 3) int32 (da, db, n)."""
        import pyopencl as cl

        mf = cl.mem_flags
        self.stride = np.int32(coef.shape[1])
        self.b_offset = np.int32(b_offset)
        coef = np.ascontiguousarray(coef, dtype=np.float64)
        sysint3 = np.ascontiguousarray(sysint3, dtype=np.int32)
        self.coef_buf = cl.Buffer(self.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=coef if coef.size else np.zeros(1))
        self.sys_buf = cl.Buffer(self.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR,
                                 hostbuf=sysint3 if sysint3.size else np.zeros(3, dtype=np.int32))

    def _run(self, kernel, n, inputs, outputs):
        import pyopencl as cl

        mf = cl.mem_flags
        bufs = [cl.Buffer(self.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(a)) for a in inputs]
        out_bufs = [cl.Buffer(self.ctx, mf.WRITE_ONLY, o.nbytes) for o in outputs]
        padded = (n + self.local - 1) // self.local * self.local
        kernel(self.queue, (padded,), (self.local,), self.coef_buf, self.sys_buf, self.stride, self.b_offset, *bufs,
               np.int32(n), *out_bufs)
        for o, b in zip(outputs, out_bufs):
            cl.enqueue_copy(self.queue, o, b)
        self.queue.finish()

    def dets(self, job_sys, job_v):
        """(sign (J,) int32, log|det| (J,), determinant evaluations (J,)) of system job_sys
        at v1 = job_v (``_det_checked``: an exact zero is re-checked a hair away)."""
        n = job_sys.shape[0]
        sign = np.zeros(n, dtype=np.int32)
        log = np.zeros(n)
        dets = np.zeros(n, dtype=np.int32)
        if n:
            self._run(self.k_det, n, [job_sys.astype(np.int32), job_v.astype(np.float64)], [sign, log, dets])
        return sign, log, dets

    def illinois(self, job_sys, job_f, job_s):
        """Roots pinned to ROOT_TOL (``_illinois``) in brackets job_f (J, 4) = (lo, hi,
        log|det(lo)|, log|det(hi)|) with signs job_s (J, 2); returns (root, evaluations)."""
        n = job_sys.shape[0]
        root = np.zeros(n)
        dets = np.zeros(n, dtype=np.int32)
        if n:
            self._run(self.k_ill, n, [job_sys.astype(np.int32), job_f.astype(np.float64), job_s.astype(np.int32)],
                      [root, dets])
        return root, dets


def solve_two_bounce_opencl(index, refract1, refract2, x_start, x_end, P, N, eta, pieces, out_uv, out_count, stats):
    """The two-bounce solve with its determinant work on OpenCL device index; fills the
    arrays as ``two_bounce.solve_two_bounce_batch`` does."""
    from .two_bounce_staged import solve_staged

    solve_staged(OpenCLDeterminants(index), refract1, refract2, x_start, x_end, P, N, eta, pieces, out_uv, out_count, stats)
