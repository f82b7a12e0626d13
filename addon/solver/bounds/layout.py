"""The shared layout of the Bernstein bounds engines (Fan et al. 2025 §4, §6.1).

A *piece* is one row of ``PIECE_FIELDS`` float64: the caster box (u1, v1), the receiver
barycentric and UV bounds, the irradiance bounds Ē, E̲ and the quadtree depth (``P_*``
columns); two-bounce pair-level rows add the receiver index (``P_RECEIVER``).  Also here: the
orientation rule of a vertex (the side rules of addon/solver/CONTRACT.md), the IOR ratio of a side, the §6.1
midpoint split, and the chain codes of the two-bounce engines (bit 0: vertex 1 refracts,
bit 1: vertex 2 refracts).  Every engine module imports these; this module imports none of them.
"""

from ..runtime.jit import kernel

# Piece record layout (one row of ``pieces``).
P_U0, P_U1, P_V0, P_V1 = 0, 1, 2, 3          # caster (u1, v1) box
P_BU0, P_BU1, P_BV0, P_BV1 = 4, 5, 6, 7      # receiver barycentric (uk, vk) bound
P_X0, P_X1, P_Y0, P_Y1 = 8, 9, 10, 11        # receiver UV texture-space bound
P_EHI, P_ELO, P_DEPTH = 12, 13, 14           # irradiance bound Ē, lower bound E̲, depth
PIECE_FIELDS = 15
P_RECEIVER = PIECE_FIELDS  # extra column of the two-bounce pair-level rows: the receiver triangle

ONE_BOUNCE_STATS = 4  # position evaluations, irradiance evaluations, unbounded-irradiance leaves, capacity stops
TWO_BOUNCE_STATS = 4  # position evaluations, stage-1 misses (light of the piece misses triangle 2), constant-form fallbacks, capacity stops

POS_PAD = 1e-9  # absolute outward padding of barycentric / UV bounds (rounding of the coefficients)
IRR_PAD = 1e-9  # relative padding of the irradiance bound
MIN_WIDTH = 1e-6  # smallest (uk, vk) box side used in the implicit irradiance bound (enlarged, so still conservative)

CHAIN_CODES = {"RR": 0, "TR": 1, "RT": 2, "TT": 3}


@kernel
def orientation_mask(side_lo, side_hi, ndot_lo, ndot_hi):
    """Orientations o = sign(side)·sign(n·ng) (CONTRACT.md: the light's side of the geometric
    normal turned to the shading normal) possible when the side (x_source - x)·ng ranges over
    [side_lo, side_hi] and n·ng over [ndot_lo, ndot_hi]: bit 1 for o = +1, bit 2 for -1."""
    mask = 0
    if side_hi > 0.0:
        if ndot_hi > 0.0:
            mask |= 1
        if ndot_lo < 0.0:
            mask |= 2
    if side_lo < 0.0:
        if ndot_hi > 0.0:
            mask |= 2
        if ndot_lo < 0.0:
            mask |= 1
    return mask


@kernel
def ior_ratio(o, eta):
    """η' = η_i/η_t for the side o (o > 0: light arrives from outside, IOR 1 -> eta)."""
    return 1.0 / eta if o > 0.0 else eta


@kernel
def push_children(stack, top, lo, hi, depth):
    """Push the four midpoint children of the box lo <= (u1, v1) <= hi (§6.1 subdivision) that
    reach into the triangle (lower corner with u1 + v1 < 1) as rows (u_lo, u_hi, v_lo, v_hi,
    depth + 1) at stack[top:]; returns the new top."""
    um = 0.5 * (lo[0] + hi[0])
    vm = 0.5 * (lo[1] + hi[1])
    for k in range(4):
        a0 = lo[0] if k & 1 == 0 else um
        a1 = um if k & 1 == 0 else hi[0]
        b0 = lo[1] if k & 2 == 0 else vm
        b1 = vm if k & 2 == 0 else hi[1]
        if a0 + b0 < 1.0:
            stack[top, 0], stack[top, 1], stack[top, 2], stack[top, 3], stack[top, 4] = a0, a1, b0, b1, depth + 1
            top += 1
    return top
