"""The conservative tuple cull (addon/bake/cull.py) never loses a path, and does cull."""

import numpy as np
import pytest

from addon.bake import cull
from addon.bake.cull import OneBounceCull, scatter_caps, scatter_caps_numpy
from addon.bake.pipeline import BakeSettings, bake
from addon.solver import solve_tuples

from fixtures.bake_scenes import ring_scene


def _curved_triangles(rng, n, bend_deg):
    """Random small triangles around the origin facing roughly +z, corner normals bent up to ``bend_deg``."""
    c = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), rng.uniform(-0.2, 0.2, n)])
    P = c[:, None, :] + rng.normal(scale=0.25, size=(n, 3, 3)) * [1, 1, 0.3]
    ng = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    ng /= np.linalg.norm(ng, axis=1, keepdims=True)
    ng *= np.sign(ng[:, 2:3])
    N = ng[:, None, :] + np.tan(np.radians(bend_deg)) * rng.uniform(-1, 1, (n, 3, 3)) / np.sqrt(3)
    N /= np.linalg.norm(N, axis=2, keepdims=True)
    return P, N


def _samples(rng, m, z):
    pos = np.column_stack([rng.uniform(-3, 3, m), rng.uniform(-3, 3, m), np.full(m, z)])
    order = np.lexsort((pos[:, 0], pos[:, 1]))  # grid-like texel order so that tiles are compact
    return pos[order]


def _paths(chain, x0, P, N, eta, pos, tri_idx, smp_idx):
    ti, uv = solve_tuples(chain, x0[tri_idx], pos[smp_idx], P[tri_idx][:, None], N[tri_idx][:, None], eta[tri_idx])
    return ti, uv


@pytest.mark.parametrize("chain", ["R", "T"])
def test_cull_keeps_every_path_of_the_full_enumeration(chain):
    rng = np.random.default_rng(21 if chain == "R" else 22)
    found_total = 0
    kept_fraction = []
    for trial in range(4):
        n_tri, n_smp = 60, 1600
        P, N = _curved_triangles(rng, n_tri, bend_deg=(5, 15, 30, 60)[trial])
        eta = np.full(n_tri, 1.33 if trial % 2 else 1.5)
        light = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(1.5, 3.0)])
        if chain == "T" and trial == 3:
            light[2] = -2.0  # light inside the medium (r > 1: the cone needs the critical-angle guard)
        x0 = np.broadcast_to(light, (n_tri, 3)).copy()
        # Receivers where the chain sends light, facing the casters: R back to the light's
        # side, T through to the other side.
        up = light[2] > 0
        z = (1.2 if up else -1.5) if chain == "R" else (-1.0 if up else 1.0)
        pos = _samples(rng, n_smp, z)
        geo = np.tile([0.0, 0.0, -1.0 if z > 0 else 1.0], (n_smp, 1))
        # Full enumeration.
        tri_all = np.repeat(np.arange(n_tri), n_smp)
        smp_all = np.tile(np.arange(n_smp), n_tri)
        ti, uv = _paths(chain, x0, P, N, eta, pos, tri_all, smp_all)
        p = P[tri_all[ti]]
        x1 = p[:, 0] + uv[:, :1] * (p[:, 1] - p[:, 0]) + uv[:, 1:2] * (p[:, 2] - p[:, 0])
        front = np.sum((x1 - pos[smp_all[ti]]) * geo[smp_all[ti]], axis=1) > 0
        full = set(zip(tri_all[ti][front].tolist(), smp_all[ti][front].tolist()))
        # Culled enumeration.
        cull = OneBounceCull(chain, x0, P, N, eta, pos, geo, np.arange(n_smp), 40)
        got_pairs = []
        for lt, s in cull.batches(5000):
            got_pairs += list(zip(lt.tolist(), s.tolist()))
        assert len(got_pairs) == len(set(got_pairs)), "no tuple twice"
        missing = full - set(got_pairs)
        assert not missing, f"trial {trial}: the cull dropped {len(missing)} of {len(full)} paths"
        found_total += len(full)
        kept_fraction.append(len(got_pairs) / (n_tri * n_smp))
    assert found_total > 200, "the scenes must have paths for the test to mean anything"
    # Gently curved triangles are culled hard; strongly bent ones keep more.
    assert kept_fraction[0] < 0.25, kept_fraction


def test_cone_contains_sampled_scattered_directions():
    """The cap of scattered directions contains the directions at random points of the triangle."""
    rng = np.random.default_rng(4)
    P, N = _curved_triangles(rng, 200, bend_deg=20)
    eta = np.full(200, 1.5)
    x0 = np.tile([0.3, -0.2, 2.5], (200, 1))
    for chain in ("R", "T"):
        side, d, theta = scatter_caps(chain, x0, P, N, eta)
        assert np.mean(theta < 3.0) > 0.8
        for _ in range(20):
            a, b = rng.random(200), rng.random(200)
            flip = a + b > 1
            a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
            x1 = P[:, 0] + a[:, None] * (P[:, 1] - P[:, 0]) + b[:, None] * (P[:, 2] - P[:, 0])
            n = N[:, 0] + a[:, None] * (N[:, 1] - N[:, 0]) + b[:, None] * (N[:, 2] - N[:, 0])
            n /= np.linalg.norm(n, axis=1, keepdims=True)
            wi = x1 - x0
            wi /= np.linalg.norm(wi, axis=1, keepdims=True)
            no = np.where((np.sum(wi * n, axis=1) < 0)[:, None], n, -n)
            ci = -np.sum(wi * no, axis=1)
            if chain == "R":
                wo = wi + 2 * ci[:, None] * no
                ok = np.ones(200, bool)
            else:
                r = np.where(np.sum(wi * n, axis=1) < 0, 1 / 1.5, 1.5)
                k = 1 - r * r * (1 - ci * ci)
                ok = k > 0
                wo = r[:, None] * wi + (r * ci - np.sqrt(np.maximum(k, 0)))[:, None] * no
            ang = np.arccos(np.clip(np.sum(wo * d, axis=1), -1, 1))
            assert np.all(ang[ok] <= theta[ok] + 1e-12)


