"""Irradiance bound of a one-bounce refraction piece: the implicit form (Fan et al. 2025 eq 17–19).

The refracted direction holds √β, so the explicit Jacobian of eq 15–16 would need the √β
approximation; instead the specular constraints F (for two vectors b tangent to the caster,
the intersection of both bounds) and G are differentiated implicitly over the 4-D box
U1 × (the piece's position bound): |∂u1/∂uk| = |det ∂(F,G)/∂(uk,vk)| / |det ∂(F,G)/∂(u1,v1)|,
no √ involved.  The determinants are built per piece as sums over monomials in the box's
(uk, vk) coordinates of 2-D scaled-Bernstein products in (u1, v1) (workspace ``U`` rows, slots
``U_*``), then bounded with eq 3; the final degree is (10, 10, 3, 3) in (u1, v1, uk, vk).
Ē = max |d0·(e1×e2)|·|det_k| / min |d0|³ / |det_1| / |e_k1 × e_k2|, padded by IRR_PAD.

Tested against the reference engine and dense finite differences in
tests/solver/test_bounds_validity.py.
"""

import math

import numpy as np

from ..runtime.jit import kernel
from .slot_algebra import E2, N4, SCR4, coef_minmax, cross_fields, dot_const, dot_fields, elevate2, mac2, pderiv, ratio_bound, to_bernstein, zero_fill
from .layout import IRR_PAD, MIN_WIDTH, ior_ratio
from .one_bounce_position import S_D, S_N, S_X, box_orientation_mask, caster_unit
from ..polynomials.bernstein import abs_lower, abs_upper


# slots of the refraction irradiance workspace U (rows of UW coefficients: polynomials in
# (u1, v1) only, extents (1, 1, p, q) with p, q <= 11); 0..11 as S_X.. (for caster_unit)
UW = 128
U_RR = 12                   # r = xc - x1, xc the receiver point at the (uk, vk) box corner (3)
U_C = 15                    # c = d0 × n (3)
U_COS, U_L0, U_G0, U_G3, U_G4 = 18, 19, 20, 21, 22
U_GU = 23                   # ∂G_β/∂u1, β = 0 (g0), 1 (g3), 2 (g4)
U_GV = 26                   # ∂G_β/∂v1
U_L00, U_L10, U_L01 = 29, 30, 31
U_A, U_A2, U_M = 32, 33, 34  # A = c·b, A², m = n × b (3)
U_B00, U_B10, U_B01 = 37, 38, 39
U_P = 40                    # l_α A² for |α| <= 1 (3)
U_R = 43                    # L0 × (the α coefficient of B²) (6)
U_T, U_TMP, U_TMP2 = 49, 50, 51
U_F = 52                    # f_α (6), α in the order 00, 10, 01, 20, 11, 02
U_FU = 58                   # ∂f_α/∂u1 (6)
U_FV = 64                   # ∂f_α/∂v1 (6)
U_DET = 70                  # det1 coefficient of σ^a τ^b, |(a, b)| <= 3 (10), order 00, 10, 01, 20, 11, 02, 30, 21, 12, 03
U_NK = 80                   # detk coefficient of 1, σ, τ (3)
U_NC = 83                   # cos × detk (3)
U_E = 86                    # elevated copies (3)
NU = 89


