"""One-bounce solver against closed-form optics: planar mirror, flat refracting interface,
and degenerate input (no path, no NaN, clear errors)."""

import numpy as np
import pytest

from addon.solver import path_irradiance, solve_tuples


def _flat_triangle(n, size=50.0):
    P = np.array([[-size, 0.0, -size], [size, 0.0, -size], [0.0, 0.0, size]])
    N = np.array([[0.0, 1.0, 0.0]] * 3)
    return np.broadcast_to(P, (n, 1, 3, 3)).copy(), np.broadcast_to(N, (n, 1, 3, 3)).copy()


def _point(P, uv):
    p0, p1, p2 = P[:, 0, 0], P[:, 0, 1], P[:, 0, 2]
    return p0 + uv[:, :1] * (p1 - p0) + uv[:, 1:2] * (p2 - p0)


def _fresnel(cos_i, n1, n2):
    """Unpolarised dielectric Fresnel reflectance, textbook form."""
    sin_t = n1 / n2 * np.sqrt(1.0 - cos_i**2)
    cos_t = np.sqrt(1.0 - sin_t**2)
    rs = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)
    rp = (n1 * cos_t - n2 * cos_i) / (n1 * cos_t + n2 * cos_i)
    return 0.5 * (rs**2 + rp**2)


def test_planar_mirror_matches_image_source():
    rng = np.random.default_rng(7)
    n = 500
    P, N = _flat_triangle(n)
    x0 = np.column_stack([rng.uniform(-3, 3, n), rng.uniform(0.2, 4, n), rng.uniform(-3, 3, n)])
    x2 = np.column_stack([rng.uniform(-3, 3, n), rng.uniform(0.2, 4, n), rng.uniform(-3, 3, n)])
    ti, uv = solve_tuples("R", x0, x2, P, N, 1.5)
    assert np.array_equal(ti, np.arange(n)), "every configuration has exactly one mirror path"
    image = x0 * np.array([1.0, -1.0, 1.0])
    s = image[:, 1] / (image[:, 1] - x2[:, 1])
    expected = image + s[:, None] * (x2 - image)
    np.testing.assert_allclose(_point(P, uv), expected, rtol=0, atol=1e-9)
    # Irradiance: I cos(theta_r) / d^2 with d the distance from the image source.
    nr = rng.normal(size=(n, 3))
    d = x2 - image
    dist = np.linalg.norm(d, axis=1)
    analytic = np.abs(np.sum(d * nr, 1)) / np.linalg.norm(nr, axis=1) / dist**3
    got = path_irradiance("R", x0, x2, P, N, 1.5, ti, uv, receiver_normal=nr)
    np.testing.assert_allclose(got.irradiance, analytic, rtol=1e-9)
    np.testing.assert_allclose(got.fresnel, 1.0)
    # Dielectric reflectance at the image-source angle.
    cos_i = x0[:, 1] / np.linalg.norm(x0 - expected, axis=1)
    glass = path_irradiance("R", x0, x2, P, N, 1.5, ti, uv, reflectance="dielectric")
    np.testing.assert_allclose(glass.fresnel, _fresnel(cos_i, 1.0, 1.5), rtol=1e-9)


def _snell_point(h1, h2, r, n1, n2):
    """Independent 1-D solve: where a ray from height h1 to depth h2, r apart, crosses."""
    lo, hi = 0.0, r
    for _ in range(200):
        x = 0.5 * (lo + hi)
        f = n1 * x / np.hypot(x, h1) - n2 * (r - x) / np.hypot(r - x, h2)
        lo, hi = (x, hi) if f < 0 else (lo, x)
    return 0.5 * (lo + hi)


