/* The surface's gradients at the fibers as a sparse solve (optitac_edge/core/gradient_solve.py builds the
 * plan's gs_* arrays): the minimum-curvature system scipy's Clough-Tocher estimate converges to,
 * K g = B v, K = C C^T with C lower triangular in an envelope padded to OK_GS_PAD. */
#ifndef OK_GRADIENT_SOLVE_H
#define OK_GRADIENT_SOLVE_H

#include "frame_kernel.h"

/* The plan's gradient solve in range (its arrays were sized by the caller): 0, or -1 with err set. */
int ok_check_gradient_solve(const ok_plan *p, char *err, int err_len);
/* g (2N: d/dx at the N fibers, then d/dy) of the values v (N); y: 2N + 2 OK_GS_PAD floats of scratch,
 * passed OK_GS_PAD in. */
void ok_gradient_solve(const ok_plan *p, const float *v, float *restrict y, float *restrict g);

#endif
