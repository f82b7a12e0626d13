"""The ``forward-flux`` estimator's two forms (addon/bake/estimators/forward_flux.py): the default
(per-sub-triangle terms in Numba kernels, addon/solver/estimators/flux_kernel.py, and coarse
refinement levels above the first grid) against the numpy reference form
(``ForwardFlux.reference``), on hand-built scenes; determinism bit for bit."""

import numpy as np
import pytest

from addon.bake.estimators import forward_flux as FF
from addon.bake.estimators import forward_images as FI
from addon.bake.estimators.forward_flux import ForwardFlux
from addon.bake.pipeline import BakeSettings, bake, texel_areas
from addon.bake.scene import Light
from fixtures.bake_scenes import mirror_scene, wavy_sheet
from fixtures.checks import rel_mse


def _bake(sc, res, reference=False):
    old = ForwardFlux.reference
    ForwardFlux.reference = reference
    try:
        out = bake(sc, BakeSettings(resolution=res, margin=0))
    finally:
        ForwardFlux.reference = old
    img = np.concatenate([out.raw[k].ravel() for k in sorted(out.raw)])
    return img, out.report["estimators"]["forward-flux"]


def test_kernels_compute_the_reference_terms(monkeypatch):
    """Without coarse levels the kernel form refines the same sub-triangles and computes the
    same power, densities and splat (the kernels themselves: tests/solver/test_solver_flux_kernel.py);
    only the centroid's transport factor, interpolated instead of traced, differs, by far less
    than the estimate's own error."""
    sc = wavy_sheet(3, 64, n=16)
    ref, ref_rep = _bake(sc, 64, reference=True)
    monkeypatch.setattr(FF, "IMAGE_COARSE", 0)
    new, new_rep = _bake(sc, 64)
    print(f"relMSE {rel_mse(new, ref):.2e}, power ratio {new.sum() / ref.sum() - 1:.2e}")
    assert new_rep["sub_triangles"] == ref_rep["sub_triangles"] > 1000
    assert ref.max() > 0
    assert rel_mse(new, ref) <= 1e-10
    assert abs(new.sum() / ref.sum() - 1.0) <= 1e-6


@pytest.mark.parametrize("n, res, fewer", [(16, 64, 0.4), (60, 128, 0.2)])
def test_coarse_levels_stay_converged(n, res, fewer, monkeypatch):
    """Coarse levels only stop small straight images with a linear density early: on sheets
    whose triangles' images are a few texels (n = 60) or larger (n = 16) the texture stays
    within relMSE 3e-5 of a converged bake (an 8 x 8 first grid, no coarse levels), as the
    reference form's is (within 1e-6), with at most ``fewer`` of its sub-triangles, and the
    same power."""
    sc = wavy_sheet(5, res, n=n)
    ref, ref_rep = _bake(sc, res, reference=True)
    new, new_rep = _bake(sc, res)
    monkeypatch.setattr(FI, "IMAGE_GRID", 8)
    monkeypatch.setattr(FF, "IMAGE_COARSE", 0)
    fine, fine_rep = _bake(sc, res)
    print(f"n {n} res {res}: sub-triangles {new_rep['sub_triangles']:,} (reference {ref_rep['sub_triangles']:,}, converged "
          f"{fine_rep['sub_triangles']:,}), relMSE to converged {rel_mse(new, fine):.2e} (reference {rel_mse(ref, fine):.2e}), "
          f"power ratio {new.sum() / ref.sum() - 1:.2e}")
    assert fine_rep["sub_triangles"] > 2 * ref_rep["sub_triangles"]
    assert rel_mse(ref, fine) <= 1e-6
    assert new_rep["sub_triangles"] <= fewer * ref_rep["sub_triangles"]
    assert rel_mse(new, fine) <= 3e-5
    assert abs(new.sum() / ref.sum() - 1.0) <= 1e-4


def test_mirror_matches_the_reference():
    """A 2-triangle mirror (a large image per caster): the same texture as the reference form."""
    sc, _ = mirror_scene(resolution=64)
    ref, _ = _bake(sc, 64, reference=True)
    new, _ = _bake(sc, 64)
    assert ref.max() > 0 and rel_mse(new, ref) <= 1e-20


def test_textures_are_deterministic():
    """The same scene baked twice gives the same texture bit for bit (threads included)."""
    sc = wavy_sheet(2, 64, n=30)
    a, _ = _bake(sc, 64)
    b, _ = _bake(sc, 64)
    np.testing.assert_array_equal(a, b)


def test_texel_areas_are_kept_for_a_receiver_that_does_not_move():
    """texel_areas is a function of the receiver alone: a second call (another frame of the
    same floor) returns the kept result, equal to a fresh measurement; a moved receiver is
    measured again."""
    from addon.bake.pipeline import _texel_areas

    a = wavy_sheet(1, 32, n=4)
    b = wavy_sheet(2, 32, n=4)
    ra, rb = a.receivers[0], b.receivers[0]
    first = texel_areas(a, ra)
    again = texel_areas(b, rb)
    assert again is first and not again.flags.writeable
    np.testing.assert_array_equal(again, _texel_areas(b, rb, 16, 1 << 20))
    b.tri_p[rb.tri_index] *= 1.5
    moved = texel_areas(b, rb)
    assert moved is not first and np.isclose(moved.sum(), 2.25 * first.sum())


