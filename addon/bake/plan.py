"""The planner: which chains to bake, per light x caster x receiver, and why (no bpy).

"Model no more than a scene needs — and no less":

1. **Roles and topology.**  R needs reflecting casters (metal, glass), T refracting ones
   (water, glass); a single refraction into a *closed* solid ends inside it, so T leaves out
   closed objects (a glass sphere's caustic is TT) — except for a light inside the solid
   (:func:`addon.bake.checks.lights_inside`), whose T chain starts inside it.  Two-bounce chains (RR, RT, TR, TT) take
   every caster of the roles their vertices need.  ``settings.chains`` restricts; a chain the
   estimator's solver cannot solve is kept with a "skipped: ..." status.
2. **Reach and energy** (``bounces="auto"``, the default): the flux probe
   (:mod:`addon.bake.probe`) estimates the caustic power each (light, chain, caster objects)
   brings to each receiver.  A chain is baked onto a receiver when its share of that
   receiver's estimated caustic power is at least ``settings.plan_threshold`` (0.5 %), for the
   lights whose probe reached that receiver through it; the rest is skipped and reported
   with the reason (below the threshold, or no light path found).
3. **Forced** (``bounces`` 1 or 2): every chain of up to that many bounces that step 1
   allows, onto every receiver, without the probe.

The plan's report (:meth:`Plan.report`) lists every (light, chain, casters, receiver) with its
estimated share (the probe) and its baked share (the power the estimators delivered,
``ctx.ledger``), and a one-line summary per receiver.  Tested in tests/bake/test_bake_plan.py
(a single refracting sheet needs no two-bounce work; every sample scene's default bake keeps
≥ 99 % of a forced two-bounce bake's energy).
"""

import time
from dataclasses import dataclass

import numpy as np

from .context import EnergyLedger
from .estimators.path_points import chain_status
from .checks import lights_inside
from .lights import sample_light
from .probe import PROBE_POINTS, PROBE_POINTS_TWO_BOUNCE, probe_chain
from .scene import ROLE_BOTH, ROLE_REFLECT, ROLE_REFRACT

CHAINS = ("R", "T", "RR", "RT", "TR", "TT")
CHAIN_ROLES = {"R": (ROLE_REFLECT, ROLE_BOTH), "T": (ROLE_REFRACT, ROLE_BOTH)}
CLOSED_T = "a single refraction into a closed solid ends inside it"


@dataclass
class PlannedChain:
    """One chain from one light: its casters per vertex (global triangle ids), the receivers
    it is baked onto, the estimator that bakes it, and "baked" or "skipped: <why>"."""

    chain: str
    light: int
    vertices: list
    receivers: tuple
    estimator: str
    status: str = "baked"

    @property
    def baked(self):
        return self.status == "baked" and len(self.receivers) > 0


