"""The interface every estimator of :mod:`addon.bake.estimators` implements.

The pipeline (:mod:`addon.bake.pipeline`) builds one estimator per name with the planned
chains it bakes, then calls, in this order:

1. :meth:`Estimator.prepare` once: work shared by every receiver and band (forward images,
   photons); a generator yielding ``(fraction or None, message)`` between bounded chunks.
2. :meth:`Estimator.accumulate` per receiver and band of texel rows: adds irradiance at the
   band's supersamples into ``sums`` (W/m² per sample, summed per texel; the pipeline divides
   by the samples per texel); a generator too.
3. :meth:`Estimator.receiver_flux` per receiver: the flux (W per texel) that the pipeline
   divides by each texel's world area (texel-averaged irradiance), or None.
4. :meth:`Estimator.report`: what it did (counts, timings are in the shared timer).

Every estimator adds the power it delivers per chain, caster objects and receiver to
``ctx.ledger`` (the plan's baked shares).
"""

COUNT_KEYS = ("tuples_tile_cull", "tuples", "paths", "paths_front", "paths_lit", "paths_visible")


class Estimator:
    name = ""
    device = "cpu (numba)"

    def __init__(self, ctx, items):
        self.ctx = ctx
        self.items = list(items)  # PlannedChain, status "baked", estimator == self.name
        self.counts = dict.fromkeys(COUNT_KEYS, 0)
        self.chain_counts = {it.chain: {"tuples": 0, "paths": 0, "paths_visible": 0} for it in self.items}

    def prepare(self):
        """Shared work before the receivers (a generator; default: none)."""
        return
        yield  # noqa: unreachable (makes this a generator)

    def accumulate(self, rec_index, band, sums):
        """Irradiance at the band's supersamples into ``sums`` (a generator; default: none)."""
        return
        yield  # noqa: unreachable

    def receiver_flux(self, rec_index):
        """(H W, 3) W per texel of receiver ``rec_index`` or None (a generator returning it)."""
        return None
        yield  # noqa: unreachable

    def add_counts(self, chain, st):
        for k in COUNT_KEYS:
            self.counts[k] += st.get(k, 0)
        cc = self.chain_counts[chain]
        for k in cc:
            cc[k] += st.get(k, 0)

    def report(self):
        return {}
