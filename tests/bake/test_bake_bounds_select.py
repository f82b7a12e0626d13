"""Bernstein-bounds selection of the path-points estimator and the reach of first casters
(addon/bake/bounds_select.py; Fan et al. 2025 §4.2–4.3, §6.1).

* Conservative and tighter: on small scenes the exact paths (every (tuple, sample) pair of the
  cone cull solved by ``solve_tuples``: an independent enumeration) all have their pair kept by
  the bounded selection, which keeps strictly fewer pairs than the cone cull (the ratio is
  printed and capped): glass slab TT (point light and sun), glass ball TT, two concave
  mirrors RR (a periscope), and the one-bounce bounds from the sun (a light point per caster).
* γ-sampling on the two-bounce Ē and on the sun's bounds keeps the energy; at γ = ∞ the
  texture equals the cone cull's.
* The per-pair kernels reproduce the engines' own drivers for one light point
  (``tuples.two_bounce_pairs``, ``two_bounce.bound_two_bounce``): the same pairs and pieces.
* ``reachable_first`` never drops a first-vertex triangle from which a forward-traced exact
  path (``bounds_scenes.forward_trace`` / ``forward_trace_two``, numpy, no solver) lands on a
  receiver, and drops some.
* A glass-sphere TT bake at 128² with path-points (exact two-bounce Specular Polynomials at the
  bounded pairs) matches the forward-flux bake.
"""

import time

import numpy as np
import pytest

from addon.bake import bounds_select as B
from addon.bake.estimators.path_points import chain_emitters
from addon.bake.pipeline import BakeSettings, bake, make_context
from addon.bake.plan import make_plan
from addon.bake.cull import TupleCull, first_casters_reaching
from addon.bake.lights import sample_light
from addon.bake.raster import rasterise
from addon.bake.scene import Light, build_scene
from addon.solver import solve_tuples

from fixtures import bounds_scenes as S
from fixtures.bake_scenes import box, floor, glass_sphere_scene, ring, uv_sphere

# Every test here bakes with the Bernstein-bound engines: in a fresh process the first one
# spends minutes (2-core machine) loading and compiling them, so the file is in the slow tier.
pytestmark = pytest.mark.slow


def _pairs(batches, n):
    keys = [e * n + s for e, s, *_ in batches]
    return np.unique(np.concatenate(keys)) if keys else np.zeros(0, dtype=np.int64)


def _selections(sc, chain, samples=1, rows=None, seed=1):
    """(cone keys, bounded keys, keys with an exact path, the bounded selection) of one band:
    key = emitter * samples_in_band + sample."""
    settings = BakeSettings(samples=samples, bounces=len(chain), chains=(chain,), two_bounce="exact", one_bounce="points",
                              cull="bounds", seed=seed, margin=0)
    ctx = make_context(sc, settings)
    item = make_plan(ctx).items[0]
    ls = sample_light(sc.lights[0], 1, seed)
    em, tri_of, x0_of = chain_emitters(ctx, item, ls, 0)
    rec = sc.receivers[0]
    W, H = rec.resolution
    band = rasterise(sc, rec, samples, seed, True, rows=rows or (0, H))
    n = band.size
    cone = _pairs(TupleCull(em, band.position, band.geo_normal, band.texel, W).batches(1 << 30), n)
    e, s = cone // n, cone % n
    tri = tri_of[e]
    ti, _ = solve_tuples(chain, x0_of[e], band.position[s], sc.tri_p[tri], sc.tri_n[tri], sc.tri_ior[tri[:, 0]])
    with_path = np.unique(cone[ti])
    sel = B.bounds_cull(sc, settings, chain, ls, 0, em, tri_of, x0_of, band, W, rec)
    bounded = _pairs(sel.batches(1 << 30), n)
    return cone, bounded, with_path, sel


