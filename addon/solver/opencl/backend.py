"""Optional OpenCL back end of the solver (pyopencl).

One bounce: the kernel (``opencl/one_bounce.cl``) is the Numba pipeline of ``one_bounce.py``
written in OpenCL C, step for step, so both return the same paths.  Two bounces: the
pipeline of ``spoly/two_bounce`` runs in stages over a batch (``two_bounce/staged.py``): the
systems' construction and (u1, v1) pre-pass (``stage_a.cl`` with ``frame.cl``, ``system.cl``,
``prepass.cl``; on CPU devices Numba beside it), the resultant scan over the Bézout
determinants (Fan et al. 2024, eq 29: samples, degeneracy, Illinois pins, root lists), the
candidates' back-substitution and path-space polish, the refinement and the candidates at the
refined roots (``two_bounce.cl`` with ``roots.cl`` and ``two_vertex.cl``) on the device.

Host side: each device keeps its context, queue, programs and device buffers (grow-only, by
role) between calls; inputs are written without waiting.  One-bounce tuples come as rows
(:func:`solve_one_bounce_opencl`) or as int32 (emitter, point) pairs over tables uploaded
once (:func:`one_bounce_table`, :func:`solve_one_bounce_pairs`).  Its output is compacted on
the device: on CPUs one kernel appends path records by an atomic counter (the host sorts
them); on GPUs a filter stage, prefix sums (``scan.cl``), a solve over the surviving tuples
only (full warps) and a gather write them in canonical order.  A two-bounce batch waits
twice: for its systems' counts, for its paths.  Work-groups are small on CPUs and several warps on GPUs (:meth:`_Device.work_group`).  A :class:`Profiler` attached with :func:`set_profiling`
records the device time of every command and the host steps (``bench/opencl_profile.py``).

Double precision is required: a
device without ``cl_khr_fp64`` is refused with a clear message.  Without pyopencl or any
OpenCL device, callers get :class:`OpenCLUnavailable` and fall back to Numba.

On Linux CPUs, Debian's ``pocl-opencl-icd`` provides a device; set
``OCL_ICD_VENDORS=/etc/OpenCL/vendors`` if pyopencl's bundled ICD loader does not find it.
"""

import os
import time

import numpy as np

_KERNEL_FILE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "one_bounce.cl")
_KERNEL_FILE_2 = os.path.join(os.path.dirname(os.path.abspath(__file__)), "two_bounce.cl")
_SCAN_FILE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "scan.cl")
# Work-group size of the prefix-sum kernels (scan.cl), at most the kernels' limit.
SCAN_WORK_GROUP = 256
# Path slots per tuple in the split (GPU) pipeline, as SLOTS in one_bounce.cl.
SLOTS = 8
# Work-group size on CPU devices: every work-item holds ~13 KB (one bounce) or ~18 KB (two
# bounces) of private scratch, and CPU drivers (PoCL) place a whole work-group's private
# memory on one thread's stack, so groups stay small there.
CPU_WORK_GROUP = 8
# Work-group size asked for on GPUs (clamped to what the kernel allows): whole warps /
# wavefronts, a few per group (the fastest of 32-256 on an H200: bench/results/opencl_shapes_gpu.md).
GPU_WORK_GROUP = 256
SMALL_WORK_GROUP = 32  # ... for launches of few, long work-items (the forward-flux refine and splat: _Device.small_work_group)
# Tuples per one-bounce launch: bounds the device buffers (~200 bytes in, ~40 bytes of
# path records and, in the split pipeline, ~150 bytes of flags, slots and offsets per tuple)
# while keeping launches large.
ONE_BOUNCE_BATCH = 1 << 22
# Path records held on the device per one-bounce launch: this many per tuple (planted
# workloads have ~1.1), at least PATH_RECORDS_MIN; more are made room for by running again.
PATH_RECORDS_PER_TUPLE = 2
PATH_RECORDS_MIN = 1024
# Statistic slots of the one-bounce kernel (acc[1:], 5 counters each): spreads its atomics.
N_SLOTS = 1024
_cache = {}  # device index -> _Device
_cache2 = {}  # device index -> its two-bounce kernels ({name: kernel}, local size)
TWO_BOUNCE_KERNELS = ("det_batch", "stage_a", "gather_systems", "scan_samples", "scan_degenerate", "scan_pins",
                      "scan_roots", "refine_flags", "refine_samples", "refine_assemble", "candidates_scan",
                      "candidates_refined")
# Stage A's bivariate scratch on the device (N_SLOTS x 48 x 48 doubles, ~1 MB a work-item): a
# batch's tuples run in launches of as many work-items as this holds (on GPUs GPU_STAGE_A_SCRATCH_BYTES,
# within an eighth of the device's memory: thousands of work-items a launch).
STAGE_A_SCRATCH_BYTES = 256 << 20
GPU_STAGE_A_SCRATCH_BYTES = 4 << 30
# A two-bounce batch's system store on GPUs (staged.BATCH_BYTES on CPUs), within a 32nd of the
# device's memory: batches of thousands of tuples keep a GPU busy between the host's two waits.
GPU_BATCH_BYTES = 1 << 30
# The refinement's per-piece sub-samples and pins held on the device at once (two_bounce.cl
# refine_samples): the systems of a batch are refined in cuts whose storage fits this (GPUs:
# GPU_REFINE_SUB_BYTES).
REFINE_SUB_BYTES = 64 << 20
GPU_REFINE_SUB_BYTES = 1 << 30


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


class Profiler:
    """Per-stage times of the OpenCL calls while attached with :func:`set_profiling`:
    device time of each enqueued command (OpenCL profiling events, by stage label) and
    host seconds of the host-side steps, plus launch and synchronisation counts."""

    def __init__(self):
        self.events = []
        self.host = {}
        self.launches = 0
        self.syncs = 0

    def event(self, stage, evt):
        self.events.append((stage, evt))

    def host_time(self, stage, seconds):
        self.host[stage] = self.host.get(stage, 0.0) + seconds

    def device_seconds(self):
        """{stage: summed device seconds of its commands}."""
        out = {}
        for stage, evt in self.events:
            evt.wait()
            out[stage] = out.get(stage, 0.0) + (evt.profile.end - evt.profile.start) * 1e-9
        return out


