/* The sweep's coarse scores on a CPU, in C: each row's best sample and its second-best ratio.
 *
 * semidense._coarse_scores_torch defines them on the cost volume (M, S) of a chunk of keyframe
 * pixels, the cost taken as inf where fewer than `need` neighbours see the sample: the lowest
 * cost and its first index (torch.min(dim=1): a NaN is the minimum where there is one), and
 * 1 - c1 / c2 with c2 the lowest finite local minimum more than `exclusion` samples from the
 * best (no higher than either neighbour; beyond the ends inf), or the largest finite cost where
 * there is none. In torch that is some thirty passes over the (M, S) volume (the minimum with
 * its indices alone is slow on a CPU); here one pass a row, and the same numbers (comparisons,
 * one division, the clamps), bit for bit (test/test_native_sweep_scores.py).
 *
 * cost, count: (M, S) contiguous float32; out: c1 and distinct (M,) float32, best (M,) int64.
 */
#include <math.h>
#include <stdint.h>

void sweep_scores(const float *cost, const float *count, int64_t M, int S, float need, int exclusion, float *c1_out,
                  int64_t *best_out, float *distinct_out, int threads) {
#pragma omp parallel for num_threads(threads) schedule(static) if (threads > 1)
    for (int64_t m = 0; m < M; m++) {
        const float *c = cost + m * S, *n = count + m * S;
        /* torch.where(count >= need, cost, inf): a NaN count fails the test too */
#define MASKED(s) ((n[(s)] >= need) ? c[(s)] : INFINITY)
        float c1 = INFINITY;
        int best = 0, nan = 0;
        for (int s = 0; s < S; s++) {
            float x = MASKED(s);
            if (isnan(x)) {
                c1 = x, best = s, nan = 1;
                break;
            }
            if (x < c1) c1 = x, best = s;
        }
        float c2 = INFINITY, largest = -INFINITY;
        if (!nan) {
            float left = INFINITY, x = MASKED(0);
            for (int s = 0; s < S; s++) {
                float right = (s + 1 < S) ? MASKED(s + 1) : INFINITY;
                if (isfinite(x)) {
                    if (x > largest) largest = x;
                    int far = (s > best + exclusion) || (s < best - exclusion);
                    if (far && x <= left && x <= right && x < c2) c2 = x;
                }
                left = x, x = right;
            }
        } else { /* c1 is NaN, and so is the ratio; c2 as torch would have it does not matter */
            c2 = 1.0f;
        }
#undef MASKED
        if (!isfinite(c2)) c2 = largest;
        float d = 1.0f - c1 / (c2 < 1e-6f ? 1e-6f : c2);
        c1_out[m] = c1;
        best_out[m] = best;
        distinct_out[m] = (d < 0.0f) ? 0.0f : ((d > 1.0f) ? 1.0f : d);
    }
}
