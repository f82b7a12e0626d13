// Python's max(a, b) and min(a, b), as the Numba kernels these programs port compute them:
// a unless b is larger (smaller), so a NaN in b is never taken and of two equal values the
// first is kept.  fmax / fmin differ on NaN and on signed zeros, which would change bits.
// Included (// @INCLUDE numba_math.cl@) by every program that needs them, once per program.
#define NB_MAX(a, b) ((b) > (a) ? (b) : (a))
#define NB_MIN(a, b) ((b) < (a) ? (b) : (a))