class _Device:
    """One OpenCL device: context, queue, programs, work-group sizes and the device buffers
    kept between calls (grow-only, by role)."""

    def __init__(self, cl, dev, label):
        self.cl = cl
        self.dev = dev
        self.label = label
        self.ctx = cl.Context([dev])
        self.queue = cl.CommandQueue(self.ctx)
        self.profiler = None
        self.is_cpu = bool(dev.type & cl.device_type.CPU)
        program = self._build(_KERNEL_FILE)
        self.kernel_one = cl.Kernel(program, "solve_one_bounce")
        self.kernel_scatter = cl.Kernel(program, "scatter_survivors")
        self.kernel_gather = cl.Kernel(program, "gather_paths")
        self.local_one = self.work_group(self.kernel_one)
        scan = self._build(_SCAN_FILE)
        self.kernels_scan = tuple(cl.Kernel(scan, name) for name in ("scan_blocks", "scan_sums", "scan_add"))
        self.local_scan = min(SCAN_WORK_GROUP, *(self.kernel_info(k)[0] for k in self.kernels_scan))
        self.kernels_two = None
        self.programs = {}  # (file, defines) -> program, or the OpenCLUnavailable of its build (program())
        self.kernels = {}  # (file, kernel name, defines) -> kernel (kernel())
        self.buffers = {}
        self.path_capacity = 0

    def _build(self, path, defines=()):
        """The program of the file path (:meth:`build_source`)."""
        with open(path) as f:
            return self.build_source(f.read(), os.path.dirname(path), defines)

    def program(self, path, defines=()):
        """The program of file ``path`` with ``defines`` (:meth:`_build`), built once; a program
        the driver rejects raises OpenCLUnavailable with its log, now and on every later call
        (the callers fall back to Numba)."""
        key = (path, tuple(defines))
        got = self.programs.get(key)
        if got is None:
            try:
                got = self._build(path, defines)
            except self.cl.Error as ex:
                got = OpenCLUnavailable(f"{os.path.basename(path)} does not build on {self.label}: {str(ex).strip()[:2000]}")
            self.programs[key] = got
        if isinstance(got, OpenCLUnavailable):
            raise got
        return got

    def kernel(self, path, name, defines=()):
        """Kernel ``name`` of :meth:`program` (path, defines), made once."""
        key = (path, name, tuple(defines))
        if key not in self.kernels:
            self.kernels[key] = self.cl.Kernel(self.program(path, defines), name)
        return self.kernels[key]

    def build_source(self, source, folder, defines=()):
        """The program of source, its shared parts and generated tables pasted in
        (:func:`_assemble`, sources from folder), built with ``-D name=value`` for each
        (name, value) of defines."""
        options = ["-cl-std=CL1.2"] + [f"-D{name}={value}" for name, value in defines]
        return self.cl.Program(self.ctx, _assemble(source, folder)).build(options=options)

    def work_group(self, kernel):
        """The work-group size for kernel here: CPU_WORK_GROUP on CPUs; on other devices
        GPU_WORK_GROUP (or CAUSTIC_OPENCL_WORK_GROUP) within the kernel's limit, rounded down
        to the preferred multiple (the warp width)."""
        cl = self.cl
        if self.is_cpu:
            return CPU_WORK_GROUP
        wanted = int(os.environ.get("CAUSTIC_OPENCL_WORK_GROUP", GPU_WORK_GROUP))
        limit = kernel.get_work_group_info(cl.kernel_work_group_info.WORK_GROUP_SIZE, self.dev)
        multiple = kernel.get_work_group_info(cl.kernel_work_group_info.PREFERRED_WORK_GROUP_SIZE_MULTIPLE, self.dev)
        size = min(wanted, limit)
        return max(multiple * (size // multiple), 1) if size >= multiple else max(size, 1)

    def small_work_group(self, kernel):
        """The work-group size for a launch of few, long work-items (a chunk's emitters, a
        texture's rows): :meth:`work_group` on CPUs; on other devices at most SMALL_WORK_GROUP, so
        that its groups spread over many compute units instead of filling a few."""
        size = self.work_group(kernel)
        return size if self.is_cpu else min(size, SMALL_WORK_GROUP)

    def kernel_info(self, kernel):
        """(kernel's maximum work-group size, private memory bytes per work-item or None)."""
        cl = self.cl
        limit = kernel.get_work_group_info(cl.kernel_work_group_info.WORK_GROUP_SIZE, self.dev)
        try:
            private = kernel.get_work_group_info(cl.kernel_work_group_info.PRIVATE_MEM_SIZE, self.dev)
        except Exception:  # not every driver answers
            private = None
        return int(limit), private

    def set_profiling(self, profiler):
        """Attach a Profiler (a new queue with profiling events) or detach it (None)."""
        props = self.cl.command_queue_properties.PROFILING_ENABLE if profiler is not None else 0
        self.queue.finish()
        self.queue = self.cl.CommandQueue(self.ctx, properties=props)
        self.profiler = profiler

    def buffer(self, role, nbytes):
        """A device buffer of at least nbytes for role, reused while large enough; a
        larger request replaces it by one 1.5 times as large (fewer reallocations when
        sizes creep up)."""
        held = self.buffers.get(role)
        if held is None or held.size < nbytes:
            size = max(nbytes, int(1.5 * held.size) if held is not None else 0, 64)
            held = self.cl.Buffer(self.ctx, self.cl.mem_flags.READ_WRITE, size)
            self.buffers[role] = held
        return held

    def upload(self, arrays):
        """Read-only device buffers of their own holding arrays (kept by the caller, not by
        role); returns once the copies are done, so the host arrays may go."""
        cl = self.cl
        buffers = []
        for a in arrays:
            buf = cl.Buffer(self.ctx, cl.mem_flags.READ_ONLY, max(a.nbytes, 64))
            if a.nbytes:
                evt = cl.enqueue_copy(self.queue, buf, a, is_blocking=False)
                if self.profiler is not None:
                    self.profiler.event("host->device", evt)
            buffers.append(buf)
        self.queue.finish()
        return buffers

    def write(self, role, array, stage="host->device"):
        """Enqueue (without waiting) array into role's buffer; returns the buffer."""
        buf = self.buffer(role, array.nbytes)
        if array.nbytes:
            evt = self.cl.enqueue_copy(self.queue, buf, array, is_blocking=False)
            if self.profiler is not None:
                self.profiler.event(stage, evt)
        return buf

    def read_only(self, role, array, stage="host->device"):
        """A device buffer holding ``array`` for the commands enqueued next: on a CPU device the
        array itself (USE_HOST_PTR: no copy, the device reads host memory; the caller keeps the
        array alive and unchanged until those commands are done), elsewhere role's buffer
        written (:meth:`write`)."""
        if self.is_cpu and array.nbytes and array.flags.c_contiguous:
            flags = self.cl.mem_flags.READ_ONLY | self.cl.mem_flags.USE_HOST_PTR
            return self.cl.Buffer(self.ctx, flags, hostbuf=array)
        return self.write(role, array, stage)

    def read(self, array, buf, stage="device->host", wait=True):
        if array.nbytes:
            evt = self.cl.enqueue_copy(self.queue, array, buf, is_blocking=wait)
            if self.profiler is not None:
                self.profiler.event(stage, evt)
                if wait:
                    self.profiler.syncs += 1

    def launch(self, kernel, stage, n, local, *args):
        if n <= 0:
            return  # nothing to run (an empty range is no valid NDRange)
        padded = (n + local - 1) // local * local
        evt = kernel(self.queue, (padded,), (local,), *args)
        if self.profiler is not None:
            self.profiler.event(stage, evt)
            self.profiler.launches += 1

    def host(self, stage, seconds):
        if self.profiler is not None:
            self.profiler.host_time(stage, seconds)


def _assemble(source, folder, done=None):
    """source with each line ``// @INCLUDE name@ ...`` replaced by the file name of folder (the
    OpenCL sources shared between programs: roots.cl, two_vertex.cl, numba_math.cl, ...),
    assembled in turn (an included file may include others), each file once per program, and
    each line ``// @NODE_TABLES@ ...`` / ``// @TWO_BOUNCE_TABLES@ ...`` by the solver's tables
    (:func:`_node_tables`, :func:`two_bounce_tables`)."""
    generated = {"// @NODE_TABLES@": _node_tables, "// @TWO_BOUNCE_TABLES@": two_bounce_tables}
    out = []
    done = set() if done is None else done
    for line in source.split("\n"):
        marker = next((m for m in generated if line.startswith(m)), None)
        if marker is not None:
            out.append(generated[marker]())
        elif line.startswith("// @INCLUDE "):
            name = line[len("// @INCLUDE "):].split("@", 1)[0]
            if name not in done:
                done.add(name)
                with open(os.path.join(folder, name)) as f:
                    out.append(_assemble(f.read(), folder, done))
        else:
            out.append(line)
    return "\n".join(out)


def _node_tables():
    """The one-bounce solver's Chebyshev nodes and node-values-to-Bernstein matrices
    (``spoly.one_bounce``: the full resultants' and the deflated ones') as OpenCL constants, written as hexadecimal floats so that the
    device computes with the very same doubles."""
    from ..spoly import one_bounce

    def table(name):
        flat = np.ascontiguousarray(getattr(one_bounce, name), dtype=np.float64).ravel()
        return f"__constant double {name}[{flat.size}] = {{" + ", ".join(float(x).hex() for x in flat) + "};"

    names = []
    for chain in ("R", "T"):
        for suffix in ("", "_DEFLATED", "_DEFLATED_WIDE"):
            names += [f"NODES_{chain}{suffix}", f"TO_BERNSTEIN_{chain}{suffix}"]
    return "\n".join(table(name) for name in names)


def _context(index):
    """The _Device for OpenCL device index, created (program built) on first use."""
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
    entry = _Device(cl, dev, f"{platform}: {name}")
    _cache[index] = entry
    return entry


def device_name(index):
    return _context(index).label


def device_is_gpu(device):
    """Whether ``device`` ("numba", "opencl" or "opencl:N") names an OpenCL device that is not a
    CPU (False also when there is no such device: the caller runs on Numba)."""
    if device in (None, "numba"):
        return False
    try:
        return not _context(parse_device(device)).is_cpu
    except OpenCLUnavailable:
        return False


def set_profiling(index, profiler):
    """Record per-stage times of device index's calls into profiler (a :class:`Profiler`;
    None stops recording).  The queue is recreated with profiling events enabled."""
    _context(index).set_profiling(profiler)


def device_info(index):
    """What the profile reports about device index: its name, type, compute units, and per
    kernel the work-group size used, the kernel's maximum and its private memory per
    work-item (None where the driver does not say)."""
    d = _context(index)
    info = dict(name=d.label, type="CPU" if d.is_cpu else "GPU/accelerator", compute_units=d.dev.max_compute_units,
                kernels={})
    limit, private = d.kernel_info(d.kernel_one)
    info["kernels"]["solve_one_bounce"] = dict(local=d.local_one, max_local=limit, private_bytes=private)
    if d.kernels_two is not None:
        kernels, local = d.kernels_two
        for name, k in kernels.items():
            limit, private = d.kernel_info(k)
            info["kernels"][name] = dict(local=local, max_local=limit, private_bytes=private)
    return info


STAGE_WHOLE, STAGE_FILTER, STAGE_SOLVE = 0, 1, 2  # as in one_bounce.cl


def _two_stage(d):
    """Whether one-bounce launches run as a filter stage then a solve stage over the survivors
    (GPUs: most tuples of a bake fail the cheap set-up, and a warp that solves one tuple waits
    for it) or as one stage (CPUs).  CAUSTIC_OPENCL_STAGES=1 or 2 overrides."""
    forced = os.environ.get("CAUSTIC_OPENCL_STAGES")
    if forced in ("1", "2"):
        return forced == "2"
    return not d.is_cpu


class OneBounceTable:
    """A one-bounce solve's inputs kept on an OpenCL device: emitter rows (x_start (E, 3), the
    triangle's P, N (E, 1, 3, 3), eta (E,)) and receiver points (x_end (S, 3)).  Tuples are then
    (emitter, point) index pairs (:func:`solve_one_bounce_pairs`): 8 bytes per tuple cross to the
    device instead of ~190.  Built by :func:`one_bounce_table`; its buffers live as long as it."""

    def __init__(self, d, x_start, P, N, eta, x_end):
        t0 = time.perf_counter()
        arrays = [np.ascontiguousarray(a, dtype=np.float64) for a in (x_start, x_end, P, N, eta)]
        self.n_emitters, self.n_points = arrays[0].shape[0], arrays[1].shape[0]
        d.host("pack", time.perf_counter() - t0)
        self.buffers = d.upload(arrays)
        self.device = d


def one_bounce_table(index, x_start, P, N, eta, x_end):
    """Upload a one-bounce solve's emitters (x_start, P, N, eta rows) and receiver points
    (x_end rows) to OpenCL device index once; returns the :class:`OneBounceTable` that
    :func:`solve_one_bounce_pairs` solves index pairs over."""
    return OneBounceTable(_context(index), x_start, P, N, eta, x_end)


def solve_one_bounce_opencl(index, refract, x_start, x_end, P, N, eta):
    """Run the one-bounce kernel over the tuples in launches of up to ONE_BOUNCE_BATCH.
    Returns (tuple_index (m,) int64, uv (m, 2), totals (5,) int64 = roots, candidates, paths,
    skipped, overflow = tuples with more than 8 paths, ordered): the stored paths of every
    tuple, in canonical order when ``ordered`` (the split pipeline on GPUs), else in no
    particular order (the caller sorts them), and the summed statistics."""
    d = _context(index)
    t0 = time.perf_counter()
    n = x_start.shape[0]
    # P and N of (n, 1, 3, 3) are read in place when contiguous (the kernel reads 9 doubles a tuple)
    arrays = [np.ascontiguousarray(a, dtype=np.float64) for a in (x_start, x_end, P, N, eta)]
    d.host("pack", time.perf_counter() - t0)

    def launch(b0, b1):
        # the tuples stay alive here until _in_batches has read every batch's paths back
        bufs = [d.read_only(role, a[b0:b1]) for role, a in zip(("x_start", "x_end", "P", "N", "eta"), arrays)]
        return _one_bounce_launch(d, refract, b1 - b0, b0, bufs, None)

    tuple_index, uv, totals, ordered = _in_batches(d, n, launch)
    return tuple_index, uv, totals[:5], ordered


def solve_one_bounce_pairs(index, refract, table, e, s):
    """The one-bounce solve of the tuples (table's emitter e[i], table's point s[i]) on OpenCL
    device index (the table from :func:`one_bounce_table` on the same device).  Returns as
    :func:`solve_one_bounce_opencl`, tuple_index counting pairs.  The kernel checks the pairs
    against the table (IndexError for any outside it); int32 pairs are sent as they are."""
    d = _context(index)
    if table.device is not d:
        raise ValueError("the table was uploaded to another OpenCL device")
    t0 = time.perf_counter()
    e = np.ascontiguousarray(e, dtype=np.int32)
    s = np.ascontiguousarray(s, dtype=np.int32)
    n = e.shape[0]
    if s.shape != (n,):
        raise ValueError(f"emitter and point index arrays differ in shape: {e.shape} and {s.shape}")
    d.host("validate", time.perf_counter() - t0)

    def launch(b0, b1):
        pairs = (d.read_only("tuple_e", e[b0:b1]), d.read_only("tuple_s", s[b0:b1]), np.int32(table.n_emitters),
                 np.int32(table.n_points))
        return _one_bounce_launch(d, refract, b1 - b0, b0, table.buffers, pairs)

    result = _in_batches(d, n, launch)
    if result[2][5]:
        raise IndexError(f"{result[2][5]:,} pair indices outside the table ({table.n_emitters} emitters, {table.n_points} points)")
    return result[0], result[1], result[2][:5], result[3]


def _in_batches(d, n, launch):
    """launch(b0, b1) over [0, n) in batches of ONE_BOUNCE_BATCH; the batches' paths joined,
    their statistics summed, and whether every batch came in canonical order."""
    parts_index, parts_uv = [], []
    totals = np.zeros(6, dtype=np.int64)
    ordered = True
    for b0 in range(0, n, ONE_BOUNCE_BATCH):
        ti, uv, sums, in_order = launch(b0, min(n, b0 + ONE_BOUNCE_BATCH))
        parts_index.append(ti)
        parts_uv.append(uv)
        totals += sums
        ordered = ordered and in_order
    t1 = time.perf_counter()
    if len(parts_index) == 1:
        tuple_index, uv = parts_index[0], parts_uv[0]
    else:
        tuple_index = np.concatenate(parts_index) if parts_index else np.zeros(0, dtype=np.int64)
        uv = np.concatenate(parts_uv) if parts_uv else np.zeros((0, 2))
    d.host("unpack", time.perf_counter() - t1)
    return tuple_index, uv, totals, ordered


def _one_bounce_launch(d, refract, n, first, inputs, pairs):
    """One launch over n tuples: inputs = the device buffers of (x_start, x_end, P, N, eta),
    pairs = the buffers of the (emitter, point) indices or None (row i of each input is tuple
    i).  Returns (tuple_index, uv, statistics, ordered): the paths (in canonical order when
    ``ordered``) and the summed statistics (roots, candidates, paths, skipped, overflow, pairs
    outside the tables)."""
    paired = np.int32(0 if pairs is None else 1)
    if pairs is None:
        pairs = (d.buffer("no_pairs", 64), d.buffer("no_pairs", 64), np.int32(0), np.int32(0))
    acc = np.zeros(2 + 5 * N_SLOTS, dtype=np.int32)  # the path counter, the statistics' slots, bad pairs
    acc_buf = d.buffer("acc", acc.nbytes)
    _fill_zero(d, acc_buf, acc.nbytes)
    args = (paired, *pairs, *inputs, np.int32(n), np.int32(first))
    split = _two_stage(d)
    if split:
        tuple_index, uv = _split_launch(d, refract, n, first, args, acc_buf, acc)
    else:
        tuple_index, uv = _whole_launch(d, refract, n, args, acc_buf, acc)
    sums = np.append(acc[1:-1].reshape(N_SLOTS, 5).sum(axis=0, dtype=np.int64), acc[-1])
    return tuple_index, uv, sums, split


def _fill_zero(d, buf, nbytes):
    evt = d.cl.enqueue_fill_buffer(d.queue, buf, np.int32(0), 0, nbytes)
    if d.profiler is not None:
        d.profiler.event("zero", evt)


def _whole_launch(d, refract, n, args, acc_buf, acc):
    """The one-stage kernel (CPUs): paths appended by an atomic counter, in no particular
    order.  When the records overflow the path buffers, they grow to fit and the kernel runs
    again."""
    dummy = d.buffer("no_pairs", 64)
    capacity = max(d.path_capacity, PATH_RECORDS_PER_TUPLE * n, PATH_RECORDS_MIN)
    while True:
        d.path_capacity = capacity
        tuple_buf = d.buffer("path_tuple", 4 * capacity)
        uv_buf = d.buffer("path_uv", 16 * capacity)
        d.launch(d.kernel_one, "kernel solve_one_bounce", n, d.local_one, np.int32(1 if refract else 0),
                 np.int32(STAGE_WHOLE), *args, np.int32(capacity), np.int32(N_SLOTS), acc_buf, tuple_buf, uv_buf,
                 dummy, dummy, np.int32(0), dummy, dummy)
        d.read(acc, acc_buf)
        m = int(acc[0])
        if m <= capacity:
            break
        capacity = int(1.25 * m)
        _fill_zero(d, acc_buf, acc.nbytes)
    return _read_paths(d, m, tuple_buf, uv_buf)


def _split_launch(d, refract, n, first, args, acc_buf, acc):
    """The split pipeline (GPUs): the filter stage flags the tuples that need the solve, a
    prefix sum places them in tuple order, the solve stage runs over them alone (full warps) into
    per-survivor slots, a prefix sum of the slot counts places the records, and the gather writes
    them: canonical order without a host sort.  When the records overflow the path buffers, they
    grow to fit and only the gather runs again."""
    flags = d.buffer("flags", 4 * n)
    pos = d.buffer("positions", 4 * n)
    survivors = d.buffer("survivors", 4 * n)
    slot_uv = d.buffer("slot_uv", 16 * SLOTS * n)
    slot_count = d.buffer("slot_count", 4 * n)
    offsets = d.buffer("offsets", 4 * n)
    dummy = d.buffer("no_pairs", 64)
    refract = np.int32(1 if refract else 0)
    capacity = max(d.path_capacity, PATH_RECORDS_PER_TUPLE * n, PATH_RECORDS_MIN)
    d.path_capacity = capacity
    tuple_buf = d.buffer("path_tuple", 4 * capacity)
    uv_buf = d.buffer("path_uv", 16 * capacity)
    tail = (np.int32(capacity), np.int32(N_SLOTS), acc_buf, tuple_buf, uv_buf)
    d.launch(d.kernel_one, "kernel one_bounce filter", n, d.local_one, refract, np.int32(STAGE_FILTER), *args, *tail,
             flags, dummy, np.int32(0), dummy, dummy)
    kept, kept_at = _scan(d, flags, pos, n, "kept")
    d.launch(d.kernel_scatter, "kernel compaction", n, d.local_scan, flags, pos, survivors, np.int32(n))
    d.launch(d.kernel_one, "kernel one_bounce solve", n, d.local_one, refract, np.int32(STAGE_SOLVE), *args, *tail,
             survivors, kept, np.int32(kept_at), slot_uv, slot_count)
    records, records_at = _scan(d, slot_count, offsets, n, "records")
    d.read(acc, acc_buf, wait=False)  # the statistics are final once the solve stage has run
    total = np.zeros(1, dtype=np.int32)
    while True:
        d.launch(d.kernel_gather, "kernel gather", n, d.local_scan, np.int32(first), survivors, kept, np.int32(kept_at),
                 slot_uv, slot_count, offsets, np.int32(capacity), tuple_buf, uv_buf)
        evt = d.cl.enqueue_copy(d.queue, total, records, src_offset=4 * records_at, is_blocking=True)
        if d.profiler is not None:
            d.profiler.event("device->host", evt)
            d.profiler.syncs += 1
        m = int(total[0])
        if m <= capacity:
            break
        capacity = int(1.25 * m)
        d.path_capacity = capacity
        tuple_buf = d.buffer("path_tuple", 4 * capacity)
        uv_buf = d.buffer("path_uv", 16 * capacity)
    return _read_paths(d, m, tuple_buf, uv_buf)


def _scan(d, src, dst, n, role):
    """dst[i] = src[0] + ... + src[i - 1] over n ints on the device (scan.cl).  Returns (the
    block-sums buffer, index of the grand total in it): later kernels read the total there, so
    the host does not wait for it."""
    k_blocks, k_sums, k_add = d.kernels_scan
    L = d.local_scan
    n_blocks = max((n + L - 1) // L, 1)
    sums = d.buffer(f"scan_{role}", 4 * (n_blocks + 1))
    local = d.cl.LocalMemory(4 * L)
    d.launch(k_blocks, "kernel compaction", n, L, src, dst, sums, np.int32(n), local)
    d.launch(k_sums, "kernel compaction", L, L, sums, np.int32(n_blocks), local)
    d.launch(k_add, "kernel compaction", n, L, dst, sums, np.int32(n))
    return sums, n_blocks


def _read_paths(d, m, tuple_buf, uv_buf):
    """The first m path records, read back."""
    tuple_index = np.empty(m, dtype=np.int32)
    uv = np.empty((m, 2))
    d.read(tuple_index, tuple_buf, wait=False)
    d.read(uv, uv_buf, wait=False)
    d.queue.finish()
    if d.profiler is not None and m:
        d.profiler.syncs += 1
    return tuple_index.astype(np.int64), uv


# --- two bounces --------------------------------------------------------------------------------


def refine_bytes_per_system(pieces):
    """Device memory of one system's refinement sub-samples (two_bounce.cl refine_samples): per
    piece SUB_SAMPLES + 3 samples (v, log|det|: 8 bytes each, sign: 4), SUB_SAMPLES pins (8) and
    a determinant count (4)."""
    from ..spoly.two_bounce.params import SUB_SAMPLES

    return pieces * ((SUB_SAMPLES + 3) * 20 + SUB_SAMPLES * 8 + 4)


def _stage_a_on_device(d):
    """Whether the two-bounce systems (stage A) are built on the device d (GPUs) or on Numba
    beside it (CPUs: the same cores, and Numba's vector kernels are ~2x faster than the
    device's scalar code there).  CAUSTIC_OPENCL_STAGE_A=device or host overrides."""
    forced = os.environ.get("CAUSTIC_OPENCL_STAGE_A")
    if forced in ("device", "host"):
        return forced == "device"
    return not d.is_cpu


def _two_bounce_defines():
    """two_bounce/params.py's constants that two_bounce.cl uses, as build options (exact:
    doubles as hexadecimal literals)."""
    from ..polynomials.roots import MAX_DEGREE
    from ..spoly.two_bounce import params

    out = []
    for name in ("ROOT_TOL", "KINK", "DIP_FLAT", "PRODUCTIVE_RADIUS", "B_RELATIVE", "ACCEPT_RESIDUAL", "SAME_PATH",
                 "NEAR_PATH", "V_MARGIN_APPROX", "V_MARGIN_EXACT", "LIVE_TOL", "HIT_MARGIN_EXACT", "HIT_MARGIN_APPROX",
                 "HERON_TOL", "HERON_CUT"):
        out.append((name, float(getattr(params, name)).hex()))
    for name in ("SUB_SAMPLES", "NOISY_CHANGES", "DIP_STEPS", "POLISH_STEPS", "N_SEEDS", "MAX_PATHS_TWO_BOUNCE",
                 "BOTH_DIRECTIONS", "N_STATS", "STAT_ROOTS", "STAT_CANDIDATES", "STAT_PATHS", "STAT_SKIPPED", "STAT_DETS",
                 "STAT_ACCEPTED", "STAT_NEAR", "MAXD", "N_SLOTS", "MAX_PIECES", "LIVE_DEPTH", "LIVE_DEPTH_LOW",
                 "LIVE_LOW_DEGREE", "LIVE_PREPASS", "LIVE_SLOT0", "LIVE_STACK", "V_MAJOR_SLOT", "HIT_TEST", "HIT_SLOT",
                 "BETA_SLOT", "BETA_GRID", "BETA_MASK_FROM", "SQRT_BANDS", "SQRT_BAND_REACH", "HERON_SQRT",
                 "HERON_FIT_GRID", "HERON_CHECK_GRID"):
        out.append((name, int(getattr(params, name))))
    out.append(("MAX_DEGREE", int(MAX_DEGREE)))
    out.append(("N_SQRT_PIECES", int(params.SQRT_PIECES.shape[0])))
    out.append(("N_HERON_CUTS", int(params.HERON_CUTS.shape[0])))
    return out


def two_bounce_tables():
    """two_bounce/params.py's tables as OpenCL constants (hexadecimal doubles: exact):
    SQRT_PIECES_T[N_SQRT_PIECES][5] (lo, hi, c0, c1, d1 of eq 23's pieces) and
    HERON_CUTS_T[N_HERON_CUTS]; the two-bounce program says `// @TWO_BOUNCE_TABLES@` where
    they go."""
    from ..spoly.two_bounce import params

    rows = ",\n".join("    {" + ", ".join(float(x).hex() for x in row) + "}" for row in params.SQRT_PIECES)
    cuts = ", ".join(float(x).hex() for x in params.HERON_CUTS)
    return (f"__constant double SQRT_PIECES_T[{params.SQRT_PIECES.shape[0]}][5] = {{\n{rows}\n}};\n"
            f"__constant double HERON_CUTS_T[{params.HERON_CUTS.shape[0]}] = {{{cuts}}};\n")


def _two_bounce_program(index):
    """The _Device of index with its two-bounce kernels (TWO_BOUNCE_KERNELS, local size)
    built once."""
    d = _context(index)  # OpenCLUnavailable / OpenCLNoDoublePrecision as for one bounce
    if d.kernels_two is None:
        # OpenCLUnavailable for a driver that rejects the program: the caller falls back to Numba
        kernels = {name: d.kernel(_KERNEL_FILE_2, name, _two_bounce_defines()) for name in TWO_BOUNCE_KERNELS}
        # ~18 KB of private scratch per work-item (the Bézout matrix): small groups on CPUs
        # (see CPU_WORK_GROUP); on a GPU it lives in per-thread local memory.
        d.kernels_two = (kernels, min(d.work_group(k) for k in kernels.values()))
    _cache2[index] = d.kernels_two
    return d


def two_bounce_device_name(index):
    """Like :func:`device_name`, and builds the two-bounce program (so a build error surfaces
    before any work)."""
    _two_bounce_program(index)
    return device_name(index)


class OpenCLSystemSolver:
    """Stages A-E of ``two_bounce.staged`` on an OpenCL device: per batch the tuples go up once;
    stage A builds the systems (``stage_a.cl``; on CPU devices Numba does, :func:`_stage_a_on_device`),
    the resultant scan (``find_v_roots``: samples, degeneracy, Illinois pins, root lists), the
    candidates at the scan roots (stage C), the refinement (``refine_v_roots``) and the
    candidates at the refined roots, seeded polish and straight line (stage E) run one after
    the other on the device (``two_bounce.cl``), and the host reads the paths and statistics.
    A tuple with a system whose refined roots overflow the device's capacity is left to the
    host."""

    def __init__(self, index):
        self.device = _two_bounce_program(index)
        self.k, self.local = self.device.kernels_two
        self.name = self.device.label
        # staged.solve_staged's batch store: the default on CPUs, larger on GPUs (within a 32nd of
        # the device's memory: the scan's buffers of a batch take several times the store)
        d = self.device
        self.batch_bytes = None if d.is_cpu else min(GPU_BATCH_BYTES, d.dev.global_mem_size // 32)

    def load(self, coef, sysint3, b_offset, live_mask, margin, pieces):
        """coef (S, stride) packed systems, sysint3 (S, 3) int32 (da, db, n), live_mask (S, pieces)
        int8, margin (S,): the scan of system s runs over [-margin[s], 1 + margin[s]]."""
        d = self.device
        self.S = coef.shape[0]
        self.pieces = int(pieces)
        self.stride = np.int32(coef.shape[1])
        self.b_offset = np.int32(b_offset)
        self.coef_buf = d.write("coef", np.ascontiguousarray(coef, dtype=np.float64))
        self.sys_buf = d.write("sysint3", np.ascontiguousarray(sysint3, dtype=np.int32))
        self.live_buf = d.write("live", np.ascontiguousarray(live_mask, dtype=np.int8))
        self.margin_buf = d.write("margin", np.ascontiguousarray(margin, dtype=np.float64))

    def _system_args(self):
        return self.coef_buf, self.sys_buf, self.stride, self.b_offset, self.live_buf, self.margin_buf

    def _wait(self):
        d = self.device
        d.queue.finish()
        if d.profiler is not None:
            d.profiler.syncs += 1

    def solve_batch(self, refract1, refract2, x_start, x_end, P, N, eta, pieces, stride, b_offset, sys_cap, out_uv,
                    out_count, stats):
        """Stages A-E of one batch of tuples (``staged._solve_batch``) on the device: stage A's
        systems (stage_a.cl), one wait for the systems' counts, the staged systems gathered
        tuple by tuple, then the scan, the candidates, the refinement and the candidates at the
        refined roots (two_bounce.cl), one wait for the paths.  Fills out_uv, out_count, stats;
        returns (state (n,): 0 nothing to solve, 1 solved here, 2 more than sys_cap systems;
        left (n,) bool: tuples with a system whose refined roots overflowed the capacity),
        the tuples of state 2 or left to be solved on the host."""
        from ..spoly.two_bounce.params import MAX_PIECES, N_SLOTS, MAXD

        d, n, pc = self.device, x_start.shape[0], int(pieces)
        state = np.zeros(n, dtype=np.int8)
        left = np.zeros(n, dtype=bool)
        if not n:
            return state, left
        f64 = lambda a: np.ascontiguousarray(a, dtype=np.float64)  # noqa: E731
        w = d.write
        self.tuple_bufs = [w("x_start", f64(x_start)), w("x_end", f64(x_end)), w("P", f64(P)), w("N", f64(N)),
                           w("eta", f64(eta))]
        if not _stage_a_on_device(d):
            return self._stage_a_on_host(refract1, refract2, x_start, x_end, P, N, eta, pc, stride, b_offset, sys_cap,
                                         out_uv, out_count, stats)
        coef_all = d.buffer("stage_a_coef", n * sys_cap * stride * 8)
        sysint_all = d.buffer("stage_a_sysint", n * sys_cap * 7 * 4)
        live_all = d.buffer("stage_a_live", n * sys_cap * max(pc, 1))
        nsys_buf = d.buffer("stage_a_nsys", n * 4)
        state_buf = d.buffer("state", n)
        self.stats_buf = d.buffer("stats", n * stats.shape[1] * 8)
        per_item = N_SLOTS * (MAXD + 1) ** 2 * 8
        budget = STAGE_A_SCRATCH_BYTES if d.is_cpu else min(GPU_STAGE_A_SCRATCH_BYTES, d.dev.global_mem_size // 8,
                                                               d.dev.max_mem_alloc_size)
        items = max(1, min(n, budget // per_item))
        scratch = d.buffer("stage_a_scratch", items * per_item)
        live_scratch = d.buffer("stage_a_live_scratch", items * MAX_PIECES)
        for t0 in range(0, n, items):
            d.launch(self.k["stage_a"], "kernel stage_a", min(items, n - t0), self.local, np.int32(bool(refract1)),
                     np.int32(bool(refract2)), *self.tuple_bufs, np.int32(b_offset), np.int32(stride), np.int32(sys_cap),
                     np.int32(pc), np.int32(t0), np.int32(min(items, n - t0)), coef_all, sysint_all, nsys_buf, state_buf,
                     self.stats_buf, live_all, scratch, live_scratch)
        nsys = np.zeros(n, dtype=np.int32)
        d.read(nsys, nsys_buf, wait=False)
        d.read(state, state_buf, wait=False)
        self._wait()
        # the staged tuples' systems, tuple by tuple in stage A's order
        m = np.where(state == 1, nsys, 0)
        sys_first = np.concatenate([[0], np.cumsum(m)]).astype(np.int32)
        S = int(sys_first[-1])
        owner = np.repeat(np.arange(n, dtype=np.int32), m)
        slot = (np.arange(S) - np.repeat(sys_first[:-1], m)).astype(np.int32)
        self.S, self.pieces, self.stride, self.b_offset = S, pc, np.int32(stride), np.int32(b_offset)
        self.coef_buf = d.buffer("coef", S * stride * 8)
        self.sys7_buf = d.buffer("sysint7", S * 7 * 4)
        self.sys_buf = d.buffer("sysint3", S * 3 * 4)
        self.live_buf = d.buffer("live", S * max(pc, 1))
        self.margin_buf = d.buffer("margin", S * 8)
        solve_buf = d.buffer("solve", S)
        refinable_buf = d.buffer("refined", S)
        d.launch(self.k["gather_systems"], "kernel gather_systems", S, self.local, w("owner", owner), w("slot", slot),
                 np.int32(S), np.int32(bool(refract1)), np.int32(bool(refract2)), np.int32(stride), np.int32(sys_cap),
                 np.int32(pc), coef_all, sysint_all, live_all, self.coef_buf, self.sys7_buf, self.sys_buf, self.live_buf,
                 self.margin_buf, solve_buf, refinable_buf)
        over = self._solve_systems(refract1, refract2, n, w("sys_first", sys_first), state_buf, solve_buf, refinable_buf,
                                   out_uv, out_count, stats)
        mine = state == 1
        if S:
            left[owner[over < 0]] = True
        out_count[state == 0] = 0
        return state, mine & left

    def _stage_a_on_host(self, refract1, refract2, x_start, x_end, P, N, eta, pc, stride, b_offset, sys_cap, out_uv,
                         out_count, stats):
        """:meth:`solve_batch` with stage A on Numba (``staged.stage_a_on_host``), its systems
        uploaded, then stages B-E on the device: for CPU devices, where the host's vector
        kernels build the systems ~2x faster than the device's scalar code."""
        from ..spoly.two_bounce.staged import stage_a_on_host

        d, n = self.device, x_start.shape[0]
        state, b = stage_a_on_host(refract1, refract2, x_start, x_end, P, N, eta, pc, stride, b_offset, sys_cap, stats)
        self.load(b.coef, b.sysint3, b_offset, b.live_mask, b.margin, pc)
        S = b.S
        sysint = b.sysint
        w = d.write
        self.sys7_buf = w("sysint7", np.ascontiguousarray(sysint, dtype=np.int32))
        self.stats_buf = w("stats", np.ascontiguousarray(stats, dtype=np.int64))
        solve_buf = w("solve", (sysint[:, 1] == 1).astype(np.int8))
        refinable_buf = w("refined", ((sysint[:, 1] == 1) & ((sysint[:, 0] & 2) == 0)).astype(np.int8))
        state_buf = w("state", state.astype(np.int8))
        over = self._solve_systems(refract1, refract2, n, w("sys_first", b.sys_first.astype(np.int32)), state_buf,
                                   solve_buf, refinable_buf, out_uv, out_count, stats)
        left = np.zeros(n, dtype=bool)
        if S:
            left[b.owner[over < 0]] = True
        out_count[state != 1] = 0
        return state, left & (state == 1)

    def _solve_systems(self, refract1, refract2, n, first_buf, state_buf, solve_buf, refinable_buf, out_uv, out_count,
                       stats):
        """Stages B-E of the gathered systems (kernels of two_bounce.cl, one wait); fills
        out_uv, out_count (state-1 tuples), stats (all); returns the refinement's per-system
        counts (-1: overflow)."""
        from ..spoly.two_bounce.params import REFINE_LEVELS, SUB_SAMPLES
        from ..spoly.two_bounce.staged import refine_capacity

        d, S, P = self.device, self.S, self.pieces
        ps, pieces, pn = np.int32(S), np.int32(P), np.int32(n)
        r1, r2 = np.int32(bool(refract1)), np.int32(bool(refract2))
        cap = refine_capacity(S)
        if not REFINE_LEVELS:
            refinable_buf = d.write("refined", np.zeros(S, dtype=np.int8))
        uv_buf = d.buffer("out_uv", out_uv.nbytes)
        meta_buf = d.buffer("meta", n * (out_uv.shape[1] + 1) * 2 * 8)
        count_buf = d.buffer("out_count", n * 4)
        sg = d.buffer("scan_sign", S * (P + 1) * 4)
        lg = d.buffer("scan_log", S * (P + 1) * 8)
        sample_dets = d.buffer("scan_sample_dets", S * (P + 1) * 4)
        degenerate = d.buffer("scan_degenerate", S)
        pin = d.buffer("scan_pin", S * P * 8)
        pin_dets = d.buffer("scan_pin_dets", S * P * 4)
        nv_buf = d.buffer("scan_nv", S * 4)
        roots_buf = d.buffer("scan_roots", S * P * 8)
        piece_buf = d.buffer("scan_piece_of", S * P * 4)
        scan_dets = d.buffer("scan_dets", S * 4)
        productive = d.buffer("productive", S * P)
        found = d.buffer("refine_found", S * cap * 8)
        found_count = d.buffer("refine_count", S * 4)
        refine_dets = d.buffer("refine_dets", S * 4)
        args = self._system_args()
        tuples = (first_buf, state_buf, *self.tuple_bufs, r1, r2)
        d.launch(self.k["scan_samples"], "kernel scan_samples", S * (P + 1), self.local, *args, solve_buf, pieces, ps,
                 sg, lg, sample_dets)
        d.launch(self.k["scan_degenerate"], "kernel scan_degenerate", S, self.local, solve_buf, pieces, ps, sg, degenerate)
        d.launch(self.k["scan_pins"], "kernel scan_pins", S * P, self.local, *args, solve_buf, degenerate, pieces, ps, sg,
                 lg, pin, pin_dets)
        d.launch(self.k["scan_roots"], "kernel scan_roots", S, self.local, self.live_buf, self.margin_buf, solve_buf,
                 degenerate, pieces, ps, sg, sample_dets, pin, pin_dets, nv_buf, roots_buf, piece_buf, scan_dets)
        d.launch(self.k["candidates_scan"], "kernel candidates_scan", n, self.local, self.coef_buf, self.sys7_buf,
                 self.stride, self.b_offset, *tuples, pieces, nv_buf, roots_buf, productive, uv_buf, meta_buf, count_buf,
                 self.stats_buf, pn)
        # the refinement, in cuts of the systems whose sub-samples fit REFINE_SUB_BYTES
        row = SUB_SAMPLES + 3
        per_system = refine_bytes_per_system(P)
        budget = REFINE_SUB_BYTES if d.is_cpu else min(GPU_REFINE_SUB_BYTES, d.dev.max_mem_alloc_size)
        cut = max(1, min(max(S, 1), budget // per_system))
        flags = d.buffer("refine_flags", S * P)
        sub = [d.buffer("refine_sub_v", cut * P * row * 8), d.buffer("refine_sub_s", cut * P * row * 4),
               d.buffer("refine_sub_l", cut * P * row * 8), d.buffer("refine_sub_pin", cut * P * SUB_SAMPLES * 8)]
        sub_dets = d.buffer("refine_sub_dets", cut * P * 4)
        for s0 in range(0, S, cut):
            m = min(cut, S - s0)
            system_args = (*args, refinable_buf, pieces, np.int32(s0), np.int32(m), sg, lg, nv_buf, roots_buf, piece_buf,
                           productive, np.int32(cap), found)
            d.launch(self.k["refine_flags"], "kernel refine_flags", m, self.local, *system_args, flags, refine_dets)
            d.launch(self.k["refine_samples"], "kernel refine_samples", m * P, self.local, *system_args, flags, *sub,
                     sub_dets)
            d.launch(self.k["refine_assemble"], "kernel refine_assemble", m, self.local, *system_args, flags, *sub,
                     sub_dets, found_count, refine_dets)
        d.launch(self.k["candidates_refined"], "kernel candidates_refined", n, self.local, self.coef_buf, self.sys7_buf,
                 self.stride, self.b_offset, *tuples, nv_buf, scan_dets, np.int32(cap), found, found_count, refine_dets,
                 uv_buf, meta_buf, count_buf, self.stats_buf, pn)
        counts = np.zeros(n, dtype=np.int32)
        over = np.zeros(S, dtype=np.int32)
        staged_stats = np.zeros(stats.shape, dtype=np.int64)
        staged_uv = np.zeros(out_uv.shape)
        d.read(counts, count_buf, wait=False)
        d.read(staged_stats, self.stats_buf, wait=False)
        d.read(staged_uv, uv_buf, wait=False)
        d.read(over, found_count, wait=False)
        self._wait()
        stats[...] = staged_stats
        out_count[...] = counts
        out_uv[...] = staged_uv
        return over

    def dets(self, job_sys, job_v):
        """(sign (J,) int32, log|det| (J,), determinant evaluations (J,)) of the loaded system
        job_sys at v1 = job_v (``resultant.det_checked``): the determinant alone, for tests."""
        d = self.device
        n = job_sys.shape[0]
        sign = np.zeros(n, dtype=np.int32)
        log = np.zeros(n)
        dets = np.zeros(n, dtype=np.int32)
        if n:
            bufs = [d.write("job_sys", np.ascontiguousarray(job_sys, dtype=np.int32)),
                    d.write("job_v", np.ascontiguousarray(job_v, dtype=np.float64))]
            outs = [d.buffer(f"job_out{i}", o.nbytes) for i, o in enumerate((sign, log, dets))]
            d.launch(self.k["det_batch"], "kernel det_batch", n, self.local, self.coef_buf, self.sys_buf, self.stride,
                     self.b_offset, *bufs, np.int32(n), *outs)
            for o, b in zip((sign, log, dets), outs):
                d.read(o, b, wait=False)
            self._wait()
        return sign, log, dets


def solve_two_bounce_opencl(index, refract1, refract2, x_start, x_end, P, N, eta, pieces, out_uv, out_count, stats):
    """The two-bounce solve with its determinant work on OpenCL device index; fills the
    arrays as ``two_bounce.solve_two_bounce_batch`` does."""
    from ..spoly.two_bounce.staged import solve_staged

    solve_staged(OpenCLSystemSolver(index), refract1, refract2, x_start, x_end, P, N, eta, pieces, out_uv, out_count, stats)
