"""The Specular Polynomials solver (Fan et al. 2024): the solver interface, one bounce (R, T), two bounces (RR, RT, TR, TT) and its staged form for the OpenCL back end."""
