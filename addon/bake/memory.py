"""The bake's memory budget (no bpy): what its texel arrays need, checked before the bake
starts, and a one-line error instead of a ``MemoryError`` traceback when memory runs out.

:func:`texel_bytes` counts the arrays the pipeline itself holds per receiver (sums, coverage,
the image before and after padding, texel areas, each estimator's flux texture) and per band
of supersamples; :func:`check_budget` raises :class:`BakeMemoryError` when that exceeds the
budget (``BakeSettings.memory_budget``, or :data:`MEMORY_FRACTION` of the memory available
now), and so does a scene whose triangles (``BYTES_PER_TRIANGLE`` each: their arrays, the
BVH, one chunk of the forward images) with the textures exceed it.
"""

import os

from .scene import SceneError

MEMORY_FRACTION = 0.5  # default budget: this share of the memory available when the bake starts
BYTES_PER_TEXEL = 8 * 3 * 3 + 8 + 8 + 4 * 3 + 1  # sums, raw image, padded copy (f64 x 3); cover, area; float32 image; mask
BYTES_PER_FLUX_TEXEL = 8 * 3  # one estimator's flux texture (W per texel, f64 x 3)
BYTES_PER_SAMPLE = 8 * 2 + 8 * 2 + 8 * 2 + 8 * 3 * 3  # one supersample of a band: texel, tri, bary, uv, point, normals
# one scene triangle: its arrays, the BVH, the per-caster culling and one chunk of forward
# images (measured: the peak of a default bake of a glass sphere at 1024² grows by ~2.1 kB per
# triangle from 100k to 300k triangles, bench/memory.py)
BYTES_PER_TRIANGLE = 2200


class BakeMemoryError(SceneError):
    """The bake does not fit in memory (one line)."""


def available_memory():
    """Bytes of memory available now (Linux ``MemAvailable``; elsewhere free physical pages), or None."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def budget(settings):
    """The bake's memory budget in bytes (None: unknown, nothing is checked)."""
    if settings.memory_budget:
        return float(settings.memory_budget)
    free = available_memory()
    return None if free is None else MEMORY_FRACTION * free


def texel_bytes(resolutions, band_samples, flux_textures):
    """Bytes the pipeline's own arrays take at most: every receiver's (W, H) texel arrays with
    ``flux_textures`` flux textures each, and one band of ``band_samples`` supersamples."""
    texels = sum(int(w) * int(h) for w, h in resolutions)
    return texels * (BYTES_PER_TEXEL + BYTES_PER_FLUX_TEXEL * flux_textures) + int(band_samples) * BYTES_PER_SAMPLE


def gb(n):
    return f"{n / 1e9:.1f} GB"


def check_budget(resolutions, settings, flux_textures=1, triangles=0):
    """Raise :class:`BakeMemoryError` when the texel arrays of a bake at ``resolutions``, or
    they and a scene of ``triangles`` triangles (``BYTES_PER_TRIANGLE`` each), do not fit the
    budget (before anything is computed)."""
    limit = budget(settings)
    need = texel_bytes(resolutions, settings.band_samples, flux_textures)
    if limit is not None and need > limit:
        biggest = max(resolutions, key=lambda r: r[0] * r[1])
        raise BakeMemoryError(f"the bake needs about {gb(need)} for its textures ({len(resolutions)} receiver(s), up to "
                              f"{biggest[0]} x {biggest[1]} texels), more than its memory budget of {gb(limit)}; "
                              "lower the resolution or raise the memory budget")
    scene_need = int(triangles) * BYTES_PER_TRIANGLE
    if limit is not None and need + scene_need > limit:
        raise BakeMemoryError(f"the bake needs about {gb(need + scene_need)} ({int(triangles):,} triangles and the "
                              f"textures), more than its memory budget of {gb(limit)}; simplify the casters (fewer "
                              "triangles), lower the resolution or raise the memory budget")


def out_of_memory(stage):
    """The one-line error for a ``MemoryError`` raised during ``stage``."""
    return BakeMemoryError(f"out of memory while {stage}; lower the resolution, the samples or the image depth, or "
                           "close other programs")
