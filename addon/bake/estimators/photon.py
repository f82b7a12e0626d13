"""The ``photon`` estimator: light tracing into texel histograms (the baseline).

Photons are traced from the lights as the bake models them (:func:`addon.bake.lights.sample_light`:
points with their emission profile, sun directions; ``settings.light_samples`` per light) by
:mod:`addon.solver.estimators.photon`, following only the planned chains, and their flux is binned per
receiver texel; the pipeline divides it by the world area each texel covers on its receiver:

    E = flux / A,

the texel-averaged irradiance (W/m²), an unbiased estimate of the mean over the texel of the
per-point irradiance the path estimators take at their supersamples.  The sun is traced as
exactly parallel light.  Photons deposit on every receiver a planned chain reaches (the
tracer follows chains, not receivers).  Tested against the path estimators
(tests/bake/test_bake_methods.py).
"""

import time

import numpy as np

from ...solver.estimators.photon import CHAINS, make_emitters, photon_steps
from .base import Estimator


def light_sample_dicts(ctx):
    """The light samples of every light as :func:`addon.solver.estimators.photon.make_emitters` takes them."""
    out = []
    for ls in ctx.lsamples:
        for m in range(ls.size):
            if ls.kind == "sun":
                out.append(dict(kind="sun", direction=ls.direction[m], rgb=ls.rgb[m]))
            else:
                out.append(dict(kind="point", position=ls.position[m], rgb=ls.rgb[m], lobe=ls.lobe[m], spot_axis=ls.spot_axis,
                                spot_cos=ls.spot_cos, spot_smooth=ls.spot_smooth))
    return out


class Photon(Estimator):
    name = "photon"

    def __init__(self, ctx, items):
        super().__init__(ctx, items)
        self.chains = sorted({it.chain for it in self.items}, key=CHAINS.index)
        self.flux = None
        self.photons = self.deposited = 0
        self.per_chain = {}
        self.light_samples = 0

    def prepare(self):
        ctx = self.ctx
        scene = ctx.scene
        tri_rec, tri_uv = ctx.receiver_of_triangle()
        t0 = time.perf_counter()
        first = np.unique(np.concatenate([it.vertices[0] for it in self.items])) if self.items else np.zeros(0, dtype=np.int64)
        samples = light_sample_dicts(ctx)
        self.light_samples = len(samples)
        emitters = make_emitters(samples, scene.tri_p[first].reshape(-1, 3), ctx.extent, ctx.settings.photons if self.chains else 0)
        ctx.timer.since("emit", t0)
        if not self.chains or int(emitters.start[-1]) == 0:
            return
        steps = photon_steps(scene.tri_p, scene.tri_n, scene.tri_role, scene.tri_ior, scene.tri_tint, tri_rec, tri_uv,
                             [r.resolution for r in ctx.receivers], emitters, self.chains, seed=ctx.settings.seed,
                             bvh=ctx.bvh, eps=ctx.eps)
        res = yield from ctx.timer.timed_steps("trace", steps,
                                               lambda done, total: (0.9 * done / max(1, total), f"photons: {done:,}/{total:,}"))
        self.flux, self.photons, self.deposited, self.per_chain = res.flux, res.photons, res.deposited, res.per_chain

    def receiver_flux(self, rec_index):
        if self.flux is None:
            return None
        offset = sum(r.resolution[0] * r.resolution[1] for r in self.ctx.receivers[:rec_index])
        W, H = self.ctx.receivers[rec_index].resolution
        f = self.flux[offset:offset + W * H]
        # photons carry no caster ids: their power goes to the ledger per receiver as chain "*"
        self.ctx.ledger.add(-1, "*", [-1], None, [rec_index], [float(f.mean(axis=1).sum())])
        return f
        yield  # noqa: unreachable

    def report(self):
        return {"photons": int(self.photons), "photons_deposited": int(self.deposited), "light_samples": self.light_samples,
                "per_chain": dict(self.per_chain)}
