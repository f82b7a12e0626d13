"""addon.solver.path_irradiance checked against independent references (one bounce).

* geometry = dOmega0/dA_perp: central finite differences (4-point stencil) of the light -> receiver
  map traced with the reference forward tracer (tests/reference/bruteforce.py): the emission
  direction at x0 is perturbed by small angles along two orthonormal directions, the rays are traced
  (plane of the triangle, interpolated normal extended smoothly, reflect/refract per the contract)
  to the plane through x_end perpendicular to the arriving ray, and 1 / |dX/da x dX/db| is compared
  with the solver's geometry term (relative 1e-4). Focal paths (tiny area) are skipped and counted.
* flat mirror: geometry = 1 / (|x1-x0| + |x2-x1|)^2 exactly.
* direction, cos_receiver, irradiance = geometry * fresnel * cos_receiver.
* fresnel: mirror 1; dielectric reflectance (unpolarised, own implementation) from outside; conductor
  (complex IOR) from outside; T: 1 - F with the contract's cos_i and side.
"""
from __future__ import annotations

import numpy as np
import pytest

from reference import bruteforce as bf

SEED = 777
GEOM_RTOL = 1e-4
FOCAL_REL_AREA = 1e-3  # skip paths whose ray-tube area / (unfolded length)^2 is below this
CONDUCTOR_K = 2.7

_CACHE: dict = {}


def _api():
    try:
        from addon.solver import path_irradiance, solve_tuples  # noqa: WPS433
    except Exception as exc:  # pragma: no cover
        pytest.fail(f"addon.solver not importable: {exc!r}")
    return solve_tuples, path_irradiance


def _data(chain):
    """A few hundred planted tuples (tilted + curved normal fields) and the solver's paths."""
    if chain in _CACHE:
        return _CACHE[chain]
    solve_tuples, _ = _api()
    rng = np.random.default_rng([SEED, ord(chain)])
    n = 400
    P = bf.random_triangles(rng, n)
    N = bf.random_normals(rng, P, "tilt", max_tilt_deg=40.0)
    curv = rng.choice([-1.0, 1.0], n) * rng.uniform(1.0, 3.0, n)
    sph = rng.random(n) < 0.4
    N[sph] = bf.random_normals(rng, P[sph], "sphere", curvature=curv[sph])
    eta = bf.random_eta(rng, n)
    x0, x2, uvp, ok = bf.plant_paths(rng, chain, P, N, eta, dist_log10=(-0.3, 2.0), max_theta_deg=80.0)
    assert ok.all()
    P4, N4 = P[:, None].copy(), N[:, None].copy()
    ti, uv = solve_tuples(chain, x0, x2, P4, N4, eta)
    rn = bf._random_unit(rng, n)
    d = dict(chain=chain, P=P4, N=N4, eta=eta, x0=x0, x2=x2, ti=ti, uv=uv, rn=rn)
    _CACHE[chain] = d
    return d