class Plan:
    """The planned chains (:attr:`items`), the probe's estimates and what was left out."""

    def __init__(self, mode, threshold, items, notes, probe=None, probe_points=0, probe_seconds=0.0):
        self.mode = mode
        self.threshold = threshold
        self.items = items
        self.notes = notes  # plan-level reasons: chains left out before any per-receiver decision
        self.probe = probe  # EnergyLedger of the probe (auto), or None
        self.probe_points = probe_points
        self.probe_seconds = probe_seconds

    def baked_items(self):
        return [it for it in self.items if it.baked]

    def report(self, scene, receivers, ledger):
        """The ``plan`` section of report.json: mode, threshold, probe cost, notes, one row per
        (light, chain, caster objects, receiver) with estimated and baked shares and status,
        and a summary line per receiver."""
        names = scene.objects
        rows = []
        for r, rec in enumerate(receivers):
            est_total = self.probe.total(receiver=r) if self.probe is not None else 0.0
            baked_total = ledger.total(receiver=r)
            for it in self.items:
                keys = set()
                for src in (self.probe, ledger):
                    if src is not None:
                        keys |= {(k[2], k[3]) for k in src.power if k[0] == it.light and k[1] == it.chain and k[4] == r}
                if not keys:
                    keys = {None}
                for pair in sorted(keys, key=lambda p: (-1, -1) if p is None else p):
                    casters = (["*"] if pair is None else [names[pair[0]]] + ([names[pair[1]]] if pair[1] >= 0 else []))
                    match = dict(light=it.light, chain=it.chain, receiver=r)
                    if pair is not None:
                        match.update(obj1=pair[0], obj2=pair[1])
                    est = self.probe.total(**match) / est_total if self.probe is not None and est_total > 0 else None
                    got = ledger.total(**match) / baked_total if baked_total > 0 else 0.0
                    rows.append({"light": scene.lights[it.light].name, "chain": it.chain, "casters": casters,
                                 "receiver": rec.name, "estimator": it.estimator, "estimated_share": est,
                                 "baked_share": got if r in it.receivers and it.status == "baked" else 0.0,
                                 "status": self.status_for(it, r)})
        return {"mode": self.mode, "threshold": self.threshold, "probe": {"points": int(self.probe_points),
                                                                           "seconds": self.probe_seconds},
                "notes": list(self.notes), "chains": rows, "summary": self.summary(receivers, ledger)}

    def status_for(self, item, r):
        """"baked" or "skipped: <why>" for planned chain ``item`` on receiver index ``r``."""
        if item.status != "baked" or r in item.receivers:
            return item.status
        if self.probe is None:
            return "skipped"
        total = self.probe.total(receiver=r)
        share = self.probe.total(chain=item.chain, receiver=r) / total if total > 0 else 0.0
        if self.probe.total(light=item.light, chain=item.chain, receiver=r) == 0.0:
            return "skipped: the probe found no light path from this light to the receiver"
        return f"skipped: {100 * share:.2g} % of the receiver's caustic energy (< {100 * self.threshold:.2g} %)"

    def summary(self, receivers, ledger):
        """One line per receiver: the baked chains with their baked shares (largest first),
        then the skipped ones, e.g. ``Floor: TT 95.1 %, R 4.9 % (skipped: RR, RT, TR)``."""
        lines = []
        for r, rec in enumerate(receivers):
            total = ledger.total(receiver=r)
            baked, skipped = {}, []
            for it in self.items:
                if it.status == "baked" and r in it.receivers:
                    baked[it.chain] = ledger.total(chain=it.chain, receiver=r)  # every light's
            for it in self.items:
                if it.chain not in baked and it.chain not in skipped:
                    skipped.append(it.chain)
            parts = [f"{c} {100 * p / total:.1f} %" if total > 0 else c for c, p in sorted(baked.items(), key=lambda kv: -kv[1])]
            line = f"{rec.name}: " + (", ".join(parts) if parts else "no caustic")
            if skipped:
                line += f" (skipped: {', '.join(skipped)})"
            lines.append(line)
        return lines


def candidate_chains(settings):
    """The chains the settings allow: up to ``max_bounces()``, restricted to ``settings.chains``."""
    nb = settings.max_bounces()
    return [c for c in CHAINS if len(c) <= nb and (not settings.chains or c in settings.chains)]


def chain_casters(scene, chain, closed):
    """Global caster ids per vertex of ``chain`` (T leaves out the ``closed`` objects)."""
    verts = [np.flatnonzero(np.isin(scene.tri_role, CHAIN_ROLES[c])) for c in chain]
    if chain == "T" and closed:
        verts[0] = verts[0][~np.isin(scene.tri_object[verts[0]], list(closed))]
    return verts


def closed_refracting(scene):
    """The refracting objects that are closed solids (a single refraction into them ends inside)."""
    refracting = np.isin(scene.tri_role, CHAIN_ROLES["T"])
    return scene.closed_objects(np.unique(scene.tri_object[refracting]))


def structural_chains(scene, max_bounces=2, closed=None):
    """The chains of up to ``max_bounces`` that the scene's roles and topology allow (step 1);
    ``closed`` the scene's :func:`closed_refracting` when the caller has it."""
    closed = closed_refracting(scene) if closed is None else closed
    return [c for c in CHAINS if len(c) <= max_bounces and all(v.size for v in chain_casters(scene, c, closed))]