@kernel
def _det_to_bernstein4(U, out, tmp):
    """out (extents (4, 4, 11, 11), order (uk, vk, u1, v1)) = Σ_{a+b<=3} σ^a τ^b D_ab, D_ab =
    U[U_DET..] (extents 9 - a - b in (u1, v1), elevated to 11), in the degree-(3, 3)
    Bernstein basis of the (uk, vk) box.  σ^a = Σ_i C(i, a)/C(3, a) B_i^3(σ), so with
    m_a = D_a / C(3, a) placed in slab a the coefficients c_i = Σ_a C(i, a) m_a are three
    rounds of Pascal-triangle sums (6 slab additions per axis, no multiplications), in place.
    Slab (a, b) starts at (4 a + b)·121; extents are written as constants (fixed-length loops)."""
    third = 1.0 / 3.0
    ninth = 1.0 / 9.0
    elevate2(U[U_DET], 9, 11, 1.0, out[0:121], tmp)              # (0, 0)
    elevate2(U[U_DET + 1], 8, 11, third, out[484:605], tmp)      # (1, 0)
    elevate2(U[U_DET + 2], 8, 11, third, out[121:242], tmp)      # (0, 1)
    elevate2(U[U_DET + 3], 7, 11, third, out[968:1089], tmp)     # (2, 0)
    elevate2(U[U_DET + 4], 7, 11, ninth, out[605:726], tmp)      # (1, 1)
    elevate2(U[U_DET + 5], 7, 11, third, out[242:363], tmp)      # (0, 2)
    elevate2(U[U_DET + 6], 6, 11, 1.0, out[1452:1573], tmp)      # (3, 0)
    elevate2(U[U_DET + 7], 6, 11, ninth, out[1089:1210], tmp)    # (2, 1)
    elevate2(U[U_DET + 8], 6, 11, ninth, out[726:847], tmp)      # (1, 2)
    elevate2(U[U_DET + 9], 6, 11, 1.0, out[363:484], tmp)        # (0, 3)
    for slab in (7, 10, 11, 13, 14, 15):                         # a + b > 3
        for k in range(slab * 121, slab * 121 + 121):
            out[k] = 0.0
    for j in range(4):  # along uk (slab index a -> i) for each vk slab
        for r in range(3):
            for i in range(3, r, -1):
                d = (i * 4 + j) * 121
                e = ((i - 1) * 4 + j) * 121
                for k in range(121):
                    out[d + k] += out[e + k]
    for i in range(4):  # along vk
        for r in range(3):
            for j in range(3, r, -1):
                d = (i * 4 + j) * 121
                e = d - 121
                for k in range(121):
                    out[d + k] += out[e + k]


@kernel
def _num_to_bernstein4(U, kscale, out, tmp):
    """out (extents (4, 4, 11, 11)) = kscale (N00 + σ N10 + τ N01), N = U[U_NC..] elevated to
    (11, 11), in the degree-(3, 3) Bernstein basis of (uk, vk): σ = Σ_i (i/3) B_i^3(σ)."""
    e0 = U[U_E]
    e1 = U[U_E + 1]
    e2 = U[U_E + 2]
    elevate2(U[U_NC], 9, 11, kscale, e0, tmp)
    elevate2(U[U_NC + 1], 8, 11, kscale, e1, tmp)
    elevate2(U[U_NC + 2], 8, 11, kscale, e2, tmp)
    for i in range(4):
        wi = i / 3.0
        for j in range(4):
            wj = j / 3.0
            base = (i * 4 + j) * 121
            for k in range(121):
                out[base + k] = e0[k] + wi * e1[k] + wj * e2[k]


@kernel
def _det_alpha0(U, ia, ig):
    """det1 terms of f_α, |α| = 0 (extents 7): f_α,u1 g_β,v1 - f_α,v1 g_β,u1 for β = 0 (g0,
    extents 4) into γ = α (slot ig) and β = σ, τ (g3, g4, extents 3) into γ = α + β (slots 1,
    2).  The extents are written as constants so that each mac2 is compiled for its fixed
    loop lengths (about 2x faster than the generic loops on these 3..7-long rows)."""
    fu = U[U_FU + ia]
    fv = U[U_FV + ia]
    mac2(fu, 6, 7, U[U_GV], 4, 3, U[U_DET + ig], 1.0)
    mac2(fv, 7, 6, U[U_GU], 3, 4, U[U_DET + ig], -1.0)
    for k in range(2):
        mac2(fu, 6, 7, U[U_GV + 1 + k], 3, 2, U[U_DET + 1 + k], 1.0)
        mac2(fv, 7, 6, U[U_GU + 1 + k], 2, 3, U[U_DET + 1 + k], -1.0)


