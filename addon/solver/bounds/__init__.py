"""Bernstein bounds for caustics (Fan et al. 2025): which triangle tuples can light which
receiver texels, and how much.  Pure numpy/Numba (never imports bpy).

- ``layout``: the piece row columns and the rules every engine shares (leaf module).
- ``slot_algebra``, ``one_bounce_position``, ``one_bounce_irradiance``, ``one_bounce``: the
  one-bounce engine (R, T; §4.2–4.5, §6.1) and ``bound_one_bounce``, its entry point.
- ``affine``, ``two_bounce_irradiance``, ``two_bounce_position``, ``two_bounce_image``,
  ``two_bounce``: the two-bounce engine (RR, RT, TR, TT) and ``bound_two_bounce``.
- ``tuples``: two-bounce tuple construction through a BVH (§6.1); ``sampling``: γ-sampling (§5).

The readable reference engines the tests compare against live in tests/reference/.
"""
