"""Bernstein bounds for caustics (Fan et al. 2025): which triangle tuples can light which
receiver texels, and how much.  Pure numpy/Numba (never imports bpy).

- ``bernstein``: tensor-product Bernstein arithmetic and the rational range bound (§4.1, eq 1–3).
- ``interval``: interval arithmetic on the same quantities (the comparison of Fig. 4).
- ``chain1``: position and irradiance bounds of one-bounce chains R and T with domain
  subdivision (§4.2–4.5, §6.1), and ``bound_one_bounce`` (the batch entry point).
"""
