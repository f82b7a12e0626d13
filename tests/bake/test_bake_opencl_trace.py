"""Forward-flux with its points traced on OpenCL (``addon/solver/opencl/trace.cl``, PoCL on the
CPU in CI): the kernel is trace_chain_points step for step, so the traced points and the baked
textures are Numba's bit for bit, for one-vertex (R, T) and two-vertex (TT) chains, rays that miss
a flat receiver extended onto its plane included; and the two-bounce path-points bake with its
solve on the device equals the Numba bake to the paths' polish."""

import numpy as np
import pytest

from addon.bake.estimators.forward_images import _bvh_args, scene_arrays
from addon.bake.pipeline import BakeSettings, bake
from addon.bake.scene import Light
from addon.solver.estimators.forward_image import trace_chain_points
from addon.solver.geometry.bvh import build_bvh
from fixtures.bake_scenes import glass_sphere_scene, ring_scene, wavy_sheet
from fixtures.opencl import opencl_device_or_skip


def _trace_both(index, sc, chain, first, second, n=20000, seed=5):
    """Random points on the first casters, lit from a point light, traced by both back ends."""
    from addon.solver.opencl.tracing import OpenCLPointTracer

    rng = np.random.default_rng(seed)
    bvh = build_bvh(sc.tri_p)
    tri_rec, tri_uv, second_ok, planes = scene_arrays(sc, sc.receivers, np.asarray(second, dtype=np.int64))
    emit = np.asarray(first, dtype=np.int64)
    x0 = np.tile(np.asarray(sc.lights[0].position, dtype=np.float64), (emit.size, 1))
    e = rng.integers(0, emit.size, n)
    u = rng.uniform(0, 1, n)
    v = rng.uniform(0, 1, n) * (1 - u)
    args = (len(chain), chain[0] == "T", chain[-1] == "T", second_ok, tri_rec, tri_uv, sc.tri_p, sc.tri_n,
            sc.tri_ior, sc.tri_role.astype(np.int64))
    outs = [(np.empty(n, dtype=np.int64), np.empty(n, dtype=np.int64), np.empty((n, 2)), np.empty(n)) for _ in range(2)]
    trace_chain_points(e, u, v, x0, emit, *args, *_bvh_args(bvh), 1e-6, planes, *outs[0])
    OpenCLPointTracer(index, *args, _bvh_args(bvh), x0, emit, 1e-6, planes).trace(e, u, v, *outs[1])
    return outs, planes


@pytest.mark.opencl
@pytest.mark.parametrize("case", ["ring R", "sphere TT", "sheet T"])
def test_points_traced_on_opencl_are_numbas(case):
    index = opencl_device_or_skip()
    if case == "ring R":
        sc = ring_scene(resolution=32)
        chain = "R"
    elif case == "sphere TT":
        sc = glass_sphere_scene(resolution=32)
        chain = "TT"
    else:
        sc = wavy_sheet(0, 32, n=40)
        chain = "T"
    casters = np.flatnonzero(sc.tri_role > 0)
    (numba, ocl), planes = _trace_both(index, sc, chain, casters, casters)
    landed = numba[1] >= 0
    assert landed.mean() > 0.2, "the case must land a fair share of its points"
    if case == "sheet T":  # the floor is flat: rays that miss it land on its plane, extended, on both
        assert planes.shape[0] == 1
        outside = landed & ((numba[2] < 0) | (numba[2] > 1)).any(axis=1)
        assert outside.sum() > 100
    for a, b in zip(numba, ocl):
        np.testing.assert_array_equal(a, b)


@pytest.mark.opencl
def test_forward_flux_bake_traced_on_opencl_equals_numba():
    """The default bake with device="opencl": the same texture bit for bit, and the report
    says where the points were traced."""
    opencl_device_or_skip()
    sc = glass_sphere_scene(resolution=48)
    cpu = bake(sc, BakeSettings(resolution=48))
    ocl = bake(sc, BakeSettings(resolution=48, device="opencl"))
    assert cpu.report["devices"]["forward-flux"] == "cpu (numba)"
    assert ocl.report["devices"]["forward-flux"].startswith("opencl: ")
    for k in cpu.images:
        assert cpu.images[k].max() > 0
        np.testing.assert_array_equal(ocl.images[k], cpu.images[k])


