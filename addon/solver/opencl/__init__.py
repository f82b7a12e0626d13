"""The optional OpenCL back end (pyopencl) and its kernels (*.cl)."""