def test_supersample_counts_are_kept_when_no_estimator_reads_the_samples():
    """forward-flux alone reads only how many supersamples each texel has: the second frame
    of a receiver that does not move skips the rasterisation and gives the same coverage and
    texture as a bake with the samples rasterised (direct light on: the samples are read)."""
    a = wavy_sheet(1, 48, n=12)
    b = wavy_sheet(2, 48, n=12)
    bake(a, BakeSettings(resolution=48, margin=0))
    second = bake(b, BakeSettings(resolution=48, margin=0))
    assert "raster" not in second.report["timings"]
    direct = bake(b, BakeSettings(resolution=48, margin=0, direct=True))
    assert direct.report["timings"].get("raster", 0.0) > 0.0
    np.testing.assert_array_equal(second.coverage["Floor"], direct.coverage["Floor"])
    caustic_only = bake(b, BakeSettings(resolution=48, margin=0, seed=7))  # another seed: counted afresh
    assert caustic_only.report["timings"].get("raster", 0.0) > 0.0


@pytest.mark.parametrize("case", ["sheet", "mirror", "sheet-sun"])
def test_landed_kernel_refines_as_the_numpy_levels(monkeypatch, case):
    """The kernel that refines the sub-triangles landing on one receiver (addon/solver/estimators/
    refine_kernel.py) decides as the level-by-level numpy refinement it replaces: the same
    number of final sub-triangles per level, the same partly landed / border / dropped counts
    and the same texture (the sub-triangles come in another order: the splat's sums differ in
    the last bits).  The sheet's images cross the floor's edge (extended onto the floor's plane:
    images beyond it dropped); the mirror's too, cut by bisection there (the floor not extended:
    borders, lost sub-triangles handed back to the numpy levels)."""
    if case == "mirror":
        monkeypatch.setattr(FI, "EXTEND_FLAT_RECEIVERS", False)
        sc, _ = mirror_scene(resolution=64)
    elif case == "sheet":
        sc = wavy_sheet(4, 96, n=40)
    else:  # parallel light: a uniform flux per area of each caster
        sc = wavy_sheet(4, 96, n=40, light=Light("Sun", "sun", (1.0, 1.0, 1.0), 3.0, direction=(0.2, -0.1, -1.0)))
    from addon.solver.estimators import refine_kernel

    monkeypatch.setattr(refine_kernel, "MESH_SHARED", False)  # every point traced from its own emitter, as numpy
    monkeypatch.setattr(FI, "LANDED_KERNEL", False)
    ref, ref_rep = _bake(sc, 96)
    monkeypatch.setattr(FI, "LANDED_KERNEL", True)
    new, new_rep = _bake(sc, 96)
    for a, b in zip(ref_rep["passes"], new_rep["passes"]):
        for k in ("sub_triangles", "final_per_depth", "partial", "border", "dropped"):
            assert a[k] == b[k], (k, a[k], b[k])
    assert new_rep["sub_triangles"] > 1000 and ref.max() > 0
    assert rel_mse(new, ref) <= 1e-20


def test_next_frame_refits_the_bvh_and_bakes_as_a_fresh_tree(monkeypatch):
    """An animation's next frame refits the last frame's BVH (pipeline.scene_bvh) and bakes the
    same texture bit for bit as with a tree built for it (closest hits do not depend on the
    tree's shape: tests/bake/test_bake_bvh.py)."""
    from addon.bake import pipeline

    monkeypatch.setattr(pipeline, "_BVH_KEPT", {})
    bake(wavy_sheet(1, 64, n=30), BakeSettings(resolution=64, margin=0))
    a, _ = _bake(wavy_sheet(2, 64, n=30), 64)
    assert pipeline._BVH_KEPT.get("refits") == 1
    monkeypatch.setattr(pipeline, "_BVH_KEPT", {})
    b, _ = _bake(wavy_sheet(2, 64, n=30), 64)
    assert "refits" not in pipeline._BVH_KEPT and a.max() > 0
    np.testing.assert_array_equal(a, b)


def test_mesh_points_are_traced_once(monkeypatch):
    """The casters' corners and edge midpoints shared by neighbouring triangles of a smooth mesh
    are traced once (refine_kernel.mesh_point_traces): about 2 points per caster where 6 were
    traced, the same refinement but for decisions that rounding flips, and the same texture to
    rounding (relMSE 1e-12)."""
    from addon.solver.estimators import refine_kernel

    sc = wavy_sheet(4, 96, n=40)
    monkeypatch.setattr(refine_kernel, "MESH_SHARED", False)
    ref, ref_rep = _bake(sc, 96)
    monkeypatch.setattr(refine_kernel, "MESH_SHARED", True)
    new, new_rep = _bake(sc, 96)
    a, b = ref_rep["passes"][0], new_rep["passes"][0]
    print(f"points {a['points_traced']:,} -> {b['points_traced']:,}, sub-triangles {a['sub_triangles']:,} -> "
          f"{b['sub_triangles']:,}, relMSE {rel_mse(new, ref):.1e}")
    # a smooth grid has about 1/2 vertex and 3/2 edges per triangle: 2 points traced where 6 were
    assert a["points_traced"] - b["points_traced"] >= 3 * a["emitters"]
    assert abs(b["sub_triangles"] - a["sub_triangles"]) <= 1e-3 * a["sub_triangles"]
    assert ref.max() > 0 and rel_mse(new, ref) <= 1e-12


