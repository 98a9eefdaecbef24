/* The seed bracket of a frame's new pixels in one pass on a CPU, in C (filter_bracket.bracket_seeds).
 *
 * A new pixel's first search spans its measured neighbours' inverse depths (within seed_radius
 * px) instead of the whole range. In torch that is a gather of each such pixel's window through
 * the keyframe's padded pixel-to-row map, a masked minimum and maximum over it, then the interval's
 * ends widened by 2 min_search_px px at the epipolar motion there: some twenty small ops a frame,
 * and 49 gathered entries a pixel at the default radius of 3. Here one loop per pixel does the same,
 * every operation the torch code's in its order and float32 rounding (-ffp-contract=off):
 * torch's ``p / t`` is ``reciprocal(t) * p``, clamp keeps a NaN, the minimum and maximum are exact
 * (a NaN among the neighbours makes the pixel's range NaN, as amin / amax do), and the motion's
 * hypot is computed in double and rounded once (torch's correctly rounded result). The same
 * intervals bit for bit (test/test_native_bracket.py).
 *
 * seeds (S,): positions in the frame's searched rows of the pixels without a prior; rows (R,) the
 * keyframe rows searched; attempts, updates (M,) int64; mu (M,) float32; padded_flat (M,) each
 * row's pixel in the image padded by r, padded_rows that padded image's row at each pixel (m: none),
 * wp its width; a (3, .) stride as the searched rows' projections at infinity, b K t; lo, hi (R,)
 * narrowed in place and use (R,) bytes set where bracketed; count[0] the rows bracketed.
 */
#include <math.h>
#include <stdint.h>

#include "filter_native.h"

void filter_bracket(int64_t S, const int64_t *seeds, const int64_t *rows, const int64_t *attempts,
                    const int64_t *updates, const float *mu, const int64_t *padded_flat, const int64_t *padded_rows,
                    int64_t m, int r, int64_t wp, const float *a, int64_t as, float b0, float b1, float b2, float pad,
                    float rho_min, float rho_max, float *lo, float *hi, uint8_t *use, int64_t *count) {
    int64_t n = 0;
    for (int64_t s = 0; s < S; s++) {
        const int64_t i = seeds[s], k = rows[i];
        if (attempts[k] != 1) continue; /* choose_rows counted this attempt: only a first one */
        float low = INFINITY, high = -INFINITY;
        int nan = 0;
        const int64_t centre = padded_flat[k];
        for (int dy = -r; dy <= r; dy++) {
            const int64_t *line = padded_rows + centre + dy * wp;
            for (int dx = -r; dx <= r; dx++) { /* branch-free: which neighbours count is unpredictable */
                const int64_t q = line[dx];
                const int64_t at = (q < m) ? q : 0;
                const int counts = (q < m) & (updates[at] > 0);
                const float v = mu[at];
                nan |= counts & (v != v);
                low = (counts && v < low) ? v : low;
                high = (counts && v > high) ? v : high;
            }
        }
        if (nan || !isfinite(low)) continue; /* no measured neighbour (or a NaN one): the whole range */
        const float a0 = a[i], a1 = a[as + i], a2 = a[2 * as + i];
        lo[i] = clamp_range(low - (1.0f / clamp_below(row_motion_one(a0, a1, a2, b0, b1, b2, low), 1e-9f)) * pad, rho_min,
                            rho_max);
        hi[i] = clamp_range(high + (1.0f / clamp_below(row_motion_one(a0, a1, a2, b0, b1, b2, high), 1e-9f)) * pad, rho_min,
                            rho_max);
        use[i] = 1;
        n++;
    }
    count[0] = n;
}
