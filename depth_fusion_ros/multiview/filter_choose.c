/* One frame's geometry for every pixel of the filter's keyframe and the pixels it searches, in
 * one pass on a CPU, in C (filter_geometry.frame_geometry, then filter_frame_update.choose_rows).
 *
 * In torch that is some sixty passes over the keyframe's candidate pixels (tens of thousands), each
 * a dispatch: the projection at infinity, the epipolar motion and direction, the gradient along
 * it, the visibility, then the tests that pick the rows this frame searches. Here one pass
 * computes and writes the same: every operation the torch code's, in its order and float32
 * rounding (-ffp-contract=off), with ATen's addcmul as the fused multiply-add its vector kernel
 * is, and torch's ``p / t`` as ``reciprocal(t) * p``. The one function torch takes from a
 * vector library, hypot, is computed in double and rounded once: torch's correctly rounded
 * result wherever it is not subnormal (a motion that small is no motion at all here). The
 * same numbers and rows bit for bit (test/test_native_filter_choose.py).
 *
 * Pixels (M,): us, vs, mu, var float32, prior and only uint8 (torch bool; only may be NULL),
 * attempts int64 (the first attempts counted in place), grad (2, M) float32; h: torch's
 * float32 copy of H transposed (rows: H's columns). Out: a (3, M), j, along (M,) float32,
 * visible (M,) uint8, rows (the searched pixels, ascending), and counts[0..2]: the rows, the
 * estimates (prior) and the estimates visible.
 */
#include <math.h>
#include <stddef.h>
#include <stdint.h>

#include "filter_native.h"

/* The geometry of the M pixels: branch-free, so the compiler vectorises it. */
static void geometry(int64_t M, const float *restrict us, const float *restrict vs,
                     const float *restrict mu, const float *restrict grad, const float *restrict h, float b0,
                     float b1, float b2, float cu, float cu_limit, float cv, float cv_limit, float *restrict a_out,
                     float *restrict j_out, float *restrict along_out, uint8_t *restrict visible_out) {
    for (int64_t i = 0; i < M; i++) {
        const float u = us[i], v = vs[i], rho = mu[i];
        /* a = addcmul(addcmul(h2, h0, u), h1, v): two fused multiply-adds per coordinate */
        const float a0 = fmaf(h[3], v, fmaf(h[0], u, h[6]));
        const float a1 = fmaf(h[4], v, fmaf(h[1], u, h[7]));
        const float a2 = fmaf(h[5], v, fmaf(h[2], u, h[8]));
        const float w = a2 + rho * b2;
        const float nu = a2 * b0 - a0 * b2;
        const float nv = a2 * b1 - a1 * b2;
        const float norm = hypot_rounded(nu, nv);
        const float wc = clamp_below(w, 1e-9f);
        a_out[i] = a0, a_out[M + i] = a1, a_out[2 * M + i] = a2;
        j_out[i] = norm / clamp_below(w * w, 1e-12f);
        along_out[i] = fabsf(grad[i] * nu + grad[M + i] * nv) / clamp_below(norm, 1e-9f);
        visible_out[i] = (uint8_t)((w > 1e-9f) & (fabsf((a0 + rho * b0) / wc - cu) <= cu_limit) &
                                   (fabsf((a1 + rho * b1) / wc - cv) <= cv_limit));
    }
}

void filter_choose(int64_t M, const float *us, const float *vs, const float *mu, const float *var,
                   const uint8_t *prior, const uint8_t *only, int64_t *attempts, const float *grad, const float *h,
                   float b0, float b1, float b2, float cu, float cu_limit, float cv, float cv_limit,
                   float min_gradient, float min_information, float pixel_sigma, float pose_factor, int with_pose,
                   int seeding, int64_t seed_attempts, float *a_out, float *j_out, float *along_out,
                   uint8_t *visible_out, int64_t *rows_out, int64_t *counts) {
    int64_t n_rows = 0, n_estimates = 0, n_seen = 0;
    geometry(M, us, vs, mu, grad, h, b0, b1, b2, cu, cu_limit, cv, cv_limit, a_out, j_out, along_out, visible_out);
    for (int64_t i = 0; i < M; i++) { /* choose_rows */
        const float rho = mu[i], j = j_out[i];
        const int visible = visible_out[i];
        const int estimate = prior[i] != 0, fresh = !estimate;
        n_estimates += estimate;
        n_seen += estimate && visible;
        int want = (along_out[i] >= min_gradient) && (fresh || visible);
        if (want && !fresh) /* var >= min_information * measurement_variance(mu, j) */
            want = var[i] >= min_information * measurement_tau2(j, rho, pixel_sigma, pose_factor, with_pose);
        if (want && fresh) want = seeding && attempts[i] < seed_attempts;
        if (want && only != NULL) want = only[i] != 0;
        if (want) {
            rows_out[n_rows++] = i;
            attempts[i] += fresh;
        }
    }
    counts[0] = n_rows, counts[1] = n_estimates, counts[2] = n_seen;
}