@pytest.mark.opencl
def test_the_scene_goes_to_the_device_once_per_bvh():
    """Passes and caster chunks of one bake share the scene's upload (keyed by the BVH's arrays,
    released with them); another BVH gets its own; new triangle arrays with the same BVH are
    uploaded again."""
    import gc

    from addon.solver.opencl import tracing

    index = opencl_device_or_skip()
    sc = ring_scene(resolution=16)
    bvh = _bvh_args(build_bvh(sc.tri_p))
    args = (sc.tri_p, sc.tri_n, sc.tri_ior, sc.tri_role.astype(np.int64))
    first = tracing.device_scene(index, *args, bvh)
    assert tracing.device_scene(index, *args, bvh) is first
    moved = (sc.tri_p + 0.0, *args[1:])
    assert tracing.device_scene(index, *moved, bvh) is not first
    other = _bvh_args(build_bvh(sc.tri_p))
    assert tracing.device_scene(index, *args, other) is not first
    held = len(tracing._kept)
    del other
    gc.collect()
    assert len(tracing._kept) == held - 1


@pytest.mark.opencl
@pytest.mark.slow  # two TT path-points bakes (the first compiles the two-bounce solver): ~1 min
def test_two_bounce_path_points_bake_on_opencl_equals_numba():
    """The exact two-bounce estimator (path-points, TT through a glass sphere) with
    device="opencl": the staged two-bounce solve on the device (systems, scan, polish) finds the
    same paths as Numba, so the texture equals the CPU bake to the paths' polish (~1e-15), and
    the report says where the paths were solved."""
    opencl_device_or_skip()
    sc = glass_sphere_scene(resolution=32, segments=16, rings=8)
    base = dict(samples=1, bounces=2, chains=("TT",), margin=0, seed=1, resolution=32, two_bounce="exact")
    cpu = bake(sc, BakeSettings(**base))
    ocl = bake(sc, BakeSettings(**base, device="opencl"))
    assert ocl.report["devices"]["path-points"].startswith("opencl: ")
    assert cpu.report["counts"]["paths_visible"] == ocl.report["counts"]["paths_visible"] > 100
    a, b = cpu.raw["floor"], ocl.raw["floor"]
    assert a.max() > 0
    np.testing.assert_allclose(b, a, rtol=0, atol=1e-12 * a.max())


@pytest.mark.opencl
@pytest.mark.parametrize("case", ["sphere", "sphere seeded", "sheet", "sheet sun", "ring"])
def test_landed_refinement_on_opencl_returns_numbas_records(monkeypatch, case):
    """refine.cl (the landed refinement, one work-item per emitter) returns refine_kernel.py's
    records: the same final and handed-back sub-triangles, every field bit for bit, in the same
    order, and the bake the same texture; here with launches of a few emitters, record lists
    that start empty (each launch overflows and runs again) and a shared-point table of 16 slots
    (points traced again once it is half full).  "seeded": the path-seeded estimator's images
    (straight to the margin only, no density test)."""
    from addon.solver.estimators import refine_kernel
    from addon.solver.opencl import tracing

    opencl_device_or_skip()
    settings = {"two_bounce": "seeded"} if case == "sphere seeded" else {}
    if case.startswith("sphere"):  # TT, TR, ...: lost points, borders, sub-triangles handed back
        sc, res = glass_sphere_scene(resolution=48), 48
    elif case == "ring":
        sc, res = ring_scene(resolution=48), 48
    else:  # the floor extended onto its plane: images beyond its edge dropped in the kernel
        light = Light("Sun", "sun", (1.0, 1.0, 1.0), 3.0, direction=(0.2, -0.1, -1.0)) if case == "sheet sun" else None
        sc, res = wavy_sheet(4, 64, n=30, light=light), 64
    monkeypatch.setattr(tracing, "REFINE_TABLE_BITS", 4)
    monkeypatch.setattr(tracing, "REFINE_TABLE_BYTES", 40 * 16 * 37)  # 37 emitters a launch
    monkeypatch.setattr(tracing, "REFINE_RECORDS_PER_EMITTER", (0, 0))
    calls = []
    real = refine_kernel.refine_landed

    def spy(*args, **kw):
        out = real(*args, **kw)
        calls.append((kw.get("device") is not None, out))
        return out

    monkeypatch.setattr(refine_kernel, "refine_landed", spy)
    cpu = bake(sc, BakeSettings(resolution=res, **settings))
    numba_calls = [c[1] for c in calls]
    del calls[:]
    ocl = bake(sc, BakeSettings(resolution=res, device="opencl", **settings))
    assert all(on_device for on_device, _ in calls) and len(calls) == len(numba_calls) > 0
    if settings:  # the two-bounce chains' path-seeded images were refined and traced on the device
        assert ocl.report["devices"]["path-seeded"].endswith("(refinement, tracing of the forward images; Newton on the CPU)")
    finals = hands = 0
    for a, (_, b) in zip(numba_calls, calls):
        for k in a:
            if k != "traced":
                np.testing.assert_array_equal(a[k], b[k], err_msg=k)
        finals += a["emitter"].size
        hands += a["hand_emitter"].size
    # the ring's sub-triangles at this size all reach across its shadow's edge: handed back
    assert (finals > 500 or case == "ring") and (hands > 50 or case.startswith("sheet")), (finals, hands)
    for k in cpu.images:
        assert cpu.images[k].max() > 0
        np.testing.assert_array_equal(ocl.images[k], cpu.images[k])


