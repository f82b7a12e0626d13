"""RNA properties: scene bake settings (``scene.caustic_bake``) and per-object roles
(``object.caustic_bake``).  Thin: plain settings, turned into a BakeSettings by
:func:`bake_settings`; no maths here.

The object roles are read by ``addon.bake.extract``; an object whose group says "auto" falls
back to the custom properties ``caustic_role`` / ``caustic_receiver`` / ``caustic_resolution``
(scripts and older files keep working).
"""

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

# addon.bake.settings.ESTIMATORS and SOLVERS (what each computes: that module's doc).
ESTIMATOR_ITEMS = (
    ("forward-flux", "Forward Flux", "Caster triangles traced forward in sub-triangles whose flux is spread over their "
     "images: texel-averaged irradiance, noise-free, every chain (default)"),
    ("path-points", "Exact Paths", "Every exact specular path at every texel supersample, found by the solver below"),
    ("path-seeded", "Seeded Paths", "Exact two-bounce paths at the supersamples by Newton from forward-image seeds "
     "(one-bounce chains: exact paths)"),
    ("photon", "Photon Tracing", "Light tracing into the texture (texel-averaged, noisy); every chain"),
)
SOLVER_ITEMS = (
    ("spoly", "Specular Polynomials", "Deterministic: every specular path of each triangle tuple (Fan et al. 2024); every chain"),
    ("newton", "Newton (MNEE)", "Newton from one or two deterministic seeds per tuple; misses paths. Chains R and T"),
    ("sms", "Specular Manifold Sampling", "Newton from random seeds per tuple (biased SMS); misses paths. Chains R and T"),
    ("curve", "Curve Walk (MNEE)", "Dimension-reduction MNEE: walks the coplanarity curve. Chain T only"),
)
BOUNCE_ITEMS = (
    ("auto", "Auto", "Bake the chains of up to two bounces that carry at least the threshold's share of a receiver's "
     "caustic energy (estimated by a quick forward probe); the rest is skipped and listed after the bake"),
    ("1", "1", "Every one-bounce chain the materials allow (R, T)"),
    ("2", "2", "Every chain of up to two bounces the materials allow (R, T, RR, RT, TR, TT)"),
)
DEVICE_ITEMS = (
    ("numba", "CPU", "Solve on the CPU with Numba"),
    ("opencl", "OpenCL",
     "Use the first OpenCL device with double precision: Forward Flux refines, traces and splats there "
     "(the same texture); Exact Paths solves one- and two-bounce chains there; no OpenCL device / "
     "pyopencl falls back to the CPU with a warning"),
)
QUALITY_ITEMS = (
    ("PREVIEW", "Preview", "Fast look: 1 sample per texel, 1 light sample (the fields below are ignored)"),
    ("FINAL", "Final", "The samples and light samples set below"),
)
FRAME_RANGE_ITEMS = (
    ("CURRENT", "Current Frame", "Bake the current frame: one texture per receiver"),
    ("SCENE", "Scene Frame Range", "Bake every frame of the scene's frame range: an EXR sequence per receiver in the "
     "output folder, shown as an image sequence (each frame's caustic at its frame)"),
)
ROLE_ITEMS = (
    ("auto", "Auto", "From the material: glass = reflect + refract, metal / glossy = reflect, "
     "transmissive = refract, anything else casts no caustics"),
    ("reflect", "Reflect", "A mirror (tinted by the material colour)"),
    ("refract", "Refract", "A single refracting interface (water surface)"),
    ("both", "Reflect & Refract", "Glass: Fresnel-weighted reflection and refraction"),
    ("none", "None", "Casts no caustics (still blocks light)"),
)
RECEIVER_ITEMS = (
    ("auto", "Auto", "A receiver if it has a UV map and casts no caustics"),
    ("yes", "Yes", "Always a receiver (needs a UV map)"),
    ("no", "No", "Never a receiver"),
)


