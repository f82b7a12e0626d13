"""Temporal stability: frame-to-frame flicker of each bake method under a slowly moving light.

    .venv/bin/python bench/flicker.py [--scenes mirror_plane,water_pool] [--frames 5] [--res 48] [--no-write]

Frames f = 0 .. F-1 of a sample scene (sample_blends/*.blend via addon/bake/extract.py) with
every point / spot / area light moved by f x (2, 1, 0) mm and every sun turned by f x 0.05
degrees about the world z axis (slow motion: the caustic shifts by a fraction of a texel
per frame).  Each method bakes every frame with the same settings and seed (as
``--frames`` does in the CLI).

Definition.  With B_f the method's texture of frame f and R_f the reference's (path-points with the spoly
solver at ``--ref-samples`` supersamples, the same fixed supersample positions every frame, so its
change is the true change up to a near-constant aliasing error), and L the texels lit in
any reference frame (all receivers, RGB):

    flicker = sqrt( mean_{f, L} [ ((B_{f+1} - B_f) - (R_{f+1} - R_f))² ] ) / mean_{f, L} R_f

the RMS frame-to-frame change that the reference does not have, relative to the mean lit
irradiance (0 = changes exactly as the reference does).  ``motion`` is the same with B = 0
(the reference's own RMS change per frame, for scale).  Deterministic methods only flicker
where their error changes between frames (paths lost / found by seeded Newton, supersample
aliasing at moving edges); photon tracing with a fixed seed reuses its random numbers, so
its noise is partly coherent over frames ("photon"), while a new seed per frame
("photon-reseed") shows independent noise.

Methods by their estimator names (``--estimator``; path-points with its ``--solver``); the
default, forward-flux, must not flicker more than the reference moves (``motion``).

Writes the "flicker" section of BENCHMARKS.md.
"""

import argparse
import math
import os
import platform
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path[:0] = [ROOT, HERE]


def moved(scene, f):
    """A copy of ``scene`` whose lights moved to frame f (see the module docstring)."""
    import copy

    sc = copy.copy(scene)
    sc.lights = []
    a = math.radians(0.05 * f)
    rz = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
    for light in scene.lights:
        lt = copy.deepcopy(light)
        if lt.type == "sun":
            lt.direction = rz @ lt.direction
        else:
            lt.position = lt.position + f * np.array([0.002, 0.001, 0.0])
        sc.lights.append(lt)
    return sc


def flicker(frames, ref):
    """(flicker, motion) of a list of image stacks against the reference's (module docstring)."""
    R = np.array(ref)
    B = np.array(frames)
    lit = np.any(R > 0, axis=0)
    dB = np.diff(B, axis=0)[:, lit]
    dR = np.diff(R, axis=0)[:, lit]
    mean = R[:, lit].mean()
    return float(np.sqrt(np.mean((dB - dR) ** 2)) / mean), float(np.sqrt(np.mean(dR ** 2)) / mean)


def main(argv=None):
    from addon.bake.pipeline import BakeSettings, bake
    from chart import load_scene, stack

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="mirror_plane,water_pool")
    ap.add_argument("--frames", type=int, default=5)
    ap.add_argument("--res", type=int, default=48)
    ap.add_argument("--ref-samples", type=int, default=16)
    ap.add_argument("--photons", type=int, default=1_000_000)
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args(argv)
    methods = [("forward-flux", dict(estimator="forward-flux")),
               ("path-points/spoly", dict(estimator="path-points", solver="spoly", samples=4)),
               ("path-points/newton", dict(estimator="path-points", solver="newton", samples=4)),
               ("path-points/sms", dict(estimator="path-points", solver="sms", samples=4, sms_seeds=16)),
               ("path-points/curve", dict(estimator="path-points", solver="curve", samples=4)),
               ("photon", dict(estimator="photon", photons=args.photons)),
               ("photon-reseed", dict(estimator="photon", photons=args.photons))]
    lines = [f"Machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}; {args.res}² textures, "
             f"{args.frames} frames, lights moving (2, 1, 0) mm / sun turning 0.05° per frame; reference path-points/spoly at "
             f"{args.ref_samples} supersamples; date {time.strftime('%Y-%m-%d')}.", "",
             "flicker = RMS over lit texels and frame pairs of ((B_{f+1} - B_f) - (R_{f+1} - R_f)) / mean lit R "
             "(the frame-to-frame change the reference does not have; definition in `bench/flicker.py`); "
             "motion = the reference's own RMS change per frame / mean lit R.", "",
             "| scene | motion | method | knob | flicker | seconds / frame | note |", "|---|---|---|---|---|---|---|"]
    for name in args.scenes.split(","):
        scene, _ = load_scene(name, args.res)
        frames = [moved(scene, f) for f in range(args.frames)]
        base = dict(resolution=args.res, margin=0, seed=1)
        ref = [stack(bake(sc, BakeSettings(estimator="path-points", solver="spoly", samples=args.ref_samples, **base)))
               for sc in frames]
        for label, kw in methods:
            imgs, secs, note = [], 0.0, ""
            for f, sc in enumerate(frames):
                s = BakeSettings(**{**base, **kw, **({"seed": 1 + f} if label == "photon-reseed" else {})})
                t0 = time.perf_counter()
                out = bake(sc, s)
                secs += time.perf_counter() - t0
                imgs.append(stack(out))
                skipped = [c["chain"] for c in out.report["chains"] if c["status"] != "baked"]
                note = ("skipped " + ",".join(skipped)) if skipped else ""
            if all(not np.any(i) for i in imgs):
                lines.append(f"| {name} | | {label} | | | | nothing baked ({note}) |")
                continue
            fl, motion = flicker(imgs, ref)
            knob = (f"{kw['photons']:,} photons" if kw["estimator"] == "photon" else
                    "depth 6 (default)" if kw["estimator"] == "forward-flux" else
                    f"{kw['samples']} spp, {kw['sms_seeds']} seeds" if kw.get("solver") == "sms" else f"{kw['samples']} spp")
            lines.append(f"| {name} | {motion:.2e} | {label} | {knob} | {fl:.2e} | {secs / len(frames):.2f} | {note} |")
            print(lines[-1], flush=True)
    body = "\n".join(lines)
    print(body)
    if not args.no_write:
        from solver import write_section

        write_section(os.path.join(ROOT, "BENCHMARKS.md"), "flicker", "Temporal stability: flicker per method (`bench/flicker.py`)", body)


if __name__ == "__main__":
    main()