def _slab(light):
    P, N = box(centre=(0.0, 0.0, 1.0), half=(0.6, 0.6, 0.06))
    return build_scene([floor(half=1.6, resolution=24), dict(name="slab", tri_p=P, tri_n=N, role="both", ior=1.5)], [light])


def _periscope(resolution=24, bend=0.1):
    """Two concave mirrors (paraboloid patches, ``bounds_scenes.curved_plane``) as a periscope:
    the light under the ceiling mirror A, A sends light to B, B to the floor: RR."""
    from fixtures.bake_scenes import mirror_facing

    objs = []
    for name, normal, centre, size in (("A", (0.0, 0.0, -1.0), (-0.8, 0.0, 2.2), 1.2), ("B", (-0.8, 0.0, -0.6), (0.6, 0.0, 1.4), 2.0)):
        _, _, R, _, _ = mirror_facing(normal, size=size, centre=centre)
        P, N = S.curved_plane(n=4, bend=bend)
        objs.append(dict(name=name, tri_p=(size * P) @ R.T + np.asarray(centre), tri_n=N @ R.T, role="reflect"))
    # the floor around the image (a strip near x = 1.25: the mirrors focus in one direction)
    return build_scene([floor(half=0.9, cx=1.25, resolution=resolution)] + objs,
                       [Light("Point", "point", (1, 1, 1), 30.0, position=(-1.3, 0.1, 1.4))])


SUN = Light("Sun", "sun", (1.0, 1.0, 1.0), 3.0, direction=(-0.3, 0.2, -1.0))

