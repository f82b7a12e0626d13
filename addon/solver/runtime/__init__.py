"""Numba set-up (cache, threads, kernel decorator) and the vector kernels of the hot loops."""
