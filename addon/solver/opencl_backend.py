"""Optional OpenCL back end of the one-bounce solver (pyopencl).

The kernel (``opencl/one_bounce.cl``) is the Numba pipeline of ``one_bounce.py`` written in
OpenCL C, step for step, so both return the same paths.  Double precision is required: a
device without ``cl_khr_fp64`` is refused with a clear message.  Without pyopencl or any
OpenCL device, callers get :class:`OpenCLUnavailable` and fall back to Numba.

On Linux CPUs, Debian's ``pocl-opencl-icd`` provides a device; set
``OCL_ICD_VENDORS=/etc/OpenCL/vendors`` if pyopencl's bundled ICD loader does not find it.
"""

import os

import numpy as np

_KERNEL_FILE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "opencl", "one_bounce.cl")
_MAX_PATHS = 8
WORK_GROUP = 8
_cache = {}


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
