"""Two-bounce Bernstein bounds (Fan et al. 2025 §4.3 with remainder variables, §6.1 tuples).

* Tuple construction through the BVH keeps every (T1, T2) pair that an exact forward-traced
  path uses, on the paper's slab and ball meshes, with a tuple count near the authors'.
* Position bounds (RR, RT, TR, TT): every exact two-bounce path traced forward from (u1, v1)
  lies in the position bound of its tuple's piece containing (u1, v1) (receiver barycentrics
  and UV): zero violations; the bounds are tight (median width asserted).
* Convergence: on a small box the bound approaches the exact image of the box.
* The ξ2 endpoint bound (coefficients at ξ2 = 0 and 1 together) contains sampled values of the
  5-variable rational function.
"""

import os
import sys

import numpy as np
import pytest

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
for p in (HERE, ROOT):
    if p not in sys.path:
        sys.path.insert(0, p)

import bounds_scenes as S  # noqa: E402
from addon.solver.bounds.chain2 import bound_two_bounce, piece_position_two, CHAIN_CODES  # noqa: E402
from addon.solver.bounds.tuples import two_bounce_pairs  # noqa: E402


def _scene(name, chain):
    sc = S.scene(name)
    sc["chain"] = chain
    return sc


@pytest.mark.parametrize("name,chain,n_first,most_per_first", [
    ("slab10k", "TT", 600, 20.0), ("slab10k", "RR", 600, 20.0), ("ball1280", "TT", 1280, 16.0)])
def test_tuples_contain_every_traced_pair(name, chain, n_first, most_per_first):
    sc = _scene(name, chain)
    first = np.random.default_rng(3).choice(sc["caster_P"].shape[0], n_first, replace=False)
    pairs, rep = two_bounce_pairs(chain, sc["light"], sc["caster_P"], sc["caster_N"], sc["eta"], first=first)
    rng = np.random.default_rng(4)
    tri = np.repeat(first, 32)
    a, b = rng.random(tri.size), rng.random(tri.size)
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    t2, _, _, _, _ = S.forward_trace_two(chain, sc["light"], sc["caster_P"], sc["caster_N"], sc["eta"], tri,
                                         np.stack([a, b], 1), sc["receiver_P"])
    ok = t2 >= 0
    traced = set(zip(tri[ok].tolist(), t2[ok].tolist()))
    have = set(map(tuple, pairs.tolist()))
    print(f"\n{name} {chain}: {rep['pairs']} pairs from {n_first} first triangles ({rep['pairs_per_first']:.2f} each; "
          f"authors' slab10k TT: 12.7), {len(traced)} traced pairs, {rep['node_tests']} node tests")
    assert len(traced) > 100
    assert traced <= have
    assert len(pairs) == len(set(map(tuple, pairs.tolist())))  # no duplicates
    assert rep["pairs_per_first"] <= most_per_first
    assert np.all(pairs[:, 0] != pairs[:, 1])


@pytest.mark.parametrize("name,chain,n_first,widest", [
    ("slab10k", "TT", 60, 0.05), ("slab10k", "RT", 120, 0.1), ("slab10k", "TR", 60, 0.1), ("slab10k", "RR", 400, 0.2),
    ("ball1280", "TT", 80, 0.05)])
def test_position_bounds_hold_every_traced_path(name, chain, n_first, widest):
    sc = _scene(name, chain)
    first = np.random.default_rng(5).choice(sc["caster_P"].shape[0], n_first, replace=False)
    pairs, _ = two_bounce_pairs(chain, sc["light"], sc["caster_P"], sc["caster_N"], sc["eta"], first=first)
    res = bound_two_bounce(chain, sc["light"], sc["caster_P"], sc["caster_N"], sc["receiver_P"], sc["receiver_UV"],
                           eta=sc["eta"], pairs=pairs, max_depth=1)
    paths = S.trace_two(sc, first, samples_per_triangle=64)
    c = S.check_bounds_two(res, sc, paths)
    print(f"\n{name} {chain}: {c['paths']} paths, {res.report['tuples']} tuples, {res.report['pieces_per_tuple']:.2f} "
          f"pieces/tuple, violations {c['position_violations']} (missing tuple {c['missing_tuple']}, piece "
          f"{c['missing_piece']}), median width {c['median_width']}, constant forms {res.report['constant_forms']}")
    assert c["paths"] >= 200
    assert c["missing_tuple"] == 0
    assert c["position_violations"] == 0
    assert max(c["median_width"]) < widest


