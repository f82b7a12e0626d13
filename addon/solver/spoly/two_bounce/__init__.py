"""Two-bounce Specular Polynomials: the RR, RT, TR and TT chains (Fan et al. 2024, §3.4–4.3).

For a tuple (x0, triangle 1, triangle 2, x3) the unknowns are the barycentrics (u1, v1) of x1.
The scaled scattered direction d̃1 (reflection eq 19, degree 3; refraction eq 21–22 with √β
replaced by the piecewise rational r of eq 23, or by one Heron step on a fitted quadratic
where that fits the triangle) is mapped to triangle 2 by the rational coordinate mapping
(eq 14–17), so that the constraints at vertex 2 become a bivariate polynomial system
(Table 3): coplanarity a (eq 6) and the law at vertex 2, b (R: product form eq 13; T: square
form eq 10 with η_in on the light's side).  c2 is the normal of the plane of incidence, so
that neither form vanishes on whole curves.

Modules, each depending only on those before it:
  params     constants, slot map, switches, statistics indices, the √ pieces of eq 23
  (../../polynomials/bivariate.py: the polynomial algebra in (u, v))
  prepass    1. where a and b can vanish together: Bernstein quadtree over [-m, 1+m]², boxes
             dropped by sign, by the hit test on triangle 2, by the √ piece's β band
  sqrt       the √β of eq 21–23: rational pieces, the Heron fit, which pieces to solve
  system     building a and b (Table 3)
  resultant  2. the resultant scan (eq 28–31): hybrid Bézout determinant at one v1, sign
             changes pinned by Illinois regula falsi, refinement of kinks, dips resolved
  solve      3. paths (§4.3): candidates at the roots polished in path space and validated;
             per tuple (both orientations, reciprocity) and the batch entry
             ``solve_two_bounce_batch``
  staged     the same pipeline cut into batch stages for the OpenCL back end

Invariants: float64; fixed-size scratch per work item, no allocation per tuple; the vector
kernels of ``runtime/simd.py`` do the scalar loops' operations in their order (bit for bit).
Tested in tests/solver/test_solver_two_bounce.py (analytic cases, planted paths, brute-force
recall, the √ fit, the pre-pass hit test) and tests/solver/test_opencl_two_bounce.py (the
stages), bench/two_bounce_recall.py (10,000-tuple acceptance sets).  Design decisions and
their measurements: docs/decisions/two-bounce-solver.md.
"""

from .params import DEFAULT_PIECES, MAX_PATHS_TWO_BOUNCE, MAX_PIECES, N_STATS, SQRT_PIECES
from .resultant import det_bezout
from .solve import solve_two_bounce_batch
from .sqrt import sqrt_approx

__all__ = ["DEFAULT_PIECES", "MAX_PATHS_TWO_BOUNCE", "MAX_PIECES", "N_STATS", "SQRT_PIECES", "det_bezout",
           "solve_two_bounce_batch", "sqrt_approx"]
