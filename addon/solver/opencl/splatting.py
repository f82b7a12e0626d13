"""The forward-flux splat on an OpenCL device (``splat.cl``): the device form of
``estimators.splat.splat_triangles``, into flux textures that stay on the device for a whole
pass (its caster chunks add to them) and come back once.

Each band of rows is one work-item taking every sub-triangle in order, so a texel sums its
sub-triangles' shares in their order: the same bits as the Numba splat (same arithmetic, FP
contraction off).  A CPU device takes one work-group of bands per compute unit (each band scans
every triangle: more bands than cores only repeat that scan), other devices one row a band.
"""

import os

import numpy as np

from ..estimators.splat import band_first_rows
from .backend import OpenCLUnavailable, _context, _fill_zero

_KERNEL_FILE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "splat.cl")


def _kernel(index):
    d = _context(index)
    return d, d.kernel(_KERNEL_FILE, "splat_bands")  # OpenCLUnavailable: the caller splats on Numba


class OpenCLSplat:
    """Flux textures (H W, 3) of receivers of ``sizes`` ((W, H) each) on OpenCL device
    ``index``, zero at the start.  :meth:`add` splats sub-triangles onto one of them (as
    ``splat_triangles``), :meth:`arrays` reads them all back."""

    def __init__(self, index, sizes):
        self.device, self.kernel = _kernel(index)
        d = self.device
        self.name = d.label
        self.sizes = [(int(w), int(h)) for w, h in sizes]
        self.textures = []
        try:
            for w, h in self.sizes:
                buf = d.cl.Buffer(d.ctx, d.cl.mem_flags.READ_WRITE, max(24 * w * h, 64))
                _fill_zero(d, buf, max(24 * w * h, 64))
                self.textures.append(buf)
            d.queue.finish()  # an allocation the device cannot make fails here, not in a later splat
        except d.cl.Error as ex:
            raise OpenCLUnavailable(f"no room for the flux textures on {d.label}: {ex}") from ex
        self.local = d.small_work_group(self.kernel)  # a band per row: ~10^3 work-items, each over a chunk's triangles

    def add(self, r, tri_uv, flux, density, region=None):
        """Splat triangles (UV corners ``tri_uv`` (m, 3, 2), ``flux`` (m, 3), corner ``density``
        (m, 3), clipped to ``region`` (K, 3) rows a u + b v + c >= 0 when given) onto receiver
        r's texture."""
        m = int(tri_uv.shape[0])
        W, H = self.sizes[r]
        if m == 0 or H == 0:
            return
        d = self.device
        band_first = band_first_rows(H, self.local * d.dev.max_compute_units if d.is_cpu else H)
        region = np.zeros((0, 3)) if region is None else np.ascontiguousarray(region, dtype=np.float64)
        bufs = [d.write(f"splat_{k}", np.ascontiguousarray(a, dtype=dt)) for k, a, dt in (
            ("uv", tri_uv, np.float64), ("flux", flux, np.float64), ("density", density, np.float64),
            ("bands", band_first, np.int64), ("region", region, np.float64))]
        n_bands = band_first.size - 1
        d.launch(self.kernel, "kernel splat_bands", n_bands, self.local, bufs[0], bufs[1], bufs[2], np.int32(m),
                 np.int64(W), np.int64(H), self.textures[r], bufs[3], np.int32(n_bands), bufs[4], np.int32(region.shape[0]))

    def arrays(self):
        """The textures, (H W, 3) each, read back."""
        out = []
        for (w, h), buf in zip(self.sizes, self.textures):
            a = np.empty((w * h, 3))
            self.device.read(a, buf, wait=False)
            out.append(a)
        self.device.queue.finish()
        if self.device.profiler is not None:
            self.device.profiler.syncs += 1
        return out