@pytest.mark.parametrize("from_outside", [True, False])
def test_flat_interface_refraction_matches_snell_and_analytic_irradiance(from_outside):
    eta = 1.33
    rng = np.random.default_rng(11 if from_outside else 12)
    n = 200
    P, N = _flat_triangle(n)  # normals +y: the medium of IOR eta is below (y < 0)
    h1 = rng.uniform(0.5, 3.0, n)
    h2 = rng.uniform(0.5, 3.0, n)
    r = rng.uniform(0.05, 1.0 if from_outside else 0.6, n)  # inside: stay below the critical angle
    phi = rng.uniform(0, 2 * np.pi, n)
    side = 1.0 if from_outside else -1.0
    x0 = np.column_stack([np.zeros(n), side * h1, np.zeros(n)])
    x2 = np.column_stack([r * np.cos(phi), -side * h2, r * np.sin(phi)])
    n1, n2 = (1.0, eta) if from_outside else (eta, 1.0)
    ti, uv = solve_tuples("T", x0, x2, P, N, eta)
    assert np.array_equal(ti, np.arange(n))
    x_cross = np.array([_snell_point(h1[i], h2[i], r[i], n1, n2) for i in range(n)])
    expected = np.column_stack([x_cross * np.cos(phi), np.zeros(n), x_cross * np.sin(phi)])
    np.testing.assert_allclose(_point(P, uv), expected, rtol=0, atol=1e-10)
    # E = I T sin(t1) / (r dr/dt1) on the horizontal receiver, r = h1 tan t1 + h2 tan t2.
    t1 = np.arctan2(x_cross, h1)
    t2 = np.arcsin(n1 / n2 * np.sin(t1))
    dt2 = n1 * np.cos(t1) / (n2 * np.cos(t2))
    dr = h1 / np.cos(t1) ** 2 + h2 / np.cos(t2) ** 2 * dt2
    transmittance = 1.0 - _fresnel(np.cos(t1), n1, n2)
    analytic = transmittance * np.sin(t1) / (r * dr)
    got = path_irradiance("T", x0, x2, P, N, eta, ti, uv, receiver_normal=np.tile([0.0, 1.0, 0.0], (n, 1)))
    np.testing.assert_allclose(got.fresnel, transmittance, rtol=1e-9)
    np.testing.assert_allclose(got.irradiance, analytic, rtol=1e-7)


def test_near_critical_angle_from_inside_stays_below_it():
    """From inside a flat interface every point above is reachable, with the incidence
    angle approaching (never passing) the critical angle; the square form's spurious
    solutions beyond it (total internal reflection) must all be rejected."""
    eta = 1.5
    n = 50
    P, N = _flat_triangle(n)
    x0 = np.tile([0.0, -1.0, 0.0], (n, 1))
    far = np.linspace(2.0, 40.0, n)
    x2 = np.column_stack([far, np.full(n, 0.05), np.zeros(n)])
    ti, uv = solve_tuples("T", x0, x2, P, N, eta)
    assert np.array_equal(ti, np.arange(n))
    x1 = _point(P, uv)
    sin1 = x1[:, 0] / np.hypot(x1[:, 0], 1.0)
    sin2 = (far - x1[:, 0]) / np.hypot(far - x1[:, 0], 0.05)
    assert np.all(sin1 < 1.0 / eta)
    np.testing.assert_allclose(eta * sin1, sin2, rtol=1e-9)
    # A receiver on the light's side of the interface has no refraction path.
    ti, _ = solve_tuples("T", x0, x0 + [3.0, -0.5, 0.0], P, N, eta)
    assert ti.size == 0