def _reference_geometry(chain, x0, x2, P, N, eta, uv):
    """Finite-difference dOmega/dA_perp per path (rows aligned). Returns (G, rel_area, fd_spread)."""
    origin = P[:, 0].copy()  # work relative to p0 (translation invariance, less cancellation)
    x0 = x0 - origin
    x2 = x2 - origin
    P = P - origin[:, None, :]
    m = len(x0)
    x1, _, _, _ = bf.interpolate(P, N, uv[:, 0], uv[:, 1])
    wi, L0 = bf._unit(x1 - x0)
    wo, L1 = bf._unit(x2 - x1)
    a, b = bf._perp_basis(wi)
    size = bf.tri_size(P)
    plane_n = wo

    def trace(alpha, beta):
        d = wi + alpha[:, None] * a + beta[:, None] * b
        out = bf.trace_one_bounce(x0, d, P, N, eta, chain, x2, plane_n)
        return out["hit"], out["ok"]

    def deriv(delta):
        z = np.zeros(m)
        cols = []
        ok_all = np.ones(m, bool)
        for axis in (0, 1):
            pts = {}
            for k in (-2, -1, 1, 2):
                al = k * delta if axis == 0 else z
                be = k * delta if axis == 1 else z
                pts[k], ok = trace(al, be)
                ok_all &= ok
            cols.append((-pts[2] + 8 * pts[1] - 8 * pts[-1] + pts[-2]) / (12 * delta)[:, None])
        area = bf._norm(np.cross(cols[0], cols[1]))
        return area, ok_all

    hit0, ok0 = trace(np.zeros(m), np.zeros(m))
    # steps: footprint 1e-2 .. 1e-5 of the triangle; per path the pair of neighbouring steps
    # that agree best is used (truncation error vs. round-off; near TIR the map bends fast)
    deltas = [f * size / L0 for f in (1e-2, 2.5e-3, 6.25e-4, 1.5625e-4, 3.90625e-5)]
    areas, oks = [], []
    for dl in deltas:
        ar, o = deriv(dl)
        areas.append(ar)
        oks.append(o)
    areas = np.array(areas)
    oks = np.array(oks)
    with np.errstate(all="ignore"):
        spreads = np.abs(areas[1:] / areas[:-1] - 1.0)
    spreads = np.where(np.isfinite(spreads) & oks[1:] & oks[:-1], spreads, np.inf)
    j = np.argmin(spreads, axis=0)
    area = areas[j + 1, np.arange(m)]
    spread = spreads[j, np.arange(m)]
    G = 1.0 / area
    rel_area = area / (L0 + L1) ** 2
    ok = ok0 & np.isfinite(spread) & (bf._norm(hit0 - x2) <= 1e-6 * (L0 + L1))
    return G, rel_area, spread, ok


@pytest.mark.parametrize("chain", ["R", "T"])
def test_geometry_term_finite_differences(chain):
    d = _data(chain)
    _, path_irradiance = _api()
    ti, uv = d["ti"], d["uv"]
    assert len(ti) >= 380, len(ti)  # the planted paths are there
    out = path_irradiance(chain, d["x0"], d["x2"], d["P"], d["N"], d["eta"], ti, uv)
    geo = np.asarray(out.geometry, np.float64)
    assert geo.shape == (len(ti),) and np.isfinite(geo).all() and (geo > 0).all()

    G, rel_area, spread, ok = _reference_geometry(
        chain, d["x0"][ti], d["x2"][ti], d["P"][ti, 0], d["N"][ti, 0], d["eta"][ti], uv
    )
    focal = rel_area < FOCAL_REL_AREA
    fd_bad = spread > 1e-6  # the two FD step sizes disagree: the reference itself is unreliable
    use = ok & ~focal & ~fd_bad
    rel = np.abs(geo / G - 1.0)
    bad = np.flatnonzero(use & (rel > GEOM_RTOL))
    print(
        f"\n[{chain}] geometry term: paths={len(ti)} compared={int(use.sum())} skipped focal={int((ok & focal).sum())} "
        f"FD-unreliable={int((ok & ~focal & fd_bad).sum())} trace-failed={int((~ok).sum())}; "
        f"rel err max={rel[use].max():.3g} median={np.median(rel[use]):.3g}; >1e-4: {len(bad)}"
    )
    msg = "\n".join(
        f"tuple {ti[r]}: solver geometry={geo[r]!r} finite-diff={G[r]!r} rel={rel[r]:.3g}\n"
        f"x_start={d['x0'][ti[r]].tolist()!r}\nx_end={d['x2'][ti[r]].tolist()!r}\n"
        f"P={d['P'][ti[r]].tolist()!r}\nN={d['N'][ti[r]].tolist()!r}\neta={float(d['eta'][ti[r]])!r}\nuv={uv[r].tolist()!r}"
        for r in bad[:4]
    )
    assert use.sum() >= 300, "too few paths compared"
    assert len(bad) == 0, f"{len(bad)} geometry terms off by > {GEOM_RTOL}\n{msg}"