CASES = {
    # name: (scene, chain, samples, rows, most bounded / cone)
    "slab_TT": (lambda: _slab(Light("Point", "point", (1, 1, 1), 30.0, position=(0.5, 0.2, 3.0))), "TT", 4, None, 0.5),
    "slab_TT_sun": (lambda: _slab(SUN), "TT", 4, None, 0.5),
    "ball_TT": (lambda: glass_sphere_scene(resolution=32, segments=8, rings=4), "TT", 1, (15, 17), 0.5),
    "periscope_RR": (_periscope, "RR", 4, None, 0.5),
    "ring_R_sun": (lambda: build_scene([floor(half=1.6, resolution=32),
                                        dict(name="ring", tri_p=ring(24)[0], tri_n=ring(24)[1], role="reflect")],
                                       [Light("Sun", "sun", (1, 1, 1), 2.0, direction=(-1.0, 0.1, -0.45))]), "R", 4, None, 0.7),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_bounded_selection_keeps_every_exact_path_with_fewer_pairs(name):
    make, chain, samples, rows, most = CASES[name]
    t0 = time.perf_counter()
    cone, bounded, with_path, sel = _selections(make(), chain, samples, rows)
    lost = np.setdiff1d(with_path, bounded)
    print(f"\n{name}: cone {cone.size:,} pairs, bounded {bounded.size:,} ({bounded.size / cone.size:.3f} of the cone's), "
          f"with a path {with_path.size:,}, lost {lost.size}; {time.perf_counter() - t0:.1f} s")
    assert with_path.size >= 20
    assert lost.size == 0
    assert np.all(np.isin(bounded, cone))  # a subset of the cone cull's pairs
    assert bounded.size < most * cone.size


def test_per_pair_kernels_reproduce_the_engines():
    """One light point: ``bvh_pairs`` = ``tuples.two_bounce_pairs`` and ``two_bounce_bounds_points``
    (no pruning) = ``two_bounce.bound_two_bounce`` (no irradiance pass), piece for piece."""
    from addon.solver.bounds.two_bounce import bound_two_bounce
    from addon.solver.bounds.tuples import two_bounce_pairs

    sc = glass_sphere_scene(resolution=8, segments=12, rings=6)
    P, N = sc.tri_p[sc.tri_role > 0], sc.tri_n[sc.tri_role > 0]
    rec = sc.receivers[0]
    x0 = sc.lights[0].position
    for chain in ("TT", "RR"):
        pairs, _ = two_bounce_pairs(chain, x0, P, N, 1.5)
        ref = bound_two_bounce(chain, x0, P, N, sc.tri_p[rec.tri_index], rec.uv, 1.5, pairs=pairs, irradiance=False, max_depth=2)
        mine = B.bvh_pairs(chain, x0, P, N, 1.5, np.arange(P.shape[0]))
        assert np.array_equal(mine, pairs)
        tu, start, pc, _ = B.two_bounce_bounds_points(chain, x0, P, N, 1.5, pairs, sc.tri_p[rec.tri_index], rec.uv,
                                                      settings=dict(max_depth=2, capacity=16, prune=False, image_split=1))
        assert ref.tuples.shape[0] > 100
        assert np.array_equal(np.column_stack([pairs[tu[:, 0]], tu[:, 1]]), ref.tuples)
        assert np.array_equal(pc, ref.pieces)


@pytest.mark.parametrize("name", ["slab_TT", "ring_R_sun"])
def test_gamma_sampling_with_the_new_bounds_keeps_the_energy(name):
    """γ-sampling (§5: P = min(γ Ẽ, 1), weight 1/P, eq 24, 28) on the two-bounce bounds' Ē and
    on the sun's per-caster bounds (Ē scaled by |x1 - x0|², the sun's far-point intensity): fewer
    pairs solved than enumerating, the same total irradiance within the noise of one
    realisation; with γ = ∞ the texture equals the cone cull's."""
    make, chain, samples, _, _ = CASES[name]
    sc = make()
    base = dict(samples=samples, seed=2, margin=0, bounces=len(chain), chains=(chain,), two_bounce="exact", one_bounce="points")
    cone = bake(sc, BakeSettings(**base, cull="cone"))
    full = bake(sc, BakeSettings(**base, cull="bounds"))
    part = bake(sc, BakeSettings(**base, cull="bounds", gamma=0.02))
    a, b, c = cone.raw["floor"], full.raw["floor"], part.raw["floor"]
    n_full, n_part = full.report["counts"]["tuples"], part.report["counts"]["tuples"]
    ratio = c.sum() / b.sum()
    print(f"\n{name}: pairs cone {cone.report['counts']['tuples']:,}, bounds {n_full:,}, gamma=0.02 {n_part:,}; "
          f"energy ratio {ratio:.4f}")
    assert b.max() > 0
    assert np.abs(a - b).max() <= 1e-12 * a.max()
    assert full.report["counts"]["paths_visible"] == cone.report["counts"]["paths_visible"]
    assert n_part < n_full
    assert abs(ratio - 1) < 0.25


def _traced_firsts(chain, x0, P, N, eta, first, RP, per=64, seed=5):
    """First triangles (indices into ``first``) with a forward-traced exact path onto a receiver
    triangle, and how many paths were traced."""
    rng = np.random.default_rng(seed)
    tri = np.repeat(first, per)
    a, b = rng.random(tri.size), rng.random(tri.size)
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    uv = np.stack([a, b], 1)
    if len(chain) == 1:
        hit, _, _ = S.forward_trace(chain, x0, P[tri], N[tri], eta, uv, RP)
    else:
        _, hit, _, _, _ = S.forward_trace_two(chain, x0, P, N, eta, tri, uv, RP)
    ok = hit >= 0
    return np.unique(np.searchsorted(first, tri[ok])), int(ok.sum())


@pytest.mark.parametrize("case", ["ring_R", "ring_R_sun", "water_T", "ball_TT", "periscope_RR"])
def test_reach_never_drops_a_first_triangle_with_a_traced_path(case):
    from addon.demo import wavy_water

    RP = floor(half=1.6)["tri_p"]
    sun = None
    if case.startswith("ring"):
        P, N = ring(48)
        chain, eta, x0 = "R", 1.0, np.array([2.6, 0.0, 1.3])
        if case.endswith("sun"):
            sun = np.array([-1.0, 0.1, -0.45]) / np.linalg.norm([-1.0, 0.1, -0.45])
    elif case == "water_T":
        P, N = wavy_water(cells=10, size=2.0, amplitude=0.08)
        swap = lambda a: a[..., [0, 2, 1]] * np.array([1.0, -1.0, 1.0])  # noqa: E731
        P, N = swap(P), swap(N)
        P[..., 2] += 1.0
        chain, eta, x0 = "T", 1.33, np.array([0.3, -0.2, 3.0])
    elif case == "ball_TT":
        P, N = uv_sphere(24, 12)
        chain, eta, x0 = "TT", 1.5, np.array([0.3, 0.2, 3.0])
    else:
        sc = _periscope()
        P, N = sc.tri_p[sc.tri_role > 0], sc.tri_n[sc.tri_role > 0]
        chain, eta, x0 = "RR", 1.0, sc.lights[0].position
        RP = floor(half=2.5, cx=1.0)["tri_p"]
    first = np.arange(P.shape[0])
    if sun is not None:  # a far point behind each triangle, as lights.light_points
        x0 = P.mean(axis=1) - 1e5 * 4.0 * sun
    t0 = time.perf_counter()
    if len(chain) == 1:
        keep = B.reachable_first(chain, x0, P, N, eta, RP)
        cone = B.reachable_first(chain, x0, P, N, eta, RP, use_bounds=False)
    else:
        keep = B.reachable_first(chain, x0, P, N, eta, RP, P, N, eta, ids1=first, ids2=first)
        cone = B.reachable_first(chain, x0, P, N, eta, RP, P, N, eta, ids1=first, ids2=first, use_bounds=False)
    dt = time.perf_counter() - t0
    # the forward-flux skip: the first cone against clustered targets (receivers, or the second casters)
    fast = first_casters_reaching(chain, x0, P, N, eta, RP if len(chain) == 1 else P)
    if sun is not None:  # trace each triangle from its own far point
        lit = []
        n_paths = 0
        for t in first:
            got, k = _traced_firsts(chain, x0[t], P, N, eta, np.array([t]), RP, seed=5 + int(t))
            lit.append(np.array([t])[got])
            n_paths += k
        lit = np.concatenate(lit)
    else:
        lit, n_paths = _traced_firsts(chain, x0, P, N, eta, first, RP, per=256)
    print(f"\n{case}: {P.shape[0]} first triangles, {lit.size} with traced paths ({n_paths:,} paths); kept by the bounds "
          f"{keep.sum()}, by the cones alone {cone.sum()}; {dt:.2f} s; by the forward-flux skip {fast.sum()}")
    assert lit.size >= (5 if case == "periscope_RR" else 50)
    assert keep[lit].all()
    assert cone[lit].all()
    assert fast[lit].all()
    if case in ("ring_R", "ring_R_sun", "water_T"):  # triangles that light nothing are skipped
        assert fast.sum() < 0.8 * P.shape[0]
    assert keep.sum() < P.shape[0]
    if len(chain) == 1:  # one bounce: the bounds run on the cone's (triangle, receiver) pairs only
        assert not np.any(keep & ~cone)


@pytest.mark.parametrize("scene", ["ring", "ball"])
def test_forward_flux_skips_casters_that_reach_nothing_and_keeps_the_texture(scene, monkeypatch):
    """forward-flux traces only the first casters whose scattered light can reach the chain's
    next targets (cull.first_casters_reaching): the texture must be bit for bit the texture
    of a bake that traces every lit caster, and the skip must drop some casters (the ring's
    outer wall reflects away from the floor; the ball's lit top refracts into the ball, so TT
    keeps all its first triangles while R drops those reflecting upward)."""
    from addon.bake.estimators import forward_images

    from fixtures.bake_scenes import ring_scene

    sc = ring_scene(resolution=32, segments=48) if scene == "ring" else glass_sphere_scene(resolution=32, segments=24, rings=12)
    settings = BakeSettings(samples=1, seed=3, margin=0, bounces=2)
    skipped = bake(sc, settings)
    monkeypatch.setattr(forward_images, "first_casters_reaching",
                        lambda chain, x0, tri_p1, *a: np.ones(tri_p1.shape[0], dtype=bool))
    every = bake(sc, settings)
    passes = skipped.report["estimators"]["forward-flux"]["passes"]
    reach = {p["chain"]: p["reach"] for p in passes}
    print(f"\n{scene}: " + ", ".join(f"{c}: {r['reaching']}/{r['lit']} lit casters reach ({r['seconds'] * 1e3:.1f} ms)"
                                      for c, r in reach.items()))
    for name in every.raw:
        assert every.raw[name].max() > 0
        assert np.array_equal(skipped.raw[name], every.raw[name])
    assert sum(r["reaching"] for r in reach.values()) < sum(r["lit"] for r in reach.values())
    if scene == "ball":
        assert reach["TT"]["reaching"] == reach["TT"]["lit"]


@pytest.mark.slow
def test_glass_sphere_tt_path_points_with_bounds_matches_forward_flux():
    """Glass sphere (32 x 16 UV sphere, IOR 1.5, point light on the axis) TT at 128², one
    jittered sample per texel: path-points (the exact two-bounce Specular Polynomials at every
    (tuple, sample) pair the Bernstein bounds keep, no γ-sampling) against forward flux
    (texel averages).

    Metric: per-texel relative MSE with a floor, mean over covered texels of
    ((a - b) / max(b, 0.1 mean(b)))² (a path-points, b flux).  The plain relMSE
    mean((a - b)²) / mean(b²) is dominated by the 2 x 2 texels at the sphere's axial focus on
    the floor, where the irradiance is singular: there a point sample is heavy-tailed while flux
    gives the texel average (measured: plain relMSE 0.70, all of it within 3 texels of the
    axis; per-texel metric 1.2e-3, median |relative error| 1.4e-3; 90 s, 2.8M pairs solved)."""
    res = 128
    sc = glass_sphere_scene(resolution=res, segments=32, rings=16)
    base = dict(samples=1, bounces=2, chains=("TT",), margin=0, seed=1, resolution=res)
    t0 = time.perf_counter()
    flux = bake(sc, BakeSettings(**base, two_bounce="flux"))
    t1 = time.perf_counter()
    pts = bake(sc, BakeSettings(**base, two_bounce="exact", cull="bounds"))
    t2 = time.perf_counter()
    cov = flux.coverage["floor"]
    a = pts.raw["floor"][..., 0][cov]
    b = flux.raw["floor"][..., 0][cov]
    rel = (a - b) / np.maximum(b, 0.1 * b.mean())
    metric = float(np.mean(rel ** 2))
    plain = float(np.mean((a - b) ** 2) / np.mean(b ** 2))
    c = pts.report["counts"]
    tm = pts.report["timings"]
    print(f"\nflux {t1 - t0:.1f} s; path-points {t2 - t1:.1f} s (cull {tm['cull']:.1f} s, solve {tm['solve']:.1f} s), "
          f"{c['tuples']:,} tuples solved, {c['paths_visible']:,} paths; per-texel relMSE (floor 0.1 mean) {metric:.2e}, "
          f"median |rel| {np.median(np.abs(rel)):.1e}, plain relMSE {plain:.3f}")
    assert c["paths_visible"] >= 0.95 * cov.sum()  # the floor is lit by TT almost everywhere
    assert metric < 5e-3
    assert np.median(np.abs(rel)) < 5e-3
    from fixtures.checks import rel_mse  # the project's relMSE (floor 1e-2 mean² over lit texels)

    project = rel_mse(pts.raw["floor"][..., 0], flux.raw["floor"][..., 0])
    print(f"relMSE (tests/fixtures/checks.py rel_mse) {project:.2e}")
    assert project < 5e-3
    assert c["tuples"] < 250 * c["paths_visible"]  # the cone cull keeps ~16,000 per path here