@pytest.mark.parametrize("chain", ["R", "T"])
def test_degenerate_tuples_give_no_path_and_no_nan(chain):
    good_P, good_N = _flat_triangle(1)
    x0 = np.array([0.1, 1.0, 0.2])
    x2 = np.array([0.5, 2.0 if chain == "R" else -2.0, -0.3])
    cases = []
    # zero-area triangle (collinear vertices)
    cases.append((x0, x2, np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0.0]]), good_N[0, 0]))
    # all vertices equal
    cases.append((x0, x2, np.zeros((3, 3)), good_N[0, 0]))
    # zero normals
    cases.append((x0, x2, good_P[0, 0], np.zeros((3, 3))))
    # normals lying in the triangle's plane (parallel to the surface)
    cases.append((x0, x2, good_P[0, 0], np.array([[1.0, 0, 0]] * 3)))
    # endpoints in the triangle's plane
    cases.append((np.array([0.3, 0.0, 0.1]), x2, good_P[0, 0], good_N[0, 0]))
    cases.append((x0, np.array([0.3, 0.0, 0.1]), good_P[0, 0], good_N[0, 0]))
    # start equals end
    cases.append((x0, x0, good_P[0, 0], good_N[0, 0]))
    # grazing: endpoints a hair above the plane, far apart
    cases.append((np.array([-10.0, 1e-9, 0]), np.array([10.0, 1e-9 if chain == "R" else -1e-9, 0]), good_P[0, 0], good_N[0, 0]))
    # vertex normals pointing opposite ways (interpolated normal vanishes inside)
    cases.append((x0, x2, good_P[0, 0], np.array([[0, 1.0, 0], [0, -1.0, 0], [0, 1.0, 0]])))
    xs = np.array([c[0] for c in cases])
    xe = np.array([c[1] for c in cases])
    P = np.array([c[2] for c in cases])[:, None]
    N = np.array([c[3] for c in cases])[:, None]
    ti, uv = solve_tuples(chain, xs, xe, P, N, 1.5)
    assert np.all(np.isfinite(uv))
    degenerate_expected_empty = [0, 1, 2, 3, 4, 5, 6]
    assert not set(ti.tolist()) & set(degenerate_expected_empty), ti
    if ti.size:
        irr = path_irradiance(chain, xs, xe, P, N, 1.5, ti, uv)
        assert np.all(np.isfinite(irr.irradiance))
    # A good tuple in the same batch is still solved.
    ti2, _ = solve_tuples(chain, np.vstack([xs, x0]), np.vstack([xe, x2]), np.vstack([P, good_P]), np.vstack([N, good_N]), 1.5)
    assert ti2[-1] == len(cases)


def test_bad_input_raises_clear_value_errors():
    P, N = _flat_triangle(2)
    x0 = np.array([[0.0, 1.0, 0.0]] * 2)
    x2 = np.array([[1.0, 1.0, 0.0]] * 2)
    with pytest.raises(ValueError, match="unknown chain"):
        solve_tuples("X", x0, x2, P, N, 1.5)
    with pytest.raises(ValueError, match="x_start must have shape"):
        solve_tuples("R", x0[:, :2], x2, P, N, 1.5)
    with pytest.raises(ValueError, match=r"P must have shape \(n, 1, 3, 3\)"):
        solve_tuples("R", x0, x2, P[:, 0], N, 1.5)
    with pytest.raises(ValueError, match="tuples but x_start has"):
        solve_tuples("R", x0, x2[:1], P, N, 1.5)
    bad = x0.copy()
    bad[1, 2] = np.nan
    with pytest.raises(ValueError, match="NaN or Inf"):
        solve_tuples("R", bad, x2, P, N, 1.5)
    badN = N.copy()
    badN[0, 0, 1, 0] = np.inf
    with pytest.raises(ValueError, match="N contains NaN or Inf"):
        solve_tuples("T", x0, x2, P, badN, 1.5)
    # a NaN in a later chunk of a large batch (the one-bounce kernel flags it per tuple)
    many = 1000
    bigP = np.repeat(P[:1], many, axis=0)
    bigP[700, 0, 2, 1] = np.nan
    with pytest.raises(ValueError, match=r"P contains NaN or Inf \(first at tuple 700\)"):
        solve_tuples("R", np.repeat(x0[:1], many, axis=0), np.repeat(x2[:1], many, axis=0), bigP,
                     np.repeat(N[:1], many, axis=0), 1.5)
    with pytest.raises(ValueError, match="eta"):
        solve_tuples("T", x0, x2, P, N, -1.0)
    with pytest.raises(ValueError, match="eta"):
        solve_tuples("T", x0, x2, P, N, [1.5, 1.5, 1.5])
    # Empty batch is fine.
    ti, uv = solve_tuples("R", np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 1, 3, 3)), np.zeros((0, 1, 3, 3)), 1.5)
    assert ti.shape == (0,) and uv.shape == (0, 2)
