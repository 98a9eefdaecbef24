/* One frame's matches into the filter's keyframe state on a CPU, in C (filter_matches.apply_matches).
 *
 * filter_matches defines it in torch: each searched row with a valid match takes the Gaussian x
 * uniform update (filter_update.gaussian_uniform_update; a row without a prior its first
 * measurement), each row with a prior that matched nothing an outlier vote (b += 1), and a row
 * whose inlier ratio falls below the limit goes back to "no estimate". About sixty torch ops on
 * the few thousand rows of a frame, each a pass and a dispatch; here one pass before the
 * exponential and the square root and one after them. Those two stay torch's own calls: this
 * torch's CPU exp and sqrt are MKL's vector functions, within an ulp of the exact result but not
 * always the nearest float, so only the same call gives the same numbers. Every other operation
 * is the torch code's, in its order and float32 rounding (-ffp-contract=off, no FMA: the same
 * numbers bit for bit, test/test_native_filter_apply.py), including torch's way of writing a
 * scalar over a tensor (``p / t`` is ``reciprocal(t) * p``).
 *
 * rows: the keyframe row of each searched row; meas: the searched rows that measured (valid);
 * votes: those with a prior that did not. State arrays (M,): mu, var, a, b float32, updates
 * int64, prior and the searched rows' fresh flags uint8 (torch bool).
 */
#include <stdint.h>

#include "filter_native.h"

/* The measurement variance (filter_matches.measurement_variance), the Gaussian term's exponent
 * -0.5 (x - mu)^2 / (var + tau2) and 2 pi (var + tau2), whose square root it is divided by, of
 * each measuring row. */
void filter_measure_exponent(const int64_t *rows, const int64_t *meas, int64_t n, const float *x,
                             const float *j_x, const float *mu, const float *var, float pixel_sigma,
                             float pose_factor, int with_pose, float two_pi, float *tau2_out, float *arg_out,
                             float *spread_out) {
    for (int64_t k = 0; k < n; k++) {
        const int64_t i = meas[k], r = rows[i];
        const float tau2 = measurement_tau2(j_x[i], x[i], pixel_sigma, pose_factor, with_pose);
        const float d = x[i] - mu[r];
        const float total = var[r] + tau2;
        tau2_out[k] = tau2;
        arg_out[k] = (-0.5f * (d * d)) / total;
        spread_out[k] = two_pi * total;
    }
}

/* Back to "no estimate" (filter_keyframe.no_estimate: the mean and variance of the whole range,
 * the prior Beta, no measurement, no prior). */
#define RESET(r) (mu[r] = none_mu, var[r] = none_var, a[r] = init_a, b[r] = init_b, updates[r] = 0, prior[r] = 0)

/* The posterior of each measuring row from exp(exponent) and sqrt(2 pi total) (torch's, in e_in
 * and root_in; gaussian_uniform_update), a first measurement (init_a, init_b: the prior Beta)
 * where the row had no prior, the resets, then the votes. */
void filter_measure_finish(const int64_t *rows, const int64_t *meas, int64_t n, const float *x, const float *cost,
                           const uint8_t *fresh, const float *tau2_in, const float *e_in, const float *root_in,
                           const int64_t *votes, int64_t n_votes, float *mu, float *var, float *a, float *b,
                           int64_t *updates, uint8_t *prior, float *key_cost, float span, float none_mu,
                           float none_var, float init_a, float init_b, float min_ratio) {
    for (int64_t k = 0; k < n; k++) {
        const int64_t i = meas[k], r = rows[i];
        const float m0 = mu[r], v0 = var[r], a0 = a[r], b0 = b[r], tau2 = tau2_in[k], xi = x[i];
        const float s2 = 1.0f / (1.0f / v0 + 1.0f / tau2);
        const float m = s2 * (m0 / v0 + xi / tau2);
        const float ab = a0 + b0;
        float c1 = ((a0 / ab) * e_in[k]) / root_in[k];
        float c2 = (b0 / ab) / span;
        const float norm = c1 + c2;
        c1 = c1 / norm, c2 = c2 / norm;
        const float ab1 = ab + 1.0f, a1 = a0 + 1.0f;
        const float c1a1 = c1 * a1, c2a = c2 * a0;
        const float f = c1a1 / ab1 + c2a / ab1;
        const float ab12 = ab1 * (ab1 + 1.0f);
        const float e = (c1a1 * (a0 + 2.0f)) / ab12 + (c2a * a1) / ab12;
        float mu_n = c1 * m + c2 * m0;
        float var_n = clamp_below((c1 * (s2 + m * m) + c2 * (v0 + m0 * m0)) - mu_n * mu_n, 1e-12f);
        float a_n = (e - f) / (f - e / f);
        float b_n = (a_n * (1.0f - f)) / f;
        if (fresh[i]) { /* a first measurement */
            mu_n = xi, var_n = tau2, a_n = init_a, b_n = init_b;
        }
        mu[r] = mu_n, var[r] = var_n, a[r] = a_n, b[r] = b_n;
        updates[r] += 1, prior[r] = 1, key_cost[r] = cost[i];
        if (!fresh[i] && a_n / (a_n + b_n) < min_ratio) RESET(r);
    }
    for (int64_t k = 0; k < n_votes; k++) { /* filter_update.outlier_vote */
        const int64_t r = rows[votes[k]];
        b[r] = b[r] + 1.0f;
        if (a[r] / (a[r] + b[r]) < min_ratio) RESET(r);
    }
}
