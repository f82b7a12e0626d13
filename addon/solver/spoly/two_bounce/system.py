"""The bivariate system of one two-bounce tuple (Fan et al. 2024 §3.4, Table 3).

The scaled scattered direction d̃1 at vertex 1 (reflection eq 19; refraction eq 21-22 with
√β replaced by a √ piece of eq 23 or the Heron √) is mapped to triangle 2 by the rational
coordinate mapping (eq 14-17); the constraints at vertex 2 are then a = coplanarity (eq 6)
and b = the law at vertex 2 (R: product form eq 13; T: square form eq 10), polynomials in
the barycentrics (u1, v1) of x1.  ``build_system`` also stores the map's κ, ũ2, ṽ2, t̃ for
the pre-pass's hit test.

Tested in tests/solver/test_solver_two_bounce.py (degrees, the hit test, and every solver
test through it).
"""

from ...runtime.jit import kernel
from .params import HIT_MARGIN_APPROX, HIT_MARGIN_EXACT, HIT_SLOT, MAXD, SQRT_PIECES
from ...polynomials.bivariate import badd, bmul_acc, bzero, vcross, vcross_const, vdot, vdot_const, vlin


@kernel
def build_system(refract1, refract2, orient1, eta1_ratio, piece, S, heron, eta_in2, eta_out2, flat2, c2, geo_l, biv):
    """Fill biv[0] = a (returned da) and biv[1] = b (returned db) in the local frame geo_l.

    orient1: ±1, the sign turning n1 to the incoming side (refraction only);
    eta1_ratio: η' at vertex 1; piece: row of SQRT_PIECES, S: √β scale; piece < 0: the
    Heron √ of :func:`heron_sqrt_fit` with the quadratic's coefficients ``heron``."""
    x0 = (geo_l[0, 0], geo_l[0, 1], geo_l[0, 2])
    x3 = (geo_l[1, 0], geo_l[1, 1], geo_l[1, 2])
    e11 = (geo_l[2, 0], geo_l[2, 1], geo_l[2, 2])
    e12 = (geo_l[3, 0], geo_l[3, 1], geo_l[3, 2])
    n10 = (geo_l[4, 0], geo_l[4, 1], geo_l[4, 2])
    m11 = (geo_l[5, 0], geo_l[5, 1], geo_l[5, 2])
    m12 = (geo_l[6, 0], geo_l[6, 1], geo_l[6, 2])
    p20 = (geo_l[7, 0], geo_l[7, 1], geo_l[7, 2])
    e21 = (geo_l[8, 0], geo_l[8, 1], geo_l[8, 2])
    e22 = (geo_l[9, 0], geo_l[9, 1], geo_l[9, 2])
    n20 = (geo_l[10, 0], geo_l[10, 1], geo_l[10, 2])
    m21 = (geo_l[11, 0], geo_l[11, 1], geo_l[11, 2])
    m22 = (geo_l[12, 0], geo_l[12, 1], geo_l[12, 2])
    zero = (0.0, 0.0, 0.0)
    # slots: vector polys use biv[k:k+3]
    a = biv[0]
    b = biv[1]
    s1 = biv[2]
    s2 = biv[3]
    s3 = biv[4]
    s4 = biv[5]
    s5 = biv[6]
    D0 = biv[7:10]
    N1 = biv[10:13]
    DT = biv[13:16]  # d̃1
    V1 = biv[16:19]
    N2 = biv[19:22]  # κ n2
    D2 = biv[22:25]  # κ (x3 - x2)
    T2 = biv[25:28]
    V2 = biv[28:31]
    S1 = biv[31:34]  # x1 - p20
    Q = biv[34:37]
    vlin(D0, (-x0[0], -x0[1], -x0[2]), e11, e12)
    vlin(N1, n10, m11, m12)
    # --- d̃1
    dd0n = vdot(D0, 1, N1, 1, s1)  # d0·n1
    vdot(N1, 1, N1, 1, s2)  # |n1|²
    ddt = 3
    if not refract1:
        # d̃ = -2 (d0·n) n + d0 |n|²
        for c in range(3):
            bzero(DT[c], 3)
            bmul_acc(s1, 2, N1[c], 1, DT[c], -2.0)
            bmul_acc(s2, 2, D0[c], 1, DT[c], 1.0)
    else:
        r = eta1_ratio
        vdot(D0, 1, D0, 1, s3)  # |d0|²
        # β = |n|²|d0|² (1 - r²) + r² (d0·n)²   (degree 4)  -> s4
        bzero(s4, 4)
        bmul_acc(s2, 2, s3, 2, s4, 1.0 - r * r)
        bmul_acc(s1, 2, s1, 2, s4, r * r)
        # √β ≈ Rn / Rd: Rn -> s5, Rd -> s3 (|d0|² no longer needed), degrees dn, dd
        if piece < 0:
            # Heron step from the fitted quadratic q: Rn = β + q², Rd = 2q
            Q2 = biv[28]
            bzero(Q2, 2)
            Q2[0, 0] = heron[0]
            Q2[1, 0] = heron[1]
            Q2[0, 1] = heron[2]
            Q2[2, 0] = heron[3]
            Q2[1, 1] = heron[4]
            Q2[0, 2] = heron[5]
            bzero(s5, 4)
            badd(s5, 4, s4, 4, 1.0)
            bmul_acc(Q2, 2, Q2, 2, s5, 1.0)
            bzero(s3, 2)
            badd(s3, 2, Q2, 2, 2.0)
            dd = 2
        else:
            # eq (23): √β ≈ S (c0 + c1 β/S²) / (1 + d1 β/S²) = (S c0 S² + S c1 β) / (S² + d1 β)
            c0 = SQRT_PIECES[piece, 2]
            c1 = SQRT_PIECES[piece, 3]
            d1 = SQRT_PIECES[piece, 4]
            S2 = S * S
            bzero(s5, 4)
            badd(s5, 4, s4, 4, S * c1)
            s5[0, 0] += S * c0 * S2
            bzero(s3, 4)
            badd(s3, 4, s4, 4, d1)
            s3[0, 0] += S2
            dd = 4
        # d̃ = Rd r (d0 |n|² - (d0·n) n) - orient Rn n       (degree dd + 3: 5 Heron, 7 pieces)
        ddt = dd + 3
        for c in range(3):
            bzero(V1[c], 3)
            bmul_acc(s2, 2, D0[c], 1, V1[c], r)
            bmul_acc(s1, 2, N1[c], 1, V1[c], -r)
            bzero(DT[c], ddt)
            bmul_acc(s3, dd, V1[c], 3, DT[c], 1.0)
            bmul_acc(s5, 4, N1[c], 1, DT[c], -orient1)
    # --- mapping to triangle 2: PV = d̃ × e22, κ = PV·e21, ũ = PV·(x1 - p20), ṽ = d̃·((x1 - p20) × e21)
    vlin(S1, (-p20[0], -p20[1], -p20[2]), e11, e12)
    vcross_const(DT, ddt, e22, V1)  # PV
    vdot_const(V1, ddt, e21, s1)  # κ      (degree ddt)
    vdot(V1, ddt, S1, 1, s2)  # ũ        (degree ddt + 1)
    # (x1 - p20) × e21 is linear: Q
    vcross_const(S1, 1, e21, Q)
    vdot(DT, ddt, Q, 1, s3)  # ṽ
    dm = ddt + 1
    # copies for the pre-pass's hit test (the slots above are reused below): κ, ũ, ṽ and
    # t̃ = e22·((x1 - p20) × e21) (the ray parameter times κ); degree and margin in a spare corner
    for i in range(dm + 1):
        for j in range(dm + 1):
            biv[HIT_SLOT, i, j] = s1[i, j] if i + j <= ddt else 0.0
            biv[HIT_SLOT + 1, i, j] = s2[i, j]
            biv[HIT_SLOT + 2, i, j] = s3[i, j]
    bzero(biv[HIT_SLOT + 3], 1)
    for c in range(3):
        biv[HIT_SLOT + 3, 0, 0] += e22[c] * Q[c, 0, 0]
        biv[HIT_SLOT + 3, 1, 0] += e22[c] * Q[c, 1, 0]
        biv[HIT_SLOT + 3, 0, 1] += e22[c] * Q[c, 0, 1]
    biv[HIT_SLOT, MAXD, 0] = ddt
    biv[HIT_SLOT, MAXD, 1] = HIT_MARGIN_APPROX if refract1 else HIT_MARGIN_EXACT
    # κ n2 and κ (x3 - p20) - ũ e21 - ṽ e22
    x3r = (x3[0] - p20[0], x3[1] - p20[1], x3[2] - p20[2])
    for c in range(3):
        bzero(D2[c], dm)
        badd(D2[c], dm, s1, ddt, x3r[c])
        badd(D2[c], dm, s2, dm, -e21[c])
        badd(D2[c], dm, s3, dm, -e22[c])
    if flat2:
        dn2 = 0
        for c in range(3):
            bzero(N2[c], 0)
            N2[c, 0, 0] = n20[c]
    else:
        dn2 = dm
        for c in range(3):
            bzero(N2[c], dm)
            badd(N2[c], dm, s1, ddt, n20[c])
            badd(N2[c], dm, s2, dm, m21[c])
            badd(N2[c], dm, s3, dm, m22[c])
    # --- a = (d̃ × (x3 - x1)) · κn2
    vlin(S1, x3, (-e11[0], -e11[1], -e11[2]), (-e12[0], -e12[1], -e12[2]))  # x3 - x1
    vcross(DT, ddt, S1, 1, V1)
    da = vdot(V1, ddt + 1, N2, dn2, a)
    # --- b
    if not refract2:
        vcross_const(N2, dn2, c2, T2)  # t2 = κn2 × c2
        d_a = vdot(DT, ddt, N2, dn2, s1)  # d̃·n
        d_b = vdot(D2, dm, T2, dn2, s2)  # d2·t
        vdot(DT, ddt, T2, dn2, s3)  # d̃·t
        vdot(D2, dm, N2, dn2, s4)  # d2·n
        db = d_a + d_b
        bzero(b, db)
        bmul_acc(s1, d_a, s2, d_b, b, 1.0)
        bmul_acc(s3, d_a, s4, d_b, b, 1.0)
    else:
        # η_in² |d2|² ((d̃ × n)·c)² - η_out² |d̃|² ((d2 × n)·c)²
        vcross(DT, ddt, N2, dn2, V1)
        dq1 = vdot_const(V1, ddt + dn2, c2, s1)  # (d̃ × n)·c
        vcross(D2, dm, N2, dn2, V2)
        dq2 = vdot_const(V2, dm + dn2, c2, s2)  # (d2 × n)·c
        vdot(D2, dm, D2, dm, s3)  # |d2|²
        vdot(DT, ddt, DT, ddt, s4)  # |d̃|²
        # s5 = s1², then b = η_in² s3 s5
        bzero(s5, 2 * dq1)
        bmul_acc(s1, dq1, s1, dq1, s5, 1.0)
        db = 2 * dm + 2 * dq1
        bzero(b, db)
        bmul_acc(s3, 2 * dm, s5, 2 * dq1, b, eta_in2 * eta_in2)
        bzero(s5, 2 * dq2)
        bmul_acc(s2, dq2, s2, dq2, s5, 1.0)
        bmul_acc(s4, 2 * ddt, s5, 2 * dq2, b, -eta_out2 * eta_out2)
    return da, db