def test_geometry_flat_mirror_exact():
    """Flat mirror (all vertex normals = face normal): dOmega/dA_perp = 1/(L0+L1)^2."""
    solve_tuples, path_irradiance = _api()
    rng = np.random.default_rng([SEED, 1])
    n = 200
    P = bf.random_triangles(rng, n)
    fn, _ = bf._unit(np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]))
    N = np.repeat(fn[:, None, :], 3, axis=1) * np.where(rng.random(n) < 0.5, -1.0, 1.0)[:, None, None]
    eta = bf.random_eta(rng, n)
    x0, x2, uvp, ok = bf.plant_paths(rng, "R", P, N, eta, dist_log10=(-0.3, 2.0))
    ti, uv = solve_tuples("R", x0, x2, P[:, None], N[:, None], eta)
    assert len(ti) == n and (ti == np.arange(n)).all()  # a flat mirror has exactly one path
    out = path_irradiance("R", x0, x2, P[:, None], N[:, None], eta, ti, uv)
    x1, _, _, _ = bf.interpolate(P, N, uv[:, 0], uv[:, 1])
    L = bf._norm(x1 - x0) + bf._norm(x2 - x1)
    rel = np.abs(np.asarray(out.geometry) * L**2 - 1.0)
    print(f"\n[flat mirror] max rel err {rel.max():.3g}")
    assert rel.max() < 1e-7, (np.argmax(rel), rel.max())
    np.testing.assert_allclose(out.fresnel, 1.0, rtol=0, atol=0)
    np.testing.assert_allclose(out.cos_receiver, 1.0, rtol=0, atol=1e-15)


def _path_frame(chain, d):
    ti, uv = d["ti"], d["uv"]
    P, N = d["P"][ti, 0], d["N"][ti, 0]
    x1, nhat, ng, _ = bf.interpolate(P, N, uv[:, 0], uv[:, 1])
    wi, _ = bf._unit(x1 - d["x0"][ti])
    wo, _ = bf._unit(d["x2"][ti] - x1)
    s = np.sign(bf._dot(d["x0"][ti] - x1, ng))
    cos_i = -bf._dot(wi, s[:, None] * nhat)
    return wo, s, cos_i


@pytest.mark.parametrize("chain", ["R", "T"])
def test_direction_cos_receiver_irradiance(chain):
    d = _data(chain)
    _, path_irradiance = _api()
    ti, uv = d["ti"], d["uv"]
    wo, s, cos_i = _path_frame(chain, d)
    refl = "dielectric"
    out = path_irradiance(chain, d["x0"], d["x2"], d["P"], d["N"], d["eta"], ti, uv, receiver_normal=d["rn"],
                          reflectance=refl)
    direction = np.asarray(out.direction, np.float64)
    assert direction.shape == (len(ti), 3)
    np.testing.assert_allclose(bf._norm(direction), 1.0, atol=1e-12)
    # the arriving direction from x1 to x_end (the solver's uv may be off by its polish, ~1e-7 rad)
    assert np.abs(direction - wo).max() < 1e-6, np.abs(direction - wo).max()
    cos_ref = np.abs(bf._dot(direction, d["rn"][ti]))
    np.testing.assert_allclose(out.cos_receiver, cos_ref, rtol=1e-12, atol=1e-14)
    irr = np.asarray(out.geometry) * np.asarray(out.fresnel) * np.asarray(out.cos_receiver)
    np.testing.assert_allclose(out.irradiance, irr, rtol=1e-12, atol=0)
    assert np.isfinite(out.irradiance).all() and (np.asarray(out.irradiance) >= 0).all()
    # receiver_normal None -> cos 1 and irradiance = geometry * fresnel
    out0 = path_irradiance(chain, d["x0"], d["x2"], d["P"], d["N"], d["eta"], ti, uv, reflectance=refl)
    np.testing.assert_allclose(out0.cos_receiver, 1.0, rtol=0, atol=1e-15)
    np.testing.assert_allclose(out0.irradiance, np.asarray(out0.geometry) * np.asarray(out0.fresnel), rtol=1e-12)
    np.testing.assert_allclose(out0.geometry, out.geometry, rtol=1e-14)


