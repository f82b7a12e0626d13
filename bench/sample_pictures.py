"""Pictures of the samples for the README: each sample scene baked with the operator's defaults
at 512², then rendered with Cycles (its own caustics off: the bake shows them) and with EEVEE.

    .venv/bin/python bench/sample_pictures.py [--samples water_pool,glass_sphere] [--size 480x360]

Writes ``docs/pictures/<sample>_cycles.png`` and ``<sample>_eevee.png`` and prints the seconds
each step took.  Baked into a temporary copy of each .blend: the samples are not changed.
"""

import argparse
import os
import shutil
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path[:0] = [ROOT]
SAMPLES = ("mirror_plane", "metal_ring", "glass_sphere", "glass_slab", "water_pool")


def picture(name, out_dir, width, height, tmp):
    import bpy

    path = os.path.join(tmp, name + ".blend")
    shutil.copy(os.path.join(ROOT, "sample_blends", name + ".blend"), path)
    bpy.ops.wm.open_mainfile(filepath=path)
    sc = bpy.context.scene
    sc.caustic_bake.resolution = 512
    t0 = time.perf_counter()
    if bpy.ops.caustics.bake(save_blend=False) != {"FINISHED"}:
        raise RuntimeError(f"{name}: the bake failed")
    times = {"bake": time.perf_counter() - t0}
    sc.render.resolution_x, sc.render.resolution_y = width, height
    sc.render.resolution_percentage = 100
    sc.render.image_settings.file_format = "PNG"
    for engine, label in (("CYCLES", "cycles"), ("BLENDER_EEVEE", "eevee")):
        sc.render.engine = engine
        if engine == "CYCLES":
            sc.cycles.device = "CPU"
            sc.cycles.samples = 32
            sc.cycles.use_denoising = False
            sc.cycles.caustics_reflective = False  # the baked caustics are shown instead
            sc.cycles.caustics_refractive = False
        else:
            sc.eevee.taa_render_samples = 16
        sc.render.filepath = os.path.join(out_dir, f"{name}_{label}.png")
        t0 = time.perf_counter()
        bpy.ops.render.render(write_still=True)
        times[label] = time.perf_counter() - t0
    return times


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", default=",".join(SAMPLES))
    ap.add_argument("--size", default="480x360")
    args = ap.parse_args(argv)
    width, height = (int(v) for v in args.size.split("x"))
    out_dir = os.path.join(ROOT, "docs", "pictures")
    os.makedirs(out_dir, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        os.environ.setdefault("BLENDER_USER_RESOURCES", os.path.join(tmp, "resources"))
        import addon

        addon.register()
        for name in args.samples.split(","):
            times = picture(name, out_dir, width, height, tmp)
            print(f"{name}: " + ", ".join(f"{k} {v:.1f} s" for k, v in times.items()), flush=True)


if __name__ == "__main__":
    main()
