// The bivariate scratch of a two-bounce work-item on the device: N_SLOTS slots of
// BIV_N x BIV_N doubles in global memory (the biv array of addon/solver/spoly/two_bounce, same
// slot map: two_bounce/params.py), slot k at SLOT(biv, k), element (i, j) (the coefficient of
// u^i v^j, or a tensor Bernstein coefficient) at [i * BIV_N + j].  Pasted by the host into the
// two-bounce program (// @INCLUDE biv.cl@) after the build options' defines (MAXD, N_SLOTS) and
// the tables of two_bounce_tables (SQRT_PIECES_T, HERON_CUTS_T).
#define BIV_N (MAXD + 1)
#define BIV_SLOT_SIZE (BIV_N * BIV_N)
#define SLOT(biv, k) ((biv) + (long)(k) * BIV_SLOT_SIZE)
#define AT(p, i, j) ((p)[(i) * BIV_N + (j)])