class CausticBakeSceneSettings(bpy.types.PropertyGroup):
    resolution: IntProperty(name="Resolution", description="Texels per side of each receiver's caustic texture "
                            "(unless the object overrides it)", default=256, min=8, max=16384, soft_max=4096)
    samples: IntProperty(name="Samples per Texel", description="Supersamples per texel (rounded up to a square grid)",
                         default=4, min=1, max=256, soft_max=64)
    light_samples: IntProperty(name="Light Samples", description="Samples over the size of sized lights "
                               "(soft caustics); 1 treats every light as a point", default=1, min=1, max=4096, soft_max=64)
    bounces: EnumProperty(name="Max Bounces", items=BOUNCE_ITEMS, default="auto")
    plan_threshold: FloatProperty(name="Skip Below", description="Auto bounces: skip chains that carry less than this "
                                  "share of a receiver's caustic energy", default=0.005, min=0.0, max=0.5, soft_max=0.1,
                                  precision=3, step=0.1, subtype="FACTOR")
    quality: EnumProperty(name="Quality", items=QUALITY_ITEMS, default="FINAL")
    estimator: EnumProperty(name="Estimator", items=ESTIMATOR_ITEMS, default="forward-flux")
    solver: EnumProperty(name="Solver", items=SOLVER_ITEMS, default="spoly")
    sms_seeds: IntProperty(name="Seeds per Tuple", description="Specular Manifold Sampling: random Newton seeds per tuple",
                           default=16, min=1, max=4096, soft_max=256)
    photons: IntProperty(name="Photons", description="Photon Tracing: photons traced over all lights",
                         default=1_000_000, min=1, soft_max=100_000_000)
    device: EnumProperty(name="Device", items=DEVICE_ITEMS, default="numba")
    seed: IntProperty(name="Seed", description="Seed of the supersample jitter and light samples", default=0, min=0)
    margin: IntProperty(name="Margin", description="Texels of padding over UV seams", default=16, min=0, max=256)
    memory_budget: FloatProperty(name="Memory Budget", description="Memory (GB) the bake's textures may take; a "
                                 "bake that needs more stops before it starts. 0: half the memory available",
                                 default=0.0, min=0.0, soft_max=256.0, precision=1, unit="NONE")
    output_dir: StringProperty(name="Output Folder", description="Where the EXR textures are written "
                               "(// = next to the .blend); an unsaved file packs them", default="//caustics/",
                               subtype="DIR_PATH")
    pack: BoolProperty(name="Pack Textures", description="Pack the baked textures into the .blend (one frame; "
                       "an image sequence stays in the output folder)", default=False)
    frame_range: EnumProperty(name="Frames", items=FRAME_RANGE_ITEMS, default="CURRENT",
                              description="Which frames the bake bakes")
    last_plan: StringProperty(name="Last Plan", description="What the last bake modelled: per receiver, the chains "
                              "baked with their share of its caustic energy, and the chains skipped", default="")


class CausticBakeObjectSettings(bpy.types.PropertyGroup):
    role: EnumProperty(name="Caster", items=ROLE_ITEMS, default="auto",
                       description="How this object casts caustics")
    receiver: EnumProperty(name="Receiver", items=RECEIVER_ITEMS, default="auto",
                           description="Whether this object receives a caustic texture")
    resolution: IntProperty(name="Resolution", description="Texels per side of this receiver's texture "
                            "(0: the scene's setting)", default=0, min=0, max=16384, soft_max=4096)


classes = (CausticBakeSceneSettings, CausticBakeObjectSettings)


def register_properties():
    bpy.types.Scene.caustic_bake = PointerProperty(type=CausticBakeSceneSettings)
    bpy.types.Object.caustic_bake = PointerProperty(type=CausticBakeObjectSettings)


def unregister_properties():
    del bpy.types.Object.caustic_bake
    del bpy.types.Scene.caustic_bake


def bake_frames(props, scene):
    """The frames a bake of ``scene`` with settings ``props`` bakes as a sequence: None for the
    current frame (one texture per receiver), else the scene's frame range, start to end."""
    if props.frame_range != "SCENE":
        return None
    return list(range(int(scene.frame_start), int(scene.frame_end) + 1))


def bake_settings(props):
    """The BakeSettings for the scene settings ``props`` (a CausticBakeSceneSettings, or
    anything with the same attributes).  ``resolution`` stays 0: every receiver brings its own
    (its override, or the scene's resolution given to extract_scene)."""
    from ..bake.settings import BakeSettings

    preview = props.quality == "PREVIEW"
    bounces = str(props.bounces)
    return BakeSettings(
        resolution=0,
        samples=1 if preview else int(props.samples),
        light_samples=1 if preview else int(props.light_samples),
        bounces=bounces if bounces == "auto" else int(bounces),
        plan_threshold=float(props.plan_threshold),
        estimator=str(props.estimator),
        solver=str(props.solver),
        seed=int(props.seed),
        margin=int(props.margin),
        device=str(props.device),
        sms_seeds=int(props.sms_seeds),
        photons=int(props.photons),
        memory_budget=1e9 * float(getattr(props, "memory_budget", 0.0)),
    )