@kernel
def _det_alpha1(U, ia, ig, ig1):
    """As _det_alpha0 for |α| = 1 (extents 6): γ = α in slot ig, γ = α + σ, α + τ in slots
    ig1, ig1 + 1."""
    fu = U[U_FU + ia]
    fv = U[U_FV + ia]
    mac2(fu, 5, 6, U[U_GV], 4, 3, U[U_DET + ig], 1.0)
    mac2(fv, 6, 5, U[U_GU], 3, 4, U[U_DET + ig], -1.0)
    for k in range(2):
        mac2(fu, 5, 6, U[U_GV + 1 + k], 3, 2, U[U_DET + ig1 + k], 1.0)
        mac2(fv, 6, 5, U[U_GU + 1 + k], 2, 3, U[U_DET + ig1 + k], -1.0)


@kernel
def _det_alpha2(U, ia, ig, ig1):
    """As _det_alpha0 for |α| = 2 (extents 5)."""
    fu = U[U_FU + ia]
    fv = U[U_FV + ia]
    mac2(fu, 4, 5, U[U_GV], 4, 3, U[U_DET + ig], 1.0)
    mac2(fv, 5, 4, U[U_GU], 3, 4, U[U_DET + ig], -1.0)
    for k in range(2):
        mac2(fu, 4, 5, U[U_GV + 1 + k], 3, 2, U[U_DET + ig1 + k], 1.0)
        mac2(fv, 5, 4, U[U_GU + 1 + k], 2, 3, U[U_DET + ig1 + k], -1.0)


