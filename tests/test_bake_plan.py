"""Chain planning from roles and the bounce setting (addon/bake/driver.plan_chains)."""

import numpy as np

from addon.bake.driver import chain_supported, plan_chains
from addon.bake.scene import Light, build_scene


def _cube(offset):
    v = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float) + offset
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    return np.array([[v[q[0]], v[q[i]], v[q[i + 1]]] for q in faces for i in (1, 2)])


def _scene():
    floor = np.array([[[-5, -5, 0], [5, -5, 0], [5, 5, 0]]], float)
    sheet = np.array([[[-1, -1, 2], [1, -1, 2], [1, 1, 2]]], float)
    return build_scene([dict(name="floor", tri_p=floor, uv=floor[:, :, :2], receiver=True),
                        dict(name="glass_cube", tri_p=_cube((0, 0, 1)), role="both"),
                        dict(name="water", tri_p=sheet, role="refract"),
                        dict(name="metal_cube", tri_p=_cube((3, 0, 1)), role="reflect")],
                       [Light("L", "point", (1, 1, 1), 1.0, position=(0, 0, 5))])


def test_closed_objects():
    sc = _scene()
    assert sc.closed_objects() == {1, 3}


def test_plan_one_bounce():
    sc = _scene()
    plan = {p["chain"]: p for p in plan_chains(sc, bounces=1)}
    assert set(plan) == {"R", "T"}
    obj = lambda ids: set(np.unique(sc.tri_object[ids]).tolist())  # noqa: E731
    assert obj(plan["R"]["vertices"][0]) == {1, 3}  # glass reflects, metal reflects
    assert obj(plan["T"]["vertices"][0]) == {2}  # the closed glass cube has no single refraction
    assert all(p["status"] == "baked" for p in plan.values())


def test_plan_two_bounces_and_restriction():
    sc = _scene()
    plan = {p["chain"]: p for p in plan_chains(sc, bounces=2)}
    assert set(plan) == {"R", "T", "RR", "RT", "TR", "TT"}
    obj = lambda ids: set(np.unique(sc.tri_object[ids]).tolist())  # noqa: E731
    assert obj(plan["TT"]["vertices"][0]) == obj(plan["TT"]["vertices"][1]) == {1, 2}
    assert obj(plan["RT"]["vertices"][0]) == {1, 3} and obj(plan["RT"]["vertices"][1]) == {1, 2}
    for chain in ("RR", "RT", "TR", "TT"):
        assert (plan[chain]["status"] == "baked") == chain_supported(chain)
    assert [p["chain"] for p in plan_chains(sc, bounces=2, only=("TT",))] == ["TT"]
    # No casters of a kind, no chain.
    sc.tri_role[sc.tri_role == 2] = 0
    sc.tri_role[sc.tri_role == 3] = 0
    assert [p["chain"] for p in plan_chains(sc, bounces=2)] == ["R", "RR"]