@pytest.mark.opencl
@pytest.mark.parametrize("part", ["refine", "splat"])
def test_forward_flux_kernel_that_does_not_build_warns_and_uses_numba(monkeypatch, tmp_path, part):
    """A driver that rejects refine.cl or splat.cl (here a source with a syntax error) is no crash:
    the bake warns with the build log, does that part on Numba and bakes the same texture."""
    from addon.solver.opencl import splatting, tracing

    opencl_device_or_skip()
    broken = tmp_path / f"{part}.cl"
    broken.write_text("__kernel void nothing(__global double *x) { x[0] = ; }\n")
    if part == "refine":
        monkeypatch.setattr(tracing, "_REFINE_FILE", str(broken))
    else:
        monkeypatch.setattr(splatting, "_KERNEL_FILE", str(broken))
    sc = wavy_sheet(4, 48, n=20)
    cpu = bake(sc, BakeSettings(resolution=48))
    doing = {"refine": "refining", "splat": "splatting"}[part]
    with pytest.warns(RuntimeWarning, match=f"(?s)OpenCL unavailable.*{part}.cl does not build.*expected expression.*{doing} on Numba"):
        ocl = bake(sc, BakeSettings(resolution=48, device="opencl"))
    label = ocl.report["devices"]["forward-flux"]
    assert label.startswith("opencl: ") and label.endswith("(tracing, splat)" if part == "refine" else "(refinement, tracing)")
    for k in cpu.images:
        assert cpu.images[k].max() > 0
        np.testing.assert_array_equal(ocl.images[k], cpu.images[k])