@pytest.mark.parametrize("chain", ["R", "T"])
def test_fresnel(chain):
    d = _data(chain)
    _, path_irradiance = _api()
    ti, uv = d["ti"], d["uv"]
    eta = d["eta"][ti]
    _, s, cos_i = _path_frame(chain, d)
    outside = s > 0
    if chain == "R":
        mirror = path_irradiance("R", d["x0"], d["x2"], d["P"], d["N"], d["eta"], ti, uv, reflectance="mirror")
        np.testing.assert_array_equal(np.asarray(mirror.fresnel), 1.0)
        diel = np.asarray(
            path_irradiance("R", d["x0"], d["x2"], d["P"], d["N"], d["eta"], ti, uv, reflectance="dielectric").fresnel
        )
        ref_out = bf.fresnel_dielectric(cos_i, 1.0, eta)
        err = np.abs(diel - ref_out)[outside]
        print(f"\n[R dielectric] from outside: n={int(outside.sum())} max abs err {err.max():.3g}")
        assert err.max() < 1e-9, err.max()
        # from inside (x0 behind the surface) the contract does not say which side's IOR is used;
        # report what the solver does (IOR eta -> 1 incl. TIR, or 1 -> eta) without asserting
        ins = ~outside
        if ins.any():
            r_in = bf.fresnel_dielectric(cos_i[ins], eta[ins], 1.0)
            r_out = bf.fresnel_dielectric(cos_i[ins], 1.0, eta[ins])
            print(
                f"[R dielectric] from inside: n={int(ins.sum())}: |F - F(eta->1)| max "
                f"{np.abs(diel[ins] - r_in).max():.3g}, |F - F(1->eta)| max {np.abs(diel[ins] - r_out).max():.3g}"
            )
        cond = np.asarray(
            path_irradiance("R", d["x0"], d["x2"], d["P"], d["N"], d["eta"], ti, uv, reflectance="conductor",
                            conductor_k=CONDUCTOR_K).fresnel
        )
        ref_c = bf.fresnel_conductor(cos_i, eta, CONDUCTOR_K)
        errc = np.abs(cond - ref_c)[outside]
        print(f"[R conductor k={CONDUCTOR_K}] from outside: max abs err {errc.max():.3g}")
        assert errc.max() < 1e-9, errc.max()
    else:
        fr = np.asarray(path_irradiance("T", d["x0"], d["x2"], d["P"], d["N"], d["eta"], ti, uv).fresnel)
        eta_i = np.where(outside, 1.0, eta)
        eta_t = np.where(outside, eta, 1.0)
        ref = 1.0 - bf.fresnel_dielectric(cos_i, eta_i, eta_t)
        err = np.abs(fr - ref)
        print(
            f"\n[T transmittance] n={len(ti)} (from outside {int(outside.sum())}, inside {int((~outside).sum())}) "
            f"max abs err {err.max():.3g}"
        )
        bad = np.flatnonzero(err > 1e-9)
        assert len(bad) == 0, [(int(ti[r]), float(fr[r]), float(ref[r]), float(cos_i[r]), float(s[r]), float(eta[r]))
                               for r in bad[:5]]


def test_reference_fd_against_flat_interface_analytic():
    """Self-check of the finite-difference reference (no solver): on the axis of a flat interface
    a point source at height h0 seen through it at depth h1 gives dOmega/dA = 1/(h0 + h1 eta_i/eta_t)^2
    (and 1/(h0 + h1)^2 for the flat mirror)."""
    P = np.array([[[-1.0, -1, 0], [2, -1, 0], [-1, 2, 0]]]) + np.array([300.0, -200.0, 50.0])
    N = np.array([[[0.0, 0, 1.0]] * 3])
    uv = np.array([[1 / 3, 1 / 3]])
    x1 = P[0].mean(0)
    for chain, eta, h0, h1 in (("T", 1.5, 2.0, 3.0), ("T", 1.5, -2.0, 3.0), ("T", 0.7, 1.0, 0.5), ("R", 1.5, 2.0, 3.0)):
        x0 = (x1 + np.array([0, 0, h0]))[None]
        sgn = -np.sign(h0) if chain == "T" else np.sign(h0)
        x2 = (x1 + np.array([0, 0, sgn * h1]))[None]
        eta_i, eta_t = (1.0, eta) if h0 > 0 else (eta, 1.0)
        ref = 1.0 / (abs(h0) + h1 * eta_i / eta_t) ** 2 if chain == "T" else 1.0 / (abs(h0) + h1) ** 2
        G, _, spread, ok = _reference_geometry(chain, x0, x2, P, N, np.array([eta]), uv)
        assert ok[0] and abs(G[0] / ref - 1) < 1e-8, (chain, eta, h0, G[0], ref)
