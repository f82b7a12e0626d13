"""The up-front estimate of a bake (no bpy): at least how long it takes and how much memory it
needs, from the scene and the settings alone, before anything is computed, so that the
operator and the CLI can ask before a very large job (:func:`needs_confirmation`).

Seconds are counts times per-unit costs measured on a 2-core machine (bench/bake.py prints the
estimate next to the measured time of the sample scenes):

- the texel stages: every supersample of every receiver texel (``samples`` for the coverage,
  at least ``AREA_SAMPLES`` for the texel areas), ``SUPERSAMPLE_SECONDS`` each;
- forward-flux, per one-bounce chain the scene's materials allow (T leaves out closed solids,
  as the planner does) and light sample: ``CASTER_SECONDS`` per first-vertex caster triangle
  and ``TEXEL_SECONDS`` per receiver texel (the images it splats);
- path-points: ``EXACT_SECONDS`` per supersample and chain; photon: ``PHOTON_SECONDS`` per photon.

Two-bounce chains are left out: whether the planner keeps them depends on the energy its probe
finds, and their cost on the pairs of casters that hold paths, so the figure is a lower bound
("at least") of a first bake; a repeated bake of a receiver that did not move skips its texel
stages (kept coverage and texel areas) and takes less.  The texel stages, which make a very large resolution expensive, are
predictable.  Memory is :func:`addon.bake.memory.texel_bytes` plus ``BYTES_PER_TRIANGLE`` per
scene triangle, what :func:`addon.bake.memory.check_budget` checks.
"""

from dataclasses import dataclass

from .memory import BYTES_PER_TRIANGLE, gb, texel_bytes

SUPERSAMPLE_SECONDS = 0.5e-6  # texel stages, per supersample (coverage raster, texel areas, padding)
CASTER_SECONDS = 25e-6  # forward-flux, one-bounce chain: per first-vertex caster triangle and light sample ...
TEXEL_SECONDS = 0.15e-6  # ... and per receiver texel
EXACT_SECONDS = 10e-6  # path-points, per supersample and chain
PHOTON_SECONDS = 1e-6  # photon, per photon
CONFIRM_SECONDS = 600.0  # a bake estimated to take longer asks before it starts


@dataclass
class BakeEstimate:
    """At least how long a bake takes (``seconds``; ``forward_seconds`` of it the one-bounce
    forward images) and the memory it needs (bytes), for ``texels`` receiver texels and
    ``casters`` first-vertex caster triangles (summed over the one-bounce chains, lights and
    light samples)."""

    seconds: float
    forward_seconds: float
    memory: int
    texels: int
    casters: int

    def line(self):
        """``at least about 3 min 5 s and 1.2 GB of memory``."""
        from .pipeline import format_seconds

        return f"at least about {format_seconds(self.seconds)} and {gb(self.memory)} of memory"

    def times(self, n):
        """The estimate of ``n`` such bakes one after the other (the frames of a range)."""
        return BakeEstimate(self.seconds * n, self.forward_seconds * n, self.memory, self.texels, self.casters)

    def as_dict(self):
        return {"seconds": float(self.seconds), "forward_seconds": float(self.forward_seconds),
                "memory_bytes": int(self.memory), "texels": int(self.texels), "casters": int(self.casters)}


def estimate_bake(scene, settings):
    """The :class:`BakeEstimate` of baking ``scene`` (an extracted scene model) with
    ``settings`` (see the module docstring for the model)."""
    import dataclasses

    from .pipeline import AREA_SAMPLES
    from .plan import candidate_chains, chain_casters, closed_refracting, structural_chains
    from .raster import grid_side
    from .settings import resolve_aliases

    settings = resolve_aliases(dataclasses.replace(settings))
    size = int(settings.resolution)
    resolutions = [(size, size) if size else tuple(int(v) for v in r.resolution) for r in scene.receivers]
    texels = sum(w * h for w, h in resolutions)
    samples = grid_side(settings.samples) ** 2 + grid_side(max(int(settings.samples), AREA_SAMPLES)) ** 2
    seconds = texels * samples * SUPERSAMPLE_SECONDS
    forward = 0.0
    casters = 0
    n_light = len(scene.lights) * max(1, int(settings.light_samples))
    closed = closed_refracting(scene) if settings.caustics else set()
    allowed = structural_chains(scene, closed=closed) if settings.caustics else []
    chains = [c for c in candidate_chains(settings) if c in allowed]
    exact = 0
    for chain in chains:
        name = settings.estimator_for(chain)
        if name in ("path-points", "path-seeded"):
            exact += 1
        elif name == "forward-flux" and len(chain) == 1:
            first = chain_casters(scene, chain, closed)[0]
            forward += (first.size * CASTER_SECONDS + texels * TEXEL_SECONDS) * n_light
            casters += int(first.size) * n_light
    seconds += texels * grid_side(settings.samples) ** 2 * EXACT_SECONDS * exact
    if any(settings.estimator_for(c) == "photon" for c in chains):
        seconds += int(settings.photons) * PHOTON_SECONDS
    memory = texel_bytes(resolutions, settings.band_samples, 1) + int(scene.n_triangles) * BYTES_PER_TRIANGLE
    return BakeEstimate(seconds + forward, forward, memory, texels, casters)


def needs_confirmation(estimate):
    """Whether a bake so large should be confirmed before it starts (``CONFIRM_SECONDS``)."""
    return estimate.seconds > CONFIRM_SECONDS