def make_plan(ctx):
    """The :class:`Plan` of a bake (see the module doc)."""
    steps = plan_steps(ctx)
    while True:
        try:
            next(steps)
        except StopIteration as done:
            return done.value


def plan_steps(ctx):
    """:func:`make_plan` in steps: a generator yielding ``(fraction, message)`` before each
    probe of a chain and returning the :class:`Plan`."""
    scene, settings = ctx.scene, ctx.settings
    t0 = time.perf_counter()
    notes, items = [], []
    if not settings.caustics:
        return Plan("none", settings.plan_threshold, items, notes)
    closed = closed_refracting(scene)
    inside = lights_inside(scene, sorted(closed))
    chains = candidate_chains(settings)
    for li, objs in sorted(inside.items()):
        light, names = scene.lights[li].name, ", ".join(repr(scene.objects[o]) for o in objs)
        notes.append(f"T: light {light!r} is inside the closed {names}: its T chain starts inside")
        reflects = np.any(np.isin(scene.tri_role[np.isin(scene.tri_object, objs)], CHAIN_ROLES["R"]))
        if "T" not in chains:
            ctx.warnings.append(f"light {light!r} is inside the closed refracting object {names}: its light leaves "
                                "through a refraction (chain T), which these settings leave out")
        elif reflects and "RT" not in chains:
            ctx.warnings.append(f"light {light!r} is inside the closed refracting object {names}: light reflected "
                                "inside before it leaves (chain RT) needs 2 bounces; set Max Bounces (--bounces) to 2 "
                                "or Auto")
    all_receivers = tuple(range(len(ctx.receivers)))
    for chain in chains:
        verts = chain_casters(scene, chain, closed)
        solids = sorted(scene.objects[o] for o in closed)  # closed_refracting: every one refracts
        if chain == "T" and solids:
            notes.append(f"T: {CLOSED_T} ({', '.join(solids)}); its caustic is TT")
        estimator = settings.estimator_for(chain)
        status = (chain_status(settings, chain) if estimator == "path-points" else None) or "baked"
        for li in range(len(scene.lights)):
            # A light inside a closed solid: its T chain starts inside, through that solid.
            lv = chain_casters(scene, chain, closed - set(inside[li])) if chain == "T" and li in inside else verts
            if any(v.size == 0 for v in lv):
                continue
            items.append(PlannedChain(chain, li, lv, all_receivers, estimator, status))
    if settings.bounces != "auto":
        return Plan(f"forced {settings.bounces}", settings.plan_threshold, items, notes)
    probe = EnergyLedger()
    points = 0
    tri_rec, tri_uv = ctx.receiver_of_triangle()
    centres = [sample_light(light, 1, settings.seed) for light in scene.lights]
    for k, it in enumerate(items):
        yield k / max(1, len(items)), f"planning: probe {it.chain} ({k + 1}/{len(items)})"
        if it.status == "baked":
            second = it.vertices[1] if len(it.vertices) > 1 else np.zeros(0, dtype=np.int64)
            budget = PROBE_POINTS_TWO_BOUNCE if len(it.chain) > 1 else PROBE_POINTS
            points += probe_chain(ctx, it.light, centres[it.light], it.chain, it.vertices[0], second, tri_rec, tri_uv, probe,
                                  budget)
    for it in items:
        if it.status != "baked":
            continue
        keep = []
        for r in all_receivers:
            total = probe.total(receiver=r)
            if total > 0 and probe.total(chain=it.chain, receiver=r) >= settings.plan_threshold * total \
                    and probe.total(light=it.light, chain=it.chain, receiver=r) > 0:
                keep.append(r)
        it.receivers = tuple(keep)
        if not keep:
            reached = [probe.total(chain=it.chain, receiver=r) / probe.total(receiver=r) for r in all_receivers
                       if probe.total(light=it.light, chain=it.chain, receiver=r) > 0]
            it.status = ("skipped: the probe found no light path to a receiver" if not reached else
                         f"skipped: at most {100 * max(reached):.2g} % of a receiver's caustic energy "
                         f"(< {100 * settings.plan_threshold:.2g} %)")
    return Plan("auto", settings.plan_threshold, items, notes, probe, points, time.perf_counter() - t0)
