/* Scalar helpers the filter's native kernels share, each the torch operation it stands for, in
 * torch's float32 rounding (the kernels are built with -ffp-contract=off). Included by
 * matching_cost.c, filter_choose.c, filter_bracket.c and filter_apply.c; native_build digests
 * it with each of them, so a change here rebuilds them all. */
#ifndef DEPTH_FUSION_FILTER_NATIVE_H
#define DEPTH_FUSION_FILTER_NATIVE_H

#include <math.h>

/* torch.clamp(v, min=low): a NaN stays NaN */
static inline float clamp_below(float v, float low) { return (v != v) ? v : (v < low ? low : v); }

/* torch.clamp(v, low, high): a NaN stays NaN */
static inline float clamp_range(float v, float low, float high) {
    if (v != v) return v;
    v = (v < low) ? low : v;
    return (v > high) ? high : v;
}

/* torch.hypot (SLEEF's, correctly rounded): computed in double and rounded once, the same
 * float wherever the result is not subnormal */
static inline float hypot_rounded(float u, float v) { return (float)sqrt((double)u * u + (double)v * v); }

/* filter_geometry.row_motion at one row: |d p / d rho| of the projection a + rho b
 * (cost_volume.epipolar_motion, then hypot) */
static inline float row_motion_one(float a0, float a1, float a2, float b0, float b1, float b2, float rho) {
    float w = a2 + rho * b2;
    float w2 = clamp_below(w * w, 1e-12f);
    float du = (b0 * a2 - a0 * b2) / w2, dv = (b1 * a2 - a1 * b2) / w2;
    return hypot_rounded(du, dv);
}

/* filter_matches.measurement_variance at one row: (pixel_sigma / clamp(j, 1e-6))^2, plus
 * (rho pose_factor)^2 with the pose term (torch's p / t is reciprocal(t) * p) */
static inline float measurement_tau2(float j, float rho, float pixel_sigma, float pose_factor, int with_pose) {
    const float t = (1.0f / clamp_below(j, 1e-6f)) * pixel_sigma;
    float tau2 = t * t;
    if (with_pose) {
        const float p = rho * pose_factor;
        tau2 = tau2 + p * p;
    }
    return tau2;
}

#endif