def test_bake_with_and_without_cull_is_identical():
    sc = ring_scene(resolution=16, segments=24)
    a = bake(sc, BakeSettings(samples=4, cull=True, margin=0, one_bounce="points"))  # the cull serves exact paths
    b = bake(sc, BakeSettings(samples=4, cull=False, margin=0, one_bounce="points"))
    np.testing.assert_array_equal(a.raw["floor"], b.raw["floor"])
    assert a.report["counts"]["paths_visible"] == b.report["counts"]["paths_visible"] > 100
    assert a.report["counts"]["tuples"] < 0.5 * b.report["counts"]["tuples"]


@pytest.mark.parametrize("chain", ["R", "T"])
def test_scatter_caps_kernel_equals_the_numpy_caps(chain):
    """The cone caps' kernel (cull._scatter_caps) against their numpy form (vertex_cap,
    normal_cap, propagate_cap): gentle and wild normal fields, glancing and behind-the-plane
    light, degenerate triangles, caps handed in (two bounces' second vertex), two IORs."""
    rng = np.random.default_rng(11)
    n = 4000
    P, N = _curved_triangles(rng, n, 25.0)
    N[: n // 4] = rng.normal(size=(n // 4, 3, 3))  # wild corner normals: inconsistent / no cone
    P[n // 4: n // 4 + 50, 2] = P[n // 4: n // 4 + 50, 0]  # degenerate: two equal corners
    x0 = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-2, 2, n), rng.uniform(-0.5, 3.0, n)])
    x0[-100:] = P[-100:, 0]  # the light in the triangle's plane (side 0)
    eta = np.where(rng.uniform(size=n) < 0.5, 1.33, 1.5)
    kinds = [None, (rng.normal(size=(n, 3)), rng.uniform(0.0, 1.2, n))]
    kinds[1][0][:] /= np.linalg.norm(kinds[1][0], axis=1, keepdims=True)
    kinds[1][1][:10] = 4.0  # no cone handed in
    for incoming in kinds:
        side, d, theta = scatter_caps(chain, x0, P, N, eta, incoming)
        side_np, d_np, theta_np = scatter_caps_numpy(chain, x0, P, N, eta, incoming)
        assert np.array_equal(side, side_np)
        np.testing.assert_allclose(theta, theta_np, rtol=1e-12, atol=1e-12)
        capped = theta_np < 4.0
        assert 0.2 * n < capped.sum() < n  # both kinds present
        np.testing.assert_allclose(d[capped], d_np[capped], rtol=0, atol=1e-12)


@pytest.mark.parametrize("case", ["sheet T", "ring R", "sphere T"])
def test_reach_kernel_decides_as_the_emitters_cone_test(case):
    """first_casters_reaching's kernel (sphere, plane and the cap's cosine per caster, no
    trigonometry per node, nearer child first) keeps exactly the casters for which some leaf
    of the target sphere tree passes the Emitters' cone test (_tile_ok, the path-points cull's)
    at every node down to it: a brute-force descent over the whole tree here."""
    from fixtures.bake_scenes import glass_sphere_scene, ring_scene, wavy_sheet

    sc = {"sheet T": lambda: wavy_sheet(3, 64, n=24), "ring R": lambda: ring_scene(64),
          "sphere T": lambda: glass_sphere_scene(resolution=64)}[case]()
    chain = case[-1]
    cas, rec = np.flatnonzero(sc.tri_role > 0), np.flatnonzero(sc.tri_role == 0)
    x0 = np.tile(np.asarray(sc.lights[0].position, float), (cas.size, 1))
    P, N, eta = sc.tri_p[cas], sc.tri_n[cas], sc.tri_ior[cas]
    centre, radius = cull.sphere_tree(sc.tri_p[rec], depth=4)
    got = cull.first_casters_reaching(chain, x0, P, N, eta, sc.tri_p[rec], (centre, radius))
    em = cull.one_bounce_emitters(chain, x0, P, N, eta)
    args = (em.part_start, em.part_c, em.part_r, em.part_d, em.part_t, em.tri_ng, em.tri_p0, em.side_req, centre, radius)

    def reaches(t, k):
        if radius[k] < 0 or not cull._tile_ok(t, k, *args):
            return False
        return 2 * k + 2 >= radius.size or reaches(t, 2 * k + 1) or reaches(t, 2 * k + 2)

    want = np.array([reaches(t, 0) for t in range(cas.size)])
    assert 0 < want.sum()
    np.testing.assert_array_equal(got, want)