@pytest.mark.opencl
def test_forward_flux_gpu_shapes_bake_numbas_texture(monkeypatch):
    """The launch shapes a GPU gets (chunks of GPU_CHUNK_SCALE times the casters, all of a
    chunk's emitters in one refine launch with the GPU table budget, a splat band per row, small
    work-groups), run here on PoCL taken for a GPU: the same texture bit for bit."""
    from addon.solver.opencl import backend

    from addon.bake.estimators import forward_flux

    index = opencl_device_or_skip()
    d = backend._context(index)
    sc = wavy_sheet(3, 64, n=30)
    monkeypatch.setattr(forward_flux, "CASTER_CHUNK", 100)
    cpu = bake(sc, BakeSettings(resolution=64))
    monkeypatch.setattr(d, "is_cpu", False)
    assert d.small_work_group(d.kernel(backend._SCAN_FILE, "scan_blocks")) <= backend.SMALL_WORK_GROUP
    ocl = bake(sc, BakeSettings(resolution=64, device=f"opencl:{index}"))
    assert ocl.report["devices"]["forward-flux"].endswith("(refinement, tracing, splat)")
    assert backend.device_is_gpu(f"opencl:{index}") and not backend.device_is_gpu("numba")
    passes = [r["estimators"]["forward-flux"]["passes"][0] for r in (cpu.report, ocl.report)]
    casters = passes[0]["emitters"]
    assert casters > 1000 and passes[0]["chunks"] == -(-casters // 100)
    assert passes[1]["chunks"] == -(-casters // (100 * forward_flux.GPU_CHUNK_SCALE))
    for k in cpu.images:
        assert cpu.images[k].max() > 0
        np.testing.assert_array_equal(ocl.images[k], cpu.images[k])


@pytest.mark.opencl
def test_forward_flux_on_opencl_two_receivers_of_other_sizes():
    """A glass sphere over two floors of different, non-square texture sizes (each its own
    device texture, its sub-triangles splatted onto it): Numba's textures bit for bit."""
    from addon.bake.scene import build_scene
    from fixtures.bake_scenes import floor, uv_sphere

    opencl_device_or_skip()
    P, N = uv_sphere(24, 12)
    left = floor(half=0.8, cx=-0.8, name="left")
    right = floor(half=0.8, cx=0.8, name="right")
    left["resolution"], right["resolution"] = (40, 24), (17, 33)
    sc = build_scene([left, right, dict(name="sphere", tri_p=P, tri_n=N, role="both", ior=1.5)],
                     [Light("Point", "point", (1.0, 1.0, 1.0), 80.0, position=(0.3, 0.1, 3.0))])
    cpu = bake(sc, BakeSettings())  # resolution 0: each receiver's own
    ocl = bake(sc, BakeSettings(device="opencl"))
    assert {k: v.shape for k, v in ocl.images.items()} == {"left": (24, 40, 3), "right": (33, 17, 3)}
    for k in cpu.images:
        assert cpu.images[k].max() > 0
        np.testing.assert_array_equal(ocl.images[k], cpu.images[k])


@pytest.mark.opencl
@pytest.mark.parametrize("trouble", ["no such device", "no room on the device", "no room to refine"])
def test_forward_flux_device_trouble_warns_and_bakes_numbas_texture(monkeypatch, trouble):
    """A device that does not exist, or one without room for the pass's flux textures (here an
    allocation failure), is no crash: the bake warns and does that part on Numba, the same
    texture."""
    import pyopencl as cl

    from addon.solver.opencl import splatting

    index = opencl_device_or_skip()
    sc = wavy_sheet(4, 48, n=20)
    cpu = bake(sc, BakeSettings(resolution=48))
    if trouble == "no such device":
        device, expected = "opencl:99", "(?s)OpenCL unavailable.*does not exist.*splatting on Numba"
    elif trouble == "no room on the device":
        def full(d, buf, nbytes):
            raise cl.MemoryError("clEnqueueFillBuffer failed: MEM_OBJECT_ALLOCATION_FAILURE")

        monkeypatch.setattr(splatting, "_fill_zero", full)
        device, expected = f"opencl:{index}", "(?s)no room for the flux textures.*ALLOCATION_FAILURE.*splatting on Numba"
    else:
        from addon.solver.opencl import backend

        d = backend._context(index)
        real = d.buffer

        def buffer(role, nbytes):
            if role == "refine_key":
                raise cl.MemoryError("clCreateBuffer failed: MEM_OBJECT_ALLOCATION_FAILURE")
            return real(role, nbytes)

        monkeypatch.setattr(d, "buffer", buffer)
        device, expected = f"opencl:{index}", "(?s)refine_emitters failed.*ALLOCATION_FAILURE.*refining on Numba"
    with pytest.warns(RuntimeWarning, match=expected):
        got = bake(sc, BakeSettings(resolution=48, device=device))
    label = got.report["devices"]["forward-flux"]
    assert label == {"no such device": "cpu (numba)"}.get(trouble, label)
    if trouble != "no such device":  # the report says what ran on the device
        assert label.endswith("(tracing, splat)" if trouble == "no room to refine" else "(refinement, tracing)")
    for k in cpu.images:
        assert cpu.images[k].max() > 0
        np.testing.assert_array_equal(got.images[k], cpu.images[k])