def test_mesh_points_are_shared_only_between_equal_light_points_and_materials():
    """mesh_points on a 2 x 2 grid of quads (8 triangles: 9 vertices, 16 edges, 25 points):
    under one light point every corner and midpoint is one point; emitters of two light points
    (an area light's samples) or of two IORs share nothing across them."""
    from addon.solver.estimators.refine_kernel import mesh_points

    s = np.linspace(0.0, 1.0, 3)
    V = np.array([[x, y, 0.0] for x in s for y in s])
    quads = [(i * 3 + j, (i + 1) * 3 + j, (i + 1) * 3 + j + 1, i * 3 + j + 1) for i in range(2) for j in range(2)]
    idx = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    tri_p = V[idx]
    tri_n = np.broadcast_to([0.0, 0.0, 1.0], tri_p.shape).copy()

    def count(x0, t1, ior):
        args = [np.asarray(x0, dtype=np.float64), np.asarray(t1, dtype=np.int64)] + [None] * 6 + [
            tri_p, tri_n, np.asarray(ior, dtype=np.float64), np.full(8, 2, dtype=np.int64)]
        e, u, v, index = mesh_points(len(t1), args)
        assert index.shape == (len(t1), 6) and index.max() == e.size - 1
        return e.size

    t1 = np.arange(8)
    one = np.tile([0.3, 0.2, 2.0], (8, 1))
    assert count(one, t1, np.full(8, 1.33)) == 25
    two = np.concatenate([one, one + [0.01, 0.0, 0.0]])
    assert count(two, np.concatenate([t1, t1]), np.full(8, 1.33)) == 50
    assert count(np.concatenate([one, one]), np.concatenate([t1, t1]), np.full(8, 1.33)) == 25
    assert count(one, t1, np.where(t1 < 4, 1.33, 1.5)) == 25 + 5  # the 3 vertices and 2 edges on x = 0.5 split


@pytest.mark.parametrize("uv_box", [(0.0, 1.0), (0.25, 0.75)])
def test_flat_floor_extended_beyond_its_edge_bakes_as_the_bisected_border(monkeypatch, uv_box):
    """A third of the sheet's light falls past the floor's edge.  Extended onto the floor's
    plane (addon/solver/geometry/receiver_planes.py) the images that cross the edge are clipped
    there by the splat, instead of cut by bisection inside the caster: the same texture (relMSE
    1e-6; measured 1e-7 and 2e-7) with far fewer points traced and no border cuts; the floor's UVs
    filling the texture or a middle square of it (the clip follows the UV region, not the
    texture's edge); and the power booked is what the texture holds (irradiance x texel area).
    Coarse images are held to the strict rule here (linear to 1 % x (1 texel / length)²) so
    the two differ by the edge alone (the coarse rule's own error: test_coarse_levels_stay_converged)."""
    monkeypatch.setattr(FI, "IMAGE_COARSE_LINEAR", 1.0)
    sc = wavy_sheet(3, 96, n=40, uv_box=uv_box)
    monkeypatch.setattr(FI, "EXTEND_FLAT_RECEIVERS", False)
    ref = bake(sc, BakeSettings(resolution=96, margin=0))
    monkeypatch.setattr(FI, "EXTEND_FLAT_RECEIVERS", True)
    new = bake(sc, BakeSettings(resolution=96, margin=0))
    a, b = ref.raw["Floor"], new.raw["Floor"]
    pa, pb = (r.report["estimators"]["forward-flux"]["passes"][0] for r in (ref, new))
    print(f"relMSE {rel_mse(b, a):.1e}; points {pb['points_traced']:,} vs {pa['points_traced']:,}; border "
          f"{pb['border']} vs {pa['border']}")
    assert a.max() > 0 and pa["border"] > 100
    assert rel_mse(b, a) <= 1e-6
    assert pb["points_traced"] <= 0.7 * pa["points_traced"] and pb["border"] == 0
    assert pb["extended_receivers"] == ["Floor"] and pa["extended_receivers"] == []
    lo, hi = (int(round(96 * x)) for x in uv_box)
    outside = np.ones((96, 96), dtype=bool)
    outside[lo:hi, lo:hi] = False
    assert not b[outside].any()
    area = texel_areas(sc, sc.receivers[0]).reshape(96, 96)
    held = (b[..., 0] * area).sum()
    booked = new.report["receivers"]["Floor"]["caustic_power"]
    assert abs(held / booked - 1.0) <= 1e-9
