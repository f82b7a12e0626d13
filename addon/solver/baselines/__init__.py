"""Baseline solvers behind the same interface: Newton, Specular Manifold Sampling, the MNEE coplanarity-curve walk."""