@kernel
def box_irradiance_refract(W, U, scr, x0, P, N, Q, eta, lo, hi, pos):
    """(Ē, E̲) for refraction (eq 17–19) on the 4-D box (uk, vk) × (u1, v1), as
    the reference piece_irradiance_refract: the same polynomials det ∂(F, G)/∂(u1, v1) and
    (d0·ng) det ∂(F, G)/∂(uk, vk), bounded by eq 3 at the same final degree (3, 3, 10, 10) in
    (uk, vk, u1, v1), so the same bound up to rounding.

    Built without 4-D products: with σ, τ in [0, 1] the coordinates of the (uk, vk) box,
    d1 = xk - x1 = r + σ E1 + τ E2 (r = xc - x1 affine in (u1, v1), E1, E2 the box's edge
    vectors), so G = (d0×n)·d1 = g0 + σ g3 + τ g4 is affine and F = |d1|² A² - η² |d0|² B²
    (A = (d0×n)·b, B = d1·(n×b)) is quadratic in (σ, τ), with (u1, v1)-polynomial
    coefficients f_α.  The determinants are then sums over σ^a τ^b (total degree <= 3 for
    det1, <= 1 for detk) of 2-D products (about 5x fewer operations than the tensor 4-D
    products, whose (uk, vk) extents (3, 3) ignore the total degree), converted to the 4-D
    Bernstein basis at the end (σ^a = Σ_i C(i, a)/C(3, a) B_i^3(σ)).  Coefficients stay in
    scaled form: eq 3 takes coefficient ratios at one degree, where the binomial factors
    cancel."""
    lo4 = scr[20:24]
    hi4 = scr[24:28]
    hi_v = scr[32:34]
    lo_v = scr[34:36]
    lo4[2], hi4[2], lo4[3], hi4[3] = lo[0], hi[0], lo[1], hi[1]
    for k in range(2):
        a, b = pos[2 * k], pos[2 * k + 1]
        if b - a < MIN_WIDTH:
            a, b = 0.5 * (a + b) - 0.5 * MIN_WIDTH, 0.5 * (a + b) + 0.5 * MIN_WIDTH
        lo4[k], hi4[k] = a, b
    mask = box_orientation_mask(x0, P, N, lo, hi)
    if mask == 0:
        return 0.0, 0.0
    e1 = (P[1, 0] - P[0, 0], P[1, 1] - P[0, 1], P[1, 2] - P[0, 2])
    e2 = (P[2, 0] - P[0, 0], P[2, 1] - P[0, 1], P[2, 2] - P[0, 2])
    ek1 = (Q[1, 0] - Q[0, 0], Q[1, 1] - Q[0, 1], Q[1, 2] - Q[0, 2])
    ek2 = (Q[2, 0] - Q[0, 0], Q[2, 1] - Q[0, 1], Q[2, 2] - Q[0, 2])
    ws = hi4[0] - lo4[0]
    wt = hi4[1] - lo4[1]
    w2 = hi[0] - lo[0]
    w3 = hi[1] - lo[1]
    E1 = (ws * ek1[0], ws * ek1[1], ws * ek1[2])
    E2v = (wt * ek2[0], wt * ek2[1], wt * ek2[2])
    xc = (Q[0, 0] + lo4[0] * ek1[0] + lo4[1] * ek2[0], Q[0, 1] + lo4[0] * ek1[1] + lo4[1] * ek2[1],
          Q[0, 2] + lo4[0] * ek1[2] + lo4[1] * ek2[2])
    caster_unit(U, x0, P, N, Q, lo, hi)  # x, n, d on the (u1, v1) box (affine)
    tmp = U[U_TMP]
    for c in range(3):
        for k in range(4):
            U[U_RR + c, k] = xc[c] - U[S_X + c, k]
    ng = (e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0])
    dot_const(U, S_D, E2, ng, U[U_COS])                        # d0·ng (2,2)
    e3 = dot_fields(U, S_D, E2, S_D, E2, U[U_L0], tmp)           # |d0|² (3,3)
    for k in range(9):
        U[U_TMP2, k] = U[U_L0, k]
    to_bernstein(U[U_TMP2], e3)
    dlo, dhi = coef_minmax(U[U_TMP2], 9)
    if dlo <= 0.0:
        return np.inf, 0.0
    ec = cross_fields(U, S_D, E2, S_N, E2, U_C, tmp)           # c = d0 × n (3,3)
    dot_fields(U, U_C, ec, U_RR, E2, U[U_G0], tmp)              # g0 = c·r (4,4)
    dot_const(U, U_C, ec, E1, U[U_G3])                         # g3 = c·E1 (3,3)
    dot_const(U, U_C, ec, E2v, U[U_G4])                        # g4 = c·E2
    e44 = (1, 1, 4, 4)
    pderiv(U[U_G0], e44, 2, w2, U[U_GU])
    pderiv(U[U_G0], e44, 3, w3, U[U_GV])
    pderiv(U[U_G3], ec, 2, w2, U[U_GU + 1])
    pderiv(U[U_G3], ec, 3, w3, U[U_GV + 1])
    pderiv(U[U_G4], ec, 2, w2, U[U_GU + 2])
    pderiv(U[U_G4], ec, 3, w3, U[U_GV + 2])
    # |d1|² = l00 + σ l10 + τ l01 + σ² |E1|² + στ 2 E1·E2 + τ² |E2|²
    dot_fields(U, U_RR, E2, U_RR, E2, U[U_L00], tmp)
    dot_const(U, U_RR, E2, (2.0 * E1[0], 2.0 * E1[1], 2.0 * E1[2]), U[U_L10])
    dot_const(U, U_RR, E2, (2.0 * E2v[0], 2.0 * E2v[1], 2.0 * E2v[2]), U[U_L01])
    l20 = E1[0] * E1[0] + E1[1] * E1[1] + E1[2] * E1[2]
    l11 = 2.0 * (E1[0] * E2v[0] + E1[1] * E2v[1] + E1[2] * E2v[2])
    l02 = E2v[0] * E2v[0] + E2v[1] * E2v[1] + E2v[2] * E2v[2]
    # t1, t2: unit tangents of the caster (as the reference engine)
    l = math.sqrt(e1[0] ** 2 + e1[1] ** 2 + e1[2] ** 2)
    t1 = (e1[0] / l, e1[1] / l, e1[2] / l)
    t2 = (ng[1] * t1[2] - ng[2] * t1[1], ng[2] * t1[0] - ng[0] * t1[2], ng[0] * t1[1] - ng[1] * t1[0])
    l = math.sqrt(t2[0] ** 2 + t2[1] ** 2 + t2[2] ** 2)
    t2 = (t2[0] / l, t2[1] / l, t2[2] / l)
    ak = math.sqrt((ek1[1] * ek2[2] - ek1[2] * ek2[1]) ** 2 + (ek1[2] * ek2[0] - ek1[0] * ek2[2]) ** 2
                   + (ek1[0] * ek2[1] - ek1[1] * ek2[0]) ** 2)
    DET1 = scr[SCR4:SCR4 + N4]
    NUM = scr[SCR4 + N4:SCR4 + 2 * N4]
    nfin = N4
    kscale = 1.0 / (ws * wt)  # detk in (uk, vk) units: ∂/∂uk = (1/ws) ∂/∂σ, ∂/∂vk = (1/wt) ∂/∂τ
    best_hi = 0.0
    best_lo = np.inf
    for variant in range(2):
        hi_v[variant] = np.inf
        lo_v[variant] = 0.0
    for bi in range(2):
        bb = t1 if bi == 0 else t2
        dot_const(U, U_C, ec, bb, U[U_A])                      # A (3,3)
        zero_fill(25, U[U_A2])
        mac2(U[U_A], 3, 3, U[U_A], 3, 3, U[U_A2], 1.0)    # A² (5,5)
        for k in range(4):                                 # m = n × b (affine)
            n0, n1, n2 = U[S_N, k], U[S_N + 1, k], U[S_N + 2, k]
            U[U_M, k] = n1 * bb[2] - n2 * bb[1]
            U[U_M + 1, k] = n2 * bb[0] - n0 * bb[2]
            U[U_M + 2, k] = n0 * bb[1] - n1 * bb[0]
        dot_fields(U, U_RR, E2, U_M, E2, U[U_B00], tmp)         # B = b00 + σ b10 + τ b01
        dot_const(U, U_M, E2, E1, U[U_B10])
        dot_const(U, U_M, E2, E2v, U[U_B01])
        # l_α A² (|α| <= 1)
        zero_fill(49, U[U_P])
        mac2(U[U_L00], 3, 3, U[U_A2], 5, 5, U[U_P], 1.0)          # (7,7)
        zero_fill(36, U[U_P + 1])
        mac2(U[U_L10], 2, 2, U[U_A2], 5, 5, U[U_P + 1], 1.0)      # (6,6)
        zero_fill(36, U[U_P + 2])
        mac2(U[U_L01], 2, 2, U[U_A2], 5, 5, U[U_P + 2], 1.0)
        # |d0|² × (coefficients of B²): b00², 2 b00 b10, 2 b00 b01, b10², 2 b10 b01, b01²
        zero_fill(25, U[U_T])
        mac2(U[U_L0], 3, 3, U[U_B00], 3, 3, U[U_T], 1.0)          # L0 b00 (5,5)
        zero_fill(49, U[U_R])
        mac2(U[U_T], 5, 5, U[U_B00], 3, 3, U[U_R], 1.0)           # (7,7)
        zero_fill(36, U[U_R + 1])
        mac2(U[U_T], 5, 5, U[U_B10], 2, 2, U[U_R + 1], 2.0)       # (6,6)
        zero_fill(36, U[U_R + 2])
        mac2(U[U_T], 5, 5, U[U_B01], 2, 2, U[U_R + 2], 2.0)
        for t in range(3):
            zero_fill(9, U[U_TMP2])
            x = U_B10 if t < 2 else U_B01
            y = U_B10 if t == 0 else U_B01
            mac2(U[x], 2, 2, U[y], 2, 2, U[U_TMP2], 1.0 if t != 1 else 2.0)   # (3,3)
            zero_fill(25, U[U_R + 3 + t])
            mac2(U[U_L0], 3, 3, U[U_TMP2], 3, 3, U[U_R + 3 + t], 1.0)       # (5,5)
        for variant in range(2):
            if not (mask >> variant) & 1:
                continue
            o = 1.0 if variant == 0 else -1.0
            eta_f = 1.0 / ior_ratio(o, eta)
            s = -eta_f * eta_f
            # f_α = l_α A² - η² L0 (B²)_α, extents 7 - |α|; their u1 / v1 derivatives
            for ia in range(6):
                da = 0 if ia == 0 else (1 if ia < 3 else 2)
                na = 7 - da
                fa = U[U_F + ia]
                ra = U[U_R + ia]
                if ia < 3:
                    pa = U[U_P + ia]
                    for k in range(na * na):
                        fa[k] = pa[k] + s * ra[k]
                else:
                    lc = l20 if ia == 3 else (l11 if ia == 4 else l02)
                    a2 = U[U_A2]
                    for k in range(25):
                        fa[k] = lc * a2[k] + s * ra[k]
                pderiv(fa, (1, 1, na, na), 2, w2, U[U_FU + ia])
                pderiv(fa, (1, 1, na, na), 3, w3, U[U_FV + ia])
            # det1 = F_u1 G_v1 - F_v1 G_u1 = Σ_γ σ^γa τ^γb Σ_{α+β=γ} (f_α,u1 g_β,v1 - f_α,v1 g_β,u1)
            for ig in range(10):
                dg = 0 if ig == 0 else (1 if ig < 3 else (2 if ig < 6 else 3))
                zero_fill((9 - dg) * (9 - dg), U[U_DET + ig])
            _det_alpha0(U, 0, 0)
            _det_alpha1(U, 1, 1, 3)
            _det_alpha1(U, 2, 2, 4)
            for ba in range(3):
                _det_alpha2(U, 3 + ba, 3 + ba, 6 + ba)
            # F_σ G_τ - F_τ G_σ with F_σ = f10 + 2σ f20 + τ f11, F_τ = f01 + σ f11 + 2τ f02, G_σ = g3, G_τ = g4
            # (sizes written out as constants: the kernels are then compiled for fixed loop lengths)
            zero_fill(64, U[U_NK])
            mac2(U[U_F + 1], 6, 6, U[U_G4], 3, 3, U[U_NK], 1.0)    # f10 g4 - f01 g3 (8, 8)
            mac2(U[U_F + 2], 6, 6, U[U_G3], 3, 3, U[U_NK], -1.0)
            zero_fill(81, U[U_NC])
            mac2(U[U_COS], 2, 2, U[U_NK], 8, 8, U[U_NC], 1.0)
            zero_fill(49, U[U_NK + 1])
            mac2(U[U_F + 3], 5, 5, U[U_G4], 3, 3, U[U_NK + 1], 2.0)    # σ: 2 f20 g4 - f11 g3 (7, 7)
            mac2(U[U_F + 4], 5, 5, U[U_G3], 3, 3, U[U_NK + 1], -1.0)
            zero_fill(64, U[U_NC + 1])
            mac2(U[U_COS], 2, 2, U[U_NK + 1], 7, 7, U[U_NC + 1], 1.0)
            zero_fill(49, U[U_NK + 2])
            mac2(U[U_F + 4], 5, 5, U[U_G4], 3, 3, U[U_NK + 2], 1.0)    # τ: f11 g4 - 2 f02 g3
            mac2(U[U_F + 5], 5, 5, U[U_G3], 3, 3, U[U_NK + 2], -2.0)
            zero_fill(64, U[U_NC + 2])
            mac2(U[U_COS], 2, 2, U[U_NK + 2], 7, 7, U[U_NC + 2], 1.0)
            _det_to_bernstein4(U, DET1, tmp)
            _num_to_bernstein4(U, kscale, NUM, tmp)
            a, b2, c, d = ratio_bound(NUM, DET1, nfin, scr[SCR4 + 2 * N4:SCR4 + 3 * N4])
            hi_v[variant] = min(hi_v[variant], abs_upper(a, b2, c, d))
            lo_v[variant] = max(lo_v[variant], abs_lower(a, b2, c, d))
    for variant in range(2):
        if not (mask >> variant) & 1:
            continue
        best_hi = max(best_hi, hi_v[variant])
        best_lo = min(best_lo, lo_v[variant])
    if best_lo == np.inf:
        best_lo = 0.0
    return best_hi * dlo ** -1.5 / ak * (1.0 + IRR_PAD), best_lo * dhi ** -1.5 / ak * (1.0 - IRR_PAD)