def test_position_bound_converges_to_the_image_of_a_small_box():
    """Slab TT: around traced paths, a box of side 1e-3 in (u1, v1): the bound's width is within
    a factor 1.5 of the exact image's width (a 25 x 25 grid traced forward), and contains it."""
    sc = _scene("slab10k", "TT")
    paths = S.trace_two(sc, np.arange(0, 9999, 997), samples_per_triangle=4, seed=7)
    checked = 0
    out = np.zeros(8)
    stats = np.zeros(4, dtype=np.int64)
    for i in range(paths["tri"].shape[0]):
        t1, t2, r = paths["tri"][i], paths["t2"][i], paths["hit"][i]
        lo = np.clip(paths["uv"][i] - 5e-4, 0.0, None)
        hi = lo + 1e-3
        if hi[0] + hi[1] > 1.0:
            continue
        g = np.linspace(0.0, 1.0, 25)
        uu, vv = np.meshgrid(lo[0] + 1e-3 * g, lo[1] + 1e-3 * g)
        uv = np.stack([uu.ravel(), vv.ravel()], 1)
        tt2, hit, buv, _, _ = S.forward_trace_two("TT", sc["light"], sc["caster_P"], sc["caster_N"], sc["eta"],
                                                  np.full(uv.shape[0], t1), uv, sc["receiver_P"])
        same = (tt2 == t2) & (hit == r)
        if not same.all():
            continue  # the box straddles an edge of T2 or of the receiver: widths not comparable
        assert piece_position_two(CHAIN_CODES["TT"], sc["light"], sc["caster_P"][t1], sc["caster_N"][t1], sc["caster_P"][t2],
                                  sc["caster_N"][t2], sc["receiver_P"][r], sc["receiver_UV"][r], sc["eta"], lo, hi, out, stats)
        wu = buv[:, 0].max() - buv[:, 0].min()
        wv = buv[:, 1].max() - buv[:, 1].min()
        assert out[0] <= buv[:, 0].min() and buv[:, 0].max() <= out[1]
        assert out[2] <= buv[:, 1].min() and buv[:, 1].max() <= out[3]
        assert out[1] - out[0] <= 1.5 * wu + 4e-9
        assert out[3] - out[2] <= 1.5 * wv + 4e-9
        checked += 1
    assert checked >= 10


def test_remainder_endpoint_bound_contains_the_function_of_the_remainder_variable():
    """pu/q with pu = (1-ξ) p0 + ξ p1, q likewise: eq 3 over the ξ = 0 and ξ = 1 coefficient sets
    together (chain2's handling of ξ2) bounds it over the 5-variable box."""
    from addon.solver.bounds.bernstein import _bound_of_coefficients, evaluate, power_to_bernstein
    from addon.solver.bounds.chain2 import _flat_common

    rng = np.random.default_rng(11)
    for _ in range(20):
        p0 = power_to_bernstein(rng.normal(size=(3, 3, 2, 2)))
        p1 = power_to_bernstein(rng.normal(size=(3, 3, 2, 2)))
        q0 = power_to_bernstein(np.abs(rng.normal(size=(2, 2, 1, 1))) + 0.5)
        q1 = power_to_bernstein(np.abs(rng.normal(size=(2, 2, 1, 1))) + 0.5)
        fp, _, fq = _flat_common(p0, p0, q0, p1, p1, q1)
        lo, hi, lo2, hi2 = _bound_of_coefficients(fp, fq)
        assert lo2 > hi2  # q has one sign: a single interval
        x = rng.random((400, 5))
        vals = []
        for a, b, c, d, xi in x:
            num = (1 - xi) * evaluate(p0, a, b, c, d) + xi * evaluate(p1, a, b, c, d)
            den = (1 - xi) * evaluate(q0, a, b, c, d) + xi * evaluate(q1, a, b, c, d)
            vals.append(num / den)
        vals = np.array(vals)
        assert lo <= vals.min() and vals.max() <= hi
        # and tight: the corners of the box (ξ in {0, 1}) reach within the coefficient hull
        assert hi - lo <= 6.0 * (vals.max() - vals.min())


@pytest.mark.parametrize("name,chain,n_first", [("slab10k", "TT", 40), ("slab10k", "RR", 40), ("slab10k", "RT", 40),
                                                 ("slab10k", "TR", 40), ("ball80", "TT", 80)])
def test_fast_engine_gives_the_reference_pieces(name, chain, n_first):
    """chain2_fast (the default engine) against chain2's own functions: the same tuples and pieces
    (boxes, depths, receivers); position bounds equal up to rounding (the fast engine
    re-associates eq 9 and works in scaled Bernstein form), except where rounding flips the sign
    of a near-zero numerator coefficient in the reciprocal case of eq 3 (one piece of ball80 TT):
    there the fast bound is the wider one.  Never narrower than the reference's."""
    from addon.solver.bounds.chain1 import P_BU0, P_BU1, P_BV0, P_BV1, P_X0, P_X1, P_Y0, P_Y1

    sc = _scene(name, chain)
    first = np.random.default_rng(8).choice(sc["caster_P"].shape[0], n_first, replace=False)
    pairs, _ = two_bounce_pairs(chain, sc["light"], sc["caster_P"], sc["caster_N"], sc["eta"], first=first)
    res = {}
    for engine in ("reference", "fast"):
        res[engine] = bound_two_bounce(chain, sc["light"], sc["caster_P"], sc["caster_N"], sc["receiver_P"], sc["receiver_UV"],
                                       eta=sc["eta"], pairs=pairs, max_depth=2 if name.startswith("ball") else 1, engine=engine)
    a, b = res["reference"], res["fast"]
    assert a.tuples.shape[0] > 20
    np.testing.assert_array_equal(a.tuples, b.tuples)
    np.testing.assert_array_equal(a.piece_tuple, b.piece_tuple)
    assert a.report["box_evaluations"] == b.report["box_evaluations"]
    np.testing.assert_array_equal(a.pieces[:, :4], b.pieces[:, :4])
    np.testing.assert_array_equal(a.pieces[:, 12:], b.pieces[:, 12:])
    lo = [P_BU0, P_BV0, P_X0, P_Y0]
    hi = [P_BU1, P_BV1, P_X1, P_Y1]
    assert np.all(b.pieces[:, lo] <= a.pieces[:, lo] + 1e-12) and np.all(b.pieces[:, hi] >= a.pieces[:, hi] - 1e-12)
    same = np.all(np.abs(a.pieces[:, 4:12] - b.pieces[:, 4:12]) <= 1e-12, axis=1)
    print(f"\n{name} {chain}: {a.pieces.shape[0]} pieces, {int((~same).sum())} wider in the fast engine")
    assert same.mean() >= 0.999
